"""Rectified stereo camera model, read from KITTI's ``calib.txt`` (P0 and P1 lines)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import SnapsGraphError
from .io_utils import atomic_write_text, read_text

# P0/P1 of KITTI odometry sequence 00 (grey cameras), the synthetic renderer's default camera.
KITTI00_P0 = np.array([[718.856, 0.0, 607.1928, 0.0], [0.0, 718.856, 185.2157, 0.0], [0.0, 0.0, 1.0, 0.0]])
KITTI00_P1 = np.array([[718.856, 0.0, 607.1928, -386.1448], [0.0, 718.856, 185.2157, 0.0], [0.0, 0.0, 1.0, 0.0]])
KITTI00_SIZE = (1241, 376)  # width, height

# Plausible calibration: anything outside is a malformed calib.txt, not a camera.
MIN_FOCAL_PX, MAX_FOCAL_PX = 1.0, 1e5
MIN_BASELINE_M, MAX_BASELINE_M = 0.0, 10.0
CALIB_MAX_BYTES = 2**20  # a calib.txt is a few lines


@dataclass(frozen=True)
class StereoCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    width: int = 0  # 0 when unknown (calib.txt does not carry the image size)
    height: int = 0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def P0(self) -> np.ndarray:
        P = np.zeros((3, 4))
        P[:, :3] = self.K
        return P

    @property
    def P1(self) -> np.ndarray:
        P = self.P0
        P[0, 3] = -self.fx * self.baseline_m
        return P

    def with_size(self, width: int, height: int) -> "StereoCamera":
        return StereoCamera(self.fx, self.fy, self.cx, self.cy, self.baseline_m, width, height)

    def scaled(self, width: int, height: int) -> "StereoCamera":
        """The same camera rendered at another image size (intrinsics scale with it)."""
        if not self.width or not self.height:
            raise ValueError("scaled() needs a camera with a known size")
        sx, sy = width / self.width, height / self.height
        return StereoCamera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.baseline_m, width, height)

    @classmethod
    def from_projections(
        cls, P0: np.ndarray, P1: np.ndarray, width: int = 0, height: int = 0, source: str = "calib"
    ) -> "StereoCamera":
        P0 = np.asarray(P0, float).reshape(3, 4)
        P1 = np.asarray(P1, float).reshape(3, 4)
        fx, fy, cx, cy = P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]
        if not np.all(np.isfinite(P0)) or not np.all(np.isfinite(P1)):
            raise SnapsGraphError(f"{source}: P0/P1 contain non-finite numbers")
        for f, name in ((fx, "P0[0,0] (fx)"), (fy, "P0[1,1] (fy)")):
            if not MIN_FOCAL_PX < f <= MAX_FOCAL_PX:
                raise SnapsGraphError(
                    f"{source}: focal length {name} = {f:.6g} px is not in ({MIN_FOCAL_PX:g}, {MAX_FOCAL_PX:g}]"
                )
        if not (abs(cx) <= MAX_FOCAL_PX and abs(cy) <= MAX_FOCAL_PX):
            raise SnapsGraphError(f"{source}: principal point ({cx:.6g}, {cy:.6g}) px is absurd")
        # A rectified pinhole P = K [R | t] with K upper triangular without skew: the last row is
        # (0, 0, 1); skew or a rotated row would be ignored by every formula that reads K.
        for name, P in (("P0", P0), ("P1", P1)):
            if not np.allclose(P[2, :3], (0.0, 0.0, 1.0), atol=1e-6):
                raise SnapsGraphError(
                    f"{source}: {name}'s third row starts {P[2, :3].tolist()}, not [0, 0, 1] (not a rectified camera)"
                )
            if abs(P[0, 1]) > 1e-3 * fx or abs(P[1, 0]) > 1e-3 * fx:
                raise SnapsGraphError(f"{source}: {name} has skew ({P[0, 1]:.6g}, {P[1, 0]:.6g}); a rectified camera has none")
        if abs(P1[1, 3] - P0[1, 3]) > 1e-3 * fy:  # rows no longer match: not a horizontal rectified pair
            raise SnapsGraphError(
                f"{source}: P1[1,3] - P0[1,3] = {P1[1, 3] - P0[1, 3]:.6g}: a vertical offset between the cameras "
                "(a rectified horizontal pair has none)"
            )
        # A rectified pair shares K: P1 = K [I | -B e_x] (a different focal length would silently
        # scale the baseline and every depth).
        for (i, j), name in (((0, 0), "fx"), ((1, 1), "fy"), ((0, 2), "cx"), ((1, 2), "cy")):
            if not np.isclose(P1[i, j], P0[i, j], rtol=1e-4, atol=1e-6):
                raise SnapsGraphError(
                    f"{source}: P1's {name} = {P1[i, j]:.6g} differs from P0's {P0[i, j]:.6g} "
                    "(a rectified stereo pair shares its intrinsics)"
                )
        baseline = (P0[0, 3] - P1[0, 3]) / fx  # P0[0,3] is 0 for KITTI's left grey camera
        if not MIN_BASELINE_M < baseline <= MAX_BASELINE_M:
            raise SnapsGraphError(
                f"{source}: baseline (P0[0,3] - P1[0,3]) / fx = {baseline:.6g} m is not in ({MIN_BASELINE_M:g}, {MAX_BASELINE_M:g}]"
            )
        return cls(float(fx), float(fy), float(cx), float(cy), float(baseline), width, height)

    def check_image_size(self, width: int, height: int, source: str = "calib") -> None:
        """SnapsGraphError unless the principal point lies inside a ``width`` x ``height`` image."""
        if not (0 <= self.cx <= width and 0 <= self.cy <= height):
            raise SnapsGraphError(
                f"{source}: principal point ({self.cx:.6g}, {self.cy:.6g}) lies outside the {width}x{height} images"
            )

    @classmethod
    def from_calib_file(cls, path: str | Path) -> "StereoCamera":
        path = Path(path)
        text = read_text(path, "calibration", max_bytes=CALIB_MAX_BYTES)
        mats: dict[str, np.ndarray] = {}
        for lineno, line in enumerate(text.splitlines(), 1):
            if ":" not in line:
                continue
            label, _, rest = line.partition(":")
            label = label.strip()
            if label not in ("P0", "P1"):
                continue
            try:
                values = [float(v) for v in rest.split()]
            except ValueError:
                raise SnapsGraphError(f"{path}:{lineno}: {label} has a value that is not a number") from None
            if len(values) != 12:
                raise SnapsGraphError(f"{path}:{lineno}: {label} needs 12 numbers, found {len(values)}")
            mats[label] = np.array(values).reshape(3, 4)
        for label in ("P0", "P1"):
            if label not in mats:
                raise SnapsGraphError(f"{path}: no '{label}:' line (need P0 and P1 of the rectified grey cameras)")
        return cls.from_projections(mats["P0"], mats["P1"], source=str(path))

    def calib_text(self) -> str:
        def row(label: str, P: np.ndarray) -> str:
            return label + ": " + " ".join(f"{v:.12e}" for v in P.reshape(-1))

        return row("P0", self.P0) + "\n" + row("P1", self.P1) + "\n"

    def write_calib(self, path: str | Path) -> None:
        atomic_write_text(path, self.calib_text())

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """Eq. 1: z = f B / d; non-positive disparity gives 0 (invalid)."""
        d = np.asarray(disparity, dtype=np.float32)
        z = np.zeros_like(d)
        valid = d > 0
        z[valid] = (self.fx * self.baseline_m) / d[valid]
        return z

    def backproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Eq. 2: pixel (u, v) at depth z to a 3D point in the camera frame, shape (N, 3)."""
        x = z * (u - self.cx) / self.fx
        y = z * (v - self.cy) / self.fy
        return np.stack([x, y, z], axis=-1)


def kitti00_camera(width: int | None = None, height: int | None = None) -> StereoCamera:
    cam = StereoCamera.from_projections(KITTI00_P0, KITTI00_P1, *KITTI00_SIZE)
    if width and height and (width, height) != KITTI00_SIZE:
        cam = cam.scaled(width, height)
    return cam
