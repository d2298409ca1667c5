"""Monocular loop verification (no right image) against ground truth, on real KITTI images.

The pipeline's monocular path (``verification.mono``): every ``REFERENCE_EVERY``-th frame's
keypoints are triangulated against a later frame of the same pass using the odometry's length,
and a candidate is verified by PnP of those points on the current frame's keypoints
(``verification.features.verify_features`` without a depth check). Printed:

* a control of exact truth: the reference bank of KITTI 06's left images (ground-truth poses as
  odometry) against the *right* image of frame k + j (the rectified rig: R = I, 0.54 m to the
  right, composed with the drive's j frames);
* the real revisit (kitti00_loop): every pair of a revisit frame (1560-1641) and a first-pass
  frame within ``--radius`` m (ground truth): how many verify (also for the entry, frames before
  1580, where the car turns in at another angle), rotation and
  translation errors against poses/00.txt, per axis, and the agreement between references of one
  current frame (carried to each other by the first pass's truth, locally exact);
* false pairs (10-40 m apart in the truth): how many verify, and how many pass the
  ``MAX_DISTANCE_M`` gate.

``--pct P --seed S`` builds the bank from odometry drifted by the drift tool instead of the truth.

    python benchmarks/bench_mono_verify.py [--data ../shared/data] [--radius 2] [--pct 1 --seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from revisit_reference import image_reference

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.drift import drift_trajectory
from snaps_graph.geometry import log_so3, rotation_angle_deg
from snaps_graph.trajectory_io import read_kitti_poses
from snaps_graph.verification.features import LOOP_QUERY_FEATURES, MAX_DISTANCE_M, verify_features
from snaps_graph.verification.mono import MonoFeatureBank, two_view_features

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data"


def bank_of(seq: KittiSequence, poses: np.ndarray, cfg: Config) -> tuple[MonoFeatureBank, dict[int, int], float]:
    """The reference bank of a sequence's left images with ``poses`` (one per frame number) as odometry."""
    bank = MonoFeatureBank(seq.camera, cfg.frontend, cfg.verification)
    k_of = {}
    t0 = time.perf_counter()
    for k, f in enumerate(seq):
        k_of[int(f.index)] = k
        bank.observe(k, f, poses[int(f.index)])
    return bank, k_of, (time.perf_counter() - t0) * 1e3 / len(seq)


def direction_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def control(path: Path, cfg: Config) -> None:
    if not path.is_dir():
        print(f"control skipped: {path} not found")
        return
    seq = KittiSequence(path)
    assert seq._gt_all is not None
    gt = {int(f): seq._gt_all[i] for i, f in enumerate(seq.indices)}
    poses = np.array([gt[f] for f in sorted(gt)])
    bank, k_of, _ = bank_of(seq, poses, cfg)
    T_lr = np.eye(4)
    T_lr[0, 3] = seq.camera.baseline_m
    for j in (0, 1, 2):
        res = []
        for r in sorted(gt):
            if bank.reference(k_of[r]) is None or r + j not in gt:
                continue
            T = np.linalg.solve(gt[r], gt[r + j]) @ T_lr
            cur = two_view_features(seq[k_of[r + j]].right, cfg.verification, LOOP_QUERY_FEATURES)
            m = verify_features(
                bank.reference(k_of[r]), cur, None, seq.camera, cfg.frontend, cfg.verification, unique=bank.merged
            )
            if m is not None:
                e = m.T_ref_cur
                res.append(
                    (
                        rotation_angle_deg(T[:3, :3].T @ e[:3, :3]),
                        np.linalg.norm(e[:3, 3] - T[:3, 3]),
                        direction_deg(e[:3, 3], T[:3, 3]),
                    )
                )
        if res:
            a = np.array(res)
            print(
                f"control, KITTI 06 left k vs right k+{j} ({len(a)} pairs, {np.linalg.norm(T[:3, 3]):.2f} m apart): rotation median "
                f"{np.median(a[:, 0]):.3f} deg, translation {np.median(a[:, 1]):.3f} m, direction {np.median(a[:, 2]):.2f} deg"
            )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data (kitti00_loop/, kitti/)")
    ap.add_argument("--radius", type=float, default=2.0, help="pairs within this distance (m, ground truth)")
    ap.add_argument("--pct", type=float, default=None, help="build the bank from odometry drifted by this percent")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", type=Path, default=None)
    args = ap.parse_args()
    cfg = Config.load(args.config) if args.config else Config()
    control(args.data / "kitti" / "sequences" / "06", cfg)
    root = args.data / "kitti00_loop"
    seq = KittiSequence(root / "sequences" / "00")
    G = read_kitti_poses(root / "poses" / "00.txt")
    odo = G if args.pct is None else drift_trajectory(G[: int(seq.indices[-1]) + 1], args.seed, pct=args.pct)
    bank, k_of, ms = bank_of(seq, odo, cfg)
    stored = [f for f in k_of if bank.reference(k_of[f]) is not None]
    print(
        f"kitti00_loop: {len(stored)} references stored, odometry {'truth' if args.pct is None else f'drifted {args.pct:g} %, seed {args.seed}'}; "
        f"bank {ms:.1f} ms per frame"
    )
    queries = {}

    def verify(c: int, r: int):
        if c not in queries:
            queries[c] = bank.query(k_of[c], seq[k_of[c]])
        return verify_features(
            bank.reference(k_of[r]), queries[c], None, seq.camera, cfg.frontend, cfg.verification, unique=bank.merged
        )

    pairs = [
        (r, c) for c in range(1560, 1642) for r in stored if r <= 230 and np.linalg.norm(G[r][:3, 3] - G[c][:3, 3]) <= args.radius
    ]
    out, t_ms = [], []
    for r, c in pairs:
        t0 = time.perf_counter()
        m = verify(c, r)
        t_ms.append((time.perf_counter() - t0) * 1e3)
        if m is not None:
            out.append((r, c, m))
    entry = [p for p in pairs if p[1] < 1580]
    print(
        f"revisit pairs within {args.radius:g} m: {len(pairs)}, verified {len(out)} (the entry: {len(entry)}, verified "
        f"{sum(c < 1580 for _, c, _ in out)}); verify median {np.median(t_ms):.1f} ms per pair"
    )
    if out:
        T_gt = [np.linalg.solve(G[r], G[c]) for r, c, _ in out]
        E = [m.T_ref_cur for _, _, m in out]
        rot = np.array([rotation_angle_deg(t[:3, :3].T @ e[:3, :3]) for t, e in zip(T_gt, E)])
        axes = np.degrees([log_so3(t[:3, :3].T @ e[:3, :3]) for t, e in zip(T_gt, E)])
        dt = np.array([e[:3, 3] - t[:3, 3] for t, e in zip(T_gt, E)])
        dirn = np.array([direction_deg(e[:3, 3], t[:3, 3]) for t, e in zip(T_gt, E)])
        ground = np.array([direction_deg(e[[0, 2], 3], t[[0, 2], 3]) for t, e in zip(T_gt, E)])
        print(
            f"rotation error median {np.median(rot):.3f} deg, p90 {np.percentile(rot, 90):.3f}; about x (pitch), y (yaw), z (roll) "
            + ", ".join(f"{v:+.3f}" for v in np.median(axes, axis=0))
            + " deg"
        )
        print(
            f"translation error median {np.median(np.linalg.norm(dt, axis=1)):.2f} m; x (right), y (down), z (forward) "
            + ", ".join(f"{v:+.2f}" for v in np.median(dt, axis=0))
            + " m"
        )
        print(
            f"  the truth's height offset of the revisit median {np.median([t[1, 3] for t in T_gt]):+.2f} m, the estimate's "
            f"{np.median([e[1, 3] for e in E]):+.2f} m (same road, same car)"
        )
        print(
            f"direction error median {np.median(dirn):.2f} deg, p90 {np.percentile(dirn, 90):.2f}; in the ground plane (x, z) median {np.median(ground):.2f} deg"
        )
        ref = image_reference()  # where the first pass's images put the second: the truth the images agree with
        seen = [(np.linalg.solve(G[r], ref[c]), m.T_ref_cur) for r, c, m in out if c in ref]
        if seen:
            rot_i = np.array([rotation_angle_deg(t[:3, :3].T @ e[:3, :3]) for t, e in seen])
            dt_i = np.array([e[:3, 3] - t[:3, 3] for t, e in seen])
            print(
                f"against the image reference (revisit_reference.py, {len(seen)} pairs): rotation error median {np.median(rot_i):.3f} deg, "
                f"p90 {np.percentile(rot_i, 90):.3f}; translation error median {np.median(np.linalg.norm(dt_i, axis=1)):.2f} m, "
                "x, y, z " + ", ".join(f"{v:+.2f}" for v in np.median(dt_i, axis=0)) + " m"
            )
        by_cur: dict[int, list] = {}
        for r, c, m in out:
            by_cur.setdefault(c, []).append((r, m.T_ref_cur))
        agree_r, agree_t = [], []
        for lst in by_cur.values():
            r0, T0 = lst[0]
            for r, T in lst[1:]:
                T_in0 = np.linalg.solve(G[r0], G[r]) @ T  # the same current pose through the first pass's truth
                agree_r.append(rotation_angle_deg(T0[:3, :3].T @ T_in0[:3, :3]))
                agree_t.append(float(np.linalg.norm(T0[:3, 3] - T_in0[:3, 3])))
        if agree_r:
            print(
                f"agreement between references of one frame ({len(agree_r)} pairs): rotation median {np.median(agree_r):.3f} deg, "
                f"position {np.median(agree_t):.3f} m"
            )
    false = [
        (r, c) for c in range(1560, 1661, 2) for r in stored if r <= 230 and 10 < np.linalg.norm(G[r][:3, 3] - G[c][:3, 3]) <= 40
    ]
    ver = [m for m in (verify(c, r) for r, c in false) if m is not None]
    near = sum(np.linalg.norm(m.T_ref_cur[:3, 3]) <= MAX_DISTANCE_M for m in ver)
    print(f"false pairs (10-40 m apart): {len(false)}, verified {len(ver)}, within MAX_DISTANCE_M {MAX_DISTANCE_M:g} m: {near}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
