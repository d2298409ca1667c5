"""Paper Fig. 3/4: trajectories and deviation from ground truth without and with SNAPS (and refined).

Runs the full pipeline (VO + SNAPS + iSAM2 online + batch at the end) on synthetic renderings
along KITTI 00 and 07 (rendered once, reused), and on any real KITTI sequence given with --seq
(ground truth found as for `snaps-graph run`). Writes per path a run folder with report.md,
trajectories.png (Fig. 3) and errors.png (Fig. 4), and results/experiments/fig3_fig4.md.

    python experiments/fig3_fig4.py [--paths 00 07] [--seq /data/kitti/sequences/05 ...]
"""

from __future__ import annotations

import argparse

from _common import RESULTS, false_loops, md_table, synthetic_dir

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.report import compare_run
from snaps_graph.runner import run_sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--paths", nargs="*", default=["00", "07"], help="synthetic paths: 00, 07, loop or a KITTI pose file")
    ap.add_argument("--seq", nargs="*", default=[], help="real KITTI-format sequence folders")
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--config", default=None)
    args = ap.parse_args()
    cfg0 = Config.load(args.config) if args.config else Config()
    out_root = RESULTS / "fig3_fig4"
    rows = []
    jobs = [(f"synthetic {p}", synthetic_dir(p, args.width, args.height)) for p in args.paths]
    jobs += [(f"real {s}", s) for s in args.seq]
    for name, seq_dir in jobs:
        seq = KittiSequence(seq_dir)
        run_dir = out_root / name.replace(" ", "_").replace("/", "_")
        cfg = Config.from_dict(cfg0.to_dict())
        result, metrics = run_sequence(seq, run_dir, cfg, loops="snaps", refine="both")
        compare_run(run_dir)
        tr = metrics.get("trajectories")
        if not tr:
            print(f"{name}: no ground truth, see {run_dir}/report.md")
            continue
        fl = false_loops(result.loops, seq.gt_poses, seq.indices, cfg.loop.radius_m)
        red = 1 - tr["snaps"]["mean_deviation"] / tr["vo"]["mean_deviation"]
        for t in ("vo", "snaps", "isam2", "batch"):
            m = tr[t]
            rows.append([name, t, len(seq), len(result.loops) if t != "vo" else "", fl if t != "vo" else "",
                         m["mean_deviation"], m["ate_rmse"], m["t_rel"], m["r_rel"]])
        print(f"{name}: SNAPS mean deviation {tr['vo']['mean_deviation']:.2f} -> {tr['snaps']['mean_deviation']:.2f} m ({100 * red:.0f}% less)")
    text = "# Fig. 3/4: trajectories and deviation from ground truth\n\n"
    text += "Command: `python experiments/fig3_fig4.py " + " ".join(["--paths", *args.paths] + (["--seq", *args.seq] if args.seq else [])) + "`\n\n"
    text += md_table(["sequence", "trajectory", "frames", "loops", "false loops", "mean dev m", "ATE m", "t_rel %", "r_rel deg/100m"], rows)
    text += "\nThe paper (real KITTI, its own VO): mean deviation 16.79 m without loop closure, 5.94 m with SNAPS (-65%).\n"
    text += "Per sequence: `fig3_fig4/<sequence>/trajectories.png` (Fig. 3), `errors.png` (Fig. 4), `report.md`.\n"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "fig3_fig4.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
