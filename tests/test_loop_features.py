"""Loop-verification features independent of the tracker, and the loop factor's covariance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from snaps_graph.backend import noise
from snaps_graph.backend.pose_graph import PoseGraph, loop_covariance
from snaps_graph.config import Config, FrontendConfig, GraphConfig, LoopConfig, VerificationConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.frontend.keyframe import MIN_STEREO_POINTS
from snaps_graph.frontend.motion import MIN_INLIERS
from snaps_graph.geometry import inv, rotation_angle_deg
from snaps_graph.loop.policy import DRIFT, PAPER, LoopPolicy
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.types import FrameFeatures
from snaps_graph.verification.features import REFERENCE_EVERY, LoopFeatureBank, pose_covariance, verify_features


@pytest.fixture(scope="module")
def kitti_pair(kitti06_dir):
    seq = KittiSequence(kitti06_dir, frames="0:4")
    return seq, seq[0], seq[3]


@pytest.mark.parametrize("detector", ["orb", "sift"])
def test_verify_features_recovers_relative_pose(kitti_pair, detector):
    seq, f0, f3 = kitti_pair
    cfg, vcfg = FrontendConfig(), VerificationConfig(detector=detector)
    bank = LoopFeatureBank(seq.camera, cfg, vcfg)
    bank.add(0, f0)
    ref = bank.reference(0)
    assert ref is not None and len(ref.uv) >= MIN_STEREO_POINTS
    m = verify_features(ref, bank.query(3, f3), f3, seq.camera, cfg, vcfg)
    assert m is not None and m.inliers >= MIN_INLIERS
    G = inv(seq.gt_poses[0]) @ seq.gt_poses[3]  # 3.6 m forward
    # Real KITTI 06 (exposure, blur): ORB 0.17 m off, SIFT 0.06 m; the tracker's own verifier 0.15 m.
    assert np.linalg.norm(m.T_ref_cur[:3, 3] - G[:3, 3]) < 0.25
    assert rotation_angle_deg(m.T_ref_cur[:3, :3].T @ G[:3, :3]) < 0.6
    sig = np.sqrt(np.diag(m.cov))
    assert np.all(sig > 0) and sig[:3].max() < 0.01 and sig[3:].max() < 0.2


def test_depth_check_rejects_a_lookalike_at_another_distance(kitti_pair):
    """The reference's points twice as far project the same in its own image; PnP then finds a
    pose (the scene scaled by 2), but the current frame's stereo disagrees: no loop."""
    seq, f0, f3 = kitti_pair
    cfg, vcfg = FrontendConfig(), VerificationConfig()
    bank = LoopFeatureBank(seq.camera, cfg, vcfg)
    bank.add(0, f0)
    ref = bank.reference(0)
    assert ref is not None
    cur = bank.query(3, f3)
    assert verify_features(ref, cur, f3, seq.camera, cfg, vcfg) is not None
    far = FrameFeatures(ref.uv, ref.pts3d * 2.0, ref.desc)
    assert verify_features(far, cur, f3, seq.camera, cfg, vcfg) is None
    # Without the check the scaled scene passes.
    assert verify_features(far, cur, f3, seq.camera, cfg, vcfg, depth_check_px=0.0) is not None


def test_verify_features_rejects_an_unrelated_frame(kitti_pair):
    seq, f0, f3 = kitti_pair
    cfg, vcfg = FrontendConfig(), VerificationConfig()
    bank = LoopFeatureBank(seq.camera, cfg, vcfg)
    bank.add(0, f0)
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 256, (seq.camera.height, seq.camera.width), dtype=np.uint8)
    fake = type(f3)(index=9, timestamp=0.9, left=noise, right=noise)
    assert verify_features(bank.reference(0), bank.query(9, fake), fake, seq.camera, cfg, vcfg) is None


def test_bank_keeps_every_nth_frame_and_finds_the_nearest(kitti_pair):
    seq, f0, _ = kitti_pair
    bank = LoopFeatureBank(seq.camera, FrontendConfig(), VerificationConfig())
    assert bank.wants(0) and bank.wants(10) and not bank.wants(3)
    ref = FrameFeatures(np.zeros((1, 2), np.float32), np.zeros((1, 3), np.float32), np.zeros((1, 32), np.uint8))
    for k in (0, 5, 10):
        bank.put(k, ref)
    assert bank.nearest(6) == 5 and bank.nearest(8) == 10 and bank.nearest(12) == 10 and bank.nearest(40) is None
    assert bank.nbytes() == 3 * (8 + 12 + 32)


def test_pose_covariance_shrinks_with_more_points():
    from snaps_graph.camera import StereoCamera

    cam = StereoCamera(700.0, 700.0, 600.0, 180.0, 0.54, 1200, 360)
    rng = np.random.default_rng(0)

    def cov(n: int) -> np.ndarray:
        pts = np.stack([rng.uniform(-10, 10, n), rng.uniform(-2, 2, n), rng.uniform(5, 40, n)], 1)
        uv = np.stack([700 * pts[:, 0] / pts[:, 2] + 600, 700 * pts[:, 1] / pts[:, 2] + 180], 1)
        uv = uv + rng.normal(0, 1.0, uv.shape)
        return pose_covariance(np.eye(4), pts, uv, cam, 0.1)[0]

    c50, c800 = cov(50), cov(800)
    assert np.all(np.linalg.eigvalsh(c50) > 0)
    assert np.trace(c800) < 0.25 * np.trace(c50)  # ~1/n


def test_loop_factor_uses_the_verification_covariance():
    cfg = GraphConfig()
    C = np.diag([1e-6] * 3 + [1e-4] * 3)
    eff = loop_covariance(cfg, C)
    assert eff is not None
    floor = np.array([noise.LOOP_SIGMA_FLOOR_ROT_RAD] * 3 + [noise.LOOP_SIGMA_FLOOR_TRANS_M] * 3)
    assert np.allclose(np.diag(eff), noise.LOOP_COV_SCALE * np.diag(C) + floor**2)
    assert loop_covariance(cfg, np.full((6, 6), np.nan)) is None
    assert loop_covariance(cfg, -np.eye(6)) is None
    g = PoseGraph(cfg, mode="batch")
    T = np.eye(4)
    for k in range(3):
        T[0, 3] = k
        g.add_frame(k, T.copy())
    meas = np.eye(4)
    meas[0, 3] = 2.0
    info = g.add_loop(0, 2, 0.2, meas, covariance=C)
    assert info.sigmas is not None
    assert np.allclose(info.sigmas, np.sqrt(np.diag(eff)))
    info_q = g.add_loop(0, 2, 0.2, meas)  # no covariance: Q-scaled sigmas as before
    assert info_q.sigmas is not None
    assert info_q.sigmas[3] == pytest.approx(cfg.loop_sigma_trans_m / 0.2)


def test_pipeline_keeps_reference_features(tiny_seq):
    seq = KittiSequence(tiny_seq)
    pipe = SlamPipeline(seq.camera, Config(), loops="snaps", refine="none", build_map=False)
    for f in seq:
        pipe.process(f)
    pipe.finish()
    assert pipe.verifier is not None and pipe.verifier.bank is not None
    assert set(pipe.verifier.bank._ref) <= {0, REFERENCE_EVERY}


def test_discount_window_follows_the_loop_span():
    from snaps_graph.loop.correction import window_length

    assert window_length(PAPER, 100, 1000) == 100 and window_length(PAPER, 100, 120) == 100
    span = dataclasses.replace(DRIFT, span_factor=0.5, span_max=300)
    assert window_length(span, 100, 120) == 60 and window_length(span, 100, 1000) == 300


def test_span_window_moves_fewer_frames_on_a_short_loop():
    """Same loop, window by span: a loop 150 frames long corrects 75 frames with factor 0.5."""
    from snaps_graph.loop.snaps import SnapsLoopCloser

    def moved(cfg: LoopConfig, policy: LoopPolicy) -> int:
        c = SnapsLoopCloser(cfg, policy=policy)
        T = np.eye(4)
        T[2, 3] = 1.0
        img = np.full((120, 240), 100, np.uint8)
        for k in range(151):
            c.step(k, T, img)
        before = c.positions
        c._correct(150, 0, 1.0, np.array([1.0, 0.0, 0.0]), 1, None)
        return int(np.count_nonzero(np.any(c.positions != before, axis=1)))

    assert moved(LoopConfig(discount_length=300), dataclasses.replace(DRIFT, discount_window="fixed")) == 150
    assert moved(LoopConfig(), dataclasses.replace(DRIFT, span_factor=0.5)) == 76  # s in [N-75, N]


def test_discount_shapes_fall_to_zero_at_the_window_start():
    from snaps_graph.loop.correction import discount

    cfg = DRIFT
    s = np.arange(0, 201, dtype=float)
    g = discount(cfg, 3, s, window=200)
    assert g[0] == pytest.approx(1 - np.exp(-3)) and np.all(np.diff(g) < 0)
    assert g[-1] < 0.03 and np.max(np.abs(np.diff(g))) < 0.03  # no step anywhere
    paper = discount(PAPER, 1, s[:101])
    assert paper[-1] > 0.8  # the paper's curve at K = 100: a step from 0.86 to 0 at N - K
    assert np.array_equal(discount(cfg, 1, s[:101]), paper)  # no window given: the paper's curve


def test_reference_points_use_the_disparity_offset(kitti_pair):
    """A rig whose disparities read 0.5 px large (offset +0.5): corrected points lie farther."""
    from snaps_graph.verification.features import detect_loop_keypoints, stereo_points

    seq, f0, _ = kitti_pair
    cfg = FrontendConfig()
    uv, _, _ = detect_loop_keypoints(f0.left, VerificationConfig())
    i0, p0 = stereo_points(f0.left, f0.right, uv, seq.camera, cfg)
    i1, p1 = stereo_points(f0.left, f0.right, uv, seq.camera, cfg, offset_px=0.5)
    common, a, b = np.intersect1d(i0, i1, return_indices=True)
    assert len(common) > 100
    assert np.all(p1[b, 2] > p0[a, 2])


def test_subpixel_loop_keypoints_sit_on_the_corners():
    """A patchwork of grey squares with corners at known sub-pixel positions: ORB's pyramid
    keypoints lie a few pixels off them (level grids), the refined ones within a pixel."""
    import cv2

    from snaps_graph.verification.features import detect_loop_keypoints

    H, W, s, off = 360, 480, 24.0, np.array([0.37, 0.61])
    yy, xx = np.mgrid[0 : H * 8, 0 : W * 8] / 8.0  # 8x supersampled
    lv = np.random.default_rng(0).integers(30, 225, (H // 10, W // 10))
    big = lv[np.floor((yy - off[1]) / s).astype(int) % lv.shape[0], np.floor((xx - off[0]) / s).astype(int) % lv.shape[1]]
    img = cv2.GaussianBlur(cv2.resize(big.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA), (0, 0), 0.8)
    img = img.astype(np.uint8)

    def median_px_from_corner(sp: float) -> float:
        uv, _, _ = detect_loop_keypoints(img, VerificationConfig(), 500, subpixel_px=sp)
        c = uv + 0.5 - off  # pixel k covers [k, k + 1) of the supersampled plane
        return float(np.median(np.hypot(c[:, 0] - s * np.round(c[:, 0] / s), c[:, 1] - s * np.round(c[:, 1] / s))))

    before, after = median_px_from_corner(0.0), median_px_from_corner(2.0)
    assert after < 1.0 and after < 0.4 * before  # measured 0.69 against 3.22 px
