"""Latency statistics of a run (metrics.json's ``latency_ms``, the paper's Fig. 5 stages).

One implementation for the pipeline's records and for a results folder's frames.csv columns.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def latency_stats(values: np.ndarray) -> dict:
    """n / median / mean / p95 / max of the finite samples (ms), ``{"n": 0}`` when there is none: each
    stage of metrics.json's ``latency_ms``, the pipeline's too, so one reader serves both.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size),
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


def latency_samples(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Latency samples (ms) per stage, keyed as the pipeline's ``latency_ms``; absent columns absent."""
    out: dict[str, np.ndarray] = {}
    if "t_total_ms" in cols:
        out["total"] = cols["t_total_ms"]
    if "t_vo_ms" in cols:
        out["vo"] = cols["t_vo_ms"]
    if "t_loop_ms" in cols:
        t = cols["t_loop_ms"]
        if "loop_candidates" in cols:
            cand = cols["loop_candidates"]
            out["loop_no_candidate"] = t[cand == 0]
            out["loop_with_candidates"] = t[cand > 0]
        else:
            out["loop_all"] = t
        if "loop_closed" in cols:
            out["loop_closed"] = t[cols["loop_closed"] > 0]
    if "t_graph_ms" in cols:
        out["graph"] = cols["t_graph_ms"]
    return out


LATENCY_LABELS = {
    "total": "total per frame",
    "vo": "front end (VO)",
    "loop_no_candidate": "SNAPS, no candidate",
    "loop_with_candidates": "SNAPS, with candidates",
    "loop_closed": "SNAPS, loop closed",
    "loop_all": "SNAPS, all frames",
    "graph": "graph update",
}


def summarise_samples(samples: dict[str, np.ndarray]) -> dict:
    out: dict[str, Any] = {k: latency_stats(v) for k, v in samples.items()}
    total = samples.get("total")
    if total is not None:
        t = total[np.isfinite(total)]
        if t.size and t.sum() > 0:
            out["frames_per_s"] = float(t.size / (t.sum() / 1e3))
    return out


def latency_summary(columns: dict[str, np.ndarray]) -> dict:
    """metrics.json's ``latency_ms`` from frames.csv-named columns (t_total_ms, t_vo_ms, t_loop_ms,
    loop_candidates, loop_closed, t_graph_ms; any may be absent): per stage (total, vo,
    loop_no_candidate, loop_with_candidates, loop_closed, graph) ``latency_stats``, plus
    frames_per_s from the total. SNAPS is split by candidates because the paper's Fig. 5 is:
    microseconds without a candidate, tens of milliseconds with one.
    """
    return summarise_samples(latency_samples({k: np.asarray(v, float) for k, v in columns.items()}))


def records_latency_summary(records: list) -> dict:
    """``latency_summary`` of the pipeline's per-frame records (``types.FrameRecord``)."""
    cols = ("t_total_ms", "t_vo_ms", "t_loop_ms", "loop_candidates", "loop_closed", "t_graph_ms")
    return latency_summary({c: np.array([getattr(r, c) for r in records], float) for c in cols})
