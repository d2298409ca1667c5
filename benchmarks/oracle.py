"""A ground-truth loop oracle: the floor any loop closure could reach on a VO trajectory.

:func:`loop_oracle` builds a run's pose graph over the VO steps, adds an exact loop factor at
every true revisit and optimises it in batch (why it is a floor and not zero:
docs/loop-closure.md, "The dev paths"). A research tool beside the benchmarks that use it
(bench_loops_dev.py, bench_pipeline.py, bench_graph.py, experiments/): it reads ground truth,
and nothing in the package uses it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from snaps_graph.backend.pose_graph import PoseGraph
from snaps_graph.config import Config
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation
from snaps_graph.geometry import wrap_deg, yaw_deg

REVISIT_MAX_YAW_DEG = 10.0  # the loop policies' candidate heading limit (Table I): the revisits SNAPS may close


@dataclass
class OracleResult:
    poses: np.ndarray  # (N, 4, 4) optimised with every true revisit closed exactly
    pairs: list[tuple[int, int]] = field(default_factory=list)  # (reference, current) loop pairs
    mean_deviation: float = float("nan")
    ate_rmse: float = float("nan")


def true_revisit_pairs(
    gt: np.ndarray, radius_m: float, frame_distance: int, max_yaw_deg: float, step: int = 5
) -> list[tuple[int, int]]:
    """(reference, current) pairs at the true revisits of a ground-truth path.

    Every ``step``-th frame k that has an earlier frame j <= k - frame_distance within
    ``radius_m`` and ``max_yaw_deg`` of it gets one pair, to the nearest such j.
    """
    if step < 1:
        raise ValueError("step must be >= 1")
    p = gt[:, :3, 3]
    yaw = np.asarray(yaw_deg(gt[:, :3, :3]))
    pairs = []
    for k in range(frame_distance, len(p), step):
        d = np.linalg.norm(p[: k - frame_distance + 1] - p[k], axis=1)
        ok = (d <= radius_m) & (np.abs(wrap_deg(yaw[: k - frame_distance + 1] - yaw[k])) <= max_yaw_deg)
        if ok.any():
            cand = np.flatnonzero(ok)
            pairs.append((int(cand[np.argmin(d[cand])]), k))
    return pairs


def odometry_graph(
    vo: np.ndarray,
    cfg: Config,
    inliers: np.ndarray | None = None,
    ok: np.ndarray | None = None,
    initial: np.ndarray | None = None,
    covs: Sequence[np.ndarray | None] | None = None,
) -> PoseGraph:
    """A batch-mode graph of a run's VO steps, as the pipeline builds it: frame k gets the step
    from ``vo`` with the noise of its ``inliers`` / ``ok`` (frames.csv; default: reference
    sigmas, all good), or with ``covs[k]`` (``VOResult.cov``) where the step has one, and
    the initial estimate ``initial[k]`` (default: the VO pose)."""
    n = len(vo)
    inliers = np.zeros(n, int) if inliers is None else np.asarray(inliers, int)
    ok = np.ones(n, bool) if ok is None else np.asarray(ok, bool)
    initial = vo if initial is None else initial
    graph = PoseGraph(cfg.graph, mode="batch", drift=cfg.odometry.model())
    for k in range(n):
        T_rel = None if k == 0 else np.linalg.solve(vo[k - 1], vo[k])
        cov = None if covs is None else covs[k]
        graph.add_frame(k, initial[k], T_rel, inliers=int(inliers[k]), ok=bool(ok[k]), cov=cov)
    return graph


def loop_oracle(
    vo: np.ndarray,
    gt: np.ndarray,
    cfg: Config | None = None,
    inliers: np.ndarray | None = None,
    ok: np.ndarray | None = None,
    step: int = 5,
    covs: Sequence[np.ndarray | None] | None = None,
    max_yaw_deg: float = REVISIT_MAX_YAW_DEG,
) -> OracleResult:
    """Batch-optimise the VO chain with an exact loop factor at every true revisit.

    ``vo`` and ``gt``: (N, 4, 4) T_world_cam of the same frames; ``inliers``, ``ok`` and ``covs``
    (the steps' ``VOResult.cov``) set the odometry noise as in a run (default: reference sigmas, all
    frames good). The revisit geometry is ``cfg.loop``'s, so the oracle sees the revisits SNAPS may
    close; each loop has the tightest noise a verified loop gets (the ``loop_sigma_floor_*``).
    """
    vo = np.asarray(vo, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if vo.shape != gt.shape or vo.ndim != 3 or vo.shape[1:] != (4, 4):
        raise ValueError(f"vo {vo.shape} and gt {gt.shape} must both be (N, 4, 4)")
    cfg = cfg or Config()
    graph = odometry_graph(vo, cfg, inliers, ok, covs=covs)
    pairs = true_revisit_pairs(gt, cfg.loop.radius_m, cfg.loop.frame_distance, max_yaw_deg, step)
    for j, k in pairs:
        graph.add_loop(j, k, 1.0, np.linalg.solve(gt[j], gt[k]), covariance=np.zeros((6, 6)))
    poses = graph.optimize_batch()
    return OracleResult(poses, pairs, mean_deviation(poses, gt), ate_rmse(poses, gt))
