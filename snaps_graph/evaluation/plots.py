"""Figures: top-down trajectories, position error over frames, latency box plots (paper Fig. 4-5).

matplotlib is imported inside each function, with the non-interactive Agg backend, so
``import snaps_graph`` stays light and plotting works on a headless machine. Every figure is
rendered to memory and written with ``io_utils.atomic_write_bytes`` (temporary file in the same
folder, then ``os.replace``), so a reader never sees half a PNG, and every figure is closed.

Trajectory naming: a key ``"gt"`` (or ``"ground truth"``) is the ground truth and is drawn in
black; loop pairs are drawn on ``"snaps"`` (the trajectory SNAPS corrected) when present, else on
the first estimate.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import atomic_write_bytes

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


def plot_trajectories(
    path_png: str | Path,
    trajs: Mapping[str, np.ndarray],
    loops: Sequence[tuple[int, int]] | None = None,
    title: str = "Trajectories (top-down)",
) -> Path:
    """Top-down view: x (right) against z (forward) in KITTI camera axes, equal aspect.

    ``trajs`` maps a name to an (N, 4, 4) pose stack; ``loops`` are (frame, reference) *row*
    indices into those stacks, drawn as thin lines between the two positions on the SNAPS
    trajectory (the one whose positions the loop moved). Returns the path written.
    """
    if not trajs:
        raise SnapsGraphError(f"{path_png}: no trajectory to plot")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 7))
    names = list(trajs)
    estimates = [n for n in names if n.lower() not in GT_NAMES]
    for i, name in enumerate(names):
        # Earlier estimates are drawn wider, so VO stays visible where SNAPS left it unchanged.
        rank = estimates.index(name) if name in estimates else 0
        p = np.asarray(trajs[name])[:, :3, 3]
        is_gt = name.lower() in GT_NAMES
        ax.plot(
            p[:, 0],
            p[:, 2],
            color=_colour(name, i),
            lw=1.6 if is_gt else 1.1 + 0.6 * (len(estimates) - 1 - rank),
            ls="--" if is_gt else "-",
            label=name,
            zorder=1 if is_gt else 2,
        )
    ax.plot([0.0], [0.0], "ko", ms=4, zorder=4)
    if loops:
        on = next((n for n in estimates if n.lower() == "snaps"), estimates[0] if estimates else names[0])
        p = np.asarray(trajs[on])[:, :3, 3]
        pairs = np.asarray(loops, dtype=int).reshape(-1, 2)
        pairs = pairs[(pairs >= 0).all(axis=1) & (pairs < len(p)).all(axis=1)]
        for k, (a, b) in enumerate(pairs):
            ax.plot(
                [p[a, 0], p[b, 0]],
                [p[a, 2], p[b, 2]],
                color="orange",
                lw=0.8,
                zorder=3,
                label=f"loops on {on}" if k == 0 else None,
            )
    ax.set_aspect("equal", adjustable="datalim")
    return _finish(fig, ax, path_png, title, "x [m] (right)", "z [m] (forward)")


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
    """Box plots of latency samples in milliseconds on a log axis (paper Fig. 5).

    A log axis because the stages span five decades (SNAPS without candidates: microseconds;
    a frame: hundreds of milliseconds). Non-positive and non-finite samples cannot sit on a log
    axis and are left out; a series with no sample left is drawn as an empty, labelled slot.
    """
    if not samples:
        raise SnapsGraphError(f"{path_png}: no latency series to plot")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(samples)), 4.5))
    data, labels = [], []
    for name, values in samples.items():
        v = np.asarray(values, dtype=float).reshape(-1)
        data.append(v[np.isfinite(v) & (v > 0)])
        labels.append(f"{name}\n(n={data[-1].size})")
    positions = [i + 1 for i, v in enumerate(data) if v.size]
    if positions:
        ax.boxplot([data[i - 1] for i in positions], positions=positions, showfliers=True, whis=(5, 95))
    ax.set_xlim(0.5, len(labels) + 0.5)
    ax.set_xticks(np.arange(1, len(labels) + 1), labels, fontsize=8)
    ax.set_yscale("log")
    if not positions:  # a log axis needs a range even with nothing on it
        ax.set_ylim(1e-3, 1e3)
    ax.set_ylabel("time per frame [ms] (log)")
    ax.set_title(title + " (whiskers: 5th-95th percentile)")
    ax.grid(True, which="both", axis="y", lw=0.3)
    return _save(fig, path_png)
