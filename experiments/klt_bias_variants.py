"""KLT row bias by image band for ways of removing the LK window bias (tracking_bias.py's companion).

One-frame pairs of the rendered KITTI 00 path; LK starts at the exact position plus 0.3 px noise
(a stand-in for the front end's constant-velocity prediction). Variants: the plain 11 px fit; the
default 11 px + 7 px linear extrapolation in the window's second moment (w^2 - 1) / 12; the 11 px
fit re-converged at level 0 first; quadratic fits through 11/7/5 and 11/9/7; linear 11/5 and 11/9.
Prints median / mean (sd, standard error) of the row error in px per band (positive = too low).

    python experiments/klt_bias_variants.py [--trajectory ../shared/data/kitti_gt/00.txt] [--frames 0:400] [--every 40]
"""

import argparse

import cv2
import numpy as np

from snaps_graph.frontend import depth as depth_mod
from snaps_graph.frontend import features as feat
from snaps_graph.synth import SyntheticSequence, load_trajectory

BANDS = ((0, 180), (180, 220), (220, 280), (280, 400))


def lk(a, b, p0, p1, w, lev, eps, use_init=True):
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, eps)
    q, st, _ = cv2.calcOpticalFlowPyrLK(
        a,
        b,
        np.ascontiguousarray(p0, np.float32).reshape(-1, 1, 2),
        None if p1 is None else np.ascontiguousarray(p1, np.float32).reshape(-1, 1, 2),
        winSize=(w, w),
        maxLevel=lev,
        criteria=crit,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW if p1 is not None else 0,
    )
    return q.reshape(-1, 2).astype(np.float64), st.reshape(-1) == 1


m = feat.window_moment


def quadratic(ws, ps):
    """Lagrange extrapolation of three fits (windows ``ws``) to a zero second moment."""
    ms = np.array([m(w) for w in ws])
    L = [np.prod([(0 - ms[k]) / (ms[i] - ms[k]) for k in range(3) if k != i]) for i in range(3)]
    return L[0] * ps[0] + L[1] * ps[1] + L[2] * ps[2]


def variants(a, b, uv, guess):
    out = {}
    p11, ok = lk(a, b, uv, guess, 11, 3, 0.01)
    out["plain11"] = (p11, ok)
    p7, s7 = lk(a, b, uv, p11, 7, 0, 0.001)
    ok7 = ok & s7 & np.all(np.abs(p11 - p7) <= 0.5, 1)
    cur = p11.copy()
    cur[ok7] -= m(11) / (m(11) - m(7)) * (p11 - p7)[ok7]
    out["lin 11/7 (default)"] = (cur, ok)
    p11c, s11 = lk(a, b, uv, p11, 11, 0, 0.001)
    out["plain11 reconverged"] = (p11c, ok & s11)
    p7c, s7c = lk(a, b, uv, p11c, 7, 0, 0.001)
    okc = ok & s11 & s7c & np.all(np.abs(p11c - p7c) <= 0.5, 1)
    c2 = p11c.copy()
    c2[okc] -= m(11) / (m(11) - m(7)) * (p11c - p7c)[okc]
    out["lin 11c/7"] = (c2, ok & s11)
    p5, s5 = lk(a, b, uv, p7c, 5, 0, 0.001)
    okq = okc & s5 & np.all(np.abs(p11c - p5) <= 0.5, 1)
    c3 = p11c.copy()
    c3[okq] = quadratic((11, 7, 5), (p11c, p7c, p5))[okq]
    out["quad 11c/7/5"] = (c3, ok & s11)
    p9, s9 = lk(a, b, uv, p11c, 9, 0, 0.001)
    ok9 = okc & s9 & np.all(np.abs(p11c - p9) <= 0.5, 1)
    c4 = p11c.copy()
    c4[ok9] = quadratic((11, 9, 7), (p11c, p9, p7c))[ok9]
    out["quad 11c/9/7"] = (c4, ok & s11)
    p5b, s5b = lk(a, b, uv, p11, 5, 0, 0.001)
    ok5 = ok & s5b & np.all(np.abs(p11 - p5b) <= 0.5, 1)
    c5 = p11.copy()
    c5[ok5] -= m(11) / (m(11) - m(5)) * (p11 - p5b)[ok5]
    out["lin 11/5"] = (c5, ok)
    p9b, s9b = lk(a, b, uv, p11, 9, 0, 0.001)
    ok9b = ok & s9b & np.all(np.abs(p11 - p9b) <= 0.5, 1)
    c9 = p11.copy()
    c9[ok9b] -= m(11) / (m(11) - m(9)) * (p11 - p9b)[ok9b]
    out["lin 11/9"] = (c9, ok)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectory", default="../shared/data/kitti_gt/00.txt", help="KITTI poses file to render along")
    ap.add_argument("--frames", default="0:400")
    ap.add_argument("--every", type=int, default=40, help="one frame pair every this many frames")
    args = ap.parse_args()
    poses, times = load_trajectory(args.trajectory, args.frames)
    every = args.every
    seq = SyntheticSequence(poses, width=1241, height=376, seed=0, times=times)
    cam = seq.camera
    rng = np.random.default_rng(0)
    acc = {}
    for i in range(0, len(seq) - 1, every):
        f0 = seq.render(i)
        uv = feat.detect_corners(f0.left, feat.KLT.features, feat.KLT, avoid=np.zeros((0, 2), np.float32))
        z = depth_mod.sample_depth(f0.depth, uv)
        uv, z = uv[z > 0], z[z > 0]
        P = np.c_[(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z, np.ones(len(z))]
        f1 = seq.render(i + 1, with_depth=False)
        Q = (np.linalg.solve(seq.gt_poses[i + 1], seq.gt_poses[i]) @ P.T).T
        true = np.c_[cam.fx * Q[:, 0] / Q[:, 2] + cam.cx, cam.fy * Q[:, 1] / Q[:, 2] + cam.cy]
        for gname, guess in (("start true+N(0.3)", true + rng.normal(0, 0.3, true.shape)),):
            for name, (p, ok) in variants(f0.left, f1.left, uv, guess).items():
                e = p[:, 1] - true[:, 1]
                keep = ok & (np.abs(e) < 2)
                acc.setdefault((gname, name), []).append(np.c_[uv[keep, 1], e[keep]])
    for (g, name), parts in acc.items():
        a = np.concatenate(parts)
        row = []
        for lo, hi in BANDS:
            s = (a[:, 0] >= lo) & (a[:, 0] < hi)
            e = a[s, 1]
            row.append(f"{np.median(e):+.4f}/{e.mean():+.4f}({e.std():.3f}, sem {e.std() / np.sqrt(s.sum()):.4f})")
        print(f"{g:<18} {name:<22} " + "  ".join(row))
    print("bands", BANDS, " median/mean(sd) px")


if __name__ == "__main__":
    main()
