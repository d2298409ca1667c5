"""Can a revisit's start be verified? The frames before each revisit's first verified loop, tried.

Reads a results folder of ``snaps-graph run`` (loops.jsonl, frames.csv, poses_gt.txt,
config.toml) and the sequence it ran on. For each revisit's first verified loop (no verified loop
in the ``inter_frame_pause`` frames before it) it takes the frames ``reference_every``,
2 ``reference_every``, ... up to ``--back`` frames before it and verifies each as the run
verifies a current frame (its own loop keypoints, the stereo depth check) against every stored
reference (every ``reference_every``-th frame) within ``--span`` frames of the earlier pass's
frame nearest to it in the ground truth; a verified pose more than ``max_distance_m`` from the
reference is refused, as in a run. Prints per frame that distance, the references tried and
those that verify, with their ground-truth distance. Why it matters: docs/loop-closure.md,
"Where the refinement stops".

    python experiments/revisit_start.py RUN SEQ [--back 50] [--span 40]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.results_io import read_frames_csv, read_loops
from snaps_graph.trajectory_io import read_poses
from snaps_graph.verification.features import MAX_DISTANCE_M, REFERENCE_EVERY, LoopFeatureBank, verify_features


def first_loops(run: Path, row: dict[int, int], pause: int) -> list[tuple[int, int]]:
    """(row, reference row) of frames.csv of each verified loop with no verified loop in the
    ``pause`` frames before it."""
    loops = read_loops(run / "loops.jsonl", row)
    verified = sorted((d["row"], d["reference_row"]) for d in loops if d.get("verified"))
    out, last = [], None
    for n, r in verified:
        if last is None or n - last > pause:
            out.append((n, r))
        last = n
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("seq", type=Path)
    ap.add_argument("--back", type=int, default=50, help="frames before the first loop to try")
    ap.add_argument("--span", type=int, default=40, help="references within this many frames of the nearest one")
    args = ap.parse_args()
    cfg = Config.load(args.run / "config.toml")
    seq = KittiSequence(args.seq)
    cam = seq.camera
    gt = read_poses(args.run / "poses_gt.txt")[:, :3, 3]
    frames = read_frames_csv(args.run / "frames.csv")
    ids = [int(i) for i in frames["frame"]]
    row = {f: k for k, f in enumerate(ids)}
    offset = frames["vo_disparity_offset_px"]
    every = REFERENCE_EVERY
    bank = LoopFeatureBank(cam, cfg.frontend, cfg.verification, background=False)
    added: set[int] = set()  # references computed (a frame with too few stereo points stores none)
    for kn, kr0 in first_loops(args.run, row, cfg.loop.inter_frame_pause):
        print(f"first verified loop {ids[kn]} -> {ids[kr0]} (ground truth {np.linalg.norm(gt[kn] - gt[kr0]):.1f} m apart)")
        for km in range((kn - 1) // every * every, kn - args.back - 1, -every):
            earlier = km - cfg.loop.frame_distance
            if earlier <= 0:
                break
            d = np.linalg.norm(gt[: earlier + 1] - gt[km], axis=1)
            near = int(np.argmin(d))
            frame = seq[km]
            query = bank.query(km, frame)
            tried, passed = 0, []
            lo = max(0, near - args.span)
            for kr in range(lo + (-lo) % every, min(earlier, near + args.span) + 1, every):
                if kr not in added:
                    bank.add(kr, seq[kr])
                    added.add(kr)
                m = verify_features(bank.reference(kr), query, frame, cam, cfg.frontend, cfg.verification, float(offset[km]))
                tried += 1
                if m is not None and np.linalg.norm(m.T_ref_cur[:3, 3]) <= MAX_DISTANCE_M:
                    passed.append(f"{ids[kr]} ({np.linalg.norm(gt[kr] - gt[km]):.1f} m, {m.inliers} inliers)")
            print(
                f"  frame {ids[km]}: nearest earlier frame {ids[near]} at {d[near]:.1f} m; "
                f"{tried} references tried, {len(passed)} verify{': ' + ', '.join(passed) if passed else ''}"
            )
    bank.close()


if __name__ == "__main__":
    main()
