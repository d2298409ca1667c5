"""numpy (N, 4, 4) poses <-> gtsam Pose3 / Values, keyed 0..N-1."""

from __future__ import annotations

import gtsam
import numpy as np


def to_pose3(T: np.ndarray) -> gtsam.Pose3:
    """A Pose3 from a 4x4 whose rotation is projected onto SO(3) (SVD), so tiny numerical
    non-orthogonality from chained float products never reaches GTSAM's retractions."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:  # a reflection: flip the weakest axis
        U[:, -1] *= -1
        R = U @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), np.asarray(T[:3, 3], dtype=float))


def array_to_values(poses) -> gtsam.Values:
    """Keys 0..N-1 holding the (N, 4, 4) poses (rotations projected onto SO(3), see to_pose3)."""
    values = gtsam.Values()
    for k, T in enumerate(poses):
        values.insert(k, to_pose3(T))
    return values


def values_to_array(values: gtsam.Values, n: int | None) -> np.ndarray:
    """Poses of keys 0..n-1 as (n, 4, 4) (n None: all); extractPose3 gives rows [R row-major (9),
    t (3)] in key order, and our keys are exactly 0..n-1."""
    flat = gtsam.utilities.extractPose3(values)
    if n is None:
        n = flat.shape[0]
    if flat.shape[0] != n:
        raise RuntimeError(f"expected {n} poses in the estimate, found {flat.shape[0]}")
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = flat[:, :9].reshape(n, 3, 3)
    out[:, :3, 3] = flat[:, 9:]
    out[:, 3, 3] = 1.0
    return out
