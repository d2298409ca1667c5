"""Where a frame's time goes: CPU and wall milliseconds per pipeline stage, in the thread that runs it.

Runs the pipeline (default config, ``--loops``, ``--refine``) over the frames, reading them inline
(no read-ahead, so reading is timed too), with timers wrapped around the stages: reading
(``read_grey``, two images), KLT tracking, PnP, the stereo of the tracked points and the
re-detection with its stereo (worker thread), the stereo BA, the local BA, SNAPS (with its
thumbnail), the graph. CPU is ``time.thread_time`` of the calling thread (OpenCV's own pool
threads are not in it); it is the robust figure on a loaded machine, the wall time is not.
Also prints minor page faults and process CPU per frame, and the load average.

    python benchmarks/bench_stages.py [--seq results/data/street00_1000] [--frames 0:500]
        [--loops snaps] [--refine isam2]
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from snaps_graph.backend import pose_graph
from snaps_graph.config import Config
from snaps_graph.datasets import kitti
from snaps_graph.datasets.open import open_dataset
from snaps_graph.frontend import depth, features, local_ba, odometry, tracking
from snaps_graph.loop import snaps as snaps_mod
from snaps_graph.pipeline import SlamPipeline

STAGES: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0])  # this frame: name -> [cpu s, wall s]


def _wrap(owner, name: str, label: str) -> None:
    if not hasattr(owner, name):
        return
    fn = getattr(owner, name)

    def timed(*args, **kwargs):
        c0, t0 = time.thread_time(), time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            s = STAGES[label]
            s[0] += time.thread_time() - c0
            s[1] += time.perf_counter() - t0

    setattr(owner, name, timed)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", default="results/data/street00_1000")
    ap.add_argument("--frames", default="0:500")
    ap.add_argument("--loops", default="snaps")
    ap.add_argument("--refine", default="isam2")
    args = ap.parse_args()

    SO = odometry.StereoOdometry
    _wrap(kitti, "read_grey", "read (2 images)")
    _wrap(features, "track_klt", "KLT tracking")
    _wrap(depth, "sparse_depth", "sparse stereo, all calls")  # inside the two stereo stages below
    _wrap(tracking, "pnp_ransac", "PnP RANSAC")
    _wrap(tracking.KltTracker, "_stereo_tracked", "stereo of tracked points")
    _wrap(tracking.KltTracker, "_detect_new", "re-detection + its stereo")
    _wrap(tracking, "refine_motion", "stereo BA")
    _wrap(tracking, "make_keyframe", "keyframe bookkeeping")
    _wrap(local_ba.LocalBundleAdjuster, "add_keyframe", "local BA")
    _wrap(snaps_mod.SnapsLoopCloser, "step", "SNAPS (+ thumbnail)")
    _wrap(pose_graph.PoseGraph, "add_frame", "graph add_frame")
    _wrap(pose_graph.PoseGraph, "update", "graph iSAM2 update")
    _wrap(SO, "process", "front end (main thread)")
    _wrap(SlamPipeline, "process", "pipeline.process")

    ds = open_dataset(args.seq, frames=args.frames)
    pipe = SlamPipeline(ds.camera, Config(), loops=args.loops, refine=args.refine)
    rows = []
    r0, f0, t0 = os.times(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
    for frame in ds:
        pipe.process(frame)
        rows.append({k: tuple(v) for k, v in STAGES.items()})
        STAGES.clear()
    wall = time.perf_counter() - t0
    r1, f1 = os.times(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    pipe.finish()
    n = len(rows)
    cpu = (r1.user - r0.user + r1.system - r0.system) / n * 1e3
    print(
        f"{n} frames of {args.seq} (--loops {args.loops} --refine {args.refine}), load {os.getloadavg()[0]:.2f}; "
        f"process CPU {cpu:.1f} ms/frame, {(f1 - f0) / n:.0f} page faults/frame, wall {n / wall:.1f} frames/s"
    )
    print("ms per frame: mean over all frames; median over the frames where the stage ran")
    print(f"{'stage':<28}{'cpu mean':>9}{'cpu med':>9}{'wall mean':>10}{'wall med':>9}{'frames':>7}")
    for k in sorted({k for r in rows for k in r}, key=lambda k: -np.mean([r.get(k, (0, 0))[0] for r in rows])):
        ran = np.array([k in r for r in rows])
        c = np.array([r.get(k, (0.0, 0.0))[0] for r in rows]) * 1e3
        w = np.array([r.get(k, (0.0, 0.0))[1] for r in rows]) * 1e3
        print(f"{k:<28}{c.mean():9.2f}{np.median(c[ran]):9.2f}{w.mean():10.2f}{np.median(w[ran]):9.2f}{ran.sum():7d}")


if __name__ == "__main__":
    main()
