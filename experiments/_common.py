"""Shared by the experiment scripts: data, a VO cache, and replays of SNAPS + graph over it.

The front end is the expensive stage and does not depend on SNAPS or graph parameters, so an
experiment runs it once per sequence (``vo_cache``) and replays the cached VO results through the
real pipeline (``SlamPipeline(frontend=CachedOdometry(...))``) for every setting it sweeps. The
replay feeds SNAPS the stored thumbnails (with thumbnail scale 1), which gives exactly the
thumbnails a full run computes. Latency figures of a replay cover SNAPS and the graph only.

Experiments that run whole runs (fig3_fig4, table1_sweep) go through ``snaps-graph batch``'s API
instead (``run_plan``): one Ray task per run, on this machine or a cluster, resumable; their
results are read back from the run folders (``read_loops``, ``read_frames``, metrics.json).
"""

from __future__ import annotations

import copy
import csv
import json
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.loop.uiqi import make_thumbnail
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.types import (
    StereoFrame,
    VOResult,
)

RESULTS = ROOT / "results" / "experiments"
SHARED = ROOT.parent / "shared" / "data"
PATHS = {"00": SHARED / "kitti_gt" / "00.txt", "07": SHARED / "kitti_gt" / "07.txt", "loop": "loop"}


def config_from_set(items: list[str]) -> Config:
    """The default Config with ``--set section.key=value`` overrides (``Config.with_overrides``,
    as ``snaps-graph run --set``); a bad one exits with a one-line error."""
    from snaps_graph.errors import SnapsGraphError

    try:
        return Config().with_overrides(items)
    except SnapsGraphError as exc:
        raise SystemExit(f"error: {exc}") from None


def frontend_from_args(description: str):
    """``SEQ [--frames A:B] [--set section.key=value ...]`` of the front-end experiments: the
    sequence (with ground truth) and the front-end config with the overrides."""
    import argparse

    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("seq")
    ap.add_argument("--frames", default=None)
    ap.add_argument("--set", nargs="*", default=[], help="config overrides section.key=value (TOML values)")
    args = ap.parse_args()
    return KittiSequence(args.seq, frames=args.frames), config_from_set(args.set).frontend


def synthetic_dir(path: str, width: int = 1241, height: int = 376, seed: int = 0, frames: str | None = None) -> Path:
    """Render a synthetic sequence along a KITTI path (or the built-in loop) once; reuse it after."""
    from tqdm import tqdm

    from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder

    tag = f"{path}_{width}x{height}_s{seed}" + (f"_{frames.replace(':', '-')}" if frames else "")
    out = RESULTS / "data" / tag
    if (out / "poses.txt").is_file():
        return out
    poses, times = load_trajectory(str(PATHS.get(path, path)), frames)
    seq = SyntheticSequence(poses, width=width, height=height, seed=seed, times=times)
    with tqdm(total=len(seq), desc=f"render {tag}", unit="frame", mininterval=2) as bar:
        render_to_folder(seq, out, progress=lambda *_: bar.update(1), overwrite=True)
    return out


@dataclass
class VOCache:
    camera: object
    indices: np.ndarray
    timestamps: np.ndarray
    gt: np.ndarray | None
    results: dict[int, VOResult]
    thumbs: dict[int, np.ndarray]
    vo_ms: np.ndarray  # front-end time per frame, ms


def vo_cache(seq: KittiSequence, cfg: Config) -> VOCache:
    from tqdm import tqdm

    from snaps_graph.frontend.odometry import StereoOdometry

    vo = StereoOdometry(seq.camera, cfg.frontend)
    results, thumbs, times = {}, {}, []
    for f in tqdm(seq, total=len(seq), desc="vo", unit="frame", mininterval=2):
        t0 = time.perf_counter()
        results[f.index] = vo.process(f)
        times.append((time.perf_counter() - t0) * 1e3)
        thumbs[f.index] = make_thumbnail(f.left, cfg.loop.thumbnail_scale)
    vo.close()
    return VOCache(seq.camera, seq.indices, seq.timestamps, seq.gt_poses, results, thumbs, np.array(times))


class CachedOdometry:
    """A front end that returns stored results (the pipeline's pluggable front-end interface)."""

    disparity_offset_px = 0.0  # the cached results carry their own (VOResult.disparity_offset_px)

    def __init__(self, cache: VOCache):
        self.cache = cache

    def process(self, frame: StereoFrame) -> VOResult:
        return copy.copy(self.cache.results[frame.index])

    def close(self) -> None:
        pass


def replay(cache: VOCache, cfg: Config, refine: str = "batch", loops: str = "snaps", setup=None):
    """Run SNAPS + graph over cached VO; returns (RunResult, pipeline). ``setup(pipeline)`` runs
    before the first frame (e.g. benchmarks/_loop_research.use_closer)."""
    cfg = copy.deepcopy(cfg)
    cfg.loop.thumbnail_scale = 1.0  # the cached thumbnails are already at the configured scale
    pipe = SlamPipeline(cache.camera, cfg, loops=loops, refine=refine, build_map=False, frontend=CachedOdometry(cache))
    if setup is not None:
        setup(pipe)
    for idx, t in zip(cache.indices, cache.timestamps):
        th = cache.thumbs[int(idx)]
        pipe.process(StereoFrame(int(idx), float(t), th, th))
    return pipe.finish(), pipe


def add_batch_args(ap) -> None:
    """The options of an experiment that runs its cells through ``snaps-graph batch``'s API."""
    ap.add_argument("--address", default=None, help="join this Ray cluster (default: Ray on this machine)")
    ap.add_argument("--max-parallel", type=int, default=None, help="at most this many runs at once")


def run_plan(plan: dict, out: Path, args, source: str) -> list[tuple[object, dict]]:
    """Run a plan (a dict as a plan file holds) through the batch API into ``out``; finished
    cells are skipped. Returns (cell, record) pairs in plan order; ``cell.folder(out)`` is the run."""
    from snaps_graph.batch import plan_from_dict, run_batch

    p = plan_from_dict(plan, source=source)
    records = run_batch(p, out, address=args.address, max_parallel=args.max_parallel)
    return list(zip(p.cells, records))


def read_loops(run_dir: Path) -> list[SimpleNamespace]:
    """A run folder's loops.jsonl, one object per loop (``.frame``, ``.reference``, ...)."""
    text = (Path(run_dir) / "loops.jsonl").read_text()
    return [SimpleNamespace(**json.loads(line)) for line in text.splitlines() if line.strip()]


def read_frames(run_dir: Path) -> dict[str, np.ndarray]:
    """A run folder's frames.csv as columns of floats."""
    with open(Path(run_dir) / "frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {
        k: np.array([float(r[k]) if r[k] not in ("", "True", "False") else float(r[k] == "True") for r in rows])
        for k in (rows[0] if rows else {})
    }


def false_loops(loops, gt: np.ndarray, indices: np.ndarray, radius_m: float) -> int:
    k_of = {int(i): k for k, i in enumerate(indices)}
    return sum(np.linalg.norm(gt[k_of[l.reference], :3, 3] - gt[k_of[l.frame], :3, 3]) > radius_m for l in loops)


def md_table(header: list[str], rows: list[list]) -> str:
    def fmt(v):
        if v is None:  # a metric metrics.json holds as null (not computable)
            return "n/a"
        if isinstance(v, float):
            return "n/a" if v != v else f"{v:.3f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"
