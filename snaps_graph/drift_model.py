"""The odometry's drift model: how a trajectory's error grows with the distance driven.

One model for every part that needs one: the pose graph's odometry factors (:func:`step_covariance`),
the drift-aware candidate search (:func:`position_sigma`), the heuristic correction's shape and the
``drift`` tool that makes drifted odometry. Rotation errors are random walks in the distance driven
(heading, pitch, roll, in degrees per sqrt(metre)) plus optional constant rates; the translation
error is a scale error plus a small random walk. A drift whose heading wanders moves the middle of
a loop along the road's turns, not along the loop's offset: what the model says decides how a
loop's correction is spread. Camera axes as KITTI's: x right, y down, z forward.
Calibration: docs/loop-closure.md, "The drift model".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import adjoint

# The distance over which a bias (a scale error, a constant rate) is matched by a random walk of
# the same 1-sigma size, where a step's noise must be independent of the others (graph factors).
BIAS_REFERENCE_M = 1000.0


@dataclass(frozen=True)
class DriftModel:
    """Error rates of an odometry (1 sigma where random)."""

    heading_deg_per_sqrt_m: float = 0.07  # heading random walk
    pitch_deg_per_sqrt_m: float = 0.017  # pitch random walk
    roll_deg_per_sqrt_m: float = 0.017  # roll random walk
    scale_pct: float = 0.02  # translation scale error, percent
    trans_m_per_sqrt_m: float = 0.002  # translation random walk of each step, every axis
    heading_deg_per_100m: float = 0.0  # constant heading rate (a systematic turn)
    roll_deg_per_100m: float = 0.0  # constant roll rate

    def scaled(self, k: float) -> DriftModel:
        """Every rate times ``k``: the same shape of error, ``k`` times its size."""
        return DriftModel(*(k * v for v in (
            self.heading_deg_per_sqrt_m,
            self.pitch_deg_per_sqrt_m,
            self.roll_deg_per_sqrt_m,
            self.scale_pct,
            self.trans_m_per_sqrt_m,
            self.heading_deg_per_100m,
            self.roll_deg_per_100m,
        )))  # fmt: skip

    def rotation_var_per_m(self) -> np.ndarray:
        """Variance per metre driven of the step's rotation [pitch (x), heading (y), roll (z)], rad^2/m,
        the rates folded in as walks of equal size after BIAS_REFERENCE_M."""
        rad = math.pi / 180.0
        walk = (rad * np.array([self.pitch_deg_per_sqrt_m, self.heading_deg_per_sqrt_m, self.roll_deg_per_sqrt_m])) ** 2
        rate = (rad / 100.0 * np.array([0.0, self.heading_deg_per_100m, self.roll_deg_per_100m])) ** 2
        return walk + rate * BIAS_REFERENCE_M

    def translation_var_per_m(self) -> np.ndarray:
        """Variance per metre driven of the step's translation [lateral x, vertical y, forward z], m^2/m."""
        walk = np.full(3, self.trans_m_per_sqrt_m**2)
        walk[2] += (self.scale_pct / 100.0) ** 2 * BIAS_REFERENCE_M
        return walk


def step_covariance(model: DriftModel, driven_m: float, chord: np.ndarray | None = None) -> np.ndarray:
    """6x6 covariance of one odometry step that drove ``driven_m`` metres, in GTSAM's Pose3 tangent
    order (rx, ry, rz rad, then tx, ty, tz m) in the step's end frame. ``chord``: the step's
    translation seen from its end frame (R^T t of T_rel; default forward, +z). A heading error
    grown along the step moves its end sideways (variance q D^3 / 3, tied to the heading by
    q D^2 / 2), and a pitch error up or down: negligible for one frame's step, most of the error
    of a step across frames left out."""
    D = max(float(driven_m), 0.0)
    q_rot = model.rotation_var_per_m()  # pitch (x), heading (y), roll (z)
    q_tr = model.translation_var_per_m()
    fwd = np.array([0.0, 0.0, 1.0])
    if chord is not None and float(np.linalg.norm(chord)) > 1e-9:
        fwd = np.asarray(chord, dtype=float) / float(np.linalg.norm(chord))
    down = np.array([0.0, 1.0, 0.0])
    lat = np.cross(down, fwd)
    if float(np.linalg.norm(lat)) < 1e-6:  # a step straight up or down: no heading lever
        lat = np.array([1.0, 0.0, 0.0])
    lat /= np.linalg.norm(lat)
    vert = np.cross(fwd, lat)
    C = np.zeros((6, 6))
    C[:3, :3] = np.diag(q_rot * D)
    C[3:, 3:] = q_tr[0] * D * np.outer(lat, lat) + q_tr[1] * D * np.outer(vert, vert) + q_tr[2] * D * np.outer(fwd, fwd)
    C[3:, 3:] += (q_rot[1] * np.outer(lat, lat) + q_rot[0] * np.outer(vert, vert)) * D**3 / 3.0
    C[1, 3:] = C[3:, 1] = q_rot[1] * D * D / 2.0 * lat  # heading -> sideways
    C[0, 3:] = C[3:, 0] = -q_rot[0] * D * D / 2.0 * vert  # pitch -> up / down
    return C


def path_covariance(model: DriftModel, poses: np.ndarray) -> np.ndarray:
    """6x6 covariance of the relative pose from ``poses[0]`` to ``poses[-1]`` (T_world_cam, in
    driving order) when each step between them drifts by the model: every step's error carried to
    the last frame by the adjoint. A step across frames left out bends with the road its poses
    follow, which a chord cannot say (the heading error of one stretch moves the end sideways
    of that stretch)."""
    P = np.asarray(poses, dtype=float)
    end_inv = np.linalg.inv(P[-1])
    C = np.zeros((6, 6))
    for k in range(len(P) - 1):
        T = np.linalg.solve(P[k], P[k + 1])
        chord = T[:3, :3].T @ T[:3, 3]
        Ad = adjoint(end_inv @ P[k + 1])
        C += Ad @ step_covariance(model, float(np.linalg.norm(T[:3, 3])), chord) @ Ad.T
    return 0.5 * (C + C.T)


def position_sigma(model: DriftModel, driven_m: np.ndarray | float) -> np.ndarray:
    """1-sigma ground-plane position error (m) after ``driven_m`` metres: the scale error along the
    path, the lateral error of the heading walk (variance h^2 D^3 / 3) and rate (h D^2 / 2), and
    the translation walk."""
    D = np.asarray(driven_m, dtype=float)
    rad = math.pi / 180.0
    h = rad * model.heading_deg_per_sqrt_m
    c = rad * model.heading_deg_per_100m / 100.0
    var = (model.scale_pct / 100.0 * D) ** 2 + h * h * D**3 / 3.0 + (0.5 * c * D * D) ** 2 + model.trans_m_per_sqrt_m**2 * D
    return np.sqrt(var)


def heading_sigma_deg(model: DriftModel, driven_m: np.ndarray | float) -> np.ndarray:
    """1-sigma heading error (deg) after ``driven_m`` metres."""
    D = np.asarray(driven_m, dtype=float)
    return np.hypot(model.heading_deg_per_sqrt_m * np.sqrt(D), model.heading_deg_per_100m * D / 100.0)


__all__ = ["BIAS_REFERENCE_M", "DriftModel", "heading_sigma_deg", "path_covariance", "position_sigma", "step_covariance"]
