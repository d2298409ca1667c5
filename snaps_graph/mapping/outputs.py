"""The map's files in a results folder: ``map.ply``, ``map.png`` and, with ``per_trajectory``,
``map_<trajectory>.ply``. The runner calls :func:`write_map_outputs` once, after the run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import MapConfig
from ..errors import SnapsGraphError
from .cloud_map import CloudMap

BEST_ORDER = ("batch", "isam2", "snaps", "vo")  # map.trajectory = "best": the most refined available


def map_trajectory_name(want: str, available: list[str] | tuple[str, ...]) -> str:
    """The trajectory ``map.trajectory`` names among those a run computed."""
    if want == "best":
        for name in BEST_ORDER:
            if name in available:
                return name
    if want not in available:
        raise SnapsGraphError(f"map.trajectory = '{want}' was not computed in this run (have: {', '.join(available)})")
    return want


def write_map_outputs(
    out_dir: str | Path,
    cloud_map: CloudMap,
    trajectories: dict[str, np.ndarray],
    gt_poses: np.ndarray | None,
    cfg: MapConfig,
) -> dict | None:
    """Write the map files into ``out_dir``; returns metrics.json's ``map`` entry (None when the
    map holds no point, and nothing is written)."""
    if cloud_map.num_stored_points() == 0:
        return None
    out = Path(out_dir)
    name = map_trajectory_name(cfg.trajectory, list(trajectories))
    poses = trajectories[name]
    cloud = cloud_map.build(poses)  # built once, for both the PLY and the picture
    cloud_map.write_ply(out / "map.ply", poses, cloud=cloud)
    trajs = dict(trajectories)
    if gt_poses is not None:
        trajs = {"gt": gt_poses, **trajs}
    cloud_map.render_topdown_png(out / "map.png", poses, trajs, cloud=cloud)
    if cfg.per_trajectory:  # re-posed from the stored keyframe clouds
        for tname, tposes in trajectories.items():
            cloud_map.write_ply(out / f"map_{tname}.ply", tposes)
    return {"trajectory": name, "keyframes": len(cloud_map), "bytes": cloud_map.memory_bytes()}
