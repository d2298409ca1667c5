"""Where the first pass's images put the second pass on the real revisit: a reference for the
two-session figures that the images agree with, unlike KITTI's ground truth there.

The ground truth of ``../shared/data/kitti00_loop`` is consistent within each pass, but between the
passes it contradicts the images: its relative pose between a second-pass frame and the nearest
first-pass frame leaves the images' feature matches a far larger epipolar (Sampson) error than
the pose the images fit (``epipolar_check`` prints both; docs/odometry-input.md). So a second
session's agreement with the first cannot be judged against it at the half-metre level.

The reference: for each second-pass frame f in the revisit, SIFT points of the nearest first-pass
frame j are triangulated from first-pass frame pairs (j - g, j + g) at their ground-truth poses
(one pass: consistent), and f's pose in the ground truth's world is solved by PnP (RANSAC, then
Levenberg-Marquardt) against them. OpenCV throughout: none of the pipeline's own verification code.
Its own uncertainty is printed as the spread between two choices of the pairs.

    python benchmarks/revisit_reference.py                  # the epipolar check, the reference against the GT
    python benchmarks/revisit_reference.py --loops RUN ...  # the runs' loops against both
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from snaps_graph.camera import StereoCamera
from snaps_graph.trajectory_io import read_poses

DATA = ROOT.parent / "shared" / "data" / "kitti00_loop"
IMAGES = DATA / "sequences" / "00" / "image_0"
FIRST_PASS = np.arange(100, 231)
SECOND_PASS = range(1573, 1642)
GAPS = (2, 3, 4, 5)  # first-pass pairs (j - g, j + g) whose triangulated points are pooled
MIN_PARALLAX_DEG = 1.0
MAX_DEPTH_M = 60.0
REPROJECTION_PX = 1.0
MIN_INLIERS = 30
CACHE = ROOT / "results" / "revisit_reference"


def camera() -> np.ndarray:
    """The left camera's K, read as every run reads calib.txt."""
    return StereoCamera.from_calib_file(DATA / "sequences" / "00" / "calib.txt").K


def nearest_first(gt: np.ndarray, f: int) -> int:
    """The first-pass frame nearest to frame ``f`` by the ground truth."""
    return int(FIRST_PASS[np.argmin(np.linalg.norm(gt[FIRST_PASS][:, :3, 3] - gt[f][:3, 3], axis=1))])


class Features:
    """SIFT keypoints and descriptors per frame, computed once."""

    def __init__(self) -> None:
        self.sift = cv2.SIFT_create(4000)
        self.cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        if f not in self.cache:
            img = cv2.imread(str(IMAGES / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
            kp, desc = self.sift.detectAndCompute(img, None)
            self.cache[f] = (np.array([k.pt for k in kp], np.float64).reshape(-1, 2), desc)
        return self.cache[f]


def ratio_matches(d1: np.ndarray, d2: np.ndarray, ratio: float) -> np.ndarray:
    pairs = cv2.BFMatcher().knnMatch(d1, d2, k=2)
    return np.array(
        [(m.queryIdx, m.trainIdx) for m, n in (p for p in pairs if len(p) == 2) if m.distance < ratio * n.distance]
    ).reshape(-1, 2)


def triangulated(feats: Features, gt: np.ndarray, K: np.ndarray, j1: int, j2: int) -> tuple[np.ndarray, np.ndarray]:
    """(points in the world, descriptors) of frame j1's keypoints matched in j2, both at their GT poses."""
    (u1, d1), (u2, d2) = feats(j1), feats(j2)
    m = ratio_matches(d1, d2, 0.75)
    if len(m) < 8:
        return np.zeros((0, 3)), np.zeros((0, 128), np.float32)
    X = cv2.triangulatePoints(K @ np.linalg.inv(gt[j1])[:3], K @ np.linalg.inv(gt[j2])[:3], u1[m[:, 0]].T, u2[m[:, 1]].T)
    X = (X[:3] / X[3]).T
    ok = np.ones(len(X), bool)
    for j, u in ((j1, u1[m[:, 0]]), (j2, u2[m[:, 1]])):
        Tc = np.linalg.inv(gt[j])
        Xc = X @ Tc[:3, :3].T + Tc[:3, 3]
        z = np.maximum(Xc[:, 2], 1e-9)
        uv = np.column_stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]])
        ok &= (Xc[:, 2] > 2.0) & (Xc[:, 2] < MAX_DEPTH_M) & (np.linalg.norm(uv - u, axis=1) < REPROJECTION_PX)
    r1, r2 = X - gt[j1][:3, 3], X - gt[j2][:3, 3]
    cos = np.sum(r1 * r2, 1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-12)
    ok &= cos < np.cos(np.radians(MIN_PARALLAX_DEG))
    return X[ok], d1[m[ok, 0]]


def locate(feats: Features, gt: np.ndarray, K: np.ndarray, f: int, gaps: tuple[int, ...]) -> np.ndarray | None:
    """Second-pass frame f's T_world_cam (the GT's world) from the nearest first-pass frame's
    triangulated points, or None with fewer than MIN_INLIERS."""
    j = nearest_first(gt, f)
    parts = [triangulated(feats, gt, K, max(j - g, FIRST_PASS[0]), min(j + g, FIRST_PASS[-1])) for g in gaps]
    X = np.concatenate([p[0] for p in parts])
    desc = np.concatenate([p[1] for p in parts])
    u, d = feats(f)
    if len(X) < MIN_INLIERS:
        return None
    m = ratio_matches(desc, d, 0.8)
    if len(m) < MIN_INLIERS:
        return None
    obj, img = X[m[:, 0]], u[m[:, 1]]
    cv2.setRNGSeed(0)
    ok, rv, tv, inl = cv2.solvePnPRansac(
        obj, img, K, None, reprojectionError=REPROJECTION_PX, iterationsCount=2000, confidence=0.999, flags=cv2.SOLVEPNP_EPNP
    )
    if not ok or inl is None or len(inl) < MIN_INLIERS:
        return None
    inl = inl.ravel()
    rv, tv = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rv, tv)
    R, _ = cv2.Rodrigues(rv)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, (-R.T @ tv).ravel()
    return T


def image_reference(gaps: tuple[int, ...] = GAPS) -> dict[int, np.ndarray]:
    """Second-pass frame -> T_world_cam where the first pass's images put it (cached in results/)."""
    key = hashlib.sha256(repr((gaps, MIN_PARALLAX_DEG, MAX_DEPTH_M, REPROJECTION_PX, MIN_INLIERS)).encode()).hexdigest()[:12]
    path = CACHE / f"reference_{key}.npz"
    if path.is_file():
        z = np.load(path)
        return dict(zip(z["frames"].tolist(), z["poses"]))
    gt, K, feats = read_poses(DATA / "poses" / "00.txt"), camera(), Features()
    ref = {f: T for f in SECOND_PASS if (T := locate(feats, gt, K, f, gaps)) is not None}
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(path, frames=np.array(sorted(ref)), poses=np.array([ref[f] for f in sorted(ref)]).reshape(-1, 4, 4))
    return ref


def consistent_truth(gt: np.ndarray, reference: dict[int, np.ndarray], frames: range = range(1540, 1661)) -> np.ndarray:
    """The ground truth with ``frames`` (the second pass) moved to where the images put them: the
    correction inv(gt_f) @ reference_f as a rotation vector and an offset, each component fitted by
    a quadratic in the frame number over the located frames (smooth: the ground truth's error is,
    and a per-frame reference's noise would become odometry noise), held at its ends beyond them."""
    fs = np.array(sorted(reference))
    D = [np.linalg.inv(gt[f]) @ reference[f] for f in fs]
    comp = np.array([np.r_[Rotation.from_matrix(d[:3, :3]).as_rotvec(), d[:3, 3]] for d in D])
    mid = float(fs.mean())
    coef = [np.polyfit(fs - mid, comp[:, c], 2) for c in range(6)]
    out = gt.copy()
    for f in frames:
        v = np.array([np.polyval(c, np.clip(f, fs[0], fs[-1]) - mid) for c in coef])
        C = np.eye(4)
        C[:3, :3], C[:3, 3] = Rotation.from_rotvec(v[:3]).as_matrix(), v[3:]
        out[f] = gt[f] @ C
    return out


def sampson(K: np.ndarray, T_2_1: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances (px) of matches x1 <-> x2 under relative pose T_2_1 (X_2 = R X_1 + t)."""
    t = T_2_1[:3, 3] / np.linalg.norm(T_2_1[:3, 3])
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T_2_1[:3, :3]
    F = np.linalg.inv(K).T @ E @ np.linalg.inv(K)
    h1, h2 = np.column_stack([x1, np.ones(len(x1))]), np.column_stack([x2, np.ones(len(x2))])
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    return np.abs(np.sum(h2 * Fx1, 1)) / np.sqrt(Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2)


def epipolar_check(frames: range = range(1577, 1636, 6)) -> None:
    """Per second-pass frame and its nearest first-pass frame: the median Sampson error of the
    images' matches (RANSAC inliers of their own essential matrix) under the pose the images fit,
    under the ground truth's, and under the image reference's."""
    gt, K, feats, ref = read_poses(DATA / "poses" / "00.txt"), camera(), Features(), image_reference()
    print("frame  first | matches | median Sampson px: images' own fit   ground truth   reference")
    for f in frames:
        j = nearest_first(gt, f)
        (u1, d1), (u2, d2) = feats(j), feats(f)
        m = ratio_matches(d1, d2, 0.8)
        x1, x2 = u1[m[:, 0]], u2[m[:, 1]]
        E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, 1.0)
        inl = mask.ravel() > 0
        x1, x2 = x1[inl], x2[inl]
        _, R, t, _ = cv2.recoverPose(E[:3], np.ascontiguousarray(x1), np.ascontiguousarray(x2), K)
        own = np.eye(4)
        own[:3, :3], own[:3, 3] = R, t.ravel()
        cols = [np.median(sampson(K, own, x1, x2)), np.median(sampson(K, np.linalg.inv(gt[f]) @ gt[j], x1, x2))]
        cols.append(np.median(sampson(K, np.linalg.inv(ref[f]) @ gt[j], x1, x2)) if f in ref else float("nan"))
        print(f"{f:5d} {j:6d} | {len(x1):7d} | {cols[0]:26.2f} {cols[1]:14.2f} {cols[2]:11.2f}")


def loop_errors(runs: list[Path]) -> None:
    """The verified loops from the second pass to the first in ``runs`` (results folders of runs
    over the revisit, a prior's loops included): their relative pose against the reference's and
    against the ground truth's, RMS per axis (rotation vector and offset in the first-pass camera)."""
    gt, ref = read_poses(DATA / "poses" / "00.txt"), image_reference()
    errs: dict[str, list[np.ndarray]] = {"reference": [], "ground truth": []}
    for run in runs:
        for line in (run / "loops.jsonl").read_text().splitlines():
            lp = json.loads(line) if line.strip() else {}
            f, j = lp.get("frame"), lp.get("reference")
            if f not in ref or j not in FIRST_PASS or not lp.get("verified"):
                continue
            T = np.eye(4)
            T[:3, :4] = np.array(lp["T_ref_cur"]).reshape(3, 4)
            for name, truth in (("reference", ref[f]), ("ground truth", gt[f])):
                E = np.linalg.solve(np.linalg.inv(gt[j]) @ truth, T)
                errs[name].append(np.r_[Rotation.from_matrix(E[:3, :3]).as_rotvec(), E[:3, 3]])
    for name, e in errs.items():
        if not e:
            sys.exit("no verified loop from the second pass to the first in those runs")
        a = np.array(e)
        rms = np.sqrt((a**2).mean(0))
        print(
            f"{len(a)} loops against the {name}: RMS rotation (x, y, z) {rms[0]:.4f} {rms[1]:.4f} {rms[2]:.4f} rad,"
            f" offset (x right, y down, z ahead) {rms[3]:.3f} {rms[4]:.3f} {rms[5]:.3f} m; mean offset {a[:, 3].mean():+.3f} {a[:, 4].mean():+.3f} {a[:, 5].mean():+.3f} m"
        )


def main() -> None:
    if not IMAGES.is_dir():
        sys.exit(f"{IMAGES}: not found (the real revisit, ../shared/data/kitti00_loop)")
    if len(sys.argv) > 2 and sys.argv[1] == "--loops":
        loop_errors([Path(p) for p in sys.argv[2:]])
        return
    epipolar_check()
    gt = read_poses(DATA / "poses" / "00.txt")
    ref, alt = image_reference(), image_reference((3,))
    print(f"\nreference: {len(ref)} of {len(SECOND_PASS)} second-pass frames located")
    print("frame | reference - ground truth, in the camera (x right, y down, z ahead): m          deg (rotation vector)")
    for f in sorted(ref)[::4]:
        d = np.linalg.inv(gt[f]) @ ref[f]
        r = np.degrees(Rotation.from_matrix(d[:3, :3]).as_rotvec())
        print(f"{f:5d} | {d[0, 3]:+6.2f} {d[1, 3]:+6.2f} {d[2, 3]:+6.2f}      {r[0]:+6.2f} {r[1]:+6.2f} {r[2]:+6.2f}")
    fit = consistent_truth(gt, ref)
    res = np.array([np.linalg.norm(fit[f][:3, 3] - ref[f][:3, 3]) for f in sorted(ref)])
    print(
        f"the smooth fit through it (consistent_truth, --truth images): residual mean {res.mean():.3f} m, max {res.max():.3f} m"
    )
    common = sorted(set(ref) & set(alt))
    spread = np.array([np.linalg.norm(ref[f][:3, 3] - alt[f][:3, 3]) for f in common])
    print(
        f"the reference's own spread (pairs {GAPS} pooled against (3,) alone, {len(common)} frames): mean {spread.mean():.3f} m, max {spread.max():.3f} m"
    )


if __name__ == "__main__":
    main()
