"""DEM ingest: every real file type, georeferencing of known summits, voids, corrupt files."""

import re
import shutil

import numpy as np
import pytest
import rasterio
from affine import Affine

from terrain_nav_ros.core.terrain.dem_io import (
    Dem,
    DemError,
    dem_files,
    fill_voids,
    mosaic,
    open_dem,
    sample_dem,
)
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin

# file, EPSG (None: local metres), guessed, shape, storage dtype, nodata, (min, max) elevation
REAL_DEMS = [
    ("dem/N44E005.hgt", 4326, False, (1201, 1201), ">i2", -32768, (32, 2757)),
    ("dem/bigtujunga_srtm30m_utm11.tif", 32611, False, (643, 1197), "int16", 32767, (315, 2295)),
    ("dem/front_range_srtm3.asc", 4326, True, (758, 758), "int32", 0, (1547, 4320)),
    ("dem/gredos_25m_epsg23030.tif", 23030, False, (410, 601), "float32", -32768, (514, 2410)),
    ("dem/halffork_5m.asc", None, True, (248, 256), "float32", -9999, (1996.5, 2197.75)),
    ("imagery/rmnp_dem_4326.tif", 4326, False, (187, 152), "uint16", 65535, (2200, 4261)),
    ("imagery/swellendam_srtm3_4326.tif", 4326, False, (619, 919), "float32", None, (0, 1699)),
]


@pytest.mark.parametrize("rel,epsg,guessed,shape,dtype,nodata,zrange", REAL_DEMS,
                         ids=[r[0].split("/")[1] for r in REAL_DEMS])
def test_real_dems_open_lazily_and_read(shared_data, rel, epsg, guessed, shape, dtype, nodata,
                                        zrange):
    with open_dem(shared_data / rel) as dem:
        assert dem.shape == shape
        assert dem.dtype == np.dtype(dtype)
        assert (dem.crs.to_epsg() if dem.crs else None) == epsg
        assert dem.local_metres == (epsg is None)
        assert dem.crs_guessed == guessed
        assert dem.is_north_up
        if nodata is not None:
            assert dem.nodata == nodata
        z = dem.read()
        assert z.dtype == np.float32 and z.shape == shape
        assert np.nanmin(z) >= zrange[0] - 1 and np.nanmax(z) == pytest.approx(zrange[1], abs=0.01)
        # windows are slices of the whole; outside the raster is NaN
        assert np.array_equal(dem.read(np.s_[10:50, 20:90]), z[10:50, 20:90], equal_nan=True)
        edge = dem.read_window(-5, shape[1] - 5, 10, 10)
        assert np.isnan(edge[:5]).all() and np.isnan(edge[:, 5:]).all()
        assert np.array_equal(edge[5:, :5], z[:5, -5:], equal_nan=True)
        # georeference: the highest cell maps to CRS coordinates and back to the same cell
        r, c = np.unravel_index(np.nanargmax(z), z.shape)
        x, y = dem.pixel_to_crs(c, r)
        c2, r2 = dem.crs_to_pixel(x, y)
        assert (round(float(r2)), round(float(c2))) == (r, c)
        left, bottom, right, top = dem.bounds
        assert left < x < right and bottom < y < top


def test_nodata_becomes_nan(shared_data):
    dem = open_dem(shared_data / "dem/halffork_5m.asc")
    with rasterio.open(shared_data / "dem/halffork_5m.asc") as ds:
        raw = ds.read(1)
    z = dem.read()
    assert np.array_equal(np.isnan(z), raw == -9999)
    assert np.isnan(z).sum() == 38589
    assert np.array_equal(z[~np.isnan(z)], raw[raw != -9999])


def test_hgt_georeference_from_name_and_ventoux(shared_data, tmp_path):
    dem = open_dem(shared_data / "dem/N44E005.hgt")
    half = 1.5 / 3600  # SRTM posts are cell centres on whole 3" multiples
    assert dem.bounds == pytest.approx((5 - half, 44 - half, 6 + half, 45 + half))
    assert dem.res == pytest.approx((3 / 3600, 3 / 3600))
    z = dem.read()
    assert np.isnan(z).sum() == 4822  # -32768 voids (non-void-filled tile)
    # Mont Ventoux summit 44.1741 N 5.2789 E, 1909/1910 m: the cell there reads ~1900 m and the
    # highest cell within ~1.5 km is at most one cell away
    c, r = (int(round(float(v))) for v in dem.crs_to_pixel(5.2789, 44.1741))
    assert z[r, c] == pytest.approx(1900, abs=15)
    win = z[r - 20:r + 21, c - 20:c + 21]
    dr, dc = np.subtract(np.unravel_index(np.nanargmax(win), win.shape), 20)
    assert max(abs(dr), abs(dc)) <= 1 and 1890 <= np.nanmax(win) <= 1915
    # the ENU round trip through the mission frame lands on the same cell
    origin = EnuOrigin(44.0, 5.5, 500.0)
    lon, lat = dem.pixel_to_crs(c, r)
    e, n, u = origin.geodetic_to_enu(lat, lon, 1900.0)
    lat2, lon2, _ = origin.enu_to_geodetic(e, n, u)
    c2, r2 = dem.crs_to_pixel(lon2, lat2)
    assert (float(c2), float(r2)) == pytest.approx((c, r), abs=1e-6)
    # the SW corner comes from the name: the same bytes as N45E006 sit one degree NE
    moved = tmp_path / "N45E006.hgt"
    shutil.copyfile(shared_data / "dem/N44E005.hgt", moved)
    assert open_dem(moved).bounds == pytest.approx((6 - half, 45 - half, 7 + half, 46 + half))


def test_srtm1_tile(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.integers(0, 3000, (3601, 3601)).astype(">i2")
    data[100:103, 200:205] = -32768
    path = tmp_path / "S34E020.hgt"
    data.tofile(path)
    dem = open_dem(path)
    assert dem.shape == (3601, 3601) and dem.res == pytest.approx((1 / 3600, 1 / 3600))
    assert dem.bounds[:2] == pytest.approx((20 - 0.5 / 3600, -34 - 0.5 / 3600))
    win = dem.read(np.s_[95:110, 195:210])
    assert np.isnan(win).sum() == 15
    assert np.array_equal(win[~np.isnan(win)], data[95:110, 195:210][data[95:110, 195:210] >= 0])


def test_front_range_longs_peak_agrees_with_rmnp(shared_data):
    # Longs Peak 40.2550 N 105.6150 W, 4346 m. Both SRTM-derived grids put their highest post two
    # 3" posts west of the published summit (radar layover on the east face); they must agree.
    peaks = []
    for rel in ("dem/front_range_srtm3.asc", "imagery/rmnp_dem_4326.tif"):
        dem = open_dem(shared_data / rel)
        z = dem.read()
        r, c = np.unravel_index(np.nanargmax(z), z.shape)
        peaks.append(dem.pixel_to_crs(c, r))
        assert 4250 <= z[r, c] <= 4346
    for lon, lat in peaks:
        assert abs(lat - 40.2550) < 0.002 and abs(lon + 105.6150) < 0.003
    assert np.hypot(*np.subtract(*peaks)) < 0.002


def test_asc_crs_from_header_and_prj(shared_data, tmp_path):
    lonlat = open_dem(shared_data / "dem/front_range_srtm3.asc")
    assert lonlat.crs.to_epsg() == 4326 and "taken as WGS84 longitude and latitude" in \
        lonlat.warning                       # a guess is said: it could be another place
    local = open_dem(shared_data / "dem/halffork_5m.asc")
    assert local.local_metres and local.crs_guessed and local.res == (5.0, 5.0)
    assert "no .prj: its CRS is taken as local metres" in local.warning
    # with a .prj the CRS is the file's, not a guess
    asc = tmp_path / "halffork.asc"
    shutil.copyfile(shared_data / "dem/halffork_5m.asc", asc)
    from pyproj import CRS

    asc.with_suffix(".prj").write_text(CRS.from_epsg(32613).to_wkt("WKT1_ESRI"))
    dem = open_dem(asc)
    assert dem.crs.to_epsg() == 32613 and not dem.crs_guessed and dem.warning is None
    # and an explicit override wins
    assert open_dem(shared_data / "dem/halffork_5m.asc", crs="EPSG:32613").crs.to_epsg() == 32613
    assert open_dem(shared_data / "dem/front_range_srtm3.asc", crs="local").local_metres


def test_sample_dem_matplotlib():
    dem = sample_dem()
    assert dem.shape == (344, 403) and dem.dtype == np.int16
    assert dem.crs.to_epsg() == 4326
    assert dem.bounds == pytest.approx((-84.41375, 36.44625, -84.0779167, 36.7329167), abs=1e-6)
    assert dem.res == pytest.approx((1 / 1200, 1 / 1200))
    z = dem.read()
    assert not np.isnan(z).any() and (np.nanmin(z), np.nanmax(z)) == (236, 1076)
    r, c = np.unravel_index(np.argmax(z), z.shape)
    lon, lat = dem.pixel_to_crs(c, r)
    assert (float(lon), float(lat)) == pytest.approx((-84.41375 + (c + 0.5) / 1200,
                                                      36.7329167 - (r + 0.5) / 1200), abs=1e-6)


@pytest.mark.parametrize("dtype,kw", [
    ("uint16", dict()), ("int32", dict()), ("float64", dict()),
    ("float32", dict(tiled=True, blockxsize=64, blockysize=64, compress="deflate")),
    ("int16", dict(compress="lzw")), ("float32", dict(ENDIANNESS="BIG")),
])
def test_geotiff_dtypes_and_layouts(shared_data, tmp_path, dtype, kw):
    src = open_dem(shared_data / "dem/bigtujunga_srtm30m_utm11.tif")
    z = src.read(np.s_[100:300, 200:450])
    nodata = 0 if dtype == "uint16" else -9999
    stored = z.astype(dtype)
    stored[5:9, 7:12] = nodata
    path = tmp_path / f"crop_{dtype}.tif"
    transform = src.transform @ Affine.translation(200, 100)
    with rasterio.open(path, "w", driver="GTiff", width=250, height=200, count=1, dtype=dtype,
                       crs="EPSG:32611", transform=transform, nodata=nodata, **kw) as ds:
        ds.write(stored, 1)
    dem = open_dem(path)
    assert dem.dtype.newbyteorder("=") == np.dtype(dtype) and dem.crs.to_epsg() == 32611
    assert dem.transform.almost_equals(transform)
    back = dem.read()
    assert np.isnan(back).sum() == 20
    ok = ~np.isnan(back)
    assert np.array_equal(back[ok], stored[ok].astype(np.float32))
    assert np.array_equal(dem.read(np.s_[50:60, 60:80]), back[50:60, 60:80], equal_nan=True)


def test_mosaic_of_adjacent_hgt_tiles(shared_data, tmp_path):
    for name in ("N44E005.hgt", "N44E006.hgt"):  # the same bytes stand in for the east tile
        shutil.copyfile(shared_data / "dem/N44E005.hgt", tmp_path / name)
    west, east = open_dem(tmp_path / "N44E005.hgt"), open_dem(tmp_path / "N44E006.hgt")
    m = mosaic([west, east])
    assert m.shape == (1201, 2401)  # adjacent SRTM tiles share their edge column
    assert m.bounds == pytest.approx((west.bounds[0], west.bounds[1], east.bounds[2],
                                      east.bounds[3]))
    z = west.read()
    win = m.read(np.s_[300:340, 1180:1220])  # across the seam
    assert np.array_equal(win[:, :21], z[300:340, 1180:1201], equal_nan=True)
    assert np.array_equal(win[:, 20:], z[300:340, 0:20], equal_nan=True) or \
        np.array_equal(win[:, 21:], z[300:340, 1:20], equal_nan=True)


def test_mosaic_reassembles_split_dem(shared_data):
    dem = open_dem(shared_data / "dem/gredos_25m_epsg23030.tif")
    z = dem.read()
    t = dem.transform
    parts = [Dem.from_array(z[r0:r1, c0:c1], t @ Affine.translation(c0, r0), dem.crs)
             for r0, r1 in ((0, 200), (200, 410)) for c0, c1 in ((0, 350), (350, 601))]
    m = mosaic(parts[::-1])
    assert m.shape == z.shape and m.transform.almost_equals(t)
    assert np.array_equal(m.read(), z, equal_nan=True)
    with pytest.raises(DemError, match="aligned"):
        mosaic([parts[0], Dem.from_array(z, t @ Affine.translation(0.5, 0), dem.crs)])
    with pytest.raises(DemError, match="CRS"):
        mosaic([parts[0], Dem.from_array(z, t, "EPSG:32630")])


# -- voids ----------------------------------------------------------------------------------
def test_fill_voids_halffork_keeps_outside_and_fills_holes(shared_data):
    z = open_dem(shared_data / "dem/halffork_5m.asc").read()
    outside = np.isnan(z)
    holes = np.zeros_like(outside)
    holes[100:106, 120:126] = True  # 36 cells
    holes[120:123, 140:143] = True
    big = np.zeros_like(outside)
    big[60:90, 130:160] = True  # 900 cells
    assert not (outside & (holes | big)).any()
    punched = z.copy()
    punched[holes | big] = np.nan
    filled, large = fill_voids(punched, max_area=100)
    # the clipped-catchment border void is outside the survey, not a hole: never filled
    assert np.array_equal(large, outside | big)
    err = filled[holes] - z[holes]
    assert np.sqrt(np.mean(err ** 2)) < 1.5  # metres, on a 5 m grid
    assert np.array_equal(filled[~(holes | big)], z[~(holes | big)], equal_nan=True)


def test_fill_voids_srtm_tile(shared_data):
    z = open_dem(shared_data / "dem/N44E005.hgt").read()
    void = np.isnan(z)
    filled, large = fill_voids(z, max_area=256)
    assert 0 < large.sum() < void.sum()
    assert not (large & ~void).any()
    # what remains are the big voids (or voids on the tile edge)
    from scipy import ndimage as ndi

    labels, n = ndi.label(large, structure=np.ones((3, 3)))
    areas = np.bincount(labels.ravel())[1:]
    edge = set(np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])) - {0}
    assert all(a > 256 or (i + 1) in edge for i, a in enumerate(areas))
    assert np.nanmin(filled) >= np.nanmin(z) - 1 and np.nanmax(filled) <= np.nanmax(z) + 1
    # holes punched into real data come back close to the truth (linear over the rim)
    rng = np.random.default_rng(0)
    punched = z.copy()
    for _ in range(60):
        r, c = rng.integers(50, 1100, 2)
        s = rng.integers(2, 7)
        if not void[r - 1:r + s + 1, c - 1:c + s + 1].any():
            punched[r:r + s, c:c + s] = np.nan
    holes = np.isnan(punched) & ~void
    refilled, _ = fill_voids(punched)
    err = refilled[holes] - z[holes]
    assert holes.sum() > 300 and np.sqrt(np.mean(err ** 2)) < 30  # alpine relief, 90 m cells
    assert np.sqrt(np.mean(err ** 2)) < 0.2 * np.std(z[holes])


def test_dem_filled(shared_data):
    dem = open_dem(shared_data / "dem/N44E005.hgt")
    f = dem.filled(256)
    assert f.shape == dem.shape and f.crs == dem.crs and f.transform == dem.transform
    assert np.isnan(f.read()).sum() == fill_voids(dem.read(), 256)[1].sum()


# -- errors ---------------------------------------------------------------------------------
ASC_HEADER = "ncols 4\nnrows 3\nxllcorner 500000\nyllcorner 4000000\ncellsize 10\n" \
             "NODATA_value -9999\n"
ASC_ROWS = "1 2 3 4\n5 6 7 8\n9 10 11 12\n"


def _assert_dem_error(path, match, **kw):
    with pytest.raises(DemError, match=match) as info:
        open_dem(path, **kw)
    assert str(path) in str(info.value)
    assert isinstance(info.value, ValueError)


def test_good_tiny_asc(tmp_path):
    p = tmp_path / "ok.asc"
    p.write_text(ASC_HEADER + ASC_ROWS)
    dem = open_dem(p)
    assert dem.local_metres and dem.shape == (3, 4)
    assert dem.read()[2, 3] == 12


def test_missing_file(tmp_path):
    _assert_dem_error(tmp_path / "nope.tif", "no such DEM file")


def test_wrong_asc_header(tmp_path):
    p = tmp_path / "bad_header.asc"
    p.write_text(ASC_HEADER.replace("ncols 4", "ncols four") + ASC_ROWS)
    _assert_dem_error(p, "header")
    p2 = tmp_path / "no_header.asc"
    p2.write_text(ASC_ROWS)
    _assert_dem_error(p2, "header")


def test_truncated_asc(tmp_path):
    p = tmp_path / "truncated.asc"
    p.write_text(ASC_HEADER + "1 2 3 4\n5 6\n")
    _assert_dem_error(p, "truncated")


@pytest.mark.parametrize("dims,values", [
    ((100, 100), "1 2 3 4\n"),                        # too short to hold them: no scan
    ((100, 100), " ".join(["1234.5"] * 9000)),         # long enough in bytes: counted
    ((10**9, 10**9), "1 2 3\n"),                      # a header promising 8 GB of row index
], ids=["four_values", "nine_tenths", "absurd_header"])
def test_truncated_asc_fails_at_once_within_the_file(tmp_path, dims, values):
    """GDAL's AAIGrid driver hung and grew to 24 GB on a 100x100 header with four values
    (issue 22): the size the header promises is checked against the file first."""
    p = tmp_path / "cut.asc"
    p.write_text(f"ncols {dims[1]}\nnrows {dims[0]}\nxllcorner 0\nyllcorner 0\n"
                 f"cellsize 30\n{values}")
    _assert_dem_error(p, "truncated ESRI ASCII grid: the header promises")


@pytest.mark.parametrize("k,token", [(0, "abc"), (57, "1.2.3"), (130, "12x"), (199, "\x00\xff")])
@pytest.mark.parametrize("chunk", [64, 1 << 22], ids=["small_chunks", "one_chunk"])
def test_asc_value_that_is_not_a_number_is_named_with_its_place(tmp_path, monkeypatch, k,
                                                                 token, chunk):
    """GDAL reads 'abc' as 0 and '1.2.3' as 1.2 without a word: refused, naming where."""
    from terrain_nav_ros.core.terrain import dem_io

    monkeypatch.setattr(dem_io, "_CHUNK", chunk)  # tokens across chunk edges, the last alone
    values = [f"{1000 + i}.5" for i in range(200)]
    values[k] = token
    p = tmp_path / "garbled.asc"
    p.write_bytes(("ncols 20\nnrows 10\nxllcorner 0\nyllcorner 0\ncellsize 30\n"
                   + "\n".join(" ".join(values[r:r + 20]) for r in range(0, 200, 20))
                   + "\n").encode("latin-1"))
    shown = token.encode("latin-1").decode("ascii", "backslashreplace")
    _assert_dem_error(p, re.escape(f"value {k + 1} (row {k // 20 + 1}, column {k % 20 + 1}) "
                                   f"is {shown!r}, not a number"))
    p.write_text(p.read_text("latin-1").replace(token, "-9999", 1))
    assert open_dem(p).read().shape == (10, 20)


def test_ascii_grid_checked_whatever_its_suffix(tmp_path):
    p = tmp_path / "grid.txt"
    p.write_text(ASC_HEADER + "1 2 3 4\n5 6\n")
    _assert_dem_error(p, "header promises 3 x 4 = 12 values")
    p.write_text(ASC_HEADER.upper() + ASC_ROWS)
    assert open_dem(p).read()[2, 3] == 12


def test_truncated_hgt_and_corrupt_geotiff_header(tmp_path):
    p = tmp_path / "N44E005.hgt"
    p.write_bytes(bytes(2 * 1201 * 1201 - 100))
    _assert_dem_error(p, "truncated")
    tif = tmp_path / "corrupt.tif"
    with rasterio.open(tif, "w", driver="GTiff", width=64, height=64, count=1, dtype="int16",
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(np.ones((64, 64), np.int16), 1)
    data = bytearray(tif.read_bytes())
    data[8:200] = np.random.default_rng(3).integers(0, 256, 192, np.uint8).tobytes()
    tif.write_bytes(bytes(data))
    _assert_dem_error(tif, "corrupt header")
    tif.write_bytes(b"")
    _assert_dem_error(tif, "not a readable DEM")


def test_truncated_and_misnamed_hgt(shared_data, tmp_path):
    data = (shared_data / "dem/N44E005.hgt").read_bytes()
    p = tmp_path / "N44E005.hgt"
    p.write_bytes(data[: len(data) // 2])
    _assert_dem_error(p, "truncated")
    q = tmp_path / "ventoux.hgt"
    q.write_bytes(data)
    _assert_dem_error(q, "name")


@pytest.mark.parametrize("kw", [dict(), dict(tiled=True, blockxsize=32, blockysize=32,
                                                    compress="deflate")])
def test_truncated_geotiff(tmp_path, kw):
    p = tmp_path / "cut.tif"
    z = np.random.default_rng(1).normal(1000, 50, (256, 256)).astype(np.float32)
    with rasterio.open(p, "w", driver="GTiff", width=256, height=256, count=1, dtype="float32",
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6),
                       **kw) as ds:
        ds.write(z, 1)
    data = p.read_bytes()
    # uncompressed GDAL TIFFs keep the header first: cut the pixel data's tail
    p.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(DemError) as info:
        open_dem(p)
    assert str(p) in str(info.value)


def _garbled_geotiff(path, dtype, garbage, cells=slice(None)):
    """An uncompressed 128 x 128 GeoTIFF of plausible heights whose pixel bytes for
    ``cells`` (row-major) are then overwritten with ``garbage``."""
    z = np.random.default_rng(2).normal(1000, 20, (128, 128)).astype(dtype)
    with rasterio.open(path, "w", driver="GTiff", width=128, height=128, count=1, dtype=dtype,
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(z, 1)
        offset = int(ds.get_tag_item("BLOCK_OFFSET_0_0", "TIFF", bidx=1))
    pixels = np.memmap(path, dtype=dtype, mode="r+", offset=offset, shape=z.size)
    pixels[cells] = garbage(pixels[cells].size)
    pixels.flush()
    return path, z


def test_a_few_impossible_heights_are_voids_with_a_warning_and_filled(tmp_path):
    """3e38 among heights of ~1000 m: read as voids (not as data that fill_voids and the
    tile's interpolation would spread), and a warning saying where."""
    from terrain_nav_ros.core.terrain.metamap import MetaMap

    path, _ = _garbled_geotiff(tmp_path / "spots.tif", np.float32,
                               lambda n: np.full(n, 3e38, np.float32), slice(7740, 7745))
    dem = open_dem(path)
    assert "5 of 16384 heights (0.0305 %) are impossible on Earth" in dem.warning
    assert "first 3e+38 at row 60, column 60); they are read as voids" in dem.warning
    read = dem.read()
    assert np.isnan(read[60, 60:65]).all() and np.isfinite(read).sum() == 16384 - 5
    filled, large = fill_voids(read)  # a small void: inpainted from its rim
    assert not large.any() and 900 < filled[60, 60:65].min() <= filled[60, 60:65].max() < 1100
    tile = MetaMap(dem, fill_voids=True).tile_at(0.0, 0.0, 30.0, 100, 100)
    assert tile.valid_fraction == 1.0 and tile.elevation.max() < 1200
    # an undeclared nodata value, -9999, is impossible too
    path, _ = _garbled_geotiff(tmp_path / "sentinel.tif", np.int16,
                               lambda n: np.full(n, -9999, np.int16), slice(0, 128))
    dem = open_dem(path)
    assert "128 of 16384 heights" in dem.warning and np.isnan(dem.read()[0]).all()


def _random_bytes_as(dtype):
    return lambda n: np.random.default_rng(5).integers(0, 256, n * np.dtype(dtype).itemsize,
                                                        np.uint8).view(dtype)


@pytest.mark.parametrize("dtype,garbage,first", [
    (np.float32, lambda n: np.full(n, -1e30, np.float32), "first -1e+30"),
    # random float32 bytes: ~45 % huge, ~42 % nonzero below 1e-6
    (np.float32, _random_bytes_as(np.float32), "first"),
    (np.int16, _random_bytes_as(np.int16), "first"),  # ~85 % outside -500..9000
], ids=["float_-1e30", "float_random_bytes", "int16_random_bytes"])
def test_mostly_impossible_heights_are_refused(tmp_path, dtype, garbage, first):
    path, _ = _garbled_geotiff(tmp_path / "garbage.tif", dtype, garbage)
    _assert_dem_error(path, re.escape("are impossible on Earth (outside -500..9000 m, or "
                                      f"nonzero within 1e-06 m of 0; {first}"))
    _assert_dem_error(path, "corrupt pixel data, an undeclared nodata value or heights not "
                            "in metres")


def test_unknown_crs(tmp_path):
    p = tmp_path / "no_crs.tif"
    with rasterio.open(p, "w", driver="GTiff", width=8, height=8, count=1, dtype="int16",
                       transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(np.zeros((8, 8), np.int16), 1)
    _assert_dem_error(p, "unknown CRS")
    assert open_dem(p, crs="EPSG:32611").crs.to_epsg() == 32611
    asc = tmp_path / "garbled.asc"
    asc.write_text(ASC_HEADER + ASC_ROWS)
    asc.with_suffix(".prj").write_text("this is not a projection\n")
    _assert_dem_error(asc, "unknown CRS")
    _assert_dem_error(tmp_path / "no_crs.tif", "unknown CRS", crs="EPSG:99999999")


def test_bad_npz(tmp_path):
    p = tmp_path / "bad.npz"
    np.savez(p, elevation=np.zeros((3, 3)))
    _assert_dem_error(p, "npz")


def test_window_reads_are_lazy(tmp_path):
    psutil = pytest.importorskip("psutil")
    n = 3000  # 36 MB of float32
    path = tmp_path / "big.tif"
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs="EPSG:32611", transform=Affine(10, 0, 4e5, 0, -10, 3.8e6)) as ds:
        for r0 in range(0, n, 500):
            ds.write(np.full((500, n), r0, np.float32), 1, window=((r0, r0 + 500), (0, n)))
    proc = psutil.Process()
    before = proc.memory_info().rss
    dem = open_dem(path)
    win = dem.read_window(2000, 1000, 256, 256)
    grown = proc.memory_info().rss - before
    assert win.shape == (256, 256) and (win == 2000).all()
    assert grown < 8 * 2**20  # far less than the 36 MB file


def test_dem_files_expands_dirs_and_globs(shared_data):
    files = dem_files([shared_data / "dem", str(shared_data / "imagery" / "*dem*.tif")])
    names = [f.split("/")[-1] for f in files]
    assert "N44E005.hgt" in names and "rmnp_dem_4326.tif" in names
    assert "rmnp_rgb_4326.tif" not in names and "README.md" not in names
    assert files == sorted(set(files))


def _hill_geotiff(path, z, crs="EPSG:32611", **kw):
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0],
                       count=1, dtype=z.dtype, crs=crs,
                       transform=Affine(30, 0, 4e5, 0, -30, 3.8e6), **kw) as ds:
        ds.write(z, 1)
    return path


def _hill(n=64):
    r, c = np.mgrid[0:n, 0:n]
    return (1000 + 300 * np.exp(-((r - n / 2) ** 2 + (c - n / 2) ** 2) / 200.0)).astype(
        np.float32)


@pytest.mark.parametrize("crs, units, per_unit", [
    ("EPSG:2229+6360", None, 1200 / 3937),      # state plane ftUS + NAVD88 height ftUS
    ("EPSG:32611", "ft", 0.3048),               # the band says feet
    ("EPSG:32611", "US survey foot", 1200 / 3937),
    ("EPSG:32611", "metre", 1.0),
])
def test_heights_in_feet_are_read_in_metres(tmp_path, crs, units, per_unit):
    z = _hill()
    p = _hill_geotiff(tmp_path / "feet.tif", z / per_unit, crs)
    if units:
        with rasterio.open(p, "r+") as ds:
            ds.units = (units,)
    np.testing.assert_allclose(open_dem(p).read(), z, rtol=1e-5)


def test_heights_in_an_unknown_unit_are_refused(tmp_path):
    p = _hill_geotiff(tmp_path / "cubits.tif", _hill())
    with rasterio.open(p, "r+") as ds:
        ds.units = ("cubit",)
    _assert_dem_error(p, "heights are in 'cubit'")


@pytest.mark.parametrize("dtype, scale, offset", [("int16", 1.0, 1000.0), ("int32", 0.1, 0.0)])
def test_band_scale_and_offset_are_applied(tmp_path, dtype, scale, offset):
    """Packed products: int16 heights above 1000 m, int32 decimetres."""
    z = np.round(_hill())
    p = _hill_geotiff(tmp_path / "packed.tif", np.round((z - offset) / scale).astype(dtype))
    with rasterio.open(p, "r+") as ds:
        ds.scales, ds.offsets = (scale,), (offset,)
    dem = open_dem(p)
    assert dem.warning is None
    np.testing.assert_allclose(dem.read(), z, atol=0.06)


def test_cells_under_a_gdal_mask_are_voids(tmp_path):
    """An internal mask (gdal_translate -mask, QGIS exports) with 0 under it: the masked
    cells are voids, not a cliff down to 0 m."""
    z = _hill()
    z[:, 40:] = 0.0
    p = _hill_geotiff(tmp_path / "masked.tif", z)
    with rasterio.open(p, "r+") as ds:
        ds.write_mask(np.where(z != 0, 255, 0).astype(np.uint8))
    got = open_dem(p).read()
    assert np.isnan(got[:, 40:]).all() and np.array_equal(got[:, :40], z[:, :40])


def test_a_local_engineering_crs_in_metres_is_local_metres(tmp_path):
    local = rasterio.crs.CRS.from_wkt('LOCAL_CS["site grid",UNIT["metre",1],'
                                      'AXIS["Easting",EAST],AXIS["Northing",NORTH]]')
    dem = open_dem(_hill_geotiff(tmp_path / "site.tif", _hill(), local))
    assert dem.local_metres and not dem.crs_guessed


def test_projected_coordinates_labelled_lon_lat_are_refused(tmp_path):
    p = _hill_geotiff(tmp_path / "utm_as_4326.tif", _hill(), "EPSG:4326")
    _assert_dem_error(p, "not degrees, as its CRS")


@pytest.mark.parametrize("cellsize", ["0", "-30", "nan"])
def test_an_ascii_grid_cell_size_must_be_positive(tmp_path, cellsize):
    p = tmp_path / "cell.asc"
    p.write_text(re.sub(r"cellsize \S+", f"cellsize {cellsize}", ASC_HEADER) + ASC_ROWS)
    _assert_dem_error(p, "cellsize is .*it must be a number > 0")


def test_a_geotiff_whose_cells_have_no_area_is_refused(tmp_path):
    p = tmp_path / "flat_transform.tif"
    with rasterio.open(p, "w", driver="GTiff", width=8, height=8, count=1, dtype="int16",
                       crs="EPSG:32611", transform=Affine(30, 30, 4e5, 30, 30, 3.8e6)) as ds:
        ds.write(np.zeros((8, 8), np.int16), 1)
    _assert_dem_error(p, "cell size of 0")


def test_srtm_tiles_zipped_with_lp_daac_names_and_halved_columns(shared_data, tmp_path):
    """As USGS and viewfinderpanoramas ship tiles: N44E005.hgt.zip reads like the tile;
    N44E005.SRTMGL1.hgt is a tile's name; a 1" tile at 50-60 deg has 1801 columns."""
    import zipfile

    tile = shared_data / "dem/N44E005.hgt"
    zipped = tmp_path / "N44E005.hgt.zip"
    with zipfile.ZipFile(zipped, "w") as z:
        z.write(tile, "N44E005.hgt")
    np.testing.assert_array_equal(open_dem(zipped).read(), open_dem(tile).read())
    assert str(zipped) in dem_files([tmp_path])
    named = tmp_path / "N44E005.SRTMGL3.hgt"
    shutil.copy(tile, named)
    assert open_dem(named).bounds == pytest.approx(open_dem(tile).bounds)
    high = tmp_path / "N55E010.hgt"
    np.full((3601, 1801), 100, ">i2").tofile(high)
    dem = open_dem(high)
    assert dem.shape == (3601, 1801) and dem.res == pytest.approx((2 / 3600, 1 / 3600))
    bad = tmp_path / "N99E999.hgt"
    shutil.copy(tile, bad)
    _assert_dem_error(bad, "within 89 deg of latitude")
