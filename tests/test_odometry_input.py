"""Odometry from a pose file (``run --odometry``): reading, matching to frames, the drift model,
monocular sequences, bad input, and an end-to-end run on the real revisit."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA
from inprocess import cli  # the command line in this process (tests/inprocess.py)

from snaps_graph.config import Config, OdometryConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.drift_model import path_covariance
from snaps_graph.errors import SnapsGraphError
from snaps_graph.frontend.external import PoseFileOdometry
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.trajectory_io import kitti_text, read_kitti_poses, read_pose_file, tum_text

LOOP_DATA = SHARED_DATA / "kitti00_loop"


def _poses(n: int, step: float = 1.0) -> np.ndarray:
    """n poses driving forward (camera z) with a slow left turn."""
    out = []
    for i in range(n):
        a = 0.01 * i
        T = np.eye(4)
        T[:3, :3] = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        T[:3, 3] = [0.0, 0.0, step * i]
        out.append(T)
    return np.array(out)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture
def mono_seq(tiny_seq, tmp_path) -> Path:
    """The tiny rendered sequence without its right images (8 frames, poses.txt, times.txt)."""
    out = tmp_path / "mono"
    out.mkdir()
    shutil.copytree(tiny_seq / "image_0", out / "image_0")
    for name in ("calib.txt", "times.txt", "poses.txt"):
        shutil.copy(tiny_seq / name, out / name)
    return out


# ---- reading ----
def test_formats_detected_and_equal(tmp_path):
    P = _poses(5)
    times = np.arange(5) * 0.1
    k = read_pose_file(_write(tmp_path / "a.txt", kitti_text(P)))
    t = read_pose_file(_write(tmp_path / "b.txt", tum_text(P, times)))
    assert (k.fmt, t.fmt) == ("kitti", "tum")
    assert np.array_equal(k.keys, np.arange(5)) and np.allclose(t.keys, times)
    assert np.allclose(k.poses, P, atol=1e-8) and np.allclose(t.poses, P, atol=1e-8)
    assert list(t.lines) == [1, 2, 3, 4, 5]


@pytest.mark.parametrize(
    "text, fmt, where, words",
    [
        ("", None, "", "no poses"),
        ("# only a comment\n\n", None, "", "no poses"),
        ("1 2 3\n", None, ":1", "neither a KITTI"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", None, ":2", "needs 12 numbers, found 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n", None, ":2", "NaN"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", None, ":2", "not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 0 0 1 0 0 0 0 1 0\n", None, ":2", "blank line"),
        ("0.0 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n", None, ":3", "does not increase"),
        ("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 2\n", None, ":2", "quaternion is not a rotation"),
        ("0.0 0 0 0 0 0 0 1\n", "kitti", ":1", "needs 12 numbers, found 8"),
        ("1 0 0 0 0 1 0 0 0 0 1 x\n", None, ":1", "not a number"),
    ],
)
def test_bad_pose_files(tmp_path, text, fmt, where, words):
    p = _write(tmp_path / "odo.txt", text)
    with pytest.raises(SnapsGraphError) as e:
        read_pose_file(p, fmt)
    msg = str(e.value)
    assert msg.startswith(f"{p}{where}:") and words in msg and "\n" not in msg


# ---- the front end ----
def test_relative_poses_across_a_gap_and_drift_noise(tmp_path):
    P = _poses(20, step=1.5)
    P[7, 0, 3] = 2.0  # a detour inside the gap: 2.5 m in and 2.5 m out instead of 1.5 and 1.5
    model = OdometryConfig(heading_deg_per_sqrt_m=2.0, pitch_deg_per_sqrt_m=3.0)
    odo = PoseFileOdometry(read_pose_file(_write(tmp_path / "p.txt", kitti_text(P))), model)
    from snaps_graph.types import StereoFrame

    img = np.zeros((64, 64), np.uint8)
    empty = np.zeros((0, 0), np.uint8)
    outs = [odo.process(StereoFrame(i, 0.1 * i, img, empty)) for i in (3, 4, 10)]
    assert np.allclose(outs[0].pose, np.eye(4)) and outs[0].cov is None and outs[0].drift_cov is None
    assert np.allclose(outs[2].T_rel, np.linalg.solve(P[4], P[10]), atol=1e-9)  # carried across 5..9
    assert np.allclose(outs[2].pose, np.linalg.solve(P[3], P[10]), atol=1e-9)
    # No measurement noise of its own: the graph adds the drift model's. Across the gap the model's
    # covariance along the file's own poses (the detour's 11 m), which the chord (9 m) would not give.
    assert outs[1].cov is not None and np.allclose(outs[1].cov, 0.0) and outs[1].drift_cov is None  # one step: the graph's chord
    assert outs[2].drift_cov is not None
    assert np.allclose(outs[2].drift_cov, path_covariance(model.model(), P[4:11]))
    assert outs[2].drift_cov[1, 1] == pytest.approx(math.radians(2.0) ** 2 * (4 * 1.5 + 2 * 2.5))


def test_frames_without_a_pose(tmp_path):
    kitti = PoseFileOdometry(read_pose_file(_write(tmp_path / "k.txt", kitti_text(_poses(5)))))
    with pytest.raises(SnapsGraphError, match=r"k\.txt: no pose for frame 7 .*line 8 would hold it.*fewer poses than images"):
        kitti.check([3, 4, 7], [0.3, 0.4, 0.7])
    tum = PoseFileOdometry(read_pose_file(_write(tmp_path / "t.txt", tum_text(_poses(5), np.arange(5) * 0.1))))
    tum.check([0, 1], [0.005, 0.1])  # within the tolerance
    with pytest.raises(SnapsGraphError, match=r"t\.txt:5: no pose within 0\.02 s of frame 9"):
        tum.check([0, 9], [0.0, 0.9])


# ---- monocular sequences ----
def test_monocular_kitti_with_gaps_takes_times_and_poses_by_frame_number(tmp_path, tiny_seq):
    seq = tmp_path / "gaps"
    (seq / "image_0").mkdir(parents=True)
    files = sorted((tiny_seq / "image_0").iterdir())
    for i in (0, 1, 5, 6):
        shutil.copy(files[i], seq / "image_0" / files[i].name)
    shutil.copy(tiny_seq / "calib.txt", seq / "calib.txt")
    shutil.copy(tiny_seq / "times.txt", seq / "times.txt")  # 8 lines: one per frame number
    shutil.copy(tiny_seq / "poses.txt", seq / "poses.txt")
    ds = KittiSequence(seq)
    assert not ds.stereo and list(ds.indices) == [0, 1, 5, 6]
    full = read_kitti_poses(tiny_seq / "poses.txt")
    assert ds.gt_poses is not None
    assert np.allclose(ds.gt_poses[2], np.linalg.solve(full[0], full[5]))
    assert ds[2].right.size == 0 and ds[2].index == 5
    part = KittiSequence(seq, frames="1:3")  # positions in file-number order
    assert list(part.indices) == [1, 5] and np.isclose(part.timestamps[1], ds.timestamps[2])


def test_python_api_monocular_with_pose_file(mono_seq):
    cfg = Config()
    ds = KittiSequence(mono_seq)
    odo = PoseFileOdometry(read_pose_file(mono_seq / "poses.txt"), cfg.odometry)
    pipe = SlamPipeline(ds.camera, cfg, frontend=odo)
    for f in ds:
        pipe.process(f)
    res = pipe.finish()
    assert ds.gt_poses is not None
    assert np.allclose(res.trajectories["vo"], ds.gt_poses, atol=1e-6)
    from snaps_graph.verification.mono import MonoFeatureBank

    assert pipe.verifier is not None and isinstance(pipe.verifier.bank, MonoFeatureBank)
    # the stereo VO cannot run on it: a one-line error, nothing changed
    stereo = SlamPipeline(ds.camera, cfg)
    with pytest.raises(SnapsGraphError, match="no right image: the stereo VO needs one"):
        stereo.process(ds[0])


def test_cli_monocular_errors(mono_seq, tmp_path):
    r = cli("run", str(mono_seq), "--out", str(tmp_path / "o1"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no right images" in r.stderr and "--odometry" in r.stderr
    r = cli("run", str(mono_seq), "--out", str(tmp_path / "o2"), "--odometry", str(mono_seq / "poses.txt"), "--map")
    assert r.returncode == 2 and "the map needs stereo depth" in r.stderr
    short = _write(tmp_path / "short.txt", "".join((mono_seq / "poses.txt").read_text().splitlines(True)[:5]))
    r = cli("run", str(mono_seq), "--out", str(tmp_path / "o3"), "--odometry", str(short))
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert f"{short}: no pose for frame 5" in r.stderr and "fewer poses than images" in r.stderr
    nan = _write(tmp_path / "nan.txt", (mono_seq / "poses.txt").read_text().replace("\n", "\nnan " + "0 " * 11 + "\n", 1))
    r = cli("run", str(mono_seq), "--out", str(tmp_path / "o4"), "--odometry", str(nan))
    assert r.returncode == 2 and f"{nan}:2: NaN" in r.stderr
    for o in ("o1", "o2", "o3", "o4"):
        assert not (tmp_path / o).exists()  # no half-written results


def test_cli_end_to_end_on_the_real_revisit(tmp_path):
    """kitti00_loop, left camera only, ground-truth odometry, across the 230 -> 1540 gap into the
    revisit (positions 50:191 are frames 150-230 and 1540-1599)."""
    seq = LOOP_DATA / "sequences" / "00"
    if not seq.is_dir():
        pytest.skip(f"real data not found at {LOOP_DATA} (it is in CI's ../shared/data; a user's clone lacks it)")
    out = tmp_path / "run"
    r = cli(
        "run",
        str(seq),
        "--odometry",
        str(LOOP_DATA / "poses" / "00.txt"),
        "--frames",
        "50:191",
        "--refine",
        "both",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    for name in (
        "poses_vo.txt",
        "poses_snaps.txt",
        "poses_isam2.txt",
        "poses_batch.txt",
        "frames.csv",
        "loops.jsonl",
        "metrics.json",
    ):
        assert (out / name).is_file(), name
    for name in ("vo", "snaps", "isam2", "batch"):
        assert np.all(np.isfinite(np.loadtxt(out / f"poses_{name}.txt")))
    frames = np.loadtxt(out / "frames.csv", delimiter=",", skiprows=1, usecols=0, dtype=int)
    assert frames[0] == 150 and 230 in frames and 1540 in frames and frames[-1] == 1599
    loops = [json.loads(line) for line in (out / "loops.jsonl").read_text().splitlines()]
    assert loops, "no loop closed on the revisit"
    gt = read_kitti_poses(LOOP_DATA / "poses" / "00.txt")
    for lp in loops:  # every loop is a true one: the two frames stand within 10 m
        assert np.linalg.norm(gt[lp["frame"], :3, 3] - gt[lp["reference"], :3, 3]) < 10.0, lp
    assert any(lp["verified"] and 1573 <= lp["frame"] <= 1630 for lp in loops)


def test_stereo_sequence_with_pose_file_keeps_stereo_verification(tiny_seq):
    """With a right image the pose file replaces only the VO: the stereo loop features stay."""
    from snaps_graph.verification.features import LoopFeatureBank

    ds = KittiSequence(tiny_seq)
    cfg = Config()
    pipe = SlamPipeline(ds.camera, cfg, frontend=PoseFileOdometry(read_pose_file(tiny_seq / "poses.txt"), cfg.odometry))
    for f in ds:
        pipe.process(f)
    res = pipe.finish()
    assert pipe.verifier is not None and type(pipe.verifier.bank) is LoopFeatureBank
    assert ds.gt_poses is not None
    assert np.allclose(res.trajectories["vo"], ds.gt_poses, atol=1e-6)
