"""GTSAM pose graph: odometry factors, robust loop factors, iSAM2 or batch refinement.

The rest of the package passes 4x4 numpy poses (T_world_cam) through :class:`PoseGraph`; gtsam
stays in this package. One Pose3 per frame, keyed by stream position (0, 1, 2, ... in arrival
order); every sigma vector is in GTSAM's tangent order ``[rx, ry, rz, tx, ty, tz]``. Noise
models: ``noise.py``; the decisions behind them: docs/decisions.md, "Factor graph".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from ..config import GraphConfig
from ..drift_model import DriftModel
from ..errors import SnapsGraphError
from ..io_utils import atomic_output
from ._values import array_to_values as _array_to_values
from ._values import to_pose3 as _to_pose3
from ._values import values_to_array as _values_to_array
from .noise import loop_covariance, loop_sigmas, odometry_step_covariance

PRIOR_SIGMA_ROT_RAD = 1e-4  # sigma of the first pose's prior, rad
PRIOR_SIGMA_TRANS_M = 1e-3  # sigma of the first pose's prior, m
ROBUST_PARAM = 3.0  # robust kernel width on a loop's whitened 6-vector norm (an inlier's is ~2.4)
ISAM2_RELINEARIZE_THRESHOLD = 0.01  # iSAM2 relinearisation threshold
ISAM2_RELINEARIZE_SKIP = 1  # iSAM2 relinearises every this many updates
ISAM2_LOOP_ITERATIONS = 0  # extra iSAM2 steps after an update with a loop (later updates converge it; converge() finishes)
ISAM2_FINAL_ITERATIONS = 10  # PoseGraph.converge(): at most this many extra iSAM2 steps
BATCH_MAX_ITERATIONS = 100  # batch Levenberg-Marquardt iterations
BATCH_RELATIVE_TOL = 1e-8  # LM stops when an iteration lowers the error by less than this share
# QR, not Cholesky: a flagged step's loose factor squares into a normal system too ill-conditioned
# for Cholesky, and LM then crawls and stops far from the minimum (docs/loop-closure.md).
BATCH_LINEAR_SOLVER = "MULTIFRONTAL_QR"
# A solved graph is doubtful when its loops or its odometry disagree by more than this many sigmas
# on average (sqrt of chi-square per degree of freedom; about 1 when the noise models are right).
DOUBTFUL_SIGMAS = 3.0

MODES = ("none", "isam2", "batch")  # graph.refine's values but "both" (= isam2 here + optimize_batch)


def batch_params() -> gtsam.LevenbergMarquardtParams:
    """The batch solve's Levenberg-Marquardt settings (the run's and every re-solve's)."""
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(BATCH_MAX_ITERATIONS)
    lm.setRelativeErrorTol(BATCH_RELATIVE_TOL)
    lm.setLinearSolverType(BATCH_LINEAR_SOLVER)
    return lm


@dataclass
class LoopFactorInfo:
    """What :meth:`PoseGraph.add_loop` did with one loop.

    ``sigmas`` is the 6-vector (rotation rad x3, translation m x3) of the Gaussian part of the
    factor, None when the loop was not added; ``reason`` says why it was not added ("" if added).
    """

    ref: int
    cur: int
    q: float
    added: bool
    verified: bool
    sigmas: np.ndarray | None = None
    reason: str = ""


@dataclass
class GraphStats:
    """Counts and timings of one graph (all times in milliseconds)."""

    n_frames: int = 0
    n_prior_factors: int = 0
    n_odometry_factors: int = 0
    n_flagged_odometry: int = 0
    n_loops_added: int = 0
    n_loops_verified: int = 0
    n_loops_rejected: int = 0
    n_loops_dropped: int = 0  # removed after an iSAM2 failure
    n_updates: int = 0
    update_ms: list[float] = field(default_factory=list)  # one per update() call in isam2 mode
    loop_update_ms: list[float] = field(default_factory=list)  # updates that carried a loop
    batch_ms: float = 0.0
    batch_iterations: int = 0
    batch_error_initial: float = 0.0  # the graph's error (half the chi-square) at the initial estimate
    batch_error_final: float = 0.0
    batch_stop: str = ""  # why LM stopped: converged, iteration limit, damping limit, failed
    consistency: dict = field(default_factory=dict)  # PoseGraph.consistency() of the final estimate

    @property
    def n_factors(self) -> int:
        return self.n_prior_factors + self.n_odometry_factors + self.n_loops_added - self.n_loops_dropped

    def summary(self) -> dict:
        """JSON-ready counts plus median / p95 / max of the update times."""

        def pct(values: list[float], p: float) -> float:
            return float(np.percentile(values, p)) if values else 0.0

        return {
            "n_frames": self.n_frames,
            "n_factors": self.n_factors,
            "n_odometry_factors": self.n_odometry_factors,
            "n_flagged_odometry": self.n_flagged_odometry,
            "n_loops_added": self.n_loops_added,
            "n_loops_verified": self.n_loops_verified,
            "n_loops_rejected": self.n_loops_rejected,
            "n_loops_dropped": self.n_loops_dropped,
            "n_updates": self.n_updates,
            "update_ms_median": pct(self.update_ms, 50),
            "update_ms_p95": pct(self.update_ms, 95),
            "update_ms_max": max(self.update_ms, default=0.0),
            "loop_update_ms_median": pct(self.loop_update_ms, 50),
            "loop_update_ms_max": max(self.loop_update_ms, default=0.0),
            "batch_ms": self.batch_ms,
            "batch_iterations": self.batch_iterations,
            "batch_error_initial": self.batch_error_initial,
            "batch_error_final": self.batch_error_final,
            "batch_stop": self.batch_stop,
            "consistency": self.consistency,
        }


@dataclass
class _Loop:
    ref: int
    cur: int
    measurement: gtsam.Pose3
    sigmas: np.ndarray
    active: bool = True
    cov: np.ndarray | None = None  # full 6x6 covariance (rot, trans) when verification gave one


def _check_pose(T: np.ndarray | None, what: str) -> np.ndarray:
    if T is None:
        raise SnapsGraphError(f"{what}: missing pose")
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise SnapsGraphError(f"{what}: expected a 4x4 pose, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise SnapsGraphError(f"{what}: non-finite pose")
    return T


class PoseGraph:
    """A thin wrapper over GTSAM so no other module touches the solver.

    ``mode``: "none" (keep the initial estimates), "isam2" (an incremental update per
    :meth:`update`) or "batch" (Levenberg-Marquardt on :meth:`optimize_batch`); default from
    ``cfg.refine``. The graph is built in every mode, so :meth:`optimize_batch` and :meth:`save_g2o`
    always work. ``failures`` lists (k, reason) of every solver failure or fallback; ``loops`` one
    :class:`LoopFactorInfo` per :meth:`add_loop` call.
    """

    def __init__(self, cfg: GraphConfig, mode: str | None = None, drift: DriftModel | None = None) -> None:
        """``drift``: the odometry's drift model (``Config.odometry.model()``), whose error for each
        step's distance joins its factor's noise; default :class:`DriftModel`."""
        self.cfg = cfg
        self.drift = drift if drift is not None else DriftModel()
        if mode is None:  # "both" = iSAM2 online; the batch runs on optimize_batch()
            mode = "isam2" if cfg.refine == "both" else cfg.refine
        self.mode = mode
        cfg.validate()
        if self.mode not in MODES:
            raise SnapsGraphError(f"graph refine mode '{self.mode}': expected one of {', '.join(MODES)}")
        self.failures: list[tuple[int, str]] = []
        self.loops: list[LoopFactorInfo] = []
        self.stats = GraphStats()

        self._initial: list[np.ndarray] = []  # heuristic poses, the initial estimates
        self._base = gtsam.NonlinearFactorGraph()  # prior + odometry (known inliers)
        self._loops: list[_Loop] = []
        self._steps: list[tuple[int, np.ndarray, np.ndarray]] = []  # (k, T_rel, covariance) per odometry factor
        self._anchors: list[gtsam.NonlinearFactor] = []  # loops to a fixed prior session (add_anchor)
        self._initial_values = gtsam.Values()
        # iSAM2 state: pending factors/values since the last update, the solver, cached estimate.
        self._isam: gtsam.ISAM2 | None = None
        if self.mode == "isam2":
            self._isam = self._new_isam2()
        self._pending_factors = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._pending_loops: list[_Loop] = []
        self._n_in_isam = 0  # frames whose variables are in iSAM2
        self._estimate_cache: np.ndarray | None = None
        self._batch_estimate: np.ndarray | None = None

    # ------------------------------------------------------------------ building
    def __len__(self) -> int:
        return len(self._initial)

    def add_frame(
        self,
        k: int,
        initial_pose: np.ndarray,
        T_rel: np.ndarray | None = None,
        inliers: int = 0,
        ok: bool = True,
        cov: np.ndarray | None = None,
        drift_cov: np.ndarray | None = None,
    ) -> None:
        """Add frame ``k`` (stream position; must be the next one) with its initial estimate.

        ``initial_pose`` is the heuristic (SNAPS-corrected) T_world_cam. Frame 0 gets a prior at
        it; frame k > 0 gets BetweenFactorPose3(k-1, k, T_rel) with :func:`odometry_sigmas`.
        ``T_rel`` None for k > 0 falls back on the relative pose of the two initial estimates.
        ``cov`` (6x6, Pose3 tangent at ``T_rel``) is the step's measurement noise (else
        :func:`odometry_sigmas`); the drift model's error along the step's path (``drift_cov``, default
        along the chord) is added to it.
        """
        if k != len(self._initial):
            raise SnapsGraphError(f"graph: frame key {k} out of order (expected {len(self._initial)})")
        T = _check_pose(initial_pose, f"graph frame {k} initial pose")
        pose = _to_pose3(T)
        if k == 0:
            sig = np.array([PRIOR_SIGMA_ROT_RAD] * 3 + [PRIOR_SIGMA_TRANS_M] * 3)
            factor = gtsam.PriorFactorPose3(0, pose, gtsam.noiseModel.Diagonal.Sigmas(sig))
            self.stats.n_prior_factors += 1
        else:
            if T_rel is None:
                T_rel = np.linalg.solve(self._initial[k - 1], T)
            T_rel = _check_pose(T_rel, f"graph frame {k} relative pose")
            C = odometry_step_covariance(self.cfg, self.drift, T_rel, int(inliers), bool(ok), cov, drift_cov)
            noise = gtsam.noiseModel.Gaussian.Covariance(C)
            factor = gtsam.BetweenFactorPose3(k - 1, k, _to_pose3(T_rel), noise)
            self._steps.append((k, T_rel.copy(), C))
            self.stats.n_odometry_factors += 1
            self.stats.n_flagged_odometry += int(not ok)
        # Validated: only now touch the state, so a rejected frame leaves no trace.
        self._initial.append(T.copy())
        self._initial_values.insert(k, pose)
        self._base.add(factor)
        self.stats.n_frames += 1
        if self._isam is not None:
            self._pending_factors.add(factor)
            self._pending_values.insert(k, pose)
        self._estimate_cache = None

    def add_loop(
        self, ref: int, cur: int, q: float, T_ref_cur: np.ndarray | None, covariance: np.ndarray | None = None
    ) -> LoopFactorInfo:
        """Add a loop factor BetweenFactorPose3(ref, cur) weighted by the UIQI ``q``.

        Verified (``T_ref_cur`` given): the measured relative pose. Unverified: the same-place
        assumption (zero translation, heuristic relative rotation). Never raises: a loop that
        cannot be added comes back with ``added=False`` and a ``reason``. ``covariance`` (6x6,
        rot then trans, of T_ref_cur): the factor's noise is :func:`loop_covariance` of it instead of the Q-scaled sigmas.
        """
        verified = T_ref_cur is not None
        info = LoopFactorInfo(ref=int(ref), cur=int(cur), q=float(q), added=False, verified=verified)
        n = len(self._initial)
        reason = ""
        if not (0 <= ref < n) or not (0 <= cur < n):
            reason = f"no variable for key {ref if not 0 <= ref < n else cur} (graph has {n} frames)"
        elif ref == cur:
            reason = "loop from a frame to itself"
        elif not math.isfinite(float(q)):
            reason = "non-finite similarity Q"
        elif verified and (T_ref_cur is None or np.shape(T_ref_cur) != (4, 4) or not np.all(np.isfinite(T_ref_cur))):
            reason = "measured relative pose is not a finite 4x4"
        if reason:
            info.reason = reason
            self.stats.n_loops_rejected += 1
            self.loops.append(info)
            return info

        if verified:
            measurement = _to_pose3(np.asarray(T_ref_cur, dtype=float))
        else:
            # Same place (paper §III): no translation; rotation as currently estimated.
            T_ref, T_cur = self._current_pose(ref), self._current_pose(cur)
            T_meas = np.eye(4)
            T_meas[:3, :3] = T_ref[:3, :3].T @ T_cur[:3, :3]
            measurement = _to_pose3(T_meas)
        sig = loop_sigmas(self.cfg, float(q), verified)
        cov = None
        if verified and covariance is not None:
            cov = loop_covariance(self.cfg, covariance)
            if cov is not None:
                sig = np.sqrt(np.diag(cov))
        loop = _Loop(int(ref), int(cur), measurement, sig, cov=cov)
        self._loops.append(loop)
        if self._isam is not None:
            self._pending_factors.add(self._loop_factor(loop, robust=True))
            self._pending_loops.append(loop)
        info.added, info.sigmas = True, sig
        self.stats.n_loops_added += 1
        self.stats.n_loops_verified += int(verified)
        self.loops.append(info)
        return info

    def _loop_factor(self, loop: _Loop, robust: bool) -> gtsam.BetweenFactorPose3:
        return gtsam.BetweenFactorPose3(loop.ref, loop.cur, loop.measurement, self._loop_noise(loop.sigmas, loop.cov, robust))

    def _loop_noise(self, sigmas: np.ndarray, cov: np.ndarray | None, robust: bool) -> gtsam.noiseModel.Base:
        if cov is not None:
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        else:
            noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        return robust_loop_noise(self.cfg, noise) if robust else noise

    def add_anchor(self, cur: int, T_world_cur: np.ndarray, covariance: np.ndarray | None) -> bool:
        """A verified loop to a prior session held fixed: frame ``cur`` is at ``T_world_cur`` (where
        the prior puts it, in this graph's frame), a robust unary factor with the loop's noise.
        False (nothing added, the reason in ``failures``) for a pose or key that cannot be used."""
        if not 0 <= cur < len(self._initial) or np.shape(T_world_cur) != (4, 4) or not np.all(np.isfinite(T_world_cur)):
            self.failures.append((int(cur), "loop to a prior session not added: no such frame or a non-finite pose"))
            return False
        sig = loop_sigmas(self.cfg, 1.0, True)
        cov = loop_covariance(self.cfg, covariance) if covariance is not None else None
        factor = gtsam.PriorFactorPose3(int(cur), _to_pose3(np.asarray(T_world_cur, float)), self._loop_noise(sig, cov, True))
        self._anchors.append(factor)
        if self._isam is not None:
            self._pending_factors.add(factor)
        self.stats.n_loops_added += 1
        self.stats.n_loops_verified += 1
        return True

    def _graph(self, robust: bool, anchors: bool = True) -> tuple[gtsam.NonlinearFactorGraph, int]:
        """Prior + odometry + active loops (+ the anchors to prior sessions); returns the graph and
        the number of base factors (the base factors come first, at indices 0..n_base-1)."""
        g = gtsam.NonlinearFactorGraph(self._base)
        for loop in self._loops:
            if loop.active:
                g.add(self._loop_factor(loop, robust))
        for factor in self._anchors if anchors else ():
            g.add(factor)
        return g, self._base.size()

    def factors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The graph's between factors as arrays, for a later session to join this graph: pairs
        (F, 2) of keys, measured T (F, 4, 4), covariance (F, 6, 6), robust (F,)."""
        rows = [(k - 1, k, T, C, False) for k, T, C in self._steps]
        for loop in self._loops:
            if loop.active:
                C = loop.cov if loop.cov is not None else np.diag(loop.sigmas**2)
                rows.append((loop.ref, loop.cur, loop.measurement.matrix(), C, True))
        if not rows:
            return np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), np.zeros(0, bool)
        return (
            np.array([(a, b) for a, b, *_ in rows], np.int64),
            np.array([r[2] for r in rows], float),
            np.array([r[3] for r in rows], float),
            np.array([r[4] for r in rows], bool),
        )

    # ------------------------------------------------------------------ solving
    def _new_isam2(self) -> gtsam.ISAM2:
        p = gtsam.ISAM2Params()
        p.setFactorization("QR")
        p.setRelinearizeThreshold(ISAM2_RELINEARIZE_THRESHOLD)
        p.relinearizeSkip = ISAM2_RELINEARIZE_SKIP
        return gtsam.ISAM2(p)

    def update(self) -> float:
        """One iSAM2 update with the factors and values added since the last call; returns its
        time in ms (0.0 and no work in modes "none" and "batch"). Never raises on a solver
        failure: the failure goes to ``failures`` and iSAM2 is rebuilt (:meth:`_rebuild_isam2`)."""
        if self._isam is None or (self._pending_factors.size() == 0 and self._pending_values.size() == 0):
            return 0.0
        k = len(self._initial) - 1
        has_loop = bool(self._pending_loops)
        t0 = time.perf_counter()
        try:
            self._isam.update(self._pending_factors, self._pending_values)
            if has_loop:
                self._iterate(ISAM2_LOOP_ITERATIONS)
            newest = self._isam.calculateEstimatePose3(k).matrix()
            if not np.all(np.isfinite(newest)):
                raise RuntimeError("non-finite estimate after update")
        except RuntimeError as exc:
            self.failures.append((k, f"isam2 update failed: {_one_line(exc)}"))
            self._rebuild_isam2(k, self._last_good_estimate())
        dt = (time.perf_counter() - t0) * 1e3
        self._pending_factors = gtsam.NonlinearFactorGraph()
        self._pending_values = gtsam.Values()
        self._pending_loops = []
        self._n_in_isam = len(self._initial)
        self._estimate_cache = None
        self.stats.n_updates += 1
        self.stats.update_ms.append(dt)
        if has_loop:
            self.stats.loop_update_ms.append(dt)
        return dt

    def _iterate(self, max_iterations: int) -> None:
        """Extra empty iSAM2 updates until nothing is relinearised. iSAM2 takes one Gauss-Newton
        step per update, but a robust loop factor is an IRLS problem whose weight is re-evaluated
        at each relinearisation, so right after a loop the estimate is not yet converged."""
        if self._isam is None:  # batch mode: nothing incremental to iterate
            return
        for _ in range(max_iterations):
            if self._isam.update().getVariablesRelinearized() == 0:
                break

    def converge(self, max_iterations: int | None = None) -> float:
        """isam2 mode: flush pending factors, then iterate to convergence (at most
        ``max_iterations``, default ``ISAM2_FINAL_ITERATIONS``); returns the time in ms. Call it
        once at the end of a run: online, later frames' updates converge earlier loops anyway,
        but a loop near the last frame would otherwise stay half-applied. No-op in other modes."""
        if self._isam is None:
            return 0.0
        t0 = time.perf_counter()
        self.update()
        if self._isam is None:  # the flush failed and switched iSAM2 off
            return (time.perf_counter() - t0) * 1e3
        n = ISAM2_FINAL_ITERATIONS if max_iterations is None else max_iterations
        try:
            self._iterate(n)
            newest = self._isam.calculateEstimatePose3(self._n_in_isam - 1).matrix()
            if not np.all(np.isfinite(newest)):
                raise RuntimeError("non-finite estimate after iterating")
        except RuntimeError as exc:
            k = self._n_in_isam - 1
            self.failures.append((k, f"isam2 final iterations failed: {_one_line(exc)}"))
            self._rebuild_isam2(k, self._last_good_estimate())
        self._estimate_cache = None
        self.stats.consistency = self.consistency(self.estimates())
        return (time.perf_counter() - t0) * 1e3

    def _last_good_estimate(self) -> np.ndarray:
        """Seed for a rebuild: the failed solver's estimate of the frames it held before the
        failed update where it is still finite and readable, else the initial poses."""
        seed = self._initial_array()
        m = self._n_in_isam
        if m == 0 or self._isam is None:
            return seed
        try:
            est = _values_to_array(self._isam.calculateEstimate(), None)[:m]
            if len(est) == m and np.all(np.isfinite(est)):
                seed[:m] = est
        except RuntimeError:
            pass
        return seed

    def _rebuild_isam2(self, k: int, seed: np.ndarray) -> None:
        """Fallback after a failed update: drop the loops of the failed update and rebuild iSAM2
        from all remaining factors, seeded with the last good estimate. If that fails too,
        switch iSAM2 off (estimates become the initial poses)."""
        for loop in self._pending_loops:
            loop.active = False
            self.stats.n_loops_dropped += 1
            self.failures.append((k, f"dropped loop factor {loop.ref}->{loop.cur}"))
        values = _array_to_values(seed)
        graph, _ = self._graph(robust=True)
        try:
            isam = self._new_isam2()
            isam.update(graph, values)
            newest = isam.calculateEstimatePose3(k).matrix()
            if not np.all(np.isfinite(newest)):
                raise RuntimeError("non-finite estimate after rebuild")
            self._isam = isam
        except RuntimeError as exc:
            self.failures.append((k, f"isam2 rebuild failed, isam2 off: {_one_line(exc)}"))
            self._isam = None

    def optimize_batch(self) -> np.ndarray:
        """Optimise the whole graph from the initial (heuristic) estimates; returns (N, 4, 4).

        Levenberg-Marquardt on the graph with robust loop factors. On a solver failure: the
        initial estimates, and the reason in ``failures``.
        """
        if not self._initial:
            raise SnapsGraphError("graph: optimize_batch on an empty graph")
        t0 = time.perf_counter()
        k = len(self._initial) - 1
        graph, _ = self._graph(robust=True)
        e0 = float(graph.error(self._initial_values))
        try:
            lm = batch_params()
            opt = gtsam.LevenbergMarquardtOptimizer(graph, self._initial_values, lm)
            result = opt.optimize()
            iterations = opt.iterations()
            poses = _values_to_array(result, len(self._initial))
            if not np.all(np.isfinite(poses)):
                raise RuntimeError("non-finite result")
            e1 = float(graph.error(result))
            if iterations >= BATCH_MAX_ITERATIONS:
                stop = "iteration limit"
            elif opt.lambda_() >= lm.getlambdaUpperBound():
                stop = "damping limit (no step lowered the error)"
            else:
                stop = "converged"
        except RuntimeError as exc:
            self.failures.append((k, f"batch optimisation failed: {_one_line(exc)}"))
            poses, iterations, e1, stop = self._initial_array(), 0, e0, "failed: the initial estimates kept"
        if e1 > e0:  # LM never raises the error it minimises; a rise means a failed solve
            self.failures.append((k, f"batch error rose from {e0:.4g} to {e1:.4g}: the initial estimates kept"))
            poses, e1, stop = self._initial_array(), e0, "failed: the initial estimates kept"
        self.stats.batch_ms = (time.perf_counter() - t0) * 1e3
        self.stats.batch_iterations = iterations
        self.stats.batch_error_initial, self.stats.batch_error_final, self.stats.batch_stop = e0, e1, stop
        self._batch_estimate = poses
        self.stats.consistency = self.consistency(poses)
        return poses.copy()

    def consistency(self, poses: np.ndarray) -> dict:
        """How well ``poses`` fit the graph, judged without ground truth: per factor type the
        chi-square per degree of freedom (about 1 when the noise models describe the errors), each
        loop's residual in sigmas (the root of its chi-square per degree of freedom), the loops
        beyond ``DOUBTFUL_SIGMAS``, and ``doubtful`` with the reason when the fit is suspect."""
        values = _array_to_values(np.asarray(poses, dtype=float))
        graph, n_base = self._graph(robust=False)
        chi = np.array([2.0 * graph.at(i).error(values) for i in range(graph.size())])
        n_odo = max(n_base - self.stats.n_prior_factors, 0)
        odo = chi[self.stats.n_prior_factors : n_base]
        loops = chi[n_base:]
        loop_sig = np.sqrt(loops / 6.0)
        out: dict = {
            "odometry_chi2_per_dof": float(odo.sum() / (6 * n_odo)) if n_odo else None,
            "loop_chi2_per_dof": float(loops.sum() / (6 * len(loops))) if len(loops) else None,
            "loop_residual_sigmas": [round(float(x), 3) for x in loop_sig],
            "loops_beyond": int(np.count_nonzero(loop_sig > DOUBTFUL_SIGMAS)),
            "doubtful": "",
        }
        why = []
        if out["loop_chi2_per_dof"] is not None and out["loop_chi2_per_dof"] > DOUBTFUL_SIGMAS**2:
            why.append(f"loops disagree with the odometry by {math.sqrt(out['loop_chi2_per_dof']):.1f} sigmas on average")
        elif out["loops_beyond"]:
            why.append(f"{out['loops_beyond']} of {len(loops)} loops are beyond {DOUBTFUL_SIGMAS:g} sigmas")
        if out["odometry_chi2_per_dof"] is not None and out["odometry_chi2_per_dof"] > DOUBTFUL_SIGMAS**2:
            why.append(f"the odometry is bent by {math.sqrt(out['odometry_chi2_per_dof']):.1f} sigmas on average")
        out["doubtful"] = "; ".join(why)
        return out

    # ------------------------------------------------------------------ results
    def estimates(self) -> np.ndarray:
        """Current best estimate (N, 4, 4): isam2 -> latest iSAM2 estimate (frames not yet passed
        to :meth:`update` keep their initial pose); batch -> the optimised poses once
        :meth:`optimize_batch` ran; none -> the initial poses. Never NaN."""
        n = len(self._initial)
        if n == 0:
            return np.zeros((0, 4, 4))
        if self.mode == "batch" and self._batch_estimate is not None and len(self._batch_estimate) == n:
            return self._batch_estimate.copy()
        if self._isam is None or self._n_in_isam == 0:
            return self._initial_array()
        if self._estimate_cache is None or len(self._estimate_cache) != n:
            poses = self._initial_array()
            try:
                est = _values_to_array(self._isam.calculateEstimate(), self._n_in_isam)
                poses[: self._n_in_isam] = est
            except RuntimeError as exc:
                self.failures.append((n - 1, f"isam2 estimate failed: {_one_line(exc)}"))
            bad = ~np.all(np.isfinite(poses.reshape(n, -1)), axis=1)
            for i in np.flatnonzero(bad):
                self.failures.append((int(i), "non-finite estimate replaced by the initial pose"))
                poses[i] = self._initial[i]
            self._estimate_cache = poses
        return self._estimate_cache.copy()

    def estimate(self, k: int) -> np.ndarray:
        """Best available pose of key k now (iSAM2's once k was updated, else its initial pose)."""
        return self._current_pose(k).copy()

    def set_initial_estimates(self, poses: np.ndarray) -> None:
        """Replace every key's initial estimate, which :meth:`optimize_batch` starts from (iSAM2 keeps
        its own linearisation points); the pipeline passes the final heuristic trajectory here.
        """
        poses = np.asarray(poses, float)
        if poses.shape != (len(self._initial), 4, 4) or not np.all(np.isfinite(poses)):
            raise SnapsGraphError(f"graph: set_initial_estimates needs {len(self._initial)} finite 4x4 poses")
        self._initial = [T.copy() for T in poses]
        self._initial_values = _array_to_values(poses)

    def save_g2o(self, path: str | Path) -> None:
        """Write the graph and the current estimates as a 3D g2o file, atomically.

        writeG2o cannot write Robust noise models, so the file holds a Gaussian copy of the loop
        factors (same measurement and sigmas, kernel dropped); it skips the prior (g2o fixes
        vertex 0). Read back with ``gtsam.readG2o(path, True)``.
        """
        path = Path(path)
        if not self._initial:
            raise SnapsGraphError(f"{path}: cannot write an empty graph")
        graph, _ = self._graph(robust=False)
        values = _array_to_values(self.estimates())
        with atomic_output(path) as tmp:
            gtsam.writeG2o(graph, values, str(tmp))

    # ------------------------------------------------------------------ helpers
    def _initial_array(self) -> np.ndarray:
        return np.array(self._initial) if self._initial else np.zeros((0, 4, 4))

    def _current_pose(self, k: int) -> np.ndarray:
        """Best available pose of key k without forcing a full estimate: iSAM2's if k is in it."""
        if self._isam is not None and k < self._n_in_isam:
            if self._estimate_cache is not None:
                return self._estimate_cache[k]
            try:
                T = self._isam.calculateEstimatePose3(k).matrix()
                if np.all(np.isfinite(T)):
                    return T
            except RuntimeError:
                pass
        if self.mode == "batch" and self._batch_estimate is not None and k < len(self._batch_estimate):
            return self._batch_estimate[k]
        return self._initial[k]


def robust_loop_noise(cfg: GraphConfig, noise: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """A loop factor's noise under ``cfg.robust_kernel`` (width ROBUST_PARAM); as is for "none"."""
    if cfg.robust_kernel == "none":
        return noise
    kernel = gtsam.noiseModel.mEstimator.Cauchy if cfg.robust_kernel == "cauchy" else gtsam.noiseModel.mEstimator.Huber
    return gtsam.noiseModel.Robust.Create(kernel.Create(ROBUST_PARAM), noise)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return (text[:200] + "...") if len(text) > 200 else (text or type(exc).__name__)
