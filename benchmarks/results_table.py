"""The README's results table: VO / SNAPS / iSAM2 / batch accuracy, loops and speed, and ORB-SLAM3
beside us, measured now.

Runs the command-line tool on each input it has data for and writes the table (markdown) to
``--out`` and to stdout. Every row is one ``snaps-graph`` command with ``--refine both``, printed
under the table, so each column means one trajectory in every row:

* ``kitti06``: the real KITTI 06 clip (frames 0-50, 59.9 m, no revisit), ``run --map``;
* ``demo``: the built-in 300-frame synthetic loop, ``snaps-graph demo`` (what ``make demo`` runs,
  with the batch refinement too);
* ``revisit``: the real KITTI 00 revisit (left images of frames 100-230 and 1540-1660) with
  odometry from ``snaps-graph drift`` (the ground truth with 1 % end drift, seed 0) and
  ``run --odometry DRIFTED``; below the table, the mean deviation over frames 1560-1660 (the
  revisit, as ``benchmarks/bench_revisit.py`` measures it) and the loops.

Rows whose input is not at hand (a rendering not made yet) say so and how to make it; nothing is
estimated. ``street07`` / ``street00``: the street renderings of KITTI 07 and 00 (``make data``).

The second table puts ORB-SLAM3 (stereo, the peer kit in ``../shared/peers``, set up as its
README says) beside our pipeline on the KITTI 06 clip, run alternately ``--peer-repeats`` times
each by ``bench_peers.py``'s functions; without the kit it says what is missing.

    python benchmarks/results_table.py                          # data from ../shared/data
    python benchmarks/results_table.py --kitti06 DATA/kitti/sequences/06 --out docs/results/README-table.md
    python benchmarks/results_table.py --readme README.md      # ... and the same table into the README

Frames per second are the pipeline's own rate (frames / sum of per-frame processing time, what
``run`` prints as "frames/s"); the machine's load average is printed beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"

# The street renderings of KITTI paths: (name, the `make data` recipe, its placeholder in the commands).
RENDERED = [("07", "street07", "STREET07"), ("00", "street00", "STREET00")]


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "snaps_graph.cli", *args]


def _shown(cmd: list[str], names: dict[str, str] | None = None) -> str:
    """The command as a user types it (``snaps-graph ...``), paths relative to the repository;
    ``names`` shows a data folder by its name (``KITTI06``), since it lies outside the repository."""
    words = ["snaps-graph", *cmd[3:]]
    out = []
    for w in words:
        if names and w in names:
            out.append(names[w])
            continue
        p = Path(w)
        if p.is_absolute():
            try:
                w = os.path.relpath(p, ROOT)
            except ValueError:
                pass
        out.append(shlex.quote(w))
    return " ".join(out)


BEGIN, END = "<!-- results_table.py: begin -->", "<!-- results_table.py: end -->"
LOADS: list[float] = []  # the 1-minute load average after each command ran: speed depends on it


def _run(cmd: list[str], metrics: Path | None, reuse: bool) -> dict:
    if metrics is None or not (reuse and metrics.is_file()):
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        print(f"running: {_shown(cmd)}", file=sys.stderr, flush=True)
        rc = subprocess.call(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
        if rc not in (0, 3):
            raise SystemExit(f"error: {_shown(cmd)} exited with {rc}")
        if hasattr(os, "getloadavg"):
            LOADS.append(os.getloadavg()[0])
    return json.loads(metrics.read_text()) if metrics is not None else {}


def _f(v: float | None, nd: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


TRAJECTORIES = ("vo", "snaps", "isam2", "batch")  # every row runs --refine both: one meaning per column


def _row(name: str, m: dict) -> str:
    traj = m["trajectories"]
    ate = " / ".join(_f(traj[k]["ate_rmse"]) if k in traj else "n/a" for k in TRAJECTORIES)
    drift = " / ".join(_f(traj[k]["end_drift_percent"], 2) if k in traj else "n/a" for k in TRAJECTORIES)
    path = traj["vo"]["path_length_m"]
    fps = m["latency_ms"].get("frames_per_s")
    return f"| {name} | {m['frames']} | {path:.0f} | {m['loops']} | {ate} | {drift} | {m['flagged_frames']} | {_f(fps, 1)} |"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--kitti06",
        type=Path,
        default=SHARED / "kitti" / "sequences" / "06",
        help="KITTI 06 sequence folder (image_0/, image_1/, calib.txt; poses in ../../poses/06.txt) "
        "(default: ../shared/data/kitti/sequences/06; the row is skipped when absent)",
    )
    ap.add_argument(
        "--revisit",
        type=Path,
        default=SHARED / "kitti00_loop",
        help="the KITTI 00 revisit folder (sequences/00/image_0, poses/00.txt) "
        "(default: ../shared/data/kitti00_loop; the row is skipped when absent)",
    )
    for nn, recipe, _ in RENDERED:
        ap.add_argument(
            f"--{recipe}",
            type=Path,
            default=ROOT / "results" / "data" / recipe,
            help=f"the street rendering of KITTI {nn} (`make data DATASETS={recipe}`; default: results/data/{recipe}; "
            "the row says how to make it when absent)",
        )
    ap.add_argument(
        "--work",
        type=Path,
        default=ROOT / "results" / "results_table",
        help="folder for the run folders (default: results/results_table; replaced per row)",
    )
    ap.add_argument(
        "--out", "-o", type=Path, default=ROOT / "docs" / "results" / "README-table.md", help="markdown file to write"
    )
    ap.add_argument("--reuse", action="store_true", help="read the run folders already in --work instead of running")
    ap.add_argument(
        "--peer-venv", type=Path, default=ROOT / "results" / "orb-venv", help="ORB-SLAM3's venv (../shared/peers/README.md)"
    )
    ap.add_argument("--vocab", type=Path, default=ROOT / "results" / "ORBvoc.txt", help="ORB vocabulary for ORB-SLAM3")
    ap.add_argument("--peer-script", type=Path, default=ROOT.parent / "shared" / "peers" / "peer_orbslam3.py")
    ap.add_argument("--peer-repeats", type=int, default=3, help="alternating runs of each system for the ORB-SLAM3 table")
    ap.add_argument(
        "--readme",
        type=Path,
        default=None,
        help=f"also replace the text between the markers {BEGIN!r} and {END!r} in this file (README.md) with the table",
    )
    args = ap.parse_args()

    args.work.mkdir(parents=True, exist_ok=True)
    rows: list[str] = []
    commands: list[str] = []

    if (args.kitti06 / "image_0").is_dir():
        run_dir = args.work / "kitti06"
        cmd = _cli("run", str(args.kitti06), "--out", str(run_dir), "--refine", "both", "--map", "--overwrite")
        if not args.reuse and run_dir.exists() and not (run_dir / "metrics.json").is_file():
            raise SystemExit(f"error: {run_dir}: exists and is not a results folder; choose another --work")
        rows.append(_row("real KITTI 06 clip (stereo)", _run(cmd, run_dir / "metrics.json", args.reuse)))
        commands.append(_shown(cmd, {str(args.kitti06): "KITTI06"}))
    else:
        rows.append("| real KITTI 06 clip (stereo) | not measured: no data at --kitti06 | | | | | | |")

    demo_dir = args.work / "demo"
    if not args.reuse and demo_dir.exists() and not (demo_dir / "run" / "metrics.json").is_file():
        raise SystemExit(f"error: {demo_dir}: exists and is not a demo folder; choose another --work")
    if not args.reuse and demo_dir.exists():
        shutil.rmtree(demo_dir)  # a demo folder this script wrote before (it holds run/metrics.json)
    cmd = _cli("demo", "--out", str(demo_dir), "--refine", "both")
    rows.append(_row("built-in synthetic loop (`demo`)", _run(cmd, demo_dir / "run" / "metrics.json", args.reuse)))
    commands.append(_shown(cmd))

    notes: list[str] = []
    seq00, gt00 = args.revisit / "sequences" / "00", args.revisit / "poses" / "00.txt"
    if (seq00 / "image_0").is_dir() and gt00.is_file():
        drifted, run_dir = args.work / "revisit_drifted.txt", args.work / "revisit"
        drift_cmd = _cli("drift", str(gt00), "--out", str(drifted), "--seed", "0", "--pct", "1", "--overwrite")
        cmd = _cli("run", str(seq00), "--odometry", str(drifted), "--out", str(run_dir), "--refine", "both", "--overwrite")
        if not args.reuse:
            _run(drift_cmd, None, False)
        rows.append(
            _row("real KITTI 00 revisit (left camera, drifted odometry)", _run(cmd, run_dir / "metrics.json", args.reuse))
        )
        names = {str(gt00): "KITTI00LOOP/poses/00.txt", str(seq00): "KITTI00LOOP/sequences/00"}
        commands += [_shown(drift_cmd, names), _shown(cmd, names)]
        notes.append(_revisit_note(run_dir, seq00))
    else:
        rows.append("| real KITTI 00 revisit (left camera, drifted odometry) | not measured: no data at --revisit | | | | | | |")

    for nn, recipe, shown in RENDERED:
        seq, name = getattr(args, recipe), f"rendered KITTI {nn} path, street (stereo)"
        if (seq / "image_0").is_dir():
            run_dir = args.work / recipe
            cmd = _cli("run", str(seq), "--out", str(run_dir), "--refine", "both", "--overwrite")
            rows.append(_row(name, _run(cmd, run_dir / "metrics.json", args.reuse)))
            commands.append(_shown(cmd, {str(seq): shown}))
        else:
            rows.append(f"| {name} | not measured: no rendering at --{recipe} (`make data DATASETS={recipe}`) | | | | | | |")

    peer = _peer_table(args)
    load = f"load average up to {max(LOADS):.1f} while measuring" if LOADS else "rows read from earlier runs (--reuse)"
    md = [
        "| input | frames | path m | loops | ATE m: VO / SNAPS / iSAM2 / batch | end drift %: VO / SNAPS / iSAM2 / batch "
        "| flagged | frames/s |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "VO = the odometry alone (the revisit's: the drifted pose file), SNAPS = the real-time heuristic, iSAM2 = the "
        "online refinement, batch = the offline one, in every row (`--refine both`; the demo prints VO, SNAPS and iSAM2 "
        "as `make demo` runs them). A run with frame gaps (the revisit) has its path length and end drift over its parts "
        '(docs/decisions.md, "Evaluation"). '
        f"{os.cpu_count()} CPU cores, {load}.",
        *(["", *notes] if notes else []),
        "",
        *peer,
        "",
        "Commands:",
        "",
        *(f"    {c}" for c in commands),
        "",
        "KITTI06 = the `--kitti06` folder: KITTI odometry sequence 06, frames 0-50, stereo, with its ground truth.",
        "KITTI00LOOP = the `--revisit` folder: KITTI 00's left images of frames 100-230 and 1540-1660, "
        "whose frames 1560-1641 drive again through the street of frames 109-210.",
        *(
            f"{shown} = `make data DATASETS={recipe}`: the street world rendered along KITTI {nn}'s ground truth."
            for nn, recipe, shown in RENDERED
        ),
        "",
        "Regenerate: `python benchmarks/results_table.py --readme README.md` (writes this table here and in docs/results/).",
    ]
    text = "\n".join(md) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    tmp.replace(args.out)
    if args.readme is not None:
        _splice(args.readme, text)
    print(text, end="")
    return 0


def _peer_table(args) -> list[str]:
    """ORB-SLAM3 beside our pipeline on the KITTI 06 clip (bench_peers.py's runs), or why not."""
    import numpy as np
    from bench_peers import accuracy, gt_of, ours_subprocess, peer_missing, peer_subprocess, read_cpu_ms

    title = "ORB-SLAM3 beside us, KITTI 06 clip (stereo)"
    args.peer_python = args.peer_venv / "bin" / "python"
    why = peer_missing(args) if (args.kitti06 / "image_1").is_dir() else f"no data at --kitti06 {args.kitti06}"
    if why:
        return [f"{title}: not measured here ({why}; the kit: ../shared/peers/README.md)."]
    if args.reuse and not (args.work / "peers" / "table.json").is_file():
        return [f"{title}: not measured (--reuse and no earlier runs in {args.work / 'peers'})."]
    work = args.work / "peers"
    if not args.reuse:
        runs: dict[str, list[dict]] = {"ours": [], "orb": []}
        for rep in range(args.peer_repeats):  # alternating, so both see the same load
            print(f"running: ours and ORB-SLAM3 on KITTI 06, round {rep + 1} of {args.peer_repeats}", file=sys.stderr, flush=True)
            runs["ours"].append(ours_subprocess(args.kitti06, work / f"ours_{rep}", None))
            runs["orb"].append(peer_subprocess(args, args.kitti06, "kitti", work / f"orb_{rep}"))
            LOADS.append(os.getloadavg()[0])
        gt = gt_of(args.kitti06)
        read_ms = read_cpu_ms(args.kitti06)
        table = {}
        for system, rs in runs.items():
            acc = [accuracy(r["poses"], gt) for r in rs]
            table[system] = {
                "ate": float(np.median([a[0] for a in acc])),
                "ate_range": [float(min(a[0] for a in acc)), float(max(a[0] for a in acc))],
                "drift": float(np.median([a[1] for a in acc])),
                "ms": float(np.median([np.median(r["wall_ms"]) for r in rs])),
                "cpu": float(np.median([r["run_cpu_ms_per_frame"] for r in rs])) - (read_ms if system == "orb" else 0.0),
                "lost": int(sum(r.get("lost", 0) for r in rs)),
            }
        (work / "table.json").write_text(json.dumps(table))
    table = json.loads((work / "table.json").read_text())
    names = {"ours": "snaps_graph: VO + SNAPS + iSAM2", "orb": "ORB-SLAM3 v1.0 stereo (final trajectory)"}
    lines = [
        f"{title}, {args.peer_repeats} alternating runs each (medians; ORB-SLAM3 is multi-threaded and varies run to run):",
        "",
        "| system | ATE m (range over runs) | end drift % | ms per frame | CPU ms per frame |",
        "|---|---|---|---|---|",
    ]
    for system, t in table.items():
        lo, hi = t["ate_range"]
        lines.append(
            f"| {names[system]} | {t['ate']:.3f} ({lo:.3f}-{hi:.3f}) | {t['drift']:.2f} | {t['ms']:.1f} | {t['cpu']:.1f} |"
        )
    lines += [
        "",
        "ms per frame: the median wall time of one frame's call (`process`, `track_stereo`); CPU ms per frame: the whole "
        "loop's process CPU over the frames, every thread (ORB-SLAM3's less its image reads). "
        "`python benchmarks/bench_peers.py --seqs kitti06` measures the same with more detail (docs/performance.md).",
    ]
    return lines


def _revisit_note(run_dir: Path, seq: Path) -> str:
    """The revisit's figures: mean deviation over bench_revisit's window, against the ground truth
    and against where the first pass's images put the second, and the loops."""
    import numpy as np
    from _revisit import WINDOW, frame_ids, window_deviation
    from revisit_reference import DATA, image_reference

    from snaps_graph.trajectory_io import read_kitti_poses

    frames, gt = frame_ids(seq), read_kitti_poses(run_dir / "poses_gt.txt")
    trajs = {t: read_kitti_poses(run_dir / f"poses_{t}.txt") for t in TRAJECTORIES}
    dev = {t: window_deviation(trajs[t], gt, frames) for t in TRAJECTORIES}
    truth, ref = read_kitti_poses(DATA / "poses" / "00.txt"), image_reference()
    rows = [i for i, f in enumerate(frames) if f in ref and WINDOW[0] <= f <= WINDOW[1]]
    seen = np.array([np.linalg.solve(truth[frames[0]], ref[frames[i]]) for i in rows])
    by_images = {t: float(np.linalg.norm(trajs[t][rows, :3, 3] - seen[:, :3, 3], axis=1).mean()) for t in TRAJECTORIES}
    # How far above the ground truth the images put the second pass (y down in the camera).
    up = [-np.linalg.solve(truth[frames[i]], ref[frames[i]])[1, 3] for i in rows]
    loops = [json.loads(line) for line in (run_dir / "loops.jsonl").read_text().splitlines() if line.strip()]
    shown = ", ".join(f"{lp['frame']} -> {lp['reference']}" for lp in loops) or "none"
    return (
        f"Revisit: mean deviation over frames {WINDOW[0]}-{WINDOW[1]}, odometry / SNAPS / iSAM2 / batch: "
        f"{' / '.join(f'{dev[t]:.2f}' for t in TRAJECTORIES)} m against KITTI's ground truth, which the images contradict "
        f"there (it puts the second pass {min(up):.2f}-{max(up):.2f} m lower on the same road: docs/odometry-input.md); "
        f"{' / '.join(f'{by_images[t]:.2f}' for t in TRAJECTORIES)} m against where the first pass's images put the "
        f"second (`benchmarks/revisit_reference.py`, the {len(rows)} frames it locates); loops (frame -> reference): {shown}."
    )


def _splice(path: Path, text: str) -> None:
    """Put ``text`` between the markers in ``path``; the file must hold both, once, in order."""
    old = path.read_text()
    a, b = old.find(BEGIN), old.find(END)
    if a < 0 or b < a or old.count(BEGIN) != 1 or old.count(END) != 1:
        raise SystemExit(f"error: {path}: needs one line {BEGIN} and one line {END} after it")
    new = old[: a + len(BEGIN)] + "\n" + text + old[b:]
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(new)
    tmp.replace(path)


if __name__ == "__main__":
    sys.exit(main())
