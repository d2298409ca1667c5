"""SNAPS: similarity and location-based real-time loop closure (paper §III, eq. 6, Table I).

:class:`SnapsLoopCloser` owns the real-time *heuristic* trajectory. Per frame it

1. composes the VO increment onto the previous heuristic pose (already corrected, so corrections
   persist into every later frame);
2. stores the frame's 1/6-scale thumbnail (§III-A);
3. searches loop candidates (§III-B): earlier frames j with ‖p_j − p_N‖ within the gate (current,
   corrected positions; ``search = "radius"``: the paper's fixed radius; ``"drift"``: n sigma of
   the drift model's uncertainty accrued between j and N, see :meth:`SnapsLoopCloser.search`),
   N − j ≥ frame distance M, |wrap(yaw_j − yaw_N)| ≤ max yaw difference (widened by the heading
   drift), and only if N − last pinned frame > inter-frame pause; nearest first (ties: older frame
   first), at most ``attempts`` of them are compared by UIQI (eq. 4) on thumbnails; candidates with
   Q ≥ minimum similarity are, highest Q first, the loop. With a verifier (the pipeline always has
   one), they are tried in that order and the first that passes geometric verification is the
   loop; with ``require_verification`` none passing means no loop (see :meth:`_try_close`).
   With ``pause_closer_ratio`` r > 0 the pause still searches candidates estimated closer than r
   times the last loop's distance; one verified closer than that is a loop for the factor graph
   only (weight 0, nothing corrected, the pause keeps running from the loop that started it);
4. on a loop corrects positions with our reading of eq. 6 (SPEC "SNAPS loop closure"): with
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
   share) from the window's anchor (frame N − K − 1, fixed) to N, the window's positions are re-composed from the VO steps turned
   with them (a heading error that grew along the loop bent the path, and turning it back
   straightens the middle of the loop, which δ at N cannot see), then what remains of δ is spread
   by the ramp. The share of the turn applied is the gain g = P / (P + s²)
   (``heading_drift_deg``, ``verified_heading_sigma_deg``) with P the heading variance since the
   reference.

Frame numbering. Internally frames are numbered by their position in the processed stream
(0, 1, ...): M, K and the pause count processed frames. The caller's ``index`` (the dataset's
frame number, which differs when a frame range is processed) is what :class:`LoopEvent` records in
``frame`` and ``reference``; :attr:`indices` maps one to the other.

Spatial look-up. A uniform grid hash with cell = radius maps a cell to the frames inside it, so a
query reads the 9 ground-plane (x, z) cells around p_N and checks exact distances only there: the cost does not grow
with the trajectory, only with the local density of frames. Frame N − M enters the grid when frame
N arrives (younger frames can never be candidates), and a correction re-files the moved frames that
are already in the grid, so the index always holds the corrected positions.

Similarity cost. UIQI's per-image window sums are cached per thumbnail (LRU, ``stats_cache_frames``)
so comparing the current frame with a candidate computes only the cross term; the winner's Q and
its three factors, reported in the LoopEvent, come from the same exact float64 arithmetic.

Timing. ``t_ms`` covers detection and correction: grid insertion, candidate search, similarities
(including any window sums computed on a cache miss) and eq. 6, measured with perf_counter. It
excludes making the thumbnail (a resize of the full image) and composing the pose, which the
pipeline times as part of the frame.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from time import perf_counter

import numpy as np

from ..config import LoopConfig, OdometryConfig
from ..errors import SnapsGraphError
from ..geometry import wrap_deg, yaw_deg
from ..types import CandidateRecord, LoopEvent
from .uiqi import WindowStats, make_thumbnail, shifted_pair, similarity, similarity_q, similarity_shifted, window_stats

# Geometric verification, injected by the pipeline (loop/ never imports the front end):
# reference dataset index -> (T_ref_cur, inliers) or None.
Verifier = Callable[[int], "tuple[np.ndarray, int] | None"]

# Grid cell keys pack (x, z) cell numbers into one Python int: unique while every cell
# coordinate stays within ±2^30 cells.
_RADIX = 1 << 32
# The grid hashes the ground plane (x, z; KITTI's y points down): a query reads 9 cells instead
# of 27, and height differences are left to the exact distance test.
_NEIGHBOUR_OFFSETS = tuple(dx * _RADIX + dz for dx in (-1, 0, 1) for dz in (-1, 0, 1))


def _cell_key(c) -> int:
    return int(c[0]) * _RADIX + int(c[2])


# What a search with no candidate returns (read-only, shared: the no-candidate path allocates nothing).
_NO_IDS = np.empty(0, dtype=np.int64)
_NO_IDS.flags.writeable = False
_NO_DISTS = np.empty(0)
_NO_DISTS.flags.writeable = False


@dataclass
class SnapsStep:
    """What :meth:`SnapsLoopCloser.step` returns for one frame."""

    pose: np.ndarray  # 4x4 heuristic T_world_cam of this frame, after any correction
    loop: LoopEvent | None  # the loop closed at this frame, if any
    candidates: int  # similarities computed on this frame
    t_ms: float  # detection + correction time (see module docstring)
    t_verify_ms: float = 0.0  # geometric verification time on this frame (tried or successful)


def _yaw_correction(dR: np.ndarray) -> np.ndarray:
    """World-frame axis-angle vector of the part of dR = R_target R_N^T about the world vertical y."""
    # Closest rotation about y: R_y(t) = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    return np.array([0.0, math.atan2(dR[0, 2] - dR[2, 0], dR[0, 0] + dR[2, 2]), 0.0])


def _exp_so3(rotvec: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Rodrigues: (len(scales), 3, 3) rotations Exp(scale·rotvec)."""
    theta = float(np.linalg.norm(rotvec))
    out = np.broadcast_to(np.eye(3), (len(scales), 3, 3)).copy()
    if theta == 0.0:
        return out
    k = rotvec / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.asarray(scales, float) * theta
    out += np.sin(t)[:, None, None] * K + (1.0 - np.cos(t))[:, None, None] * (K @ K)
    return out


def discount(cfg: LoopConfig, alpha: int, s_prime: np.ndarray, window: int | None = None) -> np.ndarray:
    """γ of eq. 6 for offsets s' = N − s, clamped at 0 (see module docstring).

    With ``window`` = K and ``discount_shape`` "linear": γ = (1 − e^−c)·(1 − s'/(K + 1)), the
    share of a drift that grew evenly over the window.
    """
    if window is None or cfg.discount_shape == "paper":
        return np.maximum(0.0, 1.0 - np.exp(-(cfg.discount_offset - alpha * cfg.discount_rate * s_prime)))
    return (1.0 - math.exp(-cfg.discount_offset)) * np.clip(1.0 - s_prime / (window + 1.0), 0.0, 1.0)


class SnapsLoopCloser:
    """Real-time SNAPS loop closer and owner of the heuristic trajectory (no I/O inside)."""

    def __init__(self, cfg: LoopConfig | None = None, odometry: OdometryConfig | None = None):
        self.cfg = cfg if cfg is not None else LoopConfig()
        self.cfg.validate()
        self.odometry = odometry if odometry is not None else OdometryConfig()
        self.odometry.validate()
        # Drift model of the search gate: sigma(D)^2 = (a D)^2 + (b D^2 / 2)^2 for D metres driven.
        self._drift_a = self.odometry.trans_drift_pct / 100.0
        self._drift_b = math.radians(self.odometry.rot_drift_deg_per_100m) / 100.0
        r = self.cfg.radius_m
        # Grid levels (drift search): cell sizes radius * 2^k up to the largest gate.
        self._levels = [r * 2.0**k for k in range(1 + max(0, math.ceil(math.log2(max(1.0, self.cfg.search_max_radius_m / r)))))]
        if self.cfg.search != "drift":
            self._levels = self._levels[:1]
        self._grids: list[dict[int, list[int]]] = [{} for _ in self._levels]
        self._nears: list[dict[int, int]] = [{} for _ in self._levels]
        self._cells = [np.empty((1024, 3), dtype=np.int64) for _ in self._levels]
        # A frame enters level k >= 1 once the distance driven since it makes its gate wider than
        # level k-1's cell: recent frames (the common neighbours) stay in level 0 only.
        self._level_driven = [0.0] + [self._driven_for_gate(size) for size in self._levels[:-1]]
        self._filed = [0] * len(self._levels)  # frames 0 .. _filed[k]-1 are in level k
        self._last_loop: tuple[int, int] | None = None  # (frame, reference) of the last verified loop
        self._speed = 0.0  # metres per frame number, running mean (see step)
        self._phase = 0  # rotates the sampled candidates across a wide gate (see _pick)
        cap = 1024
        self._R = np.empty((cap, 3, 3))
        self._p = np.empty((cap, 3))
        self._yaw = np.empty(cap)
        self._index = np.empty(cap, dtype=np.int64)
        self._s = np.empty(cap)  # distance driven up to each frame (estimated), m
        self._n = 0  # frames processed
        self._n_indexed = 0  # frames 0 .. _n_indexed-1 are in the grid
        # Level 0 is the paper's grid (cell = radius). _near: key -> how many non-empty grid cells
        # lie in its 3x3 neighbourhood; most frames have no indexed frame nearby, and one look-up
        # there answers that instead of nine in _grid.
        self._grid = self._grids[0]
        self._near = self._nears[0]
        self._cell = self._cells[0]
        self._thumbs: list[np.ndarray] = []
        self._stats: OrderedDict[int, WindowStats] = OrderedDict()
        self._last_pinned: int | None = None
        self._pause_from = 0  # the loop that started the current pause
        self._alpha = 0  # loops that corrected the trajectory (eq. 6's alpha)
        self._pinned_distance = 0.0  # distance of the last loop (m)
        self._loops: list[LoopEvent] = []
        self.similarities_computed = 0
        self.rejected_unverified = 0  # loops refused because no candidate verified
        self._t_verify_ms = 0.0  # verification time inside the current step (excluded from t_ms)
        self.stats_computed = 0
        # One tuple per compared candidate (types.CandidateRecord, built at the end): (n, j, distance, yaw difference, Q,
        # shift, above threshold, verification tried, passed, inliers, accepted), stream positions.
        self._cand: list[tuple] = []

    # ---- accessors ----
    def __len__(self) -> int:
        return self._n

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) heuristic trajectory T_world_cam (a copy)."""
        n = self._n
        out = np.zeros((n, 4, 4))
        out[:, :3, :3] = self._R[:n]
        out[:, :3, 3] = self._p[:n]
        out[:, 3, 3] = 1.0
        return out

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) heuristic positions (a copy)."""
        return self._p[: self._n].copy()

    @property
    def indices(self) -> np.ndarray:
        """(N,) the caller's frame index of each processed frame (stream position -> dataset index)."""
        return self._index[: self._n].copy()

    @property
    def loops(self) -> list[LoopEvent]:
        return list(self._loops)

    @property
    def last_pinned(self) -> int | None:
        """Stream position of the last pinned frame (None before the first loop)."""
        return self._last_pinned

    def thumbnail(self, k: int) -> np.ndarray:
        """Thumbnail of the frame at stream position ``k`` (uint8 for uint8 input)."""
        return self._thumbs[k]

    def pose(self, k: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self._R[k]
        T[:3, 3] = self._p[k]
        return T

    # ---- the per-frame step ----
    def step(self, index: int, T_rel: np.ndarray, left: np.ndarray, verify: Verifier | None = None) -> SnapsStep:
        """Process one frame: compose the pose, store the thumbnail, detect and close a loop.

        ``T_rel`` is T_prev_cur from the VO (ignored for the first frame, which is the identity);
        ``left`` is the full left grey image. ``verify``, when given, is called with the dataset
        index of a loop's reference and returns ``(T_ref_cur, inliers)`` from geometric
        verification or None (see :meth:`_try_close`). Raises SnapsGraphError for a non-finite or
        malformed ``T_rel`` and for an image whose size differs from the first frame's.
        """
        n = self._n
        thumb = make_thumbnail(left, self.cfg.thumbnail_scale)
        if self._thumbs and thumb.shape != self._thumbs[0].shape:
            raise SnapsGraphError(
                f"SNAPS: frame {index}: image size {np.shape(left)[1]}x{np.shape(left)[0]} differs from the first frame's"
            )
        if min(thumb.shape) < self.cfg.window:
            raise SnapsGraphError(
                f"SNAPS: frame {index}: thumbnail {thumb.shape[1]}x{thumb.shape[0]} "
                f"is smaller than the UIQI window {self.cfg.window}"
            )
        self._grow(n + 1)
        if n == 0:
            R, p = np.eye(3), np.zeros(3)
            self._s[0] = 0.0
        else:
            T = np.asarray(T_rel, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise SnapsGraphError(f"SNAPS: frame {index}: T_rel must be a finite 4x4 transform")
            R_prev, p_prev = self._R[n - 1], self._p[n - 1]
            R = R_prev @ T[:3, :3]
            p = p_prev + R_prev @ T[:3, 3]
            # Distance driven: a jump in the frame numbers (frames left out) is driven at the
            # speed of the frames before it, never less than the straight line across it.
            step_m = math.sqrt(float(T[0, 3] ** 2 + T[1, 3] ** 2 + T[2, 3] ** 2))
            gap = max(1, int(index) - int(self._index[n - 1]))
            if gap == 1:
                self._speed += 0.1 * (step_m - self._speed) if n > 1 else step_m - self._speed
            self._s[n] = self._s[n - 1] + (step_m if gap == 1 else max(step_m, gap * self._speed))
        self._R[n], self._p[n] = R, p
        self._yaw[n] = yaw_deg(R)
        self._index[n] = index
        self._thumbs.append(thumb)
        self._n = n + 1

        t0 = perf_counter()
        if n - self.cfg.frame_distance >= 0:
            self._insert(n - self.cfg.frame_distance)
            for lvl in range(1, len(self._levels)):
                self._promote(n, lvl)
        loop, computed = None, 0
        if self._last_pinned is None or n - self._pause_from > self.cfg.inter_frame_pause:
            ids, dists = self.search(n)
            if ids.size:
                pick = self._pick(len(ids))
                loop, computed = self._try_close(n, ids[pick], dists[pick], verify)
        elif self.cfg.pause_closer_ratio > 0.0:  # in the pause: only a clearly closer revisit
            ids, dists = self.search(n)
            if ids.size:
                limit = self.cfg.pause_closer_ratio * self._pinned_distance
                keep = dists < limit
                if keep.any():
                    a = self.cfg.attempts
                    loop, computed = self._try_close(n, ids[keep][:a], dists[keep][:a], verify, limit)
        # Verification (tried or successful) is the graph's work, timed on its own.
        t_verify_ms, self._t_verify_ms = self._t_verify_ms, 0.0
        t_ms = (perf_counter() - t0) * 1e3 - t_verify_ms
        if loop is not None:
            loop.t_ms = t_ms
        return SnapsStep(pose=self.pose(n), loop=loop, candidates=computed, t_ms=t_ms, t_verify_ms=t_verify_ms)

    # ---- candidates ----
    def search(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidates of stream frame ``n`` by the position gate, frame distance and yaw.

        ``search = "radius"``: within ``radius_m`` (the paper), nearest first. ``"drift"``: within
        ``search_sigmas`` standard deviations of the drift accrued between j and n (never less
        than ``radius_m``, at most ``search_max_radius_m``), nearest in sigmas first. Ignores the
        inter-frame pause and the attempts limit (``step`` applies those). Returns (stream
        positions, distances in metres), ties by older frame.
        """
        if self.cfg.search == "drift":
            return self._search_drift(n)
        cfg = self.cfg
        p = self._p[n]
        r = cfg.radius_m
        x, y, z = p.tolist()  # plain floats: numpy's per-call overhead dominates at this size
        base = math.floor(x / r) * _RADIX + math.floor(z / r)
        if base not in self._near:  # no indexed frame in the 9 cells: the common case
            return _NO_IDS, _NO_DISTS
        grid = self._grid
        found: list[int] = []
        for off in _NEIGHBOUR_OFFSETS:
            members = grid.get(base + off)
            if members:
                found.extend(members)
        if not found:
            return _NO_IDS, _NO_DISTS
        if len(found) <= 32:  # few neighbours (most frames): scalar Python beats numpy's call overhead
            return self._search_small(n, found)
        ids = np.array(found, dtype=np.int64)
        ids = ids[ids <= n - cfg.frame_distance]  # the grid holds only these, unless n is in the past
        d = np.linalg.norm(self._p[ids] - p, axis=1)
        ok = (d <= cfg.radius_m) & (np.abs(wrap_deg(self._yaw[ids] - self._yaw[n])) <= cfg.max_yaw_deg)
        ids, d = ids[ok], d[ok]
        order = np.lexsort((ids, d))
        return ids[order], d[order]

    def driven_since(self, n: int, ids: np.ndarray) -> np.ndarray:
        """Metres of odometry between each frame of ``ids`` and frame ``n``: along the path, or
        through the last verified loop (its frame and reference are tied by a measurement)."""
        s = self._s
        d = s[n] - s[ids]
        if self._last_loop is not None:
            frame, ref = self._last_loop
            d = np.minimum(d, s[n] - s[frame] + np.abs(s[ids] - s[ref]))
        return d

    def drift_sigma(self, driven: np.ndarray | float) -> np.ndarray:
        """1-sigma position error (m) after ``driven`` metres: translation drift plus the lateral
        error of a heading error that grows linearly with the distance."""
        D = np.asarray(driven, dtype=float)
        return np.hypot(self._drift_a * D, 0.5 * self._drift_b * D * D)

    def _gate(self, driven: np.ndarray | float) -> np.ndarray:
        cfg = self.cfg
        return np.clip(cfg.search_sigmas * self.drift_sigma(driven), cfg.radius_m, cfg.search_max_radius_m)

    def _search_drift(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        last = n - cfg.frame_distance
        if last < 0 or self._n_indexed == 0:
            return _NO_IDS, _NO_DISTS
        # Each level holds the frames whose gate fits its 3x3 cells (see _promote).
        x, _, z = self._p[n].tolist()
        found: list[int] = []
        for lvl, size in enumerate(self._levels):
            base = math.floor(x / size) * _RADIX + math.floor(z / size)
            if base not in self._nears[lvl]:  # no indexed frame anywhere near: the common case
                continue
            grid = self._grids[lvl]
            for off in _NEIGHBOUR_OFFSETS:
                members = grid.get(base + off)
                if members:
                    found.extend(members)
        if not found:
            return _NO_IDS, _NO_DISTS
        if len(found) > 48:  # many neighbours: one vector test drops those beyond the widest gate
            ids = np.array(found, dtype=np.int64)
            d2 = np.sum((self._p[ids] - self._p[n]) ** 2, axis=1)
            found = ids[(d2 <= cfg.search_max_radius_m**2) & (ids <= last)].tolist()
        if len(found) <= 48:  # few left (most frames): scalar Python beats numpy's call overhead
            return self._search_drift_small(n, found)
        ids = np.unique(np.array(found, dtype=np.int64))
        d = np.linalg.norm(self._p[ids] - self._p[n], axis=1)
        driven = self.driven_since(n, ids)
        sigma = np.maximum(self.drift_sigma(driven), cfg.radius_m / cfg.search_sigmas)
        gates = np.minimum(cfg.search_sigmas * sigma, cfg.search_max_radius_m)
        # The yaw gate widens by the heading drift too (n sigma of b*D, degrees).
        yaw_gate = cfg.max_yaw_deg + cfg.search_sigmas * np.degrees(self._drift_b * driven)
        ok = (d <= gates) & (np.abs(wrap_deg(self._yaw[ids] - self._yaw[n])) <= yaw_gate)
        if not ok.any():
            return _NO_IDS, _NO_DISTS
        ids, d, m = ids[ok], d[ok], d[ok] / sigma[ok]
        order = np.lexsort((ids, m))
        return ids[order], d[order]

    def _search_drift_small(self, n: int, found: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_search_drift`'s rules for a short member list, without numpy arrays."""
        cfg = self.cfg
        last = n - cfg.frame_distance
        px, py, pz = self._p[n].tolist()
        yaw_n = float(self._yaw[n])
        s_n = float(self._s[n])
        loop = self._last_loop
        if loop is not None:
            via, s_ref = s_n - float(self._s[loop[0]]), float(self._s[loop[1]])
        a2, hb = self._drift_a**2, 0.5 * self._drift_b
        k, floor, cap = cfg.search_sigmas, cfg.radius_m / cfg.search_sigmas, cfg.search_max_radius_m
        yaw_k = k * math.degrees(self._drift_b)
        hits = []
        for j in set(found):
            if j > last:
                continue
            x, y, z = self._p[j].tolist()
            d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
            if d2 > cap * cap:
                continue
            s_j = float(self._s[j])
            D = s_n - s_j
            if loop is not None:
                D = min(D, via + abs(s_j - s_ref))
            sigma = max(math.sqrt(a2 * D * D + (hb * D * D) ** 2), floor)
            gate = min(k * sigma, cap)
            if d2 > gate * gate:
                continue
            dyaw = (float(self._yaw[j]) - yaw_n + 180.0) % 360.0 - 180.0
            if abs(dyaw) <= cfg.max_yaw_deg + yaw_k * D:
                d = math.sqrt(d2)
                hits.append((d / sigma, j, d))
        if not hits:
            return _NO_IDS, _NO_DISTS
        hits.sort()  # nearest in sigmas first, ties by older frame
        return np.array([j for _, j, _ in hits], dtype=np.int64), np.array([d for _, _, d in hits])

    def _pick(self, n_found: int) -> np.ndarray:
        """Which of ``n_found`` candidates (nearest first) are compared: all up to ``attempts``;
        beyond that the nearest and, with the drift search, ``attempts`` - 1 spread evenly over
        the rest, shifted each frame, so a true match a drift's length away is reached within a
        few frames instead of never (the estimated nearest is not the true one under drift)."""
        a = self.cfg.attempts
        if n_found <= a or a <= 1 or self.cfg.search != "drift":
            return np.arange(min(a, n_found))
        rest = n_found - 1
        stride = rest / (a - 1)
        self._phase = (self._phase + 1) % max(1, math.ceil(stride))
        offs = (self._phase + np.arange(a - 1) * stride).astype(np.int64) % rest
        return np.concatenate([[0], 1 + np.unique(offs)])

    def _search_small(self, n: int, found: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`search`'s rules for a short member list, without numpy arrays."""
        cfg = self.cfg
        px, py, pz = self._p[n].tolist()
        yaw_n = float(self._yaw[n])
        r2 = cfg.radius_m * cfg.radius_m
        last = n - cfg.frame_distance
        hits = []
        for j in found:
            if j > last:
                continue
            x, y, z = self._p[j].tolist()
            d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
            if d2 > r2:
                continue
            dyaw = (float(self._yaw[j]) - yaw_n + 180.0) % 360.0 - 180.0  # wrap to [-180, 180)
            if abs(dyaw) <= cfg.max_yaw_deg or (dyaw == -180.0 and cfg.max_yaw_deg >= 180.0):
                hits.append((math.sqrt(d2), j))
        if not hits:
            return _NO_IDS, _NO_DISTS
        hits.sort()  # nearest first, ties by older frame
        return np.array([j for _, j in hits], dtype=np.int64), np.array([d for d, _ in hits])

    def _try_close(
        self, n: int, ids: np.ndarray, dists: np.ndarray, verify: Verifier | None = None, max_distance: float | None = None
    ) -> tuple[LoopEvent | None, int]:
        """Compare candidates, pick the loop, correct (eq. 6). With ``max_distance`` (a search
        inside the pause) a verification measuring the reference that far away or farther does
        not make a loop.

        δ aims at the reference position p_ref (the paper's same-place assumption). With
        ``use_verified_offset`` and a verifier that succeeds, δ aims instead at where the current
        frame really stands relative to the reference, p_ref + R_ref·t_ref_cur: revisits are
        metres apart along and across the road, and pulling N onto p_ref would add that offset
        as error. Orientations still keep their VO values.
        """
        cur = self._window_stats(n)
        if self.cfg.shift_px > 0:  # best horizontal shift per candidate (heading differences)
            scored = [similarity_shifted(cur, self._window_stats(int(j)), self.cfg.shift_px, self.cfg.shift_step_px) for j in ids]
            qs = np.array([q for q, _ in scored])
            shifts = [dx for _, dx in scored]
        else:
            qs = np.array([similarity_q(cur, self._window_stats(int(j))) for j in ids])
            shifts = [0] * len(ids)
        self.similarities_computed += len(ids)
        # Candidates at or above the threshold, highest Q first (stable: nearer first on ties).
        order = np.argsort(-qs, kind="stable")
        passing = [int(i) for i in order if qs[i] >= self.cfg.min_similarity]
        # Verification outcome per candidate: None = not tried, else the verifier's answer.
        outcome: dict[int, "tuple[np.ndarray, int] | None"] = {}
        best, verified, T_ref_cur, inliers, t_verify_ms = -1, False, None, 0, 0.0
        if passing:
            best = passing[0]
        if verify is not None and (passing or self.cfg.verify_all_candidates):
            # Geometric verification of the best candidates in turn: the first that verifies is
            # the loop. With require_verification, none verifying means no loop (a same-place
            # assumption up to the radius away does more harm than a missed loop); otherwise the
            # paper's rule: the highest Q, unverified. verify_all_candidates verifies the rest
            # too, for the record only.
            tv = perf_counter()
            for i in passing[: max(1, self.cfg.verify_attempts)]:
                outcome[i] = result = verify(int(self._index[int(ids[i])]))
                if result is not None and (max_distance is None or np.linalg.norm(result[0][:3, 3]) < max_distance):
                    best, (T_ref_cur, inliers), verified = i, result, True
                    break
            if self.cfg.verify_all_candidates:
                for i in order.tolist():
                    if i not in outcome:
                        outcome[i] = verify(int(self._index[int(ids[i])]))
            t_verify_ms = (perf_counter() - tv) * 1e3
            self._t_verify_ms = t_verify_ms
        accept = bool(passing) and (verified or verify is None or not self.cfg.require_verification)
        if passing and not accept:
            self.rejected_unverified += 1
        self._record(n, ids, dists, qs, shifts, outcome, best if accept else -1)
        if not accept:
            return None, len(ids)
        ref = int(ids[best])
        # The winner's factors, same arithmetic, at its best shift.
        margin = min(self.cfg.shift_px, (cur.shape[1] - cur.window) // 2)
        sim = similarity(*shifted_pair(cur, self._window_stats(ref), shifts[best], margin))
        target = self._p[ref].copy()
        if verified and self.cfg.use_verified_offset:
            target = target + self._R[ref] @ np.asarray(T_ref_cur, float)[:3, 3]
        delta = target - self._p[n]
        if self.cfg.correction_axes == "ground":  # the reference's height error stays out
            delta[1] = 0.0
        in_pause = max_distance is not None  # a closer revisit inside the pause: for the graph only
        rotvec = None
        if verified and self.cfg.correction_rotation != "none" and not in_pause:
            gain = self._gain((n - ref) * self.cfg.heading_drift_deg**2)
            rotvec = _yaw_correction(self._R[ref] @ np.asarray(T_ref_cur, float)[:3, :3] @ self._R[n].T) * gain
        # Eq. 6 weighs the move by Q: the confidence that N stands where the reference stood. A
        # verified loop measured where N stands, so with correction_weight = "verified" it moves
        # with weight 1 (gamma still discounts older poses); "q" is the paper's rule everywhere.
        weight = 1.0 if (verified and self.cfg.correction_weight == "verified") else sim.q
        if in_pause:
            # Correcting again re-bends what the last loop explained: the loop goes to the factor
            # graph only and the pause keeps running.
            weight, n_corrected, alpha = 0.0, 0, self._alpha
        else:
            self._alpha = alpha = self._alpha + 1
            n_corrected = self._correct(n, weight, delta, alpha, rotvec, first=ref + 1)
            self._last_pinned = self._pause_from = n
            if verified:  # the search's uncertainty restarts from this measurement
                self._last_loop = (n, ref)
        self._pinned_distance = float(np.linalg.norm(np.asarray(T_ref_cur, float)[:3, 3])) if verified else float(dists[best])
        event = LoopEvent(
            frame=int(self._index[n]),
            reference=int(self._index[ref]),
            distance_m=float(dists[best]),
            yaw_diff_deg=float(wrap_deg(self._yaw[ref] - self._yaw[n])),
            q=sim.q,
            correlation=sim.correlation,
            luminance=sim.luminance,
            contrast=sim.contrast,
            delta=delta.copy(),
            n_corrected=n_corrected,
            alpha=alpha,
            candidates=len(ids),
            t_ms=0.0,  # set by step() once the frame's detection + correction is over
            verified=verified,
            shift_px=int(shifts[best]),
            weight=float(weight),
            verify_inliers=int(inliers),
            T_ref_cur=None if T_ref_cur is None else np.asarray(T_ref_cur, float).copy(),
            t_verify_ms=t_verify_ms,
        )
        self._loops.append(event)
        return event, len(ids)

    def heading_gain(self, frames: int) -> float:
        """Share of a verified rotation applied by a loop ``frames`` after its reference: the VO's
        heading variance over that stretch against the measurement's (config comment)."""
        return self._gain(frames * self.cfg.heading_drift_deg**2)

    def _gain(self, prior: float) -> float:
        """Share of a verified turn applied when the heading's prior variance is ``prior`` deg²."""
        var = prior + self.cfg.verified_heading_sigma_deg**2
        return prior / var if var > 0 else 1.0

    # ---- records ----
    def _record(self, n, ids, dists, qs, shifts, outcome, accepted: int) -> None:
        """Append one tuple per compared candidate (no formatting; types.CandidateRecord at the end)."""
        yaw_n = float(self._yaw[n])
        yaws = self._yaw
        thr = self.cfg.min_similarity
        app = self._cand.append
        for i, j in enumerate(ids.tolist()):
            res = outcome.get(i, False)
            app(
                (
                    n,
                    j,
                    float(dists[i]),
                    float(yaws[j]) - yaw_n,
                    float(qs[i]),
                    int(shifts[i]),
                    bool(qs[i] >= thr),
                    res is not False,
                    bool(res),
                    res[1] if res else 0,
                    i == accepted,
                )
            )

    def candidate_records(self) -> list[CandidateRecord]:
        """Every similarity computed so far as :class:`CandidateRecord` (dataset frame indices),
        with Q's three factors computed now from the stored thumbnails at the recorded shift."""
        out = []
        stats: dict[int, WindowStats] = {}

        def st(k: int) -> WindowStats:
            if k not in stats:
                stats[k] = self._stats.get(k) or window_stats(self._thumbs[k], self.cfg.window)
            return stats[k]

        for n, j, d, dyaw, q, dx, above, tried, passed, inl, acc in self._cand:
            a, b = st(n), st(j)
            margin = min(self.cfg.shift_px, (a.shape[1] - a.window) // 2)
            sim = similarity(*shifted_pair(a, b, dx, margin))
            out.append(
                CandidateRecord(
                    frame=int(self._index[n]),
                    reference=int(self._index[j]),
                    distance_m=d,
                    yaw_diff_deg=float(wrap_deg(dyaw)),
                    q=q,
                    correlation=sim.correlation,
                    luminance=sim.luminance,
                    contrast=sim.contrast,
                    shift_px=dx,
                    above_threshold=above,
                    verify_tried=tried,
                    verify_passed=passed,
                    inliers=int(inl),
                    accepted=acc,
                )
            )
            if len(stats) > 64:  # records come frame by frame: keep the memory bounded
                stats.clear()
        return out

    # ---- eq. 6 ----
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
            Rs = _exp_so3(rotvec, q * frac)
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
            self._R[lo : n + 1] = _exp_so3(rotvec, q * gamma) @ self._R[lo : n + 1]
            self._yaw[lo : n + 1] = yaw_deg(self._R[lo : n + 1])
        for lvl, size in enumerate(self._levels):  # re-file moved frames that are already in the grids
            hi = min(n + 1, self._filed[lvl])
            if hi > lo:
                cells, grid = self._cells[lvl], self._grids[lvl]
                new = np.floor(self._p[lo:hi] / size).astype(np.int64)
                for k in np.flatnonzero(np.any(new != cells[lo:hi], axis=1)):
                    j = lo + int(k)
                    old_key = _cell_key(cells[j])
                    members = grid[old_key]
                    members.remove(j)
                    if not members:
                        del grid[old_key]
                        self._count_near(old_key, -1, lvl)
                    cells[j] = new[k]
                    self._file(_cell_key(new[k]), j, lvl)
        return int(np.count_nonzero(gamma > 0.0))

    # ---- storage ----
    def _insert(self, j: int) -> None:
        r = self.cfg.radius_m
        c = [math.floor(v / r) for v in self._p[j].tolist()]
        self._cell[j] = c
        self._file(_cell_key(c), j)
        self._n_indexed = self._filed[0] = j + 1

    def _promote(self, n: int, lvl: int) -> None:
        """File into level ``lvl`` the indexed frames driven far enough from (see __init__)."""
        j, s, need, size = self._filed[lvl], self._s, self._level_driven[lvl], self._levels[lvl]
        cells = self._cells[lvl]
        while j < self._n_indexed and s[n] - s[j] >= need:
            c = [math.floor(v / size) for v in self._p[j].tolist()]
            cells[j] = c
            self._file(_cell_key(c), j, lvl)
            j += 1
        self._filed[lvl] = j

    def _driven_for_gate(self, gate: float) -> float:
        """The distance driven at which the drift gate first exceeds ``gate`` metres."""
        if self.cfg.search_sigmas * float(self.drift_sigma(1e7)) <= gate:
            return math.inf
        lo, hi = 0.0, 1e7
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if self.cfg.search_sigmas * float(self.drift_sigma(mid)) > gate:
                hi = mid
            else:
                lo = mid
        return lo

    def _file(self, key: int, j: int, lvl: int = 0) -> None:
        grid = self._grids[lvl]
        members = grid.get(key)
        if members is None:
            grid[key] = [j]
            self._count_near(key, +1, lvl)
        else:
            members.append(j)

    def _count_near(self, key: int, step: int, lvl: int = 0) -> None:
        """A cell became non-empty (+1) or empty (-1): update its 3x3 neighbourhood's counts."""
        near = self._nears[lvl]
        for off in _NEIGHBOUR_OFFSETS:
            c = near.get(key + off, 0) + step
            if c:
                near[key + off] = c
            else:
                del near[key + off]

    def _window_stats(self, k: int) -> WindowStats:
        cache = self._stats
        st = cache.get(k)
        if st is not None:
            cache.move_to_end(k)
            return st
        st = window_stats(self._thumbs[k], self.cfg.window)
        self.stats_computed += 1
        if self.cfg.stats_cache_frames > 0:
            cache[k] = st
            if len(cache) > self.cfg.stats_cache_frames:
                cache.popitem(last=False)
        return st

    def _grow(self, need: int) -> None:
        cap = len(self._p)
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)

        def grown(old: np.ndarray) -> np.ndarray:
            arr = np.empty((new_cap,) + old.shape[1:], dtype=old.dtype)
            arr[:cap] = old
            return arr

        for name in ("_R", "_p", "_yaw", "_index", "_s"):
            setattr(self, name, grown(getattr(self, name)))
        self._cells = [grown(c) for c in self._cells]
        self._cell = self._cells[0]


__all__ = ["SnapsLoopCloser", "SnapsStep", "discount"]
