"""Geometric verification of a loop candidate (SPEC "Factor graph": a real relative pose).

Given the stored ``FrameFeatures`` of a reference frame and of the current frame, match their
descriptors with the ratio test and solve PnP RANSAC from the reference's 3D points to the
current frame's 2D keypoints: the same estimator as the odometry (paper eq. 3), so a verified
loop measurement has the quality of a VO step.
"""

from __future__ import annotations

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..geometry import inv, rotation_angle_deg
from ..types import FrameFeatures
from .features import match_descriptors
from .odometry import pnp_ransac


def verify_loop(
    ref: FrameFeatures, cur: FrameFeatures, camera: StereoCamera, cfg: FrontendConfig
) -> tuple[np.ndarray, int] | None:
    """(T_ref_cur 4x4, inlier count) or None.

    T_ref_cur is the pose of the current camera in the reference camera frame. None when the
    descriptors are of different kinds or there are too few matches, when PnP finds fewer than
    ``cfg.min_inliers`` inliers, or when the relative pose is non-finite or implausible (more
    than ``verify_max_translation_m`` apart or rotated by more than ``verify_max_rotation_deg``):
    a wrong loop is worse than a missed one.
    """
    found = match_and_pnp(ref, cur, camera, cfg, cfg.ratio_test)
    if found is None:
        return None
    T_cur_ref, _, _, inliers = found
    T_ref_cur = plausible(T_cur_ref, cfg)
    if T_ref_cur is None:
        return None
    return T_ref_cur, int(len(inliers))


def match_and_pnp(
    ref: FrameFeatures | None, cur: FrameFeatures | None, camera: StereoCamera, cfg: FrontendConfig, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Ratio-test matches of ``ref``'s descriptors to ``cur``'s, then PnP RANSAC of ``ref``'s 3D
    points on ``cur``'s pixels: (T_cur_ref, ref indices, cur indices, inlier positions among the
    matches), or None when the descriptor kinds differ or fewer than ``min_inliers`` survive."""
    if ref is None or cur is None or len(ref.desc) < cfg.min_inliers or len(cur.desc) < 2:
        return None
    if ref.desc.dtype != cur.desc.dtype or ref.desc.shape[1] != cur.desc.shape[1]:
        return None
    ia, ib = match_descriptors(ref.desc, cur.desc, ratio)
    if len(ia) < cfg.min_inliers:
        return None
    res = pnp_ransac(ref.pts3d[ia], cur.uv[ib], camera, cfg)
    if res is None:
        return None
    T_cur_ref, inliers = res
    if len(inliers) < cfg.min_inliers or not np.all(np.isfinite(T_cur_ref)):
        return None
    return T_cur_ref, ia, ib, inliers


def plausible(T_cur_ref: np.ndarray, cfg: FrontendConfig) -> np.ndarray | None:
    """T_ref_cur, or None when more than ``verify_max_translation_m`` apart or rotated by more
    than ``verify_max_rotation_deg``: a wrong loop is worse than a missed one."""
    T_ref_cur = inv(T_cur_ref)
    if np.linalg.norm(T_ref_cur[:3, 3]) > cfg.verify_max_translation_m:
        return None
    if rotation_angle_deg(T_ref_cur[:3, :3]) > cfg.verify_max_rotation_deg:
        return None
    return T_ref_cur
