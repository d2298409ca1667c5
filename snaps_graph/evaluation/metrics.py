"""Trajectory metrics: mean deviation, ATE RMSE, KITTI relative errors (pure numpy, no files).

Poses are (N, 4, 4) T_world_cam; row i of the estimate and of the ground truth is the same frame.
Why these three, each computed as its field does: docs/decisions.md, "Evaluation". A metric that
cannot be computed is NaN here and ``null`` / ``n/a`` downstream, with a note naming why
(``evaluate``'s ``notes``); a NaN never stands for a pose.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SnapsGraphError
from ..geometry import rotation_angles, umeyama_alignment

# The KITTI odometry benchmark's segment lengths, metres (devkit evaluate_odometry.cpp).
KITTI_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
# The devkit starts a segment at every 10th frame ("every second" at KITTI's 10 Hz).
KITTI_STEP_FRAMES: int = 10


def _check_poses(poses: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise SnapsGraphError(f"{what}: expected an (N, 4, 4) pose array, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise SnapsGraphError(f"{what}: no poses")
    if not np.all(np.isfinite(arr)):
        raise SnapsGraphError(f"{what}: non-finite pose values")
    return arr


def _check_pair(est: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = _check_poses(est, "estimate")
    gt = _check_poses(gt, "ground truth")
    if len(est) != len(gt):
        raise SnapsGraphError(f"estimate has {len(est)} poses but ground truth has {len(gt)}: lengths must match")
    return est, gt


def position_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame Euclidean distance between estimated and true positions, metres, no alignment."""
    est, gt = _check_pair(est, gt)
    with np.errstate(over="ignore"):  # inf beyond ~1e154 m: evaluate() names why
        return np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)


def mean_deviation(est: np.ndarray, gt: np.ndarray) -> float:
    """Mean distance between estimated and true positions, metres, without alignment: the paper's
    figure. Both trajectories start at the identity; aligning would hide the drift loops remove.
    """
    return float(position_errors(est, gt).mean())


def parts(frame_ids, n: int) -> list[np.ndarray]:
    """Row indices of each run of consecutive frame numbers (one part without ``frame_ids``).

    A run of frames 100-230 and 1540-1660 has two parts: nothing is known of the way between
    them, so the figures that depend on the distance driven are taken over the parts that ran."""
    if frame_ids is None:
        return [np.arange(n)]
    ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
    if len(ids) != n:
        raise SnapsGraphError(f"{len(ids)} frame numbers for {n} poses")
    cuts = np.flatnonzero(np.diff(ids) != 1) + 1
    return np.split(np.arange(n), cuts)


def path_length(poses: np.ndarray, frame_ids=None) -> float:
    """Length of the polyline through the positions, metres; with ``frame_ids``, the sum over the
    parts of consecutive frames (not the jumps across gaps between them)."""
    p = _check_poses(poses, "trajectory")[:, :3, 3]
    with np.errstate(over="ignore", invalid="ignore"):  # inf beyond ~1e154 m: evaluate() names why
        return float(sum(np.linalg.norm(np.diff(p[rows], axis=0), axis=1).sum() for rows in parts(frame_ids, len(p))))


def ate_rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """RMSE of the position error after SE(3) Umeyama alignment of est onto gt, metres, as
    ``evo_ape kitti GT EST -a`` prints it: no scale correction, since a stereo rig observes scale.
    """
    est, gt = _check_pair(est, gt)
    p_est = est[:, :3, 3]
    p_gt = gt[:, :3, 3]
    R, t, _ = umeyama_alignment(p_est, p_gt, with_scale=False)
    aligned = p_est @ R.T + t
    return float(np.sqrt(np.mean(np.sum((aligned - p_gt) ** 2, axis=1))))


def distance_along(positions: np.ndarray) -> np.ndarray:
    """Distance travelled at each row of an (N, 3) position array, metres (0 at the first row)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def _relative(poses: np.ndarray, first: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations and translations of inv(T_first) T_last for index arrays first, last."""
    Ra = poses[first, :3, :3]
    Rb = poses[last, :3, :3]
    ta = poses[first, :3, 3]
    tb = poses[last, :3, 3]
    Rab = np.einsum("kji,kjl->kil", Ra, Rb)  # Ra^T Rb
    tab = np.einsum("kji,kj->ki", Ra, tb - ta)  # Ra^T (tb - ta)
    return Rab, tab


def kitti_relative_errors(
    est: np.ndarray,
    gt: np.ndarray,
    lengths: tuple[float, ...] = KITTI_LENGTHS_M,
    step: int = KITTI_STEP_FRAMES,
) -> tuple[float, float]:
    """KITTI devkit relative errors (``evaluate_odometry.cpp``): (t_rel %, r_rel deg/100 m).

    For every ``step``-th first frame and segment length L, the last frame is the first whose
    ground-truth distance exceeds the start's + L; the error E = inv(delta_est) delta_gt, averaged
    over all segments. The angle is taken by atan2, not the devkit's acos, which turns KITTI's
    non-orthonormal rotations into phantom rotation. (nan, nan) when the path has no segment.
    """
    est, gt = _check_pair(est, gt)
    if step < 1:
        raise SnapsGraphError(f"kitti_relative_errors: step must be >= 1 frame, got {step}")
    lens = np.asarray(lengths, dtype=float)
    if lens.size == 0 or np.any(~np.isfinite(lens)) or np.any(lens <= 0):
        raise SnapsGraphError("kitti_relative_errors: segment lengths must be positive numbers of metres")
    dist = distance_along(gt[:, :3, 3])
    firsts = np.arange(0, len(gt), step)
    first_grid = np.repeat(firsts, lens.size)
    len_grid = np.tile(lens, firsts.size)
    # side="right": the first index whose distance is strictly greater (devkit's `>`).
    last_grid = np.searchsorted(dist, dist[first_grid] + len_grid, side="right")
    valid = last_grid < len(gt)
    if not np.any(valid):
        return math.nan, math.nan
    f, l, L = first_grid[valid], last_grid[valid], len_grid[valid]
    R_gt, t_gt = _relative(gt, f, l)
    R_est, t_est = _relative(est, f, l)
    # E = inv(delta_est) delta_gt
    R_err = np.einsum("kji,kjl->kil", R_est, R_gt)
    t_err_vec = np.einsum("kji,kj->ki", R_est, t_gt - t_est)
    t_err = np.linalg.norm(t_err_vec, axis=1) / L
    r_err = rotation_angles(R_err) / L
    return float(t_err.mean() * 100.0), float(np.degrees(r_err.mean()) * 100.0)


def _relative_errors_over_parts(est: np.ndarray, gt: np.ndarray, rows_of: list[np.ndarray]) -> tuple[float, float]:
    """KITTI t_rel / r_rel with segments inside each part only, averaged over all of them."""
    if len(rows_of) == 1:
        return kitti_relative_errors(est, gt)
    t_sum = r_sum = 0.0
    count = 0
    for rows in rows_of:
        dist = distance_along(gt[rows, :3, 3])
        n_seg = sum(
            int(np.sum(np.searchsorted(dist, dist[::KITTI_STEP_FRAMES] + L, side="right") < len(rows))) for L in KITTI_LENGTHS_M
        )
        if n_seg:
            t, r = kitti_relative_errors(est[rows], gt[rows])
            t_sum, r_sum, count = t_sum + t * n_seg, r_sum + r * n_seg, count + n_seg
    return (t_sum / count, r_sum / count) if count else (math.nan, math.nan)


def _end_drift(est: np.ndarray, gt: np.ndarray, rows_of: list[np.ndarray]) -> float:
    """End error over path length, %; across gaps, each part's end error relative to its own
    start (the error grown while it ran) summed over the parts, over their summed lengths."""
    error = length = 0.0
    for rows in rows_of:
        a, b = rows[0], rows[-1]
        t_gt = np.linalg.solve(gt[a], gt[b])[:3, 3]
        t_est = np.linalg.solve(est[a], est[b])[:3, 3]
        error += float(np.linalg.norm(t_est - t_gt))
        length += float(np.linalg.norm(np.diff(gt[rows, :3, 3], axis=0), axis=1).sum())
    return error / length * 100.0 if length > 0 else math.nan


def evaluate(est: np.ndarray, gt: np.ndarray, frame_ids=None) -> dict:
    """All figures for one trajectory against ground truth, as a JSON-ready dict.

    Keys: mean_deviation, ate_rmse, t_rel, r_rel, frames, path_length_m (ground truth), end_error_m,
    end_drift_percent, and the mean deviation split into horizontal (x-z plane) and vertical (|y|):
    KITTI's world frame is the first camera's, y down, so this separates drift along the ground from
    drift in height. NaN where undefined (t_rel / r_rel under 100 m, end drift on a zero-length path,
    every figure for positions that overflow when squared), with ``notes``: figure -> why, one line.

    ``frame_ids`` (the dataset's frame numbers of the rows) split a run with gaps into parts:
    path length, t_rel / r_rel and end drift are then taken over the parts that ran (``parts``;
    docs/decisions.md, "Evaluation"); the other figures do not depend on the distance driven.
    """
    est, gt = _check_pair(est, gt)
    rows_of = parts(frame_ids, len(est))
    big = max(float(np.abs(est[:, :3, 3]).max()), float(np.abs(gt[:, :3, 3]).max()))
    if big > _SQUARE_LIMIT_M:  # every figure would overflow, or be computed from ones that did
        why = f"positions of up to {big:.3g} m overflow double precision when squared; no figure from them"
        keys = [k for k in EVALUATE_KEYS if k != "frames"]
        return {k: math.nan for k in keys} | {"frames": int(len(est)), "notes": dict.fromkeys(keys, why)}
    with np.errstate(over="ignore", invalid="ignore"):  # what is not finite is named in ``notes``
        errors = position_errors(est, gt)
        t_rel, r_rel = _relative_errors_over_parts(est, gt, rows_of)
        length = path_length(gt, frame_ids)
        end_error = float(errors[-1])
        d = est[:, :3, 3] - gt[:, :3, 3]
        try:
            ate = ate_rmse(est, gt)
        except np.linalg.LinAlgError:  # the alignment's SVD on overflowed (non-finite) sums
            ate = math.nan
        m = {
            "mean_deviation": float(errors.mean()),
            "mean_deviation_horizontal": float(np.hypot(d[:, 0], d[:, 2]).mean()),
            "mean_deviation_vertical": float(np.abs(d[:, 1]).mean()),
            "ate_rmse": ate,
            "t_rel": t_rel,
            "r_rel": r_rel,
            "frames": int(len(est)),
            "path_length_m": length,
            "end_error_m": end_error,
            "end_drift_percent": (end_error / length * 100.0 if 0 < length < math.inf else math.nan)
            if len(rows_of) == 1
            else _end_drift(est, gt, rows_of),
        }
    notes = {k: _why_not(k, length, len(rows_of)) for k, v in m.items() if not math.isfinite(v)}
    return m | ({"parts": len(rows_of)} if len(rows_of) > 1 else {}) | ({"notes": notes} if notes else {})


# Positions beyond this many metres overflow a double when squared and summed (1.8e308).
_SQUARE_LIMIT_M = 1e150
EVALUATE_KEYS = (
    "mean_deviation",
    "mean_deviation_horizontal",
    "mean_deviation_vertical",
    "ate_rmse",
    "t_rel",
    "r_rel",
    "frames",
    "path_length_m",
    "end_error_m",
    "end_drift_percent",
)


def notes_text(per_traj: dict[str, dict]) -> list[str]:
    """The ``notes`` of :func:`evaluate` results by trajectory, one line per reason: the figures
    and trajectories it leaves without a number, and why."""
    why: dict[str, tuple[list[str], list[str]]] = {}
    for name, m in per_traj.items():
        for key, reason in (m.get("notes") or {}).items():
            keys, names = why.setdefault(reason, ([], []))
            keys += [key] if key not in keys else []
            names += [name] if name not in names else []
    every = len(EVALUATE_KEYS) - 1  # all but the frame count
    return [
        f"{'every figure' if len(keys) == every else ', '.join(keys)} n/a for {', '.join(names)}: {reason}"
        for reason, (keys, names) in why.items()
    ]


def _why_not(key: str, length: float, n_parts: int = 1) -> str:
    """One line: why the figure ``key`` of :func:`evaluate` could not be computed."""
    if key in ("t_rel", "r_rel") and n_parts > 1:
        return f"no part of the run (frames left out split it in {n_parts}) is as long as KITTI's shortest segment ({KITTI_LENGTHS_M[0]:g} m)"
    if key in ("t_rel", "r_rel"):
        return f"the ground-truth path is {length:.1f} m, shorter than KITTI's shortest segment ({KITTI_LENGTHS_M[0]:g} m)"
    if key == "end_drift_percent":
        return "the ground-truth path has zero length"
    return "not a finite number"
