"""Whole-run accuracy of the heuristic and the refined trajectory under drifted odometry, many seeds.

For each real driving path (KITTI ground truth, ``--paths``), each drift level (``--pct``) and each
seed, the drift tool makes the odometry; SNAPS runs on it with a verification oracle (a candidate
verifies when the ground truth puts it within ``MAX_DISTANCE_M`` (the verification's); its measurement is
the true relative pose plus noise of a real verification's size), so every loop is a true one and
what is measured is what the correction and the graph make of them. No images are rendered: all
frames share one texture, so the similarity passes and the drift gate and verification decide.

Printed per run and summarised per path: the whole-run mean deviation (3D, horizontal, vertical)
of the odometry, the heuristic (SNAPS) and the batch-refined trajectory, and beside them the same
graph solved with the process the drift tool really used ("allowed": what the loops allow).

    python benchmarks/bench_drift_graph.py [--paths 00,02,07,09,00@0:1700] [--pct 1,2] [--seeds 10]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from snaps_graph.backend.pose_graph import PoseGraph
from snaps_graph.config import Config
from snaps_graph.drift_model import DriftModel
from snaps_graph.evaluation.drift import drift_process, drift_trajectory
from snaps_graph.frontend.external import PoseFileOdometry
from snaps_graph.loop.snaps import SnapsLoopCloser
from snaps_graph.trajectory_io import PoseFile, read_poses
from snaps_graph.types import StereoFrame
from snaps_graph.verification.features import MAX_DISTANCE_M, REFERENCE_EVERY

GT_DIR = ROOT.parent / "shared" / "data" / "kitti_gt"
LOOP_NOISE_ROT_RAD = 0.002  # a real verification's errors (docs/loop-closure.md, verification accuracy)
LOOP_NOISE_TRANS_M = 0.03
IMAGE = (np.random.default_rng(0).random((120, 360)) * 255).astype(np.uint8)


def parse_path(spec: str) -> tuple[str, int, int | None]:
    name, _, rng = spec.partition("@")
    if not rng:
        return name, 0, None
    a, _, b = rng.partition(":")
    return name, int(a), int(b) if b else None


def parts(poses: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    d = poses[:, :3, 3] - gt[:, :3, 3]
    return float(np.linalg.norm(d, axis=1).mean()), float(np.hypot(d[:, 0], d[:, 2]).mean()), float(np.abs(d[:, 1]).mean())


class GroundTruthVerifier:
    """Verifies a candidate of the current frame when the ground truth puts it within the
    verification's distance; its measurement is the true relative pose with noise."""

    def __init__(self, gt: np.ndarray, rng: np.random.Generator):
        self.gt, self.rng, self.current = gt, rng, 0

    def verify(self, ref: int):
        from scipy.spatial.transform import Rotation

        T = np.linalg.solve(self.gt[ref], self.gt[self.current])
        if np.linalg.norm(T[:3, 3]) > MAX_DISTANCE_M:
            return None
        noise = np.eye(4)
        noise[:3, :3] = Rotation.from_rotvec(self.rng.normal(0, LOOP_NOISE_ROT_RAD, 3)).as_matrix()
        noise[:3, 3] = self.rng.normal(0, LOOP_NOISE_TRANS_M, 3)
        return T @ noise, 200


def run_one(spec: str, pct: float | None, seed: int, config: str | None, model: DriftModel) -> dict:
    name, a, b = parse_path(spec)
    gt_all = read_poses(GT_DIR / f"{name}.txt")
    gt = gt_all[a:b]
    gt = np.linalg.inv(gt[0]) @ gt  # the run starts at the identity
    odo = drift_trajectory(gt, seed, model, pct=pct)
    cfg = Config.load(config) if config else Config()
    n = len(gt)
    track = PoseFile("drift", "kitti", np.arange(n), odo, np.arange(1, n + 1))
    front = PoseFileOdometry(track, cfg.odometry)
    verifier = GroundTruthVerifier(gt, np.random.default_rng(1000 + seed))
    snaps = SnapsLoopCloser(cfg.loop, cfg.odometry, REFERENCE_EVERY, verifier=verifier)
    graph = PoseGraph(cfg.graph, mode="batch", drift=cfg.odometry.model())
    loop_cov = np.diag([LOOP_NOISE_ROT_RAD**2] * 3 + [LOOP_NOISE_TRANS_M**2] * 3)
    steps: list[tuple[np.ndarray, np.ndarray | None]] = []
    loops: list[tuple[int, int, np.ndarray]] = []
    at_loops: list[tuple[float, float]] = []  # (reference error, current frame's error) when a loop corrects
    last = np.eye(4)
    for k in range(n):
        vo = front.process(StereoFrame(k, 0.1 * k, IMAGE, IMAGE))
        verifier.current = k
        before = last @ vo.T_rel if k else np.eye(4)
        step = snaps.step(k, vo.T_rel, IMAGE)
        last = step.pose
        if step.loop is not None and step.loop.T_ref_cur is not None:
            ref = step.loop.reference
            at_loops.append(
                (
                    float(np.linalg.norm(snaps.traj.p[ref] - gt[ref][:3, 3])),
                    float(np.linalg.norm(before[:3, 3] - gt[k][:3, 3])),
                )
            )
        graph.add_frame(k, step.pose, None if k == 0 else vo.T_rel, inliers=vo.inliers, ok=vo.ok, cov=vo.cov)
        steps.append((vo.T_rel, vo.cov))
        if step.loop is not None:
            info = graph.add_loop(step.loop.reference, k, step.loop.q, step.loop.T_ref_cur, covariance=loop_cov)
            if info.added and step.loop.T_ref_cur is not None:
                loops.append((step.loop.reference, k, step.loop.T_ref_cur))
    heur = snaps.poses
    graph.set_initial_estimates(heur)
    t0 = time.perf_counter()
    batch = graph.optimize_batch()
    batch_s = time.perf_counter() - t0
    # What the loops allow: the same loops on a graph whose odometry noise is the drift tool's own process.
    true_model = drift_process(gt, seed, model, pct=pct)
    allowed = PoseGraph(cfg.graph, mode="batch", drift=true_model)
    for k in range(n):
        allowed.add_frame(k, heur[k], None if k == 0 else steps[k][0], cov=None if k == 0 else np.zeros((6, 6)))
    for r, c, T in loops:
        allowed.add_loop(r, c, 1.0, T, covariance=loop_cov)
    opt = allowed.optimize_batch()
    return {
        "path": spec,
        "pct": pct,
        "seed": seed,
        "loops": len(loops),
        "odo": parts(odo, gt),
        "heur": parts(heur, gt),
        "batch": parts(batch, gt),
        "allowed": parts(opt, gt),
        "iterations": graph.stats.batch_iterations,
        "batch_s": batch_s,
        "failures": len(graph.failures),
        "at_loops": at_loops,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paths", default="00,02,07,09,00@0:1700", help="KITTI ground-truth paths NN or NN@A:B")
    ap.add_argument("--pct", default="1,2", help="drift levels, percent end drift")
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0 .. N-1")
    ap.add_argument("--config", default=None, help="a config TOML (default: the defaults)")
    ap.add_argument("--jobs", type=int, default=2, help="processes")
    ap.add_argument(
        "--model",
        default="",
        help="the drift tool's model: DriftModel fields as name=value,... (default: the defaults); "
        "--pct none drives it unscaled (a systematic drift: heading_deg_per_100m=0.4,scale_pct=1)",
    )
    args = ap.parse_args()
    model = DriftModel(**{k: float(v) for k, v in (kv.split("=") for kv in args.model.split(",") if kv)})
    pcts = [None if x == "none" else float(x) for x in args.pct.split(",")]
    jobs = [(p, x, s) for p in args.paths.split(",") for x in pcts for s in range(args.seeds)]
    with ProcessPoolExecutor(args.jobs) as ex:
        futs = [ex.submit(run_one, p, x, s, args.config, model) for p, x, s in jobs]
        rows = [f.result() for f in futs]
    print(
        "path        pct seed loops | odometry 3D/hor/vert m | heur/odo 3D hor vert | batch/odo 3D hor vert | batch/heur | allowed/odo | iters"
    )
    for r in rows:
        o, h, b, al = r["odo"], r["heur"], r["batch"], r["allowed"]
        print(
            f"{r['path']:10s} {str(r['pct']):>4s} {r['seed']:4d} {r['loops']:5d} | {o[0]:6.2f} {o[1]:6.2f} {o[2]:5.2f} | "
            f"{h[0] / o[0]:5.2f} {h[1] / o[1]:5.2f} {h[2] / max(o[2], 1e-9):5.2f} | "
            f"{b[0] / o[0]:5.2f} {b[1] / o[1]:5.2f} {b[2] / max(o[2], 1e-9):5.2f} | {b[0] / h[0]:5.2f} | "
            f"{al[0] / o[0]:5.2f} | {r['iterations']}"
        )
    print()
    print("summary over runs with a loop (3D unless said):")
    looped = [r for r in rows if r["loops"] > 0]
    if not looped:
        print("  no run closed a loop")
        return
    rb_h = [r["batch"][0] / r["heur"][0] for r in looped]
    rb_o = [r["batch"][0] / r["odo"][0] for r in looped]
    rh_o = [r["heur"][0] / r["odo"][0] for r in looped]
    print(f"  runs {len(rows)}, with a loop {len(looped)}")
    print(
        f"  refined <= heuristic in {sum(x <= 1.0 for x in rb_h)}/{len(looped)} ({100 * sum(x <= 1.0 for x in rb_h) / len(looped):.0f} %)"
    )
    print(
        f"  refined / odometry: median {statistics.median(rb_o):.2f}, max {max(rb_o):.2f} (runs above 1.05: {sum(x > 1.05 for x in rb_o)})"
    )
    print(
        f"  heuristic / odometry: median {statistics.median(rh_o):.2f}, max {max(rh_o):.2f} (runs above 1.0: {sum(x > 1.0 for x in rh_o)})"
    )
    for i, what in ((1, "horizontal"), (2, "vertical")):
        ratios = [r["batch"][i] / max(r["odo"][i], 1e-9) for r in looped]
        print(f"  refined / odometry {what}: median {statistics.median(ratios):.2f}")
    al = [r["allowed"][0] / r["odo"][0] for r in looped]
    print(f"  allowed / odometry (graph with the true process): median {statistics.median(al):.2f}")
    both = [r for r in looped if r["allowed"][0] <= r["heur"][0]]
    print(
        f"  allowed <= heuristic in {len(both)}/{len(looped)}; refined <= heuristic in "
        f"{sum(r['batch'][0] <= r['heur'][0] for r in both)} of those"
    )
    print(
        f"  refined above 1.05 x odometry while allowed is not: "
        f"{sum(r['batch'][0] > 1.05 * r['odo'][0] and r['allowed'][0] <= 1.05 * r['odo'][0] for r in looped)}"
    )
    print(
        "  heuristic above the odometry: at its loops, reference error vs current frame's error (mean m), "
        "and the best the loops allow (allowed / odometry)"
    )
    why = {"reference": 0, "allowed": 0, "neither": 0}
    for r in looped:
        if r["heur"][0] > r["odo"][0] and r["at_loops"]:
            ref_e = statistics.mean(a for a, _ in r["at_loops"])
            cur_e = statistics.mean(b for _, b in r["at_loops"])
            al_o = r["allowed"][0] / r["odo"][0]
            reason = "reference" if ref_e > cur_e else "allowed" if al_o > 1.0 else "neither"
            why[reason] += 1
            print(
                f"    {r['path']:10s} {str(r['pct']):>4s} seed {r['seed']}: heur/odo {r['heur'][0] / r['odo'][0]:.2f}, "
                f"reference {ref_e:.2f} vs current {cur_e:.2f}, allowed/odo {al_o:.2f}"
                f"{'  (neither)' if reason == 'neither' else ''}"
            )
    print(
        f"  of those: reference farther from the truth {why['reference']}, the loops allow no better than the "
        f"odometry {why['allowed']}, neither {why['neither']}"
    )
    for p in dict.fromkeys(r["path"] for r in rows):
        sel = [r for r in looped if r["path"] == p]
        if sel:
            print(
                f"  {p:10s} refined/odo median {statistics.median(r['batch'][0] / r['odo'][0] for r in sel):.2f}, "
                f"heur/odo {statistics.median(r['heur'][0] / r['odo'][0] for r in sel):.2f}, "
                f"allowed/odo {statistics.median(r['allowed'][0] / r['odo'][0] for r in sel):.2f}, "
                f"refined<=heur {sum(r['batch'][0] <= r['heur'][0] for r in sel)}/{len(sel)}"
            )


if __name__ == "__main__":
    main()
