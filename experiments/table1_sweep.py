"""Paper Table I: each SNAPS design parameter swept over a range; its effect on accuracy and time.

Every setting is one run with one parameter changed from the defaults (batch refinement), over a
sequence (a synthetic rendering along KITTI 00 by default). The runs go through `snaps-graph
batch`'s API: one Ray task per setting, on this machine or a cluster (--address), each a full
run into results/experiments/table1_sweep/<sequence>/<parameter>=<value>/, skipped on a re-run
when already done. --replay instead runs the front end once in this process and replays the
cached VO through SNAPS and the graph for every setting (same poses and loops, far less work on
one machine; no parallelism). Writes results/experiments/table1_sweep.md and table1_sweep.png.

    python experiments/table1_sweep.py [--path 00] [--seq DIR] [--frames A:B] [--address ADDR] [--replay]
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np
from _common import (
    RESULTS,
    add_batch_args,
    false_loops,
    md_table,
    read_frames,
    read_loops,
    replay,
    run_plan,
    synthetic_dir,
    vo_cache,
)

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation

SWEEPS = {
    "radius_m": [5.0, 10.0, 20.0, 40.0],
    "frame_distance": [50, 100, 200, 400],
    "discount_length": [25, 50, 100, 200, 400],
    "min_similarity": [0.5, 0.65, 0.75, 0.85, 0.95],
    "inter_frame_pause": [10, 25, 50, 100, 200],
    "window": [8, 16],
    "policy": ["drift", "paper"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--path", default="00")
    ap.add_argument("--seq", default=None, help="a KITTI-format sequence with ground truth instead")
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--frames", default=None, help="frame range A:B")
    ap.add_argument("--replay", action="store_true", help="one process: VO once, replayed for every setting")
    add_batch_args(ap)
    args = ap.parse_args()
    seq_dir = args.seq or synthetic_dir(args.path, args.width, args.height)
    base = Config()
    rows, curves, vo_md, vo_ate, n_frames = (_by_replay if args.replay else _by_batch)(seq_dir, base, args)
    for row in rows:
        curves.setdefault(row[0], []).append((row[1], row[4], row[6]))
    text = "# Table I: design parameters swept\n\n"
    cmd = ("--seq " + str(args.seq) if args.seq else "--path " + args.path) + (f" --frames {args.frames}" if args.frames else "")
    cmd += " --replay" if args.replay else ""
    text += f"Command: `python experiments/table1_sweep.py {cmd}`; sequence `{seq_dir}` ({n_frames} frames).\n"
    defaults = ", ".join(f"{k} {getattr(base.loop, k)}" for k in SWEEPS)
    text += f"VO alone: mean deviation {vo_md:.3f} m, ATE {vo_ate:.3f} m. Every row changes one parameter from the defaults: {defaults}.\n"
    text += "False loops: reference farther than 10 m from the current frame in the ground truth. Time: median SNAPS ms on frames that compared candidates.\n\n"
    text += md_table(
        [
            "parameter",
            "value",
            "loops",
            "false",
            "SNAPS mean dev m",
            "SNAPS ATE m",
            "batch mean dev m",
            "batch ATE m",
            "SNAPS ms (cand.)",
            "similarities",
        ],
        rows,
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "table1_sweep.md").write_text(text)
    _plot(curves, vo_md, RESULTS / "table1_sweep.png")
    print(text)


def _by_batch(seq_dir, base: Config, args):
    """One run per setting, as Ray tasks; the rows from each run folder."""
    variants = {f"{param}={v}": {"loop": {param: v}} for param, values in SWEEPS.items() for v in values}
    plan: dict = {"sequences": [str(seq_dir)], "refine": "batch", "loops": "snaps", "variants": variants}
    if args.frames:
        plan["frames"] = args.frames
    out = RESULTS / "table1_sweep"
    rows, vo_md, vo_ate, n_frames = [], float("nan"), float("nan"), 0
    seq = None
    for cell, rec in run_plan(plan, out, args, source="table1_sweep plan"):
        param, _, _ = cell.variant.partition("=")
        value = getattr(cell.cfg.loop, param)
        if rec["status"] not in ("ok", "skipped"):
            print(f"{cell.variant}: {rec['status']} ({rec.get('reason', '')})")
            continue
        run_dir = cell.folder(out)
        if seq is None:
            seq = cell.open()
            n_frames = len(seq)
        tr = json.loads((run_dir / "metrics.json").read_text())["trajectories"]
        vo_md, vo_ate = tr["vo"]["mean_deviation"], tr["vo"]["ate_rmse"]  # the same in every run
        loops = read_loops(run_dir)
        fr = read_frames(run_dir)
        cand = fr["loop_candidates"] > 0
        rows.append(
            [
                param,
                value,
                len(loops),
                false_loops(loops, seq.gt_poses, seq.indices, base.loop.radius_m),
                tr["snaps"]["mean_deviation"],
                tr["snaps"]["ate_rmse"],
                tr["batch"]["mean_deviation"],
                tr["batch"]["ate_rmse"],
                float(np.median(fr["t_loop_ms"][cand])) if cand.any() else float("nan"),
                int(fr["loop_candidates"].sum()),
            ]
        )
    return rows, {}, vo_md, vo_ate, n_frames


def _by_replay(seq_dir, base: Config, args):
    """The front end once in this process, its cached results replayed for every setting."""
    seq = KittiSequence(seq_dir, frames=args.frames)
    cache = vo_cache(seq, base)
    gt = cache.gt
    vo_poses = np.array([cache.results[int(i)].pose for i in cache.indices])
    vo_md, vo_ate = mean_deviation(vo_poses, gt), ate_rmse(vo_poses, gt)
    rows = []
    for param, values in SWEEPS.items():
        for v in values:
            cfg = copy.deepcopy(base)
            setattr(cfg.loop, param, v)
            t0 = time.perf_counter()
            result, pipe = replay(cache, cfg, refine="batch")
            wall = time.perf_counter() - t0
            tr = result.trajectories
            t_loop = [r.t_loop_ms for r in result.records if r.loop_candidates > 0]
            row = [
                param,
                v,
                len(result.loops),
                false_loops(result.loops, gt, cache.indices, base.loop.radius_m),
                mean_deviation(tr["snaps"], gt),
                ate_rmse(tr["snaps"], gt),
                mean_deviation(tr["batch"], gt),
                ate_rmse(tr["batch"], gt),
                float(np.median(t_loop)) if t_loop else float("nan"),
                sum(r.loop_candidates for r in result.records),
            ]
            rows.append(row)
            print(
                f"{param}={v}: loops {row[2]} (false {row[3]}), SNAPS mean dev {row[4]:.2f} m, batch {row[6]:.2f} m, {wall:.1f} s"
            )
    return rows, {}, vo_md, vo_ate, len(seq)


def _plot(curves, vo_md, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(curves)
    fig, axes = plt.subplots(2, (n + 1) // 2, figsize=(4 * ((n + 1) // 2), 7))
    for ax, (param, pts) in zip(axes.ravel(), curves.items()):
        x = list(range(len(pts)))  # categorical: values may be numbers, booleans or names
        ax.plot(x, [p[1] for p in pts], "o-", label="SNAPS")
        ax.plot(x, [p[2] for p in pts], "s-", label="batch")
        ax.set_xticks(x, [str(p[0]) for p in pts])
        ax.axhline(vo_md, color="k", ls="--", lw=0.8, label="VO")
        ax.set_title(param)
        ax.set_ylabel("mean deviation [m]")
    axes.ravel()[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
