"""The real revisit under drifted odometry: does SNAPS find it, and what do the loops give?

For each drift (percent of the distance driven, ``--pct``) and seed, the ground truth of KITTI 00
(frames 0 .. last image) goes through the drift tool (snaps_graph.evaluation.drift), and
``snaps-graph run SEQ --odometry DRIFTED --refine batch`` runs SNAPS on the real left images of
the revisit subset (frames 100-230, 1540-1660: ../shared/data/kitti00_loop). Per run it prints

* whether a verified loop closes inside the revisit (frames 1573-1630), and the loops' frames;
* false loops: accepted loops whose frames stand more than ``--false-m`` apart in the truth;
* the maximum recall at 100 % precision over compared pairs within ``--true-m`` (Q + verification,
  ``snaps-graph loops``);
* the mean deviation over frames 1560-1660 of the odometry, SNAPS's heuristic and the refined
  (batch) trajectory, and the two ratios against the odometry.

``--truth images`` drifts the odometry from, and measures against, the ground truth with its
second pass moved where the first pass's images put it (``revisit_reference.consistent_truth``):
KITTI's ground truth contradicts the images between the passes, so an odometry drifted from it
disagrees with every loop by the ground truth's own error. ``--search radius`` runs the paper's fixed radius instead of the drift-aware gate; ``--verify-all``
verifies every compared pair, so the recall covers every threshold; ``--set SECTION.KEY=VALUE``
sets another config key for every run. Results go to
``--work`` (default: a temporary folder, removed at the end).

    python benchmarks/bench_revisit.py [--data ../shared/data/kitti00_loop] [--pct 1 2] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _revisit import REVISIT, WINDOW, frame_ids, whole_run, window_deviation
from revisit_reference import consistent_truth, image_reference

from snaps_graph.evaluation.drift import drift_trajectory
from snaps_graph.evaluation.loops import label_pairs, loops_run, pr_curve, read_candidates_csv
from snaps_graph.trajectory_io import read_kitti_poses, write_kitti_poses

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT / ".." / "shared" / "data" / "kitti00_loop"


def one_run(seq: Path, gt_all: np.ndarray, truth_all: np.ndarray, pct: float, seed: int, work: Path, args) -> dict:
    """One drifted run; ``truth_all`` is what the odometry is drifted from and measured against
    (``gt_all`` itself, or with ``--truth images`` its image-consistent version)."""
    frames = frame_ids(seq)
    gt, truth = gt_all[: frames[-1] + 1], truth_all[: frames[-1] + 1]
    drifted = drift_trajectory(truth, seed, pct=pct)
    name = f"p{pct:g}_s{seed}_{args.search}" + ("_images" if args.truth == "images" else "")
    odo = work / f"{name}.txt"
    write_kitti_poses(odo, drifted)
    out = work / name
    cmd = [sys.executable, str(Path(__file__).with_name("_loop_research.py")), "--search", args.search]
    cmd += ["--verify-all"] if args.verify_all else []
    cmd += ["run", str(seq), "--odometry", str(odo), "--out", str(out), "--refine", "batch", "--overwrite"]
    for kv in args.set:
        cmd += ["--set", kv]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode not in (0, 3):
        raise SystemExit(f"run failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    loops = [json.loads(line) for line in (out / "loops.jsonl").read_text().splitlines() if line.strip()]
    ev = loops_run(out, None, true_m=args.true_m, false_m=args.false_m, png=out / "loops_pr.png")
    in_revisit = [lp for lp in loops if lp.get("verified") and REVISIT[0] <= lp["frame"] <= REVISIT[1]]
    false = [lp for lp in loops if np.linalg.norm(gt[lp["frame"], :3, 3] - gt[lp["reference"], :3, 3]) > args.false_m]
    run_gt = read_kitti_poses(out / "poses_gt.txt") if args.truth == "gt" else np.linalg.inv(truth[frames[0]]) @ truth[frames]
    # Why true pairs are missed: never verified because Q < min_similarity, or above it but not
    # tried (an earlier candidate at that frame verified first), or tried and failed.
    recs = read_candidates_csv(out / "candidates.csv")
    fr = np.array([[r.frame, r.reference] for r in recs], int).reshape(-1, 2)
    lab = label_pairs(np.linalg.norm(gt[fr[:, 0], :3, 3] - gt[fr[:, 1], :3, 3], axis=1), args.true_m, args.false_m)
    true = lab == 1
    above = np.array([r.above_threshold for r in recs], bool)
    tried = np.array([r.verify_tried for r in recs], bool)
    passed = np.array([r.verify_passed for r in recs], bool)
    inl = np.array([r.inliers for r in recs], int)
    q = np.array([r.q for r in recs], float)
    breakdown = {
        "frames_compared": len(set(fr[:, 0].tolist())),
        "true": int(true.sum()),
        "below": int((true & ~above).sum()),
        "untried": int((true & above & ~tried).sum()),
        "failed": int((true & tried & ~passed).sum()),
        "verified": int((true & passed).sum()),
        "false_verified": int(((lab == 0) & passed).sum()),
        "false_inliers_max": int(inl[(lab == 0) & passed].max()) if ((lab == 0) & passed).any() else 0,
        "true_inliers_min": int(inl[true & passed].min()) if (true & passed).any() else 0,
        "recall_floor": {fl: pr_curve(q, lab, passed & (inl >= fl))["max_recall_at_100_precision"] for fl in args.inlier_floor},
    }
    est, whole = {}, {}
    for traj in ("vo", "snaps", "batch"):
        f = out / f"poses_{traj}.txt"
        if f.is_file():
            est[traj] = window_deviation(read_kitti_poses(f), run_gt, frames)
            whole[traj] = whole_run(read_kitti_poses(f), run_gt, frames)
    return {
        "pct": pct,
        "seed": seed,
        "loops": [(lp["frame"], lp["reference"], bool(lp.get("verified"))) for lp in loops],
        "closed_in_revisit": bool(in_revisit),
        "false_loops": len(false),
        "recall_p1": ev.get("max_recall_at_100_precision_verified"),
        "dev": est,
        "whole": whole,
        "breakdown": breakdown,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the kitti00_loop folder (sequences/00, poses/00.txt)")
    ap.add_argument("--pct", type=float, nargs="+", default=[1.0, 2.0], help="end drift, percent of the distance")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument(
        "--search",
        choices=["drift", "radius"],
        default="drift",
        help="the candidate gate: the drift policy's or the paper's radius",
    )
    ap.add_argument(
        "--truth",
        choices=("gt", "images"),
        default="gt",
        help="drift and measure from the ground truth, or from it with the second pass where the images put it",
    )
    ap.add_argument("--true-m", type=float, default=2.0, help="a compared pair within this is a true loop, m")
    ap.add_argument("--false-m", type=float, default=10.0, help="a loop between frames farther apart is false, m")
    ap.add_argument("--verify-all", action="store_true", help="verify every compared pair (the recall's full curve; same loops)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="another config setting (TOML value), e.g. loop.inter_frame_pause=10",
    )
    ap.add_argument(
        "--inlier-floor",
        type=int,
        nargs="*",
        default=[],
        help="also the recall counting only verifications with at least this many inliers",
    )
    ap.add_argument("--work", type=Path, default=None, help="keep the drifted files and runs here")
    args = ap.parse_args(argv)
    seq, gt_file = args.data / "sequences" / "00", args.data / "poses" / "00.txt"
    if not (seq / "image_0").is_dir() or not gt_file.is_file():
        print(f"error: {args.data}: no sequences/00/image_0 or poses/00.txt", file=sys.stderr)
        return 2
    gt_all = read_kitti_poses(gt_file)
    truth_all = consistent_truth(gt_all, image_reference()) if args.truth == "images" else gt_all
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_revisit_")
        work = Path(tmp.name)
    else:
        work = args.work
        work.mkdir(parents=True, exist_ok=True)
    print(f"search = {args.search}; deviation over frames {WINDOW[0]}-{WINDOW[1]}, m")
    print(
        f"{'pct':>4} {'seed':>4} {'revisit':>7} {'false':>5} {'R@P1':>5} {'odo':>7} {'snaps':>7} {'batch':>7} {'snaps/odo':>9} {'batch/odo':>9}  loops"
    )
    rows = []
    try:
        for pct in args.pct:
            for seed in args.seeds:
                r = one_run(seq, gt_all, truth_all, pct, seed, work, args)
                rows.append(r)
                d = r["dev"]
                odo, sn, ba = d.get("vo", np.nan), d.get("snaps", np.nan), d.get("batch", np.nan)
                rec = r["recall_p1"]
                loops = " ".join(f"{f}->{j}{'' if v else '?'}" for f, j, v in r["loops"])
                print(
                    f"{pct:4g} {seed:4d} {'yes' if r['closed_in_revisit'] else 'NO':>7} {r['false_loops']:5d} "
                    f"{rec if rec is not None else float('nan'):5.2f} {odo:7.2f} {sn:7.2f} {ba:7.2f} {sn / odo:9.2f} {ba / odo:9.2f}  {loops}",
                    flush=True,
                )
                w = r["whole"]
                if "batch" in w:
                    print(
                        f"{'':9} whole run 3D / horizontal / vertical, m: odometry "
                        + " / ".join(f"{w['vo'][k]:.2f}" for k in ("3d", "hor", "vert"))
                        + "; heuristic "
                        + " / ".join(f"{w['snaps'][k]:.2f}" for k in ("3d", "hor", "vert"))
                        + "; refined "
                        + " / ".join(f"{w['batch'][k]:.2f}" for k in ("3d", "hor", "vert"))
                        + f"; first pass {w['vo']['first']:.2f} / {w['snaps']['first']:.2f} / {w['batch']['first']:.2f}",
                        flush=True,
                    )
                b = r["breakdown"]
                floors = " ".join(f"R@P1(inliers>={fl}) {v:.2f}" for fl, v in b["recall_floor"].items())
                print(
                    f"{'':9} frames compared {b['frames_compared']}; true pairs {b['true']}: Q < min_similarity {b['below']}, "
                    f"above but not tried {b['untried']}, failed {b['failed']}, verified {b['verified']} (inliers >= {b['true_inliers_min']}); "
                    f"false pairs verified {b['false_verified']} (inliers <= {b['false_inliers_max']}) {floors}",
                    flush=True,
                )
    finally:
        if tmp is not None:
            tmp.cleanup()
    closed = sum(r["closed_in_revisit"] for r in rows)
    false = sum(r["false_loops"] for r in rows)
    sn = [r["dev"]["snaps"] / r["dev"]["vo"] for r in rows if "snaps" in r["dev"]]
    ba = [r["dev"]["batch"] / r["dev"]["vo"] for r in rows if "batch" in r["dev"]]
    recs = [r["recall_p1"] for r in rows if r["recall_p1"] is not None]
    whole = [r["whole"] for r in rows if "batch" in r["whole"]]
    if whole:
        rb_h = [w["batch"]["3d"] <= w["snaps"]["3d"] for w in whole]
        rb_o = [w["batch"]["3d"] / w["vo"]["3d"] for w in whole]
        rh_o = [w["snaps"]["3d"] <= w["vo"]["3d"] for w in whole]
        print(
            f"whole run (3D): refined <= heuristic in {sum(rb_h)}/{len(whole)}; refined / odometry median "
            f"{float(np.median(rb_o)):.2f}, max {max(rb_o):.2f}; heuristic <= odometry in {sum(rh_o)}/{len(whole)}"
        )
    print(
        f"closed in the revisit {closed}/{len(rows)}; false loops {false}; recall@P1 min {min(recs) if recs else float('nan'):.2f}; "
        f"snaps/odo max {max(sn) if sn else float('nan'):.2f}; batch/odo max {max(ba) if ba else float('nan'):.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
