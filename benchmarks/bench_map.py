"""Map figures of a results folder written by `snaps-graph run ... --map`:
accuracy per trajectory against the true world (when the run had --world-mesh), the share of
map points farther than 30 m from the path (radial streaks), map time as a share of the run, and
peak memory. With --write-world it first writes the exact world mesh of the synthetic street
rendering of a KITTI path (seed 0: the world of the street00 recipes in docs/datasets.md), for --world-mesh.

  python benchmarks/bench_map.py --write-world results/world00.ply
  python benchmarks/bench_map.py RUN_DIR [RUN_DIR ...]
  python benchmarks/bench_map.py --run SEQ OUT      # first `snaps-graph run SEQ --out OUT --refine batch --map`
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("runs", nargs="*")
ap.add_argument("--write-world", default="", help="write the synthetic world mesh here and exit")
ap.add_argument("--path", default=str(Path(__file__).resolve().parents[1].parent / "shared/data/kitti_gt/00.txt"))
ap.add_argument("--far-m", type=float, default=30.0)
ap.add_argument("--run", nargs=2, metavar=("SEQ", "OUT"), help="run SEQ with --map into OUT (replaced) first, then report it")
a = ap.parse_args()

if a.run:
    import subprocess
    import sys

    seq, out = a.run
    cmd = [sys.executable, "-m", "snaps_graph.cli", "run", seq, "--out", out, "--refine", "batch", "--map", "--overwrite"]
    subprocess.run(cmd, check=True)
    a.runs = [*a.runs, out]

if a.write_world:
    import open3d as o3d

    from snaps_graph.synth import SyntheticSequence, load_trajectory

    poses, times = load_trajectory(a.path)
    w = SyntheticSequence(poses, seed=0, times=times).world
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(w.vertices.astype(np.float64)), o3d.utility.Vector3iVector(w.triangles.astype(np.int32))
    )
    o3d.io.write_triangle_mesh(a.write_world, m)
    print(f"wrote {a.write_world}: {len(w.triangles)} triangles")

for run in map(Path, a.runs):
    import open3d as o3d
    from scipy.spatial import cKDTree

    from snaps_graph.trajectory_io import read_kitti_poses

    m = json.loads((run / "metrics.json").read_text())
    mp = m.get("map", {})
    print(f"== {run}: {m['frames']} frames, wall {m['wall_s']:.1f} s, peak RSS {m.get('peak_rss_mb', float('nan')):.0f} MiB")
    with open(run / "frames.csv") as f:
        t_map = sum(float(r["t_map_ms"]) for r in csv.DictReader(f)) / 1e3
    t_out = mp.get("t_output_s", 0.0)  # fusion of the map(s), PLY files, pictures; not the accuracy measurement
    total = m["wall_s"] + t_out
    print(
        f"map work: keyframe depth {t_map:.1f} s + fusion/files/pictures {t_out:.1f} s = {t_map + t_out:.1f} s "
        f"= {100 * (t_map + t_out) / total:.1f} % of the run ({total:.1f} s); {mp.get('keyframes')} keyframes, "
        f"{mp.get('bytes', 0) / 2**20:.1f} MiB stored depth; accuracy measurement {mp.get('t_accuracy_s', 0):.1f} s (not counted)"
    )
    chosen = mp.get("trajectory")
    if chosen in mp.get("surfaces", {}) and "t_pictures_s" in mp:
        # what a plain --map run does: depth online, one fusion, map.ply + map_mesh.ply, two pictures
        n_files = 1 + sum(1 for n in mp["surfaces"] if n != "gt" and (run / f"map_mesh_{n}.ply").is_file())
        plain = t_map + mp["surfaces"][chosen]["fuse_s"] + mp["t_files_s"] / n_files + mp["t_pictures_s"]
        print(
            f"  of which a plain --map run does: depth {t_map:.1f} s + fusion {mp['surfaces'][chosen]['fuse_s']:.1f} s + "
            f"files ~{mp['t_files_s'] / n_files:.1f} s + pictures {mp['t_pictures_s']:.1f} s = {plain:.1f} s = "
            f"{100 * plain / (m['wall_s'] + plain - t_map):.1f} % of such a run"
        )
    for name, s in mp.get("surfaces", {}).items():
        print(
            f"  fused under {name}: {s['triangles']} triangles, {s['vertices']} vertices (= map.ply points), {s['chunks']} chunk(s), "
            f"max {s['max_blocks']} blocks, {s['fuse_s']:.1f} s"
        )
    if (run / "map.ply").is_file() and chosen:
        pts = np.asarray(o3d.io.read_point_cloud(str(run / "map.ply")).points)
        path = np.asarray(read_kitti_poses(run / f"poses_{chosen}.txt"))[:, :3, 3]
        d, _ = cKDTree(path).query(pts)
        print(
            f"map.ply ({chosen}): {len(pts)} points, {100 * np.mean(d > a.far_m):.2f} % farther than {a.far_m:g} m "
            f"from the path (max {d.max():.1f} m)"
        )
    for name, acc in mp.get("accuracy", {}).items():
        p, me = acc["points"], acc["mesh"]
        print(
            f"  {name:<6} points: p50 {p['error_median_m']:.3f} p90 {p['error_p90_m']:.3f} m, completeness "
            f"{100 * p['completeness']:.1f} % (seen {100 * (p['completeness_seen'] or 0):.1f} %) | mesh vertices: p50 "
            f"{me['error_median_m']:.3f} p90 {me['error_p90_m']:.3f} m, completeness {100 * me['completeness']:.1f} % "
            f"(seen {100 * (me['completeness_seen'] or 0):.1f} %) | {acc['surface_samples']} samples within "
            f"{acc['range_m']:g} m, {100 * acc['surface_seen_share']:.0f} % seen"
        )
        if "aligned" in acc:  # moved by the trajectory's SE(3) alignment onto the truth (as the ATE)
            a, am = acc["aligned"]["points"], acc["aligned"]["mesh"]
            print(
                f"  {'':<6} aligned as the ATE: points p50 {a['error_median_m']:.3f} p90 {a['error_p90_m']:.3f} m, "
                f"completeness {100 * a['completeness']:.1f} % (seen {100 * (a['completeness_seen'] or 0):.1f} %) | mesh "
                f"vertices p50 {am['error_median_m']:.3f} p90 {am['error_p90_m']:.3f} m, seen {100 * (am['completeness_seen'] or 0):.1f} %"
            )
