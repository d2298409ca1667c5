"""How much of a run's error could loop closure remove at all? The ground-truth loop oracle.

Reads a results folder written by ``snaps-graph run`` (poses_vo.txt, frames.csv, and whichever
of poses_snaps / poses_isam2 / poses_batch it has) and the ground truth, then prints:

* the mean deviation (the paper's figure, no alignment) and ATE of each trajectory;
* the oracle: the same pose graph (the run's VO steps with their inlier noise) with an *exact*
  ground-truth loop factor at every true revisit (benchmarks/oracle.py), batch
  optimised; under the run's candidate geometry (radius, frame distance, yaw), and under a
  generous one (30 m, any heading) with 100x tighter loop factors and no robust kernel;
* how the VO's mean deviation falls when its pose at frame k is re-anchored on the ground truth,
  i.e. without the heading and position error it had accrued by frame k;
* the run's own graph (VO steps, the loops of loops.jsonl) rebuilt and batch-optimised from the
  SNAPS poses.

No detector can give more or better loops than the oracle, so its reduction is what loop
closure can reach on this VO; the rest is error the loops do not observe. Writes
``loop_oracle.md`` into the run folder.

    python experiments/loop_oracle.py results/bench/run00 [--gt GT] [--step 5]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.metrics import ate_rmse, mean_deviation
from snaps_graph.evaluation.results_io import frame_ids, read_frames_csv, read_loops
from snaps_graph.geometry import rotation_angle_deg
from snaps_graph.trajectory_io import read_poses

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from oracle import loop_oracle, odometry_graph


def md_table(header: list[str], rows: list[list]) -> str:
    def fmt(v) -> str:
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]) + "\n"


def frame_columns(run: Path, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """frames.csv's VO inlier counts, VO flags and dataset frame numbers."""
    cols = read_frames_csv(run / "frames.csv")
    rows = len(cols["vo_inliers"])
    if rows != n:
        raise SnapsGraphError(f"{run / 'frames.csv'} has {rows} rows, poses_vo.txt {n}")
    return cols["vo_inliers"].astype(int), cols["vo_ok"] == 1, frame_ids(cols, rows, run / "frames.csv")


def rebuilt_batch(run: Path, cfg: Config, vo: np.ndarray, inliers: np.ndarray, ok: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The run's graph rebuilt from its files (VO steps, loops.jsonl), batch-optimised from the
    SNAPS poses (the initial estimates a run uses)."""
    init = read_poses(run / "poses_snaps.txt") if (run / "poses_snaps.txt").is_file() else vo
    graph = odometry_graph(vo, cfg, inliers, ok, initial=init)
    for loop in read_loops(run / "loops.jsonl", {int(f): k for k, f in enumerate(ids)}):
        T = None
        if loop.get("verified") and loop.get("T_ref_cur"):
            T = np.eye(4)
            T[:3, :4] = np.array(loop["T_ref_cur"], float).reshape(3, 4)
        graph.add_loop(loop["reference_row"], loop["row"], loop["q"], T)
    return graph.optimize_batch()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="results folder of snaps-graph run")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth (default RUN/poses_gt.txt)")
    ap.add_argument("--step", type=int, default=5, help="one oracle loop every STEP revisiting frames")
    args = ap.parse_args()
    run = args.run
    try:
        gt = read_poses(args.gt or run / "poses_gt.txt")
        vo = read_poses(run / "poses_vo.txt")
        if len(gt) != len(vo):
            raise SnapsGraphError(f"ground truth has {len(gt)} poses, poses_vo.txt {len(vo)}")
        inliers, ok, ids = frame_columns(run, len(vo))
        cfg = Config.load(run / "config.toml") if (run / "config.toml").is_file() else Config()
    except (OSError, SnapsGraphError) as exc:
        sys.exit(f"error: {exc}")

    rows = []
    vo_md = mean_deviation(vo, gt)
    for name in ("vo", "snaps", "isam2", "batch"):
        path = run / f"poses_{name}.txt"
        if path.is_file():
            est = read_poses(path)
            md = mean_deviation(est, gt)
            rows.append([name, "", md, 100 * (md / vo_md - 1), ate_rmse(est, gt)])

    o = loop_oracle(vo, gt, cfg, inliers, ok, step=args.step)
    rows.append(
        [
            "oracle",
            f"{len(o.pairs)} exact loops, run's geometry",
            o.mean_deviation,
            100 * (o.mean_deviation / vo_md - 1),
            o.ate_rmse,
        ]
    )
    wide = copy.deepcopy(cfg)
    wide.loop.radius_m = 30.0
    wide.graph.robust_kernel = "none"
    wide.graph.loop_sigma_rot_rad, wide.graph.loop_sigma_trans_m = 1e-4, 1e-3
    ow = loop_oracle(vo, gt, wide, inliers, ok, step=args.step, max_yaw_deg=180.0)
    rows.append(
        [
            "oracle, generous",
            f"{len(ow.pairs)} exact loops, 30 m, any heading, 100x tighter",
            ow.mean_deviation,
            100 * (ow.mean_deviation / vo_md - 1),
            ow.ate_rmse,
        ]
    )

    est = rebuilt_batch(run, cfg, vo, inliers, ok, ids)
    md = mean_deviation(est, gt)
    rows.append(["batch, rebuilt", "the run's", md, 100 * (md / vo_md - 1), ate_rmse(est, gt)])

    anchor_rows = []
    for k in (0, 10, 50, 100, 200, 400):
        if k >= len(vo):
            break
        A = gt[k] @ np.linalg.inv(vo[k])
        heading = rotation_angle_deg(gt[k][:3, :3].T @ vo[k][:3, :3])
        md = mean_deviation(A @ vo, gt)
        anchor_rows.append([k, heading, md, 100 * (md / vo_md - 1)])

    text = f"# Loop-closure oracle for {run}\n\nCommand: `python experiments/loop_oracle.py {run}`\n\n"
    text += md_table(["trajectory", "loops", "mean dev m", "vs VO %", "ATE m"], rows)
    text += "\nVO re-anchored on the ground truth at frame k (its error before k removed):\n\n"
    text += md_table(["k", "VO rotation error at k, deg", "mean dev m", "vs VO %"], anchor_rows)
    (run / "loop_oracle.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
