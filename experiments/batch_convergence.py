"""Where does the batch refinement stop, and where would it go converged? A run's graph re-solved.

Reads a results folder of ``snaps-graph run --refine batch`` (graph.g2o, poses_snaps/vo/gt.txt,
frames.csv, config.toml) and re-solves its graph (the factors as written, the loops under the
run's robust kernel again, from the SNAPS poses as the run does) with the run's Levenberg-Marquardt
stop and to convergence, with the flagged VO steps at their sigmas and at ``--flagged-scale``
times the reference sigmas instead; the ground-truth loop oracle (benchmarks/oracle.py)
likewise. Prints 3D mean deviation / horizontal / vertical / ATE as multiples of VO's, and the
iterations. ``--exact-loops`` and ``--add-oracle A-B`` solve once instead (flagged at
``--flagged-scale``, converged): the run's loops measured by the ground truth instead, and the
oracle's exact loops whose current frame lies in A..B added. ``--oracle-skip A-B`` leaves out of
the oracle its loops whose current frame lies in A..B (frames no verification measures:
experiments/revisit_start.py). Why it matters: docs/loop-closure.md, "Where the refinement stops".

    python experiments/batch_convergence.py RUN [RUN ...] [--flagged-scale 10]
    python experiments/batch_convergence.py RUN --exact-loops [--add-oracle 4200-4300]
    python experiments/batch_convergence.py RUN --oracle-skip 4150-4237
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from snaps_graph.backend import noise
from snaps_graph.backend.pose_graph import batch_params
from snaps_graph.config import Config
from snaps_graph.evaluation.results_io import read_frames_csv
from snaps_graph.trajectory_io import read_poses

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_loops_dev import figures
from bench_model_resolve import factors, solve_factors
from oracle import REVISIT_MAX_YAW_DEG, odometry_graph, true_revisit_pairs

CONVERGED_TOL = 1e-10  # relative and absolute error decrease at which "converged" stops
CONVERGED_MAX_ITERATIONS = 2000


def solve_g2o(
    g2o: Path,
    init: np.ndarray,
    cfg: Config,
    flagged: np.ndarray,
    flag_gain: float,
    converge: bool,
    exact: np.ndarray | None = None,
    extra: Sequence[tuple[int, int]] = (),
):
    """Re-solve a written graph: (poses, iterations). Loops (non-consecutive keys) get the
    run's kernel back; a flagged step's information is multiplied by ``flag_gain``. With ``exact``
    (ground-truth poses) every loop measures the truth, and the pairs ``extra`` are added as exact
    loops at the tightest noise a verified loop gets."""
    odo, loops = factors(g2o)
    odo = [(a, b, T, C / flag_gain if flagged[b] else C) for a, b, T, C in odo]
    if exact is not None:
        loops = [(a, b, np.linalg.solve(exact[a], exact[b]), C) for a, b, _, C in loops]
    if extra:
        assert exact is not None
        tight = noise.loop_covariance(cfg.graph, np.zeros((6, 6)))
        loops += [(j, k, np.linalg.solve(exact[j], exact[k]), tight) for j, k in extra]
    params = batch_params()  # the run's own stop
    if converge:
        params.setMaxIterations(CONVERGED_MAX_ITERATIONS)
        params.setRelativeErrorTol(CONVERGED_TOL)
        params.setAbsoluteErrorTol(CONVERGED_TOL)
    return solve_factors(odo, loops, init, cfg, params)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("runs", type=Path, nargs="+", help="results folders of `snaps-graph run --refine batch`")
    ap.add_argument(
        "--flagged-scale", type=float, default=10.0, help="the flagged steps' sigmas in the variant, x the reference sigmas"
    )
    ap.add_argument("--exact-loops", action="store_true", help="solve once instead: the run's loops measured by the ground truth")
    ap.add_argument("--add-oracle", metavar="A-B", help="... and the oracle's exact loops whose current frame is in A..B")
    ap.add_argument("--oracle-skip", metavar="A-B", help="the oracle without its loops whose current frame is in A..B")
    args = ap.parse_args(argv)
    span = tuple(int(v) for v in args.add_oracle.split("-")) if args.add_oracle else None
    skip = tuple(int(v) for v in args.oracle_skip.split("-")) if args.oracle_skip else None
    gain = (noise.FLAGGED_SIGMA_SCALE / args.flagged_scale) ** 2
    print("3D mean deviation / horizontal / vertical / ATE, x VO; it = LM iterations")
    for run in args.runs:
        if not (run / "graph.g2o").is_file():
            print(f"error: {run}: no graph.g2o (run with --refine batch)", file=sys.stderr)
            return 2
        gt, vo, snaps = (read_poses(run / f"poses_{n}.txt") for n in ("gt", "vo", "snaps"))
        cols = read_frames_csv(run / "frames.csv")
        inliers = cols["vo_inliers"].astype(int)
        flagged = cols["vo_ok"] != 1
        cfg = Config.load(run / "config.toml")
        base = figures(vo, gt)
        print(f"{run.name}: VO {' / '.join(f'{v:.3f}' for v in base)} m, {int(flagged.sum())} flagged steps")
        oracle = odometry_graph(vo, cfg, inliers, ~flagged)
        pairs = true_revisit_pairs(gt, cfg.loop.radius_m, cfg.loop.frame_distance, REVISIT_MAX_YAW_DEG)
        if skip:
            pairs = [(j, k) for j, k in pairs if not skip[0] <= k <= skip[1]]
        for j, k in pairs:
            oracle.add_loop(j, k, 1.0, np.linalg.solve(gt[j], gt[k]), covariance=np.zeros((6, 6)))
        if args.exact_loops or span:
            extra = [(j, k) for j, k in pairs if span and span[0] <= k <= span[1]]
            poses, it = solve_g2o(run / "graph.g2o", snaps, cfg, flagged, gain, True, exact=gt, extra=extra)
            r = figures(poses, gt) / base
            name = "refined, loops exact" + (f" + {len(extra)} oracle loops {args.add_oracle}" if span else "")
            label = f"flagged {args.flagged_scale:g}x"
            print(f"  {name:<37} {label:<16} converged   it {it:4d}  {' / '.join(f'{v:.3f}' for v in r)}", flush=True)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            oracle.save_g2o(Path(tmp) / "oracle.g2o")
            for name, g2o, init in (
                ("refined", run / "graph.g2o", snaps),
                (f"oracle ({len(pairs)} loops)", Path(tmp) / "oracle.g2o", vo),
            ):
                for label, g in (("flagged as run", 1.0), (f"flagged {args.flagged_scale:g}x", gain)):
                    for converge in (False, True):
                        poses, it = solve_g2o(g2o, init, cfg, flagged, g, converge)
                        r = figures(poses, gt) / base
                        stop = "converged" if converge else "run's stop"
                        print(f"  {name:<20} {label:<16} {stop:<11} it {it:4d}  {' / '.join(f'{v:.3f}' for v in r)}", flush=True)
        if (run / "poses_batch.txt").is_file():
            r = figures(read_poses(run / "poses_batch.txt"), gt) / base
            print(f"  {'refined as written':<49} {' / '.join(f'{v:.3f}' for v in r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
