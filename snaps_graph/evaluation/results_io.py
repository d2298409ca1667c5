"""The results folder's files, read and written in one place (each format has this one owner).

``frames.csv`` (columns ``types.FRAME_COLUMNS``), ``loops.jsonl`` (one ``LoopEvent`` per line),
``candidates.csv`` (columns ``types.CANDIDATE_COLUMNS``), ``metrics.json`` (strict JSON) and the
trajectories ``poses_NAME.txt`` / ``.tum`` (through ``trajectory_io``). The runner writes them, the
report, the loop evaluation and the batch read them; a missing or malformed file is a
SnapsGraphError naming it (and the line where there is one).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SnapsGraphError
from ..geometry import inv
from ..io_utils import MARKER, atomic_write_text, read_text
from ..trajectory_io import read_kitti_poses, read_poses, write_kitti_poses, write_tum_poses
from ..types import CANDIDATE_COLUMNS, FRAME_COLUMNS, CandidateRecord, FrameRecord, LoopEvent

TRAJECTORY_NAMES = ("vo", "snaps", "isam2", "batch")  # report order: raw -> heuristic -> optimised
BOOL_WORDS = {"true": 1.0, "yes": 1.0, "false": 0.0, "no": 0.0}  # csv cells written from bools


# ---------------------------------------------------------------------------------------------
# Trajectories
# ---------------------------------------------------------------------------------------------
def write_trajectories(out: Path, trajectories: dict[str, np.ndarray], timestamps: np.ndarray) -> None:
    """``poses_NAME.txt`` (KITTI) and ``poses_NAME.tum`` (TUM, with ``timestamps``) per trajectory."""
    for name, poses in trajectories.items():
        write_kitti_poses(out / f"poses_{name}.txt", poses)
        write_tum_poses(out / f"poses_{name}.tum", poses, timestamps)


def write_gt(out: Path, gt_poses: np.ndarray, timestamps: np.ndarray | None = None) -> None:
    """``poses_gt.txt`` (and ``poses_gt.tum`` with ``timestamps``): the ground truth of the run's frames."""
    write_kitti_poses(out / "poses_gt.txt", gt_poses)
    if timestamps is not None:
        write_tum_poses(out / "poses_gt.tum", gt_poses, timestamps)


def read_trajectories(run: Path) -> dict[str, np.ndarray]:
    """The run's trajectories by name (``poses_vo.txt`` required, the others when present)."""
    vo_path = run / "poses_vo.txt"
    if not vo_path.is_file():
        raise SnapsGraphError(f"{vo_path}: not found (every run writes the VO trajectory)")
    trajs = {}
    for name in TRAJECTORY_NAMES:
        p = run / f"poses_{name}.txt"
        if p.is_file():
            trajs[name] = read_kitti_poses(p)
    n = len(trajs["vo"])
    for name, poses in trajs.items():
        if len(poses) != n:
            raise SnapsGraphError(f"{run / f'poses_{name}.txt'}: {len(poses)} poses, but poses_vo.txt has {n}")
    return trajs


def check_run_files(run: Path, required: tuple[str, ...], wanted: tuple[str, ...] = ()) -> list[str]:
    """One SnapsGraphError naming every ``required`` file missing from the run folder; returns the
    ``wanted`` ones (``fnmatch`` patterns) that the run wrote (its marker lists them) and that are
    gone since, for the caller to name: a command never works on a part of a run without saying so."""
    import fnmatch

    missing = [name for name in required if not (run / name).is_file()]
    if missing:
        raise SnapsGraphError(f"{run}: {', '.join(missing)} not found in the run folder")
    try:
        listed = json.loads((run / MARKER).read_text()).get("files") or []
    except (OSError, ValueError, AttributeError):
        return []  # not a folder a run wrote (or an older one): nothing is known to be expected
    return [
        name
        for name in listed
        if isinstance(name, str) and any(fnmatch.fnmatch(name, pat) for pat in wanted) and not (run / name).exists()
    ]


def rebase(poses: np.ndarray) -> np.ndarray:
    return np.einsum("ij,njk->nik", inv(poses[0]), poses)


def load_gt(
    run: Path, gt_path: str | Path | None, frame_ids: np.ndarray, rebased: bool = True
) -> tuple[np.ndarray | None, Path | None]:
    """Ground truth of the run's rows, re-based to the first (``gt_path`` or ``RUN/poses_gt.txt``;
    ``rebased=False``: as the file has it, for a run written in a prior session's frame).

    A file with one pose per row is used as is; a longer one (the whole sequence) is indexed by
    the dataset frame numbers ``frame_ids``. (None, None) when the run has none and none is given.
    """
    if gt_path is None:
        p = run / "poses_gt.txt"
        if not p.is_file():
            return None, None
    else:
        p = Path(gt_path)
        if not p.is_file():
            raise SnapsGraphError(f"{p}: ground-truth file not found")
    gt = read_poses(p)
    n = len(frame_ids)
    if len(gt) == n:
        selected = gt
    elif frame_ids.max() < len(gt):
        selected = gt[frame_ids]  # a whole-sequence file: pick the processed frames
    else:
        raise SnapsGraphError(
            f"{p}: {len(gt)} poses cover neither the run's {n} rows nor its dataset frames {frame_ids.min()}..{frame_ids.max()}"
        )
    return (rebase(selected) if rebased else selected), p


# ---------------------------------------------------------------------------------------------
# frames.csv
# ---------------------------------------------------------------------------------------------
def frames_csv_text(records: list[FrameRecord]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(FRAME_COLUMNS)
    for r in records:
        row = dataclasses.astuple(r)
        w.writerow([f"{v:.4f}" if isinstance(v, float) and c != "timestamp" else v for c, v in zip(FRAME_COLUMNS, row)])
    return buf.getvalue()


def write_frames_csv(path: str | Path, records: list[FrameRecord]) -> None:
    atomic_write_text(path, frames_csv_text(records))


def read_frames_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns of frames.csv as float arrays (empty or unparsable cells -> NaN, booleans -> 0/1)."""
    if not path.is_file():
        raise SnapsGraphError(f"{path}: not found (every run writes frames.csv)")
    reader = csv.DictReader(io.StringIO(read_text(path, "frames.csv"), newline=""))
    if not reader.fieldnames:
        raise SnapsGraphError(f"{path}: empty file, expected a header row")
    names = [n.strip() for n in reader.fieldnames]
    cells: dict[str, list[str]] = {n: [] for n in names}
    try:
        for row in reader:
            for raw_name, n in zip(reader.fieldnames, names):
                cells[n].append((row.get(raw_name) or "").strip())
    except csv.Error as exc:
        raise SnapsGraphError(f"{path}: malformed CSV ({exc})") from None
    return {n: _column(v) for n, v in cells.items()}


def _column(values: list[str]) -> np.ndarray:
    out = np.full(len(values), np.nan)
    for i, v in enumerate(values):
        low = v.lower()
        if low in BOOL_WORDS:
            out[i] = BOOL_WORDS[low]
        else:
            try:
                out[i] = float(v)
            except ValueError:
                pass
    return out


def frame_ids(cols: dict[str, np.ndarray], n_rows: int, path: Path) -> np.ndarray:
    """The dataset frame index of each row (frames.csv's ``frame`` column; 0..n-1 without one)."""
    if "frame" not in cols:
        return np.arange(n_rows)
    f = cols["frame"]
    if not np.all(np.isfinite(f)) or np.any(f != np.round(f)) or np.any(f < 0):
        raise SnapsGraphError(f"{path}: the 'frame' column must hold non-negative whole numbers")
    ids = f.astype(int)
    if len(np.unique(ids)) != len(ids):
        raise SnapsGraphError(f"{path}: the 'frame' column repeats a frame index")
    return ids


# ---------------------------------------------------------------------------------------------
# loops.jsonl
# ---------------------------------------------------------------------------------------------
def write_loops_jsonl(path: str | Path, loops: list[LoopEvent]) -> None:
    atomic_write_text(path, "".join(json.dumps(lp.to_json()) + "\n" for lp in loops))


def read_loops(path: Path, row_of_frame: dict[int, int]) -> list[dict]:
    """The run's own loop objects, each with ``row`` / ``reference_row`` (rows of frames.csv); []
    without a file. Loops to a prior session (a ``session`` key) are left out: their reference
    is that session's frame."""
    if not path.is_file():
        return []
    loops = []
    for lineno, line in enumerate(read_text(path, "loops.jsonl").splitlines(), 1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            frame, ref = int(obj["frame"]), int(obj["reference"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            raise SnapsGraphError(f"{path}:{lineno}: not a loop object with integer 'frame' and 'reference'") from None
        if obj.get("session"):
            continue
        for key, value in (("frame", frame), ("reference", ref)):
            if value not in row_of_frame:
                raise SnapsGraphError(f"{path}:{lineno}: {key} {value} is not a frame of this run (frames.csv)")
        obj["row"] = row_of_frame[frame]
        obj["reference_row"] = row_of_frame[ref]
        loops.append(obj)
    return loops


# ---------------------------------------------------------------------------------------------
# candidates.csv (columns: types.CANDIDATE_COLUMNS, in field order)
# ---------------------------------------------------------------------------------------------
_FLOATS = {"distance_m", "yaw_diff_deg", "q", "correlation", "luminance", "contrast"}
_BOOLS = {"above_threshold", "verify_tried", "verify_passed", "accepted"}


def candidates_csv_text(records: list[CandidateRecord]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CANDIDATE_COLUMNS)
    for r in records:
        w.writerow(
            f"{v:.6f}" if name in _FLOATS else (int(v) if name in _BOOLS else v)
            for name, v in zip(CANDIDATE_COLUMNS, dataclasses.astuple(r))
        )
    return buf.getvalue()


def write_candidates_csv(path: str | Path, records: list[CandidateRecord]) -> None:
    """Write ``candidates.csv`` atomically (a header only when there are no records)."""
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
                vals: dict = {}
                for c in CANDIDATE_COLUMNS:
                    cell = row[c].strip()
                    vals[c] = float(cell) if c in _FLOATS else (bool(int(cell)) if c in _BOOLS else int(cell))
            except (ValueError, TypeError, AttributeError):
                raise SnapsGraphError(f"{path}:{lineno}: malformed row") from None
            out.append(CandidateRecord(**vals))
    return out


# ---------------------------------------------------------------------------------------------
# metrics.json
# ---------------------------------------------------------------------------------------------
def json_clean(obj: Any) -> Any:
    """NaN/inf -> None and numpy scalars -> Python, so metrics.json is strict JSON."""
    if isinstance(obj, dict):
        return {str(k): json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_clean(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def write_metrics_json(path: str | Path, metrics: dict) -> dict:
    """The one writer of metrics.json (the runner's and the report's): strict JSON, atomic.
    Returns what was written (NaN -> null)."""
    clean = json_clean(metrics)
    atomic_write_text(path, json.dumps(clean, indent=2) + "\n")
    return clean


def read_metrics_json(path: Path) -> dict:
    """metrics.json as a dict ({} when absent); malformed JSON or not an object is a SnapsGraphError."""
    if not path.is_file():
        return {}
    try:
        data = json.loads(read_text(path, "metrics.json"))
    except json.JSONDecodeError as exc:
        raise SnapsGraphError(f"{path}: malformed JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise SnapsGraphError(f"{path}: expected a JSON object")
    return data
