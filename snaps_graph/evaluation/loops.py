"""Loop-closure evaluation against ground truth (``snaps-graph loops RUN_DIR``).

From a run's candidates.csv (every similarity SNAPS computed) and loops.jsonl: each compared pair
is true, false or ignored by its ground-truth distance; precision-recall over the Q threshold (Q
alone, and Q + verification), the maximum recall at 100 % precision, the revisit segments found,
the false loops. The definitions: docs/usage.md, "loops". :func:`evaluate_loops` is pure (arrays
in, dict out); :func:`loops_run` reads a run folder, writes the PR plot and returns the same dict.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..errors import SnapsGraphError
from ..geometry import wrap_deg, yaw_deg
from ..types import CandidateRecord
from .results_io import check_run_files, json_clean, load_gt, read_candidates_csv, read_frames_csv, read_loops
from .results_io import frame_ids as frame_ids_of


@dataclass(frozen=True)
class LoopEvalSettings:
    true_m: float = 5.0
    false_m: float = 10.0
    frame_distance: int = 100  # M of the revisit definition (the run's loop.frame_distance)
    max_yaw_deg: float = 10.0  # yaw limit of the revisit definition (the loop policies' limit)
    segment_gap: int = 10


def label_pairs(d_gt: ArrayLike, true_m: float, false_m: float) -> np.ndarray:
    """+1 true (d <= true_m), 0 false (d > false_m), -1 ignored (in between)."""
    d = np.asarray(d_gt, float)
    return np.where(d <= true_m, 1, np.where(d > false_m, 0, -1))


def pr_curve(q: np.ndarray, labels: np.ndarray, eligible: np.ndarray | None = None) -> dict:
    """Precision and recall at every distinct Q threshold (descending), ignored pairs left out.

    ``eligible`` (default all) marks pairs that can be predicted at all (verification passed).
    Returns thresholds, precision, recall (lists), n_true, and the maximum recall at 100 %
    precision with the threshold that reaches it and the highest Q of an eligible false pair.
    """
    q = np.asarray(q, float)
    lab = np.asarray(labels)
    el = np.ones(len(q), bool) if eligible is None else np.asarray(eligible, bool)
    keep = lab >= 0
    q, lab, el = q[keep], lab[keep], el[keep]
    n_true = int((lab == 1).sum())
    pos = el & (lab == 1)
    neg = el & (lab == 0)
    thr = np.unique(q[el])[::-1]
    # Counts of predicted true / false pairs at each threshold (q >= t), by sorted search.
    qt, qf = np.sort(q[pos]), np.sort(q[neg])
    tp = len(qt) - np.searchsorted(qt, thr, side="left")
    fp = len(qf) - np.searchsorted(qf, thr, side="left")
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
        recall = tp / n_true if n_true else np.zeros(len(thr))
    q_max_false = float(qf[-1]) if len(qf) else None
    clean = fp == 0
    if n_true and clean.any():
        i = int(np.flatnonzero(clean)[-1])  # lowest threshold without a false pair
        best_recall, best_thr = float(recall[i]), float(thr[i])
    else:
        best_recall, best_thr = 0.0, None
    return {
        "thresholds": thr.tolist(),
        "precision": np.asarray(precision, float).tolist(),
        "recall": np.asarray(recall, float).tolist(),
        "n_true": n_true,
        "n_false": int((lab == 0).sum()),
        "max_recall_at_100_precision": best_recall,
        "threshold_at_100_precision": best_thr,
        "q_max_false": q_max_false,
    }


def _revisit_mask(gt: np.ndarray, radius_m: float, frame_distance: int, max_yaw_deg: float) -> np.ndarray:
    """Rows of ``gt`` (N, 4, 4) within radius_m and max_yaw_deg of a row >= frame_distance earlier."""
    p = gt[:, :3, 3]
    yaw = np.asarray(yaw_deg(gt[:, :3, :3]), float)
    out = np.zeros(len(p), bool)
    for k in range(frame_distance, len(p)):
        m = k - frame_distance + 1
        near = np.einsum("ij,ij->i", p[:m] - p[k], p[:m] - p[k]) <= radius_m * radius_m
        if near.any():
            out[k] = bool(np.any(np.abs(wrap_deg(yaw[:m][near] - yaw[k])) <= max_yaw_deg))
    return out


def segments(mask: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """Maximal runs (first, last) of True rows; runs at most ``gap`` rows apart are joined."""
    segs: list[list[int]] = []
    for k in np.flatnonzero(mask).tolist():
        if segs and k - segs[-1][1] <= gap:
            segs[-1][1] = k
        else:
            segs.append([k, k])
    return [(a, b) for a, b in segs]


def _rows_of(row: dict[int, int], pairs) -> np.ndarray:
    """(frame, reference) dataset indices as (K, 2) run rows."""
    try:
        return np.array([[row[a], row[b]] for a, b in pairs], int).reshape(-1, 2)
    except KeyError as exc:
        raise SnapsGraphError(f"frame {exc.args[0]} of a loop or candidate is not a frame of this run") from None


def _at_threshold(q: np.ndarray, labels: np.ndarray, passed: np.ndarray, min_similarity: float) -> dict:
    """Precision and recall of the pairs at the run's Q threshold, without and with verification."""
    at_threshold = {}
    for key, el in (("", np.ones(len(q), bool)), ("_verified", passed)):
        pred = el & (q >= min_similarity)
        tp, fp = int((pred & (labels == 1)).sum()), int((pred & (labels == 0)).sum())
        n_true = int((labels == 1).sum())
        at_threshold[f"precision_at_min_similarity{key}"] = tp / (tp + fp) if tp + fp else None
        at_threshold[f"recall_at_min_similarity{key}"] = tp / n_true if n_true else None
    return at_threshold


def _settings_dict(s: LoopEvalSettings) -> dict:
    return {
        "true_m": s.true_m,
        "false_m": s.false_m,
        "frame_distance": s.frame_distance,
        "max_yaw_deg": s.max_yaw_deg,
        "segment_gap": s.segment_gap,
    }


def evaluate_loops(
    records: list[CandidateRecord],
    loops: list[tuple[int, int]],
    gt: np.ndarray,
    frame_ids: np.ndarray,
    settings: LoopEvalSettings = LoopEvalSettings(),
    min_similarity: float | None = None,
) -> dict:
    """The loop evaluation (definitions: docs/usage.md, "loops"). ``gt`` is (N, 4, 4), one pose per run row;
    ``frame_ids`` the dataset index of each row; ``loops`` the accepted (frame, reference) pairs
    (dataset indices). Frame numbers in the output are dataset indices. With ``min_similarity``
    (the run's threshold) also the precision and recall at that threshold."""
    s = settings
    row = {int(f): i for i, f in enumerate(np.asarray(frame_ids).tolist())}
    p = np.asarray(gt, float)[:, :3, 3]
    rc = _rows_of(row, [(r.frame, r.reference) for r in records])
    d_gt = np.linalg.norm(p[rc[:, 0]] - p[rc[:, 1]], axis=1) if len(rc) else np.zeros(0)
    labels = label_pairs(d_gt, s.true_m, s.false_m)
    q = np.array([r.q for r in records], float)
    tried = np.array([r.verify_tried for r in records], bool)
    passed = np.array([r.verify_passed for r in records], bool)
    plain = pr_curve(q, labels)
    verified = pr_curve(q, labels, passed)

    revisit = _revisit_mask(gt, s.true_m, s.frame_distance, s.max_yaw_deg)
    true_rows = set(rc[labels == 1, 0].tolist())
    compared_rows = set(rc[:, 0].tolist())
    searched = [k for k in np.flatnonzero(revisit).tolist() if k in true_rows]

    lr = _rows_of(row, loops)
    d_loop = np.linalg.norm(p[lr[:, 0]] - p[lr[:, 1]], axis=1) if len(lr) else np.zeros(0)
    loop_labels = label_pairs(d_loop, s.true_m, s.false_m)
    true_loop_rows = lr[loop_labels == 1, 0].tolist()
    segs = segments(revisit, s.segment_gap)
    found = [(a, b) for a, b in segs if any(a <= k <= b for k in true_loop_rows)]
    missed = [(a, b) for a, b in segs if (a, b) not in found]
    fid = np.asarray(frame_ids)
    false_loops = [
        {"frame": int(a), "reference": int(b), "distance_gt_m": float(d)}
        for (a, b), d, lab in zip(loops, d_loop, loop_labels)
        if lab == 0
    ]
    at_threshold = _at_threshold(q, labels, passed, min_similarity) if min_similarity is not None else {}
    return at_threshold | {
        "settings": _settings_dict(s),
        "pairs": len(records),
        "true_pairs": int((labels == 1).sum()),
        "false_pairs": int((labels == 0).sum()),
        "ignored_pairs": int((labels == -1).sum()),
        "frames_compared": len(compared_rows),
        "verification_tried": int(tried.sum()),
        "verification_coverage": float(tried.mean()) if len(tried) else None,
        "verified_true_pairs": int((passed & (labels == 1)).sum()),
        "verified_false_pairs": int((passed & (labels == 0)).sum()),
        "max_recall_at_100_precision": plain["max_recall_at_100_precision"],
        "max_recall_at_100_precision_verified": verified["max_recall_at_100_precision"],
        "threshold_at_100_precision": plain["threshold_at_100_precision"],
        "threshold_at_100_precision_verified": verified["threshold_at_100_precision"],
        "q_max_false": plain["q_max_false"],
        "q_max_false_verified": verified["q_max_false"],
        "q_true_median": float(np.median(q[labels == 1])) if (labels == 1).any() else None,
        "revisit_frames": int(revisit.sum()),
        "revisit_frames_searched": len(searched),
        "segments": len(segs),
        "segments_found": len(found),
        "segments_missed": len(missed),
        "segments_found_frames": [[int(fid[a]), int(fid[b])] for a, b in found],
        "segments_missed_frames": [[int(fid[a]), int(fid[b])] for a, b in missed],
        "loops": len(loops),
        "true_loops": int((loop_labels == 1).sum()),
        "ignored_loops": int((loop_labels == -1).sum()),
        "false_loops": len(false_loops),
        "false_loop_pairs": false_loops,
        "curve": {"q": plain, "q_verified": verified},
    }


def _plot_loops(
    path: str | Path, ev: dict, records: list[CandidateRecord], labels: np.ndarray, min_similarity: float | None, title: str
) -> None:
    """Two panels: precision-recall (Q alone, Q + verification) and Q of true / false pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, lab, style in (("q", "Q alone", "-"), ("q_verified", "Q + verification", "--")):
        c = ev["curve"][key]
        if c["recall"]:
            a.plot(
                c["recall"],
                c["precision"],
                style,
                drawstyle="steps-post",
                label=f"{lab} (max recall at P=1: {c['max_recall_at_100_precision']:.2f})",
            )
    a.set_xlabel("recall")
    a.set_ylabel("precision")
    a.set_xlim(0, 1.02)
    a.set_ylim(0, 1.05)
    if a.get_legend_handles_labels()[0]:  # no true pair compared: no curve to label
        a.legend(loc="lower left", fontsize=8)
    a.set_title("precision-recall over the Q threshold")
    q = np.array([r.q for r in records], float)
    passed = np.array([r.verify_passed for r in records], bool)
    lo, hi = (float(q.min()), float(q.max())) if len(q) else (0.0, 1.0)
    bins = np.linspace(lo, hi if hi > lo else lo + 1e-3, 41)
    for val, name, col in (
        (1, f"true (<= {ev['settings']['true_m']:g} m)", "tab:green"),
        (0, f"false (> {ev['settings']['false_m']:g} m)", "tab:red"),
        (-1, "ignored", "tab:grey"),
    ):
        sel = labels == val
        if sel.any():
            b.hist(q[sel], bins=bins, alpha=0.5, color=col, label=f"{name}: {int(sel.sum())}")
    sel = (labels == 0) & passed
    if sel.any():
        b.hist(q[sel], bins=bins, histtype="step", color="k", label=f"false, verified: {int(sel.sum())}")
    if min_similarity is not None:
        b.axvline(min_similarity, color="k", ls=":", label=f"min_similarity {min_similarity:g}")
    b.set_xlabel("Q (UIQI)")
    b.set_ylabel("compared pairs")
    b.legend(fontsize=8)
    b.set_title("Q of the compared pairs")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _run_loop_settings(run: Path) -> tuple[dict, float | None]:
    """The run's [loop] section (config.toml), for M, the yaw limit and min_similarity."""
    import tomllib

    p = run / "config.toml"
    if not p.is_file():
        return {}, None
    try:
        loop = tomllib.loads(p.read_text()).get("loop", {})
    except tomllib.TOMLDecodeError as exc:
        raise SnapsGraphError(f"{p}: malformed TOML ({exc})") from None
    return loop, loop.get("min_similarity")


def loops_run(
    run_dir: str | Path,
    gt_path: str | Path | None = None,
    *,
    true_m: float = 5.0,
    false_m: float = 10.0,
    png: str | Path | None = None,
    name_missing: bool = True,
) -> dict:
    """Evaluate a run folder's loop closure against ground truth; writes the PR plot (default
    RUN_DIR/loops_pr.png) and returns :func:`evaluate_loops`'s dict (with ``plot``).
    ``name_missing``: warn of the run's files deleted since (False: the caller has)."""
    run = Path(run_dir)
    if not run.is_dir():
        raise SnapsGraphError(f"{run}: run folder not found")
    if not 0 < true_m <= false_m:
        raise SnapsGraphError(f"need 0 < true distance <= false distance, got {true_m} and {false_m}")
    needed = ("frames.csv", "candidates.csv") + (("poses_gt.txt",) if gt_path is None else ())
    try:
        gone = check_run_files(run, needed, ("loops.jsonl", "config.toml"))
    except SnapsGraphError as exc:
        hint = " (pass --gt for the ground truth)" if gt_path is None and not (run / "poses_gt.txt").is_file() else ""
        raise SnapsGraphError(f"{exc}{hint}") from None
    if gone and name_missing:
        print(f"warning: {run}: {', '.join(gone)} missing (the run wrote them); evaluated without them", file=sys.stderr)
    csv_path = run / "frames.csv"
    cols = read_frames_csv(csv_path)
    n = len(next(iter(cols.values())))
    frame_ids = frame_ids_of(cols, n, csv_path)
    gt, _ = load_gt(run, gt_path, frame_ids)
    if gt is None:
        raise SnapsGraphError(f"{run}: no ground truth (no poses_gt.txt; pass --gt)")
    records = read_candidates_csv(run / "candidates.csv")
    row_of = {int(f): i for i, f in enumerate(frame_ids)}
    loops = [(int(lp["frame"]), int(lp["reference"])) for lp in read_loops(run / "loops.jsonl", row_of)]
    loop_cfg, min_sim = _run_loop_settings(run)
    settings = LoopEvalSettings(
        true_m=true_m,
        false_m=false_m,
        frame_distance=int(loop_cfg.get("frame_distance", LoopEvalSettings.frame_distance)),
        max_yaw_deg=float(loop_cfg.get("max_yaw_deg", LoopEvalSettings.max_yaw_deg)),
    )
    ev = evaluate_loops(records, loops, gt, frame_ids, settings, min_sim)
    ev["min_similarity"] = min_sim
    if records:
        row = {int(f): i for i, f in enumerate(frame_ids)}
        p = gt[:, :3, 3]
        d = np.array([np.linalg.norm(p[row[r.frame]] - p[row[r.reference]]) for r in records])
        out = Path(png) if png else run / "loops_pr.png"
        _plot_loops(out, ev, records, label_pairs(d, true_m, false_m), min_sim, f"{run.name}: loop closure")
        ev["plot"] = str(out)
    return ev


def summary_lines(ev: dict) -> list[str]:
    """Plain-text summary (the CLI's output and report.md's loop section)."""
    s = ev["settings"]

    def f(v, nd=3):
        return "n/a" if v is None else f"{v:.{nd}f}"

    cov = ev["verification_coverage"]
    if ev["true_pairs"]:
        recall = (
            f"max recall at 100% precision: Q alone {f(ev['max_recall_at_100_precision'])} "
            f"(threshold {f(ev['threshold_at_100_precision'], 4)}, highest false Q {f(ev['q_max_false'], 4)}); "
            f"Q + verification {f(ev['max_recall_at_100_precision_verified'])} "
            f"(threshold {f(ev['threshold_at_100_precision_verified'], 4)}, highest verified false Q {f(ev['q_max_false_verified'], 4)})"
        )
    else:  # recall has no denominator: a 0 would read as a detector that missed every revisit
        why = "no revisit in this run" if not ev["revisit_frames"] else "no true pair compared"
        recall = f"max recall at 100% precision: n/a ({why})"
    return [
        f"pairs compared {ev['pairs']} (true <= {s['true_m']:g} m: {ev['true_pairs']}, false > {s['false_m']:g} m: "
        f"{ev['false_pairs']}, ignored: {ev['ignored_pairs']}) at {ev['frames_compared']} frames",
        recall,
        *(
            [
                f"at the run's min_similarity {ev['min_similarity']:g}: precision {f(ev.get('precision_at_min_similarity'))}, "
                f"recall {f(ev.get('recall_at_min_similarity'))}; with verification {f(ev.get('precision_at_min_similarity_verified'))}, "
                f"{f(ev.get('recall_at_min_similarity_verified'))}"
            ]
            if ev.get("min_similarity") is not None
            else []
        ),
        f"verification tried on {ev['verification_tried']} of {ev['pairs']} pairs"
        + (f" ({100 * cov:.0f}%)" if cov is not None else "")
        + f"; passed on {ev['verified_true_pairs']} true and {ev['verified_false_pairs']} false pairs",
        f"revisit frames {ev['revisit_frames']} (within {s['true_m']:g} m and {s['max_yaw_deg']:g} deg of a frame >= "
        f"{s['frame_distance']} earlier); SNAPS compared a true pair at {ev['revisit_frames_searched']}",
        f"revisit segments {ev['segments']}: found {ev['segments_found']}, missed {ev['segments_missed']}"
        + (f" {ev['segments_missed_frames']}" if ev["segments_missed"] else ""),
        f"loops accepted {ev['loops']}: true {ev['true_loops']}, ignored band {ev['ignored_loops']}, false {ev['false_loops']}"
        + (
            f" {[(x['frame'], x['reference'], round(x['distance_gt_m'], 2)) for x in ev['false_loop_pairs']]}"
            if ev["false_loops"]
            else ""
        ),
    ]


def json_text(ev: dict, with_curve: bool = True) -> str:
    out = dict(ev) if with_curve else {k: v for k, v in ev.items() if k != "curve"}
    return json.dumps(json_clean(out), indent=2)


__all__ = [
    "LoopEvalSettings",
    "evaluate_loops",
    "label_pairs",
    "loops_run",
    "pr_curve",
    "_revisit_mask",
    "segments",
    "summary_lines",
]
