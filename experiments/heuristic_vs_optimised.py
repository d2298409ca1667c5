"""Heuristic (SNAPS) against optimised (iSAM2, batch) corrections over several paths and seeds.

Each path is rendered per seed (a different world and texture), the front end runs once, and the
result is replayed with refine = both (iSAM2 online, then batch). Writes
results/experiments/heuristic_vs_optimised.md.

    python experiments/heuristic_vs_optimised.py [--paths loop 07] [--seeds 0 1 2] [--width 620 --height 188]
"""

from __future__ import annotations

import argparse

import numpy as np
from _common import RESULTS, false_loops, md_table, replay, synthetic_dir, vo_cache

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--paths", nargs="*", default=["loop", "07"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    ap.add_argument("--width", type=int, default=620)
    ap.add_argument("--height", type=int, default=188)
    args = ap.parse_args()
    cfg = Config()
    rows, summary = [], {t: [] for t in ("vo", "snaps", "isam2", "batch")}
    for path in args.paths:
        for seed in args.seeds:
            seq = KittiSequence(synthetic_dir(path, args.width, args.height, seed))
            cache = vo_cache(seq, cfg)
            result, pipe = replay(cache, cfg, refine="both")
            nfalse = false_loops(result.loops, cache.gt, cache.indices, cfg.loop.radius_m)
            ms = {t: evaluate(p, cache.gt) for t, p in result.trajectories.items()}
            for t, m in ms.items():
                summary[t].append(m["mean_deviation"])
            rows.append(
                [
                    path,
                    seed,
                    len(seq),
                    len(result.loops),
                    nfalse,
                    *[ms[t]["mean_deviation"] for t in ("vo", "snaps", "isam2", "batch")],
                    *[ms[t]["ate_rmse"] for t in ("vo", "snaps", "isam2", "batch")],
                ]
            )
            print(rows[-1])
    text = "# Heuristic vs optimised corrections\n\n"
    text += f"Command: `python experiments/heuristic_vs_optimised.py --paths {' '.join(args.paths)} --seeds {' '.join(map(str, args.seeds))} --width {args.width} --height {args.height}`\n\n"
    text += md_table(
        [
            "path",
            "seed",
            "frames",
            "loops",
            "false",
            "VO mean dev m",
            "SNAPS",
            "iSAM2",
            "batch",
            "VO ATE m",
            "SNAPS",
            "iSAM2",
            "batch",
        ],
        rows,
    )
    text += "\nMean over all runs, mean deviation [m]: " + ", ".join(f"{t} {np.mean(v):.3f}" for t, v in summary.items()) + "\n"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "heuristic_vs_optimised.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
