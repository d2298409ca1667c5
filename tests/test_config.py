"""The configuration explains itself: every key's help and range beside it, printed by
``snaps-graph config`` as TOML comments that load back; at most 40 keys, each a user's choice;
presets by name that compose with a file and ``--set`` in one order; the previous version's
config.toml still loads, each key that became a constant with a note, and every such constant
holds the value that key had."""

from __future__ import annotations

import importlib
import re
import sys
import tomllib
from pathlib import Path

import pytest
from inprocess import Ran
from inprocess import cli as run_cli

from snaps_graph.config import PRESETS, RULES, Config, parse_set
from snaps_graph.config_retired import OLD_KEYS, Moved
from snaps_graph.config_schema import settings
from snaps_graph.errors import SnapsGraphError

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "snaps_graph.cli"]
PREVIOUS = ROOT / "tests" / "data" / "config_previous_version.toml"  # what the version before wrote


def cli(*args) -> Ran:
    return run_cli(*args, cwd=ROOT)  # in this process (tests/inprocess.py)


def _keys(cfg: Config) -> list[str]:
    """Every setting's dotted key ("frontend.mode"), the top-level ``loops`` too."""
    return [key for key, _, _ in settings(cfg)]


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
    assert commented == set(_keys(Config()))
    data = tomllib.loads(proc.stdout)  # the comments leave it TOML
    assert data == Config().to_dict()
    path = tmp_path / "x.toml"
    path.write_text(proc.stdout)
    assert Config.load(path) == Config()


def test_a_numeric_comment_states_the_range():
    text = Config().dumps(comments=True)
    assert "num_disparities = 128  # BM/SGBM disparity search range" in text and "a multiple of 16 and in [16, 1024]" in text
    assert 'mode = "klt"  #' in text and '; one of "sift", "orb", "klt"' in text
    assert "[16, 1024]" not in Config().dumps()  # a run's config.toml stays bare


def test_at_most_40_keys_each_with_help():
    keys = _keys(Config())
    budget = {"frontend": 11, "graph": 6, "map": 7, "odometry": 5}  # and the top-level loops
    for section, most in budget.items():
        assert len([k for k in keys if k.startswith(section + ".")]) <= most, section
    assert len([k for k in keys if "." not in k]) == 1  # loops
    assert len(keys) <= 40, len(keys)  # [loop] + [verification] in at most 9
    for key, f, _ in settings(Config()):
        assert f.metadata.get("help"), f"{key} has no help"
    assert set(RULES) <= set(keys)


def test_old_keys_are_gone_and_moved_ones_are_real_settings():
    keys = set(_keys(Config()))
    assert not set(OLD_KEYS) & keys
    assert {m.to for m in OLD_KEYS.values() if isinstance(m, Moved)} <= keys


def test_the_previous_versions_config_loads_to_the_defaults_with_a_note_per_key(capsys):
    """A results folder's config.toml of the version before: every key that became a constant or
    an evaluation option is one note line, every moved one is applied; the same run."""
    assert Config.load(PREVIOUS) == Config()
    err = capsys.readouterr().err
    previous = tomllib.loads(PREVIOUS.read_text())
    old = [k for k in OLD_KEYS if _value(previous, k) is not None]
    assert len(old) == len(OLD_KEYS)
    for key in old:
        assert f"note: {PREVIOUS}: {key} " in err, key
    assert err.count("\n") == len(old)


def _value(data: dict, key: str):
    for part in key.split("."):
        if not isinstance(data, dict) or part not in data:
            return None
        data = data[part]
    return data


@pytest.mark.parametrize("key", sorted(k for k, v in OLD_KEYS.items() if isinstance(v, str) and " in snaps_graph/" in v))
def test_a_setting_that_became_a_constant_keeps_its_value(key):
    """The constant the note names holds the value the previous version's default had: a config
    that set nothing runs as it did."""
    name, path = re.fullmatch(r"(\S+) in snaps_graph/(\S+)\.py", str(OLD_KEYS[key])).groups()  # type: ignore[union-attr]
    obj = importlib.import_module("snaps_graph." + path.replace("/", "."))
    for part in name.split("."):
        obj = getattr(obj, part)
    before = _value(tomllib.loads(PREVIOUS.read_text()), key)
    assert obj == before and type(obj) is type(before), (key, obj, before)


def test_an_old_key_in_a_file_is_a_note_and_a_moved_one_applies(tmp_path, capsys):
    path = tmp_path / "old.toml"
    path.write_text(
        '[frontend]\nmode = "orb"\nmin_inliers = 30\n[frontend.klt]\nwindow_px = 7\n'
        '[frontend.local_ba]\nenabled = false\nevery = 2\n[frontend.offset]\npx = 0.3\n[map]\nworld_mesh = "w.ply"\n'
    )
    cfg = Config.load(path)
    err = capsys.readouterr().err
    assert (cfg.frontend.mode, cfg.frontend.local_ba, cfg.frontend.offset_px) == ("orb", False, 0.3)
    assert (
        f"note: {path}: frontend.min_inliers = 30 is no longer a setting (MIN_INLIERS in snaps_graph/frontend/motion.py); ignored\n"
        in err
    )
    assert f"note: {path}: frontend.local_ba.enabled moved to frontend.local_ba\n" in err
    assert 'map.world_mesh = "w.ply" is no longer a setting (an evaluation option: run --world-mesh' in err
    assert err.count("\n") == 6
    both = tmp_path / "both.toml"
    both.write_text("[frontend]\noffset_px = 0.2\n[frontend.offset]\npx = 0.3\n")
    with pytest.raises(SnapsGraphError, match="frontend.offset.px and frontend.offset_px are the same setting"):
        Config.load(both)
    assert Config().with_overrides(["frontend.offset.px=0.25"]).frontend.offset_px == 0.25  # --set too


def test_set_overrides_are_parsed_as_toml_and_checked():
    cfg = Config().with_overrides(["map.keyframe_every=3", 'graph.refine="batch"', "frontend.mode=orb", "map.enabled=true"])
    assert (cfg.map.keyframe_every, cfg.graph.refine, cfg.frontend.mode, cfg.map.enabled) == (3, "batch", "orb", True)
    assert Config().map.keyframe_every != 3  # a copy: the defaults are untouched
    assert parse_set(["frontend.offset.px=1", "frontend.mode=orb"]) == {"frontend": {"offset": {"px": 1}, "mode": "orb"}}
    for bad, why in (
        ("map.keyframe_every", "expected section.key=value"),
        ("keyframe_every=3", "expected section.key=value"),
        ("map.keyframe_evry=3", r"did you mean 'map\.keyframe_every'\?"),
        ("map.keyframe_every=0", r"map\.keyframe_every must be in"),
        ("frontend.mode.x=3", r"\[frontend\.mode\] is not a section"),
        ("frontnd.mode=orb", r"unknown key 'frontnd' \(did you mean 'frontend'\?\)"),
        ("frontend.min_depth_m=90", r"frontend\.min_depth_m must be < frontend\.max_depth_m"),
        ("frontend..mode=orb", "expected section.key=value"),
    ):
        with pytest.raises(SnapsGraphError, match=why):
            Config().with_overrides([bad])
    with pytest.raises(SnapsGraphError, match="is a value, not a section"):
        parse_set(["frontend.mode=3", "frontend.mode.x=9"])


def test_a_config_dumped_and_loaded_is_the_same_config(tmp_path):
    cfg = Config().with_overrides(["frontend.offset_px=0.25", 'graph.robust_kernel="huber"', "map.depth_scale=1.0"])
    text = cfg.dumps(comments=True)
    assert tomllib.loads(text) == cfg.to_dict()
    for comments in (False, True):
        path = tmp_path / f"c{comments}.toml"
        path.write_text(cfg.dumps(comments=comments))
        assert Config.load(path) == cfg
    path = tmp_path / "dumped.toml"
    cfg.dump(path)
    assert Config.load(path).dumps() == cfg.dumps()


PAPER_FRONTEND = {"mode": "sift", "sift_first_octave": -1, "disparity": "bm_wls", "motion": "pnp", "local_ba": False}


def test_presets_by_name_and_their_order_with_a_file_and_set(tmp_path):
    assert Config.preset("default") == Config() and set(PRESETS) == {"default", "paper"}
    paper = Config.preset("paper")
    assert {k: getattr(paper.frontend, k) for k in PAPER_FRONTEND} == PAPER_FRONTEND
    assert (paper.loop.policy, paper.loop.min_similarity, paper.loop.window) == ("paper", 0.75, 8)
    file = tmp_path / "c.toml"
    file.write_text('[frontend]\nmode = "orb"\nthreads = 1\n')
    cfg = Config.compose("paper", file, ["frontend.threads=3"])  # the preset, then the file, then --set
    assert (cfg.frontend.mode, cfg.frontend.disparity, cfg.frontend.threads) == ("orb", "bm_wls", 3)
    with pytest.raises(SnapsGraphError, match="unknown preset 'papr'"):
        Config.preset("papr")


def test_run_with_the_paper_preset_dumps_its_choices(tiny_seq, tmp_path):
    proc = cli("run", tiny_seq, "-o", tmp_path / "run", "--preset", "paper", "--set", "map.keyframe_every=2", "--frames", "0:4")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    used = Config.load(tmp_path / "run" / "config.toml")  # the configuration the run dumped
    assert {k: getattr(used.frontend, k) for k in PAPER_FRONTEND} == PAPER_FRONTEND
    assert used.map.keyframe_every == 2
    proc = cli("config", "--preset", "paper")
    assert proc.returncode == 0 and 'disparity = "bm_wls"' in proc.stdout


def test_run_set_beats_the_config_file_and_lands_in_the_results(tiny_seq, tmp_path):
    file = tmp_path / "c.toml"
    file.write_text("[map]\nkeyframe_every = 7\nmax_range_m = 12.0\n")
    out = tmp_path / "out"
    r = cli("run", tiny_seq, "-o", out, "-c", file, "--set", "map.keyframe_every=2", "--frames", "0:3")
    assert r.returncode == 0, r.stderr
    ran = Config.load(out / "config.toml")
    assert ran.map.keyframe_every == 2 and ran.map.max_range_m == 12.0
    r = cli("run", tiny_seq, "-o", tmp_path / "o2", "--set", "map.keyframe_evry=2")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "did you mean" in r.stderr and "--set" in r.stderr
    assert not (tmp_path / "o2").exists()


def test_a_batch_plan_takes_a_preset_under_its_variants(tiny_seq):
    from snaps_graph.batch.plan import plan_from_dict

    plan = plan_from_dict({"sequences": [str(tiny_seq)], "preset": "paper", "variants": {"orb": {"frontend": {"mode": "orb"}}}})
    cfg = plan.cells[0].cfg
    assert (cfg.frontend.mode, cfg.frontend.disparity, cfg.frontend.local_ba) == ("orb", "bm_wls", False)
    with pytest.raises(SnapsGraphError, match="preset: unknown preset 'fast'"):
        plan_from_dict({"sequences": [str(tiny_seq)], "preset": "fast"})
