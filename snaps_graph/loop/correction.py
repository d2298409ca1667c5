"""Eq. 6's correction of the heuristic trajectory on a loop (paper §III-C, our reading).

On a loop, corrects positions with our reading of eq. 6 (SPEC "SNAPS loop closure"): with
δ = p_ref − p_N and α the number of loops closed so far (this one included), for
s ∈ [N − K, N] (clipped at 0), s' = N − s::

    γ_s = max(0, 1 − exp(−(c − α·r·s')))      c = discount_offset (3), r = discount_rate (0.01)
    p_s ← p_s + Q·γ_s·δ

The paper prints x_s^new = Q·γ·δ_x, which would throw every pose near the origin; the additive
reading moves the current frame 95 % (γ = 1 − e^-3 at s' = 0, times Q) of the way to the
reference and older frames less. γ turns negative once α·r·s' > c, which would push poses away
from the reference, so it is clamped at 0. The window never reaches the reference or older
frames (the loop's anchor; only possible when K > M). The current frame becomes the last
pinned frame.

What moves (``correction_axes``, ``correction_rotation``): the paper corrects x, y, z and keeps
the VO orientations ("xyz", "none"). The target p_ref (+ R_ref·t_ref_cur) carries the
reference's own error, and its *height* error is not smaller than the current frame's on our
renderings (the VO's height error comes from a pitch bias, not a random walk): moving z toward
it raised the height error. By default δ keeps its ground-plane components only ("ground":
world x, z; heights stay the VO's) and a verified loop also turns the window about the world
vertical toward the verified heading R_ref·R_ref_cur by the same w·γ_s ("yaw"), so the frames
after the loop continue on the corrected heading instead of re-growing the same drift.

The window (``discount_window``, ``discount_shape``): the paper's K = ``discount_length`` and
γ above; or K following the loop's span N − j ("span": min(``discount_length_max``,
``discount_span_factor``·(N − j))) with a linear ramp ("linear"), so the correction ends at 0
instead of stepping there (γ is 0.86 at s' = 100). The ramp runs in the distance driven since
the window's anchor, not in frames: drift grows with distance, so frames standing still share
one correction and frames left out (a gap in the frame numbers) carry their distance's share.

The heading turn bends the window: the headings turn progressively (by the same distance
share) from the window's anchor (frame N − K − 1, fixed) to N, the window's positions are
re-composed from the VO steps turned with them (a heading error that grew along the loop bent the path, and turning it back
straightens the middle of the loop, which δ at N cannot see), then what remains of δ is spread
by the ramp. The share of the turn applied is the gain g = P / (P + s²)
(``heading_drift_deg``, ``verified_heading_sigma_deg``) with P the heading variance since the
reference.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import LoopConfig
from ..geometry import exp_so3_scaled, yaw_deg


def yaw_correction(dR: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector of the part of dR = R_target R_N^T about the world vertical y."""
    # Closest rotation about y: R_y(t) = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    return np.array([0.0, math.atan2(dR[0, 2] - dR[2, 0], dR[0, 0] + dR[2, 2]), 0.0])


def discount(cfg: LoopConfig, alpha: int, s_prime: np.ndarray, window: int | None = None) -> np.ndarray:
    """γ of eq. 6 for offsets s' = N − s, clamped at 0 (see module docstring).

    With ``window`` = K and ``discount_shape`` "linear": γ = (1 − e^−c)·(1 − s'/(K + 1)), the
    share of a drift that grew evenly over the window.
    """
    if window is None or cfg.discount_shape == "paper":
        return np.maximum(0.0, 1.0 - np.exp(-(cfg.discount_offset - alpha * cfg.discount_rate * s_prime)))
    return (1.0 - math.exp(-cfg.discount_offset)) * np.clip(1.0 - s_prime / (window + 1.0), 0.0, 1.0)


class Correction:
    """Eq. 6 on :class:`~snaps_graph.loop.snaps.SnapsLoopCloser`'s trajectory (a mixin: the
    closer owns the arrays; re-filing moved frames is the search's)."""

    cfg: LoopConfig
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
        verified loop under correction_weight = "verified"); with ``rotvec`` (world-frame
        axis-angle toward the verified heading) first the bend (module docstring), or, for a
        window that starts at frame 0 (no anchor), R_s ← Exp(w·γ_s·rotvec)·R_s. ``first``
        is the frame after the reference: the reference and older frames are the loop's anchor
        and never move (only possible when K > M). Returns how many moved."""
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
                if self.cfg.discount_shape == "linear":
                    gamma = (1.0 - math.exp(-self.cfg.discount_offset)) * frac
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
