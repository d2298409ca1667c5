"""Ray casting and shading of a synthetic world (textures are functions of the world hit point).

Rays with z = 1 make the hit distance the exact z-depth; texture is octave noise looked up
(``cv2.remap``) at the world hit point and faded to its mean below about two pixels' wavelength;
light is ambient + Lambertian with haze, plus shadow rays with ``lighting``. Why: docs/datasets.md,
"How the world is rendered".
"""

from __future__ import annotations

import threading
from typing import Any

import cv2
import numpy as np

from ._world import BACKDROP, FACADE, GROUND, SKY, TREE, Layer, World, WorldConfig

TILE = 256  # noise tile side, cells
CHUNK = 24576  # pixels shaded at a time: 96 KB float32 temporaries (see Renderer)
# (scale m per tile cell, relative amplitude): incommensurate scales, from 5 cm grain to 6 m
# blotches; each octave costs one remap per image, four are enough next to bricks and windows.
OCTAVES = ((0.053, 0.55), (0.23, 0.6), (0.97, 0.55), (4.3, 0.35))
SUN_DIR = np.array([0.45, -0.75, 0.48])  # towards the sun, world axes (y down): high, front-right
SUN_DIR = (SUN_DIR / np.linalg.norm(SUN_DIR)).astype(np.float32)
AMBIENT, DIFFUSE = 0.55, 0.5
SUN_AMBIENT, SUN_DIFFUSE = 0.38, 0.8  # with lighting (shadows): a clear day's contrast
HAZE_M = 350.0  # haze reaches 63 % at this distance
HORIZON = 0.78  # haze / horizon brightness (0..1)


def sun_direction(config: WorldConfig, t_s: float) -> np.ndarray:
    """Unit vector towards the sun (world axes, y down) at ``t_s`` seconds after the first frame.

    The time of day starts at ``day_start_h`` and runs ``day_hours_per_minute`` hours per
    minute of trajectory, bouncing between 7:00 and 17:00 (so it never jumps). The sun rises in
    the east (world -x), stands south (world -z) at noon 50 deg high, sets in the west; it is
    at least 12 deg high.
    """
    h = config.day_start_h - 7.0 + t_s / 60.0 * config.day_hours_per_minute
    h = 7.0 + 10.0 - abs(h % 20.0 - 10.0)  # triangle wave in [7, 17]
    frac = (h - 6.0) / 12.0  # 0 at sunrise, 1 at sunset
    el = np.radians(max(50.0 * np.sin(np.pi * frac), 12.0))
    az = np.pi * frac  # 0 east, pi/2 south, pi west
    v = np.array([-np.cos(az) * np.cos(el), -np.sin(el), -np.sin(az) * np.cos(el)])
    return (v / np.linalg.norm(v)).astype(np.float32)


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
        """Bilinear periodic lookup at tile coordinates (x, y): flat arrays of < 32767 values."""
        # Wrap into [0, TILE) first: remap's border handling and np.mod on floats are both slow
        # far outside the tile; x - floor(x / T) * T is three cheap passes.
        inv, T = np.float32(1.0 / TILE), np.float32(TILE)
        mx = (x - np.floor(x * inv) * T).reshape(1, -1)  # remap takes 2-D maps: one row
        my = (y - np.floor(y * inv) * T).reshape(1, -1)
        return cv2.remap(tile, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).reshape(-1)

    def fbm(self, tu: np.ndarray, tv: np.ndarray, inv_fp: np.ndarray) -> np.ndarray:
        """Sum of octaves at texture coordinates (m); ``inv_fp`` is pixels per metre at the hit.

        Blurred-noise features are ~3 cells wide, so an octave has full weight when a cell spans
        >= 4/3 px and none below 2/3 px (it would only alias).
        """
        f32 = np.float32
        out = np.zeros(tu.shape, f32)
        for (scale, amp), tile, (c, s) in zip(OCTAVES, self.tiles, self.rot):
            inv = f32(1.0 / scale)
            x = tu * (c * inv) - tv * (s * inv)
            y = tu * (s * inv) + tv * (c * inv)
            w = np.clip(inv_fp * f32(1.5 * scale) - f32(1.0), f32(0.0), f32(1.0))
            w *= f32(amp)
            out += w * self.sample(tile, x, y)
        return out


def _hash(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) from three integer arrays (a murmur-style mix on uint32; wraps on purpose)."""
    h = a.astype(np.int64).astype(np.uint32) * np.uint32(0x9E3779B1)
    h ^= b.astype(np.int64).astype(np.uint32) * np.uint32(0x85EBCA77)
    h ^= c.astype(np.int64).astype(np.uint32) * np.uint32(0xC2B2AE3D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    h *= np.uint32(0x297A2D39)
    h ^= h >> np.uint32(15)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def _edge(dist_inside: np.ndarray, inv_fp: np.ndarray) -> np.ndarray:
    """Anti-aliased step: 1 well inside a shape, 0 outside, a one-pixel ramp at its edge
    (``dist_inside`` in metres, ``inv_fp`` pixels per metre at the hit)."""
    return np.clip(dist_inside * inv_fp + np.float32(0.5), np.float32(0.0), np.float32(1.0))


class Renderer:
    """Casts a camera's rays into a ``World`` and shades them into grey images: in chunks of ``CHUNK``
    pixels and without BLAS (docs/decisions.md, "Speed"), the ray buffer reused per thread and handed
    to open3d without a copy.
    """

    def __init__(self, world: World, fx: float, fy: float, cx: float, cy: float, width: int, height: int, seed: int):
        self.world = world
        self.fx = float(fx)
        self.width, self.height = int(width), int(height)
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        # camera-frame directions with z = 1, so the hit distance open3d returns is the z-depth
        self.cam_dirs = (((u - cx) / fx).ravel().astype(np.float32), ((v - cy) / fy).ravel().astype(np.float32))
        self.dir_norm = np.sqrt(self.cam_dirs[0] ** 2 + self.cam_dirs[1] ** 2 + np.float32(1.0)).astype(np.float32)
        self.noise = NoiseBank(seed)
        self._local = threading.local()

    def cast(
        self, R: np.ndarray, origin: np.ndarray, layer: Layer | None = None, sun: np.ndarray | None = None
    ) -> dict[str, Any]:
        """Cast one image's rays from ``origin`` with camera rotation ``R`` (world from camera),
        into the static world and, when given, a ``layer`` of the instant (traffic). With ``sun``
        (unit vector towards the sun, world axes) the hits are also tested for cast shadows."""
        import open3d as o3d

        dx, dy = self.cam_dirs
        R = np.asarray(R, np.float32)
        rays = getattr(self._local, "rays", None)
        if rays is None:
            rays = self._local.rays = np.empty((dx.size, 6), np.float32)
        rays[:, :3] = np.asarray(origin, np.float32)
        d = []
        for k in range(3):  # world directions (camera z = 1)
            rays[:, 3 + k] = dx * R[k, 0] + dy * R[k, 1] + R[k, 2]
            d.append(rays[:, 3 + k])
        tensor = o3d.core.Tensor.from_numpy(rays)
        out = self.world.scene.cast_rays(tensor)
        hit = {
            "t": out["t_hit"].numpy(),
            "prim": out["primitive_ids"].numpy(),
            "normal": out["primitive_normals"].numpy(),
            "R": R,
            "origin": np.asarray(origin, np.float32),
            "tri_face": self.world.tri_face,
            "faces": self.world.faces,
        }
        if layer is not None:
            o2 = layer.scene.cast_rays(tensor)
            t2 = o2["t_hit"].numpy()
            closer = t2 < hit["t"]
            if closer.any():
                hit["t"] = np.where(closer, t2, hit["t"])
                hit["prim"] = np.where(closer, o2["primitive_ids"].numpy() + np.uint32(layer.n_static), hit["prim"])
                hit["normal"] = np.where(closer[:, None], o2["primitive_normals"].numpy(), hit["normal"])
            hit["tri_face"], hit["faces"] = layer.tri_face, layer.faces
        if sun is not None:
            hit["sun"] = np.asarray(sun, np.float32)
            hit["shadow"] = self._shadows(hit, rays, layer)
        return hit

    def _shadows(self, hit: dict, rays: np.ndarray, layer: Layer | None) -> np.ndarray:
        """True where a hit point cannot see the sun (a ray towards it meets the world)."""
        import open3d as o3d

        t = hit["t"]
        valid = np.flatnonzero(np.isfinite(t))
        shadow = np.zeros(t.shape, bool)
        if valid.size == 0:
            return shadow
        d = rays[valid, 3:]
        n = hit["normal"][valid]
        n = np.where((np.einsum("ij,ij->i", n, d) < 0)[:, None], n, -n)  # the normal facing the camera
        srays = np.empty((valid.size, 6), np.float32)
        srays[:, :3] = rays[valid, :3] + d * t[valid, None] + n * np.float32(0.03)
        srays[:, 3:] = hit["sun"]
        tensor = o3d.core.Tensor.from_numpy(srays)
        occ = self.world.scene.test_occlusions(tensor).numpy().astype(bool)
        if layer is not None:
            occ |= layer.scene.test_occlusions(tensor).numpy().astype(bool)
        shadow[valid] = occ
        return shadow

    def depth(self, hit: dict[str, Any]) -> np.ndarray:
        """z-depth (m) of a cast as an (H, W) image, 0 where no surface was hit (the sky)."""
        t = hit["t"]
        return np.where(np.isfinite(t), t, np.float32(0.0)).astype(np.float32).reshape(self.height, self.width)

    def shade(self, hit: dict[str, Any]) -> np.ndarray:
        """Grey levels (float32 (H, W), 0..255 before exposure/noise) of a cast."""
        n_pix = self.width * self.height
        out = np.empty(n_pix, np.float32)
        for s in range(0, n_pix, CHUNK):
            sl = slice(s, min(s + CHUNK, n_pix))
            out[sl] = self._shade_chunk(hit, sl)
        return out.reshape(self.height, self.width)

    def _shade_chunk(self, hit: dict[str, Any], sl: slice) -> np.ndarray:
        world, F = self.world, hit["faces"]
        f32 = np.float32
        R, o = hit["R"], hit["origin"]
        cdx, cdy, dnorm = self.cam_dirs[0][sl], self.cam_dirs[1][sl], self.dir_norm[sl]
        dx, dy, dz = (cdx * R[k, 0] + cdy * R[k, 1] + R[k, 2] for k in range(3))
        t = hit["t"][sl]
        valid = np.isfinite(t)
        tz = np.where(valid, t, f32(0.0))
        face = np.take(hit["tri_face"], np.where(valid, hit["prim"][sl], np.uint32(0)).astype(np.int32))
        kind = np.where(valid, np.take(F.kind, face), np.uint8(SKY))
        tu_x, tu_z, tu_c, tv_c, albedo0, noise_amp = np.take(F.main, face, axis=1)
        n = hit["normal"][sl]
        nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]

        px = dx * tz + o[0]
        py = dy * tz + o[1]
        pz = dz * tz + o[2]
        dist = tz * dnorm  # Euclidean distance along the ray
        # |cos| of incidence (open3d normals may face either way)
        n_dot_d = nx * dx + ny * dy + nz * dz
        cos_i = np.abs(n_dot_d) / dnorm
        # Pixels per metre on the surface: f / distance, shrunk at grazing angles (the square
        # root is a compromise between the along- and across-ray footprints).
        inv_fp = (f32(self.fx) * np.sqrt(np.maximum(cos_i, f32(0.05)))) / np.maximum(dist, f32(1e-3))

        # Texture coordinates (m): along / up a vertical face, or world (x, z) on the ground and
        # roofs, with a per-surface random offset (see _world.MAIN_FIELDS).
        vertical = (kind == FACADE) | (kind == BACKDROP) | (kind == TREE)
        tu = px * tu_x + pz * tu_z + tu_c
        tv = np.where(vertical, -py, pz) + tv_c
        noise = self.noise.fbm(tu, tv, inv_fp)
        albedo = noise_amp * noise + albedo0

        fi = np.flatnonzero(kind == FACADE)
        if fi.size:
            sub = [np.take(a, fi) for a in (tu, tv, inv_fp, noise, albedo)]
            albedo[fi] += self._facade(np.take(F.detail, np.take(face, fi), axis=1), *sub)
        gi = np.flatnonzero(kind == GROUND)
        if gi.size:
            gx, gz, gfp = np.take(px, gi), np.take(pz, gi), np.take(inv_fp, gi)
            if world.ground_dist is None:
                albedo[gi] += self._ground(gx, gz, gfp)
            else:
                # the footprint along the ray (grazing ground), for patterns that alias first
                gfp_min = gfp * np.sqrt(np.maximum(np.take(cos_i, gi), f32(0.05)))
                albedo[gi] += self._open_ground(gx, gz, gfp, gfp_min, np.take(noise, gi), np.take(albedo, gi))

        # Light: ambient + Lambertian from the sun, normals turned towards the camera: a face
        # is sunlit when it and the sun lie on the same side of it as the viewer.
        sun = hit.get("sun", SUN_DIR)
        n_dot_l = nx * sun[0] + ny * sun[1] + nz * sun[2]
        lit = np.where((n_dot_d < 0) == (n_dot_l > 0), np.abs(n_dot_l), f32(0.0))
        if "shadow" in hit:  # lighting: stronger sun, weaker sky light, cast shadows
            lit = np.where(hit["shadow"][sl], f32(0.0), lit)
            grey = np.clip(albedo, f32(0.02), f32(1.0)) * (lit * f32(SUN_DIFFUSE) + f32(SUN_AMBIENT))
        else:
            grey = np.clip(albedo, f32(0.02), f32(1.0)) * (lit * f32(DIFFUSE) + f32(AMBIENT))
        haze = dist / (dist + f32(HAZE_M))  # rational haze: cheaper than exp, same look
        grey += (f32(HORIZON) - grey) * haze

        # Sky: brighter with elevation (world up is -y).
        sky = np.clip(dy / dnorm * f32(-2.5), f32(0.0), f32(1.0)) * f32(0.15) + f32(HORIZON)
        grey = np.where(valid, grey, sky)
        grey *= f32(255.0)
        return grey

    @staticmethod
    def _facade(detail, tu, tv, inv_fp, noise, albedo):
        """Albedo change from bricks and windows on facade pixels (1-D arrays of those pixels;
        ``detail`` holds their faces' DETAIL_FIELDS rows)."""
        f32 = np.float32
        tu_off, tv_off, brick_w, brick_h, brick_amp, win_w, win_h, win_fx, win_fy, top, ident = detail
        su = tu - tu_off  # m along the face from its corner
        sv = tv - tv_off  # m above the face's ground
        delta = np.zeros_like(tu)

        # Bricks / stones / planks: per-brick brightness (a hash) and dark mortar lines.
        bi = np.flatnonzero(brick_w > 0)
        if bi.size:
            bw, bh, u, v, ifp = (np.take(a, bi) for a in (brick_w, brick_h, su, sv, inv_fp))
            row = np.floor(v / bh)
            bu = u / bw + f32(0.5) * (row - f32(2.0) * np.floor(row * f32(0.5)))  # odd rows shifted
            col = np.floor(bu)
            rnd = _hash(col, row, np.take(ident, bi)) - f32(0.5)
            du = (bu - col - f32(0.5)) * bw  # m from the brick centre
            dv = (v / bh - row - f32(0.5)) * bh
            inside = np.minimum(bw * f32(0.5) - np.abs(du), bh * f32(0.5) - np.abs(dv)) - f32(0.025)
            mortar = f32(1.0) - _edge(inside, ifp)
            fade = np.clip(np.minimum(bh, bw) * ifp * f32(0.25) - f32(0.5), f32(0.0), f32(1.0))
            delta[bi] = fade * (np.take(brick_amp, bi) * rnd - f32(0.12) * mortar)

        # Windows: a grid of panes, each with its own brightness (reflections, lit rooms); no
        # panes below 0.8 m nor in the top 0.6 floor.
        wi = np.flatnonzero(win_w > 0)
        if wi.size:
            ww, wh, u, v, ifp, fx, fy, tp = (np.take(a, wi) for a in (win_w, win_h, su, sv, inv_fp, win_fx, win_fy, top))
            cu = np.floor(u / ww)
            cv = np.floor(v / wh)
            du = (u / ww - cu - f32(0.5)) * ww
            dv = (v / wh - cv - f32(0.55)) * wh
            inside = np.minimum(fx * ww * f32(0.5) - np.abs(du), fy * wh * f32(0.5) - np.abs(dv))
            pane = _edge(inside, ifp) * ((v > f32(0.8)) & (v < tp - f32(0.6) * wh))
            glass = _hash(cu, cv, np.take(ident, wi)) ** 2 * f32(0.35) + f32(0.08)
            fade = np.clip(np.minimum(ww, wh) * ifp * f32(0.125) - f32(0.5), f32(0.0), f32(1.0))
            pane_val = fade * (glass - f32(0.2)) + f32(0.2) + f32(0.02) * np.take(noise, wi)
            base = np.take(albedo, wi) + np.take(delta, wi)
            delta[wi] += pane * (pane_val - base)
        return delta

    def _ground(self, px, pz, inv_fp):
        """Albedo change from crisp-edged patches (repairs, stains): corners on the road surface."""
        f32 = np.float32
        pn = self.noise.sample(self.noise.patch_tile, (px + f32(311.0)) * f32(1 / 0.6), (pz - f32(127.0)) * f32(1 / 0.6))
        edge_m = f32(0.6 * 0.25)  # metres per unit of noise near a level crossing (~2-cell slope)
        patch = _edge((pn - f32(1.0)) * edge_m, inv_fp)
        stain = _edge((f32(-1.2) - pn) * edge_m, inv_fp)
        return stain * f32(0.12) - patch * f32(0.1)

    def _open_ground(self, px, pz, inv_fp, inv_fp_min, noise, albedo):
        """Albedo change on the ground of open stretches: smooth asphalt with a white edge line within
        ``road_half_width_m`` of the path, a grass verge, then field parcels (meadows and
        ploughed or cropped fields whose rows fade to their mean once under ~2 px apart, like
        any texture here; rows use the footprint along the ray, ``inv_fp_min`` px/m, as they
        alias first). Street stretches of a mixed world keep the street ground."""
        f32 = np.float32
        w = self.world
        cfg = w.config
        inv_cell = f32(1.0 / w.raster_cell)
        gx = ((px - f32(w.raster_lo[0])) * inv_cell).reshape(1, -1)
        gz = ((pz - f32(w.raster_lo[1])) * inv_cell).reshape(1, -1)
        d = cv2.remap(w.ground_dist, gx, gz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)
        street = self._ground(px, pz, inv_fp)
        rw, verge_m = f32(cfg.road_half_width_m), f32(cfg.verge_m)
        on_road = _edge(rw - d, inv_fp)
        in_field = _edge(d - (rw + verge_m), inv_fp)
        verge = np.clip(f32(1.0) - on_road - in_field, f32(0.0), f32(1.0))
        line = _edge(f32(0.075) - np.abs(d - (rw - f32(0.3))), inv_fp)
        # Field parcels on a rotated grid; per parcel (hash): brightness, row direction and
        # spacing, rows or none (meadow).
        c, s = f32(0.8), f32(0.6)
        u = px * c + pz * s
        v = pz * c - px * s
        fu, fv = (f32(x) for x in self.world.config.field_size_m)
        iu, iv = np.floor(u / fu), np.floor(v / fv)
        h1, h2, h3 = _hash(iu, iv, np.full_like(iu, 11)), _hash(iu, iv, np.full_like(iu, 12)), _hash(iu, iv, np.full_like(iu, 13))
        spacing = f32(0.5) + f32(1.2) * h3
        rows = np.cos(np.where(h2 < f32(0.5), u, v) * (f32(2 * np.pi) / spacing))
        fade = np.clip(spacing * inv_fp_min * f32(0.125) - f32(0.5), f32(0.0), f32(1.0))
        crop = np.where(h2 < f32(0.8), f32(0.13), f32(0.0))  # 20 % meadows without rows
        field = f32(0.22) + f32(0.32) * h1 + crop * fade * rows + f32(0.05) * noise
        grass = f32(0.30) + f32(0.16) * noise
        # open-road asphalt is smooth: a third of the street's grain, few repairs
        road = f32(0.34) + f32(0.3) * (albedo - f32(0.36)) + f32(0.3) * street
        open_delta = (
            on_road * (road - albedo)
            + verge * (grass - albedo)
            + in_field * (field - albedo)
            + line * (f32(0.85) - albedo - on_road * (road - albedo))
        )
        if w.open_map is None:
            return open_delta
        op = cv2.remap(w.open_map, gx, gz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)
        return street + op * (open_delta - street)
