"""Tracked points' stereo on fewer pyramid levels from a disparity guess (``STEREO_GUESS_LEVELS``)."""

from __future__ import annotations

import cv2
import numpy as np

from snaps_graph.config import FrontendConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.frontend import depth as depth_mod


def test_guess_levels_find_the_same_disparities_from_a_close_guess(kitti06_dir, monkeypatch):
    frame = next(iter(KittiSequence(kitti06_dir, frames="0:1")))
    cfg = FrontendConfig()
    uv = cv2.goodFeaturesToTrack(frame.left, 600, 0.01, 10).reshape(-1, 2).astype(np.float32)
    full = depth_mod.sparse_disparity(frame.left, frame.right, uv, cfg)
    ok = full > 0
    guess = full[ok] + np.random.default_rng(0).normal(0, 1.0, ok.sum()).astype(np.float32)  # a guess within ~1 px
    monkeypatch.setattr(depth_mod, "STEREO_GUESS_LEVELS", 1)
    few = depth_mod.sparse_disparity(frame.left, frame.right, uv[ok], cfg, guess)
    both = few > 0
    assert both.mean() > 0.97
    assert np.percentile(np.abs(few[both] - full[ok][both]), 99) < 0.01
    # without a guess the full pyramid is used, whatever STEREO_GUESS_LEVELS says
    monkeypatch.setattr(depth_mod, "STEREO_GUESS_LEVELS", 0)
    again = depth_mod.sparse_disparity(frame.left, frame.right, uv, cfg)
    assert np.array_equal(again, full)
