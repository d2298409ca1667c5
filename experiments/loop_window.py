"""What each loop's eq. 6 correction did along its window, and what a variant would have done.

Replays SNAPS's correction over a finished run (``snaps-graph run``'s poses_vo.txt, frames.csv,
loops.jsonl, config.toml, poses_gt.txt) with the run's own loops: detection is scripted (each
recorded loop frame shows its reference's texture, every other frame a texture of its own) and
verification returns the recorded T_ref_cur, so only the correction differs between variants.
Per loop and variant it prints the verified offset's error against the ground truth, the
applied move |delta|, the reference's and the loop frame's horizontal error before the loop, and
the mean horizontal error over the loop's window [reference + 1, N] before and after; then the
whole heuristic's 3D / horizontal mean deviation and ATE against VO.

    python experiments/loop_window.py RUN [--variant NAME:loop.key=value,...]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation
from snaps_graph.geometry import inv
from snaps_graph.loop import SnapsLoopCloser
from snaps_graph.loop.policy import POLICIES
from snaps_graph.trajectory_io import read_poses


def horizontal_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    d = est[:, :3, 3] - gt[:, :3, 3]
    return np.hypot(d[:, 0], d[:, 2])


class ScriptedVerifier:
    """Verifies the reference of the run's loop at the current frame with the run's measurement."""

    loop: dict | None = None

    def verify(self, ref: int) -> tuple[np.ndarray, int] | None:
        lp = self.loop
        if lp is None or ref != lp["reference"] or not lp.get("T_ref_cur"):
            return None
        T = np.eye(4)
        T[:3, :4] = np.array(lp["T_ref_cur"], float).reshape(3, 4)
        return T, int(lp.get("verify_inliers", 50))


def replay(run: Path, cfg: Config, verbose: bool) -> np.ndarray:
    vo = read_poses(run / "poses_vo.txt")
    gt = read_poses(run / "poses_gt.txt")
    with open(run / "frames.csv", newline="") as f:
        frames = [int(r["frame"]) for r in csv.DictReader(f)]
    k_of = {fr: k for k, fr in enumerate(frames)}
    loops = [json.loads(line) for line in (run / "loops.jsonl").read_text().splitlines() if line.strip()]
    loops = [lp for lp in loops if lp.get("weight", 1.0) > 0]  # graph-only loops move nothing
    script = {k_of[lp["frame"]]: lp for lp in loops}
    rng = np.random.default_rng(0)
    tex = {k: rng.integers(0, 255, (24, 48)).astype(np.uint8) for k in range(len(vo))}
    for k, lp in script.items():
        tex[k] = tex[k_of[lp["reference"]]]
    lc = cfg.loop
    lc.thumbnail_scale, lc.radius_m, lc.window = 1.0, 1e4, 8
    # The paper's radius gate, wide open: every scripted loop is a candidate.
    rule = dataclasses.replace(
        POLICIES["drift"], search="radius", max_yaw_deg=180.0, attempts=1000, search_max_radius_m=1e4, pause_graph_loops=False
    )
    verifier = ScriptedVerifier()
    closer = SnapsLoopCloser(lc, cfg.odometry, verifier=verifier, policy=rule)
    for k in range(len(vo)):
        T_rel = np.eye(4) if k == 0 else inv(vo[k - 1]) @ vo[k]
        lp = verifier.loop = script.get(k)
        before = closer.poses if lp is not None else None
        step = closer.step(frames[k], T_rel, tex[k])
        if lp is not None and verbose:
            j = k_of[lp["reference"]]
            after = closer.poses
            T = np.array(lp["T_ref_cur"], float).reshape(3, 4) if lp.get("T_ref_cur") else None
            off_err = float(np.linalg.norm(T[:, 3] - (inv(gt[j]) @ gt[k])[:3, 3])) if T is not None else float("nan")
            assert before is not None
            eb = horizontal_errors(np.concatenate([before, (before[-1] @ T_rel)[None]]), gt[: k + 1])
            ea = horizontal_errors(after, gt[: k + 1])
            d = step.loop.delta if step.loop is not None else np.zeros(3)
            print(
                f"  loop {lp['frame']}->{lp['reference']}: offset err {off_err:.3f} m, |delta| {np.linalg.norm(d):.2f} m, "
                f"h err ref {eb[j]:.2f} / N {eb[k]:.2f} -> {ea[k]:.2f} m, window mean {eb[j + 1 :].mean():.2f} -> {ea[j + 1 :].mean():.2f} m"
            )
    return closer.poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("run", type=Path)
    ap.add_argument("--variant", nargs="*", default=[], help="NAME:loop.key=value,... (base = the run's config)")
    args = ap.parse_args()
    gt = read_poses(args.run / "poses_gt.txt")
    vo = read_poses(args.run / "poses_vo.txt")
    variants = [("base", {})]
    for v in args.variant:
        name, _, sets = v.partition(":")
        variants.append((name, dict(kv.split("=", 1) for kv in sets.split(",") if kv)))
    vo_fig = (mean_deviation(vo, gt), float(horizontal_errors(vo, gt).mean()), ate_rmse(vo, gt))
    print(f"{args.run}: VO 3D {vo_fig[0]:.3f} / h {vo_fig[1]:.3f} / ATE {vo_fig[2]:.3f} m")
    if (args.run / "poses_snaps.txt").is_file():
        run_snaps = read_poses(args.run / "poses_snaps.txt")
        fig = (mean_deviation(run_snaps, gt), float(horizontal_errors(run_snaps, gt).mean()), ate_rmse(run_snaps, gt))
        print("  the run's SNAPS x VO: " + " / ".join(f"{a / b:.3f}" for a, b in zip(fig, vo_fig)))
    for name, sets in variants:
        cfg = Config.load(args.run / "config.toml") if (args.run / "config.toml").is_file() else Config()
        for key, value in sets.items():
            section, _, field = key.partition(".")
            sec = getattr(cfg, section)
            cur = getattr(sec, field)
            setattr(sec, field, type(cur)(value) if not isinstance(cur, bool) else value == "true")
        print(f"variant {name}:")
        est = replay(args.run, cfg, verbose=True)
        fig = (mean_deviation(est, gt), float(horizontal_errors(est, gt).mean()), ate_rmse(est, gt))
        print("  SNAPS x VO (3D / horizontal / ATE): " + " / ".join(f"{a / b:.3f}" for a, b in zip(fig, vo_fig)))


if __name__ == "__main__":
    main()
