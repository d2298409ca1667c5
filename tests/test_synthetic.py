"""Synthetic stereo worlds: exact depth, stereo consistency, revisits, the KITTI-layout writer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.geometry import rotation_angle_deg, wrap_deg, yaw_deg
from snaps_graph.synth import (
    SyntheticSequence,
    builtin_loop_trajectory,
    load_trajectory,
    render_to_folder,
)
from snaps_graph.trajectory_io import read_kitti_poses

W, H = 320, 96


def straight_path(n: int = 40, step: float = 1.0) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = np.arange(n) * step
    return poses


def turn_yaw(T: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ Ry
    return out


def thumb(img: np.ndarray) -> np.ndarray:
    return cv2.resize(img, (img.shape[1] // 6, img.shape[0] // 6), interpolation=cv2.INTER_AREA).astype(float)


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


@pytest.fixture(scope="module")
def loop_seq() -> SyntheticSequence:
    # 120 frames: a 100 m loop whose last 20 frames re-drive frames 0-19
    return SyntheticSequence(builtin_loop_trajectory(120), width=W, height=H, seed=3)


@pytest.fixture(scope="module")
def straight_seq() -> SyntheticSequence:
    return SyntheticSequence(straight_path(), width=W, height=H, seed=1)


# ---------------------------------------------------------------- trajectories
def test_builtin_loop_closes_and_redrives_the_start():
    P = builtin_loop_trajectory(300)
    assert P.shape == (300, 4, 4)
    np.testing.assert_allclose(P[0], np.eye(4), atol=1e-12)
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, 1.0, atol=0.02)  # ~1 m per frame, like KITTI at 10 Hz
    # frames 250..299 stand exactly where frames 0..49 stood, same orientation
    np.testing.assert_allclose(P[250:, :3, 3], P[:50, :3, 3], atol=1e-6)
    np.testing.assert_allclose(P[250:, :3, :3], P[:50, :3, :3], atol=1e-6)
    # end near start, but only after driving the whole loop (the farthest point is far away)
    assert np.linalg.norm(P[249, :3, 3] - P[0, :3, 3]) < 1.5
    assert np.linalg.norm(P[:, :3, 3], axis=1).max() > 50.0
    # curves: the heading turns through a full circle; gentle height change
    turn = np.sum(wrap_deg(np.diff(yaw_deg(P[:250]))))
    assert abs(abs(turn) - 360.0) < 3.0
    assert 1.0 < np.ptp(P[:, 1, 3]) < 5.0


def test_builtin_loop_rejects_too_few_frames():
    with pytest.raises(SnapsGraphError):
        builtin_loop_trajectory(10)


def test_load_trajectory_loop_and_range():
    poses, times = load_trajectory("loop:120", "10:30")
    assert poses.shape == (20, 4, 4) and len(times) == 20
    np.testing.assert_allclose(poses, builtin_loop_trajectory(120)[10:30])
    np.testing.assert_allclose(times, np.arange(10, 30) * 0.1)
    with pytest.raises(SnapsGraphError):
        load_trajectory("loop:abc", None)
    with pytest.raises(SnapsGraphError):
        load_trajectory("/nonexistent/poses.txt", None)


def test_load_trajectory_reads_times_beside_kitti_file(kitti_gt_dir):
    poses, times = load_trajectory(str(kitti_gt_dir / "07.txt"), "100:110")
    assert poses.shape == (10, 4, 4)
    all_poses = read_kitti_poses(kitti_gt_dir / "07.txt")
    np.testing.assert_allclose(poses, all_poses[100:110])
    stamps = np.loadtxt(kitti_gt_dir / "07_times.txt")
    np.testing.assert_allclose(times, stamps[100:110])
    # an explicit times file must match the whole path
    _, t2 = load_trajectory(str(kitti_gt_dir / "07.txt"), "0:5", times=kitti_gt_dir / "07_times.txt")
    np.testing.assert_allclose(t2, stamps[:5])
    with pytest.raises(SnapsGraphError):
        load_trajectory(str(kitti_gt_dir / "07.txt"), None, times=kitti_gt_dir / "00_times.txt")


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs",
    [
        dict(poses=np.full((3, 4, 4), np.nan)),
        dict(poses=np.zeros((3, 3, 4))),
        dict(poses=np.repeat((2 * np.eye(4))[None], 3, 0)),  # not a rotation
        dict(poses=straight_path(3), noise_std=-1.0),
        dict(poses=straight_path(3), exposure_change=1.5),
        dict(poses=straight_path(3), times=np.zeros(2)),
        dict(poses=straight_path(3), baseline_m=0.0),
        dict(poses=straight_path(3), width=0),
    ],
)
def test_bad_input_is_a_one_line_error(kwargs):
    with pytest.raises(SnapsGraphError) as err:
        SyntheticSequence(**kwargs)
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------- rendering
def test_same_seed_gives_identical_images_other_seed_differs(loop_seq):
    P = builtin_loop_trajectory(120)
    again = SyntheticSequence(P, width=W, height=H, seed=3)
    a, b = loop_seq[7], again[7]
    assert a.left.dtype == np.uint8 and a.left.shape == (H, W)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    other = SyntheticSequence(P, width=W, height=H, seed=4)[7]
    assert np.mean(np.abs(a.left.astype(int) - other.left.astype(int))) > 5.0


def test_protocol(loop_seq):
    assert len(loop_seq) == 120
    assert loop_seq.camera.width == W and loop_seq.camera.height == H
    np.testing.assert_allclose(loop_seq.gt_poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(loop_seq.timestamps[:3], [0.0, 0.1, 0.2])
    assert list(loop_seq.indices[:3]) == [0, 1, 2]
    frame = loop_seq[-1]
    assert frame.index == 119 and frame.timestamp == pytest.approx(11.9)
    with pytest.raises(IndexError):
        loop_seq[120]


def test_images_have_texture_everywhere_but_the_sky(loop_seq):
    f = loop_seq[30]
    depth = loop_seq.depth(30)
    assert np.isfinite(depth).all() and (depth == 0).any() and (depth > 0).mean() > 0.5
    gx = cv2.Sobel(f.left, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(f.left, cv2.CV_32F, 0, 1)
    grad = np.hypot(gx, gy)
    # ground rows (bottom quarter) and walls are textured: most 8x8 blocks have gradient
    blocks = grad[: H // 8 * 8, : W // 8 * 8].reshape(H // 8, 8, W // 8, 8).max(axis=(1, 3))
    valid_blocks = (depth[: H // 8 * 8, : W // 8 * 8].reshape(H // 8, 8, W // 8, 8) > 0).all(axis=(1, 3))
    assert (blocks[valid_blocks] > 20).mean() > 0.9
    # KLT corners spread over the frame (ORB's 31 px border leaves little of a 320x96 image)
    corners = cv2.goodFeaturesToTrack(f.left, 1000, 0.01, 4)
    assert corners is not None and len(corners) > 120


def test_ground_depth_matches_the_ground_plane(straight_seq):
    """Level camera 1.65 m above flat ground: bottom rows at z = h fy / (v - cy)."""
    cam = straight_seq.camera
    depth = straight_seq.depth(5)
    u = W // 2
    for v in (H - 1, H - 5, H - 12):
        expected = 1.65 * cam.fy / (v - cam.cy)
        assert depth[v, u] == pytest.approx(expected, rel=0.005)


def test_wall_depth_lies_on_a_building_face(straight_seq):
    """Turned to face the side of the street, the centre pixel's 3D point lies on a box face."""
    world = straight_seq.world
    hits = 0
    for i, turn in ((10, 90.0), (20, -90.0), (30, 90.0), (15, -90.0)):
        T = turn_yaw(straight_seq.gt_poses[i], turn)
        hit = straight_seq._renderer.cast(T[:3, :3], T[:3, 3])
        depth = straight_seq._renderer.depth(hit)
        z = float(depth[H // 2, W // 2])
        if z == 0:
            continue
        p = T[:3, :3] @ straight_seq.camera.backproject(W // 2, H // 2, z) + T[:3, 3]  # eq. 2
        best = np.inf
        for box in world.boxes:
            c = box.corners
            for k in range(4):
                a, b = c[k], c[(k + 1) % 4]
                t = b - a
                length = np.linalg.norm(t)
                t = t / length
                nrm = np.array([-t[1], t[0]])
                rel = p[[0, 2]] - a
                along = rel @ t
                if -0.01 <= along <= length + 0.01 and box.ground_y - box.height - 0.01 <= p[1] <= box.bottom_y:
                    best = min(best, abs(rel @ nrm))
        assert best < 0.01, f"frame {i}: centre point {p} is {best:.3f} m from every box face"
        assert z > 5.0  # nothing intrudes into the 5 m corridor
        hits += 1
    assert hits >= 2


def test_stereo_consistency(loop_seq):
    """Right image at (u - fB/z, v) matches the left image at textured, visible pixels."""
    i = 40
    f = loop_seq[i]
    z = loop_seq.depth(i)
    cam = loop_seq.camera
    disp = np.where(z > 0, cam.fx * cam.baseline_m / np.maximum(z, 1e-6), 0).astype(np.float32)
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    grad = np.hypot(cv2.Sobel(f.left, cv2.CV_32F, 1, 0), cv2.Sobel(f.left, cv2.CV_32F, 0, 1))
    mask = (z > 0) & (uu - disp > 2) & (grad > 30)
    assert mask.sum() > 1000

    def err(d):
        warped = cv2.remap(f.right.astype(np.float32), uu - d, vv, cv2.INTER_LINEAR)
        return np.median(np.abs(warped - f.left.astype(np.float32))[mask])

    right_disp = err(disp)
    assert right_disp < 4.0
    assert err(disp + 2.0) > 2 * right_disp  # a wrong disparity is clearly worse: the test can fail


def test_revisit_gives_the_same_image(loop_seq):
    # loop of 120 frames: frame k + 100 stands where frame k stood
    np.testing.assert_allclose(loop_seq.gt_poses[105], loop_seq.gt_poses[5], atol=1e-6)
    a, b = loop_seq[5], loop_seq[105]
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)


def test_noise_and_exposure_change_are_seeded_and_make_revisits_differ(loop_seq):
    P = builtin_loop_trajectory(120)
    clean = loop_seq[5].left.astype(float)
    noisy = SyntheticSequence(P, width=W, height=H, seed=3, noise_std=4.0)
    a = noisy[5]
    assert np.array_equal(a.left, SyntheticSequence(P, width=W, height=H, seed=3, noise_std=4.0)[5].left)
    unclipped = (clean > 20) & (clean < 235)
    assert np.std((a.left - clean)[unclipped]) == pytest.approx(4.0, rel=0.1)  # grey levels
    clean_r = loop_seq[5].right.astype(float)
    both = unclipped & (clean_r > 20) & (clean_r < 235)
    assert abs(ncc((a.left - clean)[both], (a.right - clean_r)[both])) < 0.1  # independent per camera

    exposed = SyntheticSequence(P, width=W, height=H, seed=3, exposure_change=0.3)
    gains = []
    for k in (5, 105):
        img = exposed[k].left.astype(float)
        gain, offset = np.polyfit(clean[unclipped], img[unclipped], 1)  # img = gain * clean + offset
        assert 0.7 <= gain <= 1.3 and abs(offset) <= 9.5
        gains.append(gain)
    assert abs(gains[0] - gains[1]) > 0.01  # the revisit (frame 105 = frame 5) is not pixel-identical
    assert ncc(thumb(exposed[5].left), thumb(exposed[105].left)) > 0.9  # but it is the same place


# ---------------------------------------------------------------- writer
def test_render_to_folder_reads_back(tmp_path):
    P = builtin_loop_trajectory(120)[30:34]
    P = P @ np.diag([1.0, 1.0, 1.0, 1.0])  # not rebased on input: the writer rebases
    seq = SyntheticSequence(P, width=W, height=H, seed=2)
    calls = []
    out = tmp_path / "synth"
    totals = render_to_folder(seq, out, progress=lambda: calls.append(1), write_depth=True)
    assert len(calls) == 4 and totals["frames"] == 4
    back = KittiSequence(out)
    assert len(back) == 4
    assert back.gt_poses is not None
    assert back.camera.fx == pytest.approx(seq.camera.fx) and back.camera.baseline_m == pytest.approx(seq.camera.baseline_m)
    assert (back.camera.width, back.camera.height) == (W, H)
    np.testing.assert_allclose(back.gt_poses, np.linalg.inv(P[0]) @ P, atol=1e-6)
    np.testing.assert_allclose(back.timestamps, seq.timestamps, atol=1e-6)
    for i in range(4):
        assert np.array_equal(back[i].left, seq[i].left) and np.array_equal(back[i].right, seq[i].right)
    mm = cv2.imread(str(out / "depth_0" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16
    z = seq.depth(2)
    ok = (z > 0) & (z < 65.0)
    np.testing.assert_allclose(mm[ok] / 1000.0, z[ok], atol=0.0006)
    assert (mm[z == 0] == 0).all()
    with pytest.raises(SnapsGraphError):  # never writes over an existing sequence by accident
        render_to_folder(seq, out)


# ---------------------------------------------------------------- the real KITTI 00 path
@pytest.fixture(scope="module")
def kitti00(kitti_gt_dir):
    poses, times = load_trajectory(str(kitti_gt_dir / "00.txt"))
    return SyntheticSequence(poses, width=W, height=H, times=times, seed=0)


def test_kitti00_camera_stays_1p65_m_above_the_ground(kitti00):
    P = kitti00.gt_poses
    ground_pts = P[:, :3, 3] + 1.65 * P[:, :3, 1]
    err = np.abs(kitti00.world.ground_y(ground_pts[:, 0], ground_pts[:, 2]) - ground_pts[:, 1])
    # where the path passes once (nothing of it within 15 m more than 60 frames away) the
    # ground is where the camera says it is
    xz, idx = P[:, [0, 2], 3], np.arange(len(P))
    once = np.array([not ((np.linalg.norm(xz - xz[i], axis=1) < 15) & (np.abs(idx - i) > 60)).any() for i in idx])
    assert once.sum() > 1000
    assert err[once].max() < 0.1
    # KITTI's ground truth revisits some places up to ~1.5 m higher or lower than the first
    # pass; one ground cannot meet both, it takes their average there
    assert np.median(err) < 0.05 and err.max() < 1.0
    assert np.ptp(P[:, 1, 3]) > 10.0  # the path climbs and falls: the ground follows it


def test_kitti00_no_building_in_the_corridor(kitti00):
    S = kitti00.gt_poses[:, [0, 2], 3]
    for box in kitti00.world.boxes:
        # sample each footprint's edges densely and measure the distance to every path point
        c = np.vstack([box.corners, box.corners[:1]])
        pts = np.concatenate([np.linspace(c[k], c[k + 1], 20) for k in range(4)])
        d = np.sqrt(((pts[:, None, :] - S[None, ::2, :]) ** 2).sum(-1)).min()
        assert d > 4.5


def test_kitti00_revisited_place_looks_alike(kitti00):
    P = kitti00.gt_poses
    pos, yaw = P[:, :3, 3], np.asarray(yaw_deg(P))
    # the revisit more than 100 frames later that stands closest to a first-pass pose (3D
    # distance plus rotation: KITTI's revisits differ by decimetres in height, degrees in yaw)
    best = None
    j: np.ndarray | int
    for i in range(0, len(P) - 101, 5):
        j = np.arange(i + 101, len(P))
        d = np.linalg.norm(pos[j] - pos[i], axis=1)
        ok = (d < 3.0) & (np.abs(wrap_deg(yaw[j] - yaw[i])) < 10.0)
        for k in j[ok]:
            score = np.linalg.norm(pos[k] - pos[i]) + 0.5 * rotation_angle_deg(P[i, :3, :3].T @ P[k, :3, :3])
            if best is None or score < best[2]:
                best = (i, int(k), score)
    assert best is not None
    i, j, _ = best
    far = int(np.argmax(np.linalg.norm(pos - pos[i], axis=1)))
    ti, tj, tf = (thumb(kitti00[k].left) for k in (i, j, far))
    same, other = ncc(ti, tj), ncc(ti, tf)
    assert same > 0.7, (i, j, same)
    assert other < same - 0.2, (i, far, other, same)
