"""Plans of runs on Ray: every (sequence, variant) cell is one Ray task running the ordinary runner.

``snaps-graph batch PLAN --out DIR`` checks the whole plan first, runs each cell into
``DIR/<sequence>/<variant>/`` (an ordinary results folder) and writes ``DIR/summary.csv`` and
``summary.md``. The plan's format: docs/usage.md, "batch"; resuming: docs/run-contract.md.
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
