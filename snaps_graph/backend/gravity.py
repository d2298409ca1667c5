"""Level-vehicle (gravity) prior for the batch solve: experimental, off by default.

Loops observe drift that breaks a cycle's consistency, but a constant pitch bias of the VO bends a
closed drive into a closed path on a tilted plane, which every loop accepts. A car's camera keeps
a fixed attitude to the car, and the car's attitude to gravity varies only with road grade and
camber, which average out along a drive: so each frame gets an AttitudeFactorPose3 saying that its
camera-frame gravity direction ``c`` (shared, the mounting) points along the world gravity
direction ``g`` (shared), with ``gravity_sigma_deg``. ``c`` and ``g`` minimise
sum_k |R_k c - g|^2 over the current poses (alternating closed-form steps), then
Levenberg-Marquardt solves the whole graph with those factors; ``gravity_rounds`` times. It
straightens the shape (tilts that vary along the path); a tilt of the whole path relative to the
first frame stays, since the first frame's own gravity direction is unknown. It also pulls real
changes of grade toward level: with the default odometry sigmas, t_rel / r_rel got 2-4x worse on
KITTI 00 while the ATE fell 4x (README "gravity prior"), which is why it is off by default.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from ._values import array_to_values, values_to_array


def gravity_rounds(
    base: gtsam.NonlinearFactorGraph,
    poses: np.ndarray,
    lm: gtsam.LevenbergMarquardtParams,
    sigma_deg: float,
    rounds: int,
) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """Re-solve ``base`` from ``poses`` with the level-vehicle prior on every frame, ``rounds``
    times. Returns (poses, LM iterations, c camera-frame gravity, g world gravity); raises
    RuntimeError on a failed or non-finite solve (the caller keeps the plain batch result)."""
    n = len(poses)
    noise = gtsam.noiseModel.Isotropic.Sigma(2, math.radians(sigma_deg))
    iterations = 0
    c = g = np.array([0.0, 1.0, 0.0])
    for _ in range(int(rounds)):
        c, g = gravity_directions(poses[:, :3, :3], c)
        graph = gtsam.NonlinearFactorGraph(base)
        for k in range(n):
            graph.add(gtsam.AttitudeFactorPose3(k, gtsam.Unit3(g), noise, gtsam.Unit3(c)))
        opt = gtsam.LevenbergMarquardtOptimizer(graph, array_to_values(poses), lm)
        result = opt.optimize()
        iterations += opt.iterations()
        poses = values_to_array(result, n)
        if not np.all(np.isfinite(poses)):
            raise RuntimeError("non-finite result with the gravity prior")
    return poses, iterations, c, g


def gravity_directions(R: np.ndarray, c0: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Unit c (camera frame) and g (world) minimising sum_k |R_k c - g|^2, from c0.

    Alternating closed-form steps: g = normalise(mean_k R_k c), c = normalise(mean_k R_k^T g).
    A set of nearly equal rotations (a straight drive) leaves c where it started.
    """

    def unit(v: np.ndarray) -> np.ndarray:
        norm = np.linalg.norm(v)
        if not norm > 1e-6:
            raise RuntimeError("gravity directions undefined (attitudes spread over every direction)")
        return v / norm

    c = np.asarray(c0, dtype=float) / np.linalg.norm(c0)
    g = c
    for _ in range(iterations):
        g = unit((R @ c).mean(axis=0))
        c = unit((np.transpose(R, (0, 2, 1)) @ g).mean(axis=0))
    return c, g
