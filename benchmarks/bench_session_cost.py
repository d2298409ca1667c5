"""What a prior session costs: its size on disk, the time to load it, the time per frame while the
run is not relocalised, and the memory it adds.

Given a run folder (the prior; e.g. a whole 4541-frame run of the street rendering of KITTI 00)
and a sequence that does not drive through it (so the run stays unrelocalised and every frame pays
the appearance search), prints:

- the session's size on disk, in all and per frame (target <= 40 KB per frame);
- the time to load it as a run does (read and check every file, the coarse appearance vectors,
  the verifier's references), the best of three (target <= 3 s for 4541 frames);
- per frame over the sequence, the loop closer's time (search, similarities, verification) with
  and without the prior, median and 95th percentile (target: median <= 10 ms with it);
- the peak memory of the two runs and their difference against the session's size (target:
  the difference <= 2x the size).

    python benchmarks/bench_session_cost.py PRIOR_RUN SEQUENCE [--frames 0:300] [--odometry FILE]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from snaps_graph.camera import StereoCamera
from snaps_graph.config import Config
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.session import read_session, session_folder


def load_seconds(prior: Path) -> float:
    """Read the session and set it up as a run does (the pipeline's priors), seconds."""
    t0 = time.perf_counter()
    s = read_session(prior)
    c = s.camera
    pipe = SlamPipeline(StereoCamera(c.fx, c.fy, c.cx, c.cy, c.baseline_m), Config(), priors=[s])
    elapsed = time.perf_counter() - t0
    pipe.vo.close()
    return elapsed


def run(seq: Path, out: Path, frames: str, odometry: Path | None, prior: Path | None) -> tuple[dict, list[float]]:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [str(Path(sys.executable).parent / "snaps-graph"), "run", str(seq), "--frames", frames, "--out", str(out)]
    cmd += ["--odometry", str(odometry)] if odometry else []
    cmd += ["--prior", str(prior)] if prior else []
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    metrics = json.loads((out / "metrics.json").read_text())
    rows = np.genfromtxt(out / "frames.csv", delimiter=",", names=True, dtype=None, encoding=None)
    return metrics, list(rows["t_loop_ms"] + rows["t_verify_ms"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("prior", type=Path, help="the prior's results folder")
    ap.add_argument("sequence", type=Path, help="a sequence that does not drive through the prior")
    ap.add_argument("--frames", default="0:300")
    ap.add_argument("--odometry", type=Path, help="odometry for the sequence instead of the stereo VO")
    ap.add_argument("--work", type=Path, default=ROOT / "results" / "bench_session_cost")
    args = ap.parse_args()
    folder = session_folder(args.prior)
    size = sum(p.stat().st_size for p in folder.iterdir())
    n = len(read_session(args.prior))
    print(f"session: {n} frames, {size / 2**20:.1f} MiB, {size / n / 1024:.1f} KB per frame (target <= 40)")
    loads = [load_seconds(args.prior) for _ in range(3)]
    print(f"load: {min(loads):.2f} s best of 3 (target <= 3 s for 4541 frames)")
    alone, t_alone = run(args.sequence, args.work / "alone", args.frames, args.odometry, None)
    with_prior, t_prior = run(args.sequence, args.work / "with_prior", args.frames, args.odometry, args.prior)
    reloc = with_prior["sessions"][0]
    if reloc["relocalised"]:
        print(f"note: relocalised at frame {reloc['frame']} (against {reloc['reference']}): the figures below cover all frames")
    for name, t in (("alone", t_alone), ("with the prior", t_prior)):
        print(f"loop closer per frame, {name}: median {statistics.median(t):.2f} ms, p95 {np.percentile(t, 95):.2f} ms")
    added = with_prior["peak_rss_mb"] - alone["peak_rss_mb"]
    print(
        f"peak memory: {alone['peak_rss_mb']:.0f} MiB alone, {with_prior['peak_rss_mb']:.0f} MiB with the prior: "
        f"+{added:.0f} MiB = {added * 2**20 / size:.2f}x the session's size (target <= 2)"
    )


if __name__ == "__main__":
    main()
