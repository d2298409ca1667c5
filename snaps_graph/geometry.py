"""Small SE(3) helpers on 4x4 numpy matrices (poses are T_world_cam, KITTI camera axes)."""

from __future__ import annotations

import numpy as np


def yaw_deg(R: np.ndarray) -> float | np.ndarray:
    """Heading about the camera's vertical axis: atan2(R[0,2], R[2,2]) of R_world_cam, degrees.

    Accepts one 3x3 (or 4x4) matrix or a stack (N, 3|4, 3|4).
    """
    R = np.asarray(R)
    return np.degrees(np.arctan2(R[..., 0, 2], R[..., 2, 2]))


def wrap_deg(angle: float | np.ndarray) -> float | np.ndarray:
    """Wrap degrees to (-180, 180]."""
    a = np.mod(np.asarray(angle, dtype=float) + 180.0, 360.0) - 180.0
    a = np.where(a == -180.0, 180.0, a)
    return a if a.ndim else float(a)


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4x4)."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def is_finite_pose(T: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(T)))
