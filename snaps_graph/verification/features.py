"""Loop-verification features independent of the tracker, whose KLT corners do not repeat when a
place is revisited metres apart.

``LoopFeatureBank`` keeps multi-scale keypoints, descriptors and stereo 3D points of every
``reference_every``-th frame, and the current frame's only when a candidate is verified.
:func:`verify_features`: PnP RANSAC of a reference's points, a depth check against the current
frame's stereo, and the pose's covariance for the graph (docs/decisions.md, "Loop closure (SNAPS)").
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig, VerificationConfig
from ..frontend.depth import correct_disparity, sparse_disparity
from ..frontend.features import match_descriptors
from ..frontend.keyframe import MIN_STEREO_POINTS
from ..frontend.motion import MIN_INLIERS, pnp_ransac, pose_from_rvec
from ..geometry import inv, rotation_angle_deg
from ..types import FrameFeatures, StereoFrame

LOOP_ORB_LEVELS = 8  # ORB pyramid levels of the loop keypoints
LOOP_ORB_SCALE = 1.2  # ORB pyramid ratio between levels
LOOP_ORB_FAST_THRESHOLD = 20  # ORB FAST threshold
LOOP_ORB_UPRIGHT = True  # descriptors at angle 0 (the cameras do not roll)
LOOP_RATIO_TEST = 0.8  # Lowe's ratio for loop matches
LOOP_DEPTH_MIN_RATIO = 0.5  # at least this fraction of the inliers with a current disparity must agree with the predicted one
LOOP_MIN_SIGMA_PX = 0.5  # floor of the reprojection sigma in a loop's covariance, pixels
VERIFY_MAX_TRANSLATION_M = 30.0  # a verified relative pose farther than this is implausible
VERIFY_MAX_ROTATION_DEG = 90.0  # a verified relative pose turned more than this is implausible
LOOP_ORB_FEATURES = 1000  # loop keypoints per reference frame (before the stereo check)
LOOP_QUERY_FEATURES = 1500  # loop keypoints of the current frame when verifying
REFERENCE_EVERY = 5  # loop reference features every this many frames: nearer ones share their errors
DEPTH_CHECK_PX = 1.0  # a loop inlier's disparity must agree with its prediction within this, px (0 = off)
SUBPIXEL_PX = 2.0  # loop keypoint sub-pixel refinement half-window at level 0, px (0 = off)
MAX_DISTANCE_M = 8.0  # a verified loop farther apart than this is not the same place, m


@dataclass
class LoopMatch:
    """A verified loop measurement."""

    T_ref_cur: np.ndarray  # 4x4: pose of the current camera in the reference camera frame
    inliers: int  # PnP inliers that also passed the depth check
    cov: np.ndarray  # 6x6 covariance of T_ref_cur, tangent (rot rad, trans m), right perturbation (GTSAM's Pose3)
    rms_px: float  # reprojection rms of the inliers, pixels


def detect_loop_keypoints(
    img: np.ndarray, cfg: VerificationConfig, n: int | None = None, subpixel_px: float = SUBPIXEL_PX
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Multi-scale keypoints for loops: (uv float32 (N,2), descriptors, size float32 (N,)).

    ``cfg.detector`` "orb": ORB's own pyramid, descriptors computed upright (``LOOP_ORB_UPRIGHT``: a
    place seen again gives more alike descriptors), corners refined to sub-pixel with
    ``subpixel_px`` > 0; "sift": SIFT on the half-size image. Strongest first, ties by position.
    """
    n = LOOP_ORB_FEATURES if n is None else n
    if cfg.detector == "sift":
        sift = cv2.SIFT.create(n)
        half = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        kps, desc = sift.detectAndCompute(half, None)
        if not kps or desc is None:
            return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32)
        uv = np.array([k.pt for k in kps], np.float32) * 2.0 + 0.5
        size = np.array([k.size for k in kps], np.float32) * 2.0
        resp = np.array([k.response for k in kps], np.float32)
        order = np.lexsort((uv[:, 1], uv[:, 0], -resp))
        return uv[order], np.ascontiguousarray(desc[order], np.float32), size[order]
    orb = cv2.ORB.create(nfeatures=n, scaleFactor=LOOP_ORB_SCALE, nlevels=LOOP_ORB_LEVELS, fastThreshold=LOOP_ORB_FAST_THRESHOLD)
    kps = orb.detect(img, None)
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32)
    if LOOP_ORB_UPRIGHT:
        kps = [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, 0.0, k.response, k.octave, i) for i, k in enumerate(kps)]
    else:
        for i, k in enumerate(kps):
            k.class_id = i
    kps, desc = orb.compute(img, kps)
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32)
    uv = np.array([k.pt for k in kps], np.float32)
    if subpixel_px > 0:
        uv = _subpixel(img, uv, np.array([k.octave for k in kps]), subpixel_px)
    size = np.array([k.size for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    order = np.lexsort((uv[:, 1], uv[:, 0], -resp))
    return uv[order], np.ascontiguousarray(desc[order], np.uint8), size[order]


def _subpixel(img: np.ndarray, uv: np.ndarray, octave: np.ndarray, subpixel_px: float) -> np.ndarray:
    """FAST corners found on a pyramid level sit on that level's pixel grid (up to
    ``LOOP_ORB_SCALE``^octave px off at full resolution): refine each at full resolution by
    ``cv2.cornerSubPix`` with a half-window of ``subpixel_px`` x scale^octave, and keep the
    original where the refinement moved farther than that half-window."""
    out = uv.copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01)
    for o in np.unique(octave):
        sel = np.flatnonzero(octave == o)
        half = max(2, int(round(subpixel_px * LOOP_ORB_SCALE ** int(o))))
        pts = uv[sel].reshape(-1, 1, 2).copy()
        ref = cv2.cornerSubPix(img, pts, (half, half), (-1, -1), crit).reshape(-1, 2)
        ok = np.all(np.isfinite(ref), 1) & (np.abs(ref - uv[sel]).max(1) <= half)
        out[sel[ok]] = ref[ok]
    return out


def stereo_points(
    left: np.ndarray, right: np.ndarray, uv: np.ndarray, camera: StereoCamera, cfg: FrontendConfig, offset_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """(indices of ``uv`` with valid depth, their 3D points float32 (M,3)) by sparse stereo (eq. 1-2),
    disparities corrected by the front end's disparity offset ``offset_px`` (measured - true)."""
    if len(uv) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    disp = correct_disparity(sparse_disparity(left, right, uv, cfg), uv[:, 0], offset_px, camera)
    fb = camera.fx * camera.baseline_m
    with np.errstate(divide="ignore"):
        z = np.where(disp > 0, fb / np.maximum(disp, 1e-9), 0.0)
    ok = np.flatnonzero((z >= cfg.min_depth_m) & (z <= cfg.max_depth_m))
    pts = camera.backproject(uv[ok, 0], uv[ok, 1], z[ok]).astype(np.float32)
    return ok.astype(np.int64), pts


def pose_covariance(
    T_cur_ref: np.ndarray, pts_ref: np.ndarray, uv: np.ndarray, camera: StereoCamera, min_sigma_px: float
) -> tuple[np.ndarray, float]:
    """Covariance (6x6, rot then trans) of T_ref_cur from the PnP inliers, and their rms in pixels.

    Gauss-Newton: cov = s² (JᵀJ)⁻¹ with J the reprojection Jacobian for T_ref_cur ← T_ref_cur·Exp(ξ)
    (so X_cur ← X_cur + [X_cur]ₓ ω − v to first order) and s² the residual variance per
    coordinate (2n − 6 degrees of freedom), at least ``min_sigma_px``².
    """
    R, t = T_cur_ref[:3, :3], T_cur_ref[:3, 3]
    X = pts_ref.astype(np.float64) @ R.T + t
    x, y, z = X[:, 0], X[:, 1], np.maximum(X[:, 2], 1e-6)
    fx, fy = camera.fx, camera.fy
    res_u = fx * x / z + camera.cx - uv[:, 0]
    res_v = fy * y / z + camera.cy - uv[:, 1]
    n = len(X)
    dof = max(2 * n - 6, 1)
    s2 = max(float((res_u @ res_u + res_v @ res_v) / dof), min_sigma_px**2)
    # d(u,v)/dX
    Pu = np.stack([fx / z, np.zeros(n), -fx * x / z**2], axis=1)
    Pv = np.stack([np.zeros(n), fy / z, -fy * y / z**2], axis=1)

    # dX/dω = [X]ₓ (X + [X]ₓ ω = X − ω × X), dX/dv = −I
    def row(P: np.ndarray) -> np.ndarray:  # P·[X]ₓ, P·(−I)
        xx, yy, zz = X[:, 0], X[:, 1], X[:, 2]
        dw = np.stack([P[:, 1] * zz - P[:, 2] * yy, P[:, 2] * xx - P[:, 0] * zz, P[:, 0] * yy - P[:, 1] * xx], axis=1)
        return np.concatenate([dw, -P], axis=1)

    J = np.concatenate([row(Pu), row(Pv)], axis=0)
    H = J.T @ J
    try:
        cov = s2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.diag([1.0] * 3 + [100.0] * 3)
    cov = 0.5 * (cov + cov.T)
    return cov, float(np.sqrt(s2))


def ratio_matches(
    ref: FrameFeatures | None, cur: FrameFeatures | None, cfg: FrontendConfig, ratio: float, unique: bool = False
) -> tuple[FrameFeatures, FrameFeatures, tuple[np.ndarray, np.ndarray]] | None:
    """``(ref, cur, (ref indices, cur indices))`` of ratio-test matches, or None when either side
    is missing, the descriptor kinds differ, or fewer than ``MIN_INLIERS`` matches survive.
    ``unique``: a keypoint of ``cur`` keeps only its first match (a reference merged from several
    frames holds one point several times, which must not count as several inliers)."""
    if ref is None or cur is None or len(ref.desc) < MIN_INLIERS or len(cur.desc) < 2:
        return None
    if ref.desc.dtype != cur.desc.dtype or ref.desc.shape[1] != cur.desc.shape[1]:
        return None
    ia, ib = match_descriptors(ref.desc, cur.desc, ratio)
    if unique:
        first = np.sort(np.unique(ib, return_index=True)[1])
        ia, ib = ia[first], ib[first]
    if len(ia) < MIN_INLIERS:
        return None
    return ref, cur, (ia, ib)


def match_and_pnp(
    ref: FrameFeatures | None,
    cur: FrameFeatures | None,
    camera: StereoCamera,
    cfg: FrontendConfig,
    ratio: float,
    unique: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Ratio-test matches of ``ref``'s descriptors to ``cur``'s, then PnP RANSAC of ``ref``'s 3D
    points on ``cur``'s pixels: (T_cur_ref, ref indices, cur indices, inlier positions among the
    matches), or None when the descriptor kinds differ or fewer than ``MIN_INLIERS`` survive."""
    m = ratio_matches(ref, cur, cfg, ratio, unique)
    if m is None:
        return None
    ref, cur, (ia, ib) = m
    res = pnp_ransac(ref.pts3d[ia], cur.uv[ib], camera, cfg)
    if res is None:
        return None
    T_cur_ref, inliers = res
    if len(inliers) < MIN_INLIERS or not np.all(np.isfinite(T_cur_ref)):
        return None
    return T_cur_ref, ia, ib, inliers


def plausible(T_cur_ref: np.ndarray, cfg: FrontendConfig) -> np.ndarray | None:
    """T_ref_cur, or None when more than ``VERIFY_MAX_TRANSLATION_M`` apart or rotated by more
    than ``VERIFY_MAX_ROTATION_DEG``: a wrong loop is worse than a missed one."""
    T_ref_cur = inv(T_cur_ref)
    if np.linalg.norm(T_ref_cur[:3, 3]) > VERIFY_MAX_TRANSLATION_M:
        return None
    if rotation_angle_deg(T_ref_cur[:3, :3]) > VERIFY_MAX_ROTATION_DEG:
        return None
    return T_ref_cur


def verify_features(
    ref: FrameFeatures | None,
    cur: FrameFeatures,
    cur_frame: StereoFrame | None,
    camera: StereoCamera,
    cfg: FrontendConfig,
    vcfg: VerificationConfig,
    offset_px: float = 0.0,
    unique: bool = False,
    depth_check_px: float = DEPTH_CHECK_PX,
) -> LoopMatch | None:
    """Verify a loop from the reference's 3D points to the current frame's keypoints.

    Ratio-test matches, PnP RANSAC (``pnp_ransac``), then, with ``cur_frame`` and
    ``depth_check_px`` > 0, the inliers' stereo disparity in the current frame must agree
    with their predicted one within that many pixels; at least ``MIN_INLIERS`` must pass both
    and at least ``LOOP_DEPTH_MIN_RATIO`` of the inliers that have a current disparity. The pose
    must be :func:`plausible`. None if anything fails. ``unique`` as in :func:`ratio_matches`.
    """
    found = match_and_pnp(ref, cur, camera, cfg, LOOP_RATIO_TEST, unique)
    if found is None or ref is None:
        return None
    T_cur_ref, ia, ib, inl = found
    pts, uv = ref.pts3d[ia[inl]], cur.uv[ib[inl]]
    if cur_frame is not None and depth_check_px > 0:
        Xc = pts.astype(np.float64) @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
        d_pred = camera.fx * camera.baseline_m / np.maximum(Xc[:, 2], 1e-6)
        d_raw = sparse_disparity(cur_frame.left, cur_frame.right, uv, cfg)
        d_meas = correct_disparity(d_raw, uv[:, 0], offset_px, camera)
        has = d_meas > 0
        agree = has & (np.abs(d_meas - d_pred) <= depth_check_px)
        if int(agree.sum()) < MIN_INLIERS or agree.sum() < LOOP_DEPTH_MIN_RATIO * max(int(has.sum()), 1):
            return None
        pts, uv = pts[agree], uv[agree]
        # Re-estimate on the points that passed both tests (LM from the RANSAC pose).
        rvec = cv2.Rodrigues(T_cur_ref[:3, :3])[0]
        rvec, tvec = cv2.solvePnPRefineLM(
            pts.astype(np.float64), uv.astype(np.float64), camera.K, None, rvec, T_cur_ref[:3, 3].reshape(3, 1).copy()
        )
        T = pose_from_rvec(rvec, tvec)
        if np.all(np.isfinite(T)):
            T_cur_ref = T
    T_ref_cur = plausible(T_cur_ref, cfg)
    if T_ref_cur is None:
        return None
    cov, rms = pose_covariance(T_cur_ref, pts, uv, camera, LOOP_MIN_SIGMA_PX)
    if not np.all(np.isfinite(cov)):
        return None
    return LoopMatch(T_ref_cur, int(len(pts)), cov, rms)


class LoopFeatureBank:
    """Loop features of reference frames (every ``reference_every``-th stream position) and of the
    current frame on demand, computed on one worker thread (``background=False``: inline); every
    read waits for the pending ones, so results do not depend on timing.
    """

    merged = False  # a reference holds one frame's points (verify with ``unique`` when True)

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, vcfg: VerificationConfig, background: bool = True):
        self.camera = camera
        self.cfg, self.vcfg = cfg, vcfg  # stereo depth; the keypoints and references
        self._own: dict[int, FrameFeatures] = {}  # the references this bank computed or was given
        self._ref: Mapping[int, FrameFeatures] = self._own  # what it verifies against (load: a session's)
        self._pending: dict[int, Future] = {}
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="loop-features") if background else None
        self._query_k: int | None = None
        self._query: FrameFeatures | None = None

    def __len__(self) -> int:
        self._collect()
        return len(self._ref)

    def nbytes(self) -> int:
        self._collect()
        return sum(f.uv.nbytes + f.pts3d.nbytes + f.desc.nbytes for f in self._ref.values())

    def wants(self, k: int) -> bool:
        return k % REFERENCE_EVERY == 0

    def add(self, k: int, frame: StereoFrame, offset_px: float = 0.0) -> None:
        """Compute and keep reference features for stream position ``k`` if it is one
        (``offset_px``: the front end's disparity offset for this frame)."""
        if not self.wants(k):
            return
        if self._pool is None:
            self._keep(k, self._compute(frame.left, frame.right, offset_px))
        else:
            self._pending[k] = self._pool.submit(self._compute, frame.left, frame.right, offset_px)

    def _compute(self, left: np.ndarray, right: np.ndarray, offset_px: float) -> FrameFeatures | None:
        uv, desc, _ = detect_loop_keypoints(left, self.vcfg)
        idx, pts = stereo_points(left, right, uv, self.camera, self.cfg, offset_px)
        if len(idx) < MIN_STEREO_POINTS:
            return None
        return FrameFeatures(np.ascontiguousarray(uv[idx]), pts, np.ascontiguousarray(desc[idx]))

    def _keep(self, k: int, features: FrameFeatures | None) -> None:
        if features is not None:
            self._own[k] = features

    def _collect(self) -> None:
        """Wait for the pending references and keep them (in stream order)."""
        for k in sorted(self._pending):
            self._keep(k, self._pending.pop(k).result())

    def close(self) -> None:
        self._collect()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def put(self, k: int, features: FrameFeatures) -> None:
        """Store precomputed reference features (replays)."""
        self._own[k] = features

    def load(self, refs: Mapping[int, FrameFeatures], vo_poses: np.ndarray) -> None:
        """Verify against a saved session's references by stream position, read as asked for
        (``vo_poses``: its odometry poses, which a monocular bank needs); the bank then holds
        nothing of its own."""
        self._ref = refs

    def stored(self) -> list[tuple[int, FrameFeatures]]:
        """The references kept so far, by stream position (what a session saves)."""
        self._collect()
        return sorted(self._ref.items(), key=lambda kv: kv[0])

    def reference(self, k: int) -> FrameFeatures | None:
        self._collect()
        return self._ref.get(k)

    def nearest(self, k: int) -> int | None:
        """The stored reference nearest to stream position ``k`` (ties: the older), or None."""
        self._collect()
        e = REFERENCE_EVERY
        base = k - k % e
        for c in (base, base + e, base - e, base + 2 * e) if k - base <= e // 2 else (base + e, base, base + 2 * e, base - e):
            if c in self._ref:
                return c
        return None

    def query(self, k: int, frame: StereoFrame) -> FrameFeatures:
        """The current frame's keypoints and descriptors (no depth), computed once per ``k``."""
        if self._query_k != k or self._query is None:
            uv, desc, _ = detect_loop_keypoints(frame.left, self.vcfg, LOOP_QUERY_FEATURES)
            self._query = FrameFeatures(uv, np.zeros((len(uv), 3), np.float32), desc)
            self._query_k = k
        return self._query
