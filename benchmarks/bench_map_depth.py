"""Map depth against the exact depth of the synthetic street world (KITTI 00 path, seed 0):
per variant of mapping.depth.map_depth, the share of true surface pixels kept (coverage), the
depth error by range bin (median, p90), the share of gross errors (|error| > 1 m, or depth where
the truth is sky) and the time per keyframe. This is what MapConfig's depth defaults and
max_range_m were chosen from. Usage: python benchmarks/bench_map_depth.py [--frames 0:1000:100]"""

import argparse
import copy
import time
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.frontend.depth import dense_depth
from snaps_graph.mapping import depth as depth_mod
from snaps_graph.mapping.depth import map_depth
from snaps_graph.synth import SyntheticSequence, load_trajectory

ap = argparse.ArgumentParser()
ap.add_argument("--path", default=str(Path(__file__).resolve().parents[1].parent / "shared/data/kitti_gt/00.txt"))
ap.add_argument("--frames", default="0:1000:100", help="A:B:STEP of the frames to test")
ap.add_argument("--variants", default="all", help="comma-separated substrings of variant names")
ap.add_argument("--range", type=float, default=20.0, help="gross errors are also counted among depths up to this")
a = ap.parse_args()

poses, times = load_trajectory(a.path)
t0 = time.perf_counter()
seq = SyntheticSequence(poses, seed=0, times=times)  # the world of the street00 recipes (docs/datasets.md)
print(f"world built in {time.perf_counter() - t0:.1f} s")
A, B, S = (int(x) for x in a.frames.split(":"))
frames = [seq.render(i) for i in range(A, B, S)]

base = Config()
# The variants' keys: the map matcher's constants in frontend/depth.py (depth_scale is [map]'s).
MAP_CONSTANTS = {
    "depth_method": "MAP_DEPTH_METHOD",
    "depth_block_size": "MAP_BLOCK_SIZE",
    "depth_uniqueness": "MAP_UNIQUENESS",
    "depth_lr_check_px": "MAP_LR_CHECK_PX",
    "depth_min_confidence": "MAP_MIN_CONFIDENCE",
    "depth_edge_ratio": "MAP_EDGE_RATIO",
    "depth_speckle_px": "MAP_SPECKLE_PX",
}
DEFAULTS = {name: getattr(depth_mod, name) for name in MAP_CONSTANTS.values()}
BM = dict(depth_method="bm", depth_block_size=7)
SG = dict(depth_method="sgbm", depth_block_size=5)
VARIANTS = {
    "paper bm_wls (dense_depth)": None,
    "bm raw (no checks)": dict(BM, depth_lr_check_px=0, depth_edge_ratio=0, depth_speckle_px=0, depth_uniqueness=0),
    "bm + lr": dict(BM, depth_edge_ratio=0, depth_speckle_px=0),
    "bm + lr + edge": dict(BM, depth_speckle_px=0),
    "bm + lr + edge + speckle": dict(BM),
    "bm + all + wls conf 128": dict(BM, depth_min_confidence=128.0),
    "bm + all, full size": dict(BM, depth_scale=1.0, depth_block_size=15, depth_speckle_px=200),
    "sgbm + lr + edge + speckle (default)": dict(SG),
    "sgbm + all + wls conf 64": dict(SG, depth_min_confidence=64.0),
    "sgbm + all + wls conf 128": dict(SG, depth_min_confidence=128.0),
    "sgbm block 7": dict(SG, depth_block_size=7),
    "sgbm uniqueness 25": dict(SG, depth_uniqueness=25),
    "sgbm speckle 200": dict(SG, depth_speckle_px=200),
    "sgbm edge 0.05": dict(SG, depth_edge_ratio=0.05),
}
if a.variants != "all":
    VARIANTS = {k: v for k, v in VARIANTS.items() if any(s in k for s in a.variants.split(","))}
bins = [(0, 10), (10, 20), (20, 30), (30, 40), (40, 80)]
for name, over in VARIANTS.items():
    cfg = copy.deepcopy(base)
    cfg.map.max_range_m = 80.0
    for name, v in DEFAULTS.items():
        setattr(depth_mod, name, v)
    for k, v in (over or {}).items():
        if k == "depth_scale":
            cfg.map.depth_scale = v
        else:
            setattr(depth_mod, MAP_CONSTANTS[k], v)
    errs, zt_all, z_all, kept, truth, sky, sky_r, ms = [], [], [], 0, 0, 0, 0, []
    for f in frames:
        t = time.perf_counter()
        if over is None:
            z = dense_depth(f.left, f.right, seq.camera, cfg.frontend)
            scale = 1
        else:
            z = map_depth(f.left, f.right, seq.camera, cfg.frontend, cfg.map)
            scale = round(f.left.shape[1] / z.shape[1])
        ms.append((time.perf_counter() - t) * 1e3)
        h, w = z.shape
        # the true depths of the full-size pixels each working pixel covers
        blocks = f.depth[: h * scale, : w * scale].reshape(h, scale, w, scale).transpose(0, 2, 1, 3).reshape(h, w, -1)
        anysky = (blocks <= 0).any(-1)
        zt = np.median(blocks, -1)
        est = z > 0
        truth += int(((zt > 0) & ~anysky & (zt <= 80)).sum())
        kept += int((est & (zt > 0) & ~anysky & (zt <= 80)).sum())
        sky += int((est & (blocks <= 0).all(-1)).sum())
        sky_r += int((est & (z <= a.range) & (blocks <= 0).all(-1)).sum())
        m = est & ~(blocks <= 0).all(-1)
        e = np.min(np.abs(blocks[m] - z[m][:, None]), -1)
        errs.append(e)
        zt_all.append(zt[m])
        z_all.append(z[m])
    e, zt, ze = np.concatenate(errs), np.concatenate(zt_all), np.concatenate(z_all)
    inr = ze <= a.range
    gross_r = 100 * (np.sum(e[inr] > 1) + sky_r) / max(inr.sum() + sky_r, 1)
    n_est = len(e) + sky
    row = [
        f"{name:<36} {np.median(ms):6.1f} ms  coverage {100 * kept / truth:5.1f}%  gross {100 * (np.sum(e > 1) + sky) / max(n_est, 1):5.2f}% (sky {100 * sky / max(n_est, 1):.2f}%); depth <= {a.range:g} m: gross {gross_r:.2f}%, p90 {np.percentile(e[inr], 90):.3f} m"
    ]
    for lo, hi in bins:
        sel = (zt > lo) & (zt <= hi)
        if sel.sum() > 50:
            row.append(f"{lo}-{hi} m: p50 {np.median(e[sel]):.3f} p90 {np.percentile(e[sel], 90):.3f} (n {sel.sum()})")
    print(row[0])
    print("    " + "; ".join(row[1:]))
