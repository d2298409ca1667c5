"""The configuration explains itself: every key's help and range beside it, printed by
``snaps-graph config`` as TOML comments that load back; the paper's preset; settings that are
constants in the code now still load from an older config with a note."""

from __future__ import annotations

import dataclasses
import importlib
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from snaps_graph.config import FIXED, RETIRED, RULES, Config
from snaps_graph.errors import SnapsGraphError

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "snaps_graph.cli"]
SECTIONS = ("frontend", "loop", "graph", "map", "odometry")


def cli(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, env=env, timeout=timeout, cwd=ROOT)


def _keys(cfg: Config) -> list[str]:
    return [f"{s}.{f.name}" for s in SECTIONS for f in dataclasses.fields(getattr(cfg, s))]


def test_config_prints_every_key_with_a_comment_and_loads_back(tmp_path):
    proc = cli("config")
    assert proc.returncode == 0, proc.stderr
    section = ""
    commented = set()
    for line in proc.stdout.splitlines():
        if line.startswith("["):
            section = line.strip("[]") + "."
        elif line.strip():
            key, _, rest = line.partition(" = ")
            value, sep, comment = rest.partition("  # ")
            assert sep and comment.strip(), f"no comment on {section}{key}: {line!r}"
            commented.add(section + key)
    assert commented == set(_keys(Config())) | {"loops"}
    data = tomllib.loads(proc.stdout)  # the comments leave it TOML
    assert data == Config().to_dict()
    path = tmp_path / "x.toml"
    path.write_text(proc.stdout)
    assert Config.load(path) == Config()


def test_a_numeric_comment_states_the_range():
    text = Config().dumps(comments=True)
    assert "num_disparities = 128  # BM/SGBM disparity search range, px; a multiple of 16 and in [16, 1024]" in text
    assert 'mode = "klt"  #' in text and '; one of "sift", "orb", "klt"' in text
    assert "[16, 1024]" not in Config().dumps()  # a run's config.toml stays bare


def test_config_keys_are_at_most_120_and_each_has_help():
    cfg = Config()
    keys = _keys(cfg)
    assert len(keys) <= 120, len(keys)
    for s in SECTIONS:
        for f in dataclasses.fields(getattr(cfg, s)):
            assert f.metadata.get("help"), f"{s}.{f.name} has no help"
    assert set(RULES) <= set(keys)
    assert not set(FIXED) & set(keys) and not set(RETIRED) & set(keys)


# where each setting that became a constant lives now
_HOMES = (
    "snaps_graph.frontend.depth",
    "snaps_graph.frontend.tracking",
    "snaps_graph.frontend.odometry",
    "snaps_graph.frontend.features",
    "snaps_graph.frontend.motion",
    "snaps_graph.frontend.keyframe",
    "snaps_graph.frontend.loop_features",
    "snaps_graph.frontend.lba_schedule",
    "snaps_graph.backend.pose_graph",
    "snaps_graph.backend.noise",
)


@pytest.mark.parametrize("key", sorted(FIXED))
def test_a_fixed_setting_is_the_constant_the_code_uses(key):
    name = key.split(".")[1].upper()
    homes = [m for m in _HOMES if name in vars(importlib.import_module(m))]
    assert homes, f"{name} is not a constant in {_HOMES}"
    value = getattr(importlib.import_module(homes[0]), name)
    assert value == FIXED[key] and type(value) is type(FIXED[key])


def test_an_old_config_with_a_fixed_setting_loads_with_a_note(tmp_path, capsys):
    path = tmp_path / "old.toml"
    path.write_text("[frontend]\nstereo_window_px = 11\nklt_levels = 5\n[graph]\nrobust_param = 3.0\n")
    cfg = Config.load(path)
    err = capsys.readouterr().err
    assert cfg == Config()
    assert "frontend.stereo_window_px is no longer a setting (fixed at 11)" in err
    assert "frontend.klt_levels is no longer a setting: it is fixed at 3 now, this file's 5 is ignored" in err
    assert "graph.robust_param is no longer a setting (fixed at 3.0)" in err


PAPER = {
    "frontend": dict(mode="sift", sift_first_octave=-1, disparity="bm_wls", motion="pnp", local_ba=False),
    "loop": dict(
        search="radius",
        discount_window="fixed",
        discount_shape="paper",
        discount_length=100,
        correction_axes="xyz",
        correction_rotation="none",
        use_verified_offset=False,
        correction_weight="q",
        require_verification=False,
        min_similarity=0.75,
        window=8,
        radius_m=10.0,
    ),
}


def test_the_paper_preset_runs_with_the_papers_choices(tiny_seq, tmp_path):
    preset = ROOT / "configs" / "paper.toml"
    proc = cli("run", tiny_seq, "-o", tmp_path / "run", "-c", preset)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    used = Config.load(tmp_path / "run" / "config.toml")  # the configuration the run dumped
    for section, values in PAPER.items():
        for key, value in values.items():
            assert getattr(getattr(used, section), key) == value, f"{section}.{key}"
    assert (tmp_path / "run" / "poses_snaps.txt").stat().st_size > 0


def test_set_overrides_are_parsed_as_toml_and_checked():
    cfg = Config().with_overrides(["loop.attempts=3", 'loop.search="radius"', "loop.correction_axes=xyz", "map.enabled=true"])
    assert (cfg.loop.attempts, cfg.loop.search, cfg.loop.correction_axes, cfg.map.enabled) == (3, "radius", "xyz", True)
    assert Config().loop.attempts != 3  # a copy: the defaults are untouched
    for bad, why in (
        ("loop.attempts", "expected section.key=value"),
        ("attempts=3", "expected section.key=value"),
        ("loop.atempts=3", "did you mean"),
        ("loop.attempts=-1", "loop.attempts"),
    ):
        with pytest.raises(SnapsGraphError, match=why):
            Config().with_overrides([bad])


def test_run_set_beats_the_config_file_and_lands_in_the_results(tiny_seq, tmp_path):
    file = tmp_path / "c.toml"
    file.write_text("[loop]\nattempts = 7\nmin_similarity = 0.2\n")
    out = tmp_path / "out"
    r = cli("run", tiny_seq, "-o", out, "-c", file, "--set", "loop.attempts=2", "--frames", "0:3")
    assert r.returncode == 0, r.stderr
    ran = Config.load(out / "config.toml")
    assert ran.loop.attempts == 2 and ran.loop.min_similarity == 0.2
    r = cli("run", tiny_seq, "-o", tmp_path / "o2", "--set", "loop.atempts=2")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "did you mean" in r.stderr and "--set" in r.stderr
    assert not (tmp_path / "o2").exists()
