"""Sessions: what a run keeps so that a later run can relocalise against it and close loops with
it (store.py owns the format; docs/sessions.md describes it)."""

from .store import (
    FOLDER,
    VERSION,
    Factors,
    Session,
    check_compatible,
    check_image_size,
    loop_settings,
    read_session,
    session_folder,
    write_session,
)

__all__ = [
    "FOLDER",
    "VERSION",
    "Factors",
    "Session",
    "check_compatible",
    "check_image_size",
    "loop_settings",
    "read_session",
    "session_folder",
    "write_session",
]
