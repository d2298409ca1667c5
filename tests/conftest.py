"""Shared fixtures. Tests that need ../shared/data skip with a clear reason where it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not found at {path} (it is in CI's ../shared/data; a user's clone lacks it)")
    return path


@pytest.fixture(scope="session")
def kitti06_dir() -> Path:
    """KITTI 06, frames 0-50, official layout (ground truth at ../../poses/06.txt)."""
    return _need(SHARED_DATA / "kitti" / "sequences" / "06")


@pytest.fixture(scope="session")
def kitti_gt_dir() -> Path:
    """Whole KITTI ground-truth trajectories 00.txt and 07.txt (with NN_times.txt)."""
    return _need(SHARED_DATA / "kitti_gt")
