"""The motion between the reference frame and the current one (paper eq. 3): PnP RANSAC + LM,
then (``motion = "stereo_ba"``) the two-view stereo BA on PnP's inliers, and the checks that flag
an implausible step."""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..geometry import inv, rotation_angle_deg
from .stereo_ba import STEREO_BA, stereo_two_view_ba

PNP_ITERATIONS = 200  # PnP RANSAC iterations
PNP_CONFIDENCE = 0.999  # PnP RANSAC confidence
SBA_KEEP_BELOW = 100  # below this many stereo-BA inliers, tracks near its pose are kept too (a small image)
RANSAC_SEED = 0  # cv2.setRNGSeed before every RANSAC: the same input gives the same output
PNP_REPROJECTION_PX = 1.5  # PnP RANSAC inlier threshold, px: a few times the matching noise
MIN_INLIERS = 20  # fewer PnP inliers flag the frame: below this a pose is not well determined
MAX_STEP_M = 4.0  # a larger step between frames is implausible (flagged): 40 m/s at 10 Hz, m
MAX_STEP_DEG = 20.0  # a larger turn between frames is implausible (flagged), deg


class Flag(Exception):
    """This frame is flagged for ``reason``; ``keyframe`` (usable features) may still be a reference."""

    def __init__(self, reason: str, keyframe=None):
        super().__init__(reason)
        self.reason = reason
        self.keyframe = keyframe


def pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def pnp_ransac(
    pts3d: np.ndarray, uv: np.ndarray, camera: StereoCamera, cfg: FrontendConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP RANSAC (eq. 3) then LM refinement on the inliers.

    Returns (T_cur_ref 4x4: maps points given in the reference camera frame into the current
    camera frame, inlier indices) or None when there are too few points, RANSAC fails or the
    result is not finite. The RNG is seeded here (``RANSAC_SEED``), in the calling thread,
    because OpenCV's RNG is per thread.
    """
    n = len(pts3d)
    if n < max(6, MIN_INLIERS):
        return None
    obj = np.ascontiguousarray(pts3d, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
    K = camera.K
    cv2.setRNGSeed(RANSAC_SEED)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=PNP_ITERATIONS,
        reprojectionError=PNP_REPROJECTION_PX,
        confidence=PNP_CONFIDENCE,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or inl is None or len(inl) < 6:
        return None
    inl = inl.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    T = pose_from_rvec(rvec, tvec)
    if not np.all(np.isfinite(T)):
        return None
    # Inliers of the refined pose (the count reported and used for the flags).
    proj = obj @ T[:3, :3].T + T[:3, 3]
    z = proj[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * proj[:, 0] / z + K[0, 2]
        v = K[1, 1] * proj[:, 1] / z + K[1, 2]
    err = np.hypot(u - img[:, 0], v - img[:, 1])
    inliers = np.flatnonzero((z > 0) & (err <= PNP_REPROJECTION_PX))
    return T, inliers


def project(T_cur_ref: np.ndarray, pts3d: np.ndarray, camera: StereoCamera) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions of reference-frame points seen from the current camera, and their depth."""
    p = pts3d.astype(np.float64) @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    z = p[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    uv = np.stack([camera.fx * p[:, 0] / zs + camera.cx, camera.fy * p[:, 1] / zs + camera.cy], axis=1)
    return uv.astype(np.float32), z


def check_motion(T_cur_ref: np.ndarray, inliers: int, gap: int, cfg: FrontendConfig) -> np.ndarray:
    """T_ref_cur, or Flag for too few inliers, a non-finite pose or more motion than
    ``MAX_STEP_M`` / ``MAX_STEP_DEG`` per frame over ``gap`` frames."""
    if inliers < MIN_INLIERS:
        raise Flag(f"too few PnP inliers ({inliers} < {MIN_INLIERS})")
    if not np.all(np.isfinite(T_cur_ref)):
        raise Flag("non-finite PnP pose")
    T_ref_cur = inv(T_cur_ref)
    step = float(np.linalg.norm(T_ref_cur[:3, 3]))
    angle = rotation_angle_deg(T_ref_cur[:3, :3])
    if step > MAX_STEP_M * gap or angle > MAX_STEP_DEG * gap:
        raise Flag(f"implausible motion ({step:.2f} m, {angle:.1f} deg over {gap} frame(s))")
    return T_ref_cur


def refine_motion(
    T_cur_ref: np.ndarray,
    inl: np.ndarray,
    ref_uv: np.ndarray,
    ref_disp: np.ndarray,
    cur_uv: np.ndarray,
    cur_disp: np.ndarray,
    camera: StereoCamera,
    cfg: FrontendConfig,
    true: Callable[[np.ndarray, np.ndarray], np.ndarray],
    timings: dict[str, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Stereo BA on PnP's inliers ``inl`` (``motion = "stereo_ba"``): (T_cur_ref, inlier indices,
    the pose covariance or None). ``true(uv, d)`` corrects disparities for the offset. The BA's
    own outliers are dropped from ``inl``; a small image's tracks within ``STEREO_BA.keep_px`` are kept
    (below ``SBA_KEEP_BELOW`` inliers). A degenerate BA leaves PnP's answer (``timings['sba_fallback']``)."""
    if cfg.motion != "stereo_ba" or len(inl) == 0:
        return T_cur_ref, inl, None
    t0 = time.perf_counter()
    r = stereo_two_view_ba(
        T_cur_ref,
        ref_uv[inl],
        true(ref_uv[inl], ref_disp[inl]),
        cur_uv[inl],
        true(cur_uv[inl], cur_disp[inl]),
        camera,
        STEREO_BA,
    )
    timings["sba"] = (time.perf_counter() - t0) * 1000.0
    if not r.ok:
        timings["sba_fallback"] = 1.0
        return T_cur_ref, inl, None
    if r.kept is not None and np.count_nonzero(r.inliers) < SBA_KEEP_BELOW:  # a small image: keep its tracks
        return r.T_cur_ref, inl[r.kept], r.cov
    return r.T_cur_ref, inl[r.inliers], r.cov
