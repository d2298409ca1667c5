"""SNAPS against VO on the rendered dev paths: the heuristic, the refined result and the loop oracle.

For each rendered sequence folder (``snaps-graph synth --trajectory ../shared/data/kitti_gt/NN.txt
... --out SEQ``, plain or with ``--aliasing --traffic --lighting``), runs ``snaps-graph run SEQ
--refine batch`` (or reuses the run in ``--work`` with ``--reuse``) and prints per path the VO's
3D mean deviation, horizontal and vertical mean deviation and ATE, then SNAPS's heuristic and the refined
(batch) trajectory as ratios to VO, the loop oracle beside them (the run's VO chain with an exact
loop factor at every true revisit, batch; benchmarks/oracle.py), the loops and the false
loops (references more than ``--false-m`` from the loop frame in the ground truth).

    python benchmarks/bench_loops_dev.py SEQ [SEQ ...] [--work DIR] [--reuse] [--config TOML]
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from oracle import loop_oracle

from snaps_graph.config import Config
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation
from snaps_graph.trajectory_io import read_poses


def figures(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """3D mean deviation, horizontal and vertical mean deviation, ATE (m) of ``est`` against ``gt``."""
    d = est[:, :3, 3] - gt[:, :3, 3]
    return np.array([mean_deviation(est, gt), np.hypot(d[:, 0], d[:, 2]).mean(), np.abs(d[:, 1]).mean(), ate_rmse(est, gt)])


def run_folder(seq: Path, out: Path, args) -> None:
    if args.reuse and (out / "metrics.json").is_file():
        return
    cmd = [sys.executable, "-m", "snaps_graph.cli", "run", str(seq), "--out", str(out), "--refine", "batch", "--overwrite"]
    if args.config is not None:
        cmd += ["--config", str(args.config)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode not in (0, 3):
        raise SystemExit(f"run failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr[-2000:]}")


def evaluate_run(run: Path, false_m: float) -> dict:
    gt = read_poses(run / "poses_gt.txt")
    vo = read_poses(run / "poses_vo.txt")
    with open(run / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    inliers = np.array([int(r["vo_inliers"]) for r in rows])
    ok = np.array([r["vo_ok"] == "1" for r in rows])
    k_of = {int(r["frame"]): k for k, r in enumerate(rows)}
    cfg = Config.load(run / "config.toml") if (run / "config.toml").is_file() else Config()
    out = {"vo": figures(vo, gt)}
    for name in ("snaps", "batch"):
        if (run / f"poses_{name}.txt").is_file():
            out[name] = figures(read_poses(run / f"poses_{name}.txt"), gt)
    o = loop_oracle(vo, gt, cfg, inliers, ok)
    out["oracle"] = figures(o.poses, gt)
    loops = [json.loads(line) for line in (run / "loops.jsonl").read_text().splitlines() if line.strip()]
    out["loops"] = len(loops)
    out["false"] = sum(np.linalg.norm(gt[k_of[lp["frame"]], :3, 3] - gt[k_of[lp["reference"]], :3, 3]) > false_m for lp in loops)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("seqs", type=Path, nargs="+", help="rendered sequence folders (image_0/, image_1/, calib.txt, poses.txt)")
    ap.add_argument("--work", type=Path, default=Path("results/bench_loops_dev"), help="where the runs go")
    ap.add_argument("--reuse", action="store_true", help="reuse a finished run in WORK instead of running again")
    ap.add_argument("--config", type=Path, default=None, help="a TOML config for every run")
    ap.add_argument("--false-m", type=float, default=10.0, help="a loop farther apart than this in the truth is false, m")
    args = ap.parse_args(argv)
    for seq in args.seqs:
        if not (seq / "image_0").is_dir():
            print(f"error: {seq}: not a sequence folder (no image_0/)", file=sys.stderr)
            return 2
    print("VO: metres (3D mean deviation / horizontal / vertical / ATE); the others: x VO")
    print(f"{'path':<16} {'VO m':>27} {'SNAPS x VO':>25} {'batch x VO':>25} {'oracle x VO':>25} {'loops':>5} {'false':>5}")
    for seq in args.seqs:
        name = seq.resolve().parent.name if seq.name == "sequence" else seq.name  # `snaps-graph demo` names it so
        run = args.work / name
        run_folder(seq, run, args)
        ev = evaluate_run(run, args.false_m)
        vo = ev["vo"]
        ratio = {
            key: " / ".join(f"{a / b:.2f}" for a, b in zip(ev[key], vo)) if key in ev else "n/a"
            for key in ("snaps", "batch", "oracle")
        }
        print(
            f"{name:<16} {' / '.join(f'{v:.3f}' for v in vo):>27} {ratio['snaps']:>25} {ratio['batch']:>25} {ratio['oracle']:>25} "
            f"{ev['loops']:5d} {ev['false']:5d}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
