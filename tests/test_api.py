"""The package root: the names a user starts from, each the defining module's own object, and
``import snaps_graph`` alone stays light."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import snaps_graph
from snaps_graph.types import SequenceBase, StereoSource


def test_the_root_exports_the_public_surface():
    from snaps_graph import Config, SlamPipeline, StereoFrame, open_dataset, run_sequence
    from snaps_graph.config import Config as C
    from snaps_graph.datasets.open import open_dataset as o
    from snaps_graph.pipeline import SlamPipeline as S
    from snaps_graph.runner import run_sequence as r
    from snaps_graph.types import StereoFrame as F

    assert (Config, SlamPipeline, StereoFrame, open_dataset, run_sequence) == (C, S, F, o, r)
    for name in snaps_graph.__all__:
        assert getattr(snaps_graph, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        snaps_graph.nope  # noqa: B018


def test_importing_the_package_imports_no_heavy_library():
    code = "import sys, snaps_graph; print([m for m in ('cv2', 'gtsam', 'open3d', 'matplotlib', 'scipy') if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_stereo_source_has_no_reader_specifics():
    members = set(StereoSource.__dict__)
    assert not {"left_topic", "right_topic"} & members and "source_info" in members
    assert dict(SequenceBase().source_info) == {}


def test_the_readme_example_runs_as_written(tiny_seq, tmp_path, monkeypatch):
    """The README's Python block, on the tiny sequence in place of make demo's."""
    text = (Path(__file__).parents[1] / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S)
    assert block, "README.md: no Python example"
    code = block.group(1).replace('"results/demo/sequence"', repr(str(tiny_seq)))
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    assert (tmp_path / "results" / "api_run" / "poses_isam2.txt").is_file()
