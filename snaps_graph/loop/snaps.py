"""SNAPS: similarity and location-based real-time loop closure (paper §III, eq. 6, Table I).

:class:`SnapsLoopCloser` owns the real-time *heuristic* trajectory. Per frame it composes the VO
step onto the previous, corrected pose, keeps the 1/6-scale thumbnail and, once the pause after
the last loop is over, compares up to ``attempts`` candidates (search.py) by UIQI; the loop is
picked by :meth:`~SnapsLoopCloser._try_close` and corrected by eq. 6 (correction.py). M, K and the
pause count processed frames (stream positions); :class:`LoopEvent` holds the caller's indices.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from time import perf_counter

import numpy as np

from ..config import LoopConfig, OdometryConfig
from ..drift_model import heading_sigma_deg
from ..errors import SnapsGraphError
from ..geometry import rotation_angle_deg, wrap_deg, yaw_deg
from ..types import CandidateRecord, LoopEvent
from .correction import Correction, discount, yaw_correction
from .search import CandidateSearch
from .uiqi import WindowStats, make_thumbnail, shifted_pair, similarity, similarity_q, similarity_shifted, window_stats

FOLLOW_TOL_M = 1.0  # a graph-only loop on verification alone must land this close to the track's prediction, m
FOLLOW_TOL_PER_M = 0.02  # ... plus this much per metre driven on both passes since the track's loop
FOLLOW_TOL_DEG = 3.0  # ... and turn this close, degrees

# Geometric verification, injected by the pipeline (loop/ never imports the front end):
# reference dataset index -> (T_ref_cur, inliers) or None.
Verifier = Callable[[int], "tuple[np.ndarray, int] | None"]


@dataclass
class SnapsStep:
    """What :meth:`SnapsLoopCloser.step` returns for one frame."""

    pose: np.ndarray  # 4x4 heuristic T_world_cam of this frame, after any correction
    loop: LoopEvent | None  # the loop closed at this frame, if any
    candidates: int  # similarities computed on this frame
    t_ms: float  # search, similarities and eq. 6, ms (not the thumbnail, the pose or verification)
    t_verify_ms: float = 0.0  # geometric verification time on this frame (tried or successful)


class SnapsLoopCloser(CandidateSearch, Correction):
    """Real-time SNAPS loop closer and owner of the heuristic trajectory (no I/O inside)."""

    def __init__(self, cfg: LoopConfig | None = None, odometry: OdometryConfig | None = None, pause_every: int = 1):
        """``pause_every``: in the pause, a graph-only loop is searched every this many frames
        (the verifier's reference spacing: loops measured against one stored reference share its
        errors, and the graph would count them as independent)."""
        if pause_every < 1:
            raise SnapsGraphError(f"SNAPS: pause_every must be >= 1, got {pause_every}")
        self.pause_every = int(pause_every)
        self.cfg = cfg if cfg is not None else LoopConfig()
        self.cfg.validate()
        self.odometry = odometry if odometry is not None else OdometryConfig()
        self.odometry.validate()
        self.drift_model = self.odometry.model()
        self._last_loop: tuple[int, int] | None = None  # (frame, reference) of the last verified loop
        self._track: tuple[int, int, np.ndarray] | None = None  # (frame, reference, T_ref_cur): the last verified loop
        self._speed = 0.0  # metres per frame number, running mean (see step)
        cap = 1024
        self._R = np.empty((cap, 3, 3))
        self._p = np.empty((cap, 3))
        self._yaw = np.empty(cap)
        self._index = np.empty(cap, dtype=np.int64)
        self._s = np.empty(cap)  # distance driven up to each frame (estimated), m
        self._n = 0  # frames processed
        self._init_search()
        self._thumbs: list[np.ndarray] = []
        self._stats: OrderedDict[int, WindowStats] = OrderedDict()
        self._last_pinned: int | None = None
        self._pause_from = 0  # the loop that started the current pause
        self._alpha = 0  # loops that corrected the trajectory (eq. 6's alpha)
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
                loop, computed = self._try_close(n, ids[pick], dists[pick], verify, follow=self._tracking(n, cadence=True))
        elif self.cfg.pause_graph_loops and (n - self._pause_from) % self.pause_every == 0:  # verified revisits for the graph
            ids, dists = self.search(n)
            if ids.size:
                a = self.cfg.attempts
                loop, computed = self._try_close(n, ids[:a], dists[:a], verify, in_pause=True)
        # Verification (tried or successful) is the graph's work, timed on its own.
        t_verify_ms, self._t_verify_ms = self._t_verify_ms, 0.0
        t_ms = (perf_counter() - t0) * 1e3 - t_verify_ms
        if loop is not None:
            loop.t_ms = t_ms
        return SnapsStep(pose=self.pose(n), loop=loop, candidates=computed, t_ms=t_ms, t_verify_ms=t_verify_ms)

    # ---- candidates ----
    def _tracking(self, n: int, cadence: bool = False) -> bool:
        """Whether frame n follows a verified revisit: a verified loop (of any kind) lies at most
        ``inter_frame_pause`` frames back, with graph-only loops allowed (``pause_graph_loops``);
        ``cadence``: and n is on the pause's cadence since that loop (a frame outside the pause)."""
        if not self.cfg.pause_graph_loops or self._track is None:
            return False
        age = n - self._track[0]
        return 0 < age <= self.cfg.inter_frame_pause and (not cadence or age % self.pause_every == 0)

    def _agrees(self, n: int, ref: int, T_ref_cur: np.ndarray) -> bool:
        """Whether a verified pose of n in ref agrees with the last verified loop carried along both
        passes (the estimate's relative poses since then): an aliased match lands elsewhere."""
        assert self._track is not None
        n0, r0, M0 = self._track
        W = self.pose
        pred = np.linalg.solve(W(ref), W(r0)) @ M0 @ np.linalg.solve(W(n0), W(n))
        E = np.linalg.solve(pred, np.asarray(T_ref_cur, float))
        driven = abs(self._s[n] - self._s[n0]) + abs(self._s[ref] - self._s[r0])
        tol_m = FOLLOW_TOL_M + FOLLOW_TOL_PER_M * driven
        return bool(np.linalg.norm(E[:3, 3]) <= tol_m and rotation_angle_deg(E) <= FOLLOW_TOL_DEG)

    def _first_verified(
        self, n: int, ids: np.ndarray, tries: list[int], verify: Verifier, outcome: dict, on_track: bool
    ) -> "tuple[int, tuple[np.ndarray, int]] | None":
        """Verify candidates ``tries`` in turn (each answer into ``outcome``): the first that verifies,
        and with ``on_track`` agrees with the track (:meth:`_agrees`), as (i, (T_ref_cur, inliers))."""
        for i in tries:
            outcome[i] = result = verify(int(self._index[int(ids[i])]))
            if result is not None and (not on_track or self._agrees(n, int(ids[i]), result[0])):
                return i, result
        return None

    def _try_close(
        self,
        n: int,
        ids: np.ndarray,
        dists: np.ndarray,
        verify: Verifier | None = None,
        in_pause: bool = False,
        follow: bool = False,
    ) -> tuple[LoopEvent | None, int]:
        """Compare candidates, pick the loop, correct (eq. 6). Those at or above ``min_similarity`` are
        verified highest Q first (at most ``verify_attempts``); the first that verifies is the loop, or,
        without a verifier or under ``require_verification = false``, the best Q. δ aims at p_ref, or with
        ``use_verified_offset`` at p_ref + R_ref·t_ref_cur. ``in_pause``: only a verified candidate makes
        a loop, and it goes to the graph without correcting. While a verified revisit is followed
        (:meth:`_tracking`; ``follow`` outside the pause), candidates below the threshold are verified
        too, and one that agrees with the track (:meth:`_agrees`) is a graph-only loop.
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
        graph_only = in_pause  # a loop for the factor graph only, the heuristic not corrected
        if passing:
            best = passing[0]
        tracking = follow or (in_pause and self._tracking(n))
        if verify is not None and (passing or tracking or self.cfg.verify_all_candidates):
            # Geometric verification of the best candidates in turn: the first that verifies is
            # the loop. With require_verification, none verifying means no loop (a same-place
            # assumption up to the radius away does more harm than a missed loop); otherwise the
            # paper's rule: the highest Q, unverified. verify_all_candidates verifies the rest
            # too, for the record only.
            tv = perf_counter()
            attempts = max(1, self.cfg.verify_attempts)
            hit = self._first_verified(n, ids, passing[:attempts], verify, outcome, on_track=False)
            if hit is None and tracking:
                # Along a verified revisit Q falls with traffic and light while the place is the
                # same: verification and the track's geometry decide, for the graph only.
                rest = [int(i) for i in order if int(i) not in outcome][:attempts]
                hit = self._first_verified(n, ids, rest, verify, outcome, on_track=True)
                graph_only = graph_only or hit is not None
            if self.cfg.verify_all_candidates:
                for i in order.tolist():
                    if i not in outcome:
                        outcome[i] = verify(int(self._index[int(ids[i])]))
            if hit is not None:
                best, (T_ref_cur, inliers) = hit
                verified = True
            t_verify_ms = (perf_counter() - tv) * 1e3
            self._t_verify_ms = t_verify_ms
        # A verified loop is taken; an unverified best Q only by the paper's rule, outside the pause.
        accept = verified or (bool(passing) and not in_pause and (verify is None or not self.cfg.require_verification))
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
        rotvec = None
        if verified and self.cfg.correction_rotation != "none" and not graph_only:
            gain = self._gain(float(heading_sigma_deg(self.drift_model, self._s[n] - self._s[ref])) ** 2)
            rotvec = yaw_correction(self._R[ref] @ np.asarray(T_ref_cur, float)[:3, :3] @ self._R[n].T) * gain
        # Eq. 6 weighs the move by Q: the confidence that N stands where the reference stood. A
        # verified loop measured where N stands, so with correction_weight = "verified" it moves
        # with weight 1 (gamma still discounts older poses); "q" is the paper's rule everywhere.
        weight = 1.0 if (verified and self.cfg.correction_weight == "verified") else sim.q
        if graph_only:
            # Correcting again re-bends what the last loop explained: the loop goes to the factor
            # graph only and the pause keeps running.
            weight, n_corrected, alpha = 0.0, 0, self._alpha
        else:
            self._alpha = alpha = self._alpha + 1
            n_corrected = self._correct(n, weight, delta, alpha, rotvec, first=ref + 1)
            self._last_pinned = self._pause_from = n
            if verified:  # the search's uncertainty restarts from this measurement
                self._last_loop = (n, ref)
        if verified:
            self._track = (n, ref, np.asarray(T_ref_cur, float).copy())
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
