"""Where does the VO's pitch bias come from? Tracking and stereo against exact synthetic depth.

Renders pairs of consecutive frames along a KITTI ground-truth path (default: KITTI 00, frames
0-400, every 30th), detects corners as the front end does, and compares, by image row band:

* **stereo**: the sparse LK disparity at each corner against the exact disparity from the
  renderer's depth (fx * baseline / z);
* **tracking**: the KLT position of each corner in the next frame against its exact position
  (its exact 3D point moved by the ground-truth relative pose and projected), for each LK window
  size given, and for each frame gap given (``--gaps 1 3 5``: tracking from a keyframe g frames
  back; the per-frame bias is then the row bias / g).

``--bias-windows 0 7`` repeats the tracking rows with ``KLT.bias_window_px`` (frontend/features.py) at each value (0 = the
plain LK fit; the default 7 re-fits with a 7 px window and extrapolates the window bias away).

With ``--run RUN`` it prints only the mean per-step rotation error (pitch, yaw, roll) and vertical
translation error of a results folder's VO against its ground truth, with standard errors and
the per-step scatter (standard deviation), and the vertical error each rotation component's
per-step errors build up (the world tilt they add, crossed with the true steps); it renders
nothing.

    python experiments/tracking_bias.py [--trajectory ../shared/data/kitti_gt/00.txt] [--windows 7 11 21] [--gaps 1 3 5] [--bias-windows 0 7] [--run results/bench/run00]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.frontend import depth as depth_mod
from snaps_graph.frontend import features as feat
from snaps_graph.geometry import log_so3
from snaps_graph.synth import SyntheticSequence, load_trajectory
from snaps_graph.trajectory_io import read_poses

ROOT = Path(__file__).resolve().parents[1]
BANDS = ((0, 100), (100, 180), (180, 220), (220, 280), (280, 10_000))


def band_table(title: str, v: np.ndarray, err: np.ndarray) -> None:
    print(title)
    for lo, hi in BANDS:
        m = (v >= lo) & (v < hi) & (np.abs(err) < 2)
        if m.any():
            sem = err[m].std() / np.sqrt(m.sum())
            print(
                f"  rows {lo:>3}-{min(hi, 999):<3}  n {m.sum():5d}  median {np.median(err[m]):+.4f}  mean {err[m].mean():+.4f} (+- {sem:.4f}) px"
            )


def run_bias(run: Path) -> None:
    gt, vo = read_poses(run / "poses_gt.txt"), read_poses(run / "poses_vo.txt")
    E = [np.linalg.solve(np.linalg.solve(gt[k - 1], gt[k]), np.linalg.solve(vo[k - 1], vo[k])) for k in range(1, len(vo))]
    rot = np.degrees([log_so3(e[:3, :3]) for e in E]) * 1e3  # millidegrees
    ty = np.array([e[1, 3] for e in E]) * 1e3  # mm
    n = len(E)
    print(f"{run}: per-step VO error over {n} steps (mean +- standard error)")
    for i, name in enumerate(("pitch (x)", "yaw (y)", "roll (z)")):
        print(
            f"  {name:<10} {rot[:, i].mean():+.2f} +- {rot[:, i].std() / np.sqrt(n):.2f} millideg, scatter {rot[:, i].std():.2f}"
        )
    print(f"  vertical   {ty.mean():+.3f} +- {ty.std() / np.sqrt(n):.3f} mm (camera y), scatter {ty.std():.2f}")
    # The vertical (world y) error each rotation component builds up: its per-step errors taken
    # into the world frame and summed (small angles), then crossed with the true steps.
    rad = np.radians(rot / 1e3)
    step = np.diff(gt[:, :3, 3], axis=0)
    dv = vo[:, 1, 3] - gt[:, 1, 3]
    built = []
    for i in range(3):
        tilt = np.cumsum(gt[1:, :3, i] * rad[:, i : i + 1], axis=0)  # R_world_cam[k] e_k, summed
        built.append(np.r_[0.0, np.cumsum(np.cross(tilt, step)[:, 1])])
    print(
        f"  vertical error: mean |dv| {np.abs(dv).mean():.3f} m; built by the per-step pitch errors {np.abs(built[0]).mean():.3f}, "
        f"roll {np.abs(built[2]).mean():.3f}, yaw {np.abs(built[1]).mean():.3f} (mean |.|); at the end {dv[-1]:+.2f} m: "
        f"pitch {built[0][-1]:+.2f}, roll {built[2][-1]:+.2f}, yaw {built[1][-1]:+.2f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", default=str(ROOT.parent / "shared/data/kitti_gt/00.txt"))
    ap.add_argument("--frames", default="0:400")
    ap.add_argument("--every", type=int, default=30)
    ap.add_argument("--windows", type=int, nargs="*", default=[7, 11, 21])
    ap.add_argument("--gaps", type=int, nargs="*", default=[1], help="frames between the tracked pair")
    ap.add_argument(
        "--bias-windows", type=int, nargs="*", default=None, help="KLT bias_window_px values (default: the front end's)"
    )
    ap.add_argument("--run", type=Path, default=None)
    args = ap.parse_args()
    if args.run:
        run_bias(args.run)
        return
    poses, times = load_trajectory(args.trajectory, args.frames)
    seq = SyntheticSequence(poses, width=1241, height=376, seed=0, times=times)
    cam, cfg = seq.camera, Config().frontend
    stereo_v, stereo_err = [], []
    bias_windows = args.bias_windows if args.bias_windows is not None else [feat.KLT.bias_window_px]
    keys = [(w, g, b) for w in args.windows for g in args.gaps for b in bias_windows]
    track: dict[tuple[int, int, int], list[np.ndarray]] = {k: [] for k in keys}
    for i in range(0, len(seq) - max(args.gaps), args.every):
        f0 = seq.render(i)
        uv = feat.detect_corners(f0.left, feat.KLT.features, feat.KLT, avoid=np.zeros((0, 2), np.float32))
        z = depth_mod.sample_depth(f0.depth, uv)
        uv, z = uv[z > 0], z[z > 0]
        # stereo
        zs, d = depth_mod.sparse_depth(f0.left, f0.right, uv, cam, cfg)
        ok = zs > 0
        stereo_v.append(uv[ok, 1])
        stereo_err.append(d[ok] - cam.fx * cam.baseline_m / z[ok])
        # tracking
        P = np.c_[(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z, np.ones(len(z))]
        for g in args.gaps:
            f1 = seq.render(i + g, with_depth=False)
            Q = (np.linalg.solve(seq.gt_poses[i + g], seq.gt_poses[i]) @ P.T).T
            true = np.c_[cam.fx * Q[:, 0] / Q[:, 2] + cam.cx, cam.fy * Q[:, 1] / Q[:, 2] + cam.cy]
            # The front end starts LK at the constant-velocity prediction; the exact one here.
            for w in args.windows:
                for b in bias_windows:
                    klt = feat.KltParams(window_px=w, bias_window_px=b)
                    p1, okt = feat.track_klt(f0.left, f1.left, uv, klt, true if g > 1 else None)
                    track[(w, g, b)].append(np.c_[uv[okt, 1], p1[okt, 1] - true[okt, 1]])
    band_table("stereo: sparse LK disparity - exact disparity", np.concatenate(stereo_v), np.concatenate(stereo_err))
    for (w, g, b), parts in track.items():
        a = np.concatenate(parts)
        fix = f", bias window {b} px" if 0 < b < w else ""
        band_table(
            f"tracking over {g} frame(s), {w} px window{fix}: KLT row - exact row (positive = too low in the image)",
            a[:, 0],
            a[:, 1],
        )


if __name__ == "__main__":
    main()
