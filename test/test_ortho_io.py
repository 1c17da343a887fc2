"""Georeferenced image ingest (terrain_nav_ros.core.terrain.ortho_io)."""

import math

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.control import GroundControlPoint

from terrain_nav_ros.core.terrain.ortho_io import (
    ImageError,
    OrthoImage,
    ground_cell_metres,
    undeclared_fill,
)

UTM = "EPSG:32611"
GRID = Affine(30.0, 0.0, 4e5, 0.0, -30.0, 3.8e6)


def _scene(shape=(120, 160), lo=200, hi=4000, seed=0):
    """Reflectance-like values: smooth relief shading plus noise, within [lo, hi]."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    shade = 0.5 + 0.4 * np.sin(cols / 9.0) * np.cos(rows / 13.0)
    noise = np.random.default_rng(seed).normal(0.0, 0.03, shape)
    return lo + (hi - lo) * np.clip(shade + noise, 0.0, 1.0)


def _write(path, data, dtype, **profile):
    data = np.asarray(data)
    data = data[None] if data.ndim == 2 else data
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1],
                       count=data.shape[0], dtype=dtype,
                       **({"crs": UTM, "transform": GRID} | profile)) as ds:
        ds.write(data.astype(dtype))
    return path


@pytest.mark.parametrize("dtype, fill, lo, hi", [
    ("int16", -9999, 0, 10000),       # surface reflectance x 1e4 (HLS, Landsat C2 SR)
    ("uint16", 65535, 500, 4095),     # 12-bit counts with the type's maximum as fill
    ("float32", -3.4e38, 0.0, 0.6),   # float reflectance with float32's lowest
])
def test_an_undeclared_fill_value_is_no_data_and_named(tmp_path, dtype, fill, lo, hi):
    """A fill value the file does not declare would be an edge of full contrast (read as a
    valley) and would take the percentile stretch's low or high end."""
    values = _scene(lo=lo, hi=hi)
    band = values.copy()
    band[:30] = fill                   # outside the footprint
    band[60:64, 40:90] = fill          # a gap
    path = _write(tmp_path / "fill.tif", band, dtype)
    with OrthoImage(path) as img:
        data = img.read([1])[0]
        warning = img.warning
    fill_px = np.zeros(band.shape, bool)
    fill_px[:30] = True
    fill_px[60:64, 40:90] = True
    assert np.isnan(data[fill_px]).all()
    np.testing.assert_allclose(data[~fill_px], values[~fill_px].astype(dtype), rtol=1e-6)
    assert f"{fill_px.sum()} of {fill_px.size} pixels" in warning
    assert f"{np.float32(fill):g}" in warning and "read as no data" in warning
    with OrthoImage(path) as img:     # one band as three colours: read and judged once
        grey = img.read([1, 1, 1])
        assert img.warning == warning
    np.testing.assert_array_equal(grey, np.stack([data] * 3))


def test_a_saturated_plateau_and_declared_nodata_are_not_undeclared_fill(tmp_path):
    grey = _scene(lo=20, hi=254)
    grey[:20] = 255                    # snow saturating at the type's maximum: data
    grey[100:] = 0                     # the declared nodata value
    with OrthoImage(_write(tmp_path / "snow.tif", grey, "uint8", nodata=0)) as img:
        data = img.read([1])[0]
        assert img.warning is None
    assert (data[:20] == 255).all() and np.isnan(data[100:]).all()
    assert undeclared_fill(np.full((50, 50), 7.0)) == []      # one value: nothing to judge


def test_an_undeclared_zero_is_fill_and_a_declared_one_is_not(tmp_path):
    """Landsat DN products reserve 0 for fill and often do not say so."""
    grey = _scene(lo=10, hi=250)
    grey[:, :12] = 0
    with OrthoImage(_write(tmp_path / "dn.tif", grey, "uint8")) as img:
        assert np.isnan(img.read([1])[0][:, :12]).all()
    with OrthoImage(_write(tmp_path / "declared.tif", grey, "uint8", nodata=255)) as img:
        assert (img.read([1])[0][:, :12] == 0).all()


def test_values_that_are_not_finite_are_no_data_in_every_band(tmp_path):
    bands = np.stack([_scene(lo=0.0, hi=1.0), _scene(lo=0.0, hi=1.0, seed=1)])
    bands[0, 5, 5], bands[1, 7, 9] = np.inf, np.nan
    with OrthoImage(_write(tmp_path / "f.tif", bands, "float32")) as img:
        data = img.read([1, 2])
    assert np.isnan(data[:, 5, 5]).all() and np.isnan(data[:, 7, 9]).all()
    assert np.isfinite(data).sum() == data.size - 4


def test_a_paletted_image_reads_as_its_colours(tmp_path):
    """Its indices are labels: an image whose colour table runs dark to bright for falling
    indices is bright where the indices are low."""
    index = np.clip(_scene(lo=0, hi=255), 0, 255).astype(np.uint8)
    path = _write(tmp_path / "pal.tif", index, "uint8", photometric="palette", nodata=0)
    table = {i: (255 - i, 128, i, 255) for i in range(256)}
    with rasterio.open(path, "r+") as ds:
        ds.write_colormap(1, table)
    with OrthoImage(path) as img:
        assert img.count == 3 and img.descriptions == ("red", "green", "blue")
        red, green, blue = img.read([1, 2, 3])
    seen = index > 0
    np.testing.assert_array_equal(red[seen], 255 - index[seen].astype(float))
    assert (green[seen] == 128).all() and (blue[seen] == index[seen]).all()
    assert np.isnan(red[~seen]).all()   # the index declared nodata
    with OrthoImage(path) as img, pytest.raises(ImageError, match="band 4 does not exist"):
        img.read([4])


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_an_image_with_control_points_only_is_warped_onto_their_grid(tmp_path):
    values = _scene(lo=0.0, hi=100.0)
    h, w = values.shape
    path = _write(tmp_path / "gcps.tif", values, "float32", crs=None,
                  transform=Affine.identity())
    gcps = [GroundControlPoint(r, c, *(GRID @ (c, r))) for r, c in
            ((0, 0), (0, w), (h, 0), (h, w), (h / 2, w / 3))]
    with rasterio.open(path, "r+") as ds:
        ds.gcps = (gcps, rasterio.crs.CRS.from_string(UTM))
    with OrthoImage(path) as img:
        assert img.crs == rasterio.crs.CRS.from_string(UTM)
        assert img.transform.almost_equals(GRID, precision=1e-6) and img.shape == (h, w)
        data = img.read([1])[0]
    inner = (slice(2, -2), slice(2, -2))
    np.testing.assert_allclose(data[inner], values[inner], atol=0.5)


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
@pytest.mark.parametrize("make, message", [
    (lambda p: p.write_bytes(b"II*\x00" + b"\x00" * 40), "cannot read the image"),
    (lambda p: _write(p, _scene(), "float32", crs=None, transform=Affine.identity()),
     "has no CRS"),
])
def test_an_image_that_cannot_be_placed_is_a_clear_error(tmp_path, make, message):
    path = tmp_path / "bad.tif"
    make(path)
    with pytest.raises(ImageError, match=message):
        OrthoImage(path)


def test_a_geographic_cell_is_measured_on_the_ground():
    """0.0003 deg at 60 deg N: 33.4 m north-south, half that east-west."""
    from rasterio.crs import CRS
    cell = ground_cell_metres(CRS.from_epsg(4326), Affine(3e-4, 0, 10.0, 0, -3e-4, 60.0),
                              (100, 100))
    assert cell == pytest.approx(math.sqrt(33.40 * 16.74), rel=0.01)
    assert ground_cell_metres(CRS.from_string(UTM), GRID, (100, 100)) == 30.0
