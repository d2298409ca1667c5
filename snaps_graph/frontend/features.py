"""Keypoints, descriptors, matching and tracking on the left image (paper §II-C): SIFT, ORB, or
Shi-Tomasi corners with pyramidal LK; deterministic arrays in a fixed order, so the front end
is bit-reproducible (docs/frontend.md)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..config import FrontendConfig

KLT_LEVELS = 3  # KLT pyramid levels
SIFT_FEATURES = 2000  # SIFT keypoints per image: a few hundred PnP inliers at KITTI's resolution
ORB_FEATURES = 2000  # ORB keypoints per image, the same count
RATIO_TEST = 0.75  # Lowe's ratio for descriptor matching (his 0.8, a little stricter)
KLT_BIAS_MAX_PX = 0.5  # a window-bias re-fit that moves a track farther than this keeps the plain position


@dataclass(frozen=True)
class KltParams:
    """KLT corners and their tracking (docs/frontend.md), tuned on KITTI and the street renderings;
    a test or a benchmark passes its own to the functions below."""

    features: int = 1500  # corners when re-detecting: PnP and the local BA keep a few hundred tracks
    window_px: int = 11  # LK window: large enough to lock on at KITTI's resolution
    quality: float = 0.01  # goodFeaturesToTrack quality, relative to the best corner
    min_distance_px: int = 10  # spacing between corners: spread over the image, not clustered on one facade
    border_px: int = 16  # no corner this close to the border: the next frame would push it out
    bias_window_px: int = 7  # the window-bias re-fit's window (0 = off): removes the road's flow-curvature bias
    weak_points: int = 300  # fewer points with depth than this re-detect at KLT_WEAK_QUALITY (weak texture)


KLT = KltParams()


def _kp_arrays(kps, desc) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints as (uv float32 (N,2), response float32 (N,)) plus descriptors, in a fixed order.

    Sorted by response (strongest first), then by position, so multi-threaded detectors that
    gather keypoints in a thread-dependent order still give one answer.
    """
    if not kps or desc is None:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32), desc
    uv = np.array([k.pt for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    order = np.lexsort((uv[:, 1], uv[:, 0], -resp))
    return uv[order], resp[order], desc[order]


def detect_sift(img: np.ndarray, cfg: FrontendConfig) -> tuple[np.ndarray, np.ndarray]:
    """SIFT (paper §II-C) on ``img``: (uv float32 (N,2), descriptors float32 (N,128)), N <= SIFT_FEATURES.

    ``sift_first_octave``: -1 is OpenCV's SIFT as the paper ran it (the image is doubled first,
    so the finest octave has 4x the pixels and costs most of the time); 0 starts at the image's
    own resolution (Lowe's scale space without the doubling, VLFeat's default). OpenCV has no
    switch for it, so octave 0 is run as OpenCV's SIFT on the half-size image (whose doubled
    octave is the full-resolution one) with keypoints scaled back by 2.
    """
    sift = cv2.SIFT.create(SIFT_FEATURES)
    if cfg.sift_first_octave == 0:
        half = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        kps, desc = sift.detectAndCompute(half, None)
        uv, _, desc = _kp_arrays(kps, desc)
        uv = uv * 2.0 + 0.5  # centre of half-size pixel i lies at full-size 2i + 0.5
    else:
        kps, desc = sift.detectAndCompute(img, None)
        uv, _, desc = _kp_arrays(kps, desc)
    if desc is None:
        desc = np.zeros((0, 128), np.float32)
    return uv, np.ascontiguousarray(desc, np.float32)


def detect_orb(img: np.ndarray, n: int = ORB_FEATURES) -> tuple[np.ndarray, np.ndarray]:
    """ORB on ``img``: (uv float32 (N,2), descriptors uint8 (N,32)), N <= ``n``."""
    orb = cv2.ORB.create(n)
    kps, desc = orb.detectAndCompute(img, None)
    uv, _, desc = _kp_arrays(kps, desc)
    if desc is None:
        desc = np.zeros((0, 32), np.uint8)
    return uv, np.ascontiguousarray(desc, np.uint8)


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour matches a -> b that pass Lowe's ratio test: (ia, ib) int64 index arrays.

    Binary (uint8) descriptors use Hamming distance (OpenCV's brute-force matcher); float ones
    use L2, computed as one matrix product |a|² + |b|² - 2 a·b (BLAS), about
    twice as fast here as OpenCV's brute-force float matcher for 2000 x 2000 SIFT descriptors.
    The test compares distances (not squared): d1 < ratio · d2.
    """
    na, nb = len(desc_a), len(desc_b)
    if na == 0 or nb < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if desc_a.dtype == np.uint8:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        pairs = matcher.knnMatch(desc_a, desc_b, k=2)
        ia, ib, d1, d2 = [], [], [], []
        for p in pairs:
            if len(p) == 2:
                ia.append(p[0].queryIdx)
                ib.append(p[0].trainIdx)
                d1.append(p[0].distance)
                d2.append(p[1].distance)
        ia, ib = np.array(ia, np.int64), np.array(ib, np.int64)  # type: ignore[assignment]
        keep = np.array(d1, np.float64) < ratio * np.array(d2, np.float64)
        return ia[keep], ib[keep]
    a = np.asarray(desc_a, np.float32)
    b = np.asarray(desc_b, np.float32)
    d = (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)  # |a|² is constant per row: added below
    rows = np.arange(na)
    j1 = np.argmin(d, axis=1)
    best = d[rows, j1].copy()
    d[rows, j1] = np.inf
    second = d.min(axis=1)
    aa = (a * a).sum(1)
    d1 = np.sqrt(np.maximum(best + aa, 0.0))
    d2 = np.sqrt(np.maximum(second + aa, 0.0))
    keep = d1 < ratio * d2
    return rows[keep].astype(np.int64), j1[keep].astype(np.int64)


def detect_corners(img: np.ndarray, n: int, cfg: KltParams, avoid: np.ndarray | None = None) -> np.ndarray:
    """Up to ``n`` Shi-Tomasi corners (float32 (N,2)), at least ``min_distance_px`` apart,
    none within ``border_px`` of the border, none within ``min_distance_px`` of the
    points ``avoid`` (the tracks that survived, so new corners fill the gaps).

    The mask is the border frame and the surviving points eroded by an elliptical kernel of radius
    ``min_distance_px``, built directly (``_exclusion_mask``). goodFeaturesToTrack computes
    corner eigenvalues over the whole image it is given, so it gets the mask's open frame plus a
    3-pixel margin (the 3x3 derivative, the 3x3 block and the 3x3 local-maximum test reach 3
    pixels): the same corners, the image's border band not computed.
    """
    if n <= 0:
        return np.zeros((0, 2), np.float32)
    h, w = img.shape
    b = cfg.border_px
    if avoid is not None and len(avoid):
        mask = _exclusion_mask(h, w, b, cfg.min_distance_px, avoid)
        m = b + cfg.min_distance_px if b > 0 else 0
    else:
        mask = np.zeros((h, w), np.uint8)
        mask[b : h - b, b : w - b] = 255
        m = b
    c = max(0, m - 3)
    if c > 0 and h - 2 * c > 8 and w - 2 * c > 8:
        roi = np.ascontiguousarray(img[c : h - c, c : w - c])
        pts = cv2.goodFeaturesToTrack(roi, n, cfg.quality, cfg.min_distance_px, mask=mask[c : h - c, c : w - c].copy())
        if pts is not None:
            pts = pts + np.float32(c)
    else:
        pts = cv2.goodFeaturesToTrack(img, n, cfg.quality, cfg.min_distance_px, mask=mask)
    if pts is None:
        return np.zeros((0, 2), np.float32)
    return pts.reshape(-1, 2).astype(np.float32)


def _exclusion_mask(h: int, w: int, b: int, r: int, avoid: np.ndarray) -> np.ndarray:
    """255 where a corner may be detected: ``cv2.erode`` by the (2r+1)² ellipse of the mask that
    is 255 inside a ``b``-pixel border except at the (rounded, clipped) points ``avoid``, built
    without the full-image erode (3-4x faster, the same mask). Erosion is a union of the zero
    set dilated by the kernel; OpenCV treats pixels outside the image as 255. The frame dilates
    to a frame of b + r pixels (b > 0); each point stamps the kernel (its zero pixels)."""
    m = b + r if b > 0 else 0
    pad = np.zeros((h + 2 * r, w + 2 * r), np.uint8)  # r pixels of padding: stamps never wrap
    pad[r + m : r + h - m, r + m : r + w - m] = 255
    u = np.clip(np.rint(avoid[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(avoid[:, 1]).astype(np.int64), 0, h - 1)
    ky, kx = np.nonzero(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    pad.ravel()[((v * (w + 2 * r) + u)[:, None] + (ky * (w + 2 * r) + kx)[None, :]).ravel()] = 0
    return pad[r : r + h, r : r + w].copy()


def track_klt(
    prev_img: np.ndarray,
    cur_img: np.ndarray,
    uv: np.ndarray,
    cfg: KltParams,
    guess: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track points from ``prev_img`` into ``cur_img`` with pyramidal LK.

    ``guess`` (N,2), when given, is where each point is predicted to land (constant-velocity
    projection of its 3D point); LK then starts there. Returns (uv_cur float32 (N,2), ok bool
    (N,)): converged, finite and inside the image. Outliers left over are PnP RANSAC's job.
    """
    uv = np.ascontiguousarray(uv, np.float32).reshape(-1, 2)
    if len(uv) == 0:
        return uv.copy(), np.zeros(0, bool)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    init = None if guess is None else np.ascontiguousarray(guess, np.float32).reshape(-1, 1, 2)
    flags = 0 if guess is None else cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        prev_img,
        cur_img,
        uv.reshape(-1, 1, 2),
        init,
        winSize=(cfg.window_px, cfg.window_px),
        maxLevel=KLT_LEVELS,
        criteria=crit,
        flags=flags,
    )
    p1 = p1.reshape(-1, 2)
    h, w = cur_img.shape
    ok = (st.reshape(-1) == 1) & np.all(np.isfinite(p1), axis=1)
    ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    if 0 < cfg.bias_window_px < cfg.window_px and np.any(ok):
        p1 = _window_extrapolated(prev_img, cur_img, uv, p1, ok, cfg)
    return p1.astype(np.float32), ok


def window_moment(w: int) -> float:
    """Second moment of a w-pixel window's offsets, (w^2 - 1) / 12: the LK window bias's scale."""
    return (w * w - 1) / 12.0


def _window_extrapolated(
    prev_img: np.ndarray, cur_img: np.ndarray, uv: np.ndarray, p1: np.ndarray, ok: np.ndarray, cfg: KltParams
) -> np.ndarray:
    """LK positions with the window bias removed (``bias_window_px``).

    A translation-only LK fit over a window where the flow is not linear (the road plane under
    forward motion: its image flow grows with the square of the row's distance from the horizon)
    lands off the point by the flow's curvature times the window's second moment, (w^2 - 1) / 12
    for a w-pixel window. Re-fitting at the finest level with a smaller window w2 and extrapolating
    the two positions linearly in that moment to zero removes the bias to first order.
    """
    w1, w2 = cfg.window_px, cfg.bias_window_px
    sel = np.flatnonzero(ok)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.001)
    p2, st, _ = cv2.calcOpticalFlowPyrLK(
        prev_img,
        cur_img,
        np.ascontiguousarray(uv[sel]).reshape(-1, 1, 2),
        np.ascontiguousarray(p1[sel], np.float32).reshape(-1, 1, 2),
        winSize=(w2, w2),
        maxLevel=0,
        criteria=crit,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    diff = p1[sel] - p2.reshape(-1, 2)
    good = (st.reshape(-1) == 1) & np.all(np.abs(diff) <= KLT_BIAS_MAX_PX, axis=1)
    m1, m2 = window_moment(w1), window_moment(w2)
    out = p1.copy()
    out[sel[good]] -= m1 / (m1 - m2) * diff[good]
    return out
