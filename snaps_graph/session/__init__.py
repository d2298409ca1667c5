"""Sessions: what a run keeps so that a later run can relocalise against it, close loops with it
and join its graph (store.py owns the format; docs/sessions.md describes it)."""

from .store import FOLDER, VERSION, Factors, Session, check_compatible, loop_settings, read_session, session_folder, write_session

__all__ = [
    "FOLDER",
    "VERSION",
    "Factors",
    "Session",
    "check_compatible",
    "loop_settings",
    "read_session",
    "session_folder",
    "write_session",
]
