"""Trajectory files: KITTI (12 numbers a line, row-major 3x4) and TUM (t x y z qx qy qz qw).

Poses are an (N, 4, 4) float array of T_world_cam. Writers are atomic and produce exactly what
evo's ``evo_ape kitti`` / ``evo_ape tum`` read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import SnapsGraphError
from .geometry import quaternion_to_rotation, rotation_to_quaternion
from .io_utils import atomic_write_text, read_text

ROTATION_TOLERANCE = 1e-2  # max |R R^T - I| of a KITTI pose line's rotation


def read_kitti_poses(path: str | Path) -> np.ndarray:
    path = Path(path)
    poses = []
    for lineno, line in enumerate(read_text(path, "pose").splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise SnapsGraphError(f"{path}:{lineno}: not a number in a KITTI pose line") from None
        if len(vals) != 12:
            raise SnapsGraphError(f"{path}:{lineno}: a KITTI pose line needs 12 numbers, found {len(vals)}")
        T = np.eye(4)
        T[:3, :4] = np.array(vals).reshape(3, 4)
        if not np.all(np.isfinite(T)):
            raise SnapsGraphError(f"{path}:{lineno}: non-finite pose")
        _check_rotation(T[:3, :3], f"{path}:{lineno}")
        poses.append(T)
    if not poses:
        raise SnapsGraphError(f"{path}: no poses")
    return np.array(poses)


def _check_rotation(R: np.ndarray, where: str) -> None:
    """A pose line's 3x3 part must be a rotation (loosely: files hold 6-9 digits)."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        raise SnapsGraphError(f"{where}: the 3x3 part is not a rotation (|R R^T - I| = {err:.3g}, det = {np.linalg.det(R):.3g})")


def kitti_text(poses: np.ndarray) -> str:
    rows = []
    for T in np.asarray(poses):
        rows.append(" ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1)))
    return "\n".join(rows) + "\n"


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    poses = np.asarray(poses)
    if not np.all(np.isfinite(poses)):
        raise ValueError("refusing to write non-finite poses")
    atomic_write_text(path, kitti_text(poses))


def tum_text(poses: np.ndarray, times: np.ndarray | None = None) -> str:
    poses = np.asarray(poses)
    if times is None:
        times = np.arange(len(poses), dtype=float) * 0.1
    rows = []
    for t, T in zip(times, poses):
        q = rotation_to_quaternion(T[:3, :3])
        p = T[:3, 3]
        rows.append(f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return "\n".join(rows) + "\n"


def write_tum_poses(path: str | Path, poses: np.ndarray, times: np.ndarray | None = None) -> None:
    poses = np.asarray(poses)
    if not np.all(np.isfinite(poses)):
        raise ValueError("refusing to write non-finite poses")
    if times is not None and len(times) != len(poses):
        raise ValueError("times and poses differ in length")
    if times is not None and not np.all(np.isfinite(times)):
        raise ValueError("refusing to write non-finite timestamps")
    atomic_write_text(path, tum_text(poses, times))


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    path = Path(path)
    times, poses = [], []
    for lineno, line in enumerate(read_text(path, "pose").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise SnapsGraphError(f"{path}:{lineno}: not a number in a TUM line") from None
        if len(vals) != 8:
            raise SnapsGraphError(f"{path}:{lineno}: a TUM line needs 8 numbers, found {len(vals)}")
        if not all(math.isfinite(v) for v in vals):
            raise SnapsGraphError(f"{path}:{lineno}: non-finite number in a TUM line")
        if not np.linalg.norm(vals[4:8]) > 1e-9:
            raise SnapsGraphError(f"{path}:{lineno}: zero quaternion")
        T = np.eye(4)
        T[:3, :3] = quaternion_to_rotation(vals[4:8])
        T[:3, 3] = vals[1:4]
        times.append(vals[0])
        poses.append(T)
    if not poses:
        raise SnapsGraphError(f"{path}: no poses")
    return np.array(times), np.array(poses)


def read_poses(path: str | Path) -> np.ndarray:
    """Read a KITTI or TUM file, by its extension (.tum = TUM, anything else = KITTI)."""
    path = Path(path)
    if path.suffix.lower() == ".tum":
        return read_tum_poses(path)[1]
    return read_kitti_poses(path)


def read_times(path: str | Path) -> np.ndarray:
    """Timestamps (s), one a line (first number of the line); they must be finite and increase."""
    path = Path(path)
    out: list[float] = []
    for lineno, line in enumerate(read_text(path, "times").splitlines(), 1):
        if not line.strip():
            continue
        try:
            t = float(line.split()[0])
        except ValueError:
            raise SnapsGraphError(f"{path}:{lineno}: not a number") from None
        if not math.isfinite(t):
            raise SnapsGraphError(f"{path}:{lineno}: timestamp {t} is not finite")
        if out and not t > out[-1]:
            raise SnapsGraphError(f"{path}:{lineno}: timestamp {t} does not increase (previous {out[-1]})")
        out.append(t)
    if not out:
        raise SnapsGraphError(f"{path}: no timestamps")
    return np.array(out)


def write_times(path: str | Path, times: np.ndarray) -> None:
    if not np.all(np.isfinite(times)):
        raise ValueError("refusing to write non-finite timestamps")
    atomic_write_text(path, "".join(f"{t:.6e}\n" for t in times))


ODOMETRY_FORMATS = ("kitti", "tum")


@dataclass
class PoseFile:
    """An odometry pose file as read: ``fmt`` "kitti" (``keys`` = frame numbers: line i holds
    frame i) or "tum" (``keys`` = timestamps, s); ``lines`` the 1-based line of each pose."""

    path: str
    fmt: str
    keys: np.ndarray  # (N,) frame numbers (kitti) or timestamps (tum), increasing
    poses: np.ndarray  # (N, 4, 4) T_world_cam
    lines: np.ndarray  # (N,) int


def read_pose_file(path: str | Path, fmt: str | None = None) -> PoseFile:
    """Read an odometry file, KITTI (12 numbers a line) or TUM (``t x y z qx qy qz qw``); ``fmt``
    None: by the column count of the first pose line. Every defect is a one-line error naming
    the file and the line: wrong column count, a non-number, NaN or infinity, a 3x3 part that
    is not a rotation (or a quaternion that is not a unit one), timestamps that do not increase,
    a blank line between KITTI poses (it would shift every later frame), no pose at all."""
    path = Path(path)
    if fmt is not None and fmt not in ODOMETRY_FORMATS:
        raise SnapsGraphError(f"{path}: odometry format must be one of {', '.join(ODOMETRY_FORMATS)}, not '{fmt}'")
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(read_text(path, "odometry").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            rows.append((lineno, []))
            continue
        rows.append((lineno, s.replace(",", " ").split()))
    first = next((r for _, r in rows if r), None)
    if first is None:
        raise SnapsGraphError(f"{path}: no poses (the file is empty)")
    if fmt is None:
        if len(first) not in (8, 12):
            lineno = next(n for n, r in rows if r)
            raise SnapsGraphError(
                f"{path}:{lineno}: {len(first)} numbers: neither a KITTI pose line (12) nor a TUM line (8: t x y z qx qy qz qw)"
            )
        fmt = "kitti" if len(first) == 12 else "tum"
    want = 12 if fmt == "kitti" else 8
    keys, poses, lines = [], [], []
    seen_blank = 0
    for lineno, fields in rows:
        where = f"{path}:{lineno}"
        if not fields:
            seen_blank = seen_blank or (lineno if poses else 0)
            continue
        if fmt == "kitti" and seen_blank:
            raise SnapsGraphError(f"{path}:{seen_blank}: blank line between KITTI poses (line i must hold frame i)")
        if len(fields) != want:
            raise SnapsGraphError(f"{where}: a {fmt.upper()} pose line needs {want} numbers, found {len(fields)}")
        try:
            vals = [float(v) for v in fields]
        except ValueError:
            raise SnapsGraphError(f"{where}: not a number in a {fmt.upper()} pose line") from None
        if not all(math.isfinite(v) for v in vals):
            raise SnapsGraphError(f"{where}: NaN or infinite number in a pose line")
        T = np.eye(4)
        if fmt == "kitti":
            T[:3, :4] = np.array(vals).reshape(3, 4)
            _check_rotation(T[:3, :3], where)
            keys.append(float(len(poses)))
        else:
            q = np.array(vals[4:8])
            if abs(float(np.linalg.norm(q)) - 1.0) > ROTATION_TOLERANCE:
                raise SnapsGraphError(f"{where}: the quaternion is not a rotation (|q| = {np.linalg.norm(q):.3g}, not 1)")
            if keys and not vals[0] > keys[-1]:
                raise SnapsGraphError(f"{where}: timestamp {vals[0]!r} does not increase (previous {keys[-1]!r})")
            T[:3, :3] = quaternion_to_rotation(q)
            T[:3, 3] = vals[1:4]
            keys.append(vals[0])
        poses.append(T)
        lines.append(lineno)
    return PoseFile(str(path), fmt, np.array(keys), np.array(poses), np.array(lines, int))
