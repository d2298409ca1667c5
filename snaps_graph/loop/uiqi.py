"""Universal image quality index (Wang & Bovik 2002; the paper's eq. 4-5) and thumbnails.

Q = 4·σxy·x̄·ȳ / ((σx² + σy²)(x̄² + ȳ²)) in every B×B window fully inside the image (step 1),
averaged; each window's Q is the product of its correlation, luminance and contrast, kept because
they make a loop interpretable. All of it comes from float64 box-filter window sums (exact for
8-bit images); the per-image part (:func:`window_stats`) is computed once per thumbnail. The
arithmetic and the rules for zero denominators: docs/loop-closure.md, "The similarity".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import SnapsGraphError

# A window whose N·Sxx − Sx² is below this fraction of N·Sxx is flat (docs/loop-closure.md).
_FLAT_REL_TOL = 1e-10
# Up to this window size, uint8 products and their window sums are integers below 2^24 (float32-exact).
_EXACT_F32_WINDOW = 16


@dataclass(frozen=True, eq=False)
class UIQI:
    """The index of one image pair: means over all windows of the per-window values.

    ``q`` is the mean of the per-window Q; ``correlation``, ``luminance`` and ``contrast`` are the
    means of the per-window factors (so ``q`` is *not* the product of the three means, but each
    window's Q is the product of that window's factors). The ``*_map`` fields are the per-window
    values, shape (H-B+1, W-B+1), only when ``return_maps=True``.
    """

    q: float
    correlation: float
    luminance: float
    contrast: float
    q_map: np.ndarray | None = None
    correlation_map: np.ndarray | None = None
    luminance_map: np.ndarray | None = None
    contrast_map: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class WindowStats:
    """Per-image window sums for one window size: everything Q needs except the cross term.

    ``image`` is the image used for the cross term (the caller's uint8 array itself, not a copy,
    or a float64 copy of any other type); ``s`` = Σx and ``v`` = N·Σx² − (Σx)² per valid window
    (float64, shape (H-B+1, W-B+1)); ``special`` says some window is flat or has a zero sum, so the
    slower branch with the zero-denominator rules is needed.
    """

    image: np.ndarray
    s: np.ndarray
    v: np.ndarray
    window: int
    special: bool

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]

    @property
    def nbytes(self) -> int:
        """Memory held by the statistics (not counting a shared uint8 image)."""
        extra = 0 if self.image.dtype == np.uint8 else self.image.nbytes
        return self.s.nbytes + self.v.nbytes + extra


def _window_sums(img: np.ndarray, window: int) -> np.ndarray:
    """Sum over every B×B window fully inside the image, float64: out[i, j] = img[i:i+B, j:j+B].sum()."""
    h, w = img.shape
    full = cv2.boxFilter(img, cv2.CV_64F, (window, window), anchor=(0, 0), normalize=False)
    return full[: h - window + 1, : w - window + 1]


def _check_image(image: np.ndarray, window: int, what: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2:
        raise SnapsGraphError(f"UIQI: {what} must be a 2-D grey image, got shape {image.shape}")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 2:
        raise SnapsGraphError(f"UIQI: window must be an integer >= 2 (eq. 5 divides by N-1), got {window}")
    if image.shape[0] < window or image.shape[1] < window:
        raise SnapsGraphError(
            f"UIQI: {what} of {image.shape[1]}x{image.shape[0]} pixels is smaller than the {window}x{window} window"
        )
    if image.dtype != np.uint8 and not np.all(np.isfinite(image)):
        raise SnapsGraphError(f"UIQI: {what} contains NaN or infinite pixels")
    return image


def window_stats(image: np.ndarray, window: int = 8) -> WindowStats:
    """Per-image part of Q (window sums Sx and Vx = N·Sxx − Sx²), computed once per image."""
    image = _check_image(image, window, "image")
    window = int(window)
    n = float(window * window)
    h, w = image.shape
    src = image if image.dtype == np.uint8 else image.astype(np.float64)
    # Sums straight from uint8 into float64: integer sums, exact and cheaper than converting first.
    s = _window_sums(src, window)
    sq = cv2.sqrBoxFilter(src, cv2.CV_64F, (window, window), anchor=(0, 0), normalize=False)
    nss = n * sq[: h - window + 1, : w - window + 1]
    v = nss - s * s
    if image.dtype == np.uint8:  # integer sums: v is exact, flat means v == 0
        special = not (v.all() and s.all())
    else:  # flat windows and round-off below zero
        v[v <= _FLAT_REL_TOL * nss] = 0.0
        special = bool(np.any(v == 0.0) or np.any(s == 0.0))
    return WindowStats(image=src, s=s, v=v, window=window, special=special)


def _cross(a: WindowStats, b: WindowStats) -> np.ndarray:
    """Cxy = N·Σxy − Σx·Σy per window (N(N−1)·σxy of eq. 5), a new float64 array."""
    if a.window != b.window:
        raise SnapsGraphError(f"UIQI: window sizes differ ({a.window} vs {b.window})")
    if a.shape != b.shape:
        raise SnapsGraphError(f"UIQI: image sizes differ ({a.shape[1]}x{a.shape[0]} vs {b.shape[1]}x{b.shape[0]})")
    if a.image.dtype == np.uint8 and b.image.dtype == np.uint8 and a.window <= _EXACT_F32_WINDOW:
        # Products <= 255² and their window sums <= 16·16·255² < 2^24: exact in float32, cheaper.
        prod = cv2.multiply(a.image, b.image, dtype=cv2.CV_32F)
    else:
        prod = np.multiply(a.image, b.image, dtype=np.float64)
    cxy = _window_sums(prod, a.window)
    cxy *= float(a.window * a.window)
    cxy -= a.s * b.s
    return cxy


def _factor_maps(a: WindowStats, b: WindowStats, cxy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correlation, luminance and contrast per window, with the zero-denominator rules."""
    vxy = a.v * b.v
    vsum = a.v + b.v
    msum = a.s * a.s + b.s * b.s
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cxy / np.sqrt(vxy)
        lum = 2.0 * a.s * b.s / msum
        con = 2.0 * np.sqrt(vxy) / vsum
    both_flat = vsum == 0.0
    one_flat = (vxy == 0.0) & ~both_flat
    corr[both_flat] = 1.0
    corr[one_flat] = 0.0
    con[both_flat] = 1.0
    lum[msum == 0.0] = 1.0
    return corr, lum, con


def similarity(a: WindowStats, b: WindowStats, return_maps: bool = False) -> UIQI:
    """The full index (Q and its three factors) of two prepared images."""
    corr, lum, con = _factor_maps(a, b, _cross(a, b))
    q = corr * lum * con
    res: dict[str, Any] = dict(
        q=float(q.mean()), correlation=float(corr.mean()), luminance=float(lum.mean()), contrast=float(con.mean())
    )
    if return_maps:
        res.update(q_map=q, correlation_map=corr, luminance_map=lum, contrast_map=con)
    return UIQI(**res)


def similarity_q(a: WindowStats, b: WindowStats) -> float:
    """Mean Q only (eq. 4), the fast path SNAPS uses to rank candidates.

    Where neither image has a flat or zero-sum window (the normal case for camera images), Q is the
    closed form 4·Cxy·Sx·Sy / ((Vx+Vy)(Sx²+Sy²)) with no masks; otherwise it falls back to the
    product of the factor maps so the zero-denominator rules apply. Agrees with
    :func:`similarity` to round-off (~1e-15).
    """
    cxy = _cross(a, b)
    if a.special or b.special:
        corr, lum, con = _factor_maps(a, b, cxy)
        return float((corr * lum * con).mean())
    # In place, fewest passes: Q = 4·Cxy·SxSy / ((Vx+Vy)(Sx²+Sy²)).
    sxy = a.s * b.s
    cxy *= sxy
    den = np.square(a.s)
    den += np.square(b.s)
    den *= a.v + b.v
    cxy /= den
    return 4.0 * float(cxy.mean())


def columns(a: WindowStats, c0: int, c1: int) -> WindowStats:
    """The statistics of the image's columns [c0, c1): a view, no recomputation.

    A window lies inside the crop exactly when it starts at a column in [c0, c1 - B], so the
    crop's window sums are a column slice of the full image's. ``special`` is inherited (a crop
    of an image without flat windows has none; otherwise the exact masked branch runs).
    """
    b = a.window
    if not 0 <= c0 < c1 <= a.shape[1] or c1 - c0 < b:
        raise SnapsGraphError(f"UIQI: column crop [{c0}, {c1}) does not hold a {b}-pixel window")
    return WindowStats(image=a.image[:, c0:c1], s=a.s[:, c0 : c1 - b + 1], v=a.v[:, c0 : c1 - b + 1], window=b, special=a.special)


def shifted_pair(a: WindowStats, b: WindowStats, dx: int, margin: int) -> tuple[WindowStats, WindowStats]:
    """The columns compared at shift ``dx``: a's central columns [margin, W - margin) against b's
    columns moved by dx, so a[:, x] meets b[:, x + dx] (|dx| <= margin). Every shift compares
    the same number of windows, which keeps the scores of different shifts comparable."""
    w = a.shape[1]
    if abs(dx) > margin:
        raise SnapsGraphError(f"UIQI: shift {dx} exceeds the margin {margin}")
    return columns(a, margin, w - margin), columns(b, margin + dx, w - margin + dx)


@dataclass
class _Workspace:
    prods: np.ndarray
    sums: np.ndarray
    sb: np.ndarray
    vb: np.ndarray
    t1: np.ndarray
    t2: np.ndarray


_WORKSPACES: dict[tuple[int, ...], _Workspace] = {}


def _workspace(ns: int, h: int, wc: int, hv: int, wv: int) -> _Workspace:
    """Buffers for :func:`similarity_shifted`, kept per shape: fresh large arrays page-fault on
    every call (docs/decisions.md, "Speed")."""
    key = (ns, h, wc, hv, wv)
    ws = _WORKSPACES.get(key)
    if ws is None:
        f = np.float32
        ws = _Workspace(
            np.empty((ns, h, wc), f),
            np.empty((ns * h, wc), f),
            np.empty((ns, hv, wv), f),
            np.empty((ns, hv, wv), f),
            np.empty((ns, hv, wv), f),
            np.empty((ns, hv, wv), f),
        )
        _WORKSPACES.clear()  # one thumbnail shape per run: keep only the latest
        _WORKSPACES[key] = ws
    return ws


def similarity_shifted(a: WindowStats, b: WindowStats, max_shift: int, step: int = 1) -> tuple[float, int]:
    """Rank horizontal shifts: the mean Q of a's central columns against b's columns moved by dx
    (:func:`shifted_pair`), dx in [-max_shift, max_shift] every ``step`` pixels; returns (Q at the
    best shift, that dx). All shifts are box-filtered in one stacked call and scored in float32
    (within about 1e-6 of :func:`uiqi`: enough to rank); a loop's reported Q and factors are
    computed exactly by :func:`similarity` on :func:`shifted_pair`.
    """
    if a.shape != b.shape or a.window != b.window:
        raise SnapsGraphError(f"UIQI: image sizes differ ({a.shape[1]}x{a.shape[0]} vs {b.shape[1]}x{b.shape[0]})")
    h, w = a.shape
    win = a.window
    m = int(max(0, min(max_shift, (w - win) // 2)))
    shifts = list(range(-m, m + 1, max(1, int(step))))
    if len(shifts) == 1 or a.special or b.special:  # exact path for flat windows (rare in images)
        scored = [(similarity_q(*shifted_pair(a, b, dx, m)), dx) for dx in shifts]
        q, dx = max(scored, key=lambda t: (t[0], -abs(t[1])))
        return float(q), dx
    ns = len(shifts)
    wc = w - 2 * m
    hv, wv = h - win + 1, wc - win + 1
    ws = _workspace(ns, h, wc, hv, wv)
    ca = a.image[:, m : w - m]
    for i, dx in enumerate(shifts):
        np.multiply(ca, b.image[:, m + dx : w - m + dx], out=ws.prods[i], dtype=np.float32)
        ws.sb[i] = b.s[:, m + dx : m + dx + wv]
        ws.vb[i] = b.v[:, m + dx : m + dx + wv]
    cv2.boxFilter(ws.prods.reshape(ns * h, wc), cv2.CV_32F, (win, win), dst=ws.sums, anchor=(0, 0), normalize=False)
    sxy = ws.sums.reshape(ns, h, wc)[:, :hv, :wv]
    sa = a.s[:, m : m + wv].astype(np.float32)
    va = a.v[:, m : m + wv].astype(np.float32)
    # Q = 4 (N Sxy - SaSb) SaSb / ((Va + Vb)(Sa^2 + Sb^2)), in place on the workspace.
    sab, num, den = ws.t1, ws.t2, ws.vb
    np.multiply(ws.sb, sa, out=sab)
    np.multiply(sxy, float(win * win), out=num)
    num -= sab
    num *= sab
    den += va
    np.multiply(ws.sb, ws.sb, out=ws.sb)
    ws.sb += sa * sa
    den *= ws.sb
    num /= den
    means = num.reshape(ns, -1).mean(axis=1, dtype=np.float64)
    best = int(np.argmax(means))
    return 4.0 * float(means[best]), shifts[best]


def uiqi(x: np.ndarray, y: np.ndarray, window: int = 8, return_maps: bool = False) -> UIQI:
    """Universal image quality index of two same-size grey images (eq. 4-5), B×B windows, step 1.

    The mean Q and mean factors over all (H-B+1)×(W-B+1) windows, and the per-window maps with
    ``return_maps=True``. Raises :class:`SnapsGraphError` for mismatched sizes, images smaller than
    the window, or non-finite pixels.
    """
    return similarity(window_stats(x, window), window_stats(y, window), return_maps=return_maps)


def make_thumbnail(image: np.ndarray, scale: float = 1.0 / 6.0) -> np.ndarray:
    """The paper's thumbnail (§III-A): the grey image rescaled by ``scale`` with area interpolation.

    Size: (round(W·scale), round(H·scale)), e.g. 1241×376 -> 207×63 at 1/6. A uint8 image gives a
    uint8 thumbnail (OpenCV rounds the area average; 8-bit keeps thumbnails 13 KB each and makes
    UIQI's sums exact integers); any other type gives float32. ``scale = 1`` returns a copy.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise SnapsGraphError(f"thumbnail: expected a 2-D grey image, got shape {image.shape}")
    if not 0.0 < scale <= 1.0:
        raise SnapsGraphError(f"thumbnail: scale must be in (0, 1], got {scale}")
    if image.dtype != np.uint8:
        image = image.astype(np.float32)
    h, w = image.shape
    size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
    if size == (w, h):
        return image.copy()
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)
