"""Small file helpers: atomic writes and whole-or-absent output folders, so an interrupted run
never leaves a half-written file or a folder that looks complete; reading frames ahead on a
background thread (``prefetch``)."""

from __future__ import annotations

import contextlib
import fnmatch
import glob
import json
import os
import queue
import shutil
import signal
import sys
import tempfile
import threading
import tomllib
from collections.abc import Generator, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from .errors import SnapsGraphError
from .locks import writer_lock
from .paths import unreplaceable


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder and a rename."""
    atomic_write_bytes(path, text.encode())


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


@contextmanager
def atomic_output(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path in ``path``'s folder for a writer (ours, gtsam's, open3d's) to fill; on
    success it gets ordinary permissions and is renamed onto ``path``, on any error it is
    removed. ``suffix``: for writers that pick the format from the file name (open3d)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; results are ordinary files
        fault_step()
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once: os.umask can only be read by setting it, and setting it while another thread creates
# a file would give that file the wrong mode (outputs are written from worker threads).
_UMASK = _read_umask()


def _umask() -> int:
    return _UMASK


TOML_MAX_BYTES = 16 * 2**20  # a config or a plan is a few kB
TEXT_MAX_BYTES = 512 * 2**20  # the largest text input read (a long ground-truth csv is ~100 MB)


def read_text(path: str | Path, what: str, max_bytes: int = TEXT_MAX_BYTES) -> str:
    """A text file's content (a UTF-8 byte-order mark dropped); a one-line SnapsGraphError naming
    it when it is missing, a folder, larger than ``max_bytes``, unreadable or not text (NUL
    bytes, not UTF-8)."""
    path = Path(path)
    if path.is_dir():
        raise SnapsGraphError(f"{path}: is a folder, expected a {what} file")
    if not path.is_file():
        raise SnapsGraphError(f"{path}: {what} file not found")
    data = _read_capped(path, what, max_bytes)
    if b"\0" in data:
        raise SnapsGraphError(f"{path}: binary data, expected a text {what} file")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise SnapsGraphError(f"{path}: not a text (UTF-8) file, expected a {what} file") from None


MAX_IMAGE_PIXELS = 64 * 2**20  # 64 Mpixel: far above any stereo camera, far below a decoding bomb
# OpenCV's own limit for the formats whose header is not read here (read when cv2 first decodes).
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))


def check_image_file(path: str | Path) -> None:
    """Before decoding: a PNG's or JPEG's size from its header (a small file can decode to
    gigabytes), a JPEG's end marker (libjpeg fills a truncated file with grey and goes on) and
    a PNG's end chunk (libpng prints its own line about a truncated one). A one-line
    SnapsGraphError naming the file; other formats are left to the decoder."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(256 * 1024)
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 64))
            tail = fh.read()
    except OSError as exc:
        raise SnapsGraphError(f"{path}: cannot read the image ({exc.strerror or exc})") from None
    wh = None
    if head.startswith(b"\x89PNG\r\n\x1a\n") and len(head) >= 24:
        if b"IEND" not in tail:  # libpng would print its own line about it before ours
            raise SnapsGraphError(f"{path}: truncated PNG (no IEND chunk)")
        wh = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    elif head.startswith(b"\xff\xd8"):
        if b"\xff\xd9" not in tail:
            raise SnapsGraphError(f"{path}: truncated JPEG (no end marker)")
        wh = _jpeg_size(head)
    if wh is not None and wh[0] * wh[1] > MAX_IMAGE_PIXELS:
        raise SnapsGraphError(f"{path}: image {wh[0]}x{wh[1]} is larger than {MAX_IMAGE_PIXELS / 2**20:g} Mpixel")


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's first start-of-frame segment, None when not in ``data``."""
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(data[i + 5 : i + 7], "big")
        i += 2 + length
    return None


def _read_capped(path: Path, what: str, max_bytes: int) -> bytes:
    """At most ``max_bytes`` of a file (a larger one is refused before it is read)."""
    try:
        with open(path, "rb") as fh:
            if os.fstat(fh.fileno()).st_size > max_bytes:
                raise SnapsGraphError(f"{path}: larger than {max_bytes / 2**20:g} MiB, too large for a {what} file")
            data = fh.read(max_bytes + 1)  # never more, whatever the file (or a device) holds
    except OSError as exc:
        if isinstance(exc, (FileNotFoundError, IsADirectoryError)):
            raise
        raise SnapsGraphError(f"{path}: cannot read the {what} file ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise SnapsGraphError(f"{path}: larger than {max_bytes / 2**20:g} MiB, too large for a {what} file")
    return data


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file's tables; a one-line SnapsGraphError naming it when it is missing, a folder,
    unreadable, not UTF-8 text or malformed TOML. ``what`` names the file's role ("config")."""
    path = Path(path)
    try:
        return tomllib.loads(_read_capped(path, what, TOML_MAX_BYTES).decode("utf-8-sig"))
    except FileNotFoundError:
        raise SnapsGraphError(f"{path}: {what} file not found") from None
    except IsADirectoryError:
        raise SnapsGraphError(f"{path}: is a folder, not a {what} file") from None
    except OSError as exc:
        raise SnapsGraphError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise SnapsGraphError(f"{path}: not a text (UTF-8) file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SnapsGraphError(f"{path}: malformed TOML ({exc})") from None


# Written first into every folder ``output_folder`` makes: ``--overwrite`` replaces only a folder
# that holds it (or an empty one), so it can never delete a folder the tool did not write.
MARKER = ".snaps_graph_results"
# Test-only: kill the process (``os._exit``, as kill -9 would) at the Nth filesystem step of a
# results folder (``fault_step``); the fault-injection test checks the folder after each.
FAULT_ENV = "SNAPS_GRAPH_FAULT_AT"
_FAULT_COUNT = [0]
_COMMITTED: list[Path] = []  # results folders this process completed (a Ctrl-C after them says so)


def fault_step() -> None:
    """One write or rename of a results folder; exits at the step FAULT_ENV names (tests only)."""
    at = os.environ.get(FAULT_ENV)
    if not at:
        return
    _FAULT_COUNT[0] += 1
    if _FAULT_COUNT[0] == int(at):
        os._exit(137)


def committed_folders() -> list[Path]:
    """Results folders this process has completed (renamed into place) so far."""
    return list(_COMMITTED)


def is_results_folder(folder: str | Path) -> bool:
    """``folder`` is one this tool wrote (it holds MARKER) or is empty: ``--overwrite`` may replace it."""
    folder = Path(folder)
    try:
        return (folder / MARKER).is_file() or not any(folder.iterdir())
    except OSError:
        return False


# Files the tool's later commands add to a results folder (compare, loops, batch): its own too.
ADDED_LATER = ("report.md", "*.png", "batch.json")


def foreign_entries(folder: str | Path) -> list[str]:
    """What in a results folder this tool did not write: entries neither listed in its MARKER
    (the run's files) nor added by a later command (ADDED_LATER). ``--overwrite`` keeps them."""
    folder = Path(folder)
    try:
        listed = json.loads((folder / MARKER).read_text()).get("files") or []
    except (OSError, ValueError, AttributeError):
        listed = []
    own = {MARKER, *listed}
    return sorted(
        p.name for p in folder.iterdir() if p.name not in own and not any(fnmatch.fnmatch(p.name, pat) for pat in ADDED_LATER)
    )


def _write_marker(folder: Path, files: list[str] | None) -> None:
    (folder / MARKER).write_text(json.dumps({"snaps_graph": _version(), "files": files}) + "\n")


def _abs(path: str | Path) -> Path:
    return Path(os.path.abspath(path))


def check_output_folder(path: str | Path, overwrite: bool = False, reuse: bool = False) -> Path:
    """Refuse, with a one-line SnapsGraphError, an output folder a run could not replace whole:
    a path that is a file or lies under a file, a symbolic link, the current folder (or one
    holding it), a folder whose parent cannot be written, a non-empty folder without
    ``overwrite``, and with ``overwrite`` a non-empty folder this tool did not write (no MARKER)
    (``reuse``: any folder is fine, as a resumed batch wants). Leftovers of a killed earlier
    run are recovered first (``recover_leftovers``). Call it before any work; returns the path."""
    out = Path(path)
    full = _abs(out)
    if out.is_symlink():
        raise SnapsGraphError(f"{out}: is a symbolic link (to {os.readlink(out)}); pass the folder itself")
    if out.exists() and not out.is_dir():
        raise SnapsGraphError(f"{out}: exists and is not a folder")
    cwd = _abs(os.getcwd())
    if not reuse and (full == cwd or full in cwd.parents):
        raise SnapsGraphError(f"{out}: is the current folder (or holds it), which a run would replace whole; name a new folder")
    for parent in full.parents:
        if parent.exists():
            if not parent.is_dir():
                raise SnapsGraphError(f"{parent}: is a file, cannot create the folder {out} under it")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise SnapsGraphError(f"{parent}: not writable, cannot create {out}")
            break
    with writer_lock(full, create_parents=False):  # another live writer: refused here, at once
        _check_folder_unlocked(out, full, overwrite, reuse)
    return out


def _check_folder_unlocked(out: Path, full: Path, overwrite: bool, reuse: bool) -> None:
    for note in recover_leftovers(full):
        print(f"note: {note}", file=sys.stderr)
    why = unreplaceable(full) if out.is_dir() and not reuse else None  # found now, not after every frame
    if why:
        raise SnapsGraphError(f"{out}: {why}, so a run cannot replace it")
    if out.is_dir() and not reuse and any(out.iterdir()):
        if not overwrite:
            raise SnapsGraphError(f"{out}: folder exists and is not empty (use --overwrite to replace it)")
        if not is_results_folder(out):
            raise SnapsGraphError(
                f"{out}: not a folder this tool wrote (no {MARKER} file), so --overwrite will not delete it; "
                "choose another folder or empty it yourself"
            )
        foreign = foreign_entries(out)
        if foreign:
            shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            raise SnapsGraphError(
                f"{out}: holds {shown}, which this tool did not write; move it out first (--overwrite replaces the folder whole)"
            )


def inside(path: str | Path, folder: str | Path) -> bool:
    """``path`` is ``folder`` or lies under it (links resolved)."""
    p, f = Path(path).resolve(), Path(folder).resolve()
    return p == f or f in p.parents


def check_inputs_outside(out: str | Path, inputs: Iterable[tuple[str, str | Path | None]]) -> None:
    """No input (``(role, path)`` pairs; None skipped) is or lies inside the results folder
    ``out``, which a run replaces whole: one line naming both, before the first frame."""
    for role, given in inputs:
        if given is None or str(given).startswith("live:"):
            continue
        if inside(given, out):
            raise SnapsGraphError(f"{out}: --out would replace the input {role} {given}; choose another folder")


RRD_MAGIC = b"RRF2"  # the first bytes of a rerun recording


def check_recording_path(rrd: str | Path, out: str | Path) -> Path | None:
    """Check ``--rrd`` before the first frame: a ``.rrd`` name, not a folder, an existing file
    only when it is a rerun recording, not inside another results folder, a writable folder.
    Returns its path relative to ``out`` when it lies inside the results folder (it is then
    written with the results), else None."""
    rrd = Path(rrd)
    if rrd.is_dir():
        raise SnapsGraphError(f"{rrd}: --rrd names a folder; give a file name ending in .rrd")
    if rrd.suffix != ".rrd":
        raise SnapsGraphError(f"{rrd}: --rrd must name a .rrd file")
    if inside(rrd, out):
        return rrd.resolve().relative_to(Path(out).resolve())
    if rrd.exists():
        try:
            with open(rrd, "rb") as fh:
                head = fh.read(len(RRD_MAGIC))
        except OSError as exc:
            raise SnapsGraphError(f"{rrd}: cannot read ({exc.strerror or exc})") from None
        if head != RRD_MAGIC:
            raise SnapsGraphError(f"{rrd}: exists and is not a rerun recording; --rrd replaces only a recording")
    for parent in _abs(rrd).parents:
        if (parent / MARKER).is_file():
            raise SnapsGraphError(f"{rrd}: lies inside the results folder {parent} of another run")
    for parent in _abs(rrd).parents:
        if parent.exists():
            if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
                raise SnapsGraphError(f"{parent}: not a writable folder, cannot write the recording {rrd}")
            break
    with writer_lock(rrd, create_parents=False):  # another run recording there: refused at once
        for note in remove_stale_recordings(rrd):
            print(f"note: {note}", file=sys.stderr)
    return None


def remove_stale_recordings(rrd: str | Path) -> list[str]:
    """Delete the temporary ``.NAME.tmp-PID`` recordings beside ``rrd`` that a killed run left:
    only of processes no longer running, only files that are rerun recordings (or empty). Returns
    one note per file removed."""
    full = _abs(rrd)
    notes = []
    for p in sorted(full.parent.glob(f".{glob.escape(full.name)}.tmp-*")):
        pid = p.name.rsplit("-", 1)[1]
        if not (pid.isascii() and pid.isdigit()) or p.is_symlink() or not p.is_file() or _alive(int(pid)):
            continue
        try:
            with open(p, "rb") as fh:
                if fh.read(len(RRD_MAGIC)) not in (b"", RRD_MAGIC):
                    continue
            p.unlink()
        except OSError:
            continue
        notes.append(f"{full}: removed {p.name}, the unfinished recording of a killed run")
    return notes


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


def recover_leftovers(out: str | Path, any_pid: bool = False) -> list[str]:
    """Undo what a killed run left beside ``out``: its temporary ``.NAME.tmp-PID`` (unfinished,
    deleted) and old ``.NAME.old-PID`` folders (moved back onto ``out`` when a replacement was
    cut between its two renames, else deleted). Only folders of processes no longer running
    (``any_pid``: of any other process, for a caller holding a lock) that this tool wrote
    (MARKER or empty) are touched; returns one note per action."""
    out = _abs(out)
    parent = out.parent
    if not parent.is_dir() or not out.name:
        return []
    found: dict[str, list[Path]] = {"old": [], "tmp": []}
    for kind in found:
        for p in parent.glob(f".{glob.escape(out.name)}.{kind}-*"):
            pid = p.name.rsplit("-", 1)[1]
            if not (pid.isascii() and pid.isdigit()) or not p.is_dir() or p.is_symlink() or not is_results_folder(p):
                continue
            if int(pid) == os.getpid() or (not any_pid and _alive(int(pid))):
                continue
            found[kind].append(p)
    notes = []
    olds = sorted(found["old"], key=lambda p: p.stat().st_mtime, reverse=True)
    if olds and not out.exists():
        os.replace(olds[0], out)
        notes.append(f"{out}: restored the previous results from {olds[0].name} (a run was killed while replacing them)")
        olds = olds[1:]
    for p in olds:
        remove_results_folder(p)
        notes.append(f"{out}: removed {p.name}, old results a killed run had already replaced")
    for p in found["tmp"]:
        remove_results_folder(p)
        notes.append(f"{out}: removed {p.name}, the unfinished results of a killed run")
    return notes


def remove_results_folder(folder: Path) -> None:
    """Delete a folder this tool wrote, its MARKER last (a deletion cut short is still ours)."""
    for child in folder.iterdir():
        if child.name == MARKER:
            continue
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()
    (folder / MARKER).unlink(missing_ok=True)
    folder.rmdir()


@contextmanager
def _signals_held() -> Iterator[None]:
    """Ctrl-C (and SIGTERM, SIGHUP) held back while the results folder is swapped in, then delivered to the
    handler that was in place (a signal mask would not do: another thread may take the signal)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    old: dict[int, Any] = {
        sig: signal.signal(sig, lambda signum, frame: pending.append(signum))
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    }
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        if pending:
            handler = old[pending[0]]
            if callable(handler):
                handler(pending[0], None)  # the CLI's raises, a batch driver's sets its flag
            elif handler == signal.SIG_DFL:
                if pending[0] == signal.SIGINT:
                    raise KeyboardInterrupt
                signal.raise_signal(pending[0])  # the default action, now that the swap is done


@contextmanager
def output_folder(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """A temporary sibling folder ``.NAME.tmp-PID`` (MARKER written first) to fill; on success
    it is renamed onto ``path`` (an old folder, with ``overwrite``, is moved aside to
    ``.NAME.old-PID`` first and then deleted), on any error or Ctrl-C it is deleted. So ``path``
    is either the whole new result or untouched; a kill -9 in between leaves the sibling
    folders, which the next start recovers (``recover_leftovers``). The folder's lock
    (``locks.writer_lock``) is held throughout: a second writer is refused, never overwritten."""
    check_output_folder(path, overwrite)  # refuses a bad path before the lock creates any folder
    with writer_lock(path), _output_folder(path, overwrite) as tmp:
        yield tmp


@contextmanager
def _output_folder(path: str | Path, overwrite: bool) -> Iterator[Path]:
    out = check_output_folder(path, overwrite)
    full = _abs(out)
    tmp = full.parent / f".{full.name}.tmp-{os.getpid()}"
    try:
        full.parent.mkdir(parents=True, exist_ok=True)
        if tmp.is_dir() and is_results_folder(tmp):
            remove_results_folder(tmp)
        tmp.mkdir()
        fault_step()
        _write_marker(tmp, None)  # in place: even a cut-short marker marks it
    except OSError as exc:
        raise SnapsGraphError(f"{exc.filename or tmp}: cannot create the results folder ({exc.strerror or exc})") from None
    old: Path | None = None
    done = False
    try:
        yield tmp
        check_output_folder(out, overwrite)  # nothing appeared there meanwhile
        fault_step()
        _write_marker(tmp, sorted(p.name for p in tmp.iterdir() if p.name != MARKER))  # what --overwrite may replace
        with _signals_held():
            if full.is_dir() and any(full.iterdir()):
                old = full.parent / f".{full.name}.old-{os.getpid()}"
                fault_step()
                os.replace(full, old)
            elif full.is_dir():
                full.rmdir()
            fault_step()
            os.replace(tmp, full)
            done = True
            _COMMITTED.append(full)
            if old is not None:
                fault_step()
                with contextlib.suppress(OSError):
                    remove_results_folder(old)
                fault_step()
    except BaseException as exc:
        if not done:
            if tmp.is_dir():
                with contextlib.suppress(OSError):
                    remove_results_folder(tmp)
            if old is not None and not full.exists():  # the swap failed half-way: put the old one back
                os.replace(old, full)
        if isinstance(exc, OSError):  # disk full, permissions: the user's to fix, not a crash
            where = exc.filename or out
            raise SnapsGraphError(f"{where}: cannot write the results ({exc.strerror or exc}); {out} left as it was") from None
        raise


def _version() -> str:
    from . import __version__

    return __version__


def parse_frame_range(text: str | None, n_total: int | None = None) -> tuple[int, int | None] | None:
    """Parse ``A:B`` (Python slice semantics: A included, B excluded; either may be empty).

    Returns ``(start, stop)`` with ``stop`` None for open-ended ranges, or None for no range.
    """
    if text is None or text == "":
        return None
    parts = text.split(":")
    if len(parts) != 2:
        raise SnapsGraphError(f"frame range '{text}': expected A:B, for example 0:100")
    try:
        start = int(parts[0]) if parts[0].strip() else 0
        stop = int(parts[1]) if parts[1].strip() else None
    except ValueError:
        raise SnapsGraphError(f"frame range '{text}': A and B must be whole numbers") from None
    if start < 0 or (stop is not None and stop <= start):
        raise SnapsGraphError(f"frame range '{text}': need 0 <= A < B")
    if n_total is not None:
        if start >= n_total:
            raise SnapsGraphError(f"frame range '{text}': the sequence has only {n_total} frames")
        if stop is not None:
            stop = min(stop, n_total)
    return start, stop


T = TypeVar("T")

PREFETCH_FRAMES = 2  # frames read ahead by default (a few MB at most)

_END = object()


def prefetch(items: Iterable[T], depth: int = PREFETCH_FRAMES) -> Generator[T, None, None]:
    """Yield ``items`` in order, read up to ``depth`` ahead on a daemon thread; ``depth`` <= 0:
    plain iteration. For a dataset, the next frames' images are read and decoded while the
    caller works (OpenCV's ``imread`` releases the GIL); the frames are unchanged. An exception
    of the source is raised here at its place in the order. Closing the generator (the caller
    stopped: an error, Ctrl-C) stops the thread after the item it is reading; use it as
    ``with contextlib.closing(prefetch(...)) as frames``."""
    if depth <= 0:
        yield from items
        return
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry: tuple) -> bool:
        while not stop.is_set():
            try:
                q.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for item in items:
                if not put((item, None)):
                    return
        except BaseException as exc:  # handed to the consumer, raised there
            put((_END, exc))
            return
        put((_END, None))

    thread = threading.Thread(target=work, name="prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item, exc = q.get()
            if item is _END:
                if exc is not None:
                    raise exc
                return
            yield item
    finally:
        stop.set()
        thread.join(timeout=5.0)
