"""The loop closer's verifier: does a candidate show the place the current frame shows, and where
from? It holds the loop features (stereo, or two-view without a right image), is told each frame
(:meth:`LoopVerifier.observe`) and answers :meth:`LoopVerifier.verify` for the loop closer.
"""

from __future__ import annotations

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig, VerificationConfig
from ..types import StereoFrame, VOResult
from .features import MAX_DISTANCE_M, REFERENCE_EVERY, LoopFeatureBank, verify_features
from .mono import MonoFeatureBank, two_view_covariance


class LoopVerifier:
    """Geometric verification against the frame last given to :meth:`observe`.

    The stored reference nearest to the candidate is verified (with the current frame's stereo
    depth check when it has a right image) and the result carried to the candidate by the VO poses
    between the two (at most a few frames). A verified loop's covariance is kept for its factor
    (:meth:`covariance`); an exception is recorded in ``failures`` as (k, reason), never raised.
    """

    # In the pause, a graph-only loop is searched every this many frames: loops measured against
    # one stored reference share its errors, and the graph would count them as independent.
    reference_every = REFERENCE_EVERY

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, vcfg: VerificationConfig):
        self.camera, self.cfg, self.vcfg = camera, cfg, vcfg
        self.bank: LoopFeatureBank | None = None  # set by start(): stereo or two-view features
        self.monocular = False
        self.failures: list[tuple[int, str]] = []
        self._k_of_frame: dict[int, int] = {}
        self._vo_poses: list[np.ndarray] = []
        self._current: tuple[int, StereoFrame, float] | None = None  # (k, frame, disparity offset)
        self._cov: dict[tuple[int | None, int], np.ndarray] = {}  # (prior, reference frame) -> covariance, this frame's loops
        self._priors: list[tuple[LoopFeatureBank, dict[int, int], np.ndarray]] = []  # add_prior()

    def start(self, monocular: bool) -> None:
        """At the first frame: stereo features, or two-view ones for a run without right images."""
        self.monocular = monocular
        bank = MonoFeatureBank if monocular else LoopFeatureBank
        self.bank = bank(self.camera, self.cfg, self.vcfg)

    def observe(self, k: int, frame: StereoFrame, vo: VOResult) -> None:
        """Take stream position ``k``: its reference features if it is one; the frame to verify."""
        assert self.bank is not None, "start() first"
        self._k_of_frame[int(frame.index)] = k
        self._vo_poses.append(vo.pose)
        if isinstance(self.bank, MonoFeatureBank):
            self.bank.observe(k, frame, vo.pose)
        else:
            self.bank.add(k, frame, vo.disparity_offset_px)
        self._current = (k, frame, vo.disparity_offset_px)
        self._cov.clear()

    def covariance(self, reference: int, prior: int | None = None) -> np.ndarray | None:
        """The covariance of this frame's verified loop to frame number ``reference`` (of prior
        session ``prior``), if any."""
        return self._cov.get((prior, int(reference)))

    def add_prior(self, bank: LoopFeatureBank, frame_ids: np.ndarray, vo_poses: np.ndarray) -> int:
        """A prior session's references (a bank filled from the session), its frame numbers and
        odometry poses by stream position; returns the index :meth:`verify` takes as ``prior``."""
        self._priors.append((bank, {int(f): k for k, f in enumerate(frame_ids)}, vo_poses))
        return len(self._priors) - 1

    def verify(self, reference: int, prior: int | None = None) -> tuple[np.ndarray, int] | None:
        """(T_ref_cur, inliers) of the current frame in frame number ``reference`` of this run
        (or of prior session ``prior``, :meth:`add_prior`), or None."""
        bank: LoopFeatureBank | None
        vo_poses: list[np.ndarray] | np.ndarray
        if prior is None:
            bank, k_of_frame, vo_poses = self.bank, self._k_of_frame, self._vo_poses
        else:
            bank, k_of_frame, vo_poses = self._priors[prior]
        k_ref = k_of_frame.get(reference)
        if bank is None or self.bank is None or self._current is None or k_ref is None:
            return None
        k_feat = bank.nearest(k_ref)
        if k_feat is None:
            return None
        k, frame, offset_px = self._current
        try:
            cur = self.bank.query(k, frame)
            stereo = None if self.monocular else frame
            m = verify_features(bank.reference(k_feat), cur, stereo, self.camera, self.cfg, self.vcfg, offset_px, bank.merged)
        except Exception as exc:  # best effort: an unverifiable candidate is not a loop
            self.failures.append((k, f"loop verification raised {type(exc).__name__}: {exc}"))
            return None
        if m is None:
            return None
        T = m.T_ref_cur
        if k_feat != k_ref:
            T = np.linalg.solve(vo_poses[k_ref], vo_poses[k_feat]) @ T
        if np.linalg.norm(T[:3, 3]) > MAX_DISTANCE_M:  # not the same place
            return None
        self._cov[(prior, int(reference))] = two_view_covariance(m.cov) if self.monocular else m.cov
        return T, m.inliers

    def close(self) -> None:
        if self.bank is not None:
            self.bank.close()
