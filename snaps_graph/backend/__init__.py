"""Factor-graph back end: the package that imports gtsam (see pose_graph.py)."""

from ._values import array_to_values, to_pose3, values_to_array
from .noise import loop_sigma_scale, loop_sigmas, odometry_covariance, odometry_sigmas
from .pose_graph import GraphStats, LoopFactorInfo, PoseGraph

__all__ = [
    "GraphStats",
    "LoopFactorInfo",
    "PoseGraph",
    "array_to_values",
    "loop_sigma_scale",
    "loop_sigmas",
    "odometry_covariance",
    "odometry_sigmas",
    "to_pose3",
    "values_to_array",
]
