"""Graduated non-convexity batch solve (``graph.batch_solver = "gnc"``), the alternative to
Levenberg-Marquardt with robust loop factors."""

from __future__ import annotations

import gtsam


def solve_gnc(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    n_known_inliers: int,
    lm: gtsam.LevenbergMarquardtParams,
    inlier_probability: float,
) -> gtsam.Values:
    """GncLMOptimizer over a Gaussian ``graph`` whose first ``n_known_inliers`` factors (prior and
    odometry) are known inliers and the rest (loop factors) outlier candidates; GNC supplies its
    own robust loss, so the loop factors must not be wrapped in a kernel as well. The chi-square
    inlier threshold is taken at ``inlier_probability``; GNC's own outer-iteration cap stays."""
    params = gtsam.GncLMParams(lm)
    params.setKnownInliers(list(range(n_known_inliers)))
    opt = gtsam.GncLMOptimizer(graph, initial, params)
    opt.setInlierCostThresholdsAtProbability(inlier_probability)
    return opt.optimize()
