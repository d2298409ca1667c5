"""Local-BA keyframes: every LBA_EVERY frames, or sooner once the drive has gone LBA_KEYFRAME_M."""

from __future__ import annotations

import numpy as np

from snaps_graph.camera import StereoCamera
from snaps_graph.config import FrontendConfig
from snaps_graph.frontend.lba_schedule import LocalBAScheduler

CAM = StereoCamera(fx=718.0, fy=718.0, cx=607.0, cy=185.0, baseline_m=0.54, width=1241, height=376)


def _at(z: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


def test_a_fast_drive_gets_its_keyframe_by_distance():
    s = LocalBAScheduler(CAM, FrontendConfig())
    assert (s.every, s.keyframe_m) == (3, 2.5)
    s._last, s._last_pos = 10, np.zeros(3)
    assert not s.due(11, _at(1.2))  # a normal drive: 1.2 m a frame waits for frame 13
    assert not s.due(12, _at(2.4))
    assert s.due(13, _at(3.6))
    assert s.due(11, _at(2.6))  # a fast one: 2.6 m after one frame
    assert s.due(13, _at(0.1))  # a car nearly standing still: the frame count
    s = LocalBAScheduler(CAM, FrontendConfig())
    s.keyframe_m = 0.0
    s._last, s._last_pos = 10, np.zeros(3)
    assert not s.due(11, _at(10.0))  # 0: the frame count alone
