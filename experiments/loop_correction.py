"""What should SNAPS's real-time correction (eq. 6) correct? Measured on rendered KITTI paths.

Runs the front end once per sequence (cached on disk, ``results/experiments/vo_cache``), then
replays SNAPS over the cached VO with each eq. 6 variant, detection unchanged:

- ``paper``: target p_ref, weight Q, positions only (the paper; ``use_verified_offset = false``,
  ``correction_weight = "q"``);
- ``xyz``: target p_ref + R_ref t_ref_cur (verified), weight 1, the three position components;
- ``ground``: the same, ground-plane components only (the reference's height error stays out);
- ``ground_yaw``: ground plane, plus the window turned about the vertical to the verified heading;

Prints and writes (results/experiments/loop_correction.md) per sequence and variant: the 3D,
horizontal and vertical mean deviation and ATE of the heuristic trajectory against VO, loops and
false loops, the loop evaluation of the run (max recall at 100 % precision with and without
verification), and with ``--batch`` the batch refinement and the loop oracle beside it.

    python experiments/loop_correction.py --seq results/data/street07 results/data/street00 \
        [--variants xyz ground ground_yaw] [--batch] [--verify-all]
"""

from __future__ import annotations

import argparse
import copy
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the loop-closure instruments
from _common import RESULTS, VOCache, md_table, replay, vo_cache
from _loop_research import SnapsLoopCloser, VerifyAllCloser, policy, use_closer

from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.loops import LoopEvalSettings, evaluate_loops
from snaps_graph.evaluation.metrics import evaluate
from snaps_graph.evaluation.oracle import loop_oracle
from snaps_graph.runner import write_results

VARIANTS = {
    "paper": dict(use_verified_offset=False, correction_weight="q", correction_axes="xyz", correction_rotation="none"),
    "xyz": dict(correction_axes="xyz", correction_rotation="none"),
    "ground": dict(correction_axes="ground", correction_rotation="none"),
    "ground_yaw": dict(correction_axes="ground", correction_rotation="yaw"),
    "xyz_yaw": dict(correction_axes="xyz", correction_rotation="yaw"),
}


def cached_vo(seq_dir: Path, cfg: Config, cache_dir: Path, frames: str | None = None) -> VOCache:
    """The VO cache of a sequence, from disk when the same front-end config made it before."""
    import hashlib

    tag = f"_{frames.replace(':', '-')}" if frames else ""
    key = f"{seq_dir.name}{tag}_{hashlib.md5(repr(cfg.frontend).encode()).hexdigest()[:10]}.pkl"
    path = cache_dir / key
    if path.is_file():
        with path.open("rb") as fh:
            return pickle.load(fh)
    cache = vo_cache(KittiSequence(seq_dir, frames=frames), cfg)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        pickle.dump(cache, fh, protocol=pickle.HIGHEST_PROTOCOL)
    return cache


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", nargs="+", required=True, help="KITTI-format sequences with ground truth")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--config", default=None, help="base config TOML (default: the defaults)")
    ap.add_argument("--batch", action="store_true", help="also the batch refinement and the loop oracle")
    ap.add_argument("--verify-all", action="store_true", help="verify every candidate (complete verified PR curve)")
    ap.add_argument("--cache", default=str(RESULTS / "vo_cache"))
    ap.add_argument("--frames", default=None, help="frame range A:B of every sequence")
    ap.add_argument("--set", nargs="*", default=[], help="[loop] overrides for every variant, e.g. discount_length=200")
    ap.add_argument("--out", default=str(RESULTS / "loop_correction.md"))
    ap.add_argument("--write-runs", default=None, help="also write each replay's results folder under this folder")
    args = ap.parse_args()
    base = Config.load(args.config) if args.config else Config()
    for item in args.set:
        key, value = item.split("=", 1)
        old = getattr(base.loop, key)
        setattr(base.loop, key, type(old)(value) if not isinstance(old, bool) else value.lower() == "true")
    rows = []
    for seq_arg in args.seq:
        seq_dir = Path(seq_arg)
        t0 = time.perf_counter()
        cache = cached_vo(seq_dir, base, Path(args.cache), args.frames)
        print(f"{seq_dir}: VO ready in {time.perf_counter() - t0:.1f} s ({len(cache.indices)} frames)")
        gt = cache.gt
        vo = np.array([cache.results[int(i)].pose for i in cache.indices])
        m_vo = evaluate(vo, gt)
        rows.append(
            [
                seq_dir.name,
                "VO",
                "",
                "",
                f"{m_vo['mean_deviation']:.3f}",
                f"{m_vo['mean_deviation_horizontal']:.3f}",
                f"{m_vo['mean_deviation_vertical']:.3f}",
                f"{m_vo['ate_rmse']:.3f}",
                "",
                "",
                "",
                "",
                "",
            ]
        )
        print(
            f"  VO: mean dev {m_vo['mean_deviation']:.3f} (h {m_vo['mean_deviation_horizontal']:.3f} v {m_vo['mean_deviation_vertical']:.3f}) ATE {m_vo['ate_rmse']:.3f}"
        )
        for name in args.variants:
            cfg = copy.deepcopy(base)
            rule = policy(cfg.loop.policy, **VARIANTS[name])
            closer = VerifyAllCloser if args.verify_all else SnapsLoopCloser
            t0 = time.perf_counter()
            result, pipe = replay(
                cache, cfg, refine="batch" if args.batch else "none", setup=lambda p, c=closer, r=rule: use_closer(p, c, r)
            )
            wall = time.perf_counter() - t0
            if args.write_runs:
                write_results(Path(args.write_runs) / f"{seq_dir.name}_{name}", pipe, result, gt, overwrite=True)
            m = evaluate(result.trajectories["snaps"], gt)
            ev = evaluate_loops(
                pipe.snaps.candidate_records(),
                [(l.frame, l.reference) for l in result.loops],
                gt,
                cache.indices,
                LoopEvalSettings(frame_distance=cfg.loop.frame_distance, max_yaw_deg=rule.max_yaw_deg),
                cfg.loop.min_similarity,
            )
            t_cand = [r.t_loop_ms for r in result.records if r.loop_candidates > 0]
            t_none = [r.t_loop_ms for r in result.records if r.loop_candidates == 0]

            def ratio(key: str, m: dict = m, m_vo: dict = m_vo) -> float:
                return m[key] / m_vo[key] if m_vo[key] > 0 else float("nan")

            batch = ""
            if args.batch:
                mb = evaluate(result.trajectories["batch"], gt)
                batch = f"{mb['mean_deviation']:.3f} ({mb['mean_deviation'] / m_vo['mean_deviation']:.2f}x)"
            if result.loops and name == args.variants[0]:
                # The mechanism: the VO's height error (y, KITTI's vertical) at each loop's
                # reference against the loop frame's; eq. 6's z move copies the former.
                k_of = {int(i): k for k, i in enumerate(cache.indices)}
                ev_ref = np.array([vo[k_of[l.reference], 1, 3] - gt[k_of[l.reference], 1, 3] for l in result.loops])
                ev_cur = np.array([vo[k_of[l.frame], 1, 3] - gt[k_of[l.frame], 1, 3] for l in result.loops])
                print(
                    f"  VO height error at the {len(ev_ref)} loops: reference |e| mean {np.abs(ev_ref).mean():.3f} m, "
                    f"loop frame {np.abs(ev_cur).mean():.3f} m; reference's larger at {int((np.abs(ev_ref) > np.abs(ev_cur)).sum())}"
                )
            rows.append(
                [
                    seq_dir.name,
                    name,
                    ev["loops"],
                    ev["false_loops"],
                    f"{m['mean_deviation']:.3f} ({ratio('mean_deviation'):.2f}x)",
                    f"{m['mean_deviation_horizontal']:.3f} ({ratio('mean_deviation_horizontal'):.2f}x)",
                    f"{m['mean_deviation_vertical']:.3f} ({ratio('mean_deviation_vertical'):.2f}x)",
                    f"{m['ate_rmse']:.3f} ({ratio('ate_rmse'):.2f}x)",
                    f"{ev['max_recall_at_100_precision']:.2f} / {ev['max_recall_at_100_precision_verified']:.2f}",
                    f"{ev['segments_found']}/{ev['segments']}",
                    f"{np.median(t_cand):.2f}" if t_cand else "n/a",
                    f"{1e3 * np.median(t_none):.1f}" if t_none else "n/a",
                    batch,
                ]
            )
            print(
                f"  {name:<12} loops {ev['loops']} (false {ev['false_loops']}), mean dev {rows[-1][4]}, h {rows[-1][5]}, v {rows[-1][6]}, "
                f"ATE {rows[-1][7]}, recall@P=1 {rows[-1][8]}, segments {rows[-1][9]}, SNAPS ms {rows[-1][10]} / us {rows[-1][11]}"
                + (f", batch {batch}" if batch else "")
                + f" [{wall:.1f} s]"
            )
        if args.batch:
            r0 = result.records
            o = loop_oracle(
                vo,
                gt,
                base,
                [r.vo_inliers for r in r0],
                [r.vo_ok for r in r0],
                covs=[cache.results[int(i)].cov for i in cache.indices],
            )
            rows.append(
                [
                    seq_dir.name,
                    f"oracle ({len(o.pairs)} exact loops, batch)",
                    "",
                    "",
                    f"{o.mean_deviation:.3f}",
                    "",
                    "",
                    f"{o.ate_rmse:.3f}",
                    "",
                    "",
                    "",
                    "",
                    "",
                ]
            )
            print(
                f"  oracle: {len(o.pairs)} exact loops, mean dev {o.mean_deviation:.3f} ({o.mean_deviation / m_vo['mean_deviation']:.2f}x VO), ATE {o.ate_rmse:.3f}"
            )
    header = [
        "sequence",
        "eq. 6 variant",
        "loops",
        "false",
        "mean dev m (x VO)",
        "horizontal m",
        "vertical m",
        "ATE m",
        "max recall @P=1 Q / Q+verif.",
        "segments found",
        "SNAPS ms (cand.)",
        "SNAPS us (none)",
        "batch mean dev m",
    ]
    text = "# Eq. 6 variants: what the real-time correction corrects\n\n"
    text += (
        "Command: `python experiments/loop_correction.py --seq "
        + " ".join(args.seq)
        + (" --variants " + " ".join(args.variants) if args.variants != list(VARIANTS) else "")
        + (" --batch" if args.batch else "")
        + (" --verify-all" if args.verify_all else "")
        + (" --set " + " ".join(args.set) if args.set else "")
        + "`\n\n"
    )
    text += md_table(header, rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
