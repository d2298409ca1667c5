"""Why do open roads bias the VO's scale? Corner depths and stereo error by true depth.

Renders frames along a KITTI ground-truth path in a synthetic world (``--scene``, sensor
``--noise``, ``--rectification-error``), detects corners as the KLT front end does and prints, per band of exact depth:
how many corners the front end gets there, and the error of the sparse LK stereo at them
(disparity error in pixels, and depth error in %: mean and median of z_stereo / z_true - 1,
among the depths the front end keeps, <= max_depth_m).

    python experiments/far_stereo_bias.py --scene open [--noise 2] [--frames 0:1000] [--every 25]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.frontend import depth as depth_mod
from snaps_graph.frontend import features as feat
from snaps_graph.synth import SCENES, SyntheticSequence, WorldConfig, load_trajectory

ROOT = Path(__file__).resolve().parents[1]
BANDS = ((0, 10), (10, 20), (20, 30), (30, 50), (50, 80), (80, 1e9))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", default=str(ROOT.parent / "shared/data/kitti_gt/00.txt"))
    ap.add_argument("--frames", default="0:1000")
    ap.add_argument("--every", type=int, default=25)
    ap.add_argument("--scene", default="open", choices=SCENES)
    ap.add_argument("--noise", type=float, default=0.0)
    ap.add_argument("--rectification-error", type=float, default=0.0, help="px (see snaps-graph synth)")
    args = ap.parse_args()
    poses, times = load_trajectory(args.trajectory, args.frames)
    seq = SyntheticSequence(
        poses,
        width=1241,
        height=376,
        seed=0,
        times=times,
        noise_std=args.noise,
        world_config=WorldConfig(scene=args.scene),
        rectification_error_px=args.rectification_error,
    )
    cam, cfg = seq.camera, Config().frontend
    z_true, z_est, d_err = [], [], []
    for i in range(0, len(seq), args.every):
        f = seq.render(i)
        uv = feat.detect_corners(f.left, feat.KLT.features, feat.KLT, avoid=np.zeros((0, 2), np.float32))
        z = depth_mod.sample_depth(f.depth, uv)
        zs, d = depth_mod.sparse_depth(f.left, f.right, uv, cam, cfg)
        z_true.append(z)
        z_est.append(zs)
        d_err.append(np.where((zs > 0) & (z > 0), d - cam.fx * cam.baseline_m / np.maximum(z, 1e-6), np.nan))
    z, zs, de = np.concatenate(z_true), np.concatenate(z_est), np.concatenate(d_err)
    n_frames = len(range(0, len(seq), args.every))
    print(
        f"{args.scene}, noise {args.noise}, rectification error {args.rectification_error} px: {len(z)} corners in {n_frames} frames; true depth of sky corners = 0"
    )
    print(
        f"{'true depth m':>14}{'corners/frame':>15}{'with depth':>12}{'disp err px':>13}{'|disp err|':>12}{'depth err % mean':>18}{'median':>8}"
    )
    sky = z == 0
    print(f"{'sky':>14}{sky.sum() / n_frames:>15.1f}{np.mean(zs[sky] > 0) if sky.any() else 0:>12.2f}")
    for lo, hi in BANDS:
        m = (z >= lo) & (z < hi) & (z > 0)
        k = m & (zs > 0)
        rel = zs[k] / z[k] - 1 if k.any() else np.array([np.nan])
        print(
            f"{lo:>6.0f}-{min(hi, 999):<7.0f}{m.sum() / n_frames:>15.1f}{k.sum() / max(m.sum(), 1):>12.2f}"
            f"{np.nanmean(de[k]) if k.any() else np.nan:>13.3f}{np.nanmean(np.abs(de[k])) if k.any() else np.nan:>12.3f}"
            f"{100 * np.mean(rel):>18.2f}{100 * np.median(rel):>8.2f}"
        )


if __name__ == "__main__":
    main()
