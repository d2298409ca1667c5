"""``summary.csv`` and ``summary.md`` of a batch: one row per cell, its metrics digest."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from ..evaluation.results_io import TRAJECTORY_NAMES as TRAJECTORIES
from ..io_utils import (
    atomic_write_text,
)

STATUSES = ("ok", "failed", "skipped", "cancelled")
SUMMARY_FILES = ("summary.csv", "summary.md")  # in the batch folder, beside the sequences' folders


# ---------------------------------------------------------------- summary
def summary_columns(rows: list[dict]) -> list[str]:
    cols = ["sequence", "variant", "status", "reason", "node", "wall_s", "frames", "flagged_frames", "loops"]
    for t in TRAJECTORIES:
        if any(t in (r.get("metrics") or {}) for r in rows):
            cols += [f"{t}_mean_dev_m", f"{t}_ate_m", f"{t}_t_rel_pct"]
    return cols + ["version", "commit", "config_hash"]


def summary_row(rec: dict) -> dict[str, Any]:
    m = rec.get("metrics") or {}
    row: dict[str, Any] = {
        k: rec.get(k, "")
        for k in ("sequence", "variant", "status", "reason", "node", "wall_s", "version", "commit", "config_hash")
    }
    row.update({k: m.get(k, "") for k in ("frames", "flagged_frames", "loops")})
    for t in TRAJECTORIES:
        tm = m.get(t) or {}
        row[f"{t}_mean_dev_m"], row[f"{t}_ate_m"], row[f"{t}_t_rel_pct"] = (
            tm.get("mean_deviation"),
            tm.get("ate_rmse"),
            tm.get("t_rel"),
        )
    return {k: ("" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v) for k, v in row.items()}


def write_summary(out: str | Path, records: list[dict], wall_s: float | None = None) -> None:
    """``summary.csv`` (every column, full node ids) and ``summary.md`` (the same table, short ids)."""
    out = Path(out)
    cols = summary_columns(records)
    rows = [summary_row(r) for r in records]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / SUMMARY_FILES[0], buf.getvalue())

    counts = {s: sum(r.get("status") == s for r in records) for s in STATUSES}
    head = f"# Batch summary\n\n{len(records)} cells: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    head += f" ({wall_s:.1f} s)" if wall_s is not None else ""
    lines = [head + ".\n", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            if c == "node":
                v = str(v)[:12]
            elif isinstance(v, float):
                v = f"{v:.3f}"
            elif v == "" and c.endswith(("_m", "_pct")):
                v = "n/a"
            cells.append(str(v).replace("|", "\\|"))
        lines.append("| " + " | ".join(cells) + " |")
    atomic_write_text(out / SUMMARY_FILES[1], "\n".join(lines) + "\n")
