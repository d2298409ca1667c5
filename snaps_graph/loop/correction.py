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

from ..config import LoopConfig
from ..drift_model import DriftModel
from ..geometry import exp_so3_scaled, yaw_deg


def yaw_correction(dR: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector of the part of dR = R_target R_N^T about the world vertical y."""
    # Closest rotation about y: R_y(t) = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    return np.array([0.0, math.atan2(dR[0, 2] - dR[2, 0], dR[0, 0] + dR[2, 2]), 0.0])


def discount(cfg: LoopConfig, alpha: int, s_prime: np.ndarray, window: int | None = None) -> np.ndarray:
    """γ of eq. 6 for offsets s' = N − s: max(0, 1 − exp(−(c − α·r·s'))); with ``window`` = K and
    ``discount_shape`` "drift", (1 − e^−c)·(1 − s'/(K + 1)) until :func:`drift_share` reshapes it
    by the distance driven."""
    if window is None or cfg.discount_shape == "paper":
        return np.maximum(0.0, 1.0 - np.exp(-(cfg.discount_offset - alpha * cfg.discount_rate * s_prime)))
    return (1.0 - math.exp(-cfg.discount_offset)) * np.clip(1.0 - s_prime / (window + 1.0), 0.0, 1.0)


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


class Correction:
    """Eq. 6 on :class:`~snaps_graph.loop.snaps.SnapsLoopCloser`'s trajectory (a mixin: the
    closer owns the arrays; re-filing moved frames is the search's)."""

    cfg: LoopConfig
    drift_model: DriftModel
    _R: np.ndarray  # (cap, 3, 3) orientations
    _p: np.ndarray  # (cap, 3) positions
    _yaw: np.ndarray  # (cap,) headings, degrees
    _s: np.ndarray  # (cap,) distance driven up to each frame, m

    def _refile(self, lo: int, stop: int) -> None:
        """Re-file the moved frames lo .. stop-1 in the candidate index (the search's; see search.py)."""
        raise NotImplementedError

    def _gain(self, prior: float) -> float:
        """Share of a verified turn applied when the heading's prior variance is ``prior`` deg²."""
        var = prior + self.cfg.verified_heading_sigma_deg**2
        return prior / var if var > 0 else 1.0

    def window_length(self, span: int) -> int:
        """K of eq. 6 for a loop ``span`` = N − j frames long (``discount_window``)."""
        if self.cfg.discount_window == "span":
            return int(min(self.cfg.discount_length_max, round(self.cfg.discount_span_factor * span)))
        return int(self.cfg.discount_length)

    def _correct(self, n: int, q: float, delta: np.ndarray, alpha: int, rotvec: np.ndarray | None = None, first: int = 0) -> int:
        """Eq. 6 (our reading): p_s += w·γ_s·δ for s in [max(N−K, first), N], w = Q (or 1 for a
        verified loop under correction_weight = "verified"); with ``rotvec`` (world-frame axis-angle
        toward the verified heading) first the bend, or, for a window that starts at frame 0 (no
        anchor), R_s ← Exp(w·γ_s·rotvec)·R_s. ``first`` is the frame after the reference: the
        reference and older frames are the loop's anchor and never move. Returns how many moved.
        """
        K = self.window_length(n - first + 1)
        lo = max(0, n - K, first)
        gamma = discount(self.cfg, alpha, n - np.arange(lo, n + 1, dtype=float), n - lo)
        # Each window frame's share of the drift: the distance driven from the anchor (frame
        # lo - 1) over the window's, as drift grows with distance, not frames (stops, gaps).
        frac = np.arange(1, n - lo + 2, dtype=float) / (n - lo + 1)
        if lo > 0:
            driven = self._s[lo : n + 1] - self._s[lo - 1]
            if driven[-1] > 1e-9:
                frac = driven / driven[-1]
                if self.cfg.discount_shape == "drift":
                    share = drift_share(self.drift_model, driven, heading_known=rotvec is not None)
                    gamma = (1.0 - math.exp(-self.cfg.discount_offset)) * share
        if rotvec is not None and lo > 0:
            # Turn the window's headings progressively from its anchor (frame lo - 1, fixed) to N
            # and re-compose its positions from the VO steps turned with them; the ramp below
            # then spreads only what remains of delta.
            Rs = exp_so3_scaled(rotvec, q * frac)
            steps = np.diff(self._p[lo - 1 : n + 1], axis=0)
            turned = np.einsum("kij,kj->ki", np.concatenate([np.eye(3)[None], Rs[:-1]]), steps)
            old_n = self._p[n].copy()
            self._p[lo : n + 1] = self._p[lo - 1] + np.cumsum(turned, axis=0)
            delta = delta - (self._p[n] - old_n)
            if self.cfg.correction_axes == "ground":
                delta[1] = 0.0
            self._R[lo : n + 1] = Rs @ self._R[lo : n + 1]
            self._yaw[lo : n + 1] = yaw_deg(self._R[lo : n + 1])
            rotvec = None
        self._p[lo : n + 1] += (q * gamma)[:, None] * delta
        if rotvec is not None:
            self._R[lo : n + 1] = exp_so3_scaled(rotvec, q * gamma) @ self._R[lo : n + 1]
            self._yaw[lo : n + 1] = yaw_deg(self._R[lo : n + 1])
        self._refile(lo, n + 1)
        return int(np.count_nonzero(gamma > 0.0))
