"""Motion from stereo measurements: a two-view stereo bundle adjustment (issue 11, item 1).

PnP treats each reference point's stereo depth as exact. Depth from z = f·B/d is uncertain and,
for far points, biased long (E[1/d] > 1/E[d] for noisy d), which pulls the translation. Here the
current pose T_cur_ref and every landmark are unknowns, and the data are the stereo measurements
(u_left, v, u_right) of each landmark in *both* frames of the pair, in pixels:

    reference:  u = fx·a + cx,   v = fy·b + cy,   u_r = fx·(a - B·ρ) + cx
    current:    h = R·(a, b, 1) + t·ρ;   u = fx·h_x/h_z + cx,   v = fy·h_y/h_z + cy,
                u_r = fx·(h_x - B·ρ)/h_z + cx

with each landmark in inverse depth anchored in the reference camera (a, b = normalised image
coordinates, ρ = 1/z). The parametrisation stays well conditioned as ρ → 0, so a point whose
disparity is a pixel or less constrains rotation and (barely) translation without a depth that
explodes; the residuals live in pixels, where stereo noise is symmetric, so no depth bias enters.
The reference pose is fixed (it defines the frame). Gauss-Newton with a Huber kernel on each
(point, view) block; the per-point 3x3 blocks are eliminated with a Schur complement, so an
iteration costs O(N) in vectorised numpy (a few ms for 1000 points). After the first round,
points whose error exceeds ``outlier_px`` in either view are dropped and the pose re-solved.

The pose covariance (6x6, left perturbation of T_cur_ref, rotation first) is S⁻¹, with S the
Schur complement of the information-weighted (1/σ², Huber-weighted) normal equations at the
solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCamera


@dataclass
class StereoBAResult:
    T_cur_ref: np.ndarray  # 4x4, maps reference-camera points into the current camera
    inliers: np.ndarray  # bool (N,) over the input points
    cov: np.ndarray  # 6x6 pose covariance, left perturbation [rotation, translation] of T_cur_ref
    ok: bool  # False: the seed is returned unchanged (too few points, degenerate, non-finite)
    reason: str = ""
    iterations: int = 0
    rmse_px: float = 0.0  # inliers' RMS residual per coordinate, pixels
    rho: np.ndarray | None = None  # (N,) refined inverse depths in the reference camera (1/m)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack(
        [np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1), np.stack([-v[:, 1], v[:, 0], z], 1)], 1
    )


def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * (K @ K)


def _inv3(M: np.ndarray) -> np.ndarray:
    """Inverses of a stack of 3x3 matrices (N,3,3) by the adjugate (faster than LAPACK for 3x3)."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    g, h, i = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    A, Bc, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * Bc + c * C
    out = np.stack(
        [A, -(b * i - c * h), b * f - c * e, Bc, a * i - c * g, -(a * f - c * d), C, -(a * h - b * g), a * e - b * d], 1
    )
    return out.reshape(-1, 3, 3) / det[:, None, None]


def _huber(err: np.ndarray, k: float) -> np.ndarray:
    return np.where(err <= k, 1.0, k / np.maximum(err, 1e-12))


def stereo_two_view_ba(
    T_init: np.ndarray,
    ref_uv: np.ndarray,
    ref_disp: np.ndarray,
    cur_uv: np.ndarray,
    cur_disp: np.ndarray | None,
    camera: StereoCamera,
    *,
    sigma_px: float = 0.5,
    huber_px: float = 1.0,
    outlier_px: float = 2.0,
    iterations: int = 6,
    min_points: int = 8,
) -> StereoBAResult:
    """Refine T_cur_ref (seed ``T_init``, e.g. PnP) from stereo measurements in both frames.

    ``ref_disp`` (N,) reference disparities in pixels (> 0 where known; a point without one is
    not used); ``cur_disp`` (N,) current disparities (<= 0 or NaN: that point's current right
    image coordinate is missing, its left one still counts). Never raises for degenerate data:
    ``ok=False`` with the seed, a reason and an infinite covariance.
    """
    T_init = np.asarray(T_init, np.float64)
    n = len(ref_uv)
    bad_cov = np.full((6, 6), np.inf)
    fail = lambda why, inl=None: StereoBAResult(  # noqa: E731
        T_init.copy(), np.zeros(n, bool) if inl is None else inl, bad_cov, False, why
    )
    if T_init.shape != (4, 4) or not np.all(np.isfinite(T_init)):
        return fail("non-finite seed pose")
    ref_uv = np.asarray(ref_uv, np.float64).reshape(-1, 2)
    cur_uv = np.asarray(cur_uv, np.float64).reshape(-1, 2)
    ref_disp = np.asarray(ref_disp, np.float64).reshape(-1)
    cd = np.full(n, np.nan) if cur_disp is None else np.asarray(cur_disp, np.float64).reshape(-1)
    use = np.isfinite(ref_disp) & (ref_disp > 0) & np.all(np.isfinite(ref_uv), 1) & np.all(np.isfinite(cur_uv), 1)
    if use.sum() < min_points:
        return fail(f"too few points for stereo BA ({int(use.sum())} < {min_points})")

    fx, fy, cx, cy, B = camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline_m
    idx = np.flatnonzero(use)
    zr = np.c_[ref_uv[idx], ref_uv[idx, 0] - ref_disp[idx]]  # reference (u, v, u_r)
    zc = np.c_[cur_uv[idx], cur_uv[idx, 0] - np.where(np.isfinite(cd[idx]) & (cd[idx] > 0), cd[idx], 0.0)]
    has_r = np.isfinite(cd[idx]) & (cd[idx] > 0)
    p = np.c_[(zr[:, 0] - cx) / fx, (zr[:, 1] - cy) / fy, ref_disp[idx] / (fx * B)]  # (a, b, rho)
    R, t = T_init[:3, :3].copy(), T_init[:3, 3].copy()
    # Reference rows are linear in (a, b, rho): one constant Jacobian.
    Jr = np.array([[fx, 0.0, 0.0], [0.0, fy, 0.0], [fx, 0.0, -fx * B]])
    JrTJr = Jr.T @ Jr
    active = np.ones(len(idx), bool)
    info = 1.0 / sigma_px**2
    S = None
    it_total = 0

    def residuals(R, t, p):
        pred_r = np.c_[fx * p[:, 0] + cx, fy * p[:, 1] + cy, fx * (p[:, 0] - B * p[:, 2]) + cx]
        m = np.c_[p[:, 0], p[:, 1], np.ones(len(p))]
        h = m @ R.T + p[:, 2:3] * t
        hz = h[:, 2]
        front = hz > 1e-6
        hzs = np.where(front, hz, 1.0)
        pred_c = np.c_[fx * h[:, 0] / hzs + cx, fy * h[:, 1] / hzs + cy, fx * (h[:, 0] - B * p[:, 2]) / hzs + cx]
        rr = pred_r - zr
        rc = pred_c - zc
        rc[~has_r, 2] = 0.0
        return rr, rc, h, hzs, front

    for rnd in range(2):
        for _ in range(iterations):
            it_total += 1
            rr, rc, h, hz, front = residuals(R, t, p)
            act = active & front
            if act.sum() < min_points:
                return fail(f"too few stereo BA inliers ({int(act.sum())} < {min_points})")
            er, ec = np.linalg.norm(rr, axis=1), np.linalg.norm(rc, axis=1)
            wr = info * _huber(er, huber_px) * act
            wc = info * _huber(ec, huber_px) * act
            # Current-view Jacobians.
            iz = 1.0 / hz
            P = np.zeros((len(p), 3, 3))
            P[:, 0, 0] = fx * iz
            P[:, 0, 2] = -fx * h[:, 0] * iz**2
            P[:, 1, 1] = fy * iz
            P[:, 1, 2] = -fy * h[:, 1] * iz**2
            P[:, 2, 0] = fx * iz
            P[:, 2, 2] = -fx * (h[:, 0] - B * p[:, 2]) * iz**2
            P[~has_r, 2, :] = 0.0
            dh_pose = np.concatenate([-_skew(h), p[:, 2, None, None] * np.eye(3)[None]], axis=2)  # (N,3,6)
            Jc = P @ dh_pose  # (N,3,6)
            dh_pt = np.stack([R[:, 0], R[:, 1], t], axis=1)  # (3,3): columns d h / d(a, b, rho)
            Jp = P @ dh_pt  # (N,3,3)
            Jp[:, 2, 2] += np.where(has_r, -fx * B * iz, 0.0)
            # Normal equations: per-point 3x3 blocks, pose 6x6, eliminated by a Schur complement.
            JpT = Jp.transpose(0, 2, 1)
            Hpp = wr[:, None, None] * JrTJr[None] + wc[:, None, None] * (JpT @ Jp)
            Hpp[:, [0, 1, 2], [0, 1, 2]] += 1e-9
            Hcp = wc[:, None, None] * (Jc.transpose(0, 2, 1) @ Jp)  # (N,6,3)
            sw = np.sqrt(wc)
            A = (Jc * sw[:, None, None]).reshape(-1, 6)
            Hcc = A.T @ A
            bc = -(A.T @ (rc * sw[:, None]).reshape(-1))
            bp = -(wr[:, None] * (rr @ Jr)) - wc[:, None] * (JpT @ rc[:, :, None])[:, :, 0]
            Hpp_inv = _inv3(Hpp)
            HcpHi = Hcp @ Hpp_inv  # (N,6,3)
            F = HcpHi.transpose(1, 0, 2).reshape(6, -1)
            S = Hcc - F @ Hcp.transpose(1, 0, 2).reshape(6, -1).T
            g = bc - F @ bp.reshape(-1)
            try:
                dx = np.linalg.solve(S, g)
            except np.linalg.LinAlgError:
                return fail("degenerate stereo BA (singular system)")
            rhs = bp - (Hcp * dx[None, :, None]).sum(1)
            dp = (Hpp_inv @ rhs[:, :, None])[:, :, 0]
            dR = _exp_so3(dx[:3])
            R, t = dR @ R, dR @ t + dx[3:]
            p = p + np.where(act[:, None], dp, 0.0)
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
                return fail("non-finite stereo BA update")
            if np.linalg.norm(dx) < 1e-7:
                break
        if rnd == 0:
            rr, rc, _, _, front = residuals(R, t, p)
            active = front & (np.linalg.norm(rr, axis=1) <= outlier_px) & (np.linalg.norm(rc, axis=1) <= outlier_px)
    rr, rc, _, _, front = residuals(R, t, p)
    active &= front
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    # Re-orthonormalise (GN steps compose small exponentials; keep R exactly a rotation).
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    inl = np.zeros(n, bool)
    inl[idx[active]] = True
    ncoord = 2 * active.sum() + has_r[active].sum() + 3 * active.sum()
    rmse = float(np.sqrt((np.sum(rr[active] ** 2) + np.sum(rc[active] ** 2)) / max(ncoord, 1)))
    if S is None or not np.all(np.isfinite(S)):
        return fail("degenerate stereo BA (no system)")
    ev = np.linalg.eigvalsh(S)
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return fail("degenerate stereo BA (pose not constrained)")
    cov = np.linalg.inv(S)
    if not np.all(np.isfinite(T)):
        return fail("non-finite stereo BA pose")
    rho = np.full(n, np.nan)
    rho[idx] = p[:, 2]
    return StereoBAResult(T, inl, cov, True, "", it_total, rmse, rho)
