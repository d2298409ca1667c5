"""Running a plan: one cell per Ray task (``run_cell``, the ordinary runner), the driver
(``run_batch``: resume, lock, progress, Ctrl-C) and Ray's start-up."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .. import __version__
from .._malloc import set_malloc_thresholds
from ..errors import SnapsGraphError
from ..evaluation.results_io import read_metrics_json
from ..io_utils import (
    MARKER,
    atomic_write_text,
    check_inputs_outside,
    check_output_folder,
    inside,
    is_results_folder,
    recover_leftovers,
)
from ..locks import record_signal, writer_lock
from ..runner import mostly_flagged, run_sequence
from .plan import Cell, Plan, git_commit
from .summary import SUMMARY_FILES, write_summary

CELL_FILE = "batch.json"  # written into a cell's folder after its run: the resume record
# Environment variables that size BLAS / OpenMP thread pools (read when the library loads).
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
CANCEL_GRACE_S = 10.0  # after Ctrl-C: how long cancelled tasks may take to clean up before they are killed
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20  # a cell returns a small dict; Ray's default takes 30 % of RAM


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
    """Run one cell into its folder (a Ray task's body; also callable without Ray). Limits OpenCV's
    and the BLAS libraries' threads to ``threads``, the CPUs the task was given. Never raises for a
    failed run: the returned record says ``failed`` with a one-line reason.
    """
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
        with writer_lock(folder), _signals_recorded(folder):  # held through the run: others' leftovers are stale
            _remove_stale_temp(folder)
            seq = cell.open()
            try:
                with pinned_threads(threads):
                    _, metrics = run_sequence(seq, folder, cell.cfg, overwrite=True)
            finally:
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


# Signals that end a worker and that it can catch: written into the cell's lock before it dies,
# for the driver's report (SIGKILL, the out-of-memory killer's, cannot be caught).
RECORDED_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2)


@contextlib.contextmanager
def _signals_recorded(folder: Path) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def record_and_die(signum, frame) -> None:
        record_signal(folder, signum)
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    old = {sig: signal.signal(sig, record_and_die) for sig in RECORDED_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _remove_stale_temp(folder: Path) -> None:
    """Temporary siblings left by a killed earlier attempt (``.NAME.tmp-PID``, ``.NAME.old-PID``).
    The cell's lock makes this task the only writer of ``folder``, so any other process's are stale."""
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
    """Run a plan's cells on Ray into ``out_dir``; returns one record per cell (plan order) and writes
    ``summary.csv`` / ``summary.md``. Cells complete with the same config hash are skipped. Without
    ``address`` (and no Ray already running here) a local Ray bound to 127.0.0.1 is started and
    stopped; ``max_parallel`` caps the cells in flight. On Ctrl-C (or any error) the running tasks
    are cancelled, the summary marks the unfinished cells ``cancelled``, and the exception propagates.
    """
    if max_parallel is not None and max_parallel < 1:
        raise SnapsGraphError(f"--max-parallel must be at least 1, got {max_parallel}")
    check_cell_folders(plan, out_dir)
    if address:
        _check_reachable(address)  # before anything is written
    elif not ray_init and plan.cpus_per_task > (os.cpu_count() or 1):
        raise SnapsGraphError(
            f"{plan.source}: cpus_per_task = {plan.cpus_per_task:g}, but this machine has {os.cpu_count()} CPUs (no cell could start)"
        )
    out = _check_out(out_dir)
    t0 = time.perf_counter()
    with writer_lock(out):  # one batch per folder: two would race on the same cells
        out = _check_out(out_dir)
        records: dict[tuple[str, str], dict] = {}
        todo: list[Cell] = []
        for cell in plan.cells:
            done = completed(cell, out)
            if done is not None:
                records[(cell.sequence, cell.variant)] = done
            else:
                todo.append(cell)
        with _stop_flag() as interrupted, _ray_session(address, ray_init, bool(todo)) as ray:
            _make_out(out)  # after Ray started or joined: a refused cluster leaves no folder
            _flag_on(signal.SIGTERM, interrupted)  # Ray's core took SIGTERM over when it started
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
        if cell.sequence in SUMMARY_FILES:
            raise SnapsGraphError(
                f"{plan.source}: cell {cell.sequence}/{cell.variant}: a sequence named {cell.sequence} would make the batch's {cell.sequence} a folder; name it otherwise"
            )
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


def _check_out(out_dir: str | Path) -> Path:
    """The batch folder: new, empty, or one a batch wrote (MARKER); never a user's folder whose
    summary.csv / summary.md a batch would replace."""
    out = check_output_folder(out_dir, reuse=True)
    if out.is_dir() and not is_results_folder(out):
        raise SnapsGraphError(f"{out}: not a folder this tool wrote (no {MARKER} file); choose a new or empty --out for a batch")
    for name in SUMMARY_FILES:
        if (out / name).is_dir() or (out / name).is_symlink():
            raise SnapsGraphError(f"{out / name}: is a folder or a link, where the batch writes its summary; move it away")
    return out


def _make_out(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not (out / MARKER).is_file():
            atomic_write_text(out / MARKER, json.dumps({"snaps_graph": __version__, "batch": True, "files": None}) + "\n")
    except OSError as exc:
        raise SnapsGraphError(f"{out}: cannot create the folder ({exc.strerror or exc})") from None


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
def _stop_flag() -> Iterator[threading.Event]:
    """Ctrl-C (or SIGTERM, SIGHUP) sets a flag that the driver's loop checks, instead of raising wherever the main
    thread is: an exception raised inside Ray's own calls comes out as a SystemError."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    old = {sig: _flag_on(sig, flag) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        yield flag
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _flag_on(sig: int, flag: threading.Event) -> Any:
    """Make signal ``sig`` set ``flag`` (main thread only); returns the handler it replaced."""
    if threading.current_thread() is not threading.main_thread():
        return signal.getsignal(sig)
    return signal.signal(sig, lambda *_: flag.set())


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
                rec = _result(ray, ref, cell, out)
                records[(cell.sequence, cell.variant)] = rec
                failed += rec["status"] == "failed"
                bar.update(1)
                if failed:
                    bar.set_postfix(failed=failed, refresh=False)
                if progress:
                    bar.write(_cell_line(rec), file=sys.stderr)
    except BaseException:
        _cancel(ray, pending, records, out)
        raise


def _result(ray, ref, cell: Cell, out: Path) -> dict:
    try:
        return ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        return {**_unfinished(cell), "reason": "cancelled"}
    except ray.exceptions.RayError as exc:  # the worker or its node died: the run did not finish
        return {
            "sequence": cell.sequence,
            "variant": cell.variant,
            "status": "failed",
            "reason": _after_death(cell, out) or _one_line(f"{type(exc).__name__}: {exc}"),
            "config_hash": cell.config_hash,
        }


def _after_death(cell: Cell, out: Path) -> str:
    """The cell's worker died holding the cell's lock: what stopped it (the signal it recorded,
    else one it cannot catch), its unfinished folder removed. "" when no worker held the lock."""
    folder = cell.folder(out)
    dead: dict = {}
    try:
        with writer_lock(folder, create_parents=False, stale=dead.update):  # free: its holder is gone
            removed = [n for n in recover_leftovers(folder, any_pid=True) if "unfinished" in n]
    except SnapsGraphError:  # held: another attempt runs
        return ""
    if not dead:
        return ""
    how = (
        f"by {dead['signal']}"
        if dead.get("signal")
        else "by a signal it cannot catch (SIGKILL: kill -9, the out-of-memory killer) or a crash"
    )
    tail = "; its unfinished folder removed" if removed else ""
    return f"the worker (PID {dead.get('pid', '?')}) was killed {how} while running the cell{tail}"


def _cancel(ray, pending: dict, records: dict, out: Path) -> None:
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
            rec = _result(ray, ref, cell, out)
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
