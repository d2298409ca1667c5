"""What the command line needs besides its commands (cli.py): help that shows a value's shape only
where one is typed, a folder that holds a run rather than being one, the frame numbers a run's
pose file stands for (``eval`` against a whole sequence's ground truth), and the checks and parts
of ``run`` and ``synth`` that are not the command itself."""

from __future__ import annotations

import inspect
import typing
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Optional

import typer

from .console import replacing
from .errors import SnapsGraphError
from .io_utils import check_inputs_outside, check_output_folder, inside
from .paths import why_absent
from .trajectory_io import ODOMETRY_FORMATS


def plain_metavars(app: typer.Typer) -> None:
    """No ``<bool>`` after a flag in the help, and ``--set`` shown as the SECTION.KEY=VALUE it
    takes rather than typer's ``<list[str]>``: set on the declared options, once."""
    callbacks = [cmd.callback for cmd in app.registered_commands]
    if app.registered_callback is not None:
        callbacks.append(app.registered_callback.callback)
    for fn in callbacks:
        assert fn is not None
        hints = typing.get_type_hints(fn)
        for name, param in inspect.signature(fn).parameters.items():
            info = param.default
            if not isinstance(info, typer.models.OptionInfo) or info.metavar is not None:
                continue
            if hints.get(name) in (bool, Optional[bool]):  # noqa: UP045  # the annotation as written
                info.metavar = ""
            elif "--set" in (info.param_decls or ()):
                info.metavar = "SECTION.KEY=VALUE"


def click_command(app: typer.Typer):
    """The click command ``app()`` would run, its ``-h/--help`` flags shown without ``<bool>`` too
    (click makes them itself, so they are reached through each command)."""
    command = typer.main.get_command(app)
    names = SimpleNamespace(help_option_names=(app.info.context_settings or {}).get("help_option_names", ["--help"]))
    for cmd in [command, *getattr(command, "commands", {}).values()]:
        help_option = cmd.get_help_option(names)
        if help_option is not None:
            help_option.metavar = ""
    return command


def check_output(out: Path, overwrite: bool) -> None:
    """``check_output_folder``, and earlier results that ``overwrite`` replaces noted, so a Ctrl-C
    before the new ones are complete says they were kept."""
    check_output_folder(out, overwrite)
    replacing(out, overwrite)


def rrd_size_text(rrd: Path, frames: int) -> str:
    """A recording's size in all and per frame, MB."""
    size_mb = rrd.stat().st_size / 1e6 if rrd.is_file() else float("nan")
    return f"{size_mb:.1f} MB, {size_mb / max(frames, 1):.3f} MB per frame"


def check_run_folder(run_dir: Path) -> None:
    """A mistyped path, or a folder that holds runs (``demo``'s OUT holds OUT/run): said before
    the heavy imports, naming the run folders inside."""
    if not run_dir.exists():
        raise SnapsGraphError(f"{run_dir}: run folder not found")
    if run_dir.is_dir() and not (run_dir / "poses_vo.txt").is_file():
        inner = sorted(p.parent for p in run_dir.glob("*/poses_vo.txt"))
        if inner:
            raise SnapsGraphError(f"{run_dir}: not a run folder itself; the run is in {', '.join(map(str, inner))}")


def run_frame_ids(est: Path, n: int):
    """The dataset frame numbers of a run's pose file of ``n`` poses (its folder's frames.csv),
    increasing, else None."""
    frames_csv = est.parent / "frames.csv"
    if not frames_csv.is_file():
        return None
    import numpy as np

    from .evaluation.results_io import frame_ids, read_frames_csv

    cols = read_frames_csv(frames_csv)
    if len(next(iter(cols.values()), [])) != n:
        return None  # not this file's rows
    ids = frame_ids(cols, n, frames_csv)
    return ids if len(ids) and np.all(np.diff(ids) > 0) else None


def frame_spans(ids) -> str:
    """``100-230, 1540-1660``: the runs of consecutive frame numbers."""
    from .evaluation.metrics import parts

    return ", ".join(f"{ids[r[0]]}-{ids[r[-1]]}" for r in parts(ids, len(ids)))


def run_ground_truth(est: Path, n: int, gt: Path, gt_poses, ids):
    """``gt_poses`` for the ``n`` poses of ``est``: as read when they are as many; a run of part of
    a sequence against the sequence's whole ground truth (the official KITTI file) gets its
    frames ``ids``, re-based to the first, as the run's own poses_gt.txt holds them (with a note)."""
    if len(gt_poses) == n:
        return gt_poses
    if ids is None or gt.suffix.lower() == ".tum" or ids[-1] >= len(gt_poses):
        raise SnapsGraphError(
            f"{est}: {n} poses, but {gt} has {len(gt_poses)} (one pose per frame in both; "
            "a run's own poses_gt.txt holds exactly its frames)"
        )
    import numpy as np

    typer.echo(f"note: {gt}: the run's {len(ids)} frames ({frame_spans(ids)}) of its {len(gt_poses)}", err=True)
    return np.linalg.solve(gt_poses[ids[0]], gt_poses[ids])


# The drift model's fields by the drift command's flags; a rate may be negative, a walk not.
DRIFT_FLAGS = {
    "scale-pct": "scale_pct",
    "heading-rw": "heading_deg_per_sqrt_m",
    "pitch-rw": "pitch_deg_per_sqrt_m",
    "roll-rw": "roll_deg_per_sqrt_m",
    "trans-rw": "trans_m_per_sqrt_m",
    "heading-rate": "heading_deg_per_100m",
    "roll-rate": "roll_deg_per_100m",
}


def write_drift(gt: Path, out: Path, seed: int, pct: float | None, rates: dict, overwrite: bool) -> str:
    """``snaps-graph drift``: the ground truth driven again with the drift model (the defaults with
    the given ``rates`` by flag), written to ``out`` under its lock; returns the line to print."""
    import dataclasses

    from .drift_model import DriftModel
    from .evaluation.drift import drift_trajectory, end_drift_pct
    from .locks import writer_lock
    from .trajectory_io import read_kitti_poses, write_kitti_poses

    changes = {}
    for flag, value in rates.items():
        if value is not None and not (abs(value) < 1e3 and (value >= 0 or flag.endswith("rate"))):
            raise SnapsGraphError(f"drift: --{flag} must be a number in [0, 1000), got {value}")
        if value is not None:
            changes[DRIFT_FLAGS[flag]] = value
    with writer_lock(out):  # another drift into OUT is refused at once, never overwritten
        if out.exists() and not overwrite:
            raise SnapsGraphError(f"{out} exists (pass --overwrite to replace it)")
        if out.exists() and out.resolve() == gt.resolve():
            raise SnapsGraphError(f"{out} is the input ground truth")
        poses = read_kitti_poses(gt)
        drifted = drift_trajectory(poses, seed, dataclasses.replace(DriftModel(), **changes), pct)
        write_kitti_poses(out, drifted)
    return f"wrote {out}: {len(drifted)} poses, end drift {end_drift_pct(drifted, poses):.3f} % of the distance"


def drift_fit_text(est: Path, gt: Path, segment_m: float | None) -> str:
    """``snaps-graph drift-fit``: the drift model of ``est`` against ``gt`` as a config section."""
    from .evaluation.drift import fit_drift_model, odometry_section
    from .trajectory_io import read_poses

    if segment_m is not None and not (0 < segment_m < 1e6):
        raise SnapsGraphError(f"drift-fit: --segment-m must be a length in (0, 1e6) m, got {segment_m}")
    E, G = read_poses(est), read_poses(gt)
    if len(E) != len(G):
        raise SnapsGraphError(f"{est}: {len(E)} poses, but {gt} has {len(G)}: the two must hold the same frames")
    model, L = fit_drift_model(E, G, segment_m)
    return f"# {est} against {gt}: {len(E)} poses, stretches of {L:.0f} m\n" + odometry_section(model)


# ---- run: its configuration, its inputs, its recording
def run_config(preset: str, config: Path | None, items: list[str], mode: str | None, map_all: bool):
    """``run``'s configuration: the preset, the config file, the ``--set`` items, then ``--mode``
    and ``--map-all`` (``--loops``, ``--refine`` and ``--map`` are applied by the run itself)."""
    from .config import Config

    cfg = Config.compose(preset, config, items)
    if mode is not None:
        cfg.frontend.mode = mode  # type: ignore[assignment]  # checked by the caller
    if map_all:
        cfg.map.per_trajectory = True
    return cfg


def check_run_inputs(seq_dir: Path, gt: Path | None, calib: Path | None, world_mesh: Path | None) -> None:
    """A mistyped path among ``run``'s inputs: said at once, before anything is read."""
    if not str(seq_dir).startswith("live:") and not seq_dir.exists():
        raise SnapsGraphError(f"{seq_dir}: {why_absent(seq_dir, 'sequence folder not found (nor a bag file)')}")
    for given, what in ((gt, "ground-truth"), (calib, "calibration")):
        if given is not None and not given.exists():
            raise SnapsGraphError(f"{given}: {why_absent(given, f'{what} file not found')}")
    if world_mesh is not None and not world_mesh.is_file():
        raise SnapsGraphError(f"{world_mesh}: world mesh not found")


def check_odometry(odometry: Path | None, odometry_format: str | None) -> None:
    if odometry_format is not None and odometry_format not in ODOMETRY_FORMATS:
        raise SnapsGraphError(f"--odometry-format must be one of {', '.join(ODOMETRY_FORMATS)}, not '{odometry_format}'")
    if odometry is not None and not odometry.is_file():
        raise SnapsGraphError(f"{odometry}: {why_absent(odometry, 'odometry file not found')}")


def check_stereo(seq, seq_dir: Path, has_odometry: bool, build_map: bool) -> None:
    """A sequence without right images runs only on odometry from elsewhere and without a map."""
    if seq.stereo:
        return
    if not has_odometry:
        raise SnapsGraphError(
            f"{seq_dir}: no right images: the stereo VO needs them (give odometry from elsewhere: --odometry POSES)"
        )
    if build_map:
        raise SnapsGraphError(f"{seq_dir}: no right images: the map needs stereo depth (run without --map)")


class Recording:
    """A run's rerun logger (``--viewer``, ``--rrd``): made in the run's temporary folder, closed
    before that is renamed into place, aborted when the run fails (no half-written recording)."""

    def __init__(self, seq, name: str, viewer: bool, rrd: Path | None, rrd_inside: Path | None, image_every: int):
        self.seq, self.name, self.viewer, self.rrd, self.rrd_inside, self.image_every = (
            seq,
            name,
            viewer,
            rrd,
            rrd_inside,
            image_every,
        )
        self.logger: Any = None  # a viz.rerun_logger.RerunLogger once made

    def observer(self):
        """What ``run_sequence`` takes as its observer: a function of the temporary folder, or None."""
        return self.make if (self.viewer or self.rrd is not None) else None

    def make(self, tmp: Path):
        from .viz.rerun_logger import RerunLogger

        target = tmp / self.rrd_inside if self.rrd_inside is not None else self.rrd
        seq = self.seq
        self.logger = RerunLogger(
            seq.camera, spawn=self.viewer, rrd=target, name=self.name, gt_poses=seq.gt_poses, image_every=self.image_every
        )
        return self.logger

    def close(self, tmp: Path) -> None:
        if self.logger is not None:
            self.logger.close()

    def abort(self) -> None:
        if self.logger is not None:
            self.logger.abort()


# ---- synth
# The renderer holds about a hundred bytes per pixel: 16 Mpixel is about 2 GB.
SYNTH_MAX_SIDE, SYNTH_MAX_PIXELS = 8192, 16 * 2**20


def check_synth_options(
    out: Path,
    trajectory: str,
    times: Path | None,
    width: int,
    height: int,
    seed: int,
    scene: str,
    world_mesh: Path | None,
    mesh_only: bool,
    overwrite: bool,
) -> Path | None:
    """``synth``'s options and paths, checked before anything renders; returns the world mesh's
    path inside OUT when it is written with the sequence (else None)."""
    from .synth import SCENES

    if width < 32 or height < 32:
        raise SnapsGraphError(f"--width/--height too small: {width}x{height}")
    if width > SYNTH_MAX_SIDE or height > SYNTH_MAX_SIDE or width * height > SYNTH_MAX_PIXELS:
        raise SnapsGraphError(
            f"--width/--height too large: {width}x{height} (at most {SYNTH_MAX_SIDE} a side and "
            f"{SYNTH_MAX_PIXELS // 2**20} Mpixel, what the renderer's per-pixel buffers fit in a few GB)"
        )
    if seed < 0:
        raise SnapsGraphError(f"--seed must be >= 0, not {seed}")
    if scene not in SCENES:
        raise SnapsGraphError(f"--scene '{scene}' is not one of {', '.join(SCENES)}")
    if world_mesh is not None and world_mesh.suffix.lower() not in (".ply", ".obj", ".off", ".stl"):
        raise SnapsGraphError(f"{world_mesh}: --world-mesh must name a .ply (or .obj, .off, .stl) file")
    if mesh_only and world_mesh is None:
        raise SnapsGraphError("--mesh-only needs --world-mesh FILE.ply")
    mesh_inside = None
    if not mesh_only:
        check_inputs_outside(out, [("trajectory", Path(trajectory) if trajectory != "loop" else None), ("times", times)])
        check_output(out, overwrite)
        if world_mesh is not None and inside(world_mesh, out):  # written with the sequence, not deleted by it
            mesh_inside = world_mesh.resolve().relative_to(out.resolve())
    if world_mesh is not None and mesh_inside is None:
        if world_mesh.is_dir():
            raise SnapsGraphError(f"{world_mesh}: --world-mesh names a folder")
        if world_mesh.exists() and not overwrite:
            raise SnapsGraphError(f"{world_mesh}: exists (use --overwrite to replace it)")
    return mesh_inside


def print_sessions(metrics: dict) -> None:
    """One line per prior session: where the run relocalised against it, or that it never did."""
    for entry in metrics.get("sessions", []):
        if not entry.get("relocalised"):
            typer.echo(f"never relocalised against {entry['session']}: the outputs keep the run's own frame")
        elif entry.get("frame") is None:
            typer.echo(f"started where {entry['session']} started (--same-start); {entry['loops']} loops with it")
        else:
            where = "; the outputs are in its frame" if entry.get("outputs_frame") else ""
            typer.echo(
                f"relocalised against {entry['session']} at frame {entry['frame']} (its frame {entry['reference']});"
                f" {entry['loops']} loops with it{where}"
            )
