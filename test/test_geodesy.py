"""Geodesy: WGS84 <-> local ENU (exact, sub-millimetre) and DEM CRS <-> ENU."""

import numpy as np
import pytest
from pyproj import Transformer

from terrain_nav_ros.core.terrain.geodesy import (
    EARTH_RADIUS,
    CrsEnuTransform,
    EnuOrigin,
    LocalEnuTransform,
    as_crs,
    longitude_period,
    wrap_longitude,
)

# WGS84 ellipsoid, for an independent closed-form ECEF/ENU reference
A, F = 6378137.0, 1 / 298.257223563
E2 = F * (2 - F)


def ecef(lat, lon, h):
    lat, lon = np.radians(lat), np.radians(lon)
    n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)
    return np.array([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1 - E2) + h) * np.sin(lat)])


def enu_reference(origin, lat, lon, h):
    la, lo = np.radians(origin.lat), np.radians(origin.lon)
    rot = np.array([[-np.sin(lo), np.cos(lo), 0],
                    [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                    [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    d = ecef(lat, lon, h) - ecef(origin.lat, origin.lon, origin.alt)[:, None]
    return rot @ d


ORIGINS = [EnuOrigin(44.1741, 5.2789, 1909.0), EnuOrigin(-33.99, 20.5, 120.0),
           EnuOrigin(40.2549, -105.6151, 4346.0, geoid_undulation=-16.0),
           EnuOrigin(78.2, 15.6, 0.0)]


def random_points(origin, n=2000, radius_deg=0.5, seed=0):
    rng = np.random.default_rng(seed)
    return (origin.lat + rng.uniform(-radius_deg, radius_deg, n),
            origin.lon + rng.uniform(-radius_deg, radius_deg, n),
            rng.uniform(-100.0, 6000.0, n))


@pytest.mark.parametrize("origin", ORIGINS, ids=lambda o: f"{o.lat},{o.lon}")
def test_geodetic_enu_round_trip_sub_millimetre(origin):
    lat, lon, h = random_points(origin)
    e, n, u = origin.geodetic_to_enu(lat, lon, h)
    lat2, lon2, h2 = origin.enu_to_geodetic(e, n, u)
    e2, n2, u2 = origin.geodetic_to_enu(lat2, lon2, h2)
    assert np.abs(np.stack([e2 - e, n2 - n, u2 - u])).max() < 1e-3
    # in angle too: 1e-9 deg is 0.1 mm
    assert np.abs(lat2 - lat).max() < 1e-9 and np.abs(lon2 - lon).max() < 1e-9
    assert np.abs(h2 - h).max() < 1e-3


@pytest.mark.parametrize("origin", ORIGINS, ids=lambda o: f"{o.lat},{o.lon}")
def test_enu_matches_closed_form_ecef(origin):
    lat, lon, h = random_points(origin, n=200, seed=1)
    ref = enu_reference(origin, lat, lon, h)
    got = np.stack(origin.geodetic_to_enu(lat, lon, h))
    assert np.abs(got - ref).max() < 1e-6 * np.abs(ref).max() + 1e-4


def test_enu_axes():
    o = EnuOrigin(44.0, 5.0, 100.0)
    assert np.allclose(o.geodetic_to_enu(44.0, 5.0, 100.0), 0.0, atol=1e-6)
    assert np.allclose(o.geodetic_to_enu(44.0, 5.0, 150.0), (0, 0, 50), atol=1e-6)
    e, n, u = o.geodetic_to_enu(44.01, 5.0, 100.0)  # north: ~1111 m, and the surface drops
    assert abs(e) < 1e-6 and 1100 < n < 1120 and -0.2 < u < 0
    e, n, u = o.geodetic_to_enu(44.0, 5.01, 100.0)  # east: 1111 m * cos(44 deg)
    assert 790 < e < 810 and n > 0 and n < 0.1  # a small northing: parallels curve


def test_scalars_and_broadcasting():
    o = ORIGINS[0]
    e, n, u = o.geodetic_to_enu(44.2, 5.3, 0.0)
    assert np.ndim(e) == 0
    e, n, u = o.geodetic_to_enu(np.full((3, 4), 44.2), np.full((3, 4), 5.3))
    assert e.shape == (3, 4)


@pytest.mark.parametrize("radius_deg,tol", [(0.1, 0.002), (0.3, 0.02)])
def test_surface_up_is_constant_height_surface(radius_deg, tol):
    for o in ORIGINS:
        lat, lon, _ = random_points(o, n=500, radius_deg=radius_deg, seed=2)
        for h in (o.alt, o.alt + 2000.0):
            e, n, u = o.geodetic_to_enu(lat, lon, h)
            assert np.abs(o.surface_up(e, n, h) - u).max() < tol
    o = ORIGINS[0]
    assert o.surface_up(10_000.0, 0.0) == pytest.approx(-1e8 / (2 * EARTH_RADIUS), rel=0.01)
    east, north = np.linspace(-30e3, 30e3, 7), np.linspace(-20e3, 25e3, 5)
    grid = o.surface_up(east[None, :], north[:, None], 3000.0)
    fast = o.surface_up_grid(east, north, 3000.0)
    assert fast.shape == (5, 7) and fast.dtype == np.float32
    assert np.abs(fast - grid).max() < 1e-3


def test_datum_helpers():
    o = EnuOrigin(40.0, -105.0, 1600.0, geoid_undulation=-16.5)
    assert o.orthometric_to_ellipsoidal(4346.0) == pytest.approx(4329.5)


@pytest.mark.parametrize("bad", [dict(lat=91, lon=0), dict(lat=0, lon=400),
                                 dict(lat=float("nan"), lon=0), dict(lat=0, lon=0, alt=np.inf)])
def test_origin_validation(bad):
    with pytest.raises(ValueError):
        EnuOrigin(**bad)


@pytest.mark.parametrize("epsg,x,y", [(32611, 394000.0, 3798000.0), (23030, 270000.0, 4459000.0),
                                      (4326, 5.2789, 44.1741), (3857, 587650.0, 5493000.0)])
def test_crs_enu_round_trip(epsg, x, y):
    to_geo = Transformer.from_crs(epsg, 4326, always_xy=True)
    lon, lat = to_geo.transform(x, y)
    t = CrsEnuTransform(f"EPSG:{epsg}", EnuOrigin(lat, lon, 1000.0))
    rng = np.random.default_rng(3)
    scale = 0.2 if epsg == 4326 else 20_000.0
    xs, ys = x + rng.uniform(-1, 1, 500) * scale, y + rng.uniform(-1, 1, 500) * scale
    e, n, u = t.to_enu(xs, ys)
    x2, y2 = t.from_enu(e, n)
    # ED50 goes through a Helmert datum shift whose horizontal part depends (by mm) on the
    # ellipsoidal height, which a 2-D DEM CRS does not pin down
    tol = {4326: 1e-8, 23030: 5e-3}.get(epsg, 1e-3)
    assert np.abs(x2 - xs).max() < tol and np.abs(y2 - ys).max() < tol
    # the origin is the origin (to a few cm through the ED50 datum shift, which is itself only
    # metre-accurate)
    e0, n0, u0 = t.to_enu(x, y)
    tol = 0.05 if epsg == 23030 else 1e-3
    assert abs(e0) < tol and abs(n0) < tol and abs(u0) < tol


def test_crs_enu_heights_and_grid_convergence():
    # UTM 11N well west of its central meridian (-117): grid north is rotated from true north
    t = CrsEnuTransform("EPSG:32611", EnuOrigin(34.3, -118.2, 1000.0, geoid_undulation=-35.0))
    x0, y0 = Transformer.from_crs(4326, 32611, always_xy=True).transform(-118.2, 34.3)
    e, n, _ = t.to_enu([x0, x0], [y0, y0 + 10_000.0])
    convergence = np.degrees(np.arctan2(e[1] - e[0], n[1] - n[0]))
    expected = np.degrees(np.arctan(np.tan(np.radians(-118.2 + 117)) * np.sin(np.radians(34.3))))
    assert convergence == pytest.approx(expected, abs=0.02)  # grid north is west of true
    # orthometric height H sits at ellipsoidal H + N: ENU up at the origin is H + N - alt
    _, _, u = t.to_enu(x0, y0, height=1035.0)
    assert float(u) == pytest.approx(0.0, abs=1e-3)


@pytest.mark.parametrize("lon0", [180.0, -180.0, 179.95, -179.95])
def test_longitudes_continue_across_the_antimeridian(lon0):
    # PROJ answers in [-180, 180): from_enu keeps them within half a turn of the origin's,
    # so a line across the antimeridian has monotonic longitudes
    t = CrsEnuTransform("EPSG:4326", EnuOrigin(45.0, lon0))
    x, y = t.from_enu(np.linspace(-20_000.0, 20_000.0, 41), 0.0)
    assert np.all(np.diff(x) > 0) and np.abs(x - lon0).max() < 0.3
    assert t.to_enu(x, y)[0] == pytest.approx(np.linspace(-20_000.0, 20_000.0, 41), abs=1e-6)
    assert t.period == 360.0 and t.x_origin == pytest.approx(lon0 if lon0 > -180 else -180.0)
    assert CrsEnuTransform("EPSG:32660", EnuOrigin(45.0, lon0)).period is None


def test_wrap_longitude():
    assert wrap_longitude([-179.5, 179.5, 540.0, np.inf], 180.0) == pytest.approx(
        [180.5, 179.5, 180.0, np.inf])
    assert wrap_longitude(-250.0, 0.0, 400.0) == pytest.approx(150.0)  # grads
    assert longitude_period("EPSG:4807") == pytest.approx(400.0)  # NTF (Paris), grads


def test_local_transform():
    t = LocalEnuTransform(482787.97, 4360722.71)
    e, n, u = t.to_enu(482797.97, 4360702.71, height=2000.0)
    assert (e, n, u) == pytest.approx((10.0, -20.0, 2000.0))
    assert t.from_enu(e, n) == pytest.approx((482797.97, 4360702.71))


def test_unknown_crs():
    with pytest.raises(ValueError, match="unknown CRS"):
        as_crs("EPSG:99999999")
