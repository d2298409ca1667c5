"""The drift tool: deterministic for a seed, frame 0 kept, the end drift where --pct puts it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from snaps_graph.drift_model import DriftModel
from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.drift import drift_trajectory, end_drift_pct

GT00 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "kitti_gt" / "00.txt"


def _square(n_side: int = 200, step: float = 1.0) -> np.ndarray:
    """A 4-sided closed drive on the ground plane (camera z forward, turning about y)."""
    poses, T = [], np.eye(4)
    for k in range(4 * n_side):
        poses.append(T.copy())
        S = np.eye(4)
        S[2, 3] = step
        if (k + 1) % n_side == 0:
            c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
            S[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T = T @ S
    return np.array(poses)


def test_seed_reproducible_and_seeds_differ():
    gt = _square()
    a, b = drift_trajectory(gt, 3), drift_trajectory(gt, 3)
    assert np.array_equal(a, b)
    assert not np.allclose(a, drift_trajectory(gt, 4))


@pytest.mark.parametrize("pct", [1.0, 2.0])
def test_end_drift_hits_pct(pct):
    gt = _square()
    for seed in range(3):
        d = drift_trajectory(gt, seed, pct=pct)
        assert abs(end_drift_pct(d, gt) - pct) < 0.01 * pct
        assert np.all(np.isfinite(d))
        assert np.allclose(d[0], gt[0])
        R = d[:, :3, :3]
        assert np.allclose(R @ np.transpose(R, (0, 2, 1)), np.eye(3), atol=1e-9)


def test_frame0_identity_and_zero_model_is_gt():
    gt = _square(50)
    assert np.allclose(drift_trajectory(gt, 0)[0], np.eye(4))
    assert np.allclose(drift_trajectory(gt, 0, DriftModel(0, 0, 0, 0, 0)), gt)
    with pytest.raises(SnapsGraphError):
        drift_trajectory(gt, 0, DriftModel(0, 0, 0, 0, 0), pct=1.0)
    with pytest.raises(SnapsGraphError):
        drift_trajectory(gt[:1], 0)


@pytest.mark.skipif(not GT00.is_file(), reason="../shared/data/kitti_gt/00.txt absent (a user's clone has no ../shared)")
def test_long_real_path():
    from snaps_graph.trajectory_io import read_kitti_poses

    gt = read_kitti_poses(GT00)
    d = drift_trajectory(gt, 1, pct=1.0)
    assert abs(end_drift_pct(d, gt) - 1.0) < 0.01
    assert np.all(np.isfinite(d))
    # the error grows along the path: the first 100 m drift far less than the end
    assert np.linalg.norm(d[100, :3, 3] - gt[100, :3, 3]) < np.linalg.norm(d[-1, :3, 3] - gt[-1, :3, 3]) / 5


def test_cli_writes_and_never_replaces(tmp_path):
    from inprocess import cli

    from snaps_graph.trajectory_io import read_kitti_poses, write_kitti_poses

    gt_file, out = tmp_path / "gt.txt", tmp_path / "drifted.txt"
    write_kitti_poses(gt_file, _square(50))
    cmd = ["drift", gt_file, "--out", out, "--seed", "2", "--pct", "1"]
    done = cli(*cmd)
    assert done.returncode == 0, done.stderr
    d = read_kitti_poses(out)
    assert abs(end_drift_pct(d, _square(50)) - 1.0) < 0.02
    before = out.read_bytes()
    again = cli(*cmd)
    assert again.returncode == 2 and again.stderr.startswith("error:") and "exists" in again.stderr
    assert out.read_bytes() == before
