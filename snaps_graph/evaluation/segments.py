"""Per-segment errors: where along a run each trajectory is better or worse than the odometry.

A whole-run mean can hide a refinement that improved the revisit and spoilt the middle; split by
the distance driven, the same comparison shows where each correction landed.
"""

from __future__ import annotations

import numpy as np

from .metrics import distance_along, position_errors

SEGMENTS = 8  # a run is split into this many stretches of equal ground-truth distance
MIN_FRAMES = 5  # ...fewer when a stretch would hold fewer frames than this


def segment_bounds(gt: np.ndarray, segments: int = SEGMENTS) -> list[tuple[int, int]]:
    """Row ranges [a, b) of stretches of equal ground-truth distance, each of at least MIN_FRAMES rows."""
    n = len(gt)
    k = max(1, min(int(segments), n // MIN_FRAMES))
    s = distance_along(gt[:, :3, 3])
    if s[-1] <= 0.0:
        cuts = np.linspace(0, n, k + 1).astype(int)
    else:
        cuts = np.searchsorted(s, np.linspace(0.0, s[-1], k + 1)[1:-1], side="left")
        cuts = np.concatenate([[0], cuts, [n]])
    bounds = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
    return bounds or [(0, n)]


def segment_errors(trajs: dict[str, np.ndarray], gt: np.ndarray, segments: int = SEGMENTS) -> list[dict]:
    """One row per stretch: its rows, its frames' distance span and each trajectory's mean position error (m)."""
    s = distance_along(gt[:, :3, 3])
    errs = {name: position_errors(p, gt) for name, p in trajs.items()}
    rows = []
    for a, b in segment_bounds(gt, segments):
        row: dict = {"rows": [a, b - 1], "from_m": float(s[a]), "to_m": float(s[b - 1])}
        row["mean_error_m"] = {name: float(e[a:b].mean()) for name, e in errs.items()}
        rows.append(row)
    return rows


def worse_than(rows: list[dict], name: str, base: str, tolerance: float = 1.05) -> list[int]:
    """Indices of the stretches where ``name``'s error exceeds ``tolerance`` x ``base``'s."""
    out = []
    for i, r in enumerate(rows):
        e = r["mean_error_m"]
        if name in e and base in e and e[name] > tolerance * e[base]:
            out.append(i)
    return out


__all__ = ["SEGMENTS", "segment_bounds", "segment_errors", "worse_than"]
