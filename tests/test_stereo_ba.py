"""Motion from stereo measurements (two-view stereo BA) and the keyframe-window local BA."""

from __future__ import annotations

import numpy as np
import pytest

from snaps_graph.camera import StereoCamera
from snaps_graph.config import Config, FrontendConfig
from snaps_graph.frontend import lba_schedule
from snaps_graph.frontend.motion import pnp_ransac
from snaps_graph.frontend.stereo_ba import StereoBAParams, stereo_two_view_ba

# A wide kernel (1.0 / 2.0 px, 6 steps): the BA's own behaviour, apart from the front end's tight default.
WIDE = StereoBAParams(huber_px=1.0, outlier_px=2.0, iterations=6)

CAM = StereoCamera(fx=718.0, fy=718.0, cx=607.0, cy=185.0, baseline_m=0.54, width=1241, height=376)


def _motion(yaw_deg=0.5, t=(0.02, 0.01, -1.0)) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T  # T_cur_ref: the camera moves 1 m forward


def _observe(X, T, rng, sigma, outliers=0.0):
    """Stereo measurements (uv, disparity) of reference points X in the reference and current frames."""

    def proj(P):
        return np.c_[CAM.fx * P[:, 0] / P[:, 2] + CAM.cx, CAM.fy * P[:, 1] / P[:, 2] + CAM.cy], CAM.fx * CAM.baseline_m / P[:, 2]

    n = len(X)
    uv_r, d_r = proj(X)
    uv_c, d_c = proj(X @ T[:3, :3].T + T[:3, 3])
    uv_r = uv_r + rng.normal(0, sigma, uv_r.shape)
    uv_c = uv_c + rng.normal(0, sigma, uv_c.shape)
    d_r = d_r + rng.normal(0, sigma * np.sqrt(2), n)
    d_c = d_c + rng.normal(0, sigma * np.sqrt(2), n)
    bad = rng.random(n) < outliers
    uv_c[bad] += rng.normal(0, 15.0, (bad.sum(), 2))
    return uv_r, d_r, uv_c, d_c


def _points(rng, n, zmin, zmax):
    z = rng.uniform(zmin, zmax, n)
    u, v = rng.uniform(0, CAM.width, n), rng.uniform(0, CAM.height, n)
    return np.c_[(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z]


def test_stereo_ba_beats_pnp_on_far_points_scale():
    """Far points (15-120 m, disparity 3-26 px) with 0.5 px noise and 10 % outliers: PnP on the
    triangulated points (noisy depth taken as exact) gets the step length wrong on average
    (measured over 30 trials: -0.85 %, sd 2.2 %); the stereo BA far less (-0.26 %, sd 1.2 %)."""
    rng = np.random.default_rng(0)
    T = _motion()
    true_step = np.linalg.norm(T[:3, 3])
    err_pnp, err_ba = [], []
    cfg = FrontendConfig(max_depth_m=200.0)
    for _ in range(8):
        X = _points(rng, 500, 15.0, 120.0)
        uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.5, outliers=0.1)
        keep = d_r > 1.0
        P = CAM.backproject(uv_r[keep, 0], uv_r[keep, 1], CAM.fx * CAM.baseline_m / d_r[keep])
        pnp = pnp_ransac(P, uv_c[keep], CAM, cfg)
        assert pnp is not None
        Tp, inl = pnp
        r = stereo_two_view_ba(Tp, uv_r[keep][inl], d_r[keep][inl], uv_c[keep][inl], d_c[keep][inl], CAM, WIDE)
        assert r.ok and np.all(np.isfinite(r.T_cur_ref)) and np.all(np.isfinite(r.cov))
        err_pnp.append(np.linalg.norm(Tp[:3, 3]) - true_step)
        err_ba.append(np.linalg.norm(r.T_cur_ref[:3, 3]) - true_step)
    assert abs(np.mean(err_ba)) < 0.5 * abs(np.mean(err_pnp))
    assert np.sqrt(np.mean(np.square(err_ba))) < np.sqrt(np.mean(np.square(err_pnp)))


def test_stereo_ba_rejects_outliers_and_recovers_exact_motion():
    rng = np.random.default_rng(1)
    T = _motion(1.0, (0.1, -0.02, -0.8))
    X = _points(rng, 300, 3.0, 40.0)
    uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.0, outliers=0.2)
    seed = T.copy()
    seed[:3, 3] += [0.05, 0.02, -0.05]  # a poor seed
    r = stereo_two_view_ba(seed, uv_r, d_r, uv_c, d_c, CAM, WIDE)
    assert r.ok
    assert np.allclose(r.T_cur_ref, T, atol=1e-5)
    bad = np.linalg.norm(uv_c - _observe(X, T, np.random.default_rng(9), 0.0)[2], axis=1) > 3
    assert not np.any(r.inliers & bad)  # every gross outlier dropped
    assert r.inliers.sum() >= 0.9 * (~bad).sum()


def test_keep_px_keeps_tracks_a_tight_estimate_left_out():
    """0.5 px noise against the default 0.3 / 0.6 px kernel: the estimate leaves out many good
    points; the points ``kept`` with ``keep_px`` = 2 are 94 % of them, and still no gross
    outlier. ``keep_px`` does not change the estimate."""
    rng = np.random.default_rng(3)
    T = _motion()
    X = _points(rng, 300, 3.0, 40.0)
    uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.5, outliers=0.1)
    clean = _observe(X, T, np.random.default_rng(9), 0.0)[2]
    bad = np.linalg.norm(uv_c - clean, axis=1) > 3
    cfg = StereoBAParams()
    assert (cfg.huber_px, cfg.outlier_px, cfg.keep_px) == (0.3, 0.6, 2.0)
    tight = stereo_two_view_ba(T, uv_r, d_r, uv_c, d_c, CAM, StereoBAParams(keep_px=0.6))
    kept = stereo_two_view_ba(T, uv_r, d_r, uv_c, d_c, CAM, cfg)
    assert tight.ok and kept.ok
    assert kept.kept is not None
    assert np.array_equal(tight.T_cur_ref, kept.T_cur_ref) and np.array_equal(tight.inliers, kept.inliers)
    assert tight.inliers.sum() < 0.8 * (~bad).sum()
    assert kept.kept.sum() >= 0.9 * (~bad).sum() and not np.any(kept.kept & bad)  # measured 94 %


def test_stereo_ba_degenerate_inputs_fall_back():
    rng = np.random.default_rng(2)
    T = _motion()
    X = _points(rng, 5, 5.0, 20.0)
    uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.1)
    r = stereo_two_view_ba(T, uv_r, d_r, uv_c, d_c, CAM, WIDE)  # too few points
    assert not r.ok and r.reason and np.array_equal(r.T_cur_ref, T)
    r = stereo_two_view_ba(T, np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), None, CAM, WIDE)
    assert not r.ok and np.array_equal(r.T_cur_ref, T)
    nan_seed = T.copy()
    nan_seed[0, 3] = np.nan
    X = _points(rng, 100, 5.0, 20.0)
    uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.1)
    r = stereo_two_view_ba(nan_seed, uv_r, d_r, uv_c, d_c, CAM, WIDE)
    assert not r.ok and "seed" in r.reason
    # All points at infinity (disparity ~ 0): rotation is observable, the result stays finite.
    X = _points(rng, 200, 5000.0, 9000.0)
    uv_r, d_r, uv_c, d_c = _observe(X, T, rng, 0.05)
    r = stereo_two_view_ba(T, uv_r, np.abs(d_r) + 1e-3, uv_c, d_c, CAM, WIDE)
    assert np.all(np.isfinite(r.T_cur_ref))
    if r.ok:
        R_err = r.T_cur_ref[:3, :3] @ T[:3, :3].T
        assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 0.05


def test_local_ba_keeps_poses_finite_and_reduces_error():
    from snaps_graph.frontend.local_ba import LocalBundleAdjuster

    rng = np.random.default_rng(3)
    X = _points(rng, 400, 4.0, 40.0) + [0, 0, 0]  # world points seen from keyframes moving along z
    n_kf = 6
    gt = [np.eye(4) for _ in range(n_kf)]
    for k in range(n_kf):
        gt[k][:3, 3] = [0.0, 0.0, 1.0 * k]
    lba = LocalBundleAdjuster(CAM, FrontendConfig())
    lba.window, lba.iterations, lba.huber_px = n_kf, 10, 1.0
    errs_in, errs_out = [], []
    for k in range(n_kf):
        Tcw = np.linalg.inv(gt[k])
        Pc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
        vis = Pc[:, 2] > 2.0
        uv = np.c_[CAM.fx * Pc[:, 0] / Pc[:, 2] + CAM.cx, CAM.fy * Pc[:, 1] / Pc[:, 2] + CAM.cy]
        vis &= (uv[:, 0] > 0) & (uv[:, 0] < CAM.width) & (uv[:, 1] > 0) & (uv[:, 1] < CAM.height)
        d = CAM.fx * CAM.baseline_m / Pc[:, 2]
        uv_n = uv + rng.normal(0, 0.3, uv.shape)
        d_n = d + rng.normal(0, 0.4, d.shape)
        noisy = gt[k].copy()
        if k > 0:
            noisy[:3, 3] += rng.normal(0, 0.05, 3)  # VO pose error
        out = lba.add_keyframe(k, noisy, np.flatnonzero(vis), uv_n[vis], d_n[vis])
        assert np.all(np.isfinite(out))
        if k > 0:
            errs_in.append(np.linalg.norm(noisy[:3, 3] - gt[k][:3, 3]))
            errs_out.append(np.linalg.norm(out[:3, 3] - gt[k][:3, 3]))
    assert np.mean(errs_out) < 0.5 * np.mean(errs_in)
    assert len(lba.stats.times_ms) == n_kf - 1 and not lba.stats.failures


@pytest.mark.parametrize(
    "key,value",
    [("motion", '"bundle"'), ("local_ba", '"yes"'), ("offset_px", "11.0")],
)
def test_bad_new_frontend_settings_are_one_line_errors(key, value):
    from snaps_graph.errors import SnapsGraphError

    FrontendConfig(motion="pnp")
    with pytest.raises(SnapsGraphError, match=f"frontend.{key}"):
        Config().with_overrides([f"frontend.{key}={value}"])


@pytest.fixture(scope="module")
def small_rendering():
    """16 frames of the built-in loop at 620x188, rendered once, and the PnP chain's ATE on them."""
    from snaps_graph.synth import SyntheticSequence, builtin_loop_trajectory

    seq = SyntheticSequence(builtin_loop_trajectory(300)[:16], width=620, height=188, seed=0)
    frames = [seq[i] for i in range(len(seq))]
    return seq, frames, _run_vo(seq, frames, FrontendConfig(motion="pnp"))


def _run_vo(seq, frames, cfg):
    from snaps_graph.evaluation.metrics import ate_rmse
    from snaps_graph.frontend import StereoOdometry

    with StereoOdometry(seq.camera, cfg) as vo:
        res = [vo.process(f) for f in frames]
    poses = np.array([r.pose for r in res])
    assert all(r.ok for r in res) and np.all(np.isfinite(poses))
    return ate_rmse(poses, seq.gt_poses)


def test_vo_variants_track_a_small_rendering(small_rendering, monkeypatch):
    """The front end with a local BA every 2 frames tracks every frame of a small rendering with
    finite poses and stays within a few centimetres of the ground truth (the plain PnP chain as
    the yardstick)."""
    seq, frames, ate_pnp = small_rendering
    monkeypatch.setattr(lba_schedule, "LBA_EVERY", 2)
    ate = _run_vo(seq, frames, FrontendConfig(local_ba=True))
    assert ate < max(0.05, 1.5 * ate_pnp), (ate, ate_pnp)


def test_vo_result_carries_the_stereo_ba_covariance(small_rendering, monkeypatch):
    """Every measured step of the default front end carries a finite, positive definite 6x6
    covariance of T_rel (the stereo BA's, widened on local-BA keyframes by the correction);
    the first frame and a PnP-only front end carry none."""
    from snaps_graph.frontend import StereoOdometry

    seq, frames, _ = small_rendering
    monkeypatch.setattr(lba_schedule, "LBA_EVERY", 2)
    for cfg, expect in (
        (FrontendConfig(), True),
        (FrontendConfig(motion="pnp", local_ba=False), False),
    ):
        with StereoOdometry(seq.camera, cfg) as vo:
            res = [vo.process(f) for f in frames]
        assert res[0].cov is None
        for r in res[1:]:
            if not expect:
                assert r.cov is None
                continue
            assert r.cov is not None and r.cov.shape == (6, 6) and np.all(np.isfinite(r.cov))
            assert np.linalg.eigvalsh(r.cov).min() > 0
            assert np.sqrt(r.cov[0, 0]) < 0.01 and np.sqrt(r.cov[5, 5]) < 0.1  # rad, m: a measurement, not a guess
