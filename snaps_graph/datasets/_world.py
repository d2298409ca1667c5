"""Procedural street world built once along a whole camera path (geometry only; see ``_shade``).

The world is one triangle mesh in open3d's ``RaycastingScene`` (Embree):

* a **ground heightfield** that follows the path: each path sample deposits the height of the
  point ``camera_height_m`` below the camera (along the camera's down axis) and the grid takes a
  normalised Gaussian average of them (normalised convolution), blended far from the path into
  a much smoother average, so the ground under the camera is at ``camera_height_m`` and the
  height between path points is interpolated smoothly. One ground cannot meet two passes that
  disagree in height: KITTI 00's ground truth revisits some places up to ~1.5 m higher or lower,
  and there the ground takes the average (the camera stands up to ~0.75 m off 1.65 m); where
  the path passes once the error is under 0.06 m;
* **buildings, low walls and posts**: oriented boxes placed along both sides of the path with
  random frontage, gaps, setback, depth and height, plus a second row further back. A box is
  kept only if its whole footprint lies at least ``corridor_m`` from *every* part of the path
  (an exact Euclidean distance transform of the rasterised path) and does not overlap an
  earlier box; so crossings and revisits never put a wall in the road, and driving the same
  street twice finds the same buildings (the second pass finds the slots taken);
* a **backdrop** of distant hills around the ground's edge, so the horizon is not an empty edge.

Each triangle maps to a *face* (``tri_face``); the face table carries what the shader needs
(kind, texture origin and tangent, per-surface random offset and style). Everything is a
deterministic function of the path and the seed, so the same seed gives the same world.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import SnapsGraphError

# Face kinds (the shader switches on these).
GROUND, FACADE, ROOF, BACKDROP = 0, 1, 2, 3
SKY = 255  # a pixel with no hit


@dataclass
class WorldConfig:
    """Numbers that shape a synthetic world (lengths in metres).

    Defaults give a KITTI-like street: 1.65 m camera height (KITTI's camera is 1.65 m above the
    road), a free corridor of 5 m each side of the path, buildings 4-24 m tall with gaps.
    """

    camera_height_m: float = 1.65  # ground lies this far below the camera (camera down axis)
    ground_cell_m: float = 2.0  # heightfield grid spacing
    ground_smooth_m: float = 3.0  # Gaussian sigma of the height average near the path
    ground_far_smooth_m: float = 40.0  # sigma of the fallback average far from the path
    ground_margin_m: float = 150.0  # ground extends this far beyond the path's bounding box
    corridor_m: float = 5.0  # no building footprint within this distance of any path point
    setback_max_m: float = 4.0  # front faces stand corridor_m .. corridor_m + this from the path
    frontage_m: tuple[float, float] = (7.0, 24.0)  # building length along the street
    depth_m: tuple[float, float] = (6.0, 16.0)  # building depth away from the street
    height_m: tuple[float, float] = (4.0, 24.0)  # building height above the ground
    gap_m: tuple[float, float] = (2.0, 9.0)  # gap between neighbours, when there is one
    gap_probability: float = 0.5  # chance of a gap after a building (else they nearly touch)
    wall_probability: float = 0.2  # chance a slot holds a low wall (1-2.5 m) instead
    post_spacing_m: float = 18.0  # mean spacing of thin posts at the corridor edge (0: none)
    second_row_offset_m: float = 26.0  # setback of a second row of buildings (0: none)
    backdrop_height_m: tuple[float, float] = (12.0, 45.0)  # distant hills on the ground's edge
    path_step_m: float = 1.0  # the path is resampled at this arc-length step
    extend_m: float = 80.0  # the street continues straight this far beyond both path ends
    occupancy_cell_m: float = 0.5  # raster cell for the corridor and overlap checks


# Per-face attributes the shader reads, packed as rows of two float32 blocks so that one
# ``np.take(block, face, axis=1)`` fetches them all for every pixel (one gather instead of many).
#
# Texture coordinates (m) of a hit p: tu = tu_x*p_x + tu_z*p_z + tu_c, and tv = -p_y + tv_c on
# vertical faces (height), p_z + tv_c on horizontal ones. Both include a random per-surface
# offset (tu_off, tv_off) that decorrelates surfaces; without it, tu runs along a facade from its
# corner and tv is the height above the facade's ground.
MAIN_FIELDS = (
    "tu_x", "tu_z", "tu_c", "tv_c",
    "albedo",  # base brightness 0..1
    "noise_amp",  # amplitude of the multi-scale noise
)
DETAIL_FIELDS = (  # facades only
    "tu_off", "tv_off",
    "brick_w",  # brick / stone / plank length (m); 0 = no bricks
    "brick_h",  # brick course height (m)
    "brick_amp",  # per-brick brightness spread
    "win_w",  # window cell width (m); 0 = no windows
    "win_h",  # floor height (m)
    "win_fx",  # window width as a fraction of the cell
    "win_fy",  # window height as a fraction of the floor
    "top",  # facade height above its ground (m); windows stop below it
    "ident",  # surface identity (an integer < 2**24, exact in float32) for per-brick/window hashes
)


@dataclass
class FaceTable:
    kind: np.ndarray  # (F,) uint8: GROUND / FACADE / ROOF / BACKDROP
    main: np.ndarray  # (len(MAIN_FIELDS), F) float32
    detail: np.ndarray  # (len(DETAIL_FIELDS), F) float32

    def __len__(self) -> int:
        return len(self.kind)

    def column(self, name: str) -> np.ndarray:
        if name in MAIN_FIELDS:
            return self.main[MAIN_FIELDS.index(name)]
        return self.detail[DETAIL_FIELDS.index(name)]


@dataclass
class Box:
    corners: np.ndarray  # (4, 2) footprint corners (x, z), counter-clockwise seen from above
    ground_y: float  # ground level at the footprint (y down)
    bottom_y: float  # buried bottom (below the lowest ground under the footprint)
    height: float
    style: str  # "building" | "wall" | "post"


class World:
    """Geometry of one world: the mesh, the face table and the open3d scene to cast rays into."""

    def __init__(self, positions: np.ndarray, down_axes: np.ndarray, seed: int = 0, config: WorldConfig | None = None):
        """Build the world along ``positions`` (N, 3) camera centres with camera down axes (N, 3)."""
        import open3d as o3d  # lazily: only the renderer needs it

        self.config = cfg = config or WorldConfig()
        positions = np.asarray(positions, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
            raise SnapsGraphError("synthetic world: need an (N, 3) array of camera positions")
        self.rng = np.random.default_rng([int(seed), 0x5EED])
        ground_pts = positions + cfg.camera_height_m * np.asarray(down_axes, dtype=np.float64)
        self.samples, self.tangents, self.sample_ground_y = _resample_path(
            positions, ground_pts[:, 1], cfg.path_step_m, cfg.extend_m)

        verts: list[np.ndarray] = []
        tris: list[np.ndarray] = []
        tri_face: list[np.ndarray] = []
        rows: list[dict] = []

        # -- ground --
        gv, gt = self._build_ground()
        verts.append(gv)
        tris.append(gt)
        tri_face.append(np.zeros(len(gt), np.int32))
        rows.append(self._face_row(GROUND, np.zeros(3), np.array([1.0, 0.0, 0.0]), albedo=0.36, noise_amp=0.11))
        n_vert = len(gv)

        # -- boxes --
        self.boxes = self._place_boxes()
        for box in self.boxes:
            bv, bt, bf, brows = self._box_mesh(box, len(rows))
            verts.append(bv)
            tris.append(bt + n_vert)
            tri_face.append(bf)
            rows.extend(brows)
            n_vert += len(bv)

        # -- backdrop --
        dv, dt, df, drows = self._backdrop_mesh(len(rows))
        verts.append(dv)
        tris.append(dt + n_vert)
        tri_face.append(df)
        rows.extend(drows)

        self.vertices = np.concatenate(verts).astype(np.float32)
        self.triangles = np.concatenate(tris).astype(np.uint32)
        self.tri_face = np.concatenate(tri_face).astype(np.int32)
        self.faces = _table(rows)

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        # Commit the acceleration structure now (the first cast does it), so concurrent casts
        # from several render threads never race on the lazy commit.
        self.scene.cast_rays(o3d.core.Tensor(np.array([[0, -1e4, 0, 0, 1, 0]], np.float32)))

    # ------------------------------------------------------------------ ground
    def _build_ground(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        cell = cfg.ground_cell_m
        lo = self.samples.min(0) - cfg.ground_margin_m
        hi = self.samples.max(0) + cfg.ground_margin_m
        nx = int(np.ceil((hi[0] - lo[0]) / cell)) + 1
        nz = int(np.ceil((hi[1] - lo[1]) / cell)) + 1
        self.ground_origin = lo
        self.ground_shape = (nz, nx)
        ix = np.clip(np.rint((self.samples[:, 0] - lo[0]) / cell).astype(int), 0, nx - 1)
        iz = np.clip(np.rint((self.samples[:, 1] - lo[1]) / cell).astype(int), 0, nz - 1)
        w = np.zeros((nz, nx), np.float64)
        wh = np.zeros((nz, nx), np.float64)
        np.add.at(w, (iz, ix), 1.0)
        np.add.at(wh, (iz, ix), self.sample_ground_y)

        def avg(sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
            s = max(sigma_m / cell, 0.5)
            k = int(2 * np.ceil(3 * s) + 1)
            W = cv2.GaussianBlur(w, (k, k), s, borderType=cv2.BORDER_CONSTANT)
            WH = cv2.GaussianBlur(wh, (k, k), s, borderType=cv2.BORDER_CONSTANT)
            return W, WH / np.maximum(W, 1e-12)

        # Normalised convolution: a weighted mean of nearby path heights. It is exact on a
        # straight path with a constant grade (symmetric weights), and smooth everywhere.
        W1, h1 = avg(cfg.ground_smooth_m)
        W2, h2 = avg(cfg.ground_far_smooth_m)
        w_ref1 = np.median(W1[iz, ix])
        w_ref2 = np.median(W2[iz, ix])
        a1 = np.clip(W1 / (0.5 * w_ref1), 0.0, 1.0)
        a2 = np.clip(W2 / (0.05 * w_ref2), 0.0, 1.0)
        mean_y = float(np.mean(self.sample_ground_y))
        far = a2 * h2 + (1.0 - a2) * mean_y
        self.height_grid = (a1 * h1 + (1.0 - a1) * far).astype(np.float64)

        xs = lo[0] + np.arange(nx) * cell
        zs = lo[1] + np.arange(nz) * cell
        X, Z = np.meshgrid(xs, zs)
        v = np.stack([X, self.height_grid, Z], -1).reshape(-1, 3)
        idx = np.arange(nz * nx).reshape(nz, nx)
        a = idx[:-1, :-1].ravel()
        b = idx[:-1, 1:].ravel()  # +x
        c = idx[1:, :-1].ravel()  # +z
        d = idx[1:, 1:].ravel()
        t = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
        return v, t

    def ground_y(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Ground height (world y, down) at (x, z), bilinear in the heightfield grid."""
        cell = self.config.ground_cell_m
        nz, nx = self.ground_shape
        gx = np.clip((np.asarray(x) - self.ground_origin[0]) / cell, 0, nx - 1.000001)
        gz = np.clip((np.asarray(z) - self.ground_origin[1]) / cell, 0, nz - 1.000001)
        i0, j0 = np.floor(gz).astype(int), np.floor(gx).astype(int)
        fz, fx = gz - i0, gx - j0
        H = self.height_grid
        return (
            H[i0, j0] * (1 - fx) * (1 - fz) + H[i0, j0 + 1] * fx * (1 - fz)
            + H[i0 + 1, j0] * (1 - fx) * fz + H[i0 + 1, j0 + 1] * fx * fz
        )

    # ------------------------------------------------------------------ boxes
    def _place_boxes(self) -> list[Box]:
        cfg = self.config
        rng = self.rng
        cell = cfg.occupancy_cell_m
        pad = cfg.corridor_m + cfg.setback_max_m + max(cfg.second_row_offset_m, 0) + cfg.depth_m[1] + cfg.frontage_m[1] + 5.0
        lo = self.samples.min(0) - pad
        hi = self.samples.max(0) + pad
        shape = (int(np.ceil((hi[1] - lo[1]) / cell)) + 1, int(np.ceil((hi[0] - lo[0]) / cell)) + 1)
        # Exact Euclidean distance of every cell to the rasterised path polyline.
        path_img = np.full(shape, 255, np.uint8)
        pts = np.rint((self.samples - lo) / cell).astype(np.int32)
        if len(pts) > 1:
            cv2.polylines(path_img, [pts.reshape(-1, 1, 2)], False, 0, 1)
        else:
            path_img[pts[0, 1], pts[0, 0]] = 0
        dist = cv2.distanceTransform(path_img, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell
        # half a cell of slack for the rasterisation of the path and of the footprint
        clear = dist >= cfg.corridor_m + cell
        occupied = np.zeros(shape, bool)

        boxes: list[Box] = []
        s_total = len(self.samples) * cfg.path_step_m

        def try_box(k: int, side: float, frontage: float, offset: float, depth: float, height: float, style: str) -> bool:
            p, t = self.samples[k], self.tangents[k]
            n = side * np.array([-t[1], t[0]])  # left (+1) / right (-1) normal in the xz plane
            f0, f1 = p + n * offset, p + n * (offset + depth)
            half = 0.5 * frontage * t
            corners = np.array([f0 - half, f0 + half, f1 + half, f1 - half])
            if side < 0:
                corners = corners[::-1]
            g = (corners - lo) / cell
            x0, y0 = np.floor(g.min(0)).astype(int) - 1
            x1, y1 = np.ceil(g.max(0)).astype(int) + 2
            if x0 < 0 or y0 < 0 or x1 > shape[1] or y1 > shape[0]:
                return False
            mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.fillConvexPoly(mask, np.rint(g - [x0, y0]).astype(np.int32), 1)
            m = mask.astype(bool)
            if not clear[y0:y1, x0:x1][m].all() or occupied[y0:y1, x0:x1][m].any():
                return False
            # Reserve a 1 m halo so neighbours never touch (they read as one block otherwise).
            halo = cv2.dilate(mask, np.ones((3, 3), np.uint8), iterations=max(1, int(round(1.0 / cell)))).astype(bool)
            occupied[y0:y1, x0:x1] |= halo
            gy = self.ground_y(corners[:, 0], corners[:, 1])
            boxes.append(Box(corners, float(np.min(gy)), float(np.max(gy)) + 1.0, height, style))
            return True

        def at(arc: float) -> int:  # index of the path sample at an arc length
            return min(max(int(round(arc / cfg.path_step_m)), 0), len(self.samples) - 1)

        rows = [(0.0, cfg.setback_max_m)]
        if cfg.second_row_offset_m > 0:
            rows.append((cfg.second_row_offset_m, cfg.second_row_offset_m + 10.0))
        for row, (off_lo, off_hi) in enumerate(rows):
            for side in (1.0, -1.0):
                s = rng.uniform(0, 10.0)  # arc length where the next slot starts
                while s < s_total:
                    frontage = rng.uniform(*cfg.frontage_m)
                    is_wall = row == 0 and rng.random() < cfg.wall_probability
                    if is_wall:
                        depth, height = rng.uniform(0.3, 0.6), rng.uniform(1.0, 2.5)
                    else:
                        depth, height = rng.uniform(*cfg.depth_m), rng.uniform(*cfg.height_m)
                    offset = cfg.corridor_m + 0.6 + off_lo + rng.uniform(0, off_hi - off_lo)
                    style = "wall" if is_wall else "building"
                    # On a bend a long slot may touch the corridor (inside of the bend: its ends
                    # swing in) or a neighbour (its back converges): try shallower, then shorter.
                    shallow = min(depth, 6.0)
                    for f, off, dep in ((frontage, offset, depth), (frontage, offset, shallow),
                                        (frontage / 2, offset, shallow), (frontage / 2, offset + 3.0, shallow)):
                        if try_box(at(s + f / 2), side, f, off, dep, height, style):
                            break
                    gap = rng.uniform(*cfg.gap_m) if rng.random() < cfg.gap_probability else 1.2
                    s += frontage + gap
        if cfg.post_spacing_m > 0:
            for side in (1.0, -1.0):
                s = rng.uniform(0, cfg.post_spacing_m)
                while s < s_total:
                    try_box(at(s), side, 0.3, cfg.corridor_m + 0.4 + rng.uniform(0, 1.0), 0.3, rng.uniform(3.0, 6.0), "post")
                    s += rng.uniform(0.5, 1.5) * cfg.post_spacing_m
        return boxes

    def _box_mesh(self, box: Box, face0: int):
        rng = self.rng
        top_y = box.ground_y - box.height
        c = box.corners
        v = np.zeros((8, 3))
        v[:4, 0], v[:4, 2], v[:4, 1] = c[:, 0], c[:, 1], box.bottom_y
        v[4:, 0], v[4:, 2], v[4:, 1] = c[:, 0], c[:, 1], top_y
        style = box.style
        if style == "building":
            albedo = rng.uniform(0.3, 0.75)
            win_w, win_h = rng.uniform(2.2, 4.0), rng.uniform(2.8, 3.8)
            win_fx, win_fy = rng.uniform(0.35, 0.7), rng.uniform(0.4, 0.65)
            bricks = rng.random() < 0.45
            brick_w, brick_h = (rng.uniform(0.45, 0.8), rng.uniform(0.18, 0.32)) if bricks else (0.0, 0.0)
            brick_amp = rng.uniform(0.1, 0.25) if bricks else 0.0
            noise_amp = rng.uniform(0.06, 0.14)
        elif style == "wall":
            albedo = rng.uniform(0.35, 0.7)
            win_w = win_h = win_fx = win_fy = 0.0
            brick_w, brick_h, brick_amp = rng.uniform(0.3, 0.7), rng.uniform(0.15, 0.35), rng.uniform(0.15, 0.3)
            noise_amp = 0.1
        else:  # post: plain, dark or light, so it stands out from what is behind it
            albedo = rng.choice([0.15, 0.85])
            win_w = win_h = win_fx = win_fy = 0.0
            brick_w = brick_h = brick_amp = 0.0
            noise_amp = 0.05
        tris, faces, rows = [], [], []
        for k in range(4):
            k1 = (k + 1) % 4
            # two triangles of the side quad (bottom k, bottom k1, top k1, top k)
            tris += [[k, k1, 4 + k1], [k, 4 + k1, 4 + k]]
            faces += [face0 + len(rows)] * 2
            t3 = v[k1] - v[k]
            t3[1] = 0.0
            t3 /= max(np.linalg.norm(t3), 1e-9)
            origin = np.array([v[k, 0], box.ground_y, v[k, 2]])
            rows.append(self._face_row(
                FACADE, origin, t3, albedo=albedo * rng.uniform(0.9, 1.1), noise_amp=noise_amp,
                win_w=win_w, win_h=win_h, win_fx=win_fx, win_fy=win_fy, top=box.height,
                brick_w=brick_w, brick_h=brick_h, brick_amp=brick_amp,
            ))
        tris += [[4, 5, 6], [4, 6, 7]]
        faces += [face0 + len(rows)] * 2
        rows.append(self._face_row(ROOF, np.zeros(3), np.array([1.0, 0.0, 0.0]), albedo=albedo * 0.8, noise_amp=noise_amp))
        return v, np.array(tris), np.array(faces, np.int32), rows

    def _backdrop_mesh(self, face0: int):
        """Hills on the rectangle 2 m inside the ground's edge, heights a smooth random profile."""
        cfg = self.config
        nz, nx = self.ground_shape
        lo = self.ground_origin + 2.0
        hi = self.ground_origin + np.array([(nx - 1), (nz - 1)]) * cfg.ground_cell_m - 2.0
        ring = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [lo[0], lo[1]]])
        seg = np.linalg.norm(np.diff(ring, axis=0), axis=1)
        perim = float(seg.sum())
        n = max(int(perim / 10.0), 16)
        s = np.linspace(0.0, perim, n + 1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        pts = np.stack([np.interp(s, cum, ring[:, 0]), np.interp(s, cum, ring[:, 1])], 1)
        # smooth periodic height profile: a few random harmonics
        hmin, hmax = cfg.backdrop_height_m
        prof = np.zeros(n + 1)
        for h in range(1, 9):
            prof += self.rng.normal() / h * np.cos(2 * np.pi * h * s / perim + self.rng.uniform(0, 2 * np.pi))
        prof = (prof - prof.min()) / max(np.ptp(prof), 1e-9)
        heights = hmin + (hmax - hmin) * prof
        gy = self.ground_y(pts[:, 0], pts[:, 1])
        bottom = np.stack([pts[:, 0], gy + 5.0, pts[:, 1]], 1)
        top = np.stack([pts[:, 0], gy - heights, pts[:, 1]], 1)
        v = np.concatenate([bottom, top])
        tris, faces, rows = [], [], []
        m = n + 1
        for k in range(n):
            tris += [[k, k + 1, m + k + 1], [k, m + k + 1, m + k]]
            faces += [face0 + len(rows)] * 2
            t3 = np.array([pts[k + 1, 0] - pts[k, 0], 0.0, pts[k + 1, 1] - pts[k, 1]])
            t3 /= max(np.linalg.norm(t3), 1e-9)
            # origin shifted back by s so tu runs continuously along the whole ring
            origin = np.array([pts[k, 0], gy[k], pts[k, 1]]) - t3 * s[k]
            rows.append(self._face_row(BACKDROP, origin, t3, albedo=0.3, noise_amp=0.16, same_offset=True))
        return v, np.array(tris), np.array(faces, np.int32), rows

    def _face_row(self, kind: int, origin: np.ndarray, tangent: np.ndarray, albedo: float, noise_amp: float,
                  win_w: float = 0.0, win_h: float = 0.0, win_fx: float = 0.0, win_fy: float = 0.0,
                  top: float = 0.0, brick_w: float = 0.0, brick_h: float = 0.0, brick_amp: float = 0.0,
                  same_offset: bool = False) -> dict:
        if same_offset and getattr(self, "_backdrop_offset", None) is not None:
            offset = self._backdrop_offset
        else:
            offset = self.rng.uniform(0.0, 1000.0, 2)
            if same_offset:
                self._backdrop_offset = offset
        return dict(kind=kind, origin=origin, tangent=tangent, offset=offset, albedo=albedo, noise_amp=noise_amp,
                    win_w=win_w, win_h=win_h, win_fx=win_fx, win_fy=win_fy, top=top,
                    brick_w=brick_w, brick_h=brick_h, brick_amp=brick_amp,
                    ident=int(self.rng.integers(1, 2**24)))


def _table(rows: list[dict]) -> FaceTable:
    origin = np.array([r["origin"] for r in rows], dtype=np.float64)
    tangent = np.array([r["tangent"] for r in rows], dtype=np.float64)
    offset = np.array([r["offset"] for r in rows], dtype=np.float64)
    kind = np.array([r["kind"] for r in rows], dtype=np.uint8)
    vertical = (kind == FACADE) | (kind == BACKDROP)
    cols = {
        "tu_x": tangent[:, 0], "tu_z": tangent[:, 2],
        # horizontal faces have tangent (1, 0, 0) and origin 0: tu = x + off_u, tv = z + off_v
        "tu_c": offset[:, 0] - (origin[:, 0] * tangent[:, 0] + origin[:, 2] * tangent[:, 2]),
        "tv_c": np.where(vertical, origin[:, 1], 0.0) + offset[:, 1],
        "tu_off": offset[:, 0], "tv_off": offset[:, 1],
    }
    for name in MAIN_FIELDS + DETAIL_FIELDS:
        if name not in cols:
            cols[name] = np.array([r[name] for r in rows], dtype=np.float64)
    main = np.stack([cols[n] for n in MAIN_FIELDS]).astype(np.float32)
    detail = np.stack([cols[n] for n in DETAIL_FIELDS]).astype(np.float32)
    return FaceTable(kind, main, detail)


def _resample_path(positions: np.ndarray, ground_y: np.ndarray, step: float, extend: float = 0.0):
    """Resample the path's (x, z) at a constant arc-length step; unit tangents; ground heights.

    The street is extended straight (level) by ``extend`` metres beyond both ends, so a camera
    near the end of a short path still looks down a lined street, not an empty plain.
    """
    xz = positions[:, [0, 2]]
    seg = np.linalg.norm(np.diff(xz, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(cum[-1])
    if total < step:
        samples, gy = xz[:1].copy(), ground_y[:1].copy()
        tangents = np.array([[0.0, 1.0]])
    else:
        s = np.arange(0.0, total + 1e-9, step)
        samples = np.stack([np.interp(s, cum, xz[:, 0]), np.interp(s, cum, xz[:, 1])], 1)
        gy = np.interp(s, cum, ground_y)
        d = np.gradient(samples, axis=0)
        tangents = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    n_ext = int(extend / step)
    if n_ext == 0:
        return samples, tangents, gy
    k = np.arange(1, n_ext + 1)[:, None] * step
    if len(samples) > 1:  # heading over the last/first few metres (one step can be noisy)
        m = min(len(samples) - 1, 5)
        t_end = samples[-1] - samples[-1 - m]
        t_start = samples[m] - samples[0]
        t_end, t_start = t_end / np.linalg.norm(t_end), t_start / np.linalg.norm(t_start)
    else:
        # a single pose: its camera heading (z axis) is not known here, extend along +z
        t_end = t_start = tangents[0]
    head = _free_run(samples[0] - k * t_start, samples[int(30 / step):], 3 * 5.0)[::-1]
    tail = _free_run(samples[-1] + k * t_end, samples[: max(len(samples) - int(30 / step), 0)], 3 * 5.0)
    samples = np.concatenate([head, samples, tail])
    tangents = np.concatenate([np.repeat(t_start[None], len(head), 0), tangents, np.repeat(t_end[None], len(tail), 0)])
    gy = np.concatenate([np.full(len(head), gy[0]), gy, np.full(len(tail), gy[-1])])
    return samples, tangents, gy


def _free_run(ext: np.ndarray, others: np.ndarray, min_gap: float) -> np.ndarray:
    """The extension points up to the first that comes within ``min_gap`` of ``others`` (so a
    path that ends where it began, like a loop, does not get a phantom street across it)."""
    if len(others) == 0:
        return ext
    d = np.sqrt(((ext[:, None, :] - others[None, :, :]) ** 2).sum(-1)).min(1)
    bad = np.flatnonzero(d < min_gap)
    return ext[: bad[0]] if len(bad) else ext
