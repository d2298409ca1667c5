"""Synthetic stereo sequences with exact ground truth: a procedural world (_world.py), its
shading (_shade.py) and the rendered sequence and folder writer (sequence.py)."""

from .sequence import (
    SCENES,
    RenderedFrame,
    SyntheticSequence,
    WorldConfig,
    builtin_loop_trajectory,
    load_trajectory,
    render_to_folder,
)

__all__ = [
    "SCENES",
    "RenderedFrame",
    "SyntheticSequence",
    "WorldConfig",
    "builtin_loop_trajectory",
    "load_trajectory",
    "render_to_folder",
]
