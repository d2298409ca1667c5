"""snaps_graph: stereo visual SLAM with SNAPS loop closure feeding a GTSAM pose graph."""

__version__ = "0.1.0"

from . import _malloc  # noqa: E402,F401  # glibc malloc thresholds (speed; see _malloc.py)
