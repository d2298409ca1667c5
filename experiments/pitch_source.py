"""Which input makes the VO's per-step pitch bias? The two-view stereo BA on exact and measured inputs.

Renders consecutive frame pairs along a KITTI ground-truth path (default: KITTI 00, frames
0-1000, every 10th), detects corners as the front end does and solves each pair's motion with the
front end's stereo BA (``stereo_two_view_ba``, started at the true motion) from:

* exact correspondences and disparities (the renderer's depth): the BA itself, no error;
* KLT tracks (the default tracker, started at the true position) or measured sparse-stereo
  disparities in place of the exact ones, one input at a time;
* KLT's row or column errors alone, or its errors clipped to +-0.5 px (what the tails add);
* KLT tracks in one image-row band or depth band only, exact elsewhere: where the error enters.

It prints each input's mean per-step rotation error (pitch, yaw, roll, millidegrees), vertical
translation error (camera y, mm) and step-length error (%), with standard errors over the pairs.

With ``--kernel HUBER OUTLIER`` every solve uses that robust kernel; ``--noise`` adds sensor noise.

    python experiments/pitch_source.py [--trajectory ../shared/data/kitti_gt/00.txt] [--frames 0:1000] [--every 10] [--noise 2] [--kernel 0.3 0.6]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.frontend import depth as depth_mod
from snaps_graph.frontend import features as feat
from snaps_graph.frontend.stereo_ba import STEREO_BA, stereo_two_view_ba
from snaps_graph.geometry import log_so3
from snaps_graph.synth import SyntheticSequence, load_trajectory

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", default=str(ROOT.parent / "shared/data/kitti_gt/00.txt"))
    ap.add_argument("--frames", default="0:1000")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.0, help="sensor noise of the rendering, grey levels")
    ap.add_argument(
        "--kernel",
        type=float,
        nargs=2,
        metavar=("HUBER", "OUTLIER"),
        default=None,
        help="the stereo BA's Huber and outlier thresholds, px (default: the config's)",
    )
    args = ap.parse_args()
    poses, times = load_trajectory(args.trajectory, args.frames)
    seq = SyntheticSequence(poses, width=1241, height=376, seed=0, times=times, noise_std=args.noise)
    cam, cfg = seq.camera, Config().frontend
    huber, outlier = args.kernel if args.kernel else (STEREO_BA.huber_px, STEREO_BA.outlier_px)
    ba_cfg = dataclasses.replace(STEREO_BA, huber_px=huber, outlier_px=outlier)
    fb = cam.fx * cam.baseline_m
    out: dict[str, list[np.ndarray]] = {}
    for i in range(1, len(seq) - 1, args.every):
        f0, f1 = seq.render(i), seq.render(i + 1)
        uv = feat.detect_corners(f0.left, feat.KLT.features, feat.KLT)
        z = depth_mod.sample_depth(f0.depth, uv)
        dm0 = depth_mod.sparse_disparity(f0.left, f0.right, uv, cfg)
        keep = (z > 0) & (dm0 > 0)
        uv, z, dm0 = uv[keep], z[keep], dm0[keep]
        P = np.c_[(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z]
        T = np.linalg.solve(seq.gt_poses[i + 1], seq.gt_poses[i])  # T_cur_ref
        Q = P @ T[:3, :3].T + T[:3, 3]
        true = np.c_[cam.fx * Q[:, 0] / Q[:, 2] + cam.cx, cam.fy * Q[:, 1] / Q[:, 2] + cam.cy].astype(np.float32)
        de0, de1 = fb / z, fb / Q[:, 2]
        klt, ok = feat.track_klt(f0.left, f1.left, uv, feat.KLT, true.copy())
        seen = np.abs(depth_mod.sample_depth(f1.depth, true) - Q[:, 2]) < 0.05 * Q[:, 2]  # not occluded

        def klt_in(sel: np.ndarray, true: np.ndarray = true, klt: np.ndarray = klt) -> np.ndarray:
            """Exact positions, KLT's where ``sel``."""
            return np.where(sel[:, None], klt, true)

        v = uv[:, 1]
        inputs = {
            "exact tracks, exact disparities": (true, de0, de1, seen),
            "KLT tracks": (klt, de0, de1, seen & ok),
            "measured disparities": (true, dm0, depth_mod.sparse_disparity(f1.left, f1.right, true, cfg), seen),
            "KLT tracks, measured disparities": (klt, dm0, depth_mod.sparse_disparity(f1.left, f1.right, klt, cfg), seen & ok),
            "KLT row errors only": (np.c_[true[:, 0], klt[:, 1]], de0, de1, seen & ok),
            "KLT column errors only": (np.c_[klt[:, 0], true[:, 1]], de0, de1, seen & ok),
            "KLT errors clipped to +-0.5 px": (true + np.clip(klt - true, -0.5, 0.5), de0, de1, seen & ok),
            "KLT in rows < 180 only": (klt_in(v < 180), de0, de1, seen & ok),
            "KLT in rows 180-220 only": (klt_in((v >= 180) & (v < 220)), de0, de1, seen & ok),
            "KLT in rows 220-280 only": (klt_in((v >= 220) & (v < 280)), de0, de1, seen & ok),
            "KLT in rows >= 280 only": (klt_in(v >= 280), de0, de1, seen & ok),
            "KLT at depth < 10 m only": (klt_in(z < 10), de0, de1, seen & ok),
            "KLT at depth 10-20 m only": (klt_in((z >= 10) & (z < 20)), de0, de1, seen & ok),
            "KLT at depth 20-40 m only": (klt_in((z >= 20) & (z < 40)), de0, de1, seen & ok),
            "KLT at depth >= 40 m only": (klt_in(z >= 40), de0, de1, seen & ok),
        }
        for name, (c, d0, d1, use) in inputs.items():
            s = use & (d1 > 0)
            r = stereo_two_view_ba(T, uv[s], d0[s], c[s], d1[s], cam, ba_cfg)
            E = np.linalg.solve(T, r.T_cur_ref)
            step = (np.linalg.norm(r.T_cur_ref[:3, 3]) / np.linalg.norm(T[:3, 3]) - 1) * 100
            out.setdefault(name, []).append(np.r_[np.degrees(log_so3(E[:3, :3])) * 1e3, E[1, 3] * 1e3, step])
    print(
        f"{args.trajectory} frames {args.frames}, every {args.every}th pair: mean per-step error of the two-view stereo BA (+- standard error)"
    )
    for name, rows in out.items():
        a = np.array(rows)
        mu, se = a.mean(0), a.std(0) / np.sqrt(len(a))
        print(
            f"  {name:<34} pitch {mu[0]:+.2f} +- {se[0]:.2f}  yaw {mu[1]:+.2f} +- {se[1]:.2f}  roll {mu[2]:+.2f} +- {se[2]:.2f} mdeg"
            f"  vertical {mu[3]:+.3f} +- {se[3]:.3f} mm  step {mu[4]:+.3f} +- {se[4]:.3f} %  ({len(a)} pairs)"
        )


if __name__ == "__main__":
    main()
