"""Map accuracy against the true world surface (a triangle mesh, e.g. ``synth --world-mesh``).

Error: each map point's and mesh vertex's distance to the true surface (median, p90).
Completeness: the share of the true surface near the path, and of the part a camera saw, within
``tolerance_m`` of the map. The definitions and why both: docs/decisions.md, "Map".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SnapsGraphError

MIN_SAMPLES = 200_000  # surface samples within range wanted (a share: +-0.1 % at 70 %)
RANGE_M = 20.0  # completeness counts true surface within this of the path: what a 15 m map range can see, m
TOLERANCE_M = 0.2  # ...and within this of the map: about the TSDF voxel and the stereo depth error at 10 m, m


class WorldSurface:
    """The true world: a triangle mesh loaded once, queried for distances and sampled."""

    def __init__(self, mesh_path: str | Path):
        import open3d as o3d

        path = Path(mesh_path)
        if not path.is_file():
            raise SnapsGraphError(f"{path}: world mesh not found")
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) == 0:
            raise SnapsGraphError(f"{path}: not a triangle mesh (no triangles read)")
        self.path = path
        self.vertices = np.asarray(mesh.vertices, np.float32)
        self.triangles = np.asarray(mesh.triangles, np.uint32)
        if not np.all(np.isfinite(self.vertices)):
            raise SnapsGraphError(f"{path}: the mesh has non-finite vertices")
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        a, b, c = (self.vertices[self.triangles[:, i]].astype(np.float64) for i in range(3))
        self._area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        self._cum = np.cumsum(self._area)
        self._samples: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) of each point (n, 3) to the surface."""
        import open3d as o3d

        if len(points) == 0:
            return np.zeros(0, np.float32)
        return self.scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, np.float32))).numpy()

    def samples_near(
        self,
        poses: np.ndarray,
        range_m: float,
        K: np.ndarray,
        size: tuple[int, int],
        seed: int = 0,
        min_samples: int = MIN_SAMPLES,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Uniform area samples of the surface within ``range_m`` of the positions of ``poses``
        ((n, 4, 4) T_world_cam), and for each whether one of these cameras (intrinsics ``K``,
        image ``size`` = (w, h)) sees: in view of one of its 8 nearest cameras, unblocked. Cached."""
        from scipy.spatial import cKDTree

        positions = poses[:, :3, 3]
        key = (poses.shape, float(np.sum(poses)), float(range_m), seed, min_samples)
        if key in self._samples:
            return self._samples[key]
        tree = cKDTree(positions)
        rng = np.random.default_rng(seed)
        kept: list[np.ndarray] = []
        n_kept = 0
        per_round = min(2_000_000, 5 * min_samples)
        for _ in range(20):  # enough rounds for ~min_samples, even along a short path in a big world
            tri = np.searchsorted(self._cum, rng.random(per_round) * self._cum[-1])
            tri = np.minimum(tri, len(self.triangles) - 1)
            r1, r2 = np.sqrt(rng.random(len(tri))), rng.random(len(tri))
            a, b, c = (self.vertices[self.triangles[tri, i]] for i in range(3))
            p = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
            d, _ = tree.query(p, distance_upper_bound=range_m)
            p = p[np.isfinite(d)]
            kept.append(p.astype(np.float32))
            n_kept += len(p)
            if n_kept >= min_samples:
                break
        pts = np.concatenate(kept) if kept else np.zeros((0, 3), np.float32)
        seen = self._seen(pts, poses, tree, range_m, K, size) if len(pts) else np.zeros(0, bool)
        self._samples[key] = (pts, seen)
        return pts, seen

    def _seen(self, pts: np.ndarray, poses: np.ndarray, tree, range_m: float, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        import open3d as o3d

        seen = np.zeros(len(pts), bool)
        _, idx = tree.query(pts, k=min(8, len(poses)))
        idx = idx.reshape(len(pts), -1)
        w, h = size
        for j in range(idx.shape[1]):
            todo = np.flatnonzero(~seen)
            T = poses[idx[todo, j]]
            rel = pts[todo].astype(np.float64) - T[:, :3, 3]
            pc = np.einsum("nji,nj->ni", T[:, :3, :3], rel)  # R^T (p - t): the camera frame
            z = pc[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = K[0, 0] * pc[:, 0] / z + K[0, 2]
                v = K[1, 1] * pc[:, 1] / z + K[1, 2]
            inview = (z > 0.1) & (z <= range_m) & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
            if not inview.any():
                continue
            todo, rel = todo[inview], rel[inview]
            dist = np.linalg.norm(rel, axis=1)
            origin = T[inview, :3, 3]
            rays = np.concatenate([origin, rel / np.maximum(dist, 1e-6)[:, None]], axis=1).astype(np.float32)
            t_hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            seen[todo] = t_hit >= dist - 0.05
        return seen


def map_accuracy(
    world: WorldSurface,
    points: np.ndarray,
    vertices: np.ndarray,
    views: np.ndarray,
    K: np.ndarray,
    size: tuple[int, int],
    range_m: float = RANGE_M,
    tolerance_m: float = TOLERANCE_M,
    min_samples: int = MIN_SAMPLES,
    alignment: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
    """Accuracy and completeness of one map (surface ``points`` and mesh ``vertices``, world
    frame) against ``world``; the surface that should be mapped is the one within ``range_m`` of
    the cameras ``views`` ((n, 4, 4) T_world_cam, intrinsics ``K``, image ``size`` (w, h)) --
    the true poses when known, so every trajectory is measured against the same surface.

    ``alignment`` (R, t): the map is measured a second time moved by x -> R x + t, under the key
    ``"aligned"`` -- the trajectory's own SE(3) alignment onto the true one (as the ATE aligns;
    the map plays no part in it), which removes the first frame's arbitrary anchoring."""
    samples, seen = world.samples_near(
        np.asarray(views, np.float64), range_m, np.asarray(K, np.float64), size, min_samples=min_samples
    )
    out = _measure(world, points, vertices, samples, seen, tolerance_m)
    if alignment is not None:
        R, t = (np.asarray(a, np.float64) for a in alignment)
        moved_points = (points.astype(np.float64) @ R.T + t).astype(np.float32)
        moved_vertices = moved_points if vertices is points else (vertices.astype(np.float64) @ R.T + t).astype(np.float32)
        out["aligned"] = _measure(world, moved_points, moved_vertices, samples, seen, tolerance_m)
    out["surface_samples"] = int(len(samples))
    out["surface_seen_share"] = float(seen.mean()) if len(seen) else None
    out["range_m"] = float(range_m)
    out["tolerance_m"] = float(tolerance_m)
    return out


def _measure(
    world: WorldSurface, points: np.ndarray, vertices: np.ndarray, samples: np.ndarray, seen: np.ndarray, tolerance_m: float
) -> dict:
    """Error (median, p90, share within tolerance) and completeness of the points and vertices."""
    from scipy.spatial import cKDTree

    out: dict = {}
    sets = (("points", points),) if vertices is points else (("points", points), ("mesh", vertices))
    for name, pts in sets:
        d = world.distance(pts)
        out[name] = {
            "n": int(len(pts)),
            "error_median_m": float(np.median(d)) if len(d) else None,
            "error_p90_m": float(np.percentile(d, 90)) if len(d) else None,
            "share_within_tolerance": float(np.mean(d <= tolerance_m)) if len(d) else None,
        }
        if len(pts) and len(samples):
            dd, _ = cKDTree(pts).query(samples, distance_upper_bound=tolerance_m)
            hit = np.isfinite(dd)
            out[name]["completeness"] = float(hit.mean())
            out[name]["completeness_seen"] = float(hit[seen].mean()) if seen.any() else None
        else:
            out[name]["completeness"] = out[name]["completeness_seen"] = 0.0 if len(samples) else None
    if vertices is points:  # map.ply holds the mesh vertices: one set, reported under both names
        out["mesh"] = out["points"]
    return out
