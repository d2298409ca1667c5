"""Pictures of a fused map, headless: a top-down view of the surface points (matplotlib's Agg
canvas) and a perspective view of the mesh ray-cast on the CPU with open3d's
``RaycastingScene`` (the GPU ``OffscreenRenderer`` needs EGL or Vulkan, absent on a headless
machine: "Failed to load vulkan library")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SnapsGraphError
from ..io_utils import atomic_output

_GROUND_CELL_M = 5.0  # heights are shown above the lowest map point in this x-z cell
_GROUND_BAND_M = 0.25  # points this close above the local ground are the ground (road, kerb)


def _local_height(ref: np.ndarray, query: np.ndarray | None = None, cell: float = _GROUND_CELL_M) -> np.ndarray:
    """Height (-y) of ``query`` (default ``ref``) above the lowest ``ref`` point in the same
    ``cell`` x ``cell`` metre column: walls and objects stand out from a road that climbs."""
    query = ref if query is None else query
    key_r = np.floor(ref[:, [0, 2]] / cell).astype(np.int64)
    key_q = np.floor(query[:, [0, 2]] / cell).astype(np.int64)
    lo = np.minimum(key_r.min(0), key_q.min(0))
    span = int(max(key_r[:, 1].max(), key_q[:, 1].max()) - lo[1] + 1)
    kr = (key_r[:, 0] - lo[0]) * span + (key_r[:, 1] - lo[1])
    kq = (key_q[:, 0] - lo[0]) * span + (key_q[:, 1] - lo[1])
    cells, inv = np.unique(kr, return_inverse=True)
    ground = np.full(len(cells), -np.inf)
    np.maximum.at(ground, inv, ref[:, 1])  # y points down: the lowest point has the largest y
    i = np.clip(np.searchsorted(cells, kq), 0, len(cells) - 1)
    g = np.where(cells[i] == kq, ground[i], query[:, 1])
    return g - query[:, 1]


def _cluster_vertices(v: np.ndarray, t: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering: vertices in one ``cell`` grid cube merge (their mean); triangles that
    collapse are dropped."""
    key = np.floor(v / cell).astype(np.int64)
    key -= key.min(axis=0)
    dims = key.max(axis=0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    _, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    out_v = np.zeros((len(counts), 3))
    np.add.at(out_v, inv, v)
    out_v /= counts[:, None]
    tt = inv[t]
    keep = (tt[:, 0] != tt[:, 1]) & (tt[:, 1] != tt[:, 2]) & (tt[:, 0] != tt[:, 2])
    return out_v.astype(np.float32), tt[keep].astype(np.uint32)


def _figure(w_in: float, h_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in))
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path, dpi: int) -> None:
    with atomic_output(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")


def _positions(traj: np.ndarray) -> np.ndarray:
    t = np.asarray(traj, dtype=np.float64)
    return t[:, :3, 3] if t.ndim == 3 else t


def _topdown_axes(
    ax,
    points: np.ndarray,
    values: np.ndarray,
    trajectories: dict,
    *,
    cmap: str,
    vmin: float,
    vmax: float,
    max_points: int,
    title: str,
):
    stride = max(1, int(np.ceil(len(points) / max_points)))
    p, v = points[::stride], values[::stride]
    order = np.argsort(v, kind="stable")  # high values drawn last: walls over ground
    sc = ax.scatter(p[order, 0], p[order, 2], c=v[order], s=0.2, cmap=cmap, vmin=vmin, vmax=vmax, linewidths=0, rasterized=True)
    for name, traj in trajectories.items():
        q = _positions(traj)
        ax.plot(q[:, 0], q[:, 2], lw=1.0, label=name)
    if trajectories:
        ax.legend(loc="best", fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(title, fontsize=9)
    return sc


def topdown_png(
    path: str | Path,
    points: np.ndarray,
    trajectories: dict[str, np.ndarray],
    *,
    grey: np.ndarray | None = None,
    title: str = "",
    max_points: int = 300_000,
    dpi: int = 150,
) -> None:
    """Top-down view (x across, z up the page) of surface ``points`` coloured by height above the
    local ground (``_local_height``), with each trajectory ((N, 4, 4) or (N, 3)) drawn over it.

    With ``grey`` (the points' image intensity), the ground itself is drawn in contrast-stretched
    grey: its height is nearly constant, so a height colour shows one flat tone where the image
    shows lane marks, kerbs and shadows."""
    path = Path(path)
    if len(points) == 0:
        raise SnapsGraphError(f"{path}: the map is empty, nothing to draw")
    h = _local_height(points)
    hi = max(float(np.percentile(h, 98)), 1e-3)
    fig = _figure(8, 8)
    ax = fig.add_subplot(1, 1, 1)
    title = title or f"fused map, top-down: {len(points)} surface points"
    if grey is not None and len(grey) == len(points):
        ground = h < _GROUND_BAND_M
        g = np.asarray(grey, dtype=np.float64).reshape(-1)
        glo, ghi = np.percentile(g[ground], [2, 98]) if ground.any() else (0.0, 255.0)
        stride = max(1, int(np.ceil(len(points) / max_points)))
        pg = points[::stride][ground[::stride]]
        ax.scatter(
            pg[:, 0], pg[:, 2], c=g[::stride][ground[::stride]], s=0.2, cmap="gray", vmin=glo, vmax=max(ghi, glo + 1),
            linewidths=0, rasterized=True,
        )  # fmt: skip
        raised = ~ground
        sc = _topdown_axes(
            ax, points[raised], h[raised], trajectories, cmap="viridis", vmin=_GROUND_BAND_M, vmax=max(hi, _GROUND_BAND_M + 1e-3),
            max_points=max_points, title=title,
        )  # fmt: skip
        label = f"height above the local ground (m); ground below {_GROUND_BAND_M:g} m in image grey"
    else:
        sc = _topdown_axes(ax, points, h, trajectories, cmap="viridis", vmin=0.0, vmax=hi, max_points=max_points, title=title)
        label = f"height above the local ground (m; lowest point in {_GROUND_CELL_M:g} m cells)"
    fig.colorbar(sc, ax=ax, shrink=0.7, label=label)
    fig.tight_layout()
    _save(fig, path, dpi)


def side_by_side_png(
    path: str | Path,
    maps: dict[str, tuple[np.ndarray, np.ndarray | None]],
    trajectories: dict[str, np.ndarray],
    *,
    max_points: int = 200_000,
    dpi: int = 120,
    error_max_m: float = 0.5,
) -> None:
    """One top-down panel per trajectory's map (``maps``: name -> (points, error to the true
    surface or None)), same axes; coloured by the error when known, else by height."""
    path = Path(path)
    names = [n for n, (p, _) in maps.items() if len(p)]
    if not names:
        raise SnapsGraphError(f"{path}: no map to draw")
    fig = _figure(6 * len(names), 6.5)
    axes = [fig.add_subplot(1, len(names), i + 1) for i in range(len(names))]
    allp = np.concatenate([maps[n][0] for n in names])
    lo, hi = np.percentile(-allp[:, 1], [2, 98])
    sc = None
    for ax, n in zip(axes, names):
        pts, err = maps[n]
        traj = {n: trajectories[n]} if n in trajectories else {}
        if "gt" in trajectories:
            traj = {"gt": trajectories["gt"], **traj}
        if err is not None:
            sc = _topdown_axes(
                ax,
                pts,
                np.minimum(err, error_max_m),
                traj,
                cmap="inferno_r",
                vmin=0.0,
                vmax=error_max_m,
                max_points=max_points,
                title=f"{n}: p90 error {np.percentile(err, 90):.2f} m",
            )
        else:
            sc = _topdown_axes(
                ax, pts, -pts[:, 1], traj, cmap="viridis", vmin=lo, vmax=max(hi, lo + 1e-3), max_points=max_points, title=n
            )
    xs = [ax.get_xlim() for ax in axes]
    ys = [ax.get_ylim() for ax in axes]
    for ax in axes:
        ax.set_xlim(min(x[0] for x in xs), max(x[1] for x in xs))
        ax.set_ylim(min(y[0] for y in ys), max(y[1] for y in ys))
    label = f"distance to the true surface (m, clipped at {error_max_m:g})" if maps[names[0]][1] is not None else "height -y (m)"
    fig.colorbar(sc, ax=axes, shrink=0.6, label=label)
    _save(fig, path, dpi)


def _round_length(m: float) -> float:
    """The largest of 1, 2, 5 x 10^k metres not above ``m`` (at least 0.1 m)."""
    m = max(float(m), 0.1)
    k = 10.0 ** np.floor(np.log10(m))
    return float(max(f * k for f in (1.0, 2.0, 5.0) if f * k <= m + 1e-9))


def _project(rays: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel (u, v) of each 3D point in the pinhole image whose rays (H, W, 6) are ``rays``: the
    camera's axes and focal length read off the rays themselves (no convention assumed)."""
    h, w = rays.shape[:2]
    eye = rays[0, 0, :3].astype(np.float64)
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    fwd = unit(rays[(h - 1) // 2, (w - 1) // 2, 3:].astype(np.float64) + rays[h // 2, w // 2, 3:])
    right = unit(rays[h // 2, w - 1, 3:] - rays[h // 2, 0, 3:]).astype(np.float64)
    down = unit(rays[h - 1, w // 2, 3:] - rays[0, w // 2, 3:]).astype(np.float64)
    edge = rays[h // 2, w - 1, 3:].astype(np.float64)
    f = ((w - 1) / 2.0) / (edge @ right / (edge @ fwd))
    d = points - eye
    z = np.maximum(d @ fwd, 1e-6)
    return np.stack([(w - 1) / 2.0 + f * (d @ right) / z, (h - 1) / 2.0 + f * (d @ down) / z], axis=1)


def _px(uv: np.ndarray) -> tuple[int, int]:
    return int(round(float(uv[0]))), int(round(float(uv[1])))


def perspective_png(
    path: str | Path,
    vertices: np.ndarray,
    triangles: np.ndarray,
    trajectory: np.ndarray | None = None,
    *,
    width: int = 1100,
    height: int = 620,
    elevation_deg: float = 35.0,
    fov_deg: float = 50.0,
    title: str = "",
) -> None:
    """A perspective view of the mesh from above, turned as the top view (map.png: x to the right,
    z up the page, so seen from -z), ray-cast on the CPU; coloured by height above the local
    ground, shaded by the surface normal; the x and z axes drawn on the ground at the mesh's near
    left corner, as long as the scale they are labelled with (true at that corner's distance)."""
    import cv2

    path = Path(path)
    if len(triangles) == 0:
        raise SnapsGraphError(f"{path}: the mesh is empty, nothing to draw")
    n_triangles = len(triangles)
    lo, hi = np.percentile(vertices, [1, 99], axis=0)
    # Embree's tree costs ~80 B a triangle (KITTI 00: 9.5 M triangles, +0.8 GB): cluster the
    # vertices on a grid of about one pixel's footprint first, which the picture cannot resolve.
    cell = float(np.linalg.norm((hi - lo)[[0, 2]])) / width
    if cell > 0.2:
        vertices, triangles = _cluster_vertices(vertices, triangles, cell)
    centre = (lo + hi) / 2.0
    extent = float(np.linalg.norm((hi - lo)[[0, 2]]))
    r, hit, n, p = _cast_rays(vertices, triangles, centre, extent, width, height, elevation_deg, fov_deg)
    bgr, hhi = _shaded_heights(vertices, hit, n, p)
    bgr, step = _axes_and_frame(bgr, r, hit, vertices, lo, extent)
    w = max(bgr.shape[1], 560)
    if bgr.shape[1] < w:
        bgr = np.hstack([bgr, np.full((bgr.shape[0], w - bgr.shape[1], 3), 255, np.uint8)])
    text = title or f"fused mesh, perspective: {n_triangles} triangles (CPU ray casting)"
    text += f"; seen from -z, turned as the top view; arrows: {step:g} m along x and z"
    ok, buf = cv2.imencode(".png", np.vstack([_legend_bar(w, text, hhi), bgr]))
    if not ok:  # pragma: no cover
        raise SnapsGraphError(f"{path}: could not encode the picture")
    with atomic_output(path, suffix=".png") as tmp:
        Path(tmp).write_bytes(buf.tobytes())


def _cast_rays(vertices, triangles, centre, extent: float, width: int, height: int, elevation_deg: float, fov_deg: float):
    """Rays of the view (H, W, 6), which hit the mesh, the hit normals and points."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)), o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32))
    )
    # look at the centre from -z, raised by elevation_deg: x runs to the right as in the top view
    horiz = np.array([0.0, 0.0, -1.0])
    dist = 0.5 * extent / np.tan(np.deg2rad(fov_deg) / 2.0) * 1.1 + 5.0
    e = np.deg2rad(elevation_deg)
    eye = centre + dist * (np.cos(e) * horiz + np.sin(e) * np.array([0.0, -1.0, 0.0]))
    # open3d's pinhole rays run the image's rows along `up` (first row nearest -up): KITTI's y,
    # pointing down, gives an upright picture (with -y it came out turned by 180 degrees).
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        fov_deg=fov_deg, center=centre.tolist(), eye=eye.tolist(), up=[0.0, 1.0, 0.0], width_px=width, height_px=height
    )
    ans = scene.cast_rays(rays)
    t = ans["t_hit"].numpy()
    n = ans["primitive_normals"].numpy()
    hit = np.isfinite(t)
    r = rays.numpy()
    p = r[..., :3] + r[..., 3:] * np.where(hit, t, 0.0)[..., None]
    return r, hit, n, p


def _shaded_heights(vertices, hit, n, p) -> tuple[np.ndarray, float]:
    """The BGR picture: height above the local ground in viridis, shaded by the normal; white
    where no ray hit. Also the height at the colour scale's top (98th percentile)."""
    from matplotlib import colormaps

    hgt = np.zeros(hit.shape)
    if hit.any():
        hgt[hit] = _local_height(vertices.astype(np.float64), p[hit].astype(np.float64))
    hlo, hhi = (0.0, max(float(np.percentile(hgt[hit], 98)), 1e-3)) if hit.any() else (0.0, 1.0)
    rgb = colormaps["viridis"](np.clip((hgt - hlo) / max(hhi - hlo, 1e-3), 0, 1))[..., :3]
    light = np.array([0.3, -1.0, -0.4])
    light /= np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.abs(n @ light)
    img = np.where(hit[..., None], rgb * shade[..., None], 1.0)
    return np.ascontiguousarray((img[..., ::-1] * 255).astype(np.uint8)), hhi


def _axes_and_frame(bgr, r, hit, vertices, lo, extent: float) -> tuple[np.ndarray, float]:
    """Axes on the ground at the near left corner, each a round length (about a fifth of the
    map), then the picture cropped to the mesh and the axes. Returns it and the axes' length."""
    import cv2

    step = _round_length(extent / 5.0)
    ground_y = float(np.percentile(vertices[:, 1], 90))  # y down: the ground lies low in the mesh
    origin = np.array([lo[0], ground_y, lo[2]])
    ends = {"x": origin + [step, 0.0, 0.0], "z": origin + [0.0, 0.0, step]}
    uv = _project(r, np.vstack([origin, *ends.values()]))
    for (name, _), end in zip(ends.items(), uv[1:]):
        cv2.arrowedLine(bgr, _px(uv[0]), _px(end), (0, 0, 0), 2, cv2.LINE_AA, tipLength=0.12)
        cv2.putText(bgr, name, _px(end + 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    top, left = 0, 0
    if hit.any():  # framed on the mesh and the axes: the rays that missed are only margin
        rows, cols = np.nonzero(hit.any(axis=1))[0], np.nonzero(hit.any(axis=0))[0]
        m = 10
        r0 = int(min(rows[0], uv[:, 1].min()) - m)
        r1 = int(max(rows[-1], uv[:, 1].max()) + m + 1)
        c0 = int(min(cols[0], uv[:, 0].min()) - m)
        c1 = int(max(cols[-1], uv[:, 0].max()) + m + 1)
        top, left = max(r0, 0), max(c0, 0)
        bgr = bgr[top:r1, left:c1]
    return bgr, step


def _legend_bar(w: int, text: str, hhi: float) -> np.ndarray:
    """The title line and the colour legend: height above the local ground, 0 to ``hhi``."""
    import cv2
    from matplotlib import colormaps

    bar = np.full((52, w, 3), 255, np.uint8)
    cv2.putText(bar, text, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ramp = colormaps["viridis"](np.linspace(0.0, 1.0, 200))[:, :3][:, ::-1]
    bar[30:44, 60:260] = (ramp[None, :, :] * 255).astype(np.uint8)
    cv2.putText(bar, "0 m", (28, 42), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, f"{hhi:.1f} m above the local ground", (266, 42), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return bar
