"""Inputs beyond KITTI folders (EuRoC, ROS 1/2 bags, live devices), convert, and the rerun log."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from snaps_graph.config import Config
from snaps_graph.datasets.euroc import EurocSequence
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.datasets.open import open_dataset, open_live
from snaps_graph.datasets.rectify import StereoRectifier
from snaps_graph.datasets.rosbag import RosbagSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import run_sequence

sys.path.insert(0, str(Path(__file__).parent))
from bagutil import make_image, write_stereo_bag  # noqa: E402
from conftest import SHARED_DATA, _need, need_extra  # noqa: E402
from inprocess import Ran  # noqa: E402
from inprocess import cli as run_cli  # noqa: E402

N_BAG = 8  # frames of the KITTI 06 clip written into test bags


@pytest.fixture(scope="module")
def euroc_dir() -> Path:
    """EuRoC V1_01_easy, first 95 raw stereo frames, no ground truth (cam1 lists 4 missing images)."""
    return _need(SHARED_DATA / "euroc" / "V1_01_easy_first95")


def cli(*args: str) -> Ran:
    return run_cli(*args)  # in this process (tests/inprocess.py)


def run_poses(seq) -> dict[str, np.ndarray]:
    pipe = SlamPipeline(seq.camera, Config(), loops="snaps", refine="none")
    for f in seq:
        pipe.process(f)
    return pipe.finish().trajectories


def sift_row_offsets(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """v_left - v_right of SIFT matches (ratio test) between two images, sub-pixel."""
    sift = cv2.SIFT_create(1500)
    k1, d1 = sift.detectAndCompute(left, None)
    k2, d2 = sift.detectAndCompute(right, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in pairs if m.distance < 0.7 * n.distance]
    return np.array([k1[m.queryIdx].pt[1] - k2[m.trainIdx].pt[1] for m in good])


# ---------------------------------------------------------------- EuRoC


def test_euroc_pairs_what_exists_and_rectifies_rows(euroc_dir):
    seq = open_dataset(euroc_dir)
    assert type(seq).__name__ == "EurocSequence"
    assert isinstance(seq, EurocSequence) and isinstance(seq.rectifier, StereoRectifier)
    assert len(seq) == 95 and seq.gt_poses is None
    assert any("4 listed images are missing" in n for n in seq.notes)
    cam = seq.camera
    assert (cam.width, cam.height) == (752, 480)
    assert 0.10 < cam.baseline_m < 0.12  # the VI-Sensor's 11 cm
    # In the rectified frame the right camera sits on +x: the rectifying rotation is right.
    from snaps_graph.datasets.euroc import read_sensor_yaml

    c0, c1 = (read_sensor_yaml(seq.path / c / "sensor.yaml") for c in ("cam0", "cam1"))
    t01 = (np.linalg.inv(c0["T_BS"]) @ c1["T_BS"])[:3, 3]
    d = seq.rectifier.R_rect_raw @ t01
    assert d[0] > 0 and np.hypot(d[1], d[2]) < 1e-9 * np.linalg.norm(d) + 1e-12
    for i in (0, 47, 94):
        f = seq[i]
        assert f.left.dtype == np.uint8 and f.left.shape == (480, 752)
        dv = sift_row_offsets(f.left, f.right)
        dv = dv[np.abs(dv) < 10]  # drop the few outright false matches
        assert len(dv) > 100
        assert np.median(np.abs(dv)) <= 0.5, (i, np.median(np.abs(dv)))
        raw_dv = sift_row_offsets(*seq.raw_pair(i))
        assert np.median(np.abs(raw_dv)) > 3.0  # raw rows are ~12 px apart: the check can fail


def _euroc_copy(src: Path, dst: Path) -> Path:
    """A EuRoC folder beside ``src``'s images (symlinked), to add files to."""
    for cam in ("cam0", "cam1"):
        (dst / "mav0" / cam).mkdir(parents=True)
        shutil.copy(src / "mav0" / cam / "sensor.yaml", dst / "mav0" / cam / "sensor.yaml")
        shutil.copy(src / "mav0" / cam / "data.csv", dst / "mav0" / cam / "data.csv")
        os.symlink((src / "mav0" / cam / "data").resolve(), dst / "mav0" / cam / "data")
    return dst


def test_euroc_ground_truth_for_the_rectified_left_camera(euroc_dir, tmp_path):
    root = _euroc_copy(euroc_dir, tmp_path / "seq")
    t_img = np.array([int(l.split(",")[0]) for l in (root / "mav0/cam0/data.csv").read_text().splitlines()[1:]], np.int64)
    # Body at 200 Hz from 0.12 s after the first image: moving 0.5 m/s along world x and yawing
    # 0.2 rad/s about world z; the first frames fall before the ground truth.
    t_gt = np.arange(t_img[0] + 120_000_000, t_img[-1] + 10_000_000, 5_000_000, dtype=np.int64)
    s = (t_gt - t_gt[0]) * 1e-9
    yaw = 0.2 * s
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for t, x, a in zip(t_gt, 0.5 * s, yaw):
        lines.append(f"{t},{x:.9f},1.0,2.0,{np.cos(a / 2):.12f},0,0,{np.sin(a / 2):.12f},0,0,0")
    (root / "mav0/state_groundtruth_estimate0").mkdir()
    (root / "mav0/state_groundtruth_estimate0/data.csv").write_text("\n".join(lines) + "\n")

    seq = open_dataset(root)
    assert isinstance(seq, EurocSequence) and isinstance(seq.rectifier, StereoRectifier)
    n_before = int(np.sum(t_img < t_gt[0]))
    assert n_before == 3 and len(seq) == 95 - n_before
    assert any("outside the ground truth" in n for n in seq.notes)
    gt = seq.gt_poses
    assert gt is not None
    assert gt.shape == (len(seq), 4, 4) and np.allclose(gt[0], np.eye(4))
    # Relative rotation angle = the body's yaw change; rigid offsets cancel in the angle.
    t_frames = t_img[n_before:]
    dyaw = 0.2 * (t_frames - t_frames[0]) * 1e-9
    ang = np.arccos(np.clip((np.trace(gt[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert np.allclose(ang, dyaw, atol=1e-6)
    # Expected pose, composed by hand: camera_k in camera_0 = (W_B0 B_C R1ᵀ)⁻¹ (W_Bk B_C R1ᵀ).
    from snaps_graph.datasets.euroc import read_sensor_yaml

    T_BS = read_sensor_yaml(root / "mav0/cam0/sensor.yaml")["T_BS"]
    T_raw_rect = np.eye(4)
    T_raw_rect[:3, :3] = seq.rectifier.R_rect_raw.T

    def body(t_ns):
        a, x = 0.2 * (t_ns - t_gt[0]) * 1e-9, 0.5 * (t_ns - t_gt[0]) * 1e-9
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        T[:3, 3] = [x, 1.0, 2.0]
        return T @ T_BS @ T_raw_rect

    want = np.array([np.linalg.inv(body(t_frames[0])) @ body(t) for t in t_frames])
    assert np.abs(gt - want).max() < 1e-6  # interpolated between 200 Hz samples
    # Metres moved: the body's path length (camera offset turns with the body, so compare a chord).
    assert abs(np.linalg.norm(gt[-1, :3, 3]) - np.linalg.norm(want[-1, :3, 3])) < 1e-6


@pytest.mark.parametrize(
    "mangle, expect",
    [
        (
            lambda t: t.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]"),
            "'intrinsics' needs 4 numbers",
        ),
        (lambda t: t.replace("T_BS:", "T_BS: [1, 2\nbroken:"), "not valid YAML"),
        (lambda t: t.replace("radial-tangential", "equidistant"), "distortion_model 'equidistant' is not supported"),
    ],
)
def test_malformed_sensor_yaml_is_one_line(euroc_dir, tmp_path, mangle, expect):
    root = _euroc_copy(euroc_dir, tmp_path / "seq")
    y = root / "mav0/cam0/sensor.yaml"
    y.write_text(mangle(y.read_text()))
    proc = cli("run", str(root), "--out", str(tmp_path / "out"))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "sensor.yaml" in lines[0] and expect in lines[0], proc.stderr


def test_euroc_95_frames_end_to_end(euroc_dir, tmp_path):
    out = tmp_path / "run"
    proc = cli("run", str(euroc_dir), "--out", str(out), "--refine", "isam2")
    assert proc.returncode == 0, proc.stderr
    assert "95 frames" in proc.stdout and "4 listed images are missing" in proc.stderr
    from snaps_graph.trajectory_io import read_kitti_poses

    for name in ("vo", "snaps", "isam2"):
        p = read_kitti_poses(out / f"poses_{name}.txt")
        assert p.shape == (95, 4, 4) and np.all(np.isfinite(p))
    import csv

    rows = list(csv.DictReader(open(out / "frames.csv")))
    flagged = [r["frame"] for r in rows if r["vo_ok"] == "0"]
    assert not flagged, flagged  # measured: none
    # The MAV stands on the ground for these 4.7 s (frames 0 and 94 show the same view, only the
    # exposure differs): the VO must not wander (measured: 3 mm end, 1.5 cm path).
    vo = read_kitti_poses(out / "poses_vo.txt")
    assert np.linalg.norm(vo[-1, :3, 3]) < 0.05


# ---------------------------------------------------------------- ROS bags


@pytest.fixture(scope="module")
def kitti8(kitti06_dir):
    return KittiSequence(kitti06_dir, frames=f"0:{N_BAG}")


@pytest.fixture(scope="module")
def kitti8_poses(kitti8):
    return run_poses(kitti8)


@pytest.mark.parametrize("kind, compressed, name", [("mcap", False, "b.mcap"), ("ros1", True, "b.bag")])
def test_bag_gives_the_folders_poses(kind, compressed, name, kitti8, kitti8_poses, tmp_path):
    bag_dir = tmp_path / "bag"
    write_stereo_bag(bag_dir, kitti8, kind, compressed=compressed) if kind != "ros1" else write_stereo_bag(
        tmp_path / name, kitti8, kind, compressed=compressed
    )
    path = bag_dir if kind != "ros1" else tmp_path / name
    if kind == "mcap":
        assert list(bag_dir.glob("*.mcap"))  # a real MCAP storage file inside the ROS 2 bag folder
    seq = open_dataset(path)
    assert type(seq).__name__ == "RosbagSequence" and len(seq) == N_BAG and not seq.notes
    assert isinstance(seq, RosbagSequence)
    assert seq.camera == kitti8.camera
    assert np.allclose(seq.timestamps, kitti8.timestamps, atol=1e-9)
    poses = run_poses(seq)
    for k in ("vo", "snaps"):
        assert np.abs(poses[k][:, :3, 3] - kitti8_poses[k][:, :3, 3]).max() <= 1e-6
    assert np.array_equal(seq[5].left, kitti8[5].left)  # random access too


def test_bag_sqlite3_and_bare_mcap(kitti8, tmp_path):
    write_stereo_bag(tmp_path / "sq", kitti8, "sqlite3", n=3)
    write_stereo_bag(tmp_path / "mc", kitti8, "mcap", n=3)
    for path in (tmp_path / "sq", next((tmp_path / "mc").glob("*.mcap"))):
        seq = open_dataset(path)
        assert len(seq) == 3 and all(np.array_equal(a.right, b.right) for a, b in zip(seq, (kitti8[i] for i in range(3))))


def test_bag_raw_images_rectified_from_camera_info(euroc_dir, tmp_path):
    """A bag of EuRoC's raw pairs with CameraInfo K, D, R, P gives EuRoC's rectified pairs."""
    eu = open_dataset(euroc_dir, frames="0:3")
    assert isinstance(eu, EurocSequence) and isinstance(eu.rectifier, StereoRectifier)
    pairs = [(eu.timestamps[i], *eu.raw_pair(i)) for i in range(3)]
    write_stereo_bag(tmp_path / "raw", None, "mcap", raw_pairs=pairs, infos=eu.rectifier.info, prefix="/cam")
    seq = open_dataset(tmp_path / "raw")
    assert isinstance(seq, RosbagSequence)
    assert seq.rectifier is not None and seq.camera == eu.camera
    for a, b in zip(seq, eu):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    # EuRoC's own bags carry no CameraInfo: --calib gives the sensor.yaml pair instead.
    write_stereo_bag(tmp_path / "nocal", None, "mcap", raw_pairs=pairs, infos=eu.rectifier.info, prefix="/x", camera_info=False)
    with pytest.raises(SnapsGraphError, match="give the calibration with --calib"):
        open_dataset(tmp_path / "nocal")
    seq = open_dataset(tmp_path / "nocal", calib=euroc_dir)
    assert seq.camera == eu.camera and all(np.array_equal(a.right, b.right) for a, b in zip(seq, eu))


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "rgb8", "bgr8"])
def test_image_encodings(encoding, kitti8):
    need_extra("rosbags")
    from rosbags.typesys import Stores, get_typestore

    from snaps_graph.datasets.rosbag import decode_image

    T = get_typestore(Stores.LATEST).types
    h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="x")
    grey = kitti8[0].left[:50, :80].copy()
    msg = make_image(T["sensor_msgs/msg/Image"], h, grey, encoding)
    assert np.array_equal(decode_image(msg, "sensor_msgs/msg/Image"), grey)
    if encoding == "rgb8":  # channel order matters: a pure red image is dark in grey, pure blue darker
        rgb = np.zeros((4, 4, 3), np.uint8)
        rgb[..., 0] = 255
        m = T["sensor_msgs/msg/Image"](
            header=h, height=4, width=4, encoding="rgb8", is_bigendian=0, step=12, data=rgb.reshape(-1)
        )
        assert decode_image(m, "sensor_msgs/msg/Image")[0, 0] == 76  # 0.299 * 255
        m.encoding = "bgr8"  # type: ignore[attr-defined]  # rosbags types every message as MsgType, without its fields
        assert decode_image(m, "sensor_msgs/msg/Image")[0, 0] == 29  # 0.114 * 255


def test_bad_bags_are_one_line(kitti8, tmp_path):
    need_extra("rosbags")
    # unknown encoding
    from rosbags.typesys import Stores, get_typestore

    from snaps_graph.datasets.rosbag import decode_image

    T = get_typestore(Stores.LATEST).types
    h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="x")
    m = T["sensor_msgs/msg/Image"](
        header=h, height=2, width=2, encoding="yuv422", is_bigendian=0, step=4, data=np.zeros(8, np.uint8)
    )
    with pytest.raises(SnapsGraphError, match="encoding 'yuv422' is not supported"):
        decode_image(m, "sensor_msgs/msg/Image", "b.bag: /cam/image")
    write_stereo_bag(tmp_path / "yuv", kitti8, "mcap", n=2, encoding="yuv422")
    proc = cli("run", str(tmp_path / "yuv"), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "image encoding 'yuv422' is not supported" in proc.stderr, (
        proc.stderr
    )
    # one image topic: monocular (this one without CameraInfo), and the stereo VO cannot run on it
    _write_single_topic_bag(tmp_path / "single", kitti8)
    proc = cli("run", str(tmp_path / "single"), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "no sensor_msgs/CameraInfo topic beside" in proc.stderr
    proc = cli("run", str(tmp_path / "single"), "--out", str(tmp_path / "o"), "--calib", str(kitti8.path / "calib.txt"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "no right images" in proc.stderr
    # two candidate pairs: the user must choose; then it runs
    write_stereo_bag(tmp_path / "two", kitti8, "mcap", n=2, extra_topics=("/other/left/image", "/other/right/image"))
    with pytest.raises(SnapsGraphError, match="several stereo pairs"):
        open_dataset(tmp_path / "two")
    with pytest.raises(SnapsGraphError, match="no sensor_msgs/CameraInfo"):
        open_dataset(tmp_path / "two", left_topic="/other/left/image", right_topic="/other/right/image")
    seq = open_dataset(tmp_path / "two", left_topic="/stereo/left/image_raw", right_topic="/stereo/right/image_raw")
    assert len(seq) == 2
    # images without calibration
    write_stereo_bag(tmp_path / "nocal", kitti8, "mcap", n=2, camera_info=False)
    with pytest.raises(SnapsGraphError, match="no sensor_msgs/CameraInfo topic beside /stereo/left/image_raw"):
        open_dataset(tmp_path / "nocal")
    seq = open_dataset(tmp_path / "nocal", calib=kitti8.path / "calib.txt")  # a calib.txt: size from the images
    assert isinstance(seq, RosbagSequence)
    assert seq.camera == kitti8.camera and np.array_equal(seq[1].left, kitti8[1].left)


def _write_single_topic_bag(path: Path, seq) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(2):
            h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=10 + i, nanosec=0), frame_id="c")
            w.write(
                c,
                (10 + i) * 10**9,
                ts.serialize_cdr(make_image(T["sensor_msgs/msg/Image"], h, seq[i].left, "mono8"), "sensor_msgs/msg/Image"),
            )


def test_stereo_topics_found_by_name():
    from snaps_graph.datasets.rosbag import _camera_info_topic, find_stereo_topics

    realsense = [
        "/camera/infra1/image_rect_raw",
        "/camera/infra2/image_rect_raw",
        "/camera/color/image_raw",
        "/camera/depth/image_rect_raw",
    ]
    assert find_stereo_topics(realsense) == [("/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw")]
    assert find_stereo_topics(["/cam0/image_raw", "/cam1/image_raw", "/imu0"]) == [("/cam0/image_raw", "/cam1/image_raw")]
    zed = [
        "/zed/zed_node/left/image_rect_color",
        "/zed/zed_node/right/image_rect_color",
        "/zed/zed_node/left_raw/image_raw_color",
        "/zed/zed_node/right_raw/image_raw_color",
        "/zed/zed_node/rgb/image_rect_color",
    ]
    assert len(find_stereo_topics(zed)) == 2  # raw and rectified pairs: the user chooses
    assert find_stereo_topics(["/camera/image_raw", "/lefty/image"]) == []
    infos = ["/zed/zed_node/left/camera_info", "/zed/zed_node/right/camera_info"]
    assert _camera_info_topic("/zed/zed_node/left/image_rect_color/compressed", infos) == "/zed/zed_node/left/camera_info"


def test_stamp_pairing_drops_unpaired():
    from snaps_graph.datasets.rectify import match_stamps

    tl = np.array([0, 50, 100, 150, 200]) * 1_000_000
    tr = np.array([1, 49, 151, 180, 260]) * 1_000_000  # 100 ms has no partner; 180 is 20 ms off 200
    il, ir = match_stamps(tl, tr)
    assert il.tolist() == [0, 1, 3] and ir.tolist() == [0, 1, 2]


# ---------------------------------------------------------------- live


class FakeCapture:
    """A cv2.VideoCapture stand-in that plays back a list of images."""

    def __init__(self, images):
        self.images, self.i, self.released = list(images), -1, False

    def grab(self):
        self.i += 1
        return self.i < len(self.images)

    def retrieve(self):
        return (True, self.images[self.i]) if self.i < len(self.images) else (False, None)

    def release(self):
        self.released = True


def test_live_two_devices_and_side_by_side(kitti8, kitti8_poses, kitti06_dir):
    frames = [kitti8[i] for i in range(N_BAG)]
    colour = [cv2.cvtColor(f.left, cv2.COLOR_GRAY2BGR) for f in frames]  # devices give BGR
    fakes = {"0": FakeCapture(colour), "1": FakeCapture([f.right for f in frames])}
    live = open_live("live:0,1", calib=kitti06_dir / "calib.txt", capture_factory=lambda d: fakes[d])
    assert live.camera == kitti8.camera  # size learnt from the first frame
    poses = run_poses(live)
    assert np.abs(poses["vo"][:, :3, 3] - kitti8_poses["vo"][:, :3, 3]).max() <= 1e-6
    live.close()
    assert fakes["0"].released and fakes["1"].released

    sbs = FakeCapture([np.hstack([f.left, f.right]) for f in frames[:3]])
    live = open_live("live:0", frames="0:2", calib=kitti06_dir / "calib.txt", capture_factory=lambda d: sbs)
    got = list(live)
    assert len(got) == 2 and np.array_equal(got[1].right, frames[1].right) and got[1].index == 1
    with pytest.raises(SnapsGraphError, match="needs --calib"):
        open_live("live:0", capture_factory=lambda d: sbs)


# ---------------------------------------------------------------- convert


def test_convert_euroc_and_bag_to_kitti(euroc_dir, kitti8, tmp_path):
    out = tmp_path / "k"
    proc = cli("convert", str(euroc_dir), "--out", str(out), "--frames", "10:14")
    assert proc.returncode == 0, proc.stderr
    eu = open_dataset(euroc_dir, frames="10:14")
    assert isinstance(eu, EurocSequence)
    back = KittiSequence(out)
    assert len(back) == 4 and back.gt_poses is None
    assert abs(back.camera.baseline_m - eu.camera.baseline_m) < 1e-9 and abs(back.camera.fx - eu.camera.fx) < 1e-6
    assert np.array_equal(back[3].left, eu[3].left) and np.allclose(back.timestamps, eu.timestamps, atol=1e-5)
    # a bag with ground truth given as KITTI poses: poses.txt is written
    write_stereo_bag(tmp_path / "bag", kitti8, "mcap", n=4)
    gt_file = tmp_path / "gt.txt"
    from snaps_graph.trajectory_io import write_kitti_poses

    write_kitti_poses(gt_file, kitti8.gt_poses[:4])
    proc = cli("convert", str(tmp_path / "bag"), "--out", str(tmp_path / "k2"), "--gt", str(gt_file))
    assert proc.returncode == 0 and "with poses.txt" in proc.stdout, proc.stderr
    k2 = KittiSequence(tmp_path / "k2")
    assert k2.gt_poses is not None
    assert np.allclose(k2.gt_poses, kitti8.gt_poses[:4], atol=1e-9) and np.array_equal(k2[2].right, kitti8[2].right)


# ---------------------------------------------------------------- rerun


class _InjectLoop:
    """Delegates to the logger, pretending frame 6 closed a loop with frame 1 (the clip has none)."""

    def __init__(self, logger):
        self.logger = logger

    def on_frame(self, pipe, frame, out):
        if out.k == 6:
            from snaps_graph.types import LoopEvent

            loop = LoopEvent(
                frame=out.frame,
                reference=1,
                distance_m=1.0,
                yaw_diff_deg=2.0,
                q=0.3,
                correlation=0.5,
                luminance=0.9,
                contrast=2 / 3,
                delta=np.zeros(3),
                n_corrected=4,
                alpha=1,
                candidates=3,
                t_ms=1.0,
            )
            out = dataclasses.replace(out, loop=loop)
        self.logger.on_frame(pipe, frame, out)

    def on_finish(self, pipe, result):
        self.logger.on_finish(pipe, result)


def test_rrd_recording_holds_the_entities(kitti8, tmp_path):
    chunk = pytest.importorskip("rerun.chunk", reason="reading .rrd back needs rerun-sdk's rerun.chunk (0.41 has it)")
    RrdReader = chunk.RrdReader

    from snaps_graph.viz.rerun_logger import RerunLogger

    rrd = tmp_path / "run.rrd"
    logger = RerunLogger(kitti8.camera, rrd=rrd, gt_poses=kitti8.gt_poses, path_every=3)
    run_sequence(kitti8, tmp_path / "out", Config(), refine="isam2", build_map=True, observer=_InjectLoop(logger))
    logger.close()
    chunks = list(RrdReader(rrd).stream())
    paths = {c.entity_path for c in chunks}
    for e in (
        "/world",
        "/world/camera",
        "/world/camera/image",
        "/world/camera/image/features",
        "/world/trajectory/vo",
        "/world/trajectory/snaps",
        "/world/trajectory/refined",
        "/world/trajectory/gt",
        "/world/loops",
        "/loops",
        "/metrics/frame_ms",
        "/metrics/vo_ms",
        "/metrics/inliers",
        "/metrics/q",
        "/world/map/kf_0",
    ):
        assert e in paths, (e, sorted(paths))
    image_rows = sum(c.num_rows for c in chunks if c.entity_path == "/world/camera/image" and not c.is_static)
    assert image_rows == N_BAG
    text = " ".join(str(c.to_record_batch().to_pydict()) for c in chunks if c.entity_path == "/loops")
    assert "Q 0.300 = correlation 0.500 x luminance 0.900 x contrast 0.667" in text
    assert RrdReader(rrd).blueprints()  # the layout travels with the recording


def test_failed_run_leaves_no_recording(kitti06_dir, tmp_path):
    pytest.importorskip("rerun")
    seq = tmp_path / "seq"
    for d in ("image_0", "image_1"):
        (seq / d).mkdir(parents=True)
        for i in range(4):
            shutil.copy(kitti06_dir / d / f"{i:06d}.png", seq / d / f"{i:06d}.png")
    shutil.copy(kitti06_dir / "calib.txt", seq / "calib.txt")
    (seq / "image_1" / "000002.png").write_bytes(b"not a png")  # fails mid-run, at frame 2
    proc = cli("run", str(seq), "--out", str(tmp_path / "o"), "--rrd", str(tmp_path / "r.rrd"))
    assert proc.returncode == 2 and "000002.png: unreadable image" in proc.stderr.strip().splitlines()[-1]
    assert not list(tmp_path.glob("*rrd*")) and not (tmp_path / "o").exists()


def test_viewer_without_display_is_one_line(kitti06_dir, tmp_path):
    pytest.importorskip("rerun")
    no_display = {"DISPLAY": None, "WAYLAND_DISPLAY": None}  # None: unset for the call
    proc = run_cli("run", kitti06_dir, "--frames", "0:2", "--out", tmp_path / "o", "--viewer", env=no_display)
    if sys.platform.startswith("linux"):
        assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1].startswith("error: --viewer: no display")
        assert not (tmp_path / "o").exists()


def test_no_flag_no_rerun(kitti06_dir, tmp_path):
    """Without --viewer/--rrd the run never imports rerun (logging costs nothing)."""
    argv = ["snaps-graph", "run", str(kitti06_dir), "--out", str(tmp_path / "o"), "--frames", "0:3"]
    code = (
        f"import sys; from snaps_graph.cli import main; sys.argv={argv!r}\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\nprint('RERUN' if 'rerun' in sys.modules else 'CLEAN')"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.stdout.strip().splitlines()[-1] == "CLEAN", proc.stdout + proc.stderr


# ---------------------------------------------------------------- monocular (cam0 alone) + pose file


def test_euroc_cam0_alone_with_absolute_tum_odometry(euroc_dir, tmp_path):
    """A EuRoC folder with cam0 alone: undistorted monocular frames; a TUM file stamped in
    absolute seconds (as EuRoC tools write them) matches the frames; without it, one-line error."""
    from snaps_graph.datasets.euroc import EurocSequence
    from snaps_graph.trajectory_io import tum_text

    mono = tmp_path / "mono" / "mav0"
    mono.mkdir(parents=True)
    shutil.copytree(euroc_dir / "mav0" / "cam0", mono / "cam0")
    seq = EurocSequence(mono.parent, frames="0:12")
    assert not seq.stereo and seq.camera.baseline_m == 0.0 and len(seq) == 12
    f = seq[3]
    assert f.right.size == 0 and f.left.shape == (seq.camera.height, seq.camera.width)
    stamps = np.array([int(line.split(",")[0]) for line in (mono / "cam0" / "data.csv").read_text().splitlines()[1:]])
    poses = np.repeat(np.eye(4)[None], len(stamps), 0)
    poses[:, 2, 3] = 0.05 * np.arange(len(stamps))  # 5 cm a frame forward
    odo = tmp_path / "odo.tum"
    odo.write_text(tum_text(poses, stamps * 1e-9))
    out = tmp_path / "run"
    proc = cli("run", str(mono.parent), "--frames", "0:12", "--odometry", str(odo), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    vo = np.loadtxt(out / "poses_vo.txt")
    assert np.allclose(vo[:, 11], 0.05 * np.arange(12), atol=1e-6)  # z of each frame, from the file
    proc = cli("run", str(mono.parent), "--frames", "0:12", "--out", str(tmp_path / "run2"))
    assert proc.returncode == 2 and "no right images" in proc.stderr and proc.stderr.count("\n") == 1


def test_bag_with_one_image_topic_is_monocular(kitti8, tmp_path):
    """A ROS 2 bag with one image topic (and its CameraInfo): monocular frames, run on a TUM
    file stamped in the bag's absolute time."""
    need_extra("rosbags")
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from snaps_graph.trajectory_io import tum_text

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Image, Info, Roi = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"], T["sensor_msgs/msg/RegionOfInterest"]
    cam = kitti8.camera
    t0 = 1_600_000_000_000_000_000
    stamps = [t0 + int(round(kitti8[i].timestamp * 1e9)) for i in range(4)]
    bag = tmp_path / "mono_bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        cc = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        for i, t_ns in enumerate(stamps):
            img = kitti8[i].left
            h = Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id="cam")
            w.write(ci, t_ns, ts.serialize_cdr(make_image(Image, h, img, "mono8"), "sensor_msgs/msg/Image"))
            info = Info(
                header=h,
                height=img.shape[0],
                width=img.shape[1],
                distortion_model="plumb_bob",
                d=np.zeros(5),
                k=cam.K.reshape(-1).copy(),
                r=np.eye(3).reshape(-1),
                p=cam.P0.reshape(-1).copy(),
                binning_x=0,
                binning_y=0,
                roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            w.write(cc, t_ns, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
    seq = open_dataset(bag)
    assert isinstance(seq, RosbagSequence)
    assert not seq.stereo and len(seq) == 4 and seq.camera.baseline_m == 0.0 and seq.camera.fx == cam.fx
    assert seq[2].right.size == 0 and np.array_equal(seq[2].left, kitti8[2].left)
    gt = kitti8.gt_poses[:4]
    odo = tmp_path / "odo.tum"
    odo.write_text(tum_text(gt, np.array(stamps) * 1e-9))
    result, _ = run_sequence(seq, tmp_path / "out", odometry=odo)
    assert np.allclose(result.trajectories["vo"], gt, atol=1e-6)
    with pytest.raises(SnapsGraphError, match="no right image"):
        SlamPipeline(seq.camera, Config()).process(seq[0])
