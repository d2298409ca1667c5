"""Figures: top-down trajectories, position error over frames, latency box plots (paper Fig. 4-5).

matplotlib is imported inside each function with the Agg backend, so ``import snaps_graph`` stays
light and plotting works headless; each PNG is written atomically and every figure closed.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import atomic_write_bytes
from .metrics import distance_along

GT_NAMES = ("gt", "ground truth", "ground_truth")
# Fixed colours per known trajectory so every figure of every run reads the same way.
TRAJECTORY_COLOURS = {"vo": "tab:red", "snaps": "tab:blue", "isam2": "tab:green", "batch": "tab:purple"}
FIGURE_DPI = 120


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path_png: str | Path) -> Path:
    plt = _pyplot()
    path = Path(path_png)
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=FIGURE_DPI, bbox_inches="tight")
    finally:
        plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _finish(fig, ax, path_png: str | Path, title: str, xlabel: str, ylabel: str) -> Path:
    """Labels, light grid, legend; then save atomically and close."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, path_png)


def _colour(name: str, index: int) -> str:
    if name.lower() in GT_NAMES:
        return "black"
    return TRAJECTORY_COLOURS.get(name.lower(), f"C{(index + 4) % 10}")


# A path whose extent is below this is drawn in a window of at least this size, so millimetres of
# jitter of a standing camera are not auto-scaled into what looks like a drive.
STATIONARY_EXTENT_M = 1.0
MIN_HEIGHT_SPAN_M = 0.2
# Equal axes hide a lateral drift on a long straight drive: past this aspect the narrow axis is stretched.
MAX_EQUAL_ASPECT = 8.0


def top_view_scale(ext_x: float, ext_z: float) -> str:
    """How the top view is scaled: "stationary" (a fixed window), "stretched" or "equal" axes."""
    if max(ext_x, ext_z) < STATIONARY_EXTENT_M:
        return "stationary"
    if max(ext_x, ext_z) > MAX_EQUAL_ASPECT * max(min(ext_x, ext_z), 1e-9):
        return "stretched"
    return "equal"


# Two estimates closer than this everywhere (of the path's extent, at least 1 mm) draw as one line.
COINCIDE_FRACTION = 0.002


def coinciding(trajs: Mapping[str, np.ndarray]) -> dict[str, tuple[str, float]]:
    """Estimates that lie on an earlier one: name -> (that one's name, largest distance, m)."""
    names = [n for n in trajs if n.lower() not in GT_NAMES]
    pos = {n: np.asarray(trajs[n])[:, :3, 3] for n in names}
    if not names:
        return {}
    allp = np.concatenate(list(pos.values()))
    tol = max(COINCIDE_FRACTION * float(np.ptp(allp[:, [0, 2]], axis=0).max()), 1e-3)
    out: dict[str, tuple[str, float]] = {}
    for i, n in enumerate(names):
        for m in names[:i]:
            if m in out or len(pos[m]) != len(pos[n]):
                continue
            gap = float(np.linalg.norm(pos[n] - pos[m], axis=1).max())
            if gap <= tol:
                out[n] = (m, gap)
                break
    return out


def _length(m: float) -> str:
    return f"{m * 100:.1f} cm" if m >= 0.01 else f"{m * 1000:.1f} mm"


def plot_trajectories(
    path_png: str | Path,
    trajs: Mapping[str, np.ndarray],
    loops: Sequence[tuple[int, int]] | None = None,
    title: str = "Trajectories",
    frames: Sequence[int] | np.ndarray | None = None,
    others: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Top view (x right against z forward, KITTI camera axes) beside height (-y) over distance.

    ``trajs`` maps a name to an (N, 4, 4) pose stack, ``"gt"`` (or ``"ground truth"``) the ground
    truth; ``loops`` are (frame, reference) *row* indices, drawn on ``"snaps"`` (else the first
    estimate); ``frames``, the rows' frame numbers: lines break across a gap in them, and the
    distance does not count the jump. ``others``: trajectories of other frames (a prior session's)
    drawn in the top view only, thin and grey. Returns the path written.
    """
    if not trajs:
        raise SnapsGraphError(f"{path_png}: no trajectory to plot")
    plt = _pyplot()
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(12, 5.5), gridspec_kw={"width_ratios": [1.15, 1]})
    names = list(trajs)
    estimates = [n for n in names if n.lower() not in GT_NAMES]
    gt_name = next((n for n in names if n.lower() in GT_NAMES), None)
    ref = np.asarray(trajs[gt_name if gt_name is not None else names[0]])[:, :3, 3]
    dist = distance_along(ref)
    gaps = np.zeros(len(ref), bool)  # row i starts a part after a gap in the frame numbers
    if frames is not None and len(frames) == len(ref):
        gaps[1:] = np.diff(np.asarray(frames, dtype=np.int64)) != 1
        step = np.linalg.norm(np.diff(ref, axis=0), axis=1) * ~gaps[1:]
        dist = np.concatenate([[0.0], np.cumsum(step)])

    same_as = coinciding(trajs)
    for i, name in enumerate(names):
        # Earlier estimates are drawn wider, so VO stays visible where SNAPS left it unchanged.
        rank = estimates.index(name) if name in estimates else 0
        p = np.asarray(trajs[name])[:, :3, 3]
        is_gt = name.lower() in GT_NAMES
        style = dict(
            color=_colour(name, i),
            lw=1.6 if is_gt else 1.1 + 0.6 * (len(estimates) - 1 - rank),
            ls="--" if is_gt else "-",
            label=name if name not in same_as else f"{name} (on {same_as[name][0]}: within {_length(same_as[name][1])})",
            zorder=1 if is_gt else 2,
        )
        ax.plot(_broken(p[:, 0], gaps), _broken(p[:, 2], gaps), **style)
        if len(p) == len(dist):
            axh.plot(_broken(dist, gaps), _broken(-p[:, 1], gaps), **style)
    for name, poses in (others or {}).items():
        q = np.asarray(poses)[:, :3, 3]
        ax.plot(q[:, 0], q[:, 2], color="0.55", lw=0.9, ls=":", label=name, zorder=0)
    ax.plot([0.0], [0.0], "ko", ms=4, zorder=4)
    if loops and names:
        _draw_loops(ax, axh, trajs, loops, estimates, names, dist, ref)
    note = _top_view_extent(ax, trajs)
    if same_as:
        note += "\n" + "; ".join(f"{n} lies on {o}" for n, (o, _) in same_as.items())
    if gaps.any():
        note += f"\n{int(gaps.sum()) + 1} parts of the sequence: no line across the frames not run"
    ax.set_title("top view" + note, fontsize=10)
    ax.set_xlabel("x [m] (right)")
    ax.set_ylabel("z [m] (forward)")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=8)
    ylo, yhi = axh.get_ylim()
    if yhi - ylo < MIN_HEIGHT_SPAN_M:  # a flat drive's height noise is not auto-scaled into a slope
        mid = (ylo + yhi) / 2
        axh.set_ylim(mid - MIN_HEIGHT_SPAN_M / 2, mid + MIN_HEIGHT_SPAN_M / 2)
    axh.set_title("height over distance", fontsize=10)
    axh.set_xlabel(f"distance along {'the ground truth' if gt_name is not None else names[0]} [m]")
    axh.set_ylabel("height -y [m]")
    axh.grid(True, lw=0.3)
    fig.suptitle(title)
    return _save(fig, path_png)


def _broken(v: np.ndarray, gaps: np.ndarray) -> np.ndarray:
    """``v`` with NaN before each part after a gap: the line is not drawn across it."""
    v = np.asarray(v, dtype=float)
    return np.insert(v, np.flatnonzero(gaps), np.nan, axis=0) if len(v) == len(gaps) and gaps.any() else v


def _draw_loops(ax, axh, trajs, loops, estimates: list[str], names: list[str], dist: np.ndarray, ref: np.ndarray) -> None:
    """The loops on ``"snaps"`` (else the first estimate): a link in the top view, an arc over distance."""
    on = next((n for n in estimates if n.lower() == "snaps"), estimates[0] if estimates else names[0])
    p = np.asarray(trajs[on])[:, :3, 3]
    pairs = np.asarray(loops, dtype=int).reshape(-1, 2)
    pairs = pairs[(pairs >= 0).all(axis=1) & (pairs < len(p)).all(axis=1)]
    for k, (a, b) in enumerate(pairs):
        # frame (hollow) linked to its reference (dot); a revisit a metre aside is a short link
        ax.plot([p[a, 0], p[b, 0]], [p[a, 2], p[b, 2]], color="orange", lw=0.8, zorder=3)
        ax.plot(p[b, 0], p[b, 2], ".", color="darkorange", ms=4, zorder=3, label="loop reference" if k == 0 else None)
        ax.plot(
            p[a, 0],
            p[a, 2],
            "o",
            color="orange",
            ms=5,
            mfc="none",
            zorder=3,
            label=f"loops ({len(pairs)})" if k == 0 else None,
        )
        if len(p) == len(dist):
            # over distance the two ends lie far apart: an arc from the reference to the frame
            x = np.linspace(dist[b], dist[a], 24)
            y0, y1 = -p[b, 1], -p[a, 1]
            lift = 0.08 * max(np.ptp(-ref[:, 1]), MIN_HEIGHT_SPAN_M)
            axh.plot(x, np.linspace(y0, y1, 24) + lift * np.sin(np.linspace(0, np.pi, 24)), color="orange", lw=0.6, zorder=0)


def _top_view_extent(ax, trajs) -> str:
    """Limits and aspect of the top view from the paths' extent; a note for its title."""
    allp = np.concatenate([np.asarray(t)[:, :3, 3] for t in trajs.values()])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    ext_x, ext_z = float(hi[0] - lo[0]), float(hi[2] - lo[2])
    note = ""
    scale = top_view_scale(ext_x, ext_z)
    if scale == "stationary":
        cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
        half = STATIONARY_EXTENT_M / 2
        ax.set_xlim(cx - half, cx + half)
        ax.set_ylim(cz - half, cz + half)
        ax.set_aspect("equal", adjustable="box")
        note = f" - near-stationary: the path spans {max(ext_x, ext_z) * 100:.1f} cm"
    elif scale == "stretched":
        note = f" - {'x' if ext_x < ext_z else 'z'} axis stretched (not to scale)"
    else:
        ax.set_aspect("equal", adjustable="datalim")
    return note


def plot_errors(
    path_png: str | Path,
    errors: Mapping[str, np.ndarray],
    title: str = "Position error against ground truth (no alignment)",
    ylabel: str = "position error [m]",
    frames: np.ndarray | None = None,
) -> Path:
    """Error over frames, one line per trajectory. ``frames`` labels the x axis (row index if None)."""
    if not errors:
        raise SnapsGraphError(f"{path_png}: no error series to plot")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    for i, (name, err) in enumerate(errors.items()):
        e = np.asarray(err, dtype=float).reshape(-1)
        x = np.arange(len(e)) if frames is None or len(frames) != len(e) else np.asarray(frames)
        ax.plot(x, e, color=_colour(name, i), lw=1.0, label=name)
    return _finish(fig, ax, path_png, title, "frame", ylabel)


def plot_latency_box(
    path_png: str | Path,
    samples: Mapping[str, np.ndarray],
    title: str = "Latency per frame",
) -> Path:
    """Box plots of latency samples in milliseconds on a log axis (paper Fig. 5): the stages span five
    decades. Non-positive and non-finite samples are left out; an empty series gets a note, no column.
    """
    if not samples:
        raise SnapsGraphError(f"{path_png}: no latency series to plot")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(5.0, 1.5 * len(samples)), 4.5))
    data, labels, empty = [], [], []
    for name, values in samples.items():
        v = np.asarray(values, dtype=float).reshape(-1)
        v = v[np.isfinite(v) & (v > 0)]
        if v.size:
            data.append(v)
            labels.append(name.replace(", ", ",\n") + f"\n(n={v.size})")  # wrapped: long labels overlap
        else:
            empty.append(name)
    ax.set_yscale("log")
    if data:
        ax.boxplot(data, positions=np.arange(1, len(data) + 1), showfliers=True, whis=(5, 95))
        ax.set_xticks(np.arange(1, len(data) + 1), labels, fontsize=8)
    else:  # a log axis needs a range even with nothing on it
        ax.set_ylim(1e-3, 1e3)
        ax.set_xticks([])
    if empty:
        ax.text(0.99, 0.98, "no sample: " + ", ".join(empty), transform=ax.transAxes, ha="right", va="top", fontsize=7)
    ax.set_ylabel("time per frame [ms] (log)")
    ax.set_title(title + " (whiskers: 5th-95th percentile)")
    ax.grid(True, which="both", axis="y", lw=0.3)
    return _save(fig, path_png)


def plot_segments(path_png: str | Path, rows: list[dict], title: str = "Mean position error per stretch") -> Path:
    """Grouped bars: each trajectory's mean error over each stretch of the run (segments.segment_errors)."""
    if not rows:
        raise SnapsGraphError(f"{path_png}: no stretch to plot")
    plt = _pyplot()
    names = list(rows[0]["mean_error_m"])
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(rows) * max(1, len(names)) / 2), 4))
    width = 0.8 / max(1, len(names))
    x = np.arange(len(rows))
    for i, name in enumerate(names):
        ax.bar(
            x + (i - (len(names) - 1) / 2) * width,
            [r["mean_error_m"][name] for r in rows],
            width,
            color=_colour(name, i),
            label=name,
        )
    ax.set_xticks(x, [f"{r['from_m']:.0f}-{r['to_m']:.0f}" for r in rows], rotation=30)
    return _finish(fig, ax, path_png, title, "stretch of the ground truth, m driven", "mean position error [m]")
