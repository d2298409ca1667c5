"""A newcomer's first session: the README's quick-start commands run as written on the shared
clips, the CLI's habits (-h, --version, -o, -c), `config` as commented TOML, .tum files on the
input's clock, and report.md linking only files that exist.

The quick start is read from README.md itself (its "Quick start" code block), so the test fails
when the README drifts from the tool. Data paths map to the shared clips (``DATA/kitti/...`` to
../shared/data/kitti/..., ``DATA/euroc/V1_01_easy`` to the EuRoC clip, ``recording.bag`` to a bag
written from the KITTI clip); a ``run`` without ``--frames`` gets ``--frames 0:12`` to keep the
test within seconds. Lines naming data the test cannot stand in for are skipped and listed."""

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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from bagutil import write_stereo_bag  # noqa: E402
from conftest import SHARED_DATA  # noqa: E402

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


def _sg(bin_dir: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["snaps-graph", *args], cwd=cwd, env=_env(bin_dir), capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def quickstart(bin_dir, tmp_path_factory):
    """Runs the quick start in a fresh folder: (folder, {line: completed process}, skipped lines)."""
    if not KITTI06.is_dir() or not EUROC.is_dir():
        pytest.skip(f"the shared clips are not at {SHARED_DATA} (CI has them; a user's clone lacks ../shared)")
    work = tmp_path_factory.mktemp("newcomer")
    from snaps_graph.datasets.kitti import KittiSequence

    write_stereo_bag(work / "recording.bag", KittiSequence(KITTI06), "ros1", n=N_FRAMES)
    stand_ins = {"DATA/kitti/sequences/06": str(KITTI06), "DATA/euroc/V1_01_easy": str(EUROC)}
    done, skipped = {}, []
    for line in _quickstart_lines():
        if line.startswith(".") or "rosbag2_dir" in line or "results/demo" in line:
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
        done[line] = subprocess.run(["bash", "-c", cmd], cwd=work, env=_env(bin_dir), capture_output=True, text=True, timeout=300)
    return work, done, skipped


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
    np.testing.assert_allclose(_tum_stamps(res / "bag" / "poses_vo.tum"), BAG_BASE_S + kitti_t, rtol=0, atol=1e-6)


def test_report_links_only_files_it_wrote(quickstart):
    work, _, _ = quickstart
    run = work / "results" / "kitti06"
    links = re.findall(r"\]\(([^)#\s]+)\)", (run / "report.md").read_text())
    assert links, "report.md links nothing"
    missing = [link for link in links if not link.startswith("http") and not (run / link).exists()]
    assert not missing, f"report.md links files that do not exist: {missing}"


def test_help_version_and_short_options(bin_dir, tiny_seq, tmp_path):
    for args in (["-h"], ["--help"], ["run", "-h"], ["demo", "-h"]):
        proc = _sg(bin_dir, tmp_path, *args)
        assert proc.returncode == 0 and "Usage" in proc.stdout, f"{args}: {proc.stderr}"
    from snaps_graph import __version__

    proc = _sg(bin_dir, tmp_path, "--version")
    assert proc.returncode == 0 and __version__ in proc.stdout
    cfg = tmp_path / "c.toml"
    cfg.write_text(_sg(bin_dir, tmp_path, "config").stdout)
    proc = _sg(bin_dir, tmp_path, "run", str(tiny_seq), "-o", "r", "-c", str(cfg), "--frames", "0:4")
    assert proc.returncode == 0, proc.stderr
    assert len(np.loadtxt(tmp_path / "r" / "poses_vo.txt")) == 4


def _config_text(bin_dir: Path, cwd: Path) -> str:
    proc = _sg(bin_dir, cwd, "config")
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_config_output_is_toml(bin_dir, tmp_path):
    parsed = tomllib.loads(_config_text(bin_dir, tmp_path))
    assert "loop" in parsed and "frontend" in parsed


def test_config_every_key_has_a_comment(bin_dir, tmp_path):
    lines = _config_text(bin_dir, tmp_path).splitlines()
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
