"""Benchmark: render a synthetic stereo sequence along KITTI 00's path to disk.

Prints the world build time, stereo pairs per second written to disk (wall clock), and the
milliseconds per pair spent in each stage (ray casting, shading, PNG writing; summed over the
worker threads, so they can add up to more than the wall time per pair).

    python benchmarks/bench_synth.py                 # 100 full-size frames of KITTI 00's path
    python benchmarks/bench_synth.py --frames 20 --width 620 --height 188
    python benchmarks/bench_synth.py --scene open --traffic --lighting   # what the worlds cost

Without ../shared/data the built-in loop is used instead. Target: >= 5 pairs/s at 1241x376 on
a 2-core machine.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from snaps_graph.synth import SCENES, SyntheticSequence, WorldConfig, load_trajectory, render_to_folder

ROOT = Path(__file__).resolve().parents[1]
KITTI00 = ROOT.parent / "shared" / "data" / "kitti_gt" / "00.txt"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="frames to render (default 100)")
    ap.add_argument("--start", type=int, default=0, help="first frame of the path")
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--workers", type=int, default=2, help="render threads (default 2)")
    ap.add_argument(
        "--trajectory",
        default=str(KITTI00) if KITTI00.is_file() else "loop",
        help="KITTI pose file or 'loop' (default: KITTI 00's ground truth)",
    )
    ap.add_argument("--depth", action="store_true", help="also write depth_0/ (uint16 mm)")
    ap.add_argument("--scene", default="street", choices=SCENES)
    for flag in ("aliasing", "traffic", "lighting"):
        ap.add_argument(f"--{flag}", action="store_true", help=f"hard world: {flag}")
    args = ap.parse_args()
    world = WorldConfig(scene=args.scene, aliasing=args.aliasing, traffic=args.traffic, lighting=args.lighting)

    # As the CLI does: the path is cut to the frames first, the world is built along that cut.
    poses, times = load_trajectory(args.trajectory, f"{args.start}:{args.start + args.frames}")
    t0 = time.perf_counter()
    seq = SyntheticSequence(poses, width=args.width, height=args.height, times=times, world_config=world)
    build_s = time.perf_counter() - t0
    stop = args.start + len(seq)

    with tempfile.TemporaryDirectory(prefix="bench_synth_") as tmp:
        totals = render_to_folder(seq, tmp, write_depth=args.depth, workers=args.workers)
    n = int(totals["frames"])
    print(
        f"trajectory      {args.trajectory} frames {args.start}:{stop} ({n} pairs), {args.width}x{args.height}, "
        f"{args.workers} workers, scene {args.scene}"
        + "".join(f", {f}" for f in ("aliasing", "traffic", "lighting") if getattr(args, f))
    )
    print(f"world build     {build_s:.2f} s ({len(seq.world.boxes)} boxes, {len(seq.world.triangles)} triangles)")
    print(f"throughput      {n / totals['wall_s']:.2f} pairs/s written to disk ({totals['wall_s']:.2f} s wall)")
    for stage in ("cast", "shade", "write"):
        print(f"  {stage:<6} {totals[stage] / n:8.1f} ms per pair (elapsed inside the workers, summed over them)")


if __name__ == "__main__":
    main()
