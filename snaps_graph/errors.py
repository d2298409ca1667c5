"""User-facing errors.

Anything a user can cause (a bad path, a malformed calibration, mismatched images) raises
``SnapsGraphError`` with a one-line message that names the file. The CLI prints that line and
exits with status 2; it never shows a traceback for these.
"""


class SnapsGraphError(Exception):
    """A user error with a one-line, human-readable message."""
