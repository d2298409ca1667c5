"""One entry point for every input: ``open_dataset`` picks the reader by what the path holds.

| path holds                                   | reader                         |
|----------------------------------------------|--------------------------------|
| ``image_0/``, ``image_1/``, ``calib.txt``    | ``KittiSequence`` (KITTI, synth)|
| ``mav0/cam0``, ``mav0/cam1`` (or is ``mav0``)| ``EurocSequence``              |
| ``.bag`` file                                | ``RosbagSequence`` (ROS 1)     |
| folder with ``metadata.yaml``, ``.mcap``, ``.db3`` | ``RosbagSequence`` (ROS 2) |
| ``live:0,1`` / ``live:0`` (side by side)     | ``LiveStereo`` (needs ``calib``)|
"""

from __future__ import annotations

from pathlib import Path

from ..errors import SnapsGraphError
from ..io_utils import parse_frame_range
from ..types import StereoSource


def _dataset_kind(path: str | Path) -> str:
    """'kitti' | 'euroc' | 'bag' | 'live' for what ``path`` holds; a one-line error otherwise."""
    from .euroc import find_mav0
    from .rosbag import is_bag

    if str(path).startswith("live:"):
        return "live"
    p = Path(path)
    if not p.exists():
        raise SnapsGraphError(f"{p}: sequence folder not found (nor a bag file)")
    if is_bag(p):
        return "bag"
    if p.is_dir() and find_mav0(p) is not None:
        return "euroc"
    if p.is_dir():
        _wrong_folder(p)
        return "kitti"  # KittiSequence says what is missing
    raise SnapsGraphError(
        f"{p}: not a readable sequence (expected a KITTI folder with image_0/ and image_1/, a EuRoC mav0/ folder, "
        "a ROS 1 .bag, a ROS 2 bag folder or a .mcap/.db3 file)"
    )


def _wrong_folder(p: Path) -> None:
    """A one-line error naming the fix for the usual wrong folder: a EuRoC camera folder, or a
    KITTI root that holds sequences instead of being one."""
    if (p / "image_0").is_dir():
        return
    if p.name in ("cam0", "cam1") and ((p / "data.csv").is_file() or (p / "sensor.yaml").is_file()):
        mav0 = p.parent
        holder = mav0.parent if mav0.name == "mav0" else mav0
        raise SnapsGraphError(f"{p}: a EuRoC camera folder; pass the folder holding mav0/ ({holder})")
    for root in (p, p / "sequences"):
        seqs = (
            sorted(c.name for c in root.iterdir() if (c / "image_0").is_dir() or (c / "mav0").is_dir()) if root.is_dir() else []
        )
        if seqs:
            shown = ", ".join(seqs[:8]) + (", ..." if len(seqs) > 8 else "")
            raise SnapsGraphError(f"{p}: holds sequences {shown}: pass one of them (e.g. {root / seqs[0]})")


def open_dataset(
    path: str | Path,
    frames: str | None = None,
    gt: str | Path | None = None,
    left_topic: str | None = None,
    right_topic: str | None = None,
    calib: str | Path | None = None,
) -> StereoSource:
    """A dataset (``camera``, ``len``, iteration of ``StereoFrame``, ``timestamps``, ``gt_poses``)
    for a KITTI folder, a EuRoC sequence, a ROS 1/2 bag or a live device (``live:DEV[,DEV]``).
    ``calib`` (live sources; bags without CameraInfo): a calib.txt of rectified cameras or a folder
    with cam0/ and cam1/ sensor.yaml."""
    kind = _dataset_kind(path)
    if kind != "bag" and (left_topic or right_topic):
        raise SnapsGraphError(f"{path}: --left-topic/--right-topic apply to ROS bags only")
    if kind in ("kitti", "euroc") and calib is not None:
        raise SnapsGraphError(f"{path}: --calib applies to bags and live sources only (this dataset carries its calibration)")
    if kind == "kitti":
        from .kitti import KittiSequence

        return KittiSequence(path, frames=frames, gt=gt)
    if kind == "euroc":
        from .euroc import EurocSequence

        return EurocSequence(path, frames=frames, gt=gt)
    if kind == "bag":
        from .rosbag import RosbagSequence

        return RosbagSequence(path, frames=frames, gt=gt, left_topic=left_topic, right_topic=right_topic, calib=calib)
    return open_live(str(path), frames=frames, calib=calib)


def open_live(spec: str, frames: str | None = None, calib: str | Path | None = None, capture_factory=None):
    """``live:DEV`` (side by side) or ``live:DEV,DEV`` (left, right); ``frames`` ``A:B`` reads
    B - A frames (``:`` alone or None: until the device stops)."""
    from .euroc import load_calibration
    from .live import LiveStereo, open_capture

    devices = [d for d in spec[len("live:") :].split(",") if d.strip()]
    if len(devices) not in (1, 2):
        raise SnapsGraphError(f"{spec}: expected live:DEV (side by side) or live:LEFT,RIGHT")
    if calib is None:
        raise SnapsGraphError(f"{spec}: a live source needs --calib (a calib.txt, or a folder with cam0/ and cam1/ sensor.yaml)")
    camera, rectifier = load_calibration(calib)
    rng = parse_frame_range(frames)
    max_frames = None if rng is None or rng[1] is None else rng[1] - rng[0]
    factory = capture_factory or open_capture
    caps = [factory(d.strip()) for d in devices]
    return LiveStereo(
        caps[0], caps[1] if len(caps) == 2 else None, camera=camera, rectifier=rectifier, max_frames=max_frames, source=spec
    )
