"""Stereo visual odometry (paper §II-B..D): one interface, three feature modes.

``StereoOdometry.process(frame)`` takes one rectified stereo pair at a time and returns a
``VOResult`` at once. For every frame N:

1. 2D correspondences between the reference frame (the last frame whose motion was estimated,
   normally N-1) and frame N: descriptor matching ("sift", the paper's; "orb") or LK tracking
   ("klt", the fast default).
2. PnP with RANSAC (paper eq. 3, ``cv2.solvePnPRansac``) from the reference frame's 3D points
   (eq. 2: keypoint + stereo depth of eq. 1) to frame N's 2D keypoints, then Levenberg-Marquardt
   refinement on the inliers (``cv2.solvePnPRefineLM``). PnP gives T_cur_ref (it maps reference
   points into the current camera); the pose is T_world_cur = T_world_ref · inv(T_cur_ref).
3. With ``motion = "stereo_ba"`` (the default) PnP's pose is the seed and its inliers the data of
   a two-view stereo bundle adjustment (``stereo_ba.py``): the pose and every landmark are
   refined from (u_left, v, u_right) in both frames under a Huber kernel, so a far point's
   uncertain, long-biased depth no longer pulls the translation.
4. Stereo depth of frame N's keypoints, so frame N can be the next reference.
5. With ``local_ba`` a reference frame becomes a keyframe every ``lba_every`` frames (sooner
   once the drive has gone ``lba_keyframe_m`` from the last one) and a
   sliding-window stereo BA over the last ``lba_window`` keyframes (``local_ba.py``; KLT tracks
   keep a landmark id while they live) refines it; the chain continues from the refined pose.

At speed (large motion, or frames skipped: index gaps) KLT starts from the constant-velocity
prediction scaled to the gap, also after flagged frames; when PnP on the tracks still fails,
``klt_retry = "orb"`` retries once on ORB matches detected afresh plus the tracks.

Weak texture. goodFeaturesToTrack's quality threshold is relative to the image's strongest
corner; on an open road that is a far tree line against the sky (beyond ``max_depth_m``), which
can suppress every corner of the weakly textured ground that stereo can range. So when tracked
plus newly detected points with depth are fewer than ``klt_weak_points`` and most of the new
corners are out of range (beyond ``max_depth_m``), corners are detected once more at
``klt_weak_quality``.

Disparity offset. Every disparity the front end uses (depth for PnP and the next reference,
the stereo BA, the local BA, loop verification) is corrected as true = measured - offset * gain
(``depth.offset_gain``: by default a turn of the right camera, whose offset grows toward the
image's sides as 1 + ((u_r - cx) / fx)^2; ``disparity_offset_model``), with the offset
``disparity_offset_px`` (a known rig residual) or, with ``estimate_disparity_offset`` in klt +
local BA, the running estimate: each local-BA solve estimates the offset jointly (``local_ba.py``)
and reports what its data alone say; their information-weighted mean, clamped to
±``disparity_offset_max_px``, replaces the configured offset once
``disparity_offset_min_solves`` solves contributed, its standard error is at most
``disparity_offset_max_sd_px`` and it differs from it by at least
``disparity_offset_min_px`` and by ``disparity_offset_min_z`` standard errors. Until then the
local BA holds the offset in its pose solve, so a rig without an offset runs exactly as with the
estimate off; once applied, the offset is solved jointly with the window's poses and the
running estimate forgets older solves (``disparity_offset_memory_solves``).
``VOResult.disparity_offset_px`` is the offset each frame was measured with.

Robustness. A frame is flagged (``ok=False`` with a ``reason``) when its left image is flat or
black (grey std below ``min_frame_std``), blurred (mean |Laplacian| below
``min_sharpness_ratio`` times the reference's), when PnP has fewer than ``min_inliers``
inliers, when the motion is non-finite or implausible (more than ``max_step_m`` /
``max_step_deg`` per frame), when stereo finds depth at fewer than ``min_stereo_points``
keypoints (a swapped or broken stereo pair), or when OpenCV raises. A flagged frame's pose
follows the constant-velocity guess (the last good step's motion, scaled to the index gap). Its features become the new
reference only if they are usable (sharp, non-flat, enough keypoints with depth); otherwise
the last good reference stays, and the next frame is tracked against it directly, so the guess
does not enter the chain: T_world_cur = T_world_ref · T_ref_cur for the reference's pose.

Parallelism. OpenCV releases the GIL, so independent stages of the same frame run in two
threads (``threads``): in "klt" mode stereo depth of the tracked points runs beside PnP, and
re-detection with its stereo beside the stereo BA; in "sift"/"orb" dense depth runs beside
keypoint detection, and sparse depth beside matching + PnP. An LK call on many points (KLT
tracking, sparse stereo; ``lk_split_min``) is split in two halves run in two threads: LK
tracks each point alone, so the halves give the same numbers as one call. Each stage's inputs
are fixed before it starts and RANSAC is seeded (``ransac_seed``) in the thread that runs it,
so the output is bit-identical run to run.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..errors import SnapsGraphError
from ..geometry import adjoint, inv, rotation_angle_deg, scale_motion
from ..types import FrameFeatures, StereoFrame, VOResult
from . import depth as depth_mod
from . import features as feat
from .depth import correct_disparity, offset_gain
from .stereo_ba import stereo_two_view_ba


def chain_information(cov: np.ndarray, axes: str) -> np.ndarray:
    """Information (6x6, [rotation, translation]) of the chain's step between keyframes for
    ``lba_chain``: "yaw" = the marginal of the rotation about the camera's y axis only, "yaw_roll"
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


def pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def pnp_ransac(
    pts3d: np.ndarray, uv: np.ndarray, camera: StereoCamera, cfg: FrontendConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP RANSAC (eq. 3) then LM refinement on the inliers.

    Returns (T_cur_ref 4x4: maps points given in the reference camera frame into the current
    camera frame, inlier indices) or None when there are too few points, RANSAC fails or the
    result is not finite. The RNG is seeded here (``ransac_seed``), in the calling thread,
    because OpenCV's RNG is per thread.
    """
    n = len(pts3d)
    if n < max(6, cfg.min_inliers):
        return None
    obj = np.ascontiguousarray(pts3d, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
    K = camera.K
    cv2.setRNGSeed(cfg.ransac_seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=cfg.pnp_iterations,
        reprojectionError=cfg.pnp_reprojection_px,
        confidence=cfg.pnp_confidence,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or inl is None or len(inl) < 6:
        return None
    inl = inl.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    T = pose_from_rvec(rvec, tvec)
    if not np.all(np.isfinite(T)):
        return None
    # Inliers of the refined pose (the count reported and used for the flags).
    proj = obj @ T[:3, :3].T + T[:3, 3]
    z = proj[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * proj[:, 0] / z + K[0, 2]
        v = K[1, 1] * proj[:, 1] / z + K[1, 2]
    err = np.hypot(u - img[:, 0], v - img[:, 1])
    inliers = np.flatnonzero((z > 0) & (err <= cfg.pnp_reprojection_px))
    return T, inliers


def project(T_cur_ref: np.ndarray, pts3d: np.ndarray, camera: StereoCamera) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions of reference-frame points seen from the current camera, and their depth."""
    p = pts3d.astype(np.float64) @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    z = p[:, 2]
    zs = np.where(z > 1e-6, z, 1.0)
    uv = np.stack([camera.fx * p[:, 0] / zs + camera.cx, camera.fy * p[:, 1] / zs + camera.cy], axis=1)
    return uv.astype(np.float32), z


def sharpness(img: np.ndarray) -> float:
    """Mean absolute Laplacian (3x3): drops sharply when an image is blurred. (OpenCV's L1 norm
    is an exact integer sum: the same value as ``np.abs(lap).mean()``, several times faster.)"""
    lap = cv2.Laplacian(img, cv2.CV_16S, ksize=1)
    return cv2.norm(lap, cv2.NORM_L1) / lap.size


def empty_features(mode: str) -> FrameFeatures:
    d = np.zeros((0, 128), np.float32) if mode == "sift" else np.zeros((0, 32), np.uint8)
    return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32), d)


@dataclass
class _Keyframe:
    """What a frame leaves for the next one: its keypoints with depth, and the pose it was given."""

    index: int
    pose: np.ndarray  # T_world_cam (VO chain)
    left: np.ndarray  # left image (KLT tracks from it)
    uv: np.ndarray  # (N,2) float32, only keypoints with valid depth
    pts3d: np.ndarray  # (N,3) float32, camera frame
    disp: np.ndarray  # (N,) float32 disparity, pixels (the next stereo search starts there)
    desc: np.ndarray | None  # (N,D) descriptors in sift/orb modes
    sharpness: float
    features: FrameFeatures  # for loop verification
    ids: np.ndarray  # (N,) int64 landmark ids (klt: persistent across frames; -1 where unknown)
    # (N,) bool: depth within max_depth_m (PnP's points); the rest are far points (stereo BA only)
    near: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    right: np.ndarray | None = None  # right image (klt_retry matches ORB keypoints with depth from it)


class _Flag(Exception):
    """Internal: this frame is flagged for ``reason``; ``usable`` features may be a reference."""

    def __init__(self, reason: str, keyframe: _Keyframe | None = None):
        super().__init__(reason)
        self.reason = reason
        self.keyframe = keyframe


class _Inline:
    """Runs a task at once in the caller's thread (threads = 1), with a Future-like result()."""

    def __init__(self, fn: Callable, *args: Any):
        try:
            self._value, self._exc = fn(*args), None
        except BaseException as exc:  # re-raised by result(), like a Future
            self._value, self._exc = None, exc

    def result(self) -> Any:
        if self._exc is not None:
            raise self._exc
        return self._value


class StereoOdometry:
    """Streaming stereo VO. ``process`` one ``StereoFrame`` at a time; see the module docstring."""

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig | None = None):
        self.cfg = cfg or FrontendConfig()
        self.cfg.validate()
        self.camera = camera
        self._pool = ThreadPoolExecutor(max_workers=self.cfg.threads - 1) if self.cfg.threads > 1 else None
        # runs the second half of a split LK call (``lk_split_min``); its tasks never wait on others
        self._split_pool = ThreadPoolExecutor(max_workers=1) if self.cfg.threads > 1 and self.cfg.lk_split_min > 0 else None
        self._ref: _Keyframe | None = None
        self._pose = np.eye(4)  # pose of the last processed frame
        self._velocity = np.eye(4)  # T_rel of the last good frame (constant-velocity guess) ...
        self._velocity_gap = 1  # ... over this many frame indices
        self._have_velocity = False  # a good step has been measured
        self._last_index = 0  # index of the last processed frame
        self._last_ok = False
        self._n = 0  # frames processed
        self._next_id = 0  # next landmark id (klt)
        self._sba_cov: np.ndarray | None = None  # the last stereo BA's pose covariance (VOResult.cov)
        self._lba = None
        self._lba_last = -(10**9)  # frame index of the last local BA keyframe
        self._lba_last_pos = np.zeros(3)  # and its position
        self._chain_cov: np.ndarray | None = None  # the chain's covariance since that keyframe (T_cur_kf)
        self._lba_prev_pose: np.ndarray | None = None  # its pose as handed out
        self._offset = float(self.cfg.disparity_offset_px)  # disparity offset applied (measured - true, px)
        self._offset_sum = [0.0, 0.0, 0]  # running estimate: sum of info * offset, sum of info, solves
        if self.cfg.local_ba and self.cfg.mode == "klt":  # needs persistent tracks (landmark ids)
            from .local_ba import LocalBundleAdjuster

            self._lba = LocalBundleAdjuster(camera, self.cfg)
            self._lba.offset_joint = False  # held until the running estimate is applied

    @property
    def disparity_offset_px(self) -> float:
        """The disparity offset applied now (configured, or the running estimate)."""
        return self._offset

    def _update_offset(self, n_before: int) -> None:
        """Fold the local BA's new per-solve offset estimates into the running estimate."""
        assert self._lba is not None
        acc = self._offset_sum
        mem = self.cfg.disparity_offset_memory_solves
        for off, info in self._lba.stats.offsets[n_before:]:
            if np.isfinite(off) and np.isfinite(info) and info > 0:
                if self._lba.offset_joint and mem > 0:  # applied: older solves fade (they saw a worse offset)
                    acc[0] *= 1.0 - 1.0 / mem
                    acc[1] *= 1.0 - 1.0 / mem
                acc[0] += info * off
                acc[1] += info
                acc[2] += 1
        observed = acc[1] > 0 and acc[1] ** -0.5 <= self.cfg.disparity_offset_max_sd_px
        if acc[2] >= self.cfg.disparity_offset_min_solves and observed:
            lim = self.cfg.disparity_offset_max_px
            est = float(np.clip(acc[0] / acc[1], -lim, lim))
            need = max(self.cfg.disparity_offset_min_px, self.cfg.disparity_offset_min_z * acc[1] ** -0.5)
            if self._lba.offset_joint or abs(est - self.cfg.disparity_offset_px) >= need:
                self._offset = est
                self._lba.offset_px = est
                self._lba.offset_joint = True

    def _true(self, uv: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Measured disparities ``d`` at left points ``uv`` corrected for the offset applied now."""
        u = np.asarray(uv).reshape(-1, 2)[:, 0]
        return correct_disparity(d, u, self._offset, self.camera)

    def _sparse_depth(self, left: np.ndarray, right: np.ndarray, uv: np.ndarray, guess: np.ndarray | None = None):
        """(depth from the corrected disparity, measured disparity) at ``uv``."""
        z, d = self._split(lambda u, g: depth_mod.sparse_depth(left, right, u, self.camera, self.cfg, g), uv, guess)
        if self._offset != 0.0:
            z = depth_mod.depth_from_disparity(self._true(uv, d), self.camera, self.cfg)
        return z, d

    def _split(self, fn: Callable, uv: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """``fn(uv, guess)`` -> two per-point arrays, run on the two halves of the points in two
        threads (``lk_split_min``) and joined: LK tracks each point alone, so the result is the
        same as one call on all points."""
        n = len(uv)
        if self._split_pool is None or n < max(2, self.cfg.lk_split_min):
            return fn(uv, guess)
        k = n // 2
        second = self._split_pool.submit(fn, uv[k:], None if guess is None else guess[k:])
        a0, a1 = fn(uv[:k], None if guess is None else guess[:k])
        b0, b1 = second.result()
        return np.concatenate([a0, b0]), np.concatenate([a1, b1])

    # ---- lifecycle ----
    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._split_pool is not None:
            self._split_pool.shutdown(wait=True)
            self._split_pool = None

    def __enter__(self) -> "StereoOdometry":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _submit(self, fn: Callable, *args: Any) -> Future | _Inline:
        if self._pool is None:
            return _Inline(fn, *args)
        return self._pool.submit(fn, *args)

    # ---- main entry ----
    def process(self, frame: StereoFrame) -> VOResult:
        """Estimate the pose of ``frame``; never raises for a bad image, never returns NaN.

        A malformed frame (not 2-D uint8, left/right sizes differ, not the camera's size)
        is a user error: SnapsGraphError.
        """
        t_start = time.perf_counter()
        left, right = frame.left, frame.right
        depth_mod.check_stereo_pair(left, right)
        if self.camera.width and (left.shape[1], left.shape[0]) != (self.camera.width, self.camera.height):
            raise SnapsGraphError(
                f"frame {frame.index}: image {left.shape[1]}x{left.shape[0]} differs from the camera's {self.camera.width}x{self.camera.height}"
            )
        timings: dict[str, float] = {}
        first = self._n == 0
        self._n += 1
        prev_pose = self._pose
        gap_last = max(1, frame.index - self._last_index) if not first else 1
        ref = self._ref  # the frame this one is measured from
        self._sba_cov = None
        result = None
        flagged: tuple[str, _Keyframe | None] | None = None
        try:
            kf_or_none, T_ref_cur, inliers, matches = self._estimate(frame, first, timings)
        except _Flag as flag:
            flagged = (flag.reason, flag.keyframe)
        except cv2.error as exc:  # OpenCV refusing an odd image: flag, do not crash
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "error"
            flagged = (f"OpenCV error: {msg}", None)
        if flagged is not None:
            result = self._flagged(frame, prev_pose, flagged[0], flagged[1], timings, gap_last)
        if result is None:
            if first:
                pose = np.eye(4)
                T_rel = np.eye(4)
            else:
                pose = self._ref.pose @ T_ref_cur
            kf = kf_or_none
            if not first and self._chain_cov is not None:
                if (
                    self._sba_cov is None
                    or not np.all(np.isfinite(self._sba_cov))
                    or ref is None
                    or ref.index != self._last_index
                ):
                    self._chain_cov = None  # a step without a covariance: no chain factor up to the next keyframe
                else:
                    Ad = adjoint(inv(T_ref_cur))
                    self._chain_cov = self._sba_cov + Ad @ self._chain_cov @ Ad.T
            if self._lba is not None and (first or self._keyframe_due(frame.index, pose)):
                self._lba_last, self._lba_last_pos = frame.index, pose[:3, 3].copy()
                t_ba = time.perf_counter()
                n_off = len(self._lba.stats.offsets)
                chained = pose
                chain = None
                if self._chain_cov is not None and self._lba_prev_pose is not None and self.cfg.lba_chain != "off":
                    N = np.linalg.solve(pose, self._lba_prev_pose)  # T_cur_prevkf along the chain
                    chain = (N, chain_information(self._chain_cov * self.cfg.lba_chain_scale, self.cfg.lba_chain))
                args = (frame.index, pose, kf.ids[kf.near], kf.uv[kf.near], kf.disp[kf.near], chain)
                self._chain_cov = np.zeros((6, 6))
                pose = self._lba.add_keyframe(*args)
                timings["lba"] = (time.perf_counter() - t_ba) * 1000.0
                correction = self._lba_done(pose, chained, n_off)
                if self._sba_cov is not None:  # this step carries the correction: its size joins the noise
                    self._sba_cov = self._sba_cov + correction
            if not first:
                T_rel = inv(prev_pose) @ pose
            kf.pose = pose
            self._ref = kf
            self._pose = pose
            if not first:  # measured motion from the reference (not through a flagged frame's guess)
                self._velocity = inv(ref.pose) @ pose
                self._velocity_gap = max(1, frame.index - ref.index)
                self._have_velocity = True
            self._last_ok = True
            # The stereo BA measured T_ref_cur: it is T_rel when ref is the previous frame.
            from_prev = not first and ref is not None and ref.index == self._last_index
            cov = self._sba_cov if from_prev else None
            result = VOResult(
                index=frame.index,
                T_rel=T_rel,
                pose=pose,
                ok=True,
                inliers=inliers,
                matches=matches,
                features=kf.features,
                cov=cov,
            )
        result.disparity_offset_px = self._offset
        self._last_index = frame.index
        timings["total"] = (time.perf_counter() - t_start) * 1000.0
        result.timings_ms = timings
        return result

    def _lba_done(self, pose: np.ndarray, chained: np.ndarray, n_off: int) -> np.ndarray:
        """Book a local BA's answer ``pose`` for the keyframe whose chained pose was ``chained``;
        returns the covariance the correction adds to the step that carries it (its size)."""
        self._lba_prev_pose = pose.copy()
        if self.cfg.estimate_disparity_offset:
            self._update_offset(n_off)
        c = inv(chained) @ pose
        w = 0.5 * np.array([c[2, 1] - c[1, 2], c[0, 2] - c[2, 0], c[1, 0] - c[0, 1]])  # small angles
        return np.diag(np.r_[w, c[:3, 3]] ** 2)

    def _flagged(
        self,
        frame: StereoFrame,
        prev_pose: np.ndarray,
        reason: str,
        keyframe: _Keyframe | None,
        timings: dict[str, float],
        gap: int = 1,
    ) -> VOResult:
        T_rel = self._scaled_velocity(gap) if self._n > 1 else np.eye(4)
        pose = prev_pose @ T_rel
        if self._lba is not None:
            self._lba.reset()
        self._chain_cov, self._lba_prev_pose = None, None
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

    # ---- estimation ----
    def _estimate(self, frame: StereoFrame, first: bool, timings: dict[str, float]):
        """(keyframe of this frame, T_ref_cur, inliers, matches); raises _Flag to flag."""
        cfg = self.cfg
        t0 = time.perf_counter()
        left = frame.left
        std = float(cv2.meanStdDev(left)[1][0, 0])
        sharp = sharpness(left)
        timings["quality"] = (time.perf_counter() - t0) * 1000.0
        if not std >= cfg.min_frame_std:
            raise _Flag(f"flat or black image (grey std {std:.2f} < {cfg.min_frame_std})")
        if self._ref is not None and sharp < cfg.min_sharpness_ratio * self._ref.sharpness:
            raise _Flag(
                f"blurred image (sharpness {sharp:.2f} < {cfg.min_sharpness_ratio} x reference {self._ref.sharpness:.2f})"
            )
        if cfg.mode == "klt":
            return self._estimate_klt(frame, first, sharp, timings)
        return self._estimate_descriptors(frame, first, sharp, timings)

    def _check_motion(self, T_cur_ref: np.ndarray, inliers: int, gap: int) -> np.ndarray:
        cfg = self.cfg
        if inliers < cfg.min_inliers:
            raise _Flag(f"too few PnP inliers ({inliers} < {cfg.min_inliers})")
        if not np.all(np.isfinite(T_cur_ref)):
            raise _Flag("non-finite PnP pose")
        T_ref_cur = inv(T_cur_ref)
        step = float(np.linalg.norm(T_ref_cur[:3, 3]))
        angle = rotation_angle_deg(T_ref_cur[:3, :3])
        if step > cfg.max_step_m * gap or angle > cfg.max_step_deg * gap:
            raise _Flag(f"implausible motion ({step:.2f} m, {angle:.1f} deg over {gap} frame(s))")
        return T_ref_cur

    def _make_keyframe(
        self,
        frame: StereoFrame,
        uv: np.ndarray,
        z: np.ndarray,
        disp: np.ndarray,
        desc: np.ndarray | None,
        sharp: float,
        timings: dict[str, float],
        ids: np.ndarray | None = None,
    ) -> _Keyframe:
        """Keep keypoints with valid depth; back-project them (eq. 2); pick the loop features."""
        cfg = self.cfg
        valid = z > 0
        uv, z, disp = uv[valid], z[valid], disp[valid]
        near = z <= cfg.max_depth_m
        ids = ids[valid] if ids is not None else np.full(len(uv), -1, np.int64)
        desc = desc[valid] if desc is not None else None
        pts3d = self.camera.backproject(uv[:, 0], uv[:, 1], z).astype(np.float32)
        t0 = time.perf_counter()
        near_idx = np.flatnonzero(near)
        m = len(near_idx)
        # Loop features. Detected keypoints come strongest first, so the first loop_features are
        # the ones most likely to be detected again when the place is revisited; tracked corners
        # have no such order, so an evenly spread subset is kept.
        if desc is not None:
            pick = near_idx[: cfg.loop_features]
            fdesc = desc[pick]
        else:
            pick = near_idx if m <= cfg.loop_features else near_idx[np.linspace(0, m - 1, cfg.loop_features).astype(np.int64)]
            fdesc = np.zeros((len(pick), 32), np.uint8)  # loops verify with their own features (loop_features.py)
        features = FrameFeatures(np.ascontiguousarray(uv[pick]), np.ascontiguousarray(pts3d[pick]), np.ascontiguousarray(fdesc))
        timings["features"] = timings.get("features", 0.0) + (time.perf_counter() - t0) * 1000.0
        return _Keyframe(
            frame.index, np.eye(4), frame.left, uv, pts3d, disp, desc, sharp, features, ids, near=near, right=frame.right
        )

    def _conclude(self, kf: _Keyframe, T_cur_ref: np.ndarray | None, n_inl: int, gap: int, failure: str):
        """Flag or accept the frame. Motion problems are reported first; a frame whose own
        stereo failed (a swapped or broken pair) is flagged even when PnP succeeded, since its
        depth, and so its next step, cannot be trusted."""
        n_near = int(np.count_nonzero(kf.near))
        usable = n_near >= self.cfg.min_stereo_points
        if T_cur_ref is None:
            raise _Flag(failure, kf if usable else None)
        try:
            T_ref_cur = self._check_motion(T_cur_ref, n_inl, gap)
        except _Flag as flag:
            raise _Flag(flag.reason, kf if usable else None) from None
        if not usable:
            raise _Flag(f"too few keypoints with stereo depth ({n_near} < {self.cfg.min_stereo_points})")
        return T_ref_cur

    def _refine_motion(
        self,
        T_cur_ref: np.ndarray,
        inl: np.ndarray,
        ref_uv: np.ndarray,
        ref_disp: np.ndarray,
        cur_uv: np.ndarray,
        cur_disp: np.ndarray,
        timings: dict[str, float],
    ):
        """Stereo BA on PnP's inliers (``motion = "stereo_ba"``): (T_cur_ref, inlier indices).

        ``inl`` indexes the arrays; the BA's own outliers are dropped from it. If the BA is
        degenerate, PnP's answer stands (recorded in ``timings['sba_fallback']``)."""
        if self.cfg.motion != "stereo_ba" or len(inl) == 0:
            return T_cur_ref, inl
        t0 = time.perf_counter()
        cfg = self.cfg
        r = stereo_two_view_ba(
            T_cur_ref,
            ref_uv[inl],
            self._true(ref_uv[inl], ref_disp[inl]),
            cur_uv[inl],
            self._true(cur_uv[inl], cur_disp[inl]),
            self.camera,
            cfg,
        )
        timings["sba"] = (time.perf_counter() - t0) * 1000.0
        if not r.ok:
            timings["sba_fallback"] = 1.0
            self._sba_cov = None
            return T_cur_ref, inl
        self._sba_cov = r.cov
        if r.kept is not None and np.count_nonzero(r.inliers) < cfg.sba_keep_below:  # a small image: keep its tracks
            return r.T_cur_ref, inl[r.kept]
        return r.T_cur_ref, inl[r.inliers]

    def _keyframe_due(self, index: int, pose: np.ndarray) -> bool:
        """A local-BA keyframe is due ``lba_every`` frames after the last one, or sooner once the
        drive has gone ``lba_keyframe_m`` from it (a fast drive keeps the keyframes' spacing)."""
        if index - self._lba_last >= self.cfg.lba_every:
            return True
        m = self.cfg.lba_keyframe_m
        return m > 0 and float(np.linalg.norm(pose[:3, 3] - self._lba_last_pos)) >= m

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

    # -- klt --
    def _stereo_klt(
        self, frame: StereoFrame, uv: np.ndarray, guess: np.ndarray | None, timings: dict[str, float], detect: bool = True
    ):
        """Stereo depth at tracked points; if too few (and ``detect``), detect new corners and add theirs."""
        z, d = self._stereo_tracked(frame, uv, guess, timings)
        return (z, d, *self._detect_new(frame, uv, z, timings, detect))

    def _stereo_tracked(self, frame: StereoFrame, uv: np.ndarray, guess: np.ndarray | None, timings: dict[str, float]):
        """Stereo (depth, disparity) at the tracked points."""
        t0 = time.perf_counter()
        z, d = self._sparse_depth(frame.left, frame.right, uv, guess)
        timings["depth"] = (time.perf_counter() - t0) * 1000.0
        return z, d

    def _detect_new(self, frame: StereoFrame, uv: np.ndarray, z: np.ndarray, timings: dict[str, float], detect: bool = True):
        """If fewer tracked points ``uv`` than ``klt_min_tracks`` have depth ``z`` (and ``detect``):
        new corners away from them, with their stereo (new uv, depth, disparity). In weak texture
        under a far field (fewer than ``klt_weak_points`` points with depth after that, the new
        corners mostly beyond ``max_depth_m``) corners are detected once more at
        ``klt_weak_quality``."""
        cfg = self.cfg
        n_valid = int(np.count_nonzero(z > 0))
        new_uv = np.zeros((0, 2), np.float32)
        z2, d2 = np.zeros(0, np.float32), np.zeros(0, np.float32)
        ms = {"depth": 0.0, "features": 0.0}

        def add_corners(quality: float) -> None:
            nonlocal new_uv, z2, d2
            t = time.perf_counter()
            n = cfg.klt_features - n_valid - int(np.count_nonzero(z2 > 0))
            qcfg = cfg if quality == cfg.klt_quality else dataclasses.replace(cfg, klt_quality=quality)
            extra = feat.detect_corners(frame.left, n, qcfg, avoid=np.concatenate([uv[z > 0], new_uv]))
            t_det = time.perf_counter()
            if len(extra):
                z3, d3 = self._sparse_depth(frame.left, frame.right, extra)
                new_uv, z2, d2 = np.concatenate([new_uv, extra]), np.concatenate([z2, z3]), np.concatenate([d2, d3])
            ms["features"] += (t_det - t) * 1000.0
            ms["depth"] += (time.perf_counter() - t_det) * 1000.0

        if detect and n_valid < cfg.klt_min_tracks:
            add_corners(cfg.klt_quality)
            # Only where the far field took the ranking: most new corners lie beyond max_depth_m
            # (a valid disparity); where stereo failed on them, more corners would not help.
            far = int(np.count_nonzero((d2 > 0) & (z2 <= 0)))
            weak = n_valid + int(np.count_nonzero(z2 > 0)) < cfg.klt_weak_points and 2 * far > len(new_uv)
            if weak and cfg.klt_weak_quality < cfg.klt_quality:
                add_corners(cfg.klt_weak_quality)
        timings["depth"] = timings.get("depth", 0.0) + ms["depth"]
        timings["features"] = ms["features"]
        return new_uv, z2, d2

    def _estimate_klt(self, frame: StereoFrame, first: bool, sharp: float, timings: dict[str, float]):
        """KLT from the reference (the last frame whose motion was estimated) into this frame,
        PnP (+ stereo BA)."""
        cfg = self.cfg
        ref = self._ref
        if first or ref is None:
            z, d, new_uv, z2, d2 = self._stereo_klt(frame, np.zeros((0, 2), np.float32), None, timings)
            kf = self._make_keyframe(frame, new_uv, z2, d2, None, sharp, timings, ids=self._new_ids(len(new_uv)))
            if not first:
                self._conclude(kf, None, 0, 1, "no reference frame to track from")
            elif np.count_nonzero(kf.near) < cfg.min_stereo_points:
                raise _Flag("too few keypoints with stereo depth")
            return kf, np.eye(4), 0, 0
        gap = max(1, frame.index - ref.index)
        t0 = time.perf_counter()
        pred = self._prediction(gap)
        guess = None
        dguess = ref.disp
        if pred is not None:
            guess, zp = project(pred, ref.pts3d, self.camera)
            guess = np.where((zp > 0)[:, None], guess, ref.uv)
            if cfg.stereo_guess_levels < cfg.stereo_levels:  # predict the disparity too
                dp = self.camera.fx * self.camera.baseline_m / np.maximum(zp, 1e-6)
                gain = offset_gain(guess[:, 0], dp, self.camera)
                dguess = np.where(zp > 0, dp + self._offset * gain, ref.disp)
        uv_cur, ok = self._split(lambda u, g: feat.track_klt(ref.left, frame.left, u, cfg, g), ref.uv, guess)
        idx = np.flatnonzero(ok)
        timings["match"] = (time.perf_counter() - t0) * 1000.0
        # Stereo of the tracked points runs beside PnP, re-detection (and its stereo) beside the stereo BA.
        stereo = self._submit(self._stereo_tracked, frame, uv_cur[idx], dguess[idx], timings)
        t1 = time.perf_counter()
        near_pos = np.flatnonzero(ref.near[idx])  # PnP takes the points with trusted depth only
        pnp = pnp_ransac(ref.pts3d[idx[near_pos]], uv_cur[idx[near_pos]], self.camera, cfg)
        timings["pnp"] = (time.perf_counter() - t1) * 1000.0
        z, d = stereo.result()
        detection = self._submit(self._detect_new, frame, uv_cur[idx], z, timings)
        if pnp is None:
            keep = np.ones(len(idx), bool)
            T_cur_ref, n_inl = None, 0
        else:
            T_cur_ref, inl = pnp
            inl = near_pos[inl]
            if cfg.motion == "stereo_ba":  # far points join the BA (its outlier test screens them)
                inl = np.sort(np.concatenate([inl, np.flatnonzero(~ref.near[idx])]))
            T_cur_ref, inl = self._refine_motion(T_cur_ref, inl, ref.uv[idx], ref.disp[idx], uv_cur[idx], d, timings)
            n_inl = len(inl)
            keep = np.zeros(len(idx), bool)
            keep[inl] = True  # drop PnP outliers: mostly bad tracks
        if cfg.klt_retry == "orb" and n_inl < cfg.min_inliers and ref.right is not None:
            klt = (ref.pts3d[idx[near_pos]], ref.uv[idx[near_pos]], ref.disp[idx[near_pos]], uv_cur[idx[near_pos]], d[near_pos])
            cov_klt = self._sba_cov
            retry = self._orb_retry(ref, frame, klt, timings)
            if not (retry is not None and len(retry[1]) > n_inl):
                self._sba_cov = cov_klt
            if retry is not None and len(retry[1]) > n_inl:
                T_cur_ref, n_inl = retry[0], len(retry[1])
                pnp = retry
                keep = np.zeros(len(idx), bool)  # keep the KLT tracks among the inliers
                keep[near_pos[retry[1][retry[1] < len(near_pos)]]] = True
                timings["retry_ok"] = 1.0
        new_uv, z2, d2 = detection.result()
        uv_next = np.concatenate([uv_cur[idx][keep], new_uv])
        z_next = np.concatenate([z[keep], z2])
        d_next = np.concatenate([d[keep], d2])
        ids_next = np.concatenate([ref.ids[idx][keep], self._new_ids(len(new_uv))])
        kf = self._make_keyframe(frame, uv_next, z_next, d_next, None, sharp, timings, ids=ids_next)
        T_ref_cur = self._conclude(kf, T_cur_ref, n_inl, gap, f"PnP failed ({len(idx)} tracks)")
        return kf, T_ref_cur, n_inl, len(idx)

    def _orb_retry(self, ref: _Keyframe, frame: StereoFrame, klt: tuple, timings: dict[str, float]):
        """Motion from ``klt_retry_features`` ORB keypoints detected afresh in the reference and
        this frame, matched by descriptor (scale-invariant, so they survive the looming and the
        large flow of a fast drive that KLT does not), together with the KLT correspondences
        ``klt`` = (ref points 3D, ref uv, ref disparity, cur uv, cur disparity): PnP RANSAC on
        the union, then the stereo BA. (T_cur_ref, inliers: indices into the union, the KLT ones first) or None."""
        cfg, cam = self.cfg, self.camera
        assert ref.right is not None
        t0 = time.perf_counter()
        ocfg = dataclasses.replace(cfg, orb_features=cfg.klt_retry_features)
        uv_r, desc_r = feat.detect_orb(ref.left, ocfg)
        z_r, d_r = self._sparse_depth(ref.left, ref.right, uv_r)
        has_depth = np.flatnonzero(z_r > 0)
        uv_c, desc_c = feat.detect_orb(frame.left, ocfg)
        ia, ib = feat.match_descriptors(desc_r[has_depth], desc_c, cfg.ratio_test)
        ia = has_depth[ia]
        k_pts, k_ruv, k_rd, k_cuv, k_cd = klt
        res = None
        if len(ia) + len(k_pts) >= max(6, cfg.min_inliers):
            pts = np.concatenate([k_pts, cam.backproject(uv_r[ia, 0], uv_r[ia, 1], z_r[ia])]).astype(np.float64)
            cur_uv = np.concatenate([k_cuv, uv_c[ib]]).astype(np.float32)
            res = pnp_ransac(pts, cur_uv, cam, cfg)
        if res is not None and cfg.motion == "stereo_ba":
            _, d_c = depth_mod.sparse_depth(frame.left, frame.right, uv_c[ib], cam, cfg)
            res = self._refine_motion(
                res[0],
                res[1],
                np.concatenate([k_ruv, uv_r[ia]]).astype(np.float32),
                np.concatenate([k_rd, d_r[ia]]).astype(np.float32),
                cur_uv,
                np.concatenate([k_cd, d_c]).astype(np.float32),
                timings,
            )
        timings["retry"] = (time.perf_counter() - t0) * 1000.0
        return res

    def _new_ids(self, n: int) -> np.ndarray:
        """Fresh landmark ids for ``n`` newly detected points."""
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        return ids

    # -- sift / orb --
    def _detect(self, img: np.ndarray):
        if self.cfg.mode == "sift":
            return feat.detect_sift(img, self.cfg)
        return feat.detect_orb(img, self.cfg)

    def _estimate_descriptors(self, frame: StereoFrame, first: bool, sharp: float, timings: dict[str, float]):
        cfg = self.cfg
        cam = self.camera
        dense = cfg.disparity in depth_mod.DENSE_METHODS

        def dense_task():
            t = time.perf_counter()
            dm = depth_mod.dense_disparity(frame.left, frame.right, cfg)
            return dm, (time.perf_counter() - t) * 1000.0

        t0 = time.perf_counter()
        dense_future = self._submit(dense_task) if dense else None
        uv, desc = self._detect(frame.left)
        timings["features"] = (time.perf_counter() - t0) * 1000.0

        def depth_task():
            if dense:
                disp_map, ms = dense_future.result()
                t = time.perf_counter()
                disp = depth_mod.sample_depth(disp_map, uv)  # nearest-pixel disparity
                z = depth_mod.depth_from_disparity(self._true(uv, disp), cam, cfg)
                return z, disp, ms + (time.perf_counter() - t) * 1000.0
            t = time.perf_counter()
            z, disp = self._sparse_depth(frame.left, frame.right, uv)
            return z, disp, (time.perf_counter() - t) * 1000.0

        depth_future = dense_future if dense else self._submit(depth_task)
        ref = self._ref
        result = None
        n_matches = 0
        if not first and ref is not None and ref.desc is not None and len(ref.desc):
            t1 = time.perf_counter()
            ia, ib = feat.match_descriptors(ref.desc, desc, cfg.ratio_test)
            timings["match"] = (time.perf_counter() - t1) * 1000.0
            n_matches = len(ia)
            t2 = time.perf_counter()
            result = pnp_ransac(ref.pts3d[ia], uv[ib], cam, cfg)
            timings["pnp"] = (time.perf_counter() - t2) * 1000.0
        if dense:
            z, disp, timings["depth"] = depth_task()
        else:
            z, disp, timings["depth"] = depth_future.result()
        kf = self._make_keyframe(frame, uv, z, disp, desc, sharp, timings)
        if first:
            if np.count_nonzero(kf.near) < cfg.min_stereo_points:
                raise _Flag("too few keypoints with stereo depth")
            return kf, np.eye(4), 0, 0
        if ref is None:
            self._conclude(kf, None, 0, 1, "no reference frame to match against")
        gap = max(1, frame.index - ref.index)
        if result is None:
            self._conclude(kf, None, 0, gap, f"PnP failed ({n_matches} matches)")
        T_cur_ref, inl = result  # type: ignore[misc]  # _conclude raised when None
        T_cur_ref, inl = self._refine_motion(T_cur_ref, inl, ref.uv[ia], ref.disp[ia], uv[ib], disp[ib], timings)
        T_ref_cur = self._conclude(kf, T_cur_ref, len(inl), gap, "")
        return kf, T_ref_cur, len(inl), n_matches
