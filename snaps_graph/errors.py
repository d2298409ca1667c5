"""User-facing errors: anything a user can cause (a bad path, a malformed calibration, mismatched
images) raises ``SnapsGraphError`` with a one-line message naming the file; the CLI prints that
line and exits with status 2, never with a traceback.
"""

import threading

_INTERRUPTED = threading.Event()


class SnapsGraphError(Exception):
    """A user error with a one-line, human-readable message."""


def note_interrupt() -> None:
    """Ctrl-C was pressed (the CLI's SIGINT handler): an error that follows is its consequence
    (an extension module whose import it cut reports ImportError), not a failure to report."""
    _INTERRUPTED.set()


def interrupted() -> bool:
    """Ctrl-C was pressed in this process."""
    return _INTERRUPTED.is_set()
