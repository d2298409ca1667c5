"""What each of the front end's cost settings buys in CPU and costs in accuracy, on the KITTI 06 clip.

Each variant is the default configuration with one ``section.key=value`` changed (the CLI's
``--set``; several joined by ``;``, as the built-in list's last cost variant, all of them at once). Runs alternate: the default, then every variant, ``--rounds`` times, each in a fresh
interpreter through ``bench_peers.py``'s own run (VO + SNAPS + iSAM2, no map, frames read into
memory first), then ORB-SLAM3's tracking once a round when its venv and vocabulary are present
(``bench_peers.py`` says how; skipped with the reason otherwise). The machine's speed drifts
between runs by more than most variants save, so a variant's CPU is compared within each round,
with the default's and ORB-SLAM3's of that round, and the per-round ratios' median is given.
Per variant: median per-frame wall and CPU time (medians over frames, then over rounds), those
ratios, ATE and end drift of the iSAM2 trajectory, and whether its poses equal the default's bit
for bit. A variant meets the speed targets' CPU bound when its CPU is at most
half ORB-SLAM3's; it keeps the accuracy when ATE <= 0.045 m and end drift <= 0.85 %.

The second group, "perturbation", changes a setting that costs nothing: how far the clip's ATE
moves under a change that buys no time is the yardstick for the first group's accuracy figures.

    python benchmarks/bench_budget.py [--rounds 2] [--variants frontend.klt.features=1000,...]
        [--peer-venv results/orb-venv] [--work results/budget]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_peers as peers  # noqa: E402

from snaps_graph.config import Config  # noqa: E402
from snaps_graph.errors import SnapsGraphError  # noqa: E402

ROOT = peers.ROOT
SEQ = "kitti06"
MAX_ATE_M, MAX_DRIFT_PERCENT, MAX_RATIO = peers.MAX_ATE_M, peers.MAX_DRIFT_PERCENT, peers.MAX_RATIO

# settings that remove work from every frame (or every keyframe / loop reference)
COST_VARIANTS = [
    "frontend.klt.features=1000",
    "frontend.klt.features=800",
    "frontend.klt.window_px=9",
    "frontend.klt.min_distance_px=12",
    "frontend.klt.bias_window_px=0",
    "frontend.stereo_guess_levels=3",
    "frontend.stereo_guess_levels=2",
    "frontend.stereo_ba.iterations=2",
    "frontend.local_ba.iterations=3",
    "frontend.local_ba.max_landmarks=200",
    "frontend.local_ba.every=4",
    # the cheaper settings above that cost least accuracy, all at once
    "frontend.klt.features=1000;frontend.klt.min_distance_px=12;frontend.stereo_guess_levels=3;frontend.local_ba.iterations=3",
]
# settings moved by a hair: no time bought, only the clip's sensitivity measured
PERTURBATION_VARIANTS = [
    "frontend.klt.quality=0.0105",
    "frontend.klt.border_px=17",
    "frontend.pnp_reprojection_px=1.45",
]


def write_config(item: str, work: Path) -> Path:
    """A TOML file of the default configuration with ``item`` (``;``-separated ``section.key=value``
    settings) applied; a bad setting: a one-line error."""
    cfg = Config().with_overrides([x for x in item.split(";") if x]) if item else Config()
    name = hashlib.sha256(item.encode()).hexdigest()[:12]
    path = work / "configs" / f"{name}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    cfg.dump(path)
    return path


def label(item: str) -> str:
    """The table's name of a variant: the setting, or ``all at once (N)`` for several."""
    settings = [x for x in item.split(";") if x]
    return "(the defaults)" if not settings else settings[0] if len(settings) == 1 else f"all at once ({len(settings)})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument(
        "--variants", default=None, help="comma-separated variants, each section.key=value[;...] (default: the built-in lists)"
    )
    ap.add_argument("--peer-venv", type=Path, default=ROOT / "results" / "orb-venv")
    ap.add_argument("--vocab", type=Path, default=ROOT / "results" / "ORBvoc.txt")
    ap.add_argument("--peer-script", type=Path, default=ROOT.parent / "shared" / "peers" / "peer_orbslam3.py")
    ap.add_argument("--work", type=Path, default=ROOT / "results" / "budget")
    args = ap.parse_args()
    if args.rounds < 1:
        print("error: --rounds must be at least 1")
        return 2
    rel, preset = peers.SEQUENCES[SEQ]
    seq = (ROOT / rel).resolve()
    if not seq.exists():
        print(f"{SEQ}: skipped, {seq} not found")
        return 0
    groups = {"cost": COST_VARIANTS, "perturbation": PERTURBATION_VARIANTS}
    if args.variants:
        groups = {"given": [v.strip() for v in args.variants.split(",") if v.strip()]}
    items = [""] + [v for vs in groups.values() for v in vs]
    try:
        configs = {item: write_config(item, args.work) for item in items}
    except SnapsGraphError as exc:  # a malformed or out-of-range item: its one-line reason
        print(f"error: {exc}")
        return 2
    args.peer_python = args.peer_venv / "bin" / "python"
    why = peers.peer_missing(args)
    if why:
        print(f"ORB-SLAM3 skipped: {why}")
    print(f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")

    runs: dict[str, list[dict]] = {item: [] for item in items}
    orb: list[dict] = []
    for rnd in range(args.rounds):
        if not why:
            try:
                orb.append(peers.peer_subprocess(args, seq, preset, args.work / f"r{rnd}" / "orb"))
                print(f"round {rnd}: ORB-SLAM3: {np.median(orb[-1]['cpu_ms']):.1f} ms CPU", flush=True)
            except (RuntimeError, OSError, ValueError, KeyError) as exc:
                why = str(exc)
                print(f"ORB-SLAM3 skipped from here on: {why}")
                orb = []
        for i, item in enumerate(items):
            try:
                runs[item].append(peers.ours_subprocess(seq, args.work / f"r{rnd}" / f"v{i}", str(configs[item])))
            except subprocess.CalledProcessError as exc:
                print(f"error: {label(item)}: our run failed (exit status {exc.returncode}; its message above)")
                return 2
            print(f"round {rnd}: {label(item)}: {np.median(runs[item][-1]['cpu_ms']):.1f} ms CPU", flush=True)
    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")

    gt = peers.gt_of(seq)
    gt = None if gt is None else gt[: len(runs[""][0]["wall_ms"])]
    cpu_of = {item: np.array([np.median(r["cpu_ms"]) for r in rs]) for item, rs in runs.items()}
    orb_cpu = np.array([np.median(r["cpu_ms"]) for r in orb]) if len(orb) == args.rounds else None
    base_digest = runs[""][0]["digest"]
    print()
    if orb_cpu is not None:
        per_round = ", ".join(f"{x:.1f}" for x in orb_cpu)
        print(f"ORB-SLAM3 tracking: CPU median {np.median(orb_cpu):.1f} ms a frame (rounds: {per_round})")
    head = (
        f"{'group':12} {'variant':36} {'ms/frame':>8} {'CPU ms':>7} {'x default':>9} {'x ORB':>6} "
        f"{'ATE m':>6} {'drift %':>7} {'same poses':>10} {'CPU bound':>9} {'accuracy':>8}"
    )
    print(head)
    print("-" * len(head))
    for group, vs in [("", [""])] + list(groups.items()):
        for item in vs:
            rs = runs[item]
            wall = float(np.median([np.median(r["wall_ms"]) for r in rs]))
            cpu = float(np.median(cpu_of[item]))
            ate, drift = peers.accuracy(rs[0]["poses"], gt)
            to_default = float(np.median(cpu_of[item] / cpu_of[""]))
            ratio = float(np.median(cpu_of[item] / orb_cpu)) if orb_cpu is not None else float("nan")
            cpu_ok = "n/a" if orb_cpu is None else ("met" if ratio <= MAX_RATIO else "NOT met")
            acc_ok = "kept" if ate <= MAX_ATE_M and drift <= MAX_DRIFT_PERCENT else "lost"
            same = "yes" if rs[0]["digest"] == base_digest else "no"
            print(
                f"{group or 'default':12} {label(item):36} {wall:8.1f} {cpu:7.1f} {to_default:9.2f} "
                f"{peers.fmt(ratio, '.2f'):>6} {peers.fmt(ate, '.3f'):>6} {peers.fmt(drift, '.2f'):>7} {same:>10} "
                f"{cpu_ok:>9} {acc_ok:>8}"
            )
            if len({r["digest"] for r in rs}) > 1:
                print(f"  {label(item)}: poses differ between rounds")
    for item in items:
        if ";" in item:
            print(f"{label(item)}: {item.replace(';', ' ')}")
    print(
        f"{os.cpu_count()} cores; ms/frame and CPU ms: medians over frames, then over {args.rounds} rounds; "
        "x default, x ORB: the median over rounds of the CPU against that round's; "
        f"accuracy kept: ATE <= {MAX_ATE_M} m and end drift <= {MAX_DRIFT_PERCENT} %"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
