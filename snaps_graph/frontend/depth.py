"""Stereo depth by eq. 1, z = f·B / d: dense (paper §II-B: StereoBM + WLS, or SGBM) for the
paper's front end, sparse (LK along the row with a left-right check) at keypoints, where
it costs milliseconds, not a disparity map (docs/frontend.md)."""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..errors import SnapsGraphError

STEREO_WINDOW_PX = 11  # sparse stereo LK window, pixels
STEREO_LEVELS = 4  # sparse stereo LK pyramid levels (disparities up to ~100 px near the car)
STEREO_MAX_DY_PX = 1.0  # a stereo match may leave its row by at most this (rectified pair)
STEREO_LR_CHECK_PX = 0.5  # the right-to-left re-track must land this close
SGBM_BLOCK_SIZE = 5  # front-end SGBM block size, pixels (odd)
WLS_LAMBDA = 8000.0  # WLS filter smoothness
WLS_SIGMA = 1.5  # WLS filter colour sensitivity
BM_BLOCK_SIZE = 15  # front-end StereoBM block size, pixels: the paper's
STEREO_GUESS_LEVELS = 4  # sparse stereo LK levels for a point with a predicted disparity

DENSE_METHODS = ("bm_wls", "sgbm")  # the dense values of FrontendConfig.disparity


def check_stereo_pair(left: np.ndarray, right: np.ndarray) -> None:
    """A one-line SnapsGraphError unless both images are 2-D uint8 of the same size."""
    for name, img in (("left", left), ("right", right)):
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.dtype != np.uint8:
            desc = f"{img.dtype} {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
            raise SnapsGraphError(f"{name} image must be a 2-D uint8 grey array, got {desc}")
        if min(img.shape) < 32:
            raise SnapsGraphError(f"{name} image is too small ({img.shape[1]}x{img.shape[0]} pixels)")
    if left.shape != right.shape:
        raise SnapsGraphError(
            f"left image {left.shape[1]}x{left.shape[0]} and right image {right.shape[1]}x{right.shape[0]} differ in size"
        )


def offset_gain(u_left: np.ndarray, d: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """The disparity offset's factor at each point: a right camera turned by a small angle a about
    its y axis images column u_r at u_r + fx·a·(1 + x²), x = (u_r - cx) / fx, so the offset at the
    centre column grows by 1 + x² toward the sides (u_r = u_left - d; 1 where d is not finite)."""
    x = (np.asarray(u_left, np.float64) - np.asarray(d, np.float64) - camera.cx) / camera.fx
    return 1.0 + np.where(np.isfinite(x), x, 0.0) ** 2


def true_disparity(d: np.ndarray, offset_px: float, gain: np.ndarray | float = 1.0) -> np.ndarray:
    """Measured disparities corrected for the offset (measured = true + offset * gain, ``gain``
    from ``offset_gain``); invalid ones (<= 0, NaN) stay invalid, and a corrected one that is
    not positive becomes invalid."""
    if offset_px == 0.0:
        return d
    d = np.asarray(d)
    return np.where(d > 0, d - offset_px * np.asarray(gain), d).astype(d.dtype)


def correct_disparity(d: np.ndarray, u_left: np.ndarray, offset_px: float, camera: StereoCamera) -> np.ndarray:
    """``true_disparity`` with ``offset_gain`` at each point (left column ``u_left``, measured
    disparity ``d``); ``d`` itself, and no gain computed, when there is no offset."""
    if offset_px == 0.0:
        return d
    return true_disparity(d, offset_px, offset_gain(u_left, d, camera))


# stereo_order: pairs looked at before giving up on a verdict, and what one needs
ORDER_MAX_FRAMES = 10
ORDER_MIN_MATCHES = 20  # row-consistent ORB matches with |disparity| >= 1 px
ORDER_SWAPPED_SHARE = 0.8  # of those with negative disparity: the right camera is on the left


def stereo_order(left: np.ndarray, right: np.ndarray) -> tuple[str, str]:
    """Is this a left/right pair in that order? ("ok" | "swapped" | "same" | "unknown", why).

    A rectified pair's matches lie on one row with disparity u_left - u_right > 0; swapped
    cameras give the opposite sign, a right image that repeats the left gives none. ORB matches
    (cross-checked, same row within 1.5 px) decide where ``ORDER_MIN_MATCHES`` have |d| >= 1 px;
    textureless or far-only pairs are "unknown"."""
    if max(float(left.std()), float(right.std())) < 2.0:  # black or flat (a camera warming up): no verdict
        return "unknown", "textureless images"
    if np.abs(left.astype(np.int16) - right.astype(np.int16)).mean() < 0.5:
        return "same", "the right image repeats the left one (no disparity)"
    orb = cv2.ORB_create(1000)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    if dl is None or dr is None:
        return "unknown", "no features"
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    ul = np.array([kl[m.queryIdx].pt for m in matches]).reshape(-1, 2)
    ur = np.array([kr[m.trainIdx].pt for m in matches]).reshape(-1, 2)
    d = (ul[:, 0] - ur[:, 0])[np.abs(ul[:, 1] - ur[:, 1]) <= 1.5]
    d = d[np.abs(d) >= 1.0]
    if len(d) < ORDER_MIN_MATCHES:
        return "unknown", f"{len(d)} row-consistent matches"
    neg = float(np.mean(d < 0))
    why = f"{neg:.0%} of {len(d)} matched corners lie further right in the right image than in the left"
    return ("swapped" if neg >= ORDER_SWAPPED_SHARE else "ok" if neg <= 0.5 else "unknown"), why


def dense_disparity(left: np.ndarray, right: np.ndarray, cfg: FrontendConfig, method: str | None = None) -> np.ndarray:
    """Dense disparity of the left image, float32 pixels, <= 0 where unknown.

    ``method`` defaults to ``cfg.disparity`` when that is a dense method, else "bm_wls":
    - "bm_wls" (the paper's): StereoBM on the left image, a right matcher
      (``cv2.ximgproc.createRightMatcher``) for the right-to-left map, and the WLS filter
      (``createDisparityWLSFilter``, lambda ``WLS_LAMBDA``, sigma ``WLS_SIGMA``) that fuses both
      with the left image as guide. WLS fills occlusions along edges, which is why the paper uses
      it: keypoints sit on edges.
    - "sgbm": semi-global matching (``StereoSGBM``, 3-way), no post-filter.
    OpenCV returns fixed-point disparities (x16); this returns them in pixels.
    """
    check_stereo_pair(left, right)
    cfg.validate()
    method = method or (cfg.disparity if cfg.disparity in DENSE_METHODS else "bm_wls")
    if method == "bm_wls":
        bm = cv2.StereoBM.create(cfg.num_disparities, BM_BLOCK_SIZE)
        right_matcher = cv2.ximgproc.createRightMatcher(bm)
        wls = cv2.ximgproc.createDisparityWLSFilter(bm)
        wls.setLambda(WLS_LAMBDA)
        wls.setSigmaColor(WLS_SIGMA)
        disp_l = bm.compute(left, right)
        disp_r = right_matcher.compute(right, left)
        disp16 = wls.filter(disp_l, left, disparity_map_right=disp_r)
    elif method == "sgbm":
        b = SGBM_BLOCK_SIZE
        sgbm = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=cfg.num_disparities,
            blockSize=b,
            P1=8 * b * b,  # OpenCV's recommended smoothness penalties for grey images
            P2=32 * b * b,
            disp12MaxDiff=1,
            uniquenessRatio=10,
            speckleWindowSize=100,
            speckleRange=2,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        disp16 = sgbm.compute(left, right)
    else:
        raise SnapsGraphError(f"frontend.disparity: unknown dense method '{method}' (use one of {', '.join(DENSE_METHODS)})")
    return disp16.astype(np.float32) / 16.0


def depth_from_disparity(disparity: np.ndarray, camera: StereoCamera, cfg: FrontendConfig) -> np.ndarray:
    """Eq. 1, z = f·B / d, float32; 0 where d <= 0 or z is outside [min_depth_m, max_depth_m]."""
    z = camera.depth_from_disparity(disparity)
    z[(z < cfg.min_depth_m) | (z > cfg.max_depth_m)] = 0.0
    return z


def dense_depth(left: np.ndarray, right: np.ndarray, camera: StereoCamera, cfg: FrontendConfig) -> np.ndarray:
    """Depth map of the left image, float32 metres (H, W), 0 = invalid.

    Uses ``cfg.disparity`` when it names a dense method, else the paper's BM + WLS (the sparse
    mode has no dense map to offer, and the map stage needs one on keyframes).
    """
    return depth_from_disparity(dense_disparity(left, right, cfg), camera, cfg)


def sample_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at pixel positions ``uv`` (N, 2), nearest pixel, 0 outside the image or invalid."""
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
    h, w = depth.shape
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(len(uv), np.float32)
    out[inside] = depth[v[inside], u[inside]]
    return out


def sparse_disparity(
    left: np.ndarray,
    right: np.ndarray,
    uv: np.ndarray,
    cfg: FrontendConfig,
    guess_px: np.ndarray | None = None,
) -> np.ndarray:
    """Disparity (float32 pixels, 0 = no match) of left-image points ``uv`` (N, 2).

    Each point is tracked into the right image with pyramidal LK (window ``STEREO_WINDOW_PX``,
    ``STEREO_LEVELS`` pyramid levels), starting from ``u - guess_px`` when a disparity guess is
    given (the previous frame's disparity of a tracked point: it changes little between frames,
    so LK starts next to the answer), then with ``STEREO_GUESS_LEVELS`` pyramid levels. A match
    is kept when LK converged, it stays within ``STEREO_MAX_DY_PX`` of the same row (rectified
    pair), the disparity is positive, and, if ``STEREO_LR_CHECK_PX`` > 0, tracking the right
    point back lands within that many pixels of the left point.
    """
    uv = np.ascontiguousarray(uv, dtype=np.float32).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return np.zeros(0, np.float32)
    win = (STEREO_WINDOW_PX, STEREO_WINDOW_PX)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    flags = 0
    init = None
    if guess_px is not None:
        g = np.where(np.isfinite(guess_px) & (guess_px > 0), guess_px, 0.0).astype(np.float32)
        init = uv.copy()
        init[:, 0] -= g
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        left,
        right,
        uv.reshape(-1, 1, 2),
        None if init is None else init.reshape(-1, 1, 2),
        winSize=win,
        maxLevel=STEREO_LEVELS if init is None else min(STEREO_LEVELS, STEREO_GUESS_LEVELS),
        criteria=crit,
        flags=flags,
    )
    p1 = p1.reshape(-1, 2)
    d = uv[:, 0] - p1[:, 0]
    ok = (st.reshape(-1) == 1) & np.all(np.isfinite(p1), axis=1)
    ok &= np.abs(p1[:, 1] - uv[:, 1]) <= STEREO_MAX_DY_PX
    ok &= d > 0
    if STEREO_LR_CHECK_PX > 0 and np.any(ok):
        idx = np.flatnonzero(ok)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            right,
            left,
            p1[idx].reshape(-1, 1, 2),
            uv[idx].reshape(-1, 1, 2).copy(),
            winSize=win,
            maxLevel=1,
            criteria=crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        err = np.linalg.norm(back.reshape(-1, 2) - uv[idx], axis=1)
        bad = (st2.reshape(-1) != 1) | ~(err <= STEREO_LR_CHECK_PX)
        ok[idx[bad]] = False
    return np.where(ok, d, 0.0).astype(np.float32)


def sparse_depth(
    left: np.ndarray,
    right: np.ndarray,
    uv: np.ndarray,
    camera: StereoCamera,
    cfg: FrontendConfig,
    guess_px: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(depth, disparity) at left-image points ``uv``: eq. 1 on ``sparse_disparity``; 0 = invalid."""
    disp = sparse_disparity(left, right, uv, cfg, guess_px)
    return depth_from_disparity(disp, camera, cfg), disp
