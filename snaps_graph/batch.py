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
    frontend = { klt_features = 1000 }

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

import contextlib
import csv
import dataclasses
import fcntl
import functools
import hashlib
import io
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from . import __version__
from ._malloc import set_malloc_thresholds
from .config import Config, FrontendMode, LoopMode, RefineMode, choices
from .datasets.open import open_dataset
from .errors import SnapsGraphError
from .evaluation.results_io import read_metrics_json
from .io_utils import (
    MARKER,
    atomic_write_text,
    check_inputs_outside,
    check_output_folder,
    inside,
    is_results_folder,
    parse_frame_range,
    read_toml,
    recover_leftovers,
)
from .runner import mostly_flagged, run_sequence

CELL_FILE = "batch.json"  # written into a cell's folder after its run: the resume record
STATUSES = ("ok", "failed", "skipped", "cancelled")
TRAJECTORIES = ("vo", "snaps", "isam2", "batch")
# Environment variables that size BLAS / OpenMP thread pools (read when the library loads).
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
CANCEL_GRACE_S = 10.0  # after Ctrl-C: how long cancelled tasks may take to clean up before they are killed
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20  # a cell returns a small dict; Ray's default takes 30 % of RAM

# Run options a plan (top level or a variant) may give: key -> (config key it sets, type).
RUN_OPTIONS: dict[str, tuple[str | None, Any]] = {
    "frames": (None, str),
    "refine": ("graph.refine", RefineMode),
    "loops": ("loops", LoopMode),
    "map": ("map.enabled", bool),
    "mode": ("frontend.mode", FrontendMode),
    "map_all": ("map.per_trajectory", bool),
}
TOP_ONLY = ("sequences", "variants", "config", "cpus_per_task")
CONFIG_SECTIONS = ("frontend", "loop", "graph", "map")
READER_KEYS = ("left_topic", "right_topic", "calib")  # a sequence table's reader options, as `run` takes them
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+=,-]*$")


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (sequence, variant) run of a plan: everything its task needs."""

    sequence: str  # folder name under DIR
    variant: str  # folder name under DIR/<sequence>
    seq_path: str  # absolute
    gt: str | None  # absolute ground-truth file, None when the sequence has none
    frames: str | None
    cfg: Config
    config_hash: str
    reader: tuple[tuple[str, str], ...] = ()  # reader options: left_topic, right_topic, calib

    def open(self):
        """The dataset, read as ``run`` reads it."""
        return open_dataset(self.seq_path, frames=self.frames, gt=self.gt, **dict(self.reader))

    def folder(self, out_dir: str | Path) -> Path:
        return Path(out_dir) / self.sequence / self.variant


@dataclasses.dataclass
class Plan:
    source: str
    cells: list[Cell]
    cpus_per_task: float = 1.0


# ---------------------------------------------------------------- plan parsing
def load_plan(path: str | Path) -> Plan:
    """Read and check a plan file (see the module docstring); a one-line error names it."""
    path = Path(path)
    data = read_toml(path, "plan")
    return plan_from_dict(data, source=str(path), base_dir=path.parent)


def plan_from_dict(data: dict[str, Any], source: str = "plan", base_dir: str | Path = ".") -> Plan:
    """Check a plan given as a dict (what a plan file holds) and expand it into cells.

    Experiments build plans this way in memory. ``base_dir``: where relative paths start."""
    base = Path(base_dir)
    allowed = (*TOP_ONLY, *RUN_OPTIONS)
    for key in data:
        if key not in allowed:
            hint = " (config overrides go under [variants.NAME])" if key in CONFIG_SECTIONS else ""
            raise SnapsGraphError(f"{source}: unknown key '{key}'{hint}; a plan has {', '.join(allowed)}")
    cpus = data.get("cpus_per_task", 1)
    if isinstance(cpus, bool) or not isinstance(cpus, (int, float)) or not (0 < cpus <= 1024) or not math.isfinite(cpus):
        raise SnapsGraphError(f"{source}: cpus_per_task must be a number in (0, 1024], got {cpus!r}")

    base_cfg = Config()
    if "config" in data:
        if not isinstance(data["config"], str):
            raise SnapsGraphError(f"{source}: config must be a path (string), got {data['config']!r}")
        try:
            base_cfg = Config.load(_resolve(base, data["config"]))
        except SnapsGraphError as exc:
            raise SnapsGraphError(f"{source}: config: {exc}") from None
    top = _run_options(data, source, "")

    variants = data.get("variants", {})
    if not isinstance(variants, dict):
        raise SnapsGraphError(f"{source}: variants must be tables [variants.NAME]")
    if not variants:
        variants = {"default": {}}
    resolved: dict[str, tuple[Config, str | None]] = {}
    for name, body in variants.items():
        where = f"variants.{name}"
        _check_name(name, source, where)
        if not isinstance(body, dict):
            raise SnapsGraphError(f"{source}: [{where}] must be a table")
        resolved[name] = _variant_config(base_cfg, top, body, source, where)

    seqs = _sequences(data, source, base)
    cells: list[Cell] = []
    checked: dict[tuple[str, str | None], str | None] = {}  # (sequence, frames) -> its ground-truth file
    digests: dict[str, str] = {}
    for s_name, s_path, s_gt, reader in seqs:
        for v_name, (cfg, frames) in resolved.items():
            seq_key = (s_name, frames)
            if seq_key not in checked:
                checked[seq_key] = _check_sequence(s_name, s_path, s_gt, frames, reader, source)
            gt = checked[seq_key]
            extra = "".join(f";{k}={v}" for k, v in reader)
            if s_name not in digests:
                digests[s_name] = inputs_digest([s_path, gt, *(v for k, v in reader if k == "calib")])
            key = config_hash(cfg, s_path + extra, frames, gt, digests[s_name])
            cells.append(Cell(s_name, v_name, s_path, gt, frames, cfg, key, reader))
    return Plan(source, cells, float(cpus))


def _check_sequence(name: str, path: str, gt: str | None, frames: str | None, reader: tuple, source: str) -> str | None:
    """Open a sequence as its cells will (calibration, images, frame range, ground truth); returns
    its ground-truth file (absolute) or None."""
    try:
        seq = open_dataset(path, frames=frames, gt=gt, **dict(reader))
    except SnapsGraphError as exc:
        raise SnapsGraphError(f"{source}: sequence '{name}': {exc}") from None
    try:
        found = getattr(seq, "gt_path", None) or (gt if seq.gt_poses is not None else None)
        return str(Path(found).absolute()) if found is not None else None
    finally:
        close = getattr(seq, "close", None)
        if close is not None:
            close()


def _resolve(base: Path, path: str) -> Path:
    p = Path(path).expanduser()
    return (p if p.is_absolute() else base / p).absolute()


def _check_name(name: Any, source: str, where: str) -> None:
    if not isinstance(name, str) or not _NAME.match(name):
        raise SnapsGraphError(
            f"{source}: {where}: name {name!r} must start with a letter or digit and hold only letters, digits and . _ + = , -"
        )


def _run_options(table: dict[str, Any], source: str, prefix: str) -> dict[str, Any]:
    """The run options of a plan table, each checked (``prefix``: "variants.NAME." or "")."""
    out: dict[str, Any] = {}
    for key, (_, typ) in RUN_OPTIONS.items():
        if key not in table:
            continue
        value, where = table[key], f"{source}: {prefix}{key}"
        if key == "map" and prefix and isinstance(value, dict):
            continue  # in a variant, map = { ... } is the [map] config section
        allowed = choices(typ)
        if allowed is not None:
            if not isinstance(value, str) or value not in allowed:
                raise SnapsGraphError(f"{where} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
        elif typ is bool:
            if not isinstance(value, bool):
                raise SnapsGraphError(f"{where}: expected true/false, got {value!r}")
        elif key == "frames":
            if not isinstance(value, str):
                raise SnapsGraphError(f'{where}: expected a frame range "A:B" (a string), got {value!r}')
            try:
                parse_frame_range(value)
            except SnapsGraphError as exc:
                raise SnapsGraphError(f"{where}: {exc}") from None
        out[key] = value
    return out


def _variant_config(
    base: Config, top: dict[str, Any], body: dict[str, Any], source: str, where: str
) -> tuple[Config, str | None]:
    """The checked configuration of one variant and its frame range.

    Precedence, lowest first: the plan's ``config`` file, the plan's run options, the variant's
    config sections, the variant's run options (as on the command line, an option beats the
    config file)."""
    for key in body:
        if key not in (*CONFIG_SECTIONS, *RUN_OPTIONS):
            raise SnapsGraphError(
                f"{source}: {where}: unknown key '{key}'; a variant has the config sections "
                f"{', '.join(CONFIG_SECTIONS)} and the run options {', '.join(RUN_OPTIONS)}"
            )
    own = _run_options(body, source, f"{where}.")
    merged = base.to_dict()
    _apply_options(merged, top)
    for section in CONFIG_SECTIONS:
        if section in body and not (section == "map" and isinstance(body[section], bool)):  # map = true: the run option
            if not isinstance(body[section], dict):
                raise SnapsGraphError(f"{source}: {where}.{section} must be a table, e.g. {section} = {{ key = value }}")
            for k, v in body[section].items():
                if k not in merged[section]:
                    raise SnapsGraphError(f"{source}: {where}: unknown key '{section}.{k}'")
                merged[section][k] = v
    _apply_options(merged, own)
    cfg = Config.from_dict(merged, source=f"{source}: {where}")
    return cfg, own.get("frames", top.get("frames"))


def _apply_options(merged: dict[str, Any], options: dict[str, Any]) -> None:
    for key, value in options.items():
        target = RUN_OPTIONS[key][0]
        if target is None:
            continue
        section, _, field = target.rpartition(".")
        (merged[section] if section else merged)[field] = value


def _sequences(data: dict[str, Any], source: str, base: Path) -> list[tuple[str, str, str | None, tuple]]:
    """(name, absolute path, ground-truth file or None, reader options) per plan sequence; names unique."""
    seqs = data.get("sequences")
    if not isinstance(seqs, list) or not seqs:
        raise SnapsGraphError(f"{source}: sequences must be a non-empty list of sequence folders")
    out: list[tuple[str, str, str | None, tuple]] = []
    for i, entry in enumerate(seqs):
        where = f"sequences[{i}]"
        path: Any
        name: Any
        gt: Any = None
        reader: list[tuple[str, str]] = []
        if isinstance(entry, str):
            path, name = entry, None
        elif isinstance(entry, dict):
            unknown = set(entry) - {"path", "name", "gt", *READER_KEYS}
            if unknown:
                raise SnapsGraphError(
                    f"{source}: {where}: unknown key '{sorted(unknown)[0]}' (a sequence has path, name, gt, {', '.join(READER_KEYS)})"
                )
            path, name, gt = entry.get("path"), entry.get("name"), entry.get("gt")
            for key in ("path", "gt", *READER_KEYS):
                if entry.get(key) is not None and not isinstance(entry[key], str):
                    raise SnapsGraphError(f"{source}: {where}.{key}: expected a string, got {entry[key]!r}")
            if path is None:
                raise SnapsGraphError(f'{source}: {where}: a sequence table needs path = "..."')
            for key in READER_KEYS:
                if entry.get(key) is not None:
                    reader.append((key, str(_resolve(base, entry[key])) if key == "calib" else entry[key]))
        else:
            raise SnapsGraphError(f"{source}: {where}: expected a folder or a table {{ path = ..., name = ... }}, got {entry!r}")
        if path.startswith("live:"):
            raise SnapsGraphError(
                f"{source}: {where}: a live device cannot be a batch cell (it can be neither repeated nor resumed)"
            )
        full = _resolve(base, path)
        if name is None:  # the folder's name (a EuRoC mav0/ folder: its parent's; a bag file: its stem)
            name = full.parent.name if full.name == "mav0" else (full.stem if full.is_file() else full.name)
        _check_name(name, source, where)
        if any(name == o[0] for o in out):
            raise SnapsGraphError(
                f'{source}: {where}: two sequences are named \'{name}\' (their folder); give one a name: {{ path = "{path}", name = "..." }}'
            )
        out.append((name, str(full), str(_resolve(base, gt)) if gt is not None else None, tuple(reader)))
    return out


def config_hash(cfg: Config, seq_path: str, frames: str | None, gt: str | None, inputs: str = "") -> str:
    """What decides a run's output: the full configuration, the sequence, the frames, the ground
    truth, the inputs' content (``inputs_digest``) and the code (version and commit)."""
    text = json.dumps(
        {
            "config": cfg.dumps(),
            "sequence": seq_path,
            "frames": frames or "",
            "gt": gt or "",
            "inputs": inputs,
            "code": f"{__version__} {git_commit()}",
        },
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


DIGEST_CONTENT_BYTES = 16 * 2**20  # files up to this size are hashed whole (calibration, times, ground truth)


def inputs_digest(paths) -> str:
    """A digest of every file under ``paths`` (files or folders; None skipped): each file's
    relative name, size and modification time, and the content of the small ones. A changed
    calibration, ground truth, time or image gives another digest, so a resumed batch re-runs."""
    h = hashlib.sha256()
    for given in paths:
        if given is None:
            continue
        root = Path(given)
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for f in files:
            st = f.stat()
            h.update(f"{f.relative_to(root) if f != root else f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
            if st.st_size <= DIGEST_CONTENT_BYTES and f.suffix.lower() not in (".png", ".jpg", ".jpeg", ".pgm"):
                h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()[:16]


# ---------------------------------------------------------------- one cell (a Ray task)
def completed(cell: Cell, out_dir: str | Path) -> dict | None:
    """The record of a finished run of ``cell`` with the same config hash, else None."""
    folder = cell.folder(out_dir)
    if not (folder / "metrics.json").is_file():
        return None
    try:
        rec = json.loads((folder / CELL_FILE).read_text())
        metrics = read_metrics_json(folder / "metrics.json")
    except (OSError, ValueError, SnapsGraphError):
        return None
    if not isinstance(rec, dict) or rec.get("config_hash") != cell.config_hash:
        return None
    files = rec.get("files")
    if not isinstance(files, dict) or not files:
        return None
    for name, size in files.items():  # the folder whole, as the run left it
        f = folder / name
        if not f.is_file() or f.stat().st_size != size:
            return None
    rec.pop("files", None)
    rec.update(status="skipped", metrics=_metrics_digest(metrics))
    return rec


def run_cell(cell: Cell, out_dir: str, threads: int) -> dict:
    """Run one cell into its folder (a Ray task's body; also callable without Ray).

    Pins OpenCV's and BLAS's thread pools to ``threads`` (the CPUs the task was given: Ray sets
    OMP_NUM_THREADS for its workers; threadpoolctl limits the BLAS libraries already loaded;
    cv2.setNumThreads sizes OpenCV's pool; the other variables serve libraries loaded later). Never
    raises for a failed run: the returned record says ``failed`` with a one-line reason."""
    t0 = time.perf_counter()
    rec: dict[str, Any] = {
        "sequence": cell.sequence,
        "variant": cell.variant,
        "node": _node_id(),
        "threads": threads,
        "version": __version__,
        "commit": git_commit(),
        "config_hash": cell.config_hash,
        "status": "failed",
        "reason": "",
    }
    folder = cell.folder(out_dir)
    set_malloc_thresholds()  # a worker process runs the pipeline as the CLI does
    try:
        _remove_stale_temp(folder)
        seq = cell.open()
        try:
            with pinned_threads(threads):
                _, metrics = run_sequence(seq, folder, cell.cfg, overwrite=True)
        finally:
            if hasattr(seq, "close"):
                seq.close()
        rec["wall_s"] = round(time.perf_counter() - t0, 3)
        rec["status"] = "ok"
        if mostly_flagged(metrics):
            rec["reason"] = f"warning: the front end flagged {metrics['flagged_frames']} of {metrics['frames']} frames"
        files = {p.name: p.stat().st_size for p in sorted(folder.iterdir()) if p.is_file() and p.name != CELL_FILE}
        atomic_write_text(folder / CELL_FILE, json.dumps(rec | {"files": files}, indent=2) + "\n")
        rec["metrics"] = _metrics_digest(metrics)
    except SnapsGraphError as exc:
        rec["reason"] = _one_line(str(exc))
    except Exception as exc:  # a cell's bug must not stop the batch; its reason goes into the summary
        rec["reason"] = _one_line(f"{type(exc).__name__}: {exc}")
    rec.setdefault("wall_s", round(time.perf_counter() - t0, 3))
    return rec


@contextlib.contextmanager
def pinned_threads(n: int) -> Iterator[None]:
    """OpenCV's pool, the BLAS pools already loaded (threadpoolctl) and, for libraries loaded
    later, the BLAS/OpenMP variables, all at ``n`` threads; restored afterwards (a caller
    running a cell in its own process keeps its settings)."""
    import cv2
    from threadpoolctl import threadpool_limits

    old_cv, old_env = cv2.getNumThreads(), {v: os.environ.get(v) for v in THREAD_ENV}
    cv2.setNumThreads(n)
    os.environ.update({v: str(n) for v in THREAD_ENV})
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        cv2.setNumThreads(old_cv)
        for var, value in old_env.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def _remove_stale_temp(folder: Path) -> None:
    """Temporary siblings left by a killed earlier attempt (``.NAME.tmp-PID``, ``.NAME.old-PID``).
    The batch lock makes this task the only writer of ``folder``, so any other process's are stale."""
    for note in recover_leftovers(folder, any_pid=True):
        print(f"note: {note}", file=sys.stderr)


def _node_id() -> str:
    try:
        import ray

        if ray.is_initialized():
            return ray.get_runtime_context().get_node_id()
    except ImportError:
        pass
    return ""


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the package source this process runs ("" outside a git checkout), with
    ``-dirty`` when tracked files differ from it."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            # --match of no tag: always the commit hash, never a tag name
            ["git", "-C", str(here), "describe", "--always", "--dirty", "--abbrev=12", "--match=NO-TAGS"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def _metrics_digest(metrics: dict) -> dict:
    out: dict[str, Any] = {k: metrics.get(k) for k in ("frames", "flagged_frames", "loops")}
    for name, m in (metrics.get("trajectories") or {}).items():
        out[name] = {k: m.get(k) for k in ("mean_deviation", "ate_rmse", "t_rel")}
    return out


def _one_line(text: str) -> str:
    line = text.strip().splitlines()[0] if text.strip() else "unknown error"
    return line[:300]


# ---------------------------------------------------------------- the driver
def run_batch(
    plan: Plan,
    out_dir: str | Path,
    *,
    address: str | None = None,
    max_parallel: int | None = None,
    progress: bool = True,
    ray_init: dict[str, Any] | None = None,
) -> list[dict]:
    """Run a plan's cells on Ray into ``out_dir``; returns one record per cell (plan order) and
    writes ``summary.csv`` / ``summary.md``.

    Cells already complete with the same config hash are skipped. Without ``address`` (and no
    Ray already initialised in this process) a local Ray instance bound to 127.0.0.1 is started
    and stopped again; with one, the batch joins that cluster. ``max_parallel``: at most this many
    cells in flight. On Ctrl-C (or any error) the running tasks are cancelled, the summary is
    written with the unfinished cells as ``cancelled``, and the exception propagates."""
    if max_parallel is not None and max_parallel < 1:
        raise SnapsGraphError(f"--max-parallel must be at least 1, got {max_parallel}")
    check_cell_folders(plan, out_dir)
    if address:
        _check_reachable(address)  # before anything is written
    elif not ray_init and plan.cpus_per_task > (os.cpu_count() or 1):
        raise SnapsGraphError(
            f"{plan.source}: cpus_per_task = {plan.cpus_per_task:g}, but this machine has {os.cpu_count()} CPUs (no cell could start)"
        )
    out = _prepare_out(out_dir)
    t0 = time.perf_counter()
    with _lock(out):
        records: dict[tuple[str, str], dict] = {}
        todo: list[Cell] = []
        for cell in plan.cells:
            done = completed(cell, out)
            if done is not None:
                records[(cell.sequence, cell.variant)] = done
            else:
                todo.append(cell)
        with _sigint_flag() as interrupted, _ray_session(address, ray_init, bool(todo)) as ray:
            # From here on the summary is written whatever happens (Ctrl-C included).
            bar = _bar(len(plan.cells), len(plan.cells) - len(todo), progress)
            try:
                if todo:
                    _run_tasks(ray, plan, todo, out, records, bar, max_parallel, progress, interrupted)
            finally:
                bar.close()
                rows = [records.get((c.sequence, c.variant)) or _unfinished(c) for c in plan.cells]
                write_summary(out, rows, wall_s=time.perf_counter() - t0)
    return rows


def check_cell_folders(plan: Plan, out_dir: str | Path) -> None:
    """No cell folder is or holds an input, nor lies inside an input sequence folder (a variant
    named like a sequence's subfolder, ``--out`` on the folder holding the data)."""
    for cell in plan.cells:
        folder = cell.folder(out_dir)
        inputs = [("sequence", cell.seq_path), ("ground truth", cell.gt), *((k, v) for k, v in cell.reader if k == "calib")]
        try:
            check_inputs_outside(folder, inputs)
        except SnapsGraphError as exc:
            raise SnapsGraphError(f"{plan.source}: cell {cell.sequence}/{cell.variant}: {exc}") from None
        for role, given in inputs:
            if given is not None and Path(given).is_dir() and inside(folder, given):
                raise SnapsGraphError(
                    f"{plan.source}: cell {cell.sequence}/{cell.variant}: its folder {folder} lies inside the input {role} {given}; choose another --out"
                )


def _prepare_out(out_dir: str | Path) -> Path:
    """The batch folder: new, empty, or one a batch wrote (MARKER); never a user's folder whose
    summary.csv / summary.md a batch would replace."""
    out = check_output_folder(out_dir, reuse=True)
    if out.is_dir() and not is_results_folder(out):
        raise SnapsGraphError(f"{out}: not a folder this tool wrote (no {MARKER} file); choose a new or empty --out for a batch")
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not (out / MARKER).is_file():
            atomic_write_text(out / MARKER, json.dumps({"snaps_graph": __version__, "batch": True, "files": None}) + "\n")
    except OSError as exc:
        raise SnapsGraphError(f"{out}: cannot create the folder ({exc.strerror or exc})") from None
    return out


@contextlib.contextmanager
def _lock(out: Path) -> Iterator[None]:
    """One batch at a time per output folder (two would race on the same cells). The lock file
    is removed at the end, by its holder; a lock taken on a file removed meanwhile is retaken."""
    path = out / ".batch.lock"
    for _ in range(3):
        fh = open(path, "w")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            raise SnapsGraphError(f"{out}: another batch is running into this folder") from None
        try:
            same = os.fstat(fh.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        fh.close()
    else:
        raise SnapsGraphError(f"{out}: another batch is running into this folder")
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()


def _bar(total: int, initial: int, progress: bool):
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        desc="cells",
        unit="cell",
        file=sys.stderr,
        dynamic_ncols=True,
        disable=None if progress else True,
    )


def _unfinished(cell: Cell) -> dict:
    return {
        "sequence": cell.sequence,
        "variant": cell.variant,
        "status": "cancelled",
        "reason": "not finished: the batch was stopped",
        "config_hash": cell.config_hash,
    }


@contextlib.contextmanager
def _sigint_flag() -> Iterator[threading.Event]:
    """Ctrl-C sets a flag that the driver's loop checks, instead of raising wherever the main
    thread is: an exception raised inside Ray's own calls comes out as a SystemError."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    old = signal.signal(signal.SIGINT, lambda *_: flag.set())
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def _ray_session(address: str | None, ray_init: dict[str, Any] | None, needed: bool) -> Iterator[Any]:
    """Ray, started (or joined) for the batch and stopped (or left) after it; a Ray this
    process had already initialised is used as it is. Yields None when no cell needs running."""
    if not needed:
        yield None
        return
    ray = _import_ray(local=not address)
    started_here = not ray.is_initialized()
    if started_here:
        _start_ray(ray, address, ray_init)
    try:
        yield ray
    finally:
        if started_here:
            ray.shutdown()


def _run_tasks(ray, plan, todo, out, records, bar, max_parallel, progress, interrupted) -> None:
    biggest = max((n.get("Resources", {}).get("CPU", 0) for n in ray.nodes() if n.get("Alive")), default=0)
    if plan.cpus_per_task > biggest:  # Ray would wait for such a node for ever
        raise SnapsGraphError(
            f"{plan.source}: cpus_per_task = {plan.cpus_per_task:g}, but no Ray node has more than {biggest:g} CPUs"
        )
    threads = max(1, math.ceil(plan.cpus_per_task))
    task = ray.remote(run_cell).options(
        num_cpus=plan.cpus_per_task,
        max_retries=1,  # a lost node's cell is tried once more; a failing run is recorded, not retried
        scheduling_strategy="SPREAD",  # cells are CPU-heavy: over the nodes rather than packed onto one
    )  # no runtime_env for the thread variables: it would bar Ray's pre-started workers (measured +6 s)
    queue = deque(todo)
    limit = max_parallel or len(todo)
    pending: dict[Any, Cell] = {}
    failed = 0
    try:
        while queue or pending:
            if interrupted.is_set():
                raise KeyboardInterrupt
            while queue and len(pending) < limit:
                cell = queue.popleft()
                pending[task.remote(cell, str(out), threads)] = cell
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            for ref in ready:
                cell = pending.pop(ref)
                rec = _result(ray, ref, cell)
                records[(cell.sequence, cell.variant)] = rec
                failed += rec["status"] == "failed"
                bar.update(1)
                if failed:
                    bar.set_postfix(failed=failed, refresh=False)
                if progress:
                    bar.write(_cell_line(rec), file=sys.stderr)
    except BaseException:
        _cancel(ray, pending, records)
        raise


def _result(ray, ref, cell: Cell) -> dict:
    try:
        return ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        return {**_unfinished(cell), "reason": "cancelled"}
    except ray.exceptions.RayError as exc:  # the worker or its node died: the run did not finish
        return {
            "sequence": cell.sequence,
            "variant": cell.variant,
            "status": "failed",
            "reason": _one_line(f"{type(exc).__name__}: {exc}"),
            "config_hash": cell.config_hash,
        }


def _cancel(ray, pending: dict, records: dict) -> None:
    """Cancel the running tasks (KeyboardInterrupt inside them: the runner deletes its temporary
    folder); after CANCEL_GRACE_S, kill what still runs. Cells that finished meanwhile count."""
    for ref in pending:
        ray.cancel(ref)
    deadline = time.monotonic() + CANCEL_GRACE_S
    left = dict(pending)
    while left and time.monotonic() < deadline:
        ready, _ = ray.wait(list(left), num_returns=len(left), timeout=0.5)
        for ref in ready:
            cell = left.pop(ref)
            rec = _result(ray, ref, cell)
            if rec["status"] == "ok":
                records[(cell.sequence, cell.variant)] = rec
    for ref in left:
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=True)


def _import_ray(local: bool = False):
    """Ray, imported with no usage report to Ray's servers; ``local``: every address Ray uses is
    127.0.0.1 (read when Ray is imported; a multi-node cluster needs the real address instead)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if local:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    try:
        import ray
    except ImportError:
        raise SnapsGraphError("batch needs Ray: pip install 'snaps_graph[ray]'") from None
    return ray


def _start_ray(ray, address: str | None, extra: dict[str, Any] | None) -> None:
    kw: dict[str, Any] = {"log_to_driver": False, "logging_level": "WARNING"}
    if address:
        _check_reachable(address)
        kw["address"] = address
    else:  # a private instance on this machine, reachable from this machine only
        kw.update(address="local", include_dashboard=False, object_store_memory=LOCAL_OBJECT_STORE_BYTES)
    kw.update(extra or {})
    try:
        ray.init(**kw)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"--address {address}" if address else "local Ray"
        raise SnapsGraphError(f"{where}: cannot start or join a Ray cluster ({_one_line(str(exc))})") from None


def _check_reachable(address: str) -> None:
    """A HOST:PORT that nothing answers on is a one-line error at once (ray.init would retry for
    minutes). Other forms ("auto", "ray://...") are left to Ray."""
    import socket

    m = re.fullmatch(r"([\w.-]+):(\d+)", address)
    if not m:
        return
    try:
        with socket.create_connection((m.group(1), int(m.group(2))), timeout=5) as sock:
            # Ray's head speaks gRPC (HTTP/2): its answer to the client preface starts with a SETTINGS frame
            sock.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))
            head = b""
            while len(head) < 9:
                chunk = sock.recv(9 - len(head))
                if not chunk:
                    break
                head += chunk
    except OSError as exc:
        raise SnapsGraphError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc})") from None
    if len(head) < 9 or head[3] != 4:
        raise SnapsGraphError(f"--address {address}: something answers there, but not a Ray cluster (no gRPC server)")


def _cell_line(rec: dict) -> str:
    node = (rec.get("node") or "?")[:8]
    text = f"{rec['sequence']}/{rec['variant']}: {rec['status']} on node {node} in {rec.get('wall_s', 0):.1f} s"
    return text + (f" ({rec['reason']})" if rec.get("reason") else "")


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
    atomic_write_text(out / "summary.csv", buf.getvalue())

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
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")


__all__ = [
    "CELL_FILE",
    "Cell",
    "Plan",
    "completed",
    "config_hash",
    "load_plan",
    "plan_from_dict",
    "run_batch",
    "run_cell",
    "write_summary",
]
