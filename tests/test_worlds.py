"""Synthetic world variants: scenes (street / open / mixed), hard worlds (aliasing, traffic,
lighting), the world mesh. Small images and few frames: each test takes seconds."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from inprocess import cli  # the command line in this process (tests/inprocess.py)

from snaps_graph.errors import SnapsGraphError
from snaps_graph.synth import SyntheticSequence, WorldConfig, builtin_loop_trajectory, load_trajectory
from snaps_graph.trajectory_io import read_kitti_poses

W, H = 320, 96


def digest(seq: SyntheticSequence, frames) -> str:
    h = hashlib.sha256()
    for i in frames:
        f = seq.render(i)
        for a in (f.left, f.right, f.depth):
            h.update(a.tobytes())
    return h.hexdigest()[:16]


def straight(n: int, step: float = 2.0) -> np.ndarray:
    P = np.repeat(np.eye(4)[None], n, axis=0)
    P[:, 2, 3] = np.arange(n) * step
    return P


def median_depth(seq: SyntheticSequence, frames, above_horizon: bool = False) -> float:
    """Median depth of the pixels that hit something (only the rows above the principal point)."""
    rows = slice(0, int(seq.camera.cy)) if above_horizon else slice(None)
    d = np.concatenate([seq.depth(i)[rows].ravel() for i in frames])
    return float(np.median(d[d > 0]))


# ---------------------------------------------------------------- street is the original world
# Ray casting and float rounding differ in the last bits between CPUs (SIMD widths), so the
# reference is the renders' block statistics, not a digest: a change to the world, its texture,
# light or noise moves blocks by grey levels; another CPU moves them by far less than the bounds.
REFERENCE = Path(__file__).parent / "data" / "street_render_reference.json"
GRID = (4, 8)  # block rows, block columns


def block_stats(seq: SyntheticSequence, frames) -> dict[str, list[float]]:
    """Per frame: left and right block means (grey), depth block means over hit pixels (m), hit fraction."""
    out: dict[str, list[float]] = {}
    for i in frames:
        f = seq.render(i)
        for name, a in (("left", f.left), ("right", f.right)):
            blocks = a.astype(np.float64).reshape(GRID[0], a.shape[0] // GRID[0], GRID[1], a.shape[1] // GRID[1])
            out[f"{i}/{name}"] = blocks.mean((1, 3)).ravel().tolist()
        d = f.depth.astype(np.float64).reshape(GRID[0], f.depth.shape[0] // GRID[0], GRID[1], f.depth.shape[1] // GRID[1])
        hit = d > 0
        out[f"{i}/depth"] = (np.where(hit, d, 0).sum((1, 3)) / np.maximum(hit.sum((1, 3)), 1)).ravel().tolist()
        out[f"{i}/hit"] = [float(hit.mean())]
    return out


def assert_matches_reference(stats: dict[str, list[float]], key: str) -> None:
    ref = json.loads(REFERENCE.read_text())[key]
    assert sorted(stats) == sorted(ref)
    for name, values in stats.items():
        got, want = np.array(values), np.array(ref[name])
        if name.endswith(("left", "right")):
            assert np.abs(got - want).max() <= 0.25, (key, name, np.abs(got - want).max())
        elif name.endswith("depth"):
            assert np.allclose(got, want, rtol=1e-3, atol=1e-3), (key, name)
        else:
            assert abs(got[0] - want[0]) <= 0.002, (key, name)


def street_loop() -> SyntheticSequence:
    return SyntheticSequence(builtin_loop_trajectory(120), width=W, height=H, seed=3)


def street_kitti00(kitti_gt_dir: Path) -> SyntheticSequence:
    poses, times = load_trajectory(str(kitti_gt_dir / "00.txt"), "0:300")
    return SyntheticSequence(poses, width=416, height=128, seed=0, times=times, noise_std=2.0, exposure_change=0.2)


def test_street_renders_as_the_reference():
    """The built-in loop's street renders as it did before scenes and hard worlds existed."""
    seq = street_loop()
    assert_matches_reference(block_stats(seq, [0, 37, 105]), "loop")
    explicit = SyntheticSequence(
        builtin_loop_trajectory(120), width=W, height=H, seed=3, world_config=WorldConfig(scene="street")
    )
    assert digest(explicit, [37]) == digest(seq, [37])


def test_street_kitti00_with_noise_and_exposure_renders_as_the_reference(kitti_gt_dir):
    assert_matches_reference(block_stats(street_kitti00(kitti_gt_dir), [0, 150, 299]), "kitti00")


# ---------------------------------------------------------------- scenes
@pytest.fixture(scope="module")
def path00(kitti_gt_dir):
    return load_trajectory(str(kitti_gt_dir / "00.txt"), "0:200")


def test_open_scene_is_far_and_deterministic(path00):
    poses, times = path00
    street = SyntheticSequence(poses, width=W, height=H, seed=0, times=times)
    open_ = SyntheticSequence(poses, width=W, height=H, seed=0, times=times, world_config=WorldConfig(scene="open"))
    frames = [20, 80, 140, 190]
    # above the horizon: street facades 5-40 m away, open trees, farms and hills from 30 m on
    d_street, d_open = median_depth(street, frames, True), median_depth(open_, frames, True)
    assert d_open > 3.0 * d_street, (d_open, d_street)
    # nothing but the road's posts within 30 m of the path: every tree and farm stands further away
    S = open_.world.samples
    for x, z, _, r in open_.world.trees[::7]:
        assert np.min(np.hypot(S[:, 0] - x, S[:, 1] - z)) >= 30.0 - r - 0.5
    farms = [b for b in open_.world.boxes if b.style == "farm"]
    assert farms and open_.world.trees
    again = SyntheticSequence(poses, width=W, height=H, seed=0, times=times, world_config=WorldConfig(scene="open"))
    assert digest(again, [80]) == digest(open_, [80])
    other = SyntheticSequence(poses, width=W, height=H, seed=1, times=times, world_config=WorldConfig(scene="open"))
    assert digest(other, [80]) != digest(open_, [80])


def test_mixed_scene_alternates_street_and_open():
    P = straight(300)  # 600 m: several 150-400 m stretches
    cfg = WorldConfig(scene="mixed")
    seq = SyntheticSequence(P, width=W, height=H, seed=2, world_config=cfg)
    is_open = seq.world.sample_open
    assert is_open is not None
    assert is_open.any() and (~is_open).any()
    # street buildings stand only along street stretches, trees only beside open ones
    k_box = [
        int(np.argmin(np.linalg.norm(seq.world.samples - b.corners.mean(0), axis=1)))
        for b in seq.world.boxes
        if b.style == "building"
    ]
    assert k_box and not is_open[k_box].any()
    # the view down an open stretch is deeper than down a street stretch
    z_frame = P[:, 2, 3]
    arc0 = int(np.argmin(np.linalg.norm(seq.world.samples, axis=1)))  # sample of frame 0 (after the head)
    open_frames = [i for i in range(0, 300, 10) if is_open[arc0 + int(z_frame[i])]]
    street_frames = [i for i in range(0, 300, 10) if not is_open[arc0 + int(z_frame[i])]]
    assert median_depth(seq, open_frames[:4], True) > 2.0 * median_depth(seq, street_frames[:4], True)
    assert digest(SyntheticSequence(P, width=W, height=H, seed=2, world_config=cfg), [50]) == digest(seq, [50])


# ---------------------------------------------------------------- hard worlds
def test_aliasing_repeats_modules_and_blocks():
    P = straight(150)
    seq = SyntheticSequence(P, width=W, height=H, seed=4, world_config=WorldConfig(aliasing=True))
    world = seq.world
    buildings = [b for b in world.boxes if b.style == "building"]
    assert len(buildings) > 10 and all(0 <= b.module < 3 for b in buildings)
    sizes = {(round(b.height, 6), b.module) for b in buildings}
    assert len(sizes) <= 4  # one block of 4 buildings, repeated
    # two boxes of a module have identical facade rows (texture offset, identity, windows, bricks)
    same = [b for b in buildings if b.module == buildings[0].module]
    assert len(same) >= 2
    plain = SyntheticSequence(P, width=W, height=H, seed=4)
    assert len({round(b.height, 6) for b in plain.world.boxes if b.style == "building"}) > 10

    # distinct places look more alike: mean similarity of frames 40-100 m apart
    def mean_ncc(s: SyntheticSequence) -> float:
        th = {i: s[i].left.astype(float) for i in range(10, 150, 10)}
        vals = []
        for i in th:
            for j in th:
                if 20 <= j - i <= 50:
                    a, b = th[i] - th[i].mean(), th[j] - th[j].mean()
                    vals.append((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
        return float(np.mean(vals))

    assert mean_ncc(seq) > mean_ncc(plain) + 0.05
    assert digest(SyntheticSequence(P, width=W, height=H, seed=4, world_config=WorldConfig(aliasing=True)), [30]) == digest(
        seq, [30]
    )


@pytest.fixture(scope="module")
def loop300():
    # a 250 m loop whose frames 250-299 re-drive frames 0-49, 2 s apart: the revisit is ~8 min later
    P = builtin_loop_trajectory(300)
    return P, np.arange(300) * 2.0


def test_traffic_differs_between_passes(loop300):
    P, times = loop300
    cfg = WorldConfig(traffic=True, pass_radius_m=30.0)
    seq = SyntheticSequence(P, width=W, height=H, seed=5, times=times, world_config=cfg)
    tr = seq.world.traffic
    assert tr is not None
    assert len(tr.slots) > 20 and len(tr.oncoming) > 20
    # the same place on the two passes (frame k and k + 250): other parked cars
    xz = P[:, [0, 2], 3]
    near = np.array([np.linalg.norm(xz[:50] - c, axis=1).min() < 20.0 for c, *_ in tr.slots])
    assert near.sum() >= 5
    first, second = tr.parked[near, 10], tr.parked[near, 260]
    assert (first != second).any() and first.any()
    # fixed within a pass: no car appears or vanishes while the camera drives past
    for j in np.flatnonzero(near):
        in_range = np.flatnonzero(np.linalg.norm(xz[:150] - tr.slots[j][0], axis=1) < 30.0)
        assert len(set(tr.parked[j, in_range])) == 1
    # and the rendered depth shows it where no car is moving past
    diffs = [np.mean(seq.depth(k) != seq.depth(k + 250)) for k in range(0, 50, 5)]
    assert max(diffs) > 0.01
    plain = SyntheticSequence(P, width=W, height=H, seed=5, times=times)
    assert all(np.array_equal(plain.depth(k), plain.depth(k + 250)) for k in (0, 20))
    assert np.array_equal(plain.world.vertices, seq.world.vertices)  # traffic leaves the static world alone
    # a car is never where the camera is: the nearest depth in view stays above 1.5 m
    assert min(seq.depth(k)[seq.depth(k) > 0].min() for k in range(0, 300, 15)) > 1.5
    assert digest(SyntheticSequence(P, width=W, height=H, seed=5, times=times, world_config=cfg), [10, 260]) == digest(
        seq, [10, 260]
    )


def test_lighting_differs_between_passes(loop300):
    P, times = loop300
    cfg = WorldConfig(lighting=True)
    seq = SyntheticSequence(P, width=W, height=H, seed=6, times=times, world_config=cfg)
    a, b = seq.render(10), seq.render(260)
    np.testing.assert_array_equal(a.depth, b.depth)  # same pose, same geometry
    assert np.mean(np.abs(a.left.astype(int) - b.left.astype(int))) > 5.0  # other light
    sun_a, sun_b = seq.sun(10), seq.sun(260)
    assert sun_a is not None and sun_b is not None
    assert np.degrees(np.arccos(np.clip(sun_a @ sun_b, -1, 1))) > 30.0
    hit = seq._renderer.cast(seq.gt_poses[10][:3, :3], seq.gt_poses[10][:3, 3], sun=seq.sun(10))
    assert 0.02 < hit["shadow"].mean() < 0.9  # cast shadows, not everything dark
    plain = SyntheticSequence(P, width=W, height=H, seed=6, times=times)
    assert np.array_equal(plain[10].left, plain[260].left)
    assert digest(SyntheticSequence(P, width=W, height=H, seed=6, times=times, world_config=cfg), [10]) == digest(seq, [10])


# ---------------------------------------------------------------- world mesh and the CLI
def test_world_mesh_agrees_with_rendered_depth(tmp_path):
    import open3d as o3d

    out, mesh = tmp_path / "seq", tmp_path / "world.ply"
    r = cli(
        "synth",
        "--trajectory",
        "loop",
        "--frames",
        "100:106",
        "--width",
        str(W),
        "--height",
        str(H),
        "--scene",
        "mixed",
        "--traffic",
        "--depth",
        "--out",
        str(out),
        "--world-mesh",
        str(mesh),
    )
    assert r.returncode == 0, r.stderr
    m = o3d.io.read_triangle_mesh(str(mesh))
    assert len(m.triangles) > 1000
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    poses = read_kitti_poses(out / "poses.txt")
    cam = SyntheticSequence(poses, width=W, height=H).camera
    seq = SyntheticSequence(poses, width=W, height=H, world_config=WorldConfig(scene="mixed"))
    for i in (0, 5):
        T = poses[i]
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1).reshape(-1, 3) @ T[:3, :3].T
        rays = np.hstack([np.repeat(T[None, :3, 3], len(d), 0), d]).astype(np.float32)
        z = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(H, W)
        z = np.where(np.isfinite(z), z, 0.0)
        ref = seq.depth(i)  # the static world's depth from the GT pose
        ok = ref > 0
        assert np.mean((z > 0) != ok) < 1e-3
        ok &= z > 0
        assert np.percentile(np.abs(z[ok] - ref[ok]) / ref[ok], 99) < 1e-3
    # the written depth (with traffic) agrees with the mesh wherever no car stands in front
    import cv2

    mm = cv2.imread(str(out / "depth_0" / "000000.png"), cv2.IMREAD_UNCHANGED) / 1000.0
    ref = seq.depth(0)
    both = (mm > 0) & (ref > 0) & (ref < 60)
    assert np.mean(np.abs(mm[both] - ref[both]) < 0.002) > 0.8


def test_mesh_only_writes_no_images(tmp_path):
    import open3d as o3d

    r = cli(
        "synth",
        "--trajectory",
        "loop",
        "--frames",
        "0:5",
        "--out",
        str(tmp_path / "s"),
        "--world-mesh",
        str(tmp_path / "w.ply"),
        "--mesh-only",
    )
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / "s").exists()
    assert len(o3d.io.read_triangle_mesh(str(tmp_path / "w.ply")).triangles) > 1000


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--scene", "desert"], "--scene 'desert'"),
        (["--world-mesh", "world.txt"], "--world-mesh"),
        (["--mesh-only"], "--mesh-only"),
        (["--rectification-error", "9"], "rectification error"),
    ],
)
def test_bad_synth_options_are_one_line_errors(tmp_path, args, needle):
    r = cli(
        "synth", "--trajectory", "loop", "--frames", "0:3", "--width", "64", "--height", "32", "--out", str(tmp_path / "s"), *args
    )
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0]


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(scene="desert"),
        dict(open_distance_m=(2.0, 200.0)),
        dict(tree_height_m=(10.0, 5.0)),
        dict(parked_probability=1.5),
        dict(alias_modules=0),
        dict(oncoming_period_s=0.0),
        dict(day_hours_per_minute=-1.0),
    ],
)
def test_bad_world_config_is_a_one_line_error(kwargs):
    with pytest.raises(SnapsGraphError) as err:
        SyntheticSequence(straight(5), width=64, height=32, world_config=WorldConfig(**kwargs))
    assert "\n" not in str(err.value)


def test_rectification_error_shrinks_every_disparity():
    """The right camera is turned so disparities read `error` px smaller than calib.txt implies."""
    import cv2

    P = straight(30, 1.0)
    err = 0.8
    ref = SyntheticSequence(P, width=W, height=H, seed=1)
    seq = SyntheticSequence(P, width=W, height=H, seed=1, rectification_error_px=err)
    f, z = seq.render(10), seq.depth(10)
    assert np.array_equal(f.left, ref[10].left)  # the left camera is the reference
    cam = seq.camera
    disp = np.where(z > 0, cam.fx * cam.baseline_m / np.maximum(z, 1e-6), 0).astype(np.float32)
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    grad = np.hypot(cv2.Sobel(f.left, cv2.CV_32F, 1, 0), cv2.Sobel(f.left, cv2.CV_32F, 0, 1))
    mask = (z > 0) & (uu - disp > 3) & (grad > 30)

    def res(d):
        warped = cv2.remap(f.right.astype(np.float32), uu - d, vv, cv2.INTER_LINEAR)
        return np.median(np.abs(warped - f.left.astype(np.float32))[mask])

    assert res(disp - err) < 0.7 * res(disp)
    with pytest.raises(SnapsGraphError):
        SyntheticSequence(P, width=W, height=H, rectification_error_px=float("nan"))
