"""Loop closure: the SNAPS loop closer (snaps.py) composing the heuristic trajectory
(trajectory.py), the candidate index (search.py), UIQI similarity over thumbnails (uiqi.py) and
eq. 6's correction (correction.py), under a named rule (policy.py); prior sessions are searched
by appearance, then by location (prior.py, cross.py)."""

from .correction import discount
from .policy import DRIFT, PAPER, POLICIES, LoopPolicy
from .snaps import SnapsLoopCloser, SnapsStep, Verifier
from .uiqi import UIQI, WindowStats, make_thumbnail, similarity, similarity_q, uiqi, window_stats

__all__ = [
    "DRIFT",
    "PAPER",
    "POLICIES",
    "UIQI",
    "LoopPolicy",
    "SnapsLoopCloser",
    "SnapsStep",
    "Verifier",
    "WindowStats",
    "discount",
    "make_thumbnail",
    "similarity",
    "similarity_q",
    "uiqi",
    "window_stats",
]
