"""Front-end scale bias: step-length bias and end drift of stereo VO alone, per sequence folder.

For each KITTI-layout sequence folder (real, or written by ``snaps-graph synth``) runs the
front end (``StereoOdometry``, what ``snaps-graph run --loops none --refine none`` runs) over
the frames and prints

* step-length bias: sum of VO step lengths / sum of ground-truth step lengths - 1 (%): a
  front end that reads far points as too far overestimates every step;
* end drift: |p_end_vo - p_end_gt| / ground-truth path length (%);
* ATE RMSE (SE(3)-aligned, m) and the number of flagged frames;
* the disparity offset the front end applied at the end (px, measured - true; the default
  estimates it online, mode "no_offset" does not).

    python benchmarks/bench_scale_bias.py results/data/street00_1000 results/data/open00_1000
    python benchmarks/bench_scale_bias.py SEQ --modes default,sift,orb
    python benchmarks/bench_scale_bias.py SEQ --stride 2     # every 2nd frame: twice the speed
    python benchmarks/bench_scale_bias.py SEQ --stride 3 --gaps   # same, original indices (gaps of 3)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import ate_rmse, path_length
from snaps_graph.frontend import StereoOdometry
from snaps_graph.types import StereoFrame

# [frontend] values per mode, a nested section as a dict (as in a config file)
MODES = {
    "default": dict(),
    "sift": dict(mode="sift"),
    "orb": dict(mode="orb"),
    "paper": dict(mode="sift", disparity="bm_wls", sift_first_octave=-1, motion="pnp", local_ba=dict(enabled=False)),
    "no_offset": dict(offset=dict(estimate=False)),  # the default without the online disparity offset estimate
    "no_weak": dict(klt=dict(weak_points=0)),  # the default without the weak-texture corner detection
}


def step_bias(est: np.ndarray, gt: np.ndarray) -> float:
    """sum |dt_est| / sum |dt_gt| - 1 over consecutive frames."""
    se = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1).sum()
    sg = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    return float(se / max(sg, 1e-12) - 1.0)


def run(seq: KittiSequence, overrides: dict, stride: int = 1, gaps: bool = False) -> tuple[np.ndarray, int, float, float]:
    cfg = Config().merged({"frontend": overrides}, "--modes")
    t0 = time.perf_counter()
    with StereoOdometry(seq.camera, cfg.frontend) as vo:
        res = []
        for j, i in enumerate(range(0, len(seq), stride)):
            f = seq[i]  # numbered as a recording of the faster drive would be (the front end reads the index)
            res.append(vo.process(f if gaps else StereoFrame(j, f.timestamp, f.left, f.right)))
    offset = res[-1].disparity_offset_px if res else 0.0
    return np.array([r.pose for r in res]), sum(not r.ok for r in res), time.perf_counter() - t0, offset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seqs", nargs="+", help="sequence folders (image_0/, image_1/, calib.txt, poses.txt)")
    ap.add_argument("--frames", default=None, help="A:B (default: all)")
    ap.add_argument("--modes", default="default", help=f"comma list of {', '.join(MODES)}")
    ap.add_argument("--stride", type=int, default=1, help="use every STRIDE-th frame (a faster drive)")
    ap.add_argument(
        "--gaps", action="store_true", help="with --stride: keep the original frame indices (index gaps), not 0,1,2,..."
    )
    args = ap.parse_args()
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in modes:
        if m not in MODES:
            sys.exit(f"error: --modes: unknown mode '{m}' ({', '.join(MODES)})")
    if args.stride < 1:
        sys.exit("error: --stride must be >= 1")
    print(
        f"{'sequence':<34}{'mode':<9}{'frames':>7}{'path m':>9}{'step bias %':>13}{'end drift %':>13}{'ATE m':>8}{'flagged':>9}{'fps':>7}{'offset px':>11}"
    )
    for path in args.seqs:
        seq = KittiSequence(path, frames=args.frames)
        gt = seq.gt_poses
        if gt is not None:
            gt = gt[:: args.stride]
        if gt is None:
            print(f"{path}: no ground truth, skipped")
            continue
        for m in modes:
            est, flagged, wall, offset = run(seq, MODES[m], args.stride, args.gaps)
            drift = 100.0 * np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) / max(path_length(gt), 1e-9)
            print(
                f"{str(path)[-34:]:<34}{m:<9}{len(gt):>7}{path_length(gt):>9.1f}{100 * step_bias(est, gt):>13.2f}"
                f"{drift:>13.2f}{ate_rmse(est, gt):>8.3f}{flagged:>9}{len(gt) / wall:>7.1f}{offset:>+11.3f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
