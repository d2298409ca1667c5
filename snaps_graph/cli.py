"""Command line: ``snaps-graph synth | run | batch | convert | eval | compare | loops | demo | config | drift``.

Thin: each command parses its options, calls the package and prints. A ``SnapsGraphError`` is one
``error:`` line and exit status 2, never a traceback; every status: docs/usage.md.
"""

from __future__ import annotations

import os
import signal
import sys


def _sigint_while_starting(signum, frame) -> None:
    # Ctrl-C while this module's imports run (before main() installs its handler): nothing is
    # written yet, and an exception raised inside an import would print a traceback.
    print("interrupted: no results written", file=sys.stderr)
    os._exit(130)


_SIGINT_BEFORE = signal.signal(signal.SIGINT, _sigint_while_starting)

import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Optional  # noqa: E402

import typer  # noqa: E402

from . import cli_support as support  # noqa: E402  # help, folders, a run's frames
from ._malloc import set_malloc_thresholds  # noqa: E402
from .config import Config, FrontendMode, LoopMode, RefineMode  # noqa: E402
from .config_schema import choices  # noqa: E402
from .console import (  # noqa: E402  # progress, summary, Ctrl-C
    EXIT_CELLS_FAILED,
    EXIT_INTERRUPTED,
    EXIT_MOSTLY_FLAGGED,
    EXIT_USER_ERROR,
    STDOUT_ERRNOS,
    Interrupted,
    exit_interrupted,
    metrics_table,
    on_sigint,
    print_input_notes,
    print_summary,
    progress,
    stdout_failed,
    warn_mostly_flagged,
)
from .errors import SnapsGraphError, interrupted  # noqa: E402
from .io_utils import (  # noqa: E402
    PREFETCH_FRAMES,
    check_inputs_outside,
    check_recording_path,
    output_folder,
)

# Heavy modules (OpenCV, gtsam, open3d, matplotlib) are imported inside the commands that use
# them, after the cheap checks, so `config`, `--help` and a bad option answer at once.

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Stereo visual SLAM with SNAPS loop closure and a GTSAM pose graph.",
)


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"snaps-graph {__version__}")
        raise typer.Exit()


@app.callback()
def _main_options(
    version: bool = typer.Option(
        False, "--version", "-V", callback=_print_version, is_eager=True, help="Print the version, exit."
    ),
) -> None:
    """Stereo visual SLAM with SNAPS loop closure and a GTSAM pose graph."""


@app.command()
def synth(
    out: Path = typer.Option(
        ..., "--out", "-o", help="Sequence folder to write (image_0/, image_1/, calib.txt, times.txt, poses.txt)."
    ),
    trajectory: str = typer.Option(
        "loop", "--trajectory", help="A KITTI pose file to drive along, or 'loop' for the built-in closed loop."
    ),
    times: Optional[Path] = typer.Option(None, "--times", help="Timestamps file for the trajectory (default 10 Hz)."),
    frames: Optional[str] = typer.Option(None, "--frames", help="Frame range A:B (A included, B excluded)."),
    width: int = typer.Option(1241, "--width", help="Image width, pixels."),
    height: int = typer.Option(376, "--height", help="Image height, pixels."),
    seed: int = typer.Option(0, "--seed", help="World and noise seed (same seed, same images)."),
    noise: float = typer.Option(0.0, "--noise", help="Sensor noise, grey-level standard deviation."),
    exposure: float = typer.Option(0.0, "--exposure", help="Exposure change between passes (0 = none)."),
    depth: bool = typer.Option(
        False, "--depth/--no-depth", help="Also write exact depth of the left camera (depth_0/, uint16 mm)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty OUT folder (whole)."),
    scene: str = typer.Option(
        "street",
        "--scene",
        help="street (buildings from 5 m) | open (fields, trees and farms 30-200 m away) | mixed (alternating stretches).",
    ),
    aliasing: bool = typer.Option(
        False, "--aliasing", help="Hard world: buildings from a few facade modules in one repeated block."
    ),
    traffic: bool = typer.Option(False, "--traffic", help="Hard world: parked cars that differ between passes, oncoming cars."),
    lighting: bool = typer.Option(
        False, "--lighting", help="Hard world: sun and cast shadows follow a time of day along the trajectory's time."
    ),
    rectification_error: float = typer.Option(
        0.0,
        "--rectification-error",
        help="Sensor: every disparity reads this many pixels smaller than calib.txt implies (a rig's rectification residual; depth reads long, the more the farther).",
    ),
    world_mesh: Optional[Path] = typer.Option(
        None,
        "--world-mesh",
        help="Also write the static world geometry (no traffic) as a triangle mesh (.ply) in the frame of poses.txt.",
    ),
    mesh_only: bool = typer.Option(
        False, "--mesh-only", help="With --world-mesh: write the mesh only (no images; OUT is not touched)."
    ),
) -> None:
    """Render a synthetic stereo sequence along a trajectory, in KITTI layout."""
    from .synth import SyntheticSequence, WorldConfig, load_trajectory, render_to_folder

    mesh_inside = support.check_synth_options(
        out, trajectory, times, width, height, seed, scene, world_mesh, mesh_only, overwrite
    )
    world = WorldConfig(scene=scene, aliasing=aliasing, traffic=traffic, lighting=lighting)
    poses, ts = load_trajectory(trajectory, frames, times=str(times) if times else None)
    seq = SyntheticSequence(
        poses,
        width=width,
        height=height,
        seed=seed,
        noise_std=noise,
        exposure_change=exposure,
        times=ts,
        world_config=world,
        rectification_error_px=rectification_error,
    )
    if world_mesh is not None and mesh_inside is None:
        seq.write_world_mesh(world_mesh)
        typer.echo(f"wrote the world mesh ({len(seq.world.triangles)} triangles) to {world_mesh}")
        if mesh_only:
            return
    with progress(len(seq), "render") as bar, output_folder(out, overwrite) as tmp:
        render_to_folder(seq, tmp, progress=lambda *_: bar.update(1), write_depth=depth, overwrite=True)
        if mesh_inside is not None:
            seq.write_world_mesh(tmp / mesh_inside)
    if mesh_inside is not None:
        typer.echo(f"wrote the world mesh ({len(seq.world.triangles)} triangles) to {world_mesh}")
    typer.echo(f"wrote {len(seq)} stereo pairs to {out}")


@app.command()
def run(
    seq_dir: Path = typer.Argument(
        ...,
        help="A KITTI folder (image_0/, image_1/, calib.txt), a EuRoC mav0/ folder, a ROS 1 .bag, a ROS 2 bag folder or .mcap, or live:DEV[,DEV].",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Results folder."),
    frames: Optional[str] = typer.Option(None, "--frames", help="Frame range A:B (A included, B excluded)."),
    preset: str = typer.Option("default", "--preset", help="A named configuration: default | paper (then --config, --set)."),
    config: Optional[Path] = typer.Option(
        None, "--config", "-c", help="A TOML config over the preset (see `snaps-graph config`)."
    ),
    set_: list[str] = typer.Option([], "--set", help="A config value, section.key=VALUE (in TOML), after --config; repeatable."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth poses (default: SEQ/poses.txt or ROOT/poses/XX.txt)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty OUT folder (whole, at the end of the run)."),
    left_topic: Optional[str] = typer.Option(None, "--left-topic", help="ROS bag: left image topic (default: found by name)."),
    right_topic: Optional[str] = typer.Option(None, "--right-topic", help="ROS bag: right image topic (default: found by name)."),
    calib: Optional[Path] = typer.Option(
        None,
        "--calib",
        help="live:DEV, or a bag without CameraInfo: calib.txt of rectified cameras, or a folder with cam0/ and cam1/ sensor.yaml.",
    ),
    loops: Optional[str] = typer.Option(None, "--loops", help="snaps | none (default from config: snaps)."),
    refine: Optional[str] = typer.Option(None, "--refine", help="none | isam2 | batch | both (default from config: none)."),
    map_: Optional[bool] = typer.Option(None, "--map/--no-map", help="Build the point-cloud map (default from config: off)."),
    mode: Optional[str] = typer.Option(None, "--mode", help="Front-end mode override: klt | orb | sift."),
    prefetch: int = typer.Option(
        PREFETCH_FRAMES, "--prefetch", help="Frames read ahead on a background thread (0: read inline)."
    ),
    map_all: bool = typer.Option(False, "--map-all", help="With --map: also map_<trajectory>.ply for every trajectory."),
    world_mesh: Optional[Path] = typer.Option(
        None, "--world-mesh", help="With --map: the true world mesh (PLY); map accuracy per trajectory."
    ),
    viewer: bool = typer.Option(False, "--viewer", help="Spawn the rerun viewer and stream the run to it (needs rerun-sdk)."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record the run to a rerun .rrd file (needs rerun-sdk)."),
    rrd_images: int = typer.Option(10, "--rrd-images", min=1, help="With --rrd: the camera image every N frames, JPEG."),
    odometry: Optional[Path] = typer.Option(
        None,
        "--odometry",
        help="Poses from elsewhere instead of the stereo VO: a KITTI pose file (line i = frame i) or TUM "
        "(t x y z qx qy qz qw, matched by timestamp); SEQ may then be monocular.",
    ),
    odometry_format: Optional[str] = typer.Option(None, "--odometry-format", help="kitti | tum (default: by the column count)."),
    prior: list[Path] = typer.Option(
        [], "--prior", help="An earlier run's folder to relocalise against (read only); repeatable."
    ),
    same_start: bool = typer.Option(False, "--same-start", help="With --prior: the run starts where the priors started."),
) -> None:
    """Run stereo VO (+ SNAPS, + graph refinement, + map) over a sequence and write a results folder.

    The folder is written whole at the end (or not at all). Exit status: 0 done; 2 bad input (one
    `error:` line); 3 done, but more than half of the frames were flagged; 130 interrupted.
    """
    _check_choices(("--loops", loops, LoopMode), ("--refine", refine, RefineMode), ("--mode", mode, FrontendMode))
    cfg = support.run_config(preset, config, set_, mode, map_all)
    support.check_run_inputs(seq_dir, gt, calib, world_mesh)
    # Before anything is read: the configuration that will run, the output folder, and every
    # path the run reads or writes against it.
    build_map = cfg.resolved(loops=loops, refine=refine, build_map=map_).map.enabled
    inputs = [("sequence", seq_dir), ("config", config), ("ground truth", gt), ("calibration", calib), ("odometry", odometry)]
    check_inputs_outside(out, inputs + [("world mesh", world_mesh)] + [("prior", p) for p in prior])
    support.check_output(out, overwrite)
    rrd_inside = check_recording_path(rrd, out) if rrd is not None else None
    support.check_odometry(odometry, odometry_format)
    from .datasets.open import open_dataset  # the heavy imports (OpenCV, gtsam) after the checks

    seq = open_dataset(seq_dir, frames=frames, gt=gt, left_topic=left_topic, right_topic=right_topic, calib=calib)
    check_inputs_outside(out, [("ground truth", seq.gt_path)])
    support.check_stereo(seq, seq_dir, odometry is not None, build_map)
    print_input_notes(seq, frames, topics_given=left_topic is not None)
    recording = support.Recording(seq, str(seq_dir), viewer, rrd, rrd_inside, rrd_images)
    options: dict = dict(loops=loops, refine=refine, build_map=map_, overwrite=overwrite, prefetch_frames=prefetch)
    options |= dict(odometry=odometry, odometry_format=odometry_format, world_mesh=world_mesh)
    options |= dict(priors=prior, same_start=same_start)
    metrics, rate = _run_with_progress(seq, out, cfg, recording, options)
    _report_run(metrics, out, rate, frames is not None, rrd)


def _report_run(metrics: dict, out: Path, rate: float | None, partial: bool, rrd: Path | None) -> None:
    """The run's summary; exit status EXIT_MOSTLY_FLAGGED when most frames were flagged."""
    from .runner import mostly_flagged

    if rrd is not None:
        typer.echo(f"rerun recording in {rrd}: {support.rrd_size_text(rrd, metrics['frames'])}")
    print_summary(metrics, out, rate, partial=partial)
    if mostly_flagged(metrics):
        warn_mostly_flagged(metrics)
        raise typer.Exit(EXIT_MOSTLY_FLAGGED)


def _run_with_progress(seq, out: Path, cfg: Config, recording, options: dict) -> tuple[dict, float | None]:
    """``run_sequence`` under a progress bar that counts the loops; (metrics, frames per second)."""
    from .runner import run_sequence

    n_loops = 0
    with progress(len(seq) or None, "slam") as bar:

        def on_frame(o):
            nonlocal n_loops
            n_loops += o.loop is not None
            bar.set_postfix(loops=n_loops, refresh=False)
            bar.update(1)
            if bar.n == len(seq):  # the graph, map and files take a while after the last frame
                bar.phase("all frames done; refining, writing the map and files")

        try:
            _, metrics = run_sequence(
                seq, out, cfg, on_frame=on_frame, observer=recording.observer(), before_commit=recording.close, **options
            )
        except BaseException:
            recording.abort()  # no half-written recording
            raise
    support.print_sessions(metrics)
    return metrics, bar.rate


@app.command()
def batch(
    plan: Path = typer.Argument(..., help="A plan (TOML): sequences, run options, variants (config overrides)."),
    out: Path = typer.Option(
        ..., "--out", "-o", help="Folder for DIR/<sequence>/<variant>/ run folders and summary.csv / summary.md."
    ),
    address: Optional[str] = typer.Option(None, "--address", help="Join this Ray cluster (default: start Ray on this machine)."),
    max_parallel: Optional[int] = typer.Option(
        None, "--max-parallel", help="At most this many cells at once (default: as many as Ray has CPUs for)."
    ),
    set_: list[str] = typer.Option([], "--set", help="A config value per cell, section.key=VALUE, over the plan; repeatable."),
) -> None:
    """Run every (sequence, variant) cell of a plan as a Ray task; resumable; summary.csv / .md.

    Cells complete from an earlier batch with the same config hash are skipped.

    Exit status: 0 every cell ok or skipped; 2 bad plan (one `error:` line, before any task starts); 4 some cells failed (summary.md says why); 130 interrupted (running cells cancelled, finished ones kept).
    """
    from .batch import load_plan, run_batch

    p = load_plan(plan, overrides=set_)  # checked whole before any task starts
    t0 = time.perf_counter()
    try:
        rows = run_batch(p, out, address=address, max_parallel=max_parallel)
    except (Interrupted, KeyboardInterrupt):
        print(
            f"interrupted: running cells cancelled; finished cells are kept (a re-run resumes); see {out / 'summary.md'}",
            file=sys.stderr,
        )
        raise typer.Exit(EXIT_INTERRUPTED) from None
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "skipped", "failed")}
    typer.echo(
        f"{len(rows)} cells: {counts['ok']} ok, {counts['skipped']} skipped, {counts['failed']} failed "
        f"in {time.perf_counter() - t0:.1f} s; summary in {out / 'summary.md'}"
    )
    if counts["failed"]:
        raise typer.Exit(EXIT_CELLS_FAILED)


@app.command()
def convert(
    src: Path = typer.Argument(..., help="Any readable source: KITTI folder, EuRoC mav0/ folder, ROS 1/2 bag, live:DEV[,DEV]."),
    out: Path = typer.Option(
        ..., "--out", "-o", help="KITTI folder to write (image_0/, image_1/, calib.txt, times.txt, poses.txt when known)."
    ),
    frames: Optional[str] = typer.Option(None, "--frames", help="Frame range A:B (A included, B excluded)."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground truth of the source (EuRoC state csv; KITTI poses for a bag)."),
    left_topic: Optional[str] = typer.Option(None, "--left-topic", help="ROS bag: left image topic (default: found by name)."),
    right_topic: Optional[str] = typer.Option(None, "--right-topic", help="ROS bag: right image topic (default: found by name)."),
    calib: Optional[Path] = typer.Option(
        None, "--calib", help="live:DEV, or a bag without CameraInfo: calib.txt, or a folder with cam0/ and cam1/ sensor.yaml."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty OUT folder (whole, at the end)."),
) -> None:
    """Write any readable source as a KITTI folder of rectified pairs."""
    check_inputs_outside(out, [("source", src), ("ground truth", gt), ("calibration", calib)])
    support.check_output(out, overwrite)
    from .datasets.convert import write_kitti_folder
    from .datasets.open import open_dataset

    seq = open_dataset(src, frames=frames, gt=gt, left_topic=left_topic, right_topic=right_topic, calib=calib)
    print_input_notes(seq, None, topics_given=left_topic is not None)
    with progress(len(seq) or None, "convert") as bar, output_folder(out, overwrite) as tmp:  # whole or absent
        n = write_kitti_folder(seq, tmp, progress=lambda: bar.update(1), overwrite=True)
    typer.echo(f"wrote {n} stereo pairs to {out}" + (" with poses.txt" if seq.gt_poses is not None else ""))


@app.command("eval")
def eval_(
    est: Path = typer.Argument(..., help="Estimated poses (KITTI format; .tum for TUM); with two files: the reference."),
    second: Optional[Path] = typer.Argument(
        None, metavar="[EST]", help="evo's order, reference first: `snaps-graph eval GT EST` (instead of --gt)."
    ),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth poses (KITTI format; .tum for TUM)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of a table."),
) -> None:
    """Mean deviation, ATE RMSE (SE(3)-aligned), KITTI t_rel / r_rel of a trajectory.

    `snaps-graph eval EST --gt GT`, or in evo's order `snaps-graph eval GT EST`."""
    if second is not None:
        if gt is not None:
            raise_user("eval: give the ground truth once: `eval EST --gt GT` or, in evo's order, `eval GT EST`")
        est, gt = second, est
    if gt is None:
        raise SnapsGraphError("eval: no ground truth: `eval EST --gt GT` or, in evo's order (reference first), `eval GT EST`")
    if missing := [str(given) for given in (est, gt) if not given.exists()]:
        raise_user("; ".join(f"{m}: pose file not found" for m in missing))
    from .evaluation.metrics import evaluate
    from .trajectory_io import read_poses

    est_poses = read_poses(est)
    ids = support.run_frame_ids(est, len(est_poses))
    gt_poses = support.run_ground_truth(est, len(est_poses), gt, read_poses(gt), ids)
    m = evaluate(est_poses, gt_poses, ids)
    if as_json:
        from .evaluation.results_io import json_clean

        typer.echo(json.dumps(json_clean(m)))  # a metric that cannot be computed is null
        return
    typer.echo(metrics_table({est.name: m}))


@app.command()
def compare(
    run_dir: Path = typer.Argument(..., help="A results folder written by `snaps-graph run`."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground truth (default: RUN_DIR/poses_gt.txt)."),
    world_mesh: Optional[Path] = typer.Option(
        None, "--world-mesh", help="The true world mesh (PLY): accuracy of the run's maps."
    ),
) -> None:
    """Heuristic (SNAPS) against optimised corrections: report.md, PNGs and metrics.json."""
    support.check_run_folder(run_dir)
    from .evaluation.report import compare_run

    measure = None
    if world_mesh is not None:
        from .mapping.outputs import accuracy_from_files

        def measure(run, trajs, entry, gt_poses):
            acc = accuracy_from_files(run, world_mesh, trajs, entry, gt_poses)
            return {"accuracy": acc, "world_mesh": str(world_mesh)}

    compare_run(run_dir, gt, map_accuracy=measure)
    typer.echo(f"wrote {run_dir / 'report.md'}")


@app.command()
def loops(
    run_dir: Path = typer.Argument(..., help="A results folder written by `snaps-graph run` with SNAPS (candidates.csv)."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground truth (default: RUN_DIR/poses_gt.txt)."),
    true_m: float = typer.Option(5.0, "--true-m", help="A pair is a true loop within this ground-truth distance, m."),
    false_m: float = typer.Option(10.0, "--false-m", help="... and false beyond this one (ignored in between), m."),
    png: Optional[Path] = typer.Option(None, "--png", help="Precision-recall plot (default: RUN_DIR/loops_pr.png)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of text."),
) -> None:
    """Loop-closure evaluation: precision-recall over the Q threshold, revisits found, false loops."""
    support.check_run_folder(run_dir)
    from .evaluation.loops import json_text, loops_run, summary_lines

    ev = loops_run(run_dir, gt, true_m=true_m, false_m=false_m, png=png)
    if as_json:
        typer.echo(json_text(ev))
        return
    for line in summary_lines(ev):
        typer.echo(line)
    if "plot" in ev:
        typer.echo(f"wrote {ev['plot']}")


@app.command()
def demo(
    out: Path = typer.Option(Path("results/demo"), "--out", "-o", help="Where the demo writes everything."),
    frames: int = typer.Option(300, "--frames", help="Length of the built-in loop, frames."),
    width: int = typer.Option(1241, "--width"),
    height: int = typer.Option(376, "--height"),
    refine: str = typer.Option("isam2", "--refine", help="none | isam2 | batch | both."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier demo's OUT/sequence and OUT/run (whole)."),
) -> None:
    """Render the built-in loop, run VO + SNAPS + refinement + map, compare, print a summary."""
    _check_choice("--refine", refine, RefineMode)
    from .demo import run_demo

    run_demo(out, frames=frames, width=width, height=height, refine=refine, progress=progress, overwrite=overwrite)


@app.command("config")
def config_cmd(
    path: Optional[Path] = typer.Argument(None, help="A TOML config to check; default: print the defaults."),
    preset: str = typer.Option("default", "--preset", help="Start from this named configuration: default | paper."),
) -> None:
    """Print the default configuration (or a preset, or a checked, completed copy of PATH over it)
    as TOML, every key with its meaning, unit and range as a comment (the output loads back with -c)."""
    cfg = Config.compose(preset, path)
    typer.echo(cfg.dumps(comments=True), nl=False)


def raise_user(msg: str) -> None:
    raise SnapsGraphError(msg)


def _check_choice(option: str, value: str | None, literal) -> None:
    allowed = choices(literal) or ()
    if value is not None and value not in allowed:
        raise_user(f"{option} must be one of {', '.join(allowed)}, not '{value}'")


def _check_choices(*checks: tuple[str, str | None, object]) -> None:
    """:func:`_check_choice` for each (option, value, literal)."""
    for option, value, literal in checks:
        _check_choice(option, value, literal)


def main() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # `kill`, a scheduler's stop, a closed terminal: as Ctrl-C
        signal.signal(sig, on_sigint)
    set_malloc_thresholds()  # the process is ours: large frames stop costing page faults
    try:
        rc = support.click_command(app)(standalone_mode=False)
        sys.stdout.flush()
    except OSError as exc:
        if exc.filename is not None or exc.errno not in STDOUT_ERRNOS:
            raise
        stdout_failed(exc)
    except (Interrupted, KeyboardInterrupt):
        exit_interrupted()
    except SnapsGraphError as exc:
        if interrupted():
            exit_interrupted()
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    except Exception as exc:
        if interrupted():  # an import or a call cut by Ctrl-C reports its own error
            exit_interrupted()
        # click's exceptions (typer >= 0.16 vendors its own click, so matched by their interface)
        if type(exc).__name__ == "Abort":
            exit_interrupted()
        code = getattr(exc, "exit_code", None)
        if hasattr(exc, "format_message") and isinstance(code, int):
            if type(exc).__name__ == "NoArgsIsHelpError" or not code:
                exc.show()  # type: ignore[attr-defined]  # the help text
                sys.exit(code)
            ctx = getattr(exc, "ctx", None)
            where = f"{ctx.command_path}: " if ctx is not None else ""
            hint = f" (see {ctx.command_path} --help)" if ctx is not None else ""
            print(f"error: {where}{' '.join(exc.format_message().split())}{hint}", file=sys.stderr)  # type: ignore[attr-defined]
            sys.exit(code)
        raise
    sys.exit(rc if isinstance(rc, int) else 0)


@app.command()
def drift(
    gt: Path = typer.Argument(..., help="Ground-truth trajectory (a KITTI pose file)."),
    out: Path = typer.Option(..., "--out", help="Drifted trajectory to write (KITTI pose file)."),
    seed: int = typer.Option(0, "--seed", help="Random-walk seed (same seed, same file)."),
    pct: Optional[float] = typer.Option(
        None, "--pct", help="Rescale the model so the end drift is this percent of the distance driven."
    ),
    scale_pct: Optional[float] = typer.Option(None, "--scale-pct", help="Translation scale error, percent."),
    heading_rw: Optional[float] = typer.Option(None, "--heading-rw", help="Heading random walk, deg per sqrt(m)."),
    pitch_rw: Optional[float] = typer.Option(None, "--pitch-rw", help="Pitch random walk, deg per sqrt(m)."),
    roll_rw: Optional[float] = typer.Option(None, "--roll-rw", help="Roll random walk, deg per sqrt(m)."),
    trans_rw: Optional[float] = typer.Option(None, "--trans-rw", help="Translation random walk of a step, m per sqrt(m)."),
    heading_rate: Optional[float] = typer.Option(None, "--heading-rate", help="Constant heading rate, deg/100 m."),
    roll_rate: Optional[float] = typer.Option(None, "--roll-rate", help="Constant roll rate, deg/100 m."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace OUT if it exists."),
) -> None:
    """Perturb a ground truth with the drift model the graph and the search assume (heading, pitch,
    roll walks, scale error, step noise, optional rates); defaults from our stereo VO on real data."""
    rates = {"scale-pct": scale_pct, "heading-rw": heading_rw, "pitch-rw": pitch_rw, "roll-rw": roll_rw}
    rates |= {"trans-rw": trans_rw, "heading-rate": heading_rate, "roll-rate": roll_rate}
    typer.echo(support.write_drift(gt, out, seed, pct, rates, overwrite))


@app.command("drift-fit")
def drift_fit(
    est: Path = typer.Argument(..., help="The odometry's trajectory (KITTI or TUM pose file, e.g. a run's poses_vo.txt)."),
    gt: Path = typer.Argument(..., help="Its ground truth, the same frames (e.g. the run's poses_gt.txt)."),
    segment_m: Optional[float] = typer.Option(
        None, "--segment-m", help="Measure over stretches this long, m (default 100, or a third of a shorter path)."
    ),
) -> None:
    """Measure an odometry's drift model against ground truth and print it as the [odometry] section
    of a config: the graph, the loop search and the correction then assume the drift it really has."""
    typer.echo(support.drift_fit_text(est, gt, segment_m))


support.plain_metavars(app)
signal.signal(signal.SIGINT, _SIGINT_BEFORE)  # the module is imported: main() takes over

if __name__ == "__main__":
    main()
