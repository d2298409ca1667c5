"""Procedural street world built once along a whole camera path (geometry only; see ``_shade``).

One triangle mesh in open3d's ``RaycastingScene``: a ground heightfield following the path,
buildings, walls and posts kept clear of every part of the path, a backdrop of hills. Each
triangle maps to a face (``tri_face``) whose table carries what the shader needs. Deterministic
for a path and a seed; the decisions: docs/datasets.md, "How the world is rendered".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import SnapsGraphError

# Face kinds (the shader switches on these).
GROUND, FACADE, ROOF, BACKDROP, TREE = 0, 1, 2, 3, 4
SKY = 255  # a pixel with no hit

# Scene presets (``WorldConfig.scene``):
# * ``street``: the street canyon above (buildings from 5 m, a second row from ~31 m);
# * ``open``: an open road: a 7 m asphalt road with edge lines, grass verges, field parcels with
#   crop rows (fading with distance like any texture, see ``_shade``), tree lines (parallel and
#   perpendicular to the road) and farm buildings ``open_distance_m`` (30-200 m) from every part
#   of the path, delineator posts every ~50 m at the verge, hills ~450 m beyond the path;
# * ``mixed``: stretches of ``stretch_m`` (150-400 m of path) alternating between the two.
SCENES = ("street", "open", "mixed")


@dataclass
class WorldConfig:
    """Numbers that shape a synthetic world (lengths in metres); the defaults give a KITTI-like street.
    ``scene`` picks a preset (``SCENES``); ``aliasing``, ``traffic`` and ``lighting`` combine with any.
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
    # -- scene (see SCENES) --
    scene: str = "street"  # street | open | mixed
    road_half_width_m: float = 3.5  # open: asphalt within this of the path (edge line just inside)
    verge_m: float = 2.5  # open: grass verge between the road and the fields
    open_distance_m: tuple[float, float] = (30.0, 200.0)  # open: trees and buildings this far from the path
    open_ground_margin_m: float = 450.0  # open: ground (fields) and hills this far beyond the path
    open_post_spacing_m: float = 50.0  # open: mean spacing of delineator posts at the verge
    tree_line_spacing_m: float = 70.0  # open: mean arc length between tree lines, per side
    tree_spacing_m: tuple[float, float] = (4.0, 9.0)  # open: between trees of a line
    tree_line_length_m: tuple[float, float] = (50.0, 250.0)
    tree_height_m: tuple[float, float] = (7.0, 18.0)
    crown_radius_m: tuple[float, float] = (2.0, 4.5)
    farm_spacing_m: float = 160.0  # open: mean arc length between groups of farm buildings, per side
    farm_frontage_m: tuple[float, float] = (10.0, 40.0)
    farm_height_m: tuple[float, float] = (4.0, 14.0)
    field_size_m: tuple[float, float] = (50.0, 140.0)  # open: field parcels (two grid spacings)
    stretch_m: tuple[float, float] = (150.0, 400.0)  # mixed: length of each street / open stretch
    # -- hard worlds --
    aliasing: bool = False  # buildings from a few facade modules, streets repeat one block of them
    alias_modules: int = 3
    alias_block: int = 4  # buildings per repeated block
    traffic: bool = False  # parked cars (present or not per pass) and oncoming cars
    parked_offset_m: float = 3.0  # parked cars stand this far right of the path
    parked_probability: float = 0.45  # chance a parking slot is taken on a pass (street; a fifth of it in open)
    oncoming_offset_m: float = 3.2  # oncoming cars drive this far left of the path
    oncoming_period_s: float = 6.0  # mean time between oncoming cars
    oncoming_speed_mps: tuple[float, float] = (7.0, 14.0)
    pass_radius_m: float = 80.0  # a pass: consecutive frames within this of a parking slot
    lighting: bool = False  # a sun that moves with the trajectory's time of day, with cast shadows
    day_start_h: float = 8.0  # lighting: time of day at the first frame
    day_hours_per_minute: float = 1.0  # lighting: hours of daylight per minute of trajectory time


# Per-face attributes the shader reads, packed as rows of two float32 blocks so that one
# ``np.take(block, face, axis=1)`` fetches them all for every pixel (one gather instead of many).
#
# Texture coordinates (m) of a hit p: tu = tu_x*p_x + tu_z*p_z + tu_c, and tv = -p_y + tv_c on
# vertical faces (height), p_z + tv_c on horizontal ones. Both include a random per-surface
# offset (tu_off, tv_off) that decorrelates surfaces; without it, tu runs along a facade from its
# corner and tv is the height above the facade's ground.
MAIN_FIELDS = (
    "tu_x",
    "tu_z",
    "tu_c",
    "tv_c",
    "albedo",  # base brightness 0..1
    "noise_amp",  # amplitude of the multi-scale noise
)
DETAIL_FIELDS = (  # facades only
    "tu_off",
    "tv_off",
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


@dataclass
class Box:
    corners: np.ndarray  # (4, 2) footprint corners (x, z), counter-clockwise seen from above
    ground_y: float  # ground level at the footprint (y down)
    bottom_y: float  # buried bottom (below the lowest ground under the footprint)
    height: float
    style: str  # "building" | "wall" | "post" | "farm"
    module: int = -1  # aliasing: index of the facade module (identical look), -1 = its own


class World:
    """Geometry of one world: the mesh, the face table and the open3d scene to cast rays into."""

    def __init__(
        self,
        positions: np.ndarray,
        down_axes: np.ndarray,
        seed: int = 0,
        config: WorldConfig | None = None,
        times: np.ndarray | None = None,
    ):
        """Build the world along ``positions`` (N, 3) camera centres with camera down axes (N, 3)
        (``times``, s, place the traffic; default 10 Hz)."""

        self.config = cfg = config or WorldConfig()
        _check_config(cfg)
        positions = np.asarray(positions, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
            raise SnapsGraphError("synthetic world: need an (N, 3) array of camera positions")
        self.rng = np.random.default_rng([int(seed), 0x5EED])
        ground_pts = positions + cfg.camera_height_m * np.asarray(down_axes, dtype=np.float64)
        self.samples, self.tangents, self.sample_ground_y = _resample_path(
            positions, ground_pts[:, 1], cfg.path_step_m, cfg.extend_m
        )
        # Per path sample: does it lie in an open stretch? (None: all street, the world before scenes existed.)
        self.sample_open = self._stretches()
        self.ground_dist = self.open_map = None  # open scenes: rasters the ground shader reads

        verts: list[np.ndarray] = []
        tris: list[np.ndarray] = []
        tri_face: list[np.ndarray] = []
        rows: list[dict] = []
        n_vert = 0

        def add(v: np.ndarray, t: np.ndarray, f: np.ndarray, new_rows: list[dict]) -> None:
            nonlocal n_vert
            verts.append(v)
            tris.append(t + n_vert)
            tri_face.append(f)
            rows.extend(new_rows)
            n_vert += len(v)

        # -- ground --
        gv, gt = self._build_ground()
        add(
            gv,
            gt,
            np.zeros(len(gt), np.int32),
            [self._face_row(GROUND, np.zeros(3), np.array([1.0, 0.0, 0.0]), albedo=0.36, noise_amp=0.11)],
        )

        # -- boxes --
        if cfg.aliasing:
            self._make_modules(seed)
        self.boxes = self._place_boxes()
        self.trees: list[tuple[float, float, float, float]] = []  # (x, z, height, crown radius)
        if self.sample_open is not None:
            self._place_open()
        for box in self.boxes:
            add(*self._box_mesh(box, len(rows)))
        for tree in self.trees:
            add(*self._tree_mesh(*tree, len(rows)))

        # -- backdrop --
        add(*self._backdrop_mesh(len(rows)))

        self.vertices = np.concatenate(verts).astype(np.float32)
        self.triangles = np.concatenate(tris).astype(np.uint32)
        self.tri_face = np.concatenate(tri_face).astype(np.int32)
        self.faces = _table(rows)

        self.scene = _raycasting_scene(self.vertices, self.triangles)
        self.traffic = None
        if cfg.traffic:
            self.traffic = Traffic(self, positions, times, seed)

    def _stretches(self) -> np.ndarray | None:
        """Per path sample, True in an open stretch: all for ``open``, alternating for ``mixed``."""
        cfg = self.config
        if cfg.scene == "street":
            return None
        n = len(self.samples)
        if cfg.scene == "open":
            return np.ones(n, bool)
        out = np.zeros(n, bool)
        is_open = bool(self.rng.random() < 0.5)
        k = 0
        while k < n:
            m = int(round(self.rng.uniform(*cfg.stretch_m) / cfg.path_step_m))
            out[k : k + max(m, 1)] = is_open
            k += max(m, 1)
            is_open = not is_open
        return out

    # ------------------------------------------------------------------ ground
    def _build_ground(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        cell = cfg.ground_cell_m
        margin = cfg.ground_margin_m if self.sample_open is None else max(cfg.ground_margin_m, cfg.open_ground_margin_m)
        lo = self.samples.min(0) - margin
        hi = self.samples.max(0) + margin
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
            H[i0, j0] * (1 - fx) * (1 - fz)
            + H[i0, j0 + 1] * fx * (1 - fz)
            + H[i0 + 1, j0] * (1 - fx) * fz
            + H[i0 + 1, j0 + 1] * fx * fz
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

        def try_box(
            k: int, side: float, frontage: float, offset: float, depth: float, height: float, style: str, module: int = -1
        ) -> bool:
            if self.sample_open is not None and self.sample_open[k]:
                return False  # an open stretch: no street buildings
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
            boxes.append(Box(corners, float(np.min(gy)), float(np.max(gy)) + 1.0, height, style, module))
            return True

        def at(arc: float) -> int:  # index of the path sample at an arc length
            return min(max(int(round(arc / cfg.path_step_m)), 0), len(self.samples) - 1)

        rows = [(0.0, cfg.setback_max_m)]
        if cfg.second_row_offset_m > 0:
            rows.append((cfg.second_row_offset_m, cfg.second_row_offset_m + 10.0))
        for row, (off_lo, off_hi) in enumerate(rows):
            for side in (1.0, -1.0):
                s = rng.uniform(0, 10.0)  # arc length where the next slot starts
                j_block = int(rng.integers(0, 1 << 16)) if cfg.aliasing else 0  # aliasing: start in the block
                while s < s_total:
                    if cfg.aliasing:  # the same block of identical buildings, over and over
                        frontage, depth, height, setback, gap, module = self._block[j_block % len(self._block)]
                        j_block += 1
                        is_wall, offset = False, cfg.corridor_m + 0.6 + off_lo + setback * (off_hi - off_lo)
                        style = "building"
                        for f, off, dep in ((frontage, offset, depth), (frontage, offset, min(depth, 6.0))):
                            if try_box(at(s + f / 2), side, f, off, dep, height, style, module):
                                break
                        s += frontage + gap
                        continue
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
                    for f, off, dep in (
                        (frontage, offset, depth),
                        (frontage, offset, shallow),
                        (frontage / 2, offset, shallow),
                        (frontage / 2, offset + 3.0, shallow),
                    ):
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

    # ------------------------------------------------------------------ aliasing
    def _make_modules(self, seed: int) -> None:
        """Aliasing: ``alias_modules`` facade designs (every face's texture offset and identity
        fixed, so two boxes of a module and size look the same) and a block of
        ``alias_block`` buildings (size, setback, gap, module) that streets repeat. Drawn from
        their own generator: the rest of the world is drawn as without aliasing."""
        cfg = self.config
        arng = np.random.default_rng([int(seed), 0xA11A5])
        self.modules: list[dict[str, Any]] = []
        for _ in range(cfg.alias_modules):
            bricks = arng.random() < 0.5
            self.modules.append(
                dict(
                    albedo=arng.uniform(0.3, 0.75),
                    win_w=arng.uniform(2.2, 4.0),
                    win_h=arng.uniform(2.8, 3.8),
                    win_fx=arng.uniform(0.35, 0.7),
                    win_fy=arng.uniform(0.4, 0.65),
                    brick_w=arng.uniform(0.45, 0.8) if bricks else 0.0,
                    brick_h=arng.uniform(0.18, 0.32) if bricks else 0.0,
                    brick_amp=arng.uniform(0.1, 0.25) if bricks else 0.0,
                    noise_amp=arng.uniform(0.06, 0.14),
                    offsets=arng.uniform(0.0, 1000.0, (5, 2)),
                    idents=arng.integers(1, 2**24, 5),
                )
            )
        # a block: a few sizes, repeated (the modules alternate through it)
        self._block = [
            (
                float(arng.uniform(*cfg.frontage_m)),
                float(arng.uniform(*cfg.depth_m)),
                float(arng.uniform(*cfg.height_m)),
                float(arng.uniform(0.0, 1.0)),
                float(arng.uniform(*cfg.gap_m)) if arng.random() < cfg.gap_probability else 1.2,
                j % cfg.alias_modules,
            )
            for j in range(cfg.alias_block)
        ]

    # ------------------------------------------------------------------ open road
    def _place_open(self) -> None:
        """Open stretches: rasters of the distance to the path (the shader's road, verge and
        fields), delineator posts, tree lines and farm buildings ``open_distance_m`` away."""
        cfg, rng = self.config, self.rng
        cell = cfg.occupancy_cell_m
        d_lo, d_hi = cfg.open_distance_m
        pad = d_hi + max(cfg.tree_line_length_m[1], cfg.farm_frontage_m[1] * 3) + 20.0
        lo = self.samples.min(0) - pad
        hi = self.samples.max(0) + pad
        shape = (int(np.ceil((hi[1] - lo[1]) / cell)) + 1, int(np.ceil((hi[0] - lo[0]) / cell)) + 1)

        def dist_to(mask: np.ndarray) -> np.ndarray:
            img = np.full(shape, 255, np.uint8)
            pts = np.rint((self.samples - lo) / cell).astype(np.int32)
            for seg in _runs(mask):
                p = pts[seg]
                if len(p) > 1:
                    cv2.polylines(img, [p.reshape(-1, 1, 2)], False, 0, 1)
                else:
                    img[p[0, 1], p[0, 0]] = 0
            if img.min() > 0:
                return np.full(shape, 1e4, np.float32)
            return cv2.distanceTransform(img, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(cell)

        open_ = self.sample_open
        assert open_ is not None  # only open and mixed scenes have an open road
        dist = dist_to(np.ones(len(self.samples), bool))
        self.raster_lo, self.raster_cell = lo.astype(np.float64), cell
        # The shader's road edge: the distance field smoothed (exact where it is linear, i.e. away
        # from the path's own line; it removes the staircase of the rasterised path).
        self.ground_dist = cv2.GaussianBlur(dist.astype(np.float32), (0, 0), 1.5 / cell)
        if not open_.all():
            d_open, d_street = dist_to(open_), dist_to(~open_)
            is_open = (d_open < d_street).astype(np.float32)
            self.open_map = cv2.GaussianBlur(is_open, (0, 0), 4.0 / cell)  # ~4 m blend between stretches

        occ_build = np.zeros(shape, bool)  # buildings (and their halo)
        occ_tree = np.zeros(shape, bool)
        for box in self.boxes:  # street buildings of a mixed world
            self._rasterise(box.corners, lo, cell, occ_build)

        s_total = len(self.samples) * cfg.path_step_m

        def at(arc: float) -> int:
            return min(max(int(round(arc / cfg.path_step_m)), 0), len(self.samples) - 1)

        def frame(k: int, side: float):
            t = self.tangents[k]
            return self.samples[k], t, side * np.array([-t[1], t[0]])

        def footprint(corners: np.ndarray):
            g = (corners - lo) / cell
            x0, y0 = np.floor(g.min(0)).astype(int) - 1
            x1, y1 = np.ceil(g.max(0)).astype(int) + 2
            if x0 < 0 or y0 < 0 or x1 > shape[1] or y1 > shape[0]:
                return None
            mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.fillConvexPoly(mask, np.rint(g - [x0, y0]).astype(np.int32), 1)
            return (slice(y0, y1), slice(x0, x1)), mask.astype(bool)

        def square(c: np.ndarray, half: float) -> np.ndarray:
            return c + np.array([[-half, -half], [half, -half], [half, half], [-half, half]])

        # Delineator posts at the verge (thin, 1 m tall): the near field's few vertical edges.
        rw = cfg.road_half_width_m
        if cfg.open_post_spacing_m > 0:
            for side in (1.0, -1.0):
                s = rng.uniform(0, cfg.open_post_spacing_m)
                while s < s_total:
                    k = at(s)
                    p, t, n = frame(k, side)
                    c = p + n * (rw + 0.9)
                    fp = footprint(square(c, 0.3))
                    if open_[k] and fp is not None and (dist[fp[0]][fp[1]] >= rw + 0.4).all():
                        corners = square(c, 0.06)
                        gy = self.ground_y(corners[:, 0], corners[:, 1])
                        self.boxes.append(Box(corners, float(gy.min()), float(gy.max()) + 0.5, 1.0, "post"))
                    s += rng.uniform(0.5, 1.5) * cfg.open_post_spacing_m

        # Farm buildings: groups of 1-3 sheds/houses, well clear of the path and of each other.
        for side in (1.0, -1.0):
            s = rng.uniform(0, cfg.farm_spacing_m)
            while s < s_total:
                k = at(s)
                p, t, n = frame(k, side)
                offset = rng.uniform(d_lo, d_hi)
                along = rng.uniform(-20.0, 20.0)
                for _ in range(int(rng.integers(1, 4))):
                    front = rng.uniform(*cfg.farm_frontage_m)
                    depth = rng.uniform(8.0, 25.0)
                    height = rng.uniform(*cfg.farm_height_m)
                    f0 = p + n * offset + t * along
                    corners = np.array(
                        [f0 - t * front / 2, f0 + t * front / 2, f0 + t * front / 2 + n * depth, f0 - t * front / 2 + n * depth]
                    )
                    if side < 0:
                        corners = corners[::-1]
                    along += front + rng.uniform(4.0, 15.0)
                    fp = footprint(corners)
                    if not open_[k] or fp is None:
                        continue
                    sl, m = fp
                    if (dist[sl][m] < d_lo).any() or occ_build[sl][m].any() or occ_tree[sl][m].any():
                        continue
                    halo = cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=int(round(2.0 / cell))).astype(
                        bool
                    )
                    occ_build[sl] |= halo
                    gy = self.ground_y(corners[:, 0], corners[:, 1])
                    module = len(self.boxes) % cfg.alias_modules if cfg.aliasing else -1
                    self.boxes.append(Box(corners, float(gy.min()), float(gy.max()) + 1.0, height, "farm", module))
                s += rng.uniform(0.5, 1.5) * cfg.farm_spacing_m

        # Tree lines: along the road (60 %) or running away from it (hedgerows between fields).
        for side in (1.0, -1.0):
            s = rng.uniform(0, cfg.tree_line_spacing_m)
            while s < s_total:
                k = at(s)
                p, t, n = frame(k, side)
                length = rng.uniform(*cfg.tree_line_length_m)
                offset = d_lo + (d_hi - d_lo) * rng.random() ** 1.5  # more lines nearer the road
                spacing = rng.uniform(*cfg.tree_spacing_m)
                if rng.random() < 0.6:
                    start, direction, across = p + n * offset - t * length / 2, t, n
                else:
                    start, direction, across = p + n * offset, n, t
                m = max(int(length / spacing), 1)
                jit = rng.uniform(-0.3, 0.3, m) * spacing
                lat = rng.normal(0.0, 0.8, m)
                heights = rng.uniform(*cfg.tree_height_m, m)
                radii = rng.uniform(*cfg.crown_radius_m, m)
                s += rng.uniform(0.5, 1.5) * cfg.tree_line_spacing_m
                if not open_[k]:
                    continue
                for j in range(m):
                    c = start + direction * (j * spacing + jit[j]) + across * lat[j]
                    r = min(radii[j], 0.45 * heights[j])
                    fp = footprint(square(c, r))
                    if fp is None:
                        continue
                    sl, mk = fp
                    if (dist[sl][mk] < d_lo).any() or occ_build[sl][mk].any():
                        continue
                    occ_tree[sl] |= mk
                    self.trees.append((float(c[0]), float(c[1]), float(heights[j]), float(r)))

    @staticmethod
    def _rasterise(corners: np.ndarray, lo: np.ndarray, cell: float, into: np.ndarray) -> None:
        g = np.rint((corners - lo) / cell).astype(np.int32)
        mask = np.zeros(into.shape, np.uint8)
        cv2.fillConvexPoly(mask, g, 1)
        into |= mask.astype(bool)

    def _tree_mesh(self, x: float, z: float, height: float, r: float, face0: int):
        """A tree: an irregular low-poly crown (8 sectors x 4 rings) on a thin trunk."""
        rng = self.rng
        n_az = 8
        gy = float(self.ground_y(np.array([x]), np.array([z]))[0])
        rv = max(0.5 * (height - 2.0) * rng.uniform(0.6, 0.95), r * 0.8)  # vertical radius: trunk 2-6 m
        cy = gy - (height - rv)  # crown centre (y down)
        els = np.radians([-60.0, -20.0, 20.0, 60.0])
        phase = rng.uniform(0, 2 * np.pi)
        az = phase + 2 * np.pi * np.arange(n_az) / n_az
        rad = r * np.cos(els)[:, None] * (1.0 + 0.18 * rng.standard_normal((len(els), n_az)))
        yy = cy - rv * np.sin(els)[:, None] * (1.0 + 0.1 * rng.standard_normal((len(els), n_az)))
        ring = np.stack([x + rad * np.cos(az), yy, z + rad * np.sin(az)], -1).reshape(-1, 3)
        bottom, top = np.array([[x, cy + rv * 0.8, z]]), np.array([[x, cy - rv, z]])
        v = [bottom, ring, top]
        tris, faces, rows = [], [], []
        nr = len(els)
        ib, it = 0, 1 + nr * n_az

        def idx(j: int, i: int) -> int:
            return 1 + j * n_az + i % n_az

        albedo = rng.uniform(0.14, 0.3)
        noise_amp = rng.uniform(0.14, 0.2)
        offset = rng.uniform(0.0, 1000.0, 2)
        for i in range(n_az):
            f = face0 + len(rows)
            tris.append([ib, idx(0, i + 1), idx(0, i)])
            for j in range(nr - 1):
                tris += [[idx(j, i), idx(j, i + 1), idx(j + 1, i + 1)], [idx(j, i), idx(j + 1, i + 1), idx(j + 1, i)]]
            tris.append([idx(nr - 1, i), idx(nr - 1, i + 1), it])
            faces += [f] * (2 * nr)
            a = az[i] + np.pi / n_az
            rows.append(
                self._face_row(
                    TREE,
                    np.array([x, gy, z]),
                    np.array([-np.sin(a), 0.0, np.cos(a)]),
                    albedo=albedo * rng.uniform(0.9, 1.1),
                    noise_amp=noise_amp,
                    offset=offset,
                )
            )
        # trunk: a thin box from below the ground to the crown's centre
        base = len(ring) + 2
        w = 0.15 + 0.02 * height
        tv = np.array([[x - w, gy + 0.5, z - w], [x + w, gy + 0.5, z - w], [x + w, gy + 0.5, z + w], [x - w, gy + 0.5, z + w]])
        tv = np.concatenate([tv, tv + np.array([0.0, cy - gy - 0.5, 0.0])])
        v.append(tv)
        f = face0 + len(rows)
        for k in range(4):
            k1 = (k + 1) % 4
            tris += [[base + k, base + k1, base + 4 + k1], [base + k, base + 4 + k1, base + 4 + k]]
            faces += [f] * 2
        rows.append(
            self._face_row(TREE, np.array([x, gy, z]), np.array([1.0, 0.0, 0.0]), albedo=0.18, noise_amp=0.08, offset=offset)
        )
        return np.concatenate(v), np.array(tris), np.array(faces, np.int32), rows

    def _box_mesh(self, box: Box, face0: int):
        rng = self.rng
        top_y = box.ground_y - box.height
        c = box.corners
        v = np.zeros((8, 3))
        v[:4, 0], v[:4, 2], v[:4, 1] = c[:, 0], c[:, 1], box.bottom_y
        v[4:, 0], v[4:, 2], v[4:, 1] = c[:, 0], c[:, 1], top_y
        style = box.style
        if box.module >= 0:
            return self._module_mesh(box, v, face0)
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
        elif style == "farm":  # sheds and farmhouses: plank or plain walls, few windows
            albedo = rng.uniform(0.3, 0.7)
            has_windows = rng.random() < 0.5
            win_w, win_h = (rng.uniform(3.0, 6.0), rng.uniform(3.0, 4.0)) if has_windows else (0.0, 0.0)
            win_fx, win_fy = rng.uniform(0.2, 0.4), rng.uniform(0.3, 0.5)
            planks = rng.random() < 0.5
            brick_w, brick_h = (rng.uniform(2.0, 5.0), rng.uniform(0.2, 0.4)) if planks else (0.0, 0.0)
            brick_amp = rng.uniform(0.1, 0.2) if planks else 0.0
            noise_amp = rng.uniform(0.08, 0.14)
        else:  # post: plain, dark or light, so it stands out from what is behind it
            albedo = rng.choice([0.15, 0.85])
            win_w = win_h = win_fx = win_fy = 0.0
            brick_w = brick_h = brick_amp = 0.0
            noise_amp = 0.05

        def wall(k: int, origin: np.ndarray, t3: np.ndarray):
            return self._face_row(
                FACADE,
                origin,
                t3,
                albedo=albedo * rng.uniform(0.9, 1.1),
                noise_amp=noise_amp,
                win_w=win_w,
                win_h=win_h,
                win_fx=win_fx,
                win_fy=win_fy,
                top=box.height,
                brick_w=brick_w,
                brick_h=brick_h,
                brick_amp=brick_amp,
            )

        def roof():
            return self._face_row(ROOF, np.zeros(3), np.array([1.0, 0.0, 0.0]), albedo=albedo * 0.8, noise_amp=noise_amp)

        return self._walls_and_roof(box, v, face0, wall, roof)

    def _module_mesh(self, box: Box, v: np.ndarray, face0: int):
        """A box in one of the aliasing modules: every face as the module's, no random draw."""
        mod = self.modules[box.module]
        look = {k: mod[k] for k in ("win_w", "win_h", "win_fx", "win_fy", "brick_w", "brick_h", "brick_amp")}

        def wall(k: int, origin: np.ndarray, t3: np.ndarray):
            return self._face_row(
                FACADE,
                origin,
                t3,
                albedo=mod["albedo"],
                noise_amp=mod["noise_amp"],
                top=box.height,
                offset=mod["offsets"][k],
                ident=int(mod["idents"][k]),
                **look,
            )

        def roof():
            return self._face_row(
                ROOF,
                np.zeros(3),
                np.array([1.0, 0.0, 0.0]),
                albedo=mod["albedo"] * 0.8,
                noise_amp=mod["noise_amp"],
                offset=mod["offsets"][4],
                ident=int(mod["idents"][4]),
            )

        return self._walls_and_roof(box, v, face0, wall, roof)

    @staticmethod
    def _walls_and_roof(box: Box, v: np.ndarray, face0: int, wall, roof):
        """(vertices, triangles, face ids, face rows) of a box: its four side quads (bottom k,
        bottom k+1, top k+1, top k), then its roof. ``wall(k, origin, tangent)`` and ``roof()``
        make the face rows, called in that order, so a caller's random draws keep their order."""
        tris, faces, rows = [], [], []
        for k in range(4):
            k1 = (k + 1) % 4
            tris += [[k, k1, 4 + k1], [k, 4 + k1, 4 + k]]
            faces += [face0 + len(rows)] * 2
            t3 = v[k1] - v[k]
            t3[1] = 0.0
            t3 /= max(np.linalg.norm(t3), 1e-9)
            rows.append(wall(k, np.array([v[k, 0], box.ground_y, v[k, 2]]), t3))
        tris += [[4, 5, 6], [4, 6, 7]]
        faces += [face0 + len(rows)] * 2
        rows.append(roof())
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

    def _face_row(
        self,
        kind: int,
        origin: np.ndarray,
        tangent: np.ndarray,
        albedo: float,
        noise_amp: float,
        win_w: float = 0.0,
        win_h: float = 0.0,
        win_fx: float = 0.0,
        win_fy: float = 0.0,
        top: float = 0.0,
        brick_w: float = 0.0,
        brick_h: float = 0.0,
        brick_amp: float = 0.0,
        same_offset: bool = False,
        offset: np.ndarray | None = None,
        ident: int | None = None,
    ) -> dict:
        if offset is not None:
            pass
        elif same_offset and getattr(self, "_backdrop_offset", None) is not None:
            offset = self._backdrop_offset
        else:
            offset = self.rng.uniform(0.0, 1000.0, 2)
            if same_offset:
                self._backdrop_offset = offset
        return dict(
            kind=kind,
            origin=origin,
            tangent=tangent,
            offset=offset,
            albedo=albedo,
            noise_amp=noise_amp,
            win_w=win_w,
            win_h=win_h,
            win_fx=win_fx,
            win_fy=win_fy,
            top=top,
            brick_w=brick_w,
            brick_h=brick_h,
            brick_amp=brick_amp,
            ident=int(self.rng.integers(1, 2**24)) if ident is None else ident,
        )


def _check_config(cfg: WorldConfig) -> None:
    """One-line errors for world settings that cannot build a world."""

    def bad(what: str) -> None:
        raise SnapsGraphError(f"synthetic world: {what}")

    if cfg.scene not in SCENES:
        bad(f"scene '{cfg.scene}' is not one of {', '.join(SCENES)}")
    for name in (
        "open_distance_m",
        "tree_spacing_m",
        "tree_line_length_m",
        "tree_height_m",
        "crown_radius_m",
        "farm_frontage_m",
        "farm_height_m",
        "field_size_m",
        "stretch_m",
        "oncoming_speed_mps",
    ):
        lo, hi = getattr(cfg, name)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
            bad(f"{name} {(lo, hi)} must be a range 0 < lo <= hi")
    if cfg.open_distance_m[0] < cfg.road_half_width_m + cfg.verge_m:
        bad(f"open_distance_m starts at {cfg.open_distance_m[0]} m, inside the road and verge")
    if cfg.alias_modules < 1 or cfg.alias_block < 1:
        bad(f"alias_modules {cfg.alias_modules} and alias_block {cfg.alias_block} must be >= 1")
    if not 0.0 <= cfg.parked_probability <= 1.0:
        bad(f"parked_probability {cfg.parked_probability} must be in [0, 1]")
    if not cfg.oncoming_period_s > 0 or not cfg.pass_radius_m > 0:
        bad("oncoming_period_s and pass_radius_m must be > 0")
    if not np.isfinite(cfg.day_hours_per_minute) or cfg.day_hours_per_minute < 0:
        bad(f"day_hours_per_minute {cfg.day_hours_per_minute} must be >= 0")


def _raycasting_scene(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)), o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32))
    )
    # Commit the acceleration structure now (the first cast does it), so concurrent casts
    # from several render threads never race on the lazy commit.
    scene.cast_rays(o3d.core.Tensor(np.array([[0, -1e4, 0, 0, 1, 0]], np.float32)))
    return scene


@dataclass
class Layer:
    """Geometry of one instant added to the static world (traffic): its own scene, and the
    face lookups of static + layer triangles (layer triangle j is prim n_static + j)."""

    scene: Any  # open3d RaycastingScene
    tri_face: np.ndarray
    faces: FaceTable
    n_static: int


class Traffic:
    """Parked and oncoming cars (two boxes each: body and cabin), a function of the frame; drawn from
    its own generator, so the static world is the same with or without traffic.

    A parking slot is taken or free for a whole pass (consecutive frames within ``pass_radius_m``),
    so no car pops in view but revisits see other cars; oncoming cars spawn 80-150 m ahead and drive
    back along the path, hidden while within 1.2 m of any part of it.
    """

    def __init__(self, world: "World", positions: np.ndarray, times: np.ndarray | None, seed: int):
        cfg = world.config
        self.world = world
        rng = np.random.default_rng([int(seed), 0x7AFF1C])
        xz = positions[:, [0, 2]]
        n = len(xz)
        self.times = np.arange(n) * 0.1 if times is None else np.asarray(times, float)
        step = cfg.path_step_m
        n_head = int(np.argmin(np.linalg.norm(world.samples[: int(cfg.extend_m / step) + 2] - xz[0], axis=1)))
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
        self.frame_arc = cum + n_head * step
        self.samples, self.tangents = world.samples, world.tangents
        s_total = len(self.samples) * step
        # clearance raster: distance of every cell to the path
        cell = 0.5
        self.lo = self.samples.min(0) - 20.0
        shape = tuple(int(np.ceil(v / cell)) + 1 for v in (self.samples.max(0) - self.lo + 20.0)[::-1])
        img = np.full(shape, 255, np.uint8)
        pts = np.rint((self.samples - self.lo) / cell).astype(np.int32)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, 0, 1)
        self.dist = cv2.distanceTransform(img, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * cell
        self.cell = cell

        # parked slots
        slots = []  # (centre xz, tangent, dims, look)
        s = rng.uniform(0.0, 6.0)
        while s < s_total:
            dims = self._dims(rng)
            k = min(int(round(s / step)), len(self.samples) - 1)
            t = self.tangents[k]
            right = np.array([t[1], -t[0]])
            c = self.samples[k] + right * (cfg.parked_offset_m + rng.uniform(-0.15, 0.15))
            look = self._look(rng)
            if self._clear(c, t, dims):
                slots.append((c, t, dims, look, k))
            s += dims[0] + rng.uniform(0.8, 3.0)
        self.slots = slots
        # taken or free per pass: (n_slots, n_frames) booleans
        self.parked = np.zeros((len(slots), n), bool)
        p_open = cfg.parked_probability * 0.2
        for j, (c, _, _, _, k) in enumerate(slots):
            near = np.linalg.norm(xz - c, axis=1) < cfg.pass_radius_m
            p = p_open if world.sample_open is not None and world.sample_open[k] else cfg.parked_probability
            for run in _runs(near):
                self.parked[j, run] = rng.random() < p

        # oncoming cars: (spawn time, start arc, speed, dims, look)
        self.oncoming = []
        t = self.times[0] + rng.exponential(cfg.oncoming_period_s)
        while t < self.times[-1]:
            a0 = float(np.interp(t, self.times, self.frame_arc))
            self.oncoming.append(
                (t, a0 + rng.uniform(80.0, 150.0), rng.uniform(*cfg.oncoming_speed_mps), self._dims(rng), self._look(rng))
            )
            t += rng.exponential(cfg.oncoming_period_s)

    @staticmethod
    def _dims(rng) -> tuple[float, float, float, float]:
        """(length, width, body height, total height): a car, or one time in eight a van."""
        if rng.random() < 0.125:
            return rng.uniform(4.8, 5.6), rng.uniform(1.9, 2.05), rng.uniform(1.9, 2.3), 0.0
        return rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.9), rng.uniform(0.8, 0.95), rng.uniform(1.4, 1.55)

    @staticmethod
    def _look(rng) -> tuple[float, np.ndarray, int]:
        paint = float(np.clip(rng.choice([0.1, 0.2, 0.45, 0.65, 0.85]) + rng.normal(0, 0.04), 0.05, 0.95))
        return paint, rng.uniform(0.0, 1000.0, 2), int(rng.integers(1, 2**24))

    def _footprint(self, c: np.ndarray, t: np.ndarray, length: float, width: float) -> np.ndarray:
        n = np.array([-t[1], t[0]])
        hl, hw = 0.5 * length * t, 0.5 * width * n
        return np.array([c - hl - hw, c + hl - hw, c + hl + hw, c - hl + hw])

    def _clear(self, c: np.ndarray, t: np.ndarray, dims) -> bool:
        """The footprint (grown by 1.2 m) keeps clear of every part of the path."""
        corners = self._footprint(c, t, dims[0] + 2.4, dims[1] + 2.4)
        g = (corners - self.lo) / self.cell
        x0, y0 = np.floor(g.min(0)).astype(int)
        x1, y1 = np.ceil(g.max(0)).astype(int) + 1
        if x0 < 0 or y0 < 0 or x1 > self.dist.shape[1] or y1 > self.dist.shape[0]:
            return True  # beyond the raster: far from the path
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, np.rint(g - [x0, y0]).astype(np.int32), 1)
        return bool((self.dist[y0:y1, x0:x1][mask.astype(bool)] > 0.5 * self.cell).all())

    def vehicles(self, i: int) -> list[tuple[np.ndarray, np.ndarray, tuple, tuple]]:
        """(centre xz, heading xz, dims, look) of every car present at frame ``i``."""
        out = [(c, t, dims, look) for (c, t, dims, look, _), on in zip(self.slots, self.parked[:, i]) if on]
        now = self.times[i]
        cam_arc = self.frame_arc[i]
        step = self.world.config.path_step_m
        arcs = np.arange(len(self.samples)) * step
        for t0, s0, v, dims, look in self.oncoming:
            if t0 > now:
                break
            s = s0 - v * (now - t0)
            if s < cam_arc - 60.0 or now - t0 > 60.0 or s < 0 or s > arcs[-1]:
                continue
            p = np.array([np.interp(s, arcs, self.samples[:, 0]), np.interp(s, arcs, self.samples[:, 1])])
            k = min(int(round(s / step)), len(self.samples) - 1)
            t = self.tangents[k]
            c = p + np.array([-t[1], t[0]]) * self.world.config.oncoming_offset_m
            if self._clear(c, t, dims):
                out.append((c, -t, dims, look))
        return out

    def mesh(self, i: int, face0: int = 0):
        """Vertices, triangles, triangle faces and face rows of the cars at frame ``i``."""
        world = self.world
        verts, tris, faces, rows = [], [], [], []
        nv = 0
        for c, t, (length, width, body_h, total_h), (paint, offset, ident) in self.vehicles(i):
            gy = float(world.ground_y(np.array([c[0]]), np.array([c[1]]))[0])
            parts = [(self._footprint(c, t, length, width), gy + 0.3, gy - body_h, paint)]
            if total_h > body_h:  # a cabin, inset, set back a little
                parts.append(
                    (self._footprint(c - 0.1 * length * t, t, 0.55 * length, width - 0.2), gy - body_h + 0.01, gy - total_h, 0.12)
                )
            for corners, bottom, top, albedo in parts:
                v = np.zeros((8, 3))
                v[:4, 0], v[:4, 2], v[:4, 1] = corners[:, 0], corners[:, 1], bottom
                v[4:, 0], v[4:, 2], v[4:, 1] = corners[:, 0], corners[:, 1], top
                for k in range(4):
                    k1 = (k + 1) % 4
                    tris += [[nv + k, nv + k1, nv + 4 + k1], [nv + k, nv + 4 + k1, nv + 4 + k]]
                    faces += [face0 + len(rows)] * 2
                    t3 = v[k1] - v[k]
                    t3[1] = 0.0
                    t3 /= max(np.linalg.norm(t3), 1e-9)
                    rows.append(
                        world._face_row(
                            FACADE,
                            np.array([v[k, 0], gy, v[k, 2]]),
                            t3,
                            albedo=albedo,
                            noise_amp=0.03,
                            offset=offset,
                            ident=ident,
                        )
                    )
                tris += [[nv + 4, nv + 5, nv + 6], [nv + 4, nv + 6, nv + 7]]
                faces += [face0 + len(rows)] * 2
                # roof texture in the car's own frame: tu along it, tv across (moves with it)
                rows.append(
                    world._face_row(
                        FACADE,
                        np.array([v[4, 0], gy, v[4, 2]]),
                        np.array([t[0], 0.0, t[1]]),
                        albedo=albedo * 0.9,
                        noise_amp=0.03,
                        offset=offset,
                        ident=ident,
                    )
                )
                rows[-1]["kind"] = ROOF
                verts.append(v)
                nv += 8
        if not verts:
            return None
        return np.concatenate(verts), np.array(tris), np.array(faces, np.int32), rows

    def layer(self, i: int) -> Layer | None:
        """The cars of frame ``i`` as a ``Layer`` (None when there are none)."""
        world = self.world
        m = self.mesh(i, len(world.faces))
        if m is None:
            return None
        v, t, f, rows = m
        local = _table(rows)
        faces = FaceTable(
            np.concatenate([world.faces.kind, local.kind]),
            np.concatenate([world.faces.main, local.main], axis=1),
            np.concatenate([world.faces.detail, local.detail], axis=1),
        )
        return Layer(_raycasting_scene(v, t), np.concatenate([world.tri_face, f]), faces, len(world.triangles))


def _table(rows: list[dict]) -> FaceTable:
    origin = np.array([r["origin"] for r in rows], dtype=np.float64)
    tangent = np.array([r["tangent"] for r in rows], dtype=np.float64)
    offset = np.array([r["offset"] for r in rows], dtype=np.float64)
    kind = np.array([r["kind"] for r in rows], dtype=np.uint8)
    vertical = (kind == FACADE) | (kind == BACKDROP) | (kind == TREE)
    cols = {
        "tu_x": tangent[:, 0],
        "tu_z": tangent[:, 2],
        # horizontal faces have tangent (1, 0, 0) and origin 0: tu = x + off_u, tv = z + off_v
        "tu_c": offset[:, 0] - (origin[:, 0] * tangent[:, 0] + origin[:, 2] * tangent[:, 2]),
        "tv_c": np.where(vertical, origin[:, 1], 0.0) + offset[:, 1],
        "tu_off": offset[:, 0],
        "tv_off": offset[:, 1],
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
    head = _free_run(samples[0] - k * t_start, samples[int(30 / step) :], 3 * 5.0)[::-1]
    tail = _free_run(samples[-1] + k * t_end, samples[: max(len(samples) - int(30 / step), 0)], 3 * 5.0)
    samples = np.concatenate([head, samples, tail])
    tangents = np.concatenate([np.repeat(t_start[None], len(head), 0), tangents, np.repeat(t_end[None], len(tail), 0)])
    gy = np.concatenate([np.full(len(head), gy[0]), gy, np.full(len(tail), gy[-1])])
    return samples, tangents, gy


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the maximal runs of True in a boolean array."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) > 1) + 1
    return np.split(idx, cut)


def _free_run(ext: np.ndarray, others: np.ndarray, min_gap: float) -> np.ndarray:
    """The extension points up to the first that comes within ``min_gap`` of ``others`` (so a
    path that ends where it began, like a loop, does not get a phantom street across it)."""
    if len(others) == 0:
        return ext
    d = np.sqrt(((ext[:, None, :] - others[None, :, :]) ** 2).sum(-1)).min(1)
    bad = np.flatnonzero(d < min_gap)
    return ext[: bad[0]] if len(bad) else ext
