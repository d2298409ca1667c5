"""Benchmark the point-cloud map on KITTI 06 (frames 0-50): bytes stored per keyframe,
projected memory for KITTI 00 (4541 frames, a keyframe every 5), build / re-pose / PLY times,
and a top-down PNG. Depth comes from the package's dense_depth (BM + WLS) or OpenCV SGBM
(--depth sgbm); only the map is timed. Usage: python bench_cloud_map.py [--frames N] [--out DIR]"""
import argparse
import resource
import time
from pathlib import Path

import cv2
import numpy as np

from snaps_graph.config import MapConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.mapping import CloudMap

ap = argparse.ArgumentParser()
ap.add_argument("--seq", default="../shared/data/kitti/sequences/06")
ap.add_argument("--frames", type=int, default=51)
ap.add_argument("--out", default="results")
ap.add_argument("--depth", choices=["package", "sgbm"], default="package",
                help="package: snaps_graph.frontend.depth.dense_depth (paper: BM + WLS); sgbm: OpenCV SGBM here")
ap.add_argument("--gt00", default="../shared/data/kitti_gt/00.txt", help="stress test: KITTI 00 path, '' to skip")
a = ap.parse_args()

seq = KittiSequence(a.seq)
cam = seq.camera
cfg = MapConfig()
m = CloudMap(cam, cfg)
sgbm = cv2.StereoSGBM_create(0, 128, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10,
                             speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
n = min(a.frames, len(seq))
t_add, raw, kept, cache = 0.0, [], [], []
import open3d  # noqa: F401  (import cost kept out of the per-keyframe time)

for i in range(n):
    if not m.should_add(i):
        continue
    f = seq[i]
    if a.depth == "package":
        from snaps_graph.config import FrontendConfig
        from snaps_graph.frontend.depth import dense_depth
        depth = dense_depth(f.left, f.right, cam, FrontendConfig())
    else:
        depth = cam.depth_from_disparity(sgbm.compute(f.left, f.right).astype(np.float32) / 16.0)
    s = cfg.pixel_step
    z = depth[::s, ::s]
    raw.append(int(((z > 0) & (z <= cfg.max_range_m)).sum()))
    cache.append((depth, f.left))
    t0 = time.perf_counter(); kept.append(m.add_keyframe(i, depth, f.left)); t_add += time.perf_counter() - t0
gt = seq.gt_poses[:n]
per_kf = m.memory_bytes() / len(m)
print(f"depth from {a.depth}; image {cam.width}x{cam.height}, pixel_step {cfg.pixel_step}, max_range {cfg.max_range_m} m, "
      f"keyframe voxel {cfg.keyframe_voxel_size_m} m, map voxel {cfg.voxel_size_m} m")
print(f"keyframes {len(m)}: valid grid points/kf {np.mean(raw):.0f}, kept after keyframe voxel {np.mean(kept):.0f} "
      f"({100*np.mean(kept)/np.mean(raw):.0f}%)")
print(f"stored {per_kf/1e3:.1f} kB/keyframe (13 B/point); add_keyframe {1e3*t_add/len(m):.1f} ms/keyframe")
n00 = len(range(0, 4541, 5))
print(f"projected KITTI 00 ({n00} keyframes): stored {n00*per_kf/1e6:.0f} MB (build peak: see the stress line)")
t0 = time.perf_counter(); pcd = m.build(gt); t1 = time.perf_counter()
shifted = gt.copy(); shifted[:, 0, 3] += 10.0
pcd2 = m.build(shifted); t2 = time.perf_counter()
c1, c2 = np.asarray(pcd.points).mean(0), np.asarray(pcd2.points).mean(0)
print(f"build {1e3*(t1-t0):.0f} ms -> {len(pcd.points)} points; re-pose build {1e3*(t2-t1):.0f} ms, "
      f"centroid shift {c2-c1} (expect [10 0 0])")
out = Path(a.out); out.mkdir(parents=True, exist_ok=True)
t0 = time.perf_counter(); npts = m.write_ply(out / "cloud_map_kitti06.ply", gt); t1 = time.perf_counter()
m.render_topdown_png(out / "cloud_map_kitti06_topdown.png", gt, {"ground truth": gt}); t2 = time.perf_counter()  # builds again
m.render_topdown_png(out / "cloud_map_kitti06_topdown_intensity.png", gt, {"ground truth": gt}, colour_by="intensity")
print(f"write_ply {1e3*(t1-t0):.0f} ms ({npts} points, {(out/'cloud_map_kitti06.ply').stat().st_size/1e6:.1f} MB); "
      f"render_topdown_png {1e3*(t2-t1):.0f} ms")
print(f"peak RSS (KITTI 06 part) {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1e3:.0f} MB")

if a.gt00 and Path(a.gt00).is_file():
    from snaps_graph.trajectory_io import read_kitti_poses
    gt00 = np.asarray(read_kitti_poses(a.gt00))
    m00 = CloudMap(cam, cfg)
    t0 = time.perf_counter()
    for j, k in enumerate(range(0, len(gt00), cfg.keyframe_every)):
        d, img = cache[j % len(cache)]  # KITTI 06 depth maps recycled along the KITTI 00 path
        m00.add_keyframe(k, d, img)
    t1 = time.perf_counter(); pcd00 = m00.build(gt00); t2 = time.perf_counter()
    m00.render_topdown_png(out / "cloud_map_kitti00_stress_topdown.png", gt00, {"KITTI 00 ground truth": gt00}, cloud=pcd00)
    t3 = time.perf_counter()
    print(f"KITTI 00 stress ({len(m00)} keyframes, 06 depth recycled along the 00 path): stored "
          f"{m00.memory_bytes()/1e6:.0f} MB ({m00.num_stored_points()} points), add {t1-t0:.1f} s, "
          f"build {t2-t1:.1f} s -> {len(pcd00.points)} points, topdown (prebuilt cloud) {t3-t2:.1f} s, "
          f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1e3:.0f} MB")
