"""The front end's worker threads. OpenCV releases the GIL, so independent stages of one frame run
side by side; an LK call on many points runs as two halves (LK tracks each point alone, so the
halves give the numbers one call would). Each task's inputs are fixed before it starts, so the
output does not depend on timing."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np


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
    """``threads - 1`` workers for whole stages, and one more for the second half of a split LK
    call on at least ``split_min`` points (0: never split); its tasks never wait on others."""

    def __init__(self, threads: int, split_min: int):
        self.split_min = split_min
        self._pool = ThreadPoolExecutor(max_workers=threads - 1) if threads > 1 else None
        self._split_pool = ThreadPoolExecutor(max_workers=1) if threads > 1 and split_min > 0 else None

    def submit(self, fn: Callable, *args: Any) -> Future | Inline:
        if self._pool is None:
            return Inline(fn, *args)
        return self._pool.submit(fn, *args)

    def split(self, fn: Callable, uv: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """``fn(uv, guess)`` -> two per-point arrays, on the two halves of the points in two threads."""
        n = len(uv)
        if self._split_pool is None or n < max(2, self.split_min):
            return fn(uv, guess)
        k = n // 2
        second = self._split_pool.submit(fn, uv[k:], None if guess is None else guess[k:])
        a0, a1 = fn(uv[:k], None if guess is None else guess[:k])
        b0, b1 = second.result()
        return np.concatenate([a0, b0]), np.concatenate([a1, b1])

    def close(self) -> None:
        for pool in (self._pool, self._split_pool):
            if pool is not None:
                pool.shutdown(wait=True)
        self._pool = self._split_pool = None
