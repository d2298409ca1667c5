"""A newcomer's first session: the README's quick-start commands run as written on the shared
clips, the CLI's habits (-h, --version, -o, -c), `config` as commented TOML, .tum files on the
input's clock, and report.md linking only files that exist.

The quick start is read from README.md itself (its "Quick start" code block), so the test fails
when the README drifts from the tool. Data paths map to the shared clips (``DATA/kitti/...`` to
../shared/data/kitti/..., ``DATA/euroc/V1_01_easy`` to the EuRoC clip, ``recording.bag`` to a bag
written from the KITTI clip); a ``run`` without ``--frames`` gets ``--frames 0:12`` to keep the
test within seconds. Lines naming data the test cannot stand in for are skipped and listed.

Then what the first hour once got wrong: the demo's revisit replayed its first pass (Q = 1),
figures across a run's frame gaps, and the messages of help, --odometry reports, a folder holding
a run, Ctrl-C over --overwrite, eval with the whole ground truth and process() after finish()."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from inprocess import Ran, cli  # the command line in this process (tests/inprocess.py)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from bagutil import write_stereo_bag  # noqa: E402
from conftest import SHARED_DATA, installed, need_extra  # noqa: E402

N_FRAMES = 8  # frames per quick-start run
BAG_BASE_S = 1.6e9  # bagutil's header stamps start here (s)
KITTI06 = SHARED_DATA / "kitti" / "sequences" / "06"
EUROC = SHARED_DATA / "euroc" / "V1_01_easy_first95"


def _quickstart_lines() -> list[str]:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"## Quick start[^\n]*\n+```bash\n(.*?)```", text, re.S)
    assert m, "README.md: no '## Quick start' section with a bash code block"
    lines = []
    for line in m.group(1).splitlines():
        words = shlex.split(line, comments=True)
        if words:
            lines.append(shlex.join(words).replace("'&&'", "&&").replace("'>'", ">"))
    return lines


def _env(bin_dir: Path) -> dict:
    path = os.pathsep.join([str(bin_dir), str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    return dict(os.environ, PATH=path, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")


@pytest.fixture(scope="module")
def bin_dir(tmp_path_factory) -> Path:
    """``snaps-graph`` on PATH as this tree's code (what ``. .venv/bin/activate`` gives a user)."""
    d = tmp_path_factory.mktemp("bin")
    shim = d / "snaps-graph"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m snaps_graph.cli "$@"\n')
    shim.chmod(0o755)
    return d


def _sg(cwd: Path, *args: str) -> Ran:
    """``snaps-graph ARGS`` run in ``cwd``, in this process (the quick start and Ctrl-C run the script)."""
    return cli(*args, cwd=cwd)


@pytest.fixture(scope="module")
def quickstart(bin_dir, tmp_path_factory):
    """Runs the quick start in a fresh folder: (folder, {line: completed process}, skipped lines).
    The ``snaps-graph`` lines run in this process; the console script itself is run by
    test_ctrl_c_over_an_earlier_run_with_overwrite_says_it_was_kept."""
    if not KITTI06.is_dir() or not EUROC.is_dir():
        pytest.skip(f"the shared clips are not at {SHARED_DATA} (CI has them; a user's clone lacks ../shared)")
    work = tmp_path_factory.mktemp("newcomer")
    from snaps_graph.datasets.kitti import KittiSequence

    no_bag = not installed("rosbags")  # a core install reads no bag: its line is skipped, the rest run
    if not no_bag:
        write_stereo_bag(work / "recording.bag", KittiSequence(KITTI06), "ros1", n=N_FRAMES)
    stand_ins = {
        "DATA/kitti/sequences/06": str(KITTI06),
        "DATA/kitti/poses/06.txt": str(KITTI06.parents[1] / "poses" / "06.txt"),
        "DATA/euroc/V1_01_easy": str(EUROC),
    }
    done, skipped = {}, []
    for line in _quickstart_lines():
        if line.startswith(".") or "rosbag2_dir" in line or "results/demo" in line or (no_bag and "recording.bag" in line):
            skipped.append(line)  # the venv (the shim stands in), a bag with other topic names, make demo's output
            continue
        if line.startswith("evo_ape") and not (Path(sys.executable).parent / "evo_ape").exists():
            skipped.append(line)
            continue
        cmd = line
        for name, path in stand_ins.items():
            cmd = cmd.replace(name, path)
        cmd = re.sub(
            r"(snaps-graph run (?:(?!&&).)*)",
            lambda m: m.group(1) if "--frames" in m.group(1) else f"{m.group(1)} --frames 0:{N_FRAMES}",
            cmd,
        )
        done[line] = _run_line(cmd, work, bin_dir)
    return work, done, skipped


def _run_line(cmd: str, cwd: Path, bin_dir: Path) -> Ran | subprocess.CompletedProcess:
    """One quick-start line as the shell runs it: its ``snaps-graph`` commands in this process,
    joined by ``&&``, a ``> FILE`` written as the shell would; another program (evo_ape) by the shell."""
    if not cmd.startswith("snaps-graph "):
        return subprocess.run(["bash", "-c", cmd], cwd=cwd, env=_env(bin_dir), capture_output=True, text=True, timeout=300)
    outs, errs, code = [], [], 0
    for part in cmd.split(" && "):
        words = shlex.split(part)
        target = words[words.index(">") + 1] if ">" in words else None
        assert words[0] == "snaps-graph", part
        proc = cli(*words[1 : words.index(">") if target else None], cwd=cwd)
        errs.append(proc.stderr)
        if target:
            (cwd / target).write_text(proc.stdout)
        else:
            outs.append(proc.stdout)
        code = proc.returncode
        if code:
            break
    return Ran(shlex.split(cmd), code, "".join(outs), "".join(errs))


def test_quickstart_commands_run_as_written(quickstart):
    work, done, skipped = quickstart
    assert len(done) >= 6, f"too few quick-start commands ran: {list(done)} (skipped {skipped})"
    for line, proc in done.items():
        assert proc.returncode == 0, f"README quick start: `{line}` exited {proc.returncode}:\n{proc.stderr[-1500:]}"
    assert (work / "results" / "kitti06" / "report.md").is_file()


def test_frames_range_writes_its_ground_truth_and_names_it(quickstart):
    work, done, _ = quickstart
    run = work / "results" / "first20"
    line = next(k for k in done if "results/first20" in k)
    assert len(np.loadtxt(run / "poses_gt.txt")) == len(np.loadtxt(run / "poses_vo.txt")) == 20
    assert len(np.loadtxt(run / "poses_gt.tum")) == 20
    assert f"evo_ape kitti {Path('results/first20') / 'poses_gt.txt'}" in done[line].stdout


def _tum_stamps(path: Path) -> np.ndarray:
    return np.loadtxt(path)[:, 0]


def test_tum_stamps_are_the_inputs(quickstart):
    work, _, _ = quickstart
    res = work / "results"
    kitti_t = np.loadtxt(KITTI06 / "times.txt")[:N_FRAMES]
    np.testing.assert_allclose(_tum_stamps(res / "kitti06" / "poses_vo.tum"), kitti_t, atol=1e-6)
    np.testing.assert_allclose(_tum_stamps(res / "kitti06" / "poses_gt.tum"), kitti_t, atol=1e-6)
    cam0 = np.loadtxt(EUROC / "mav0" / "cam0" / "data.csv", delimiter=",", dtype=np.int64, usecols=0)[:N_FRAMES]
    np.testing.assert_allclose(_tum_stamps(res / "v101" / "poses_vo.tum"), cam0 * 1e-9, rtol=0, atol=1e-6)
    if installed("rosbags"):
        np.testing.assert_allclose(_tum_stamps(res / "bag" / "poses_vo.tum"), BAG_BASE_S + kitti_t, rtol=0, atol=1e-6)


def test_report_links_only_files_it_wrote(quickstart):
    work, _, _ = quickstart
    run = work / "results" / "kitti06"
    links = re.findall(r"\]\(([^)#\s]+)\)", (run / "report.md").read_text())
    assert links, "report.md links nothing"
    missing = [link for link in links if not link.startswith("http") and not (run / link).exists()]
    assert not missing, f"report.md links files that do not exist: {missing}"


def test_help_version_and_short_options(tiny_seq, tmp_path):
    for args in (["-h"], ["--help"], ["run", "-h"], ["demo", "-h"]):
        proc = _sg(tmp_path, *args)
        assert proc.returncode == 0 and "Usage" in proc.stdout, f"{args}: {proc.stderr}"
    from snaps_graph import __version__

    proc = _sg(tmp_path, "--version")
    assert proc.returncode == 0 and __version__ in proc.stdout
    cfg = tmp_path / "c.toml"
    cfg.write_text(_sg(tmp_path, "config").stdout)
    proc = _sg(tmp_path, "run", str(tiny_seq), "-o", "r", "-c", str(cfg), "--frames", "0:4")
    assert proc.returncode == 0, proc.stderr
    assert len(np.loadtxt(tmp_path / "r" / "poses_vo.txt")) == 4


def _config_text(cwd: Path) -> str:
    proc = _sg(cwd, "config")
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_config_output_is_toml(tmp_path):
    parsed = tomllib.loads(_config_text(tmp_path))
    assert "loop" in parsed and "frontend" in parsed


def test_config_every_key_has_a_comment(tmp_path):
    lines = _config_text(tmp_path).splitlines()
    bare = []
    for i, line in enumerate(lines):
        if re.match(r"\s*[A-Za-z_][\w.]*\s*=", line):
            above = lines[i - 1].strip() if i else ""
            if "#" not in line.split("=", 1)[1] and not above.startswith("#"):
                bare.append(line.split("=")[0].strip())
    assert not bare, f"config keys without a comment: {bare[:10]}{' ...' if len(bare) > 10 else ''}"


def test_progress_in_a_log_has_rate_eta_and_the_phase(monkeypatch):
    """Without a terminal: a line every LOG_EVERY_S with rate and ETA, the final rate (the one the
    summary prints), and the phase after the last frame; a short run prints nothing."""
    import io

    from snaps_graph import console

    quiet = io.StringIO()
    with console.Progress(3, "slam", stream=quiet) as bar:
        for _ in range(3):
            bar.update(1)
        bar.phase("writing")
    assert quiet.getvalue() == ""
    monkeypatch.setattr(console, "LOG_EVERY_S", 0.0)
    log = io.StringIO()
    with console.Progress(4, "slam", stream=log) as bar:
        for _ in range(4):
            bar.update(1)
        bar.phase("writing the map")
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("slam: 1/4 frames, ") and "frames/s, ETA " in lines[0]
    assert len(lines) == 5 and lines[-1] == "slam: writing the map ..."
    assert lines[-2] == f"slam: 4/4 frames, {bar.rate:.1f} frames/s"  # once, with the summary's rate


def test_bag_topics_found_by_name_are_printed_and_recorded(quickstart):
    need_extra("rosbags")
    work, done, _ = quickstart
    line = next(k for k in done if "recording.bag" in k)
    assert "topics: left /stereo/left/image_raw, right /stereo/right/image_raw" in done[line].stdout
    metrics = json.loads((work / "results" / "bag" / "metrics.json").read_text())
    assert metrics["topics"] == {"left_topic": "/stereo/left/image_raw", "right_topic": "/stereo/right/image_raw"}


def test_progress_on_a_terminal_closes_at_the_last_frame_and_names_the_phase():
    import io
    import time

    from snaps_graph import console

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    with console.Progress(3, "slam", stream=term) as bar:
        for _ in range(3):
            time.sleep(0.05)
            bar.update(1)
        bar.phase("writing the map")
    text = term.getvalue()
    assert "3/3" in text and text.endswith("slam: writing the map ...\n")
    shown = float(re.findall(r"([\d.]+)frame/s", text)[-1])
    assert bar.rate is not None
    assert abs(shown - bar.rate) <= 0.05 * bar.rate  # the bar's final rate is the summary's


# ------------------------------------------------------------------ the demo is a real revisit
def test_demo_second_pass_is_another_lane_in_other_traffic_and_light():
    """The demo's revisit (frames 250-299 over 0-49) drives 1-3 m aside, past other cars, in
    other light: its thumbnails compare as a real revisit's do, never as the same image (the
    demo once re-drove the same poses in a static world: Q = 1.0000 on 11 of its 12 loops)."""
    from snaps_graph.demo import demo_sequence
    from snaps_graph.loop.uiqi import make_thumbnail, similarity_q, window_stats

    seq = demo_sequence(300, width=620, height=188)
    gt = seq.gt_poses
    first, second = gt[:50, :3, 3], gt[250:, :3, 3]
    aside = np.linalg.norm(second - first, axis=1)
    assert np.all((aside >= 1.0) & (aside <= 3.0)), (aside.min(), aside.max())
    cfg = seq.world.config
    assert cfg.traffic and cfg.lighting
    sun_a, sun_b = seq.sun(5), seq.sun(255)
    assert sun_a is not None and sun_b is not None
    assert np.degrees(np.arccos(np.clip(sun_a @ sun_b, -1, 1))) > 10.0  # the sun moved between the passes
    qs = []
    for k in (5, 20, 35, 48):
        a, b = (window_stats(make_thumbnail(seq.render(i, with_depth=False).left), 16) for i in (k, k + 250))
        qs.append(similarity_q(a, b))
    assert max(qs) < 0.95 and float(np.median(qs)) <= 0.7, qs


# ------------------------------------------------------------------ figures across frame gaps
def test_figures_across_a_frame_gap_count_only_the_parts_that_ran():
    """Frames 0-149 and 1000-1149, the ground truth of the second part going on where the first
    ended (the way between is unknown), the odometry 1 % long and 8.5 m off after the gap:
    path length, end drift and t_rel are the two parts' own (298 m, 1 %, about 1 %); taken as
    one drive the same rows would read a 3.9 % end drift."""
    from snaps_graph.evaluation.metrics import evaluate, path_length

    ids = np.r_[0:150, 1000:1150]
    gt = np.tile(np.eye(4), (len(ids), 1, 1))
    gt[:, 2, 3] = np.r_[0:150, 150:300] * 1.0  # 1 m per frame along z
    est = gt.copy()
    est[:150, 2, 3] *= 1.01
    est[150:, 2, 3] = est[149, 2, 3] + 8.5 + (gt[150:, 2, 3] - gt[149, 2, 3]) * 1.01
    assert path_length(gt, ids) == pytest.approx(298.0)
    m = evaluate(est, gt, ids)
    assert m["parts"] == 2 and m["path_length_m"] == pytest.approx(298.0)
    assert m["end_drift_percent"] == pytest.approx(1.0, rel=1e-9)
    assert m["t_rel"] == pytest.approx(1.0, rel=0.02)  # segments of 100 m inside each part
    whole = evaluate(est, gt)  # no frame numbers: one drive, the gap's 8.5 m counted as drift
    assert "parts" not in whole and whole["end_drift_percent"] > 3.5


def test_real_revisit_at_one_percent_prints_about_one_percent_end_drift(tmp_path):
    """The README's revisit: odometry drifted by 1 % (`snaps-graph drift`) over KITTI 00's frames
    100-230 and 1540-1660, 1064 m driven between them. Counted over the parts that ran, the
    odometry's end drift reads 0.8-1.2 % (it read 8.91 % when the gap was a 69 m jump)."""
    loop = SHARED_DATA / "kitti00_loop"
    if not loop.is_dir():
        pytest.skip(f"the real revisit is not at {loop}")
    drifted = tmp_path / "drifted.txt"
    proc = _sg(tmp_path, "drift", str(loop / "poses" / "00.txt"), "--out", str(drifted), "--seed", "0", "--pct", "1")
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "revisit"
    args = ["run", str(loop / "sequences" / "00"), "--odometry", str(drifted), "-o", str(run), "--loops", "none"]
    proc = _sg(tmp_path, *args)
    assert proc.returncode == 0, proc.stderr
    vo = json.loads((run / "metrics.json").read_text())["trajectories"]["vo"]
    assert vo["parts"] == 2
    assert 0.8 <= vo["end_drift_percent"] <= 1.2, vo["end_drift_percent"]
    assert 150.0 < vo["path_length_m"] < 180.0  # 76 m + 91 m of driving in the two parts


# ------------------------------------------------------------------ help and messages
def test_help_shows_no_type_names_for_flags_or_set(tmp_path):
    for args in (["-h"], ["run", "-h"], ["demo", "-h"], ["batch", "-h"], ["synth", "-h"]):
        proc = _sg(tmp_path, *args)
        assert proc.returncode == 0, proc.stderr
        assert "<bool>" not in proc.stdout and "<list[str]>" not in proc.stdout, (args, proc.stdout)
    run_help = " ".join(_sg(tmp_path, "run", "-h").stdout.split())
    assert "--set SECTION.KEY=VALUE" in run_help
    assert "--overwrite" in run_help


def test_short_version_flag(tmp_path):
    from snaps_graph import __version__

    proc = _sg(tmp_path, "-V")
    assert proc.returncode == 0 and proc.stdout.strip() == f"snaps-graph {__version__}", proc.stderr


def test_odometry_run_report_names_the_pose_file(tiny_seq, tmp_path):
    """In an --odometry run the "vo" poses are the given file's: the report says so, never
    "pure visual odometry"."""
    odo = tmp_path / "my_odometry.txt"
    odo.write_text((tiny_seq / "poses.txt").read_text())
    proc = _sg(tmp_path, "run", str(tiny_seq), "--odometry", str(odo), "-o", "r", "--frames", "0:6")
    assert proc.returncode == 0, proc.stderr
    assert _sg(tmp_path, "compare", "r").returncode == 0
    report = (tmp_path / "r" / "report.md").read_text()
    assert "pure visual odometry" not in report and "my_odometry.txt" in report
    proc = _sg(tmp_path, "run", str(tiny_seq), "-o", "s", "--frames", "0:4")
    assert proc.returncode == 0 and _sg(tmp_path, "compare", "s").returncode == 0
    assert "pure visual odometry" in (tmp_path / "s" / "report.md").read_text()  # our own VO's run


def test_compare_on_a_folder_holding_the_run_names_it(tiny_seq, tmp_path):
    """`compare results/demo` (the demo writes its run in results/demo/run) points to the run."""
    proc = _sg(tmp_path, "run", str(tiny_seq), "-o", "demo/run", "--frames", "0:4")
    assert proc.returncode == 0, proc.stderr
    for command in ("compare", "loops"):
        proc = _sg(tmp_path, command, "demo")
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert f"the run is in {Path('demo') / 'run'}" in proc.stderr, proc.stderr


def test_eval_takes_the_whole_ground_truth_for_part_of_a_sequence(tiny_seq, tmp_path):
    """The official ground-truth file holds every frame; a run of frames 2-6 is scored on those
    (re-based to the first), exactly as against the run's own poses_gt.txt."""
    proc = _sg(tmp_path, "run", str(tiny_seq), "-o", "part", "--frames", "2:7")
    assert proc.returncode == 0, proc.stderr
    full = _sg(tmp_path, "eval", "part/poses_vo.txt", "--gt", str(tiny_seq / "poses.txt"), "--json")
    own = _sg(tmp_path, "eval", "part/poses_vo.txt", "--gt", "part/poses_gt.txt", "--json")
    assert full.returncode == 0 and own.returncode == 0, full.stderr + own.stderr
    assert "frames (2-6)" in full.stderr
    a, b = json.loads(full.stdout), json.loads(own.stdout)
    for key in ("mean_deviation", "ate_rmse", "end_drift_percent"):
        assert a[key] == pytest.approx(b[key], abs=1e-9), key
    loose = tmp_path / "loose.txt"  # a pose file outside a run folder: no frames known, refused
    loose.write_text((tmp_path / "part" / "poses_vo.txt").read_text())
    proc = _sg(tmp_path, "eval", str(loose), "--gt", str(tiny_seq / "poses.txt"))
    assert proc.returncode == 2 and "poses_gt.txt" in proc.stderr


def test_process_after_finish_says_the_pipeline_is_finished(tiny_seq):
    from snaps_graph.config import Config
    from snaps_graph.datasets.kitti import KittiSequence
    from snaps_graph.errors import SnapsGraphError
    from snaps_graph.pipeline import SlamPipeline

    seq = KittiSequence(tiny_seq)
    slam = SlamPipeline(seq.camera, Config(), loops="none", refine="none")
    for i in range(3):
        slam.process(seq[i])
    slam.finish()
    with pytest.raises(SnapsGraphError, match="finished"):
        slam.process(seq[3])


def test_ctrl_c_over_an_earlier_run_with_overwrite_says_it_was_kept(bin_dir, tiny_seq, tmp_path):
    import shutil
    import signal
    import time

    seq = tmp_path / "seq"
    shutil.copytree(tiny_seq, seq)
    for side in ("image_0", "image_1"):  # the 8 pairs repeated (hard links): a run that lasts
        src = sorted((seq / side).glob("*.png"))
        for i in range(len(src), 3000):
            os.link(src[i % len(src)], seq / side / f"{i:06d}.png")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(3000)))
    (seq / "poses.txt").unlink()
    assert _sg(tmp_path, "run", str(seq), "-o", "old", "--frames", "0:4").returncode == 0
    before = (tmp_path / "old" / "poses_vo.txt").read_text()
    proc = subprocess.Popen(
        ["snaps-graph", "run", str(seq), "-o", "old", "--overwrite"],
        cwd=tmp_path,
        env=_env(bin_dir),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".old.tmp-*")) and time.monotonic() < deadline:  # frames being processed
        assert proc.poll() is None, "the run ended before it could be interrupted"
        time.sleep(0.05)
    time.sleep(0.5)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "no results written" not in stderr and "earlier results in old are kept" in stderr, stderr
    assert (tmp_path / "old" / "poses_vo.txt").read_text() == before


# ------------------------------------------------------------------ pictures
def test_trajectory_picture_notes_lines_that_coincide(tmp_path):
    from snaps_graph.evaluation.plots import coinciding, plot_trajectories
    from snaps_graph.synth import builtin_loop_trajectory

    gt = builtin_loop_trajectory(120)
    vo = gt.copy()
    vo[:, 0, 3] += np.linspace(0.0, 2.0, len(gt))  # drifts sideways
    snaps = vo.copy()
    snaps[:, 2, 3] += 1e-4  # no loop corrected anything: on the odometry
    isam2 = gt.copy()
    same = coinciding({"gt": gt, "vo": vo, "snaps": snaps, "isam2": isam2})
    assert set(same) == {"snaps"} and same["snaps"][0] == "vo" and same["snaps"][1] == pytest.approx(1e-4)
    png = plot_trajectories(tmp_path / "t.png", {"gt": gt, "vo": vo, "snaps": snaps, "isam2": isam2}, loops=[(110, 5)])
    assert png.stat().st_size > 10_000


def test_mesh_picture_projection_is_upright_and_turned_as_the_top_view():
    """The perspective picture looks from -z with x to the right and the far side up, as the top
    view does; the axes drawn on it are projected through the picture's own rays."""
    import open3d as o3d

    from snaps_graph.mapping.render import _project, _round_length

    eye, centre = np.array([0.0, -30.0, -60.0]), np.zeros(3)
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        fov_deg=50.0, center=centre.tolist(), eye=eye.tolist(), up=[0.0, 1.0, 0.0], width_px=400, height_px=240
    ).numpy()
    uv = _project(rays, np.array([centre, [10.0, 0.0, 0.0], [0.0, 0.0, 10.0]]))
    assert np.allclose(uv[0], [199.5, 119.5], atol=1.0)  # the centre in the middle
    assert uv[1, 0] > uv[0, 0] + 20  # +x to the right
    assert uv[2, 1] < uv[0, 1] - 5  # +z (away from the eye) up the picture
    hit = rays[int(round(uv[1, 1])), int(round(uv[1, 0]))]
    d = np.array([10.0, 0.0, 0.0]) - hit[:3]
    assert np.degrees(np.arccos(d @ hit[3:] / np.linalg.norm(d) / np.linalg.norm(hit[3:]))) < 0.5  # the pixel's ray passes it
    assert [_round_length(x) for x in (0.05, 3.0, 17.0, 240.0)] == [0.1, 2.0, 10.0, 200.0]
