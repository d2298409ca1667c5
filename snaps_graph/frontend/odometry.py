"""Stereo visual odometry (paper §II-B..D): ``StereoOdometry.process(frame)`` takes one rectified
stereo pair and returns its ``VOResult`` at once; a bad frame is flagged and follows the
constant-velocity guess, never a NaN (docs/frontend.md)."""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..errors import SnapsGraphError
from ..geometry import inv, scale_motion
from ..types import StereoFrame, VOResult
from . import depth as depth_mod
from .descriptors import DescriptorMatcher
from .keyframe import Keyframe, Stereo, empty_features, sharpness
from .lba_schedule import LocalBAScheduler
from .motion import Flag, pnp_ransac
from .threads import Workers
from .tracking import Estimate, KltTracker

MIN_FRAME_STD = 3.0  # a frame whose grey std is below this is black or flat
MIN_SHARPNESS_RATIO = 0.35  # mean |Laplacian| below this x the reference's: blurred

__all__ = ["StereoOdometry", "pnp_ransac"]


class StereoOdometry:
    """Streaming stereo VO. ``process`` one ``StereoFrame`` at a time; docs/frontend.md says what it does."""

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig | None = None):
        self.cfg = cfg or FrontendConfig()
        self.cfg.validate()
        self.camera = camera
        self._workers = Workers(self.cfg.threads)
        klt = self.cfg.mode == "klt"
        # the local BA needs persistent tracks (landmark ids): klt only
        self._lba = LocalBAScheduler(camera, self.cfg) if self.cfg.local_ba and klt else None
        stereo = Stereo(camera, self.cfg, lambda: self.disparity_offset_px)
        self._klt = KltTracker(camera, self.cfg, stereo, self._workers) if klt else None
        self._matcher = DescriptorMatcher(camera, self.cfg, stereo, self._workers)
        self._ref: Keyframe | None = None
        self._pose = np.eye(4)  # pose of the last processed frame
        self._velocity = np.eye(4)  # T_rel of the last good frame (constant-velocity guess) ...
        self._velocity_gap = 1  # ... over this many frame indices
        self._have_velocity = False  # a good step has been measured
        self._last_index = 0  # index of the last processed frame
        self._last_ok = False
        self._n = 0  # frames processed

    @property
    def disparity_offset_px(self) -> float:
        """The disparity offset applied now (configured, or the running estimate)."""
        return self._lba.offset.offset if self._lba is not None else float(self.cfg.offset_px)

    def close(self) -> None:
        self._workers.close()

    def __enter__(self) -> "StereoOdometry":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def process(self, frame: StereoFrame) -> VOResult:
        """Estimate the pose of ``frame``; never raises for a bad image, never returns NaN.
        A malformed frame (not 2-D uint8, left/right sizes differ, not the camera's size) is a
        user error: SnapsGraphError."""
        t_start = time.perf_counter()
        self._check_frame(frame)
        timings: dict[str, float] = {}
        first, ref, prev_pose = self._n == 0, self._ref, self._pose
        self._n += 1
        gap = 1 if first else max(1, frame.index - self._last_index)
        try:
            estimate = self._estimate(frame, first, timings)
        except Flag as flag:
            result = self._flagged(frame, prev_pose, flag.reason, flag.keyframe, gap)
        except cv2.error as exc:  # OpenCV refusing an odd image: flag, do not crash
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "error"
            result = self._flagged(frame, prev_pose, f"OpenCV error: {msg}", None, gap)
        else:
            result = self._accept(frame, first, ref, prev_pose, estimate, timings)
        result.disparity_offset_px = self.disparity_offset_px
        self._last_index = frame.index
        timings["total"] = (time.perf_counter() - t_start) * 1000.0
        result.timings_ms = timings
        return result

    def _check_frame(self, frame: StereoFrame) -> None:
        left, right = frame.left, frame.right
        depth_mod.check_stereo_pair(left, right)
        if self.camera.width and (left.shape[1], left.shape[0]) != (self.camera.width, self.camera.height):
            raise SnapsGraphError(
                f"frame {frame.index}: image {left.shape[1]}x{left.shape[0]} differs from the camera's {self.camera.width}x{self.camera.height}"
            )

    def _estimate(self, frame: StereoFrame, first: bool, timings: dict[str, float]) -> Estimate:
        """The image checks, then the mode's correspondences and motion; raises Flag to flag."""
        t0 = time.perf_counter()
        std = float(cv2.meanStdDev(frame.left)[1][0, 0])
        sharp = sharpness(frame.left)
        timings["quality"] = (time.perf_counter() - t0) * 1000.0
        if not std >= MIN_FRAME_STD:
            raise Flag(f"flat or black image (grey std {std:.2f} < {MIN_FRAME_STD})")
        if self._ref is not None and sharp < MIN_SHARPNESS_RATIO * self._ref.sharpness:
            raise Flag(f"blurred image (sharpness {sharp:.2f} < {MIN_SHARPNESS_RATIO} x reference {self._ref.sharpness:.2f})")
        if self._klt is not None:
            return self._klt.estimate(frame, self._ref, first, self._prediction, sharp, timings)
        return self._matcher.estimate(frame, self._ref, first, sharp, timings)

    def _accept(
        self,
        frame: StereoFrame,
        first: bool,
        ref: Keyframe | None,
        prev_pose: np.ndarray,
        estimate: Estimate,
        timings: dict[str, float],
    ) -> VOResult:
        """Chain the measured step, let the local BA refine a keyframe, and make ``frame`` the reference."""
        kf, T_ref_cur, inliers, matches, cov = estimate
        pose = np.eye(4) if first or ref is None else ref.pose @ T_ref_cur
        # The stereo BA measured T_ref_cur: it is T_rel when ref is the previous frame.
        from_prev = not first and ref is not None and ref.index == self._last_index
        if self._lba is not None:
            if not first:
                self._lba.chain_step(cov, T_ref_cur, from_prev)
            pose, correction = self._lba.refine(frame.index, pose, kf, first, timings)
            if cov is not None and correction is not None:  # this step carries the correction: its size joins the noise
                cov = cov + correction
        T_rel = np.eye(4) if first else inv(prev_pose) @ pose
        kf.pose = pose
        self._ref = kf
        self._pose = pose
        if not first and ref is not None:  # measured motion from the reference (not through a flagged frame's guess)
            self._velocity = inv(ref.pose) @ pose
            self._velocity_gap = max(1, frame.index - ref.index)
            self._have_velocity = True
        self._last_ok = True
        return VOResult(
            frame.index, T_rel, pose, True, inliers=inliers, matches=matches, features=kf.features, cov=cov if from_prev else None
        )

    def _flagged(self, frame: StereoFrame, prev_pose: np.ndarray, reason: str, keyframe: Keyframe | None, gap: int) -> VOResult:
        T_rel = self._scaled_velocity(gap) if self._n > 1 else np.eye(4)
        pose = prev_pose @ T_rel
        if self._lba is not None:
            self._lba.reset()
        if not np.all(np.isfinite(pose)):  # cannot happen with finite inputs; belt and braces
            T_rel, pose = np.eye(4), prev_pose.copy()
        self._pose = pose
        self._last_ok = False
        if keyframe is not None:
            keyframe.pose = pose
            self._ref = keyframe
        feats = keyframe.features if keyframe is not None else empty_features(self.cfg.mode)
        if self._n == 1:  # the first frame is the origin whatever happens
            return VOResult(frame.index, np.eye(4), np.eye(4), True, reason="", features=feats)
        return VOResult(frame.index, T_rel, pose, False, reason=reason, features=feats)

    def _scaled_velocity(self, gap: int) -> np.ndarray:
        """The last good step's motion scaled to ``gap`` frame indices (constant velocity per
        index: its twist times gap / the step's own gap). Identity before any good step."""
        if gap == self._velocity_gap:
            return self._velocity.copy()
        return scale_motion(self._velocity, gap / self._velocity_gap)

    def _prediction(self, gap: int) -> np.ndarray | None:
        """T_cur_ref predicted by constant velocity over ``gap`` frame indices from the last
        good step (also across index gaps and after flagged frames); None before any step."""
        if not (self._have_velocity or self._last_ok):
            return None
        return inv(self._scaled_velocity(gap))
