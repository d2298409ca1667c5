"""Point-cloud map (SPEC "Map"): keyframe clouds in camera frames, posed on demand.

The only part of the package that imports open3d, and only lazily inside ``CloudMap``'s
methods, so ``import snaps_graph`` does not load it.
"""

from .cloud_map import CloudMap
from .outputs import write_map_outputs

__all__ = ["CloudMap", "write_map_outputs"]
