"""The hand-written bundle adjustments against gtsam on the same small problems: the same stereo
measurements as gtsam's GenericStereoFactor3D, no robust kernel, the reference (oldest) pose held;
both must reach the same minimum (pose, landmarks, cost)."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from snaps_graph.camera import StereoCamera
from snaps_graph.config import FrontendConfig
from snaps_graph.frontend import local_ba
from snaps_graph.frontend.local_ba import LocalBundleAdjuster
from snaps_graph.frontend.stereo_ba import StereoBAParams, stereo_two_view_ba
from snaps_graph.geometry import rotation_angles

CAM = StereoCamera(fx=718.0, fy=718.0, cx=607.0, cy=185.0, baseline_m=0.54, width=1241, height=376)
SIGMA_PX = 0.5  # both solvers' pixel noise (isotropic, u, v and u_r)
PLAIN = 100.0  # a Huber width and outlier cut no residual reaches: plain least squares


def _pose(yaw_deg: float, t) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def _stereo(P: np.ndarray) -> np.ndarray:
    """(u, v, u_r) of camera-frame points (N, 3)."""
    u = CAM.fx * P[:, 0] / P[:, 2] + CAM.cx
    return np.c_[u, CAM.fy * P[:, 1] / P[:, 2] + CAM.cy, u - CAM.fx * CAM.baseline_m / P[:, 2]]


def _points(rng, n: int) -> np.ndarray:
    z = rng.uniform(6.0, 40.0, n)
    u, v = rng.uniform(100, CAM.width - 100, n), rng.uniform(40, CAM.height - 40, n)
    return np.c_[(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z]


def _gtsam_solve(T_world_cam: list[np.ndarray], world_points: np.ndarray, meas: list[np.ndarray]):
    """gtsam's optimum: stereo factors (u_l, u_r, v) of every point in every camera, camera 0 held."""
    K = gtsam.Cal3_S2Stereo(CAM.fx, CAM.fy, 0.0, CAM.cx, CAM.cy, CAM.baseline_m)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, SIGMA_PX)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, (T, z) in enumerate(zip(T_world_cam, meas)):
        values.insert(X(i), gtsam.Pose3(T))
        for j, (u, v, ur) in enumerate(z):
            graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, ur, v), noise, X(i), L(j), K))
    graph.add(gtsam.NonlinearEqualityPose3(X(0), gtsam.Pose3(T_world_cam[0])))
    for j, p in enumerate(world_points):
        values.insert(L(j), np.asarray(p, float))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(100)
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    poses = [out.atPose3(X(i)).matrix() for i in range(len(T_world_cam))]
    points = np.array([out.atPoint3(L(j)) for j in range(len(world_points))])
    return poses, points, graph.error(out)


def _angle(R: np.ndarray) -> float:
    """Rotation angle, radians (accurate near 0, unlike arccos of the trace)."""
    return float(rotation_angles(R[None])[0])


def test_stereo_two_view_ba_reaches_gtsams_minimum():
    rng = np.random.default_rng(3)
    P = _points(rng, 40)  # reference camera frame
    T = _pose(1.0, (0.05, -0.02, -1.2))  # T_cur_ref
    z_ref = _stereo(P) + rng.normal(0, SIGMA_PX, (40, 3))
    z_cur = _stereo(P @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, SIGMA_PX, (40, 3))
    T_init = T @ _pose(0.3, (0.02, 0.01, 0.03))  # a seed a little off, as from PnP
    cfg = StereoBAParams(huber_px=PLAIN, outlier_px=PLAIN, keep_px=PLAIN, iterations=20)
    d_ref, d_cur = z_ref[:, 0] - z_ref[:, 2], z_cur[:, 0] - z_cur[:, 2]
    res = stereo_two_view_ba(T_init, z_ref[:, :2], d_ref, z_cur[:, :2], d_cur, CAM, cfg, sigma_px=SIGMA_PX)
    assert res.ok and res.inliers.all() and res.rho is not None

    # gtsam: the reference camera is the world; the current camera sits at T_cur_ref^-1.
    seed = (z_ref[:, :2] - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy]
    depth = CAM.fx * CAM.baseline_m / d_ref
    poses, points, error = _gtsam_solve([np.eye(4), np.linalg.inv(T_init)], np.c_[seed * depth[:, None], depth], [z_ref, z_cur])
    T_gtsam = np.linalg.inv(poses[1])
    # measured: 2e-10 m, 1e-11 rad, inverse depths within 1.5e-9 (relative)
    assert np.abs(res.T_cur_ref[:3, 3] - T_gtsam[:3, 3]).max() < 1e-8
    assert _angle(res.T_cur_ref[:3, :3].T @ T_gtsam[:3, :3]) < 1e-9
    assert np.allclose(res.rho, 1.0 / points[:, 2], rtol=1e-7, atol=0)
    # The same cost: the BA's RMS residual over its 6 coordinates a point against gtsam's
    # 0.5 * sum((r / sigma)^2).
    n_coord = 6 * len(P)
    assert np.isclose(res.rmse_px**2 * n_coord, 2.0 * SIGMA_PX**2 * error, rtol=1e-9)
    # ...and a true minimum: the residuals are the noise's size, not the seed's.
    assert 0.3 < res.rmse_px < 0.7


def test_local_ba_window_reaches_gtsams_minimum(monkeypatch):
    rng = np.random.default_rng(5)
    n_kf, n_pts = 4, 60
    truth = [_pose(0.4 * k, (0.03 * k, 0.0, 1.5 * k)) for k in range(n_kf)]  # T_world_cam, driving forward
    world = _points(rng, n_pts) + [0.0, 0.0, 5.0]
    meas = []
    for T in truth:
        Pc = (world - T[:3, 3]) @ T[:3, :3]  # camera frame: R^T (X - t)
        meas.append(_stereo(Pc) + rng.normal(0, SIGMA_PX, (n_pts, 3)))
    given = [truth[0]] + [T @ _pose(0.2, (0.02, -0.01, 0.03)) for T in truth[1:]]  # VO a little off
    # The window, iterations and kernel are the local BA's constants: this solve's, set before it is built.
    monkeypatch.setattr(local_ba, "LBA_WINDOW", n_kf)
    monkeypatch.setattr(local_ba, "LBA_ITERATIONS", 30)
    monkeypatch.setattr(local_ba, "STEREO_BA", StereoBAParams(huber_px=PLAIN))
    lba = LocalBundleAdjuster(CAM, FrontendConfig(estimate_offset=False))
    ids = np.arange(n_pts)
    for k, (T, z) in enumerate(zip(given, meas)):
        lba.add_keyframe(k, T, ids, z[:, :2], z[:, 0] - z[:, 2])
    assert not lba.stats.failures, lba.stats.failures
    ours = [kf.pose for kf in lba.kfs]

    assert min(np.abs(a[:3, 3] - b[:3, 3]).max() for a, b in zip(ours[1:], given[1:])) > 1e-3  # it did move them
    # gtsam from the VO poses, the landmarks from the first camera's stereo.
    z0 = meas[0]
    depth = CAM.fx * CAM.baseline_m / (z0[:, 0] - z0[:, 2])
    pc = np.c_[(z0[:, 0] - CAM.cx) / CAM.fx * depth, (z0[:, 1] - CAM.cy) / CAM.fy * depth, depth]
    poses, _, _ = _gtsam_solve(given, pc @ given[0][:3, :3].T + given[0][:3, 3], meas)
    for T_ours, T_gtsam in zip(ours, poses):
        # measured: at most 4e-9 m and 2e-10 rad
        assert np.abs(T_ours[:3, 3] - T_gtsam[:3, 3]).max() < 1e-7
        assert _angle(T_ours[:3, :3].T @ T_gtsam[:3, :3]) < 1e-8
