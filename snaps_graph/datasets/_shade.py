"""Ray casting and shading of a synthetic world (textures are functions of the world hit point).

Decisions:

* **Rays** are built from precomputed camera-frame directions ``((u - cx)/fx, (v - cy)/fy, 1)``.
  open3d returns the hit distance in units of the direction's length, so with z = 1 the hit
  distance *is* the z-depth: the depth map is exact, with no division.
* **Texture** is a deterministic function of the world hit point and the surface it lies on
  (face table in ``_world``), never of the pixel or the frame: a place looks the same on every
  visit and in both cameras, which is what loop closure and stereo matching need.
* **Noise** is a sum of octaves, each a bilinear lookup (``cv2.remap``, which releases the GIL and
  is vectorised) into a small precomputed tile of smoothed white noise, at scales that are not
  multiples of each other and with a per-octave rotation, so the sum never visibly repeats.
* **Anti-aliasing**: one ray per pixel cannot resolve detail smaller than a pixel, so each
  octave, brick and window pattern fades to its mean once its wavelength spans fewer than about
  two pixels at the hit (footprint = distance / fx, stretched at grazing angles). Far surfaces
  go smooth instead of shimmering, so the same place renders alike from nearby poses.
* **Light**: ambient + Lambertian from a fixed sun (faces of different orientation differ), a
  gentle distance haze toward the horizon colour, and a sky whose brightness grows with
  elevation. No shadows (they would need a second cast per pixel).
"""

from __future__ import annotations

import cv2
import numpy as np

from ._world import BACKDROP, FACADE, GROUND, ROOF, SKY, World

TILE = 256  # noise tile side, cells
# (scale m per tile cell, relative amplitude): incommensurate scales, from 4 cm grain to 9 m blotches
OCTAVES = ((0.043, 0.45), (0.13, 0.5), (0.41, 0.55), (1.37, 0.6), (3.9, 0.55), (9.1, 0.5))
SUN_DIR = np.array([0.45, -0.75, 0.48])  # towards the sun, world axes (y down): high, front-right
SUN_DIR = SUN_DIR / np.linalg.norm(SUN_DIR)
AMBIENT, DIFFUSE = 0.55, 0.5
HAZE_M = 350.0  # haze reaches 63 % at this distance
HORIZON = 0.78  # haze / horizon brightness (0..1)


class NoiseBank:
    """Tiles of band-limited, zero-mean, unit-std periodic noise, one per octave."""

    def __init__(self, seed: int):
        rng = np.random.default_rng([int(seed), 0x7E57])
        self.tiles = []
        self.rot = []
        for _ in OCTAVES:
            white = rng.standard_normal((TILE, TILE)).astype(np.float32)
            # wrap-around blur keeps the tile periodic (BORDER_WRAP is not offered by blur: pad)
            pad = np.pad(white, 8, mode="wrap")
            tile = cv2.GaussianBlur(pad, (0, 0), 1.0)[8:-8, 8:-8]
            tile = (tile - tile.mean()) / tile.std()
            self.tiles.append(np.ascontiguousarray(tile))
            a = rng.uniform(0, np.pi)
            self.rot.append((np.float32(np.cos(a)), np.float32(np.sin(a))))
        # A separate coarse tile for ground patches (tar repairs, stains) with crisp edges.
        white = rng.standard_normal((TILE, TILE)).astype(np.float32)
        tile = cv2.GaussianBlur(np.pad(white, 8, mode="wrap"), (0, 0), 2.0)[8:-8, 8:-8]
        self.patch_tile = np.ascontiguousarray((tile - tile.mean()) / tile.std())

    @staticmethod
    def sample(tile: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear periodic lookup at tile coordinates (x, y) (any real values)."""
        # Wrap into [0, TILE) first: remap's own border handling is 10x slower far outside the
        # tile, and np.mod on floats is slower still; x - floor(x / T) * T is three cheap passes.
        inv = np.float32(1.0 / TILE)
        mx = (x - np.floor(x * inv) * np.float32(TILE)).astype(np.float32, copy=False)
        my = (y - np.floor(y * inv) * np.float32(TILE)).astype(np.float32, copy=False)
        return cv2.remap(tile, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def fbm(self, tu: np.ndarray, tv: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Sum of octaves at texture coordinates (m); octaves finer than ~2 px fade out."""
        out = np.zeros(tu.shape, np.float32)
        for (scale, amp), tile, (c, s) in zip(OCTAVES, self.tiles, self.rot):
            inv = np.float32(1.0 / scale)
            x = (tu * c - tv * s) * inv
            y = (tu * s + tv * c) * inv
            # blurred-noise features are ~3 cells wide: full weight at >= 4 px, none at <= 2 px
            w = np.clip(np.float32(1.5 * scale) / footprint - np.float32(1.0), 0.0, 1.0)
            out += np.float32(amp) * w * self.sample(tile, x, y)
        return out


def _hash(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) from three integer arrays (a murmur-style mix on uint32; wraps on purpose)."""
    h = a.astype(np.int64).astype(np.uint32) * np.uint32(0x9E3779B1)
    h ^= b.astype(np.int64).astype(np.uint32) * np.uint32(0x85EBCA77)
    h ^= c.astype(np.uint32) * np.uint32(0xC2B2AE3D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def _edge(dist_inside: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """Anti-aliased step: 1 well inside a shape, 0 outside, a one-pixel ramp at its edge."""
    return np.clip(dist_inside / footprint + np.float32(0.5), 0.0, 1.0)


class Renderer:
    """Casts a camera's rays into a ``World`` and shades them into grey images."""

    def __init__(self, world: World, fx: float, fy: float, cx: float, cy: float, width: int, height: int, seed: int):
        self.world = world
        self.fx = float(fx)
        self.width, self.height = int(width), int(height)
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        self.dirs_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1).astype(np.float32)
        self.dir_norm = np.linalg.norm(self.dirs_cam, axis=-1).astype(np.float32)
        self.noise = NoiseBank(seed)

    def cast(self, R: np.ndarray, origin: np.ndarray) -> dict[str, np.ndarray]:
        """Cast one image's rays from ``origin`` with camera rotation ``R`` (world from camera)."""
        import open3d as o3d

        d = self.dirs_cam @ R.T.astype(np.float32)
        rays = np.empty((self.height, self.width, 6), np.float32)
        rays[..., :3] = np.asarray(origin, np.float32)
        rays[..., 3:] = d
        out = self.world.scene.cast_rays(o3d.core.Tensor(rays))
        t = out["t_hit"].numpy()
        return {"t": t, "prim": out["primitive_ids"].numpy(), "normal": out["primitive_normals"].numpy(), "dirs": d,
                "origin": np.asarray(origin, np.float32)}

    @staticmethod
    def depth(hit: dict[str, np.ndarray]) -> np.ndarray:
        """z-depth (m) of a cast, 0 where no surface was hit (the sky)."""
        t = hit["t"]
        return np.where(np.isfinite(t), t, np.float32(0.0)).astype(np.float32)

    def shade(self, hit: dict[str, np.ndarray]) -> np.ndarray:
        """Grey levels (float32, 0..255 before exposure/noise) of a cast."""
        world, F = self.world, self.world.faces
        t, d, o = hit["t"], hit["dirs"], hit["origin"]
        valid = np.isfinite(t)
        tz = np.where(valid, t, np.float32(0.0))
        face = world.tri_face[np.where(valid, hit["prim"], 0)]
        kind = np.where(valid, F.kind[face], np.uint8(SKY))

        px = o[0] + tz * d[..., 0]
        py = o[1] + tz * d[..., 1]
        pz = o[2] + tz * d[..., 2]
        n = hit["normal"]
        dist = tz * self.dir_norm  # Euclidean distance along the ray
        # cos of incidence (normals from open3d may face either way: use |n.d|)
        cos_i = np.abs(n[..., 0] * d[..., 0] + n[..., 1] * d[..., 1] + n[..., 2] * d[..., 2]) / self.dir_norm
        footprint = dist / np.float32(self.fx) / np.sqrt(np.maximum(cos_i, np.float32(0.05)))
        footprint = np.maximum(footprint, np.float32(1e-4))

        vertical = (kind == FACADE) | (kind == BACKDROP)
        org = F.origin[face]
        tan = F.tangent[face]
        su = (px - org[..., 0]) * tan[..., 0] + (pz - org[..., 2]) * tan[..., 2]  # along the face
        sv = org[..., 1] - py  # height above the face's ground
        tu = np.where(vertical, su, px)
        tv = np.where(vertical, sv, pz)
        off = F.offset[face]
        noise = self.noise.fbm(tu + off[..., 0], tv + off[..., 1], footprint)

        albedo = F.albedo[face] + F.noise_amp[face] * noise

        # Bricks / stones / planks: a per-brick brightness (hash) and dark mortar lines.
        bw, bh = F.brick_w[face], F.brick_h[face]
        has_brick = bw > 0
        if has_brick.any():
            bws = np.where(has_brick, bw, np.float32(1.0))
            bhs = np.where(has_brick, bh, np.float32(1.0))
            row = np.floor(sv / bhs)
            bu = su / bws + np.float32(0.5) * np.mod(row, 2)
            col = np.floor(bu)
            ident = F.ident[face]
            rnd = _hash(col, row, ident) - np.float32(0.5)
            fade = np.clip(np.minimum(bhs, bws) / footprint * np.float32(0.25) - np.float32(0.5), 0.0, 1.0)
            mortar_w = np.float32(0.025)
            du = (bu - col - np.float32(0.5)) * bws  # m from the brick centre
            dv = (sv / bhs - row - np.float32(0.5)) * bhs
            inside = np.minimum(bws * 0.5 - np.abs(du), bhs * 0.5 - np.abs(dv)) - mortar_w
            brick = _edge(inside, footprint)
            albedo += np.where(has_brick, fade * (F.brick_amp[face] * rnd - np.float32(0.12) * (1 - brick)), 0.0)

        # Windows: a grid of dark panes, each with its own brightness (reflections, lit rooms).
        ww, wh = F.win_w[face], F.win_h[face]
        has_win = ww > 0
        if has_win.any():
            wws = np.where(has_win, ww, np.float32(1.0))
            whs = np.where(has_win, wh, np.float32(1.0))
            cu = np.floor(su / wws)
            cv = np.floor(sv / whs)
            du = (su / wws - cu - np.float32(0.5)) * wws
            dv = (sv / whs - cv - np.float32(0.55)) * whs
            inside = np.minimum(F.win_fx[face] * wws * 0.5 - np.abs(du), F.win_fy[face] * whs * 0.5 - np.abs(dv))
            pane = _edge(inside, footprint)
            # no panes below 0.8 m or within one floor of the top
            pane *= (sv > 0.8) & (sv < F.top[face] - 0.6 * whs)
            glass = np.float32(0.08) + np.float32(0.35) * _hash(cu, cv, F.ident[face]) ** 2
            fade = np.clip(np.minimum(wws, whs) / footprint * np.float32(0.125) - np.float32(0.5), 0.0, 1.0)
            mean_glass = np.float32(0.2)
            pane_val = fade * glass + (1 - fade) * mean_glass
            albedo = np.where(has_win, albedo * (1 - pane) + pane * (pane_val + np.float32(0.2) * noise * 0.1), albedo)

        # Ground patches: crisp-edged repairs / stains that give corners on the road surface.
        is_ground = kind == GROUND
        if is_ground.any():
            pn = self.noise.sample(self.noise.patch_tile, (px + 311.0) / np.float32(0.6), (pz - 127.0) / np.float32(0.6))
            edge_m = np.float32(0.6 * 0.25)  # d(noise)/dx ~ 1 / (2 cells) -> metres per unit noise
            patch = _edge((pn - np.float32(1.0)) * edge_m, footprint)
            stain = _edge((-np.float32(1.2) - pn) * edge_m, footprint)
            albedo += np.where(is_ground, np.float32(-0.1) * patch + np.float32(0.12) * stain, 0.0)

        # Light: ambient + Lambertian, normals oriented towards the camera.
        ndotl = np.abs(n[..., 0] * SUN_DIR[0] + n[..., 1] * SUN_DIR[1] + n[..., 2] * SUN_DIR[2])
        # a surface facing away from the sun (relative to the viewer) gets only ambient light
        facing = (n[..., 0] * d[..., 0] + n[..., 1] * d[..., 1] + n[..., 2] * d[..., 2]) < 0
        sun_side = (n[..., 0] * SUN_DIR[0] + n[..., 1] * SUN_DIR[1] + n[..., 2] * SUN_DIR[2]) > 0
        lit = np.where(facing == sun_side, ndotl, np.float32(0.0))
        grey = np.clip(albedo, 0.02, 1.0) * (np.float32(AMBIENT) + np.float32(DIFFUSE) * lit)
        haze = np.float32(1.0) - np.exp(-dist / np.float32(HAZE_M))
        grey = grey * (1 - haze) + np.float32(HORIZON) * haze

        # Sky: brighter with elevation (world up is -y).
        elev = -d[..., 1] / self.dir_norm
        sky = np.float32(HORIZON) + np.float32(0.15) * np.clip(elev * 2.5, 0.0, 1.0)
        grey = np.where(valid, grey, sky)
        return grey * np.float32(255.0)
