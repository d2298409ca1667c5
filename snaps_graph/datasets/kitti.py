"""KITTI odometry sequence reader (also reads what ``snaps-graph synth`` writes; layout: docs/datasets.md).

Frames are read lazily in numeric file-number order; a frame's number is its file's (its position
when a stem is not a number). times.txt and poses.txt hold one line per image, or one per frame
number from 0; ``A:B`` selects positions. Without ``image_1/`` the sequence is monocular. Every
user error is a one-line ``SnapsGraphError`` naming the file.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoCamera
from ..errors import SnapsGraphError
from ..io_utils import check_image_file, parse_frame_range
from ..trajectory_io import read_kitti_poses, read_times
from ..types import StereoFrame
from ._selection import FrameSelection

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")


def _numbered(p: Path) -> bool:
    """The stem is a whole number in ASCII digits (str.isdigit also accepts '²', which int refuses)."""
    return p.stem.isascii() and p.stem.isdigit()


def _list_images(folder: Path) -> list[Path]:
    """Image files in file-number order: stems that are whole numbers sort as numbers (0.png,
    2.png, 10.png), others after them, by name."""
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file()]
    return sorted(files, key=lambda p: (0, int(p.stem), p.name) if _numbered(p) else (1, 0, p.name))


def _frame_numbers(files: list[Path]) -> np.ndarray:
    """The frames' numbers: the files' numbers when every stem is a whole number (KITTI's
    000000.png), else positions 0, 1, 2, ... A number used twice (1.png, 01.png) is an error."""
    named = [p for p in files if not _numbered(p)]
    if named and len(named) < len(files):  # the order between the two kinds is a guess: times and poses would slip
        raise SnapsGraphError(f"{named[0]}: a named image among numbered ones (name them all 000000.png, 000001.png, ...)")
    if named:
        return np.arange(len(files))
    numbers = np.array([int(p.stem) for p in files])
    dup = np.flatnonzero(np.diff(numbers) == 0)
    if len(dup):
        a, b = files[dup[0]], files[dup[0] + 1]
        raise SnapsGraphError(f"{b}: frame number {numbers[dup[0]]} is also {a.name}")
    return numbers


def read_grey(path: Path) -> np.ndarray:
    """Read an image as 8-bit grey; a one-line error if it cannot be read."""
    check_image_file(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SnapsGraphError(f"{path}: unreadable image")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        else:
            raise SnapsGraphError(f"{path}: unsupported pixel type {img.dtype}")
    return img


class KittiSequence(FrameSelection):
    """A KITTI-format stereo sequence, read frame by frame."""

    def __init__(self, path: str | Path, frames: str | None = None, gt: str | Path | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise SnapsGraphError(f"{self.path}: sequence folder not found")
        left_dir, right_dir = self.path / "image_0", self.path / "image_1"
        if not left_dir.is_dir():
            raise SnapsGraphError(f"{left_dir}: missing image folder (expected image_0/, and image_1/ for stereo)")
        self.stereo = right_dir.is_dir()
        self._left = _list_images(left_dir)
        self._right = _list_images(right_dir) if self.stereo else []
        if not self._left:
            raise SnapsGraphError(f"{left_dir}: no images")
        if self.stereo and len(self._left) != len(self._right):
            raise SnapsGraphError(
                f"{self.path}: {len(self._left)} left images in image_0/ but {len(self._right)} right images in image_1/"
            )
        for lp, rp in zip(self._left, self._right):
            if lp.stem != rp.stem:
                raise SnapsGraphError(f"{rp}: right image does not pair with left image {lp.name}")
        self._numbers = _frame_numbers(self._left)
        self._numbered = all(_numbered(p) for p in self._left)
        n_all = len(self._left)
        self.camera = StereoCamera.from_calib_file(self.path / "calib.txt")

        times_path = self.path / "times.txt"
        if times_path.is_file():
            times = self._per_image(read_times(times_path), times_path, "timestamps")
        else:
            times = self._numbers * 0.1 if self._numbered else np.arange(n_all) * 0.1  # KITTI's 10 Hz
        self._times_all = times

        self.gt_path = self._find_gt(gt)
        self._gt_all = None
        if self.gt_path is not None:
            self._gt_all = self._per_image(read_kitti_poses(self.gt_path), self.gt_path, "poses")

        rng = parse_frame_range(frames, n_all)
        start, stop = (0, n_all) if rng is None else (rng[0], rng[1] if rng[1] is not None else n_all)
        self.start, self.stop = start, stop

        # The image size is read once from the first frame; every frame must match it.
        first = read_grey(self._left[start])
        self.camera = self.camera.with_size(first.shape[1], first.shape[0])
        self.camera.check_image_size(first.shape[1], first.shape[0], source=str(self.path / "calib.txt"))

    def _per_image(self, values: np.ndarray, path: Path, what: str) -> np.ndarray:
        """One row per image: the file holds one per image, or (numbered files) one per frame
        number from 0, of which the images' rows are taken."""
        n_all = len(self._left)
        if len(values) == n_all:
            return values
        if self._numbered and len(values) > int(self._numbers[-1]):
            return values[self._numbers]
        if self._numbered:
            raise SnapsGraphError(
                f"{path}: {len(values)} {what} for {n_all} images numbered up to {self._numbers[-1]} "
                f"(need one per image, or one per frame number from 0)"
            )
        raise SnapsGraphError(f"{path}: {len(values)} {what} for {n_all} images")

    def _find_gt(self, gt: str | Path | None) -> Path | None:
        if gt is not None:
            p = Path(gt)
            if not p.is_file():
                raise SnapsGraphError(f"{p}: ground-truth file not found")
            return p
        local = self.path / "poses.txt"
        if local.is_file():
            return local
        official = self.path.parent.parent / "poses" / f"{self.path.name}.txt"
        if self.path.parent.name == "sequences" and official.is_file():
            return official
        return None

    # ---- dataset protocol ----
    @property
    def indices(self) -> np.ndarray:
        """The selected frames' numbers (the files' numbers)."""
        return self._numbers[self.start : self.stop]

    def frame_source(self, number: int) -> str | None:
        """The left image file of frame ``number`` (for error messages), None if not in the sequence."""
        hits = np.flatnonzero(self._numbers == number)
        return str(self._left[int(hits[0])]) if len(hits) else None

    def __getitem__(self, i: int) -> StereoFrame:
        k = self._position(i)
        left = read_grey(self._left[k])
        right = read_grey(self._right[k]) if self.stereo else np.zeros((0, 0), np.uint8)
        if self.stereo and left.shape != right.shape:
            raise SnapsGraphError(
                f"{self._right[k]}: size {right.shape[1]}x{right.shape[0]} differs from left image {left.shape[1]}x{left.shape[0]}"
            )
        if (left.shape[1], left.shape[0]) != (self.camera.width, self.camera.height):
            raise SnapsGraphError(
                f"{self._left[k]}: size {left.shape[1]}x{left.shape[0]} differs from the sequence's {self.camera.width}x{self.camera.height}"
            )
        return StereoFrame(int(self._numbers[k]), float(self._times_all[k]), left, right)

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]
