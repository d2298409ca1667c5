"""stereo_order: the sign of a pair's disparities tells left from right (and a repeated image)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.frontend.depth import stereo_order


def _pair(shift: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A textured left image and the right camera's view of a plane: the texture moved ``shift``
    pixels to the left (disparity +shift)."""
    rng = np.random.default_rng(1)
    left = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (5, 5), 1.5)
    right = np.roll(left, -shift, axis=1)
    return left, right


def test_a_textured_pair_is_ok_and_its_swap_is_swapped():
    left, right = _pair()
    assert stereo_order(left, right)[0] == "ok"
    verdict, why = stereo_order(right, left)
    assert verdict == "swapped" and "100%" in why, why


def test_a_repeated_image_is_same_and_a_blank_pair_unknown():
    left, _ = _pair()
    assert stereo_order(left, left.copy())[0] == "same"
    blank = np.full((240, 320), 90, np.uint8)
    assert stereo_order(blank, blank + 20)[0] == "unknown"  # no corners: no verdict


def test_real_kitti_pairs_are_ok_and_swapped_ones_are_not(kitti06_dir):
    seq = KittiSequence(kitti06_dir)
    for i in (0, 25, 50):
        f = seq[i]
        assert stereo_order(f.left, f.right)[0] == "ok"
        assert stereo_order(f.right, f.left)[0] == "swapped"


@pytest.mark.parametrize("shift", [1, 3])
def test_small_disparities_give_no_false_swap(shift):
    """A far-only view (disparities of a pixel or few) is never called swapped."""
    left, right = _pair(shift)
    assert stereo_order(left, right)[0] in ("ok", "unknown")
