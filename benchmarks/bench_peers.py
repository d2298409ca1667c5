"""Our pipeline against ORB-SLAM3 (stereo) on the same sequences, side by side, interleaved.

Ours: VO + SNAPS + iSAM2, no map (``SlamPipeline``), every frame read into memory before the
timed loop. Per frame: the wall time of ``process(frame)`` and the process CPU time during it
(every thread of ours: the front end's second thread, the loop-feature worker, the local BA
worker). Accuracy: the iSAM2 trajectory after the last frame.

ORB-SLAM3 v1.0 stereo through ``pyorbslam3``, run by the peer script (``--peer-script``, in its own
venv, ``--peer-venv``): per frame the wall time and the process CPU time of ``track_stereo``
(images read before the call, as ours). Accuracy: its final trajectory (``poses.txt``) and what
tracking returned per frame (``poses_online.txt``). ORB-SLAM3 is GPL-3.0: this benchmark runs it
as a separate program when it is installed, and it is never a dependency of snaps_graph; without
its venv, vocabulary or script the peer columns are skipped with the reason printed.

Runs alternate (ours, theirs, ours, theirs, ...; ``--repeats`` each); the table gives, per system
and sequence, the median over runs of the per-run median per-frame time, the spread (min-max of
the per-run medians), the median CPU time per frame, the mean CPU per frame (sum / frames) and the
whole loop's CPU per frame (with the work between calls; ORB-SLAM3's less its image reads),
ATE RMSE (SE(3)-aligned) and end drift against ground truth, and our time / theirs. A raw EuRoC
sequence is rectified once into ``--work`` (``snaps-graph convert``), so both systems see the same
rectified images. Our poses' SHA-256 is printed per run: the runs must agree bit for bit.

    python benchmarks/bench_peers.py [--seqs kitti06,euroc] [--repeats 3]
        [--peer-venv results/orb-venv] [--vocab results/ORBvoc.txt]
        [--peer-script ../shared/peers/peer_orbslam3.py] [--work results/peers] [--config ours.toml]
        [--clip street=results/data/street00@0:500 ...]

``--clip`` adds any KITTI-layout folder (a frame range of it), run with the peer's KITTI feature
settings and the folder's own calibration; accuracy where it has ground truth.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.metrics import evaluate

ROOT = Path(__file__).resolve().parents[1]

# the targets this benchmark checks (bench_budget.py checks the same)
MAX_RATIO = 0.5  # our wall and CPU time against ORB-SLAM3's
MIN_FPS = 30.0  # KITTI 06, frames a second
MAX_ATE_M = 0.045  # KITTI 06
MAX_DRIFT_PERCENT = 0.85  # KITTI 06, end drift

SEQUENCES = {  # name -> (path from the project root, the peer's settings preset)
    "kitti06": ("../shared/data/kitti/sequences/06", "kitti"),
    "euroc": ("../shared/data/euroc/V1_01_easy_first95/mav0", "euroc"),
}


def kitti_folder(name: str, path: Path, work: Path) -> Path:
    """A KITTI-layout folder of ``path`` (itself, or a rectified copy written once into ``work``)."""
    if (path / "calib.txt").is_file() and (path / "image_1").is_dir():
        return path
    out = work / f"{name}_rect"
    if not (out / "calib.txt").is_file():
        from snaps_graph.datasets.convert import write_kitti_folder
        from snaps_graph.datasets.open import open_dataset

        write_kitti_folder(open_dataset(path), out, overwrite=True)
        print(f"{name}: rectified {path} into {out}")
    return out


def run_ours(seq: Path, out: Path, config: str | None = None, frames: str | None = None) -> dict:
    """One run of our pipeline in this process (called in a fresh interpreter per run);
    ``config``: a TOML file (default: the default configuration); ``frames``: a range A:B."""
    from snaps_graph._malloc import set_malloc_thresholds
    from snaps_graph.config import Config
    from snaps_graph.datasets.kitti import KittiSequence
    from snaps_graph.pipeline import SlamPipeline

    set_malloc_thresholds()  # as `snaps-graph run` has them (idempotent)
    ds = KittiSequence(seq, frames=frames)
    stereo_frames = [ds[i] for i in range(len(ds))]
    cfg = Config.load(config) if config else Config()
    pipe = SlamPipeline(ds.camera, cfg, loops="snaps", refine="isam2", build_map=False)
    wall, cpu = [], []
    c_run, t_run = time.process_time(), time.perf_counter()
    for f in stereo_frames:
        t, c = time.perf_counter(), time.process_time()
        pipe.process(f)
        wall.append((time.perf_counter() - t) * 1e3)
        cpu.append((time.process_time() - c) * 1e3)
    res = pipe.finish()
    c_run, t_run = time.process_time() - c_run, time.perf_counter() - t_run
    poses = np.ascontiguousarray(res.trajectories["isam2"], np.float64)
    np.save(out / "poses.npy", poses)
    return {
        "wall_ms": wall,
        "cpu_ms": cpu,
        "run_cpu_ms_per_frame": c_run * 1e3 / len(stereo_frames),
        "run_wall_s": t_run,
        "digest": hashlib.sha256(poses.tobytes()).hexdigest(),
        "vo_digest": hashlib.sha256(np.ascontiguousarray(res.trajectories["vo"], np.float64).tobytes()).hexdigest(),
    }


def ours_subprocess(seq: Path, out: Path, config: str | None, frames: str | None = None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    extra = (["--config", str(config)] if config else []) + (["--frames", frames] if frames else [])
    subprocess.run([sys.executable, __file__, "--ours-run", str(seq), str(out), *extra], check=True, env=env)
    d = json.loads((out / "ours.json").read_text())
    d["poses"] = np.load(out / "poses.npy")
    return d


def peer_subprocess(args, seq: Path, preset: str, out: Path, frames: str | None = None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    cmd = [str(args.peer_python), str(args.peer_script), str(seq), str(out), "--vocab", str(args.vocab), "--preset", preset]
    cmd += ["--frames", frames] if frames else []
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"peer run failed ({r.returncode}): {r.stderr.strip().splitlines()[-1:]}")
    import csv

    with open(out / "frames.csv") as fh:
        rows = list(csv.DictReader(fh))
    from snaps_graph.trajectory_io import read_kitti_poses

    return {
        "wall_ms": [float(r["track_ms"]) for r in rows],
        "cpu_ms": [float(r["track_cpu_ms"]) for r in rows],
        "lost": sum(r["state"] != "OK" for r in rows),
        # the whole tracking loop's CPU per frame (with its local mapping between calls, and the
        # peer script's image reads)
        "run_cpu_ms_per_frame": float(json.loads((out / "summary.json").read_text())["cpu_ms_per_frame"]),
        "poses": read_kitti_poses(out / "poses.txt"),
        "poses_online": read_kitti_poses(out / "poses_online.txt"),
    }


def peer_missing(args) -> str | None:
    """Why ORB-SLAM3 cannot run here, or None."""
    if not args.peer_python.is_file():
        return f"no peer venv at {args.peer_venv} (see ../shared/peers/README.md)"
    if not args.vocab.is_file():
        return f"no ORB vocabulary at {args.vocab}"
    if not args.peer_script.is_file():
        return f"no peer script at {args.peer_script}"
    r = subprocess.run([str(args.peer_python), "-c", "import pyorbslam3"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"{args.peer_python}: cannot import pyorbslam3"
    return None


def read_cpu_ms(seq: Path, frames: str | None = None) -> float:
    """CPU ms per frame of reading a pair as the peer script does (two grey imreads): taken off
    ORB-SLAM3's whole-loop CPU, whose loop reads the images and ours does not (at most 100
    pairs of ``frames`` are timed)."""
    import cv2

    from snaps_graph.datasets.kitti import KittiSequence

    ds = KittiSequence(seq, frames=frames)
    lefts = sorted((seq / "image_0").glob("*.png"))[ds.start : ds.stop][:100]
    c = time.process_time()
    for a in lefts:
        cv2.imread(str(a), cv2.IMREAD_GRAYSCALE)
        cv2.imread(str(seq / "image_1" / a.name), cv2.IMREAD_GRAYSCALE)
    return (time.process_time() - c) * 1e3 / max(len(lefts), 1)


def gt_of(seq: Path, frames: str | None = None) -> np.ndarray | None:
    """Ground truth of the selected frames, or None."""
    from snaps_graph.datasets.kitti import KittiSequence

    gt = KittiSequence(seq, frames=frames).gt_poses
    return None if gt is None else np.asarray(gt)


def accuracy(poses: np.ndarray, gt: np.ndarray | None) -> tuple[float, float]:
    if gt is None:
        return float("nan"), float("nan")
    m = evaluate(np.asarray(poses), gt)
    return m["ate_rmse"], m["end_drift_percent"]


def fmt(x: float, spec: str = ".1f") -> str:
    return "n/a" if not np.isfinite(x) else format(x, spec)


def print_targets(rows: list[dict]) -> None:
    """Each target with what this run measured."""
    print("targets:")
    for r in rows:
        if not r["system"].startswith("ours"):
            continue
        checks = []
        if "ratio_wall" in r:
            checks += [
                (f"wall <= {MAX_RATIO}x ORB-SLAM3's: {r['ratio_wall']:.2f}x", r["ratio_wall"] <= MAX_RATIO),
                (
                    f"CPU <= {MAX_RATIO}x ORB-SLAM3's: {r['ratio_cpu']:.2f}x (median), {r['ratio_cpu_run']:.2f}x (whole loop)",
                    r["ratio_cpu"] <= MAX_RATIO,
                ),
            ]
        if r["seq"] == "kitti06":
            fps = 1000.0 / r["wall"]
            checks += [
                (f">= {MIN_FPS:.0f} frames/s: {fps:.1f}", fps >= MIN_FPS),
                (f"ATE <= {MAX_ATE_M} m: {fmt(r['ate'], '.3f')}", r["ate"] <= MAX_ATE_M),
                (f"end drift <= {MAX_DRIFT_PERCENT} %: {fmt(r['drift'], '.2f')}", r["drift"] <= MAX_DRIFT_PERCENT),
            ]
        if len(r["digests"]) > 1:
            checks.append((f"poses bit-identical between {len(r['digests'])} runs", r["identical"]))
        else:
            print(f"  {r['seq']:9} (bit-identical poses: needs --repeats 2 or more)")
        for text, ok in checks:
            print(f"  {r['seq']:9} {'met    ' if ok else 'NOT met'}  {text}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seqs", default="kitti06,euroc", help=f"comma-separated, of {', '.join(SEQUENCES)}")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--peer-venv", type=Path, default=ROOT / "results" / "orb-venv")
    ap.add_argument("--vocab", type=Path, default=ROOT / "results" / "ORBvoc.txt")
    ap.add_argument("--peer-script", type=Path, default=ROOT.parent / "shared" / "peers" / "peer_orbslam3.py")
    ap.add_argument("--work", type=Path, default=ROOT / "results" / "peers")
    ap.add_argument("--config", default=None, help="TOML config for our runs (default: the defaults)")
    ap.add_argument(
        "--clip",
        action="append",
        default=[],
        metavar="NAME=PATH[@A:B]",
        help="also a KITTI-layout folder (frames A:B of it), run with the peer's KITTI settings; repeatable",
    )
    ap.add_argument("--frames", default=None, help=argparse.SUPPRESS)  # a clip's range, for --ours-run
    ap.add_argument("--ours-run", nargs=2, metavar=("SEQ", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.ours_run:
        seq, out = Path(args.ours_run[0]), Path(args.ours_run[1])
        try:
            (out / "ours.json").write_text(json.dumps(run_ours(seq, out, args.config, args.frames)))
        except SnapsGraphError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return 0
    clips: dict[str, tuple[Path, str | None]] = {}
    for item in args.clip:
        name, sep, rest = item.partition("=")
        path, _, frames = rest.partition("@")
        if not sep or not name or not path or name in SEQUENCES or name in clips:
            print(f"error: --clip {item}: expected NAME=PATH[@A:B] with a new name")
            return 2
        clips[name] = (Path(path).resolve(), frames or None)
    args.peer_python = args.peer_venv / "bin" / "python"
    why = peer_missing(args)
    if why:
        print(f"ORB-SLAM3 skipped: {why}")
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")

    rows = []
    names = [n for n in args.seqs.split(",") if n] + list(clips)
    for name in names:
        frames = None
        if name in clips:
            src, frames = clips[name]
            preset = "kitti"
        elif name in SEQUENCES:
            rel, preset = SEQUENCES[name]
            src = (ROOT / rel).resolve()
        else:
            print(f"error: unknown sequence '{name}' (known: {', '.join(SEQUENCES)}; others through --clip)")
            return 2
        if not src.exists():
            print(f"{name}: skipped, {src} not found")
            continue
        try:
            seq = src if name in clips else kitti_folder(name, src, args.work)
            gt = gt_of(seq, frames)
            if not (seq / "image_1").is_dir():
                raise SnapsGraphError(f"{seq}: no right images (image_1/); both systems run stereo")
        except SnapsGraphError as exc:
            print(f"error: {name}: {exc}")
            return 2
        runs: dict[str, list[dict]] = {"ours": [], "orb": []}
        for rep in range(args.repeats):
            try:
                runs["ours"].append(ours_subprocess(seq, args.work / name / f"ours_{rep}", args.config, frames))
            except subprocess.CalledProcessError as exc:
                print(f"error: {name}: our run failed (exit status {exc.returncode}; its message above)")
                return 2
            if not why:
                try:
                    runs["orb"].append(peer_subprocess(args, seq, preset, args.work / name / f"orb_{rep}", frames))
                except (RuntimeError, OSError, ValueError, KeyError) as exc:  # its output unreadable too
                    why = str(exc)
                    print(f"ORB-SLAM3 skipped from here on: {why}")
                    runs["orb"] = []
            print(
                f"{name} run {rep}: ours median {np.median(runs['ours'][-1]['wall_ms']):.1f} ms"
                + (f", ORB-SLAM3 {np.median(runs['orb'][-1]['wall_ms']):.1f} ms" if runs["orb"] else "")
                + f"; our poses sha256 {runs['ours'][-1]['digest'][:16]}",
                flush=True,
            )
        n = len(runs["ours"][0]["wall_ms"])
        read_ms = read_cpu_ms(seq, frames)
        print(f"{name}: reading a pair (two grey imreads) takes {read_ms:.1f} ms CPU", flush=True)
        gt = None if gt is None else gt[:n]
        for system, rs in runs.items():
            if not rs:
                continue
            med = np.array([np.median(x["wall_ms"]) for x in rs])
            cmed = np.array([np.median(x["cpu_ms"]) for x in rs])
            cmean = np.array([np.mean(x["cpu_ms"]) for x in rs])
            crun = np.array([x["run_cpu_ms_per_frame"] for x in rs]) - (read_ms if system == "orb" else 0.0)
            acc = [accuracy(x["poses"], gt) for x in rs]
            row = dict(
                seq=name,
                system="ours (VO+SNAPS+iSAM2)" if system == "ours" else "ORB-SLAM3 final",
                frames=n,
                wall=float(np.median(med)),
                wall_lo=float(med.min()),
                wall_hi=float(med.max()),
                cpu=float(np.median(cmed)),
                cpu_mean=float(np.median(cmean)),
                cpu_run=float(np.median(crun)),
                ate=float(np.median([a[0] for a in acc])),
                ate_lo=float(min(a[0] for a in acc)),
                ate_hi=float(max(a[0] for a in acc)),
                drift=float(np.median([a[1] for a in acc])),
            )
            if system == "ours":
                digests = {x["digest"] for x in rs}
                row["identical"] = len(digests) == 1
                row["digests"] = [x["digest"] for x in rs]
            else:
                online = [accuracy(x["poses_online"], gt) for x in rs]
                row["ate_online"] = float(np.median([a[0] for a in online]))
                row["lost"] = int(sum(x["lost"] for x in rs))
            rows.append(row)
        if runs["orb"]:
            o, t = rows[-2], rows[-1]
            o["ratio_wall"], o["ratio_cpu"] = o["wall"] / t["wall"], o["cpu"] / t["cpu"]
            o["ratio_cpu_mean"] = o["cpu_mean"] / t["cpu_mean"]
            o["ratio_cpu_run"] = o["cpu_run"] / t["cpu_run"]

    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print()
    head = (
        f"{'sequence':9} {'system':22} {'frames':>6} {'ms/frame':>9} {'spread':>13} {'CPU ms':>7} {'CPU mean':>8} {'CPU run':>7} "
        f"{'ATE m':>7} {'ATE spread':>13} {'drift %':>7} {'ours/theirs: wall, CPU, mean, run':>36}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        ratio = ""
        if "ratio_wall" in r:
            ratio = f"{r['ratio_wall']:.2f}x, {r['ratio_cpu']:.2f}x, {r['ratio_cpu_mean']:.2f}x, {r['ratio_cpu_run']:.2f}x"
        print(
            f"{r['seq']:9} {r['system']:22} {r['frames']:6d} {r['wall']:9.1f} {r['wall_lo']:6.1f}-{r['wall_hi']:<6.1f} "
            f"{r['cpu']:7.1f} {r['cpu_mean']:8.1f} {r['cpu_run']:7.1f} {fmt(r['ate'], '.3f'):>7} "
            f"{fmt(r['ate_lo'], '.3f') + '-' + fmt(r['ate_hi'], '.3f'):>13} {fmt(r['drift'], '.2f'):>7} {ratio:>36}"
        )
    for r in rows:
        if "identical" in r:
            shown = " ".join(d[:16] for d in r["digests"])
            print(
                f"{r['seq']}: our poses bit-identical across {args.repeats} runs: {'yes' if r['identical'] else 'NO'} ({shown})"
            )
        if "ate_online" in r:
            print(f"{r['seq']}: ORB-SLAM3 online (tracking) ATE {fmt(r['ate_online'], '.3f')} m; frames lost {r['lost']}")
    print_targets(rows)
    print(
        f"{os.cpu_count()} cores; ms/frame and CPU ms: medians over frames (median over runs); CPU mean: per-frame "
        "CPU summed / frames; CPU run: the whole loop's process CPU / frames (ORB-SLAM3's with its mapping "
        "threads between calls, less the image reads measured above; ours reads before the loop)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
