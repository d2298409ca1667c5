"""Loop verification, loop-factor noise and eq. 6's window, measured end to end.

Runs the front end once per sequence (cached on disk without its per-frame features,
``results/experiments/vo_cache_lv``), then replays the real pipeline over the cached VO with the
real images, so the loop-verification features (``verification/features.py``) are computed as in
a full run. Each ``--variant NAME:section.key=value,...`` is one replay (``base`` = the config as
given). Per sequence and variant it prints the loop evaluation (max recall at 100 % precision
with and without verification, revisit frames searched, loops, false loops), VO / SNAPS / batch
mean deviation (3D, horizontal, vertical) and ATE, the verification time, and with ``--batch``
the loop oracle beside the batch.

    python experiments/loop_verification.py --seq results/data/street07 \\
        --variant base "k300:loop.discount_length=300" [--batch] [--verify-all] [--pause 0]

The VO cache is keyed by the front-end settings and source files, so a replay reproduces a
user's run with the same config; ``--compare-run RUN_DIR`` (a ``snaps-graph run`` of the same
sequence) prints the largest difference between the replay's poses and the run's.

``--verify-all`` verifies every compared candidate and ``--pause 0`` sets the inter-frame pause
to 0, so every revisit frame is searched: the precision-recall figures of the verifier, not of a
deployable run (every verified loop then corrects the trajectory).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the loop-closure instruments
from _common import RESULTS, CachedOdometry, md_table
from _loop_research import SnapsLoopCloser, VerifyAllCloser, policy, use_closer

import snaps_graph
from snaps_graph.config import Config
from snaps_graph.datasets.kitti import KittiSequence
from snaps_graph.evaluation.loops import LoopEvalSettings, evaluate_loops
from snaps_graph.evaluation.metrics import evaluate
from snaps_graph.evaluation.oracle import loop_oracle
from snaps_graph.frontend.odometry import StereoOdometry
from snaps_graph.geometry import rotation_angle_deg, wrap_deg, yaw_deg
from snaps_graph.pipeline import SlamPipeline
from snaps_graph.runner import write_results
from snaps_graph.trajectory_io import read_kitti_poses

# The VO depends on these sources as much as on the settings: a cache made by an older front end
# would replay a VO no user's run produces (how an earlier table disagreed with the CLI).
# Loop verification (its own package, not among them) runs in the replay, never in the cached VO:
# editing it keeps the cache.
VO_SOURCES = ("frontend/*.py", "camera.py", "geometry.py", "datasets/kitti.py")


def frontend_key(cfg: Config) -> str:
    """Hash of the front-end settings the VO depends on ([frontend]; [verification] is not among
    them) and of the front end's source files."""
    h = hashlib.md5(repr(sorted(dataclasses.asdict(cfg.frontend).items())).encode())
    root = Path(snaps_graph.__file__).parent
    for pattern in VO_SOURCES:
        for f in sorted(root.glob(pattern)):
            h.update(f.read_bytes())
    return h.hexdigest()[:10]


def cached_vo(seq: KittiSequence, seq_dir: Path, cfg: Config, cache_dir: Path, frames: str | None) -> dict:
    tag = f"_{frames.replace(':', '-')}" if frames else ""
    path = cache_dir / f"{seq_dir.name}{tag}_{frontend_key(cfg)}.pkl"
    if path.is_file():
        with path.open("rb") as fh:
            return pickle.load(fh)
    from tqdm import tqdm

    vo = StereoOdometry(seq.camera, cfg.frontend)
    results = {}
    for f in tqdm(seq, total=len(seq), desc="vo", unit="frame", mininterval=5):
        r = vo.process(f)
        r.features = None  # the tracker's loop features are not used ("separate")
        results[f.index] = r
    vo.close()
    cache_dir.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        pickle.dump(results, fh, protocol=pickle.HIGHEST_PROTOCOL)
    return results


def apply(cfg: Config, items: list[str]) -> dict:
    """Set each section.key=value; the loop rule's flags (loop.FLAG, a LoopPolicy field) are
    returned instead, for :func:`policy`."""
    flags: dict = {}
    rule = policy(cfg.loop.policy)
    for item in items:
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        obj = rule if section == "loop" and hasattr(rule, name) else getattr(cfg, section)
        old = getattr(obj, name)
        new = value.lower() == "true" if isinstance(old, bool) else type(old)(value)
        if obj is rule:
            flags[name] = new
        else:
            setattr(obj, name, new)
    return flags


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", nargs="+", required=True)
    ap.add_argument("--variant", nargs="+", default=["base"], help="NAME[:section.key=value,...]")
    ap.add_argument("--config", default=None)
    ap.add_argument("--batch", action="store_true")
    ap.add_argument("--verify-all", action="store_true")
    ap.add_argument("--pause", type=int, default=None, help="override loop.inter_frame_pause")
    ap.add_argument("--frames", default=None)
    ap.add_argument("--cache", default=str(RESULTS / "vo_cache_lv"))
    ap.add_argument("--write-runs", default=None)
    ap.add_argument(
        "--compare-run",
        nargs="+",
        default=[],
        help="CLI run folders (snaps-graph run SEQ --out DIR, same config), one per --seq: "
        "prints how far the replay's VO and SNAPS poses lie from the run's",
    )
    ap.add_argument("--out", default=str(RESULTS / "loop_verification.md"))
    args = ap.parse_args()
    base = Config.load(args.config) if args.config else Config()
    if args.pause is not None:
        base.loop.inter_frame_pause = args.pause
    rows = []
    for i_seq, seq_arg in enumerate(args.seq):
        seq_dir = Path(seq_arg)
        seq = KittiSequence(seq_dir, frames=args.frames)
        t0 = time.perf_counter()
        results = cached_vo(seq, seq_dir, base, Path(args.cache), args.frames)
        print(f"{seq_dir}: VO ready in {time.perf_counter() - t0:.1f} s ({len(results)} frames)", flush=True)
        gt = seq.gt_poses
        vo = np.array([results[int(i)].pose for i in seq.indices])
        m_vo = evaluate(vo, gt)

        def fmt(m: dict, key: str, m_vo: dict = m_vo) -> str:
            return f"{m[key]:.3f} ({m[key] / m_vo[key]:.2f}x)" if m_vo[key] > 0 else f"{m[key]:.3f}"

        rows.append(
            [
                seq_dir.name,
                "VO",
                "",
                "",
                "",
                "",
                f"{m_vo['mean_deviation']:.3f}",
                f"{m_vo['mean_deviation_horizontal']:.3f}",
                f"{m_vo['mean_deviation_vertical']:.3f}",
                f"{m_vo['ate_rmse']:.3f}",
                "",
                "",
            ]
        )
        print(
            f"  VO mean dev {m_vo['mean_deviation']:.3f} h {m_vo['mean_deviation_horizontal']:.3f} v {m_vo['mean_deviation_vertical']:.3f} ATE {m_vo['ate_rmse']:.3f}",
            flush=True,
        )
        for spec in args.variant:
            name, _, sets = spec.partition(":")
            cfg = copy.deepcopy(base)
            rule = policy(cfg.loop.policy, **apply(cfg, [s for s in sets.split(",") if s]))
            t0 = time.perf_counter()
            pipe = SlamPipeline(
                seq.camera,
                cfg,
                loops="snaps",
                refine="batch" if args.batch else "none",
                build_map=False,
                frontend=CachedOdometry(type("C", (), {"results": results})()),
            )
            use_closer(pipe, VerifyAllCloser if args.verify_all else SnapsLoopCloser, rule)
            for f in seq:
                pipe.process(f)
            result = pipe.finish()
            wall = time.perf_counter() - t0
            if i_seq < len(args.compare_run) and name == args.variant[0].partition(":")[0]:
                run_dir = Path(args.compare_run[i_seq])
                for traj in ("vo", "snaps"):
                    cli = read_kitti_poses(run_dir / f"poses_{traj}.txt")
                    d = np.linalg.norm(cli[:, :3, 3] - result.trajectories[traj][:, :3, 3], axis=1)
                    print(f"  {name} vs {run_dir}: {traj} poses differ by at most {d.max():.2e} m", flush=True)
            if args.write_runs:
                write_results(Path(args.write_runs) / f"{seq_dir.name}_{name}", pipe, result, gt, overwrite=True)
            ev = evaluate_loops(
                pipe.snaps.candidate_records(),
                [(lp.frame, lp.reference) for lp in result.loops],
                gt,
                seq.indices,
                LoopEvalSettings(frame_distance=cfg.loop.frame_distance, max_yaw_deg=rule.max_yaw_deg),
                cfg.loop.min_similarity,
            )
            m = evaluate(result.trajectories["snaps"], gt)
            batch = ""
            if args.batch:
                mb = evaluate(result.trajectories["batch"], gt)
                batch = f"{fmt(mb, 'mean_deviation')} h {fmt(mb, 'mean_deviation_horizontal')} ATE {fmt(mb, 'ate_rmse')}"
            t_cand = [r.t_loop_ms for r in result.records if r.loop_candidates > 0]
            t_none = [r.t_loop_ms for r in result.records if r.loop_candidates == 0]
            t_ver = [r.t_verify_ms for r in result.records if r.t_verify_ms > 0]
            bank = pipe.verifier.bank if pipe.verifier is not None else None
            lat = (
                f"{np.median(t_cand):.2f} ms / {1e3 * np.median(t_none):.0f} us"
                + (f", verify median {np.median(t_ver):.0f} ms on {len(t_ver)} frames" if t_ver else "")
                + (f", refs {len(bank)} ({bank.nbytes() / 2**20:.1f} MiB)" if bank is not None else "")
            )
            # Verified loops against ground truth: translation / rotation error of the measurement.
            k_of = {int(i): k for k, i in enumerate(seq.indices)}
            errs = []
            per_loop = []
            for lp in result.loops:
                if lp.verified and lp.T_ref_cur is not None:
                    G = np.linalg.solve(gt[k_of[lp.reference]], gt[k_of[lp.frame]])
                    errs.append(float(np.linalg.norm(lp.T_ref_cur[:3, 3] - G[:3, 3])))
                    dyaw = float(wrap_deg(yaw_deg(lp.T_ref_cur[:3, :3]) - yaw_deg(G[:3, :3])))
                    drot = rotation_angle_deg(lp.T_ref_cur[:3, :3].T @ G[:3, :3])
                    per_loop.append(f"{lp.frame}-{lp.reference}: t {errs[-1]:.3f} m, rot {drot:.3f}, yaw {dyaw:+.3f} deg")
            if per_loop:
                print(f"  {name} loop errors: " + "; ".join(per_loop), flush=True)
            rows.append(
                [
                    seq_dir.name,
                    name,
                    f"{ev['max_recall_at_100_precision']:.2f} / {ev['max_recall_at_100_precision_verified']:.2f}",
                    f"{ev['revisit_frames_searched']}/{ev['revisit_frames']}",
                    f"{ev['loops']} ({ev['false_loops']})",
                    f"{max(errs):.3f}" if errs else "",
                    fmt(m, "mean_deviation"),
                    fmt(m, "mean_deviation_horizontal"),
                    fmt(m, "mean_deviation_vertical"),
                    fmt(m, "ate_rmse"),
                    batch,
                    lat,
                ]
            )
            print(
                f"  {name}: recall@P=1 Q/verified {rows[-1][2]} (true pairs {ev['true_pairs']}, false pairs {ev['false_pairs']}, verified true {ev['verified_true_pairs']}, "
                f"verified false {ev['verified_false_pairs']}), revisits searched {rows[-1][3]}, segments {ev['segments_found']}/{ev['segments']}, "
                f"loops {rows[-1][4]}, max loop error {rows[-1][5]} m; SNAPS {rows[-1][6]} h {rows[-1][7]} v {rows[-1][8]} ATE {rows[-1][9]}"
                + (f"; batch {batch}" if batch else "")
                + f"; {lat} [{wall:.0f} s]",
                flush=True,
            )
        if args.batch:
            r0 = result.records
            o = loop_oracle(
                vo, gt, base, [r.vo_inliers for r in r0], [r.vo_ok for r in r0], covs=[results[int(i)].cov for i in seq.indices]
            )
            mo = evaluate(o.poses, gt)
            rows.append(
                [
                    seq_dir.name,
                    f"oracle ({len(o.pairs)} exact loops)",
                    "",
                    "",
                    "",
                    "",
                    fmt(mo, "mean_deviation"),
                    fmt(mo, "mean_deviation_horizontal"),
                    fmt(mo, "mean_deviation_vertical"),
                    fmt(mo, "ate_rmse"),
                    "",
                    "",
                ]
            )
            print(
                f"  oracle: {len(o.pairs)} exact loops, mean dev {rows[-1][6]} h {rows[-1][7]} v {rows[-1][8]}, ATE {rows[-1][9]}",
                flush=True,
            )
    header = [
        "sequence",
        "variant",
        "max recall @P=1 Q / verified",
        "revisits searched",
        "loops (false)",
        "max loop t error m",
        "SNAPS mean dev m",
        "horizontal m",
        "vertical m",
        "ATE m",
        "batch",
        "SNAPS latency",
    ]
    cmd = (
        "python experiments/loop_verification.py --seq "
        + " ".join(args.seq)
        + " --variant "
        + " ".join(f'"{v}"' for v in args.variant)
    )
    cmd += (
        (" --batch" if args.batch else "")
        + (" --verify-all" if args.verify_all else "")
        + (f" --pause {args.pause}" if args.pause is not None else "")
    )
    text = f"# Loop verification\n\nCommand: `{cmd}`\n\n" + md_table(header, rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
