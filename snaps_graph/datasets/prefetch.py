"""Reading ahead: a dataset's frames read and decoded on a background thread while the caller works.

Decoding a stereo pair is a sizeable share of a frame's wall time (README, speed), outside the
pipeline's own per-frame time; OpenCV's ``imread`` releases the GIL, so on a second core it
overlaps the front end. The frames come out in the source's order, unchanged: results do not depend on it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Generator, Iterable
from typing import TypeVar

T = TypeVar("T")

PREFETCH_FRAMES = 2  # frames read ahead by default (a few MB at most)

_END = object()


def prefetch(items: Iterable[T], depth: int = PREFETCH_FRAMES) -> Generator[T, None, None]:
    """Yield ``items`` in order, read up to ``depth`` ahead on a daemon thread; ``depth`` <= 0:
    plain iteration. An exception of the source is raised here at its place in the order.
    Closing the generator (the caller stopped: an error, Ctrl-C) stops the thread after the
    item it is reading; use it as ``with contextlib.closing(prefetch(...)) as frames``."""
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
