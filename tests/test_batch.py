"""`snaps-graph batch`: plan checking, cells, resume records, summary; and on a 2-node Ray
cluster bound to 127.0.0.1: cells on both nodes, a re-run that skips them, Ctrl-C.

Sequences are tiny renderings made by the package's own renderer (no ../shared needed)."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

# Before Ray is imported anywhere in this process: every address Ray uses is 127.0.0.1, and no
# usage report leaves the machine.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"

import pytest  # noqa: E402
from conftest import need_extra  # noqa: E402
from inprocess import cli  # noqa: E402  # the command line in this process (tests/inprocess.py)

from snaps_graph.batch import CELL_FILE, completed, load_plan, plan_from_dict, run_batch, run_cell  # noqa: E402
from snaps_graph.errors import SnapsGraphError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
N_FRAMES, W, H = 24, 320, 96


@pytest.fixture(scope="module")
def seqs(tmp_path_factory) -> dict[str, Path]:
    """A 24-frame 320x96 rendering of the built-in loop, and a copy whose frame 5 is unreadable."""
    from snaps_graph.synth import SyntheticSequence, load_trajectory, render_to_folder

    root = tmp_path_factory.mktemp("seqs")
    poses, times = load_trajectory("loop", f"0:{N_FRAMES}")
    good = root / "good"
    render_to_folder(SyntheticSequence(poses, width=W, height=H, seed=0, times=times), good)
    broken = root / "broken"
    shutil.copytree(good, broken)
    (broken / "image_0" / "000005.png").write_bytes(b"not a png")
    return {"good": good, "broken": broken}


def write_plan(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ---------------------------------------------------------------- the plan
def test_plan_expands_cells_with_overrides_and_hashes(seqs, tmp_path):
    plan = plan_from_dict(
        {
            "sequences": [str(seqs["good"]), {"path": str(seqs["good"]), "name": "again"}],
            "frames": "0:16",
            "refine": "batch",
            "variants": {"default": {}, "tight": {"loop": {"min_similarity": 0.3}, "refine": "none"}},
        },
        source="p.toml",
    )
    assert [(c.sequence, c.variant) for c in plan.cells] == [
        ("good", "default"),
        ("good", "tight"),
        ("again", "default"),
        ("again", "tight"),
    ]
    default, tight = plan.cells[0], plan.cells[1]
    assert default.cfg.graph.refine == "batch" and default.cfg.loop.min_similarity == 0.15
    # a variant's own option beats the plan's
    assert tight.cfg.graph.refine == "none" and tight.cfg.loop.min_similarity == 0.3
    assert default.gt is not None
    assert default.frames == "0:16" and default.gt.endswith("poses.txt")
    assert default.config_hash != tight.config_hash
    # the same path under another name is the same run: same hash, its own folder
    assert plan.cells[2].config_hash == default.config_hash
    assert plan.cells[2].folder(tmp_path) != default.folder(tmp_path)
    # the hash is a function of the plan: reading it again gives the same hashes
    again = plan_from_dict({"sequences": [str(seqs["good"])], "frames": "0:16", "refine": "batch"}, source="p.toml")
    assert again.cells[0].variant == "default" and again.cells[0].config_hash == default.config_hash
    # --set beats the plan and its variants, and changes the hash
    over = plan_from_dict(
        {"sequences": [str(seqs["good"])], "frames": "0:16", "variants": {"tight": {"loop": {"min_similarity": 0.3}}}},
        overrides=["loop.min_similarity=0.25"],
    )
    assert over.cells[0].cfg.loop.min_similarity == 0.25 and over.cells[0].config_hash != tight.config_hash


def test_plan_paths_are_relative_to_the_plan_file(seqs, tmp_path):
    (tmp_path / "data").mkdir()
    shutil.copytree(seqs["good"], tmp_path / "data" / "s1")
    (tmp_path / "base.toml").write_text("[loop]\nradius_m = 7.0\n")
    plan = load_plan(write_plan(tmp_path / "plan.toml", 'sequences = ["data/s1"]\nconfig = "base.toml"\n'))
    assert plan.cells[0].seq_path == str(tmp_path / "data" / "s1")
    assert plan.cells[0].cfg.loop.radius_m == 7.0


@pytest.mark.parametrize(
    "body, expect",
    [
        ('sequences = ["{good}"]\n[loop]\nradius_m = 3.0\n', "unknown key 'loop' (config overrides go under [variants.NAME])"),
        (
            'sequences = ["{good}"]\n[variants.tight]\nloop = {{ min_similarty = 0.3 }}\n',
            "variants.tight: unknown key 'loop.min_similarty'",
        ),
        (
            'sequences = ["{good}"]\n[variants.tight]\nloop = {{ min_similarity = 3.0 }}\n',
            "variants.tight: loop.min_similarity must be in (0, 1]",
        ),
        ('sequences = ["{good}"]\n[variants.tight]\nlopp = 1\n', "variants.tight: unknown key 'lopp'"),
        ('sequences = ["{good}"]\nrefine = "fast"\n', "refine must be one of"),
        ('sequences = ["{good}"]\n[variants.v]\nmap = "yes"\n', "variants.v.map: expected true/false"),
        ('sequences = ["{good}"]\nframes = "10:5"\n', "frames: frame range '10:5'"),
        ('sequences = ["{good}"]\nframes = "0:999"\n[variants.v]\nframes = "30:40"\n', "sequence 'good':"),
        ("frames = '0:5'\n", "sequences must be a non-empty list"),
        ('sequences = ["{good}/nope"]\n', "sequence 'nope':"),
        ('sequences = ["{good}", "{good}"]\n', "two sequences are named 'good'"),
        ('sequences = [{{ path = "{good}", name = "../up" }}]\n', "sequences[0]: name '../up'"),
        ('sequences = ["{good}"]\n[variants."a b"]\n', "variants.a b: name 'a b'"),
        ('sequences = ["{good}"]\ncpus_per_task = 0\n', "cpus_per_task must be"),
        ('sequences = ["{good}"]\nconfig = "missing.toml"\n', "config: "),
        (
            'sequences = ["{good}"]\n[variants.m]\nmap = {{ enabled = true, trajectory = "batch" }}\n',
            "variants.m: map.trajectory = 'batch' needs",
        ),
        (
            'sequences = ["{good}"]\nmap = true\n[variants.m]\nmap = {{ trajectory = "isam2" }}\n',
            "variants.m: map.trajectory = 'isam2' needs",
        ),
        ("sequences = [", "malformed TOML"),
        ('sequences = ["live:0"]\n', "sequences[0]: a live device cannot be a batch cell"),
        ('sequences = [{{ path = "{good}", topic = "/cam" }}]\n', "sequences[0]: unknown key 'topic'"),
        ('sequences = [{{ path = "{good}", calib = "c.txt" }}]\n', "sequence 'good': "),
    ],
)
def test_plan_errors_name_the_plan_and_the_key(seqs, tmp_path, body, expect):
    plan = write_plan(tmp_path / "plan.toml", body.format(good=seqs["good"]))
    with pytest.raises(SnapsGraphError) as err:
        load_plan(plan)
    msg = str(err.value)
    assert msg.startswith(str(plan)) and expect in msg and "\n" not in msg


def test_cli_bad_plan_is_one_line_error_before_anything_is_written(seqs, tmp_path):
    plan = write_plan(
        tmp_path / "plan.toml", f'sequences = ["{seqs["good"]}"]\n[variants.x]\ngraph = {{ odom_sigma_rot_rad = -1.0 }}\n'
    )
    out = tmp_path / "out"
    proc = cli("batch", plan, "--out", out)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"error: {plan}: variants.x: graph.odom_sigma_rot_rad must be in (0, 3.14159], got -1"
    )
    assert not out.exists()


def test_a_euroc_sequence_is_a_cell_like_any_run_input(tmp_path):
    """Anything `run` reads: here EuRoC (the reader found by what the path holds)."""
    euroc = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc" / "V1_01_easy_first95"
    if not euroc.exists():
        pytest.skip(f"real data not found at {euroc} (it is in CI's ../shared/data)")
    plan = plan_from_dict({"sequences": [str(euroc)], "frames": "0:6", "loops": "none"})
    cell = plan.cells[0]
    assert cell.sequence == "V1_01_easy_first95" and cell.gt is None
    need_extra("threadpoolctl")  # a cell pins its threads
    rec = run_cell(cell, str(tmp_path), threads=1)
    assert rec["status"] == "ok", rec["reason"]
    assert rec["metrics"]["frames"] == 6 and "vo" not in rec["metrics"]  # no ground truth: no metrics per trajectory


# ---------------------------------------------------------------- one cell, without Ray
def test_run_cell_records_ok_and_failed_and_resume_checks_the_hash(seqs, tmp_path):
    need_extra("threadpoolctl")  # a cell pins its threads
    plan = plan_from_dict(
        {
            "sequences": [str(seqs["good"]), str(seqs["broken"])],
            "frames": "0:8",
            "variants": {"a": {}, "b": {"loop": {"radius_m": 5.0}}},
        }
    )
    ok_cell, other_variant, bad_cell = plan.cells[0], plan.cells[1], plan.cells[2]
    rec = run_cell(ok_cell, str(tmp_path), threads=1)
    assert rec["status"] == "ok" and rec["metrics"]["frames"] == 8 and "vo" in rec["metrics"]
    folder = ok_cell.folder(tmp_path)
    assert (folder / "metrics.json").is_file() and (folder / CELL_FILE).is_file()
    done = completed(ok_cell, tmp_path)
    assert done is not None and done["status"] == "skipped"
    assert completed(other_variant, tmp_path) is None  # never ran
    # the same folder with another configuration is not complete for it
    moved = type(ok_cell)(**{**ok_cell.__dict__, "config_hash": other_variant.config_hash})
    assert completed(moved, tmp_path) is None

    bad = run_cell(bad_cell, str(tmp_path), threads=1)
    assert bad["status"] == "failed" and "000005.png: unreadable image" in bad["reason"] and "\n" not in bad["reason"]
    assert not bad_cell.folder(tmp_path).exists()  # whole or absent
    parent = bad_cell.folder(tmp_path).parent
    assert not parent.exists() or not any(p.name.startswith(".") for p in parent.iterdir())


def test_pinned_threads_limits_opencv_and_blas_and_restores_them(monkeypatch):
    need_extra("threadpoolctl")
    import cv2
    from threadpoolctl import threadpool_info

    from snaps_graph.batch import pinned_threads

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    before = cv2.getNumThreads()
    with pinned_threads(1):
        assert cv2.getNumThreads() == 1 and os.environ["OPENBLAS_NUM_THREADS"] == "1"
        assert all(p["num_threads"] == 1 for p in threadpool_info())
    assert cv2.getNumThreads() == before and "OPENBLAS_NUM_THREADS" not in os.environ


# ---------------------------------------------------------------- on a 2-node Ray cluster
@pytest.fixture(scope="module")
def cluster():
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    node: dict[str, Any] = {"num_cpus": 1, "node_ip_address": "127.0.0.1", "object_store_memory": 100 * 2**20}
    c = Cluster(initialize_head=True, head_node_args={**node, "include_dashboard": False})
    c.add_node(**node)
    c.wait_for_nodes()
    try:
        yield c
    finally:
        if ray.is_initialized():
            ray.shutdown()
        c.shutdown()


def read_summary(out: Path) -> list[dict]:
    with open(out / "summary.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_cluster_cells_land_on_both_nodes_and_a_rerun_skips_them(cluster, seqs, tmp_path):
    import ray

    plan = plan_from_dict(
        {
            "sequences": [str(seqs["good"]), {"path": str(seqs["good"]), "name": "again"}, str(seqs["broken"])],
            "frames": "0:12",
            "variants": {"a": {}, "b": {"loop": {"radius_m": 5.0}}},
        }
    )
    out = tmp_path / "out"
    rows = run_batch(plan, out, address=cluster.address, progress=False)
    assert not ray.is_initialized()  # the batch disconnected from the cluster it joined

    summary = read_summary(out)
    assert [(r["sequence"], r["variant"], r["status"]) for r in summary] == [
        ("good", "a", "ok"),
        ("good", "b", "ok"),
        ("again", "a", "ok"),
        ("again", "b", "ok"),
        ("broken", "a", "failed"),
        ("broken", "b", "failed"),
    ]
    assert all("unreadable image" in r["reason"] for r in summary[4:])
    nodes = {n["NodeID"] for n in _alive_nodes(cluster)}
    used = {r["node"] for r in summary[:4]}
    assert len(nodes) == 2 and used == nodes, f"cells ran on {used}, cluster nodes {nodes}"
    for r in summary[:4]:
        assert float(r["vo_mean_dev_m"]) >= 0 and r["config_hash"] and r["version"]
        assert (out / r["sequence"] / r["variant"] / "metrics.json").is_file()
    assert (out / "summary.md").read_text().count("| ok |") == 4
    assert [r["status"] for r in rows] == [r["status"] for r in summary]

    again = run_batch(plan, out, address=cluster.address, progress=False)
    assert [r["status"] for r in again] == ["skipped"] * 4 + ["failed"] * 2  # failed cells are tried again
    assert [r["status"] for r in read_summary(out)] == ["skipped"] * 4 + ["failed"] * 2
    assert [r["node"] for r in read_summary(out)[:4]] == [r["node"] for r in summary[:4]]  # as recorded when run


def _alive_nodes(cluster) -> list[dict]:
    import ray

    ray.init(address=cluster.address)
    try:
        return [n for n in ray.nodes() if n["Alive"]]
    finally:
        ray.shutdown()


@pytest.mark.parametrize("kill", [False, True], ids=["ctrl-c", "kill"])
def test_ctrl_c_cancels_the_cells_and_exits_130(cluster, seqs, tmp_path, kill):
    """Ctrl-C at the terminal (SIGINT to the group) and `kill` (SIGTERM to the driver) alike."""
    variants = "".join(f"[variants.v{i}]\nloop = {{ radius_m = {5 + i}.0 }}\n" for i in range(8))
    plan = write_plan(tmp_path / "plan.toml", f'sequences = ["{seqs["good"]}"]\n{variants}')
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "snaps_graph.cli", "batch", str(plan), "--out", str(out), "--address", cluster.address],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not _cell_running(out):
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        if kill:
            proc.send_signal(signal.SIGTERM)  # what `kill PID` or a scheduler's stop does
        else:
            os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1].startswith("interrupted:")
    assert "Traceback" not in err
    statuses = [r["status"] for r in read_summary(out)]
    assert "cancelled" in statuses and set(statuses) <= {"ok", "cancelled"}
    # nothing half-written: every cell folder is complete or absent, no temporary folders left
    for p in (out / "good").iterdir() if (out / "good").exists() else []:
        assert not p.name.startswith("."), p
        assert (p / "metrics.json").is_file() and (p / CELL_FILE).is_file()


def _cell_running(out: Path) -> bool:
    """A cell of this batch is running: its temporary results folder exists (made at its start).
    Not a process listing: other batches on the machine run cells too."""
    folder = out / "good"
    return folder.is_dir() and any(p.name.startswith(".") and ".tmp-" in p.name for p in folder.iterdir())


def test_an_address_nothing_answers_on_is_a_one_line_error(seqs, tmp_path):
    plan = plan_from_dict({"sequences": [str(seqs["good"])], "frames": "0:4"})
    out = tmp_path / "out"
    with pytest.raises(SnapsGraphError, match=r"^--address 127\.0\.0\.1:1: no Ray cluster answers there"):
        run_batch(plan, out, address="127.0.0.1:1", progress=False)
    assert not (out / "summary.csv").exists()


# ---------------------------------------------------------------- never stale, never on an input
def test_resume_is_keyed_on_the_inputs_content_and_checks_the_folder_whole(seqs, tmp_path):
    need_extra("threadpoolctl")  # a cell pins its threads
    seq = tmp_path / "seq"
    shutil.copytree(seqs["good"], seq)
    body = {"sequences": [str(seq)], "frames": "0:6"}
    cell = plan_from_dict(body).cells[0]
    out = tmp_path / "out"
    assert run_cell(cell, str(out), threads=1)["status"] == "ok"
    done = completed(plan_from_dict(body).cells[0], out)
    assert done is not None and done["status"] == "skipped"
    # another ground truth (same path): not the same run
    poses = (seq / "poses.txt").read_text().splitlines()
    (seq / "poses.txt").write_text("\n".join(poses[1:] + poses[:1]) + "\n")
    assert completed(plan_from_dict(body).cells[0], out) is None
    (seq / "poses.txt").write_text("\n".join(poses) + "\n")
    # another calibration: not the same run either
    calib = (seq / "calib.txt").read_text()
    (seq / "calib.txt").write_text(calib.replace("P0:", "P0: ", 1))
    assert completed(plan_from_dict(body).cells[0], out) is None
    # the same inputs again, but a pose file of the folder deleted: re-run, not skipped
    (seq / "calib.txt").write_text(calib)
    fresh = plan_from_dict(body).cells[0]
    assert run_cell(fresh, str(out), threads=1)["status"] == "ok"
    assert completed(fresh, out) is not None
    (fresh.folder(out) / "poses_vo.txt").unlink()
    assert completed(fresh, out) is None


def test_a_cell_folder_never_lands_on_an_input(seqs, tmp_path):
    data = tmp_path / "data"
    seq = data / "seq"
    shutil.copytree(seqs["good"], seq)

    def digest():
        return {p: p.read_bytes() for p in sorted(data.rglob("*")) if p.is_file()}

    before = digest()
    plan = plan_from_dict({"sequences": [str(seq)], "frames": "0:4", "variants": {"image_0": {}}})
    with pytest.raises(SnapsGraphError, match=r"cell seq/image_0: its folder .* lies inside the input sequence"):
        run_batch(plan, data, progress=False)  # --out on the folder holding the data
    with pytest.raises(SnapsGraphError, match=r"lies inside the input sequence"):
        run_batch(plan_from_dict({"sequences": [str(seq)], "frames": "0:4"}), seq / "image_0", progress=False)
    (data / "summary.csv").write_text("the user's own table\n")  # a folder a batch did not write
    before = digest()
    with pytest.raises(SnapsGraphError, match=r"not a folder this tool wrote"):
        run_batch(plan_from_dict({"sequences": [{"path": str(seq), "name": "other"}], "frames": "0:4"}), data, progress=False)
    assert digest() == before and not (data / ".batch.lock").exists()


def test_cpus_per_task_above_the_machine_is_a_one_line_error(seqs, tmp_path):
    plan = plan_from_dict({"sequences": [str(seqs["good"])], "frames": "0:4", "cpus_per_task": 1000})
    with pytest.raises(SnapsGraphError, match=r"cpus_per_task = 1000, but this machine has \d+ CPUs"):
        run_batch(plan, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_an_address_where_something_else_listens_fails_at_once_and_leaves_no_lock(seqs, tmp_path):
    import socket
    import threading

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)

    def answer():  # an HTTP/1 server: reads a request, answers, closes
        conn, _ = server.accept()
        conn.recv(100)
        conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")
        conn.close()

    threading.Thread(target=answer, daemon=True).start()
    address = f"127.0.0.1:{server.getsockname()[1]}"
    plan = plan_from_dict({"sequences": [str(seqs["good"])], "frames": "0:4"})
    t0 = time.monotonic()
    with pytest.raises(SnapsGraphError, match=r"something answers there, but not a Ray cluster"):
        run_batch(plan, tmp_path / "out", address=address, progress=False)
    assert time.monotonic() - t0 < 10
    assert not (tmp_path / "out" / ".batch.lock").exists()
    server.close()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["term", "kill-9"])
def test_a_worker_killed_by_a_signal_is_reported_with_it_and_leaves_no_temporary_folder(cluster, seqs, tmp_path, sig):
    """The cell's worker killed (each attempt: Ray retries a lost worker once): the summary names
    the signal (one the worker cannot catch said as such) and the cell's folder holds nothing."""
    import threading

    long = tmp_path / "long"
    shutil.copytree(seqs["good"], long)
    for side in ("image_0", "image_1"):  # the 24 pairs repeated to 3000 frames: a cell of minutes
        src = sorted((long / side).glob("*.png"))
        for i in range(len(src), 3000):
            os.link(src[i % len(src)], long / side / f"{i:06d}.png")
    (long / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(3000)))
    (long / "poses.txt").unlink()
    out = tmp_path / "out"
    rows: list[dict] = []
    driver = threading.Thread(
        target=lambda: rows.extend(
            run_batch(plan_from_dict({"sequences": [str(long)]}), out, address=cluster.address, progress=False)
        )
    )
    driver.start()
    killed: set[int] = set()
    deadline = time.monotonic() + 240
    while driver.is_alive() and time.monotonic() < deadline:
        folder = out / "long"
        for tmp in folder.glob(".default.tmp-*") if folder.is_dir() else []:
            pid = int(tmp.name.rsplit("-", 1)[1])  # the worker running the cell
            if pid not in killed:
                time.sleep(0.5)  # into the frames
                killed.add(pid)
                os.kill(pid, sig)
        time.sleep(0.05)
    driver.join(timeout=60)
    assert killed and rows and rows[0]["status"] == "failed", rows
    reason = rows[0]["reason"]
    expect = "killed by SIGTERM" if sig == signal.SIGTERM else "killed by a signal it cannot catch (SIGKILL"
    assert expect in reason and "its unfinished folder removed" in reason, reason
    assert [p.name for p in (out / "long").iterdir()] == []  # no temporary folder, no lock
