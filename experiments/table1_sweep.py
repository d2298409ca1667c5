"""Paper Table I: each SNAPS design parameter swept over a range; its effect on accuracy and time.

The front end runs once over the sequence (a synthetic rendering along KITTI 00 by default); every
setting is then replayed through SNAPS and the graph (batch refinement) with one parameter changed
from the defaults. Writes results/experiments/table1_sweep.md and table1_sweep.png.

    python experiments/table1_sweep.py [--path 00] [--seq DIR]
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np
from _common import RESULTS, false_loops, md_table, replay, synthetic_dir, vo_cache

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation

SWEEPS = {
    "radius_m": [5.0, 10.0, 20.0, 40.0],
    "frame_distance": [50, 100, 200, 400],
    "discount_length": [25, 50, 100, 200, 400],
    "min_similarity": [0.5, 0.65, 0.75, 0.85, 0.95],
    "inter_frame_pause": [10, 25, 50, 100, 200],
    "attempts": [1, 2, 5, 10, 20],
    "max_yaw_deg": [5.0, 10.0, 20.0, 45.0],
    "use_verified_offset": [False, True],
    "shift_px": [0, 4, 8, 12],
    "window": [8, 16],
    "correction_weight": ["q", "verified"],
    "correction_axes": ["xyz", "ground"],
    "correction_rotation": ["none", "yaw", "full"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--path", default="00")
    ap.add_argument("--seq", default=None, help="a KITTI-format sequence with ground truth instead")
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    args = ap.parse_args()
    seq_dir = args.seq or synthetic_dir(args.path, args.width, args.height)
    seq = KittiSequence(seq_dir)
    base = Config()
    cache = vo_cache(seq, base)
    gt = cache.gt
    vo_poses = np.array([cache.results[int(i)].pose for i in cache.indices])
    vo_md, vo_ate = mean_deviation(vo_poses, gt), ate_rmse(vo_poses, gt)
    rows, curves = [], {}
    for param, values in SWEEPS.items():
        for v in values:
            cfg = copy.deepcopy(base)
            setattr(cfg.loop, param, v)
            t0 = time.perf_counter()
            result, pipe = replay(cache, cfg, refine="batch")
            wall = time.perf_counter() - t0
            tr = result.trajectories
            t_loop = [r.t_loop_ms for r in result.records if r.loop_candidates > 0]
            row = [param, v, len(result.loops), false_loops(result.loops, gt, cache.indices, base.loop.radius_m),
                   mean_deviation(tr["snaps"], gt), ate_rmse(tr["snaps"], gt),
                   mean_deviation(tr["batch"], gt), ate_rmse(tr["batch"], gt),
                   float(np.median(t_loop)) if t_loop else float("nan"), sum(r.loop_candidates for r in result.records)]
            rows.append(row)
            curves.setdefault(param, []).append((v, row[4], row[6]))
            print(f"{param}={v}: loops {row[2]} (false {row[3]}), SNAPS mean dev {row[4]:.2f} m, batch {row[6]:.2f} m, {wall:.1f} s")
    text = "# Table I: design parameters swept\n\n"
    text += f"Command: `python experiments/table1_sweep.py {'--seq ' + str(args.seq) if args.seq else '--path ' + args.path}`; sequence `{seq_dir}` ({len(seq)} frames).\n"
    defaults = ", ".join(f"{k} {getattr(base.loop, k)}" for k in SWEEPS)
    text += f"VO alone: mean deviation {vo_md:.3f} m, ATE {vo_ate:.3f} m. Every row changes one parameter from the defaults: {defaults}.\n"
    text += "False loops: reference farther than 10 m from the current frame in the ground truth. Time: median SNAPS ms on frames that compared candidates.\n\n"
    text += md_table(["parameter", "value", "loops", "false", "SNAPS mean dev m", "SNAPS ATE m", "batch mean dev m", "batch ATE m", "SNAPS ms (cand.)", "similarities"], rows)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "table1_sweep.md").write_text(text)
    _plot(curves, vo_md, RESULTS / "table1_sweep.png")
    print(text)


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
