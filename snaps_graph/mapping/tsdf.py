"""TSDF map: keyframe depth kept compressed, fused into a surface under any trajectory.

A keyframe keeps its map depth (uint16 mm) and grey image PNG-encoded in memory, so a fusion
under another trajectory never recomputes stereo; fusion is open3d's ``VoxelBlockGrid`` on the
CPU, in chunks of at most ``TSDF_MAX_BLOCKS`` (docs/decisions.md, "Map"). open3d is imported
inside the methods, so ``import snaps_graph`` stays light.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import StereoCamera
from ..config import MapConfig
from ..errors import SnapsGraphError

_MM = 1000.0  # stored depth: uint16 millimetres
TSDF_TRUNC_VOXELS = 6.0  # truncation distance, voxels: spans the stereo depth error within the map's range
TSDF_MAX_BLOCKS = 40000  # a chunk is extracted at this many blocks (6 KB each): bounds memory to about 0.25 GB
TSDF_MIN_WEIGHT = 1.0  # surface kept where at least this many keyframes saw it: the map depth is filtered already
TSDF_MIN_COMPONENT = 0  # mesh pieces of fewer triangles are dropped; 0 keeps all, as every result here does


@dataclass
class FusedSurface:
    """The fused map under one trajectory: a triangle mesh and the surface points, world frame."""

    vertices: np.ndarray  # float32 (V, 3)
    triangles: np.ndarray  # int32 (T, 3)
    vertex_grey: np.ndarray  # uint8 (V,)
    stats: dict = field(default_factory=dict)

    @property
    def points(self) -> np.ndarray:
        """Surface points: the mesh vertices, i.e. the TSDF's zero crossings on voxel edges (the
        set ``extract_point_cloud`` returns; taken from the mesh, it costs nothing more)."""
        return self.vertices

    @property
    def point_grey(self) -> np.ndarray:
        return self.vertex_grey


class FusedMap:
    """Compressed keyframe depth; ``fuse(poses)`` integrates it into a TSDF under a trajectory."""

    def __init__(self, camera: StereoCamera, cfg: MapConfig | None = None) -> None:
        cfg = cfg if cfg is not None else MapConfig()  # validated on construction
        self.camera = camera
        self.cfg = cfg
        self.trunc_voxels, self.max_blocks = TSDF_TRUNC_VOXELS, TSDF_MAX_BLOCKS
        self.min_weight, self.min_component = TSDF_MIN_WEIGHT, TSDF_MIN_COMPONENT
        # k -> (depth PNG bytes (uint16 mm), grey PNG bytes or None, (width, height))
        self._kf: dict[int, tuple[bytes, bytes | None, tuple[int, int]]] = {}

    # ---- keyframes ----
    def should_add(self, k: int) -> bool:
        return k % self.cfg.keyframe_every == 0

    def add_keyframe(self, k: int, depth: np.ndarray, image: np.ndarray | None = None) -> int:
        """Store keyframe ``k``: ``depth`` float metres (h, w), 0 = invalid, at the camera's size
        or uniformly scaled from it (``map_depth``'s working size); ``image`` uint8 grey at the
        camera's size or the depth's, resized to the depth's. Returns the valid depth pixels."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise SnapsGraphError(f"keyframe index must be a non-negative integer, got {k!r}")
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.size == 0:
            raise SnapsGraphError(f"keyframe {k}: depth must be a non-empty (H, W) array, got shape {depth.shape}")
        h, w = depth.shape
        self._intrinsics(w, h)  # the size must be the camera's, scaled
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(depth) & (depth > 0) & (depth <= min(self.cfg.max_range_m, 65.0))
        mm = np.where(ok, np.rint(depth * _MM), 0).astype(np.uint16)
        grey = None
        if image is not None:
            image = np.asarray(image)
            if image.dtype != np.uint8 or image.ndim != 2:
                raise SnapsGraphError(f"keyframe {k}: image must be a uint8 (H, W) grey array, got {image.dtype} {image.shape}")
            if image.shape != (h, w):
                image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
            grey = _png(image)
        self._kf[int(k)] = (_png(mm), grey, (w, h))
        return int(ok.sum())

    @property
    def keyframes(self) -> list[int]:
        return sorted(self._kf)

    def __len__(self) -> int:
        return len(self._kf)

    def memory_bytes(self) -> int:
        """Bytes of the stored (compressed) keyframes."""
        return sum(len(d) + (len(g) if g else 0) for d, g, _ in self._kf.values())

    def depth(self, k: int) -> np.ndarray:
        """Keyframe ``k``'s stored depth, float32 metres (1 mm steps), 0 = invalid."""
        if k not in self._kf:
            raise SnapsGraphError(f"keyframe {k} is not in the map")
        return cv2.imdecode(np.frombuffer(self._kf[k][0], np.uint8), cv2.IMREAD_UNCHANGED).astype(np.float32) / _MM

    def keyframe_cloud(self, k: int, step: int = 2) -> tuple[np.ndarray, np.ndarray | None]:
        """Keyframe ``k``'s stored depth as points in its camera frame, every ``step``-th pixel:
        (xyz float32 (n, 3), grey uint8 (n,) or None). For viewers; fusion does not use it."""
        z = self.depth(k)[::step, ::step]
        h, w = self._kf[k][2][1], self._kf[k][2][0]
        K = self._intrinsics(w, h)
        rows, cols = np.nonzero(z > 0)
        zz = z[rows, cols]
        u = cols.astype(np.float32) * step
        v = rows.astype(np.float32) * step
        xyz = np.stack([(u - K[0, 2]) * zz / K[0, 0], (v - K[1, 2]) * zz / K[1, 1], zz], axis=1).astype(np.float32)
        grey_png = self._kf[k][1]
        grey = None
        if grey_png is not None:
            img = cv2.imdecode(np.frombuffer(grey_png, np.uint8), cv2.IMREAD_UNCHANGED)
            grey = img[::step, ::step][z > 0]
        return xyz, grey

    # ---- fusion ----
    def fuse(self, poses: np.ndarray) -> FusedSurface:
        """Integrate every keyframe's depth under ``poses`` ((N, 4, 4) T_world_cam indexed by
        stream position) and extract the surface seen by at least ``min_weight`` keyframes."""
        import open3d as o3d
        import open3d.core as o3c

        poses = self._check_poses(poses)
        if not self._kf:
            raise SnapsGraphError("the map has no keyframes, nothing to fuse")
        t0 = time.perf_counter()
        cfg = self.cfg
        dev = o3c.Device("CPU:0")
        parts: list[tuple] = []
        n_blocks_max = 0

        def new_grid():
            return o3d.t.geometry.VoxelBlockGrid(
                attr_names=("tsdf", "weight", "color"),
                attr_dtypes=(o3c.float32, o3c.uint16, o3c.uint16),
                attr_channels=((1), (1), (3)),
                voxel_size=cfg.tsdf_voxel_m,
                block_resolution=8,
                block_count=min(20000, self.max_blocks),  # grows by rehashing; allocating all at once costs seconds
                device=dev,
            )

        vbg = new_grid()
        n_in_grid = 0
        for k in self.keyframes:
            d_png, g_png, (w, h) = self._kf[k]
            mm = cv2.imdecode(np.frombuffer(d_png, np.uint8), cv2.IMREAD_UNCHANGED)
            if not np.any((mm > 0) & (mm <= cfg.max_range_m * _MM)):  # nothing in range: open3d refuses such a frame
                continue
            if g_png is not None:
                grey = cv2.imdecode(np.frombuffer(g_png, np.uint8), cv2.IMREAD_UNCHANGED)
            else:
                grey = np.full((h, w), 128, np.uint8)
            depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(mm)))
            colour = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(np.repeat(grey[:, :, None], 3, axis=2))))
            K = o3c.Tensor(self._intrinsics(w, h), o3c.float64)
            ext = o3c.Tensor(np.linalg.inv(poses[k]), o3c.float64)  # world -> camera
            blocks = vbg.compute_unique_block_coordinates(
                depth, K, ext, depth_scale=_MM, depth_max=cfg.max_range_m, trunc_voxel_multiplier=self.trunc_voxels
            )
            if n_in_grid and vbg.hashmap().size() + len(blocks) > self.max_blocks:
                n_blocks_max = max(n_blocks_max, vbg.hashmap().size())
                parts.append(self._extract(vbg))
                vbg = new_grid()
                blocks = vbg.compute_unique_block_coordinates(
                    depth, K, ext, depth_scale=_MM, depth_max=cfg.max_range_m, trunc_voxel_multiplier=self.trunc_voxels
                )
                n_in_grid = 0
            vbg.integrate(
                blocks,
                depth,
                colour,
                K,
                ext,
                depth_scale=_MM,
                depth_max=cfg.max_range_m,
                trunc_voxel_multiplier=self.trunc_voxels,
            )
            n_in_grid += 1
        n_blocks_max = max(n_blocks_max, vbg.hashmap().size())
        parts.append(self._extract(vbg))
        del vbg
        surf = _concat(parts)
        dt = time.perf_counter() - t0
        surf.stats = {
            "keyframes": len(self._kf),
            "chunks": len(parts),
            "max_blocks": int(n_blocks_max),
            "vertices": len(surf.vertices),
            "triangles": len(surf.triangles),
            "fuse_s": dt,
        }
        return surf

    def _extract(self, vbg) -> tuple:
        if vbg.hashmap().size() == 0:  # nothing integrated (open3d refuses an empty grid)
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros(0, np.uint8)
        w = max(float(self.min_weight) - 0.5, 0.0)  # open3d keeps weight > threshold
        mesh = vbg.extract_triangle_mesh(weight_threshold=w)
        if "positions" in mesh.vertex and len(mesh.vertex.positions):
            v = mesh.vertex.positions.numpy().astype(np.float32)
            t = mesh.triangle.indices.numpy().astype(np.int32)
            if "colors" in mesh.vertex:
                vg = np.clip(np.rint(mesh.vertex.colors.numpy().mean(axis=1) * 255.0), 0, 255).astype(np.uint8)
            else:
                vg = np.full(len(v), 128, np.uint8)
        else:
            v, t, vg = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros(0, np.uint8)
        if self.min_component > 0 and len(t):
            v, t, vg = _drop_small_components(v, t, vg, self.min_component)
        return v, t, vg

    def _intrinsics(self, w: int, h: int) -> np.ndarray:
        cam = self.camera
        if not cam.width or not cam.height:
            raise SnapsGraphError("the map needs a camera with a known image size")
        sx, sy = w / cam.width, h / cam.height
        if abs(sx - sy) > 0.02 or not 0 < sx <= 1.0 + 1e-9:
            raise SnapsGraphError(f"depth is {w}x{h}, not the camera's {cam.width}x{cam.height} uniformly scaled down")
        return np.array([[cam.fx * sx, 0, (cam.cx + 0.5) * sx - 0.5], [0, cam.fy * sy, (cam.cy + 0.5) * sy - 0.5], [0, 0, 1]])

    def _check_poses(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise SnapsGraphError(f"poses must have shape (N, 4, 4), got {poses.shape}")
        ks = self.keyframes
        if ks and ks[-1] >= len(poses):
            raise SnapsGraphError(f"poses has {len(poses)} entries but the map has keyframe {ks[-1]}")
        if ks and not np.all(np.isfinite(poses[ks])):
            raise SnapsGraphError("a keyframe pose is not finite")
        return poses


def _drop_small_components(v: np.ndarray, t: np.ndarray, vg: np.ndarray, min_triangles: int):
    """Remove connected pieces of fewer than ``min_triangles`` triangles: a wrong depth seen once
    leaves a small floating patch, real surfaces are large connected sheets."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v.astype(np.float64)), o3d.utility.Vector3iVector(t))
    labels, counts, _ = m.cluster_connected_triangles()
    keep_t = np.asarray(counts)[np.asarray(labels)] >= min_triangles
    t = t[keep_t]
    used = np.zeros(len(v), bool)
    used[t.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[t].astype(np.int32), vg[used]


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8/uint16 image
        raise SnapsGraphError("could not encode a keyframe image")
    return buf.tobytes()


def _concat(parts: list[tuple]) -> FusedSurface:
    vs, ts, vgs = [], [], []
    off = 0
    for v, t, vg in parts:
        vs.append(v)
        ts.append(t + off)
        vgs.append(vg)
        off += len(v)
    return FusedSurface(np.concatenate(vs), np.concatenate(ts).astype(np.int32), np.concatenate(vgs))
