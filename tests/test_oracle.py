"""The research tools outside the package: the ground-truth loop oracle (benchmarks/oracle.py) and
the loop closer under research switches (benchmarks/_loop_research.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.evaluation.metrics import mean_deviation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _loop_research import with_switches  # noqa: E402
from oracle import loop_oracle, true_revisit_pairs  # noqa: E402


def yaw_pose(x: float, z: float, yaw_deg: float) -> np.ndarray:
    a = math.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    T[0, 3], T[2, 3] = x, z
    return T


def square_laps(laps: int = 2, side: int = 20) -> np.ndarray:
    """A square driven ``laps`` times, 1 m steps, turning 90 degrees at each corner."""
    poses, x, z, yaw = [], 0.0, 0.0, 0.0
    for _ in range(laps):
        for _ in range(4):
            for _ in range(side):
                poses.append(yaw_pose(x, z, yaw))
                x += math.sin(math.radians(yaw))
                z += math.cos(math.radians(yaw))
            yaw += 90.0
    return np.array(poses)


def drifted(gt: np.ndarray, yaw_bias_deg: float) -> np.ndarray:
    """Chain the true steps with a constant yaw bias per step (VO heading drift)."""
    out = [gt[0]]
    bias = yaw_pose(0.0, 0.0, yaw_bias_deg)
    for k in range(1, len(gt)):
        out.append(out[-1] @ np.linalg.solve(gt[k - 1], gt[k]) @ bias)
    return np.array(out)


def cfg() -> Config:
    c = Config()
    c.loop.frame_distance = 50
    c.loop.radius_m = 3.0
    return c


def test_true_revisit_pairs_are_the_second_lap():
    gt = square_laps()
    c = cfg()
    pairs = true_revisit_pairs(gt, c.loop.radius_m, c.loop.frame_distance, 10.0, step=1)
    assert pairs, "the second lap revisits the first"
    for j, k in pairs:
        assert k >= 80 and k - j >= c.loop.frame_distance
        assert np.linalg.norm(gt[j, :3, 3] - gt[k, :3, 3]) <= c.loop.radius_m
    # Every second-lap frame k >= 80 lies on a first-lap frame (k - 80), which is the nearest one.
    assert all(j == k - 80 for j, k in pairs)
    assert len(pairs) == 80


def test_oracle_removes_drift_that_loops_observe():
    gt = square_laps()
    vo = drifted(gt, 0.2)  # 0.2 deg per metre: ~16 deg over the 160 m
    before = mean_deviation(vo, gt)
    res = loop_oracle(vo, gt, cfg())
    assert before > 2.0
    assert res.mean_deviation < 0.5 * before
    assert np.all(np.isfinite(res.poses))


def test_oracle_keeps_error_that_no_loop_observes():
    # A 30 m lead-in driven once, then the square twice. A heading error on a lead-in step turns
    # everything after it rigidly; every revisited pair lies after the error, so the exact loops
    # agree with the VO: the oracle cannot (and must not) remove that error.
    lead = np.array([yaw_pose(0.0, float(z), 0.0) for z in range(-30, 0)])
    gt = np.concatenate([lead, square_laps()])
    vo: list[np.ndarray] | np.ndarray
    vo = [gt[0]]
    for k in range(1, len(gt)):
        step = np.linalg.solve(gt[k - 1], gt[k])
        vo.append(vo[-1] @ step @ (yaw_pose(0.0, 0.0, 2.0) if k == 10 else np.eye(4)))
    vo = np.array(vo)
    before = mean_deviation(vo, gt)
    res = loop_oracle(vo, gt, cfg())
    assert before > 0.5
    assert res.pairs and min(j for j, _ in res.pairs) >= 30  # loops only on the square
    assert abs(res.mean_deviation - before) < 0.05 * before
    # The same error on the square (frame 40, revisited by frame 120) is observed and removed.
    vo2: list[np.ndarray] | np.ndarray
    vo2 = [gt[0]]
    for k in range(1, len(gt)):
        step = np.linalg.solve(gt[k - 1], gt[k])
        vo2.append(vo2[-1] @ step @ (yaw_pose(0.0, 0.0, 2.0) if k == 40 else np.eye(4)))
    vo2 = np.array(vo2)
    assert loop_oracle(vo2, gt, cfg()).mean_deviation < 0.5 * mean_deviation(vo2, gt)


def test_oracle_weighs_the_steps_by_the_covariances_it_is_given():
    """With the steps' covariances (as the pipeline weighs them) the exact
    loops put a heading error on the one step whose covariance allows it; with the inlier
    sigmas (all steps alike) the same correction is spread over the lap."""
    gt = square_laps()
    vo: list[np.ndarray] | np.ndarray
    vo = [gt[0]]
    for k in range(1, len(gt)):
        vo.append(vo[-1] @ np.linalg.solve(gt[k - 1], gt[k]) @ (yaw_pose(0.0, 0.0, 2.0) if k == 40 else np.eye(4)))
    vo = np.array(vo)
    tight, loose = np.diag([1e-8] * 3 + [1e-6] * 3), np.diag([1e-2] * 3 + [1e-6] * 3)
    covs = [None] + [loose if k == 40 else tight for k in range(1, len(gt))]
    c = cfg()
    spread = loop_oracle(vo, gt, c).mean_deviation
    placed = loop_oracle(vo, gt, c, covs=covs).mean_deviation
    assert placed < 0.02 and placed < 0.25 * spread, (placed, spread)


def test_the_research_closer_is_built_as_the_pipeline_builds_its_own():
    """bench_revisit swaps the pipeline's loop closer for this one: it must take every argument
    the pipeline passes (priors too) and only change the gate."""
    cfg = Config()
    closer = with_switches("radius", False)(cfg.loop, cfg.odometry, 5, verifier=None, priors=None)
    assert closer.policy.search == "radius" and closer.pause_every == 5
    assert with_switches(None, False)(cfg.loop, cfg.odometry).policy.search == "drift"
