"""Loops between the run and its prior sessions (the paper's search, across sessions).

Until a prior is relocalised its frames are found by appearance (:meth:`PriorMap.shortlist`, then
UIQI); after, near the current position under the same gate as the run's own frames, with the
distance driven counted through the last verified match between the two sessions. Every loop
across sessions is verified: no same-place assumption bridges two sessions.
"""

from __future__ import annotations

from dataclasses import dataclass
from time import perf_counter
from typing import Protocol

import numpy as np

from ..geometry import wrap_deg
from .prior import PriorMap, gist
from .search import CandidateIndex
from .trajectory import Trajectory
from .uiqi import Thumbnails, similarity_q

# Verifications per frame and prior before relocalisation: bounds the cost of a frame that looks
# like many prior frames (the best Q first).
APPEARANCE_VERIFY = 1


class PriorVerifier(Protocol):
    """Geometric verification against a prior session's frames too."""

    def verify(self, reference: int, prior: int | None = None) -> tuple[np.ndarray, int] | None:
        """(T_ref_cur, inliers) of the current frame in frame number ``reference`` of prior
        ``prior`` (None: of the run itself), or None."""
        ...


@dataclass
class CrossMatch:
    """A verified match of the current frame to a prior frame."""

    prior: int  # index of the prior
    j: int  # the prior's stream position
    T_ref_cur: np.ndarray  # the current frame in the prior frame's camera
    inliers: int
    candidates: int  # similarities computed on this frame, all priors
    t_verify_ms: float
    relocalised: bool  # this match relocalised the run against the prior
    graph_only: bool = False  # found in the pause after a correction: for the graph only


class CrossSession:
    """The search over the priors for one run: :meth:`detect` per frame."""

    def __init__(
        self,
        priors: list[PriorMap],
        traj: Trajectory,
        thumbs: Thumbnails,
        index: CandidateIndex,
        verifier: PriorVerifier,
        pause_every: int = 1,
    ):
        """As :class:`SnapsLoopCloser`: the run's trajectory, thumbnails and candidate index (its
        rule and gates serve the priors too); in the pause after a correction, graph-only loops
        every ``pause_every`` frames (the verifier's reference spacing) under ``pause_graph_loops``."""
        self.priors, self.traj, self.thumbs, self.index = priors, traj, thumbs, index
        self.cfg, self.policy, self.verifier = index.cfg, index.policy, verifier
        self.pause_every = pause_every

    def detect(self, n: int) -> tuple[CrossMatch | None, int, float]:
        """The first verified match of frame ``n`` over the priors (None), similarities computed,
        verification time in ms."""
        computed, t_verify = 0, 0.0
        g: np.ndarray | None = None
        for i, prior in enumerate(self.priors):
            graph_only = False
            if prior.relocalised:
                age = n - prior.pause_from
                graph_only = age <= self.cfg.inter_frame_pause
                if graph_only and not (self.policy.pause_graph_loops and age % self.pause_every == 0):
                    continue
                ids, tries = self.near(n, prior), self.policy.verify_attempts
            else:
                g = gist(self.thumbs[n]) if g is None else g
                ids, tries = prior.shortlist(g), APPEARANCE_VERIFY
            if not ids.size:
                continue
            cur = self.thumbs.stats(n)
            qs = np.array([similarity_q(cur, prior.thumbs.stats(int(j))) for j in ids])
            computed += len(ids)
            order = [int(o) for o in np.argsort(-qs, kind="stable") if qs[o] >= self.cfg.min_similarity][:tries]
            match, dt = self._verify(n, i, prior, [int(ids[o]) for o in order])
            t_verify += dt
            if match is not None:
                match.candidates, match.t_verify_ms, match.graph_only = computed, t_verify, graph_only
                return match, computed, t_verify
        return None, computed, t_verify

    def _verify(self, n: int, i: int, prior: PriorMap, js: list[int]) -> tuple[CrossMatch | None, float]:
        """Verify prior frames ``js`` in turn: the first that verifies (and, before relocalisation,
        confirms an earlier match) as a match; the time spent, ms."""
        t0 = perf_counter()
        for j in js:
            res = self.verifier.verify(int(prior.frame_ids[j]), prior=i)
            if res is None:
                continue
            T_ref_cur, inliers = np.asarray(res[0], float), int(res[1])
            relocalised = False
            if not prior.relocalised:
                T = prior.transform(j, T_ref_cur, self.traj.pose(n))
                if not prior.offer(n, j, T, float(self.traj.s[n])):
                    break  # remembered; the relocalisation waits for a confirming match
                relocalised = True
            return CrossMatch(i, j, T_ref_cur, inliers, 0, 0.0, relocalised), (perf_counter() - t0) * 1e3
        return None, (perf_counter() - t0) * 1e3

    def driven(self, n: int, prior: PriorMap, ids: np.ndarray) -> np.ndarray:
        """Metres of odometry between own frame ``n`` and prior frames ``ids``, through the last
        verified match between the two sessions."""
        assert prior.anchor is not None
        return (self.traj.s[n] - self.traj.s[prior.anchor[0]]) + prior.driven_since_anchor(ids)

    def near(self, n: int, prior: PriorMap) -> np.ndarray:
        """Prior frames within the gates of own frame ``n`` (:meth:`CandidateIndex.admit`),
        nearest first, at most ``attempts``."""
        p = self.traj.p[n]
        ids = prior.near(p, self.index.reach)
        if not ids.size:
            return ids
        d = np.linalg.norm(prior.p[ids] - p, axis=1)
        ok, m = self.index.admit(d, wrap_deg(prior.yaw[ids] - self.traj.yaw[n]), self.driven(n, prior, ids))
        ids, m = ids[ok], m[ok]
        return ids[np.lexsort((ids, m))][: self.policy.attempts]


__all__ = ["APPEARANCE_VERIFY", "CrossMatch", "CrossSession", "PriorVerifier"]
