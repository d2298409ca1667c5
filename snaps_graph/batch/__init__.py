"""Plans of runs on Ray: every (sequence, variant) cell is one Ray task running the ordinary runner.

A plan (TOML) names sequences and variants; ``snaps-graph batch PLAN --out DIR`` runs each cell
into ``DIR/<sequence>/<variant>/``, an ordinary results folder, and writes ``DIR/summary.csv``
and ``DIR/summary.md``::

    sequences = ["/data/kitti/sequences/00", { path = "results/seq07", name = "s07", gt = "gt.txt" }, "/data/euroc/MH_01"]
    frames = "0:1000"      # run options: frames, config, refine, loops, map, mode, map_all
    refine = "batch"
    cpus_per_task = 1      # CPUs Ray reserves per cell (OpenCV and BLAS threads are pinned to it)
    [variants.default]
    [variants.tight]
    loop = { min_similarity = 0.3 }   # config overrides, checked like a config file
    frontend.klt = { features = 1000 }

A sequence is anything ``run`` reads except a live device (KITTI, EuRoC, ROS bags; a table may
add ``gt``, ``left_topic``, ``right_topic``, ``calib``). Relative paths are relative to the plan
file. Everything is checked on the driver before any task starts (the plan's keys and values,
each variant's configuration, each sequence with its frame range), and an error names the plan
file and the key.

Resuming: a finished cell leaves ``batch.json`` (its config hash, node, wall time, version and
commit) beside ``metrics.json``; a re-run skips a cell whose folder holds both with the same
hash, and re-runs (replacing whole) a cell whose configuration changed or that failed. The hash
covers what decides the run's output: the full configuration, the sequence path (with its
reader options), the frame range and the ground-truth file.
"""

from __future__ import annotations

from .plan import Cell, Plan, config_hash, load_plan, plan_from_dict
from .run import CELL_FILE, completed, pinned_threads, run_batch, run_cell
from .summary import write_summary

__all__ = [
    "CELL_FILE",
    "Cell",
    "Plan",
    "completed",
    "config_hash",
    "load_plan",
    "pinned_threads",
    "plan_from_dict",
    "run_batch",
    "run_cell",
    "write_summary",
]
