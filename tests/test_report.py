"""compare_run on fake run folders built from a real ground-truth path (KITTI 07)."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.latency import latency_summary
from snaps_graph.evaluation.metrics import ate_rmse, kitti_relative_errors, mean_deviation
from snaps_graph.evaluation.report import compare_run
from snaps_graph.geometry import inv
from snaps_graph.trajectory_io import read_kitti_poses, write_kitti_poses

FIRST = 50  # the fake run processed dataset frames 50..1100 of KITTI 07
LOOP_FRAME, LOOP_REF = 1050, 60  # dataset indices
Q, CORR, LUM = 0.8, 0.9, 0.95
GAMMA0 = 1.0 - math.exp(-3.0)
K = 100  # discount length
BATCH_OFFSET = np.array([0.3, 0.0, 0.4])  # batch = truth shifted by 0.5 m


def rebase(poses: np.ndarray) -> np.ndarray:
    return np.einsum("ij,njk->nik", inv(poses[0]), poses)


def drifted(gt: np.ndarray, yaw_bias_deg: float, scale: float) -> np.ndarray:
    a = math.radians(yaw_bias_deg)
    bias = np.eye(4)
    bias[:3, :3] = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    est = [np.eye(4)]
    for k in range(len(gt) - 1):
        step = inv(gt[k]) @ gt[k + 1]
        step[:3, 3] *= scale
        est.append(est[-1] @ step @ bias)
    return np.array(est)


def snaps_correction(vo: np.ndarray, row: int, ref_row: int) -> tuple[np.ndarray, np.ndarray]:
    """eq. 6 with alpha = 1 on positions, and frames after the loop shifted with the loop frame."""
    delta = vo[ref_row, :3, 3] - vo[row, :3, 3]
    out = vo.copy()
    s_prime = row - np.arange(row - K, row + 1)
    gamma = np.clip(1.0 - np.exp(-(3.0 - 1 * 0.01 * s_prime)), 0.0, None)
    out[row - K : row + 1, :3, 3] += Q * gamma[:, None] * delta
    out[row + 1 :, :3, 3] += Q * gamma[-1] * delta
    return out, delta


def write_frames_csv(path: Path, frames: np.ndarray, loop_row: int | None, columns: list[str] | None = None) -> dict:
    n = len(frames)
    i = np.arange(n)
    cand = ((i % 7) == 0).astype(int)
    cols = {
        "frame": frames,
        "timestamp": frames * 0.1,
        "t_total_ms": 90.0 + (i % 20) * 1.5,
        "t_vo_ms": 80.0 + (i % 10),
        "vo_ok": ["True"] * n,
        "vo_inliers": 300 - (i % 50),
        "t_loop_ms": np.where(cand > 0, 20.0 + (i % 13), 0.003),
        "loop_candidates": cand * 3,
        "loop_closed": (i == loop_row).astype(int) if loop_row is not None else np.zeros(n, int),
        "t_graph_ms": 0.2 + (i % 5) * 0.01,
    }
    names = columns or list(cols)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for k in range(n):
            w.writerow(
                [
                    cols[c][k] if isinstance(cols[c][k], str) else f"{cols[c][k]:.4f}" if c.startswith("t") else cols[c][k]
                    for c in names
                ]
            )
    return cols


@pytest.fixture(scope="module")
def run07(tmp_path_factory, kitti_gt_dir):
    """A run over frames 50..1100 with vo, snaps (one loop) and batch; GT passed as the whole file."""
    run = tmp_path_factory.mktemp("run07")
    gt_file = kitti_gt_dir / "07.txt"
    gt = rebase(read_kitti_poses(gt_file)[FIRST:])
    frames = np.arange(FIRST, FIRST + len(gt))
    row, ref_row = LOOP_FRAME - FIRST, LOOP_REF - FIRST
    vo = drifted(gt, yaw_bias_deg=0.01, scale=1.01)
    snaps, delta = snaps_correction(vo, row, ref_row)
    batch = gt.copy()
    batch[:, :3, 3] += BATCH_OFFSET
    write_kitti_poses(run / "poses_vo.txt", vo)
    write_kitti_poses(run / "poses_snaps.txt", snaps)
    write_kitti_poses(run / "poses_batch.txt", batch)
    cols = write_frames_csv(run / "frames.csv", frames, row)
    loop = {
        "frame": LOOP_FRAME,
        "reference": LOOP_REF,
        "distance_m": float(np.linalg.norm(delta)),
        "yaw_diff_deg": 3.0,
        "q": Q,
        "correlation": CORR,
        "luminance": LUM,
        "contrast": Q / (CORR * LUM),
        "delta": delta.tolist(),
        "n_corrected": K + 1,
        "alpha": 1,
        "candidates": 3,
        "t_ms": 25.0,
        "verified": True,
        "verify_inliers": 80,
    }
    (run / "loops.jsonl").write_text(json.dumps(loop) + "\n")
    (run / "config.toml").write_text('loops = "snaps"\n\n[loop]\ndiscount_offset = 3.0\n')
    (run / "metrics.json").write_text(json.dumps({"frames": len(gt), "wall_s": 12.5, "latency_ms": {"old": 1}}))
    result = compare_run(run, gt_file)
    return {
        "run": run,
        "gt": gt,
        "vo": vo,
        "snaps": snaps,
        "batch": batch,
        "delta": delta,
        "cols": cols,
        "row": row,
        "result": result,
        "report": (run / "report.md").read_text(),
    }


def table_rows(report: str, header_start: str) -> list[dict[str, str]]:
    """Rows of the markdown table whose header starts with ``| header_start``."""
    lines = report.splitlines()
    start = next(i for i, l in enumerate(lines) if l.startswith(f"| {header_start}"))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for l in lines[start + 2 :]:
        if not l.startswith("|"):
            break
        rows.append(dict(zip(header, [c.strip() for c in l.strip("|").split("|")])))
    return rows


def test_trajectory_table_holds_the_metrics(run07):
    rows = {r["trajectory"]: r for r in table_rows(run07["report"], "trajectory")}
    assert list(rows) == ["vo", "snaps", "batch"]
    gt = run07["gt"]
    for name in rows:
        est = run07[name]
        t_rel, r_rel = kitti_relative_errors(est, gt)
        assert rows[name]["frames"] == str(len(gt))
        assert rows[name]["mean deviation [m]"] == f"{mean_deviation(est, gt):.3f}"
        assert rows[name]["ATE RMSE [m]"] == f"{ate_rmse(est, gt):.3f}"
        assert rows[name]["t_rel [%]"] == f"{t_rel:.3f}"
        assert rows[name]["r_rel [deg/100 m]"] == f"{r_rel:.4f}"
    assert rows["batch"]["mean deviation [m]"] == "0.500"
    assert rows["batch"]["ATE RMSE [m]"] == "0.000"  # a constant offset is aligned away
    assert float(rows["snaps"]["mean deviation [m]"]) < float(rows["vo"]["mean deviation [m]"])
    vo_md, snaps_md = mean_deviation(run07["vo"], gt), mean_deviation(run07["snaps"], gt)
    assert rows["snaps"]["vs vo"] == f"{(snaps_md - vo_md) / vo_md * 100:+.1f}%"


def test_loop_table_compares_heuristic_and_optimised_corrections(run07):
    (loop,) = table_rows(run07["report"], "frame")
    row = run07["row"]
    step = Q * GAMMA0 * np.linalg.norm(run07["delta"])
    assert (loop["frame"], loop["reference"], loop["Q"], loop["verified"]) == (str(LOOP_FRAME), str(LOOP_REF), "0.8000", "yes")
    assert loop["SNAPS step [m]"] == f"{step:.3f}"
    assert loop["heuristic [m]"] == f"{step:.3f}"  # first loop: the move equals eq. 6's step
    opt = np.linalg.norm(run07["batch"][row, :3, 3] - run07["vo"][row, :3, 3])
    assert loop["optimised batch [m]"] == f"{opt:.3f}"
    err_snaps = np.linalg.norm(run07["snaps"][row, :3, 3] - run07["gt"][row, :3, 3])
    assert loop["error snaps [m]"] == f"{err_snaps:.3f}"
    assert loop["error batch [m]"] == "0.500"
    assert step > 1.0  # the fixture's loop really moves the frame


def test_latency_table_and_figures(run07):
    rows = {r["stage"]: r for r in table_rows(run07["report"], "stage")}
    cols = run07["cols"]
    total = np.round(cols["t_total_ms"], 4)
    assert rows["total per frame"]["median [ms]"] == f"{np.median(total):.4f}"
    assert rows["total per frame"]["p95 [ms]"] == f"{np.percentile(total, 95):.4f}"
    cand = cols["loop_candidates"] > 0
    assert rows["SNAPS, with candidates"]["frames"] == str(int(cand.sum()))
    assert rows["SNAPS, no candidate"]["mean [ms]"] == "0.0030"
    assert rows["SNAPS, loop closed"]["frames"] == "1"
    direct = latency_summary({k: np.round(cols[k], 4) for k in ("t_total_ms", "t_loop_ms", "loop_candidates")})
    assert direct["loop_with_candidates"]["n"] == int(cand.sum()) and "vo" not in direct
    assert direct["total"]["median"] == pytest.approx(np.median(total))
    for name in ("trajectories.png", "errors.png", "latency.png"):
        data = (run07["run"] / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name
        assert f"]({name})" in run07["report"]


def test_metrics_json_is_updated_and_strict(run07):
    text = (run07["run"] / "metrics.json").read_text()
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert data["wall_s"] == 12.5 and data["frames"] == len(run07["gt"])  # kept
    assert set(data["trajectories"]) == {"vo", "snaps", "batch"}
    assert set(data["trajectories"]["vo"]) >= {
        "mean_deviation",
        "ate_rmse",
        "t_rel",
        "r_rel",
        "frames",
        "path_length_m",
        "end_error_m",
        "end_drift_percent",
    }
    assert data["trajectories"]["batch"]["mean_deviation"] == pytest.approx(0.5, abs=1e-6)
    assert data["latency_ms"]["total"]["n"] == len(run07["gt"]) and "old" not in data["latency_ms"]
    assert data["loop_corrections"][0]["optimised_m"]["batch"] > 0
    assert data == run07["result"]


def test_without_ground_truth_no_error_columns(tmp_path, kitti_gt_dir):
    gt = rebase(read_kitti_poses(kitti_gt_dir / "07.txt")[:300])
    vo = drifted(gt, 0.02, 1.0)
    write_kitti_poses(tmp_path / "poses_vo.txt", vo)
    write_frames_csv(tmp_path / "frames.csv", np.arange(300), None, columns=["frame", "t_total_ms", "t_vo_ms"])
    result = compare_run(tmp_path)
    report = (tmp_path / "report.md").read_text()
    (row,) = table_rows(report, "trajectory")
    assert "mean deviation [m]" not in row and row["frames"] == "300"
    assert not (tmp_path / "errors.png").exists() and (tmp_path / "latency.png").exists()
    assert "trajectories" not in result and "loop_no_candidate" not in result["latency_ms"]
    assert "No loop closed in this run (no loops.jsonl)" in report


def test_short_path_prints_na_and_writes_null(tmp_path):
    gt = np.tile(np.eye(4), (60, 1, 1))
    gt[:, 2, 3] = np.arange(60) * 1.0  # 59 m: no 100 m segment
    vo = gt.copy()
    vo[:, 0, 3] = np.arange(60) * 0.01
    write_kitti_poses(tmp_path / "poses_vo.txt", vo)
    write_kitti_poses(tmp_path / "poses_gt.txt", gt)
    write_frames_csv(tmp_path / "frames.csv", np.arange(60), None)
    (tmp_path / "loops.jsonl").write_text("")
    result = compare_run(tmp_path)
    (row,) = table_rows((tmp_path / "report.md").read_text(), "trajectory")
    assert row["t_rel [%]"] == "n/a" and row["r_rel [deg/100 m]"] == "n/a"
    assert row["mean deviation [m]"] == f"{np.mean(np.arange(60) * 0.01):.3f}"
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["trajectories"]["vo"]["t_rel"] is None and result["trajectories"]["vo"]["r_rel"] is None


def test_missing_or_bad_inputs_name_the_file(tmp_path):
    with pytest.raises(SnapsGraphError, match="run folder not found"):
        compare_run(tmp_path / "nope")
    with pytest.raises(SnapsGraphError, match="poses_vo.txt"):
        compare_run(tmp_path)
    gt = np.tile(np.eye(4), (30, 1, 1))
    gt[:, 2, 3] = np.arange(30)
    write_kitti_poses(tmp_path / "poses_vo.txt", gt)
    with pytest.raises(SnapsGraphError, match="frames.csv"):
        compare_run(tmp_path)
    write_frames_csv(tmp_path / "frames.csv", np.arange(100, 130), None)
    with pytest.raises(SnapsGraphError, match="missing_gt.txt"):
        compare_run(tmp_path, tmp_path / "missing_gt.txt")
    write_kitti_poses(tmp_path / "short_gt.txt", gt[:20])
    with pytest.raises(SnapsGraphError, match="short_gt.txt"):
        compare_run(tmp_path, tmp_path / "short_gt.txt")
    (tmp_path / "loops.jsonl").write_text(json.dumps({"frame": 5, "reference": 1}) + "\n")
    with pytest.raises(SnapsGraphError, match=r"loops.jsonl:1: frame 5 is not a frame of this run"):
        compare_run(tmp_path)
    (tmp_path / "loops.jsonl").write_text("")
    write_kitti_poses(tmp_path / "poses_snaps.txt", gt[:29])
    with pytest.raises(SnapsGraphError, match="poses_snaps.txt: 29 poses"):
        compare_run(tmp_path)


def test_latency_box_draws_no_column_for_a_stage_without_positive_samples(tmp_path):
    from snaps_graph.evaluation.plots import plot_latency_box

    path = plot_latency_box(tmp_path / "lat.png", {"graph": np.array([]), "loop": np.array([0.0, -1.0])})
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5_000
    assert [p.name for p in tmp_path.iterdir()] == ["lat.png"]  # no temporary file left behind


def test_snaps_step_uses_the_weight_eq6_applied(run07, tmp_path, kitti_gt_dir):
    # A verified loop under correction_weight = "verified" moves with weight 1, not Q.
    run = tmp_path / "run"
    shutil.copytree(run07["run"], run)
    loop = json.loads((run / "loops.jsonl").read_text())
    loop["weight"] = 1.0
    (run / "loops.jsonl").write_text(json.dumps(loop) + "\n")
    compare_run(run, kitti_gt_dir / "07.txt")
    (row,) = table_rows((run / "report.md").read_text(), "frame")
    assert row["SNAPS step [m]"] == f"{GAMMA0 * np.linalg.norm(run07['delta']):.3f}"
    assert row["Q"] == "0.8000"


def test_top_view_scale_shows_lateral_drift_and_never_magnifies_jitter(tmp_path):
    from snaps_graph.evaluation.plots import plot_trajectories, top_view_scale

    assert top_view_scale(0.004, 0.009) == "stationary"  # centimetres of jitter: a fixed 1 m window
    assert top_view_scale(0.5, 60.0) == "stretched"  # a straight drive: lateral drift visible
    assert top_view_scale(40.0, 60.0) == "equal"
    poses = np.tile(np.eye(4), (20, 1, 1))
    poses[:, 2, 3] = np.linspace(0.0, 60.0, 20)
    path = plot_trajectories(tmp_path / "t.png", {"gt": poses, "vo": poses}, loops=[(19, 0)])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def linked_files(md: str) -> list[str]:
    """Relative targets of the markdown links and pictures in ``md``."""
    import re

    return [t for t in re.findall(r"\]\(([^)\s]+)\)", md) if "://" not in t and not t.startswith("#")]


@pytest.mark.parametrize("candidates", [False, True])
def test_every_file_report_md_links_exists(tmp_path, candidates):
    """With ground truth, no loop and (optionally) a SNAPS that compared no pair: the report links
    only pictures it wrote (no loops_pr.png without a compared pair)."""
    from snaps_graph.evaluation.results_io import write_candidates_csv

    gt = np.tile(np.eye(4), (60, 1, 1))
    gt[:, 2, 3] = np.arange(60) * 1.0
    write_kitti_poses(tmp_path / "poses_vo.txt", gt)
    write_kitti_poses(tmp_path / "poses_gt.txt", gt)
    write_frames_csv(tmp_path / "frames.csv", np.arange(60), None)
    if candidates:
        write_candidates_csv(tmp_path / "candidates.csv", [])
    compare_run(tmp_path)
    md = (tmp_path / "report.md").read_text()
    links = linked_files(md)
    assert "trajectories.png" in links and "errors.png" in links
    assert ("## Loop closure against ground truth" in md) is candidates
    missing = [t for t in links if not (tmp_path / t).is_file()]
    assert not missing, missing


def test_every_file_report_md_links_exists_with_a_loop(run07):
    links = linked_files((run07["run"] / "report.md").read_text())
    assert links and not [t for t in links if not (run07["run"] / t).is_file()]
