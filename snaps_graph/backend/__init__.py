"""Factor-graph back end: the package that imports gtsam (see pose_graph.py)."""

from .pose_graph import GraphStats, LoopFactorInfo, PoseGraph, loop_sigma_scale, loop_sigmas, odometry_covariance, odometry_sigmas

__all__ = [
    "GraphStats",
    "LoopFactorInfo",
    "PoseGraph",
    "loop_sigma_scale",
    "loop_sigmas",
    "odometry_covariance",
    "odometry_sigmas",
]
