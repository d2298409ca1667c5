"""Odometry from elsewhere (wheels, GNSS/INS, LiDAR, another VO) as the front end: a pose file's
relative poses with the ``[odometry]`` drift model's step covariance, since a pose file carries none
(docs/frontend.md). No file I/O: the runner reads the file."""

from __future__ import annotations

import numpy as np

from ..config import OdometryConfig
from ..drift_model import path_covariance
from ..errors import SnapsGraphError
from ..trajectory_io import PoseFile
from ..types import StereoFrame, VOResult

TIME_TOLERANCE_S = 0.02  # TUM stamps: a frame takes the nearest pose within this (KITTI 10 Hz, EuRoC 20 Hz)


def driven_distance(track: PoseFile) -> np.ndarray:
    """Cumulative distance driven at each pose of the file, metres."""
    p = track.poses[:, :3, 3]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def time_origin(track: PoseFile, first_time_s: float, origin_s: float | None) -> float:
    """The time origin to match a TUM file against a dataset whose frame times count from
    ``origin_s`` (absolute, s; EuRoC and bags): the origin when the file's first stamp is nearer
    the dataset's first frame in absolute time than in relative time, else 0 (KITTI files)."""
    if track.fmt != "tum" or origin_s is None:
        return 0.0
    t = float(track.keys[0])
    return float(origin_s) if abs(t - (origin_s + first_time_s)) < abs(t - first_time_s) else 0.0


class PoseFileOdometry:
    """A front end (``process(frame) -> VOResult``, ``close()``) reading its poses from a pose file.

    KITTI files are matched by frame number (line i holds frame i), TUM files by timestamp (the
    nearest pose within ``tolerance_s``). A frame without a pose is a ``SnapsGraphError`` naming
    the file and the line that would hold it; :meth:`check` tests a whole run's frames up front."""

    def __init__(
        self,
        track: PoseFile,
        cfg: OdometryConfig | None = None,
        tolerance_s: float = TIME_TOLERANCE_S,
        time_origin_s: float = 0.0,
    ):
        """``time_origin_s``: added to a frame's timestamp before it is matched to a TUM stamp (a
        dataset whose frame times count from its first frame: see :func:`time_origin`)."""
        self.track = track
        self.cfg = cfg or OdometryConfig()
        self._model = self.cfg.model()
        self.tolerance_s = float(tolerance_s)
        self.time_origin_s = float(time_origin_s)
        self._origin_inv: np.ndarray | None = None
        self._prev: np.ndarray | None = None
        self._prev_at = 0
        self._driven = driven_distance(track)
        self._pose = np.eye(4)
        self.disparity_offset_px = 0.0  # no stereo: nothing to correct

    def locate(self, frame: int, timestamp: float) -> int:
        """The position in the track of frame ``frame`` (taken at ``timestamp``)."""
        tr = self.track
        n = len(tr.keys)
        if tr.fmt == "kitti":
            if not 0 <= frame < n:
                raise SnapsGraphError(
                    f"{tr.path}: no pose for frame {frame} (the file ends at line {int(tr.lines[-1])}, frame {n - 1}; "
                    f"line {frame + 1} would hold it): fewer poses than images"
                )
            return int(frame)
        timestamp = timestamp + self.time_origin_s
        i = int(np.searchsorted(tr.keys, timestamp))
        best = min((j for j in (i - 1, i) if 0 <= j < n), key=lambda j: abs(tr.keys[j] - timestamp))
        if not abs(tr.keys[best] - timestamp) <= self.tolerance_s:
            raise SnapsGraphError(
                f"{tr.path}:{int(tr.lines[best])}: no pose within {self.tolerance_s:g} s of frame {frame} "
                f"(t = {timestamp:.6f}; the nearest, on this line, is t = {tr.keys[best]:.6f})"
            )
        return best

    def check(self, frames, timestamps) -> None:
        """A ``SnapsGraphError`` for the first frame without a pose (before any is processed)."""
        for f, t in zip(frames, timestamps):
            self.locate(int(f), float(t))

    def relative(self, a: tuple[int, float], b: tuple[int, float]) -> np.ndarray:
        """T_a_b between two frames (frame number, timestamp) from the file's poses."""
        Pa = self.track.poses[self.locate(*a)]
        Pb = self.track.poses[self.locate(*b)]
        return np.linalg.solve(Pa, Pb)

    def process(self, frame: StereoFrame) -> VOResult:
        at = self.locate(int(frame.index), float(frame.timestamp))
        P = self.track.poses[at]
        if self._prev is None:
            self._origin_inv = np.linalg.inv(P)
            T_rel = np.eye(4)
            cov = None
        else:
            T_rel = np.linalg.solve(self._prev, P)
            cov = np.zeros((6, 6))  # no measurement noise of its own: the graph adds the drift model's
        assert self._origin_inv is not None
        prev_at = self._prev_at
        self._prev, self._prev_at = P, at
        self._pose = self._origin_inv @ P
        drift_cov = None
        if cov is not None and abs(at - prev_at) > 1:  # frames left out: the drift along the file's own path
            lo, hi = sorted((prev_at, at))
            drift_cov = path_covariance(self._model, self.track.poses[lo : hi + 1][:: 1 if at > prev_at else -1])
        return VOResult(int(frame.index), T_rel, self._pose.copy(), True, cov=cov, drift_cov=drift_cov)

    def close(self) -> None:
        pass
