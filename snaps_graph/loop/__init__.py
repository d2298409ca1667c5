"""Loop closure: UIQI similarity (uiqi.py), the SNAPS loop closer (snaps.py) with its candidate
search (search.py) and eq. 6 correction (correction.py)."""

from .snaps import SnapsLoopCloser, SnapsStep, discount
from .uiqi import UIQI, WindowStats, make_thumbnail, similarity, similarity_q, uiqi, window_stats

__all__ = [
    "UIQI",
    "SnapsLoopCloser",
    "SnapsStep",
    "WindowStats",
    "discount",
    "make_thumbnail",
    "similarity",
    "similarity_q",
    "uiqi",
    "window_stats",
]
