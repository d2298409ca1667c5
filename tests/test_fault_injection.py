"""A run killed (as by kill -9) at every write and rename of its results folder: the folder is then
exactly the old results (absent where there were none) or exactly the new ones once the next start
has recovered the leftovers, and that start says what it did.

The kill is the test-only hook ``io_utils.FAULT_ENV``: ``os._exit`` at the Nth filesystem step. The
pipeline runs once; each kill is a forked child writing the same results, so the test takes seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import pytest

from snaps_graph import io_utils
from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.io_utils import FAULT_ENV, MARKER, check_output_folder
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import write_results

KILLED = 137


def digest(folder: Path) -> dict[str, str] | None:
    """Every file under ``folder`` and its content hash (metrics.json without the process's peak
    memory, which differs between processes); None when the folder is absent."""
    if not folder.exists():
        return None
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            data = p.read_bytes()
            if p.name == "metrics.json":
                m = json.loads(data)
                m.pop("peak_rss_mb", None)
                data = json.dumps(m, sort_keys=True).encode()
            out[str(p.relative_to(folder))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.fixture(scope="module")
def finished(tiny_seq):
    seq = KittiSequence(tiny_seq, frames="0:4")
    pipe = SlamPipeline(seq.camera, Config(), loops="none", refine="none")
    for f in seq:
        pipe.process(f)
    return pipe, pipe.finish(), seq.gt_poses


def write_in_child(out: Path, finished, fault_at: int | None, gt: bool = True) -> int:
    """Write the results folder in a forked child, killed at step ``fault_at``; its exit status."""
    pipe, result, gt_poses = finished
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fork with threads: the child only writes files
        pid = os.fork()
    if pid == 0:
        code = 1
        try:
            io_utils._FAULT_COUNT[0] = 0
            if fault_at is not None:
                os.environ[FAULT_ENV] = str(fault_at)
            write_results(out, pipe, result, gt_poses if gt else None, overwrite=True)
            code = 0
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


@pytest.mark.parametrize("with_old", [False, True], ids=["new-folder", "replacing-old"])
def test_a_kill_at_every_step_leaves_old_or_new_results_and_the_next_start_recovers(finished, tmp_path, capfd, with_old):
    new_ref, old_ref = tmp_path / "new_ref", tmp_path / "old_ref"
    assert write_in_child(new_ref, finished, None) == 0
    assert write_in_child(old_ref, finished, None, gt=False) == 0  # other results: no ground truth
    new, old = digest(new_ref), digest(old_ref)
    assert new is not None
    assert new != old and MARKER in new
    steps = 0
    for n in range(1, 100):
        out = tmp_path / f"run{n}"
        if with_old:
            assert write_in_child(out, finished, None, gt=False) == 0
        code = write_in_child(out, finished, n)
        if code == 0:  # past the last step: the whole write went through
            assert digest(out) == new and not leftovers(out)
            break
        assert code == KILLED
        steps += 1
        had = leftovers(out)
        capfd.readouterr()
        check_output_folder(out, overwrite=True)  # the next start
        notes = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
        assert not leftovers(out), (n, leftovers(out))
        assert digest(out) in ((old, new) if with_old else (None, new)), n
        assert len(notes) == len(had) and all(line.startswith("note: ") and "killed" in line for line in notes), (n, had, notes)
    # mkdir, one per file but the marker, the marker's list, the swap (and: move the old aside,
    # delete it, done)
    assert steps == 1 + (len(new) - 1) + 1 + 1 + (3 if with_old else 0), steps


def test_recovery_touches_only_folders_this_tool_wrote(tmp_path, capfd):
    out = tmp_path / "run"
    stranger = tmp_path / ".run.tmp-999999999"  # named like a leftover, but not ours (no marker)
    stranger.mkdir()
    (stranger / "thesis.tex").write_text("mine\n")
    check_output_folder(out, overwrite=True)
    assert (stranger / "thesis.tex").read_text() == "mine\n"
    assert "note:" not in capfd.readouterr().err
