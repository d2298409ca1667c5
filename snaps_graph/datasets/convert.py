"""``snaps-graph convert``: any readable source to the KITTI layout ``KittiSequence`` reads.

The rectified grey pairs numbered from 0, calib.txt of the rectified pair, times.txt (the
source's seconds) and, when known, poses.txt (re-based, for the rectified left camera); every
file written atomically.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import atomic_write_bytes
from ..trajectory_io import write_kitti_poses, write_times


def write_kitti_folder(
    dataset, out_dir: str | Path, progress: Callable[[], object] | None = None, overwrite: bool = False
) -> int:
    """Write ``dataset`` to ``out_dir``; returns the number of pairs written."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SnapsGraphError(f"{out}: exists and is not a folder")
    dirs = [out / "image_0", out / "image_1"]
    for d in dirs:
        old = sorted(d.glob("*.png")) if d.is_dir() else []
        if old and not overwrite:
            raise SnapsGraphError(f"{d}: already holds {len(old)} images; choose an empty folder (or --overwrite)")
        for p in old:
            p.unlink()
        d.mkdir(parents=True, exist_ok=True)
    times = []
    for frame in dataset:
        n = len(times)
        for d, img in zip(dirs, (frame.left, frame.right)):
            ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise SnapsGraphError(f"{d}: PNG encoding failed for frame {n}")
            atomic_write_bytes(d / f"{n:06d}.png", png.tobytes())
        times.append(frame.timestamp)
        if progress is not None:
            progress()
    n = len(times)
    if n == 0:
        raise SnapsGraphError(f"{out}: the source gave no frames")
    dataset.camera.write_calib(out / "calib.txt")
    write_times(out / "times.txt", np.array(times))
    gt = dataset.gt_poses
    if gt is not None:
        write_kitti_poses(out / "poses.txt", gt[:n])
    return n
