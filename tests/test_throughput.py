"""Speed work that must not change results: reading ahead, the front end's thread overlap."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest

from snaps_graph.config import FrontendConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.errors import SnapsGraphError
from snaps_graph.frontend import StereoOdometry
from snaps_graph.io_utils import prefetch


def _prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "prefetch"]


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_prefetch_yields_every_item_in_order(depth):
    assert list(prefetch(iter(range(50)), depth)) == list(range(50))
    assert list(prefetch([], depth)) == []


def test_prefetch_raises_the_source_error_at_its_place():
    def source():
        yield from range(5)
        raise SnapsGraphError("000005.png: unreadable image")

    got = []
    with pytest.raises(SnapsGraphError, match="000005.png: unreadable image"):
        for x in prefetch(source(), 2):
            got.append(x)
    assert got == [0, 1, 2, 3, 4]


def test_prefetch_stops_reading_when_the_consumer_stops():
    read = []

    def source():
        for i in range(1000):
            read.append(i)
            yield i

    with contextlib.closing(prefetch(source(), 2)) as items:
        for x in items:
            if x == 3:
                break
    time.sleep(0.3)
    assert not _prefetch_threads()
    assert len(read) <= 4 + 2 + 1  # what was consumed, the queue, the item in hand


def test_prefetched_frames_equal_the_reader_frames(tiny_seq):
    seq = KittiSequence(tiny_seq)
    for a, b in zip(seq, prefetch(seq, 2), strict=True):
        assert a.index == b.index and a.timestamp == b.timestamp
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)


def test_front_end_threads_do_not_change_the_result(kitti06_dir):
    """threads = 2 overlaps stereo with PnP and re-detection with the stereo BA; threads = 1
    runs the same stages in order: the poses must be the same bits."""
    frames = list(KittiSequence(kitti06_dir, frames="0:8"))
    runs = []
    for threads in (1, 2):
        with StereoOdometry(KittiSequence(kitti06_dir, frames="0:1").camera, FrontendConfig(threads=threads)) as vo:
            runs.append([vo.process(frames[0])])
            assert vo._klt is not None
            n_first = vo._klt._next_id  # landmark ids handed out to the first frame's corners
            runs[-1] += [vo.process(f) for f in frames[1:]]
            assert vo._klt._next_id > n_first  # re-detection ran after the first frame
    for a, b in zip(*runs):
        assert a.ok and b.ok
        assert np.array_equal(a.pose, b.pose)
        assert np.array_equal(a.features.uv, b.features.uv)


_FAULTS = """
import resource, cv2, numpy as np
import snaps_graph.backend  # gtsam: after this import glibc's defaults faulted on every call
from snaps_graph import _malloc
applied = _malloc.set_malloc_thresholds()
img = (np.random.default_rng(0).random((376, 1241)) * 255).astype(np.uint8)
cv2.goodFeaturesToTrack(img, 1000, 0.01, 10)
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    cv2.goodFeaturesToTrack(img, 1000, 0.01, 10)
print(applied, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 5)
"""


def test_image_temporaries_do_not_page_fault_on_every_call():
    """A KITTI-sized corner detection allocates about 11 MB of temporaries; with the package's
    malloc thresholds they are reused, not faulted in afresh on every call."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _FAULTS], capture_output=True, text=True, check=True).stdout.split()
    if out[0] != "True":
        pytest.skip("malloc thresholds not applied here (not glibc, or MALLOC_*_ set)")
    assert float(out[1]) < 500  # 11 MB afresh would be ~2700 faults


def test_cli_prefetch_option_gives_the_same_results(tiny_seq, tmp_path):
    from inprocess import cli

    outs = []
    for n in ("0", "3"):
        out = tmp_path / f"run{n}"
        proc = cli("run", tiny_seq, "--out", out, "--prefetch", n)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "wall" in proc.stdout and "frames/s" in proc.stdout
        outs.append(out)
    assert (outs[0] / "poses_vo.txt").read_text() == (outs[1] / "poses_vo.txt").read_text()
    assert (outs[0] / "poses_snaps.txt").read_text() == (outs[1] / "poses_snaps.txt").read_text()
