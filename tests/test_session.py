"""Sessions: a run keeps what a later run needs; a later run relocalises against it by appearance,
closes loops across the two and refines both; the prior is read, never written; bad priors are
one-line errors."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA, need_extra
from inprocess import cli

from snaps_graph.camera import StereoCamera
from snaps_graph.errors import SnapsGraphError
from snaps_graph.evaluation.drift import drift_trajectory
from snaps_graph.session import Factors, Session, read_session, write_session
from snaps_graph.trajectory_io import read_poses, write_kitti_poses

LOOP = SHARED_DATA / "kitti00_loop"
SEQ = LOOP / "sequences" / "00"


def digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def small_session(n: int = 12) -> Session:
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n) * 1.5
    refs = np.arange(0, n, 5)
    rows = [3, 0, 4][: len(refs)]
    start = np.concatenate([[0], np.cumsum(rows)])
    m = int(start[-1])
    return Session(
        name="",
        camera=StereoCamera(700.0, 700.0, 600.0, 180.0, 0.54, 1200, 360),
        image_size=(1200, 360),
        monocular=False,
        loop_settings={"thumbnail_scale": 1 / 6, "window": 16, "detector": "orb"},
        config_digest="x",
        trajectory="snaps",
        frame_ids=np.arange(n) + 10,
        timestamps=np.arange(n) * 0.1,
        poses=poses,
        vo_poses=poses.copy(),
        driven=np.arange(n) * 1.5,
        thumbs=rng.integers(0, 255, (n, 60, 200), dtype=np.uint8),
        refs=refs,
        ref_start=start,
        ref_uv=rng.random((m, 2), dtype=np.float32),
        ref_pts=rng.random((m, 3), dtype=np.float32),
        ref_desc=rng.integers(0, 255, (m, 32), dtype=np.uint8),
        factors=Factors(np.array([[0, 1]]), np.eye(4)[None], np.eye(6)[None] * 1e-4, np.array([False])),
        gt_origin=np.eye(4),
    )


def test_a_session_reads_back_as_written(tmp_path):
    s = small_session()
    write_session(tmp_path / "run" / "session", s)
    r = read_session(tmp_path / "run")
    assert r.name == str(tmp_path / "run") and len(r) == len(s) and r.camera == s.camera
    for field in ("frame_ids", "poses", "thumbs", "refs", "ref_start", "ref_uv", "ref_desc", "gt_origin"):
        assert np.array_equal(getattr(r, field), getattr(s, field)), field
    assert np.array_equal(r.features(2).pts3d, s.ref_pts[3:7])
    assert isinstance(r.thumbs, np.memmap)  # the large arrays are read lazily


def test_sift_descriptors_are_stored_as_bytes_and_read_back_as_they_were(tmp_path):
    s = small_session()
    s.ref_desc = np.random.default_rng(1).integers(0, 256, (len(s.ref_uv), 128)).astype(np.float32)
    write_session(tmp_path / "run" / "session", s)
    assert np.load(tmp_path / "run" / "session" / "ref_desc.npy").dtype == np.uint8
    got = read_session(tmp_path / "run").features(0).desc
    assert got.dtype == np.float32 and np.array_equal(got, s.ref_desc[:3])


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda f: f.joinpath("thumbs.npy").write_bytes(f.joinpath("thumbs.npy").read_bytes()[:-100]), "truncated"),
        (lambda f: f.joinpath("ref_uv.npy").write_bytes(b"\0" * f.joinpath("ref_uv.npy").stat().st_size), "corrupted"),
        (lambda f: f.joinpath("factors.npz").unlink(), "missing"),
        (lambda f: f.joinpath("session.json").write_text("{"), "not a readable session index"),
        (lambda f: _edit_index(f, version=99), "version 99"),
        (lambda f: _edit_index(f, format="other"), "not a snaps-graph session index"),
    ],
)
def test_a_damaged_session_is_a_one_line_error_naming_the_file(tmp_path, damage, message):
    folder = tmp_path / "run" / "session"
    write_session(folder, small_session())
    damage(folder)
    with pytest.raises(SnapsGraphError) as info:
        read_session(tmp_path / "run")
    text = str(info.value)
    assert message in text and str(folder) in text and "\n" not in text


def _edit_index(folder: Path, **changes) -> None:
    index = json.loads((folder / "session.json").read_text())
    index.update(changes)
    (folder / "session.json").write_text(json.dumps(index))


def test_a_folder_that_is_not_a_run_is_refused(tmp_path):
    (tmp_path / "notes").mkdir()
    with pytest.raises(SnapsGraphError, match="not the results folder of a run"):
        read_session(tmp_path / "notes")
    with pytest.raises(SnapsGraphError, match="prior not found"):
        read_session(tmp_path / "absent")


# ---------------------------------------------------------------- two sessions on real images
@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory):
    """kitti00_loop as two sessions, each with its own drifted odometry: A = frames 100-230, B =
    frames 1559-1608 with --prior A (B's odometry starts from a pose far from A's frame)."""
    if not SEQ.is_dir():
        pytest.skip(f"real data not found at {LOOP} (it is in CI's ../shared/data; a user's clone lacks it)")
    work = tmp_path_factory.mktemp("sessions")
    gt = read_poses(LOOP / "poses" / "00.txt")
    far = np.eye(4)
    far[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    far[:3, 3] = [300.0, 5.0, -200.0]
    write_kitti_poses(work / "odo_a.txt", drift_trajectory(gt, 0, pct=1.0))
    write_kitti_poses(work / "odo_b.txt", far @ drift_trajectory(gt, 1, pct=1.0))
    a, b = work / "A", work / "B"
    ran = cli("run", SEQ, "--frames", "0:131", "--odometry", work / "odo_a.txt", "--refine", "batch", "--out", a)
    assert ran.returncode == 0, ran.stderr
    before = digests(a)
    ran = cli("run", SEQ, "--frames", "150:200", "--odometry", work / "odo_b.txt", "--refine", "batch", "--prior", a, "--out", b)
    assert ran.returncode == 0, ran.stderr
    return a, b, before, gt, ran


def test_the_later_run_relocalises_against_the_prior_and_lands_in_its_frame(two_sessions):
    a, b, _, gt, ran = two_sessions
    metrics = json.loads((b / "metrics.json").read_text())
    entry = metrics["sessions"][0]
    assert entry["relocalised"] and 1573 <= entry["frame"] <= 1630, entry
    assert f"relocalised against {a}" in ran.stdout
    loops = [json.loads(line) for line in (b / "loops.jsonl").read_text().splitlines()]
    cross = [lp for lp in loops if lp.get("session") == str(a)]
    assert len(cross) >= 3 and sum(lp["relocalised"] for lp in cross) == 1
    for lp in cross:  # every loop across the sessions is a true one
        assert np.linalg.norm(gt[lp["frame"]][:3, 3] - gt[lp["reference"]][:3, 3]) < 10.0, lp
    # The outputs are in A's frame: B's positions against the ground truth re-based on A's first
    # frame (before relocalisation B knew only its own frame, hundreds of metres away).
    frames = np.loadtxt(b / "frames.csv", delimiter=",", skiprows=1, usecols=0, dtype=np.int64)
    truth = np.linalg.inv(gt[100]) @ gt[frames]
    assert np.allclose(read_poses(b / "poses_gt.txt"), truth, atol=1e-6)
    after = frames >= entry["frame"]
    for name in ("snaps", "batch"):
        d = read_poses(b / f"poses_{name}.txt")[after, :3, 3] - truth[after, :3, 3]
        assert np.hypot(d[:, 0], d[:, 2]).mean() < 1.5, name
    # The prior where B placed it (in its own frame: as A wrote it), and B's session in A's frame too.
    assert np.allclose(read_poses(b / "poses_prior0.txt"), read_poses(a / "poses_batch.txt"), atol=1e-3)
    origin = read_session(b).gt_origin
    assert origin is not None and np.allclose(origin, gt[100])


def test_compare_shows_the_sessions_and_measures_in_the_prior_frame(two_sessions, tmp_path):
    a, b, _, _, _ = two_sessions
    run = tmp_path / "B"
    shutil.copytree(b, run)
    ran = cli("compare", run)
    assert ran.returncode == 0, ran.stderr
    report = (run / "report.md").read_text()
    assert f"Prior `{a}`: relocalised at frame" in report and "in the prior's frame, as the run wrote it" in report
    # Measured against the ground truth in A's frame (re-based to B's first frame, it would be tens of metres off).
    assert json.loads((run / "metrics.json").read_text())["trajectories"]["batch"]["mean_deviation"] < 2.0


def test_the_prior_folder_is_never_written(two_sessions):
    a, _, before, _, _ = two_sessions
    assert digests(a) == before


def test_same_start_skips_the_appearance_search(two_sessions, tmp_path):
    a, _, before, gt, _ = two_sessions
    write_kitti_poses(tmp_path / "odo.txt", drift_trajectory(gt, 2, pct=1.0))
    ran = cli(
        "run", SEQ, "--frames", "0:40", "--odometry", tmp_path / "odo.txt", "--prior", a, "--same-start", "--out", tmp_path / "c"
    )
    assert ran.returncode == 0, ran.stderr
    assert f"started where {a} started" in ran.stdout
    snaps = read_poses(tmp_path / "c" / "poses_snaps.txt")
    assert np.allclose(snaps[0], read_session(a).poses[0], atol=1e-9)
    assert digests(a) == before  # read, never written


def test_a_recording_of_a_run_with_a_prior(two_sessions, tmp_path):
    """The viewer draws in the outputs' frame and the prior beside the run; the recording completes."""
    need_extra("rerun")
    a, _, before, gt, _ = two_sessions
    write_kitti_poses(tmp_path / "odo.txt", drift_trajectory(gt, 1, pct=1.0))
    rrd = tmp_path / "b.rrd"
    ran = cli(
        "run", SEQ, "--frames", "150:190", "--odometry", tmp_path / "odo.txt", "--prior", a, "--out", tmp_path / "b", "--rrd", rrd
    )
    assert ran.returncode == 0, ran.stderr
    assert f"relocalised against {a}" in ran.stdout and rrd.read_bytes()[:4] == b"RRF2"
    assert digests(a) == before  # read, never written


def _bad_prior_cases(a: Path, work: Path) -> list[tuple[list, object]]:
    other_cam = work / "other_cam"
    shutil.copytree(a, other_cam)
    _edit_index(other_cam / "session", camera={"fx": 500.0, "fy": 500.0, "cx": 600.0, "cy": 180.0, "baseline_m": 0.5})
    cut = work / "cut"
    shutil.copytree(a, cut)
    (cut / "session" / "thumbs.npy").write_bytes((cut / "session" / "thumbs.npy").read_bytes()[:1000])
    (work / "plain").mkdir()
    return [
        (["--prior", a, "--prior", a], "given twice"),
        (["--prior", other_cam], other_cam / "session" / "session.json"),
        (["--prior", cut], cut / "session" / "thumbs.npy"),
        (["--prior", work / "plain"], work / "plain" / "session" / "session.json"),
        (["--prior", a, "--loops", "none"], "needs loop closure"),
        (["--prior", a, "--set", "verification.detector=sift"], "detector"),
    ]


def test_bad_priors_are_one_line_errors_and_leave_everything_as_it_was(two_sessions, tmp_path):
    a, _, before, gt, _ = two_sessions
    write_kitti_poses(tmp_path / "odo.txt", gt)
    for extra, named in _bad_prior_cases(a, tmp_path):
        out = tmp_path / "out"
        ran = cli("run", SEQ, "--frames", "0:20", "--odometry", tmp_path / "odo.txt", "--out", out, *extra)
        lines = [line for line in ran.stderr.splitlines() if line.strip()]
        assert ran.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:"), (extra, ran.stderr)
        assert str(named) in lines[0] and "Traceback" not in ran.stderr, (extra, lines)
        assert not out.exists()
    # The prior as the output folder, or holding it: refused before anything is written.
    for out in (a, a / "inner"):
        ran = cli("run", SEQ, "--frames", "0:20", "--odometry", tmp_path / "odo.txt", "--prior", a, "--out", out, "--overwrite")
        assert ran.returncode == 2 and str(a) in ran.stderr and "Traceback" not in ran.stderr
    assert digests(a) == before


def test_the_sessions_map_holds_each_prior_map_where_the_run_placed_it(tmp_path):
    import open3d as o3d

    from snaps_graph.mapping.sessions import write_sessions_map

    def cloud(path: Path, xyz: np.ndarray) -> None:
        c = o3d.geometry.PointCloud()
        c.points = o3d.utility.Vector3dVector(xyz)
        o3d.io.write_point_cloud(str(path), c)

    out, prior, empty = tmp_path / "run", tmp_path / "prior", tmp_path / "no_map"
    for folder in (out, prior, empty):
        folder.mkdir()
    cloud(out / "map.ply", np.zeros((3, 3)))
    cloud(prior / "map.ply", np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]))
    T = np.eye(4)
    T[:3, 3] = [10.0, 0.0, -5.0]
    entry = write_sessions_map(out, [(prior, T), (empty, np.eye(4))])  # a prior without a map is left out
    assert entry == {"file": "map_sessions.ply", "sessions": 2, "points": 5}
    got = np.asarray(o3d.io.read_point_cloud(str(out / "map_sessions.ply")).points)
    assert np.allclose(got[3:], [[11.0, 0.0, -5.0], [10.0, 2.0, -5.0]])
    assert write_sessions_map(empty, [(prior, T)]) is None  # no map of this run: nothing written
