"""SNAPS candidate search (paper §III-B): which earlier frames may be the place the car is at now.

A uniform grid hash over the corrected ground-plane positions (cell = radius; the drift search
adds levels radius·2^k) maps a cell to its frames, so a query checks exact distances only in the
9 cells around p_N. Frame N − M enters when frame N arrives and a correction re-files the moved
frames. The gates: :meth:`CandidateIndex.search` and docs/loop-closure.md, "The search".
"""

from __future__ import annotations

import math

import numpy as np

from ..config import LoopConfig
from ..drift_model import DriftModel, heading_sigma_deg, position_sigma
from ..geometry import wrap_deg
from .policy import LoopPolicy
from .trajectory import Trajectory

# Grid cell keys pack (x, z) cell numbers into one Python int: unique while every cell
# coordinate stays within ±2^30 cells.
_RADIX = 1 << 32
# The grid hashes the ground plane (x, z; KITTI's y points down): a query reads 9 cells instead
# of 27, and height differences are left to the exact distance test.
_NEIGHBOUR_OFFSETS = tuple(dx * _RADIX + dz for dx in (-1, 0, 1) for dz in (-1, 0, 1))


def _gather(grid: dict, base: int, found: list[int]) -> None:
    """Append the frames filed in the 9 cells around cell key ``base`` to ``found``."""
    for off in _NEIGHBOUR_OFFSETS:
        members = grid.get(base + off)
        if members:
            found.extend(members)


def _cell_key(c) -> int:
    return int(c[0]) * _RADIX + int(c[2])


# What a search with no candidate returns (read-only, shared: the no-candidate path allocates nothing).
_NO_IDS = np.empty(0, dtype=np.int64)
_NO_IDS.flags.writeable = False
_NO_DISTS = np.empty(0)
_NO_DISTS.flags.writeable = False


class CandidateIndex:
    """The grid index over a :class:`~snaps_graph.loop.trajectory.Trajectory` and the gates of
    the candidate search (``policy.search``: the paper's radius or the drift gate)."""

    def __init__(self, traj: Trajectory, cfg: LoopConfig, policy: LoopPolicy, model: DriftModel):
        self.traj, self.cfg, self.policy = traj, cfg, policy
        # The frame and reference of the last verified loop: the search's uncertainty restarts there.
        self.last_loop: tuple[int, int] | None = None
        # The drift model's position variance after D metres, as c1 D + c2 D^2 + c3 D^3
        # (drift_model.position_sigma, no rates), inlined in the per-frame loop below.
        self._model = model
        self._var_coef = (
            model.trans_m_per_sqrt_m**2,
            (model.scale_pct / 100.0) ** 2,
            math.radians(model.heading_deg_per_sqrt_m) ** 2 / 3.0,
        )
        self._heading_walk = model.heading_deg_per_sqrt_m
        r = cfg.radius_m
        self._sigmas = policy.search_sigmas
        self._cap = max(policy.search_max_radius_m, r)  # the drift gate never below the paper's radius
        # Grid levels (drift search): cell sizes radius * 2^k up to the largest gate.
        self._levels = [r * 2.0**k for k in range(1 + max(0, math.ceil(math.log2(max(1.0, self._cap / r)))))]
        if policy.search != "drift":
            self._levels = self._levels[:1]
        self._grids: list[dict[int, list[int]]] = [{} for _ in self._levels]
        self._nears: list[dict[int, int]] = [{} for _ in self._levels]
        self._cells = [np.empty((1024, 3), dtype=np.int64) for _ in self._levels]
        # A frame enters level k >= 1 once the distance driven since it makes its gate wider than
        # level k-1's cell: recent frames (the common neighbours) stay in level 0 only.
        self._level_driven = [0.0] + [self._driven_for_gate(size) for size in self._levels[:-1]]
        self._filed = [0] * len(self._levels)  # frames 0 .. _filed[k]-1 are in level k
        self._phase = 0  # rotates the sampled candidates across a wide gate (see pick)
        self._n_indexed = 0  # frames 0 .. _n_indexed-1 are in the grid
        # Level 0 is the paper's grid (cell = radius). _near: key -> how many non-empty grid cells
        # lie in its 3x3 neighbourhood; most frames have no indexed frame nearby, and one look-up
        # there answers that instead of nine in _grid.
        self._grid = self._grids[0]
        self._near = self._nears[0]

    def add(self, n: int) -> None:
        """Frame ``n`` arrived: frame n - M enters the index, older ones the wider levels."""
        j = n - self.cfg.frame_distance
        if j < 0:
            return
        self._reserve(self.traj.capacity)
        self._insert(j)
        for lvl in range(1, len(self._levels)):
            self._promote(n, lvl)

    def _reserve(self, cap: int) -> None:
        old = len(self._cells[0])
        if cap > old:
            for lvl, cells in enumerate(self._cells):
                grown = np.empty((cap, 3), dtype=np.int64)
                grown[:old] = cells
                self._cells[lvl] = grown

    def search(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidates of stream frame ``n`` by the position gate, frame distance and yaw.

        ``search = "radius"``: within ``radius_m`` (the paper), nearest first. ``"drift"``: within
        ``search_sigmas`` standard deviations of the drift accrued between j and n (never less
        than ``radius_m``, at most ``search_max_radius_m``), nearest in sigmas first. Ignores the
        inter-frame pause and the attempts limit (``step`` applies those). Returns (stream
        positions, distances in metres), ties by older frame.
        """
        if self.policy.search == "drift":
            return self._search_drift(n)
        cfg = self.cfg
        p = self.traj.p[n]
        r = cfg.radius_m
        x, y, z = p.tolist()  # plain floats: numpy's per-call overhead dominates at this size
        base = math.floor(x / r) * _RADIX + math.floor(z / r)
        if base not in self._near:  # no indexed frame in the 9 cells: the common case
            return _NO_IDS, _NO_DISTS
        found: list[int] = []
        _gather(self._grid, base, found)
        if not found:
            return _NO_IDS, _NO_DISTS
        if len(found) <= 32:  # few neighbours (most frames): scalar Python beats numpy's call overhead
            return self._search_small(n, found)
        ids = np.array(found, dtype=np.int64)
        ids = ids[ids <= n - cfg.frame_distance]  # the grid holds only these, unless n is in the past
        d = np.linalg.norm(self.traj.p[ids] - p, axis=1)
        ok = (d <= cfg.radius_m) & (np.abs(wrap_deg(self.traj.yaw[ids] - self.traj.yaw[n])) <= self.policy.max_yaw_deg)
        ids, d = ids[ok], d[ok]
        order = np.lexsort((ids, d))
        return ids[order], d[order]

    def driven_since(self, n: int, ids: np.ndarray) -> np.ndarray:
        """Metres of odometry between each frame of ``ids`` and frame ``n``: along the path, or
        through the last verified loop (its frame and reference are tied by a measurement)."""
        s = self.traj.s
        d = s[n] - s[ids]
        if self.last_loop is not None:
            frame, ref = self.last_loop
            d = np.minimum(d, s[n] - s[frame] + np.abs(s[ids] - s[ref]))
        return np.maximum(d, 0.0)

    def drift_sigma(self, driven: np.ndarray | float) -> np.ndarray:
        """1-sigma position error (m) after ``driven`` metres, by the drift model."""
        return position_sigma(self._model, driven)

    def gates(self, driven: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(sigma, gate) in metres after ``driven`` metres: the drift sigma, never below the paper's
        radius / ``search_sigmas``, and ``search_sigmas`` of it, at most ``search_max_radius_m``."""
        cfg = self.cfg
        sigma = np.maximum(self.drift_sigma(driven), cfg.radius_m / self._sigmas)
        return sigma, np.minimum(self._sigmas * sigma, self._cap)

    @property
    def reach(self) -> float:
        """The farthest any candidate may lie, m: the drift gate's cap, or the paper's radius."""
        return self._cap if self.policy.search == "drift" else self.cfg.radius_m

    def admit(self, d: np.ndarray, dyaw: np.ndarray | float, driven: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which candidates ``d`` metres and ``dyaw`` degrees (wrapped) away, ``driven`` metres of
        odometry apart, pass the position and yaw gates, and their order key: the distance in
        sigmas (drift search) or in metres (the paper's radius)."""
        if self.policy.search != "drift":
            return (d <= self.cfg.radius_m) & (np.abs(dyaw) <= self.policy.max_yaw_deg), d
        sigma, gates = self.gates(driven)
        # The yaw gate widens by the heading drift too (n sigma of the heading walk, degrees).
        yaw_gate = self.policy.max_yaw_deg + self._sigmas * heading_sigma_deg(self._model, driven)
        return (d <= gates) & (np.abs(dyaw) <= yaw_gate), d / sigma

    def _search_drift(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        last = n - cfg.frame_distance
        if last < 0 or self._n_indexed == 0:
            return _NO_IDS, _NO_DISTS
        # Each level holds the frames whose gate fits its 3x3 cells (see _promote).
        x, _, z = self.traj.p[n].tolist()
        found: list[int] = []
        for lvl, size in enumerate(self._levels):
            base = math.floor(x / size) * _RADIX + math.floor(z / size)
            if base not in self._nears[lvl]:  # no indexed frame anywhere near: the common case
                continue
            _gather(self._grids[lvl], base, found)
        if not found:
            return _NO_IDS, _NO_DISTS
        if len(found) > 48:  # many neighbours: one vector test drops those beyond the widest gate
            ids = np.array(found, dtype=np.int64)
            d2 = np.sum((self.traj.p[ids] - self.traj.p[n]) ** 2, axis=1)
            found = ids[(d2 <= self._cap**2) & (ids <= last)].tolist()
        if len(found) <= 48:  # few left (most frames): scalar Python beats numpy's call overhead
            return self._search_drift_small(n, found)
        return self._search_drift_vector(n, found)

    def _search_drift_vector(self, n: int, found: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_search_drift`'s rules for a long member list, as numpy arrays."""
        cfg = self.cfg
        ids = np.unique(np.array(found, dtype=np.int64))
        ids = ids[ids <= n - cfg.frame_distance]
        d = np.linalg.norm(self.traj.p[ids] - self.traj.p[n], axis=1)
        ok, m = self.admit(d, wrap_deg(self.traj.yaw[ids] - self.traj.yaw[n]), self.driven_since(n, ids))
        if not ok.any():
            return _NO_IDS, _NO_DISTS
        ids, d, m = ids[ok], d[ok], m[ok]
        order = np.lexsort((ids, m))
        return ids[order], d[order]

    def _search_drift_small(self, n: int, found: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_search_drift`'s rules for a short member list, without numpy arrays."""
        cfg = self.cfg
        last = n - cfg.frame_distance
        px, py, pz = self.traj.p[n].tolist()
        yaw_n = float(self.traj.yaw[n])
        s_n = float(self.traj.s[n])
        loop = self.last_loop
        if loop is not None:
            via, s_ref = s_n - float(self.traj.s[loop[0]]), float(self.traj.s[loop[1]])
        c1, c2, c3 = self._var_coef
        k, floor, cap = self._sigmas, cfg.radius_m / self._sigmas, self._cap
        yaw_k = k * self._heading_walk
        hits = []
        for j in set(found):
            if j > last:
                continue
            x, y, z = self.traj.p[j].tolist()
            d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
            if d2 > cap * cap:
                continue
            s_j = float(self.traj.s[j])
            D = s_n - s_j
            if loop is not None:
                D = max(min(D, via + abs(s_j - s_ref)), 0.0)
            sigma = max(math.sqrt(D * (c1 + D * (c2 + D * c3))), floor)
            gate = min(k * sigma, cap)
            if d2 > gate * gate:
                continue
            dyaw = (float(self.traj.yaw[j]) - yaw_n + 180.0) % 360.0 - 180.0
            if abs(dyaw) <= self.policy.max_yaw_deg + yaw_k * math.sqrt(D):
                d = math.sqrt(d2)
                hits.append((d / sigma, j, d))
        if not hits:
            return _NO_IDS, _NO_DISTS
        hits.sort()  # nearest in sigmas first, ties by older frame
        return np.array([j for _, j, _ in hits], dtype=np.int64), np.array([d for _, _, d in hits])

    def pick(self, n_found: int) -> np.ndarray:
        """Which of ``n_found`` candidates (nearest first) are compared: all up to ``attempts``;
        beyond that the nearest and, with the drift search, ``attempts`` - 1 spread evenly over
        the rest, shifted each frame, so a true match a drift's length away is reached within a
        few frames instead of never (the estimated nearest is not the true one under drift)."""
        a = self.policy.attempts
        if n_found <= a or a <= 1 or self.policy.search != "drift":
            return np.arange(min(a, n_found))
        rest = n_found - 1
        stride = rest / (a - 1)
        self._phase = (self._phase + 1) % max(1, math.ceil(stride))
        offs = (self._phase + np.arange(a - 1) * stride).astype(np.int64) % rest
        return np.concatenate([[0], 1 + np.unique(offs)])

    def _search_small(self, n: int, found: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`search`'s rules for a short member list, without numpy arrays."""
        cfg = self.cfg
        px, py, pz = self.traj.p[n].tolist()
        yaw_n = float(self.traj.yaw[n])
        r2 = cfg.radius_m * cfg.radius_m
        last = n - cfg.frame_distance
        hits = []
        for j in found:
            if j > last:
                continue
            x, y, z = self.traj.p[j].tolist()
            d2 = (x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2
            if d2 > r2:
                continue
            dyaw = (float(self.traj.yaw[j]) - yaw_n + 180.0) % 360.0 - 180.0  # wrap to [-180, 180)
            if abs(dyaw) <= self.policy.max_yaw_deg or (dyaw == -180.0 and self.policy.max_yaw_deg >= 180.0):
                hits.append((math.sqrt(d2), j))
        if not hits:
            return _NO_IDS, _NO_DISTS
        hits.sort()  # nearest first, ties by older frame
        return np.array([j for _, j in hits], dtype=np.int64), np.array([d for d, _ in hits])

    def _insert(self, j: int) -> None:
        r = self.cfg.radius_m
        c = [math.floor(v / r) for v in self.traj.p[j].tolist()]
        self._cells[0][j] = c
        self._file(_cell_key(c), j)
        self._n_indexed = self._filed[0] = j + 1

    def _promote(self, n: int, lvl: int) -> None:
        """File into level ``lvl`` the indexed frames driven far enough from (see __init__)."""
        j, s, need, size = self._filed[lvl], self.traj.s, self._level_driven[lvl], self._levels[lvl]
        cells = self._cells[lvl]
        while j < self._n_indexed and s[n] - s[j] >= need:
            c = [math.floor(v / size) for v in self.traj.p[j].tolist()]
            cells[j] = c
            self._file(_cell_key(c), j, lvl)
            j += 1
        self._filed[lvl] = j

    def _driven_for_gate(self, gate: float) -> float:
        """The distance driven at which the drift gate first exceeds ``gate`` metres."""
        if self._sigmas * float(self.drift_sigma(1e7)) <= gate:
            return math.inf
        lo, hi = 0.0, 1e7
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if self._sigmas * float(self.drift_sigma(mid)) > gate:
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

    def refile(self, lo: int, stop: int) -> None:
        """Re-file frames lo .. stop-1 that a correction moved and that are already in the grids."""
        for lvl, size in enumerate(self._levels):
            hi = min(stop, self._filed[lvl])
            if hi > lo:
                cells, grid = self._cells[lvl], self._grids[lvl]
                new = np.floor(self.traj.p[lo:hi] / size).astype(np.int64)
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
