"""What the chain's heading factor does inside one local-BA solve.

Runs the front end on a sequence with ground truth. At every keyframe that has a chain factor
the window is solved twice from the same state: once without the factor (the result thrown
away) and once with it (the run continues with that one). For each solve it compares, against
ground truth, (a) the newest keyframe relative to the window's gauge (oldest) keyframe, the pose
handed out, and (b) the second keyframe relative to the gauge, the step the next window inherits
(full windows only). Rotation in millidegrees about the camera's x (pitch), y (yaw), z (roll),
translation in mm. It also prints how the factor's yaw change moves the other components
(slope and correlation over the solves).

    python experiments/chain_ab.py results/data/street00_1000 [--frames A:B] [--set frontend.key=value ...]
"""

from __future__ import annotations

import copy

import numpy as np
from _common import frontend_from_args

from snaps_graph.frontend import StereoOdometry, local_ba
from snaps_graph.geometry import inv, log_so3


def main() -> None:
    seq, fcfg = frontend_from_args(__doc__.split("\n")[0])
    gt = seq.gt_poses
    rec: list[np.ndarray] = []
    orig = local_ba.LocalBundleAdjuster.add_keyframe

    def err(G: np.ndarray, P0: np.ndarray, P1: np.ndarray) -> np.ndarray:
        d = inv(G) @ (inv(P0) @ P1)
        return np.r_[np.degrees(log_so3(d[:3, :3])) * 1e3, d[:3, 3] * 1e3]

    def hook(self, key, pose, ids, uv, disp, chain=None):
        if chain is None or not self.kfs:
            return orig(self, key, pose, ids, uv, disp, chain)
        saved, stats, off = copy.deepcopy(self.kfs), copy.deepcopy(self.stats), self.offset_px
        orig(self, key, pose, ids, uv, disp, None)
        alt = [k.pose.copy() for k in self.kfs]
        self.kfs, self.stats, self.offset_px = saved, stats, off
        out = orig(self, key, pose, ids, uv, disp, chain)
        k = [f.key for f in self.kfs]
        P = [f.pose for f in self.kfs]
        Gn, G1 = inv(gt[k[0]]) @ gt[k[-1]], inv(gt[k[0]]) @ gt[k[1]]
        full = float(len(k) == self.window)
        rec.append(np.r_[err(Gn, alt[0], alt[-1]), err(Gn, P[0], P[-1]), err(G1, alt[0], alt[1]), err(G1, P[0], P[1]), full])
        return out

    local_ba.LocalBundleAdjuster.add_keyframe = hook  # type: ignore[method-assign]
    with StereoOdometry(seq.camera, fcfg) as vo:
        for f in seq:
            vo.process(f)
    R = np.array(rec)
    np.set_printoptions(precision=3, suppress=True)
    print(f"{len(R)} solves with a chain factor; rot x y z (mdeg), trans x y z (mm)")
    F = R[:, -1] > 0
    for title, a, b in (("newest vs gauge", R[:, 0:6], R[:, 6:12]), ("second vs gauge", R[F, 12:18], R[F, 18:24])):
        d = b - a
        print(title)
        print("  without factor  mean", a.mean(0), " rms", np.sqrt((a**2).mean(0)))
        print("  with factor     mean", b.mean(0), " rms", np.sqrt((b**2).mean(0)))
        print("  difference      mean", d.mean(0), " sem", d.std(0) / np.sqrt(len(d)))
    d = R[:, 6:12] - R[:, 0:6]
    for i, name in ((0, "pitch"), (2, "roll"), (3, "sideways"), (4, "vertical")):
        slope = np.polyfit(d[:, 1], d[:, i], 1)[0]
        print(f"newest: d {name} / d yaw slope {slope:+.3f}, correlation {np.corrcoef(d[:, 1], d[:, i])[0, 1]:+.2f}")


if __name__ == "__main__":
    main()
