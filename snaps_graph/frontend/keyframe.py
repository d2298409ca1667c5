"""What a frame leaves for the next one (its keypoints with depth and the pose it was given),
and the offset-corrected sparse stereo both feature paths measure depth with."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NoReturn

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..types import FrameFeatures, StereoFrame
from . import depth as depth_mod
from .depth import correct_disparity
from .motion import Flag, check_motion

MIN_STEREO_POINTS = 40  # a frame with fewer keypoints with depth cannot be a reference
FRAME_FEATURES = 500  # keypoints with depth kept per frame in the VO result: the viewer's points, a light record


@dataclass
class Keyframe:
    index: int
    pose: np.ndarray  # T_world_cam (VO chain)
    left: np.ndarray  # left image (KLT tracks from it)
    uv: np.ndarray  # (N,2) float32, only keypoints with valid depth
    pts3d: np.ndarray  # (N,3) float32, camera frame
    disp: np.ndarray  # (N,) float32 disparity, pixels (the next stereo search starts there)
    desc: np.ndarray | None  # (N,D) descriptors in sift/orb modes
    sharpness: float
    features: FrameFeatures  # VOResult.features
    ids: np.ndarray  # (N,) int64 landmark ids (klt: persistent across frames; -1 where unknown)
    right: np.ndarray | None = None  # right image (the ORB retry matches keypoints with depth from it)


def sharpness(img: np.ndarray) -> float:
    """Mean absolute Laplacian (3x3): drops sharply when an image is blurred. (OpenCV's L1 norm
    is an exact integer sum: the same value as ``np.abs(lap).mean()``, several times faster.)"""
    lap = cv2.Laplacian(img, cv2.CV_16S, ksize=1)
    return cv2.norm(lap, cv2.NORM_L1) / lap.size


def empty_features(mode: str) -> FrameFeatures:
    d = np.zeros((0, 128), np.float32) if mode == "sift" else np.zeros((0, 32), np.uint8)
    return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32), d)


class Stereo:
    """Sparse stereo at left points, corrected for the disparity offset applied now (``offset()``)."""

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, offset: Callable[[], float]):
        self.camera, self.cfg, self.offset = camera, cfg, offset

    def true(self, uv: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Measured disparities ``d`` at left points ``uv`` corrected for the offset."""
        u = np.asarray(uv).reshape(-1, 2)[:, 0]
        return correct_disparity(d, u, self.offset(), self.camera)

    def depth(self, left: np.ndarray, right: np.ndarray, uv: np.ndarray, guess: np.ndarray | None = None):
        """(depth from the corrected disparity, measured disparity) at ``uv``."""
        z, d = depth_mod.sparse_depth(left, right, uv, self.camera, self.cfg, guess)
        if self.offset() != 0.0:
            z = depth_mod.depth_from_disparity(self.true(uv, d), self.camera, self.cfg)
        return z, d


def make_keyframe(
    frame: StereoFrame,
    uv: np.ndarray,
    z: np.ndarray,
    disp: np.ndarray,
    desc: np.ndarray | None,
    sharp: float,
    camera: StereoCamera,
    cfg: FrontendConfig,
    timings: dict[str, float],
    ids: np.ndarray | None = None,
) -> Keyframe:
    """Keep keypoints with valid depth; back-project them (eq. 2); pick the frame's features.

    Detected keypoints come strongest first, so the first ``FRAME_FEATURES`` are kept; tracked
    corners have no such order, so an evenly spread subset is kept (without descriptors: loops
    verify with their own features, ``verification/features.py``)."""
    valid = z > 0
    uv, z, disp = uv[valid], z[valid], disp[valid]
    ids = ids[valid] if ids is not None else np.full(len(uv), -1, np.int64)
    desc = desc[valid] if desc is not None else None
    pts3d = camera.backproject(uv[:, 0], uv[:, 1], z).astype(np.float32)
    t0 = time.perf_counter()
    m = len(uv)
    if desc is not None:
        pick = np.arange(min(m, FRAME_FEATURES))
        fdesc = desc[pick]
    else:
        pick = np.arange(m) if m <= FRAME_FEATURES else np.linspace(0, m - 1, FRAME_FEATURES).astype(np.int64)
        fdesc = np.zeros((len(pick), 32), np.uint8)
    features = FrameFeatures(np.ascontiguousarray(uv[pick]), np.ascontiguousarray(pts3d[pick]), np.ascontiguousarray(fdesc))
    timings["features"] = timings.get("features", 0.0) + (time.perf_counter() - t0) * 1000.0
    return Keyframe(frame.index, np.eye(4), frame.left, uv, pts3d, disp, desc, sharp, features, ids, right=frame.right)


def reject(kf: Keyframe, failure: str, cfg: FrontendConfig) -> NoReturn:
    """Flag the frame; its keyframe may still be the next reference when it has enough depth."""
    raise Flag(failure, kf if len(kf.uv) >= MIN_STEREO_POINTS else None)


def conclude(kf: Keyframe, T_cur_ref: np.ndarray | None, n_inl: int, gap: int, failure: str, cfg: FrontendConfig) -> np.ndarray:
    """T_ref_cur of an accepted frame, else Flag. Motion problems are reported first; a frame whose
    own stereo failed (a swapped or broken pair) is flagged even when PnP succeeded, since its
    depth, and so its next step, cannot be trusted."""
    usable = len(kf.uv) >= MIN_STEREO_POINTS
    if T_cur_ref is None:
        reject(kf, failure, cfg)
    try:
        T_ref_cur = check_motion(T_cur_ref, n_inl, gap, cfg)
    except Flag as flag:
        raise Flag(flag.reason, kf if usable else None) from None
    if not usable:
        raise Flag(f"too few keypoints with stereo depth ({len(kf.uv)} < {MIN_STEREO_POINTS})")
    return T_ref_cur
