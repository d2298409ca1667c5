"""EuRoC MAV reader (ASL layout: docs/datasets.md): raw stereo, rectified once, optional ground truth.

Pairs are matched by timestamp (images listed but missing are skipped and noted) and rectified
with ``cv2.stereoRectify`` (alpha = 0); the body ground truth is interpolated at the frame times
for the rectified left camera, T_W_rect = T_W_B(t)·T_BS_cam0·T_raw_rect, frames outside its span
dropped. With ``cam0`` alone the sequence is monocular (undistorted, baseline 0).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..camera import StereoCamera
from ..errors import SnapsGraphError
from ..io_utils import parse_frame_range, read_text
from ..types import StereoFrame
from ._selection import FrameSelection
from .kitti import read_grey
from .rectify import StereoRectifier, interpolate_poses, match_stamps


def find_mav0(path: str | Path) -> Path | None:
    """The ``mav0`` folder of a EuRoC sequence at ``path`` (the folder itself or its parent)."""
    p = Path(path)
    for cand in (p, p / "mav0"):
        if (cand / "cam0").is_dir() and (cand / "cam1").is_dir():
            return cand
    for cand in (p, p / "mav0"):  # monocular: cam0 alone
        if (cand / "cam0" / "data.csv").is_file():
            return cand
    return None


def read_sensor_yaml(path: Path) -> dict:
    """A EuRoC camera ``sensor.yaml`` as K (3x3), D (4,), T_BS (4x4), size (w, h)."""
    import yaml

    text = "\n".join(l for l in read_text(path, "camera calibration").splitlines() if not l.startswith("%"))
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise SnapsGraphError(f"{path}: not valid YAML{line}") from None
    if not isinstance(d, dict):
        raise SnapsGraphError(f"{path}: expected a YAML mapping of camera fields")

    def numbers(key: str, n: int) -> np.ndarray:
        v = d.get(key)
        if isinstance(v, dict):
            v = v.get("data")
        try:
            arr = np.array(v, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise SnapsGraphError(f"{path}: '{key}' must be a list of numbers") from None
        if arr.size != n:
            raise SnapsGraphError(f"{path}: '{key}' needs {n} numbers, found {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise SnapsGraphError(f"{path}: '{key}' has non-finite numbers")
        return arr

    model = d.get("camera_model", "pinhole")
    if model != "pinhole":
        raise SnapsGraphError(f"{path}: camera_model '{model}' is not supported (pinhole only)")
    dist = d.get("distortion_model", "radial-tangential")
    if dist not in ("radial-tangential", "radtan", "plumb_bob"):
        raise SnapsGraphError(f"{path}: distortion_model '{dist}' is not supported (radial-tangential only)")
    fu, fv, cu, cv = numbers("intrinsics", 4)
    if fu <= 0 or fv <= 0:
        raise SnapsGraphError(f"{path}: focal lengths must be positive")
    w, h = numbers("resolution", 2).astype(int)
    T = numbers("T_BS", 16).reshape(4, 4)
    if abs(np.linalg.det(T[:3, :3]) - 1) > 1e-3 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise SnapsGraphError(f"{path}: T_BS is not a rigid transform")
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    return {"K": K, "D": numbers("distortion_coefficients", 4), "T_BS": T, "size": (int(w), int(h))}


def _read_image_list(csv_path: Path) -> tuple[np.ndarray, list[Path], int]:
    """(stamps ns, image paths, number listed but missing) from a EuRoC ``data.csv``."""
    text = read_text(csv_path, "image list")
    stamps, files, missing = [], [], 0
    folder = csv_path.parent / "data"
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [s.strip() for s in line.split(",")]
        if len(parts) < 2:
            raise SnapsGraphError(f"{csv_path}:{lineno}: expected 'timestamp,filename'")
        try:
            t = int(parts[0])
        except ValueError:
            raise SnapsGraphError(f"{csv_path}:{lineno}: timestamp '{parts[0]}' is not an integer (ns)") from None
        f = folder / parts[1]
        if not f.is_file():
            missing += 1
            continue
        stamps.append(t)
        files.append(f)
    ts = np.array(stamps, np.int64)
    if len(ts) > 1 and np.any(np.diff(ts) <= 0):
        order = np.argsort(ts, kind="stable")
        ts, files = ts[order], [files[i] for i in order]
        if np.any(np.diff(ts) == 0):
            raise SnapsGraphError(f"{csv_path}: repeated timestamps")
    return ts, files, missing


def _read_euroc_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t ns, positions (N,3), quaternions wxyz (N,4)) of the body from a EuRoC state csv."""
    rows = []
    for lineno, line in enumerate(read_text(path, "ground-truth").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(",")
        if len(parts) < 8:
            raise SnapsGraphError(f"{path}:{lineno}: expected at least 8 columns (t, p xyz, q wxyz)")
        try:
            rows.append((int(parts[0]), *(float(v) for v in parts[1:8])))
        except ValueError:
            raise SnapsGraphError(f"{path}:{lineno}: a value is not a number") from None
    if len(rows) < 2:
        raise SnapsGraphError(f"{path}: fewer than 2 ground-truth samples")
    t = np.array([r[0] for r in rows], np.int64)
    v = np.array([r[1:] for r in rows], float)
    if not np.all(np.isfinite(v)):
        raise SnapsGraphError(f"{path}: non-finite values")
    order = np.argsort(t, kind="stable")
    return t[order], v[order, :3], v[order, 3:7]


def _stereo_rectifier(mav0: Path) -> tuple[StereoRectifier, np.ndarray]:
    """The rectifier of a EuRoC rig from cam0/ and cam1/ sensor.yaml, and cam0's T_BS."""
    c0 = read_sensor_yaml(mav0 / "cam0" / "sensor.yaml")
    c1 = read_sensor_yaml(mav0 / "cam1" / "sensor.yaml")
    src = str(mav0 / "cam1" / "sensor.yaml")
    if c0["size"] != c1["size"]:
        raise SnapsGraphError(f"{src}: resolution {c1['size']} differs from cam0's {c0['size']}")
    T_c0_c1 = np.linalg.inv(c0["T_BS"]) @ c1["T_BS"]
    rect = StereoRectifier.from_calibration(c0["K"], c0["D"], c1["K"], c1["D"], T_c0_c1, c0["size"], source=src)
    return rect, c0["T_BS"]


def load_calibration(calib: str | Path):
    """(camera, None) from a calib.txt of rectified cameras; (None, rectifier) from a folder with
    EuRoC-style cam0/ and cam1/ sensor.yaml (raw cameras, rectified on the fly)."""
    p = Path(calib)
    if p.is_file():
        return StereoCamera.from_calib_file(p), None
    mav0 = find_mav0(p) if p.is_dir() else None
    if mav0 is None:
        raise SnapsGraphError(f"{p}: not a calib.txt nor a folder with cam0/sensor.yaml and cam1/sensor.yaml")
    return None, _stereo_rectifier(mav0)[0]


class MonoUndistorter:
    """cam0 alone: undistorted into a pinhole camera of the same orientation (the rectifier's
    interface, for a monocular sequence: ``rectify`` keeps the empty right image)."""

    def __init__(self, K: np.ndarray, D: np.ndarray, size: tuple[int, int], source: str):
        import cv2

        w, h = (int(v) for v in size)
        newK, _ = cv2.getOptimalNewCameraMatrix(np.asarray(K, float), np.asarray(D, float), (w, h), 0.0)
        if not np.all(np.isfinite(newK)) or newK[0, 0] <= 0 or newK[1, 1] <= 0:
            raise SnapsGraphError(f"{source}: the intrinsics and distortion give no valid undistorted camera")
        self._maps = cv2.initUndistortRectifyMap(np.asarray(K, float), np.asarray(D, float), None, newK, (w, h), cv2.CV_32FC1)
        self.camera = StereoCamera(float(newK[0, 0]), float(newK[1, 1]), float(newK[0, 2]), float(newK[1, 2]), 0.0, w, h)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        return cv2.remap(left, self._maps[0], self._maps[1], cv2.INTER_LINEAR), right

    def rect_pose(self, T: np.ndarray) -> np.ndarray:
        return np.asarray(T, float)


class EurocSequence(FrameSelection):
    """A EuRoC MAV stereo sequence, rectified, read frame by frame (the dataset protocol)."""

    def __init__(self, path: str | Path, frames: str | None = None, gt: str | Path | None = None):
        mav0 = find_mav0(path)
        if mav0 is None:
            raise SnapsGraphError(f"{path}: not a EuRoC sequence (no mav0/cam0 and mav0/cam1)")
        self.path = mav0
        self.notes: list[str] = []
        self.stereo = (mav0 / "cam1").is_dir()
        self.rectifier: StereoRectifier | MonoUndistorter
        if self.stereo:
            self.rectifier, self.T_BS0 = _stereo_rectifier(mav0)
        else:
            c0 = read_sensor_yaml(mav0 / "cam0" / "sensor.yaml")
            self.rectifier = MonoUndistorter(c0["K"], c0["D"], c0["size"], str(mav0 / "cam0" / "sensor.yaml"))
            self.T_BS0 = c0["T_BS"]
        self.camera = self.rectifier.camera

        t0, f0, miss0 = _read_image_list(mav0 / "cam0" / "data.csv")
        t1, f1, miss1 = _read_image_list(mav0 / "cam1" / "data.csv") if self.stereo else (t0, f0, 0)
        for cam, miss in (("cam0", miss0), ("cam1", miss1)):
            if miss:
                self.notes.append(f"{mav0 / cam / 'data.csv'}: {miss} listed images are missing from {cam}/data/ (skipped)")
        il, ir = match_stamps(t0, t1)
        unpaired = (len(t0) - len(il)) + (len(t1) - len(ir))
        if unpaired:
            self.notes.append(f"{mav0}: {len(t0) - len(il)} cam0 and {len(t1) - len(ir)} cam1 images have no partner (dropped)")
        if len(il) == 0:
            raise SnapsGraphError(f"{mav0}: no cam0/cam1 images share a timestamp")
        stamps = t0[il]
        lefts, rights = [f0[i] for i in il], [f1[i] for i in ir]

        gt_all = None
        gt_path = Path(gt) if gt is not None else mav0 / "state_groundtruth_estimate0" / "data.csv"
        if gt is not None or gt_path.is_file():
            tg, pg, qg = _read_euroc_groundtruth(gt_path)
            inside = (stamps >= tg[0]) & (stamps <= tg[-1])
            if not inside.any():
                raise SnapsGraphError(f"{gt_path}: its time span does not overlap the images'")
            if not inside.all():
                self.notes.append(f"{gt_path}: {int((~inside).sum())} frames outside the ground truth's time span (dropped)")
                keep = np.nonzero(inside)[0]
                stamps, lefts, rights = stamps[keep], [lefts[i] for i in keep], [rights[i] for i in keep]
            T_W_B = interpolate_poses((tg - tg[0]) * 1e-9, pg, qg, (stamps - tg[0]) * 1e-9)
            gt_all = self.rectifier.rect_pose(T_W_B @ self.T_BS0)
        self.gt_path: Path | None = gt_path if gt_all is not None else None
        self._gt_all = gt_all
        self._times_all = (stamps - stamps[0]) * 1e-9  # seconds from the first pair
        self.t0_ns = int(stamps[0])
        self._left, self._right = lefts, rights

        n_all = len(lefts)
        rng = parse_frame_range(frames, n_all)
        self.start, self.stop = (0, n_all) if rng is None else (rng[0], rng[1] if rng[1] is not None else n_all)
        self.raw_pair(0)  # the first pair now: an unreadable image or a wrong size stops before the run

    # ---- dataset protocol ----
    def raw_pair(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The unrectified images of frame ``i`` (position in the selection)."""
        k = self.start + i
        left = read_grey(self._left[k])
        right = read_grey(self._right[k]) if self.stereo else np.zeros((0, 0), np.uint8)
        want = (self.camera.height, self.camera.width)
        for p, img in ((self._left[k], left), (self._right[k], right)) if self.stereo else ((self._left[k], left),):
            if img.shape != want:
                raise SnapsGraphError(f"{p}: size {img.shape[1]}x{img.shape[0]} differs from sensor.yaml's {want[1]}x{want[0]}")
        return left, right

    def __getitem__(self, i: int) -> StereoFrame:
        k = self._position(i)
        left, right = self.rectifier.rectify(*self.raw_pair(k - self.start))
        return StereoFrame(k, float(self._times_all[k]), left, right)

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]
