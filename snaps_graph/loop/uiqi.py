"""Universal image quality index (Wang & Bovik 2002; the paper's eq. 4-5) and thumbnails.

Q = 4·σxy·x̄·ȳ / ((σx² + σy²)(x̄² + ȳ²)) in every B×B window fully inside the image (step 1),
averaged; each window's Q is the product of its correlation, luminance and contrast, kept because
they make a loop interpretable. All of it comes from float64 box-filter window sums (exact for
8-bit images); the per-image part (:func:`window_stats`) is computed once per thumbnail. The
arithmetic and the rules for zero denominators: docs/loop-closure.md, "The similarity".
"""

from __future__ import annotations

from collections import OrderedDict
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
    th, tw = thumbnail_shape((h, w), scale)
    size = (tw, th)
    if size == (w, h):
        return image.copy()
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def thumbnail_shape(shape: tuple[int, ...], scale: float) -> tuple[int, int]:
    """(rows, columns) of :func:`make_thumbnail`'s thumbnail of an image of ``shape``."""
    h, w = shape[:2]
    return max(1, int(round(h * scale))), max(1, int(round(w * scale)))


# Thumbnails whose window sums are kept (~180 KB each at 1/6 of KITTI's size): a loop's candidates
# come back frame after frame, and 512 cover the candidates of a revisit with room to spare.
STATS_CACHE_FRAMES = 512


class Thumbnails:
    """Every frame's thumbnail (13 KB at 1/6 of KITTI's size) and a bounded cache of their
    window sums, by stream position."""

    def __init__(self, window: int, thumbs: Any = None, cache_frames: int = STATS_CACHE_FRAMES):
        """``thumbs``: thumbnails already made (a prior session's, an (N, h, w) array, read by
        row), else an empty list :meth:`append` grows; ``cache_frames``: window sums kept."""
        self.window = window
        self._thumbs: Any = [] if thumbs is None else thumbs
        self._stats: OrderedDict[int, WindowStats] = OrderedDict()
        self._cache_frames = cache_frames

    def __len__(self) -> int:
        return len(self._thumbs)

    def __getitem__(self, k: int) -> np.ndarray:
        return self._thumbs[k]

    def append(self, thumb: np.ndarray) -> None:
        """Keep the next frame's thumbnail (:func:`make_thumbnail`)."""
        self._thumbs.append(thumb)

    def stats(self, k: int) -> WindowStats:
        """The window sums of thumbnail ``k``, from the cache or computed and cached."""
        cache = self._stats
        st = cache.get(k)
        if st is not None:
            cache.move_to_end(k)
            return st
        st = window_stats(self._thumbs[k], self.window)
        cache[k] = st
        if len(cache) > self._cache_frames:
            cache.popitem(last=False)
        return st

    def cached(self, k: int) -> WindowStats | None:
        """The cached window sums of thumbnail ``k``, without computing them."""
        return self._stats.get(k)
