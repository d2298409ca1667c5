"""Shared pieces of the raw-camera readers (EuRoC, ROS bags, live): stereo rectification,
timestamp pairing and conversion of any 8/16-bit image to 8-bit grey.

Rectification is OpenCV's ``stereoRectify`` (or a CameraInfo's own R/P), its remap tables
computed once as float maps (``CV_32FC1``: less CPU than fixed-point, docs/performance.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import StereoCamera
from ..errors import SnapsGraphError
from ..geometry import slerp


class StereoRectifier:
    """Undistort and rectify raw stereo pairs into a ``StereoCamera`` (KITTI convention:
    same rows, right camera at +baseline along x, no distortion).

    ``R_rect_raw``: rotation from the raw left camera frame into the rectified left frame
    (a point x_raw becomes R_rect_raw @ x_raw); poses given for the raw left camera are moved
    to the rectified one with ``T_raw_rect`` (``rect_pose``).
    """

    def __init__(self, map_left, map_right, camera: StereoCamera, R_rect_raw: np.ndarray):
        self._map_l, self._map_r = map_left, map_right
        self.camera = camera
        self.R_rect_raw = np.asarray(R_rect_raw, float)
        # What a ROS CameraInfo of each raw camera would carry: ((K, D, R, P) left, (K, D, R, P) right).
        self.info: tuple = ()

    @classmethod
    def from_calibration(
        cls,
        K0: np.ndarray,
        D0: np.ndarray,
        K1: np.ndarray,
        D1: np.ndarray,
        T_c0_c1: np.ndarray,
        size: tuple[int, int],
        source: str = "calibration",
    ) -> "StereoRectifier":
        """``T_c0_c1``: 4x4 pose of the right camera in the left camera frame; ``size``: (w, h)."""
        T_c1_c0 = np.linalg.inv(np.asarray(T_c0_c1, float))
        R, t = T_c1_c0[:3, :3], T_c1_c0[:3, 3]
        if np.linalg.norm(t) <= 0:
            raise SnapsGraphError(f"{source}: the two cameras are at the same place (zero baseline)")
        try:
            R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
                np.asarray(K0, float),
                np.asarray(D0, float).reshape(1, -1),
                np.asarray(K1, float),
                np.asarray(D1, float).reshape(1, -1),
                tuple(int(v) for v in size),
                np.ascontiguousarray(R),
                t.reshape(3, 1).copy(),
                flags=cv2.CALIB_ZERO_DISPARITY,
                alpha=0,
            )
        except cv2.error as exc:
            raise SnapsGraphError(f"{source}: stereo rectification failed ({str(exc).strip().splitlines()[-1]})") from None
        if abs(P2[0, 3]) < abs(P2[1, 3]):
            raise SnapsGraphError(f"{source}: the cameras are stacked vertically; only side-by-side stereo is supported")
        if P2[0, 3] > 0:
            raise SnapsGraphError(f"{source}: the 'right' camera is left of the 'left' camera (swap them)")
        return cls.from_rectification(K0, D0, R1, P1, K1, D1, R2, P2, size, source)

    @classmethod
    def from_rectification(
        cls, K0, D0, R0, P0, K1, D1, R1, P1, size: tuple[int, int], source: str = "calibration"
    ) -> "StereoRectifier":
        """From the rectification each camera already has (ROS ``CameraInfo``: K, D, R, P)."""
        w, h = int(size[0]), int(size[1])
        P0, P1 = np.asarray(P0, float).reshape(3, 4), np.asarray(P1, float).reshape(3, 4)
        camera = StereoCamera.from_projections(P0, P1, w, h, source=source)
        maps = []
        for K, D, R, P in ((K0, D0, R0, P0), (K1, D1, R1, P1)):
            maps.append(
                cv2.initUndistortRectifyMap(
                    np.asarray(K, float).reshape(3, 3),
                    np.asarray(D, float).reshape(-1),
                    np.asarray(R, float).reshape(3, 3),
                    P[:3, :3],
                    (w, h),
                    cv2.CV_32FC1,
                )
            )
        rect = cls(maps[0], maps[1], camera, np.asarray(R0, float).reshape(3, 3))
        rect.info = tuple(
            tuple(np.asarray(m, float).reshape(-1) for m in (K, D, R, P)) for K, D, R, P in ((K0, D0, R0, P0), (K1, D1, R1, P1))
        )
        return rect

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        l = cv2.remap(left, *self._map_l, cv2.INTER_LINEAR)
        r = cv2.remap(right, *self._map_r, cv2.INTER_LINEAR)
        return l, r

    def rect_pose(self, T_world_raw: np.ndarray) -> np.ndarray:
        """Poses of the raw left camera (..., 4, 4) -> poses of the rectified left camera."""
        T_raw_rect = np.eye(4)
        T_raw_rect[:3, :3] = self.R_rect_raw.T
        return np.asarray(T_world_raw) @ T_raw_rect


def match_stamps(t_left_ns, t_right_ns, tol_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pair two sorted lists of integer nanosecond stamps one to one: each left stamp with the
    nearest right stamp within ``tol_ns`` (default: a quarter of the median left period, at
    least 1 microsecond); returns the indices of the pairs, in time order."""
    tl, tr = np.asarray(t_left_ns, np.int64), np.asarray(t_right_ns, np.int64)
    if len(tl) == 0 or len(tr) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if tol_ns is None:
        period = int(np.median(np.diff(tl))) if len(tl) > 1 else 0
        tol_ns = max(period // 4, 1000)
    if len(tr) > 1:
        j = np.clip(np.searchsorted(tr, tl), 1, len(tr) - 1)
        prev_closer = np.abs(tl - tr[j - 1]) <= np.abs(tr[j] - tl)
        j = np.where(prev_closer, j - 1, j)
    else:
        j = np.zeros(len(tl), np.int64)
    ok = np.abs(tr[j] - tl) <= tol_ns
    il, ir = np.nonzero(ok)[0], j[ok]
    # One to one: a right stamp claimed twice keeps its nearest left stamp.
    keep = np.ones(len(il), bool)
    seen: dict[int, int] = {}
    for n, (a, b) in enumerate(zip(il, ir)):
        if b in seen:
            m = seen[b]
            if abs(tl[a] - tr[b]) < abs(tl[il[m]] - tr[b]):
                keep[m] = False
                seen[b] = n
            else:
                keep[n] = False
        else:
            seen[b] = n
    return il[keep], ir[keep]


def to_grey(img: np.ndarray, encoding: str = "", source: str = "image") -> np.ndarray:
    """An image as uint8 grey. ``encoding``: a ROS encoding (mono8, mono16, rgb8, bgr8, rgba8,
    bgra8) or "" for OpenCV's channel order; 16-bit keeps its high byte (as ``read_grey``)."""
    enc = encoding.lower()
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] == 3:
            code = cv2.COLOR_RGB2GRAY if enc.startswith("rgb") else cv2.COLOR_BGR2GRAY
        elif img.shape[2] == 4:
            code = cv2.COLOR_RGBA2GRAY if enc.startswith("rgb") else cv2.COLOR_BGRA2GRAY
        else:
            raise SnapsGraphError(f"{source}: {img.shape[2]} channels, cannot make a grey image")
        img = cv2.cvtColor(img, code)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise SnapsGraphError(f"{source}: unsupported pixel type {img.dtype}")
    return np.ascontiguousarray(img)


def interpolate_poses(t_src: np.ndarray, p: np.ndarray, q_wxyz: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Poses (N,4,4) at ``t_query`` from samples (positions linear, orientations slerp);
    ``t_query`` must lie within ``t_src``'s span."""
    t_src, t_query = np.asarray(t_src, np.float64), np.asarray(t_query, np.float64)
    q = np.asarray(q_wxyz, float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    i = (
        np.clip(np.searchsorted(t_src, t_query, side="right") - 1, 0, len(t_src) - 2)
        if len(t_src) > 1
        else np.zeros(len(t_query), np.int64)
    )
    if len(t_src) == 1:
        a = np.zeros(len(t_query))
        q0, q1, p0, p1 = q[i], q[i], p[i], p[i]
    else:
        dt = t_src[i + 1] - t_src[i]
        a = np.clip(np.where(dt > 0, (t_query - t_src[i]) / np.where(dt > 0, dt, 1), 0.0), 0.0, 1.0)
        q0, q1, p0, p1 = q[i], q[i + 1], p[i], p[i + 1]
    T = np.tile(np.eye(4), (len(t_query), 1, 1))
    if not len(t_query):
        return T
    T[:, :3, :3] = slerp(q0[:, [1, 2, 3, 0]], q1[:, [1, 2, 3, 0]], a)  # (x, y, z, w) order
    T[:, :3, 3] = (1 - a)[:, None] * p0 + a[:, None] * p1
    return T
