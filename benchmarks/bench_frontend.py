"""Front-end speed and accuracy: a naive OpenCV version of the paper's VO against ours.

The naive pipeline (here, not in the package) is the paper's front end written the obvious
way: StereoBM + WLS on the full image, SIFT (2000 features) on the left image, OpenCV
brute-force matching with Lowe's ratio test, PnP RANSAC, everything sequential. It is the yard
stick: our default mode must take at most a quarter of its median frame time, measured side by
side in the same run, and the SIFT mode at most 100 ms.

Runs every mode over the same frames (images are read once, before timing) and prints, per
mode, the median milliseconds per stage and per frame, frames/s, the ratio to the naive
pipeline, flagged frames, ATE RMSE after SE(3) Umeyama alignment, end-point drift
(|p_end_est - p_end_gt| / ground-truth path length) and the step-length bias (sum of VO step
lengths / sum of ground-truth step lengths - 1: a scale error of the translation).

    python benchmarks/bench_frontend.py [--seq ../shared/data/kitti/sequences/06] [--frames 0:51]
        [--modes naive,default,klt_pnp,sift,sift_sba,sift_sparse,orb] [--config extra.toml] [--repeats N]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from naive_vo import NaiveVO  # the paper's front end written plainly

from snaps_graph.config import Config, FrontendConfig
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.metrics import ate_rmse, evaluate, path_length
from snaps_graph.frontend import StereoOdometry, depth, features, lba_schedule, local_ba

# [frontend] values per mode (as in a config file)
MODES = {
    "default": dict(),  # the default configuration
    "klt_pnp": dict(mode="klt", motion="pnp", local_ba=False),  # klt + sparse stereo + PnP only
    "klt_sba": dict(mode="klt", motion="stereo_ba", local_ba=False),
    "klt_lba": dict(mode="klt", motion="stereo_ba", local_ba=True),  # every frame a keyframe (PATCHES)
    "klt_lba2": dict(mode="klt", motion="stereo_ba", local_ba=True),
    "klt_lba3": dict(mode="klt", motion="stereo_ba", local_ba=True),
    "klt_lba3w6": dict(mode="klt", motion="stereo_ba", local_ba=True),
    "sift": dict(mode="sift", disparity="bm_wls", sift_first_octave=-1, motion="pnp", local_ba=False),  # the paper's front end
    "sift_sba": dict(mode="sift", disparity="bm_wls", sift_first_octave=-1, motion="stereo_ba"),
    "sift_sparse": dict(mode="sift", disparity="sparse"),  # what mode = "sift" runs by default
    "sift_fo-1": dict(mode="sift", disparity="sparse", sift_first_octave=-1),
    "orb": dict(mode="orb"),
    "no_offset": dict(estimate_offset=False),  # the default without the online disparity offset estimate
    "no_weak": dict(),  # the default without the weak-texture corner detection (PATCHES)
    "no_chain": dict(),  # the default without the chain's heading factor in the local BA
    "chain_yaw": dict(),  # the chain's heading alone in the local BA (the default before yaw_roll)
    "sgl1": dict(),  # tracked points' stereo from the predicted disparity, 2 pyramid levels
    "sgl2": dict(),  # ... 3 pyramid levels
    "no_bias_fix": dict(),  # the default with the plain 11 px LK fit
}
# The front end's constants a mode changes: (module, name, value), restored after the mode's run.
PATCHES = {
    "klt_lba": [(lba_schedule, "LBA_EVERY", 1)],
    "klt_lba2": [(lba_schedule, "LBA_EVERY", 2), (local_ba, "LBA_WINDOW", 8)],
    "klt_lba3": [(local_ba, "LBA_WINDOW", 8)],
    "klt_lba3w6": [],
    "no_weak": [(features, "KLT", features.KltParams(weak_points=0))],
    "no_chain": [(lba_schedule, "LBA_CHAIN", "off")],
    "chain_yaw": [(lba_schedule, "LBA_CHAIN", "yaw")],
    "sgl1": [(depth, "STEREO_GUESS_LEVELS", 1)],
    "sgl2": [(depth, "STEREO_GUESS_LEVELS", 2)],
    "no_bias_fix": [(features, "KLT", features.KltParams(bias_window_px=0))],
}


def step_bias_percent(poses: np.ndarray, gt: np.ndarray) -> float:
    """100 * (sum of VO step lengths / sum of ground-truth step lengths - 1)."""
    s_vo = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()
    s_gt = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    return 100.0 * (s_vo / max(s_gt, 1e-12) - 1.0)


def step_error_axes_percent(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Sum of the per-step translation errors in each true step's start camera frame (x right,
    y down, z forward), % of the true path. A constant rotation between the estimate's camera
    and the ground truth's (a calibration between them) shows as a steady x / y share that no
    front end can remove; z is the step-length bias."""
    Ra, Re = gt[:-1, :3, :3], est[:-1, :3, :3]
    Rg = np.einsum("kji,kjl->kil", Ra, gt[1:, :3, :3])  # the true steps' rotations
    tg = np.einsum("kji,kj->ki", Ra, gt[1:, :3, 3] - gt[:-1, :3, 3])
    te = np.einsum("kji,kj->ki", Re, est[1:, :3, 3] - est[:-1, :3, 3])
    err = np.einsum("nji,nj->ni", Rg, te - tg)
    return 100.0 * err.sum(0) / max(path_length(gt), 1e-9)


def accuracy(poses: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    """(ATE m, end drift % of the path, step-length bias %) of ``poses`` against ``gt``."""
    drift = 100.0 * np.linalg.norm(poses[-1, :3, 3] - gt[-1, :3, 3]) / max(path_length(gt), 1e-9)
    return ate_rmse(poses, gt), drift, step_bias_percent(poses, gt)


def frontend_config(name: str, base: FrontendConfig | None = None) -> FrontendConfig:
    cfg = Config(frontend=copy.deepcopy(base) if base is not None else FrontendConfig())
    return cfg.merged({"frontend": MODES[name]}, f"mode {name}").frontend


def run(name, seq, frames, base=None):
    cam = seq.camera
    if name == "naive":
        vo = NaiveVO(cam, FrontendConfig())
        out = [vo.process(f) for f in frames]
        poses = np.array([o[0] for o in out])
        flagged = sum(not o[1] for o in out)
        timings = [o[2] for o in out]
    else:
        saved = [(mod, key, getattr(mod, key)) for mod, key, _ in PATCHES.get(name, [])]
        for mod, key, value in PATCHES.get(name, []):
            setattr(mod, key, value)
        try:
            with StereoOdometry(cam, frontend_config(name, base)) as vo:
                res = [vo.process(f) for f in frames]
        finally:
            for mod, key, value in saved:
                setattr(mod, key, value)
        poses = np.array([r.pose for r in res])
        flagged = sum(not r.ok for r in res)
        timings = [r.timings_ms for r in res]
        if res and res[-1].disparity_offset_px != 0.0:
            timings[-1] = dict(timings[-1], offset_px=res[-1].disparity_offset_px)
    return poses, flagged, timings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", default=str(ROOT.parent / "shared" / "data" / "kitti" / "sequences" / "06"))
    ap.add_argument("--frames", default=None, help="A:B (default: all)")
    ap.add_argument("--modes", default="naive,default,klt_pnp,sift")
    ap.add_argument("--config", default=None, help="TOML whose [frontend] section is the base of every mode")
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="runs of every mode, interleaved (mode order repeated): the times are the median over runs of each run's median",
    )
    ap.add_argument(
        "--eval-from",
        type=int,
        default=0,
        help="also print ATE, end drift and step bias of frames K..N, both trajectories re-anchored at frame K "
        "(KITTI 06: 12, where the ground truth's heading disagrees with every front end before)",
    )
    args = ap.parse_args()
    base = None
    if args.config:
        from snaps_graph.config import Config

        base = Config.load(args.config).frontend
    seq = KittiSequence(args.seq, frames=args.frames)
    frames = list(seq)  # read once: timing excludes PNG decoding
    gt = seq.gt_poses
    names = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in names:
        if m != "naive" and m not in MODES:
            sys.exit(f"unknown mode '{m}' (naive, {', '.join(MODES)})")
    print(
        f"{args.seq}: {len(frames)} frames {seq.camera.width}x{seq.camera.height}, "
        f"OpenCV {cv2.__version__}, cv2 threads {cv2.getNumThreads()}"
    )
    if gt is not None:
        print(f"ground-truth path length {path_length(gt):.1f} m")
    medians = {}
    stages = ("depth", "features", "match", "pnp", "sba", "lba", "total")
    print(
        f"{'mode':12s} "
        + " ".join(f"{s:>9s}" for s in stages)
        + "   frames/s  ratio/naive  CPU_ms  flagged  ATE_m  drift_%  step_bias_%"
    )
    runs: dict[str, list] = {name: [] for name in names}
    for _ in range(max(1, args.repeats)):
        for name in names:
            c0 = time.process_time()
            out = run(name, seq, frames, base)
            runs[name].append((*out, (time.process_time() - c0) * 1000.0 / len(frames)))
    for name in names:
        poses, flagged, timings, _ = runs[name][-1]
        per_run = []
        for _, _, tr, _ in runs[name]:
            steady = tr[1:] if len(tr) > 1 else tr  # frame 0 has no matching
            per_run.append({s: float(np.median([t.get(s, 0.0) for t in steady])) for s in stages})
        med = {s: float(np.median([m[s] for m in per_run])) for s in stages}
        cpu = float(np.median([r[3] for r in runs[name]]))
        medians[name] = med["total"]
        ratio = med["total"] / medians["naive"] if "naive" in medians else float("nan")
        if gt is not None and len(gt) >= 3:
            ate, drift, sbias = accuracy(poses, gt)
        else:
            ate = drift = sbias = float("nan")
        print(
            f"{name:12s} "
            + " ".join(f"{med[s]:9.1f}" for s in stages)
            + f"   {1000.0 / med['total']:8.1f}  {ratio:11.3f}  {cpu:6.1f}  {flagged:7d}  {ate:5.3f}  {drift:7.2f}  {sbias:+11.2f}"
        )
        spans = [("", 0)] if gt is not None and len(gt) >= 3 else []
        if gt is not None and 0 < args.eval_from < len(gt) - 2:
            k = args.eval_from
            ate_k, drift_k, sbias_k = accuracy(np.linalg.inv(poses[k]) @ poses[k:], np.linalg.inv(gt[k]) @ gt[k:])
            print(f"{'':12s} from frame {k}: ATE {ate_k:.3f} m, end drift {drift_k:.2f} %, step bias {sbias_k:+.2f} %")
            spans.append((f"from frame {k}: ", k))
        for label, k in spans:
            ex, ey, ez = step_error_axes_percent(poses[k:], gt[k:])
            print(f"{'':12s} {label}step error in the camera frame, % of the path: x {ex:+.2f} y {ey:+.2f} z {ez:+.2f}")
        if gt is not None and len(gt) >= 200:  # long enough for KITTI's t_rel (100 m segments)
            m = evaluate(poses, gt)
            print(
                f"{'':12s} mean deviation {m['mean_deviation']:.3f} m (horizontal {m['mean_deviation_horizontal']:.3f}, "
                f"vertical {m['mean_deviation_vertical']:.3f}), t_rel {m['t_rel']:.3f} %, r_rel {m['r_rel']:.4f} deg/100 m"
            )
        if "offset_px" in timings[-1]:
            print(f"{'':12s} disparity offset applied at the end: {timings[-1]['offset_px']:+.3f} px")
        kf_ms = [t["lba"] for t in timings if "lba" in t]
        if kf_ms:
            print(f"{'':12s} local BA on {len(kf_ms)} keyframes: median {np.median(kf_ms):.1f} ms, max {np.max(kf_ms):.1f} ms")
    print(
        "(ms are medians over frames 1..N; stages of our modes overlap in two threads, so they need not add up to total; "
        "CPU_ms: process CPU per frame, all threads)"
    )
    if args.repeats > 1:
        for name in names:
            totals = [float(np.median([t.get("total", 0.0) for t in r[2][1:]])) for r in runs[name]]
            print(f"{name:12s} per-run median ms: {' '.join(f'{x:.1f}' for x in totals)}")


if __name__ == "__main__":
    main()
