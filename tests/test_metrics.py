"""Trajectory metrics, cross-checked against evo (API and CLI) and the KITTI devkit's algorithm."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, need_extra

from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.metrics import (
    ate_rmse,
    evaluate,
    kitti_relative_errors,
    mean_deviation,
    path_length,
    umeyama_alignment,
)
from snaps_graph.geometry import inv
from snaps_graph.trajectory_io import read_kitti_poses, write_kitti_poses, write_tum_poses

LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


def rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def drifted(gt: np.ndarray, yaw_bias_deg: float, scale: float) -> np.ndarray:
    """VO-like drift: every GT step scaled in length and followed by an extra yaw, accumulated."""
    est = [np.eye(4)]
    bias = np.eye(4)
    bias[:3, :3] = rot_y(yaw_bias_deg)
    for k in range(len(gt) - 1):
        step = inv(gt[k]) @ gt[k + 1]
        step[:3, 3] *= scale
        est.append(est[-1] @ step @ bias)
    return np.array(est)


def straight_line(n: int, step_m: float = 1.0) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n) * step_m
    return poses


def rebased_gt(kitti_gt_dir: Path, name: str) -> np.ndarray:
    """A real GT path, re-based, rotations projected onto SO(3) (the file's are orthonormal to ~1e-7
    only, and non-rotations make the devkit's acos and our atan2 angle formula disagree)."""
    gt = read_kitti_poses(kitti_gt_dir / name)
    u, _, vt = np.linalg.svd(gt[:, :3, :3])
    gt[:, :3, :3] = u @ vt
    return np.einsum("ij,njk->nik", inv(gt[0]), gt)


def devkit_reference(est: np.ndarray, gt: np.ndarray, lengths=LENGTHS, step: int = 10) -> tuple[float, float]:
    """evaluate_odometry.cpp's calcSequenceErrors, transcribed loop for loop (slow, independent)."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i, :3, 3] - gt[i - 1, :3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > dist[first] + length:
                    last = i
                    break
            if last == -1:
                continue
            delta_gt = inv(gt[first]) @ gt[last]
            delta_est = inv(est[first]) @ est[last]
            err = inv(delta_est) @ delta_gt
            d = 0.5 * (err[0, 0] + err[1, 1] + err[2, 2] - 1.0)
            r_errs.append(math.acos(max(min(d, 1.0), -1.0)) / length)
            t_errs.append(float(np.linalg.norm(err[:3, 3])) / length)
    return float(np.mean(t_errs)) * 100.0, math.degrees(float(np.mean(r_errs))) * 100.0


# ---------------------------------------------------------------- evo API on real ground truth
@pytest.fixture(scope="module", params=["07.txt", "00.txt"])
def real_pair(request, kitti_gt_dir):
    gt = rebased_gt(kitti_gt_dir, request.param)
    return drifted(gt, yaw_bias_deg=0.004, scale=1.015), gt


def test_mean_deviation_and_ate_match_evo_api(real_pair):
    need_extra("evo")
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PosePath3D

    est, gt = real_pair
    ref = PosePath3D(poses_se3=list(gt))

    raw = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    raw.process_data((ref, PosePath3D(poses_se3=list(est))))
    evo_mean = raw.get_statistic(evo_metrics.StatisticsType.mean)

    aligned = PosePath3D(poses_se3=list(est))
    aligned.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    evo_rmse = ape.get_statistic(evo_metrics.StatisticsType.rmse)

    assert evo_mean > 3.0 and evo_rmse > 1.0  # the drift is real, so agreement means something
    assert mean_deviation(est, gt) == pytest.approx(evo_mean, abs=1e-6)
    assert ate_rmse(est, gt) == pytest.approx(evo_rmse, abs=1e-6)


def test_umeyama_matches_evo_and_recovers_a_known_similarity(real_pair):
    need_extra("evo")
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    est, gt = real_pair
    src, dst = est[:, :3, 3], gt[:, :3, 3]
    for with_scale in (False, True):
        R, t, s = umeyama_alignment(src, dst, with_scale)
        R_evo, t_evo, s_evo = evo_umeyama(src.T, dst.T, with_scale)
        np.testing.assert_allclose(R, R_evo, atol=1e-9)
        np.testing.assert_allclose(t, t_evo, atol=1e-6)
        assert s == pytest.approx(s_evo, rel=1e-9)

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(50, 3)) * 10.0
    R_true = rot_y(37.0) @ np.array([[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]])
    t_true = np.array([4.0, -2.0, 7.5])
    R, t, s = umeyama_alignment(pts, 1.7 * pts @ R_true.T + t_true, with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-10)
    assert s == pytest.approx(1.7, rel=1e-12)


def test_kitti_relative_errors_equal_the_devkit_loops_on_real_gt(kitti_gt_dir):
    gt = rebased_gt(kitti_gt_dir, "07.txt")
    est = drifted(gt, yaw_bias_deg=0.01, scale=0.98)
    t_rel, r_rel = kitti_relative_errors(est, gt)
    t_ref, r_ref = devkit_reference(est, gt)
    assert t_rel > 0.5 and r_rel > 0.5
    assert t_rel == pytest.approx(t_ref, rel=1e-9)
    assert r_rel == pytest.approx(r_ref, rel=1e-6)


# ---------------------------------------------------------------- evo's command line reads our files
def _evo_ape_rmse(fmt: str, gt_file: Path, est_file: Path) -> float:
    exe = Path(sys.executable).parent / "evo_ape"
    if not exe.exists():
        pytest.skip(f"evo_ape not installed beside {sys.executable}")
    proc = subprocess.run(
        [str(exe), fmt, str(gt_file), str(est_file), "-a"],
        capture_output=True,
        text=True,
        timeout=120,
        env={"MPLBACKEND": "Agg", "PATH": str(exe.parent), "HOME": str(Path.home())},
    )
    assert proc.returncode == 0, proc.stderr
    match = re.search(r"^\s*rmse\s+([-+0-9.eE]+)\s*$", proc.stdout, re.MULTILINE)
    assert match, proc.stdout
    return float(match.group(1))


def test_evo_ape_cli_reads_our_kitti_and_tum_files(tmp_path, kitti_gt_dir):
    gt = rebased_gt(kitti_gt_dir, "07.txt")
    est = drifted(gt, yaw_bias_deg=0.006, scale=1.02)
    ours = ate_rmse(est, gt)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    assert _evo_ape_rmse("kitti", tmp_path / "gt.txt", tmp_path / "est.txt") == pytest.approx(ours, abs=1e-4)
    times = np.arange(len(gt)) * 0.1
    write_tum_poses(tmp_path / "gt.tum", gt, times)
    write_tum_poses(tmp_path / "est.tum", est, times)
    assert _evo_ape_rmse("tum", tmp_path / "gt.tum", tmp_path / "est.tum") == pytest.approx(ours, abs=1e-4)


# ---------------------------------------------------------------- hand-made cases with known answers
def test_identical_trajectories_have_zero_errors(kitti_gt_dir):
    gt = read_kitti_poses(kitti_gt_dir / "07.txt")  # as read: rotations orthonormal to ~1e-7 only
    m = evaluate(gt.copy(), gt)
    assert m["mean_deviation"] == 0.0 and m["end_error_m"] == 0.0
    assert m["ate_rmse"] < 1e-9
    assert m["t_rel"] < 1e-9
    assert m["r_rel"] < 1e-9
    assert m["path_length_m"] == pytest.approx(694.697, abs=1e-3)
    assert m["frames"] == 1101


def test_translation_scale_gives_the_expected_t_rel():
    gt = straight_line(500)  # 1 m a frame: the devkit's last frame is first + L + 1, chord L + 1
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    expected = np.mean([0.02 * (L + 1) / L for f in range(0, 500, 10) for L in LENGTHS if f + L + 1 <= 499]) * 100
    t_rel, r_rel = kitti_relative_errors(est, gt)
    assert t_rel == pytest.approx(expected, rel=1e-12)
    assert 2.0 < t_rel < 2.03
    assert r_rel == 0.0


def test_constant_yaw_rate_bias_gives_the_expected_r_rel():
    gt = straight_line(900)
    bias_deg = 0.01  # per frame; a segment of n frames turns n * bias
    est = drifted(gt, yaw_bias_deg=bias_deg, scale=1.0)
    segments = [(L + 1) / L for f in range(0, 900, 10) for L in LENGTHS if f + L + 1 <= 899]
    expected = np.mean(segments) * bias_deg * 100.0  # rad/m -> deg/100 m with bias in degrees
    _, r_rel = kitti_relative_errors(est, gt)
    assert r_rel == pytest.approx(expected, rel=1e-9)
    assert r_rel == pytest.approx(1.0, abs=0.01)


def test_offsets_and_rigid_motions():
    gt = drifted(straight_line(300), yaw_bias_deg=0.2, scale=1.0)  # a curve, so alignment is 3D-determined
    shifted = gt.copy()
    shifted[:, :3, 3] += np.array([1.0, 2.0, 2.0])
    assert mean_deviation(shifted, gt) == pytest.approx(3.0, abs=1e-12)
    assert ate_rmse(shifted, gt) < 1e-9  # a constant offset is aligned away
    moved = np.einsum("ij,njk->nik", np.block([[rot_y(30.0), np.array([[5.0], [0.0], [-3.0]])], [np.zeros((1, 3)), 1.0]]), gt)
    assert ate_rmse(moved, gt) < 1e-9
    assert mean_deviation(moved, gt) > 5.0
    end = gt.copy()
    end[-1, :3, 3] += np.array([0.0, 0.0, 3.0])
    m = evaluate(end, gt)
    assert m["end_error_m"] == pytest.approx(3.0)
    assert m["end_drift_percent"] == pytest.approx(3.0 / path_length(gt) * 100.0)
    assert m["mean_deviation"] == pytest.approx(3.0 / 300)


def test_short_path_has_undefined_relative_errors():
    gt = straight_line(101)  # exactly 100 m: no frame lies strictly beyond 100 m
    m = evaluate(gt * 1.0, gt)
    assert math.isnan(m["t_rel"]) and math.isnan(m["r_rel"])
    assert m["mean_deviation"] == 0.0 and m["path_length_m"] == pytest.approx(100.0)
    t_rel, _ = kitti_relative_errors(gt, gt, lengths=(50.0,))
    assert t_rel == 0.0


def test_bad_input_is_a_one_line_user_error():
    gt = straight_line(20)
    with pytest.raises(SnapsGraphError, match="lengths must match"):
        evaluate(gt[:10], gt)
    bad = gt.copy()
    bad[5, 0, 3] = np.nan
    with pytest.raises(SnapsGraphError, match="non-finite"):
        ate_rmse(bad, gt)
    with pytest.raises(SnapsGraphError, match=r"\(N, 4, 4\)"):
        mean_deviation(gt[:, :3, :], gt)
    with pytest.raises(SnapsGraphError, match="lengths must match"):
        kitti_relative_errors(gt, gt[:-1])


def test_mean_deviation_splits_into_horizontal_and_vertical():
    gt = straight_line(50)
    est = gt.copy()
    est[:, 0, 3] += 3.0  # sideways (x)
    est[:, 1, 3] += 4.0  # down (KITTI y): 5 m in all
    m = evaluate(est, gt)
    assert m["mean_deviation"] == pytest.approx(5.0)
    assert m["mean_deviation_horizontal"] == pytest.approx(3.0)
    assert m["mean_deviation_vertical"] == pytest.approx(4.0)


def test_step_error_axes_shows_a_turned_camera_frame_sideways():
    """A straight drive measured in a camera frame turned 0.5 deg in yaw: every step's error lies
    sideways (x), about 0.87 % of the path, with no forward (z) share; an exact estimate gives 0."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_frontend import step_error_axes_percent  # a front-end benchmark's measure

    gt = np.array([np.eye(4) for _ in range(20)])
    gt[:, 2, 3] = np.arange(20) * 1.2
    a = np.radians(0.5)
    Q = np.eye(4)
    Q[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    turned = np.linalg.inv(Q) @ gt @ Q  # the same motion seen from the turned frame
    ex, ey, ez = step_error_axes_percent(turned, gt)
    assert abs(abs(ex) - 100 * np.sin(a)) < 1e-6 and abs(ey) < 1e-9 and abs(ez) < 0.01, (ex, ey, ez)
    assert np.allclose(step_error_axes_percent(gt, gt), 0.0)
