"""Map: keyframe depth fused into a TSDF mesh under any trajectory (``FusedMap``), its files and
pictures (``outputs``), accuracy against a true world mesh (``accuracy``). The only part of the
package that imports open3d, and only lazily inside methods.
"""

from .outputs import write_map_outputs
from .tsdf import FusedMap, FusedSurface

__all__ = ["FusedMap", "FusedSurface", "write_map_outputs"]
