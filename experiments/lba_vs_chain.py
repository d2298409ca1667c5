"""Does the keyframe local BA improve the step into each keyframe? Against the frame-to-frame chain.

Runs the front end on a sequence with ground truth and records, at every local-BA keyframe, the
pose the frame-to-frame chain gave it (the BA's input) and the pose the BA handed back. For each
pair of consecutive keyframes it prints the error of the step from the previous keyframe's
handed-back pose to (a) the chain's pose and (b) the BA's pose, against the ground-truth step:
mean and RMS per axis (rotation in millidegrees about the camera's x = pitch, y = yaw, z = roll;
translation in mm), and the RMS yaw and sideways (x) error by the ground-truth yaw of the step.

    python experiments/lba_vs_chain.py results/demo/sequence [--frames A:B] [--set frontend.local_ba=false ...]
"""

from __future__ import annotations

import numpy as np
from _common import frontend_from_args

from snaps_graph.frontend import StereoOdometry, local_ba
from snaps_graph.geometry import inv, log_so3


def _rotvec_mdeg(R: np.ndarray) -> np.ndarray:
    return np.degrees(log_so3(R)) * 1e3


def main() -> None:
    seq, fcfg = frontend_from_args(__doc__.split("\n")[0])
    gt = seq.gt_poses
    rec: list[tuple[int, np.ndarray, np.ndarray]] = []
    orig = local_ba.LocalBundleAdjuster.add_keyframe

    def hook(self, key, pose, ids, uv, disp, chain=None):
        out = orig(self, key, pose, ids, uv, disp, chain)
        rec.append((key, pose.copy(), out.copy()))
        return out

    local_ba.LocalBundleAdjuster.add_keyframe = hook  # type: ignore[method-assign]
    with StereoOdometry(seq.camera, fcfg) as vo:
        for f in seq:
            vo.process(f)

    def err(Ta, Tb, ka, kb):
        d = inv(inv(gt[ka]) @ gt[kb]) @ (inv(Ta) @ Tb)
        return np.r_[_rotvec_mdeg(d[:3, :3]), d[:3, 3] * 1e3]

    pairs = list(zip(rec[:-1], rec[1:]))
    ec = np.array([err(o0, i1, k0, k1) for (k0, _, o0), (k1, i1, _) in pairs])
    eb = np.array([err(o0, o1, k0, k1) for (k0, _, o0), (k1, _, o1) in pairs])
    gy = np.array([_rotvec_mdeg((inv(gt[k0]) @ gt[k1])[:3, :3])[1] for (k0, _, _), (k1, _, _) in pairs])
    np.set_printoptions(precision=2, suppress=True)
    print(f"{len(pairs)} keyframe steps; axes: rot x y z (mdeg), trans x y z (mm)")
    for name, e in (("chain", ec), ("local BA", eb)):
        print(f"{name:9s} mean {e.mean(0)}  rms {np.sqrt((e**2).mean(0))}")
    ay = np.abs(gy)
    for lo, hi in ((0, 2000), (2000, 4000), (4000, 6000), (6000, 10**6)):
        m = (ay >= lo) & (ay < hi)
        if m.sum() >= 3:
            r = {(n, i): float(np.sqrt((e[m, i] ** 2).mean())) for n, e in (("c", ec), ("b", eb)) for i in (1, 3)}
            print(
                f"|gt yaw| {lo / 1e3:.0f}-{min(hi, 99000) / 1e3:.0f} deg per step (n {m.sum()}): rms yaw chain {r['c', 1]:.1f} "
                f"BA {r['b', 1]:.1f} mdeg; rms sideways chain {r['c', 3]:.1f} BA {r['b', 3]:.1f} mm"
            )


if __name__ == "__main__":
    main()
