"""A joint refinement of two sessions, measured: the prior's saved factors and this run's own,
joined by the run's verified loops to the prior as between factors, against the prior held fixed
(what a run does). Why the prior stays fixed: docs/sessions.md, "The graph".

Runs B (``SEQ --frames``) with ``--prior A`` as the pipeline does, recording each loop to the prior
with its covariance; then solves the joint graph by the run's own batch settings (QR) with: every
loop; only the loops to A's frames below / from ``--split``; the odometry's step covariances
scaled per axis to their size against the ground truth; the loops' covariances times 10 and 100.
Printed per solve: A's and B's mean deviation from the ground truth (A's first pose where A put
it), beside A alone and B with A held fixed; and A's per-segment error alone and joint.

    python experiments/joint_sessions.py results/bench_sessions/rendered/A results/data/street00 --frames 1540:4541
"""

from __future__ import annotations

import argparse
import pickle
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from snaps_graph.backend import to_pose3
from snaps_graph.backend.noise import loop_covariance, loop_sigmas
from snaps_graph.backend.pose_graph import PRIOR_SIGMA_ROT_RAD, PRIOR_SIGMA_TRANS_M, batch_params, robust_loop_noise
from snaps_graph.config import Config
from snaps_graph.datasets.open import open_dataset
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import run_sequence
from snaps_graph.session import Session, read_session
from snaps_graph.trajectory_io import read_poses

Link = tuple[int, int, np.ndarray, np.ndarray | None]  # (A's position, B's position, T_ref_cur, covariance)


def run_recording(a: Path, seq: Path, frames: str, out: Path) -> tuple[list[Link], np.ndarray, np.ndarray]:
    """B with --prior A; returns its loops to A, its real-time trajectory (its own frame) and T_own_prior."""
    links: list[Link] = []
    kept: dict = {}
    add, finish = SlamPipeline._add_session_loop, SlamPipeline.finish

    def add_recording(self, k_cur, loop):  # type: ignore[no-untyped-def]
        assert self.snaps is not None and self.verifier is not None
        j = self.snaps.priors[loop.prior].position(loop.reference)
        cov = self.verifier.covariance(loop.reference, loop.prior)
        links.append((j, k_cur, np.asarray(loop.T_ref_cur, float), None if cov is None else np.array(cov)))
        add(self, k_cur, loop)

    def finish_recording(self):  # type: ignore[no-untyped-def]
        result = finish(self)
        assert self.snaps is not None
        kept.update(initial=np.array(self.snaps.poses), T_own_prior=np.array(self.snaps.priors[0].T_own_prior))
        return result

    SlamPipeline._add_session_loop, SlamPipeline.finish = add_recording, finish_recording  # type: ignore[method-assign]
    try:
        shutil.rmtree(out, ignore_errors=True)
        run_sequence(open_dataset(seq, frames=frames), out, refine="batch", priors=[a])
    finally:
        SlamPipeline._add_session_loop, SlamPipeline.finish = add, finish  # type: ignore[method-assign]
    return links, kept["initial"], kept["T_own_prior"]


def step_errors(s: Session, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The odometry steps' errors against the ground truth, (N, 6) rotation vector and offset, and
    their sigmas (N, 6)."""
    e, sig = [], []
    f = s.factors
    for (i, j), T, C, robust in zip(f.pairs, f.measured, f.covariance, f.robust):
        if robust or j != i + 1:
            continue
        D = np.linalg.solve(np.linalg.solve(gt[s.frame_ids[i]], gt[s.frame_ids[j]]), T)
        e.append(np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]])
        sig.append(np.sqrt(np.diag(C)))
    return np.array(e), np.array(sig)


def step_scale(s: Session, gt: np.ndarray) -> np.ndarray:
    """Per axis the RMS of the odometry steps' errors in units of their sigmas."""
    e, sig = step_errors(s, gt)
    return np.sqrt(((e / sig) ** 2).mean(0))


def solve(
    A: Session,
    B: Session,
    links: list[Link],
    initial: np.ndarray,
    T_own_prior: np.ndarray,
    scales=(None, None),
    link_scale=1.0,
    gap: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) refined jointly, in A's frame (A's first pose where A put it). ``gap``: B's own
    factors kept only between its frames with loops to A less than ``gap`` frames apart (B's
    revisits of A alone, not its tours between them); B's other poses are then returned as
    they came."""
    cfg = Config().graph
    key = lambda j: gtsam.symbol("a", j)  # noqa: E731
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, T in enumerate(initial):
        v.insert(k, to_pose3(T))
    for j, T in enumerate(T_own_prior @ A.poses):
        v.insert(key(j), to_pose3(T))
    sigmas = np.r_[[PRIOR_SIGMA_ROT_RAD] * 3, [PRIOR_SIGMA_TRANS_M] * 3]
    g.add(gtsam.PriorFactorPose3(0, to_pose3(initial[0]), gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
    ks = sorted(k for _, k, _, _ in links)
    spans = [(a, b) for a, b in zip(ks, ks[1:]) if b - a < (gap if gap is not None else len(initial) + 1)]
    inside = lambda i, j: gap is None or any(a <= i and j <= b for a, b in spans)  # noqa: E731
    for s, kf, scale in ((A, key, scales[0]), (B, lambda k: k, scales[1])):
        f = s.factors
        for (i, j), T, C, robust in zip(f.pairs, f.measured, f.covariance, f.robust):
            if s is B and not inside(int(i), int(j)):
                continue
            C = np.asarray(C, float)
            if scale is not None and not robust and j == i + 1:
                C = C * np.outer(scale, scale)
            noise = gtsam.noiseModel.Gaussian.Covariance(C)
            g.add(
                gtsam.BetweenFactorPose3(
                    kf(int(i)), kf(int(j)), to_pose3(np.asarray(T, float)), robust_loop_noise(cfg, noise) if robust else noise
                )
            )
    for j, k, T, cov in links:
        c = loop_covariance(cfg, cov * link_scale) if cov is not None else None
        noise = (
            gtsam.noiseModel.Gaussian.Covariance(c)
            if c is not None
            else gtsam.noiseModel.Diagonal.Sigmas(loop_sigmas(cfg, 1.0, True))
        )
        g.add(gtsam.BetweenFactorPose3(key(j), int(k), to_pose3(T), robust_loop_noise(cfg, noise)))
    for k in range(len(initial)):  # a frame no factor touches (B cut into its revisits) stays put
        g.add(gtsam.PriorFactorPose3(k, to_pose3(initial[k]), gtsam.noiseModel.Isotropic.Sigma(6, 1e3)))
    r = gtsam.LevenbergMarquardtOptimizer(g, v, batch_params()).optimize()
    a = np.array([r.atPose3(key(j)).matrix() for j in range(len(A.poses))])
    b = np.array([r.atPose3(k).matrix() for k in range(len(initial))])
    G = A.poses[0] @ np.linalg.inv(a[0])
    return G @ a, G @ b


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("prior", type=Path, help="A: a results folder with its session")
    ap.add_argument("seq", type=Path, help="the sequence B is taken from (with its ground truth)")
    ap.add_argument("--frames", required=True, help="B's frames, as run --frames")
    ap.add_argument("--split", type=int, default=200, help="A's frame splitting the loops into two sets")
    ap.add_argument("--gap", type=int, default=100, help="B's loops to A further apart than this end a revisit")
    ap.add_argument("--work", type=Path, default=Path(__file__).resolve().parents[1] / "results" / "joint_sessions")
    args = ap.parse_args()
    gt = read_poses(args.seq / "poses.txt")
    A = read_session(args.prior)
    gt = np.linalg.inv(gt[A.frame_ids[0]]) @ gt  # A's frame: its first camera
    cache = args.work / "recording.pkl"
    if cache.is_file() and (args.work / "B" / "metrics.json").is_file():
        links, initial, T_own_prior = pickle.loads(cache.read_bytes())
    else:
        links, initial, T_own_prior = run_recording(args.prior, args.seq, args.frames, args.work / "B")
        cache.write_bytes(pickle.dumps((links, initial, T_own_prior)))
    B = read_session(args.work / "B")
    fa, fb = A.frame_ids, B.frame_ids
    dev = lambda P, f: float(np.linalg.norm(P[:, :3, 3] - gt[f][:, :3, 3], axis=1).mean())  # noqa: E731
    held = read_poses(args.work / "B" / "poses_batch.txt")
    print(f"{len(links)} loops to A; A alone {dev(A.poses, fa):.3f} m, B with A held fixed {dev(held, fb):.3f} m")
    wa, wb = step_scale(A, gt), step_scale(B, gt)
    print("steps' errors in sigmas, RMS per axis (rot x y z, offset x y z): A", np.round(wa, 3), "B", np.round(wb, 3))
    sel: dict[str, Callable[[int], bool]] = {"every loop": lambda j: True, f"loops to A < {args.split}": lambda j: j < args.split}
    sel[f"loops to A >= {args.split}"] = lambda j: j >= args.split
    joint: dict[str, np.ndarray] = {}
    for name, keep in sel.items():
        joint[name], b = solve(A, B, [lk for lk in links if keep(lk[0])], initial, T_own_prior)
        print(f"joint, {name}: A {dev(joint[name], fa):.3f} m, B {dev(b, fb):.3f} m")
    for name, kw in (
        ("steps scaled to their true size", {"scales": (wa, wb)}),
        ("loops x10", {"link_scale": 10.0}),
        ("loops x100", {"link_scale": 100.0}),
        (f"B's odometry only within its revisits (loops < {args.gap} frames apart)", {"gap": args.gap}),
    ):
        a, b = solve(A, B, links, initial, T_own_prior, **kw)  # type: ignore[arg-type]
        print(f"joint, every loop, {name}: A {dev(a, fa):.3f} m, B {dev(b, fb):.3f} m")
    print("A per 100 frames, alone / joint (every loop), m:")
    for s in range(0, len(fa), 100):
        sl = slice(s, s + 100)
        print(f"  {fa[s]:5d}: {dev(A.poses[sl], fa[sl]):.2f} / {dev(joint['every loop'][sl], fa[sl]):.2f}")
    E, _ = step_errors(A, gt)
    E = E[: len(E) // 200 * 200]
    ratio = E.reshape(-1, 200, 6).sum(1).var(0) / (200 * E.var(0))
    print("A's steps: variance of a 200-step sum over 200 x a step's, per axis (1: independent):", np.round(ratio, 2))


if __name__ == "__main__":
    main()
