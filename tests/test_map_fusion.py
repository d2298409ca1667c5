"""Map depth (no fill-in), TSDF fusion from stored depth, accuracy against a true mesh, outputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from snaps_graph.camera import StereoCamera
from snaps_graph.config import Config, FrontendConfig, MapConfig
from snaps_graph.errors import SnapsGraphError
from snaps_graph.mapping.depth import map_camera, map_depth
from snaps_graph.mapping.tsdf import FusedMap

CAM = StereoCamera(fx=500.0, fy=500.0, cx=319.5, cy=159.5, baseline_m=0.5, width=640, height=320)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.5)
    return cv2.normalize(t, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _pose(t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


# ---------------------------------------------------------------- map depth


def test_map_depth_of_a_shifted_texture_and_a_flat_sky():
    d = 16  # full-size px: every textured pixel has disparity d (8 px at the working half size)
    big = _texture(320, 640 + d)
    big[:100] = 200  # a flat "sky" band: no texture, no evidence
    left, right = big[:, :640].copy(), big[:, d:].copy()
    z = map_depth(left, right, CAM, FrontendConfig(), MapConfig(max_range_m=40.0))
    assert z.shape == (160, 320) and z.dtype == np.float32
    inner = z[60:-10, 80:-10]
    assert np.count_nonzero(inner) > 0.8 * inner.size
    assert np.median(inner[inner > 0]) == pytest.approx(CAM.fx * CAM.baseline_m / d, rel=0.01)  # 15.6 m
    assert np.count_nonzero(z[:45]) == 0  # nothing is filled into the flat band
    far = map_depth(left, right, CAM, FrontendConfig(), MapConfig(max_range_m=10.0))
    assert np.count_nonzero(far) == 0  # 15.6 m is beyond the range


def test_map_depth_corrects_the_front_ends_disparity_offset():
    """Told that disparities read 1 px small, the map adds 1 px (0.5 at its half size) to every
    pixel's disparity, times 1 + x^2 at the right-image column (a turned right camera)."""
    d = 16
    big = _texture(320, 640 + d - 1)
    left, right = big[:, :640].copy(), big[:, d - 1 :].copy()  # measured disparity 15 px
    fcfg = FrontendConfig()
    plain = map_depth(left, right, CAM, fcfg, MapConfig(max_range_m=40.0))
    fixed = map_depth(left, right, CAM, fcfg, MapConfig(max_range_m=40.0), offset_px=-1.0)
    cam = map_camera(CAM, 0.5, 640, 320)
    vv, uu = np.nonzero((plain > 0) & (fixed > 0))
    assert len(uu) > 0.5 * plain.size
    fb = cam.fx * cam.baseline_m
    d0, d1 = fb / plain[vv, uu], fb / fixed[vv, uu]
    x = (uu - d0 - cam.cx) / cam.fx
    gain = 1.0 + x**2
    assert np.allclose(d1 - d0, 0.5 * gain, atol=1e-3)
    assert gain.max() > 1.3  # the sides get a third more


def test_map_depth_leaves_a_depth_edge_empty():
    """Near plane (disparity 24 px) on the left half, far plane (8 px) on the right: pixels keep
    one of the two depths, never a blend across the edge."""
    tex_far, tex_near = _texture(320, 700, 1), _texture(320, 700, 2)
    left = np.concatenate([tex_near[:, 100:420], tex_far[:, 100:420]], axis=1)
    right = np.concatenate([tex_near[:, 124:444], tex_far[:, 108:428]], axis=1)
    z = map_depth(left, right, CAM, FrontendConfig(), MapConfig(max_range_m=40.0))
    near, far = CAM.fx * CAM.baseline_m / 24, CAM.fx * CAM.baseline_m / 8
    v = z[20:-20][z[20:-20] > 0]
    assert v.size > 1000
    off = np.minimum(np.abs(v - near) / near, np.abs(v - far) / far)
    assert np.mean(off > 0.05) < 0.01  # no blended depths


def test_map_depth_options_and_errors(monkeypatch):
    from snaps_graph.mapping import depth as depth_mod

    big = _texture(320, 656)
    left, right = big[:, :640].copy(), big[:, 16:].copy()
    z = map_depth(left, right, CAM, FrontendConfig(), MapConfig(max_range_m=40.0))
    assert np.median(z[z > 0]) == pytest.approx(15.625, rel=0.02)
    monkeypatch.setattr(depth_mod, "MAP_BLOCK_SIZE", 11)
    z1 = map_depth(left, right, CAM, FrontendConfig(), MapConfig(depth_scale=1.0, max_range_m=40.0))
    assert z1.shape == (320, 640)
    with pytest.raises(SnapsGraphError, match="depth_scale"):
        MapConfig(depth_scale=2.0)
    c = map_camera(CAM, 0.5, 640, 320)
    assert (c.width, c.height, c.cx, c.fx) == (320, 160, 159.5, 250.0)


# ---------------------------------------------------------------- fusion


def _wall_map(depth_m=10.0, n=3, min_weight: float | None = None) -> FusedMap:
    m = FusedMap(CAM, MapConfig(tsdf_voxel_m=0.1))
    m.trunc_voxels = 4.0
    if min_weight is not None:
        m.min_weight = min_weight
    for k in range(n):
        m.add_keyframe(k * 5, np.full((160, 320), depth_m, np.float32), np.full((320, 640), 90, np.uint8))
    return m


def test_fused_wall_lies_at_its_depth_and_follows_the_poses():
    m = _wall_map(10.0)
    poses = np.repeat(np.eye(4)[None], 11, axis=0)
    s = m.fuse(poses)
    assert len(s.triangles) > 1000 and s.points is s.vertices
    assert np.abs(s.vertices[:, 2] - 10.0).max() < 0.03
    assert abs(int(np.median(s.vertex_grey)) - 90) <= 2
    moved = m.fuse(np.repeat(_pose((3.0, 0.0, 5.0))[None], 11, axis=0))  # re-posed from stored depth
    assert np.median(moved.vertices[:, 2]) == pytest.approx(15.0, abs=0.03)
    assert np.median(moved.vertices[:, 0]) - np.median(s.vertices[:, 0]) == pytest.approx(3.0, abs=0.1)


def test_stored_depth_is_compressed_and_exact_to_a_millimetre():
    m = FusedMap(CAM, MapConfig(max_range_m=20.0))
    z = np.random.default_rng(0).uniform(2, 19, (160, 320)).astype(np.float32)
    z[:20] = 0
    m.add_keyframe(0, z)
    back = m.depth(0)
    assert np.abs(back - z).max() <= 0.0005 + 1e-5 and np.all(back[:20] == 0)
    assert m.memory_bytes() < z.nbytes


def test_min_weight_drops_surfaces_seen_once():
    poses = np.repeat(np.eye(4)[None], 11, axis=0)
    assert len(_wall_map(10.0, 1, 2.0).fuse(poses).triangles) == 0
    assert len(_wall_map(10.0, 2, 2.0).fuse(poses).triangles) > 1000


def test_chunked_fusion_bounds_the_grid():
    m = FusedMap(CAM, MapConfig(tsdf_voxel_m=0.1, max_range_m=20.0))
    m.trunc_voxels, m.max_blocks = 4.0, 1000
    poses = np.array([_pose((40.0 * k, 0.0, 0.0)) for k in range(4)])
    for k in range(4):
        m.add_keyframe(k, np.full((160, 320), 15.0, np.float32))
    s = m.fuse(poses)
    assert s.stats["chunks"] == 4 and s.stats["max_blocks"] <= 1000
    assert np.abs(s.vertices[:, 2] - 15.0).max() < 0.03
    # a keyframe whose depth lies wholly beyond the range is skipped (open3d would refuse it)
    far = FusedMap(CAM, MapConfig(max_range_m=20.0))
    far.add_keyframe(0, np.full((160, 320), 15.0, np.float32))
    far.add_keyframe(5, np.full((160, 320), 9.0, np.float32))
    far.cfg = MapConfig(max_range_m=10.0)
    near = far.fuse(np.repeat(np.eye(4)[None], 6, axis=0))
    assert len(near.vertices) and np.abs(near.vertices[:, 2] - 9.0).max() < 0.05


def test_fused_map_bad_input():
    m = FusedMap(CAM, MapConfig())
    with pytest.raises(SnapsGraphError, match="scaled"):
        m.add_keyframe(0, np.ones((100, 100), np.float32))
    with pytest.raises(SnapsGraphError, match="no keyframes"):
        m.fuse(np.repeat(np.eye(4)[None], 2, axis=0))
    m.add_keyframe(4, np.ones((160, 320), np.float32))
    with pytest.raises(SnapsGraphError, match="keyframe 4"):
        m.fuse(np.repeat(np.eye(4)[None], 2, axis=0))
    with pytest.raises(SnapsGraphError, match="tsdf_voxel_m"):
        MapConfig(tsdf_voxel_m=0.0)


# ---------------------------------------------------------------- accuracy


def _write_world(path, boxes=True):
    """A 100 m x 100 m ground plane at y = 1.65 (y down) and a 4 m box beside the path."""
    import open3d as o3d

    g = o3d.geometry.TriangleMesh()
    g.vertices = o3d.utility.Vector3dVector([[-50, 1.65, -50], [50, 1.65, -50], [50, 1.65, 50], [-50, 1.65, 50]])
    g.triangles = o3d.utility.Vector3iVector([[0, 2, 1], [0, 3, 2]])
    if boxes:
        b = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 4.0)
        b.translate([5.0, 1.65 - 4.0, 10.0])
        g += b
    o3d.io.write_triangle_mesh(str(path), g)
    return path


def test_accuracy_of_exact_offset_and_partial_maps(tmp_path):
    from snaps_graph.mapping.accuracy import WorldSurface, map_accuracy

    world = WorldSurface(_write_world(tmp_path / "w.ply", boxes=False))
    poses = np.array([_pose((0.0, 0.0, z)) for z in np.arange(0.0, 20.0, 1.0)])
    rng = np.random.default_rng(0)
    xz = rng.uniform(-30, 30, (200_000, 2))
    exact = np.column_stack([xz[:, 0], np.full(len(xz), 1.65), xz[:, 1]]).astype(np.float32)
    a = map_accuracy(world, exact, exact, poses, CAM.K, (640, 320), 10.0, 0.2, min_samples=20_000)
    assert a["points"]["error_p90_m"] < 1e-4 and a["points"]["completeness"] > 0.95
    lifted = exact + np.array([0, 0.5, 0], np.float32)
    b = map_accuracy(world, lifted, lifted, poses, CAM.K, (640, 320), 10.0, 0.2, min_samples=20_000)
    assert b["points"]["error_median_m"] == pytest.approx(0.5, abs=1e-3) and b["points"]["completeness"] < 0.01
    half = exact[exact[:, 0] < 0]
    c = map_accuracy(world, half, half, poses, CAM.K, (640, 320), 10.0, 0.2, min_samples=20_000)
    assert 0.4 < c["points"]["completeness"] < 0.6
    assert c["points"]["completeness_seen"] is not None and 0.0 < c["surface_seen_share"] < 1.0
    # a trajectory off by a rigid motion (lifted 0.5 m): the map is too, and the trajectory's own
    # alignment onto the truth puts it back, while the anchored figure keeps the offset
    from snaps_graph.mapping.outputs import trajectory_alignment

    est = poses.copy()
    est[:, 1, 3] += 0.5
    d = map_accuracy(
        world, lifted, lifted, poses, CAM.K, (640, 320), 10.0, 0.2, min_samples=20_000, alignment=trajectory_alignment(est, poses)
    )
    assert d["points"]["error_median_m"] == pytest.approx(0.5, abs=1e-3)
    assert d["aligned"]["points"]["error_p90_m"] < 1e-3 and d["aligned"]["points"]["completeness"] > 0.95
    assert trajectory_alignment(est, None) is None and trajectory_alignment(est, poses[:5]) is None
    with pytest.raises(SnapsGraphError, match="not found"):
        WorldSurface(tmp_path / "missing.ply")


# ---------------------------------------------------------------- outputs + report


def test_write_map_outputs_and_compare_report(tmp_path, monkeypatch):
    import functools

    from snaps_graph.evaluation.report import map_section_lines
    from snaps_graph.mapping import accuracy
    from snaps_graph.mapping.outputs import accuracy_from_files, write_map_outputs

    world = _write_world(tmp_path / "w.ply")
    cam = CAM
    # keyframe depth of the ground plane (y = 1.65) seen by a level camera, exact
    v, u = np.mgrid[0:160, 0:320].astype(np.float32)
    yn = (v - (cam.cy + 0.5) * 0.5 + 0.5) / (cam.fy * 0.5)
    ground = np.where(yn > 0.01, 1.65 / np.maximum(yn, 1e-6), 0).astype(np.float32)
    ground[ground > 20] = 0
    cfg = MapConfig(tsdf_voxel_m=0.1, per_trajectory=True)
    m = FusedMap(cam, cfg)
    m.trunc_voxels = 4.0
    monkeypatch.setattr(accuracy, "map_accuracy", functools.partial(accuracy.map_accuracy, min_samples=20_000))
    n = 21
    gt = np.array([_pose((0.0, 0.0, 0.5 * k)) for k in range(n)])
    for k in range(0, n, 5):
        m.add_keyframe(k, ground)
    vo = gt.copy()
    vo[:, 1, 3] -= 0.3  # a VO drawn 0.3 m too high
    out = tmp_path / "run"
    out.mkdir()
    entry = write_map_outputs(out, m, {"vo": vo, "batch": gt}, gt, cfg, world_mesh=world)
    assert entry is not None
    for f in ("map.ply", "map_mesh.ply", "map.png", "map_mesh.png", "map_compare.png", "map_vo.ply", "map_mesh_vo.ply"):
        assert (out / f).is_file(), f
    acc = entry["accuracy"]
    assert set(acc) == {"vo", "batch", "gt"}
    assert acc["batch"]["points"]["error_p90_m"] < 0.05
    assert acc["vo"]["points"]["error_median_m"] == pytest.approx(0.3, abs=0.05)
    assert acc["batch"]["points"]["completeness_seen"] > acc["vo"]["points"]["completeness_seen"]
    json.dumps(entry)  # metrics.json-ready
    md = "\n".join(map_section_lines(out, entry))
    assert "| batch |" in md and "map_compare.png" in md
    # compare --world-mesh: the same measurement from the files in the folder
    again = accuracy_from_files(out, world, {"vo": vo, "batch": gt}, json.loads(json.dumps(entry)), gt, 20.0, 0.2, 20_000)
    assert set(again) == {"vo", "batch"}
    assert again["batch"]["points"]["error_p90_m"] == pytest.approx(acc["batch"]["points"]["error_p90_m"], abs=0.01)


def test_config_round_trip_of_map_fields(tmp_path):
    cfg = Config()
    cfg.map.trajectory = "vo"
    cfg.map.depth_scale = 1.0
    cfg.dump(tmp_path / "c.toml")
    back = Config.load(tmp_path / "c.toml")
    assert back.map.trajectory == "vo" and back.map.depth_scale == 1.0


def test_pictures_colour_height_above_the_local_ground():
    from snaps_graph.mapping.render import _local_height

    # y points down: a 3 m wall on a road that has climbed 10 m reads 0..3 m, not 10..13 m
    road = np.array([[x, -10.0, z] for x in range(4) for z in range(4)], float)
    wall = np.array([[1.0, -10.0 - h, 1.0] for h in (1.0, 3.0)])
    h = _local_height(np.vstack([road, wall]))
    assert np.allclose(h[: len(road)], 0.0) and np.allclose(h[len(road) :], [1.0, 3.0])
    q = _local_height(np.vstack([road, wall]), np.array([[2.0, -12.0, 2.0], [50.0, -7.0, 50.0]]))
    assert np.allclose(q, [2.0, 0.0])  # a query in an empty cell counts as ground


def test_an_empty_map_is_flagged_not_fatal(tmp_path):
    from snaps_graph.mapping.outputs import write_map_outputs

    m = FusedMap(CAM, MapConfig())
    m.add_keyframe(0, np.zeros((160, 320), np.float32))  # a black frame: no valid depth
    entry = write_map_outputs(tmp_path, m, {"vo": np.eye(4)[None]}, None, MapConfig())
    assert entry is not None
    assert "empty" in entry and not (tmp_path / "map.ply").exists()
    assert write_map_outputs(tmp_path, FusedMap(CAM, MapConfig()), {"vo": np.eye(4)[None]}, None, MapConfig()) is None


def test_keyframe_cloud_backprojects_the_stored_depth():
    """A viewer's keyframe points: a fronto-parallel plane at 5 m comes back at z = 5 m."""
    import numpy as np

    from snaps_graph.camera import kitti00_camera
    from snaps_graph.mapping.tsdf import FusedMap

    cam = kitti00_camera(620, 188)
    fm = FusedMap(cam)
    depth = np.full((188, 620), 5.0, np.float32)
    depth[:, :100] = 0.0  # invalid strip
    fm.add_keyframe(0, depth, np.full((188, 620), 77, np.uint8))
    xyz, grey = fm.keyframe_cloud(0, step=2)
    assert len(xyz) == 94 * (310 - 50)
    assert np.allclose(xyz[:, 2], 5.0, atol=1e-3)
    assert grey is not None and len(grey) == len(xyz) and np.all(grey == 77)
    fx, cx = cam.fx, cam.cx  # the depth is at the camera's own size
    assert np.isclose(xyz[:, 0].min(), (100 - cx) * 5.0 / fx, atol=1e-3)  # the invalid strip is gone
