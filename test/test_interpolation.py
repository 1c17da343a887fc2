"""DEM refinement (dissertation 2.1.3): IDW and splines beat nearest on real terrain."""

import numpy as np
import pytest

from terrain_nav_ros.core.terrain.dem_io import open_dem, sample_dem
from terrain_nav_ros.core.terrain.interpolation import (
    METHODS,
    decimate,
    idw,
    idw_grid,
    refine,
    refine_coords,
)


def test_idw_basics():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    vals = np.array([1.0, 2.0, 3.0, 4.0])
    # passes through the samples, and the centre is the plain mean
    assert np.allclose(idw(pts, vals, pts, k=4), vals)
    assert idw(pts, vals, [[0.5, 0.5]], k=4) == pytest.approx([2.5])
    # a constant field stays constant; values stay within the sample range
    q = np.random.default_rng(0).uniform(-1, 2, (100, 2))
    assert np.allclose(idw(pts, np.full(4, 7.0), q, k=3), 7.0)
    z = idw(pts, vals, q, k=4)
    assert z.min() >= 1 and z.max() <= 4
    # a higher power is more local: closer to the nearest sample
    near = idw(pts, vals, [[0.2, 0.1]], k=4, power=8)[0]
    far = idw(pts, vals, [[0.2, 0.1]], k=4, power=1)[0]
    assert abs(near - 1.0) < abs(far - 1.0)
    # outside max_distance: NaN
    assert np.isnan(idw(pts, vals, [[10.0, 10.0]], k=2, max_distance=1.0)[0])


def test_idw_grid_skips_voids_and_uses_metric_distances():
    z = np.arange(20, dtype=np.float32).reshape(4, 5)
    z[1, 2] = np.nan
    out = idw_grid(z, [2.0, 0.0], [1.0, 0.0], k=4)
    assert np.isfinite(out).all() and out[1] == pytest.approx(0.0, abs=1e-6)
    # with cells 3x wider than tall, the row neighbours are the near ones
    z2 = np.array([[0.0, 10.0], [1.0, 11.0]], dtype=np.float32)
    wide = idw_grid(z2, [0.0], [0.4], k=3, aspect=3.0)[0]
    assert wide < 1.0


def test_refine_geometry():
    assert np.allclose(refine_coords(3, 2), [-0.25, 0.25, 0.75, 1.25, 1.75, 2.25])
    z = np.random.default_rng(1).normal(size=(10, 13)).astype(np.float32)
    for m in METHODS:
        out = refine(z, 2, m)
        assert out.shape == (20, 26) and out.dtype == np.float32
        assert np.isfinite(out).all()
    assert refine(z, 2.5, "bicubic").shape == (25, 32)
    # refining 10 m -> 5 m -> 2.5 m composes to 10 m -> 2.5 m (same grid convention)
    assert np.allclose(refine(refine(z, 2, "bilinear"), 2, "bilinear").shape, (40, 52))
    with pytest.raises(ValueError, match="kriging"):
        refine(z, 2, "kriging")


@pytest.mark.parametrize("method", ["bilinear", "bicubic", "spline"])
def test_refine_reproduces_a_plane(method):
    rows, cols = np.mgrid[0:12, 0:15]
    z = (3.0 * cols - 2.0 * rows + 100).astype(np.float32)
    out = refine(z, 4, method)
    rr, cc = refine_coords(12, 4), refine_coords(15, 4)
    truth = 3.0 * cc[None, :] - 2.0 * rr[:, None] + 100
    inner = np.s_[8:-8, 8:-8]  # edges are clamped (replicated)
    assert np.abs(out[inner] - truth[inner]).max() < 1e-3


def test_spline_is_interpolating_and_masks_voids():
    z = np.random.default_rng(2).normal(size=(9, 9)).astype(np.float32)
    out = refine(z, 3, "spline")
    assert np.allclose(out[1::3, 1::3], z, atol=1e-5)  # odd factor: centres coincide
    z[4, 4] = np.nan
    out = refine(z, 3, "spline")
    assert np.isnan(out[13, 13]) and np.isfinite(out[1, 1])
    assert np.isnan(refine(z, 3, "bilinear")[13, 13])


def test_decimate_is_block_mean():
    z = np.arange(16, dtype=np.float32).reshape(4, 4)
    assert np.array_equal(decimate(z, 2), [[2.5, 4.5], [10.5, 12.5]])
    assert decimate(np.ones((5, 7)), 2).shape == (2, 3)


def _real_dems(shared_data):
    yield "jacksboro (matplotlib)", sample_dem().read(), 1.0
    for rel, aspect in [("dem/N44E005.hgt", 0.72), ("dem/bigtujunga_srtm30m_utm11.tif", 1.0),
                        ("dem/front_range_srtm3.asc", 0.76), ("dem/gredos_25m_epsg23030.tif", 1.0),
                        ("dem/halffork_5m.asc", 1.0)]:
        yield rel, open_dem(shared_data / rel).read(), aspect


@pytest.mark.parametrize("factor", [2, 4])
def test_decimate_then_refine_beats_nearest_on_real_dems(shared_data, factor):
    for name, z, aspect in _real_dems(shared_data):
        # a 160 x 160 crop with data keeps IDW quick
        rows, cols = np.nonzero(~np.isnan(z))
        r0, c0 = int(np.median(rows)) - 80, int(np.median(cols)) - 80
        crop = z[max(r0, 0):max(r0, 0) + 160, max(c0, 0):max(c0, 0) + 160]
        coarse = decimate(crop, factor)
        truth = crop[:coarse.shape[0] * factor, :coarse.shape[1] * factor]
        rmse = {}
        for m in METHODS:
            out = refine(coarse, factor, m, aspect=aspect, k=8, power=2)
            ok = ~np.isnan(out) & ~np.isnan(truth)
            assert ok.mean() > 0.5, (name, m)
            rmse[m] = float(np.sqrt(np.mean((out[ok] - truth[ok]) ** 2)))
        for m in ("bilinear", "bicubic", "spline", "idw"):
            assert rmse[m] < rmse["nearest"], (name, factor, rmse)
        # the smooth interpolators beat IDW's bull's-eyes, and cubic beats linear
        assert rmse["spline"] < rmse["idw"] and rmse["bicubic"] < rmse["bilinear"] * 1.02, \
            (name, factor, rmse)
