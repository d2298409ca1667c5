"""Small file helpers: atomic writes and whole-or-absent output folders, so an interrupted run
never leaves a half-written file or a folder that looks complete; reading frames ahead on a
background thread (``prefetch``)."""

from __future__ import annotations

import os
import queue
import shutil
import tempfile
import threading
import tomllib
from collections.abc import Generator, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

from .errors import SnapsGraphError


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


def read_text(path: str | Path, what: str) -> str:
    """A text file's content; a one-line SnapsGraphError naming it when it is missing, a folder,
    unreadable or not text (NUL bytes, not UTF-8)."""
    path = Path(path)
    if path.is_dir():
        raise SnapsGraphError(f"{path}: is a folder, expected a {what} file")
    if not path.is_file():
        raise SnapsGraphError(f"{path}: {what} file not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SnapsGraphError(f"{path}: cannot read the {what} file ({exc.strerror or exc})") from None
    if b"\0" in data:
        raise SnapsGraphError(f"{path}: binary data, expected a text {what} file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise SnapsGraphError(f"{path}: not a text (UTF-8) file, expected a {what} file") from None


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file's tables; a one-line SnapsGraphError naming it when it is missing, a folder,
    unreadable, not UTF-8 text or malformed TOML. ``what`` names the file's role ("config")."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_bytes().decode("utf-8"))
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


def check_output_folder(path: str | Path, overwrite: bool = False, reuse: bool = False) -> Path:
    """Refuse, with a one-line SnapsGraphError, an output folder a run could not replace whole:
    a path that is a file or lies under a file, a folder whose parent cannot be written, or a
    non-empty folder without ``overwrite`` (``reuse``: a non-empty folder is fine, as a resumed
    batch wants). Call it before any work; returns the path."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise SnapsGraphError(f"{out}: exists and is not a folder")
    for parent in out.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise SnapsGraphError(f"{parent}: is a file, cannot create the folder {out} under it")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise SnapsGraphError(f"{parent}: not writable, cannot create {out}")
            break
    if out.is_dir() and not (overwrite or reuse) and any(out.iterdir()):
        raise SnapsGraphError(f"{out}: folder exists and is not empty (use --overwrite to replace it)")
    return out


@contextmanager
def output_folder(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """A temporary sibling folder ``.NAME.tmp-PID`` to fill; on success it is renamed onto
    ``path`` (an old folder, with ``overwrite``, is moved aside first and then deleted), on any
    error or Ctrl-C it is deleted. So ``path`` is either the whole new result or untouched."""
    out = check_output_folder(path, overwrite)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
    except OSError as exc:
        raise SnapsGraphError(f"{exc.filename or tmp}: cannot create the results folder ({exc.strerror or exc})") from None
    old: Path | None = None
    try:
        yield tmp
        check_output_folder(out, overwrite)  # nothing appeared there meanwhile
        if out.is_dir() and any(out.iterdir()):
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
        elif out.is_dir():
            out.rmdir()
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not out.exists():  # the swap failed half-way: put the old one back
            os.replace(old, out)
        if isinstance(exc, OSError):  # disk full, permissions: the user's to fix, not a crash
            where = exc.filename or out
            raise SnapsGraphError(f"{where}: cannot write the results ({exc.strerror or exc}); {out} left as it was") from None
        raise


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
