"""UIQI (eq. 4-5) against a direct per-window reference, known values and the zero-denominator rules."""

from __future__ import annotations

import numpy as np
import pytest

from snaps_graph.errors import SnapsGraphError
from snaps_graph.loop.uiqi import make_thumbnail, similarity, similarity_q, uiqi, window_stats


def reference_maps(x: np.ndarray, y: np.ndarray, B: int) -> dict[str, np.ndarray]:
    """Plain per-window loop with eq. 5's unbiased statistics and the documented rules."""
    x = x.astype(np.float64)
    y = y.astype(np.float64)
    H, W = x.shape
    out = {k: np.empty((H - B + 1, W - B + 1)) for k in ("q", "corr", "lum", "con")}
    for i in range(H - B + 1):
        for j in range(W - B + 1):
            wx = x[i : i + B, j : j + B].ravel()
            wy = y[i : i + B, j : j + B].ravel()
            mx, my = wx.mean(), wy.mean()
            vx, vy = wx.var(ddof=1), wy.var(ddof=1)
            cxy = np.sum((wx - mx) * (wy - my)) / (wx.size - 1)
            if vx == 0 and vy == 0:
                corr, con = 1.0, 1.0
            elif vx == 0 or vy == 0:
                corr, con = 0.0, 0.0
            else:
                corr = cxy / np.sqrt(vx * vy)
                con = 2 * np.sqrt(vx * vy) / (vx + vy)
            lum = 1.0 if mx == 0 and my == 0 else 2 * mx * my / (mx * mx + my * my)
            out["corr"][i, j], out["lum"][i, j], out["con"][i, j] = corr, lum, con
            out["q"][i, j] = corr * lum * con
    return out


def assert_matches_reference(x: np.ndarray, y: np.ndarray, B: int) -> None:
    ref = reference_maps(x, y, B)
    res = uiqi(x, y, window=B, return_maps=True)
    assert res.q_map is not None and res.correlation_map is not None
    assert res.luminance_map is not None and res.contrast_map is not None
    np.testing.assert_allclose(res.q_map, ref["q"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.correlation_map, ref["corr"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.luminance_map, ref["lum"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.contrast_map, ref["con"], rtol=0, atol=1e-9)
    assert res.q == pytest.approx(ref["q"].mean(), abs=1e-9)
    assert res.correlation == pytest.approx(ref["corr"].mean(), abs=1e-9)
    assert res.luminance == pytest.approx(ref["lum"].mean(), abs=1e-9)
    assert res.contrast == pytest.approx(ref["con"].mean(), abs=1e-9)


def test_matches_reference_random_uint8_and_float():
    rng = np.random.default_rng(1)
    x = rng.integers(0, 256, (20, 31), dtype=np.uint8)
    y = np.clip(x.astype(int) + rng.integers(-40, 41, x.shape), 0, 255).astype(np.uint8)
    assert_matches_reference(x, y, 8)
    assert_matches_reference(x, y, 5)
    xf = rng.uniform(0, 255, (17, 23))
    yf = 0.6 * xf + rng.normal(0, 20, xf.shape) + 30
    assert_matches_reference(xf, yf, 8)


def test_matches_reference_on_kitti_thumbnails(kitti06_dir):
    from snaps_graph.datasets.kitti import KittiSequence

    seq = KittiSequence(kitti06_dir)
    a = make_thumbnail(seq[0].left)
    b = make_thumbnail(seq[12].left)
    assert a.dtype == np.uint8 and a.shape == (62, 204)  # 1226x370 / 6
    assert_matches_reference(a, b, 8)
    # Nearby frames of the same street are more alike than distant ones.
    assert uiqi(a, make_thumbnail(seq[1].left)).q > uiqi(a, make_thumbnail(seq[50].left)).q


def test_hand_computed_single_window():
    # x = [1 2; 3 4], y = [2 2; 3 5], B = 2: x̄ = 2.5, ȳ = 3, σx² = 5/3, σy² = 2, σxy = 5/3
    # Q = 4·(5/3)·2.5·3 / ((5/3 + 2)(6.25 + 9)) = 600/671
    x = np.array([[1, 2], [3, 4]], dtype=np.uint8)
    y = np.array([[2, 2], [3, 5]], dtype=np.uint8)
    r = uiqi(x, y, window=2)
    assert r.q == pytest.approx(600 / 671, abs=1e-12)
    assert r.correlation == pytest.approx((5 / 3) / np.sqrt(10 / 3), abs=1e-12)
    assert r.luminance == pytest.approx(60 / 61, abs=1e-12)
    assert r.contrast == pytest.approx(2 * np.sqrt(10 / 3) / (11 / 3), abs=1e-12)


def test_scaled_image_has_known_q():
    # y = a·x: correlation 1, luminance = contrast = 2a/(1+a²) in every window, so Q = (2a/(1+a²))².
    rng = np.random.default_rng(2)
    x = (2 * rng.integers(1, 128, (30, 40))).astype(np.uint8)
    r = uiqi(x, x // 2)
    assert r.q == pytest.approx(0.64, abs=1e-12)
    assert r.correlation == pytest.approx(1.0, abs=1e-12)
    assert r.luminance == pytest.approx(0.8, abs=1e-12)
    assert r.contrast == pytest.approx(0.8, abs=1e-12)


def test_identity_symmetry_and_factors_multiply():
    rng = np.random.default_rng(3)
    x = rng.integers(0, 256, (25, 30), dtype=np.uint8)
    y = rng.integers(0, 256, (25, 30), dtype=np.uint8)
    assert uiqi(x, x).q == pytest.approx(1.0, abs=1e-12)
    rxy, ryx = uiqi(x, y, return_maps=True), uiqi(y, x, return_maps=True)
    assert rxy.q_map is not None and ryx.q_map is not None and rxy.correlation_map is not None
    assert rxy.luminance_map is not None and rxy.contrast_map is not None
    np.testing.assert_allclose(rxy.q_map, ryx.q_map, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rxy.q_map, rxy.correlation_map * rxy.luminance_map * rxy.contrast_map, atol=1e-15)
    assert rxy.q_map.shape == (25 - 8 + 1, 30 - 8 + 1)
    assert abs(rxy.q) < 0.1  # independent textures: no correlation


def test_flat_windows_get_the_defined_values():
    B = 4
    a = np.full((4, 4), 100, np.uint8)
    b = np.full((4, 4), 50, np.uint8)
    z = np.zeros((4, 4), np.uint8)
    tex = np.arange(16, dtype=np.uint8).reshape(4, 4) * 10
    assert uiqi(a, a, B).q == 1.0
    assert uiqi(z, z, B).q == 1.0  # both means 0 and both flat
    r = uiqi(a, b, B)
    assert r.q == pytest.approx(2 * 100 * 50 / (100**2 + 50**2), abs=1e-15)  # luminance only
    assert (r.correlation, r.contrast) == (1.0, 1.0)
    r = uiqi(a, tex, B)
    assert r.q == 0.0 and r.correlation == 0.0 and r.contrast == 0.0
    # Mixed image: flat left half, textured right half; compare the maps to the reference.
    rng = np.random.default_rng(4)
    x = np.full((12, 20), 80, np.uint8)
    x[:, 10:] = rng.integers(0, 256, (12, 10))
    y = x.copy()
    y[:, :6] = 120
    assert_matches_reference(x, y, 4)
    assert np.isfinite(uiqi(x, y, 4).q)


def test_fast_path_equals_full_index():
    rng = np.random.default_rng(5)
    x = rng.integers(0, 256, (63, 207), dtype=np.uint8)
    y = np.clip(x.astype(int) + rng.normal(0, 30, x.shape), 0, 255).astype(np.uint8)
    sx, sy = window_stats(x), window_stats(y)
    assert not sx.special and not sy.special
    assert similarity_q(sx, sy) == pytest.approx(uiqi(x, y).q, abs=1e-13)
    assert similarity(sx, sy).q == uiqi(x, y).q
    # The special branch (a flat patch) agrees too.
    x[:20, :20] = 7
    sx = window_stats(x)
    assert sx.special
    assert similarity_q(sx, sy) == pytest.approx(uiqi(x, y).q, abs=1e-13)


def test_q_decreases_with_noise():
    rng = np.random.default_rng(6)
    base = rng.uniform(40, 200, (63, 207))
    qs = [uiqi(base, base + rng.normal(0, s, base.shape)).q for s in (0.0, 5.0, 20.0, 60.0)]
    assert qs[0] == pytest.approx(1.0)
    assert qs[0] > qs[1] > qs[2] > qs[3]


def test_thumbnail_size_and_type():
    img = np.random.default_rng(7).integers(0, 256, (376, 1241), dtype=np.uint8)
    t = make_thumbnail(img)
    assert t.shape == (63, 207) and t.dtype == np.uint8
    # Area interpolation: a 6x6 block average (INTER_AREA at an integer factor).
    sq = np.kron(np.arange(12, dtype=np.uint8).reshape(3, 4) * 20, np.ones((6, 6), np.uint8))
    np.testing.assert_array_equal(make_thumbnail(sq), np.arange(12).reshape(3, 4) * 20)
    assert make_thumbnail(img.astype(np.float64)).dtype == np.float32


def test_bad_input_is_a_clear_error():
    x = np.zeros((10, 10), np.uint8)
    with pytest.raises(SnapsGraphError, match="sizes differ"):
        uiqi(x, np.zeros((10, 11), np.uint8))
    with pytest.raises(SnapsGraphError, match="smaller than"):
        uiqi(x[:5], x[:5])
    with pytest.raises(SnapsGraphError, match="NaN"):
        uiqi(np.full((10, 10), np.nan), x)
    with pytest.raises(SnapsGraphError, match="2-D"):
        uiqi(np.zeros((10, 10, 3)), np.zeros((10, 10, 3)))
    with pytest.raises(SnapsGraphError, match="window"):
        uiqi(x, x, window=1)


def test_thumbnail_shape_matches_the_thumbnail_and_the_cache_is_bounded():
    from snaps_graph.loop.uiqi import STATS_CACHE_FRAMES, Thumbnails, make_thumbnail, thumbnail_shape, window_stats

    for h, w in [(376, 1241), (370, 1226), (7, 5)]:
        img = np.zeros((h, w), np.uint8)
        assert make_thumbnail(img, 1 / 6).shape == thumbnail_shape((h, w), 1 / 6)
    rng = np.random.default_rng(4)
    store = Thumbnails(8)
    for _ in range(STATS_CACHE_FRAMES + 2):
        store.append(rng.integers(0, 256, (12, 12), dtype=np.uint8))
    first = store.stats(0)
    np.testing.assert_array_equal(first.v, window_stats(store[0], 8).v)
    assert store.stats(0) is first and store.cached(0) is first  # cached, not recomputed
    for k in range(1, STATS_CACHE_FRAMES + 1):
        store.stats(k)
    assert store.cached(0) is None and store.cached(STATS_CACHE_FRAMES) is not None  # the oldest went
