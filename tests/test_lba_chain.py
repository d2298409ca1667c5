"""The chain's relative-pose factor in the local BA window (the window's yaw noise)."""

import numpy as np

from snaps_graph.frontend.lba_schedule import chain_information
from snaps_graph.frontend.local_ba import _add_chain_factor
from snaps_graph.geometry import exp_so3, log_so3


def _pose(w, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = exp_so3(np.asarray(w, float)), t
    return T


def _residual(Rcw, tcw, N):
    RP = Rcw[1] @ Rcw[0].T
    tP = tcw[1] - RP @ tcw[0]
    RE = RP @ N[:3, :3].T
    return np.r_[log_so3(RE), tP - RE @ N[:3, 3]]


def _one_step(free: int):
    """One Gauss-Newton step on a single chain factor, moving only pose ``free`` (0 or 1)."""
    Tcw = [_pose([0.01, 0.3, -0.02], [0.5, -0.1, 2.0]), _pose([-0.02, 0.35, 0.01], [0.7, 0.0, 1.1])]
    N = Tcw[1] @ np.linalg.inv(Tcw[0]) @ _pose([0.004, -0.006, 0.003], [0.02, -0.01, 0.03])
    Rcw = np.array([T[:3, :3] for T in Tcw])
    tcw = np.array([T[:3, 3] for T in Tcw])
    S, g = np.zeros((12, 12)), np.zeros(12)
    _add_chain_factor(S, g, 1, Rcw, tcw, N, np.eye(6))
    sl = slice(6 * free, 6 * free + 6)
    dx = np.linalg.solve(S[sl, sl], g[sl])
    before = np.linalg.norm(_residual(Rcw, tcw, N))
    Rcw[free], tcw[free] = exp_so3(dx[:3]) @ Rcw[free], exp_so3(dx[:3]) @ tcw[free] + dx[3:]
    return before, np.linalg.norm(_residual(Rcw, tcw, N))


def test_chain_factor_jacobians_bring_the_residual_to_zero():
    for free in (0, 1):  # the newer pose's Jacobian (identity) and the older one's (-Ad_N)
        before, after = _one_step(free)
        assert before > 0.02
        assert after < 0.01 * before


def test_chain_information_keeps_only_the_axes_asked_for():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T + 0.1 * np.eye(6)
    yaw = chain_information(cov, "yaw")
    assert yaw[1, 1] == 1 / cov[1, 1] and np.count_nonzero(yaw) == 1
    yr = chain_information(cov, "yaw_roll")
    assert np.allclose(yr[1:3, 1:3], np.linalg.inv(cov[1:3, 1:3])) and np.count_nonzero(yr) == 4
    rot = chain_information(cov, "rotation")
    assert np.allclose(rot[:3, :3], np.linalg.inv(cov[:3, :3])) and not rot[3:].any()
    assert np.allclose(chain_information(cov, "full"), np.linalg.inv(cov))
    assert not chain_information(cov, "off").any()
