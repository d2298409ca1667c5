"""Live stereo from OpenCV capture devices: two cameras (``live:0,1``) or one side by side (``live:0``).

A stream, without random access: ``__len__`` is the frame limit (0 = unlimited), timestamps are
seconds since the first grab, no ground truth. Both devices are grabbed before either is read, so
the exposures are as close as the driver allows; images are rectified by a given
``StereoRectifier``, else must be rectified already. A device is an index or anything OpenCV opens.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from ..camera import StereoCamera
from ..errors import SnapsGraphError
from ..types import SequenceBase, StereoFrame
from .rectify import StereoRectifier, to_grey


def open_capture(device: str | int):
    import cv2

    dev = int(device) if isinstance(device, str) and device.strip().isascii() and device.strip().isdigit() else device
    cap = cv2.VideoCapture(dev)
    if not cap.isOpened():
        raise SnapsGraphError(f"live:{device}: cannot open the capture device")
    return cap


class LiveStereo(SequenceBase):
    """Stereo frames from ``left`` and ``right`` capture objects (anything with ``grab()``,
    ``retrieve()``, ``release()``, like ``cv2.VideoCapture``), or from one side-by-side
    ``left`` when ``right`` is None."""

    def __init__(
        self,
        left,
        right=None,
        *,
        camera: StereoCamera | None = None,
        rectifier: StereoRectifier | None = None,
        max_frames: int | None = None,
        source: str = "live",
        clock=time.monotonic,
    ):
        cam = rectifier.camera if rectifier is not None else camera
        if cam is None:
            raise SnapsGraphError(f"{source}: a live source needs a calibration (calib.txt or cam0/cam1 sensor.yaml)")
        self._left, self._right = left, right
        self.rectifier = rectifier
        self.camera: StereoCamera = cam
        self.max_frames = max_frames
        self.source = source
        self._clock = clock
        self._count = 0
        self._t0: float | None = None
        self.gt_poses = None
        self.gt_origin = None
        self.notes: list[str] = []
        self._pending: StereoFrame | None = None
        if not self.camera.width:  # calib.txt carries no size: the first frame tells it
            self._pending = self.read()
            if self._pending is None:
                raise SnapsGraphError(f"{source}: no frame from the device")

    def __len__(self) -> int:
        return self.max_frames or 0

    @property
    def indices(self) -> np.ndarray:
        raise SnapsGraphError(
            f"{self.source}: a live source has no frame list before the run (a pose file needs a recorded sequence)"
        )

    @property
    def timestamps(self) -> np.ndarray:
        raise SnapsGraphError(
            f"{self.source}: a live source has no timestamps before the run (a pose file needs a recorded sequence)"
        )

    def read(self) -> StereoFrame | None:
        """The next stereo frame, or None when a device has no more frames."""
        if self._pending is not None:
            frame, self._pending = self._pending, None
            return frame
        if self.max_frames is not None and self._count >= self.max_frames:
            return None
        caps = [self._left] if self._right is None else [self._left, self._right]
        if not all(c.grab() for c in caps):
            return None
        t = self._clock()
        imgs = []
        for c in caps:
            ok, img = c.retrieve()
            if not ok or img is None:
                return None
            imgs.append(to_grey(np.asarray(img), "", self.source))
        if self._right is None:
            w = imgs[0].shape[1]
            if w % 2:
                raise SnapsGraphError(f"{self.source}: side-by-side image width {w} is odd")
            left, right = imgs[0][:, : w // 2], imgs[0][:, w // 2 :]
        else:
            left, right = imgs
        if left.shape != right.shape:
            raise SnapsGraphError(
                f"{self.source}: left {left.shape[1]}x{left.shape[0]} and right {right.shape[1]}x{right.shape[0]} differ"
            )
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        want = (self.camera.height, self.camera.width)
        if self.camera.width and left.shape != want:
            raise SnapsGraphError(
                f"{self.source}: frames are {left.shape[1]}x{left.shape[0]}, the calibration is for {want[1]}x{want[0]}"
            )
        if self._t0 is None:
            self._t0 = t
            if not self.camera.width:
                self.camera = self.camera.with_size(left.shape[1], left.shape[0])
        frame = StereoFrame(self._count, float(t - self._t0), np.ascontiguousarray(left), np.ascontiguousarray(right))
        self._count += 1
        return frame

    def __iter__(self) -> Iterator[StereoFrame]:
        while (f := self.read()) is not None:
            yield f

    def close(self) -> None:
        for c in (self._left, self._right):
            if c is not None:
                c.release()
