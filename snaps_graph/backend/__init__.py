"""Factor-graph back end: the package that imports gtsam (see pose_graph.py)."""

from .noise import loop_sigma_scale, loop_sigmas, odometry_covariance, odometry_sigmas
from .pose_graph import GraphStats, LoopFactorInfo, PoseGraph

__all__ = [
    "GraphStats",
    "LoopFactorInfo",
    "PoseGraph",
    "loop_sigma_scale",
    "loop_sigmas",
    "odometry_covariance",
    "odometry_sigmas",
]
