"""Metamap tiles: north-up ENU grids sampled from real DEMs through the right CRS transform."""

import numpy as np
import pytest
from affine import Affine
from pyproj import Transformer
from scipy import ndimage as ndi

from terrain_nav_ros.core.terrain.dem_io import Dem, DemError, open_dem, sample_dem
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.core.terrain.metamap import DemTile, MetaMap, OutsideDemError, remap_masked


def exact_reference(dem, origin, georef, reference_height, order=1):
    """Per-pixel exact ENU -> DEM CRS, then bilinear (order 1) or cubic spline on the whole DEM."""
    from terrain_nav_ros.core.terrain.geodesy import CrsEnuTransform

    t = CrsEnuTransform(dem.crs, origin)
    cols, rows = np.meshgrid(np.arange(georef.width), np.arange(georef.height))
    e, n = georef.pixel_to_enu(cols, rows)
    x, y = t.from_enu(e, n, reference_height)
    c, r = dem.crs_to_pixel(x, y)
    z = dem.read()
    if order > 1:  # a spline cannot take NaN: nearest-fill voids (the tile masks near them)
        z = z[tuple(ndi.distance_transform_edt(np.isnan(z), return_distances=False,
                                               return_indices=True))]
    return ndi.map_coordinates(z, [r, c], order=order, cval=np.nan, prefilter=order > 1)


def centre_origin(dem, alt=0.0, **kw):
    left, bottom, right, top = dem.bounds
    lon, lat = Transformer.from_crs(dem.crs, 4326, always_xy=True).transform(
        0.5 * (left + right), 0.5 * (bottom + top))
    return EnuOrigin(lat, lon, alt, **kw)


@pytest.mark.parametrize("rel,gsd", [
    ("dem/gredos_25m_epsg23030.tif", 25.0),  # ED50 / UTM 30N, 1.5 deg west of its meridian
    ("dem/bigtujunga_srtm30m_utm11.tif", 30.0),  # UTM 11N: grid convergence ~0.7 deg
    ("dem/N44E005.hgt", 50.0),  # geographic
    ("dem/front_range_srtm3.asc", 40.0),  # geographic, CRS guessed from the header
])
@pytest.mark.parametrize("interpolation", ["bilinear", "spline"])
def test_tile_matches_exact_per_pixel_sampling(shared_data, rel, gsd, interpolation):
    dem = open_dem(shared_data / rel)
    origin = centre_origin(dem, alt=1500.0)
    mm = MetaMap(dem, origin, interpolation=interpolation)
    georef = GeoReference.centred(1234.5, -876.5, gsd, 200, 160)
    tile = mm.tile(georef)
    assert isinstance(tile, DemTile) and tile.georef == georef
    assert tile.elevation.shape == (160, 200) and tile.elevation.dtype == np.float32
    assert tile.heights == "orthometric"
    ref = exact_reference(dem, origin, georef, mm.reference_height,
                          order=1 if interpolation == "bilinear" else 3)
    both = ~np.isnan(ref) & ~tile.nodata
    assert both.mean() > 0.95
    err = np.abs(tile.elevation[both] - ref[both])
    # OpenCV quantises sample positions to 1/32 cell: errors are slope x cell / 64 at most
    slope = np.nanpercentile(np.hypot(*np.gradient(ref)), 99)
    assert np.median(err) < 0.05 * slope + 0.01
    assert err.max() < 0.1 * slope + 0.05


def test_tile_rotation_follows_grid_convergence(shared_data):
    # A UTM DEM sampled north-up in ENU is rotated by the meridian convergence: ENU north
    # is not the grid's column direction. Check with a synthetic DEM equal to its own northing.
    src = open_dem(shared_data / "dem/bigtujunga_srtm30m_utm11.tif")
    rows, cols = np.mgrid[0:src.height, 0:src.width]
    _, northing = src.pixel_to_crs(cols, rows)
    dem = Dem.from_array((northing - northing.mean()).astype(np.float32), src.transform,
                         src.crs)
    origin = centre_origin(src)
    tile = MetaMap(dem, origin).tile_at(0.0, 0.0, 30.0, 301, 301)
    gy, gx = np.gradient(tile.elevation.astype(float))
    # d(northing)/d(east) = -sin(convergence)... the field tilts eastwards by the convergence
    angle = np.degrees(np.arctan2(np.nanmedian(gx), -np.nanmedian(gy)))
    lam0 = -117.0
    expected = np.degrees(np.arctan(np.tan(np.radians(origin.lon - lam0))
                                    * np.sin(np.radians(origin.lat))))
    assert angle == pytest.approx(expected, abs=0.05)  # grid north is west of true north
    assert abs(expected) > 0.5  # the test would be vacuous near the central meridian


def test_known_summit_through_the_tile_server(shared_data):
    dem = open_dem(shared_data / "dem/N44E005.hgt")
    mm = MetaMap(dem, EnuOrigin(44.0, 5.5, 300.0))
    tile = mm.tile_at_geodetic(44.1741, 5.2789, 30.0, 101, 101)
    z = tile.elevation
    assert z[50, 50] == pytest.approx(1900, abs=15)
    r, c = np.unravel_index(np.nanargmax(z), z.shape)
    assert np.hypot(r - 50, c - 50) * 30.0 < 150.0  # SRTM3 posts are ~70 x 90 m
    # the ENU of that pixel goes back to Ventoux's cell
    e, n = tile.georef.pixel_to_enu(50, 50)
    lat, lon, _ = mm.origin.enu_to_geodetic(e, n, mm.origin.surface_up(e, n))
    assert (float(lat), float(lon)) == pytest.approx((44.1741, 5.2789), abs=1e-8)


def test_native_gsd_local_metres_reproduces_cells(shared_data):
    dem = open_dem(shared_data / "dem/halffork_5m.asc")
    mm = MetaMap(dem)  # local metres: ENU origin at the DEM centre
    assert mm.native_gsd == pytest.approx(5.0)
    # 256 x 248 cells centred at the origin: tile pixel centres fall on DEM cell centres
    tile = mm.tile_at(0.0, 0.0, 5.0, 256, 248)
    assert np.array_equal(tile.nodata, np.isnan(dem.read()))
    assert np.allclose(tile.elevation, dem.read(), atol=1e-3, equal_nan=True)
    shifted = MetaMap(dem, local_origin=dem.pixel_to_crs(0, 0)).tile_at(0.0, 0.0, 5.0, 3, 3)
    assert np.isnan(shifted.elevation[0]).all() and np.isnan(shifted.elevation[:, 0]).all()


def test_partial_overlap_masks_and_outside_raises(shared_data):
    dem = open_dem(shared_data / "dem/gredos_25m_epsg23030.tif")
    mm = MetaMap(dem, centre_origin(dem))
    west, east, south, north = mm.enu_bounds[0]
    tile = mm.tile_at(east, 0.5 * (south + north), 25.0, 100, 40)  # straddles the east edge
    assert 0.3 < tile.valid_fraction < 0.7
    assert not tile.nodata[:, :40].any() and tile.nodata[:, 60:].all()
    assert np.isnan(tile.elevation[tile.nodata]).all()
    with pytest.raises(OutsideDemError, match="outside every loaded DEM") as info:
        mm.tile_at(east + 5000.0, 0.0, 25.0, 100, 100)
    assert isinstance(info.value, DemError) and isinstance(info.value, ValueError)


def test_coarse_tile_is_box_averaged(shared_data):
    dem = open_dem(shared_data / "dem/halffork_5m.asc")
    mm = MetaMap(dem)
    coarse = mm.tile_at(0.0, 0.0, 20.0, 64, 62)
    fine = dem.read()
    blocks = fine.reshape(62, 4, 64, 4).mean(axis=(1, 3))
    both = ~np.isnan(blocks) & ~coarse.nodata
    assert both.sum() > 1000
    assert np.abs(coarse.elevation[both] - blocks[both]).max() < 1e-3


def test_aligned_tiles_become_one_seamless_mosaic(shared_data):
    dem = open_dem(shared_data / "dem/gredos_25m_epsg23030.tif")
    z = dem.read()
    t = dem.transform
    parts = [Dem.from_array(z[:, :300], t, dem.crs),
             Dem.from_array(z[:, 300:], t @ Affine.translation(300, 0), dem.crs)]
    origin = centre_origin(dem)
    whole = MetaMap(dem, origin).tile_at(0.0, 0.0, 25.0, 200, 200)
    split = MetaMap(parts, origin)
    assert len(split.layers) == 1
    assert np.array_equal(split.tile_at(0.0, 0.0, 25.0, 200, 200).elevation, whole.elevation,
                          equal_nan=True)


def test_mixed_crs_sources_fill_each_other(shared_data):
    # the Front Range ASCII grid (SRTM3) and the RMNP GeoTIFF overlap around Longs Peak
    fr = open_dem(shared_data / "dem/front_range_srtm3.asc")
    rm = open_dem(shared_data / "imagery/rmnp_dem_4326.tif")
    origin = EnuOrigin(40.2549, -105.6151, 4000.0)
    mm = MetaMap([fr, rm], origin)
    assert len(mm.layers) == 2
    west = mm.enu_bounds[0][0]
    tile = mm.tile_at(west, 0.0, 200.0, 60, 60)  # half west of the Front Range grid
    only_fr = MetaMap(fr, origin).tile_at(west, 0.0, 200.0, 60, 60)
    assert tile.valid_fraction > only_fr.valid_fraction + 0.3
    ok = ~only_fr.nodata
    assert np.array_equal(tile.elevation[ok], only_fr.elevation[ok])


def test_fill_voids_reduces_nodata(shared_data):
    dem = open_dem(shared_data / "dem/N44E005.hgt")
    origin = EnuOrigin(44.5, 5.5, 500.0)
    raw = MetaMap(dem, origin).tile_at(0.0, 0.0, 70.0, 1000, 1000)
    filled = MetaMap(dem, origin, fill_voids=True).tile_at(0.0, 0.0, 70.0, 1000, 1000)
    assert raw.nodata.sum() > 1000 and filled.nodata.sum() == 0  # only small voids here
    # valid cells keep their values, except next to a void where raw is a one-sided average
    ok = ~raw.nodata
    same = np.isclose(filled.elevation[ok], raw.elevation[ok], atol=1e-3)
    assert same.mean() > 0.99
    # the tile's largest void (536 cells, near 44.978 N 5.934 E) is reported, not invented
    big = MetaMap(dem, EnuOrigin(44.978, 5.934, 500.0), fill_voids=True,
                  max_void_area=256).tile_at(0.0, 0.0, 70.0, 41, 41)
    assert 100 < big.nodata.sum() < 41 * 41


@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic", "spline", "idw"])
def test_interpolation_modes_on_sample_dem(interpolation):
    dem = sample_dem()
    mm = MetaMap(dem, interpolation=interpolation)
    tile = mm.tile_at(0.0, 0.0, 25.0, 64, 64)  # 3x finer than the 3" grid
    assert tile.valid_fraction == 1.0
    ref = MetaMap(dem).tile_at(0.0, 0.0, 25.0, 64, 64).elevation
    assert np.abs(tile.elevation - ref).mean() < 10.0
    assert 236 - 1 <= tile.elevation.min() and tile.elevation.max() <= 1076 + 30


@pytest.mark.parametrize("width", [1, 2, 7])
def test_narrow_bicubic_tiles_hold_data(width):
    # OpenCV's bicubic remap with a NaN border gave all-NaN maps under 8 px wide
    z = np.add.outer(np.arange(40.0), 3.0 * np.arange(50.0)).astype(np.float32)
    maps = np.dstack(np.meshgrid(np.arange(width) + 20.3, np.arange(5) + 10.6)).astype(np.float32)
    assert remap_masked(z, maps, None, "bicubic") == pytest.approx(
        maps[..., 1] + 3.0 * maps[..., 0], abs=0.25)  # a plane: OpenCV's cubic bends it
    mm = MetaMap(sample_dem(), interpolation="bicubic")
    assert mm.tile_at(0.0, 0.0, 100.0, width, 3).valid_fraction == 1.0


def test_default_origin_is_dem_centre():
    dem = sample_dem()
    mm = MetaMap(dem)
    assert (mm.origin.lat, mm.origin.lon) == pytest.approx((36.5896, -84.2458), abs=1e-3)
    w, e, s, n = mm.enu_bounds[0]
    assert w < 0 < e and s < 0 < n
    assert (e - w) == pytest.approx(403 * 74.6, rel=0.01)  # 3" of longitude at 36.6 N
    assert (n - s) == pytest.approx(344 * 92.6, rel=0.01)


def test_enu_heights():
    dem = sample_dem()
    origin = EnuOrigin(36.5896, -84.2458, 500.0, geoid_undulation=-31.0)
    ortho = MetaMap(dem, origin).tile_at(0.0, 0.0, 100.0, 201, 201)
    enu = MetaMap(dem, origin, heights="enu").tile_at(0.0, 0.0, 100.0, 201, 201)
    assert enu.heights == "enu"
    # at the origin: u = H + N - alt
    assert enu.elevation[100, 100] == pytest.approx(ortho.elevation[100, 100] - 31.0 - 500.0,
                                                    abs=1e-3)
    # 10 km east the surface has dropped by d^2 / 2R ~ 7.85 m below the tangent plane
    drop = (ortho.elevation[100, 200] - 531.0) - enu.elevation[100, 200]
    assert drop == pytest.approx(1e8 / (2 * 6_371_000.0), abs=0.05)


def test_bad_arguments():
    dem = sample_dem()
    with pytest.raises(ValueError, match="interpolation"):
        MetaMap(dem, interpolation="kriging")
    with pytest.raises(ValueError, match="heights"):
        MetaMap(dem, heights="geoid")
    local = Dem.from_array(np.zeros((4, 4)), (0, 1, 0, 4, 0, -1))
    with pytest.raises(DemError, match="mix"):
        MetaMap([dem, local])


def _terrain(lon, lat):
    """A surface continuous across the antimeridian, sloping ~87 m per degree of longitude
    there: a DEM misplaced by a cell is off by metres."""
    return (1000.0 + 5000.0 * np.sin(np.radians(lon)) + 300.0 * (lat - 45.0)).astype(np.float32)


def _lonlat_geotiff(path, left, right, cell, south=44.5, north=45.5):
    """A GeoTIFF in EPSG:4326 over [left, right] x [south, north] holding :func:`_terrain`."""
    import rasterio

    width, height = round((right - left) / cell), round((north - south) / cell)
    lon = left + (np.arange(width) + 0.5) * cell
    lat = north - (np.arange(height) + 0.5) * cell
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1,
                       dtype="float32", crs="EPSG:4326",
                       transform=Affine(cell, 0, left, 0, -cell, north)) as ds:
        ds.write(_terrain(lon[None, :], lat[:, None]), 1)
    return open_dem(path)


@pytest.mark.parametrize("lon0,spans,cell", [
    (180.0, [(179.5, 180.5)], 1 / 120),  # one DEM, longitudes past 180
    (-180.0, [(-180.5, -179.5)], 1 / 120),  # one DEM, longitudes before -180
    (179.95, [(179.0, 180.0), (-180.0, -179.0)], 1 / 120),  # a tile either side
    (-179.95, [(-180.0, -179.0), (179.0, 180.0)], 1 / 120),
    (-179.97, [(-180.0, 180.0)], 0.25),  # a global DEM, its two edges meeting at the mission
])
def test_dem_across_the_antimeridian(tmp_path, lon0, spans, cell):
    dems = [_lonlat_geotiff(tmp_path / f"{i}.tif", *s, cell) for i, s in enumerate(spans)]
    origin = EnuOrigin(45.0, lon0)
    mm = MetaMap(dems, origin)
    assert len(mm.layers) == 1  # tiles either side of 180 (or a DEM's two ends) meet
    georef = GeoReference.centred(0.0, 0.0, 100.0, 120, 100)  # 12 km across the antimeridian
    tile = mm.tile(georef)
    assert tile.valid_fraction == 1.0
    cols, rows = np.meshgrid(np.arange(120), np.arange(100))
    e, n = georef.pixel_to_enu(cols, rows)
    lat, lon, _ = origin.enu_to_geodetic(e, n, origin.surface_up(e, n))
    assert lon.min() < -179.9 and lon.max() > 179.9  # the tile does straddle it
    # bilinear samples of a smooth surface: OpenCV's 1/32-cell positions, and for the
    # 0.25 deg DEM the surface's curvature between posts
    tol = 0.05 if cell < 0.01 else 0.5
    assert np.abs(tile.elevation - _terrain(lon, lat)).max() < tol
