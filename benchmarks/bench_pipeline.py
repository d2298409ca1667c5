"""End-to-end accuracy and latency on a synthetic rendering along a KITTI ground-truth path.

Renders the sequence once (or reuses it), runs VO + SNAPS + iSAM2 over it, then the batch
optimisation of the same graph (``--refine both``), and prints for every trajectory: mean deviation (the paper's
figure), ATE RMSE (SE(3)-aligned), t_rel, r_rel; the SNAPS reduction of mean deviation against VO;
true revisits found versus missed and false loops (ground truth); latency per stage.

    python benchmarks/bench_pipeline.py --trajectory ../shared/data/kitti_gt/00.txt \
        --seq results/bench/seq00 [--frames 0:4541] [--width 1241 --height 376]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from oracle import REVISIT_MAX_YAW_DEG, loop_oracle, true_revisit_pairs

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import evaluate
from snaps_graph.io_utils import PREFETCH_FRAMES, prefetch
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import latency_summary, write_results


def ensure_sequence(args) -> Path:
    seq = Path(args.seq)
    if (seq / "calib.txt").is_file() and (seq / "image_1").is_dir():
        return seq  # an existing sequence (rendered before, or real KITTI)
    from tqdm import tqdm

    from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder

    poses, times = load_trajectory(args.trajectory, args.frames)
    synth = SyntheticSequence(poses, width=args.width, height=args.height, seed=args.seed, noise_std=args.noise, times=times)
    t0 = time.perf_counter()
    with tqdm(total=len(synth), desc="render", unit="frame", mininterval=2) as bar:
        render_to_folder(synth, seq, progress=lambda *_: bar.update(1))
    dt = time.perf_counter() - t0
    print(f"rendered {len(synth)} stereo pairs in {dt:.1f} s = {len(synth) / dt:.2f} pairs/s")
    return seq


def revisit_stats(gt: np.ndarray, loops, frame_ids, cfg) -> dict:
    """True revisits (ground truth) found versus missed, and false loops."""
    p = gt[:, :3, 3]
    revisit = np.zeros(len(p), bool)
    for _, k in true_revisit_pairs(gt, cfg.loop.radius_m, cfg.loop.frame_distance, REVISIT_MAX_YAW_DEG, step=1):
        revisit[k] = True
    # Segments: maximal runs of revisit frames (a gap of < 10 frames joins runs).
    segs, start, last = [], None, None
    for k in np.flatnonzero(revisit):
        if start is None:
            start = last = k
        elif k - last <= 10:
            last = k
        else:
            segs.append((start, last))
            start = last = k
    if start is not None:
        segs.append((start, last))
    k_of = {f: k for k, f in enumerate(frame_ids)}
    loop_ks = [k_of[l.frame] for l in loops]
    found = sum(any(a <= k <= b for k in loop_ks) for a, b in segs)
    false = [l for l in loops if np.linalg.norm(p[k_of[l.reference]] - p[k_of[l.frame]]) > cfg.loop.radius_m]
    # Frames the loops could have corrected: segments at least 20 frames long are the real revisits.
    long_segs = [(a, b) for a, b in segs if b - a >= 20]
    found_long = sum(any(a <= k <= b for k in loop_ks) for a, b in long_segs)
    return {
        "revisit_frames": int(revisit.sum()),
        "revisit_segments": len(segs),
        "segments_found": int(found),
        "revisit_segments_20plus": len(long_segs),
        "segments_20plus_found": int(found_long),
        "loops": len(loops),
        "false_loops": len(false),
        "false_loop_pairs": [(l.frame, l.reference) for l in false],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", default=str(ROOT.parent / "shared/data/kitti_gt/00.txt"))
    ap.add_argument("--seq", default=str(ROOT / "results/bench/seq00"))
    ap.add_argument("--frames", default=None, help="range of the trajectory to render (A:B)")
    ap.add_argument("--run-frames", default=None, help="range of the rendered sequence to run")
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--config", default=None)
    ap.add_argument("--mode", default=None, help="front-end mode override")
    ap.add_argument("--out", default=None, help="also write the results folder here")
    ap.add_argument("--json", default=None, help="write the figures as JSON here")
    ap.add_argument("--prefetch", type=int, default=PREFETCH_FRAMES, help="frames read ahead on a thread (0: none)")
    ap.add_argument("--naive-frames", type=int, default=30, help="frames of the naive front end timed in the same run (0: skip)")
    ap.add_argument(
        "--false-loops", type=float, default=0.05, help="fraction of false loop factors added for the robustness check"
    )
    args = ap.parse_args()

    seq_dir = ensure_sequence(args)
    seq = KittiSequence(seq_dir, frames=args.run_frames)
    cfg = Config.load(args.config) if args.config else Config()
    if args.mode:
        cfg.frontend.mode = args.mode
    pipe = SlamPipeline(seq.camera, cfg, loops="snaps", refine="both", build_map=False)
    from tqdm import tqdm

    t0 = time.perf_counter()
    with contextlib.closing(prefetch(seq, args.prefetch)) as frames:
        covs = []  # each step's VOResult.cov, as the graph got it (the oracle's noise)
        for frame in tqdm(frames, total=len(seq), desc="slam", unit="frame", mininterval=2):
            covs.append(pipe.process(frame).vo.cov)
    wall = time.perf_counter() - t0
    result = pipe.finish()  # iSAM2 estimate, then the batch optimisation of the same graph
    t_batch = pipe.graph.stats.batch_ms / 1e3
    batch = result.trajectories["batch"]
    gt = seq.gt_poses

    figures: dict = {"frames": len(seq), "wall_s": wall, "batch_s": t_batch, "trajectories": {}}
    print(f"\n{len(seq)} frames of {seq_dir}, {wall:.1f} s ({len(seq) / wall:.1f} frames/s), mode {cfg.frontend.mode}")
    print(
        f"{'trajectory':<10}{'mean dev m':>12}{'horiz m':>9}{'vert m':>8}{'ATE m':>10}{'t_rel %':>10}{'r_rel deg/100m':>16}{'end drift %':>13}"
    )
    for name, poses in result.trajectories.items():
        m = evaluate(poses, gt)
        figures["trajectories"][name] = m
        print(
            f"{name:<10}{m['mean_deviation']:>12.3f}{m['mean_deviation_horizontal']:>9.3f}{m['mean_deviation_vertical']:>8.3f}{m['ate_rmse']:>10.3f}{m['t_rel']:>10.3f}{m['r_rel']:>16.4f}{m['end_drift_percent']:>13.3f}"
        )
    tr = figures["trajectories"]
    if "snaps" in tr:
        red = 1 - tr["snaps"]["mean_deviation"] / tr["vo"]["mean_deviation"]
        figures["snaps_mean_deviation_reduction"] = red
        print(f"SNAPS reduces the mean deviation by {100 * red:.1f}% against VO (paper: 65%)")
        for name in ("isam2", "batch"):
            if name in tr:
                ratio = tr[name]["mean_deviation"] / tr["snaps"]["mean_deviation"]
                figures[f"{name}_over_snaps_mean_deviation"] = ratio
                print(f"{name} mean deviation / SNAPS mean deviation = {ratio:.3f} (target <= 0.5)")
        # What any loop closure could reach on this VO: exact ground-truth loops at every revisit.
        rows = result.records
        o = loop_oracle(result.trajectories["vo"], gt, cfg, [r.vo_inliers for r in rows], [r.vo_ok for r in rows], covs=covs)
        ored = 1 - o.mean_deviation / tr["vo"]["mean_deviation"]
        figures["oracle"] = {"loops": len(o.pairs), "mean_deviation": o.mean_deviation, "ate_rmse": o.ate_rmse, "reduction": ored}
        print(
            f"oracle ({len(o.pairs)} exact ground-truth loops at the true revisits, same graph): mean deviation "
            f"{o.mean_deviation:.3f} m ({100 * ored:.1f}% below VO), ATE {o.ate_rmse:.3f} m: the most loop closure reaches on this VO"
        )
    rs = revisit_stats(gt, result.loops, pipe.frame_ids, cfg)
    figures["revisits"] = rs
    print(
        f"loops closed {rs['loops']}, false loops {rs['false_loops']}; true revisit segments found "
        f"{rs['segments_found']}/{rs['revisit_segments']} (of those >= 20 frames long: {rs['segments_20plus_found']}/{rs['revisit_segments_20plus']})"
    )
    verified = sum(l.verified for l in result.loops)
    print(f"loop factors verified geometrically: {verified}/{len(result.loops)}")
    lat = latency_summary(result.records)
    figures["latency_ms"] = lat
    print("latency (ms): median / p95")
    for key in ("total", "vo", "loop_no_candidate", "loop_with_candidates", "loop_closed", "graph"):
        s = lat[key]
        if s.get("n"):
            print(f"  {key:<22}{s['median']:>10.4f}{s['p95']:>10.4f}   (n={s['n']})")
    loop_graph = [r.t_graph_ms for r in result.records if r.loop_closed]
    if loop_graph:
        print(f"  graph update on loop frames: median {np.median(loop_graph):.2f} ms, max {np.max(loop_graph):.2f} ms")
        figures["graph_loop_update_ms"] = {"median": float(np.median(loop_graph)), "max": float(np.max(loop_graph))}
    print(f"  batch optimisation of {len(batch)} poses: {t_batch:.2f} s")
    if args.out:
        write_results(args.out, pipe, result, gt, overwrite=True)
        print(f"results in {args.out}")  # before the false loops below touch the graph
    if args.naive_frames:
        from naive_vo import NaiveVO  # the paper's front end written plainly (benchmarks/)

        from snaps_graph.config import FrontendConfig

        naive = NaiveVO(seq.camera, FrontendConfig())
        frames = [seq[i] for i in range(min(args.naive_frames, len(seq)))]
        t_naive = float(np.median([naive.process(f)[2]["total"] for f in frames][1:]))
        g = lat["graph"]["median"]
        figures["naive_frontend_ms"] = t_naive
        print(
            f"naive front end (BM+WLS, SIFT 2000, BF ratio, PnP RANSAC): median {t_naive:.1f} ms/frame over {len(frames)} frames"
        )
        print(
            f"  iSAM2 update median {g:.3f} ms = {100 * g / t_naive:.2f}% of it (target <= 2%); "
            f"our front end median {lat['vo']['median']:.1f} ms = {100 * lat['vo']['median'] / t_naive:.1f}% of it"
        )
    if args.false_loops > 0 and result.loops:
        # Robustness: random pairs as loop factors with a high Q, then the batch again.
        rng = np.random.default_rng(0)
        n_false = max(1, int(round(args.false_loops * len(result.loops))))
        n = len(batch)
        added = 0
        while added < n_false:
            a, b = sorted(rng.integers(0, n, 2))
            if b - a < 200:
                continue
            T = np.eye(4)
            T[:3, 3] = rng.normal(scale=2.0, size=3)
            pipe.graph.add_loop(int(a), int(b), 0.95, T if rng.random() < 0.5 else None)
            added += 1
        batch_false = pipe.graph.optimize_batch()
        ate0 = figures["trajectories"]["batch"]["ate_rmse"]
        ate1 = evaluate(batch_false, gt)["ate_rmse"]
        figures["false_loops"] = {
            "added": n_false,
            "ate_clean": ate0,
            "ate_with_false": ate1,
            "change_percent": 100 * (ate1 - ate0) / ate0,
        }
        print(
            f"robustness: {n_false} false loop factors ({100 * args.false_loops:.0f}% of {len(result.loops)}), "
            f"batch ATE {ate0:.3f} -> {ate1:.3f} m ({100 * (ate1 - ate0) / ate0:+.1f}%, target within 10%)"
        )
    if pipe.graph.failures:
        print(f"graph failures: {len(pipe.graph.failures)}: {pipe.graph.failures[:3]}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(figures, indent=2, default=float))


if __name__ == "__main__":
    main()
