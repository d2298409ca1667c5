"""Point-cloud map: back-projection (eq. 2), validity, posing, re-posing, PLY, PNG, memory."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from snaps_graph.camera import StereoCamera, kitti00_camera
from snaps_graph.config import MapConfig
from snaps_graph.errors import SnapsGraphError
from snaps_graph.mapping import CloudMap

CAM = kitti00_camera()  # 1241 x 376, fx = fy = 718.856, cx = 607.1928, cy = 185.2157
SMALL = StereoCamera(fx=100.0, fy=100.0, cx=4.0, cy=3.0, baseline_m=0.5, width=8, height=6)


def _raw(**kw) -> MapConfig:
    """No voxel steps: every valid grid pixel is one point, in grid order."""
    return MapConfig(keyframe_voxel_size_m=0.0, voxel_size_m=0.0, **kw)


def _pose(t=(0.0, 0.0, 0.0), yaw_deg: float = 0.0) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def _plane(depth_m: float = 10.0) -> np.ndarray:
    return np.full((CAM.height, CAM.width), depth_m, np.float32)


def test_plane_backprojects_to_known_depth_and_extents():
    m = CloudMap(CAM, _raw(pixel_step=4))
    n = m.add_keyframe(0, _plane(10.0))
    assert n == 311 * 94  # u = 0, 4, ..., 1240; v = 0, 4, ..., 372
    xyz, colour = m.keyframe_cloud(0)
    assert colour is None and xyz.dtype == np.float32
    assert np.allclose(xyz[:, 2], 10.0)
    # x = z (u - cx) / fx, y = z (v - cy) / fy at the grid's first and last columns/rows
    assert xyz[:, 0].min() == pytest.approx(10 * (0 - 607.1928) / 718.856, abs=1e-4)  # -8.4466
    assert xyz[:, 0].max() == pytest.approx(10 * (1240 - 607.1928) / 718.856, abs=1e-4)  # 8.8030
    assert xyz[:, 1].min() == pytest.approx(10 * (0 - 185.2157) / 718.856, abs=1e-4)  # -2.5766
    assert xyz[:, 1].max() == pytest.approx(10 * (372 - 185.2157) / 718.856, abs=1e-4)  # 2.5984


def test_keyframe_voxel_keeps_plane_and_thins_it():
    cfg = MapConfig(pixel_step=4, keyframe_voxel_size_m=0.15)
    m = CloudMap(CAM, cfg)
    n = m.add_keyframe(0, _plane(10.0))
    xyz, _ = m.keyframe_cloud(0)
    # grid spacing at 10 m is 4 * 10 / 718.856 = 0.056 m, so a 0.15 m voxel holds ~2-3 x 2-3 points
    assert 311 * 94 / 9 <= n <= 311 * 94 / 4
    assert np.allclose(xyz[:, 2], 10.0, atol=1e-5)
    assert xyz[:, 0].min() == pytest.approx(-8.4466, abs=0.15)
    assert xyz[:, 0].max() == pytest.approx(8.8030, abs=0.15)


def test_invalid_and_out_of_range_depths_are_dropped():
    m = CloudMap(SMALL, _raw(pixel_step=1, max_range_m=40.0))
    depth = np.full((6, 8), 5.0, np.float32)
    depth[0, :] = 0.0  # no disparity
    depth[1, 0] = -3.0
    depth[1, 1] = np.nan
    depth[1, 2] = np.inf
    depth[1, 3] = 40.5  # beyond max range
    depth[1, 4] = 40.0  # exactly max range: kept
    n = m.add_keyframe(0, depth)
    assert n == 48 - 8 - 4
    xyz, _ = m.keyframe_cloud(0)
    assert np.all(np.isfinite(xyz))
    assert sorted(set(np.round(xyz[:, 2], 3))) == [5.0, 40.0]
    # all-invalid depth keeps nothing but is still a keyframe
    assert m.add_keyframe(5, np.zeros((6, 8), np.float32)) == 0
    assert len(m) == 2


def test_grey_intensity_is_sampled_at_the_pixel_and_replicated_to_rgb():
    m = CloudMap(SMALL, _raw(pixel_step=2))
    u, v = np.meshgrid(np.arange(8), np.arange(6))
    image = (10 * u + 30 * v).astype(np.uint8)
    depth = np.full((6, 8), 2.0, np.float32)
    m.add_keyframe(0, depth, image)
    xyz, grey = m.keyframe_cloud(0)
    assert grey.dtype == np.uint8 and grey.ndim == 1
    pu = np.rint(xyz[:, 0] * 100.0 / 2.0 + 4.0)  # invert eq. 2 to the pixel
    pv = np.rint(xyz[:, 1] * 100.0 / 2.0 + 3.0)
    assert np.array_equal(grey, (10 * pu + 30 * pv).astype(np.uint8))
    cols = np.asarray(m.build(np.tile(np.eye(4), (1, 1, 1))).colors)
    assert np.allclose(cols[:, 0], grey / 255.0) and np.allclose(cols[:, 0], cols[:, 2])


def test_colour_image_and_missing_image_mix():
    m = CloudMap(SMALL, _raw(pixel_step=1))
    image = np.zeros((6, 8, 3), np.uint8)
    image[..., 0], image[..., 1], image[..., 2] = 200, 100, 50
    m.add_keyframe(0, np.full((6, 8), 2.0), image)
    m.add_keyframe(1, np.full((6, 8), 3.0))  # no image: mid-grey in the output
    assert m.keyframe_cloud(0)[1].shape == (48, 3)
    cols = np.rint(np.asarray(m.build(np.tile(np.eye(4), (2, 1, 1))).colors) * 255)
    assert np.array_equal(cols[:48], np.tile([200, 100, 50], (48, 1)))
    assert np.array_equal(cols[48:], np.full((48, 3), 128))


def test_translated_pose_moves_centroid_by_ten_metres():
    m = CloudMap(CAM, MapConfig())  # default voxels on
    m.add_keyframe(0, _plane(10.0))
    c0 = np.asarray(m.build(_pose()[None]).points).mean(axis=0)
    c1 = np.asarray(m.build(_pose((10.0, 0.0, 0.0))[None]).points).mean(axis=0)
    assert c1 - c0 == pytest.approx([10.0, 0.0, 0.0], abs=1e-6)
    assert c0[2] == pytest.approx(10.0, abs=1e-6)


def test_rotated_pose_puts_points_where_they_belong():
    m = CloudMap(CAM, _raw())
    m.add_keyframe(0, _plane(10.0))
    T = _pose((1.0, -2.0, 3.0), yaw_deg=90.0)  # camera looks along world +x
    pts = np.asarray(m.build(T[None]).points)
    # the plane 10 m ahead of the camera lies at world x = 1 + 10, and its lateral spread is along -z
    assert np.allclose(pts[:, 0], 11.0, atol=1e-5)
    assert pts[:, 2].max() == pytest.approx(3.0 + 8.4466, abs=1e-3)
    assert pts[:, 2].min() == pytest.approx(3.0 - 8.8030, abs=1e-3)


def test_reposing_reuses_stored_clouds():
    m = CloudMap(CAM, _raw(keyframe_every=5))
    m.add_keyframe(0, _plane(10.0))
    m.add_keyframe(5, _plane(20.0))
    stored = [m.keyframe_cloud(k)[0].copy() for k in (0, 5)]
    n0 = len(stored[0])
    A = np.tile(np.eye(4), (6, 1, 1))
    A[5] = _pose((0.0, 0.0, 5.0))
    B = A.copy()
    B[5] = _pose((3.0, 0.0, 7.0), yaw_deg=30.0)  # a refinement moved keyframe 5 only
    pa = np.asarray(m.build(A).points)
    pb = np.asarray(m.build(B).points)
    assert np.allclose(pa[:n0], pb[:n0])  # keyframe 0 untouched
    D = B[5] @ np.linalg.inv(A[5])  # the pose difference maps A's points of keyframe 5 onto B's
    assert np.allclose(pa[n0:] @ D[:3, :3].T + D[:3, 3], pb[n0:], atol=1e-5)
    for k, xyz in zip((0, 5), stored):  # stored camera-frame clouds unchanged
        assert np.array_equal(m.keyframe_cloud(k)[0], xyz)


def test_chunked_build_merges_a_revisit_to_one_point_per_voxel():
    """Two keyframes seeing the same plane from the same place (a revisit) in separate chunks
    give the same map as one keyframe alone."""
    cfg = MapConfig(build_chunk_points=1)  # every keyframe its own chunk
    one, two = CloudMap(CAM, cfg), CloudMap(CAM, cfg)
    one.add_keyframe(0, _plane(10.0))
    two.add_keyframe(0, _plane(10.0))
    two.add_keyframe(1, _plane(10.0))
    T = _pose((50.0, 0.0, 40.0))  # the whole plane inside one 100 m tile
    p1 = np.asarray(one.build(T[None]).points)
    p2 = np.asarray(two.build(np.stack([T, T])).points)
    assert len(p2) == len(p1)
    assert np.allclose(np.sort(p2, axis=0), np.sort(p1, axis=0), atol=1e-6)
    assert len(p1) < len(one.keyframe_cloud(0)[0])  # the map voxel (0.3 m) thinned it again


def test_write_ply_round_trip(tmp_path):
    import open3d as o3d

    m = CloudMap(CAM, MapConfig())
    m.add_keyframe(0, _plane(10.0), np.full((CAM.height, CAM.width), 90, np.uint8))
    path = tmp_path / "out" / "map.ply"
    n = m.write_ply(path, _pose()[None])
    assert n == len(m.build(_pose()[None]).points) > 1000
    back = o3d.io.read_point_cloud(str(path))
    assert len(back.points) == n
    assert np.allclose(np.asarray(back.colors), 90 / 255.0, atol=1 / 255)
    assert b"format binary_little_endian" in path.read_bytes()[:200]
    assert sorted(p.name for p in path.parent.iterdir()) == ["map.ply"]  # no temp file left
    with pytest.raises(SnapsGraphError, match=r"\.ply"):
        m.write_ply(tmp_path / "map.pcd", _pose()[None])


def test_topdown_png_is_a_valid_image(tmp_path):
    import cv2

    m = CloudMap(CAM, MapConfig(topdown_dpi=40))
    m.add_keyframe(0, _plane(10.0))
    m.add_keyframe(5, _plane(15.0))
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[5] = _pose((0.0, 0.0, 4.0))
    path = tmp_path / "map.png"
    drawn = m.render_topdown_png(path, poses, {"gt": poses, "xyz": poses[:, :3, 3]}, max_points=500)
    assert 250 <= drawn <= 500
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (320, 320, 3)  # 8 x 8 inch at 40 dpi
    assert img.std() > 5  # not a blank canvas
    m.render_topdown_png(tmp_path / "grey.png", poses, colour_by="intensity")
    assert cv2.imread(str(tmp_path / "grey.png")) is not None
    with pytest.raises(SnapsGraphError, match="trajectory 'bad'"):
        m.render_topdown_png(path, poses, {"bad": np.zeros((4, 2))})


def test_memory_per_keyframe_is_bounded():
    n_grid = 311 * 94
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 40.0, (CAM.height, CAM.width)).astype(np.float32)
    image = rng.integers(0, 256, (CAM.height, CAM.width), dtype=np.uint8)
    raw = CloudMap(CAM, _raw(pixel_step=4, max_range_m=40.0))
    assert raw.add_keyframe(0, depth, image) == n_grid
    assert raw.memory_bytes() == 13 * n_grid  # float32 xyz + uint8 grey: 380,142 B
    m = CloudMap(CAM, MapConfig(pixel_step=4))
    kept = m.add_keyframe(0, depth, image)
    assert m.memory_bytes() == 13 * kept <= 13 * n_grid
    m.add_keyframe(5, depth, image)
    assert m.memory_bytes() == 2 * 13 * kept and m.num_stored_points() == 2 * kept


def test_keyframe_bookkeeping():
    m = CloudMap(SMALL, MapConfig(keyframe_every=5))
    assert [k for k in range(12) if m.should_add(k)] == [0, 5, 10]
    m.add_keyframe(10, np.full((6, 8), 2.0))
    m.add_keyframe(0, np.full((6, 8), 2.0))
    m.add_keyframe(0, np.full((6, 8), 3.0))  # replaces
    assert len(m) == 2 and m.keyframes == [0, 10]
    assert np.allclose(m.keyframe_cloud(0)[0][:, 2], 3.0)
    assert len(CloudMap(SMALL).build(np.zeros((0, 4, 4))).points) == 0


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda m: m.add_keyframe(0, np.ones((5, 8))), "depth is 8x5 but the camera is 8x6"),
        (lambda m: m.add_keyframe(0, np.ones(48)), r"\(H, W\)"),
        (lambda m: m.add_keyframe(-1, np.ones((6, 8))), "non-negative"),
        (lambda m: m.add_keyframe(0, np.ones((6, 8)), np.ones((6, 8))), "uint8"),
        (lambda m: m.add_keyframe(0, np.ones((6, 8)), np.ones((6, 7), np.uint8)), "matching depth"),
        (lambda m: m.keyframe_cloud(3), "not in the map"),
    ],
)
def test_bad_keyframe_input(call, message):
    with pytest.raises(SnapsGraphError, match=message):
        call(CloudMap(SMALL))


def test_bad_poses_and_empty_map(tmp_path):
    m = CloudMap(SMALL)
    with pytest.raises(SnapsGraphError, match="empty"):
        m.write_ply(tmp_path / "m.ply", np.eye(4)[None])
    m.add_keyframe(5, np.full((6, 8), 2.0))
    with pytest.raises(SnapsGraphError, match="has 3 entries but the map has keyframe 5"):
        m.build(np.tile(np.eye(4), (3, 1, 1)))
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[5, 0, 3] = np.nan
    with pytest.raises(SnapsGraphError, match="keyframe 5 is not finite"):
        m.build(poses)
    with pytest.raises(SnapsGraphError, match=r"\(N, 4, 4\)"):
        m.build(np.eye(4))
    with pytest.raises(SnapsGraphError, match="pixel_step"):
        CloudMap(SMALL, MapConfig(pixel_step=0))


def test_import_does_not_load_open3d():
    code = "import sys, snaps_graph.mapping; print('open3d' in sys.modules, 'matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
