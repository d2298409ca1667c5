"""Config, camera, KITTI reader, trajectory files, frame ranges: the foundation's contracts."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from snaps_graph.camera import StereoCamera, kitti00_camera
from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.geometry import wrap_deg, yaw_deg
from snaps_graph.io_utils import atomic_output, atomic_write_text, parse_frame_range
from snaps_graph.trajectory_io import (
    quaternion_to_rotation,
    read_kitti_poses,
    read_tum_poses,
    rotation_to_quaternion,
    write_kitti_poses,
    write_tum_poses,
)

ROOT = Path(__file__).resolve().parents[1]


# ---- config ----
def test_config_roundtrip(tmp_path):
    cfg = Config()
    cfg.loop.radius_m = 12.5
    cfg.frontend.mode = "sift"
    cfg.map.enabled = True
    p = tmp_path / "c.toml"
    cfg.dump(p)
    back = Config.load(p)
    assert back.loop.radius_m == 12.5
    assert back.frontend.mode == "sift"
    assert back.map.enabled is True
    assert back.to_dict() == cfg.to_dict()


@pytest.mark.parametrize(
    "path", sorted((Path(__file__).resolve().parents[1] / "benchmarks" / "configs").glob("*.toml")), ids=lambda p: p.name
)
def test_shipped_benchmark_configs_load(path):
    cfg = Config.load(path)
    assert cfg.to_dict() != Config().to_dict()  # each one changes something


def test_budget_benchmark_variants_are_valid_overrides(tmp_path):
    """bench_budget.py's built-in variants: each a key the config has, in range, and not the default."""
    import importlib.util
    import sys

    path = ROOT / "benchmarks" / "bench_budget.py"
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location("bench_budget", path)
        assert spec and spec.loader
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(path.parent))
    for item in mod.COST_VARIANTS + mod.PERTURBATION_VARIANTS:
        cfg = Config.load(mod.write_config(item, tmp_path))
        assert cfg.to_dict() != Config().to_dict(), item


def test_config_table1_defaults():
    """Table I's values, except the similarity settings tuned for the exact index and the
    discount length K = 300 where gamma itself ends for the first loop (README, measured)."""
    from snaps_graph.loop.policy import DRIFT

    c = Config().loop
    assert (c.radius_m, c.frame_distance, c.discount_length) == (10.0, 100, 100)
    assert (c.inter_frame_pause, DRIFT.attempts, DRIFT.max_yaw_deg, c.policy) == (50, 5, 10.0, "drift")
    assert c.thumbnail_scale == pytest.approx(1 / 6)
    assert (c.min_similarity, c.window, DRIFT.require_verification) == (0.15, 16, True)


@pytest.mark.parametrize(
    "text,msg",
    [
        ("[loop]\nradius = 3\n", "unknown key 'loop.radius'"),
        ("[loop]\nradius_m = 'far'\n", "expected a finite number"),
        ("[loop]\nframe_distance = 1.5\n", "expected an integer"),
        ("[loop\n", "malformed TOML"),
    ],
)
def test_config_errors(tmp_path, text, msg):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SnapsGraphError, match=msg):
        Config.load(p)


# ---- camera ----
def test_camera_from_kitti06_calib(kitti06_dir):
    cam = StereoCamera.from_calib_file(kitti06_dir / "calib.txt")
    assert cam.fx == pytest.approx(707.0912)
    assert cam.cx == pytest.approx(601.8873)
    assert cam.cy == pytest.approx(183.1104)
    assert cam.baseline_m == pytest.approx(379.8145 / 707.0912)


def test_camera_depth_and_backprojection():
    cam = kitti00_camera()
    z = cam.depth_from_disparity(np.array([[10.0, 0.0, -1.0]]))
    assert z[0, 0] == pytest.approx(718.856 * 0.537165 / 10.0, rel=1e-4)
    assert z[0, 1] == 0 and z[0, 2] == 0
    p = cam.backproject(np.array([cam.cx + 71.8856]), np.array([cam.cy]), np.array([10.0]))
    assert p[0] == pytest.approx([1.0, 0.0, 10.0])


def test_calib_roundtrip(tmp_path):
    cam = kitti00_camera()
    cam.write_calib(tmp_path / "calib.txt")
    back = StereoCamera.from_calib_file(tmp_path / "calib.txt")
    assert back.baseline_m == pytest.approx(cam.baseline_m, rel=1e-9)
    assert back.fx == pytest.approx(cam.fx)


@pytest.mark.parametrize(
    "text,msg",
    [
        ("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n", "no 'P1:' line"),
        ("P0: 1 0 0\nP1: 1 0 0 0 0 1 0 0 0 0 1 0\n", "needs 12 numbers"),
        ("P0: 1 0 0 0 0 1 0 0 0 0 1 x\nP1: 1 0 0 0 0 1 0 0 0 0 1 0\n", "not a number"),
        ("P0: 700 0 600 0 0 700 180 0 0 0 1 0\nP1: 700 0 600 0 0 700 180 0 0 0 1 0\n", "baseline"),
    ],
)
def test_calib_errors(tmp_path, text, msg):
    (tmp_path / "calib.txt").write_text(text)
    with pytest.raises(SnapsGraphError, match=msg):
        StereoCamera.from_calib_file(tmp_path / "calib.txt")


# ---- reader ----
def test_kitti06_reader(kitti06_dir):
    seq = KittiSequence(kitti06_dir)
    assert len(seq) == 51
    f = seq[10]
    assert f.index == 10 and f.left.shape == (370, 1226) and f.left.dtype == np.uint8
    assert f.timestamp == pytest.approx(1.044989e00, rel=1e-6) or f.timestamp > 1.0
    assert seq.gt_poses is not None
    assert seq.gt_poses.shape == (51, 4, 4)
    assert np.allclose(seq.gt_poses[0], np.eye(4))
    assert (seq.camera.width, seq.camera.height) == (1226, 370)


def test_kitti06_frame_range_rebases_gt(kitti06_dir):
    full = KittiSequence(kitti06_dir)
    part = KittiSequence(kitti06_dir, frames="20:30")
    assert full.gt_poses is not None and part.gt_poses is not None
    assert len(part) == 10 and part[0].index == 20 and list(part.indices) == list(range(20, 30))
    expect = np.linalg.inv(full.gt_poses[20]) @ full.gt_poses[25]
    assert np.allclose(part.gt_poses[5], expect, atol=1e-9)
    path_len = np.linalg.norm(np.diff(full.gt_poses[:, :3, 3], axis=0), axis=1).sum()
    assert 55 < path_len < 65  # the README's 59.9 m


def _copy_clip(src: Path, dst: Path, n: int = 3) -> Path:
    for sub in ("image_0", "image_1"):
        (dst / sub).mkdir(parents=True)
        for i in range(n):
            shutil.copy(src / sub / f"{i:06d}.png", dst / sub / f"{i:06d}.png")
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    return dst


def test_reader_errors(kitti06_dir, tmp_path):
    seq = _copy_clip(kitti06_dir, tmp_path / "s")
    # times.txt of the wrong length
    (seq / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(SnapsGraphError, match="times.txt: 2 timestamps for 3 images"):
        KittiSequence(seq)
    (seq / "times.txt").unlink()
    # poses of the wrong length
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(SnapsGraphError, match="1 poses for 3 images"):
        KittiSequence(seq)
    (seq / "poses.txt").unlink()
    # unreadable image
    (seq / "image_1" / "000001.png").write_bytes(b"not a png")
    s = KittiSequence(seq)
    with pytest.raises(SnapsGraphError, match="000001.png: unreadable image"):
        s[1]
    # left/right size mismatch
    img = cv2.imread(str(kitti06_dir / "image_1" / "000001.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(seq / "image_1" / "000001.png"), img[:-2])
    with pytest.raises(SnapsGraphError, match="differs from left image"):
        KittiSequence(seq)[1]
    # different numbers of images
    (seq / "image_1" / "000002.png").unlink()
    with pytest.raises(SnapsGraphError, match="3 left images .* but 2 right images"):
        KittiSequence(seq)
    # missing calibration
    shutil.copy(kitti06_dir / "image_1" / "000002.png", seq / "image_1" / "000002.png")
    (seq / "calib.txt").unlink()
    with pytest.raises(SnapsGraphError, match="calib.txt: calibration file not found"):
        KittiSequence(seq)
    with pytest.raises(SnapsGraphError, match="sequence folder not found"):
        KittiSequence(tmp_path / "nope")


def test_frame_range_parse():
    assert parse_frame_range("0:50") == (0, 50)
    assert parse_frame_range("10:") == (10, None)
    assert parse_frame_range(None) is None
    assert parse_frame_range("0:500", 51) == (0, 51)
    for bad in ("5", "a:b", "9:3", "-1:4"):
        with pytest.raises(SnapsGraphError):
            parse_frame_range(bad)
    with pytest.raises(SnapsGraphError, match="only 51 frames"):
        parse_frame_range("60:70", 51)


# ---- trajectory files ----
def _random_poses(n=20, seed=1):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.normal(size=4)
        T = np.eye(4)
        T[:3, :3] = quaternion_to_rotation(q)
        T[:3, 3] = rng.normal(scale=50, size=3)
        out.append(T)
    return np.array(out)


def test_kitti_and_tum_roundtrip(tmp_path):
    poses = _random_poses()
    write_kitti_poses(tmp_path / "a.txt", poses)
    assert np.allclose(read_kitti_poses(tmp_path / "a.txt"), poses, atol=1e-7)
    line = (tmp_path / "a.txt").read_text().splitlines()[0]
    assert len(line.split()) == 12 and not line.endswith(" ")
    times = np.arange(len(poses)) * 0.1
    write_tum_poses(tmp_path / "a.tum", poses, times)
    t, back = read_tum_poses(tmp_path / "a.tum")
    assert np.allclose(t, times) and np.allclose(back, poses, atol=1e-7)


def test_quaternion_branches():
    for angle, axis in [(179.9, [1, 0, 0]), (179.9, [0, 1, 0]), (179.9, [0, 0, 1]), (10, [1, 1, 0])]:
        R, _ = cv2.Rodrigues(np.radians(angle) * np.array(axis, float) / np.linalg.norm(axis))
        assert np.allclose(quaternion_to_rotation(rotation_to_quaternion(R)), R, atol=1e-9)


def test_refuse_nan_pose(tmp_path):
    poses = _random_poses(3)
    poses[1, 0, 3] = np.nan
    with pytest.raises(ValueError):
        write_kitti_poses(tmp_path / "x.txt", poses)
    assert not (tmp_path / "x.txt").exists()


def test_yaw_and_wrap():
    R, _ = cv2.Rodrigues(np.array([0.0, np.radians(30.0), 0.0]))
    assert yaw_deg(R) == pytest.approx(30.0)
    assert wrap_deg(190.0) == pytest.approx(-170.0)
    assert wrap_deg(-180.0) == pytest.approx(180.0)


# ---- atomic outputs ----
def test_atomic_output_gives_ordinary_files_and_cleans_up(tmp_path):
    import os

    umask = os.umask(0)
    os.umask(umask)
    atomic_write_text(tmp_path / "a" / "x.txt", "hello\n")
    assert (tmp_path / "a" / "x.txt").read_text() == "hello\n"
    assert (tmp_path / "a" / "x.txt").stat().st_mode & 0o777 == 0o666 & ~umask
    with atomic_output(tmp_path / "a" / "m.ply", suffix=".ply") as tmp:
        assert tmp.suffix == ".ply" and tmp.parent == tmp_path / "a"
        tmp.write_bytes(b"ply")
    assert (tmp_path / "a" / "m.ply").stat().st_mode & 0o777 == 0o666 & ~umask
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "a" / "bad.g2o") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer failed")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["m.ply", "x.txt"]  # nothing half-written


# ---- package layout ----
def _module_graph() -> dict[str, set[str]]:
    """snaps_graph module -> the package modules it imports (anywhere in the file, lazy ones too)."""
    import ast

    root = Path(__file__).resolve().parents[1] / "snaps_graph"
    files = {}
    for f in root.rglob("*.py"):
        parts = ["snaps_graph", *f.relative_to(root).with_suffix("").parts]
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f

    def resolve(name: str) -> str:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, set[str]] = {}
    for mod, f in files.items():
        pkg = mod.split(".") if f.name == "__init__.py" else mod.split(".")[:-1]
        deps = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    full = ".".join(pkg[: len(pkg) - node.level + 1] + ([node.module] if node.module else []))
                elif node.module and node.module.startswith("snaps_graph"):
                    full = node.module
                else:
                    continue
                deps |= {resolve(f"{full}.{a.name}") if f"{full}.{a.name}" in files else resolve(full) for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {resolve(a.name) for a in node.names if a.name.startswith("snaps_graph")}
        graph[mod] = deps - {mod, ""}
    return graph


def test_module_graph_sees_imports():
    graph = _module_graph()
    assert "snaps_graph.evaluation.results_io" in graph["snaps_graph.evaluation.report"]
    assert "snaps_graph.pipeline" in graph["snaps_graph.runner"]


def test_no_import_circle_in_the_package():
    """No module reaches itself through the package's imports (lazy imports count: a circle is one
    idea split over two files)."""
    graph = _module_graph()
    circles = []
    for start in sorted(graph):
        seen, stack = set(), [(start, [start])]
        while stack:
            mod, path = stack.pop()
            for dep in sorted(graph.get(mod, ())):
                if dep == start:
                    circles.append(" -> ".join([*path, start]))
                elif dep not in seen:
                    seen.add(dep)
                    stack.append((dep, [*path, dep]))
    assert not circles, circles[:5]


def test_every_reader_shares_the_stereo_source_defaults():
    """Each reader subclasses SequenceBase, so the optional StereoSource members exist on all."""
    from snaps_graph.datasets.euroc import EurocSequence
    from snaps_graph.datasets.live import LiveStereo
    from snaps_graph.datasets.rosbag import RosbagSequence
    from snaps_graph.synth import SyntheticSequence
    from snaps_graph.types import SequenceBase

    for reader in (KittiSequence, EurocSequence, RosbagSequence, LiveStereo, SyntheticSequence):
        assert issubclass(reader, SequenceBase), reader
    base = SequenceBase()
    assert (base.gt_path, base.stereo, base.t0_ns, tuple(base.notes), base.frame_source(3)) == (None, True, None, (), None)
    base.close()


def test_no_probing_of_a_dataset():
    """The StereoSource members are read directly: no getattr/hasattr on a dataset in the package."""
    import re

    probe = re.compile(r"\b(getattr|hasattr)\((seq|dataset|ds|source|sequence)\b")
    hits = [
        f"{f.relative_to(ROOT)}:{i}"
        for f in sorted((ROOT / "snaps_graph").rglob("*.py"))
        for i, line in enumerate(f.read_text().splitlines(), 1)
        if probe.search(line)
    ]
    assert not hits, hits
