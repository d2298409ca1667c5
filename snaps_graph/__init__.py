"""snaps_graph: stereo visual SLAM with SNAPS loop closure feeding a GTSAM pose graph.

The public surface is here; each name is imported on first use, so ``import snaps_graph`` stays
light (no OpenCV, gtsam or open3d until a run needs them)::

    from snaps_graph import Config, open_dataset, run_sequence

    result, metrics = run_sequence(open_dataset("data/kitti/sequences/06"), "results/06", Config())
"""

from __future__ import annotations

from importlib import import_module as _import_module
from typing import Any

__version__ = "0.1.0"

# name -> the module that defines it (imported by name here, not at the top: the root imports no
# module of its own, so no import circle runs through it)
_EXPORTS = {
    "Config": "config",
    "StereoCamera": "camera",
    "StereoFrame": "types",
    "StereoSource": "types",
    "open_dataset": "datasets.open",
    "SlamPipeline": "pipeline",
    "FrameOutput": "pipeline",
    "RunResult": "pipeline",
    "run_sequence": "runner",
    "write_results": "runner",
    "read_session": "session",
    "Session": "session",
    "SnapsGraphError": "errors",
}

__all__ = [
    "Config",
    "FrameOutput",
    "RunResult",
    "Session",
    "SlamPipeline",
    "SnapsGraphError",
    "StereoCamera",
    "StereoFrame",
    "StereoSource",
    "__version__",
    "open_dataset",
    "read_session",
    "run_sequence",
    "write_results",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'snaps_graph' has no attribute {name!r}")
    value = getattr(_import_module(f".{module}", __name__), name)
    globals()[name] = value  # once imported, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
