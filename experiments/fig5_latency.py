"""Paper Fig. 5: latency box plots (SNAPS with no candidate, SNAPS with candidates, whole frame).

Reads frames.csv of one or more run folders written by `snaps-graph run` (or by fig3_fig4.py)
and writes results/experiments/fig5_latency.png and fig5_latency.md.

    python experiments/fig5_latency.py results/experiments/fig3_fig4/synthetic_00
"""

from __future__ import annotations

import argparse
import csv

import numpy as np
from _common import RESULTS, md_table

from snaps_graph.evaluation.plots import plot_latency_box


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    args = ap.parse_args()
    none, cand, closed, total, vo, graph = [], [], [], [], [], []
    for run in args.runs:
        with open(f"{run}/frames.csv") as fh:
            for r in csv.DictReader(fh):
                t = float(r["t_loop_ms"])
                (cand if int(r["loop_candidates"]) > 0 else none).append(t)
                if int(r["loop_closed"]):
                    closed.append(t)
                total.append(float(r["t_total_ms"]))
                vo.append(float(r["t_vo_ms"]))
                graph.append(float(r["t_graph_ms"]))
    samples = {
        "SNAPS, no candidate": none,
        "SNAPS, candidates": cand,
        "SNAPS, loop closed": closed,
        "graph update": graph,
        "front end": vo,
        "whole frame": total,
    }
    samples = {k: np.array(v) for k, v in samples.items() if v}
    RESULTS.mkdir(parents=True, exist_ok=True)
    plot_latency_box(RESULTS / "fig5_latency.png", samples, title="Latency per frame (paper Fig. 5)")
    paper = {"SNAPS, no candidate": "0.00294", "SNAPS, candidates": "27.0", "whole frame": "295"}
    rows = [
        [k, len(v), float(np.mean(v)), float(np.median(v)), float(np.percentile(v, 95)), paper.get(k, "")]
        for k, v in samples.items()
    ]
    text = "# Fig. 5: latency\n\nCommand: `python experiments/fig5_latency.py " + " ".join(args.runs) + "`\n\n"
    text += md_table(["stage", "frames", "mean ms", "median ms", "p95 ms", "paper mean ms"], rows)
    text += "\nThe paper: 4-core laptop CPU; ours: the 2-core machine the command ran on.\n"
    (RESULTS / "fig5_latency.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
