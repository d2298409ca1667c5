"""SO(3) helpers: the batched exponential agrees with the single one."""

import numpy as np

from snaps_graph.geometry import exp_so3, exp_so3_scaled


def test_batched_exp_matches_the_single_exp():
    w = np.array([0.1, -0.4, 0.25])
    scales = np.array([0.0, 0.3, 1.0, 2.5])
    Rs = exp_so3_scaled(w, scales)
    assert Rs.shape == (4, 3, 3)
    for R, s in zip(Rs, scales, strict=True):
        assert np.allclose(R, exp_so3(s * w), atol=1e-12)
    assert np.array_equal(exp_so3_scaled(np.zeros(3), scales), np.broadcast_to(np.eye(3), (4, 3, 3)))
