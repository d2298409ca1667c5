"""snaps_graph: stereo visual SLAM with SNAPS loop closure feeding a GTSAM pose graph."""

__version__ = "0.1.0"
