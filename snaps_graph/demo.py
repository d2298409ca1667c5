"""``make demo`` / ``snaps-graph demo``: the whole product on built-in data, in a few minutes.

Renders the built-in loop, runs VO + SNAPS + the chosen refinement + the map on it, writes the
comparison report and prints a summary. OUT/sequence and OUT/run are checked before anything is
rendered and replaced only with ``overwrite`` (and only when this tool wrote them).
"""

from __future__ import annotations

import time
from pathlib import Path

from .config import Config
from .console import loops_text
from .datasets.kitti import KittiSequence
from .evaluation.report import compare_run
from .io_utils import check_output_folder, output_folder
from .runner import run_sequence
from .synth import SyntheticSequence, builtin_loop_trajectory, render_to_folder


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
    t0 = time.perf_counter()
    poses = builtin_loop_trajectory(frames)
    synth = SyntheticSequence(poses, width=width, height=height, seed=0)
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
