"""A run: read a dataset, drive :class:`~snaps_graph.pipeline.SlamPipeline`, write the results folder.

The folder is checked before the first frame and is whole or absent: written into a temporary
sibling ``.NAME.tmp-PID``, renamed into place at the end (docs/run-contract.md). Each file has
one writer (``evaluation.results_io``), metrics.json last; the files: README.md, "What a run writes".
"""

from __future__ import annotations

import contextlib
import resource
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from .config import Config
from .errors import SnapsGraphError, interrupted
from .evaluation.latency import records_latency_summary as latency_summary
from .evaluation.metrics import evaluate
from .evaluation.results_io import (
    write_candidates_csv,
    write_frames_csv,
    write_gt,
    write_loops_jsonl,
    write_metrics_json,
    write_trajectories,
)
from .io_utils import PREFETCH_FRAMES, inside, output_folder, prefetch
from .mapping.outputs import write_map_outputs
from .mapping.sessions import write_sessions_map
from .pipeline import FrameOutput, RunResult, SlamPipeline, pose_file_frontend
from .session import Session, read_session, session_folder, write_session
from .trajectory_io import read_pose_file
from .types import StereoSource

# Exit status of `snaps-graph run` when more than this fraction of the frames was flagged by the
# front end (the results are written; the run is suspect). See cli.EXIT_MOSTLY_FLAGGED.
FLAGGED_FRACTION_LIMIT = 0.5


def run_sequence(
    dataset: StereoSource,
    out_dir: str | Path,
    cfg: Config | None = None,
    *,
    loops: str | None = None,
    refine: str | None = None,
    build_map: bool | None = None,
    overwrite: bool = False,
    on_frame: Callable[[FrameOutput], None] | None = None,
    observer=None,
    prefetch_frames: int = PREFETCH_FRAMES,
    before_commit: Callable[[Path], None] | None = None,
    odometry=None,
    odometry_format: str | None = None,
    world_mesh: str | Path | None = None,
    priors: Iterable[str | Path] = (),
    same_start: bool = False,
) -> tuple[RunResult, dict]:
    """Run a whole dataset (any reader of ``datasets.open.open_dataset``) and write the results folder;
    the configuration and the folder are checked before the first frame. ``observer``: a
    ``SlamPipeline.observer`` (the rerun logger) or a function of the temporary folder that makes
    one; ``prefetch_frames``: frames read ahead on a thread (0: none); ``before_commit``: called with
    the whole temporary folder before it is renamed; ``odometry``: a pose file (KITTI or TUM,
    ``odometry_format`` or detected; a pose for every frame) or a front end, instead of the stereo VO;
    ``world_mesh``: the true world (PLY), the map's accuracy measured against it; ``priors``:
    results folders of earlier runs to relocalise against (read, never written); ``same_start``:
    the run starts where they started.
    """
    sessions = read_priors(priors, out_dir)
    if (cfg or Config()).resolved(loops=loops, refine=refine, build_map=build_map).map.enabled and world_mesh:
        if not Path(world_mesh).is_file():  # else the map stage fails after every frame
            what = "is a folder, not a world mesh" if Path(world_mesh).is_dir() else "world mesh not found"
            raise SnapsGraphError(f"{world_mesh}: {what}")
    frontend = odometry
    if isinstance(odometry, (str, Path)):  # read before the folder opens: a bad file leaves nothing
        t0_ns = dataset.t0_ns
        track = read_pose_file(odometry, odometry_format)
        frontend = pose_file_frontend(track, cfg, dataset.indices, dataset.timestamps, None if t0_ns is None else t0_ns * 1e-9)
    with output_folder(out_dir, overwrite) as tmp:
        pipe = SlamPipeline(
            dataset.camera,
            cfg,
            loops=loops,
            refine=refine,
            build_map=build_map,
            frontend=frontend,
            priors=sessions,
            same_start=same_start,
        )
        if callable(observer) and not hasattr(observer, "on_frame"):
            observer = observer(tmp)
        pipe.observer = observer
        with contextlib.closing(prefetch(dataset, prefetch_frames)) as frames:  # the next frames are read meanwhile
            for frame in frames:
                try:
                    out = pipe.process(frame)
                except SnapsGraphError as exc:  # name the frame's file where the dataset knows it
                    where = dataset.frame_source(frame.index)
                    if where is None:
                        raise
                    raise SnapsGraphError(f"{where}: {exc}") from None
                if on_frame is not None:
                    on_frame(out)
        result = pipe.finish()
        t0_ns = dataset.t0_ns  # .tum keeps the sequence's own clock (evo matches stamps)
        topics = dict(dataset.source_info)  # a bag's image topics
        t0_s = 0.0 if t0_ns is None else t0_ns * 1e-9
        gt, origin = ground_truth_in_output_frame(pipe, dataset.gt_poses, dataset.gt_origin)
        metrics = _write_all(tmp, pipe, result, gt, t0_s, topics, world_mesh, origin)
        if before_commit is not None:
            before_commit(tmp)
    return result, metrics


def ground_truth_in_output_frame(
    pipe: SlamPipeline, gt: np.ndarray | None, origin: np.ndarray | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The ground truth in the frame the outputs are in, and the ground truth's pose of that frame's
    origin: re-based on the run's first frame, or, once relocalised, on the prior's (None when
    either lacks ground truth: the figures would compare two frames)."""
    i = pipe.frame_prior
    if i is None or gt is None:
        return gt, origin
    prior_origin = pipe.priors[i].gt_origin
    if origin is None or prior_origin is None:
        return None, None
    return np.linalg.inv(prior_origin) @ origin @ gt, prior_origin


def read_priors(priors: Iterable[str | Path], out_dir: str | Path) -> list[Session]:
    """The prior sessions, checked before the results folder opens: each once, none the output."""
    sessions: list[Session] = []
    seen: dict[Path, str] = {}
    for given in priors:
        path = Path(given)
        full = path.resolve()
        if full == Path(out_dir).resolve():
            raise SnapsGraphError(f"{path}: the prior is the output folder; a run never writes its prior, name another --out")
        if inside(out_dir, full):
            raise SnapsGraphError(f"{path}: the output folder {out_dir} lies inside the prior; a run never writes its prior")
        if full in seen:
            raise SnapsGraphError(f"{path}: given twice as a prior (also as {seen[full]})")
        seen[full] = str(given)
        sessions.append(read_session(path))
    return sessions


def write_results(
    out_dir: str | Path, pipe: SlamPipeline, result: RunResult, gt_poses: np.ndarray | None = None, *, overwrite: bool = False
) -> dict:
    """Write the results folder, whole or not at all; returns the metrics (also metrics.json)."""
    with output_folder(out_dir, overwrite) as tmp:
        return _write_all(tmp, pipe, result, gt_poses)


def _write_all(
    out: Path,
    pipe: SlamPipeline,
    result: RunResult,
    gt_poses: np.ndarray | None,
    t0_s: float = 0.0,
    topics: dict | None = None,
    world_mesh: str | Path | None = None,
    gt_origin: np.ndarray | None = None,
) -> dict:
    stamps = result.timestamps + t0_s
    write_trajectories(out, result.trajectories, stamps)
    session = pipe.session(result)
    if session is not None:  # what a later run needs to relocalise against this one
        session.gt_origin = gt_origin
        write_session(session_folder(out), session)
    for i, poses in result.prior_trajectories.items():  # the priors as the run placed them (drawn by compare)
        write_trajectories(out, {f"prior{i}": poses}, pipe.priors[i].timestamps)
    if gt_poses is not None:
        write_gt(out, gt_poses, stamps)
    write_frames_csv(out / "frames.csv", result.records)
    write_loops_jsonl(out / "loops.jsonl", result.loops)
    if pipe.snaps is not None:  # every similarity SNAPS computed (types.CandidateRecord)
        write_candidates_csv(out / "candidates.csv", pipe.snaps.candidate_records())
    pipe.cfg.dump(out / "config.toml")
    failures = list(result.graph_failures)
    try:
        pipe.graph.save_g2o(out / "graph.g2o")
    except Exception as exc:  # the graph file is a convenience; never lose the run for it
        failures.append((-1, f"graph.g2o not written: {exc}"))

    metrics = run_metrics(result, gt_poses, failures)
    if pipe.map is not None:
        try:
            map_metrics = write_map_outputs(out, pipe.map, result.trajectories, gt_poses, pipe.cfg.map, world_mesh)
        except Exception as exc:  # the map is built from the trajectories: never lose them for it
            if interrupted():  # Ctrl-C cut an import or a call: the user stopped, the map did not fail
                raise
            map_metrics = {"error": _one_line(f"{type(exc).__name__}: {exc}")}
        if map_metrics is not None:
            metrics["map"] = map_metrics
            placed = pipe.placed_priors()
            if placed and "error" not in map_metrics:  # the priors' maps beside this run's, one file
                sessions_map = write_sessions_map(out, [(Path(pipe.priors[i].name), T) for i, T in placed])
                if sessions_map is not None:
                    map_metrics["sessions"] = sessions_map
    if result.sessions:
        metrics["sessions"] = result.sessions
    track = getattr(pipe.vo, "track", None)  # a pose-file front end (run --odometry): the report names it
    if track is not None:
        metrics["odometry_file"] = str(track.path)
    if topics:
        metrics["topics"] = topics  # the image topics that ran (a bag's, found by name or given)
    metrics["peak_rss_mb"] = peak_rss_mb()
    write_metrics_json(out / "metrics.json", metrics)
    return metrics


def _one_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return (lines[0] if lines else "unknown error")[:300]


def run_metrics(result: RunResult, gt_poses: np.ndarray | None, graph_failures: Iterable | None = None) -> dict:
    """Per-trajectory metrics (with ground truth), latency summaries, flagged frames."""
    n = len(result.records)
    metrics: dict = {
        "frames": n,
        "flagged_frames": result.n_flagged,
        "loops": len(result.loops),
        # the rest went to the factor graph only (found inside the pause after a loop)
        "loops_corrected": sum(1 for lp in result.loops if lp.weight > 0.0),
        "wall_s": result.wall_s,
    }
    if gt_poses is not None:
        ids = [r.frame for r in result.records]  # frames with gaps: figures over the parts that ran
        metrics["trajectories"] = {name: evaluate(p, gt_poses, ids) for name, p in result.trajectories.items()}
    metrics["latency_ms"] = latency_summary(result.records)
    metrics["peak_rss_mb"] = peak_rss_mb()
    failures = result.graph_failures if graph_failures is None else graph_failures
    metrics["graph_failures"] = [{"k": k, "reason": r} for k, r in failures]
    metrics["graph"] = result.graph_stats  # factor counts, solve times
    return metrics


def mostly_flagged(metrics: dict) -> bool:
    """More than FLAGGED_FRACTION_LIMIT of the frames flagged by the front end."""
    return metrics.get("flagged_frames", 0) > FLAGGED_FRACTION_LIMIT * max(metrics.get("frames", 0), 1)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


__all__ = [
    "FLAGGED_FRACTION_LIMIT",
    "latency_summary",
    "mostly_flagged",
    "run_metrics",
    "run_sequence",
    "write_results",
]
