"""A run's pose graph solved again with another drift model: what the model alone does to the refinement.

Reads RUN/graph.g2o (the odometry and loop factors the run solved) and the run's poses, takes out
of each odometry factor the drift model the run used (RUN/config.toml's ``[odometry]``, its
step's own measurement noise stays), puts in another model's, and solves from the run's
heuristic trajectory as the run did (Levenberg-Marquardt, the run's robust loop kernel). Prints
the odometry's error in metres and each solve's as a ratio to it (3D mean deviation / horizontal /
vertical / ATE). The run's own model comes first: it reproduces the run's refined trajectory.
For runs of the stereo front end: a pose file's step across frames left out carries the model
along its path (``drift_model.path_covariance``), which this takes out along the chord.

    python benchmarks/bench_model_resolve.py RUN [--config TOML ...] [--scale K ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gtsam
import numpy as np
from bench_loops_dev import figures

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from snaps_graph.backend import array_to_values, to_pose3, values_to_array
from snaps_graph.backend.noise import ODOM_FLOOR_ROT_RAD, ODOM_FLOOR_TRANS_M
from snaps_graph.backend.pose_graph import (
    PRIOR_SIGMA_ROT_RAD,
    PRIOR_SIGMA_TRANS_M,
    batch_params,
    robust_loop_noise,
)
from snaps_graph.config import Config
from snaps_graph.drift_model import DriftModel, step_covariance
from snaps_graph.trajectory_io import read_poses

FLOOR = np.diag(np.array([ODOM_FLOOR_ROT_RAD] * 3 + [ODOM_FLOOR_TRANS_M] * 3) ** 2)


def factors(g2o: Path) -> tuple[list, list]:
    """(odometry, loops) of a graph.g2o as (a, b, T_a_b, covariance) in GTSAM's [rot, trans] order."""
    graph, _ = gtsam.readG2o(str(g2o), True)
    odo, loops = [], []
    for i in range(graph.size()):
        f = graph.at(i)
        if isinstance(f, gtsam.BetweenFactorPose3):
            a, b = f.keys()
            (odo if b == a + 1 else loops).append((a, b, f.measured().matrix(), f.noiseModel().covariance()))
    return odo, loops


def solve_factors(
    odo: list, loops: list, initial: np.ndarray, cfg: Config, params: gtsam.LevenbergMarquardtParams | None = None
) -> tuple[np.ndarray, int]:
    """(poses, iterations): the factors solved as a run solves its graph (the first pose's prior,
    the loops under the run's robust kernel, Levenberg-Marquardt from ``initial``)."""
    g = gtsam.NonlinearFactorGraph()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([PRIOR_SIGMA_ROT_RAD] * 3 + [PRIOR_SIGMA_TRANS_M] * 3))
    g.add(gtsam.PriorFactorPose3(0, to_pose3(initial[0]), prior))
    for a, b, T, C in odo:
        g.add(gtsam.BetweenFactorPose3(a, b, to_pose3(T), gtsam.noiseModel.Gaussian.Covariance(C)))
    for a, b, T, C in loops:
        g.add(gtsam.BetweenFactorPose3(a, b, to_pose3(T), robust_loop_noise(cfg.graph, gtsam.noiseModel.Gaussian.Covariance(C))))
    opt = gtsam.LevenbergMarquardtOptimizer(g, array_to_values(initial), params if params is not None else batch_params())
    result = opt.optimize()
    return values_to_array(result, len(initial)), opt.iterations()


def solve(odo: list, loops: list, initial: np.ndarray, used: DriftModel, model: DriftModel, cfg: Config) -> np.ndarray:
    """The run's factors solved with ``model`` in place of the drift model ``used`` in every odometry factor."""
    swapped = []
    for a, b, T, C in odo:
        t = T[:3, 3]
        chord, driven = T[:3, :3].T @ t, float(np.linalg.norm(t))
        own = C - step_covariance(used, driven, chord) - FLOOR  # the step's own measurement noise
        swapped.append((a, b, T, own + step_covariance(model, driven, chord) + FLOOR))
    return solve_factors(swapped, loops, initial, cfg)[0]


def load_run(run: Path) -> tuple[Config, np.ndarray, np.ndarray, np.ndarray, list, list] | None:
    """(config, ground truth, VO, heuristic, odometry factors, loop factors) of a run folder, or
    None after a one-line error naming the missing file."""
    for name in ("graph.g2o", "poses_vo.txt", "poses_snaps.txt", "poses_gt.txt"):
        if not (run / name).is_file():
            print(f"error: {run / name}: missing (a run with loops, --refine batch and ground truth)", file=sys.stderr)
            return None
    cfg = Config.load(run / "config.toml") if (run / "config.toml").is_file() else Config()
    gt, vo, heuristic = (read_poses(run / f"poses_{n}.txt") for n in ("gt", "vo", "snaps"))
    odo, loops = factors(run / "graph.g2o")
    return cfg, gt, vo, heuristic, odo, loops


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("run", type=Path, help="a run folder with graph.g2o, poses_vo/snaps/gt.txt and config.toml")
    ap.add_argument("--config", type=Path, nargs="*", default=[], help="configs whose [odometry] to solve with")
    ap.add_argument("--scale", type=float, nargs="*", default=[], help="the run's model with every rate times K")
    args = ap.parse_args(argv)
    run = args.run
    loaded = load_run(run)
    if loaded is None:
        return 2
    cfg, gt, vo, heuristic, odo, loops = loaded
    used = cfg.odometry.model()
    models = {"the run's model": used}
    models.update({f"{c}": Config.load(c).odometry.model() for c in args.config})
    models.update({f"x {k:g}": used.scaled(k) for k in args.scale})
    base = figures(vo, gt)
    fmt = lambda v: " / ".join(f"{x:.2f}" for x in v)  # noqa: E731
    print(f"{run}: {len(odo)} odometry and {len(loops)} loop factors")
    print(f"{'odometry, m':<28} {' / '.join(f'{x:.3f}' for x in base)}  (3D / horizontal / vertical / ATE)")
    print(f"{'heuristic, x odometry':<28} {fmt(figures(heuristic, gt) / base)}")
    for name, model in models.items():
        print(f"{name:<28} {fmt(figures(solve(odo, loops, heuristic, used, model, cfg), gt) / base)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
