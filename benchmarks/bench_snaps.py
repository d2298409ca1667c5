"""Latency benchmark of the SNAPS loop closer on KITTI 00's ground-truth path (4541 poses, 3.7 km).

VO is simulated as the true relative poses with a systematic drift (a yaw bias per frame and a
translation scale error), so the heuristic trajectory drifts like real stereo VO and SNAPS has to
find revisits by its own (drifted, corrected) positions. Thumbnails have the real 1/6-scale size
(207x63, fed at ``thumbnail_scale = 1``): a deterministic place texture keyed by the *true*
position's coarse cell and heading quadrant (smoothed random noise) plus per-frame noise, so
revisits look alike and different places do not. Everything else is LoopConfig's defaults
and the drift policy (``--search drift``, the drift-aware gate; ``--search radius`` = the paper's fixed radius).

Prints the median / p95 of ``SnapsStep.t_ms`` (detection + correction) for frames with no
candidate, frames that computed similarities (with and without a loop) and loop frames; the number
of loops; the cost of one UIQI comparison (cached window sums vs from scratch); and, for context,
the mean deviation from ground truth of the drifted VO chain and of the SNAPS heuristic.

    python benchmarks/bench_snaps.py                 # full sequence
    python benchmarks/bench_snaps.py --frames 1500   # reduced size
    python benchmarks/bench_snaps.py --search radius # the paper's fixed radius
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from _loop_research import CountingThumbnails, policy

from snaps_graph.config import LoopConfig
from snaps_graph.geometry import inv, yaw_deg
from snaps_graph.loop import SnapsLoopCloser, similarity_q, uiqi, window_stats
from snaps_graph.trajectory_io import read_kitti_poses

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_GT = ROOT.parent / "shared" / "data" / "kitti_gt" / "00.txt"
THUMB_HW = (63, 207)  # 1241x376 at 1/6


def yaw_rotation(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


class PlaceTextures:
    """Deterministic smoothed-noise texture per (cell x, cell z, heading quadrant) of the true pose."""

    def __init__(self, cell_m: float, seed: int):
        self.cell_m, self.seed, self._cache = cell_m, seed, {}

    def __call__(self, T_true: np.ndarray) -> np.ndarray:
        p = T_true[:3, 3]
        quadrant = int(np.floor(((yaw_deg(T_true) + 45.0) % 360.0) / 90.0))
        key = (int(np.floor(p[0] / self.cell_m)), int(np.floor(p[2] / self.cell_m)), quadrant)
        tex = self._cache.get(key)
        if tex is None:
            rng = np.random.default_rng([self.seed, key[0] & 0xFFFFFFFF, key[1] & 0xFFFFFFFF, key[2]])
            raw = rng.uniform(0.0, 255.0, THUMB_HW).astype(np.float32)
            tex = cv2.GaussianBlur(raw, (0, 0), 1.5)
            tex = (tex - tex.mean()) * (60.0 / tex.std()) + 120.0  # grey level ~120, contrast ~60
            self._cache[key] = tex
        return tex


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def row(name: str, values: list[float]) -> str:
    if not values:
        return f"  {name:<34s} n={0:5d}"
    return f"  {name:<34s} n={len(values):5d}  median {np.median(values) * 1e3:9.1f} us  p95 {pct(values, 95) * 1e3:9.1f} us"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, default=DEFAULT_GT, help="KITTI ground-truth path (default: KITTI 00)")
    ap.add_argument("--frames", type=int, default=0, help="use only the first N poses (0 = all)")
    ap.add_argument("--yaw-bias-deg", type=float, default=0.002, help="VO yaw bias per frame, degrees")
    ap.add_argument("--scale-error", type=float, default=0.005, help="VO translation scale error (0.01 = +1%%)")
    ap.add_argument("--noise", type=float, default=12.0, help="per-frame thumbnail noise, grey levels (std)")
    ap.add_argument("--cell-m", type=float, default=6.0, help="place texture cell size, metres")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--search",
        choices=["drift", "radius"],
        default="drift",
        help="the candidate gate: the drift policy's or the paper's radius",
    )
    args = ap.parse_args(argv)

    if not args.gt.is_file():
        print(f"ground truth not found: {args.gt}", file=sys.stderr)
        return 2
    gt = read_kitti_poses(args.gt)
    gt = np.linalg.inv(gt[0]) @ gt
    if args.frames:
        gt = gt[: args.frames]
    n = len(gt)

    cfg = LoopConfig(thumbnail_scale=1.0)  # the images below already have thumbnail size
    closer = SnapsLoopCloser(cfg, policy=policy("drift", search=args.search))
    closer.thumbs = thumbs = CountingThumbnails(cfg.window)
    similarities = 0
    textures = PlaceTextures(args.cell_m, args.seed)
    rng = np.random.default_rng(args.seed + 1)
    R_bias = yaw_rotation(args.yaw_bias_deg)

    vo = np.empty((n, 4, 4))
    vo[0] = np.eye(4)
    t_none, t_sim, t_loop = [], [], []
    wall0 = time.perf_counter()
    for k in range(n):
        if k == 0:
            T_rel = np.eye(4)
        else:
            T_rel = inv(gt[k - 1]) @ gt[k]
            T_rel[:3, :3] = R_bias @ T_rel[:3, :3]
            T_rel[:3, 3] *= 1.0 + args.scale_error
            vo[k] = vo[k - 1] @ T_rel
        img = textures(gt[k]) + rng.normal(0.0, args.noise, THUMB_HW).astype(np.float32)
        img = np.clip(img, 0, 255).astype(np.uint8)
        step = closer.step(k, T_rel, img)
        similarities += step.candidates
        if step.loop is not None:
            t_loop.append(step.t_ms)
        elif step.candidates:
            t_sim.append(step.t_ms)
        else:
            t_none.append(step.t_ms)
    wall = time.perf_counter() - wall0

    # One comparison in isolation: cached window sums (what SNAPS does) vs uiqi() from scratch.
    a, b = closer.thumbnail(0), closer.thumbnail(min(1, n - 1))
    sa, sb = window_stats(a, cfg.window), window_stats(b, cfg.window)
    reps = 300
    t0 = time.perf_counter()
    for _ in range(reps):
        similarity_q(sa, sb)
    t_fast = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    for _ in range(reps):
        uiqi(a, b, cfg.window)
    t_full = (time.perf_counter() - t0) / reps

    loops = closer.loops
    heur = closer.poses
    dev_vo = float(np.mean(np.linalg.norm(vo[:, :3, 3] - gt[:, :3, 3], axis=1)))
    dev_snaps = float(np.mean(np.linalg.norm(heur[:, :3, 3] - gt[:, :3, 3], axis=1)))
    cached, cache_bytes = thumbs.cache_size()
    cache_mb = cache_bytes / 2**20

    print(
        f"SNAPS latency on {args.gt.name}: {n} frames, thumbnails {THUMB_HW[1]}x{THUMB_HW[0]}, "
        f"yaw bias {args.yaw_bias_deg} deg/frame, scale error {args.scale_error:+.1%}, noise {args.noise}, search {args.search}"
    )
    print("t_ms per frame (detection + correction):")
    print(row("no candidate", t_none))
    print(row("similarities, no loop", t_sim))
    print(row("loop closed (incl. eq. 6)", t_loop))
    print(row("all frames computing similarities", t_sim + t_loop))
    print(
        f"loops closed: {len(loops)}   similarities computed: {similarities}   "
        f"window sums computed: {thumbs.computed}   stats cache: {cached} frames, {cache_mb:.0f} MB"
    )
    if loops:
        qs = np.array([e.q for e in loops])
        print(
            f"loop Q: min {qs.min():.3f} median {np.median(qs):.3f}   "
            f"|delta| median {np.median([np.linalg.norm(e.delta) for e in loops]):.2f} m   "
            f"candidates per loop frame median {np.median([e.candidates for e in loops]):.0f}"
        )
    print(f"one UIQI comparison: {t_fast * 1e6:.0f} us with cached window sums, {t_full * 1e6:.0f} us from scratch")
    print(f"mean deviation from ground truth: VO chain {dev_vo:.2f} m, SNAPS heuristic {dev_snaps:.2f} m")
    print(f"wall time {wall:.1f} s ({wall / n * 1e3:.2f} ms per frame incl. making the fake images)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
