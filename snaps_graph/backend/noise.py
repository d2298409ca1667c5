"""Noise models of the pose graph's factors (sigmas as [rx, ry, rz, tx, ty, tz]: GTSAM's Pose3 tangent order).

Odometry: the step's own measurement noise (the front end's stereo-BA covariance, scaled, else
sigmas that shrink as 1/sqrt(inliers), 100x looser on a flagged step) plus the drift model's
error for the distance it drove (:func:`odometry_step_covariance`): the process every part of
the package assumes. Loops: the verification's covariance, scaled and floored, else base sigmas
scaled by the similarity Q (:func:`loop_sigma_scale`).
"""

from __future__ import annotations

import math

import numpy as np

from ..config import GraphConfig
from ..drift_model import DriftModel, step_covariance

ODOM_MIN_INLIERS = 20  # inlier counts below this count as this many
UNVERIFIED_SIGMA_ROT_RAD = 0.5  # rotation sigma of an unverified loop (same-place assumption), rad
ODOM_REF_INLIERS = 200  # a VO step's sigmas are odom_sigma_* at this many inliers
ODOM_SIGMA_SCALE_MIN = 0.5  # clamp of the inlier scale sqrt(ODOM_REF_INLIERS / inliers)
ODOM_SIGMA_SCALE_MAX = 4.0
FLAGGED_SIGMA_SCALE = 100.0  # a flagged VO step's sigmas are this much looser
LOOP_SIGMA_SCALE_MAX = 10.0  # clip of a loop's Q scale (1 - q0) / (Q - q0)
# Added to every step's diagonal: a step that did not move still gets a determinate factor.
ODOM_FLOOR_ROT_RAD = 1e-4
ODOM_FLOOR_TRANS_M = 1e-3
UNVERIFIED_SIGMA_TRANS_M = 2.0  # an unverified loop assumes the same place: loose, metres apart still match
LOOP_Q_FLOOR = 0.0  # Q at which a loop's sigmas would be infinite: 0 suits the exact UIQI (docs/decisions.md)
ODOM_COV_SCALE = 1.0  # a stereo-BA step's covariance is used as the BA reports it
# A verified loop's PnP covariance takes its points as exact: scaled, and floored in quadrature so
# no loop is surer than about 0.1 deg and 2 cm (docs/decisions.md, loop factor noise).
LOOP_COV_SCALE = 4.0
LOOP_SIGMA_FLOOR_ROT_RAD = 0.002
LOOP_SIGMA_FLOOR_TRANS_M = 0.02


def odometry_sigmas(cfg: GraphConfig, inliers: int, ok: bool) -> np.ndarray:
    """Sigmas (rot rad x3, trans m x3) of a VO step without a covariance: the reference sigmas times
    ``sqrt(ODOM_REF_INLIERS / max(inliers, ODOM_MIN_INLIERS))`` clamped to ``[ODOM_SIGMA_SCALE_MIN,
    ODOM_SIGMA_SCALE_MAX]`` (1 when ``inliers <= 0``, not reported), times ``FLAGGED_SIGMA_SCALE`` if flagged.
    """
    if inliers > 0:
        scale = math.sqrt(ODOM_REF_INLIERS / max(inliers, ODOM_MIN_INLIERS, 1))
        scale = min(max(scale, ODOM_SIGMA_SCALE_MIN), ODOM_SIGMA_SCALE_MAX)
    else:
        scale = 1.0
    if not ok:
        scale *= FLAGGED_SIGMA_SCALE
    return scale * np.array([cfg.odom_sigma_rot_rad] * 3 + [cfg.odom_sigma_trans_m] * 3)


def odometry_covariance(cfg: GraphConfig, cov: np.ndarray | None) -> np.ndarray | None:
    """The step's own measurement covariance, ``ODOM_COV_SCALE^2 * cov``; None (use
    :func:`odometry_sigmas`) when ``cov`` is missing, not a finite symmetric 6x6 or not positive
    semi-definite."""
    if cov is None:
        return None
    C = np.asarray(cov, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return None
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C).min() < -1e-12 * max(float(np.abs(C).max()), 1e-300):
        return None
    return ODOM_COV_SCALE**2 * C


def odometry_step_covariance(
    cfg: GraphConfig,
    drift: DriftModel,
    T_rel: np.ndarray,
    inliers: int,
    ok: bool,
    cov: np.ndarray | None,
    drift_cov: np.ndarray | None = None,
) -> np.ndarray:
    """An odometry factor's 6x6 covariance: the step's measurement noise (:func:`odometry_covariance`
    of a good step's ``cov``, else :func:`odometry_sigmas`) plus the drift model's for the
    path the step drove (``drift_cov`` when the front end knows it, else along the chord), plus the floor."""
    C = odometry_covariance(cfg, cov) if ok else None
    if C is None:
        C = np.diag(odometry_sigmas(cfg, inliers, ok) ** 2)
    t = np.asarray(T_rel, dtype=float)[:3, 3]
    chord = np.asarray(T_rel, dtype=float)[:3, :3].T @ t
    floor = np.array([ODOM_FLOOR_ROT_RAD] * 3 + [ODOM_FLOOR_TRANS_M] * 3)
    if drift_cov is None or np.shape(drift_cov) != (6, 6) or not np.all(np.isfinite(drift_cov)):
        drift_cov = step_covariance(drift, float(np.linalg.norm(t)), chord)
    return C + np.asarray(drift_cov, dtype=float) + np.diag(floor**2)


def loop_sigma_scale(cfg: GraphConfig, q: float) -> float:
    """UIQI-to-noise mapping: ``clip((1 - q0) / (Q - q0), 1, LOOP_SIGMA_SCALE_MAX)``, q0 =
    ``LOOP_Q_FLOOR``. 1 at Q = 1, growing as Q falls toward q0 (information ~ (Q - q0)^2)."""
    q0 = LOOP_Q_FLOOR
    margin = min(float(q), 1.0) - q0
    if margin <= 0.0:
        return float(LOOP_SIGMA_SCALE_MAX)
    return float(min(max((1.0 - q0) / margin, 1.0), LOOP_SIGMA_SCALE_MAX))


def loop_sigmas(cfg: GraphConfig, q: float, verified: bool) -> np.ndarray:
    """Sigmas (rot rad x3, trans m x3) of a loop factor with similarity ``q``."""
    if verified:
        base = [cfg.loop_sigma_rot_rad] * 3 + [cfg.loop_sigma_trans_m] * 3
    else:
        base = [UNVERIFIED_SIGMA_ROT_RAD] * 3 + [UNVERIFIED_SIGMA_TRANS_M] * 3
    return loop_sigma_scale(cfg, q) * np.array(base)


def loop_covariance(cfg: GraphConfig, covariance: np.ndarray) -> np.ndarray | None:
    """A verified loop's factor covariance: ``LOOP_COV_SCALE`` x the verification's 6x6
    covariance (rot rad, trans m) plus the ``LOOP_SIGMA_FLOOR_*`` squared on the diagonal; None
    when the input is not a finite symmetric positive-definite 6x6."""
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return None
    floor = np.array([LOOP_SIGMA_FLOOR_ROT_RAD] * 3 + [LOOP_SIGMA_FLOOR_TRANS_M] * 3)
    C = LOOP_COV_SCALE * 0.5 * (C + C.T) + np.diag(floor**2)
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return None
    return C
