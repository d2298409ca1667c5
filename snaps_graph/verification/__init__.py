"""Loop verification: does a loop candidate show the same place, and where from? Its own keypoints
on reference frames, matched to the current frame and solved by PnP, with stereo depth
(features.py) or, without a right image, triangulated over the odometry's motion (mono.py)."""

from .features import LoopFeatureBank, LoopMatch, verify_features
from .mono import MonoFeatureBank

__all__ = ["LoopFeatureBank", "LoopMatch", "MonoFeatureBank", "verify_features"]
