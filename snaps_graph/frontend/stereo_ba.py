"""The two-view stereo bundle adjustment: the pose and every landmark (inverse depth) refined on
the pixel measurements of both frames, where stereo noise is symmetric, so no depth bias enters
as in PnP (the model and its Schur complement: docs/frontend.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import StereoCamera
from ..geometry import exp_so3


@dataclass(frozen=True)
class StereoBAParams:
    """The two-view stereo BA's kernel, outlier cut and iterations (docs/frontend.md)."""

    # A tight kernel and gate, px: the tails of the KLT tracks' errors carry the per-step pitch bias.
    huber_px: float = 0.3  # Huber width on a residual (the local BA's too)
    outlier_px: float = 0.6  # after the first round, points beyond this in either view are dropped
    keep_px: float = 2.0  # a small image keeps tracks within this of the BA's pose too (motion.SBA_KEEP_BELOW)
    iterations: int = 3  # Gauss-Newton iterations per round (two rounds): converged from PnP's seed


STEREO_BA = StereoBAParams()


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
    kept: np.ndarray | None = None  # bool (N,): within keep_px at the final pose (the inliers without keep_px)


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


@dataclass
class _Views:
    """The measurements of the used points, component-major: every per-point quantity is a
    (k, N) array, so each product of the small per-point matrices is a few whole-row numpy
    operations, not N tiny matrix products."""

    fx: float
    fy: float
    cx: float
    cy: float
    B: float
    zr: np.ndarray  # (3, N) reference (u, v, u_r)
    zc: np.ndarray  # (3, N) current (u, v, u_r); u_r unused where hr is 0
    hr: np.ndarray  # (N,) 1.0 where the current view has a disparity
    Jr: np.ndarray  # 3x3: the reference rows are linear in (a, b, rho), one constant Jacobian
    info: float  # 1 / sigma_px^2

    def residuals(self, R, t, p):
        """Reference and current residuals (3, N) at pose (R, t) and points p = (a, b, rho);
        the current camera's points h, their 1/z and whether they lie in front."""
        fx, fy, cx, cy, B = self.fx, self.fy, self.cx, self.cy, self.B
        a, b, rho = p
        rr = np.stack([fx * a + cx, fy * b + cy, fx * (a - B * rho) + cx]) - self.zr
        h = R[:, :2] @ p[:2] + R[:, 2:3] + t[:, None] * rho
        front = h[2] > 1e-6
        iz = 1.0 / np.where(front, h[2], 1.0)
        rc = np.stack([fx * h[0] * iz + cx, fy * h[1] * iz + cy, fx * (h[0] - B * rho) * iz + cx]) - self.zc
        rc[2] *= self.hr
        return rr, rc, h, iz, front


def _norm3(r):
    return np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])


def _current_jacobians(v: _Views, R, t, p, h, iz):
    """Current-view Jacobians Jc (3, 6, N) for the pose (left perturbation: dh = -[h]x dw +
    rho dt) and Jp (3, 3, N) for (a, b, rho); the u_r row is zero without a current disparity."""
    fx, fy, B, hr = v.fx, v.fy, v.B, v.hr
    rho = p[2]
    # d(pred_cur)/dh (3x3 per point, rows u, v, u_r).
    iz2 = iz * iz
    P00, P02 = fx * iz, -fx * h[0] * iz2
    P11, P12 = fy * iz, -fy * h[1] * iz2
    P20, P22 = P00 * hr, -fx * (h[0] - B * rho) * iz2 * hr
    zero = np.zeros(len(rho))
    hx, hy, hz = h
    Jc = np.stack(
        [
            [P02 * hy, P00 * hz - P02 * hx, -P00 * hy, rho * P00, zero, rho * P02],
            [P12 * hy - P11 * hz, -P12 * hx, P11 * hx, zero, rho * P11, rho * P12],
            [P22 * hy, P20 * hz - P22 * hx, -P20 * hy, rho * P20, zero, rho * P22],
        ]
    )
    M = np.c_[R[:, :2], t]  # d h / d(a, b, rho), rows x, y, z
    Jp = np.stack(
        [
            np.outer(M[0], P00) + np.outer(M[2], P02),
            np.outer(M[1], P11) + np.outer(M[2], P12),
            np.outer(M[0], P20) + np.outer(M[2], P22),
        ]
    )
    Jp[2, 2] -= fx * B * iz * hr
    return Jc, Jp


def _gauss_newton_step(v: _Views, R, t, p, rr, rc, h, iz, act, huber_px):
    """One Gauss-Newton step: the normal equations' per-point 3x3 blocks and the pose's 6x6,
    the points eliminated by a Schur complement. Returns (dx pose, dp points, S the reduced
    pose system); raises LinAlgError on a singular system."""
    wr = v.info * _huber(_norm3(rr), huber_px) * act
    wc = v.info * _huber(_norm3(rc), huber_px) * act
    sw = np.sqrt(wc)
    Jc, Jp = _current_jacobians(v, R, t, p, h, iz)  # whitened by sqrt(wc) below
    Jc *= sw
    Jp *= sw
    rcw = rc * sw
    Hpp = (Jp[:, :, None, :] * Jp[:, None, :, :]).sum(0) + wr * (v.Jr.T @ v.Jr)[:, :, None]
    Hpp[[0, 1, 2], [0, 1, 2]] += 1e-9
    Hcp = (Jc[:, :, None, :] * Jp[:, None, :, :]).sum(0)  # (6, 3, N)
    A = Jc.transpose(0, 2, 1).reshape(-1, 6)
    Hcc = A.T @ A
    bc = -(Jc * rcw[:, None, :]).sum((0, 2))
    bp = -(wr * (v.Jr.T @ rr)) - (Jp * rcw[:, None, :]).sum(0)  # (3, N)
    Hpp_inv = _inv3(Hpp.transpose(2, 0, 1)).transpose(1, 2, 0)  # (3, 3, N)
    HcpHi = (Hcp[:, :, None, :] * Hpp_inv[None]).sum(1)  # (6, 3, N)
    F = HcpHi.reshape(6, -1)
    S = Hcc - F @ Hcp.reshape(6, -1).T
    g = bc - F @ bp.reshape(-1)
    dx = np.linalg.solve(S, g)
    rhs = bp - (dx @ Hcp.reshape(6, -1)).reshape(3, -1)
    dp = (Hpp_inv * rhs[None, :, :]).sum(1)
    return dx, dp, S


def _fail(T_init: np.ndarray, n: int, why: str) -> StereoBAResult:
    return StereoBAResult(T_init.copy(), np.zeros(n, bool), np.full((6, 6), np.inf), False, why)


def stereo_two_view_ba(
    T_init: np.ndarray,
    ref_uv: np.ndarray,
    ref_disp: np.ndarray,
    cur_uv: np.ndarray,
    cur_disp: np.ndarray | None,
    camera: StereoCamera,
    cfg: StereoBAParams = STEREO_BA,
    *,
    sigma_px: float = 0.5,
    min_points: int = 8,
) -> StereoBAResult:
    """Refine T_cur_ref (seed ``T_init``, e.g. PnP) from stereo measurements in both frames.

    ``ref_disp`` (N,) reference disparities in pixels (> 0 where known; a point without one is
    not used); ``cur_disp`` (N,) current disparities (<= 0 or NaN: that point's current right
    image coordinate is missing, its left one still counts). The kernel is ``cfg.huber_px``,
    the outlier cut ``cfg.outlier_px``, ``cfg.iterations`` Gauss-Newton steps per round;
    ``kept`` holds every point within ``cfg.keep_px`` in both views at the final pose (a
    tight outlier cut for the estimate need not cut the tracks a caller keeps). Never raises for
    degenerate data: ``ok=False`` with the seed, a reason and an infinite covariance.
    """
    huber_px, outlier_px, iterations, keep_px = cfg.huber_px, cfg.outlier_px, cfg.iterations, cfg.keep_px
    T_init = np.asarray(T_init, np.float64)
    n = len(ref_uv)
    if T_init.shape != (4, 4) or not np.all(np.isfinite(T_init)):
        return _fail(T_init, n, "non-finite seed pose")
    ref_uv = np.asarray(ref_uv, np.float64).reshape(-1, 2)
    cur_uv = np.asarray(cur_uv, np.float64).reshape(-1, 2)
    ref_disp = np.asarray(ref_disp, np.float64).reshape(-1)
    cd = np.full(n, np.nan) if cur_disp is None else np.asarray(cur_disp, np.float64).reshape(-1)
    use = np.isfinite(ref_disp) & (ref_disp > 0) & np.all(np.isfinite(ref_uv), 1) & np.all(np.isfinite(cur_uv), 1)
    if use.sum() < min_points:
        return _fail(T_init, n, f"too few points for stereo BA ({int(use.sum())} < {min_points})")
    idx = np.flatnonzero(use)
    v, p, has_r = _views(idx, ref_uv, ref_disp, cur_uv, cd, camera, sigma_px)
    R, t = T_init[:3, :3].copy(), T_init[:3, 3].copy()
    active = np.ones(len(idx), bool)
    S = None
    it_total = 0
    for rnd in range(2):
        for _ in range(iterations):
            it_total += 1
            rr, rc, h, iz, front = v.residuals(R, t, p)
            act = active & front
            if act.sum() < min_points:
                return _fail(T_init, n, f"too few stereo BA inliers ({int(act.sum())} < {min_points})")
            try:
                dx, dp, S = _gauss_newton_step(v, R, t, p, rr, rc, h, iz, act, huber_px)
            except np.linalg.LinAlgError:
                return _fail(T_init, n, "degenerate stereo BA (singular system)")
            dR = exp_so3(dx[:3])
            R, t = dR @ R, dR @ t + dx[3:]
            p = p + np.where(act, dp, 0.0)
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
                return _fail(T_init, n, "non-finite stereo BA update")
            if np.linalg.norm(dx) < 1e-7:
                break
        if rnd == 0:
            rr, rc, _, _, front = v.residuals(R, t, p)
            active = front & (_norm3(rr) <= outlier_px) & (_norm3(rc) <= outlier_px)
    return _result(T_init, n, idx, v, R, t, p, active, has_r, S, it_total, keep_px)


def _views(idx, ref_uv, ref_disp, cur_uv, cd, camera: StereoCamera, sigma_px: float):
    """The used points' measurements, their initial (a, b, rho) from the reference view, and
    which have a current disparity."""
    fx, fy, cx, cy, B = camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline_m
    has_r = np.isfinite(cd[idx]) & (cd[idx] > 0)
    zr = np.stack([ref_uv[idx, 0], ref_uv[idx, 1], ref_uv[idx, 0] - ref_disp[idx]])
    zc = np.stack([cur_uv[idx, 0], cur_uv[idx, 1], cur_uv[idx, 0] - np.where(has_r, cd[idx], 0.0)])
    p = np.stack([(zr[0] - cx) / fx, (zr[1] - cy) / fy, ref_disp[idx] / (fx * B)])  # (a, b, rho)
    Jr = np.array([[fx, 0.0, 0.0], [0.0, fy, 0.0], [fx, 0.0, -fx * B]])
    v = _Views(fx, fy, cx, cy, B, zr, zc, has_r.astype(np.float64), Jr, 1.0 / sigma_px**2)
    return v, p, has_r


def _result(T_init, n, idx, v: _Views, R, t, p, active, has_r, S, it_total: int, keep_px: float) -> StereoBAResult:
    """The refined pose (re-orthonormalised), inliers, kept points, RMS residual and the pose
    covariance from the last reduced system, or a failure if that system leaves the pose free."""
    rr, rc, _, _, front = v.residuals(R, t, p)
    active &= front
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    # Re-orthonormalise (GN steps compose small exponentials; keep R exactly a rotation).
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    inl = np.zeros(n, bool)
    inl[idx[active]] = True
    kept = np.zeros(n, bool)
    kept[idx[front & (_norm3(rr) <= keep_px) & (_norm3(rc) <= keep_px)]] = True
    ncoord = 2 * active.sum() + has_r[active].sum() + 3 * active.sum()
    rmse = float(np.sqrt((np.sum(rr[:, active] ** 2) + np.sum(rc[:, active] ** 2)) / max(ncoord, 1)))
    if S is None or not np.all(np.isfinite(S)):
        return _fail(T_init, n, "degenerate stereo BA (no system)")
    ev = np.linalg.eigvalsh(S)
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return _fail(T_init, n, "degenerate stereo BA (pose not constrained)")
    cov = np.linalg.inv(S)
    if not np.all(np.isfinite(T)):
        return _fail(T_init, n, "non-finite stereo BA pose")
    rho = np.full(n, np.nan)
    rho[idx] = p[2]
    return StereoBAResult(T, inl, cov, True, "", it_total, rmse, rho, kept)
