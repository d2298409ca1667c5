"""Two-view loop verification (no stereo) against the ground truth of a real revisit.

On ``kitti00_loop`` (KITTI 00, left camera), every pair of a revisit frame (1573-1630) and a
first-pass frame (127-190) standing within ``--radius`` m of each other (ground truth) is verified
as the pipeline does without a right image (``frontend.two_view.two_view_pose``: reference
features as stored, current frame's as queried); printed: how many verify, and the median (and
90th percentile) rotation error and translation-direction error against poses/00.txt.

    python benchmarks/bench_two_view.py [--data ../shared/data/kitti00_loop] [--radius 2]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.frontend.loop_features import LOOP_ORB_FEATURES, LOOP_QUERY_FEATURES
from snaps_graph.frontend.two_view import DETECTOR, _sampson, _skew, two_view_features, two_view_pose
from snaps_graph.geometry import log_so3, rotation_angle_deg

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "kitti00_loop"
CONTROL_DATA = HERE.parent.parent / "shared" / "data" / "kitti" / "sequences" / "06"


def control(fe, detector: str) -> None:
    """A known truth on real images: KITTI 06's left image k against the right image k + j (the
    rectified rig: R = I and 0.54 m to the right, composed with the drive's j frames)."""
    if not CONTROL_DATA.is_dir():
        return
    seq = KittiSequence(CONTROL_DATA)
    assert seq._gt_all is not None
    T_lr = np.eye(4)
    T_lr[0, 3] = seq.camera.baseline_m
    for j in (0, 1, 2):
        res = []
        for k in range(0, len(seq) - j, 5):
            T = np.linalg.solve(seq._gt_all[k], seq._gt_all[k + j]) @ T_lr
            a = two_view_features(seq[k].left, fe, LOOP_ORB_FEATURES, detector)
            b = two_view_features(seq[k + j].right, fe, LOOP_QUERY_FEATURES, detector)
            m = two_view_pose(a, b, seq.camera, fe)
            if m is not None:
                res.append(errors(T, m.R_ref_cur, m.direction))
        if res:
            r = np.array(res)
            print(
                f"control, KITTI 06 left k vs right k+{j} ({len(r)} pairs, baseline {np.linalg.norm(T[:3, 3]):.2f} m): "
                f"rotation median {np.median(r[:, 0]):.3f} deg, direction {np.median(r[:, 1]):.2f} deg"
            )


def errors(T_gt: np.ndarray, R: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """(rotation error deg, translation-direction error deg) of a two-view estimate."""
    rot = rotation_angle_deg(T_gt[:3, :3].T @ R)
    t = T_gt[:3, 3] / np.linalg.norm(T_gt[:3, 3])
    return rot, float(np.degrees(np.arccos(np.clip(t @ d, -1.0, 1.0))))


def epipolar_px(T_ref_cur: np.ndarray, x_ref: np.ndarray, x_cur: np.ndarray, fx: float) -> np.ndarray:
    """Sampson distances (px) of normalised matches under the relative pose T_ref_cur."""
    t = T_ref_cur[:3, 3] / np.linalg.norm(T_ref_cur[:3, 3])
    return _sampson(_skew(t) @ T_ref_cur[:3, :3], x_cur, x_ref) * fx


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--radius", type=float, default=2.0, help="pairs within this distance (m, ground truth)")
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--detector", choices=("orb", "sift"), default=DETECTOR, help="features (default: the pipeline's)")
    args = ap.parse_args()
    cfg = Config.load(args.config) if args.config else Config()
    fe = cfg.frontend
    seq = KittiSequence(args.data / "sequences" / "00")
    assert seq._gt_all is not None, "kitti00_loop ground truth (poses/00.txt) not found"
    number = {int(f): i for i, f in enumerate(seq.indices)}
    gt = {int(f): seq._gt_all[i] for f, i in number.items()}
    cur_frames = [f for f in range(1573, 1631) if f in number]
    ref_frames = [f for f in range(127, 191) if f in number]
    pairs = [(r, c) for c in cur_frames for r in ref_frames if np.linalg.norm(gt[r][:3, 3] - gt[c][:3, 3]) <= args.radius]
    refs = {
        r: two_view_features(seq[number[r]].left, fe, LOOP_ORB_FEATURES, args.detector) for r in sorted({r for r, _ in pairs})
    }
    curs = {
        c: two_view_features(seq[number[c]].left, fe, LOOP_QUERY_FEATURES, args.detector) for c in sorted({c for _, c in pairs})
    }
    rot, dirn, base, t_ms = [], [], [], []
    ok_pairs, ok_match, est = [], [], []
    Kinv = np.linalg.inv(seq.camera.K)
    for r, c in pairs:
        T_gt = np.linalg.solve(gt[r], gt[c])
        t0 = time.perf_counter()
        m = two_view_pose(refs[r], curs[c], seq.camera, fe)
        t_ms.append((time.perf_counter() - t0) * 1e3)
        if m is None:
            continue
        sub = m.pairs[:: max(1, len(m.pairs) // 100)]  # at most about 100 matches a pair for the fit
        xr = np.c_[refs[r].uv[sub[:, 0]], np.ones(len(sub))] @ Kinv.T
        xc = np.c_[curs[c].uv[sub[:, 1]], np.ones(len(sub))] @ Kinv.T
        ok_pairs.append((r, c))
        ok_match.append((xr, xc))
        est.append(m)
        er, ed = errors(T_gt, m.R_ref_cur, m.direction)
        rot.append(er)
        dirn.append(ed)
        base.append(float(np.linalg.norm(T_gt[:3, 3])))
    rot_a, dir_a, base_a = np.array(rot), np.array(dirn), np.array(base)
    print(f"features: {args.detector}")
    control(fe, args.detector)
    print(f"kitti00_loop: {len(pairs)} pairs within {args.radius:g} m (frames 1573-1630 vs 127-190), {len(rot)} verified")
    if not rot:
        return
    print(f"rotation error      median {np.median(rot_a):.3f} deg, p90 {np.percentile(rot_a, 90):.3f} deg")
    axes = np.degrees([log_so3(np.linalg.solve(gt[r], gt[c])[:3, :3].T @ m.R_ref_cur) for (r, c), m in zip(ok_pairs, est)])
    print(
        "  about the camera's x (pitch), y (yaw), z (roll): median "
        + ", ".join(f"{v:+.3f}" for v in np.median(axes, axis=0))
        + " deg"
    )
    rel = np.array([np.linalg.solve(gt[r], gt[c])[:3, 3] for r, c in ok_pairs])
    ahead = rel[:, 2] > 0
    print(
        f"  yaw error with the current frame ahead of the reference {np.median(axes[ahead, 1]):+.3f} deg, behind "
        f"{np.median(axes[~ahead, 1]):+.3f} deg; correlation with the truth's lateral offset {np.corrcoef(axes[:, 1], rel[:, 0])[0, 1]:.2f}"
    )
    cur_of = np.array([c for _, c in ok_pairs])
    for lo in range(cur_frames[0], cur_frames[-1] + 1, 20):
        sel = (cur_of >= lo) & (cur_of < lo + 20)
        if sel.any():
            print(
                f"  frames {lo}-{min(lo + 19, cur_frames[-1])}: yaw error {np.median(axes[sel, 1]):+.2f} deg, "
                f"the truth's lateral offset {np.median(rel[sel, 0]):+.2f} m, the estimate's direction x {np.median([est[i].direction[0] for i in np.flatnonzero(sel)]):+.2f}"
            )
    print(f"direction error     median {np.median(dir_a):.2f} deg, p90 {np.percentile(dir_a, 90):.2f} deg")
    for lo, hi in ((0.0, 0.5), (0.5, 1.0), (1.0, args.radius)):
        sel = (base_a >= lo) & (base_a < hi)
        if sel.any():
            print(
                f"  baseline {lo:.1f}-{hi:.1f} m: {int(sel.sum())} pairs, rotation {np.median(rot_a[sel]):.3f} deg, "
                f"direction {np.median(dir_a[sel]):.2f} deg"
            )
    print(f"two_view_pose       median {np.median(t_ms):.1f} ms per pair")

    fx = seq.camera.fx
    res_gt = np.concatenate(
        [np.abs(epipolar_px(np.linalg.solve(gt[r], gt[c]), xr, xc, fx)) for (r, c), (xr, xc) in zip(ok_pairs, ok_match)]
    )
    res_est = np.concatenate(
        [np.abs(_sampson(_skew(m.direction) @ m.R_ref_cur, xc, xr)) * fx for m, (xr, xc) in zip(est, ok_match)]
    )
    print(
        f"inlier matches' epipolar distance: median {np.median(res_gt):.2f} px under the ground truth's relative pose, "
        f"{np.median(res_est):.2f} px under the estimate"
    )
    # The ground truth's relative pose between the passes, without its height: both passes drive
    # the same road with the camera at the same height, so a height difference is the truth's.
    hz = []
    for (r, c), m in zip(ok_pairs, est):
        t = np.linalg.solve(gt[r], gt[c])[:3, 3]
        a, b = np.array([t[0], t[2]]), np.array([m.direction[0], m.direction[2]])
        hz.append(float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))))
    dz = [float(np.linalg.solve(gt[r], gt[c])[1, 3]) for r, c in ok_pairs]
    print(
        f"the truth puts the revisit {np.median(dz):.2f} m lower (median over the pairs) on the same road; "
        f"direction error in the ground plane (x, z) median {np.median(hz):.2f} deg, p90 {np.percentile(hz, 90):.2f} deg"
    )
    # Precision without the truth between the passes: one current frame verified against its
    # neighbouring references, each carried to the first by the first pass's truth (locally exact).
    spread = []
    by_cur: dict[int, list] = {}
    for (r, c), m in zip(ok_pairs, est):
        by_cur.setdefault(c, []).append((r, m))
    for lst in by_cur.values():
        r0 = lst[0][0]
        Rs = [np.linalg.solve(gt[r0], gt[r])[:3, :3] @ m.R_ref_cur for r, m in lst]
        spread += [rotation_angle_deg(Rs[0].T @ R) for R in Rs[1:]]
    if spread:
        print(
            f"rotation agreement between references of one frame (first pass's truth between them): median {np.median(spread):.3f} deg"
        )


if __name__ == "__main__":
    main()
