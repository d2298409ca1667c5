"""The disparity offset (a turned right camera): estimated online in the local BA, applied to every disparity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from snaps_graph.camera import StereoCamera
from snaps_graph.config import FrontendConfig
from snaps_graph.frontend import lba_schedule
from snaps_graph.frontend import offset as offset_mod
from snaps_graph.frontend.depth import offset_gain, true_disparity
from snaps_graph.frontend.local_ba import LocalBundleAdjuster
from snaps_graph.frontend.offset import DisparityOffsetEstimator, OffsetRule

CAM = StereoCamera(fx=718.0, fy=718.0, cx=607.0, cy=185.0, baseline_m=0.54, width=1241, height=376)


def _window_offsets(offset_px: float, seed: int = 3, estimate: bool = True, joint: bool = True):
    """Local BA over 12 keyframes 2 m apart (straight ahead) whose disparities read ``offset_px``
    too large times 1 + ((u_r - cx) / fx)^2 (a turned right camera), with noise (0.2 px in u, v;
    0.3 px in disparity); returns the BA's stats and the refined poses."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-20, 20, 1500), rng.uniform(-3, 2, 1500), rng.uniform(4, 60, 1500)]
    lba = LocalBundleAdjuster(CAM, FrontendConfig(estimate_offset=estimate))
    lba.iterations, lba.huber_px = 8, 1.0
    lba.offset_joint = joint
    poses, gts = [], []
    for k in range(12):
        gt = np.eye(4)
        gt[:3, 3] = [0.0, 0.0, 2.0 * k]
        Pc = X - gt[:3, 3]
        uv = np.c_[CAM.fx * Pc[:, 0] / Pc[:, 2] + CAM.cx, CAM.fy * Pc[:, 1] / Pc[:, 2] + CAM.cy]
        d_true = CAM.fx * CAM.baseline_m / np.maximum(Pc[:, 2], 1e-3)
        d = d_true + offset_px * (1.0 + ((uv[:, 0] - d_true - CAM.cx) / CAM.fx) ** 2)
        vis = (Pc[:, 2] > 2) & (uv[:, 0] > 0) & (uv[:, 0] < CAM.width) & (uv[:, 1] > 0) & (uv[:, 1] < CAM.height) & (d > 0.5)
        n = int(vis.sum())
        seed_pose = gt.copy()
        if k > 0:  # a VO chain with a 2 % scale error, continued from the refined keyframe
            seed_pose[:3, 3] = poses[-1][:3, 3] + [0.0, 0.0, 2.04]
        poses.append(
            lba.add_keyframe(
                k, seed_pose, np.flatnonzero(vis), uv[vis] + rng.normal(0, 0.2, (n, 2)), d[vis] + rng.normal(0, 0.3, n)
            )
        )
        gts.append(gt)
    return lba.stats, np.array(poses), np.array(gts)


@pytest.mark.parametrize("offset", [0.0, -1.0, 0.5])
def test_local_ba_recovers_a_disparity_offset(offset):
    """Every window's data-only estimate is within 0.1 px of the true offset (the info-weighted
    mean within 0.05 px), and the refined keyframes' step length is within 1 % of the truth."""
    stats, poses, gts = _window_offsets(offset)
    o = np.array(stats.offsets)
    assert len(o) == 11 and not stats.failures
    assert np.all(np.abs(o[:, 0] - offset) < 0.1), o[:, 0]
    assert abs((o[:, 0] * o[:, 1]).sum() / o[:, 1].sum() - offset) < 0.05
    assert np.all(np.isfinite(o)) and np.all(o[:, 1] > 0)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert abs(steps[-5:].mean() / 2.0 - 1.0) < 0.01, steps


def test_offset_gain_is_one_at_the_centre_and_grows_toward_the_sides():
    u = np.array([CAM.cx + 10.0, CAM.cx + 10.0 + CAM.fx * 0.5, np.nan])
    d = np.array([10.0, 10.0, 5.0])
    g = offset_gain(u, d, CAM)
    assert g == pytest.approx([1.0, 1.25, 1.0])
    assert true_disparity(d, -1.0, g) == pytest.approx([11.0, 11.25, 6.0])


def test_local_ba_without_estimate_keeps_the_offset_bias():
    """Without the unknown the same data leave the window's scale biased (the test above is not
    passing for a reason unrelated to the offset)."""
    stats, poses, _ = _window_offsets(-1.0, estimate=False)
    assert not stats.offsets
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps[-5:].mean() / 2.0 - 1.0 > 0.02, steps


def test_held_offset_leaves_the_poses_as_without_the_estimate():
    """Held (before the running estimate is applied): the same poses as with the estimate off,
    and each window's one-step estimate still within 0.15 px of the true offset."""
    stats, poses, _ = _window_offsets(-1.0, joint=False)
    _, poses_off, _ = _window_offsets(-1.0, estimate=False)
    assert np.allclose(poses, poses_off, atol=1e-9)
    o = np.array(stats.offsets)
    assert len(o) == 11 and np.all(np.abs(o[:, 0] + 1.0) < 0.15), o[:, 0]


def test_true_disparity_keeps_invalid_disparities_invalid():
    d = np.array([0.0, -1.0, np.nan, 5.0, 0.8], np.float32)
    out = true_disparity(d, -1.0)
    assert out.dtype == np.float32
    assert out[0] == 0.0 and out[1] == -1.0 and np.isnan(out[2]) and out[3] == 6.0
    assert true_disparity(d, 1.0)[4] < 0  # a corrected disparity below zero is invalid
    assert true_disparity(d, 0.0) is d  # no offset: the very same array (bit-identical runs)


def test_a_bad_offset_is_a_one_line_error():
    from snaps_graph.errors import SnapsGraphError

    with pytest.raises(SnapsGraphError, match="frontend.offset_px"):
        FrontendConfig(offset_px=20.0)


def _rendering(rect_px: float, n: int = 36):
    from snaps_graph.synth import SyntheticSequence, builtin_loop_trajectory

    seq = SyntheticSequence(builtin_loop_trajectory(300)[:n], width=620, height=188, seed=0, rectification_error_px=rect_px)
    return seq, [seq[i] for i in range(len(seq))]


def _vo(seq, frames, estimate: bool):
    """The front end with a local BA on every frame, estimating the offset (after 5 solves) or not."""
    from snaps_graph.evaluation.metrics import ate_rmse
    from snaps_graph.frontend import StereoOdometry

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(lba_schedule, "LBA_EVERY", 1)
        mp.setattr(offset_mod, "OFFSET_RULE", OffsetRule(min_solves=5))
        with StereoOdometry(seq.camera, FrontendConfig(estimate_offset=estimate)) as vo:
            res = [vo.process(f) for f in frames]
    P = np.array([r.pose for r in res])
    gt = seq.gt_poses
    assert all(r.ok for r in res) and np.all(np.isfinite(P))
    bias = (
        np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum() / np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
        - 1
    )
    return res[-1].disparity_offset_px, float(bias), ate_rmse(P, gt)


@pytest.mark.slow
def test_vo_estimates_and_removes_a_rendered_disparity_offset():
    """A rendering whose disparities read 0.5 px small (620x188): the front end estimates the
    offset to within 0.1 px, and the step-length bias shrinks to less than half; on the same
    world without an offset the estimate stays within 0.1 px of 0 and the ATE is not worse."""
    seq, frames = _rendering(0.5)
    off0, bias0, ate0 = _vo(seq, frames, estimate=False)
    off1, bias1, ate1 = _vo(seq, frames, estimate=True)
    assert off0 == 0.0 and abs(off1 - (-0.5)) < 0.1, off1
    assert bias0 > 0.02 and abs(bias1) < 0.5 * bias0, (bias0, bias1)
    assert ate1 < ate0
    seq, frames = _rendering(0.0)
    _, bias0, ate0 = _vo(seq, frames, estimate=False)
    off1, bias1, ate1 = _vo(seq, frames, estimate=True)
    assert abs(off1) < 0.1, off1
    assert ate1 <= 1.1 * ate0 + 0.005, (ate0, ate1)


def test_an_unobservable_offset_is_never_applied():
    """Solves that carry almost no information about the offset (a MAV hovering, a car standing:
    no depth change along the tracks) leave the configured offset in place, however far their
    mean lies; informative solves are then applied."""
    est = DisparityOffsetEstimator(0.0)
    assert not est.add([(25.0, 1e-4)] * 30)  # sd 100 px each, mean far beyond the clamp
    assert est.offset == 0.0
    assert est.add([(-0.3, 400.0)] * 10)  # sd 0.05 px each
    assert est.offset == pytest.approx(-0.3, abs=0.01)


def test_an_offset_within_three_standard_errors_of_the_configured_one_waits():
    """An early estimate past OffsetRule.min_px but within OffsetRule.min_z standard
    errors (an offset-free rig's first solves) is not applied; the same offset, once measured
    well enough to be significant, is."""
    est = DisparityOffsetEstimator(0.0)
    assert not est.add([(0.06, 100.0)] * 5)  # mean 0.06 px, sd 0.045 px: 1.3 sd
    assert est.offset == 0.0
    assert est.add([(0.06, 10000.0)] * 3)  # sd 0.006 px: 10 sd
    assert est.offset == pytest.approx(0.06, abs=0.001)
    est = DisparityOffsetEstimator(0.0, OffsetRule(min_z=0.0))
    assert est.add([(0.06, 100.0)] * 5)  # without the test: applied at once
    assert est.offset == pytest.approx(0.06, abs=0.001)


def test_the_offset_estimate_is_an_information_weighted_clamped_mean():
    """Hand-computed: (0.2 * 100 + 0.5 * 300) / 400 = 0.425 px; non-finite or zero-information
    solves are skipped; a mean beyond OffsetRule.max_px is clamped to it; a configured
    offset is where the significance test starts."""
    cfg = OffsetRule(min_solves=2, max_sd_px=1.0, min_z=0.0)
    est = DisparityOffsetEstimator(0.0, cfg)
    assert est.add([(0.2, 100.0), (float("nan"), 5.0), (0.5, 0.0), (0.5, 300.0)])
    assert est.offset == pytest.approx(0.425, abs=1e-12)
    est = DisparityOffsetEstimator(0.0, dataclasses.replace(cfg, max_px=1.0))
    assert est.add([(3.0, 10.0)] * 2) and est.offset == 1.0
    est = DisparityOffsetEstimator(0.4, dataclasses.replace(cfg, min_px=0.1))
    assert not est.add([(0.45, 100.0)] * 2) and est.offset == 0.4  # 0.05 px from the configured one
    assert not est.applied


@pytest.mark.parametrize("memory", [0, 20])
def test_an_applied_offset_follows_newer_solves_with_a_memory(memory):
    """Once applied, the running estimate forgets older solves with OffsetRule.memory_solves
    (they were measured with a worse offset applied): 100 later solves at -0.6 px move it to
    -0.6 within 0.01 px; without a memory the 30 earlier solves at -0.3 px still hold it back."""
    est = DisparityOffsetEstimator(0.0, OffsetRule(memory_solves=memory))
    assert est.add([(-0.3, 400.0)] * 30)
    assert est.offset == pytest.approx(-0.3, abs=1e-6)
    est.add([(-0.6, 400.0)] * 100)
    if memory:
        assert abs(est.offset + 0.6) < 0.01, est.offset
    else:
        assert est.offset > -0.55, est.offset
