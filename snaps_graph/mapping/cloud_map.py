"""Point-cloud map from keyframe depth maps, re-posable under any trajectory (SPEC "Map").

Decisions and why:

* **Clouds live in their keyframe's camera frame.** A keyframe's valid depth pixels, taken on a
  ``pixel_step`` grid, are back-projected with eq. 2 (``StereoCamera.backproject``) and kept in
  that camera's frame. The global map is built on demand as the union of these clouds under
  whichever trajectory the user picks (VO, SNAPS heuristic, iSAM2, batch), so re-posing after a
  refinement only multiplies stored points by new poses; depth is never recomputed.
* **Compact storage, bounded memory.** Each keyframe cloud is voxel-downsampled in its own frame
  (``keyframe_voxel_size_m``, half the map voxel so the global downsample decides the final
  spacing) and stored as float32 xyz (12 B/point) plus uint8 intensity (1 B/point grey, 3 B/point
  colour). Near the camera the depth grid is far denser than the voxel, so this removes most
  points where they are most redundant.
* **Validity.** A depth pixel is kept when it is finite, > 0 and <= ``max_range_m``; 0 is the
  front end's "no disparity" marker (eq. 1) and far depth is noisy (its error grows with z^2).
* **Colour.** A grey (H, W) uint8 image gives one intensity per point, replicated to RGB in the
  output cloud; an (H, W, 3) uint8 image is stored as colour, in the channel order given. When
  some keyframes have an image and others not, the latter are mid-grey (128) so the output cloud
  has colours for every point (open3d needs all or none).
* open3d and matplotlib are imported lazily inside the methods that use them, so
  ``import snaps_graph`` stays light.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..camera import StereoCamera
from ..config import MapConfig
from ..errors import SnapsGraphError
from ..io_utils import atomic_output

if TYPE_CHECKING:  # pragma: no cover
    import open3d

_MISSING_GREY = 128  # intensity of keyframes added without an image, when others have one


class CloudMap:
    """Keyframe clouds in camera frames; ``build(poses)`` unions them under a trajectory."""

    def __init__(self, camera: StereoCamera, cfg: MapConfig | None = None) -> None:
        cfg = cfg if cfg is not None else MapConfig()
        cfg.validate()
        self.camera = camera
        self.cfg = cfg
        # k -> (xyz float32 (n, 3) in camera k's frame, intensity uint8 (n,) or (n, 3) or None)
        self._clouds: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}

    # ---- keyframes ----
    def should_add(self, k: int) -> bool:
        """True on keyframes: every ``keyframe_every``-th frame, starting at frame 0."""
        return k % self.cfg.keyframe_every == 0

    def add_keyframe(self, k: int, depth: np.ndarray, image: np.ndarray | None = None) -> int:
        """Back-project keyframe ``k``'s depth (metres, (H, W); 0 = invalid) and store it; the
        optional ``image`` (uint8 (H, W) grey or (H, W, 3)) gives the points' intensity. Returns the
        number of points kept after the per-keyframe voxel. Adding ``k`` again replaces it."""
        k = _check_index(k)
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.size == 0:
            raise SnapsGraphError(f"keyframe {k}: depth must be a non-empty (H, W) array, got shape {depth.shape}")
        h, w = depth.shape
        cam = self.camera
        if cam.width and cam.height and (w, h) != (cam.width, cam.height):
            raise SnapsGraphError(f"keyframe {k}: depth is {w}x{h} but the camera is {cam.width}x{cam.height}")
        if image is not None:
            image = np.asarray(image)
            if (
                image.dtype != np.uint8
                or image.shape[:2] != (h, w)
                or image.ndim not in (2, 3)
                or (image.ndim == 3 and image.shape[2] != 3)
            ):
                raise SnapsGraphError(
                    f"keyframe {k}: image must be uint8 (H, W) or (H, W, 3) matching depth {h}x{w}, "
                    f"got {image.dtype} {image.shape}"
                )

        step = self.cfg.pixel_step
        z = depth[::step, ::step].astype(np.float32)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(z) & (z > 0) & (z <= self.cfg.max_range_m)
        vv, uu = np.nonzero(valid)
        zz = z[vv, uu]
        uu = (uu * step).astype(np.float32)
        vv = (vv * step).astype(np.float32)
        xyz = cam.backproject(uu, vv, zz).astype(np.float32)  # eq. 2
        colour = None
        if image is not None:
            colour = image[vv.astype(np.intp), uu.astype(np.intp)]

        if self.cfg.keyframe_voxel_size_m > 0 and len(xyz):
            xyz, colour = _voxel_downsample(xyz, colour, self.cfg.keyframe_voxel_size_m)
        xyz = np.ascontiguousarray(xyz, np.float32)
        for arr in (xyz, colour):  # read-only: a re-pose must never alter the stored clouds
            if arr is not None:
                arr.flags.writeable = False
        self._clouds[k] = (xyz, colour)
        return len(xyz)

    def keyframe_cloud(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The stored cloud of keyframe ``k``: (xyz float32 (n, 3) in its camera frame,
        intensity uint8 (n,) / colour (n, 3), or None)."""
        if k not in self._clouds:
            raise SnapsGraphError(f"keyframe {k} is not in the map")
        return self._clouds[k]

    @property
    def keyframes(self) -> list[int]:
        """Keyframe indices, ascending."""
        return sorted(self._clouds)

    def __len__(self) -> int:
        return len(self._clouds)

    def memory_bytes(self) -> int:
        """Bytes held by the stored clouds (array payloads; 13 B/point grey, 15 B/point colour)."""
        return sum(xyz.nbytes + (c.nbytes if c is not None else 0) for xyz, c in self._clouds.values())

    def num_stored_points(self) -> int:
        """Points held over all keyframes (before the map voxel)."""
        return sum(len(xyz) for xyz, _ in self._clouds.values())

    # ---- global map ----
    def posed_points(self, poses: np.ndarray, keyframes: list[int] | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Keyframe clouds in the world frame: p_world = R_k p_cam + t_k with T_world_cam =
        ``poses[k]``, for ``keyframes`` (default all). Returns (xyz float64 (n, 3), RGB float64
        in [0, 1] or None), no voxel step. Colours are present when any keyframe has them."""
        poses = self._check_poses(poses)
        ks = self.keyframes if keyframes is None else list(keyframes)
        missing = [k for k in ks if k not in self._clouds]
        if missing:
            raise SnapsGraphError(f"keyframe {missing[0]} is not in the map")
        have_colour = any(c is not None for _, c in self._clouds.values())
        n_total = sum(len(self._clouds[k][0]) for k in ks)
        out = np.empty((n_total, 3), np.float64)
        rgb = np.empty((n_total, 3), np.uint8) if have_colour else None
        i = 0
        for k in ks:
            xyz, c = self._clouds[k]
            n = len(xyz)
            T = poses[k]
            out[i : i + n] = xyz @ T[:3, :3].T + T[:3, 3]
            if rgb is not None:
                rgb[i : i + n] = _MISSING_GREY if c is None else (c[:, None] if c.ndim == 1 else c)
            i += n
        return out, (rgb.astype(np.float64) / 255.0 if rgb is not None else None)

    def build(self, poses: np.ndarray) -> "open3d.geometry.PointCloud":
        """The global map under ``poses`` ((N, 4, 4) T_world_cam indexed by frame, N > the last
        keyframe), voxel-downsampled with open3d at ``voxel_size_m`` (0 = no downsampling).

        Uses only the stored clouds, so building again with refined poses is cheap. To bound
        peak memory on long runs, consecutive keyframes are posed and voxelised in chunks of
        about ``build_chunk_points`` points, then the union of the chunks is voxelised once more
        tile by tile (``build_tile_m`` squares in x-z) rather than in one open3d call, whose
        per-voxel hash table was the peak (measured: +1.1 GB for KITTI 00 in one call). A place
        seen in two chunks (a revisit) ends with one point per voxel; only along tile borders
        can two points lie closer than one voxel."""
        import open3d as o3d

        poses = self._check_poses(poses)
        voxel = self.cfg.voxel_size_m
        merged = o3d.geometry.PointCloud()
        n_chunks = 0
        for group in self._chunks():
            merged += _to_o3d(*self.posed_points(poses, group), voxel)
            n_chunks += 1
        if n_chunks <= 1 or voxel <= 0 or len(merged.points) == 0:
            return merged
        pts = np.asarray(merged.points)
        cols = np.asarray(merged.colors) if merged.has_colors() else None
        tile = np.floor(pts[:, [0, 2]] / self.cfg.build_tile_m).astype(np.int64)
        key = (tile[:, 0] - tile[:, 0].min()) * (int(tile[:, 1].max() - tile[:, 1].min()) + 1) + (tile[:, 1] - tile[:, 1].min())
        del tile
        order = np.argsort(key, kind="stable")
        starts = np.flatnonzero(np.diff(key[order])) + 1
        del key
        out_pts, out_cols = [], []
        for idx in np.split(order, starts):
            down = _to_o3d(pts[idx], cols[idx] if cols is not None else None, voxel)
            out_pts.append(np.asarray(down.points).copy())
            if cols is not None:
                out_cols.append(np.asarray(down.colors).copy())
        del pts, cols, merged, order
        return _to_o3d(np.concatenate(out_pts), np.concatenate(out_cols) if out_cols else None, 0.0)

    def _chunks(self) -> list[list[int]]:
        """Consecutive keyframes grouped into chunks of about ``build_chunk_points`` points."""
        groups: list[list[int]] = []
        current: list[int] = []
        count = 0
        for k in self.keyframes:
            n = len(self._clouds[k][0])
            if current and count + n > self.cfg.build_chunk_points:
                groups.append(current)
                current, count = [], 0
            current.append(k)
            count += n
        if current:
            groups.append(current)
        return groups

    def write_ply(self, path: str | Path, poses: np.ndarray, *, cloud: "open3d.geometry.PointCloud | None" = None) -> int:
        """Build under ``poses`` and write a binary PLY atomically; returns the point count.
        ``cloud``: a map already built under ``poses`` (from ``build``), to skip rebuilding."""
        import open3d as o3d

        path = Path(path)
        if path.suffix.lower() != ".ply":
            raise SnapsGraphError(f"{path}: the map file must end in .ply")
        pcd = self.build(poses) if cloud is None else cloud
        if len(pcd.points) == 0:
            raise SnapsGraphError(f"{path}: the map is empty (no keyframe with valid depth), nothing to write")
        # open3d picks the format from the suffix, so the temporary file must end in .ply too.
        with atomic_output(path, suffix=".ply") as tmp:
            if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False, compressed=False):
                raise SnapsGraphError(f"{path}: open3d could not write the point cloud")
        return len(pcd.points)

    def render_topdown_png(
        self,
        path: str | Path,
        poses: np.ndarray,
        trajectories: dict[str, np.ndarray] | None = None,
        max_points: int = 200000,
        *,
        colour_by: str | None = None,
        cloud: "open3d.geometry.PointCloud | None" = None,
    ) -> int:
        """A top-down picture (world x across, z up the page, i.e. seen from above since y points
        down) of the map built under ``poses``, coloured by height (-y) or intensity, with each
        trajectory ((N, 4, 4) poses or (N, 3) positions) drawn over it. At most ``max_points``
        points are drawn (an even stride, deterministic). ``colour_by`` defaults to
        ``topdown_colour_by``; ``cloud`` is a map already built under ``poses``, to skip
        rebuilding. Written atomically; returns the number of map points drawn."""
        # The Agg canvas directly, not pyplot: no global backend switch, no figure registry.
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        path = Path(path)
        colour_by = colour_by or self.cfg.topdown_colour_by
        if colour_by not in ("height", "intensity"):
            raise SnapsGraphError(f"colour_by must be 'height' or 'intensity', got '{colour_by}'")
        if max_points < 1:
            raise SnapsGraphError(f"max_points must be >= 1, got {max_points}")
        pcd = self.build(poses) if cloud is None else cloud
        xyz = np.asarray(pcd.points)
        if len(xyz) == 0:
            raise SnapsGraphError(f"{path}: the map is empty (no keyframe with valid depth), nothing to draw")
        rgb = np.asarray(pcd.colors) if pcd.has_colors() else None
        stride = max(1, int(np.ceil(len(xyz) / max_points)))
        xyz = xyz[::stride]
        if colour_by == "intensity" and rgb is not None:
            values, cmap, label = rgb[::stride].mean(axis=1), "gray", "intensity"
        else:
            values, cmap, label = -xyz[:, 1], "viridis", "height -y (m)"
        lo, hi = np.percentile(values, [2, 98])  # robust colour range: a few outliers don't wash it out
        # Draw low points first so higher structure stays visible from above.
        order = np.argsort(values, kind="stable") if colour_by == "height" else slice(None)

        fig = Figure(figsize=(8, 8))
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        ax.set_facecolor("black" if cmap == "gray" else "white")
        sc = ax.scatter(
            xyz[order, 0],
            xyz[order, 2],
            c=values[order],
            s=0.3,
            cmap=cmap,
            vmin=lo,
            vmax=hi if hi > lo else lo + 1e-6,
            linewidths=0,
            rasterized=True,
        )
        fig.colorbar(sc, ax=ax, shrink=0.7, label=label)
        for name, traj in (trajectories or {}).items():
            p = _positions(traj, name)
            ax.plot(p[:, 0], p[:, 2], lw=1.2, label=name)
            ax.plot(p[:1, 0], p[:1, 2], "o", ms=4, color=ax.lines[-1].get_color())
        if trajectories:
            ax.legend(loc="best", fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.set_title(
            f"map top-down: {len(np.asarray(pcd.points))} points, voxel {self.cfg.voxel_size_m} m, {len(self)} keyframes",
            fontsize=9,
        )
        fig.tight_layout()

        with atomic_output(path, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=self.cfg.topdown_dpi, format="png")
        return len(xyz)

    # ---- helpers ----
    def _check_poses(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise SnapsGraphError(f"poses must have shape (N, 4, 4), got {poses.shape}")
        ks = self.keyframes
        if ks and ks[-1] >= len(poses):
            raise SnapsGraphError(f"poses has {len(poses)} entries but the map has keyframe {ks[-1]}")
        if ks and not np.all(np.isfinite(poses[ks])):
            bad = next(k for k in ks if not np.all(np.isfinite(poses[k])))
            raise SnapsGraphError(f"pose of keyframe {bad} is not finite")
        return poses


def _to_o3d(xyz: np.ndarray, rgb: np.ndarray | None, voxel_m: float) -> "open3d.geometry.PointCloud":
    """An open3d cloud from float64 xyz and RGB in [0, 1], voxel-downsampled when voxel_m > 0."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(xyz)
    if rgb is not None:
        pcd.colors = o3d.utility.Vector3dVector(rgb)
    return pcd.voxel_down_sample(voxel_m) if voxel_m > 0 else pcd


def _check_index(k: int) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise SnapsGraphError(f"keyframe index must be a non-negative integer, got {k!r}")
    return int(k)


def _voxel_downsample(xyz: np.ndarray, colour: np.ndarray | None, voxel_m: float) -> tuple[np.ndarray, np.ndarray | None]:
    """open3d voxel downsample of one keyframe cloud; averages points and intensities per voxel."""
    grey = colour is not None and colour.ndim == 1
    rgb = None
    if colour is not None:
        rgb = (np.repeat(colour[:, None], 3, axis=1) if grey else colour).astype(np.float64) / 255.0
    down = _to_o3d(xyz.astype(np.float64), rgb, voxel_m)
    out_xyz = np.asarray(down.points).astype(np.float32)
    out_c = None
    if colour is not None:
        c = np.clip(np.rint(np.asarray(down.colors) * 255.0), 0, 255).astype(np.uint8)
        out_c = np.ascontiguousarray(c[:, 0]) if grey else c
    return out_xyz, out_c


def _positions(traj: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(traj, dtype=np.float64)
    if t.ndim == 3 and t.shape[1:] == (4, 4):
        p = t[:, :3, 3]
    elif t.ndim == 2 and t.shape[1] == 3:
        p = t
    else:
        raise SnapsGraphError(f"trajectory '{name}' must be (N, 4, 4) poses or (N, 3) positions, got {t.shape}")
    if len(p) == 0 or not np.all(np.isfinite(p)):
        raise SnapsGraphError(f"trajectory '{name}' is empty or not finite")
    return p
