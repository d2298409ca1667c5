"""SNAPS: similarity and location-based real-time loop closure (paper §III, eq. 6, Table I).

:class:`SnapsLoopCloser` composes the heuristic trajectory (trajectory.py), the candidate index
over it (search.py), the thumbnails (uiqi.py), eq. 6 (correction.py) and a verifier given at
construction; the rule is a named :class:`~snaps_graph.loop.policy.LoopPolicy`. Per frame it
composes the VO step onto the previous, corrected pose, keeps the thumbnail and, once the pause
after the last loop is over, compares up to ``attempts`` candidates by UIQI, picks the loop and
corrects. M, K and the pause count processed frames (stream positions); :class:`LoopEvent`
holds the caller's frame numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from time import perf_counter
from typing import Protocol, cast

import numpy as np

from ..config import LoopConfig, OdometryConfig
from ..drift_model import heading_sigma_deg
from ..errors import SnapsGraphError
from ..geometry import rotation_angle_deg, wrap_deg
from ..types import CandidateRecord, LoopEvent
from .correction import correct, verified_gain, window_length, yaw_correction
from .cross import CrossMatch, CrossSession, PriorVerifier
from .policy import POLICIES, LoopPolicy
from .prior import PriorMap
from .search import CandidateIndex
from .trajectory import Trajectory
from .uiqi import UIQI, Thumbnails, WindowStats, make_thumbnail, similarity, similarity_q, thumbnail_shape, window_stats

FOLLOW_TOL_M = 1.0  # a graph-only loop on verification alone must land this close to the track's prediction, m
FOLLOW_TOL_PER_M = 0.02  # ... plus this much per metre driven on both passes since the track's loop
FOLLOW_TOL_DEG = 3.0  # ... and turn this close, degrees


class Verifier(Protocol):
    """Geometric verification of a candidate against the current frame (loop/ never imports the
    front end: the pipeline gives one, e.g. :class:`snaps_graph.verification.LoopVerifier`)."""

    def verify(self, reference: int) -> tuple[np.ndarray, int] | None:
        """(T_ref_cur, inliers) of the current frame in dataset frame ``reference``, or None.
        With prior sessions it must also take ``prior`` (:class:`~snaps_graph.loop.cross.PriorVerifier`)."""
        ...


@dataclass
class SnapsStep:
    """What :meth:`SnapsLoopCloser.step` returns for one frame."""

    pose: np.ndarray  # 4x4 heuristic T_world_cam of this frame, after any correction
    loop: LoopEvent | None  # the loop closed at this frame, if any
    candidates: int  # similarities computed on this frame
    t_ms: float  # search, similarities and eq. 6, ms (not the thumbnail, the pose or verification)
    t_verify_ms: float = 0.0  # geometric verification time on this frame (tried or successful)


@dataclass
class Choice:
    """What the comparison of one frame's candidates decided (indices into its candidates)."""

    best: int = -1  # the loop's candidate (highest Q above the threshold, or the verified one)
    accept: bool = False  # the loop is taken
    verified: bool = False
    T_ref_cur: np.ndarray | None = None
    inliers: int = 0
    graph_only: bool = False  # a loop for the factor graph only, the heuristic not corrected
    t_verify_ms: float = 0.0
    # The verifier's answer per candidate tried (absent: not tried).
    outcome: dict[int, tuple[np.ndarray, int] | None] = field(default_factory=dict)


class SnapsLoopCloser:
    """Real-time SNAPS loop closer and owner of the heuristic trajectory (no I/O inside)."""

    def __init__(
        self,
        cfg: LoopConfig | None = None,
        odometry: OdometryConfig | None = None,
        pause_every: int = 1,
        verifier: Verifier | None = None,
        policy: LoopPolicy | None = None,
        priors: list[PriorMap] | None = None,
    ):
        """``pause_every``: in the pause, a graph-only loop is searched every this many frames
        (the verifier's reference spacing: loops measured against one stored reference share its
        errors, and the graph would count them as independent). ``verifier``: geometric
        verification (None: loops by Q alone). ``policy``: the rule (default ``cfg.policy``).
        ``priors``: earlier sessions to relocalise against and close loops with (needs ``verifier``)."""
        if pause_every < 1:
            raise SnapsGraphError(f"SNAPS: pause_every must be >= 1, got {pause_every}")
        self.pause_every = int(pause_every)
        self.cfg = cfg if cfg is not None else LoopConfig()
        self.cfg.validate()
        self.odometry = odometry if odometry is not None else OdometryConfig()
        self.odometry.validate()
        self.policy = policy if policy is not None else POLICIES[self.cfg.policy]
        self.verifier = verifier
        self.drift_model = self.odometry.model()
        self.traj = Trajectory()
        self.index = CandidateIndex(self.traj, self.cfg, self.policy, self.drift_model)
        self.thumbs = Thumbnails(self.cfg.window)
        self.priors = list(priors or [])
        self.cross = self._cross_session(verifier) if self.priors else None
        self._track: tuple[int, int, np.ndarray] | None = None  # (frame, reference, T_ref_cur): the last verified loop
        self._last_pinned: int | None = None
        self._pause_from = 0  # the loop that started the current pause
        self._alpha = 0  # loops that corrected the trajectory (eq. 6's alpha)
        self._loops: list[LoopEvent] = []
        # One tuple per compared candidate (types.CandidateRecord, built at the end): (n, j, distance,
        # yaw difference, Q, above threshold, verification tried, passed, inliers, accepted), stream positions.
        self._cand: list[tuple] = []

    def _cross_session(self, verifier: Verifier | None) -> CrossSession:
        """The search over the priors, sharing this closer's trajectory, thumbnails and rule."""
        if verifier is None:
            raise SnapsGraphError("SNAPS: loops with prior sessions need a verifier")
        return CrossSession(self.priors, self.traj, self.thumbs, self.index, cast(PriorVerifier, verifier), self.pause_every)

    # ---- accessors ----
    def __len__(self) -> int:
        return len(self.traj)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) heuristic trajectory T_world_cam (a copy)."""
        return self.traj.poses()

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) heuristic positions (a copy)."""
        return self.traj.p[: len(self.traj)].copy()

    @property
    def indices(self) -> np.ndarray:
        """(N,) the caller's frame index of each processed frame (stream position -> dataset index)."""
        return self.traj.index[: len(self.traj)].copy()

    @property
    def loops(self) -> list[LoopEvent]:
        return list(self._loops)

    @property
    def last_pinned(self) -> int | None:
        """Stream position of the last pinned frame (None before the first loop)."""
        return self._last_pinned

    def thumbnail(self, k: int) -> np.ndarray:
        """Thumbnail of the frame at stream position ``k`` (uint8 for uint8 input)."""
        return self.thumbs[k]

    def pose(self, k: int) -> np.ndarray:
        return self.traj.pose(k)

    # ---- the per-frame step ----
    def check_image(self, index: int, shape: tuple[int, ...]) -> None:
        """SnapsGraphError unless an image of ``shape`` can be compared: its thumbnail has the
        first frame's size and holds the UIQI window. :meth:`step` assumes this was checked."""
        th, tw = thumbnail_shape(shape, self.cfg.thumbnail_scale)
        if len(self.thumbs) and (th, tw) != self.thumbs[0].shape:
            raise SnapsGraphError(f"SNAPS: frame {index}: image size {shape[1]}x{shape[0]} differs from the first frame's")
        if min(th, tw) < self.cfg.window:
            raise SnapsGraphError(
                f"frame {index}: image {shape[1]}x{shape[0]} is too small for SNAPS: its thumbnail ({tw}x{th} at "
                f"loop.thumbnail_scale = {self.cfg.thumbnail_scale:g}) is smaller than loop.window = {self.cfg.window}"
            )

    def step(self, index: int, T_rel: np.ndarray, left: np.ndarray) -> SnapsStep:
        """Process one frame: compose the pose, store the thumbnail, detect and close a loop.

        ``T_rel`` is T_prev_cur from the VO (ignored for the first frame, which is the identity);
        ``left`` is the full left grey image, checked by :meth:`check_image`. Raises
        SnapsGraphError for a non-finite or malformed ``T_rel``.
        """
        thumb = make_thumbnail(left, self.cfg.thumbnail_scale)
        n = self.traj.append(index, T_rel)
        self.thumbs.append(thumb)
        t0 = perf_counter()
        self.index.add(n)
        loop, computed, t_verify_ms = self._detect(n)
        if loop is None and self.cross is not None:
            match, more, t_more = self.cross.detect(n)
            computed, t_verify_ms = computed + more, t_verify_ms + t_more
            if match is not None:
                loop = self._close_prior(n, match)
        # Verification (tried or successful) is the graph's work, timed on its own.
        t_ms = (perf_counter() - t0) * 1e3 - t_verify_ms
        if loop is not None:
            loop.t_ms = t_ms
        return SnapsStep(pose=self.pose(n), loop=loop, candidates=computed, t_ms=t_ms, t_verify_ms=t_verify_ms)

    def _detect(self, n: int) -> tuple[LoopEvent | None, int, float]:
        """Search and compare outside the pause; inside it (``pause_graph_loops``), on the
        verifier's reference spacing, verified revisits for the graph only."""
        if self._last_pinned is None or n - self._pause_from > self.cfg.inter_frame_pause:
            ids, dists = self.index.search(n)
            if ids.size:
                pick = self.index.pick(len(ids))
                return self._try_close(n, ids[pick], dists[pick], follow=self._tracking(n, cadence=True))
        elif self.policy.pause_graph_loops and (n - self._pause_from) % self.pause_every == 0:
            ids, dists = self.index.search(n)
            if ids.size:
                a = self.policy.attempts
                return self._try_close(n, ids[:a], dists[:a], in_pause=True)
        return None, 0, 0.0

    # ---- candidates ----
    def _tracking(self, n: int, cadence: bool = False) -> bool:
        """Whether frame n follows a verified revisit: a verified loop (of any kind) lies at most
        ``inter_frame_pause`` frames back, with graph-only loops allowed (``pause_graph_loops``);
        ``cadence``: and n is on the pause's cadence since that loop (a frame outside the pause)."""
        if not self.policy.pause_graph_loops or self._track is None:
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
        s = self.traj.s
        driven = abs(s[n] - s[n0]) + abs(s[ref] - s[r0])
        tol_m = FOLLOW_TOL_M + FOLLOW_TOL_PER_M * driven
        return bool(np.linalg.norm(E[:3, 3]) <= tol_m and rotation_angle_deg(E) <= FOLLOW_TOL_DEG)

    def _first_verified(self, n: int, ids: np.ndarray, tries: list[int], outcome: dict, on_track: bool):
        """Verify candidates ``tries`` in turn (each answer into ``outcome``): the first that verifies,
        and with ``on_track`` agrees with the track (:meth:`_agrees`), as (i, (T_ref_cur, inliers))."""
        assert self.verifier is not None
        for i in tries:
            outcome[i] = result = self.verifier.verify(int(self.traj.index[int(ids[i])]))
            if result is not None and (not on_track or self._agrees(n, int(ids[i]), result[0])):
                return i, result
        return None

    def _try_close(
        self, n: int, ids: np.ndarray, dists: np.ndarray, in_pause: bool = False, follow: bool = False
    ) -> tuple[LoopEvent | None, int, float]:
        """Compare candidates by Q, pick the loop (:meth:`_choose`), correct (:meth:`_close`).
        Returns (the loop or None, similarities computed, verification time in ms)."""
        cur = self.thumbs.stats(n)
        qs = np.array([similarity_q(cur, self.thumbs.stats(int(j))) for j in ids])
        # Candidates at or above the threshold, highest Q first (stable: nearer first on ties).
        order = np.argsort(-qs, kind="stable")
        passing = [int(i) for i in order if qs[i] >= self.cfg.min_similarity]
        c = self._choose(n, ids, order, passing, tracking=follow or (in_pause and self._tracking(n)), in_pause=in_pause)
        self._record(n, ids, dists, qs, c.outcome, c.best if c.accept else -1)
        if not c.accept:
            return None, len(ids), c.t_verify_ms
        return self._close(n, ids, dists[c.best], cur, c), len(ids), c.t_verify_ms

    def _choose(self, n: int, ids: np.ndarray, order: np.ndarray, passing: list[int], tracking: bool, in_pause: bool) -> Choice:
        """Those at or above ``min_similarity`` are verified highest Q first (at most
        ``verify_attempts``); the first that verifies is the loop, or, without a verifier or when
        the policy does not require verification, the best Q. ``in_pause``: only a verified
        candidate makes a loop, for the graph only. While a verified revisit is followed
        (``tracking``), candidates below the threshold are verified too, and one that agrees with
        the track (:meth:`_agrees`) is a graph-only loop: Q falls with traffic and light while the
        place is the same."""
        c = Choice(best=passing[0] if passing else -1, graph_only=in_pause)
        if self.verifier is not None and (passing or tracking):
            tv = perf_counter()
            attempts = max(1, self.policy.verify_attempts)
            hit = self._first_verified(n, ids, passing[:attempts], c.outcome, on_track=False)
            if hit is None and tracking:
                rest = [int(i) for i in order if int(i) not in c.outcome][:attempts]
                hit = self._first_verified(n, ids, rest, c.outcome, on_track=True)
                c.graph_only = c.graph_only or hit is not None
            if hit is not None:
                c.best, (c.T_ref_cur, c.inliers) = hit
                c.verified = True
            c.t_verify_ms = (perf_counter() - tv) * 1e3
        # A verified loop is taken; an unverified best Q only by the paper's rule, outside the pause
        # (a same-place assumption up to the radius away does more harm than a missed loop).
        unverified_ok = not in_pause and (self.verifier is None or not self.policy.require_verification)
        c.accept = c.verified or (bool(passing) and unverified_ok)
        return c

    # ---- the loop ----
    def _close(self, n: int, ids: np.ndarray, distance_m: float, cur: WindowStats, c: Choice) -> LoopEvent:
        """Correct by eq. 6 toward the chosen candidate (a graph-only loop corrects nothing: the
        last loop already explained what it would re-bend) and record the loop."""
        ref = int(ids[c.best])
        sim = similarity(cur, self.thumbs.stats(ref))
        delta, rotvec = self._offset(n, ref, c)
        # Eq. 6 weighs the move by Q: the confidence that N stands where the reference stood. A
        # verified loop measured where N stands: under the drift policy it moves with weight 1.
        weight = 1.0 if (c.verified and self.policy.correction_weight == "verified") else sim.q
        if c.graph_only:
            weight, n_corrected, alpha = 0.0, 0, self._alpha
        else:
            self._alpha = alpha = self._alpha + 1
            n_corrected = self._correct(n, ref, weight, delta, alpha, rotvec)
            self._last_pinned = self._pause_from = n
            if c.verified:  # the search's uncertainty restarts from this measurement
                self.index.last_loop = (n, ref)
        if c.verified:
            self._track = (n, ref, np.asarray(c.T_ref_cur, float).copy())
        event = self._event(n, ref, distance_m, sim, delta, c, weight, n_corrected, alpha, len(ids))
        self._loops.append(event)
        return event

    def _offset(self, n: int, ref: int, c: Choice) -> tuple[np.ndarray, np.ndarray | None]:
        """Eq. 6's δ (toward p_ref, or where verification puts N under ``use_verified_offset``)
        and, for a verified loop that corrects, the turn toward the verified heading."""
        R, p = self.traj.R, self.traj.p
        target = p[ref].copy()
        if c.verified and self.policy.use_verified_offset:
            target = target + R[ref] @ np.asarray(c.T_ref_cur, float)[:3, 3]
        delta = target - p[n]
        if self.policy.correction_axes == "ground":  # the reference's height error stays out
            delta[1] = 0.0
        if not c.verified or self.policy.correction_rotation == "none" or c.graph_only:
            return delta, None
        gain = verified_gain(self.policy, float(heading_sigma_deg(self.drift_model, self.traj.s[n] - self.traj.s[ref])) ** 2)
        return delta, yaw_correction(R[ref] @ np.asarray(c.T_ref_cur, float)[:3, :3] @ R[n].T) * gain

    def _correct(self, n: int, ref: int, weight: float, delta: np.ndarray, alpha: int, rotvec: np.ndarray | None) -> int:
        """Eq. 6 over [max(N − K, ref + 1), N] (the reference and older frames are the loop's anchor
        and never move); the moved frames are re-filed in the index. Returns how many moved."""
        first = ref + 1
        lo = max(0, n - window_length(self.policy, self.cfg.discount_length, n - first + 1), first)
        moved = correct(self.traj, self.policy, self.drift_model, (lo, n), delta, weight, alpha, rotvec)
        self.index.refile(lo, n + 1)
        return moved

    def _close_prior(self, n: int, m: CrossMatch) -> LoopEvent:
        """A verified loop to a prior frame: the relocalising one only places the prior (nothing
        to correct); a later one corrects by eq. 6 toward where the prior puts frame n, over the
        window since the last match with that prior (its anchor)."""
        prior = self.priors[m.prior]
        target = prior.pose_own(m.j) @ m.T_ref_cur
        sim = similarity(self.thumbs.stats(n), prior.thumbs.stats(m.j))
        delta = target[:3, 3] - self.traj.p[n]
        weight, moved = 0.0, 0
        if not (m.relocalised or m.graph_only):
            if self.policy.correction_axes == "ground":
                delta[1] = 0.0
            rotvec = None
            if self.policy.correction_rotation != "none":
                D = float(self.cross.driven(n, prior, np.array([m.j]))[0]) if self.cross else 0.0
                gain = verified_gain(self.policy, float(heading_sigma_deg(self.drift_model, D)) ** 2)
                rotvec = yaw_correction(target[:3, :3] @ self.traj.R[n].T) * gain
            first = prior.pause_from + 1
            lo = max(0, n - window_length(self.policy, self.cfg.discount_length, n - first + 1), first)
            self._alpha += 1
            weight, moved = 1.0, correct(self.traj, self.policy, self.drift_model, (lo, n), delta, 1.0, self._alpha, rotvec)
            self.index.refile(lo, n + 1)
            self._last_pinned = self._pause_from = prior.pause_from = n
        prior.anchor = (n, m.j)
        c = Choice(best=0, accept=True, verified=True, T_ref_cur=m.T_ref_cur, inliers=m.inliers, t_verify_ms=m.t_verify_ms)
        event = self._event(
            n, n, float(np.linalg.norm(m.T_ref_cur[:3, 3])), sim, delta, c, weight, moved, self._alpha, m.candidates
        )
        event.reference, event.session, event.prior, event.relocalised = (
            int(prior.frame_ids[m.j]),
            prior.name,
            m.prior,
            m.relocalised,
        )
        event.yaw_diff_deg = float(wrap_deg(prior.yaw[m.j] - self.traj.yaw[n]))
        self._loops.append(event)
        return event

    def _event(
        self,
        n: int,
        ref: int,
        distance_m: float,
        sim: UIQI,
        delta: np.ndarray,
        c: Choice,
        weight: float,
        moved: int,
        alpha: int,
        candidates: int,
    ) -> LoopEvent:
        index, yaw = self.traj.index, self.traj.yaw
        return LoopEvent(
            frame=int(index[n]),
            reference=int(index[ref]),
            distance_m=float(distance_m),
            yaw_diff_deg=float(wrap_deg(yaw[ref] - yaw[n])),
            q=sim.q,
            correlation=sim.correlation,
            luminance=sim.luminance,
            contrast=sim.contrast,
            delta=delta.copy(),
            n_corrected=moved,
            alpha=alpha,
            candidates=candidates,
            t_ms=0.0,  # set by step() once the frame's detection + correction is over
            verified=c.verified,
            weight=float(weight),
            verify_inliers=int(c.inliers),
            T_ref_cur=None if c.T_ref_cur is None else np.asarray(c.T_ref_cur, float).copy(),
            t_verify_ms=c.t_verify_ms,
        )

    # ---- records ----
    def _record(self, n: int, ids: np.ndarray, dists: np.ndarray, qs: np.ndarray, outcome: dict, accepted: int) -> None:
        """Append one tuple per compared candidate (no formatting; types.CandidateRecord at the end)."""
        yaw_n = float(self.traj.yaw[n])
        yaws = self.traj.yaw
        thr = self.cfg.min_similarity
        app = self._cand.append
        for i, j in enumerate(ids.tolist()):
            res = outcome.get(i, False)
            app(
                (n, j, float(dists[i]), float(yaws[j]) - yaw_n, float(qs[i]), bool(qs[i] >= thr))
                + (res is not False, bool(res), res[1] if res else 0, i == accepted)
            )

    def candidate_records(self) -> list[CandidateRecord]:
        """Every similarity computed so far as :class:`CandidateRecord` (dataset frame indices),
        with Q's three factors computed now from the stored thumbnails."""
        out = []
        stats: dict[int, WindowStats] = {}

        def st(k: int) -> WindowStats:
            if k not in stats:
                stats[k] = self.thumbs.cached(k) or window_stats(self.thumbs[k], self.cfg.window)
            return stats[k]

        index = self.traj.index
        for n, j, d, dyaw, q, above, tried, passed, inl, acc in self._cand:
            sim = similarity(st(n), st(j))
            out.append(
                CandidateRecord(
                    frame=int(index[n]),
                    reference=int(index[j]),
                    distance_m=d,
                    yaw_diff_deg=float(wrap_deg(dyaw)),
                    q=q,
                    correlation=sim.correlation,
                    luminance=sim.luminance,
                    contrast=sim.contrast,
                    shift_px=0,
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


__all__ = ["Choice", "SnapsLoopCloser", "SnapsStep", "Verifier"]
