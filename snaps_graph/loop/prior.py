"""A prior session as the loop closer sees it: earlier frames to find by appearance, then by location.

Between two sessions there is no common frame until a first verified match, so until then a frame
is compared with every prior frame by appearance alone: a coarse normalised thumbnail ranks the
prior frames (one matrix product), the best few are compared by UIQI, and those above the threshold
go to verification. A relocalisation is taken once two verified matches agree on the
session-to-session transform; from then on the prior's frames are searched by location, in the
run's own frame, as the run's own frames are. No I/O: the arrays come from ``session``.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..geometry import inv, rotation_angle_deg, yaw_deg
from .uiqi import Thumbnails

# The coarse appearance vector: the thumbnail area-averaged to this many (rows, columns), zero
# mean and unit norm. Coarse enough to forgive a lane's shift, fine enough to rank streets apart.
GIST_SHAPE = (6, 20)
# Prior frames ranked first by the coarse vector that are compared by UIQI, per prior and frame.
APPEARANCE_SHORTLIST = 5
# A relocalisation needs this many verified matches that agree on the transform ...
CONFIRMATIONS = 2
# ... within this many frames of each other ...
CONFIRM_FRAMES = 20
# ... and this close: metres plus a share of the distance driven between them, and degrees.
AGREE_M = 1.5
AGREE_PER_M = 0.02
AGREE_DEG = 3.0
# Window sums of prior thumbnails kept per prior (a revisit asks for the same frames again).
STATS_CACHE_FRAMES = 256


def gist(thumb: np.ndarray) -> np.ndarray:
    """The coarse appearance vector of one thumbnail (float32, unit norm; zeros for a flat one)."""
    g = cv2.resize(np.asarray(thumb, np.float32), GIST_SHAPE[::-1], interpolation=cv2.INTER_AREA).ravel()
    g -= g.mean()
    norm = float(np.linalg.norm(g))
    return g / norm if norm > 0.0 else g


class PriorMap:
    """One prior session's frames: poses in the prior's frame, thumbnails, distance driven.

    ``T_own_prior`` is None until the run relocalises; then ``p``/``yaw`` hold the prior's
    positions and headings in the run's own frame and :meth:`near` searches them.
    """

    def __init__(self, name: str, poses: np.ndarray, driven: np.ndarray, frame_ids: np.ndarray, thumbs: np.ndarray, window: int):
        self.name = name
        self.poses = poses  # (N, 4, 4) T_prior_cam
        self.driven = np.asarray(driven, float)
        self.frame_ids = np.asarray(frame_ids, np.int64)
        # (N, h, w), read lazily when memory-mapped; their window sums cached as the run's own.
        self.thumbs = Thumbnails(window, thumbs, STATS_CACHE_FRAMES)
        self.gists = (
            np.stack([gist(t) for t in thumbs]) if len(thumbs) else np.zeros((0, GIST_SHAPE[0] * GIST_SHAPE[1]), np.float32)
        )
        self.T_own_prior: np.ndarray | None = None
        self.anchor: tuple[int, int] | None = None  # (own stream position, prior position) of the last verified match
        self.pause_from = 0  # own stream position of the last match that moved the trajectory (or relocalised)
        self.pending: list[tuple[int, float, np.ndarray]] = []  # (n, driven, T_own_prior) not yet confirmed
        self.p = np.zeros((0, 3))
        self.yaw = np.zeros(0)
        self._tree: cKDTree | None = None

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def relocalised(self) -> bool:
        return self.T_own_prior is not None

    def shortlist(self, g: np.ndarray) -> np.ndarray:
        """The prior frames most alike ``g`` (a :func:`gist`), best first."""
        if not len(self.gists):
            return np.zeros(0, np.int64)
        score = self.gists @ g
        k = min(APPEARANCE_SHORTLIST, len(score))
        top = np.argpartition(-score, k - 1)[:k]
        return top[np.argsort(-score[top], kind="stable")].astype(np.int64)

    def transform(self, j: int, T_ref_cur: np.ndarray, own_pose: np.ndarray) -> np.ndarray:
        """T_own_prior implied by a verified match of own frame ``own_pose`` to prior frame ``j``."""
        return own_pose @ inv(T_ref_cur) @ inv(self.poses[j])

    def offer(self, n: int, j: int, T_own_prior: np.ndarray, driven_n: float) -> bool:
        """A verified appearance match at own position ``n`` to prior frame ``j``: True once it
        confirms earlier ones (the run is then relocalised with it). Two transforms agree when
        they put prior frame ``j`` at nearly the same pose (compared at the place, not at the
        prior's origin, where a small turn becomes a large offset)."""
        self.pending = [m for m in self.pending if n - m[0] <= CONFIRM_FRAMES]
        here = T_own_prior @ self.poses[j]
        agreeing = 0
        for _, driven_m, T in self.pending:
            E = inv(T @ self.poses[j]) @ here
            tol_m = AGREE_M + AGREE_PER_M * abs(driven_n - driven_m)
            agreeing += bool(np.linalg.norm(E[:3, 3]) <= tol_m and rotation_angle_deg(E) <= AGREE_DEG)
        self.pending.append((n, driven_n, T_own_prior))
        if agreeing + 1 < CONFIRMATIONS:
            return False
        self.relocalise(T_own_prior, (n, j))
        return True

    def relocalise(self, T_own_prior: np.ndarray, anchor: tuple[int, int] | None) -> None:
        """Place the prior in the run's own frame and index its positions there."""
        self.T_own_prior = np.array(T_own_prior, float)
        self.anchor = anchor
        self.pause_from = anchor[0] if anchor is not None else 0
        self.pending = []
        own = self.T_own_prior @ self.poses
        self.p = own[:, :3, 3].copy()
        self.yaw = np.array([yaw_deg(R) for R in own[:, :3, :3]])
        self._tree = cKDTree(self.p)

    def position(self, frame: int) -> int:
        """The stream position of the prior's frame number ``frame`` (frame numbers increase)."""
        j = int(np.searchsorted(self.frame_ids, frame))
        if j >= len(self.frame_ids) or self.frame_ids[j] != frame:
            raise KeyError(f"frame {frame} is not in prior {self.name}")
        return j

    def pose_own(self, j: int) -> np.ndarray:
        """Prior frame ``j``'s pose in the run's own frame (after relocalisation)."""
        assert self.T_own_prior is not None
        return self.T_own_prior @ self.poses[j]

    def near(self, p: np.ndarray, radius: float) -> np.ndarray:
        """Prior frames within ``radius`` m of ``p`` (own frame), ascending."""
        if self._tree is None:
            return np.zeros(0, np.int64)
        return np.array(sorted(self._tree.query_ball_point(p, radius)), dtype=np.int64)

    def driven_since_anchor(self, j: np.ndarray) -> np.ndarray:
        """Metres driven in the prior between frames ``j`` and the anchor's prior frame."""
        assert self.anchor is not None
        return np.abs(self.driven[j] - self.driven[self.anchor[1]])
