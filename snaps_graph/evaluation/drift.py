"""Drifted odometry from a ground-truth trajectory: the errors a real stereo VO makes.

Each ground-truth step is driven again with a scale bias, heading and pitch random walks and an
optional roll rate; ``pct`` rescales them together to an end error of ``pct`` % of the distance.
What each term is, and the defaults' source: docs/loop-closure.md, "The drift tool".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import SnapsGraphError


@dataclass(frozen=True)
class DriftModel:
    """Error rates of a drifted odometry (1 sigma where random)."""

    # Defaults: our stereo VO on real KITTI 06 frames 0-50 (docs/loop-closure.md, "The drift tool").
    scale_bias_pct: float = 0.02  # translation scale error, percent (the sign is drawn per seed)
    heading_rw_deg_per_sqrt_m: float = 0.07  # heading random walk
    pitch_rw_deg_per_sqrt_m: float = 0.017  # pitch random walk
    roll_deg_per_100m: float = 0.0  # slow roll drift (0 = off)

    def scaled(self, k: float) -> DriftModel:
        return DriftModel(
            self.scale_bias_pct * k,
            self.heading_rw_deg_per_sqrt_m * k,
            self.pitch_rw_deg_per_sqrt_m * k,
            self.roll_deg_per_100m * k,
        )


def _steps(gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative rotations (N-1, 3, 3) and translations (N-1, 3) of T_{k-1}^-1 T_k."""
    R, t = gt[:, :3, :3], gt[:, :3, 3]
    R_rel = np.einsum("kji,kjl->kil", R[:-1], R[1:])
    t_rel = np.einsum("kji,kj->ki", R[:-1], t[1:] - t[:-1])
    return R_rel, t_rel


def _compose(gt0: np.ndarray, R_rel: np.ndarray, t_rel: np.ndarray, err: np.ndarray, scale: float) -> np.ndarray:
    """Poses from gt0 along steps whose rotations carry the error rotations ``err`` (right-multiplied)."""
    n = len(R_rel) + 1
    out = np.zeros((n, 4, 4))
    out[:, 3, 3] = 1.0
    out[0] = gt0
    R, p = gt0[:3, :3].copy(), gt0[:3, 3].copy()
    Rs = R_rel @ err
    ts = t_rel * scale
    for k in range(n - 1):
        p = p + R @ ts[k]
        R = R @ Rs[k]
        out[k + 1, :3, :3], out[k + 1, :3, 3] = R, p
    return out


def _draws(gt: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Standard normal increments per step for heading and pitch, and the scale bias's sign."""
    rng = np.random.default_rng(seed)
    m = len(gt) - 1
    return rng.standard_normal(m), rng.standard_normal(m), float(rng.choice([-1.0, 1.0]))


def _apply(gt: np.ndarray, model: DriftModel, draws, R_rel, t_rel, ds) -> np.ndarray:
    xi_h, xi_p, sign = draws
    rad = math.pi / 180.0
    rotvec = np.zeros((len(ds), 3))
    rotvec[:, 1] = model.heading_rw_deg_per_sqrt_m * rad * np.sqrt(ds) * xi_h
    rotvec[:, 0] = model.pitch_rw_deg_per_sqrt_m * rad * np.sqrt(ds) * xi_p
    rotvec[:, 2] = model.roll_deg_per_100m * rad * ds / 100.0
    err = Rotation.from_rotvec(rotvec).as_matrix()
    return _compose(gt[0], R_rel, t_rel, err, 1.0 + sign * model.scale_bias_pct / 100.0)


def end_drift_pct(est: np.ndarray, gt: np.ndarray) -> float:
    """End position error as a percent of the ground truth's path length."""
    length = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    if length <= 0.0:
        return 0.0
    return 100.0 * float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3])) / length


def drift_trajectory(gt: np.ndarray, seed: int, model: DriftModel | None = None, pct: float | None = None) -> np.ndarray:
    """(N, 4, 4) drifted poses of ground truth ``gt`` (N, 4, 4); frame 0 keeps its pose, and a seed
    always gives the same poses. Raises SnapsGraphError for non-finite input, fewer than 2 poses, or
    a ``pct`` no rescaling reaches (a path that does not move, or a model with every rate at 0).
    """
    gt = np.asarray(gt, dtype=float)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or len(gt) < 2:
        raise SnapsGraphError("drift: needs at least 2 poses (N, 4, 4)")
    if not np.all(np.isfinite(gt)):
        raise SnapsGraphError("drift: the ground truth has non-finite values")
    model = model or DriftModel()
    R_rel, t_rel = _steps(gt)
    ds = np.linalg.norm(t_rel, axis=1)
    draws = _draws(gt, seed)
    if pct is None:
        return _apply(gt, model, draws, R_rel, t_rel, ds)
    if pct < 0 or not math.isfinite(pct):
        raise SnapsGraphError(f"drift: --pct must be a finite percentage >= 0, got {pct}")
    if pct == 0:
        return gt.copy()

    def err(k: float) -> float:
        return end_drift_pct(_apply(gt, model.scaled(k), draws, R_rel, t_rel, ds), gt)

    lo, hi = 0.0, 1.0
    while err(hi) < pct:
        hi *= 2.0
        if hi > 1e4:
            raise SnapsGraphError(f"drift: no rescaling of the drift model reaches {pct} % end drift on this path")
    for _ in range(40):  # the end error is monotone enough in k for a bisection to settle
        mid = 0.5 * (lo + hi)
        if err(mid) < pct:
            lo = mid
        else:
            hi = mid
    return _apply(gt, model.scaled(hi), draws, R_rel, t_rel, ds)


__all__ = ["DriftModel", "drift_trajectory", "end_drift_pct"]
