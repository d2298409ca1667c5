"""The real revisit's facts (``../shared/data/kitti00_loop``, its README), for the benchmarks that
score it: which frames revisit, and the deviation over the revisit's window."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REVISIT = (1573, 1630)  # frames that pass within 1 m of the first pass
WINDOW = (1560, 1660)  # the deviation is measured over these frames


def frame_ids(seq: Path) -> list[int]:
    """The frame numbers of a KITTI folder's left images, in order."""
    return sorted(int(p.stem) for p in (seq / "image_0").glob("*.png"))


def window_deviation(poses: np.ndarray, gt: np.ndarray, frames: list[int]) -> float:
    """Mean position error over WINDOW; ``gt`` is the run's poses_gt.txt (row k = frames[k])."""
    sel = [k for k, f in enumerate(frames) if WINDOW[0] <= f <= WINDOW[1]]
    return float(np.mean(np.linalg.norm(poses[sel, :3, 3] - gt[sel, :3, 3], axis=1)))
