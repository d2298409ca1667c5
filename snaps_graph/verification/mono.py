"""Loop verification without stereo: reference points triangulated over the odometry's motion.

A reference's SIFT keypoints are triangulated against a frame at least ``BASELINE_M`` further
along the odometry, then verified like stereo ones (``features.verify_features``) with the
neighbouring references' points too. Why and how: docs/odometry-input.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Literal

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig, VerificationConfig
from ..frontend.keyframe import MIN_STEREO_POINTS
from ..frontend.motion import PNP_REPROJECTION_PX, RANSAC_SEED
from ..geometry import inv
from ..types import FrameFeatures, StereoFrame
from .features import LOOP_QUERY_FEATURES, LOOP_RATIO_TEST, REFERENCE_EVERY, LoopFeatureBank, detect_loop_keypoints, ratio_matches

BASELINE_M = 1.0  # a reference is triangulated against the first later frame this far along the odometry
MAX_PARTNER_FRAMES = 30  # ...arriving within this many frames, else the reference is dropped (a camera at rest)
MIN_PARALLAX_DEG = 0.5  # a triangulated point's two rays differ by at least this
MAX_DIRECTION_DEG = 20.0  # the images' direction of the partner and the odometry's agree within this
RANSAC_PROB = 0.999
REFERENCE_FEATURES = 1000  # keypoints of a reference and of its partner before matching
NEIGHBOURS = 1  # a reference's local map adds the points of this many stored references on each side
DETECTOR: Literal["orb", "sift"] = "sift"  # monocular verification's features (docs/odometry-input.md: SIFT against ORB)
# Added to a two-view loop's PnP covariance, which takes the triangulated points as exact: the
# loops' errors against where the first pass's images put the second on the real revisit
# (benchmarks/revisit_reference.py; docs/odometry-input.md), not against KITTI's ground truth there,
# which the images contradict.
TWO_VIEW_SIGMA_ROT_RAD = 0.005
TWO_VIEW_SIGMA_TRANS_M = 0.1


def two_view_covariance(cov: np.ndarray) -> np.ndarray:
    """A two-view loop's covariance: the PnP's plus the turn / offset ambiguity it cannot see."""
    return np.asarray(cov, dtype=float) + np.diag([TWO_VIEW_SIGMA_ROT_RAD**2] * 3 + [TWO_VIEW_SIGMA_TRANS_M**2] * 3)


def two_view_features(
    img: np.ndarray, cfg: VerificationConfig, n: int | None = None, detector: Literal["orb", "sift"] = DETECTOR
) -> FrameFeatures:
    """Keypoints and descriptors of one image (no depth)."""
    uv, desc, _ = detect_loop_keypoints(img, dataclasses.replace(cfg, detector=detector), n)
    return FrameFeatures(uv, np.zeros((len(uv), 3), np.float32), desc)


def partner_pose(
    x_ref: np.ndarray, x_par: np.ndarray, T_odo: np.ndarray, camera: StereoCamera, cfg: FrontendConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """(T_ref_partner, inlier mask) from the matches' essential matrix (USAC_ACCURATE, seeded) and
    the odometry's length ``|T_odo|``: the images fix rotation and direction far better than an
    odometry's step does, and triangulation is as exact as they are. None when the fit fails or
    its direction is more than ``MAX_DIRECTION_DEG`` from the odometry's."""
    cv2.setRNGSeed(RANSAC_SEED)
    E, mask = cv2.findEssentialMat(x_par, x_ref, camera.K, cv2.USAC_ACCURATE, RANSAC_PROB, PNP_REPROJECTION_PX)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    # points1 = partner, points2 = reference: X_ref = R X_partner + t
    _, R, t, mask2 = cv2.recoverPose(E, x_par, x_ref, camera.K, mask=mask.copy())
    d, d_odo = t.reshape(3), T_odo[:3, 3]
    length = float(np.linalg.norm(d_odo))
    cos = float(d @ d_odo) / max(float(np.linalg.norm(d)) * length, 1e-12)
    if not (np.all(np.isfinite(R)) and np.isfinite(cos)) or cos < np.cos(np.radians(MAX_DIRECTION_DEG)):
        return None
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = length * d / np.linalg.norm(d)
    return T, mask2.ravel() > 0


def triangulate(
    ref: FrameFeatures, partner: FrameFeatures, T_odo: np.ndarray, camera: StereoCamera, cfg: FrontendConfig
) -> FrameFeatures | None:
    """``ref``'s keypoints that match ``partner``'s, with 3D points in ``ref``'s camera frame
    triangulated from the two views (``partner`` at :func:`partner_pose`, the odometry's
    ``T_odo`` giving the length): inliers of the fit, in front of both cameras within
    [min_depth_m, max_depth_m], reprojecting within ``PNP_REPROJECTION_PX`` in both, rays at
    least ``MIN_PARALLAX_DEG`` apart. None when fewer than ``MIN_STEREO_POINTS`` remain."""
    m = ratio_matches(ref, partner, cfg, LOOP_RATIO_TEST)
    if m is None:
        return None
    ref, partner, (ia, ib) = m
    K = camera.K
    fit = partner_pose(ref.uv[ia].astype(np.float64), partner.uv[ib].astype(np.float64), T_odo, camera, cfg)
    if fit is None:
        return None
    T_ref_partner, inl = fit
    ia, ib = ia[inl], ib[inl]
    T_p_r = inv(T_ref_partner)
    P1 = K @ np.eye(3, 4)
    P2 = K @ T_p_r[:3, :]
    x1 = ref.uv[ia].astype(np.float64)
    x2 = partner.uv[ib].astype(np.float64)
    Xh = cv2.triangulatePoints(P1, P2, x1.T, x2.T)
    w = Xh[3]
    ok = np.abs(w) > 1e-12
    X = (Xh[:3] / np.where(ok, w, 1.0)).T
    Xp = X @ T_p_r[:3, :3].T + T_p_r[:3, 3]
    ok &= (X[:, 2] >= cfg.min_depth_m) & (X[:, 2] <= cfg.max_depth_m) & (Xp[:, 2] >= cfg.min_depth_m)

    def reproj(P: np.ndarray, x: np.ndarray) -> np.ndarray:
        z = np.maximum(P[:, 2], 1e-9)
        return np.hypot(camera.fx * P[:, 0] / z + camera.cx - x[:, 0], camera.fy * P[:, 1] / z + camera.cy - x[:, 1])

    ok &= (reproj(X, x1) <= PNP_REPROJECTION_PX) & (reproj(Xp, x2) <= PNP_REPROJECTION_PX)
    ray2 = X - T_ref_partner[:3, 3]
    cos = np.einsum("ij,ij->i", X, ray2) / np.maximum(np.linalg.norm(X, axis=1) * np.linalg.norm(ray2, axis=1), 1e-12)
    ok &= cos <= np.cos(np.radians(MIN_PARALLAX_DEG))
    keep = np.flatnonzero(ok)
    if len(keep) < MIN_STEREO_POINTS:
        return None
    return FrameFeatures(
        np.ascontiguousarray(ref.uv[ia[keep]]), X[keep].astype(np.float32), np.ascontiguousarray(ref.desc[ia[keep]])
    )


class MonoFeatureBank(LoopFeatureBank):
    """``LoopFeatureBank`` for frames without a right image: a reference's 3D points come from
    triangulation against its partner frame (:func:`triangulate`) instead of stereo, so a
    reference is stored once its partner has arrived. Fed by :meth:`observe` with the
    odometry's pose of every frame; computed inline (deterministic)."""

    merged = True  # a reference is a local map: one physical point may be there several times

    def __init__(self, camera: StereoCamera, cfg: FrontendConfig, vcfg: VerificationConfig):
        super().__init__(camera, cfg, vcfg, background=False)
        self._waiting: dict[int, tuple[FrameFeatures, np.ndarray]] = {}  # reference -> (its keypoints, its pose)
        self._pose: dict[int, np.ndarray] = {}  # stored reference -> its odometry pose

    def add(self, k: int, frame: StereoFrame, offset_px: float = 0.0) -> None:
        raise TypeError("a monocular bank needs each frame's pose: call observe(k, frame, pose)")

    def observe(self, k: int, frame: StereoFrame, pose: np.ndarray) -> None:
        """Take stream position ``k`` with its odometry pose (T_world_camera, 4x4)."""
        cur = two_view_features(frame.left, self.vcfg, REFERENCE_FEATURES) if self.wants(k) else None
        for j in sorted(self._waiting):
            feat_j, pose_j = self._waiting[j]
            T_j_k = inv(pose_j) @ pose
            if np.linalg.norm(T_j_k[:3, 3]) < BASELINE_M:
                if k - j >= MAX_PARTNER_FRAMES:
                    del self._waiting[j]
                continue
            if cur is None:
                cur = two_view_features(frame.left, self.vcfg, REFERENCE_FEATURES)
            del self._waiting[j]
            points = triangulate(feat_j, cur, T_j_k, self.camera, self.cfg)
            if points is not None:
                self._keep(j, points)
                self._pose[j] = pose_j
        if cur is not None and self.wants(k):
            self._waiting[k] = (cur, np.array(pose, float))

    def load(self, refs: Mapping[int, FrameFeatures], vo_poses: np.ndarray) -> None:
        super().load(refs, vo_poses)
        self._pose.update({k: np.asarray(vo_poses[k], float) for k in refs})

    def reference(self, k: int) -> FrameFeatures | None:
        """Reference ``k``'s points with those of its ``NEIGHBOURS`` stored references on each
        side, carried into ``k``'s camera frame by the odometry between them (a few metres: close
        to exact), reprojected for their pixels; ``k``'s own points first."""
        own = self._ref.get(k)
        if own is None or k not in self._pose:
            return own
        e = REFERENCE_EVERY
        parts = [own]
        for n in [k + s * d * e for d in range(1, NEIGHBOURS + 1) for s in (-1, 1)]:
            other = self._ref.get(n)
            if other is None or n not in self._pose:
                continue
            T = inv(self._pose[k]) @ self._pose[n]
            X = other.pts3d.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            front = X[:, 2] >= self.cfg.min_depth_m
            X = X[front]
            uv = np.column_stack(
                [self.camera.fx * X[:, 0] / X[:, 2] + self.camera.cx, self.camera.fy * X[:, 1] / X[:, 2] + self.camera.cy]
            )
            parts.append(FrameFeatures(uv.astype(np.float32), X.astype(np.float32), other.desc[front]))
        if len(parts) == 1:
            return own
        return FrameFeatures(
            np.concatenate([p.uv for p in parts]),
            np.concatenate([p.pts3d for p in parts]),
            np.ascontiguousarray(np.concatenate([p.desc for p in parts])),
        )

    def query(self, k: int, frame: StereoFrame) -> FrameFeatures:
        if self._query_k != k or self._query is None:
            self._query = two_view_features(frame.left, self.vcfg, LOOP_QUERY_FEATURES)
            self._query_k = k
        return self._query
