"""Speed work on the front end that must not change what it computes."""

from __future__ import annotations

import numpy as np
import pytest

from snaps_graph.camera import StereoCamera
from snaps_graph.frontend.features import KltParams
from snaps_graph.frontend.stereo_ba import StereoBAParams, stereo_two_view_ba
from snaps_graph.geometry import exp_so3

CAM = StereoCamera(fx=718.0, fy=718.0, cx=607.0, cy=185.0, baseline_m=0.54, width=1241, height=376)


def _predict(T, p):
    """Stereo predictions (reference u, v, u_r; current u, v, u_r) of inverse-depth points p = (a, b, rho)."""
    fx, fy, cx, cy, B = CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.baseline_m
    a, b, rho = p.T
    h = np.c_[a, b, np.ones(len(p))] @ T[:3, :3].T + rho[:, None] * T[:3, 3]
    ref = np.c_[fx * a + cx, fy * b + cy, fx * (a - B * rho) + cx]
    cur = np.c_[fx * h[:, 0] / h[:, 2] + cx, fy * h[:, 1] / h[:, 2] + cy, fx * (h[:, 0] - B * rho) / h[:, 2] + cx]
    return np.concatenate([ref.ravel(), cur.ravel()])


def test_stereo_ba_covariance_is_the_inverse_schur_complement_of_numeric_jacobians():
    """On noise-free data the stereo BA's pose covariance equals sigma² times the inverse of the
    Schur complement of JᵀJ, with J the finite-difference Jacobian of all six stereo
    coordinates over (pose, every point): a check of the hand-written Jacobians and elimination."""
    rng = np.random.default_rng(3)
    n = 25
    z = rng.uniform(4.0, 40.0, n)
    uv = np.c_[rng.uniform(50, 1190, n), rng.uniform(30, 350, n)]
    p = np.c_[(uv[:, 0] - CAM.cx) / CAM.fx, (uv[:, 1] - CAM.cy) / CAM.fy, 1.0 / z]
    a = np.radians(1.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.05, -0.02, -0.9]
    meas = _predict(T, p)
    ref_uv, cur = meas[: 3 * n].reshape(n, 3), meas[3 * n :].reshape(n, 3)
    seed = T.copy()
    seed[:3, 3] += [0.02, 0.01, -0.03]
    r = stereo_two_view_ba(
        seed,
        ref_uv[:, :2],
        ref_uv[:, 0] - ref_uv[:, 2],
        cur[:, :2],
        cur[:, 0] - cur[:, 2],
        CAM,
        StereoBAParams(huber_px=1.0, outlier_px=2.0, iterations=6),
    )
    assert r.ok and r.inliers.all()
    np.testing.assert_allclose(r.T_cur_ref, T, atol=1e-9)

    def f(x):
        Tx = T.copy()
        dR = exp_so3(x[:3])
        Tx[:3, :3], Tx[:3, 3] = dR @ T[:3, :3], dR @ T[:3, 3] + x[3:6]
        return _predict(Tx, p + x[6:].reshape(n, 3))

    m = 6 + 3 * n
    J = np.empty((6 * n, m))
    for j in range(m):
        e = np.zeros(m)
        e[j] = 1e-7
        J[:, j] = (f(e) - f(-e)) / 2e-7
    H = J.T @ J / 0.5**2  # sigma_px = 0.5
    S = H[:6, :6] - H[:6, 6:] @ np.linalg.solve(H[6:, 6:], H[6:, :6])
    np.testing.assert_allclose(r.cov, np.linalg.inv(S), rtol=1e-4, atol=1e-14)


@pytest.mark.parametrize("b", [0, 1, 16, 40])
@pytest.mark.parametrize("r", [1, 4, 10])
def test_exclusion_mask_equals_the_eroded_mask(b, r):
    """``detect_corners``' mask built directly equals cv2.erode of the border-and-points mask
    by the elliptical kernel, for points inside, on and beyond the image border."""
    import cv2

    from snaps_graph.frontend.features import _exclusion_mask

    rng = np.random.default_rng(b * 100 + r)
    for h, w in ((188, 620), (41, 57)):
        avoid = np.c_[rng.uniform(-6, w + 6, 200), rng.uniform(-6, h + 6, 200)].astype(np.float32)
        mask = np.zeros((h, w), np.uint8)
        mask[b : h - b, b : w - b] = 255
        u = np.clip(np.rint(avoid[:, 0]).astype(np.int64), 0, w - 1)
        v = np.clip(np.rint(avoid[:, 1]).astype(np.int64), 0, h - 1)
        mask[v, u] = 0
        expected = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        assert np.array_equal(_exclusion_mask(h, w, b, r, avoid), expected)


def test_sharpness_is_the_mean_absolute_laplacian():
    """``sharpness`` (an L1 norm in OpenCV) gives exactly numpy's mean |Laplacian|."""
    import cv2

    from snaps_graph.frontend.keyframe import sharpness

    rng = np.random.default_rng(5)
    for img in (rng.integers(0, 256, (188, 620), dtype=np.uint8), np.full((40, 50), 7, np.uint8)):
        img = cv2.GaussianBlur(img, (5, 5), 1.0) if img.std() > 0 else img
        assert sharpness(img) == float(np.mean(np.abs(cv2.Laplacian(img, cv2.CV_16S, ksize=1))))


@pytest.mark.parametrize("border, radius, quality", [(16, 10, 0.01), (16, 10, 0.001), (4, 3, 0.01), (0, 10, 0.01)])
def test_detect_corners_on_the_cropped_image_finds_the_same_corners(border, radius, quality):
    """``detect_corners`` runs goodFeaturesToTrack on the mask's open frame plus a margin: the
    corners (positions and order) are those of the whole image with the same mask."""
    import cv2

    from snaps_graph.frontend.features import _exclusion_mask, detect_corners

    rng = np.random.default_rng(border + radius)
    img = cv2.GaussianBlur(rng.integers(0, 256, (188, 620), dtype=np.uint8), (0, 0), 2.0)
    cfg = KltParams(border_px=border, min_distance_px=radius, quality=quality)
    for avoid in (None, np.c_[rng.uniform(0, 620, 300), rng.uniform(0, 188, 300)].astype(np.float32)):
        if avoid is None:
            mask = np.zeros(img.shape, np.uint8)
            mask[border : 188 - border, border : 620 - border] = 255
        else:
            mask = _exclusion_mask(188, 620, border, radius, avoid)
        expected = cv2.goodFeaturesToTrack(img, 800, quality, radius, mask=mask).reshape(-1, 2)
        got = detect_corners(img, 800, cfg, avoid)
        assert len(got) > 50 and np.array_equal(got, expected)
