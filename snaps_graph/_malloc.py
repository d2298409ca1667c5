"""glibc malloc thresholds for image-sized temporaries, set by a program that runs the pipeline
(the CLI) with ``set_malloc_thresholds()``; importing the package changes nothing.

Fixed thresholds keep OpenCV's and numpy's image-sized temporaries in the heap, where they are
reused, instead of a fresh ``mmap`` per call (docs/decisions.md, "Speed"); results do not change.
Not applied off glibc, when ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` is set (the
user's setting wins), or with ``SNAPS_GRAPH_MALLOC=default``.
"""

from __future__ import annotations

import ctypes
import os

M_TRIM_THRESHOLD = -1  # mallopt parameter numbers (glibc malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 2**20  # glibc's largest allowed value on 64-bit
TRIM_THRESHOLD_BYTES = 256 * 2**20


def _glibc() -> bool:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")  # type: ignore[union-attr]
    except (AttributeError, ValueError, OSError):
        return False


def set_malloc_thresholds() -> bool:
    """Set glibc's mmap and trim thresholds unless the user decides them; True when applied."""
    if os.environ.get("SNAPS_GRAPH_MALLOC") == "default":
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ or not _glibc():
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
            libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
        )
    except (OSError, AttributeError):
        return False
