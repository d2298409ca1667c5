"""``make bench``: the quick benchmarks, one after another, each printing its own figures.

Reduced sizes so the whole set takes minutes on 2 cores; each script's docstring gives the
full-size command behind the README's figures. A benchmark whose data (../shared/data) is absent
is skipped with the reason. Exit status 1 when any benchmark failed.

    python benchmarks/run_all.py [--only frontend,snaps] [--list]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
KITTI06 = SHARED / "kitti" / "sequences" / "06"
KITTI00_GT = SHARED / "kitti_gt" / "00.txt"

# name, script, arguments, data the script needs (None: none)
BENCHMARKS: list[tuple[str, str, list[str], Path | None]] = [
    ("frontend", "bench_frontend.py", ["--modes", "naive,default"], KITTI06),
    ("synth", "bench_synth.py", ["--frames", "20", "--width", "620", "--height", "188"], None),
    ("snaps", "bench_snaps.py", ["--frames", "1500"], KITTI00_GT),
    ("graph", "bench_graph.py", ["--frames", "1500"], KITTI00_GT),
    ("map", "bench_map.py", ["--run", str(KITTI06), str(ROOT / "results" / "bench" / "map06")], KITTI06),
    (  # the built-in loop (300 frames, closes loops; no data needed), rendered once into results/bench
        "pipeline",
        "bench_pipeline.py",
        [
            "--trajectory",
            "loop",
            "--width",
            "620",
            "--height",
            "188",
            "--seq",
            str(ROOT / "results" / "bench" / "loop300_620"),
            "--naive-frames",
            "10",
        ],
        None,
    ),
    ("batch", "bench_batch.py", ["--width", "620", "--height", "188"], None),  # 4 cells of 40 frames on local Ray
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=None, help="comma-separated names (default: all)")
    ap.add_argument("--list", action="store_true", help="print the commands and exit")
    args = ap.parse_args()
    names = [b[0] for b in BENCHMARKS]
    only = args.only.split(",") if args.only else names
    unknown = sorted(set(only) - set(names))
    if unknown:
        ap.error(f"unknown benchmark(s) {', '.join(unknown)}; have {', '.join(names)}")
    failed = []
    for name, script, extra, needs in BENCHMARKS:
        if name not in only:
            continue
        cmd = [sys.executable, str(ROOT / "benchmarks" / script), *extra]
        print(f"\n=== {name}: {' '.join(cmd[1:])}", flush=True)
        if args.list:
            continue
        if needs is not None and not needs.exists():
            print(f"skipped: {needs} not found (../shared/data)", flush=True)
            continue
        t0 = time.perf_counter()
        rc = subprocess.call(cmd, cwd=ROOT)
        print(f"=== {name}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
