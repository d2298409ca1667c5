"""The one drift model: the step covariance the graph uses, the search's sigma, the correction's
shape and the fit, each against hand-computed values or against the drift tool's own process."""

from __future__ import annotations

import math

import numpy as np
import pytest

from snaps_graph.drift_model import DriftModel, heading_sigma_deg, path_covariance, position_sigma, step_covariance
from snaps_graph.evaluation.drift import drift_process, drift_trajectory, fit_drift_model
from snaps_graph.loop.correction import drift_share

HEADING_ONLY = DriftModel(
    heading_deg_per_sqrt_m=0.1, pitch_deg_per_sqrt_m=0, roll_deg_per_sqrt_m=0, scale_pct=0, trans_m_per_sqrt_m=0
)


def _straight(n: int, step: float = 1.0) -> np.ndarray:
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, 2, 3] = step * np.arange(n)
    return P


def _curve(n: int, turn_deg: float) -> np.ndarray:
    """A drive of n 1 m steps turning ``turn_deg`` per step about the camera's y (down) axis."""
    P = [np.eye(4)]
    a = math.radians(turn_deg)
    S = np.eye(4)
    S[:3, :3] = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    S[2, 3] = 1.0
    for _ in range(n - 1):
        P.append(P[-1] @ S)
    return np.array(P)


def test_step_covariance_of_a_long_straight_step():
    """Heading walk q over D metres: heading variance q D, sideways q D^3 / 3, tied by q D^2 / 2;
    forward only the scale error; all in GTSAM's (rx, ry, rz, tx, ty, tz) order."""
    q = math.radians(0.1) ** 2
    C = step_covariance(HEADING_ONLY, 100.0)
    assert np.isclose(C[1, 1], q * 100) and np.isclose(C[3, 3], q * 100**3 / 3) and np.isclose(C[1, 3], q * 100**2 / 2)
    assert np.isclose(C[5, 5], 0.0) and np.isclose(C[4, 4], 0.0)
    assert np.all(np.linalg.eigvalsh(C) > -1e-12)


def test_path_covariance_matches_the_chord_on_a_straight_road_and_not_on_a_bend():
    straight = _straight(101)
    assert np.allclose(path_covariance(HEADING_ONLY, straight), step_covariance(HEADING_ONLY, 100.0), rtol=0.05, atol=1e-9)
    bend = _curve(101, 0.9)  # a 90 degree bend
    C = path_covariance(HEADING_ONLY, bend)
    # Forward of the end frame is no longer free of heading error, as on a straight chord.
    assert C[5, 5] > 0.1 * C[3, 3]


def test_path_covariance_is_the_drift_tools_spread():
    """The sample covariance of the drift tool's end poses over seeds agrees with path_covariance."""
    from scipy.spatial.transform import Rotation

    gt = _curve(201, 0.5)
    model = DriftModel(
        heading_deg_per_sqrt_m=0.2, pitch_deg_per_sqrt_m=0.05, roll_deg_per_sqrt_m=0.05, scale_pct=0.0, trans_m_per_sqrt_m=0.01
    )
    errs = []
    for seed in range(400):
        d = drift_trajectory(gt, seed, model)
        E = np.linalg.solve(gt[-1], d[-1])
        errs.append(np.concatenate([Rotation.from_matrix(E[:3, :3]).as_rotvec(), E[:3, 3]]))
    sample = np.cov(np.array(errs).T)
    C = path_covariance(model, gt)
    for i in (1, 3, 5):  # heading, sideways, forward
        assert 0.75 < sample[i, i] / C[i, i] < 1.33, (i, sample[i, i], C[i, i])


def test_position_and_heading_sigma():
    m = HEADING_ONLY
    assert np.isclose(position_sigma(m, 1000.0), math.radians(0.1) * math.sqrt(1000.0**3 / 3))
    assert np.isclose(heading_sigma_deg(m, 400.0), 0.1 * 20.0)


def test_drift_share_spares_the_frames_that_did_not_drift():
    """A heading walk: the first tenth of the drive holds ~1.5 % of the end's error (a linear ramp
    would say 10 %); with the end heading known the share is the smoothstep 3x^2 - 2x^3."""
    u = np.linspace(0.0, 1000.0, 11)
    free = drift_share(HEADING_ONLY, u, heading_known=False)
    bridge = drift_share(HEADING_ONLY, u, heading_known=True)
    x = u / 1000.0
    assert np.allclose(free, (3 * x**2 - x**3) / 2) and np.allclose(bridge, 3 * x**2 - 2 * x**3)
    assert free[1] < 0.02 and free[-1] == pytest.approx(1.0)
    walk = DriftModel(
        heading_deg_per_sqrt_m=1e-9, pitch_deg_per_sqrt_m=0, roll_deg_per_sqrt_m=0, scale_pct=0, trans_m_per_sqrt_m=0.1
    )
    assert np.allclose(drift_share(walk, u, heading_known=False), x, atol=1e-6)  # a translation walk: linear


def test_fit_recovers_the_drift_tools_model():
    gt = _curve(3001, 0.05)
    true = drift_process(gt, 3, pct=1.0)
    fitted, L = fit_drift_model(drift_trajectory(gt, 3, pct=1.0), gt)
    assert L == 100.0
    assert 0.7 < fitted.heading_deg_per_sqrt_m / true.heading_deg_per_sqrt_m < 1.3
    assert 0.7 < fitted.trans_m_per_sqrt_m / true.trans_m_per_sqrt_m < 1.3
