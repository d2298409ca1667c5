"""TSDF fusion settings on the synthetic street world (KITTI 00 path, seed 0), under the TRUE
poses, so only depth and fusion are measured: for exact depth and for map_depth, and for each
setting, the map error and completeness against the world mesh, the fusion time per keyframe
and the grid size. Usage: python benchmarks/bench_map_fusion.py --world results/world00.ply
[--frames 0:200] [--settings ...]"""

import argparse
import copy
import time
from pathlib import Path

import cv2
import numpy as np

from snaps_graph.config import Config
from snaps_graph.mapping.accuracy import WorldSurface, map_accuracy
from snaps_graph.mapping.depth import map_depth
from snaps_graph.mapping.tsdf import FusedMap
from snaps_graph.synth import SyntheticSequence, load_trajectory

ap = argparse.ArgumentParser()
ap.add_argument("--path", default=str(Path(__file__).resolve().parents[1].parent / "shared/data/kitti_gt/00.txt"))
ap.add_argument("--world", required=True)
ap.add_argument("--frames", default="0:200")
ap.add_argument("--settings", default="")
ap.add_argument("--exact", action="store_true", help="also fuse the exact depth")
a = ap.parse_args()
poses, times = load_trajectory(a.path)
seq = SyntheticSequence(poses, seed=0, times=times)
A, B = (int(x) for x in a.frames.split(":"))
base = Config()
world = WorldSurface(a.world)
gt = seq.gt_poses
kfs = [k for k in range(A, B) if k % base.map.keyframe_every == 0]
t0 = time.perf_counter()
frames = {k: seq.render(k) for k in kfs}
print(f"rendered {len(kfs)} keyframes in {time.perf_counter() - t0:.0f} s")
depth_ms = []
est = {}
for k, f in frames.items():
    t = time.perf_counter()
    est[k] = map_depth(f.left, f.right, seq.camera, base.frontend, base.map)
    depth_ms.append(1e3 * (time.perf_counter() - t))
print(f"map_depth {np.median(depth_ms):.1f} ms/keyframe")
h, w = est[kfs[0]].shape
exact = {k: cv2.resize(f.depth, (w, h), interpolation=cv2.INTER_NEAREST) for k, f in frames.items()}
SETTINGS = {
    "default": {},
    "min weight 2": dict(tsdf_min_weight=2.0),
    "min component 100": dict(tsdf_min_component=100),
    "min component 500": dict(tsdf_min_component=500),
    "every 10": dict(keyframe_every=10),
    "every 10, voxel 0.1": dict(keyframe_every=10, tsdf_voxel_m=0.1),
    "trunc 4 voxels": dict(tsdf_trunc_voxels=4.0),
    "voxel 0.1": dict(tsdf_voxel_m=0.1),
    "voxel 0.2": dict(tsdf_voxel_m=0.2),
    "trunc 8 voxels": dict(tsdf_trunc_voxels=8.0),
}
if a.settings:
    SETTINGS = {k: v for k, v in SETTINGS.items() if any(s in k for s in a.settings.split(","))}
for src, depths in (("exact depth", exact), ("map_depth", est))[0 if a.exact else 1 :]:
    for name, over in SETTINGS.items():
        cfg = copy.deepcopy(base.map)
        for key, v in over.items():
            if key != "tsdf_voxel_m" and key.startswith("tsdf_"):
                continue  # the fusion's constants: set on the map below
            setattr(cfg, key, v)
        m = FusedMap(seq.camera, cfg)
        for key, v in over.items():
            if key != "tsdf_voxel_m" and key.startswith("tsdf_"):
                setattr(m, key.removeprefix("tsdf_"), v)  # trunc_voxels, min_weight, ... (mapping/tsdf.py)
        for k in kfs:
            if m.should_add(k):
                m.add_keyframe(k, depths[k], frames[k].left)
        s = m.fuse(gt)
        cam = seq.camera
        acc = map_accuracy(world, s.points, s.vertices, gt[kfs], cam.K, (cam.width, cam.height))
        p = acc["points"]
        print(
            f"{src:<12} {name:<20} fuse {1e3 * s.stats['fuse_s'] / len(m):5.1f} ms/kf (total {s.stats['fuse_s']:.1f} s), {s.stats['max_blocks']} blocks, "
            f"{s.stats['triangles']} triangles | points p50 {p['error_median_m']:.3f} p90 {p['error_p90_m']:.3f} m, "
            f"completeness {100 * p['completeness']:.1f}% (seen {100 * p['completeness_seen']:.1f}%) | seen share "
            f"{100 * acc['surface_seen_share']:.0f}%",
            flush=True,
        )
