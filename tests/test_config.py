"""The configuration explains itself: every key's help and range beside it, printed by
``snaps-graph config`` as TOML comments that load back, nested sections as their own tables; the
paper's preset; settings that are constants in the code now, and keys that moved to a nested
section, still load from an older config with a note."""

from __future__ import annotations

import importlib
import sys
import tomllib
from pathlib import Path

import pytest
from inprocess import Ran
from inprocess import cli as run_cli

from snaps_graph.config import FIXED, MOVED, RETIRED, RULES, Config, parse_set
from snaps_graph.config_schema import settings
from snaps_graph.errors import SnapsGraphError

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "snaps_graph.cli"]


def cli(*args) -> Ran:
    return run_cli(*args, cwd=ROOT)  # in this process (tests/inprocess.py)


def _keys(cfg: Config) -> list[str]:
    """Every setting's dotted key ("frontend.klt.window_px"), the top-level ``loops`` too."""
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
    assert "num_disparities = 128  # BM/SGBM disparity search range, px; a multiple of 16 and in [16, 1024]" in text
    assert 'mode = "klt"  #' in text and '; one of "sift", "orb", "klt"' in text
    assert "[16, 1024]" not in Config().dumps()  # a run's config.toml stays bare


def test_config_keys_are_at_most_120_and_each_has_help():
    cfg = Config()
    keys = _keys(cfg)
    assert len([k for k in keys if "." in k]) <= 120, len(keys)  # in the sections (beside the top-level loops)
    for key, f, _ in settings(cfg):
        assert f.metadata.get("help"), f"{key} has no help"
    assert set(RULES) <= set(keys)
    assert not set(FIXED) & set(keys) and not set(RETIRED) & set(keys) and not set(MOVED) & set(keys)


# where each setting that became a constant lives now
_HOMES = (
    "snaps_graph.frontend.depth",
    "snaps_graph.frontend.tracking",
    "snaps_graph.frontend.odometry",
    "snaps_graph.frontend.features",
    "snaps_graph.frontend.motion",
    "snaps_graph.frontend.keyframe",
    "snaps_graph.verification.features",
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
    "frontend": {"mode": "sift", "sift_first_octave": -1, "disparity": "bm_wls", "motion": "pnp", "local_ba.enabled": False},
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
            obj = used
            for part in f"{section}.{key}".split("."):
                obj = getattr(obj, part)
            assert obj == value, f"{section}.{key}"
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


def test_nested_sections_are_toml_tables_that_load_back_exactly(tmp_path):
    """``[frontend.klt]`` etc. are tables of their own in the dump, help comments included; a
    changed config dumped and loaded is the same config, and to_dict stays nested."""
    cfg = Config().with_overrides(["frontend.klt.window_px=9", "frontend.offset.px=0.25", 'verification.detector="sift"'])
    text = cfg.dumps(comments=True)
    for table in (
        "[frontend]",
        "[frontend.klt]",
        "[frontend.stereo_ba]",
        "[frontend.local_ba]",
        "[frontend.offset]",
        "[verification]",
    ):
        assert f"\n{table}\n" in text
    assert "window_px = 9  # KLT window, px; in [3, 101]" in text
    assert tomllib.loads(text) == cfg.to_dict()
    assert cfg.to_dict()["frontend"]["klt"]["window_px"] == 9
    for comments in (False, True):
        path = tmp_path / f"c{comments}.toml"
        path.write_text(cfg.dumps(comments=comments))
        assert Config.load(path) == cfg
    path = tmp_path / "dumped.toml"
    cfg.dump(path)
    assert Config.load(path).dumps() == cfg.dumps()


def test_moved_keys_are_real_settings_and_each_old_one_is_gone():
    keys = set(_keys(Config()))
    assert set(MOVED.values()) <= keys
    assert len(set(MOVED.values())) == len(MOVED)
    assert not set(MOVED) & (set(RETIRED) | set(FIXED))


def test_an_old_flat_config_is_applied_at_the_new_places_with_a_note(tmp_path, capsys):
    """An older version's config.toml (a results folder's) runs as it did: each moved key's value
    lands at its new place, with one note line each."""
    path = tmp_path / "old.toml"
    path.write_text(
        "[frontend]\nklt_window_px = 13\nklt_bias_window_px = 5\nlocal_ba = false\nlba_every = 2\nsba_huber_px = 0.4\n"
        "disparity_offset_px = 0.3\nestimate_disparity_offset = false\nloop_features = 400\n"
        'loop_detector = "sift"\nloop_max_distance_m = 6.0\nmode = "klt"\n[loop]\nattempts = 4\n'
    )
    cfg = Config.load(path)
    err = capsys.readouterr().err
    fe, v = cfg.frontend, cfg.verification
    assert (fe.klt.window_px, fe.klt.bias_window_px, fe.local_ba.enabled, fe.local_ba.every) == (13, 5, False, 2)
    assert (fe.stereo_ba.huber_px, fe.offset.px, fe.offset.estimate, fe.frame_features) == (0.4, 0.3, False, 400)
    assert (v.detector, v.max_distance_m, cfg.loop.attempts) == ("sift", 6.0, 4)
    assert f"note: {path}: frontend.klt_window_px moved to frontend.klt.window_px\n" in err
    assert f"note: {path}: frontend.local_ba moved to frontend.local_ba.enabled\n" in err
    assert f"note: {path}: frontend.loop_detector moved to verification.detector\n" in err
    assert err.count("\n") == 10 and err.count("moved to") == 10
    both = tmp_path / "both.toml"
    both.write_text("[frontend]\nklt_window_px = 13\n[frontend.klt]\nwindow_px = 9\n")
    with pytest.raises(SnapsGraphError, match="frontend.klt_window_px and frontend.klt.window_px are the same setting"):
        Config.load(both)


def test_an_old_results_folder_config_reads_back(tmp_path, capsys):
    """A config.toml as older versions wrote it (every key flat) loads to the defaults it held."""
    old = {"frontend": {}, "verification": {}}
    for old_key, new_key in MOVED.items():
        obj = Config()
        for part in new_key.split("."):
            obj = getattr(obj, part)
        old["frontend"][old_key.split(".")[1]] = obj
    lines = ["[frontend]"] + [f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v)}" for k, v in old["frontend"].items()]
    path = tmp_path / "config.toml"
    path.write_text("\n".join(lines) + "\n")
    assert Config.load(path) == Config()
    assert capsys.readouterr().err.count("moved to") == len(MOVED)


def test_set_reaches_nested_sections_and_old_keys():
    cfg = Config().with_overrides(["frontend.klt.window_px=13", 'verification.detector="sift"', "frontend.local_ba.every=2"])
    assert (cfg.frontend.klt.window_px, cfg.verification.detector, cfg.frontend.local_ba.every) == (13, "sift", 2)
    assert parse_set(["frontend.klt.window_px=13", "frontend.mode=orb"]) == {
        "frontend": {"klt": {"window_px": 13}, "mode": "orb"}
    }
    assert Config().with_overrides(["frontend.klt_window_px=13"]).frontend.klt.window_px == 13  # an old key, with a note
    for bad, why in (
        ("frontend.klt.windw_px=3", r"unknown key 'frontend\.klt\.windw_px' \(did you mean 'frontend\.klt\.window_px'\?\)"),
        ("frontend.kl.window_px=3", r"unknown key 'frontend\.kl' \(did you mean 'frontend\.klt'\?\)"),
        ("frontend.window_px=3", r"did you mean 'frontend\.klt\.window_px'\?"),
        ("verification.detectr=orb", r"did you mean 'verification\.detector'\?"),
        ("frontend.klt=3", r"\[frontend\.klt\] must be a table"),
        ("frontend.mode.x=3", r"\[frontend\.mode\] is not a section"),
        ("frontend.klt.window_px=2", r"frontend\.klt\.window_px must be in \[3, 101\]"),
        ("frontend.klt.bias_window_px=11", r"frontend\.klt\.bias_window_px must be 0 or in \[3, window_px\)"),
        ("frontend..window_px=3", "expected section.key=value"),
    ):
        with pytest.raises(SnapsGraphError, match=why):
            Config().with_overrides([bad])
    with pytest.raises(SnapsGraphError, match="is a value, not a section"):
        parse_set(["frontend.klt=3", "frontend.klt.window_px=9"])


def test_a_misspelled_nested_table_in_a_file_gets_did_you_mean(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[frontend.klt]\nwindow = 9\n")
    with pytest.raises(
        SnapsGraphError, match=r"unknown key 'frontend\.klt\.window' \(did you mean 'frontend\.klt\.window_px'\?\)"
    ):
        Config.load(path)
    path.write_text("[frontend.stereoba]\nhuber_px = 1.0\n")
    with pytest.raises(SnapsGraphError, match=r"did you mean 'frontend\.stereo_ba'\?"):
        Config.load(path)


def test_an_old_drift_model_and_ramp_load_with_notes(tmp_path, capsys):
    """A config of the version before the drift model: its translation/heading rates and floors are
    read with a note and ignored, and its "linear" ramp is the drift-model ramp now."""
    p = tmp_path / "old.toml"
    p.write_text(
        '[loop]\ndiscount_shape = "linear"\nheading_drift_deg = 0.003\n'
        "[graph]\nodom_cov_floor_rot_rad = 1e-4\n[odometry]\ntrans_drift_pct = 1.0\nrot_drift_deg_per_100m = 0.1\n"
    )
    cfg = Config.load(p)
    err = capsys.readouterr().err
    assert cfg.loop.discount_shape == "drift" and cfg.odometry == Config().odometry
    for key in ("loop.discount_shape", "loop.heading_drift_deg", "graph.odom_cov_floor_rot_rad", "odometry.trans_drift_pct"):
        assert key in err
