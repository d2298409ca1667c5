"""The README's results table: VO / SNAPS / refined accuracy, loops and speed, measured now.

Runs the command-line tool on each input it has data for and writes the table (markdown) to
``--out`` and to stdout. Every row is one ``snaps-graph`` command, printed under the table:

* ``kitti06``: the real KITTI 06 clip (frames 0-50, 59.9 m, no revisit), ``run --refine isam2 --map``;
* ``demo``: the built-in 300-frame synthetic loop, ``snaps-graph demo`` (VO + SNAPS + iSAM2 + map);
* ``revisit``: the real KITTI 00 revisit (left images of frames 100-230 and 1540-1660) with
  odometry from ``snaps-graph drift`` (the ground truth with 1 % end drift, seed 0) and
  ``run --odometry DRIFTED --refine batch``; below the table, the mean deviation over frames
  1560-1660 (the revisit, as ``benchmarks/bench_revisit.py`` measures it) and the loops.

Rows whose input is not at hand (a rendering not made yet) say so and how to make it; nothing is
estimated. ``street07`` / ``street00``: the street renderings of KITTI 07 and 00
(``make data``), ``run --refine batch``.

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


def _row(name: str, m: dict) -> str:
    traj = m["trajectories"]
    refined = next((k for k in ("isam2", "batch") if k in traj), None)
    names = ["vo", "snaps"] + ([refined] if refined else [])
    ate = " / ".join(_f(traj[k]["ate_rmse"]) for k in names)
    drift = " / ".join(_f(traj[k]["end_drift_percent"], 2) for k in names)
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
        cmd = _cli("run", str(args.kitti06), "--out", str(run_dir), "--refine", "isam2", "--map", "--overwrite")
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
    cmd = _cli("demo", "--out", str(demo_dir))
    rows.append(_row("built-in synthetic loop (`demo`)", _run(cmd, demo_dir / "run" / "metrics.json", args.reuse)))
    commands.append(_shown(cmd))

    notes: list[str] = []
    seq00, gt00 = args.revisit / "sequences" / "00", args.revisit / "poses" / "00.txt"
    if (seq00 / "image_0").is_dir() and gt00.is_file():
        drifted, run_dir = args.work / "revisit_drifted.txt", args.work / "revisit"
        drift_cmd = _cli("drift", str(gt00), "--out", str(drifted), "--seed", "0", "--pct", "1", "--overwrite")
        cmd = _cli("run", str(seq00), "--odometry", str(drifted), "--out", str(run_dir), "--refine", "batch", "--overwrite")
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
            cmd = _cli("run", str(seq), "--out", str(run_dir), "--refine", "batch", "--overwrite")
            rows.append(_row(name, _run(cmd, run_dir / "metrics.json", args.reuse)))
            commands.append(_shown(cmd, {str(seq): shown}))
        else:
            rows.append(f"| {name} | not measured: no rendering at --{recipe} (`make data DATASETS={recipe}`) | | | | | | |")

    load = f"load average up to {max(LOADS):.1f} while measuring" if LOADS else "rows read from earlier runs (--reuse)"
    md = [
        "| input | frames | path m | loops | ATE m: VO / SNAPS / refined | end drift %: VO / SNAPS / refined "
        "| flagged | frames/s |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"Refined = iSAM2 (batch for the revisit and the rendering). {os.cpu_count()} CPU cores, {load}.",
        *(["", *notes] if notes else []),
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


def _revisit_note(run_dir: Path, seq: Path) -> str:
    """The revisit's figures: mean deviation over bench_revisit's window, and the loops."""
    from _revisit import WINDOW, frame_ids, window_deviation

    from snaps_graph.trajectory_io import read_kitti_poses

    frames, gt = frame_ids(seq), read_kitti_poses(run_dir / "poses_gt.txt")
    dev = {t: window_deviation(read_kitti_poses(run_dir / f"poses_{t}.txt"), gt, frames) for t in ("vo", "snaps", "batch")}
    loops = [json.loads(line) for line in (run_dir / "loops.jsonl").read_text().splitlines() if line.strip()]
    shown = ", ".join(f"{lp['frame']} -> {lp['reference']}" for lp in loops) or "none"
    return (
        f"Revisit: mean deviation over frames {WINDOW[0]}-{WINDOW[1]}, odometry / SNAPS / batch: "
        f"{dev['vo']:.2f} / {dev['snaps']:.2f} / {dev['batch']:.2f} m; loops (frame -> reference): {shown}."
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
