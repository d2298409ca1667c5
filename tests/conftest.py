"""Shared fixtures. Tests that need ../shared/data skip with a clear reason where it is absent,
and tests of an extra (pyproject.toml's optional dependencies) where it is not installed."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


# The optional modules and the extra that installs each (a core install has none of them).
EXTRAS = {"rosbags": "bags", "rerun": "viewer", "ray": "ray", "threadpoolctl": "ray", "evo": "dev"}


def installed(module: str) -> bool:
    """Whether an extra's module can be imported, without importing it (ray's import takes seconds)."""
    try:
        return importlib.util.find_spec(module) is not None
    except ImportError:
        return False


def need_extra(module: str) -> None:
    """Skip the calling test unless ``module`` is installed, naming the extra that brings it."""
    if not installed(module):
        pytest.skip(f"{module} is not installed: it comes with the {EXTRAS[module]} extra (pip install -e '.[{EXTRAS[module]}]')")


def pytest_configure(config) -> None:
    """Under pytest-xdist (make test runs ``-n auto``), in the controller before the workers start:
    evo sets up its user folder (~/.evo) at its first import, unlocked, so two workers' first evo
    imports on a fresh machine could race; it is done once here instead."""
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput") and installed("evo"):
        import evo.tools.settings  # noqa: F401


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not found at {path} (it is in CI's ../shared/data; a user's clone lacks it)")
    return path


@pytest.fixture(scope="session")
def tiny_seq(tmp_path_factory) -> Path:
    """8 stereo pairs of the built-in loop at 320x96 rendered by the package (KITTI layout, with
    poses.txt and times.txt): stands in for real data where a test needs any valid sequence."""
    from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder

    out = tmp_path_factory.mktemp("tiny") / "seq"
    poses, times = load_trajectory("loop", "0:8")
    render_to_folder(SyntheticSequence(poses, width=320, height=96, seed=0, times=times), out)
    return out


@pytest.fixture(scope="session")
def kitti06_dir() -> Path:
    """KITTI 06, frames 0-50, official layout (ground truth at ../../poses/06.txt)."""
    return _need(SHARED_DATA / "kitti" / "sequences" / "06")


@pytest.fixture(scope="session")
def kitti_gt_dir() -> Path:
    """Whole KITTI ground-truth trajectories 00.txt and 07.txt (with NN_times.txt)."""
    return _need(SHARED_DATA / "kitti_gt")
