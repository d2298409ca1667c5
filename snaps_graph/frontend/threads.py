"""The front end's worker threads. OpenCV releases the GIL, so independent stages of one frame run
side by side (one LK call already spreads over OpenCV's own threads). Each task's inputs are fixed
before it starts, so the output does not depend on timing."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any


class Inline:
    """Runs a task at once in the caller's thread (threads = 1), with a Future-like result()."""

    def __init__(self, fn: Callable, *args: Any):
        try:
            self._value, self._exc = fn(*args), None
        except BaseException as exc:  # re-raised by result(), like a Future
            self._value, self._exc = None, exc

    def result(self) -> Any:
        if self._exc is not None:
            raise self._exc
        return self._value


class Workers:
    """``threads - 1`` workers for whole stages; their tasks never wait on others."""

    def __init__(self, threads: int):
        self._pool = ThreadPoolExecutor(max_workers=threads - 1) if threads > 1 else None

    def submit(self, fn: Callable, *args: Any) -> Future | Inline:
        if self._pool is None:
            return Inline(fn, *args)
        return self._pool.submit(fn, *args)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        self._pool = None
