"""The run contract: every bad input is one line ``error: <file>: ...`` with exit 2 (or
a documented fallback), a results folder is whole or absent, the streaming pipeline survives a
rejected frame, frame numbers are the files' numbers, a mostly flagged run says so (exit 3).

Everything runs on a tiny sequence rendered by the package itself (no ../shared needed).
"""

from __future__ import annotations

import copy
import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from inprocess import Ran, cli  # the command line in this process (tests/inprocess.py)

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import write_results
from snaps_graph.synth import SyntheticSequence, load_trajectory
from snaps_graph.types import StereoFrame

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "snaps_graph.cli"]  # a process, where the process is the point (signals, stdout, imports)
N_FRAMES = 8  # frames of the tiny_seq fixture (conftest.py)
BINARY = bytes(range(256)) * 4  # not UTF-8, has NUL bytes


def assert_user_error(proc: Ran | subprocess.CompletedProcess, *names: str | Path) -> str:
    """Exit 2, exactly one line of output, ``error: `` naming every one of ``names``, no traceback."""
    text = proc.stdout + proc.stderr
    assert "Traceback" not in text, text
    assert proc.returncode == 2, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert lines[0].startswith("error: "), text
    for name in names:
        assert str(name) in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture
def seq(tiny_seq, tmp_path) -> Path:
    """A private, modifiable copy of the tiny sequence."""
    dst = tmp_path / "seq"
    shutil.copytree(tiny_seq, dst)
    return dst


def write_config(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ------------------------------------------------------------------ results folder
def test_out_naming_a_file_is_refused_before_the_first_frame(seq, tmp_path):
    target = tmp_path / "results.txt"
    target.write_text("not a folder\n")
    (seq / "image_0" / "000003.png").write_bytes(b"corrupt")  # reached only if frames were read
    proc = cli("run", seq, "--out", target)
    assert_user_error(proc, target, "not a folder")
    assert target.read_text() == "not a folder\n"


def test_out_under_a_file_is_refused(seq, tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    proc = cli("run", seq, "--out", blocker / "sub" / "run")
    assert_user_error(proc, blocker, "is a file")


def test_non_empty_out_is_refused_without_overwrite_and_replaced_whole_with_it(seq, tmp_path):
    out = tmp_path / "run"
    first = cli("run", seq, "--out", out, "--refine", "batch")
    assert first.returncode == 0, first.stderr
    assert (out / "poses_batch.txt").is_file()
    again = cli("run", seq, "--out", out, "--frames", "0:5")
    assert_user_error(again, out, "--overwrite")
    assert len((out / "poses_vo.txt").read_text().splitlines()) == N_FRAMES  # untouched
    replaced = cli("run", seq, "--out", out, "--frames", "0:5", "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert not (out / "poses_batch.txt").exists()  # nothing of the old run is left beside the new
    assert len((out / "poses_vo.txt").read_text().splitlines()) == 5
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run.")]  # no temp or old folder


def test_empty_existing_out_folder_is_used(seq, tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    proc = cli("run", seq, "--out", out, "--frames", "0:4")
    assert proc.returncode == 0, proc.stderr
    assert (out / "metrics.json").is_file()


def _long_sequence(seq: Path, n: int) -> Path:
    """The tiny sequence's 8 pairs repeated (hard links) to n frames: a run that lasts seconds."""
    for side in ("image_0", "image_1"):
        src = sorted((seq / side).glob("*.png"))
        for i in range(len(src), n):
            os.link(src[i % len(src)], seq / side / f"{i:06d}.png")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    (seq / "poses.txt").unlink()
    return seq


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "kill"])
def test_ctrl_c_prints_one_line_exits_130_and_leaves_no_folder(seq, tmp_path, sig):
    """Ctrl-C and a plain `kill` (a scheduler's stop) alike: one line, status 130, nothing left."""
    _long_sequence(seq, 3000)
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    proc = subprocess.Popen(
        CLI + ["run", str(seq), "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".run.tmp-*")) and time.monotonic() < deadline:  # frames being processed
        assert proc.poll() is None, "the run ended before it could be interrupted"
        time.sleep(0.05)
    time.sleep(0.5)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    lines = [line for line in (stdout + stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted"), lines
    assert "Traceback" not in stderr
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run")]  # no temp folder either


def test_synth_out_contract(tmp_path):
    target = tmp_path / "file"
    target.write_text("x")
    assert_user_error(cli("synth", "--out", target, "--frames", "0:3", "--width", "64", "--height", "48"), target)
    out = tmp_path / "seq"
    ok = cli("synth", "--out", out, "--frames", "0:3", "--width", "64", "--height", "48")
    assert ok.returncode == 0, ok.stderr
    assert_user_error(cli("synth", "--out", out, "--frames", "0:2", "--width", "64", "--height", "48"), out, "--overwrite")
    (out / "mine.txt").write_text("a file the user put there")
    refused = cli("synth", "--out", out, "--frames", "0:2", "--width", "64", "--height", "48", "--overwrite")
    assert "mine.txt" in assert_user_error(refused, out) and (out / "mine.txt").read_text() == "a file the user put there"
    (out / "mine.txt").unlink()
    again = cli("synth", "--out", out, "--frames", "0:2", "--width", "64", "--height", "48", "--overwrite")
    assert again.returncode == 0, again.stderr
    assert len(list((out / "image_0").glob("*.png"))) == 2 and len((out / "poses.txt").read_text().splitlines()) == 2


# ------------------------------------------------------------------ binary / non-text files
def test_eval_binary_estimate(tmp_path, tiny_seq):
    est = tmp_path / "est.txt"
    est.write_bytes(BINARY)
    assert_user_error(cli("eval", est, "--gt", tiny_seq / "poses.txt"), est)


def test_eval_binary_ground_truth(tmp_path, tiny_seq):
    gt = tmp_path / "gt.tum"
    gt.write_bytes(BINARY)
    assert_user_error(cli("eval", tiny_seq / "poses.txt", "--gt", gt), gt)


def test_run_binary_gt(seq, tmp_path):
    gt = tmp_path / "gt.txt"
    gt.write_bytes(BINARY)
    assert_user_error(cli("run", seq, "--out", tmp_path / "run", "--gt", gt), gt)
    assert not (tmp_path / "run").exists()


def test_eval_folder_instead_of_a_file(tmp_path, tiny_seq):
    assert_user_error(cli("eval", tmp_path, "--gt", tiny_seq / "poses.txt"), tmp_path, "is a folder")


@pytest.mark.parametrize("name", ["frames.csv", "loops.jsonl", "config.toml", "metrics.json", "poses_snaps.txt"])
def test_compare_binary_run_files(tiny_seq, tmp_path, name):
    run = tmp_path / "run"
    assert cli("run", tiny_seq, "--out", run, "--frames", "0:4").returncode == 0
    (run / name).write_bytes(BINARY)
    assert_user_error(cli("compare", run), run / name)


def test_out_equal_to_the_input_sequence_is_refused(seq):
    before = sorted(p.name for p in seq.iterdir())
    assert_user_error(cli("run", seq, "--out", seq, "--overwrite"), "would replace the input")
    assert sorted(p.name for p in seq.iterdir()) == before


def test_synth_binary_trajectory(tmp_path):
    traj = tmp_path / "traj.txt"
    traj.write_bytes(BINARY)
    assert_user_error(cli("synth", "--out", tmp_path / "s", "--trajectory", traj), traj)


def test_synth_binary_times(tmp_path, tiny_seq):
    times = tmp_path / "times.txt"
    times.write_bytes("\u00e9".encode("latin-1") * 10)
    assert_user_error(cli("synth", "--out", tmp_path / "s", "--trajectory", tiny_seq / "poses.txt", "--times", times), times)


def test_binary_config(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(BINARY)
    assert_user_error(cli("config", cfg), cfg)


def test_binary_times_txt(seq, tmp_path):
    (seq / "times.txt").write_bytes(BINARY)
    assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "times.txt")


# ------------------------------------------------------------------ times.txt
@pytest.mark.parametrize("bad,line", [("nan", 3), ("inf", 3), ("-inf", 3), ("0.1", 3)])
def test_times_nan_inf_or_not_increasing(seq, tmp_path, bad, line):
    """Line 3 holds nan/inf or repeats line 2's 0.1 (not increasing)."""
    times = [f"{0.1 * i:.6e}" for i in range(N_FRAMES)]
    times[line - 1] = bad
    (seq / "times.txt").write_text("\n".join(times) + "\n")
    msg = assert_user_error(cli("run", seq, "--out", tmp_path / "run"), f"{seq / 'times.txt'}:{line}")
    assert "finite" in msg or "increase" in msg


# ------------------------------------------------------------------ calibration
def _calib(seq: Path, p0: list[float], p1: list[float]) -> None:
    (seq / "calib.txt").write_text("P0: " + " ".join(map(str, p0)) + "\nP1: " + " ".join(map(str, p1)) + "\n")


def _p(f: float, cx: float, cy: float, tx: float = 0.0, fy: float | None = None) -> list[float]:
    return [f, 0, cx, tx, 0, f if fy is None else fy, cy, 0, 0, 0, 1, 0]


@pytest.mark.parametrize(
    "p0,p1,expect",
    [
        (_p(180, 160, 48), _p(360, 160, 48, -97.2), "P1's fx"),  # P1's focal doubled
        (_p(180, 160, 48), _p(180, 150, 48, -97.2), "P1's cx"),  # principal points differ
        (_p(0, 160, 48), _p(0, 160, 48, -97.2), "focal length"),
        (_p(-180, 160, 48), _p(-180, 160, 48, 97.2), "focal length"),
        (_p(1e7, 160, 48), _p(1e7, 160, 48, -5.4e6), "focal length"),
        (_p(180, 160, 48), _p(180, 160, 48, 97.2), "baseline"),  # negative baseline
        (_p(180, 160, 48), _p(180, 160, 48, 0.0), "baseline"),  # zero baseline
        (_p(180, 160, 48), _p(180, 160, 48, -1e5), "baseline"),  # 555 m
        (_p(180, 5000, 48), _p(180, 5000, 48, -97.2), "principal point"),  # outside the image
    ],
)
def test_bad_calibration(seq, tmp_path, p0, p1, expect):
    _calib(seq, p0, p1)
    msg = assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "calib.txt")
    assert expect in msg


def test_calibration_with_p0_offset_gives_the_true_baseline():
    from snaps_graph.camera import StereoCamera

    cam = StereoCamera.from_projections(
        np.array(_p(700, 600, 180, 70.0)).reshape(3, 4), np.array(_p(700, 600, 180, -308.0)).reshape(3, 4)
    )
    assert cam.baseline_m == pytest.approx(0.54)


# ------------------------------------------------------------------ configuration
BAD_CONFIGS = [
    ("[frontend]\nmax_depth_m = -1.0\n", "frontend.max_depth_m must be in (0, 10000], got -1"),
    ("[graph]\nodom_sigma_trans_m = -1\n", "graph.odom_sigma_trans_m must be in (0, 10000], got -1"),
    ("[graph]\nodom_sigma_rot_rad = 0.0\n", "graph.odom_sigma_rot_rad must be in (0, 3.14159]"),
    ("[graph]\nloop_sigma_trans_m = -0.1\n", "graph.loop_sigma_trans_m must be in (0, 10000]"),
    ('[frontend]\nmode = "fast"\n', "frontend.mode must be one of 'sift', 'orb', 'klt', got 'fast'"),
    ('[graph]\nrefine = "turbo"\n', "graph.refine must be one of"),
    ('[graph]\nrobust_kernel = "tukey"\n', "graph.robust_kernel must be one of"),
    ('loops = "maybe"\n', "loops must be one of 'snaps', 'none'"),
    ("[frontend]\nmin_depth_m = 90.0\n", "frontend.min_depth_m must be < frontend.max_depth_m"),
    ("[loop]\nmin_similarity = 1.5\n", "loop.min_similarity must be in (0, 1]"),
    ("[frontend]\nnum_disparities = 100\n", "frontend.num_disparities must be a multiple of 16"),
    ('[map]\nenabled = true\ntrajectory = "batch"\n', "map.trajectory = 'batch' needs graph.refine"),
    ("[frontend]\nthreads = 0\n", "frontend.threads must be in [1, 256]"),
    ("[nonsense]\nx = 1\n", "unknown key 'nonsense'"),
]


@pytest.mark.parametrize("text,expect", BAD_CONFIGS)
def test_config_command_checks_what_run_checks(tmp_path, tiny_seq, text, expect):
    """`snaps-graph config FILE` and `run --config FILE` fail alike, naming the file and the key;
    run fails before the first frame (the sequence path does not even exist)."""
    cfg = write_config(tmp_path / "my.toml", text)
    msg = assert_user_error(cli("config", cfg), cfg)
    assert expect in msg, msg
    run = cli("run", tmp_path / "no-such-seq", "--out", tmp_path / "run", "--config", cfg)
    assert assert_user_error(run, cfg) == msg


def test_map_trajectory_batch_without_refinement_fails_before_the_first_frame(seq, tmp_path):
    cfg = write_config(tmp_path / "m.toml", '[map]\ntrajectory = "batch"\n')
    assert cli("config", cfg).returncode == 0  # no map, nothing to check
    (seq / "image_0" / "000000.png").write_bytes(b"corrupt")  # reading any frame would fail differently
    msg = assert_user_error(cli("run", seq, "--out", tmp_path / "run", "--config", cfg, "--map"), cfg, "map.trajectory")
    assert "needs graph.refine" in msg
    assert cli("run", seq, "--out", tmp_path / "r2", "--config", cfg, "--map", "--refine", "both").returncode == 2  # the image


@pytest.mark.parametrize("opt,value", [("--refine", "fast"), ("--loops", "maybe"), ("--mode", "surf")])
def test_cli_mode_options(seq, tmp_path, opt, value):
    assert_user_error(cli("run", seq, "--out", tmp_path / "run", opt, value), opt, value)


def test_config_validated_at_construction_and_never_mutated():
    from snaps_graph.config import GraphConfig

    with pytest.raises(SnapsGraphError, match=r"^config: graph.odom_sigma_trans_m must be in \(0, 10000\], got -1$"):
        GraphConfig(odom_sigma_trans_m=-1.0)
    cfg = Config()
    before = copy.deepcopy(cfg)
    poses, times = load_trajectory("loop", "0:3")
    syn = SyntheticSequence(poses, width=320, height=96, times=times)
    pipe = SlamPipeline(syn.camera, cfg, loops="none", refine="batch", build_map=True)
    assert cfg == before  # the caller's config is untouched
    assert pipe.cfg.graph.refine == "batch" and pipe.cfg.map.enabled and pipe.cfg.loops == "none"
    cfg.graph.odom_sigma_trans_m = -1.0  # a later change cannot slip past construction either
    with pytest.raises(SnapsGraphError, match="odom_sigma_trans_m"):
        SlamPipeline(syn.camera, cfg)


def test_every_numeric_config_field_has_a_range():
    from snaps_graph.config import RULES
    from snaps_graph.config_schema import choices, settings

    missing = [key for key, _, hint in settings(Config()) if hint in (int, float) and choices(hint) is None and key not in RULES]
    assert not missing, f"add a range to config.RULES for {missing}"
    unbounded = [k for k, r in RULES.items() if r.lo is None or r.hi is None]
    assert not unbounded, f"give these config.RULES ranges both bounds (a value the checks accept must not crash): {unbounded}"


@pytest.mark.parametrize(
    "key,value",
    [
        ("frontend.num_disparities", 2**31),
        ("loop.frame_distance", 2**62),
        ("map.keyframe_every", 2**62),
    ],
)
def test_values_that_crashed_or_hung_are_out_of_range(tmp_path, key, value):
    section, _, field = key.rpartition(".")
    path = write_config(tmp_path / "c.toml", f"[{section}]\n{field} = {value}\n")
    assert key in assert_user_error(cli("config", path), path)


def test_dumped_config_loads_back(tmp_path):
    path = tmp_path / "c.toml"
    Config().dump(path)
    assert Config.load(path) == Config()


def test_an_older_runs_config_with_retired_keys_loads_with_a_note(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text("[map]\ntsdf_min_weight = 1.0\ndepth_uniqueness = 15\nkeyframe_every = 7\n")
    cfg = Config.load(path)
    assert cfg.map.keyframe_every == 7
    notes = capsys.readouterr().err.strip().splitlines()
    assert len(notes) == 2 and all(n.startswith(f"note: {path}: map.") and "ignored" in n for n in notes)
    path.write_text("[map]\npixel_stepp = 4\n")
    with pytest.raises(SnapsGraphError, match="unknown key 'map.pixel_stepp'"):
        Config.load(path)


# ------------------------------------------------------------------ streaming API
def test_rejected_frame_leaves_the_pipeline_usable(tiny_seq, tmp_path):
    seq = KittiSequence(tiny_seq)
    pipe = SlamPipeline(seq.camera, Config(), loops="snaps", refine="isam2")
    frames = list(seq)
    pipe.process(frames[0])
    small = StereoFrame(1, 0.1, frames[1].left[:50, :100].copy(), frames[1].right[:50, :100].copy())
    with pytest.raises(SnapsGraphError, match="differs from"):
        pipe.process(small)
    with pytest.raises(SnapsGraphError, match="2-D uint8"):
        pipe.process(StereoFrame(1, 0.1, frames[1].left.astype(float), frames[1].right))
    with pytest.raises(SnapsGraphError, match="must increase"):
        pipe.process(frames[0])  # a repeated frame
    with pytest.raises(SnapsGraphError, match="not finite"):
        pipe.process(StereoFrame(1, float("nan"), frames[1].left, frames[1].right))
    for f in frames[1:]:
        out = pipe.process(f)
        assert out.vo.ok and np.all(np.isfinite(out.pose))
    result = pipe.finish()
    assert result.frame_ids == list(range(N_FRAMES))
    metrics = write_results(tmp_path / "run", pipe, result, seq.gt_poses)
    assert metrics["frames"] == N_FRAMES and metrics["flagged_frames"] == 0
    assert len((tmp_path / "run" / "poses_isam2.txt").read_text().splitlines()) == N_FRAMES


# ------------------------------------------------------------------ frame numbers
def _renumber(seq: Path, numbers: list[int]) -> None:
    """Rename the pairs 000000.png... to unpadded numbers."""
    for side in ("image_0", "image_1"):
        files = sorted((seq / side).glob("*.png"))
        for f, n in zip(files, numbers):
            f.rename(seq / side / f"tmp_{n}.png")
        for n in numbers:
            (seq / side / f"tmp_{n}.png").rename(seq / side / f"{n}.png")


def test_unpadded_file_numbers_sort_as_numbers_and_name_the_frames(seq, tmp_path):
    numbers = [0, 1, 2, 5, 9, 10, 11, 50]  # text order would be 0 1 10 11 2 5 50 9
    _renumber(seq, numbers)
    ks = KittiSequence(seq)
    assert list(ks.indices) == numbers
    truth = KittiSequence(seq, frames="3:4")[0]
    assert truth.index == 5
    out = tmp_path / "run"
    proc = cli("run", seq, "--out", out)
    assert proc.returncode == 0, proc.stderr
    with open(out / "frames.csv") as fh:
        assert [int(r["frame"]) for r in csv.DictReader(fh)] == numbers
    # the images were taken in numeric order: VO tracked the real motion (text order would jump)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["flagged_frames"] == 0
    assert metrics["trajectories"]["vo"]["ate_rmse"] < 0.5


def test_duplicate_file_numbers_are_an_error(seq, tmp_path):
    for side in ("image_0", "image_1"):
        shutil.copy(seq / side / "000001.png", seq / side / "1.png")
    assert_user_error(cli("run", seq, "--out", tmp_path / "run"), "1.png")


# ------------------------------------------------------------------ flagged frames
def test_summary_counts_flagged_frames(tiny_seq, tmp_path):
    proc = cli("run", tiny_seq, "--out", tmp_path / "run", "--frames", "0:4")
    assert proc.returncode == 0
    assert re.search(r"4 frames \(0 flagged\)", proc.stdout), proc.stdout


def test_mostly_flagged_run_warns_and_exits_3(seq, tmp_path):
    for side in ("image_0", "image_1"):  # frames 2..7 black: 6 of 8 flagged
        for f in sorted((seq / side).glob("*.png"))[2:]:
            import cv2

            cv2.imwrite(str(f), np.zeros((96, 320), np.uint8))
    out = tmp_path / "run"
    proc = cli("run", seq, "--out", out)
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(warnings) == 1 and warnings[0].startswith("warning: ") and "6 of 8 frames" in warnings[0]
    assert "(6 flagged)" in proc.stdout
    assert json.loads((out / "metrics.json").read_text())["flagged_frames"] == 6  # the folder is whole


# ------------------------------------------------------------------ make bench
def test_make_bench_calls_a_script_that_exists():
    make = (ROOT / "Makefile").read_text()
    target = re.search(r"^bench:.*\n\t(.+)$", make, re.M)
    assert target, "no bench target"
    script = re.search(r"(benchmarks/\S+\.py)", target.group(1))
    assert script and (ROOT / script.group(1)).is_file()
    proc = subprocess.run([sys.executable, str(ROOT / script.group(1)), "--list"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    for name in re.findall(r"benchmarks/bench_\w+\.py|bench_\w+\.py", proc.stdout):
        assert (ROOT / "benchmarks" / Path(name).name).is_file(), name


# ------------------------------------------------------------------ usage errors and odd values
@pytest.mark.parametrize(
    "args,expect",
    [
        (["run"], "Missing argument"),
        (["synth"], "Missing option '--out'"),
        (["run", "SEQ", "--out", "X", "--bogus"], "No such option"),
        (["synth", "--out", "X", "--width", "abc"], "--width"),
        (["synth", "--out", "X", "--seed", "-1"], "--seed"),
        (["synth", "--out", "X", "--width", "100000"], "too large"),
        (["demo", "--out", "X", "--refine", "fast"], "--refine"),
    ],
)
def test_usage_errors_are_one_line(tiny_seq, tmp_path, args, expect):
    args = [str(tiny_seq) if a == "SEQ" else str(tmp_path / "out") if a == "X" else a for a in args]
    assert expect in assert_user_error(cli(*args))
    assert not (tmp_path / "out").exists()


def test_images_too_small_for_snaps_name_the_image(tmp_path):
    seq = tmp_path / "seq"
    assert cli("synth", "--out", seq, "--frames", "0:3", "--width", "40", "--height", "40").returncode == 0
    msg = assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "image_0" / "000000.png", "loop.window")
    assert "too small" in msg
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ layout
# What each part of the package may import from the package (the data's flow: camera -> front end
# -> loop verification -> loop -> back end -> map -> evaluation; the pipeline runs the stages, the
# runner does the I/O; a session's format stands apart, read by the runner, given to the pipeline).
BASE = {"errors", "types", "config", "config_schema", "drift_model", "io_utils", "geometry", "camera", "trajectory_io"}
ALLOWED = {
    "datasets": BASE | {"datasets"},
    "synth": BASE | {"synth"},
    "frontend": BASE | {"frontend"},
    "verification": BASE | {"verification", "frontend"},
    "loop": BASE | {"loop"},
    "backend": BASE | {"backend"},
    "mapping": BASE | {"mapping", "frontend"},
    "evaluation": BASE | {"evaluation", "backend"},
    "session": BASE | {"session"},
    "pipeline": BASE | {"frontend", "verification", "loop", "backend", "mapping", "session"},
    "runner": BASE | {"pipeline", "evaluation", "mapping", "session"},
}


def _package_imports(path: Path) -> set[str]:
    """Top-level snaps_graph modules/packages that ``path`` imports (relative or absolute)."""
    import ast

    pkg_parts = path.relative_to(ROOT / "snaps_graph").parts[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(pkg_parts[: len(pkg_parts) - node.level + 1])
                mod = base + (node.module.split(".") if node.module else [])
                if not mod:  # `from . import x`
                    mod = [alias.name for alias in node.names][:1]
            elif node.module and node.module.startswith("snaps_graph."):
                mod = node.module.split(".")[1:]
            else:
                continue
            out.add(mod[0])
    return out


@pytest.mark.parametrize("part", sorted(ALLOWED))
def test_imports_follow_the_data_flow(part):
    files = (
        sorted((ROOT / "snaps_graph" / part).glob("*.py"))
        if (ROOT / "snaps_graph" / part).is_dir()
        else [ROOT / "snaps_graph" / f"{part}.py"]
    )
    for f in files:
        wrong = _package_imports(f) - ALLOWED[part]
        assert not wrong, f"{f.relative_to(ROOT)} imports {sorted(wrong)} against the data flow"


def test_eval_lengths_differ_names_both_files(tmp_path, tiny_seq):
    short = tmp_path / "short.txt"
    short.write_text("".join((tiny_seq / "poses.txt").read_text().splitlines(keepends=True)[:3]))
    assert_user_error(cli("eval", short, "--gt", tiny_seq / "poses.txt"), short, tiny_seq / "poses.txt")


def test_pose_file_without_rotations_is_refused(tmp_path):
    zeros = tmp_path / "zeros.txt"
    zeros.write_text("0 0 0 0 0 0 0 0 0 0 0 0\n" * 3)
    assert "not a rotation" in assert_user_error(cli("eval", zeros, "--gt", zeros), f"{zeros}:1")


def _tiny_run(tiny_seq: Path):
    """The tiny sequence's first 3 frames through the pipeline (VO only): (pipeline, result)."""
    seq = KittiSequence(tiny_seq, frames="0:3")
    pipe = SlamPipeline(seq.camera, Config(), loops="none", refine="none")
    for f in seq:
        pipe.process(f)
    return pipe, pipe.finish()


def test_results_that_cannot_be_written_leave_nothing(tiny_seq, tmp_path, monkeypatch):
    """Disk full (or any OSError) while writing: one-line error, no folder, no temporary folder."""
    import errno

    import snaps_graph.runner as runner

    pipe, result = _tiny_run(tiny_seq)

    def full(path, records):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(runner, "write_frames_csv", full)
    with pytest.raises(SnapsGraphError, match="frames.csv: cannot write the results .No space left"):
        write_results(tmp_path / "run", pipe, result)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ stereo order
@pytest.mark.parametrize("fault", ["swapped", "same"])
def test_swapped_or_repeated_cameras_are_one_line_errors_and_leave_no_folder(seq, tmp_path, fault):
    """image_0/ and image_1/ exchanged (a classic mix-up) or the left images given twice: one line
    naming the first frame's file and the fix, before any results folder is written."""
    if fault == "swapped":
        (seq / "image_0").rename(seq / "tmp")
        (seq / "image_1").rename(seq / "image_0")
        (seq / "tmp").rename(seq / "image_1")
    else:
        shutil.rmtree(seq / "image_1")
        shutil.copytree(seq / "image_0", seq / "image_1")
    out = tmp_path / "out"
    line = assert_user_error(cli("run", seq, "--out", out, "--no-map"), seq / "image_0" / "000000.png")
    assert ("swap the two inputs" in line) == (fault == "swapped"), line
    assert ("repeats the left" in line) == (fault == "same"), line
    assert not out.exists()


# ------------------------------------------------------------------ never destroy a user's file
def tree(path: Path) -> dict[str, str]:
    """Every file under ``path`` (or the file itself) and its content hash: what must not change."""
    import hashlib

    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def no_leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if re.match(r"^\..*\.(tmp|old)-\d+$", p.name)]


@pytest.fixture(scope="module")
def finished_run(tiny_seq, tmp_path_factory) -> Path:
    """A finished results folder of the tiny sequence (5 frames), run once for the module."""
    out = tmp_path_factory.mktemp("finished") / "done"
    proc = cli("run", tiny_seq, "--out", out, "--frames", "0:5")
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture
def done_run(finished_run, tmp_path) -> Path:
    """A private copy of the finished results folder (a test may change or replace it)."""
    return Path(shutil.copytree(finished_run, tmp_path / "done"))


def test_rrd_never_replaces_an_input_or_another_runs_file(seq, done_run, tmp_path):
    before = tree(seq) | tree(done_run)
    out = tmp_path / "new"
    cases = [
        (seq / "calib.txt", "must name a .rrd file"),
        (done_run / "poses_vo.txt", "must name a .rrd file"),
        (done_run / "rec.rrd", "inside the results folder"),
        (seq, "names a folder"),
    ]
    for rrd, expect in cases:
        assert_user_error(cli("run", seq, "--out", out, "--rrd", rrd), rrd, expect)
    not_a_recording = tmp_path / "notes.rrd"
    not_a_recording.write_text("my notes\n")
    assert_user_error(cli("run", seq, "--out", out, "--rrd", not_a_recording), "not a rerun recording")
    assert not_a_recording.read_text() == "my notes\n"
    assert tree(seq) | tree(done_run) == before
    assert not out.exists() and not no_leftovers(tmp_path)


def test_rrd_inside_out_is_written_with_the_results(seq, tmp_path):
    pytest.importorskip("rerun")
    out = tmp_path / "run"
    proc = cli("run", seq, "--out", out, "--frames", "0:3", "--rrd", out / "run.rrd")
    assert proc.returncode == 0, proc.stderr
    assert (out / "run.rrd").read_bytes()[:4] == b"RRF2" and (out / "metrics.json").is_file()
    assert not no_leftovers(tmp_path)


def test_overwrite_never_deletes_a_folder_this_tool_did_not_write(seq, tmp_path):
    home = tmp_path / "home"
    (home / "docs").mkdir(parents=True)
    (home / "docs" / "thesis.tex").write_text("years of work\n")
    (home / "notes.txt").write_text("x\n")
    before = tree(home)
    line = assert_user_error(cli("run", seq, "--out", home, "--overwrite"), home, "not a folder this tool wrote")
    assert ".snaps_graph_results" in line
    assert_user_error(cli("synth", "--out", home, "--frames", "0:2", "--width", "64", "--height", "48", "--overwrite"), home)
    assert tree(home) == before and not no_leftovers(tmp_path)


@pytest.mark.parametrize("option", ["--config", "--gt"])
def test_an_input_inside_out_is_refused_before_anything_is_deleted(seq, done_run, option):
    inner = done_run / ("my.toml" if option == "--config" else "my_gt.txt")
    shutil.copy(seq / "poses.txt", inner) if option == "--gt" else inner.write_text("[loop]\nmin_similarity = 0.2\n")
    before = tree(done_run)
    assert_user_error(cli("run", seq, "--out", done_run, option, inner, "--overwrite"), inner, "would replace the input")
    assert tree(done_run) == before


def test_synth_world_mesh_inside_out_is_kept(tmp_path):
    out = tmp_path / "seq"
    args = ["synth", "--out", out, "--frames", "0:2", "--width", "64", "--height", "48", "--world-mesh", out / "world.ply"]
    for extra in ([], ["--overwrite"]):
        proc = cli(*args, *extra)
        assert proc.returncode == 0, proc.stderr
        assert (out / "world.ply").stat().st_size > 1000, proc.stdout
        assert len(list((out / "image_0").glob("*.png"))) == 2
    assert not no_leftovers(tmp_path)


def test_leftovers_of_a_killed_replacement_are_restored_and_said(seq, done_run, tmp_path):
    """kill -9 between the two renames: OUT absent, the old run in .OUT.old-PID, the new one in
    .OUT.tmp-PID. The next start puts the old one back, removes the new one and says both."""
    old = tree(done_run)
    dead = 2**22 + 12345  # above Linux's pid_max default: no such process
    shutil.copytree(done_run, tmp_path / f".done.tmp-{dead}")
    done_run.rename(tmp_path / f".done.old-{dead}")
    proc = cli("run", seq, "--out", done_run, "--frames", "0:3")
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 3 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[2].startswith("error: ") and "--overwrite" in lines[2]  # the old results are back: kept without it
    notes = "\n".join(lines[:2])
    assert all(line.startswith("note: ") for line in lines[:2])
    assert f"restored the previous results from .done.old-{dead}" in notes and f"removed .done.tmp-{dead}" in notes
    assert {k.replace(f".done.old-{dead}", "done"): v for k, v in old.items()} == tree(done_run)
    assert not no_leftovers(tmp_path)


@pytest.mark.parametrize("how", ["dot", "symlink"])
def test_out_the_current_folder_or_a_symlink_is_refused_before_the_first_frame(seq, tmp_path, how):
    (seq / "image_0" / "000003.png").write_bytes(b"corrupt")  # reached only if frames were read
    empty = tmp_path / "empty"
    empty.mkdir()
    if how == "dot":
        assert_user_error(cli("run", seq, "--out", ".", cwd=empty), "current folder")
    else:
        link = tmp_path / "link"
        link.symlink_to(empty)
        assert_user_error(cli("run", seq, "--out", link), link, "symbolic link")
    assert list(empty.iterdir()) == []


def test_ctrl_c_during_the_swap_says_the_results_are_complete(tiny_seq, tmp_path, monkeypatch):
    """SIGINT while the folder is renamed into place is held back until the swap is done; the
    results are then whole and the process knows it (the CLI's message says so)."""
    import snaps_graph.io_utils as io_utils

    pipe, result = _tiny_run(tiny_seq)
    out = tmp_path / "run"
    real_replace = os.replace

    def replace(src, dst):
        if Path(dst) == out:
            signal.raise_signal(signal.SIGINT)  # Ctrl-C at the final rename
        real_replace(src, dst)

    import threading

    monkeypatch.setattr(io_utils.os, "replace", replace)
    # Python's own Ctrl-C handler in place, as in a program started from a terminal (a runner
    # started in the background inherits SIGINT ignored, and Python then installs none).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    busy = threading.Event()
    other = threading.Thread(target=busy.wait, args=(30,), daemon=True)  # a thread that could take the signal
    other.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            write_results(out, pipe, result)
    finally:
        busy.set()
        signal.signal(signal.SIGINT, previous)
    assert (out / "metrics.json").is_file() and out.resolve() in io_utils.committed_folders()
    assert not no_leftovers(tmp_path)


def test_kill_during_the_swap_is_held_back_too(tiny_seq, tmp_path, monkeypatch):
    """SIGTERM at the final rename reaches its handler only once the folder is whole."""
    import snaps_graph.io_utils as io_utils

    pipe, result = _tiny_run(tiny_seq)
    out = tmp_path / "run"
    real_replace = os.replace
    seen: list[bool] = []

    def replace(src, dst):
        if Path(dst) == out:
            signal.raise_signal(signal.SIGTERM)
        real_replace(src, dst)

    def on_term(signum, frame):
        seen.append((out / "metrics.json").is_file())
        raise RuntimeError("terminated")

    monkeypatch.setattr(io_utils.os, "replace", replace)
    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        with pytest.raises(RuntimeError, match="terminated"):
            write_results(out, pipe, result)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert seen == [True]  # delivered once, after the swap
    assert out.resolve() in io_utils.committed_folders() and not no_leftovers(tmp_path)


def test_a_failed_map_stage_keeps_the_trajectories(seq, tmp_path, monkeypatch):
    import snaps_graph.runner as runner

    def broken(*a, **k):
        raise RuntimeError("[Open3D Error] (CreateFromDepthImage) something\nsecond line")

    syn = KittiSequence(seq, frames="0:3")
    cfg = Config()
    cfg.map.enabled = True
    monkeypatch.setattr(runner, "write_map_outputs", broken)
    _, metrics = runner.run_sequence(syn, tmp_path / "run", cfg, loops="none", refine="none", build_map=True)
    assert (tmp_path / "run" / "poses_vo.txt").is_file()
    assert metrics["map"] == {"error": "RuntimeError: [Open3D Error] (CreateFromDepthImage) something"}


# ------------------------------------------------------------------ bounded inputs, no crash
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_stdout_on_a_full_device_after_the_results_is_a_note_and_exit_0(seq, tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            CLI + ["run", str(seq), "--out", str(out), "--frames", "0:3"], stdout=full, stderr=subprocess.PIPE, text=True, env=env
        )
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 0 and len(lines) == 1 and lines[0].startswith("note: standard output not written"), proc.stderr
    assert (out / "metrics.json").is_file()


def test_the_api_refuses_what_the_readers_refuse(tiny_seq):
    seq = KittiSequence(tiny_seq, frames="0:3")
    frames = list(seq)
    pipe = SlamPipeline(seq.camera, Config(), loops="none", refine="none")
    with pytest.raises(SnapsGraphError, match="takes a StereoFrame, not NoneType"):
        pipe.process(None)  # type: ignore[arg-type]
    pipe.process(frames[0])
    with pytest.raises(SnapsGraphError, match="timestamp -1.0 does not increase"):
        pipe.process(StereoFrame(1, -1.0, frames[1].left, frames[1].right))
    pipe.process(frames[1])  # still usable


@pytest.mark.parametrize(
    "p0,p1,expect",
    [
        (_p(180, 160, 48)[:10] + [0, 0], _p(180, 160, 48, -97.2)[:10] + [0, 0], "third row"),  # P[2,2] = 0
        (_p(180, 160, 48)[:1] + [90] + _p(180, 160, 48)[2:], _p(180, 160, 48, -97.2), "skew"),
        (_p(180, 160, 48), _p(180, 160, 48, -97.2)[:7] + [-20.0] + [0, 0, 1, 0], "vertical offset"),
    ],
)
def test_degenerate_calibration_is_a_one_line_error(seq, tmp_path, p0, p1, expect):
    _calib(seq, p0, p1)
    assert expect in assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "calib.txt")


def test_calibration_with_a_byte_order_mark_is_read(seq):
    text = (seq / "calib.txt").read_text()
    (seq / "calib.txt").write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert KittiSequence(seq).camera.fx > 0


def test_a_huge_calibration_file_is_refused_without_reading_it(seq, tmp_path):
    with open(seq / "calib.txt", "r+b") as fh:
        fh.truncate(2**31)  # sparse: 2 GB that cost no disk
    assert "larger than 1 MiB" in assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "calib.txt")


def test_an_image_that_would_decode_to_gigabytes_is_refused_from_its_header(seq, tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", 32000, 32000, 8, 0, 0, 0, 0)
    bomb = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 32001 * 8)) + chunk(b"IEND", b"")
    (seq / "image_1" / "000000.png").write_bytes(bomb)
    assert "32000x32000" in assert_user_error(cli("run", seq, "--out", tmp_path / "run"), seq / "image_1" / "000000.png")


def test_a_truncated_jpeg_is_an_error_naming_it(tmp_path):
    import cv2

    from snaps_graph.datasets.kitti import read_grey

    path = tmp_path / "000000.jpg"
    ok, data = cv2.imencode(".jpg", (np.random.default_rng(0).random((96, 320)) * 255).astype(np.uint8))
    path.write_bytes(data.tobytes()[: len(data) // 2])
    with pytest.raises(SnapsGraphError, match=re.escape(f"{path}: truncated JPEG")):
        read_grey(path)


def test_numbered_and_named_images_mixed_are_refused(seq, tmp_path):
    for side in ("image_0", "image_1"):
        shutil.copy(seq / side / "000007.png", seq / side / "extra.png")
        (seq / side / "000007.png").unlink()
    assert "named image among numbered" in assert_user_error(cli("run", seq, "--out", tmp_path / "run"), "extra.png")


def test_black_first_frames_are_not_taken_for_a_repeated_camera():
    from snaps_graph.frontend.depth import stereo_order

    black = np.zeros((96, 320), np.uint8)
    assert stereo_order(black, black)[0] == "unknown"
    textured = (np.random.default_rng(0).random((96, 320)) * 255).astype(np.uint8)
    assert stereo_order(textured, textured)[0] == "same"


def test_synth_size_is_bounded_by_memory(tmp_path):
    out = tmp_path / "big"
    assert "too large" in assert_user_error(cli("synth", "--out", out, "--width", "20000", "--height", "20000"))
    assert not out.exists()


# ------------------------------------------------------------------ the command line's habits
def test_help_version_and_short_options(seq, tmp_path):
    from snaps_graph import __version__

    for args in (["-h"], ["run", "-h"], ["batch", "-h"]):
        proc = cli(*args)
        assert proc.returncode == 0 and "Usage:" in proc.stdout, (args, proc.stderr)
    version = cli("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"snaps-graph {__version__}"
    config = write_config(tmp_path / "c.toml", "[loop]\nmin_similarity = 0.2\n")
    proc = cli("run", seq, "-o", tmp_path / "run", "-c", config, "--frames", "0:3")
    assert proc.returncode == 0, proc.stderr
    assert "min_similarity = 0.2" in (tmp_path / "run" / "config.toml").read_text()


def test_eval_accepts_evos_order_reference_first(tiny_seq, tmp_path):
    gt = tiny_seq / "poses.txt"
    est = tmp_path / "est.txt"
    rows = [line.split() for line in gt.read_text().splitlines()]
    est.write_text("".join(" ".join(r[:3] + [str(float(r[3]) + 0.1)] + r[4:]) + "\n" for r in rows))
    ours = cli("eval", est, "--gt", gt, "--json")
    evo = cli("eval", gt, est, "--json")
    assert ours.returncode == 0 and evo.returncode == 0, ours.stderr + evo.stderr
    assert json.loads(ours.stdout) == json.loads(evo.stdout)
    assert "evo's order" in assert_user_error(cli("eval", est))
    assert_user_error(cli("eval", gt, est, "--gt", gt), "once")


@pytest.mark.parametrize(
    "text,expect",
    [
        ("[loop]\nmin_similarty = 0.2\n", "did you mean 'loop.min_similarity'?"),
        ("[loops]\nmin_similarity = 0.2\n", "[loops] is not a section (did you mean [loop]?)"),
        ("[frontnd]\nmode = 'klt'\n", "did you mean 'frontend'?"),
    ],
)
def test_a_misspelled_config_key_or_section_gets_did_you_mean(tmp_path, text, expect):
    path = write_config(tmp_path / "c.toml", text)
    assert expect in assert_user_error(cli("config", path), path)


def test_a_frame_range_past_the_end_runs_to_the_end_and_says_so(seq, tmp_path):
    proc = cli("run", seq, "--out", tmp_path / "run", "--frames", "2:500")
    assert proc.returncode == 0, proc.stderr
    assert f"note: --frames 2:500: the sequence has {N_FRAMES} frames; running 2:{N_FRAMES}" in proc.stderr
    assert len((tmp_path / "run" / "poses_vo.txt").read_text().splitlines()) == N_FRAMES - 2
    assert "only 8 frames" in assert_user_error(cli("run", seq, "--out", tmp_path / "r2", "--frames", "100:200"))


@pytest.mark.parametrize("args", [["run", "NOPE", "-o", "x"], ["eval", "NOPE", "--gt", "NOPE2"], ["compare", "NOPE"]])
def test_a_mistyped_path_fails_before_the_heavy_imports(tmp_path, args):
    """Checked by what the process imported, not by a clock: no OpenCV, gtsam or open3d."""
    code = (
        "import sys, runpy\n"
        f"sys.argv = ['snaps-graph', *{args!r}]\n"
        "try:\n    runpy.run_module('snaps_graph.cli', run_name='__main__')\n"
        "except SystemExit as e:\n"
        "    heavy = [m for m in ('cv2', 'gtsam', 'open3d', 'matplotlib') if m in sys.modules]\n"
        "    print('heavy:', heavy, 'exit:', e.code)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert "heavy: [] exit: 2" in proc.stdout, proc.stdout + proc.stderr
    assert "NOPE" in proc.stderr and "not found" in proc.stderr


def test_overwrite_keeps_a_file_the_user_added_to_a_results_folder(seq, done_run):
    assert cli("compare", done_run).returncode == 0  # report.md and pictures: the tool's own
    (done_run / "my_notes.txt").write_text("mine\n")
    before = tree(done_run)
    line = assert_user_error(cli("run", seq, "--out", done_run, "--frames", "0:3", "--overwrite"), "my_notes.txt")
    assert "did not write" in line and tree(done_run) == before
    (done_run / "my_notes.txt").unlink()
    proc = cli("run", seq, "--out", done_run, "--frames", "0:3", "--overwrite")
    assert proc.returncode == 0, proc.stderr
    assert len((done_run / "poses_vo.txt").read_text().splitlines()) == 3 and not (done_run / "report.md").exists()


def test_demo_keeps_the_run_contract(tmp_path, done_run):
    """An earlier demo's folders are replaced only with --overwrite, a folder the tool did not write
    never; both refused before anything is rendered."""
    demo = tmp_path / "demo"
    (demo / "sequence").mkdir(parents=True)
    (demo / "sequence" / "mine.txt").write_text("mine\n")
    before = tree(demo)
    for extra in ([], ["--overwrite"]):
        assert_user_error(cli("demo", "--out", demo, "--frames", "20", *extra), demo / "sequence")
        assert tree(demo) == before
    shutil.rmtree(demo / "sequence")
    shutil.copytree(done_run, demo / "run")  # an earlier demo's results folder: ours
    before = tree(demo)
    line = assert_user_error(cli("demo", "--out", demo, "--frames", "20"), demo / "run")
    assert "--overwrite" in line and tree(demo) == before and not (demo / "sequence").exists()


def test_wrong_folder_mistakes_name_the_fix(tmp_path):
    """A EuRoC camera folder or a folder of sequences: the error says which folder to pass."""
    cam0 = tmp_path / "V1" / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    (cam0 / "data.csv").write_text("#timestamp [ns],filename\n")
    proc = cli("run", str(cam0), "--out", str(tmp_path / "r1"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert f"a EuRoC camera folder; pass the folder holding mav0/ ({tmp_path / 'V1'})" in proc.stderr
    for name in ("06", "00"):
        (tmp_path / "kitti" / "sequences" / name / "image_0").mkdir(parents=True)
    for where in (tmp_path / "kitti", tmp_path / "kitti" / "sequences"):
        proc = cli("run", str(where), "--out", str(tmp_path / "r2"))
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1
        assert f"holds sequences 00, 06: pass one of them (e.g. {tmp_path / 'kitti' / 'sequences' / '00'})" in proc.stderr
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()


def test_an_in_process_run_leaves_the_test_process_as_it_was(seq, tmp_path):
    """tests/inprocess.py puts back what main() changes, so in-process runs cannot see each other."""
    from snaps_graph import io_utils

    def state() -> tuple:
        handlers = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)]
        return handlers, os.getcwd(), dict(os.environ), io_utils.committed_folders()

    before = state()
    proc = cli("run", seq, "--out", "r", "--frames", "0:3", cwd=tmp_path, env={"SNAPS_GRAPH_TEST_VAR": "1"})
    assert proc.returncode == 0 and (tmp_path / "r" / "metrics.json").is_file(), proc.stderr
    assert state() == before
