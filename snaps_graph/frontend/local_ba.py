"""Sliding-window local bundle adjustment over keyframes, with the rig's disparity offset as one
more unknown (the problem: docs/frontend.md). No I/O; a failed solve leaves the poses as given
and says so in ``LocalBAStats``."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..geometry import adjoint, exp_so3, log_so3, rotation_angle_deg
from .depth import offset_gain
from .offset import OFFSET_RULE
from .stereo_ba import STEREO_BA, _inv3

# The window (docs/decisions.md): six keyframes three frames apart, about 2 s at 10 Hz; the
# longest tracks first, as they constrain the most keyframes.
LBA_WINDOW = 6  # keyframes in the window
LBA_ITERATIONS = 5  # Gauss-Newton iterations per solve
LBA_MAX_LANDMARKS = 300  # landmarks in the window, longest tracks first


@dataclass
class _KF:
    key: int
    pose: np.ndarray  # T_world_cam, current estimate
    ids: np.ndarray  # (N,) int64 landmark ids (>= 0)
    uvd: np.ndarray  # (N,3) float64: u_left, v, disparity
    # The VO chain's step from the previous keyframe: (T_cur_prev, its information 6x6, left
    # perturbation [rotation, translation]); None = no chain factor.
    chain: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class LocalBAStats:
    solves: int = 0
    failures: list = field(default_factory=list)  # (key, reason)
    times_ms: list = field(default_factory=list)  # per keyframe
    landmarks: list = field(default_factory=list)  # landmarks per solve
    offsets: list = field(default_factory=list)  # (data-only offset px, its information 1/px^2) per solve


def _add_chain_factor(
    S: np.ndarray, g: np.ndarray, j: int, Rcw: np.ndarray, tcw: np.ndarray, N: np.ndarray, info: np.ndarray
) -> None:
    """Add a relative-pose factor between keyframes j-1 and j to the normal equations (S dx = g,
    left perturbations [rotation, translation] of T_cam_world): the measured T_cur_prev = N holds
    up to exp(xi), xi ~ N(0, info^-1); xi = log(T_j T_{j-1}^-1 N^-1), d xi = d_j - Ad_N d_{j-1}."""
    RP = Rcw[j] @ Rcw[j - 1].T
    tP = tcw[j] - RP @ tcw[j - 1]
    RN, tN = N[:3, :3], N[:3, 3]
    RE = RP @ RN.T
    tE = tP - RE @ tN
    xi = np.r_[log_so3(RE), tE]
    Ji = -adjoint(N)
    a, b = slice(6 * (j - 1), 6 * j), slice(6 * j, 6 * j + 6)
    S[a, a] += Ji.T @ info @ Ji
    S[a, b] += Ji.T @ info
    S[b, a] += info @ Ji
    S[b, b] += info
    g[a] -= Ji.T @ info @ xi
    g[b] -= info @ xi


class LocalBundleAdjuster:
    """Windowed stereo BA; ``add_keyframe`` returns the refined pose of the keyframe just added."""

    sigma_px = 0.5  # pixel noise of a stereo coordinate (the kernel is in pixels, so only its ratio matters)
    min_landmarks = 30  # fewer shared landmarks: no solve
    max_shift_m, max_turn_deg = 0.25, 1.0  # a solve moving the new keyframe more is discarded

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig):
        """The window, kernel, iterations, landmark cap and offset estimate of ``cfg``
        (``LBA_*``, ``STEREO_BA.huber_px``, the offset and its prior)."""
        self.camera = camera
        self.window = LBA_WINDOW
        self.iterations = LBA_ITERATIONS
        self.max_landmarks = LBA_MAX_LANDMARKS
        self.huber_px = STEREO_BA.huber_px
        self.kfs: deque[_KF] = deque(maxlen=self.window)
        self.offset_px = float(cfg.offset_px)  # disparity offset applied (and the prior's mean)
        self.estimate_offset = cfg.estimate_offset
        self.offset_prior_px = OFFSET_RULE.prior_px
        self.offset_joint = True  # False: hold the offset in the pose solve, only estimate it
        self.stats = LocalBAStats()

    def add_keyframe(
        self,
        key: int,
        pose: np.ndarray,
        ids: np.ndarray,
        uv: np.ndarray,
        disp: np.ndarray,
        chain: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Add keyframe ``key`` and solve the window; returns its refined T_world_cam (or ``pose``).

        ``chain`` = (T_cur_prev, information): the VO chain's measured step from the previous
        keyframe, added as a relative-pose factor between the two."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        disp = np.asarray(disp, np.float64).reshape(-1)
        good = (ids >= 0) & (disp > 0) & np.all(np.isfinite(uv), 1) & np.isfinite(disp)
        kf = _KF(int(key), np.asarray(pose, np.float64).copy(), ids[good], np.c_[uv[good], disp[good]], chain)
        self.kfs.append(kf)
        if len(self.kfs) < 2:
            return kf.pose.copy()
        given = [k.pose.copy() for k in self.kfs]
        t0 = time.perf_counter()
        try:
            out = self._solve()
        except Exception as exc:  # GTSAM refusing a degenerate system: keep the VO poses
            self.stats.failures.append((kf.key, f"{type(exc).__name__}: {exc}"))
            out = None
        if out is not None:
            # A solve that moves the new keyframe far from the VO's estimate is not a refinement
            # (a window bridging a tracking gap, a poorly constrained far-field window): discard.
            d = np.linalg.solve(given[-1], out)
            shift = float(np.linalg.norm(d[:3, 3]))
            turn = rotation_angle_deg(d)
            if shift > self.max_shift_m or turn > self.max_turn_deg:
                self.stats.failures.append((kf.key, f"local BA moved the keyframe {shift:.2f} m, {turn:.2f} deg: discarded"))
                for k, p in zip(self.kfs, given):
                    k.pose = p
                out = None
        self.stats.times_ms.append((time.perf_counter() - t0) * 1e3)
        self.stats.solves += 1
        return kf.pose.copy() if out is None else out

    def reset(self) -> None:
        """Forget the window (after a tracking gap: its chain holds a guessed step)."""
        self.kfs.clear()

    def _solve(self) -> np.ndarray | None:
        kfs = list(self.kfs)
        all_ids = np.concatenate([k.ids for k in kfs])
        uniq, counts = np.unique(all_ids, return_counts=True)
        shared = uniq[counts >= 2]
        if len(shared) > self.max_landmarks:
            order = np.lexsort((shared, -counts[counts >= 2]))  # the longest tracks first (they tie most keyframes), ties by id
            shared = np.sort(shared[order[: self.max_landmarks]])
        if len(shared) < self.min_landmarks:
            self.stats.failures.append((kfs[-1].key, f"too few shared landmarks ({len(shared)})"))
            return None
        poses = self._solve_numpy(kfs, shared)
        if poses is None:
            return None
        for k, p in zip(kfs, poses):
            k.pose = p
        self.stats.landmarks.append(len(shared))
        return poses[-1].copy()

    def _solve_numpy(self, kfs: list[_KF], shared: np.ndarray) -> list[np.ndarray] | None:
        """Vectorised Gauss-Newton: per-landmark 3x3 blocks eliminated by a Schur complement, the
        reduced (6W x 6W) camera system solved densely (oldest pose fixed)."""
        win = _Window.of(kfs, shared, self.camera)
        W = len(kfs)
        off0 = self.offset_px
        est = self.estimate_offset
        off = off0
        Rcw, tcw, X = win.initial_state(kfs, off0)
        info = 1.0 / self.sigma_px**2
        active = np.ones(len(win.oj), bool)
        prior_info = 1.0 / self.offset_prior_px**2
        held: tuple[float, float] | None = None
        S_full = None
        for it in range(self.iterations):
            pc, zc, r, front = win.project(Rcw, tcw, X, off)
            err = np.linalg.norm(r, axis=1)
            if it == self.iterations - 1 or it == 2:
                active &= front & (err <= 4.0 * self.huber_px)
            w = info * np.where(err <= self.huber_px, 1.0, self.huber_px / np.maximum(err, 1e-12)) * (active & front)
            lin = win.linearise(Rcw, pc, zc, r, w)
            S, g = lin.reduced_system(win, kfs, Rcw, tcw)
            if est:  # the offset: one more column, d(u_r residual)/d(offset) = -gain
                oc = lin.offset_column(win, w * (active & front), r, off - off0, prior_info)
                if self.offset_joint:
                    S, g = oc.bordered(S, g)
            try:
                if est and not self.offset_joint:  # poses with the offset held; the offset's own step
                    x = np.linalg.solve(S, np.c_[g, oc.s_dc[1:].reshape(-1)])
                    red = oc.s_dd - prior_info - float(oc.s_dc[1:].reshape(-1) @ x[:, 1])
                    step = (oc.g_d - float(oc.s_dc[1:].reshape(-1) @ x[:, 0])) / red if red > 1e-6 else np.nan
                    held = (off + step, red)
                    sol = np.r_[x[:, 0], 0.0]
                else:
                    sol = np.linalg.solve(S, g)
            except np.linalg.LinAlgError:
                self.stats.failures.append((kfs[-1].key, "singular local BA system"))
                return None
            S_full = S
            dxi, dd = (sol[:-1], float(sol[-1])) if est else (sol, 0.0)
            dx = np.r_[np.zeros(6), dxi].reshape(W, 6)
            rhs = lin.bl - np.einsum("lwij,wi->lj", lin.Hcl, dx)
            if est:
                rhs = rhs - oc.Hdl * dd
            dX = (lin.Hll_inv @ rhs[:, :, None])[:, :, 0]
            off = off + dd
            for j in range(1, W):
                dR = exp_so3(dx[j, :3])
                Rcw[j], tcw[j] = dR @ Rcw[j], dR @ tcw[j] + dx[j, 3:]
            X = X + dX
            if not (np.all(np.isfinite(Rcw)) and np.all(np.isfinite(tcw)) and np.all(np.isfinite(X)) and np.isfinite(off)):
                self.stats.failures.append((kfs[-1].key, "non-finite local BA update"))
                return None
            if np.abs(dx).max() < 1e-7 and abs(dd) < 1e-6:
                break
        self._record_offset(est, held, S_full, off, off0, prior_info)
        return _poses(Rcw, tcw)

    def _record_offset(self, est: bool, held, S_full, off: float, off0: float, prior_info: float) -> None:
        """Append this window's offset estimate (value, information from the data alone) to the stats."""
        if est and not self.offset_joint:
            if held is not None and np.all(np.isfinite(held)):
                self.stats.offsets.append(held)
        elif est and S_full is not None:
            # The offset's posterior information (the cameras marginalised), then the prior taken
            # back out: what this window's data alone say, for the caller's running estimate.
            try:
                e = np.linalg.solve(S_full, np.eye(len(S_full))[-1])
                post = 1.0 / max(float(e[-1]), 1e-12)
            except np.linalg.LinAlgError:
                post = 0.0
            data = post - prior_info
            if data > 1e-6 and np.isfinite(data):
                self.stats.offsets.append((off0 + (off - off0) * post / data, data))


def _poses(Rcw: np.ndarray, tcw: np.ndarray) -> list[np.ndarray]:
    """T_world_cam of each camera-from-world (R re-orthonormalised)."""
    poses = []
    for j in range(len(Rcw)):
        U, _, Vt = np.linalg.svd(Rcw[j])
        R = U @ Vt
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T, -R.T @ tcw[j]
        poses.append(T)
    return poses


@dataclass
class _Window:
    """The window's observations: keyframe index ``oj``, landmark index ``ol`` and (u, v, u_r)
    ``z`` per observation, with the disparity offset's gain at each u_r."""

    cam: StereoCamera
    W: int
    Lm: int
    oj: np.ndarray
    ol: np.ndarray
    z: np.ndarray
    gain: np.ndarray

    @classmethod
    def of(cls, kfs: list[_KF], shared: np.ndarray, cam: StereoCamera) -> _Window:
        oj_l, ol_l, z_l = [], [], []
        for j, k in enumerate(kfs):
            m = np.isin(k.ids, shared)
            oj_l.append(np.full(m.sum(), j))
            ol_l.append(np.searchsorted(shared, k.ids[m]))
            z_l.append(np.c_[k.uvd[m, 0], k.uvd[m, 1], k.uvd[m, 0] - k.uvd[m, 2]])
        oj, ol, z = np.concatenate(oj_l), np.concatenate(ol_l), np.concatenate(z_l)
        gain = offset_gain(z[:, 0], z[:, 0] - z[:, 2], cam) * np.ones(len(z))  # at each u_r
        return cls(cam, len(kfs), len(shared), oj, ol, z, gain)

    def initial_state(self, kfs: list[_KF], off0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-from-world transforms; landmarks (world) from their first observation in the window."""
        cam, z, oj, ol, gain = self.cam, self.z, self.oj, self.ol, self.gain
        fx, fy, cx, cy, B = cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m
        Rcw = np.array([k.pose[:3, :3].T for k in kfs])
        tcw = np.array([-k.pose[:3, :3].T @ k.pose[:3, 3] for k in kfs])
        fo = np.full(self.Lm, -1)
        fo[ol[::-1]] = np.arange(len(ol))[::-1]  # the first observation of each landmark
        zz = fx * B / np.maximum(z[fo, 0] - z[fo, 2] - off0 * gain[fo], 1e-3)
        pc = np.c_[(z[fo, 0] - cx) / fx * zz, (z[fo, 1] - cy) / fy * zz, zz]
        jf = oj[fo]
        X = np.einsum("nji,nj->ni", Rcw[jf], pc - tcw[jf])  # world = R^T (pc - t)
        return Rcw, tcw, X

    def project(self, Rcw, tcw, X, off):
        """Camera points, their clamped depth, residuals (O, 3) and whether they lie in front."""
        cam, oj, ol = self.cam, self.oj, self.ol
        fx, fy, cx, cy, B = cam.fx, cam.fy, cam.cx, cam.cy, cam.baseline_m
        pc = np.einsum("nij,nj->ni", Rcw[oj], X[ol]) + tcw[oj]
        zc = np.where(pc[:, 2] > 1e-3, pc[:, 2], 1e-3)
        pred = np.c_[fx * pc[:, 0] / zc + cx, fy * pc[:, 1] / zc + cy, fx * (pc[:, 0] - B) / zc + cx - off * self.gain]
        return pc, zc, pred - self.z, pc[:, 2] > 1e-3

    def linearise(self, Rcw, pc, zc, r, w) -> _Linear:
        """The weighted normal equations' blocks at the current estimate."""
        cam, oj, ol, W, Lm = self.cam, self.oj, self.ol, self.W, self.Lm
        fx, fy, B = cam.fx, cam.fy, cam.baseline_m
        iz = 1.0 / zc
        P = np.zeros((len(oj), 3, 3))
        P[:, 0, 0] = fx * iz
        P[:, 0, 2] = -fx * pc[:, 0] * iz**2
        P[:, 1, 1] = fy * iz
        P[:, 1, 2] = -fy * pc[:, 1] * iz**2
        P[:, 2, 0] = fx * iz
        P[:, 2, 2] = -fx * (pc[:, 0] - B) * iz**2
        sk = np.zeros((len(oj), 3, 3))
        sk[:, 0, 1], sk[:, 0, 2], sk[:, 1, 2] = pc[:, 2], -pc[:, 1], pc[:, 0]
        sk[:, 1, 0], sk[:, 2, 0], sk[:, 2, 1] = -pc[:, 2], pc[:, 1], -pc[:, 0]  # -[pc]x
        Jc = np.concatenate([P @ sk, P], axis=2)  # (O,3,6)
        Jl = P @ Rcw[oj]  # (O,3,3)
        JcT = Jc.transpose(0, 2, 1)
        wc = w[:, None, None]
        Hcl_o = wc * (JcT @ Jl)
        Hll_o = wc * (Jl.transpose(0, 2, 1) @ Jl)
        bc_o = -(w[:, None] * (JcT @ r[:, :, None])[:, :, 0])
        bl_o = -(w[:, None] * (Jl.transpose(0, 2, 1) @ r[:, :, None])[:, :, 0])
        Hll = np.zeros((Lm, 3, 3))
        np.add.at(Hll, ol, Hll_o)
        Hll[:, [0, 1, 2], [0, 1, 2]] += 1e-6
        bl = np.zeros((Lm, 3))
        np.add.at(bl, ol, bl_o)
        A = Jc * np.sqrt(w)[:, None, None]
        Hcc = np.array([A[oj == j].reshape(-1, 6).T @ A[oj == j].reshape(-1, 6) for j in range(W)])
        bc = np.zeros((W, 6))
        np.add.at(bc, oj, bc_o)
        Hcl = np.zeros((Lm, W, 6, 3))
        Hcl[ol, oj] = Hcl_o  # one observation per (landmark, keyframe)
        return _Linear(Jc, Jl, Hcc, bc, Hcl, _inv3(Hll), bl)


@dataclass
class _Linear:
    """One Gauss-Newton linearisation: Jacobians per observation (cameras Jc, landmarks Jl) and
    the normal equations' blocks (cameras Hcc, bc; landmarks Hll^-1, bl; cross terms Hcl)."""

    Jc: np.ndarray
    Jl: np.ndarray
    Hcc: np.ndarray
    bc: np.ndarray
    Hcl: np.ndarray
    Hll_inv: np.ndarray
    bl: np.ndarray

    def reduced_system(self, win: _Window, kfs: list[_KF], Rcw, tcw) -> tuple[np.ndarray, np.ndarray]:
        """The cameras' system (S, g) after the landmarks' Schur complement, with the chain
        factors, the oldest pose removed as the gauge."""
        W = win.W
        F = self.Hcl @ self.Hll_inv[:, None]  # (L,W,6,3)
        Fm = F.transpose(1, 2, 0, 3).reshape(6 * W, -1)
        Hm = self.Hcl.transpose(1, 2, 0, 3).reshape(6 * W, -1)
        # Block by block: one (6W x 3L) GEMM would be multi-threaded by OpenBLAS, which
        # is far slower than these 6-row products on a busy 2-core machine.
        S = np.empty((6 * W, 6 * W))
        for a in range(W):
            for b in range(a, W):
                blk = -(Fm[6 * a : 6 * a + 6] @ Hm[6 * b : 6 * b + 6].T)
                if a == b:
                    blk += self.Hcc[a]
                S[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] = blk
                S[6 * b : 6 * b + 6, 6 * a : 6 * a + 6] = blk.T
        g = self.bc.reshape(-1) - np.einsum("wil,l->wi", Fm.reshape(W, 6, -1), self.bl.reshape(-1)).reshape(-1)
        for j in range(1, W):  # the chain's steps between consecutive keyframes
            chain = kfs[j].chain
            if chain is not None:
                _add_chain_factor(S, g, j, Rcw, tcw, chain[0], chain[1])
        S = S[6:, 6:] + 1e-6 * np.eye(6 * (W - 1))  # the oldest pose is the gauge
        return S, g[6:]

    def offset_column(self, win: _Window, wr, r, off_shift: float, prior_info: float) -> _OffsetColumn:
        """The disparity offset's column of the reduced system (landmarks eliminated), with its
        prior about the applied offset (``off_shift`` = estimate - prior mean)."""
        ol, oj, gain = win.ol, win.oj, win.gain
        Hdl = np.zeros((win.Lm, 3))
        np.add.at(Hdl, ol, -(wr * gain)[:, None] * self.Jl[:, 2, :])
        Hdc = np.zeros((win.W, 6))
        np.add.at(Hdc, oj, -(wr * gain)[:, None] * self.Jc[:, 2, :])
        FdHll = (self.Hll_inv @ Hdl[:, :, None])[:, :, 0]  # (L,3) Hll^-1 Hld
        s_dc = Hdc - np.einsum("lwij,lj->wi", self.Hcl, FdHll)
        s_dd = (wr * gain**2).sum() - np.einsum("li,li->", Hdl, FdHll) + prior_info
        g_d = (wr * gain * r[:, 2]).sum() - prior_info * off_shift - np.einsum("li,li->", FdHll, self.bl)
        return _OffsetColumn(Hdl, s_dc, s_dd, g_d)


@dataclass
class _OffsetColumn:
    Hdl: np.ndarray  # (L,3) offset-landmark blocks
    s_dc: np.ndarray  # (W,6) offset-camera column after the landmarks' elimination
    s_dd: float
    g_d: float

    def bordered(self, S: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S, g) with the offset as one more unknown."""
        n = len(S)
        S2 = np.empty((n + 1, n + 1))
        S2[:n, :n], S2[:n, n], S2[n, :n], S2[n, n] = S, self.s_dc[1:].reshape(-1), self.s_dc[1:].reshape(-1), self.s_dd
        return S2, np.r_[g, self.g_d]
