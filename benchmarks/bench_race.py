"""Writers racing for one output: N concurrent commands into the same place, repeated.

Three races, each for N = 2, 3 and 8 at once, ``--reps`` times (default 20):

- ``run``: N ``snaps-graph run SEQ --out OUT --overwrite`` into one existing results folder;
- ``batch``: N ``snaps-graph batch PLAN --out OUT`` into one batch folder;
- ``rrd``: N ``snaps-graph run SEQ --out OUT_i --rrd REC.rrd`` onto one recording (needs rerun-sdk).

Each race passes when every command either exits 0 or is refused with one ``error:`` line naming
the holder, the commands that wrote did so one after the other (their temporary folders or files,
watched as they appear and vanish, never overlap), the output holds exactly one whole result of a
command that succeeded (the last one to write), and nothing else is left beside it. Prints per race
and N: repetitions, races passed, and the commands that wrote and were refused in total.

    python benchmarks/bench_race.py [--reps 20] [--races run,batch,rrd] [--n 2,3,8]

The test suite runs the same races once, ``run`` for N = 2 and 8 (tests/test_attack.py).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path

from snaps_graph.io_utils import ADDED_LATER, MARKER

ROOT = Path(__file__).resolve().parents[1]
REFUSED = "another run is writing it (PID "


@dataclass
class Race:
    """What N concurrent commands did: exit status and stderr per command, and when each
    command's temporary output (``.NAME.tmp-PID``) was first and last seen."""

    codes: list[int] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    pids: list[int] = field(default_factory=list)
    seen: dict[int, list[float]] = field(default_factory=dict)


def cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "snaps_graph.cli", *map(str, args)]


def race(cmds: list[list[str]], watch: Path, prefix: str | None, timeout: float = 600) -> Race:
    """Start ``cmds`` at once; watch ``watch`` for entries ``PREFIX<pid>`` (None: no watching)
    until all have ended."""
    env = dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for c in cmds]
    r = Race(pids=[p.pid for p in procs])
    deadline = time.monotonic() + timeout
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        now = time.monotonic()
        try:
            names = os.listdir(watch)
        except FileNotFoundError:
            names = []
        for name in names if prefix else []:
            if name.startswith(prefix) and name[len(prefix) :].isdigit():
                r.seen.setdefault(int(name[len(prefix) :]), [now, now])[1] = now
        time.sleep(0.002)
    for p in procs:
        try:
            _, err = p.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
        r.codes.append(p.returncode)
        r.errors.append(err)
    return r


def problems_of_commands(r: Race) -> list[str]:
    """Every command wrote (0) or was refused in one line naming the holder (2); the writers wrote
    one after another."""
    out = []
    for pid, code, err in zip(r.pids, r.codes, r.errors):
        lines = [line for line in err.splitlines() if line.strip() and not line.startswith(("note:", "slam", "cells"))]
        if code == 2:
            if len(lines) != 1 or not lines[0].startswith("error:") or REFUSED not in lines[0]:
                out.append(f"PID {pid}: refused, but not in one line naming the holder: {lines[-3:]}")
        elif code != 0:
            out.append(f"PID {pid}: exit status {code}: {lines[-3:]}")
        elif "Traceback" in err or any(line.startswith("error:") for line in lines):
            out.append(f"PID {pid}: exit 0 with an error: {lines[-3:]}")
    spans = sorted(r.seen[pid] for pid, code in zip(r.pids, r.codes) if code == 0 and pid in r.seen)
    for a, b in zip(spans, spans[1:]):
        if b[0] <= a[1]:
            out.append(f"two writers at once: {a} and {b}")
    return out


def last_writer(r: Race) -> int | None:
    """The PID whose temporary output vanished last (renamed into place last)."""
    done = [(r.seen[pid][1], pid) for pid, code in zip(r.pids, r.codes) if code == 0 and pid in r.seen]
    return max(done)[1] if done else None


def whole_run(out: Path) -> list[str]:
    """A results folder holds exactly the files its marker lists (a whole run), and what later
    commands add (a batch's batch.json)."""
    try:
        listed = json.loads((out / MARKER).read_text())["files"]
    except (OSError, ValueError, KeyError):
        return [f"{out}: no readable marker"]
    have = sorted(p.name for p in out.iterdir() if p.name != MARKER and not any(fnmatch(p.name, pat) for pat in ADDED_LATER))
    return [] if listed and have == sorted(listed) and "metrics.json" in have else [f"{out}: holds {have}, lists {listed}"]


def leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


# ---------------------------------------------------------------- the three races
def make_sequence(root: Path, frames: int = 8) -> Path:
    from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder

    seq = root / "seq"
    poses, times = load_trajectory("loop", f"0:{frames}")
    render_to_folder(SyntheticSequence(poses, width=320, height=96, seed=0, times=times), seq)
    return seq


def run_race(seq: Path, root: Path, n: int) -> tuple[list[str], int]:
    """N ``run --overwrite`` into one existing results folder; each run tagged by a config value
    it does not use (map.max_range_m without --map), read back from OUT/config.toml."""
    from snaps_graph.config import Config
    from snaps_graph.datasets.kitti import KittiSequence
    from snaps_graph.runner import run_sequence

    out = root / "out"
    # The folder the racers replace: written in this process, as a finished run leaves it.
    run_sequence(KittiSequence(seq), out, Config(), build_map=False, prefetch_frames=0)
    cmds = [cli("run", seq, "--out", out, "--overwrite", "--no-map", "--set", f"map.max_range_m={11 + i}") for i in range(n)]
    r = race(cmds, root, f".{out.name}.tmp-")
    found = problems_of_commands(r) + whole_run(out) + [f"left beside OUT: {x}" for x in leftovers(out)]
    tag = _tag(out)
    last = last_writer(r)
    if last is not None and tag != 11 + r.pids.index(last):
        found.append(f"OUT holds the run tagged {tag}, but the last to write was tagged {11 + r.pids.index(last)}")
    if last is None and tag is not None:
        found.append(f"no run wrote, but OUT holds a new run tagged {tag}")
    return found, sum(c == 0 for c in r.codes)


def _tag(out: Path) -> float | None:
    import tomllib

    try:
        return tomllib.loads((out / "config.toml").read_text())["map"]["max_range_m"]
    except (OSError, ValueError, KeyError):
        return None


def batch_race(seq: Path, root: Path, n: int) -> tuple[list[str], int]:
    """N ``batch`` into one batch folder: the folder ends with every cell whole, ok or skipped."""
    out = root / "out"
    plan = root / "plan.toml"
    plan.write_text(
        f'sequences = ["{seq}"]\nframes = "0:6"\ncpus_per_task = 1\n[variants.a]\n[variants.b]\nloop = {{ radius_m = 6.0 }}\n'
    )
    # The cells' temporary folders are the Ray workers' (other PIDs): not watched; the summary and
    # the cells' folders say what the batches left.
    r = race([cli("batch", plan, "--out", out, "--max-parallel", "1") for _ in range(n)], root, None)
    found = problems_of_commands(r)
    try:
        statuses = [line.split(",")[2] for line in (out / "summary.csv").read_text().splitlines()[1:]]
    except OSError:
        statuses = []
    if sorted(statuses) != ["ok", "ok"] and sorted(statuses) != ["skipped", "skipped"]:
        found.append(f"summary.csv statuses {statuses}")
    for cell in ("a", "b"):
        folder = out / seq.name / cell
        found += whole_run(folder) if folder.is_dir() else [f"{folder}: missing"]
        found += [f"left beside a cell: {x}" for x in leftovers(folder)]
    found += [f"left beside OUT: {x}" for x in leftovers(out)]
    return found, sum(c == 0 for c in r.codes)


def rrd_race(seq: Path, root: Path, n: int) -> tuple[list[str], int]:
    """N runs (each its own OUT) recording onto one ``.rrd``: one recording, whole."""
    rec = root / "rec.rrd"
    cmds = [cli("run", seq, "--out", root / f"out{i}", "--no-map", "--rrd", rec) for i in range(n)]
    r = race(cmds, root, f".{rec.name}.tmp-")
    found = problems_of_commands(r)
    if not rec.is_file() or rec.read_bytes()[:4] != b"RRF2":
        found.append(f"{rec}: not a whole recording")
    for i, code in enumerate(r.codes):
        if (root / f"out{i}").exists() != (code == 0):
            found.append(f"out{i}: {'present' if code else 'absent'} after exit status {code}")
    found += [f"left beside the recording: {x}" for x in leftovers(rec)]
    return found, sum(c == 0 for c in r.codes)


RACES = {"run": run_race, "batch": batch_race, "rrd": rrd_race}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--races", default="run,batch,rrd")
    ap.add_argument("--n", default="2,3,8")
    a = ap.parse_args()
    names = a.races.split(",")
    if "rrd" in names:
        try:
            import rerun  # noqa: F401
        except ImportError:
            print("rrd: skipped (rerun-sdk not installed)")
            names.remove("rrd")
    with tempfile.TemporaryDirectory() as tmp:
        seq = make_sequence(Path(tmp))
        print(f"{'race':<6}{'N':>3}{'reps':>6}{'passed':>8}{'wrote':>7}{'refused':>9}")
        for name in names:
            for n in map(int, a.n.split(",")):
                passed = wrote = 0
                for rep in range(a.reps):
                    root = Path(tmp) / f"{name}-{n}-{rep}"
                    root.mkdir()
                    found, ok = RACES[name](seq, root, n)
                    passed += not found
                    wrote += ok
                    for line in found:
                        print(f"  {name} N={n} rep {rep}: {line}", flush=True)
                print(f"{name:<6}{n:>3}{a.reps:>6}{passed:>8}{wrote:>7}{a.reps * n - wrote:>9}", flush=True)


if __name__ == "__main__":
    main()
