"""Eq. 6's correction of the heuristic trajectory on a loop (paper §III-C, our reading).

With δ = the target − p_N and α the loops closed so far, every frame s of the window [N − K, N],
s' = N − s, moves by p_s += w·γ_s·δ, γ_s = max(0, 1 − exp(−(c − α·r·s'))) or a linear ramp in
the distance driven, shaped by the drift model; by default δ keeps its ground-plane part, and a verified loop also bends
the window toward the verified heading. Our reading and the choices: docs/loop-closure.md,
"Eq. 6", and docs/decisions.md, "Loop closure (SNAPS)".
"""

from __future__ import annotations

import math

import numpy as np

from ..drift_model import DriftModel
from ..geometry import exp_so3_scaled, yaw_deg
from .policy import LoopPolicy
from .trajectory import Trajectory


def yaw_correction(dR: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector of the part of dR = R_target R_N^T about the world vertical y."""
    # Closest rotation about y: R_y(t) = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    return np.array([0.0, math.atan2(dR[0, 2] - dR[2, 0], dR[0, 0] + dR[2, 2]), 0.0])


def discount(policy: LoopPolicy, alpha: int, s_prime: np.ndarray, window: int | None = None) -> np.ndarray:
    """γ of eq. 6 for offsets s' = N − s: max(0, 1 − exp(−(c − α·r·s'))); with ``window`` = K and
    ``discount_shape`` "drift", (1 − e^−c)·(1 − s'/(K + 1)) until :func:`drift_share` reshapes it
    by the distance driven."""
    if window is None or policy.discount_shape == "paper":
        return np.maximum(0.0, 1.0 - np.exp(-(policy.discount_offset - alpha * policy.discount_rate * s_prime)))
    return (1.0 - math.exp(-policy.discount_offset)) * np.clip(1.0 - s_prime / (window + 1.0), 0.0, 1.0)


def drift_share(model: DriftModel, driven: np.ndarray, heading_known: bool) -> np.ndarray:
    """Each window frame's expected share of the position error found at its end, under the drift
    model: Cov(e(u), e(U)) / Var(e(U)) for frames ``driven`` u metres past the window's fixed anchor
    (U = the last). A heading walk's lateral error grows as u^1.5, so the frames near the anchor
    drifted far less than a linear ramp moves them; with the end's heading measured (the window
    already turned to it) the walk is a bridge and the share a smoothstep."""
    U = float(driven[-1])
    u = np.asarray(driven, dtype=float)
    qh = math.radians(model.heading_deg_per_sqrt_m) ** 2
    qt = model.trans_m_per_sqrt_m**2
    qb = (model.scale_pct / 100.0) ** 2
    if heading_known:
        num, den = qh * u * u * (3.0 * U - 2.0 * u) / 12.0, qh * U**3 / 12.0
    else:
        num, den = qh * u * u * (3.0 * U - u) / 6.0, qh * U**3 / 3.0
    num = num + qt * u + qb * u * U
    den = den + qt * U + qb * U * U
    return num / den if den > 0.0 else u / U


def window_length(policy: LoopPolicy, discount_length: int, span: int) -> int:
    """K of eq. 6 for a loop ``span`` = N − j frames long: ``discount_length`` under the fixed
    window, else the policy's share of the span, at most its longest."""
    if policy.discount_window == "span":
        return int(min(policy.span_max, round(policy.span_factor * span)))
    return int(discount_length)


def verified_gain(policy: LoopPolicy, prior: float) -> float:
    """Share of a verified turn applied when the heading's prior variance is ``prior`` deg²."""
    var = prior + policy.verified_heading_sigma_deg**2
    return prior / var if var > 0 else 1.0


def _weights(traj: Trajectory, policy: LoopPolicy, model: DriftModel, lo: int, n: int, alpha: int, turned: bool):
    """(γ, share of the distance driven) of the window frames lo .. n. Each frame's share of the
    drift: the distance driven from the anchor (frame lo - 1) over the window's, as drift grows
    with distance, not frames (stops, gaps)."""
    gamma = discount(policy, alpha, n - np.arange(lo, n + 1, dtype=float), n - lo)
    frac = np.arange(1, n - lo + 2, dtype=float) / (n - lo + 1)
    if lo > 0:
        driven = traj.s[lo : n + 1] - traj.s[lo - 1]
        if driven[-1] > 1e-9:
            frac = driven / driven[-1]
            if policy.discount_shape == "drift":
                share = drift_share(model, driven, heading_known=turned)
                gamma = (1.0 - math.exp(-policy.discount_offset)) * share
    return gamma, frac


def _bend(traj: Trajectory, lo: int, n: int, Rs: np.ndarray) -> np.ndarray:
    """Turn the window's headings by ``Rs`` from its anchor (frame lo - 1, fixed) to N and
    re-compose its positions from the VO steps turned with them; returns how far N moved."""
    steps = np.diff(traj.p[lo - 1 : n + 1], axis=0)
    turned = np.einsum("kij,kj->ki", np.concatenate([np.eye(3)[None], Rs[:-1]]), steps)
    old_n = traj.p[n].copy()
    traj.p[lo : n + 1] = traj.p[lo - 1] + np.cumsum(turned, axis=0)
    traj.R[lo : n + 1] = Rs @ traj.R[lo : n + 1]
    traj.yaw[lo : n + 1] = yaw_deg(traj.R[lo : n + 1])
    return traj.p[n] - old_n


def correct(
    traj: Trajectory,
    policy: LoopPolicy,
    model: DriftModel,
    window: tuple[int, int],
    offset: np.ndarray,
    weight: float,
    alpha: int,
    rotvec: np.ndarray | None = None,
) -> int:
    """Eq. 6 (our reading) on the window (lo, N): p_s += w·γ_s·δ for s in [lo, N], δ = ``offset``,
    w = ``weight``; with ``rotvec`` (world-frame axis-angle toward the verified heading) first
    the bend (:func:`_bend`), or, for a window that starts at frame 0 (no anchor),
    R_s ← Exp(w·γ_s·rotvec)·R_s. Frame lo - 1 is the anchor and never moves. Returns how many moved.
    """
    lo, n = window
    delta = offset
    gamma, frac = _weights(traj, policy, model, lo, n, alpha, turned=rotvec is not None)
    if rotvec is not None and lo > 0:
        # The ramp below then spreads only what remains of delta.
        delta = delta - _bend(traj, lo, n, exp_so3_scaled(rotvec, weight * frac))
        if policy.correction_axes == "ground":
            delta[1] = 0.0
        rotvec = None
    traj.p[lo : n + 1] += (weight * gamma)[:, None] * delta
    if rotvec is not None:
        traj.R[lo : n + 1] = exp_so3_scaled(rotvec, weight * gamma) @ traj.R[lo : n + 1]
        traj.yaw[lo : n + 1] = yaw_deg(traj.R[lo : n + 1])
    return int(np.count_nonzero(gamma > 0.0))
