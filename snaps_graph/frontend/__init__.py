"""Stereo visual odometry front end (paper §II-B..D): depth, features, PnP, the motion between frames."""

from .depth import dense_depth, dense_disparity, sparse_depth
from .motion import pnp_ransac
from .odometry import StereoOdometry

__all__ = ["StereoOdometry", "dense_depth", "dense_disparity", "sparse_depth", "pnp_ransac"]
