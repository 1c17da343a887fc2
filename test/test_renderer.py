"""GPU landmark renderer against the numpy reference ray caster, sun position, bad input."""

import datetime as dt

import numpy as np
import pytest

from terrain_nav_ros.core.render.raycast_reference import ReferenceRaycaster
from terrain_nav_ros.core.render.renderer import (
    EGLUnavailableError,
    InvalidTerrainError,
    LandmarkRenderer,
    NoTerrainVisibleError,
    PinholeCamera,
    RendererError,
    TerrainFrame,
    albedo_lookup,
    bilinear_local,
    build_distance_map,
    create_headless_context,
)
from terrain_nav_ros.core.render.sun import solar_position, sun_direction_enu
from terrain_nav_ros.core.terrain.georef import GeoReference


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def ctx():
    try:
        context = create_headless_context()
    except EGLUnavailableError as exc:
        pytest.skip(f"no headless EGL OpenGL context on this machine: {exc}")
    yield context
    context.release()


@pytest.fixture(scope="module")
def renderer(ctx):
    r = LandmarkRenderer(ctx)
    yield r
    r.release()


def peak_tile(n=64, gsd=30.0):
    """Gaussian peak on gentle waves; the peak sample is the unique maximum at (20, 40)."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    h = (1000 + 300 * np.exp(-((x - 40) ** 2 + (y - 20) ** 2) / (2 * 6.0**2))
         + 20 * np.sin(x / 5.0) * np.cos(y / 7.0))
    return h, GeoReference(2000.0, 9000.0, gsd, n, n)


def ridge_tile(with_ridge=True, n=64, gsd=10.0):
    """A north-south ridge (crest at col 26) in front of a valley (axis at col 42)."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    h = 1000 - 60 * np.exp(-((x - 42) ** 2) / (2 * 5.0**2)) + 5 * np.sin(y / 4.0)
    if with_ridge:
        h += 150 * np.exp(-((x - 26) ** 2) / (2 * 2.5**2))
    return h, GeoReference(0.0, n * gsd, gsd, n, n)


def look_at(position, target):
    """Optical -> ENU rotation of a level-roll camera at ``position`` aimed at ``target``."""
    f = np.asarray(target, float) - position
    f /= np.linalg.norm(f)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(f, x), f], axis=1)


def agreement(gpu, ref, cell):
    """Fraction of pixels where hit/miss agree and hits are within half a DEM cell."""
    dist = np.linalg.norm(gpu.hit_enu - ref.hit_enu, axis=-1)
    both = gpu.mask & ref.mask
    ok = (gpu.mask == ref.mask) & (~both | (dist <= 0.5 * cell))
    return ok.mean()


def assert_matches_reference(gpu, ref, cell, grey_tol=0.02):
    assert gpu.unresolved == 0
    assert agreement(gpu, ref, cell) >= 0.99
    both = gpu.mask & ref.mask
    grey_err = np.abs(gpu.grey - ref.grey)[both]
    assert np.mean(grey_err <= grey_tol) >= 0.99
    assert np.median(grey_err) < 1e-3


# ----------------------------------------------------------------------------- sun
def test_sun_noon_at_equinox_is_ninety_minus_latitude():
    # March equinox 2024-03-20 03:06 UTC; solar noon at Greenwich ~12:07 UTC.
    times = np.arange(np.datetime64("2024-03-20T11:30"), np.datetime64("2024-03-20T12:45"),
                      np.timedelta64(15, "s"))
    for lat in (45.0, 10.0, -35.0):
        az, el = solar_position(times, lat, 0.0, refraction=False)
        noon = np.argmax(el)
        assert abs(el[noon] - (90.0 - abs(lat))) < 0.5
        assert abs(((az[noon] - (180.0 if lat > 0 else 0.0)) + 180) % 360 - 180) < 1.0


def test_sun_matches_nrel_spa_reference_case():
    # Reda & Andreas (2008) SPA example: topocentric zenith 50.11162, azimuth 194.34024.
    when = dt.datetime(2003, 10, 17, 12, 30, 30, tzinfo=dt.timezone(dt.timedelta(hours=-7)))
    az, el = solar_position(when, 39.742476, -105.1786)
    assert abs(float(az) - 194.34024) < 0.01
    assert abs((90.0 - float(el)) - 50.11162) < 0.01  # SPA used 820 mbar, NOAA 1010


def test_sun_at_june_solstice_over_the_tropic():
    times = np.arange(np.datetime64("2024-06-20T17:00"), np.datetime64("2024-06-20T19:00"),
                      np.timedelta64(30, "s"))
    _, el = solar_position(times, 23.44, -90.0, refraction=False)
    assert el.max() > 89.5


def test_sun_direction_enu_axes():
    np.testing.assert_allclose(sun_direction_enu(90.0, 0.0), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(sun_direction_enu(0.0, 0.0), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(sun_direction_enu(123.0, 90.0), [0, 0, 1], atol=1e-12)


# ----------------------------------------------------------------------------- distance map
def test_distance_map_is_a_lower_bound():
    from scipy.spatial import cKDTree

    h, g = peak_tile(n=48)
    frame = TerrainFrame.from_heights(h, g)
    dmap = build_distance_map(h, frame, (12, 12, 8))
    h_local = h - frame.z0
    # Dense samples of the bilinear surface: the true distance is at most the nearest one.
    fine = (np.arange(4 * g.width) + 0.5) * g.gsd / 4
    xy = np.stack(np.meshgrid(fine, fine), -1).reshape(-1, 2)
    surface = np.column_stack([xy, bilinear_local(h_local, g.gsd, xy)])
    rng = np.random.default_rng(0)
    p = rng.uniform([0, 0, 0], frame.size, size=(4000, 3))
    idx = np.minimum((p / dmap.voxel).astype(int), np.array(dmap.shape_xyz) - 1)
    centre = (idx + 0.5) * dmap.voxel
    bound = dmap.values[idx[:, 2], idx[:, 1], idx[:, 0]] - np.linalg.norm(p - centre, axis=1)
    above = p[:, 2] > bilinear_local(h_local, g.gsd, p[:, :2])
    upper = cKDTree(surface).query(p)[0]
    assert np.all(bound[above] <= upper[above] + 1e-3)
    assert np.all(bound[~above] <= 1e-3)
    assert np.mean(bound[above] > 0.2 * upper[above]) > 0.3  # and it is useful


# ----------------------------------------------------------------------------- nadir
def test_nadir_georeference_is_exact(renderer):
    h, g = peak_tile()
    renderer.set_terrain(h, g)
    res = renderer.render_nadir(sun=(315.0, 45.0))
    assert res.rgb.shape == (64, 64, 3) and res.rgb.dtype == np.float32
    assert res.grey_u8.dtype == np.uint8 and res.georef == g
    assert res.mask.all()
    peak = np.unravel_index(np.argmax(res.hit_enu[..., 2]), g.shape)
    assert peak == np.unravel_index(np.argmax(h), h.shape) == (20, 40)
    # Every pixel sees the ground exactly below its centre, at the DEM sample's height.
    col, row = np.meshgrid(np.arange(g.width), np.arange(g.height))
    east, north = g.pixel_to_enu(col, row)
    np.testing.assert_allclose(res.hit_enu[..., 0], east, atol=1e-3)
    np.testing.assert_allclose(res.hit_enu[..., 1], north, atol=1e-3)
    np.testing.assert_allclose(res.hit_enu[..., 2], h, atol=0.05)


def test_a_draped_photo_is_shown_as_it_is_under_any_sun(renderer):
    """A real orthophoto holds its own light: a nadir render shows it pixel for pixel,
    whatever the sun; a perspective view shows its pixels where the rays hit; a new terrain
    or ``set_photo(None)`` brings back the lit albedo ramp."""
    h, g = peak_tile()
    renderer.set_terrain(h, g)
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.05, 0.95, (*h.shape, 3)).astype(np.float32)
    renderer.set_photo(photo)
    for sun in ((315.0, 45.0), (135.0, 10.0)):
        np.testing.assert_allclose(renderer.render_nadir(sun=sun).rgb, photo, atol=1e-5)
    cam = PinholeCamera(60.0, 60.0, 31.5, 31.5, 64, 64)
    eye = (2960.0, 8040.0, 4000.0)
    persp = renderer.render_perspective(cam, eye, look_at(eye, (2960.0, 8100.0, 0.0)))
    seen = persp.mask
    assert seen.mean() > 0.2
    hit_col, hit_row = g.enu_to_pixel(persp.hit_enu[seen, 0], persp.hit_enu[seen, 1])
    expected = photo[np.clip(np.rint(hit_row).astype(int), 0, 63),
                     np.clip(np.rint(hit_col).astype(int), 0, 63)]
    # bilinear against the nearest pixel of random noise
    assert np.median(np.abs(persp.rgb[seen] - expected)) < 0.15
    renderer.set_photo(None)
    lit = renderer.render_nadir(sun=(315.0, 45.0)).rgb
    assert np.abs(lit - photo).mean() > 0.1
    with pytest.raises(ValueError, match="shaped"):
        renderer.set_photo(photo[:10])


def test_nadir_matches_reference_on_other_raster(renderer):
    h, g = peak_tile()
    renderer.set_terrain(h, g)
    # Finer GSD, shifted, partly off the tile: off-tile pixels must be NaN in both.
    out = GeoReference(g.origin_east + 700.0, g.origin_north - 400.0, 17.0, 96, 80)
    gpu = renderer.render_nadir(out, sun=(135.0, 30.0))
    ref = ReferenceRaycaster(h, g).render_nadir(out, sun=(135.0, 30.0))
    assert 0.2 < gpu.mask.mean() < 1.0
    assert_matches_reference(gpu, ref, g.gsd)


def test_nadir_shadows_match_reference(renderer):
    h, g = peak_tile()
    renderer.set_terrain(h, g)
    lit = renderer.render_nadir(sun=(315.0, 15.0), shadows=False)
    gpu = renderer.render_nadir(sun=(315.0, 15.0), shadows=True)
    ref = ReferenceRaycaster(h, g).render_nadir(sun=(315.0, 15.0), shadows=True)
    assert np.count_nonzero(gpu.grey < lit.grey - 1e-3) > 50  # the peak casts a shadow
    assert_matches_reference(gpu, ref, g.gsd)


# ----------------------------------------------------------------------------- perspective
def test_oblique_view_matches_reference(renderer):
    h, g = peak_tile()
    renderer.set_terrain(h, g)
    cx, cy = g.centre
    pos = np.array([cx - 1500.0, cy - 1200.0, 1900.0])
    r = look_at(pos, [cx, cy, 1000.0])
    cam = PinholeCamera(70.0, 70.0, 47.5, 31.5, 96, 64)
    gpu = renderer.render_perspective(cam, pos, r, sun=(250.0, 30.0), shadows=True)
    ref = ReferenceRaycaster(h, g).render_perspective(cam, pos, r, sun=(250.0, 30.0),
                                                       shadows=True)
    assert 0.3 < gpu.mask.mean() < 1.0  # sees terrain and sky
    assert_matches_reference(gpu, ref, g.gsd)


def test_plain_distance_map_sphere_tracing_matches_reference(ctx):
    # The dissertation's scheme alone: no slope steps, no level of detail, coarse voxels.
    h, g = peak_tile()
    cx, cy = g.centre
    pos = np.array([cx + 1600.0, cy + 900.0, 1500.0])
    r = look_at(pos, [cx, cy, 1000.0])
    cam = PinholeCamera(60.0, 60.0, 31.5, 31.5, 64, 64)
    renderer = LandmarkRenderer(ctx, slope_steps=False, lod_pixels=0.0, cells_per_voxel=8)
    try:
        renderer.set_terrain(h, g)
        gpu = renderer.render_perspective(cam, pos, r, sun=(90.0, 40.0))
    finally:
        renderer.release()
    ref = ReferenceRaycaster(h, g).render_perspective(cam, pos, r, sun=(90.0, 40.0))
    assert_matches_reference(gpu, ref, g.gsd)


def test_sun_below_horizon_leaves_ambient_only(renderer):
    h, g = peak_tile(n=32)
    renderer.set_terrain(h, g)
    night = renderer.render_nadir(sun=(90.0, -5.0))
    ref = ReferenceRaycaster(h, g).render_nadir(sun=(90.0, -5.0))
    albedo = albedo_lookup(*renderer.albedo.table(), night.hit_enu[..., 2])
    np.testing.assert_allclose(night.rgb, albedo * renderer.ambient, atol=1e-5)
    np.testing.assert_allclose(night.rgb, ref.rgb, atol=1e-5)


def test_ridge_occludes_valley_first_intersection_wins(ctx):
    h_flat, g = ridge_tile(with_ridge=False)
    h, _ = ridge_tile(with_ridge=True)
    cam = PinholeCamera(60.0, 60.0, 31.5, 31.5, 64, 64)
    pos = np.array([-150.0, 320.0, 1500.0])
    r = look_at(pos, [480.0, 320.0, 800.0])
    renderer = LandmarkRenderer(ctx)
    try:
        renderer.set_terrain(h_flat, g)
        open_view = renderer.render_perspective(cam, pos, r)
        renderer.set_terrain(h, g)
        gpu = renderer.render_perspective(cam, pos, r)
    finally:
        renderer.release()
    ref = ReferenceRaycaster(h, g).render_perspective(cam, pos, r)
    crest_east = 26.5 * g.gsd
    # Pixels that would see the valley floor without the ridge but see the ridge with it.
    sees_valley = open_view.hit_enu[..., 0] > crest_east + 100.0
    occluded = sees_valley & (gpu.hit_enu[..., 0] < crest_east + 20.0)
    assert np.count_nonzero(occluded) > 150
    assert np.count_nonzero(sees_valley & ~occluded & gpu.mask) > 150  # far side visible
    assert_matches_reference(gpu, ref, g.gsd)
    dist = np.linalg.norm(gpu.hit_enu - ref.hit_enu, axis=-1)[occluded]
    assert np.all(dist <= 0.5 * g.gsd)


def test_real_dem_oblique_matches_reference(renderer, shared_data):
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(shared_data / "dem" / "bigtujunga_srtm30m_utm11.tif") as src:
        h = src.read(1, window=((100, 164), (500, 564))).astype(float)
        gsd = float(src.res[0])
    g = GeoReference(0.0, 64 * gsd, gsd, 64, 64)
    renderer.set_terrain(h, g)
    cx, cy = g.centre
    pos = np.array([cx - 900.0, cy, h.max() + 60.0])  # low, grazing over the ridges
    r = look_at(pos, [cx + 300.0, cy, h.mean() - 200.0])
    cam = PinholeCamera(60.0, 60.0, 39.5, 29.5, 80, 60)
    gpu = renderer.render_perspective(cam, pos, r, sun=(200.0, 25.0), shadows=True)
    ref = ReferenceRaycaster(h, g).render_perspective(cam, pos, r, sun=(200.0, 25.0),
                                                       shadows=True)
    assert_matches_reference(gpu, ref, gsd)


def test_renderer_reuses_gl_objects_across_tiles(renderer):
    h, g = peak_tile(n=48)
    renderer.set_terrain(h, g)
    program, height_tex = renderer.program, renderer._textures["height"]
    first = renderer.render_nadir()
    renderer.set_terrain(h + 10.0, g)
    second = renderer.render_nadir()
    assert renderer.program is program and renderer._textures["height"] is height_tex
    np.testing.assert_allclose(second.hit_enu[..., 2], first.hit_enu[..., 2] + 10.0, atol=0.05)



def test_framebuffers_are_kept_for_the_last_sizes_only(renderer):
    """A long flight renders tiles of ever new sizes (they follow the position's
    uncertainty): only the last few sizes' framebuffers stay, and a size rendered again
    after its framebuffer went is rendered the same."""
    from terrain_nav_ros.core.render.renderer import _KEPT_FRAMEBUFFERS

    sizes = list(range(40, 40 + 2 * (_KEPT_FRAMEBUFFERS + 3), 2))
    first = {}
    for n in sizes + sizes[:1]:
        h, g = peak_tile(n=n)
        renderer.set_terrain(h, g)
        image = renderer.render_nadir().hit_enu[..., 2]
        first.setdefault(n, image)
        assert len(renderer._fbos) <= _KEPT_FRAMEBUFFERS
    np.testing.assert_array_equal(image, first[sizes[0]])


# ----------------------------------------------------------------------------- bad input
def test_bad_terrain_is_rejected(renderer):
    h, g = peak_tile(n=32)
    bad = h.copy()
    bad[3, 4] = np.nan
    with pytest.raises(InvalidTerrainError, match="NaN"):
        renderer.set_terrain(bad, g)
    with pytest.raises(InvalidTerrainError, match="non-empty"):
        renderer.set_terrain(np.zeros((0, 0)), GeoReference(0.0, 0.0, 1.0, 0, 0))
    with pytest.raises(InvalidTerrainError, match="shape"):
        renderer.set_terrain(h[:, :20], g)
    assert issubclass(InvalidTerrainError, ValueError)


def test_view_without_terrain_raises(renderer):
    h, g = peak_tile(n=32)
    renderer.set_terrain(h, g)
    cam = PinholeCamera(40.0, 40.0, 15.5, 15.5, 32, 32)
    cx, cy = g.centre
    pos = np.array([cx, cy, 3000.0])
    up = look_at(pos, [cx + 1.0, cy, 9000.0])  # looking at the sky
    with pytest.raises(NoTerrainVisibleError):
        renderer.render_perspective(cam, pos, up)
    away = look_at(np.array([cx + 5000.0, cy, 1500.0]), [cx + 9000.0, cy, 1000.0])
    with pytest.raises(NoTerrainVisibleError):
        renderer.render_perspective(cam, [cx + 5000.0, cy, 1500.0], away)
    with pytest.raises(NoTerrainVisibleError):
        renderer.render_nadir(GeoReference(1e6, 1e6, 30.0, 16, 16))
    with pytest.raises(ValueError, match="empty"):
        renderer.render_nadir(GeoReference(cx, cy, 30.0, 0, 16))
    assert issubclass(NoTerrainVisibleError, RuntimeError)


def test_bad_pose_and_order_errors(ctx, renderer):
    fresh = LandmarkRenderer(ctx)
    try:
        with pytest.raises(RendererError, match="set_terrain"):
            fresh.render_nadir()
    finally:
        fresh.release()
    h, g = peak_tile(n=32)
    renderer.set_terrain(h, g)
    cam = PinholeCamera(40.0, 40.0, 15.5, 15.5, 32, 32)
    cx, cy = g.centre
    down = look_at(np.array([cx, cy, 5000.0]), [cx + 1.0, cy, 0.0])
    with pytest.raises(ValueError, match="below the terrain"):
        renderer.render_perspective(cam, [cx, cy, 900.0], down)
    with pytest.raises(ValueError, match="rotation"):
        renderer.render_perspective(cam, [cx, cy, 5000.0], 2 * down)
    with pytest.raises(ValueError):
        PinholeCamera(0.0, 40.0, 15.5, 15.5, 32, 32)
    with pytest.raises(ValueError):
        renderer.render_nadir(sun=(np.nan, 30.0))


def test_step_budget_exhaustion_is_reported(ctx):
    h, g = peak_tile(n=32)
    cx, cy = g.centre
    pos = np.array([cx - 1200.0, cy, 1400.0])
    r = look_at(pos, [cx, cy, 1000.0])
    cam = PinholeCamera(30.0, 30.0, 15.5, 15.5, 32, 32)
    renderer = LandmarkRenderer(ctx, max_steps=4, slope_steps=False)
    try:
        renderer.set_terrain(h, g)
        res = renderer.render_perspective(cam, pos, r)
        assert res.unresolved > 0 and res.mask.sum() + res.unresolved <= res.mask.size
        renderer.max_steps = 1
        with pytest.raises(RendererError, match="max_steps"):
            renderer.render_perspective(cam, pos, r)
    finally:
        renderer.release()


def test_missing_egl_gives_clear_error(monkeypatch):
    import moderngl

    def fail(**kwargs):
        raise Exception("eglGetDisplay failed")

    monkeypatch.setattr(moderngl, "create_standalone_context", fail)
    with pytest.raises(EGLUnavailableError, match="EGL"):
        create_headless_context()
