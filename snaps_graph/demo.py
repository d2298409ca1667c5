"""``make demo`` / ``snaps-graph demo``: the whole product on built-in data, in a few minutes.

Renders the built-in loop, runs VO + SNAPS + the chosen refinement + the map on it, writes the
comparison report and prints a summary. The loop's second pass drives another lane, past other
parked and oncoming cars, hours later in the day (``demo_sequence``): a revisit whose images
differ as a real one's do, not a replay of the first pass. OUT/sequence and OUT/run are checked before anything is
rendered and replaced only with ``overwrite`` (and only when this tool wrote them).
"""

from __future__ import annotations

import time
from pathlib import Path

from .config import Config
from .console import loops_text, replacing
from .datasets.kitti import KittiSequence
from .evaluation.report import compare_run
from .io_utils import check_output_folder, output_folder
from .runner import run_sequence
from .synth import SyntheticSequence, WorldConfig, builtin_loop_trajectory, render_to_folder

# The second pass: this far to the left of the first (a neighbouring lane)...
DEMO_LANE_OFFSET_M = 1.2
# ...with traffic (parked cars taken or free per pass, a pass being the frames within this of a
# slot: under half the loop's size, so the two passes draw their cars separately)...
DEMO_PASS_RADIUS_M = 30.0
# ...and the sun moving this many hours per minute of driving (about 2.5 h between the passes).
DEMO_DAY_HOURS_PER_MINUTE = 6.0


def demo_sequence(frames: int = 300, width: int = 1241, height: int = 376) -> SyntheticSequence:
    """The demo's rendering: the built-in loop, its second pass in another lane, traffic and a
    moving sun (the hard worlds' options of ``snaps-graph synth``)."""
    world = WorldConfig(
        traffic=True, lighting=True, pass_radius_m=DEMO_PASS_RADIUS_M, day_hours_per_minute=DEMO_DAY_HOURS_PER_MINUTE
    )
    poses = builtin_loop_trajectory(frames, lane_offset_m=DEMO_LANE_OFFSET_M)
    return SyntheticSequence(poses, width=width, height=height, seed=0, world_config=world)


def run_demo(
    out: str | Path,
    frames: int = 300,
    width: int = 1241,
    height: int = 376,
    refine: str = "isam2",
    progress=None,
    overwrite: bool = False,
) -> dict:
    out = Path(out)
    seq_dir = out / "sequence"
    run_dir = out / "run"
    for folder in (seq_dir, run_dir):  # both before the render: a refused run wastes nothing
        check_output_folder(folder, overwrite)
        replacing(folder, overwrite)
    t0 = time.perf_counter()
    synth = demo_sequence(frames, width, height)
    with output_folder(seq_dir, overwrite) as tmp:
        _with_bar(progress, len(synth), "render", lambda cb: render_to_folder(synth, tmp, progress=cb))
    t_render = time.perf_counter() - t0

    seq = KittiSequence(seq_dir)
    cfg = Config()
    cfg.map.enabled = True
    t1 = time.perf_counter()
    result, metrics = _with_bar(
        progress,
        len(seq),
        "slam",
        lambda cb: run_sequence(
            seq, run_dir, cfg, loops="snaps", refine=refine, build_map=True, overwrite=overwrite, on_frame=cb
        ),
        after="all frames done; refining, writing the map, the report and pictures",
    )
    t_run = time.perf_counter() - t1
    compare_run(run_dir)

    lat = metrics["latency_ms"]
    print(
        f"demo: rendered {len(synth)} stereo pairs in {t_render:.1f} s; SLAM at {lat['frames_per_s']:.1f} frames/s "
        f"({t_run:.1f} s), {metrics['frames']} frames ({metrics['flagged_frames']} flagged), {loops_text(metrics, 'closed')}"
    )
    for name, m in metrics.get("trajectories", {}).items():
        print(f"  {name:<6} mean deviation {m['mean_deviation']:.3f} m   ATE {m['ate_rmse']:.3f} m")
    print(f"  report: {run_dir / 'report.md'}   map: {run_dir / 'map.ply'}")
    return metrics


def _with_bar(progress, total, desc, fn, after: str | None = None):
    """``fn(step)`` with a bar from ``progress``; ``after``: the phase named once the last step is done."""
    if progress is None:
        return fn(None)
    with progress(total, desc) as bar:

        def step(*_):
            bar.update(1)
            if after is not None and bar.n == total and hasattr(bar, "phase"):
                bar.phase(after)

        return fn(step)
