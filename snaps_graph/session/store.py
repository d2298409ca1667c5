"""The session format: what a later run needs of this one to relocalise against it, close loops
with it (and, for a reader of the format, its graph). One folder, ``session/``, inside a run's results folder:

- ``session.json``: format name and version, the camera, image size, monocular or stereo, the loop
  settings the thumbnails and features depend on, the config's digest, which trajectory the poses
  are, and every other file's size and SHA-256 (a truncated or altered file is refused);
- ``thumbs.npy`` (N, h, w) uint8: the SNAPS thumbnails, memory-mapped when read;
- ``frames.npz``: per stream position the frame number, time, pose (the run's best trajectory,
  T_world_cam), odometry pose and distance driven;
- ``features.npz`` + ``ref_uv.npy``, ``ref_pts.npy``, ``ref_desc.npy``: the verifier's reference
  features (stream positions and offsets in the npz, the rows memory-mapped);
- ``factors.npz``: the run's own graph factors (pairs of stream positions, measurement, 6x6
  covariance in GTSAM's tangent order, robust or not).

docs/sessions.md describes the format for readers outside this package.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import StereoCamera
from ..errors import SnapsGraphError
from ..io_utils import atomic_output, atomic_write_text
from ..types import FrameFeatures

FORMAT = "snaps-graph session"
VERSION = 1
FOLDER = "session"  # inside a results folder
INDEX = "session.json"
MMAPPED = ("thumbs.npy", "ref_uv.npy", "ref_pts.npy", "ref_desc.npy")
ARCHIVES = {
    "frames.npz": ("frame_ids", "timestamps", "poses", "vo_poses", "driven"),
    "features.npz": ("refs", "ref_start"),
    "factors.npz": ("pairs", "measured", "covariance", "robust"),
}
CAMERA_REL_TOL = 1e-6  # intrinsics that differ by more than this share are another camera


@dataclass
class Factors:
    """A graph's between factors: ``pairs`` (F, 2) stream positions, ``measured`` (F, 4, 4)
    T_i_j, ``covariance`` (F, 6, 6), ``robust`` (F,) whether the loop kernel applies."""

    pairs: np.ndarray
    measured: np.ndarray
    covariance: np.ndarray
    robust: np.ndarray


@dataclass
class Session:
    """One run as a later run sees it (the arrays may be memory-mapped, read-only)."""

    name: str  # the results folder it was read from, or will be written to
    camera: StereoCamera
    image_size: tuple[int, int]  # (width, height)
    monocular: bool
    loop_settings: dict  # what thumbnails and features depend on: scale, window, detector
    config_digest: str
    trajectory: str  # which trajectory ``poses`` is (batch, isam2, snaps or vo)
    frame_ids: np.ndarray  # (N,) int64
    timestamps: np.ndarray  # (N,) s
    poses: np.ndarray  # (N, 4, 4) T_world_cam in the session's frame
    vo_poses: np.ndarray  # (N, 4, 4) the odometry's chain (carries a verified loop between references)
    driven: np.ndarray  # (N,) m
    thumbs: np.ndarray  # (N, h, w) uint8
    refs: np.ndarray  # (R,) stream positions with reference features
    ref_start: np.ndarray  # (R + 1,) rows of ref_uv / ref_pts / ref_desc per reference
    ref_uv: np.ndarray
    ref_pts: np.ndarray
    ref_desc: np.ndarray
    factors: Factors
    gt_origin: np.ndarray | None = None  # the ground truth's pose of the session frame's origin, when known
    desc_dtype: str = ""  # the descriptors' type when stored narrower ("float32": SIFT's whole 0-255 values as uint8)

    def __len__(self) -> int:
        return len(self.frame_ids)

    def references(self) -> Mapping[int, FrameFeatures]:
        """The reference features by stream position, each made when asked for (a prior's
        thousands of references stay on disk until a loop needs one)."""
        return _References(self)

    def features(self, r: int) -> FrameFeatures:
        """Reference ``r``'s features (views of the stored rows)."""
        a, b = int(self.ref_start[r]), int(self.ref_start[r + 1])
        desc = self.ref_desc[a:b]
        return FrameFeatures(self.ref_uv[a:b], self.ref_pts[a:b], desc.astype(self.desc_dtype) if self.desc_dtype else desc)


class _References(Mapping[int, FrameFeatures]):
    """:meth:`Session.references`: stream position -> that reference's features, on demand."""

    def __init__(self, s: Session):
        self._session = s
        self._row = {int(k): r for r, k in enumerate(s.refs)}

    def __getitem__(self, k: int) -> FrameFeatures:
        return self._session.features(self._row[k])

    def __iter__(self) -> Iterator[int]:
        return iter(self._row)

    def __len__(self) -> int:
        return len(self._row)


def session_folder(run: str | Path) -> Path:
    return Path(run) / FOLDER


def loop_settings(cfg) -> dict:
    """What a session's thumbnails and reference features depend on (``Config``): a prior made
    under other values cannot be compared with this run."""
    return {"thumbnail_scale": cfg.loop.thumbnail_scale, "window": cfg.loop.window, "detector": cfg.verification.detector}


def check_compatible(s: Session, camera: StereoCamera, settings: dict) -> None:
    """A one-line SnapsGraphError naming the session's index unless its camera and its loop
    settings are this run's (the image size: :func:`check_image_size`, at the first frame)."""
    where = session_folder(s.name) / INDEX
    c = s.camera
    for key in ("fx", "fy", "cx", "cy", "baseline_m"):
        a, b = float(getattr(camera, key)), float(getattr(c, key))
        if abs(a - b) > CAMERA_REL_TOL * max(abs(a), abs(b), 1.0):
            raise SnapsGraphError(
                f"{where}: recorded with another camera ({key} {b:g} there, {a:g} here); a prior must come from the same camera"
            )
    for key, value in settings.items():
        if s.loop_settings.get(key) != value:
            raise SnapsGraphError(
                f"{where}: its thumbnails and features were made with {key} = {s.loop_settings.get(key)!r}, this run uses {value!r}"
            )


def check_image_size(s: Session, image_size: tuple[int, int]) -> None:
    """A one-line SnapsGraphError naming the session's index unless its images were (width, height)."""
    if tuple(image_size) != tuple(s.image_size):
        raise SnapsGraphError(
            f"{session_folder(s.name) / INDEX}: images of {s.image_size[0]}x{s.image_size[1]} there, "
            f"{image_size[0]}x{image_size[1]} here; a prior must come from the same camera"
        )


def write_session(folder: str | Path, s: Session) -> None:
    """Write ``s`` into ``folder`` (created; each file atomically, the index last)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {
        "thumbs.npy": np.ascontiguousarray(s.thumbs, np.uint8),
        "ref_uv.npy": np.ascontiguousarray(s.ref_uv, np.float32),
        "ref_pts.npy": np.ascontiguousarray(s.ref_pts, np.float32),
        "ref_desc.npy": _narrow(s.ref_desc),
    }
    for name, arr in arrays.items():
        with atomic_output(folder / name) as tmp, open(tmp, "wb") as fh:
            np.save(fh, arr, allow_pickle=False)
    f = s.factors
    archives: dict[str, dict[str, np.ndarray]] = {
        "frames.npz": {
            "frame_ids": s.frame_ids,
            "timestamps": s.timestamps,
            "poses": s.poses,
            "vo_poses": s.vo_poses,
            "driven": s.driven,
        }
        | ({} if s.gt_origin is None else {"gt_origin": s.gt_origin}),
        "features.npz": {"refs": s.refs, "ref_start": s.ref_start},
        "factors.npz": {"pairs": f.pairs, "measured": f.measured, "covariance": f.covariance, "robust": f.robust},
    }
    for name, content in archives.items():
        with atomic_output(folder / name) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, allow_pickle=False, **content)
    c = s.camera
    index = {
        "format": FORMAT,
        "version": VERSION,
        "frames": len(s),
        "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "baseline_m": c.baseline_m},
        "image_size": list(s.image_size),
        "monocular": s.monocular,
        "loop": s.loop_settings,
        "config_digest": s.config_digest,
        "trajectory": s.trajectory,
        "descriptors": str(np.asarray(s.ref_desc).dtype),
        "files": {p.name: {"bytes": p.stat().st_size, "sha256": _sha256(p)} for p in sorted(folder.iterdir())},
    }
    atomic_write_text(folder / INDEX, json.dumps(index, indent=1) + "\n")


def _narrow(desc: np.ndarray) -> np.ndarray:
    """SIFT's float32 descriptors hold whole numbers 0-255: stored as uint8, a quarter of the size."""
    desc = np.ascontiguousarray(desc)
    if desc.dtype == np.float32 and desc.size and np.all((desc >= 0) & (desc <= 255) & (desc == np.round(desc))):
        return desc.astype(np.uint8)
    return desc


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_session(run: str | Path) -> Session:
    """The session of results folder ``run``, checked whole (a one-line SnapsGraphError naming the
    file otherwise); the large arrays memory-mapped read-only."""
    run = Path(run)
    folder = session_folder(run)
    index_path = folder / INDEX
    if not run.is_dir():
        raise SnapsGraphError(f"{run}: prior not found (give a results folder of an earlier run)")
    if not index_path.is_file():
        raise SnapsGraphError(f"{index_path}: not found: {run} is not the results folder of a run that kept its session")
    index = _read_index(index_path)
    _check_files(folder, index)
    loaded = {name: _load_archive(folder / name, keys) for name, keys in ARCHIVES.items()}
    big = {name: _load_mmap(folder / name) for name in MMAPPED}
    fr, fe, fa = loaded["frames.npz"], loaded["features.npz"], loaded["factors.npz"]
    s = Session(
        name=str(run),
        camera=_camera(index, index_path),
        image_size=(int(index["image_size"][0]), int(index["image_size"][1])),
        monocular=bool(index["monocular"]),
        loop_settings=dict(index["loop"]),
        config_digest=str(index["config_digest"]),
        trajectory=str(index["trajectory"]),
        frame_ids=fr["frame_ids"].astype(np.int64),
        timestamps=fr["timestamps"],
        poses=fr["poses"],
        vo_poses=fr["vo_poses"],
        driven=fr["driven"],
        thumbs=big["thumbs.npy"],
        refs=fe["refs"].astype(np.int64),
        ref_start=fe["ref_start"].astype(np.int64),
        ref_uv=big["ref_uv.npy"],
        ref_pts=big["ref_pts.npy"],
        ref_desc=big["ref_desc.npy"],
        factors=Factors(fa["pairs"].astype(np.int64), fa["measured"], fa["covariance"], fa["robust"].astype(bool)),
        gt_origin=fr.get("gt_origin"),
    )
    stored = str(s.ref_desc.dtype)
    wanted = str(index.get("descriptors", stored))
    if wanted not in ("uint8", "float32"):
        raise SnapsGraphError(f"{index_path}: descriptors of type {wanted!r}: expected uint8 or float32")
    s.desc_dtype = "" if wanted == stored else wanted
    _check_shapes(s, index, folder)
    return s


def _read_index(path: Path) -> dict:
    try:
        index = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SnapsGraphError(f"{path}: not a readable session index ({type(exc).__name__})") from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise SnapsGraphError(f"{path}: not a {FORMAT} index")
    if index.get("version") != VERSION:
        raise SnapsGraphError(
            f"{path}: session format version {index.get('version')!r}; this snaps-graph reads version {VERSION}"
        )
    need = ("frames", "camera", "image_size", "monocular", "loop", "config_digest", "trajectory", "files")
    missing = [k for k in need if k not in index]
    if missing:
        raise SnapsGraphError(f"{path}: session index lacks {', '.join(missing)}")
    return index


def _check_files(folder: Path, index: dict) -> None:
    """Every file the index lists, at its size and digest (a cut-short copy or an edited file)."""
    files = index["files"]
    for name in (*MMAPPED, *ARCHIVES):
        entry = files.get(name) if isinstance(files, dict) else None
        path = folder / name
        if not isinstance(entry, dict):
            raise SnapsGraphError(f"{folder / INDEX}: lists no {name}")
        if not path.is_file():
            raise SnapsGraphError(f"{path}: missing from the session")
        if path.stat().st_size != entry.get("bytes"):
            raise SnapsGraphError(
                f"{path}: {path.stat().st_size} bytes, the session recorded {entry.get('bytes')}: truncated or replaced"
            )
        if _sha256(path) != entry.get("sha256"):
            raise SnapsGraphError(f"{path}: contents differ from what the session recorded (corrupted)")


def _load_archive(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The archive's arrays ``keys`` (all required) and any other it holds (optional ones)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.array(z[k]) for k in keys} | {k: np.array(z[k]) for k in z.files if k not in keys}
    except (OSError, ValueError, KeyError) as exc:
        raise SnapsGraphError(f"{path}: not a readable session archive ({type(exc).__name__})") from None


def _load_mmap(path: Path) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SnapsGraphError(f"{path}: not a readable array ({type(exc).__name__})") from None


def _camera(index: dict, path: Path) -> StereoCamera:
    c = index["camera"]
    try:
        values = [float(c[k]) for k in ("fx", "fy", "cx", "cy", "baseline_m")]
        w, h = (int(v) for v in index["image_size"])
    except (TypeError, KeyError, ValueError):
        raise SnapsGraphError(f"{path}: the camera or image size is malformed") from None
    if not all(math.isfinite(v) for v in values) or values[0] <= 0 or values[1] <= 0 or w <= 0 or h <= 0:
        raise SnapsGraphError(f"{path}: the camera or image size is out of range")
    fx, fy, cx, cy, baseline = values
    return StereoCamera(fx, fy, cx, cy, baseline, width=w, height=h)


def _check_shapes(s: Session, index: dict, folder: Path) -> None:
    n, r = len(s), len(s.refs)
    checks = [
        (int(index["frames"]) == n, "frames.npz", f"{n} frames, the index says {index['frames']}"),
        (n > 0, "frames.npz", "no frames"),
        (s.poses.shape == (n, 4, 4) and s.vo_poses.shape == (n, 4, 4), "frames.npz", "poses of the wrong shape"),
        (s.timestamps.shape == (n,) and s.driven.shape == (n,), "frames.npz", "times or distances of the wrong length"),
        (bool(np.all(np.isfinite(s.poses))) and bool(np.all(np.isfinite(s.vo_poses))), "frames.npz", "non-finite poses"),
        (
            s.thumbs.ndim == 3 and len(s.thumbs) == n and s.thumbs.dtype == np.uint8,
            "thumbs.npy",
            "not one uint8 thumbnail per frame",
        ),
        (s.ref_start.shape == (r + 1,), "features.npz", "reference offsets of the wrong length"),
        (r == 0 or bool(np.all((s.refs >= 0) & (s.refs < n))), "features.npz", "a reference outside the frames"),
        (
            r == 0 or (s.ref_start[0] == 0 and bool(np.all(np.diff(s.ref_start) >= 0))),
            "features.npz",
            "reference offsets not increasing",
        ),
        (
            len(s.ref_uv) == len(s.ref_pts) == len(s.ref_desc) == (int(s.ref_start[-1]) if r else 0),
            "ref_uv.npy",
            "feature rows do not match the offsets",
        ),
        (
            bool(np.all((s.factors.pairs >= 0) & (s.factors.pairs < n))) if len(s.factors.pairs) else True,
            "factors.npz",
            "a factor outside the frames",
        ),
        (bool(np.all(np.diff(s.frame_ids) > 0)), "frames.npz", "frame numbers not increasing"),
        (
            s.gt_origin is None or (s.gt_origin.shape == (4, 4) and bool(np.all(np.isfinite(s.gt_origin)))),
            "frames.npz",
            "a malformed ground-truth origin",
        ),
    ]
    for ok, name, why in checks:
        if not ok:
            raise SnapsGraphError(f"{folder / name}: {why}")
