"""The map files of a results folder, written in one call (``write_map_outputs``), and the map
section of ``compare``'s report: ``map_mesh.ply``, ``map.ply`` (its vertices), ``map.png``,
``map_mesh.png``, with ``--map-all`` one map per trajectory, and with a world mesh the accuracy
per trajectory and ``map_compare.png`` (each map coloured by its distance to the true surface).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..config import MapConfig
from ..errors import SnapsGraphError
from ..geometry import umeyama_alignment
from ..io_utils import atomic_output
from .accuracy import MIN_SAMPLES, RANGE_M, TOLERANCE_M

_PICTURE_POINTS = 200_000
BEST_ORDER = ("batch", "isam2", "snaps", "vo")  # map.trajectory = "best": the most refined available


def _map_trajectory_name(want: str, available: list[str] | tuple[str, ...]) -> str:
    """The trajectory ``map.trajectory`` names among those a run computed."""
    if want == "best":
        for name in BEST_ORDER:
            if name in available:
                return name
    if want not in available:
        raise SnapsGraphError(f"map.trajectory = '{want}' was not computed in this run (have: {', '.join(available)})")
    return want


def _write_mesh_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray, grey: np.ndarray | None = None) -> None:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(vertices.astype(np.float64))
    m.triangles = o3d.utility.Vector3iVector(triangles.astype(np.int32))
    if grey is not None and len(grey) == len(vertices):
        m.vertex_colors = o3d.utility.Vector3dVector(np.repeat(grey.astype(np.float64)[:, None] / 255.0, 3, axis=1))
    with atomic_output(path, suffix=".ply") as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), m, write_ascii=False, compressed=False):
            raise SnapsGraphError(f"{path}: open3d could not write the mesh")


def _write_points_ply(path: Path, points: np.ndarray, grey: np.ndarray | None = None) -> None:
    import open3d as o3d

    p = o3d.geometry.PointCloud()
    p.points = o3d.utility.Vector3dVector(points.astype(np.float64))
    if grey is not None and len(grey) == len(points):
        p.colors = o3d.utility.Vector3dVector(np.repeat(grey.astype(np.float64)[:, None] / 255.0, 3, axis=1))
    with atomic_output(path, suffix=".ply") as tmp:
        if not o3d.io.write_point_cloud(str(tmp), p, write_ascii=False, compressed=False):
            raise SnapsGraphError(f"{path}: open3d could not write the point cloud")


def write_map_outputs(
    out_dir: str | Path,
    fused_map,
    trajectories: dict[str, np.ndarray],
    gt: np.ndarray | None,
    cfg: MapConfig,
    world_mesh: str | Path | None = None,
) -> dict | None:
    """Fuse ``fused_map`` (a ``FusedMap``) under the trajectory ``cfg.trajectory`` names and
    write the map files into ``out_dir``; fuse again under the other trajectories when
    ``cfg.per_trajectory`` or a ``world_mesh`` (the true world, for the accuracy) asks. Returns metrics.json's ``map`` entry
    (None when the map has no keyframe, and nothing is written). The runner calls this once."""
    if len(fused_map) == 0:
        return None
    chosen = _map_trajectory_name(cfg.trajectory, list(trajectories))
    from .render import side_by_side_png

    t0 = time.perf_counter()
    out = Path(out_dir)
    world = None
    if world_mesh:
        from .accuracy import WorldSurface

        world = WorldSurface(world_mesh)
    cam = fused_map.camera
    entry: dict = {
        "trajectory": chosen,
        "keyframes": len(fused_map),
        "bytes": fused_map.memory_bytes(),
        "camera": [cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height],
        "keyframe_every": cfg.keyframe_every,
        "surfaces": {},
    }
    names = [chosen] + ([n for n in trajectories if n != chosen] if (cfg.per_trajectory or world is not None) else [])
    if world is not None and gt is not None:
        names.append("gt")  # the map under the true poses: what depth and fusion alone achieve
    pictures: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    t_acc = 0.0
    for name in names:
        surf = fused_map.fuse(gt if name == "gt" else trajectories[name])
        if len(surf.vertices) == 0:
            if name == chosen:  # flagged, not fatal: the rest of the run's results stand
                entry["empty"] = (
                    f"the fused map is empty (no surface seen by {fused_map.min_weight:g} "
                    "keyframe(s) with valid depth); no map files written"
                )
                return entry
            continue
        tf = time.perf_counter()
        suffixes = ([""] if name == chosen else []) + ([f"_{name}"] if cfg.per_trajectory and name != "gt" else [])
        for suffix in suffixes:
            _write_mesh_ply(out / f"map_mesh{suffix}.ply", surf.vertices, surf.triangles, surf.vertex_grey)
            _write_points_ply(out / f"map{suffix}.ply", surf.points, surf.point_grey)
        entry.setdefault("t_files_s", 0.0)
        entry["t_files_s"] += time.perf_counter() - tf
        if name == chosen:
            tp = time.perf_counter()
            _map_pictures(out, surf, chosen, trajectories, gt, cfg)
            entry["t_pictures_s"] = time.perf_counter() - tp  # map.png and map_mesh.png
        entry["surfaces"][name] = {k: v for k, v in surf.stats.items()}
        stride = max(1, len(surf.points) // _PICTURE_POINTS)
        err = None
        if world is not None:
            ta = time.perf_counter()
            entry.setdefault("accuracy", {})[name] = _surface_accuracy(world, surf, name, fused_map, trajectories, gt)
            err = world.distance(surf.points[::stride])
            t_acc += time.perf_counter() - ta
        pictures[name] = (surf.points[::stride].copy(), err)
        del surf
    if len(pictures) > 1:
        side_by_side_png(out / "map_compare.png", pictures, ({"gt": gt} if gt is not None else {}) | dict(trajectories))
    if world is not None:
        entry["world_mesh"] = str(world.path)
    entry["t_accuracy_s"] = t_acc  # measuring against the world mesh (not map work)
    entry["t_output_s"] = time.perf_counter() - t0 - t_acc  # fusion, files and pictures
    return entry


def _map_pictures(
    out: Path, surf, chosen: str, trajectories: dict[str, np.ndarray], gt: np.ndarray | None, cfg: MapConfig
) -> None:
    """map.png (top-down points under every trajectory) and map_mesh.png (the mesh in perspective)."""
    from .render import perspective_png, topdown_png

    trajs = ({"gt": gt} if gt is not None else {}) | dict(trajectories)
    topdown_png(
        out / "map.png",
        surf.points,
        trajs,
        grey=surf.point_grey,
        title=f"fused map ({chosen}), top-down: {len(surf.points)} surface points, voxel {cfg.tsdf_voxel_m:g} m",
    )
    perspective_png(
        out / "map_mesh.png",
        surf.vertices,
        surf.triangles,
        trajectories[chosen],
        title=f"fused mesh ({chosen}): {len(surf.triangles)} triangles, voxel {cfg.tsdf_voxel_m:g} m",
    )


def _surface_accuracy(world, surf, name: str, fused_map, trajectories: dict[str, np.ndarray], gt: np.ndarray | None) -> dict:
    """The accuracy of the map fused under trajectory ``name`` against the world mesh."""
    from .accuracy import map_accuracy

    cam = fused_map.camera
    ref = gt if gt is not None else trajectories[name]  # the surface to map: seen from the true path
    align = trajectory_alignment(trajectories[name], gt) if name != "gt" else None
    return map_accuracy(
        world,
        surf.points,
        surf.vertices,
        ref[fused_map.keyframes],
        cam.K,
        (cam.width, cam.height),
        alignment=align,
    )


def accuracy_from_files(
    run_dir: str | Path,
    world_mesh: str | Path,
    trajectories: dict[str, np.ndarray],
    map_entry: dict,
    gt: np.ndarray | None,
    range_m: float = RANGE_M,
    tolerance_m: float = TOLERANCE_M,
    min_samples: int = MIN_SAMPLES,
) -> dict:
    """Accuracy of every map in a results folder (map.ply / map_mesh.ply of the chosen
    trajectory, map_<name>.ply / map_mesh_<name>.ply of the others) against ``world_mesh``;
    the camera and keyframe spacing come from metrics.json's ``map`` entry."""
    import open3d as o3d

    from .accuracy import WorldSurface, map_accuracy

    run = Path(run_dir)
    if "camera" not in map_entry:
        raise SnapsGraphError(f"{run / 'metrics.json'}: no map entry with a camera (was the run made with --map?)")
    fx, fy, cx, cy, w, h = map_entry["camera"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    every = int(map_entry.get("keyframe_every", 5))
    chosen = map_entry.get("trajectory", "")
    world = WorldSurface(world_mesh)
    out = {}
    for name, poses in trajectories.items():
        suffix = "" if name == chosen else f"_{name}"
        pp, mp = run / f"map{suffix}.ply", run / f"map_mesh{suffix}.ply"
        if not (pp.is_file() and mp.is_file()):
            continue
        pts = np.asarray(o3d.io.read_point_cloud(str(pp)).points, np.float32)
        verts = np.asarray(o3d.io.read_triangle_mesh(str(mp)).vertices, np.float32)
        ref = gt if gt is not None and len(gt) == len(poses) else poses
        out[name] = map_accuracy(
            world,
            pts,
            verts,
            ref[::every],
            K,
            (int(w), int(h)),
            range_m,
            tolerance_m,
            min_samples=min_samples,
            alignment=trajectory_alignment(poses, gt),
        )
    return out


def trajectory_alignment(poses: np.ndarray, gt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) moving ``poses``' positions onto ``gt``'s (SE(3) Umeyama, as the ATE), or None
    without a ground truth of the same length."""
    if gt is None or len(gt) != len(poses) or len(poses) < 3:
        return None
    R, t, _ = umeyama_alignment(poses[:, :3, 3], gt[:, :3, 3])
    return R, t
