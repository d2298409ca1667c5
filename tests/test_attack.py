"""What a careless or unlucky user does: writers racing for one output, a held or stale lock,
values and files that are not what they look like, signals, leftovers. Each case is one line
(``error:``, ``warning:`` or ``note:``) or a whole result, never a traceback, a silent result or
a file left behind. The races are benchmarks/bench_race.py's, run once here.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from inprocess import Ran, cli  # the command line in this process (tests/inprocess.py)

from snaps_graph.config import Config
from snaps_graph.errors import SnapsGraphError
from snaps_graph.io_utils import check_image_file, check_output_folder, check_recording_path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_race  # noqa: E402

CLI = [sys.executable, "-m", "snaps_graph.cli"]  # a process, where signals are the point
DEAD = 2**22 + 4321  # above Linux's pid_max default: no such process


def one_error(proc: Ran, *names) -> str:
    """Exit 2 and exactly one stderr line, ``error:`` naming each of ``names``."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for name in names:
        assert str(name) in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture
def seq(tiny_seq, tmp_path) -> Path:
    out = tmp_path / "seq"
    shutil.copytree(tiny_seq, out)
    return out


@pytest.fixture(scope="module")
def finished_run(tiny_seq, tmp_path_factory) -> Path:
    """A finished results folder of 5 frames, written in this process once for the module."""
    from snaps_graph.datasets.kitti import KittiSequence
    from snaps_graph.runner import run_sequence

    out = tmp_path_factory.mktemp("finished") / "done"
    run_sequence(KittiSequence(tiny_seq, frames="0:5"), out, Config(), loops="snaps", build_map=False, prefetch_frames=0)
    return out


@pytest.fixture
def done_run(finished_run, tmp_path) -> Path:
    """A private copy of the finished results folder (a test may change, lock or replace it)."""
    return Path(shutil.copytree(finished_run, tmp_path / "done"))


# ------------------------------------------------------------------ writers racing for one output
@pytest.mark.parametrize("n", [2, 8])  # few racers, and many: the benchmark adds 3
def test_concurrent_runs_into_one_folder_lose_nothing(tiny_seq, tmp_path, n):
    found, wrote = bench_race.run_race(tiny_seq, tmp_path, n)
    assert not found and wrote >= 1, found


def test_concurrent_batches_into_one_folder_lose_nothing(tiny_seq, tmp_path):
    pytest.importorskip("ray")
    found, wrote = bench_race.batch_race(tiny_seq, tmp_path, 2)
    assert not found and wrote >= 1, found


def test_concurrent_recordings_onto_one_file_lose_nothing(tiny_seq, tmp_path):
    pytest.importorskip("rerun")
    found, wrote = bench_race.rrd_race(tiny_seq, tmp_path, 3)
    assert not found and wrote >= 1, found


HOLD = "import sys, time\nfrom snaps_graph.locks import writer_lock\nwith writer_lock(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(120)\n"


def hold(target: Path) -> subprocess.Popen:
    """Another process holding ``target``'s lock, as a running writer does."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(target)], stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


@pytest.mark.parametrize("command", ["run", "synth", "convert", "batch", "rrd", "drift"])
def test_a_second_writer_is_refused_at_once_naming_the_holder(seq, done_run, tmp_path, command):
    target = {"rrd": tmp_path / "rec.rrd", "drift": tmp_path / "drifted.txt"}.get(command, done_run)
    holder = hold(target)
    before = bench_race.whole_run(done_run), sorted(p.name for p in done_run.iterdir())
    try:
        plan = tmp_path / "plan.toml"
        plan.write_text(f'sequences = ["{seq}"]\nframes = "0:4"\n')
        args = {
            "run": ["run", seq, "--out", done_run, "--overwrite"],
            "synth": ["synth", "--out", done_run, "--overwrite", "--frames", "0:2", "--width", "64", "--height", "48"],
            "convert": ["convert", seq, "--out", done_run, "--overwrite"],
            "batch": ["batch", plan, "--out", done_run],
            "rrd": ["run", seq, "--out", tmp_path / "other", "--rrd", target],
            "drift": ["drift", seq / "poses.txt", "--out", target],
        }[command]
        t0 = time.monotonic()
        line = one_error(cli(*args), target, f"another run is writing it (PID {holder.pid}, started ")
        assert time.monotonic() - t0 < 30, "refused before any frame"
        assert "wait for it to end" in line
    finally:
        holder.kill()
        holder.wait()
    assert (bench_race.whole_run(done_run), sorted(p.name for p in done_run.iterdir())) == before
    assert not (tmp_path / "other").exists() and not (tmp_path / "drifted.txt").exists()


def test_a_lock_left_by_a_killed_run_is_cleared_with_a_note(done_run, capfd):
    holder = hold(done_run)
    holder.send_signal(signal.SIGKILL)  # the lock file stays; the kernel drops the lock
    holder.wait()
    lock = done_run.parent / f".{done_run.name}.lock"
    assert json.loads(lock.read_text())["pid"] == holder.pid
    check_output_folder(done_run, overwrite=True)
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("note: ") and f"cleared the lock left by PID {holder.pid}" in err[0], err
    assert not lock.exists()


def test_a_file_named_like_a_lock_that_is_not_ours_is_left_alone(done_run):
    lock = done_run.parent / f".{done_run.name}.lock"
    lock.write_text("my notes\n")
    with pytest.raises(SnapsGraphError, match=r"not a lock file this tool wrote"):
        check_output_folder(done_run, overwrite=True)
    assert lock.read_text() == "my notes\n"


# ------------------------------------------------------------------ silent results
def test_a_set_value_is_one_toml_value():
    with pytest.raises(SnapsGraphError, match=r"one TOML value on one line"):
        Config().with_overrides(['loop.radius_m=1\n[graph]\nrefine="batch"'])
    assert Config().with_overrides(["loop.radius_m=7"]).loop.radius_m == 7


def test_compare_names_the_trajectory_and_files_that_are_gone(done_run, capsys):
    from snaps_graph.evaluation.report import compare_run

    (done_run / "poses_snaps.txt").unlink()
    (done_run / "metrics.json").unlink()
    compare_run(done_run)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "metrics.json, poses_snaps.txt missing" in err[0], err
    assert "Missing: `metrics.json`, `poses_snaps.txt`" in (done_run / "report.md").read_text()


def test_loops_and_eval_name_every_file_they_did_not_find(done_run, tmp_path):
    from snaps_graph.evaluation.loops import loops_run

    (done_run / "frames.csv").unlink()
    (done_run / "candidates.csv").unlink()
    with pytest.raises(SnapsGraphError, match=r"frames.csv, candidates.csv not found"):
        loops_run(done_run)
    one_error(cli("eval", tmp_path / "a.txt", "--gt", tmp_path / "b.txt"), "a.txt", "b.txt")


def test_a_metric_that_cannot_be_computed_is_a_note_not_a_bare_null(tmp_path):
    from snaps_graph.evaluation.metrics import evaluate

    gt = np.tile(np.eye(4), (20, 1, 1))
    gt[:, 0, 3] = np.arange(20) * 1e200
    est = np.tile(np.eye(4), (20, 1, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy overflow warning
        m = evaluate(est, gt)
    assert all(k in m["notes"] and "overflow" in m["notes"][k] for k, v in m.items() if k != "notes" and not v == v), m
    assert np.isnan(m["ate_rmse"]) and m["frames"] == 20
    short = evaluate(est, np.tile(np.eye(4), (20, 1, 1)))
    assert "shorter than KITTI's shortest segment" in short["notes"]["t_rel"]
    for path, poses in (("gt.txt", gt), ("est.txt", est)):
        (tmp_path / path).write_text("".join(" ".join(repr(float(x)) for x in p[:3].ravel()) + "\n" for p in poses))
    proc = cli("eval", tmp_path / "est.txt", "--gt", tmp_path / "gt.txt", "--json")
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr
    out = json.loads(proc.stdout)
    assert out["ate_rmse"] is None and "overflow" in out["notes"]["ate_rmse"]
    table = cli("eval", tmp_path / "est.txt", "--gt", tmp_path / "gt.txt").stdout
    assert "note: every figure n/a for est.txt: positions of up to" in table


def test_a_world_mesh_that_does_not_exist_is_refused_before_the_run(seq, tmp_path):
    out = tmp_path / "run"
    one_error(
        cli("run", seq, "--out", out, "--map", "--world-mesh", tmp_path / "nowhere.ply"), "nowhere.ply", "world mesh not found"
    )
    assert not out.exists()


# ------------------------------------------------------------------ tracebacks
def _superscript(seq: Path) -> None:
    for side in ("image_0", "image_1"):
        (seq / side / "000003.png").rename(seq / side / "00000³.png")


def test_a_superscript_digit_in_an_image_name_is_a_name(seq, tmp_path):
    from snaps_graph.batch import plan_from_dict
    from snaps_graph.datasets.kitti import KittiSequence

    _superscript(seq)
    with pytest.raises(SnapsGraphError, match=r"00000³.png: a named image among numbered ones"):
        KittiSequence(seq)
    with pytest.raises(SnapsGraphError, match=r"sequence 'seq': .*00000³.png: a named image among numbered ones"):
        plan_from_dict({"sequences": [str(seq)]})  # batch: the plan's check opens each sequence


def test_a_sequence_named_like_the_batch_summary_is_refused(seq, tmp_path):
    from snaps_graph.batch import plan_from_dict, run_batch

    plan = plan_from_dict({"sequences": [{"path": str(seq), "name": "summary.csv"}]})
    with pytest.raises(SnapsGraphError, match=r"would make the batch's summary.csv a folder"):
        run_batch(plan, tmp_path / "out", progress=False)
    (tmp_path / "out2" / "summary.md").mkdir(parents=True)  # in a batch folder
    (tmp_path / "out2" / ".snaps_graph_results").write_text('{"snaps_graph": "0", "batch": true, "files": null}\n')
    with pytest.raises(SnapsGraphError, match=r"summary.md: is a folder or a link"):
        run_batch(plan_from_dict({"sequences": [str(seq)]}), tmp_path / "out2", progress=False)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ leftovers and unclear messages
def test_stale_temporary_recordings_of_killed_runs_are_removed_with_a_note(tmp_path, capfd):
    rec = tmp_path / "rec.rrd"
    stale, live, foreign = (tmp_path / f".rec.rrd.tmp-{pid}" for pid in (DEAD, os.getpid(), DEAD + 1))
    stale.write_bytes(b"RRF2" + bytes(100))
    live.write_bytes(b"RRF2")
    foreign.write_text("not a recording\n")
    check_recording_path(rec, tmp_path / "out")
    err = capfd.readouterr().err.strip().splitlines()
    assert err == [f"note: {rec}: removed {stale.name}, the unfinished recording of a killed run"], err
    assert not stale.exists() and live.exists() and foreign.read_text() == "not a recording\n"


def _long(seq: Path, n: int = 3000) -> Path:
    for side in ("image_0", "image_1"):
        src = sorted((seq / side).glob("*.png"))
        for i in range(len(src), n):
            os.link(src[i % len(src)], seq / side / f"{i:06d}.png")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    (seq / "poses.txt").unlink()
    return seq


def test_sighup_ends_a_run_with_a_message_and_leaves_nothing(seq, tmp_path):
    _long(seq)
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        CLI + ["run", str(seq), "--out", str(out)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".run.tmp-*")) and time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(signal.SIGHUP)
    stdout, stderr = proc.communicate(timeout=60)
    lines = [line for line in (stdout + stderr).splitlines() if line.strip()]
    assert proc.returncode == 130 and lines == ["interrupted: no results written"], (proc.returncode, lines)
    assert not out.exists() and not [p.name for p in tmp_path.iterdir() if p.name.startswith(".run")]


def test_a_refused_address_creates_no_folder(seq, tmp_path):
    from snaps_graph.batch import plan_from_dict, run_batch

    pytest.importorskip("ray")
    with pytest.raises(SnapsGraphError, match=r"--address ray://127.0.0.1:1: cannot start or join"):
        run_batch(
            plan_from_dict({"sequences": [str(seq)], "frames": "0:4"}),
            tmp_path / "out",
            address="ray://127.0.0.1:1",
            progress=False,
        )
    assert not (tmp_path / "out").exists() and list(tmp_path.iterdir()) == [seq]


def test_an_immutable_empty_out_is_refused_before_the_first_frame(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    if subprocess.run(["chattr", "+i", str(out)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i needs root on a file system with inode flags")
    try:
        with pytest.raises(SnapsGraphError, match=r"immutable or append-only"):
            check_output_folder(out)
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=True)


def test_odometry_naming_a_folder_and_a_symlink_loop_say_so(seq, tmp_path):
    out = tmp_path / "run"
    one_error(cli("run", seq, "--out", out, "--odometry", seq), seq, "is a folder, where a file is wanted")
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    one_error(cli("run", tmp_path / "a", "--out", out), tmp_path / "a", "a loop of symbolic links")
    assert not out.exists()


def test_a_truncated_png_is_our_one_line_only(seq, tmp_path):
    png = seq / "image_0" / "000003.png"
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])
    with pytest.raises(SnapsGraphError, match=r"truncated PNG"):
        check_image_file(png)
    one_error(cli("run", seq, "--out", tmp_path / "run", "--no-map"), png, "truncated PNG")
