"""Loop-closure evaluation (evaluation/loops.py) and SNAPS's candidate records (candidates.csv).

The PR computation is checked on hand-made records whose ground truth is known; a tiny rendered
run checks that candidates.csv is written with the one column list and that `snaps-graph loops`
reads it back.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from inprocess import cli  # the command line in this process (tests/inprocess.py)

from snaps_graph.config import Config
from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.loops import (
    LoopEvalSettings,
    evaluate_loops,
    label_pairs,
    pr_curve,
    segments,
)
from snaps_graph.evaluation.results_io import read_candidates_csv, write_candidates_csv
from snaps_graph.types import CANDIDATE_COLUMNS, CandidateRecord


def rec(frame, ref, q, passed=False, tried=None, accepted=False) -> CandidateRecord:
    return CandidateRecord(
        frame,
        ref,
        1.0,
        0.0,
        q,
        q,
        1.0,
        1.0,
        0,
        q >= 0.15,
        passed if tried is None else tried,
        passed,
        30 if passed else 0,
        accepted,
    )


def test_pr_curve_known_counts():
    # true: 0.9 0.8 0.5 0.3; false: 0.6 0.2; ignored: 0.95 (never counted)
    q = np.array([0.9, 0.8, 0.5, 0.3, 0.6, 0.2, 0.95])
    lab = np.array([1, 1, 1, 1, 0, 0, -1])
    c = pr_curve(q, lab)
    assert c["n_true"] == 4 and c["n_false"] == 2
    assert c["max_recall_at_100_precision"] == pytest.approx(0.5)  # 0.9, 0.8 above the false 0.6
    assert c["threshold_at_100_precision"] == pytest.approx(0.8) and c["q_max_false"] == pytest.approx(0.6)
    at = dict(zip(c["thresholds"], zip(c["precision"], c["recall"])))
    assert at[0.5] == pytest.approx((3 / 4, 3 / 4))  # 0.9 0.8 0.5 true, 0.6 false
    assert at[0.2] == pytest.approx((4 / 6, 1.0))
    assert 0.95 not in at
    # With verification: passed on true 0.9, 0.5, 0.3 and on the false 0.2.
    passed = np.array([1, 0, 1, 1, 0, 1, 1], bool)
    v = pr_curve(q, lab, passed)
    assert v["max_recall_at_100_precision"] == pytest.approx(0.75)
    assert v["threshold_at_100_precision"] == pytest.approx(0.3) and v["q_max_false"] == pytest.approx(0.2)
    # No true pair at all: recall 0, never a division error.
    assert pr_curve(np.array([0.5]), np.array([0]))["max_recall_at_100_precision"] == 0.0


def test_label_pairs_and_segments():
    np.testing.assert_array_equal(label_pairs([0.0, 5.0, 5.1, 10.0, 10.1], 5.0, 10.0), [1, 1, -1, -1, 0])
    m = np.zeros(40, bool)
    m[[3, 4, 5, 12, 30, 31]] = True
    assert segments(m, gap=10) == [(3, 12), (30, 31)]
    assert segments(m, gap=2) == [(3, 5), (12, 12), (30, 31)]


def _out_and_back(n_out: int = 30) -> np.ndarray:
    """Drive n_out frames 1 m apart along z, turn around, drive back (heading reversed), then turn
    again and re-drive the first 10 m heading forward: frames 2*n_out.. revisit frames 0..9."""
    z = list(range(n_out)) + list(range(n_out - 1, -1, -1)) + list(range(10))
    yaw = [0.0] * n_out + [180.0] * n_out + [0.0] * 10
    gt = np.tile(np.eye(4), (len(z), 1, 1))
    for k, (zk, y) in enumerate(zip(z, yaw)):
        c, s = np.cos(np.radians(y)), np.sin(np.radians(y))
        gt[k, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        gt[k, 2, 3] = zk
    return gt


def test_evaluate_loops_revisits_segments_false_loops():
    gt = _out_and_back()
    ids = np.arange(len(gt)) + 100  # dataset indices differ from rows
    st = LoopEvalSettings(true_m=5.0, false_m=10.0, frame_distance=20, max_yaw_deg=10.0)
    records = [
        rec(162, 100, 0.4, passed=True, accepted=True),  # row 62 vs row 0: 2 m, true, accepted
        rec(165, 103, 0.3),  # 2 m: true, not verified
        rec(165, 120, 0.5, tried=True),  # row 65 (z 5) vs row 20 (z 20): 15 m, false, failed verification
        rec(166, 113, 0.2),  # z 6 vs z 13: 7 m, ignored
    ]
    loops = [(162, 100), (168, 125)]  # the second: z 8 vs z 25 = 17 m, a false loop
    ev = evaluate_loops(records, loops, gt, ids, st)
    assert (ev["pairs"], ev["true_pairs"], ev["false_pairs"], ev["ignored_pairs"]) == (4, 2, 1, 1)
    # Revisit frames: the re-driven rows 60..69 (the return leg heads 180 deg off, so it is none).
    assert ev["revisit_frames"] == 10
    assert ev["revisit_frames_searched"] == 2  # rows 62 and 65 compared a true pair
    assert (ev["segments"], ev["segments_found"], ev["segments_missed"]) == (1, 1, 0)
    assert ev["segments_found_frames"] == [[160, 169]]
    assert ev["loops"] == 2 and ev["true_loops"] == 1 and ev["false_loops"] == 1
    assert ev["false_loop_pairs"][0]["frame"] == 168
    assert ev["max_recall_at_100_precision"] == 0.0  # the false pair's Q 0.5 tops both true pairs
    assert ev["max_recall_at_100_precision_verified"] == 0.5  # the false pair failed verification
    assert ev["verification_tried"] == 2 and ev["verified_true_pairs"] == 1
    at = evaluate_loops(records, loops, gt, ids, st, min_similarity=0.35)  # admits 0.4 (true) and 0.5 (false)
    assert (at["precision_at_min_similarity"], at["recall_at_min_similarity"]) == (0.5, 0.5)
    assert (at["precision_at_min_similarity_verified"], at["recall_at_min_similarity_verified"]) == (1.0, 0.5)


def test_evaluate_loops_unknown_frame_is_user_error():
    gt = _out_and_back()
    with pytest.raises(SnapsGraphError, match="not a frame"):
        evaluate_loops([rec(5000, 0, 0.3)], [], gt, np.arange(len(gt)))


def test_candidates_csv_roundtrip(tmp_path):
    records = [rec(10, 2, 0.25, passed=True, accepted=True), rec(10, 3, 0.1, tried=False)]
    write_candidates_csv(tmp_path / "c.csv", records)
    with open(tmp_path / "c.csv") as fh:
        assert tuple(next(csv.reader(fh))) == CANDIDATE_COLUMNS
    back = read_candidates_csv(tmp_path / "c.csv")
    assert [(r.frame, r.reference, r.verify_passed, r.accepted, r.inliers) for r in back] == [
        (10, 2, True, True, 30),
        (10, 3, False, False, 0),
    ]
    assert back[0].q == pytest.approx(0.25)
    (tmp_path / "bad.csv").write_text("frame,reference\n1,2\n")
    with pytest.raises(SnapsGraphError, match="missing column"):
        read_candidates_csv(tmp_path / "bad.csv")


def test_tiny_run_writes_candidates_and_loops_cli(tmp_path):
    """A 90-frame built-in loop at 320x96 (its last 15 frames re-drive the start): candidates.csv
    holds one row per similarity computed, with the one column list, and `snaps-graph loops`
    evaluates it (no false loop on this path)."""
    from snaps_graph.runner import run_sequence
    from snaps_graph.synth import SyntheticSequence, builtin_loop_trajectory

    seq = SyntheticSequence(builtin_loop_trajectory(90), width=320, height=96, seed=0)
    cfg = Config()
    cfg.loop.frame_distance = 40
    cfg.loop.inter_frame_pause = 5
    run = tmp_path / "run"
    result, _ = run_sequence(seq, run, cfg, loops="snaps", refine="none")
    with open(run / "candidates.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == CANDIDATE_COLUMNS
    assert len(rows) == sum(r.loop_candidates for r in result.records) > 0
    accepted = {(int(r["frame"]), int(r["reference"])) for r in rows if r["accepted"] == "1"}
    assert accepted == {(l.frame, l.reference) for l in result.loops}
    for r in rows:  # Q is the product of the factors window by window, so bounded by the factors' range
        assert -1.0 <= float(r["q"]) <= 1.0 and 0.0 <= float(r["luminance"]) <= 1.0
    proc = cli("loops", run, "--json")
    assert proc.returncode == 0, proc.stderr
    ev = json.loads(proc.stdout)
    for key in (
        "pairs",
        "true_pairs",
        "false_pairs",
        "max_recall_at_100_precision",
        "max_recall_at_100_precision_verified",
        "revisit_frames",
        "revisit_frames_searched",
        "segments_found",
        "segments_missed",
        "loops",
        "false_loops",
    ):
        assert key in ev, key
    assert ev["pairs"] == len(rows) and ev["false_loops"] == 0 and ev["loops"] == len(result.loops)
    assert (run / "loops_pr.png").stat().st_size > 1000
    from snaps_graph.evaluation.report import compare_run

    metrics = compare_run(run)  # compare puts the same into report.md and metrics.json
    assert "## Loop closure against ground truth" in (run / "report.md").read_text()
    assert metrics["loop_evaluation"]["pairs"] == ev["pairs"]
    bad = cli("loops", tmp_path / "nope")
    assert bad.returncode == 2 and bad.stderr.startswith("error:")


def _straight_run(folder, n: int = 40):
    """A results folder of a straight 1 m-per-frame drive (no revisit) whose SNAPS compared nothing."""
    from snaps_graph.evaluation.results_io import write_frames_csv, write_loops_jsonl
    from snaps_graph.trajectory_io import write_kitti_poses
    from snaps_graph.types import FrameRecord

    folder.mkdir()
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n, dtype=float)
    write_kitti_poses(folder / "poses_vo.txt", poses)
    write_kitti_poses(folder / "poses_gt.txt", poses)
    rows = [FrameRecord(i, 0.1 * i, 5.0, 4.0, 1, 100, "", 0.01, 0, 0, 0.0, 0.5, 1, 0.0) for i in range(n)]
    write_frames_csv(folder / "frames.csv", rows)
    write_loops_jsonl(folder / "loops.jsonl", [])
    write_candidates_csv(folder / "candidates.csv", [])
    return folder


def test_loops_without_a_compared_pair_say_na(tmp_path):
    """No pair compared on a drive without a revisit: the recall is n/a with the reason, not 0.000,
    both in the text `snaps-graph loops` prints and in report.md."""
    from snaps_graph.evaluation.loops import loops_run, summary_lines
    from snaps_graph.evaluation.report import compare_run

    run = _straight_run(tmp_path / "run")
    ev = loops_run(run)
    assert ev["pairs"] == 0 and ev["revisit_frames"] == 0 and "plot" not in ev
    lines = summary_lines(ev)
    assert "max recall at 100% precision: n/a (no revisit in this run)" in lines
    assert not any("0.000" in line for line in lines if "recall" in line)
    out = cli("loops", run)
    assert out.returncode == 0, out.stderr
    assert "n/a (no revisit in this run)" in out.stdout
    compare_run(run)
    assert "n/a (no revisit in this run)" in (run / "report.md").read_text()
    assert not (run / "loops_pr.png").exists()
