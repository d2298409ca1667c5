"""Synthetic stereo sequences: a procedural textured street world, ray-cast along any path.

:class:`SyntheticSequence` reads like a KITTI folder (frames, ``camera``, ``gt_poses`` rebased to
the identity, ``timestamps``) plus ``depth(i)``, the left camera's exact z-depth (0 where no
surface was hit). The world is built once along the whole path; frames render lazily, and a seed
gives bit-identical images. How the world is made: docs/datasets.md, "How the world is rendered".
"""

from __future__ import annotations

import concurrent.futures as cf
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoCamera, kitti00_camera
from ..errors import SnapsGraphError
from ..io_utils import atomic_output, atomic_write_bytes, parse_frame_range
from ..trajectory_io import read_kitti_poses, read_times, write_kitti_poses, write_times
from ..types import SequenceBase, StereoFrame
from ._shade import Renderer, sun_direction
from ._world import SCENES, World, WorldConfig

__all__ = [
    "SCENES",
    "SyntheticSequence",
    "RenderedFrame",
    "WorldConfig",
    "builtin_loop_trajectory",
    "load_trajectory",
    "render_to_folder",
]

LOOP_STEP_M = 1.0  # built-in loop: metres per frame (KITTI drives ~1 m per frame at 10 Hz)
LOOP_REDRIVE_FRAMES = 50  # built-in loop: the last frames re-drive the start
LANE_CHANGE_FRAMES = 30  # built-in loop with a lane offset: the lane change before the re-drive
FRAME_PERIOD_S = 0.1  # timestamps when none are given (KITTI's 10 Hz)
PNG_COMPRESSION = 1  # fast; the images are noise-rich so higher levels gain little
DEPTH_PNG_SCALE = 1000.0  # depth_0/*.png: uint16 millimetres


@dataclass
class RenderedFrame:
    """One rendered stereo pair with the left camera's exact depth and stage timings."""

    left: np.ndarray  # uint8 (H, W)
    right: np.ndarray  # uint8 (H, W)
    depth: np.ndarray  # float32 (H, W) z-depth of the left camera, m; 0 = no hit (sky); (0, 0) if not asked
    timings_ms: dict[str, float] = field(default_factory=dict)  # "cast", "shade"


class SyntheticSequence(SequenceBase):
    """A stereo sequence rendered from a procedural world along ``poses`` (T_world_cam, KITTI axes)."""

    def __init__(
        self,
        poses: np.ndarray,
        camera: StereoCamera | None = None,
        width: int = 1241,
        height: int = 376,
        seed: int = 0,
        noise_std: float = 0.0,
        exposure_change: float = 0.0,
        times: np.ndarray | None = None,
        baseline_m: float | None = None,
        world_config: WorldConfig | None = None,
        rectification_error_px: float = 0.0,
    ):
        """``camera`` defaults to KITTI 00's P0/P1 scaled to ``width`` x ``height``; a given camera keeps
        its own size when it has one. ``baseline_m`` overrides the baseline. ``noise_std`` (grey
        levels), ``exposure_change`` and ``rectification_error_px`` (px) are the sensor options of
        ``snaps-graph synth`` (``--noise``, ``--exposure``, ``--rectification-error``), off at 0.
        """
        poses = _check_poses(poses)
        if camera is None:
            if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))) or width < 8 or height < 8:
                raise SnapsGraphError(f"synthetic: image size {width}x{height} is invalid (need whole numbers >= 8)")
            camera = kitti00_camera(int(width), int(height))
        elif not camera.width or not camera.height:
            camera = camera.with_size(int(width), int(height))
        if baseline_m is not None:
            if not np.isfinite(baseline_m) or baseline_m <= 0:
                raise SnapsGraphError(f"synthetic: baseline {baseline_m} m must be positive")
            camera = StereoCamera(camera.fx, camera.fy, camera.cx, camera.cy, float(baseline_m), camera.width, camera.height)
        if not np.isfinite(noise_std) or noise_std < 0:
            raise SnapsGraphError(f"synthetic: noise_std {noise_std} must be >= 0 (grey levels)")
        if not np.isfinite(exposure_change) or not 0 <= exposure_change < 1:
            raise SnapsGraphError(f"synthetic: exposure_change {exposure_change} must be in [0, 1)")
        if times is None:
            times = np.arange(len(poses)) * FRAME_PERIOD_S
        times = np.asarray(times, dtype=float).reshape(-1)
        if len(times) != len(poses):
            raise SnapsGraphError(f"synthetic: {len(times)} timestamps for {len(poses)} poses")

        self.camera = camera
        self.seed = int(seed)
        self.noise_std = float(noise_std)
        self.exposure_change = float(exposure_change)
        if not np.isfinite(rectification_error_px) or abs(rectification_error_px) > 5.0:
            raise SnapsGraphError(f"synthetic: rectification error {rectification_error_px} px must be within +-5 px")
        self.rectification_error_px = float(rectification_error_px)
        # The right camera turned about its y axis by -error/fx: every disparity reads `error`
        # pixels smaller than calib.txt implies (a residual of the rig's rectification).
        a = -self.rectification_error_px / camera.fx
        self._right_turn = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
        self._origin = np.array(poses[0], float)
        self._poses = np.linalg.inv(poses[0]) @ poses  # rebased: frame 0 is the identity
        self._times = times
        self.world = World(self._poses[:, :3, 3], self._poses[:, :3, 1], seed=self.seed, config=world_config, times=times)
        self._renderer = Renderer(self.world, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, self.seed)
        self._exposure = _exposure_curve(len(poses), self.seed, self.exposure_change)

    # ---- dataset protocol ----
    def __len__(self) -> int:
        return len(self._poses)

    @property
    def gt_poses(self) -> np.ndarray:
        return self._poses.copy()

    @property
    def gt_origin(self) -> np.ndarray:
        return self._origin.copy()

    @property
    def timestamps(self) -> np.ndarray:
        return self._times.copy()

    @property
    def indices(self) -> np.ndarray:
        return np.arange(len(self))

    def __getitem__(self, i: int) -> StereoFrame:
        i = self._index(i)
        f = self.render(i, with_depth=False)
        return StereoFrame(i, float(self._times[i]), f.left, f.right)

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self[i]

    def depth(self, i: int) -> np.ndarray:
        """Exact z-depth (m) of the left camera at frame ``i``, float32 (H, W); 0 = no hit (sky)."""
        i = self._index(i)
        T = self._poses[i]
        return self._renderer.depth(self._renderer.cast(T[:3, :3], T[:3, 3], self._layer(i)))

    def _layer(self, i: int):
        """The traffic of frame ``i`` (None without traffic or when no car is present)."""
        return self.world.traffic.layer(i) if self.world.traffic is not None else None

    def sun(self, i: int) -> np.ndarray | None:
        """Unit vector towards the sun at frame ``i`` with ``lighting`` (world axes), else None."""
        if not self.world.config.lighting:
            return None
        return sun_direction(self.world.config, float(self._times[i] - self._times[0]))

    def write_world_mesh(self, path: str | Path) -> None:
        """Write the static world (ground, buildings, trees, posts, hills; no traffic) as a
        triangle mesh in the frame of ``gt_poses`` (= poses.txt): PLY, or any format open3d writes."""
        import open3d as o3d

        path = Path(path)
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.world.vertices.astype(np.float64)),
            o3d.utility.Vector3iVector(self.world.triangles.astype(np.int32)),
        )
        try:
            with atomic_output(path, suffix=path.suffix or ".ply") as tmp:
                if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False):
                    raise OSError("open3d could not write it")
        except OSError as exc:
            raise SnapsGraphError(f"{path}: could not write the world mesh ({exc})") from None

    # ---- rendering ----
    def render(self, i: int, with_depth: bool = True) -> RenderedFrame:
        """Render frame ``i``: both images (uint8) and, cheaply, the left depth (from the same cast)."""
        i = self._index(i)
        T = self._poses[i]
        R, c = T[:3, :3], T[:3, 3]
        timings = {"cast": 0.0, "shade": 0.0}
        images = []
        depth = None
        gain, offset = self._exposure[i]
        t0 = time.perf_counter()
        layer, sun = self._layer(i), self.sun(i)
        timings["cast"] += (time.perf_counter() - t0) * 1e3
        R_right = R @ self._right_turn if self.rectification_error_px else R
        for side, (Rs, origin) in enumerate(((R, c), (R_right, c + R[:, 0] * self.camera.baseline_m))):
            t0 = time.perf_counter()
            hit = self._renderer.cast(Rs, origin, layer, sun)
            t1 = time.perf_counter()
            grey = self._renderer.shade(hit)
            if gain != 1.0 or offset != 0.0:
                grey = grey * np.float32(gain) + np.float32(offset)
            if self.noise_std > 0:
                rng = np.random.default_rng([self.seed, i, side, 0xA015E])
                grey = grey + rng.standard_normal(grey.shape, dtype=np.float32) * np.float32(self.noise_std)
            images.append(np.clip(np.rint(grey), 0, 255).astype(np.uint8))
            if side == 0 and with_depth:
                depth = self._renderer.depth(hit)
            t2 = time.perf_counter()
            timings["cast"] += (t1 - t0) * 1e3
            timings["shade"] += (t2 - t1) * 1e3
        if depth is None:
            depth = np.zeros((0, 0), np.float32)
        return RenderedFrame(images[0], images[1], depth, timings)

    def _index(self, i: int) -> int:
        n = len(self)
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(i)
        return int(i)


def _check_poses(poses) -> np.ndarray:
    try:
        poses = np.asarray(poses, dtype=float)
    except (TypeError, ValueError):
        raise SnapsGraphError("synthetic: poses must be an (N, 4, 4) array of numbers") from None
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise SnapsGraphError(f"synthetic: poses must have shape (N, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        first = int(np.argmax(~np.isfinite(poses).reshape(len(poses), -1).all(1)))
        raise SnapsGraphError(f"synthetic: pose {first} is not finite")
    R = poses[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((err > 1e-3) | (det < 0))
    if len(bad):
        raise SnapsGraphError(f"synthetic: pose {bad[0]} has no proper rotation (R R^T differs from I by {err[bad[0]]:.3g})")
    return poses


def _exposure_curve(n: int, seed: int, amount: float) -> np.ndarray:
    """(gain, offset) per frame: smooth random drifts (three sinusoids, periods 60-400 frames)."""
    out = np.zeros((n, 2))
    out[:, 0] = 1.0
    if amount <= 0:
        return out
    rng = np.random.default_rng([seed, 0xE7905])
    i = np.arange(n)
    for col, scale in ((0, amount), (1, 30.0 * amount)):
        periods = rng.uniform(60.0, 400.0, 3)
        phases = rng.uniform(0, 2 * np.pi, 3)
        amps = rng.uniform(0.5, 1.0, 3)
        wave = (amps[:, None] * np.sin(2 * np.pi * i[None] / periods[:, None] + phases[:, None])).sum(0) / amps.sum()
        out[:, col] += scale * wave
    return out


# ---------------------------------------------------------------- trajectories
def builtin_loop_trajectory(n_frames: int = 300, lane_offset_m: float = 0.0) -> np.ndarray:
    """A closed, curvy loop at ``LOOP_STEP_M`` per frame whose last frames re-drive the start.

    The loop's length is ``n_frames - r`` metres with ``r = min(50, n_frames // 6)`` re-driven
    frames: frame ``k + (n_frames - r)`` stands exactly where frame ``k`` stood with the same
    heading (so for 300 frames, frames 250-299 revisit frames 0-49 at a frame distance of 250).
    The shape is a smooth closed curve with bends of different radii; the road climbs and
    falls by about 2 m (grade under 5 %) and the camera pitches with it. Frame 0 is the identity.

    ``lane_offset_m`` moves the second pass into another lane: a lane change over the
    ``LANE_CHANGE_FRAMES`` before the re-drive, then the re-driven frames stand that far to
    the left (negative: right) of the first pass, heading along the road.
    """
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 60:
        raise SnapsGraphError(f"loop: need at least 60 frames, got {n_frames}")
    if not np.isfinite(lane_offset_m) or abs(lane_offset_m) > 10.0:
        raise SnapsGraphError(f"loop: lane offset {lane_offset_m} m must be within +-10 m")
    redrive = min(LOOP_REDRIVE_FRAMES, n_frames // 6)
    perimeter = (n_frames - redrive) * LOOP_STEP_M
    # A closed curve r(theta) with a few harmonics, sampled finely, then scaled to the perimeter.
    theta = np.linspace(0.0, 2 * np.pi, 4001)
    r = 1.0 + 0.18 * np.sin(2 * theta + 0.4) + 0.08 * np.cos(3 * theta + 1.1) + 0.04 * np.sin(5 * theta)
    x, z = r * np.cos(theta), r * np.sin(theta)
    seg = np.hypot(np.diff(x), np.diff(z))
    x, z = x * perimeter / seg.sum(), z * perimeter / seg.sum()
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(z)))])
    arc = np.arange(n_frames) * LOOP_STEP_M
    s = arc % perimeter
    # Lane offset per unit of driven arc: 0 on the first pass, a smooth step into the other lane.
    change_end = (n_frames - redrive) * LOOP_STEP_M
    change_len = LANE_CHANGE_FRAMES * LOOP_STEP_M

    def lane(a: np.ndarray) -> np.ndarray:
        u = np.clip((a - (change_end - change_len)) / change_len, 0.0, 1.0)
        return lane_offset_m * u * u * (3.0 - 2.0 * u)

    def place(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (x, z) at driven arc ``a``: the loop's centre line moved sideways by the lane."""
        sa = a % perimeter
        cx, cz = np.interp(sa, cum, x), np.interp(sa, cum, z)
        dx = np.interp((sa + 0.25) % perimeter, cum, x) - np.interp((sa - 0.25) % perimeter, cum, x)
        dz = np.interp((sa + 0.25) % perimeter, cum, z) - np.interp((sa - 0.25) % perimeter, cum, z)
        norm = np.hypot(dx, dz)
        d = lane(a)  # left of heading (dx, dz) in x-right / z-forward axes is (-dz, dx)
        return cx - d * dz / norm, cz + d * dx / norm

    px, pz = place(arc)
    # Heading by a centred difference along the driven arc (the lane change turns it too).
    ds = 0.25
    (xa, za), (xb, zb) = place(arc + ds), place(arc - ds)
    yaw = np.arctan2(xa - xb, za - zb)
    # Height (up) and grade: a periodic profile so the loop closes in height too.
    w = 2 * np.pi * s / perimeter
    up = 1.2 * np.sin(w) + 0.6 * np.sin(2 * w + 0.7)
    grade = (1.2 * np.cos(w) + 1.2 * np.cos(2 * w + 0.7)) * 2 * np.pi / perimeter
    pitch = np.arctan(grade)
    poses = np.zeros((n_frames, 4, 4))
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    # R = Ry(yaw) @ Rx(pitch): forward (sin yaw cos p, -sin p, cos yaw cos p), looks up on a climb.
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 0, 2] = cy, sy * sp, sy * cp
    poses[:, 1, 0], poses[:, 1, 1], poses[:, 1, 2] = 0.0, cp, -sp
    poses[:, 2, 0], poses[:, 2, 1], poses[:, 2, 2] = -sy, cy * sp, cy * cp
    poses[:, 0, 3], poses[:, 1, 3], poses[:, 2, 3] = px, -up, pz
    poses[:, 3, 3] = 1.0
    return np.linalg.inv(poses[0]) @ poses


def load_trajectory(spec: str, frames: str | None = None, times: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) and timestamps (N,) from ``spec``: a KITTI pose file, ``loop`` or ``loop:N``.

    ``loop`` is the built-in loop of 300 frames (``loop:N`` for N frames). Timestamps come from
    the ``times`` file when given (one per pose of the whole path), else, for a pose file, from
    ``<stem>_times.txt`` beside it (the kitti_gt layout), ``times.txt`` beside it (what
    ``render_to_folder`` writes) or ``../sequences/<stem>/times.txt`` (the official KITTI
    layout); otherwise 10 Hz. ``frames`` (``A:B``) selects part of the path. Poses are returned
    as read (the sequence rebases them).
    """
    spec = str(spec)
    given_times = None
    if times is not None:
        given_times = read_times(times)
    if spec == "loop" or spec.startswith("loop:"):
        n_text = spec.partition(":")[2] or "300"
        try:
            n = int(n_text)
        except ValueError:
            raise SnapsGraphError(f"trajectory '{spec}': expected loop or loop:N with N a whole number") from None
        poses = builtin_loop_trajectory(n)
        stamps = np.arange(len(poses)) * FRAME_PERIOD_S
    else:
        path = Path(spec)
        if not path.is_file():
            raise SnapsGraphError(f"{path}: trajectory file not found (give a KITTI pose file or 'loop')")
        poses = read_kitti_poses(path)
        stamps = None
        for cand in (
            path.with_name(f"{path.stem}_times.txt"),
            path.with_name("times.txt"),
            path.parent.parent / "sequences" / path.stem / "times.txt",
        ):
            if given_times is None and cand.is_file():
                stamps = read_times(cand)
                if len(stamps) != len(poses):
                    raise SnapsGraphError(f"{cand}: {len(stamps)} timestamps for {len(poses)} poses in {path}")
                break
        if stamps is None:
            stamps = np.arange(len(poses)) * FRAME_PERIOD_S
    if given_times is not None:
        if len(given_times) != len(poses):
            raise SnapsGraphError(f"{times}: {len(given_times)} timestamps for {len(poses)} poses of '{spec}'")
        stamps = given_times
    assert stamps is not None
    rng = parse_frame_range(frames, len(poses))
    if rng is not None:
        start, stop = rng
        poses, stamps = poses[start:stop], stamps[start:stop]
    return poses, stamps


# ---------------------------------------------------------------- writing
def render_to_folder(
    seq: SyntheticSequence,
    out_dir: str | Path,
    progress: Callable[[], object] | None = None,
    write_depth: bool = False,
    workers: int = 2,
    overwrite: bool = False,
) -> dict[str, float]:
    """Write ``seq`` in the KITTI layout that ``KittiSequence`` reads; return stage timings.

    ``image_0/``, ``image_1/`` (8-bit grey PNG), ``calib.txt``, ``times.txt``, ``poses.txt`` (the
    path rebased to the identity) and, with ``write_depth``, ``depth_0/`` (uint16 mm, 0 = sky or
    beyond 65.535 m). ``workers`` threads render and encode; ``progress()`` is called once per frame,
    in order, from the calling thread. A folder holding images is refused unless ``overwrite``.
    Returns total ms per stage over threads (``cast``, ``shade``, ``write``), ``wall_s``, ``frames``.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SnapsGraphError(f"{out}: exists and is not a folder")
    dirs = [out / "image_0", out / "image_1"] + ([out / "depth_0"] if write_depth else [])
    for d in dirs + [out / "depth_0"]:
        old = sorted(d.glob("*.png")) if d.is_dir() else []
        if old and not overwrite:
            raise SnapsGraphError(f"{d}: already holds {len(old)} images; choose an empty folder")
        for p in old:
            p.unlink()
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
    seq.camera.write_calib(out / "calib.txt")
    write_times(out / "times.txt", seq.timestamps)
    write_kitti_poses(out / "poses.txt", seq.gt_poses)

    params = [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]

    def job(i: int) -> dict[str, float]:
        f = seq.render(i, with_depth=write_depth)
        t0 = time.perf_counter()
        name = f"{i:06d}.png"
        images = {"image_0": f.left, "image_1": f.right}
        if write_depth:
            mm = np.rint(f.depth * DEPTH_PNG_SCALE)
            mm[(mm > 65535) | (mm < 0)] = 0
            images["depth_0"] = mm.astype(np.uint16)
        for folder, img in images.items():  # encoded in memory, written atomically
            ok, png = cv2.imencode(".png", img, params)
            try:
                if not ok:
                    raise OSError("PNG encoding failed")
                atomic_write_bytes(out / folder / name, png.tobytes())
            except OSError as exc:
                raise SnapsGraphError(f"{out}: could not write frame {name} ({exc})") from None
        f.timings_ms["write"] = (time.perf_counter() - t0) * 1e3
        return f.timings_ms

    totals = {"cast": 0.0, "shade": 0.0, "write": 0.0}
    t_start = time.perf_counter()
    n = len(seq)
    workers = max(1, int(workers))
    with cf.ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque[cf.Future] = deque()
        nxt = 0
        for _ in range(n):
            while nxt < n and len(pending) < 2 * workers:  # bounded look-ahead: bounded memory
                pending.append(pool.submit(job, nxt))
                nxt += 1
            timings = pending.popleft().result()
            for k in totals:
                totals[k] += timings.get(k, 0.0)
            if progress is not None:
                progress()
    totals["wall_s"] = time.perf_counter() - t_start
    totals["frames"] = float(n)
    return totals
