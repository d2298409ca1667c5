"""One map of all sessions: this run's ``map.ply`` with each relocalised prior's, in the outputs'
frame. The priors' maps are moved rigidly by where the run placed them (their fused surfaces are
kept; the joint refinement's bending of a prior's trajectory does not re-fuse its map)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .outputs import _write_points_ply

MAP_FILE = "map.ply"
SESSIONS_FILE = "map_sessions.ply"


def write_sessions_map(out: Path, priors: list[tuple[Path, np.ndarray]]) -> dict | None:
    """``map_sessions.ply`` from ``out``'s map.ply and each (prior folder, T_out_prior) whose
    folder holds a map.ply; None (nothing written) without this run's map or any prior's."""
    import open3d as o3d

    own = out / MAP_FILE
    parts = [(own, np.eye(4))] + [(Path(p) / MAP_FILE, T) for p, T in priors if (Path(p) / MAP_FILE).is_file()]
    if not own.is_file() or len(parts) == 1:
        return None
    points, greys = [], []
    for path, T in parts:
        cloud = o3d.io.read_point_cloud(str(path))
        xyz = np.asarray(cloud.points)
        points.append(xyz @ T[:3, :3].T + T[:3, 3])
        colours = np.asarray(cloud.colors)
        greys.append(colours[:, 0] * 255.0 if len(colours) == len(xyz) else np.full(len(xyz), 128.0))
    _write_points_ply(out / SESSIONS_FILE, np.concatenate(points), np.concatenate(greys))
    return {"file": SESSIONS_FILE, "sessions": len(parts), "points": int(sum(len(p) for p in points))}
