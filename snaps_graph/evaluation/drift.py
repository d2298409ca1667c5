"""Drifted odometry from a ground-truth trajectory, and the drift model fitted to an estimate.

Each ground-truth step is driven again with the errors of a :class:`~snaps_graph.drift_model.DriftModel`
(the model the graph and the search assume); ``pct`` rescales them together to an end error of
``pct`` % of the distance. :func:`fit_drift_model` measures a model from an estimate and its
ground truth. The terms and the defaults' source: docs/loop-closure.md, "The drift model".
"""

from __future__ import annotations

import math

import numpy as np

from ..drift_model import DriftModel
from ..errors import SnapsGraphError
from ..geometry import matrices_to_rotvecs, rotvecs_to_matrices


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


def _draws(gt: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Standard normal increments per step (heading, pitch, then roll and the three translation
    axes), and the scale error's sign; the first three draws keep their order across versions."""
    rng = np.random.default_rng(seed)
    m = len(gt) - 1
    xi_h, xi_p, sign = rng.standard_normal(m), rng.standard_normal(m), float(rng.choice([-1.0, 1.0]))
    return xi_h, xi_p, sign, rng.standard_normal(m), rng.standard_normal((m, 3))


def _apply(gt: np.ndarray, model: DriftModel, draws, R_rel, t_rel, ds) -> np.ndarray:
    xi_h, xi_p, sign, xi_r, xi_t = draws
    rad = math.pi / 180.0
    root = np.sqrt(ds)
    rotvec = np.zeros((len(ds), 3))
    rotvec[:, 1] = model.heading_deg_per_sqrt_m * rad * root * xi_h + model.heading_deg_per_100m * rad * ds / 100.0
    rotvec[:, 0] = model.pitch_deg_per_sqrt_m * rad * root * xi_p
    rotvec[:, 2] = model.roll_deg_per_sqrt_m * rad * root * xi_r + model.roll_deg_per_100m * rad * ds / 100.0
    err = rotvecs_to_matrices(rotvec)
    t_noisy = t_rel + model.trans_m_per_sqrt_m * root[:, None] * xi_t
    return _compose(gt[0], R_rel, t_noisy, err, 1.0 + sign * model.scale_pct / 100.0)


def end_drift_pct(est: np.ndarray, gt: np.ndarray) -> float:
    """End position error as a percent of the ground truth's path length."""
    length = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    if length <= 0.0:
        return 0.0
    return 100.0 * float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3])) / length


def _check(gt: np.ndarray, what: str = "the ground truth") -> np.ndarray:
    gt = np.asarray(gt, dtype=float)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or len(gt) < 2:
        raise SnapsGraphError("drift: needs at least 2 poses (N, 4, 4)")
    if not np.all(np.isfinite(gt)):
        raise SnapsGraphError(f"drift: {what} has non-finite values")
    return gt


def drift_process(gt: np.ndarray, seed: int, model: DriftModel | None = None, pct: float | None = None) -> DriftModel:
    """The model :func:`drift_trajectory` drives ``gt`` with for this ``seed``: ``model`` (default
    :class:`DriftModel`), rescaled when ``pct`` is given so the end drift is ``pct`` % of the path.
    Raises SnapsGraphError for bad input or a ``pct`` no rescaling reaches."""
    gt = _check(gt)
    model = model or DriftModel()
    if pct is None:
        return model
    if pct < 0 or not math.isfinite(pct):
        raise SnapsGraphError(f"drift: --pct must be a finite percentage >= 0, got {pct}")
    if pct == 0:
        return model.scaled(0.0)
    R_rel, t_rel = _steps(gt)
    ds = np.linalg.norm(t_rel, axis=1)
    draws = _draws(gt, seed)

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
    return model.scaled(hi)


def drift_trajectory(gt: np.ndarray, seed: int, model: DriftModel | None = None, pct: float | None = None) -> np.ndarray:
    """(N, 4, 4) drifted poses of ground truth ``gt`` (N, 4, 4); frame 0 keeps its pose, and a seed
    always gives the same poses. Raises SnapsGraphError for non-finite input, fewer than 2 poses, or
    a ``pct`` no rescaling reaches (a path that does not move, or a model with every rate at 0).
    """
    gt = _check(gt)
    used = drift_process(gt, seed, model, pct)
    if pct == 0:
        return gt.copy()
    R_rel, t_rel = _steps(gt)
    return _apply(gt, used, _draws(gt, seed), R_rel, t_rel, np.linalg.norm(t_rel, axis=1))


def fit_drift_model(est: np.ndarray, gt: np.ndarray, segment_m: float | None = None) -> tuple[DriftModel, float]:
    """The drift model of an estimate ``est`` against its ground truth ``gt`` (same frames), and the
    segment length (m) it was measured over: the relative errors over every stretch of about
    ``segment_m`` metres (default: 100 m, or a third of a shorter path). A rotation error's mean
    over a stretch of L metres is its rate x L, its variance the walk's squared rate x L; the
    scale error is the mean relative length error; the translation walk is what the steps'
    sideways and vertical errors add beyond the rotations'."""
    gt = _check(gt)
    est = _check(est, "the estimate")
    if est.shape != gt.shape:
        raise SnapsGraphError(f"drift: the estimate has {len(est)} poses and the ground truth {len(gt)}")
    R_g, t_g = _steps(gt)
    R_e, t_e = _steps(est)
    ds = np.linalg.norm(t_g, axis=1)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    if s[-1] <= 0.0:
        raise SnapsGraphError("drift: the ground truth does not move")
    L = float(segment_m) if segment_m else min(100.0, s[-1] / 3.0)
    starts = np.arange(len(gt))
    ends = np.searchsorted(s, s + L)
    ok = ends < len(gt)
    starts, ends = starts[ok], ends[ok]
    if len(starts) < 2:
        raise SnapsGraphError(f"drift: the path is shorter than one {L:g} m stretch")
    lengths = s[ends] - s[starts]
    rel_g = np.linalg.solve(gt[starts], gt[ends])
    rel_e = np.linalg.solve(est[starts], est[ends])
    err_R = np.einsum("kji,kjl->kil", rel_g[:, :3, :3], rel_e[:, :3, :3])
    rv = matrices_to_rotvecs(err_R) * 180.0 / math.pi  # [pitch, heading, roll], deg
    rate = rv.mean(axis=0) / lengths.mean()
    walk = np.sqrt(np.maximum(np.mean((rv - np.outer(lengths, rate)) ** 2, axis=0) / lengths.mean(), 0.0))
    s_e = np.concatenate([[0.0], np.cumsum(np.linalg.norm(t_e, axis=1))])
    scale = 100.0 * float(np.mean((s_e[ends] - s_e[starts]) / np.maximum(lengths, 1e-9) - 1.0))
    moving = ds > 1e-3
    step_err = t_e[moving] - t_g[moving]  # in the step's start frame: x sideways, y vertical
    trans = float(np.sqrt(np.mean(step_err[:, :2] ** 2) / max(float(np.mean(ds[moving])), 1e-9))) if moving.any() else 0.0
    model = DriftModel(
        heading_deg_per_sqrt_m=float(walk[1]),
        pitch_deg_per_sqrt_m=float(walk[0]),
        roll_deg_per_sqrt_m=float(walk[2]),
        scale_pct=abs(scale),
        trans_m_per_sqrt_m=trans,
        heading_deg_per_100m=100.0 * float(rate[1]),
        roll_deg_per_100m=100.0 * float(rate[2]),
    )
    return model, L


def odometry_section(model: DriftModel) -> str:
    """A fitted model as the config's ``[odometry]`` section: constant rates folded into the walks
    (as the graph folds them, over ``BIAS_REFERENCE_M``), since the section holds walks only."""
    var = model.rotation_var_per_m()
    walks = {
        "heading_deg_per_sqrt_m": math.degrees(math.sqrt(float(var[1]))),
        "pitch_deg_per_sqrt_m": model.pitch_deg_per_sqrt_m,
        "roll_deg_per_sqrt_m": math.degrees(math.sqrt(float(var[2]))),
        "scale_pct": model.scale_pct,
        "trans_m_per_sqrt_m": model.trans_m_per_sqrt_m,
    }
    lines = [
        f"# constant rates: heading {model.heading_deg_per_100m:+.3f}, roll {model.roll_deg_per_100m:+.3f} deg/100 m, "
        "folded into the walks",
        "[odometry]",
    ]
    return "\n".join(lines + [f"{k} = {max(v, 1e-6):.6g}" for k, v in walks.items()])


__all__ = ["DriftModel", "drift_process", "drift_trajectory", "end_drift_pct", "fit_drift_model", "odometry_section"]
