"""What ``--rrd`` costs: frames/s with and without the rerun logger recording to a file.

Images are read once, before timing (``--stream``: during the run, for long sequences; the
reading then counts in both variants alike). Runs the pipeline (default config, SNAPS, the given
refinement and map) over the frames ``--reps`` times without and with a ``RerunLogger`` writing an
``.rrd``, alternating, and prints per variant the median over repetitions of: wall frames/s,
process CPU seconds per frame (includes rerun's background batching and writing threads, so it
is the honest cost on a shared machine), and the CPU time spent inside the logger's hook per frame;
then the overhead in percent of the frame time.

    python benchmarks/bench_rerun.py [--seq ../shared/data/kitti/sequences/06] [--frames 0:51]
        [--reps 3] [--refine isam2] [--map] [--stream]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from snaps_graph.config import Config
from snaps_graph.datasets.open import open_dataset
from snaps_graph.pipeline import SlamPipeline


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class Timed:
    """Thread CPU time spent inside the logger's hooks (not wall: the machine may be shared)."""

    def __init__(self, inner):
        self.inner, self.s = inner, 0.0

    def on_frame(self, *a):
        t = time.thread_time()
        self.inner.on_frame(*a)
        self.s += time.thread_time() - t

    def on_finish(self, *a):
        t = time.thread_time()
        self.inner.on_finish(*a)
        self.s += time.thread_time() - t


def run_once(seq, frames, refine: str, build_map: bool, rrd: Path | None) -> dict:
    observer = None
    if rrd is not None:
        from snaps_graph.viz.rerun_logger import RerunLogger

        observer = Timed(RerunLogger(seq.camera, rrd=rrd, gt_poses=seq.gt_poses))
    c0, t0 = cpu_s(), time.perf_counter()
    pipe = SlamPipeline(seq.camera, Config(), loops="snaps", refine=refine, build_map=build_map)
    pipe.observer = observer
    for f in frames:
        pipe.process(f)
    pipe.finish()
    if observer is not None:
        observer.inner.close()  # flushes: the file is complete when the clock stops
    wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    n = len(frames)
    return {
        "fps": n / wall,
        "cpu_ms": cpu / n * 1e3,
        "hook_ms": (observer.s / n * 1e3) if observer else 0.0,
        "bytes": rrd.stat().st_size if rrd is not None else 0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", default=str(ROOT.parent / "shared/data/kitti/sequences/06"))
    ap.add_argument("--frames", default="0:51")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--refine", default="isam2")
    ap.add_argument("--map", action="store_true")
    ap.add_argument("--stream", action="store_true", help="read frames during the run (long sequences) instead of once before")
    a = ap.parse_args()
    seq = open_dataset(a.seq, frames=a.frames)
    frames = seq if a.stream else list(seq)
    print(
        f"{a.seq} frames {a.frames}: {len(frames)} frames {seq.camera.width}x{seq.camera.height}, refine {a.refine}, map {a.map}"
    )
    res: dict[str, list[dict]] = {"plain": [], "rrd": []}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(a.reps):
            res["plain"].append(run_once(seq, frames, a.refine, a.map, None))
            res["rrd"].append(run_once(seq, frames, a.refine, a.map, Path(tmp) / f"r{rep}.rrd"))
    med = {k: {m: float(np.median([r[m] for r in v])) for m in v[0]} for k, v in res.items()}
    print(f"{'variant':<8}{'frames/s':>10}{'CPU ms/frame':>14}{'hook CPU ms':>15}{'rrd MB':>9}")
    for k, m in med.items():
        print(f"{k:<8}{m['fps']:>10.2f}{m['cpu_ms']:>14.1f}{m['hook_ms']:>15.2f}{m['bytes'] / 1e6:>9.1f}")
    wall_over = (med["plain"]["fps"] / med["rrd"]["fps"] - 1) * 100
    cpu_over = (med["rrd"]["cpu_ms"] / med["plain"]["cpu_ms"] - 1) * 100
    hook_share = med["rrd"]["hook_ms"] / med["plain"]["cpu_ms"] * 100
    print(
        f"--rrd overhead: wall {wall_over:+.1f} %, process CPU {cpu_over:+.1f} %, hook CPU {hook_share:.1f} % of the plain frame's CPU"
    )
    print(
        "per-rep frames/s plain:",
        " ".join(f"{r['fps']:.2f}" for r in res["plain"]),
        "| rrd:",
        " ".join(f"{r['fps']:.2f}" for r in res["rrd"]),
    )


if __name__ == "__main__":
    main()
