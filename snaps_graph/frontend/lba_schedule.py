"""When the local BA runs (klt mode), what it is told about the chain, and what its answer does
(docs/frontend.md)."""

from __future__ import annotations

import time

import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..geometry import adjoint, inv
from .keyframe import Keyframe
from .local_ba import LocalBundleAdjuster
from .offset import DisparityOffsetEstimator

LBA_CHAIN_SCALE = 1.0  # multiplier of the chain step's covariance in the local-BA window
LBA_EVERY = 3  # a reference becomes a keyframe this many frames after the last
LBA_KEYFRAME_M = 2.5  # ...or once driven this far from it (0 = never): a fast drive keeps a normal one's spacing, m
# The chain's step between keyframes constrains the window's yaw and roll (not its pitch, which
# carries the tracking bias the window removes): docs/decisions.md.
LBA_CHAIN = "yaw_roll"


def chain_information(cov: np.ndarray, axes: str) -> np.ndarray:
    """Information (6x6, [rotation, translation]) of the chain's step between keyframes for
    ``axes``: "yaw" = the marginal of the rotation about the camera's y axis only, "yaw_roll"
    = the marginal of the rotation about its y and z axes, "rotation" = the marginal of the
    rotation, "full" = all six."""
    info = np.zeros((6, 6))
    if axes == "yaw":
        info[1, 1] = 1.0 / max(float(cov[1, 1]), 1e-18)
    elif axes == "yaw_roll":
        info[1:3, 1:3] = np.linalg.inv(cov[1:3, 1:3])
    elif axes == "rotation":
        info[:3, :3] = np.linalg.inv(cov[:3, :3])
    elif axes == "full":
        info = np.linalg.inv(cov)
    return info


class LocalBAScheduler:
    def __init__(self, camera: StereoCamera, cfg: FrontendConfig):
        self.cfg = cfg
        self.every, self.keyframe_m, self.chain = LBA_EVERY, LBA_KEYFRAME_M, LBA_CHAIN
        self.lba = LocalBundleAdjuster(camera, cfg)
        self.lba.offset_joint = False  # held until the running estimate is applied
        self.offset = DisparityOffsetEstimator(cfg.offset_px)
        self._last = -(10**9)  # frame index of the last keyframe
        self._last_pos = np.zeros(3)  # and its position
        self._chain_cov: np.ndarray | None = None  # the chain's covariance since that keyframe (T_cur_kf)
        self._prev_pose: np.ndarray | None = None  # its pose as handed out

    def chain_step(self, cov: np.ndarray | None, T_ref_cur: np.ndarray, from_prev: bool) -> None:
        """Carry the chain's covariance over this step; a step without a covariance (or not from
        the previous frame) leaves no chain factor up to the next keyframe."""
        if self._chain_cov is None:
            return
        if cov is None or not np.all(np.isfinite(cov)) or not from_prev:
            self._chain_cov = None
        else:
            Ad = adjoint(inv(T_ref_cur))
            self._chain_cov = cov + Ad @ self._chain_cov @ Ad.T

    def refine(
        self, index: int, pose: np.ndarray, kf: Keyframe, first: bool, timings: dict[str, float]
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """(the keyframe's refined pose, the covariance its correction adds to this step) when a
        keyframe is due, else (``pose``, None)."""
        if not (first or self.due(index, pose)):
            return pose, None
        self._last, self._last_pos = index, pose[:3, 3].copy()
        t0 = time.perf_counter()
        n_off = len(self.lba.stats.offsets)
        chained = pose
        chain = None
        if self._chain_cov is not None and self._prev_pose is not None and self.chain != "off":
            N = np.linalg.solve(pose, self._prev_pose)  # T_cur_prevkf along the chain
            chain = (N, chain_information(self._chain_cov * LBA_CHAIN_SCALE, self.chain))
        self._chain_cov = np.zeros((6, 6))
        pose = self.lba.add_keyframe(index, pose, kf.ids, kf.uv, kf.disp, chain)
        timings["lba"] = (time.perf_counter() - t0) * 1000.0
        self._prev_pose = pose.copy()
        if self.cfg.estimate_offset and self.offset.add(self.lba.stats.offsets[n_off:]):
            self.lba.offset_px = self.offset.offset
            self.lba.offset_joint = True
        c = inv(chained) @ pose
        w = 0.5 * np.array([c[2, 1] - c[1, 2], c[0, 2] - c[2, 0], c[1, 0] - c[0, 1]])  # small angles
        return pose, np.diag(np.r_[w, c[:3, 3]] ** 2)

    def reset(self) -> None:
        """Forget the window and the chain (after a flagged frame: the chain holds a guessed step)."""
        self.lba.reset()
        self._chain_cov, self._prev_pose = None, None

    def due(self, index: int, pose: np.ndarray) -> bool:
        """A keyframe is due ``every`` frames after the last one, or ``keyframe_m`` metres from it."""
        if index - self._last >= self.every:
            return True
        m = self.keyframe_m
        return m > 0 and float(np.linalg.norm(pose[:3, 3] - self._last_pos)) >= m
