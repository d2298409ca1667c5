"""``snaps-graph compare RUN_DIR``: the heuristic (SNAPS) against the optimised corrections of one run.

Writes report.md (trajectory, per-loop and latency tables; what each column means is in the
report itself), trajectories.png, errors.png (with ground truth), latency.png and, with ground
truth and candidates.csv, the loop evaluation (``loops.py``), and rewrites metrics.json's
comparison keys, keeping the others. Loop frames are dataset indices, mapped to rows by
frames.csv's ``frame`` column; the ground truth is re-based to the first row and the estimates
are used as written, so the figures equal the pipeline's own ``evaluate``.
"""

from __future__ import annotations

import math
import sys
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import atomic_write_text, read_text
from ..trajectory_io import read_kitti_poses
from .latency import LATENCY_LABELS, latency_samples, summarise_samples
from .loops import loops_run, summary_lines
from .metrics import evaluate, notes_text, parts, path_length, position_errors
from .results_io import (
    check_run_files,
    load_gt,
    read_frames_csv,
    read_loops,
    read_metrics_json,
    read_trajectories,
    write_metrics_json,
)
from .results_io import frame_ids as frame_ids_of
from .segments import segment_errors, worse_than

REFINED_NAMES = ("isam2", "batch")
# What compare reads of a run: one it wrote and that is gone since is named, never passed over.
COMPARED_FILES = ("poses_*.txt", "metrics.json", "loops.jsonl", "candidates.csv", "config.toml")
TRAJECTORY_LABELS = {
    "vo": "pure visual odometry",
    "snaps": "SNAPS heuristic (eq. 6)",
    "isam2": "iSAM2 (online) refinement",
    "batch": "batch (offline) refinement",
}


# ---------------------------------------------------------------------------------------------
# Summaries
# ---------------------------------------------------------------------------------------------
def _discount_offset(run: Path) -> float:
    """eq. 6's offset (the 3 in gamma = 1 - exp(-(3 - alpha 0.01 s'))) this run used."""
    default = 3.0  # a constant of both loop policies (snaps_graph.loop.policy)
    p = run / "config.toml"
    if not p.is_file():
        return default
    try:
        loop = tomllib.loads(read_text(p, "config")).get("loop", {})
    except tomllib.TOMLDecodeError as exc:
        raise SnapsGraphError(f"{p}: malformed TOML ({exc})") from None
    value = loop.get("discount_offset", default) if isinstance(loop, dict) else default
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SnapsGraphError(f"{p}: loop.discount_offset must be a finite number, got {value!r}")
    return float(value)


def _loop_corrections(loops: list[dict], trajs: dict[str, np.ndarray], gt: np.ndarray | None, gamma0: float) -> list[dict]:
    out = []
    p_vo = trajs["vo"][:, :3, 3]
    for lp in loops:
        row = lp["row"]
        q = lp.get("q")
        weight = lp.get("weight", q)  # what eq. 6 applied: Q, or 1 for a verified loop (older files: Q)
        delta = lp.get("delta")
        step = None
        if weight is not None and delta is not None and len(delta) == 3:
            step = abs(float(weight)) * gamma0 * float(np.linalg.norm(np.asarray(delta, float)))
        entry: dict[str, Any] = {
            "frame": int(lp["frame"]),
            "reference": int(lp["reference"]),
            "q": lp.get("q"),
            "correlation": lp.get("correlation"),
            "luminance": lp.get("luminance"),
            "contrast": lp.get("contrast"),
            "verified": lp.get("verified"),
            "snaps_step_m": step,
            "heuristic_m": (float(np.linalg.norm(trajs["snaps"][row, :3, 3] - p_vo[row])) if "snaps" in trajs else None),
            "optimised_m": {
                name: float(np.linalg.norm(trajs[name][row, :3, 3] - p_vo[row])) for name in REFINED_NAMES if name in trajs
            },
        }
        if gt is not None:
            entry["error_m"] = {name: float(np.linalg.norm(poses[row, :3, 3] - gt[row, :3, 3])) for name, poses in trajs.items()}
        out.append(entry)
    return out


# ---------------------------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------------------------
def _f(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{float(value):.{digits}f}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def _trajectory_lines(trajs: dict, metrics: dict | None, paths: dict) -> list[str]:
    if metrics is None:
        header = ["trajectory", "frames", "path length [m]", "end offset from vo [m]"]
        p_vo_end = trajs["vo"][-1, :3, 3]
        rows = [
            [
                name,
                str(paths[name]["frames"]),
                _f(paths[name]["path_length_m"], 3),
                _f(float(np.linalg.norm(trajs[name][-1, :3, 3] - p_vo_end)), 3),
            ]
            for name in trajs
        ]
        return _table(header, rows)
    header = [
        "trajectory",
        "frames",
        "mean deviation [m]",
        "vs vo",
        "horizontal / vertical [m]",
        "ATE RMSE [m]",
        "t_rel [%]",
        "r_rel [deg/100 m]",
        "end error [m]",
        "end drift [%]",
    ]
    md_vo = metrics["vo"]["mean_deviation"]
    rows = []
    for name, m in metrics.items():
        if name == "vo":
            change = "reference"
        else:
            change = (
                "n/a"
                if not (md_vo > 0 and math.isfinite(m["mean_deviation"]))
                else f"{(m['mean_deviation'] - md_vo) / md_vo * 100.0:+.1f}%"
            )
        split = f"{_f(m.get('mean_deviation_horizontal'), 3)} / {_f(m.get('mean_deviation_vertical'), 3)}"
        rows.append(
            [
                name,
                str(m["frames"]),
                _f(m["mean_deviation"], 3),
                change,
                split,
                _f(m["ate_rmse"], 3),
                _f(m["t_rel"], 3),
                _f(m["r_rel"], 4),
                _f(m["end_error_m"], 3),
                _f(m["end_drift_percent"], 3),
            ]
        )
    notes = notes_text(metrics)  # why a figure is n/a, said once for every row it concerns
    return _table(header, rows) + ([""] + [f"- {line}" for line in notes] if notes else [])


def _loop_lines(corrections: list[dict], trajs: dict, with_gt: bool) -> list[str]:
    refined = [n for n in REFINED_NAMES if n in trajs]
    header = [
        "frame",
        "reference",
        "Q",
        "correlation",
        "luminance",
        "contrast",
        "verified",
        "SNAPS step [m]",
        "heuristic [m]",
    ] + [f"optimised {n} [m]" for n in refined]
    if with_gt:
        header += [f"error {n} [m]" for n in trajs]
    rows = []
    for c in corrections:
        verified = c["verified"]
        row = [
            str(c["frame"]),
            str(c["reference"]),
            _f(c["q"], 4),
            _f(c["correlation"], 4),
            _f(c["luminance"], 4),
            _f(c["contrast"], 4),
            "n/a" if verified is None else ("yes" if verified else "no"),
            _f(c["snaps_step_m"], 3),
            _f(c["heuristic_m"], 3),
        ]
        row += [_f(c["optimised_m"].get(n), 3) for n in refined]
        if with_gt:
            row += [_f(c["error_m"][n], 3) for n in trajs]
        rows.append(row)
    return _table(header, rows)


def _segment_lines(rows: list[dict], trajs: dict) -> list[str]:
    """The per-stretch table: mean error of each trajectory, and the stretches a correction made
    worse than the odometry (more than 5 %)."""
    names = list(trajs)
    md = ["## Per stretch", "", "Mean position error (m) over stretches of equal ground-truth distance.", ""]
    md += _table(
        ["stretch (m driven)", "frames (rows)"] + names,
        [
            [f"{r['from_m']:.0f}-{r['to_m']:.0f}", f"{r['rows'][0]}-{r['rows'][1]}"]
            + [_f(r["mean_error_m"][k], 3) for k in names]
            for r in rows
        ],
    )
    md.append("")
    for name in names:
        if name == "vo":
            continue
        bad = worse_than(rows, name, "vo")
        if bad:
            spans = ", ".join(f"{rows[i]['from_m']:.0f}-{rows[i]['to_m']:.0f} m" for i in bad)
            md.append(f"- **{name}** is worse than the odometry (by more than 5 %) over {spans}.")
    md += ["", "![error per stretch](segments.png)", ""]
    return md


def _latency_lines(latency: dict) -> list[str]:
    header = ["stage", "frames", "median [ms]", "mean [ms]", "p95 [ms]", "max [ms]"]
    rows = []
    for key, label in LATENCY_LABELS.items():
        s = latency.get(key)
        if s is None:
            continue
        rows.append([label, str(s["n"]), _f(s.get("median"), 4), _f(s.get("mean"), 4), _f(s.get("p95"), 4), _f(s.get("max"), 4)])
    return _table(header, rows)


def _summary_lines(metrics: dict | None, corrections: list[dict], trajs: dict) -> list[str]:
    lines = []
    if metrics is not None:
        md_vo = metrics["vo"]["mean_deviation"]
        for name in trajs:
            if name == "vo":
                continue
            md = metrics[name]["mean_deviation"]
            change = f" ({(md - md_vo) / md_vo * 100.0:+.1f}%)" if md_vo > 0 else ""
            lines.append(f"- {name}: mean deviation {md_vo:.3f} m (vo) -> {md:.3f} m{change}.")
    if corrections:
        heur = [c["heuristic_m"] for c in corrections if c["heuristic_m"] is not None]
        if heur:
            lines.append(f"- Mean heuristic correction at the {len(corrections)} loop frame(s): {np.mean(heur):.3f} m.")
        for n in REFINED_NAMES:
            opt = [c["optimised_m"][n] for c in corrections if n in c["optimised_m"]]
            if opt:
                lines.append(f"- Mean optimised ({n}) correction at the loop frames: {np.mean(opt):.3f} m.")
    return lines


def map_section_lines(run_dir: str | Path, map_entry: dict | None) -> list[str]:
    """The ``## Map`` section of report.md from metrics.json's ``map`` entry and the pictures."""
    run = Path(run_dir)
    if not map_entry:
        return []
    md = ["## Map", ""]
    if map_entry.get("empty") or map_entry.get("error"):
        return md + [f"No map: {map_entry.get('empty') or 'the map stage failed: ' + map_entry['error']}.", ""]
    surf = map_entry.get("surfaces", {}).get(map_entry.get("trajectory"), {})
    md.append(
        f"Fused under **{map_entry.get('trajectory')}** from {map_entry.get('keyframes')} keyframes "
        f"({map_entry.get('bytes', 0) / 2**20:.1f} MiB of compressed depth): "
        f"{surf.get('triangles', 'n/a')} triangles (`map_mesh.ply`), {surf.get('vertices', 'n/a')} surface points (`map.ply`, the mesh vertices)."
    )
    acc = map_entry.get("accuracy")
    if acc:
        any_acc = next(iter(acc.values()))
        md += [
            "",
            f"Accuracy against the true world (`{map_entry.get('world_mesh', '?')}`): distance of the map's "
            "points (= the mesh vertices, `map.ply`) to the true surface; completeness = share of the true "
            f"surface within {any_acc['range_m']:g} m of the path that lies within {any_acc['tolerance_m']:g} m of "
            "the map, over all of it and over the part a keyframe camera saw (in view, within range, "
            "unoccluded: upper floors, roofs and the backs of buildings are never seen). "
            "**gt** = the same keyframe depth fused under the true poses. *Aligned*: the same map moved by "
            "its trajectory's SE(3) alignment onto the true one (the ATE's alignment; the map plays no part "
            "in it), which removes the arbitrary anchoring at the first frame and leaves the trajectory's "
            "shape error.",
            "",
        ]
        md.append(
            "| map posed by | error p50 m | error p90 m | within tol. | completeness | completeness (seen) | points "
            "| aligned: error p90 m | aligned: completeness (seen) |"
        )
        md.append("|---|---|---|---|---|---|---|---|---|")

        def f(v, pct=False):
            return "n/a" if v is None else (f"{100 * v:.1f} %" if pct else f"{v:.3f}")

        for name, a in acc.items():
            p = a["points"]
            al = a.get("aligned", {}).get("points", {})
            md.append(
                f"| {name} | {f(p['error_median_m'])} | {f(p['error_p90_m'])} | {f(p['share_within_tolerance'], True)} | "
                f"{f(p['completeness'], True)} | {f(p['completeness_seen'], True)} | {p['n']} "
                f"| {f(al.get('error_p90_m'))} | {f(al.get('completeness_seen'), True)} |"
            )
    md.append("")
    for fig, alt in (
        ("map.png", "map, top-down"),
        ("map_mesh.png", "mesh, perspective"),
        ("map_compare.png", "maps side by side"),
    ):
        if (run / fig).is_file():
            md += [f"![{alt}]({fig})", ""]
    return md


def _metrics_entry(run: Path, key: str) -> Any:
    """metrics.json's ``key`` (None without the file or the key)."""
    p = run / "metrics.json"
    if not p.is_file():
        return None
    try:
        return read_metrics_json(p).get(key)
    except SnapsGraphError:
        return None  # a malformed metrics.json is reported where it is read in full


def _odometry_file(run: Path) -> str | None:
    """The pose file a ``run --odometry`` read (metrics.json's ``odometry_file``), else None."""
    value = _metrics_entry(run, "odometry_file")
    return value if isinstance(value, str) else None


def _in_prior_frame(run: Path) -> bool:
    """The run relocalised against a prior: it wrote its trajectories and poses_gt.txt in that frame."""
    entries = _metrics_entry(run, "sessions")
    return isinstance(entries, list) and any(isinstance(e, dict) and e.get("outputs_frame") for e in entries)


def _session_lines(run: Path, priors: dict[str, np.ndarray]) -> list[str]:
    """A run with ``--prior``: where it relocalised against each prior, and the priors drawn."""
    entries = _metrics_entry(run, "sessions")
    if not isinstance(entries, list):
        return []
    md = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            continue
        if not e.get("relocalised"):
            md.append(f"Prior `{e.get('session')}`: never relocalised against; the trajectories keep the run's own frame.")
            continue
        where = (
            "from the first frame (--same-start)"
            if e.get("frame") is None
            else f"at frame {e['frame']} (its frame {e['reference']})"
        )
        frame = "; the trajectories are in its frame" if e.get("outputs_frame") else ""
        drawn = f"; its trajectory (**prior{i}**) in the top view" if f"prior{i}" in priors else ""
        md.append(f"Prior `{e.get('session')}`: relocalised {where}, {e.get('loops', 0)} loop(s) with it{frame}{drawn}.")
    return md


# ---------------------------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------------------------
@dataclass
class _Run:
    """What compare reads of a run folder."""

    path: Path
    gone: list[str]  # files the run wrote that are missing now
    trajs: dict[str, np.ndarray]
    cols: dict
    frame_ids: np.ndarray
    gt: np.ndarray | None
    gt_file: Any
    loops: list[dict]
    priors: dict[str, np.ndarray]  # poses_prior<i>.txt: the priors where the run placed them


def _read_run(run: Path, gt_path: str | Path | None) -> _Run:
    if not run.is_dir():
        raise SnapsGraphError(f"{run}: run folder not found")
    gone = check_run_files(run, ("poses_vo.txt", "frames.csv"), COMPARED_FILES)
    if gone:
        print(f"warning: {run}: {', '.join(gone)} missing (the run wrote them); compared without them", file=sys.stderr)
    trajs = read_trajectories(run)
    n = len(trajs["vo"])
    csv_path = run / "frames.csv"
    cols = read_frames_csv(csv_path)
    n_rows = len(next(iter(cols.values())))
    if n_rows != n:
        raise SnapsGraphError(f"{csv_path}: {n_rows} rows, but poses_vo.txt has {n} poses")
    frame_ids = frame_ids_of(cols, n, csv_path)
    row_of_frame = {int(f): i for i, f in enumerate(frame_ids)}
    gt, gt_file = load_gt(run, gt_path, frame_ids, rebased=not (_in_prior_frame(run) and gt_path is None))
    loops = read_loops(run / "loops.jsonl", row_of_frame)
    priors = {p.name[len("poses_") : -len(".txt")]: read_kitti_poses(p) for p in sorted(run.glob("poses_prior*.txt"))}
    return _Run(run, gone, trajs, cols, frame_ids, gt, gt_file, loops, priors)


def _figures(r: _Run, samples: dict) -> tuple[list[str], list[dict] | None]:
    """Write the trajectory, error, segment and latency figures; their names and, with ground
    truth, the segment errors."""
    from .plots import plot_errors, plot_latency_box, plot_segments, plot_trajectories

    run, trajs, gt, frame_ids = r.path, r.trajs, r.gt, r.frame_ids
    figures = []
    segments = None
    plot_trajectories(
        run / "trajectories.png",
        ({"gt": gt} if gt is not None else {}) | trajs,
        loops=[(lp["row"], lp["reference_row"]) for lp in r.loops],
        title=f"{run.name}: trajectories",
        frames=frame_ids,
        others=r.priors,
    )
    figures.append("trajectories.png")
    if gt is not None:
        plot_errors(
            run / "errors.png",
            {name: position_errors(p, gt) for name, p in trajs.items()},
            title=f"{run.name}: position error (no alignment)",
            frames=frame_ids,
        )
        figures.append("errors.png")
        segments = segment_errors(trajs, gt)
        plot_segments(run / "segments.png", segments, title=f"{run.name}: mean position error per stretch")
        figures.append("segments.png")
    if samples:
        plot_latency_box(run / "latency.png", {LATENCY_LABELS[k]: v for k, v in samples.items()}, title=f"{run.name}: latency")
        figures.append("latency.png")
    return figures, segments


def _intro_lines(r: _Run) -> list[str]:
    """The report's title and what was compared: frames, parts, ground truth, trajectories."""
    run, frame_ids, gt, trajs = r.path, r.frame_ids, r.gt, r.trajs
    n = len(trajs["vo"])
    md = [f"# Heuristic vs optimised: `{run.name}`", ""]
    runs = parts(frame_ids, n)
    spans = ", ".join(f"{frame_ids[p[0]]}..{frame_ids[p[-1]]}" for p in runs)
    md.append(f"Run folder `{run}`; {n} frames (dataset frames {spans}); {len(r.loops)} loop(s) closed.")
    if len(runs) > 1:
        md.append(
            f"The frames run in {len(runs)} parts: path length, t_rel / r_rel and end drift are taken over the parts "
            "(each part's own length and segments, each part's end error relative to its start), not across the gaps."
        )
    frame = (
        "in the prior's frame, as the run wrote it"
        if _in_prior_frame(run) and r.gt_file == run / "poses_gt.txt"
        else "re-based to the first processed frame"
    )
    md.append(
        f"Ground truth: `{r.gt_file}` ({frame})."
        if gt is not None
        else "Ground truth: none (no poses_gt.txt and no --gt), so no error columns and no errors.png."
    )
    labels = dict(TRAJECTORY_LABELS)
    odometry_file = _odometry_file(run)
    if odometry_file is not None:  # run --odometry: the "vo" poses are the given file's, not ours
        labels["vo"] = f"the odometry given as a pose file (`{Path(odometry_file).name}`)"
    md.append("Trajectories: " + "; ".join(f"**{k}** = {labels[k]}" for k in trajs) + ".")
    if r.gone:
        md.append(f"Missing: {', '.join(f'`{name}`' for name in r.gone)}, written by the run and deleted since; left out here.")
    return md + _session_lines(run, r.priors)


def _corrections_section(r: _Run, corrections: list[dict], offset: float, gamma0: float) -> list[str]:
    md = ["## Loops: heuristic vs optimised corrections", ""]
    if corrections:
        md += [
            f"SNAPS step = |w gamma_0 delta|, the move eq. 6 applies to the loop frame itself (w = the "
            f"loop's weight: Q, or 1 for a verified loop; gamma_0 = 1 - exp(-{offset:g}) = {gamma0:.4f}; "
            "delta = the eq. 6 target - p_frame). "
            "Heuristic = |p_snaps - p_vo|: how far the loop frame's position moved between the VO chain "
            "and the SNAPS trajectory (equal to the step for the first loop; later loops also carry the "
            "earlier corrections). Optimised = |p_refined - p_vo| at the same frame for each refined "
            "trajectory. Frame numbers are dataset indices. Q = correlation x luminance x contrast (eq. 4-5)."
            + (" Error columns: each trajectory's position error at the loop frame." if r.gt is not None else ""),
            "",
        ]
        md += _loop_lines(corrections, r.trajs, r.gt is not None)
    else:
        md.append("No loop closed in this run" + ("" if (r.path / "loops.jsonl").is_file() else " (no loops.jsonl)") + ".")
    return md


def _loop_evaluation_section(run: Path, gt_path: str | Path | None, figures: list[str]) -> tuple[list[str], dict]:
    """The loop closure against ground truth (candidates.csv); appends its figure to ``figures``."""
    loop_eval = loops_run(run, gt_path, name_missing=False)
    md = ["", "## Loop closure against ground truth", ""]
    md += [f"- {line}" for line in summary_lines(loop_eval)]
    md += [
        "",
        "Pairs: true within the first distance, false beyond the second, ignored in between; "
        "precision-recall over the Q threshold for Q alone and for Q + geometric verification "
        "(`snaps-graph loops RUN_DIR --json` prints the curve).",
        "",
    ]
    if "plot" in loop_eval:  # no compared pair: no picture, so no link
        figures.append(Path(loop_eval["plot"]).name)
        md += [f"![loop precision-recall]({figures[-1]})", ""]
    return md, loop_eval


def _latency_section(samples: dict, latency: dict) -> list[str]:
    md = ["", "## Latency", ""]
    if samples:
        md += _latency_lines(latency)
        fps = latency.get("frames_per_s")
        md += ["", f"Throughput: {fps:.2f} frames/s (from the total per frame)." if fps else "", "", "![latency](latency.png)"]
    else:
        md.append("frames.csv has no timing columns.")
    md.append("")
    return md


def _measured_map(r: _Run, metrics: dict, metrics_path: Path, map_accuracy: Callable[..., dict] | None) -> dict | None:
    """The metrics' map entry, with its accuracy against a world mesh when ``map_accuracy`` is given."""
    run, trajs, gt = r.path, r.trajs, r.gt
    map_entry = metrics.get("map") if isinstance(metrics.get("map"), dict) else None
    if map_accuracy is not None:
        if not map_entry:
            raise SnapsGraphError(f"{metrics_path}: no map in this run (run it with --map) to measure against a world mesh")
        measured = map_accuracy(run, trajs, map_entry, gt)
        map_entry["accuracy"] = dict(map_entry.get("accuracy") or {}) | measured["accuracy"]  # keeps the run's others
        map_entry["world_mesh"] = measured["world_mesh"]
        metrics["map"] = map_entry
    return map_entry


def compare_run(run_dir: str | Path, gt_path: str | Path | None = None, map_accuracy: Callable[..., dict] | None = None) -> dict:
    """Compare a run's trajectories (VO, SNAPS heuristic, iSAM2 / batch), write the report and return
    the updated metrics.json content. ``gt_path`` overrides ``RUN_DIR/poses_gt.txt`` (KITTI, or TUM
    by a ``.tum`` extension; one pose per row or the whole sequence); without ground truth there are
    no error columns and no errors.png. ``map_accuracy(run, trajectories, map_entry, gt, map_config)``
    measures the folder's maps against a true world (the command line passes one built on
    ``mapping.outputs.accuracy_from_files``: evaluation does not import the map). A missing or
    malformed input raises SnapsGraphError naming the file.
    """
    run = Path(run_dir)
    r = _read_run(run, gt_path)
    trajs, gt, frame_ids = r.trajs, r.gt, r.frame_ids
    offset = _discount_offset(run)
    gamma0 = 1.0 - math.exp(-offset)  # eq. 6 at s' = 0

    per_traj = {name: evaluate(p, gt, frame_ids) for name, p in trajs.items()} if gt is not None else None
    paths = {name: {"frames": len(trajs["vo"]), "path_length_m": path_length(p, frame_ids)} for name, p in trajs.items()}
    samples = latency_samples(r.cols)
    latency = summarise_samples(samples)  # = latency_summary(cols), samples kept for the box plot
    corrections = _loop_corrections(r.loops, trajs, gt, gamma0)
    figures, segments = _figures(r, samples)

    md = _intro_lines(r)
    md += ["", "## Trajectories", ""]
    md += _trajectory_lines(trajs, per_traj, paths)
    md.append("")
    if per_traj is not None:
        md += [
            "Mean deviation: mean distance between estimated and true positions, no alignment (the paper's "
            "figure). ATE RMSE: after SE(3) Umeyama alignment, as `evo_ape kitti GT EST -a` prints it. "
            "t_rel / r_rel: KITTI devkit segments of 100..800 m every 10th frame (n/a on a path shorter "
            "than 100 m). End drift: final position error / ground-truth path length.",
            "",
        ]
    md += _summary_lines(per_traj, corrections, trajs)
    md += ["", "![trajectories](trajectories.png)", ""]
    if gt is not None:
        md += ["![position error](errors.png)", ""]
        md += _segment_lines(segments or [], trajs)
    md += _corrections_section(r, corrections, offset, gamma0)
    loop_eval = None
    if gt is not None and (run / "candidates.csv").is_file():
        lines, loop_eval = _loop_evaluation_section(run, gt_path, figures)
        md += lines
    md += _latency_section(samples, latency)

    # metrics.json: keep what is there, (re)write our keys
    metrics_path = run / "metrics.json"
    metrics = read_metrics_json(metrics_path)
    map_entry = _measured_map(r, metrics, metrics_path, map_accuracy)
    if map_entry:
        md += map_section_lines(run, map_entry)
    atomic_write_text(run / "report.md", "\n".join(md))
    if per_traj is not None:
        metrics["trajectories"] = per_traj
        metrics["segments"] = segments
    metrics["paths"] = paths
    metrics["latency_ms"] = latency
    metrics["loop_corrections"] = corrections
    if loop_eval is not None:
        metrics["loop_evaluation"] = {k: v for k, v in loop_eval.items() if k not in ("curve", "plot")}
    metrics["report"] = {"markdown": "report.md", "figures": figures}
    return write_metrics_json(metrics_path, metrics)
