"""One writer per output: a lock file ``.NAME.lock`` beside each results folder, batch folder,
recording or pose file a command writes (docs/run-contract.md, "One writer at a time").

The lock is ``flock`` on that file, held from before the first frame through the final rename
into place; a second writer is refused at once, naming the holder's PID and start time. The file
lies beside the output, not inside it, so the renames of the swap never move it. The kernel drops
the lock of a process that dies, so a lock file left by a killed run is free: the next writer
takes it and says so.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import SnapsGraphError

LOCK_KEY = "snaps_graph_lock"  # in every lock file this tool writes: any other file is left alone
HOLDER_WAIT_S = 1.0  # how long a refused writer waits for the holder to write its name


def lock_path(target: str | Path) -> Path:
    """The lock file of ``target``: ``.NAME.lock`` in the same folder."""
    full = Path(os.path.abspath(target))
    return full.parent / f".{full.name}.lock"


# target -> [open lock file descriptor, nesting depth]; one process takes a target's lock once
_HELD: dict[Path, list[int]] = {}


def record_signal(target: str | Path, signum: int) -> None:
    """Write into ``target``'s lock, held by this process, the signal that is ending it: the
    process that finds the lock stale (a batch's driver) can then say what stopped the writer."""
    held = _HELD.get(Path(os.path.abspath(target)))
    if held is not None:
        _write_record(held[0], signal=signal.Signals(signum).name)


@contextmanager
def writer_lock(
    target: str | Path, *, create_parents: bool = True, stale: Callable[[dict], None] | None = None
) -> Iterator[None]:
    """Hold ``target``'s lock for the block (nested uses in one process share it); a one-line
    SnapsGraphError naming the holder when another process holds it. Missing parent folders
    are created (``create_parents``; those still empty at the end are removed again) or, when
    not, there is nothing to lock and the block runs without it. A lock a killed writer left is
    taken over with a note, or handed to ``stale`` (its record: pid, started, signal)."""
    full = Path(os.path.abspath(target))
    if full in _HELD:
        _HELD[full][1] += 1
        try:
            yield
        finally:
            _HELD[full][1] -= 1
        return
    if not full.parent.is_dir() and not create_parents:
        yield
        return
    created = _make_parents(full.parent)
    try:
        fd = _acquire(full, stale)
    except BaseException:
        _remove_empty(created)
        raise
    _HELD[full] = [fd, 1]
    try:
        yield
    finally:
        del _HELD[full]
        _release(full, fd)
        _remove_empty(created)


def _acquire(full: Path, stale: Callable[[dict], None] | None) -> int:
    path = lock_path(full)
    for _ in range(5):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except FileNotFoundError:  # a parent folder another run had made, removed meanwhile
            _make_parents(full.parent)
            continue
        except OSError as exc:
            raise SnapsGraphError(f"{full}: cannot create the lock file {path.name} beside it ({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(fd)
            os.close(fd)
            raise SnapsGraphError(
                f"{full}: another run is writing it ({holder}); wait for it to end or choose another name"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # locked a file its holder removed as it finished: take the new one
            os.close(fd)
            continue
        previous = _read(fd)
        if previous is None:
            os.close(fd)
            raise SnapsGraphError(f"{path}: exists and is not a lock file this tool wrote; move it away")
        if previous and stale is not None:
            stale(previous)
        elif previous:
            print(
                f"note: {full}: cleared the lock left by {_describe(previous)}, a run killed before it finished",
                file=sys.stderr,
            )
        _write_record(fd)
        return fd
    raise SnapsGraphError(f"{full}: cannot take the lock {path.name}: other runs keep replacing it")


def _write_record(fd: int, **extra: str) -> None:
    record = {LOCK_KEY: 1, "pid": os.getpid(), "started": _process_start()} | extra
    data = json.dumps(record).encode() + b"\n"
    os.ftruncate(fd, 0)  # a refused writer reading meanwhile sees it empty and reads again
    os.pwrite(fd, data, 0)


def _release(full: Path, fd: int) -> None:
    path = lock_path(full)
    with contextlib.suppress(OSError):  # removed by its holder, before the lock is dropped
        if os.fstat(fd).st_ino == os.stat(path).st_ino:
            path.unlink()
    os.close(fd)


def _read(fd: int) -> dict | None:
    """The record in a lock file: {} when empty, None when it is not one of ours."""
    data = os.pread(fd, 4096, 0)
    if not data.strip():
        return {}
    try:
        rec = json.loads(data)
    except ValueError:
        return None
    return rec if isinstance(rec, dict) and LOCK_KEY in rec else None


def _holder(fd: int) -> str:
    """Who holds the lock, as its file says (the holder writes it just after taking the lock)."""
    deadline = time.monotonic() + HOLDER_WAIT_S
    while True:
        rec = _read(fd)
        if rec and _alive(rec.get("pid")) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    return _describe(rec) if rec else "a process that has not yet written its PID"


def _describe(rec: dict) -> str:
    started = rec.get("started")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)) if isinstance(started, (int, float)) else "?"
    return f"PID {rec.get('pid', '?')}, started {when}"


def _alive(pid: object) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _process_start() -> float:
    """This process's start time (seconds since the epoch): from /proc on Linux, else now."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines() if line.startswith("btime"))
        return round(boot + ticks / os.sysconf("SC_CLK_TCK"), 3)
    except (OSError, ValueError, IndexError, StopIteration):
        return round(time.time(), 3)


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; returns those created, outermost first."""
    missing = [p for p in (folder, *folder.parents) if not p.exists()][::-1]
    created = []
    for p in missing:
        try:
            p.mkdir()
            created.append(p)
        except FileExistsError:
            continue
        except OSError as exc:
            _remove_empty(created)
            raise SnapsGraphError(f"{p}: cannot create the folder ({exc.strerror or exc})") from None
    return created


def _remove_empty(created: list[Path]) -> None:
    for p in reversed(created):
        try:
            p.rmdir()
        except OSError:
            break  # holds something (the results): it and its parents stay
