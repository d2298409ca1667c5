"""What a loop corrects and what it cannot: relative rotations against absolute tilt, per frame.

Re-solves a run's graph.g2o as the run does (bench_model_resolve.solve_factors) and
prints, for VO and the refined trajectory: the rotation error (deg, camera axes x = pitch,
y = heading, z = roll) between frame pairs ``--pairs A-B ...`` against the ground truth, and at
frames ``--frames`` the vertical error (m) and the pitch error relative to frame 0. A loop fixes
the relative rotations it spans; an absolute tilt carried in from before every loop stays, and
correcting a relative error that had cancelled it makes the height worse. Why it matters:
docs/loop-closure.md, "Where the refinement stops".

    python experiments/tilt_exposure.py RUN --pairs 917-922 976-989 976-4239 --frames 976 990 1992
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_model_resolve import load_run, solve_factors


def rotation_error_deg(P: np.ndarray, gt: np.ndarray, a: int, b: int) -> np.ndarray:
    """The rotation of est(a->b) against true(a->b) as a rotation vector in frame b, deg."""
    E = np.linalg.solve(np.linalg.solve(gt[a], gt[b]), np.linalg.solve(P[a], P[b]))
    return np.degrees(Rotation.from_matrix(E[:3, :3]).as_rotvec())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("run", type=Path, help="a results folder of `snaps-graph run --refine batch` with ground truth")
    ap.add_argument("--pairs", nargs="+", default=[], metavar="A-B", help="frame pairs whose relative rotation to print")
    ap.add_argument("--frames", nargs="+", type=int, default=[], help="frames whose height and pitch error to print")
    args = ap.parse_args(argv)
    loaded = load_run(args.run)
    if loaded is None:
        return 2
    cfg, gt, vo, heuristic, odo, loops = loaded
    refined, _ = solve_factors(odo, loops, heuristic, cfg)
    fmt = lambda v: " ".join(f"{x:+6.2f}" for x in v)  # noqa: E731
    print("relative rotation error, deg (pitch heading roll): VO | refined")
    for pair in args.pairs:
        a, b = (int(v) for v in pair.split("-"))
        print(f"  {a:5d} -> {b:5d}  {fmt(rotation_error_deg(vo, gt, a, b))} | {fmt(rotation_error_deg(refined, gt, a, b))}")
    print("frame: vertical error m, pitch error since frame 0 deg: VO | refined")
    for k in args.frames:
        rows = [(P[k, 1, 3] - gt[k, 1, 3], rotation_error_deg(P, gt, 0, k)[0]) for P in (vo, refined)]
        print(f"  {k:5d}  {rows[0][0]:+7.2f} {rows[0][1]:+6.2f} | {rows[1][0]:+7.2f} {rows[1][1]:+6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
