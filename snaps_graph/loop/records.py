"""Every similarity SNAPS computes, as typed records, and the one ``candidates.csv`` format.

SNAPS appends one small tuple per compared candidate while it runs (no formatting, no factor
maps: the latency figures cannot see it); :meth:`SnapsLoopCloser.candidate_records` turns them
into :class:`CandidateRecord` at the end of a run, adding Q's three factors computed exactly
from the stored thumbnails (the same float64 arithmetic as a loop's reported factors).
:data:`CANDIDATE_COLUMNS`, :func:`write_candidates_csv` and :func:`read_candidates_csv` are the
only place the file's layout is written down.

Columns (one row per compared candidate, in the order SNAPS compared them):

    frame, reference        dataset frame indices (current, earlier candidate)
    distance_m              |p_ref - p_N| on the heuristic trajectory when compared
    yaw_diff_deg            wrap(yaw_ref - yaw_N), heuristic orientations
    q                       the Q SNAPS compared with min_similarity (at the best shift)
    correlation, luminance, contrast   Q's factors at that shift (window means)
    shift_px                horizontal thumbnail shift of the best Q (0 without shift search)
    above_threshold         Q >= min_similarity
    verify_tried            geometric verification was run on this pair
    verify_passed           ... and returned a relative pose
    inliers                 PnP inliers of a passed verification (0 otherwise)
    accepted                this pair closed the loop at this frame
"""

from __future__ import annotations

import csv
import io
from dataclasses import astuple, dataclass, fields
from pathlib import Path

from ..errors import SnapsGraphError
from ..io_utils import atomic_write_text


@dataclass(frozen=True)
class CandidateRecord:
    """One similarity SNAPS computed (see the module docstring for each field)."""

    frame: int
    reference: int
    distance_m: float
    yaw_diff_deg: float
    q: float
    correlation: float
    luminance: float
    contrast: float
    shift_px: int
    above_threshold: bool
    verify_tried: bool
    verify_passed: bool
    inliers: int
    accepted: bool


CANDIDATE_COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(CandidateRecord))
_FLOATS = {"distance_m", "yaw_diff_deg", "q", "correlation", "luminance", "contrast"}
_BOOLS = {"above_threshold", "verify_tried", "verify_passed", "accepted"}


def candidates_csv_text(records: list[CandidateRecord]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CANDIDATE_COLUMNS)
    for r in records:
        w.writerow(
            f"{v:.6f}" if name in _FLOATS else (int(v) if name in _BOOLS else v)
            for name, v in zip(CANDIDATE_COLUMNS, astuple(r))
        )
    return buf.getvalue()


def write_candidates_csv(path: str | Path, records: list[CandidateRecord]) -> None:
    """Write ``candidates.csv`` (atomically; a header only when there are no records)."""
    atomic_write_text(path, candidates_csv_text(records))


def read_candidates_csv(path: str | Path) -> list[CandidateRecord]:
    """Read a ``candidates.csv``; a missing file, column or malformed cell is a SnapsGraphError."""
    path = Path(path)
    if not path.is_file():
        raise SnapsGraphError(f"{path}: not found (runs with SNAPS write candidates.csv)")
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in CANDIDATE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise SnapsGraphError(f"{path}: missing column(s) {', '.join(missing)}")
        out = []
        for lineno, row in enumerate(reader, 2):
            try:
                vals = {}
                for c in CANDIDATE_COLUMNS:
                    cell = row[c].strip()
                    if c in _FLOATS:
                        vals[c] = float(cell)
                    elif c in _BOOLS:
                        vals[c] = bool(int(cell))
                    else:
                        vals[c] = int(cell)
            except (ValueError, TypeError, AttributeError):
                raise SnapsGraphError(f"{path}:{lineno}: malformed row") from None
            out.append(CandidateRecord(**vals))
    return out


__all__ = ["CANDIDATE_COLUMNS", "CandidateRecord", "candidates_csv_text", "read_candidates_csv", "write_candidates_csv"]
