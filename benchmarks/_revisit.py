"""The real revisit's facts (``../shared/data/kitti00_loop``, its README), for the benchmarks that
score it: which frames revisit, and the deviation over the revisit's window."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REVISIT = (1573, 1630)  # frames that pass within 1 m of the first pass
WINDOW = (1560, 1660)  # the deviation is measured over these frames
FIRST_PASS = (100, 230)  # the first drive through the street, 1064 m before the revisit


def whole_run(poses: np.ndarray, gt: np.ndarray, frames: list[int]) -> dict[str, float]:
    """Mean position error over the whole run (3D, horizontal, vertical) and over the first pass, m."""
    d = poses[:, :3, 3] - gt[:, :3, 3]
    first = [k for k, f in enumerate(frames) if FIRST_PASS[0] <= f <= FIRST_PASS[1]]
    e = np.linalg.norm(d, axis=1)
    return {
        "3d": float(e.mean()),
        "hor": float(np.hypot(d[:, 0], d[:, 2]).mean()),
        "vert": float(np.abs(d[:, 1]).mean()),
        "first": float(e[first].mean()),
    }


def frame_ids(seq: Path) -> list[int]:
    """The frame numbers of a KITTI folder's left images, in order."""
    return sorted(int(p.stem) for p in (seq / "image_0").glob("*.png"))


def window_deviation(poses: np.ndarray, gt: np.ndarray, frames: list[int]) -> float:
    """Mean position error over WINDOW; ``gt`` is the run's poses_gt.txt (row k = frames[k])."""
    sel = [k for k, f in enumerate(frames) if WINDOW[0] <= f <= WINDOW[1]]
    return float(np.mean(np.linalg.norm(poses[sel, :3, 3] - gt[sel, :3, 3], axis=1)))
