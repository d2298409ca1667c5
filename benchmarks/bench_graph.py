"""Benchmark of the GTSAM back end on KITTI 00's ground-truth path (4541 poses, 3.7 km).

VO is simulated as the true relative poses plus noise and a small systematic bias (a yaw bias
per frame and a translation scale bias), so the chained "heuristic" trajectory drifts by tens of
metres like real stereo VO. Loop factors are added at true revisits: frame pairs more than
``--min-gap`` frames apart, within ``--loop-radius-m`` and ``--loop-yaw-deg`` of each other in
the ground truth, one every ``--loop-every`` frames, measured as the true relative pose plus
small noise with Q drawn in [0.80, 0.95].

Prints: iSAM2 update median / p95 per frame, the loop-closing update times, the batch time, mean
deviation and ATE RMSE (SE(3)-aligned) of chain vs iSAM2 vs batch, and the batch ATE change when
``--false-fraction`` false loops (random distant pairs claiming "same place" at high Q) are added.

    python benchmarks/bench_graph.py                 # full sequence
    python benchmarks/bench_graph.py --frames 1500   # reduced size
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from oracle import true_revisit_pairs

from snaps_graph.backend import PoseGraph
from snaps_graph.backend.noise import ODOM_REF_INLIERS
from snaps_graph.config import GraphConfig
from snaps_graph.evaluation.metrics import ate_rmse, kitti_relative_errors, mean_deviation
from snaps_graph.geometry import exp_so3
from snaps_graph.trajectory_io import read_kitti_poses

DEFAULT_GT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_gt" / "00.txt"


def perturb(T: np.ndarray, rot_sigma: float, trans_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """T (N, 4, 4) composed with a random right perturbation."""
    out = T.copy()
    out[:, :3, :3] = T[:, :3, :3] @ np.array([exp_so3(w) for w in rng.normal(0, rot_sigma, (len(T), 3))])
    out[:, :3, 3] += rng.normal(0, trans_sigma, (len(T), 3))
    return out


def simulate_vo(gt: np.ndarray, args, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Noisy biased relative poses (N, 4, 4; [0] = identity) and their chain (the drifting VO)."""
    rel = np.linalg.inv(gt[:-1]) @ gt[1:]
    rel = perturb(rel, args.rot_noise_rad, args.trans_noise_m, rng)
    bias = np.zeros((len(rel), 3))
    bias[:, 1] = args.yaw_bias_rad  # about the camera's vertical (y) axis
    rel[:, :3, :3] = rel[:, :3, :3] @ np.array([exp_so3(w) for w in bias])
    rel[:, :3, 3] *= 1.0 + args.scale_bias
    rel = np.concatenate([np.eye(4)[None], rel])
    chain = np.empty_like(rel)
    chain[0] = np.eye(4)
    for k in range(1, len(rel)):
        chain[k] = chain[k - 1] @ rel[k]
    return rel, chain


def find_loops(gt: np.ndarray, args) -> list[tuple[int, int]]:
    """(ref, cur) at true revisits (nearest reference), at most one every ``loop_every`` frames."""
    loops, last = [], -(10**9)
    for i, j in true_revisit_pairs(gt, args.loop_radius_m, args.min_gap, args.loop_yaw_deg, step=1):
        if j - last >= args.loop_every:
            loops.append((i, j))
            last = j
    return loops


def false_loops(gt: np.ndarray, n: int, args, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Random pairs at least 50 m apart in truth (so certainly wrong)."""
    p, out = gt[:, :3, 3], []
    while len(out) < n:
        i, j = sorted(rng.integers(0, len(gt), 2))
        if j - i > args.min_gap and np.linalg.norm(p[i] - p[j]) > 50.0:
            out.append((int(i), int(j)))
    return out


def build(mode: str, cfg: GraphConfig, rel, chain, loops, online: bool) -> tuple[PoseGraph, list[float], list[float]]:
    """Feed the graph frame by frame; loops[(ref, cur)] = (q, T) arrive with frame cur."""
    g = PoseGraph(cfg, mode=mode)
    by_cur: dict[int, list] = {}
    for (i, j), (q, T) in loops.items():
        by_cur.setdefault(j, []).append((i, q, T))
    frame_ms, loop_ms = [], []
    for k in range(len(chain)):
        g.add_frame(k, chain[k], None if k == 0 else rel[k], inliers=ODOM_REF_INLIERS, ok=True)
        for i, q, T in by_cur.get(k, []):
            g.add_loop(i, k, q, T)
        if online:
            dt = g.update()
            (loop_ms if k in by_cur else frame_ms).append(dt)
    return g, frame_ms, loop_ms


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, default=DEFAULT_GT)
    ap.add_argument("--frames", type=int, default=0, help="use only the first N poses (0: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rot-noise-rad", type=float, default=3e-4)
    ap.add_argument("--trans-noise-m", type=float, default=0.01)
    ap.add_argument("--yaw-bias-rad", type=float, default=5e-5)
    ap.add_argument("--scale-bias", type=float, default=0.01)
    ap.add_argument("--min-gap", type=int, default=100)
    ap.add_argument("--loop-radius-m", type=float, default=3.0)
    ap.add_argument("--loop-yaw-deg", type=float, default=10.0)
    ap.add_argument("--loop-every", type=int, default=50)
    ap.add_argument(
        "--false-fraction",
        type=float,
        nargs="+",
        default=[0.05, 0.25],
        help="false loops as a fraction of the true ones (one batch run each)",
    )
    ap.add_argument("--skip-isam2", action="store_true")
    args = ap.parse_args(argv)

    if not args.gt.is_file():
        print(f"ground truth not found: {args.gt}", file=sys.stderr)
        return 2
    gt = read_kitti_poses(args.gt)
    if args.frames:
        gt = gt[: args.frames]
    rng = np.random.default_rng(args.seed)
    cfg = GraphConfig()
    rel, chain = simulate_vo(gt, args, rng)
    pairs = find_loops(gt, args)
    true_rel = np.linalg.inv(gt[[i for i, _ in pairs]]) @ gt[[j for _, j in pairs]] if pairs else np.zeros((0, 4, 4))
    meas = perturb(true_rel, 0.005, 0.05, rng) if pairs else true_rel
    loops = {pair: (float(rng.uniform(0.80, 0.95)), meas[n]) for n, pair in enumerate(pairs)}
    path_m = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    print(f"KITTI path {args.gt.name}: {len(gt)} poses, {path_m:.0f} m; {len(loops)} true loop factors")
    if path_m > 100:
        t_rel, r_rel = kitti_relative_errors(chain, gt)
        print(f"simulated VO chain: t_rel {t_rel:.2f} %, r_rel {r_rel:.2f} deg/100 m")

    rows = [("VO chain (initial)", chain)]
    if not args.skip_isam2:
        g, frame_ms, loop_ms = build("isam2", cfg, rel, chain, loops, online=True)
        rows.append(("iSAM2 online", g.estimates()))
        t_conv = g.converge()
        rows.append(("iSAM2 + converge()", g.estimates()))
        fm = np.array(frame_ms)
        print(
            f"iSAM2 update per frame: median {np.median(fm):.2f} ms, p95 {np.percentile(fm, 95):.2f} ms, "
            f"max {fm.max():.1f} ms ({len(fm)} frames)"
        )
        if loop_ms:
            print(
                f"iSAM2 loop-closing update: median {np.median(loop_ms):.1f} ms, max {max(loop_ms):.1f} ms "
                f"({len(loop_ms)} loop frames)"
            )
        print(f"iSAM2 converge() at the end: {t_conv:.1f} ms")
        if g.failures:
            print(f"iSAM2 failures: {len(g.failures)} (first: {g.failures[0]})")

    t0 = time.perf_counter()
    gb, _, _ = build("batch", cfg, rel, chain, loops, online=False)
    t_build = time.perf_counter() - t0
    batch = gb.optimize_batch()
    rows.append(("batch LM", batch))
    print(
        f"batch (LM, {len(gt)} poses, {len(loops)} loops): {gb.stats.batch_ms / 1e3:.2f} s "
        f"optimise, {gb.stats.batch_iterations} iterations (graph build {t_build:.2f} s)"
    )
    if gb.failures:
        print(f"batch failures: {gb.failures}")

    print(f"{'trajectory':22s} {'mean dev (m)':>12s} {'ATE RMSE (m)':>12s}")
    for name, poses in rows:
        print(f"{name:22s} {mean_deviation(poses, gt):12.2f} {ate_rmse(poses, gt):12.2f}")

    ate_clean = ate_rmse(batch, gt)
    for fraction in args.false_fraction:
        n_false = max(1, round(fraction * len(loops)))
        with_false = dict(loops)
        for i, j in false_loops(gt, n_false, args, rng):  # a wrong "same place" match at a high Q
            with_false[(i, j)] = (float(rng.uniform(0.85, 0.95)), perturb(np.eye(4)[None], 0.005, 0.05, rng)[0])
        for kernel in (cfg.robust_kernel, "none"):
            kcfg = GraphConfig(robust_kernel=kernel)
            gf, _, _ = build("batch", kcfg, rel, chain, with_false, online=False)
            ate_false = ate_rmse(gf.optimize_batch(), gt)
            print(
                f"batch + {n_false} false loops ({fraction:.0%}), kernel {kernel:6s}: ATE {ate_false:7.2f} m "
                f"({100 * (ate_false - ate_clean) / ate_clean:+.1f}% vs clean)"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
