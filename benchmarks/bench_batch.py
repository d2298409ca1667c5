"""Benchmark: `snaps-graph batch` on Ray against running the same cells one after another.

Four cells (one 40-frame sequence x four variants of equal cost) are run
  1. one after another in this process (the runner, as `experiments/` did before; OpenCV and the
     front end use their default threads), then
  2. as a batch on a fresh local Ray instance with 2 CPUs, timed with Ray's start-up ("cold") and
     without it ("warm": Ray started before the clock, as when joining a running cluster;
     worker processes still import the package on their first cell),
  3. then the batch again over the finished folder (every cell skipped), in this process and as
     the `snaps-graph batch` command (Python start-up and imports included).

    python benchmarks/bench_batch.py                      # 40 full-size frames of KITTI 00's path
    python benchmarks/bench_batch.py --frames 40 --width 620 --height 188

Without ../shared/data the built-in loop is used. Targets: batch wall time <= 0.6x the serial
time; a resumed plan whose cells are all done finishes in seconds. Prints the machine's load
(the figures are only meaningful on an otherwise idle machine).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # local Ray on 127.0.0.1 only
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from snaps_graph.batch import plan_from_dict, run_batch  # noqa: E402
from snaps_graph.runner import run_sequence  # noqa: E402
from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KITTI00 = ROOT.parent / "shared" / "data" / "kitti_gt" / "00.txt"


def load() -> str:
    return open("/proc/loadavg").read().split()[0] if Path("/proc/loadavg").is_file() else "?"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--width", type=int, default=1241)
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--cells", type=int, default=4)
    ap.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance")
    ap.add_argument("--seq", default=None, help="a KITTI-format sequence instead of a rendering")
    ap.add_argument("--work", default=str(ROOT / "results" / "bench_batch"))
    args = ap.parse_args()
    work = Path(args.work)
    print(f"cpus {os.cpu_count()}, load average at start {load()} (`uptime`)")

    seq_dir = (Path(args.seq) if args.seq else work / f"seq_{args.frames}_{args.width}x{args.height}").absolute()
    if not args.seq and not (seq_dir / "poses.txt").is_file():
        traj = str(KITTI00) if KITTI00.is_file() else "loop"
        poses, times = load_trajectory(traj, f"0:{args.frames}")
        render_to_folder(
            SyntheticSequence(poses, width=args.width, height=args.height, seed=0, times=times), seq_dir, overwrite=True
        )
    # Four variants of equal cost: the loop radius does not change the work on 40 frames.
    variants = {f"r{i}": {"loop": {"radius_m": 8.0 + i}} for i in range(args.cells)}
    plan = plan_from_dict({"sequences": [str(seq_dir)], "frames": f"0:{args.frames}", "variants": variants}, source="bench plan")
    print(f"{len(plan.cells)} cells of {args.frames} frames at {args.width}x{args.height} ({seq_dir})")

    serial_dir = work / "serial"
    shutil.rmtree(serial_dir, ignore_errors=True)
    t0, cpu0 = time.perf_counter(), os.times()
    per_cell = []
    for cell in plan.cells:
        t1 = time.perf_counter()
        run_sequence(cell.open(), cell.folder(serial_dir), cell.cfg)
        per_cell.append(time.perf_counter() - t1)
    serial = time.perf_counter() - t0
    cpu = (os.times().user - cpu0.user) + (os.times().system - cpu0.system)
    print(
        f"serial (one process, one after another): {serial:.1f} s, {cpu:.1f} CPU-s = {cpu / serial:.2f} cores busy  (cells {', '.join(f'{t:.1f}' for t in per_cell)} s)  load {load()}"
    )

    import ray

    for label in ("cold", "warm"):
        out = work / f"batch_{label}"
        shutil.rmtree(out, ignore_errors=True)
        if label == "warm":
            t_init = time.perf_counter()
            ray.init(
                address="local",
                num_cpus=args.cpus,
                include_dashboard=False,
                log_to_driver=False,
                logging_level="WARNING",
                object_store_memory=128 * 2**20,
            )
            init_s = time.perf_counter() - t_init
        t0 = time.perf_counter()
        rows = run_batch(plan, out, progress=False, ray_init={"num_cpus": args.cpus})
        wall = time.perf_counter() - t0
        if ray.is_initialized():
            ray.shutdown()
        ok = sum(r["status"] == "ok" for r in rows)
        cells = ", ".join(f"{r.get('wall_s', 0):.1f}" for r in rows)
        extra = f" (Ray start {init_s:.1f} s not counted)" if label == "warm" else " (Ray start included)"
        print(
            f"batch {label}, {args.cpus} CPUs: {wall:.1f} s = {wall / serial:.2f}x serial{extra}; {ok}/{len(rows)} ok; cells {cells} s  load {load()}"
        )

    out = work / "batch_cold"
    t0 = time.perf_counter()
    rows = run_batch(plan, out, progress=False)
    resumed = time.perf_counter() - t0
    plan_file = work / "plan.toml"
    body = "".join(f"[variants.{k}]\nloop = {{ radius_m = {v['loop']['radius_m']} }}\n" for k, v in variants.items())
    plan_file.write_text(f'sequences = ["{seq_dir}"]\nframes = "0:{args.frames}"\n{body}')
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "snaps_graph.cli", "batch", str(plan_file), "--out", str(out)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    cli = time.perf_counter() - t0
    print(
        f"resumed, all {sum(r['status'] == 'skipped' for r in rows)} cells done: {resumed:.2f} s in process; "
        f"`snaps-graph batch` command {cli:.1f} s (exit {proc.returncode}: {proc.stdout.strip()})"
    )
    print(f"load average at end {load()}")


if __name__ == "__main__":
    main()
