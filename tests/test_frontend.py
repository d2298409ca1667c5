"""Stereo VO front end: depth (eq. 1), PnP motion, robustness, loop verification."""

from __future__ import annotations

import re
from typing import Any, cast

import cv2
import numpy as np
import pytest

from snaps_graph.camera import StereoCamera
from snaps_graph.config import FrontendConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.frontend import StereoOdometry, dense_depth, sparse_depth
from snaps_graph.frontend import features as feat
from snaps_graph.geometry import rotation_angle_deg
from snaps_graph.types import FrameFeatures, StereoFrame

CAM = StereoCamera(fx=500.0, fy=500.0, cx=320.0, cy=160.0, baseline_m=0.5, width=640, height=320)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Blurred noise: corners everywhere, no repetition (unambiguous matching)."""
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.5)
    return cv2.normalize(t, None, 0, 255, cv2.NORM_MINMAX)


def _render_plane(cam: StereoCamera, centre: np.ndarray, plane_z: float, tex: np.ndarray, res_m: float) -> np.ndarray:
    """Left image of a fronto-parallel textured plane z = plane_z seen by an unrotated camera at ``centre``.

    Each pixel's ray hits the plane at X = cx_c + (z - cz_c)(u - cx)/fx (and likewise Y); the
    texture (``res_m`` metres per texel, centred on the origin) is sampled there with remap.
    """
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float32), np.arange(cam.height, dtype=np.float32))
    t = plane_z - centre[2]
    X = centre[0] + t * (u - cam.cx) / cam.fx
    Y = centre[1] + t * (v - cam.cy) / cam.fy
    mx = (X / res_m + tex.shape[1] / 2).astype(np.float32)
    my = (Y / res_m + tex.shape[0] / 2).astype(np.float32)
    return cv2.remap(tex, mx, my, cv2.INTER_LINEAR).astype(np.uint8)


def _plane_frame(index: int, centre, plane_z: float = 8.0) -> StereoFrame:
    tex = _texture(600, 1200)
    c = np.asarray(centre, float)
    left = _render_plane(CAM, c, plane_z, tex, 0.02)
    right = _render_plane(CAM, c + [CAM.baseline_m, 0.0, 0.0], plane_z, tex, 0.02)
    return StereoFrame(index, index * 0.1, left, right)


# ---------------------------------------------------------------- depth (eq. 1)


@pytest.mark.parametrize("method", ["bm_wls", "sgbm"])
def test_dense_depth_of_a_shifted_texture(method):
    d = 16  # px: right(u) = left(u + d), so every pixel has disparity d
    big = _texture(320, 640 + d).astype(np.uint8)
    left, right = big[:, :640].copy(), big[:, d:].copy()
    cfg = FrontendConfig(disparity=method)
    z = dense_depth(left, right, CAM, cfg)
    assert z.dtype == np.float32 and z.shape == left.shape
    inner = z[40:-40, 160:-40]  # BM has no answer in the first num_disparities columns
    valid = inner[inner > 0]
    assert valid.size > 0.8 * inner.size
    expected = CAM.fx * CAM.baseline_m / d  # eq. 1: 15.625 m
    assert np.median(valid) == pytest.approx(expected, rel=0.01)
    assert np.all(z >= 0) and np.all(np.isfinite(z))


def test_dense_depth_range_limits_mark_invalid():
    d = 16
    big = _texture(320, 640 + d).astype(np.uint8)
    cfg = FrontendConfig(disparity="bm_wls", max_depth_m=10.0)  # 15.6 m is beyond the range
    z = dense_depth(big[:, :640].copy(), big[:, d:].copy(), CAM, cfg)
    assert np.count_nonzero(z[40:-40, 160:-40]) < 0.05 * z[40:-40, 160:-40].size


def test_sparse_depth_subpixel_disparity():
    # A plane at 8 m seen by the stereo pair: disparity 31.25 px (not a whole pixel).
    f = _plane_frame(0, [0.0, 0.0, 0.0])
    uv = feat.detect_corners(f.left, 300, feat.KLT)
    z, disp = sparse_depth(f.left, f.right, uv, CAM, FrontendConfig())
    ok = z > 0
    assert ok.mean() > 0.8
    assert np.median(disp[ok]) == pytest.approx(31.25, abs=0.05)
    assert np.percentile(np.abs(z[ok] - 8.0), 90) < 0.1


def test_depth_rejects_bad_input():
    img = np.zeros((100, 200), np.uint8)
    with pytest.raises(SnapsGraphError, match="uint8"):
        dense_depth(img.astype(np.float32), img, CAM, FrontendConfig())
    with pytest.raises(SnapsGraphError, match="differ in size"):
        dense_depth(img, img[:, :150], CAM, FrontendConfig())
    with pytest.raises(SnapsGraphError, match="num_disparities"):
        dense_depth(img, img, CAM, FrontendConfig(num_disparities=100))
    with pytest.raises(SnapsGraphError, match="mode"):
        StereoOdometry(CAM, FrontendConfig(mode=cast(Any, "surf")))


# ---------------------------------------------------------------- motion on a synthetic plane


@pytest.mark.parametrize("mode", ["klt", "sift"])
def test_pure_translation_recovered(mode):
    t_true = np.array([0.15, -0.05, 0.8])  # camera moves right, up, forward (metres)
    f0 = _plane_frame(0, [0.0, 0.0, 0.0])
    f1 = _plane_frame(1, t_true)
    with StereoOdometry(CAM, FrontendConfig(mode=mode)) as vo:
        r0 = vo.process(f0)
        r1 = vo.process(f1)
    assert r0.ok and np.array_equal(r0.pose, np.eye(4))
    assert r1.ok, r1.reason
    assert r1.inliers >= 100
    assert np.linalg.norm(r1.T_rel[:3, 3] - t_true) < 0.02
    assert rotation_angle_deg(r1.T_rel[:3, :3]) < 0.1
    assert np.allclose(r1.pose, r1.T_rel)


# ---------------------------------------------------------------- real KITTI 06


def _kitti(kitti06_dir, frames="0:11"):
    return KittiSequence(kitti06_dir, frames=frames)


@pytest.mark.parametrize(
    "mode,disparity,bound_m",
    # Bounds: measured max position errors over frames 0-10 (12 m) were 0.185 (klt),
    # 0.217 (sift + sparse) and 0.179 m (sift + BM/WLS); about 1.5x that is allowed.
    [("klt", "sparse", 0.3), ("sift", "sparse", 0.33), ("sift", "bm_wls", 0.3)],
)
def test_kitti06_tracks_every_frame(kitti06_dir, mode, disparity, bound_m):
    seq = _kitti(kitti06_dir)
    gt = seq.gt_poses
    with StereoOdometry(seq.camera, FrontendConfig(mode=mode, disparity=disparity)) as vo:
        results = [vo.process(f) for f in seq]
    assert all(r.ok for r in results), [r.reason for r in results if not r.ok]
    poses = np.array([r.pose for r in results])
    err = np.linalg.norm(poses[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert err.max() < bound_m
    assert np.linalg.norm(poses[-1, :3, 3]) == pytest.approx(np.linalg.norm(gt[-1, :3, 3]), rel=0.03)
    for r in results[1:]:
        assert np.allclose(results[0].pose @ np.eye(4), np.eye(4))
        assert r.inliers >= 100 and r.matches >= r.inliers
        f = r.features
        assert isinstance(f, FrameFeatures) and 100 <= len(f.uv) <= 500
        assert len(f.uv) == len(f.pts3d) == len(f.desc)
        assert f.uv.dtype == np.float32 and f.pts3d.dtype == np.float32
        assert f.desc.dtype == (np.float32 if mode == "sift" else np.uint8)
        assert np.all(f.pts3d[:, 2] > 0)
        assert {"depth", "features", "match", "pnp", "total"} <= set(r.timings_ms)
    # T_rel chains to the pose.
    for a, b in zip(results, results[1:]):
        assert np.allclose(a.pose @ b.T_rel, b.pose, atol=1e-9)


def test_same_input_gives_bit_identical_output(kitti06_dir):
    seq = _kitti(kitti06_dir, "0:4")
    frames = list(seq)
    runs = []
    for _ in range(2):
        with StereoOdometry(seq.camera, FrontendConfig()) as vo:
            runs.append([vo.process(f) for f in frames])
    for a, b in zip(*runs):
        assert np.array_equal(a.pose, b.pose)
        assert np.array_equal(a.features.desc, b.features.desc)


def _corrupt(f: StereoFrame, kind: str) -> StereoFrame:
    if kind == "black":
        return StereoFrame(f.index, f.timestamp, np.zeros_like(f.left), np.zeros_like(f.right))
    if kind == "blurred":
        return StereoFrame(f.index, f.timestamp, cv2.GaussianBlur(f.left, (0, 0), 4), cv2.GaussianBlur(f.right, (0, 0), 4))
    if kind == "noise":
        rng = np.random.default_rng(3)
        return StereoFrame(
            f.index,
            f.timestamp,
            rng.integers(0, 256, f.left.shape, dtype=np.uint8),
            rng.integers(0, 256, f.left.shape, dtype=np.uint8),
        )
    assert kind == "swapped"
    return StereoFrame(f.index, f.timestamp, f.right, f.left)


@pytest.mark.parametrize(
    "kind,reason",
    [
        ("black", "flat or black"),
        ("blurred", "blurred"),
        ("noise", "PnP failed|too few PnP inliers"),
        ("swapped", "stereo depth"),
    ],
)
def test_bad_frame_is_flagged_and_follows_constant_velocity(kitti06_dir, kind, reason):
    seq = _kitti(kitti06_dir, "0:9")
    gt = seq.gt_poses
    bad = 5
    with StereoOdometry(seq.camera, FrontendConfig()) as vo:
        results = [vo.process(_corrupt(f, kind) if f.index == bad else f) for f in seq]
    flagged = [r.index for r in results if not r.ok]
    assert flagged == [bad]
    r = results[bad]
    assert re.search(reason, r.reason), r.reason
    assert np.array_equal(r.T_rel, results[bad - 1].T_rel)  # constant velocity
    assert np.allclose(r.pose, results[bad - 1].pose @ r.T_rel)
    assert isinstance(r.features, FrameFeatures)
    poses = np.array([x.pose for x in results])
    assert np.all(np.isfinite(poses))
    # Tracking resumed from the last good frame: the end is as good as a clean run (< 0.3 m).
    assert np.linalg.norm(poses[-1, :3, 3] - gt[-1, :3, 3]) < 0.3


def test_first_frame_is_identity_even_when_black(kitti06_dir):
    seq = _kitti(kitti06_dir, "0:3")
    frames = list(seq)
    with StereoOdometry(seq.camera, FrontendConfig()) as vo:
        r0 = vo.process(_corrupt(frames[0], "black"))
        r1 = vo.process(frames[1])  # becomes the reference: flagged, no motion known
        r2 = vo.process(frames[2])
    assert r0.ok and np.array_equal(r0.pose, np.eye(4))
    assert not r1.ok and np.array_equal(r1.pose, np.eye(4))
    assert r2.ok and 0.8 < np.linalg.norm(r2.T_rel[:3, 3]) < 1.6  # about 1.2 m per frame here


def test_an_old_config_with_retired_keys_loads_with_a_note(tmp_path, capsys):
    """A config.toml the previous version wrote (with settings since made constants) still loads:
    each such key is a note on stderr, not an error, and the rest is read."""
    from snaps_graph.config import Config
    from snaps_graph.config_retired import OLD_KEYS

    old = tmp_path / "config.toml"
    old.write_text(
        "[frontend]\nmin_inliers = 20\n[frontend.klt]\nfeatures = 1200\n[frontend.offset]\npx = 0.25\n"
        "[graph]\nloop_cov_scale = 4.0\n[map]\ntsdf_min_weight = 1.0\n"
    )
    cfg = Config.load(old)
    assert cfg.frontend.offset_px == 0.25  # moved to frontend.offset_px, with a note
    err = capsys.readouterr().err
    for key in ("frontend.min_inliers", "frontend.klt.features", "graph.loop_cov_scale", "map.tsdf_min_weight"):
        assert key in OLD_KEYS and f"note: {old}: {key} = " in err, err
