"""Loop verification without stereo: two-view geometry between a reference frame and the current one.

SIFT features of both frames (``loop_features.detect_loop_keypoints``), ratio-test
matches, the essential matrix under RANSAC (``cv2.findEssentialMat`` with USAC_ACCURATE: local
optimisation of the inliers, which a plain 5-point RANSAC lacks; seeded) and ``cv2.recoverPose``
give the rotation and the direction of the translation; at least ``min_inliers`` matches must
agree. The metric length is not observed by one camera: it is the odometry's distance between
the two frames, capped by the paper's same-place assumption (a pair SNAPS accepts stands close;
``SAME_PLACE_M``), and the covariance leaves it loose: sigma ``SAME_PLACE_M`` along the
direction, the fitted direction's uncertainty across it, the fitted rotation's from the
Sampson residuals' Jacobian. See docs/odometry-input.md for the figures behind the choice.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import FrontendConfig
from ..geometry import rotation_angle_deg
from ..types import FrameFeatures, StereoFrame
from .loop_features import (
    LOOP_QUERY_FEATURES,
    LOOP_RATIO_TEST,
    VERIFY_MAX_ROTATION_DEG,
    LoopFeatureBank,
    detect_loop_keypoints,
    ratio_matches,
)
from .motion import RANSAC_SEED

SAME_PLACE_M = 1.0  # a loop's distance is at most this, and as uncertain (1 sigma along its direction)
RANSAC_PROB = 0.999
MIN_SIGMA_ROT_RAD = 1e-3  # the E fit's rotation sigma is never taken below this
MIN_SIGMA_DIR_RAD = 0.02  # nor the direction's


@dataclass
class TwoViewMatch:
    """A two-view loop measurement."""

    R_ref_cur: np.ndarray  # 3x3 rotation of the current camera in the reference camera frame
    direction: np.ndarray  # (3,) unit translation of the current camera, reference frame
    inliers: int
    rms_px: float  # Sampson error rms of the inliers
    cov_rot: np.ndarray  # 3x3, right perturbation of R_ref_cur (rad)
    cov_dir: np.ndarray  # 3x3 (rank 2), of ``direction`` in the reference frame
    pairs: np.ndarray  # (inliers, 2) int: the inlier matches' indices into the reference's and the current frame's features


DETECTOR: Literal["orb", "sift"] = "sift"  # two-view geometry's features (docs/odometry-input.md: SIFT against ORB)


def two_view_features(
    img: np.ndarray, cfg: FrontendConfig, n: int | None = None, detector: Literal["orb", "sift"] = DETECTOR
) -> FrameFeatures:
    """Keypoints and descriptors of one image (no depth) for two-view verification."""
    uv, desc, _ = detect_loop_keypoints(img, dataclasses.replace(cfg, loop_detector=detector), n)
    return FrameFeatures(uv, np.zeros((len(uv), 3), np.float32), desc)


class MonoFeatureBank(LoopFeatureBank):
    """``LoopFeatureBank`` for frames without a right image: keypoints and descriptors only."""

    def _compute(self, left: np.ndarray, right: np.ndarray, offset_px: float) -> FrameFeatures | None:
        f = two_view_features(left, self.cfg)
        return f if len(f.uv) >= self.cfg.min_inliers else None

    def query(self, k: int, frame: StereoFrame) -> FrameFeatures:
        if self._query_k != k or self._query is None:
            self._query = two_view_features(frame.left, self.cfg, LOOP_QUERY_FEATURES)
            self._query_k = k
        return self._query


def _sampson(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances (normalised image units) of correspondences x1 -> x2 (N,3 homogeneous)."""
    Ex1 = x1 @ E.T
    Etx2 = x2 @ E
    num = np.einsum("ij,ij->i", x2, Ex1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _exp(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _fit_covariance(
    R_rc: np.ndarray, d: np.ndarray, x_ref: np.ndarray, x_cur: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """(cov of R_rc's right perturbation, cov of d, rms) from the Sampson residuals' Jacobian in
    the 5 parameters (3 rotation, 2 direction), by central differences: cov = s² (JᵀJ)⁻¹."""
    b1 = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(d, b1)

    def residuals(p: np.ndarray) -> np.ndarray:
        R = R_rc @ _exp(p[:3])
        t = d + p[3] * b1 + p[4] * b2
        t = t / np.linalg.norm(t)
        # x_ref = R x_cur + t  (X_ref = R_rc X_cur + t): E maps cur -> ref, x_refᵀ [t]x R x_cur = 0
        return _sampson(_skew(t) @ R, x_cur, x_ref)

    r0 = residuals(np.zeros(5))
    h = 1e-6
    J = np.empty((len(r0), 5))
    for i in range(5):
        e = np.zeros(5)
        e[i] = h
        J[:, i] = (residuals(e) - residuals(-e)) / (2 * h)
    dof = max(len(r0) - 5, 1)
    s2 = float(r0 @ r0) / dof
    try:
        C = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        C = np.diag([1.0] * 5)
    B = np.stack([b1, b2], axis=1)
    return C[:3, :3], B @ C[3:, 3:] @ B.T, float(np.sqrt(s2))


def two_view_pose(
    ref: FrameFeatures | None, cur: FrameFeatures | None, camera: StereoCamera, cfg: FrontendConfig
) -> TwoViewMatch | None:
    """The relative rotation and translation direction of ``cur`` in ``ref``'s camera frame, or
    None when the descriptors differ in kind, too few matches or inliers survive, the fit is not
    finite, or the rotation is implausible (``VERIFY_MAX_ROTATION_DEG``)."""
    m = ratio_matches(ref, cur, cfg, LOOP_RATIO_TEST)
    if m is None:
        return None
    ref, cur, (ia, ib) = m
    p_ref = ref.uv[ia].astype(np.float64)
    p_cur = cur.uv[ib].astype(np.float64)
    K = camera.K
    cv2.setRNGSeed(RANSAC_SEED)
    E, mask = cv2.findEssentialMat(p_cur, p_ref, K, cv2.USAC_ACCURATE, RANSAC_PROB, cfg.pnp_reprojection_px)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    # points1 = cur, points2 = ref: X_ref = R X_cur + t, i.e. R = R_ref_cur, t along t_ref_cur
    n_good, R, t, mask2 = cv2.recoverPose(E, p_cur, p_ref, K, mask=mask.copy())
    inl = np.flatnonzero(mask2.ravel() > 0)
    if n_good < cfg.min_inliers or len(inl) < cfg.min_inliers:
        return None
    d = t.reshape(3) / max(float(np.linalg.norm(t)), 1e-12)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(d))):
        return None
    if rotation_angle_deg(R) > VERIFY_MAX_ROTATION_DEG:
        return None
    Kinv = np.linalg.inv(K)
    x_cur = np.c_[p_cur[inl], np.ones(len(inl))] @ Kinv.T
    x_ref = np.c_[p_ref[inl], np.ones(len(inl))] @ Kinv.T
    cov_rot, cov_dir, rms = _fit_covariance(R, d, x_ref, x_cur)
    if not (np.all(np.isfinite(cov_rot)) and np.all(np.isfinite(cov_dir))):
        return None
    cov_rot = cov_rot + np.eye(3) * MIN_SIGMA_ROT_RAD**2
    P = np.eye(3) - np.outer(d, d)
    cov_dir = cov_dir + P * MIN_SIGMA_DIR_RAD**2
    return TwoViewMatch(R, d, int(len(inl)), rms * camera.fx, cov_rot, cov_dir, np.c_[ia[inl], ib[inl]])


def loop_measurement(m: TwoViewMatch, odometry_distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(T_ref_cur 4x4, 6x6 covariance: rot rad then trans m, GTSAM's Pose3 tangent with right
    perturbation) of a two-view match: length min(odometry distance, ``SAME_PLACE_M``) along the
    measured direction, sigma ``SAME_PLACE_M`` along it, length x direction sigma across it."""
    s = min(max(float(odometry_distance_m), 0.0), SAME_PLACE_M)
    d = m.direction
    T = np.eye(4)
    T[:3, :3] = m.R_ref_cur
    T[:3, 3] = s * d
    C_t = SAME_PLACE_M**2 * np.outer(d, d) + max(s, 0.1 * SAME_PLACE_M) ** 2 * m.cov_dir
    R = m.R_ref_cur
    C = np.zeros((6, 6))
    C[:3, :3] = m.cov_rot
    C[3:, 3:] = R.T @ C_t @ R  # translation tangent is in the current camera's frame
    return T, 0.5 * (C + C.T)
