"""How accurate is a verified loop's relative pose? Every revisit pair against ground truth (issue 12).

For every ``--stride``-th frame N of a sequence, the stored reference j (every
``loop_reference_every``-th frame, N - j >= ``loop.frame_distance``) nearest to it in the
ground truth, if within ``--max-dist`` m and ``loop.max_yaw_deg``, is verified as the pipeline
does (``verify_nearby`` on the loop features, neighbours carried by the VO poses, the front end's disparity offset from the cached
VO of ``loop_verification.py``), once per ``--variant NAME:section.key=value,...``. Prints, per
sequence and variant, how many pairs verified and the translation / rotation errors of T_ref_cur
against the ground truth (median, 90th percentile, max), on the pairs every variant verified.

    python experiments/loop_pose_accuracy.py --seq /work/data/seq07_street \\
        --variant base "sba:frontend.loop_pose_refine=stereo_ba"
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, md_table
from loop_verification import apply, cached_vo

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.frontend.loop_features import LoopFeatureBank, verify_nearby
from snaps_graph.geometry import rotation_angle_deg, wrap_deg, yaw_deg


def pairs_of(gt: np.ndarray, cfg: Config, stride: int, max_dist: float) -> list[tuple[int, int]]:
    e, M = cfg.frontend.loop_reference_every, cfg.loop.frame_distance
    pos = gt[:, :3, 3]
    yaws = yaw_deg(gt)
    out = []
    for k in range(M, len(gt), stride):
        js = np.arange(0, k - M + 1, e)
        if len(js) == 0:
            continue
        d = np.linalg.norm(pos[js] - pos[k], axis=1)
        dy = np.abs(wrap_deg(yaws[js] - yaws[k]))
        ok = (d <= max_dist) & (dy <= cfg.loop.max_yaw_deg)
        if ok.any():
            out.append((k, int(js[ok][np.argmin(d[ok])])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", nargs="+", required=True)
    ap.add_argument("--variant", nargs="+", default=["base"], help="NAME[:section.key=value,...]")
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--max-dist", type=float, default=8.0)
    ap.add_argument("--base", nargs="*", default=[], help="section.key=value for every variant (e.g. loop.frame_distance=4)")
    ap.add_argument("--cache", default=str(RESULTS / "vo_cache_lv"))
    ap.add_argument("--out", default=str(RESULTS / "loop_pose_accuracy.md"))
    args = ap.parse_args()
    base = Config()
    apply(base, args.base)
    variants = []
    for spec in args.variant:
        name, _, sets = spec.partition(":")
        cfg = copy.deepcopy(base)
        apply(cfg, [s for s in sets.split(",") if s])
        variants.append((name, cfg))
    rows = []
    for seq_arg in args.seq:
        seq_dir = Path(seq_arg)
        seq = KittiSequence(seq_dir)
        vo = cached_vo(seq, seq_dir, base, Path(args.cache), None)
        gt = seq.gt_poses
        pairs = pairs_of(gt, base, args.stride, args.max_dist)
        banks = {name: LoopFeatureBank(seq.camera, cfg.frontend, background=False) for name, cfg in variants}
        errs: dict[str, list] = {name: [] for name, _ in variants}
        V = np.array([vo[int(i)].pose for i in seq.indices])
        e = base.frontend.loop_reference_every
        n_nb = max(cfg.frontend.loop_verify_neighbours for _, cfg in variants)
        added: dict[str, set[int]] = {name: set() for name, _ in variants}
        t0 = time.perf_counter()
        for k, j in pairs:
            k_max = k - base.loop.frame_distance
            frame = seq[k]
            G = np.linalg.solve(gt[j], gt[k])
            off = float(vo[int(seq.indices[k])].disparity_offset_px)
            for name, cfg in variants:
                bank = banks[name]
                for jj in range(j - n_nb * e, j + n_nb * e + 1, e):
                    if 0 <= jj <= k_max and jj not in added[name]:
                        bank.add(jj, seq[jj], float(vo[int(seq.indices[jj])].disparity_offset_px))
                        added[name].add(jj)
                cur = bank.query(k, frame)
                m = verify_nearby(
                    bank, j, k_max, lambda kn, j=j, V=V: np.linalg.solve(V[j], V[kn]), cur, frame, seq.camera, cfg.frontend, off
                )
                if m is None:
                    errs[name].append(None)
                    continue
                te = float(np.linalg.norm(m.T_ref_cur[:3, 3] - G[:3, 3]))
                re = rotation_angle_deg(m.T_ref_cur[:3, :3].T @ G[:3, :3])
                ye = abs(wrap_deg(yaw_deg(m.T_ref_cur) - yaw_deg(G)))
                sig_t = float(np.sqrt(np.trace(m.cov[3:, 3:])))
                errs[name].append((te, re, ye, float(np.linalg.norm(G[:3, 3])), m.inliers, sig_t))
        both = [i for i in range(len(pairs)) if all(errs[n][i] is not None for n, _ in variants)]
        print(
            f"{seq_dir.name}: {len(pairs)} pairs within {args.max_dist} m, {len(both)} verified by every variant [{time.perf_counter() - t0:.0f} s]"
        )
        for name, _ in variants:
            err = np.array([errs[name][i][:6] for i in both]) if both else np.zeros((0, 6))
            n_ver = sum(x is not None for x in errs[name])
            if len(err) == 0:
                rows.append([seq_dir.name, name, f"{n_ver}/{len(pairs)}", "", "", "", "", ""])
                continue

            def q(c: int, err: np.ndarray = err) -> str:
                return f"{np.median(err[:, c]):.3f} / {np.percentile(err[:, c], 90):.3f} / {err[:, c].max():.3f}"

            rows.append(
                [
                    seq_dir.name,
                    name,
                    f"{n_ver}/{len(pairs)}",
                    q(0),
                    q(1),
                    q(2),
                    f"{np.median(err[:, 3]):.1f}",
                    f"{np.median(err[:, 4]):.0f}, sd_t {np.median(err[:, 5]):.3f}",
                ]
            )
            print("  " + " | ".join(rows[-1][1:]), flush=True)
    header = [
        "sequence",
        "variant",
        "verified / pairs",
        "t error m: median / p90 / max",
        "rotation error deg",
        "yaw error deg",
        "median distance m",
        "median inliers, cov sd_t m",
    ]
    text = (
        "# Loop pose accuracy\n\nCommand: `python experiments/loop_pose_accuracy.py --seq "
        + " ".join(args.seq)
        + " --variant "
        + " ".join(f'"{v}"' for v in args.variant)
        + (" --base " + " ".join(args.base) if args.base else "")
        + f" --stride {args.stride} --max-dist {args.max_dist}`\n\n(errors on the pairs every variant verified)\n\n"
        + md_table(header, rows)
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
