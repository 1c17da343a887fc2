"""Minutiae (dissertation 3.3): crossing number, orientation, validation, real DEMs."""

import numpy as np
import pytest

from terrain_nav_ros.core.features.creases import CreaseParams
from terrain_nav_ros.core.features.hillshade import hillshade
from terrain_nav_ros.core.features.minutia_set import BIFURCATION, ENDING
from terrain_nav_ros.core.features.minutiae import (
    FeatureExtractor,
    MinutiaParams,
    crossing_number,
    extract_features,
    extract_minutiae,
    normalised_coordinates,
    orientation_field,
)
from terrain_nav_ros.core.terrain.georef import GeoReference

N = 256
Y_SEGMENTS = [((128, 128), (128, 216)), ((128, 128), (48, 48)), ((128, 128), (208, 48))]
# (col, row, ENU angle in degrees): endings point along their crease, the bifurcation
# along its stem.
Y_ENDINGS = [(128, 216, 90.0), (48, 48, 315.0), (208, 48, 225.0)]
Y_BIFURCATION = (128, 128, 270.0)


def valley_image(segments, n=N, width=3.0, depth=120.0):
    """uint8 image of dark Gaussian-profile valleys along (col, row) segments."""
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    dist = np.full((n, n), np.inf)
    for p0, p1 in segments:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        d = p1 - p0
        t = np.clip(((cc - p0[0]) * d[0] + (rr - p0[1]) * d[1]) / (d @ d), 0, 1)
        dist = np.minimum(dist, np.hypot(cc - p0[0] - t * d[0], rr - p0[1] - t * d[1]))
    return np.round(200 - depth * np.exp(-dist**2 / (2 * width**2))).astype(np.uint8)


def angdiff_deg(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


def find(ms, col, row, kind=None, tol=6.0):
    """Index of the minutia nearest (col, row) within tol px (of that kind), else None.

    Crease ends are blunt (the valley profile extends about 2 width past the segment end)
    and the skeleton may hook there, hence a few pixels of tolerance.
    """
    d = np.hypot(ms.col - col, ms.row - row)
    if kind is not None:
        d = np.where(ms.kind == kind, d, np.inf)
    i = int(np.argmin(d)) if len(d) else None
    return i if i is not None and d[i] <= tol else None


# --------------------------------------------------------------------------- primitives


def test_crossing_number_of_end_line_and_fork():
    sk = np.zeros((7, 7), bool)
    sk[3, 1:6] = True          # horizontal line
    sk[0:3, 3] = True          # branch going north from (3, 3)
    cn = crossing_number(sk)
    assert cn[3, 1] == 1 and cn[3, 5] == 1 and cn[0, 3] == 1
    assert cn[3, 2] == 2 and cn[1, 3] == 2
    assert cn[3, 3] == 3
    assert cn[~sk].max() == 0


def test_normalised_coordinates_eq_3_8_3_9():
    x, y = normalised_coordinates([0, 99], [0, 49], width=100, height=50)
    assert np.allclose(x, [0.01, 1.0]) and np.allclose(y, [1.0, 0.02])


def test_orientation_field_of_oblique_stripes():
    theta = np.deg2rad(30.0)  # creases run 30 deg north of east
    rr, cc = np.mgrid[0:128, 0:128].astype(float)
    # Phase varies across the creases: normal (d_col, d_row) = (sin, cos) of theta.
    img = np.cos(2 * np.pi * (cc * np.sin(theta) + rr * np.cos(theta)) / 12.0)
    angle, coherence = orientation_field(img.astype(np.float32))
    inner = (slice(24, -24), slice(24, -24))
    assert np.all(angdiff_deg(np.rad2deg(angle[inner]) * 2, 60.0) < 4.0)
    assert coherence[inner].min() > 0.9


@pytest.mark.parametrize("bad", [
    dict(block_size=1), dict(orient_sigma=0.0), dict(orient_size=0), dict(border_margin=-1),
    dict(spur_length=-2), dict(break_angle=200.0), dict(trace_length=1),
    dict(max_minutiae=-5), dict(min_quality=1.5), dict(cluster_size=0),
    dict(duplicate_distance=float("nan")),
])
def test_bad_params_raise(bad):
    with pytest.raises(ValueError):
        MinutiaParams(**bad)


def test_from_dict_rejects_unknown_keys():
    assert MinutiaParams.from_dict({"block_size": 8}).block_size == 8
    with pytest.raises(ValueError, match="unknown"):
        MinutiaParams.from_dict({"blocksize": 8})


# --------------------------------------------------------------------------- synthetic


def test_straight_valley_has_two_endings():
    ms = extract_minutiae(valley_image([((40, 128), (216, 128))]))
    assert len(ms) == 2 and np.all(ms.kind == ENDING)
    west, east = find(ms, 40, 128), find(ms, 216, 128)
    assert west is not None and east is not None
    assert angdiff_deg(np.rad2deg(ms.angle[west]), 0.0) < 15
    assert angdiff_deg(np.rad2deg(ms.angle[east]), 180.0) < 15


def test_y_valley_has_one_bifurcation_and_three_endings():
    ms = extract_minutiae(valley_image(Y_SEGMENTS))
    assert (ms.kind == BIFURCATION).sum() == 1 and (ms.kind == ENDING).sum() == 3
    col, row, ang = Y_BIFURCATION
    i = find(ms, col, row, BIFURCATION)
    assert i is not None and angdiff_deg(np.rad2deg(ms.angle[i]), ang) < 20
    for col, row, ang in Y_ENDINGS:
        i = find(ms, col, row, ENDING)
        assert i is not None, (col, row)
        assert angdiff_deg(np.rad2deg(ms.angle[i]), ang) < 15, (col, row)
    assert np.all((ms.quality > 0) & (ms.quality <= 1))


def test_rotating_the_image_rotates_the_minutiae():
    img = valley_image(Y_SEGMENTS)
    ms = extract_minutiae(img)
    rot = extract_minutiae(np.rot90(img))  # 90 deg anticlockwise on a north-up raster
    assert len(rot) == len(ms)
    for i in range(len(ms)):
        # np.rot90: (col, row) -> (row, N - 1 - col); directions turn by +90 deg.
        j = find(rot, ms.row[i], N - 1 - ms.col[i], ms.kind[i])
        assert j is not None
        assert angdiff_deg(np.rad2deg(rot.angle[j]), np.rad2deg(ms.angle[i]) + 90) < 20


def test_dtypes_give_the_same_minutiae():
    img = valley_image(Y_SEGMENTS)
    ref = extract_minutiae(img)
    for other in (img.astype(np.uint16) * 257, img / 255.0, img.astype(np.float32) - 1000):
        ms = extract_minutiae(other)
        assert len(ms) == len(ref)
        assert all(find(ms, c, r, k, tol=1.5) is not None
                   for c, r, k in zip(ref.col, ref.row, ref.kind, strict=True))


def _feature_arrays(f):
    c = f.creases
    return [c.work, c.diffused, c.creaseness, c.contrast, *c.masks.values(),
            *c.skeletons.values(), *f.phi]


def test_reused_extractor_never_overwrites_earlier_results():
    from terrain_nav_ros.core.features.minutiae import FeatureExtractor

    ext = FeatureExtractor(CreaseParams(polarity="both"))
    first = ext(valley_image(Y_SEGMENTS))
    kept = [a.copy() for a in _feature_arrays(first)]
    second = ext(valley_image([((40, 128), (216, 128))]))
    assert all(np.array_equal(a, b) for a, b in zip(_feature_arrays(first), kept, strict=True))
    assert not any(np.shares_memory(a, b) for a in _feature_arrays(first)
                   for b in _feature_arrays(second))
    # The work buffers it keeps give the same result as a fresh extractor.
    again = ext(valley_image(Y_SEGMENTS))
    assert np.array_equal(again.minutiae.col, first.minutiae.col)
    assert np.array_equal(again.minutiae.angle, first.minutiae.angle)


def test_one_extractor_in_several_threads_at_once():
    from concurrent.futures import ThreadPoolExecutor

    from terrain_nav_ros.core.features.minutiae import FeatureExtractor

    images = [valley_image(Y_SEGMENTS), valley_image([((40, 128), (216, 128))])] * 3
    ext = FeatureExtractor()
    expected = [FeatureExtractor()(img).minutiae for img in images]
    with ThreadPoolExecutor(3) as pool:
        got = list(pool.map(lambda img: ext(img).minutiae, images))
    for ms, ref in zip(got, expected, strict=True):
        assert np.array_equal(ms.col, ref.col) and np.array_equal(ms.angle, ref.angle)


def test_broken_crease_is_one_crease():
    img = valley_image([((30, 128), (122, 128)), ((130, 128), (226, 128))])
    ms = extract_minutiae(img)
    assert len(ms) == 2 and np.all(ms.kind == ENDING)
    assert find(ms, 30, 128) is not None and find(ms, 226, 128) is not None


def test_nodata_margin_removes_minutiae():
    img = valley_image(Y_SEGMENTS)
    valid = np.ones(img.shape, bool)
    valid[:, 170:] = False  # the right arm leaves the valid area
    p = MinutiaParams()
    ms = extract_minutiae(img, valid_mask=valid, params=p)
    assert find(ms, 208, 48) is None
    assert np.all(ms.col < 170 - p.border_margin)
    assert find(ms, 48, 48, ENDING) is not None


def test_georeference_and_normalised_coordinates():
    geo = GeoReference(1000.0, 2000.0, 10.0, N, N)
    ms = extract_minutiae(valley_image(Y_SEGMENTS), georef=geo)
    east, north = ms.enu()
    assert np.allclose(east, ms.extras["east"]) and np.allclose(north, ms.extras["north"])
    assert np.allclose(east, 1000.0 + (ms.col + 0.5) * 10.0)
    assert np.all((ms.extras["x_norm"] > 0) & (ms.extras["x_norm"] <= 1))
    assert np.all((ms.extras["y_norm"] > 0) & (ms.extras["y_norm"] <= 1))
    with pytest.raises(ValueError):
        extract_minutiae(valley_image(Y_SEGMENTS), georef=GeoReference(0, 0, 1.0, 10, 10))


def test_cap_keeps_the_best():
    img = valley_image(Y_SEGMENTS)
    full = extract_minutiae(img)
    capped = extract_minutiae(img, params=MinutiaParams(max_minutiae=2))
    assert len(capped) == 2
    assert np.allclose(np.sort(capped.quality), np.sort(full.quality)[-2:])


@pytest.mark.parametrize("name,image", [
    ("constant", np.full((128, 128), 99, np.uint8)),
    ("flat float", np.zeros((128, 128), np.float32)),
    ("noise", np.random.default_rng(0).normal(120, 15, (256, 256))),
    ("low-contrast noise", np.random.default_rng(1).integers(100, 103, (256, 256))
     .astype(np.uint8)),
    ("smooth hill", np.exp(-np.add.outer((np.arange(128) - 64.0) ** 2,
                                         (np.arange(128) - 64.0) ** 2) / 2000.0)),
    ("lake DEM", np.full((128, 128), 1234.0)),
    ("tiny", np.zeros((3, 3))),
])
def test_no_drainage_is_empty_with_reason(name, image):
    geo = GeoReference(0, 0, 30.0, image.shape[1], image.shape[0])
    source = "dem" if "DEM" in name else "image"
    ms = extract_minutiae(image, georef=geo, source=source)
    assert len(ms) == 0 and ms.reason, name
    assert ms.georef == geo


def test_features_carry_a_crease_debug_image():
    feats = extract_features(valley_image(Y_SEGMENTS))
    img = feats.crease_image()
    assert img.dtype == np.uint8 and img.shape == (N, N)
    assert (img == 255).sum() > 250 and set(np.unique(img)) <= {0, 128, 255}
    assert {"diffusion", "mlsec", "skeleton", "minutiae"} <= set(feats.timings)


def test_ridge_polarity_finds_bright_creases():
    bright = 255 - valley_image(Y_SEGMENTS)
    ms = extract_minutiae(bright, crease_params=CreaseParams(polarity="ridge"))
    assert (ms.kind == BIFURCATION).sum() == 1 and (ms.kind == ENDING).sum() == 3
    assert ms.extras["ridge"].all()


def test_ridges_on_request_come_from_the_bright_creases_and_give_no_minutiae():
    """A Y of valleys beside a straight ridge: ``ridges=True`` returns the ridge skeleton
    (along the ridge, and along the valleys' shoulders), apart from the valleys; the minutiae
    are the valleys' as without it."""
    img = valley_image(Y_SEGMENTS).astype(float)
    rows, cols = np.mgrid[0:N, 0:N]
    img += 120.0 * np.exp(-((cols - 40) ** 2) / (2 * 3.0 ** 2)) * ((rows > 120) & (rows < 230))
    img = np.clip(img, 0, 255).astype(np.uint8)
    plain = FeatureExtractor()(img)
    feats = FeatureExtractor(ridges=True)(img)
    assert plain.ridges is None
    r_rows, r_cols = np.nonzero(feats.ridges)
    on_ridge = (np.abs(r_cols - 40) <= 2) & (r_rows > 120) & (r_rows < 230)
    assert on_ridge.sum() > 80
    assert not (feats.ridges & feats.creases.skeleton()).any()
    assert np.array_equal(feats.minutiae.col, plain.minutiae.col)
    assert not feats.minutiae.extras["ridge"].any()
    assert "ridges" in feats.timings


# --------------------------------------------------------------------------- real DEMs


def read_dem(path):
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(path) as ds:
        band = ds.read(1, masked=True)
        return np.ma.filled(band.astype(np.float64), np.nan), abs(ds.res[0])


def test_gredos_dem_and_its_hillshade(shared_data):
    dem, gsd = read_dem(shared_data / "dem" / "gredos_25m_epsg23030.tif")
    geo = GeoReference(0.0, 0.0, gsd, dem.shape[1], dem.shape[0])
    ms = extract_minutiae(dem, georef=geo, source="dem")
    assert len(ms) >= 100, ms.reason
    assert (ms.kind == BIFURCATION).sum() >= 20 and (ms.kind == ENDING).sum() >= 50
    assert np.isfinite(ms.angle).all()
    shaded = hillshade(dem, 315, 45, gsd, dtype=np.uint8)
    assert len(extract_minutiae(shaded, georef=geo)) >= 100


def test_bigtujunga_dem(shared_data):
    dem, gsd = read_dem(shared_data / "dem" / "bigtujunga_srtm30m_utm11.tif")
    dem = dem[:512, 300:812]
    ms = extract_minutiae(dem, GeoReference(0.0, 0.0, gsd, 512, 512), source="dem")
    assert len(ms) >= 100 and (ms.kind == BIFURCATION).sum() >= 20


def test_dem_with_voids_keeps_clear_of_them(shared_data):
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(shared_data / "dem" / "halffork_5m.asc") as ds:
        band = ds.read(1, masked=True)
    dem = np.ma.filled(band.astype(float), np.nan)
    valid = ~np.ma.getmaskarray(band)
    assert not valid.all()
    p = MinutiaParams()
    feats = extract_features(dem, GeoReference(0.0, 0.0, 5.0, dem.shape[1], dem.shape[0]),
                             valid_mask=valid, source="dem", params=p)
    ms = feats.minutiae
    assert len(ms) > 0, ms.reason
    from scipy.ndimage import distance_transform_edt
    dist = distance_transform_edt(np.pad(valid, 1))[1:-1, 1:-1]
    assert np.all(dist[ms.row.astype(int), ms.col.astype(int)] >= p.border_margin - 1)
    assert not any(s[~valid].any() for s in feats.creases.skeletons.values())


# --------------------------------------------------------------------------- hillshade


def test_hillshade_lambert():
    from terrain_nav_ros.core.features.hillshade import sun_vector

    flat = np.zeros((16, 16))
    assert np.allclose(hillshade(flat, 315, 45), np.sin(np.deg2rad(45)), atol=1e-6)
    ramp = np.add.outer(np.zeros(16), np.arange(16.0))  # rises to the east
    assert hillshade(ramp, 270, 45).mean() > hillshade(ramp, 90, 45).mean()
    assert hillshade(ramp, 90, 45, dtype=np.uint8).dtype == np.uint8
    assert np.allclose(np.linalg.norm(sun_vector(123, 17)), 1.0)
    with pytest.raises(ValueError):
        sun_vector(0, 95)


def test_fused_orientation_matches_the_reference(monkeypatch):
    from terrain_nav_ros.core.features import _crease_kernels
    from terrain_nav_ros.core.features.minutiae import doubled_angle_field

    if not _crease_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the reference path is the only one")
    img = valley_image(Y_SEGMENTS, n=96).astype(np.float32)
    img += np.random.default_rng(9).normal(0, 3, img.shape).astype(np.float32)
    fused = doubled_angle_field(img)
    monkeypatch.setattr(_crease_kernels, "HAVE_NUMBA", False)
    ref = doubled_angle_field(img)
    assert np.allclose(fused[0], ref[0], atol=1e-4) and np.allclose(fused[1], ref[1], atol=1e-4)


def test_warm_up_compiles_every_kernel():
    from terrain_nav_ros.core.features import _crease_kernels
    from terrain_nav_ros.core.features.minutiae import warm_up

    warm_up()
    if _crease_kernels.HAVE_NUMBA:
        kernels = [getattr(_crease_kernels, k) for k in dir(_crease_kernels)
                   if k.endswith("_kernel")]
        assert kernels and all(k.signatures for k in kernels)


def test_fused_walker_matches_the_reference(monkeypatch):
    from terrain_nav_ros.core.features import _crease_kernels
    from terrain_nav_ros.core.features import minutiae as M

    if not _crease_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the reference path is the only one")
    rng = np.random.default_rng(10)
    img = valley_image(Y_SEGMENTS + [((20, 200), (230, 150)), ((60, 240), (90, 130))])
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    skel = extract_features(img).creases.skeletons["valley"]
    skel_p = np.pad(skel, 1)
    code_p = M._neighbour_code(skel_p)
    cn_p = np.where(skel_p, M._CN_LUT[code_p], 0)
    rows, cols = np.nonzero((cn_p == 1) | (cn_p == 3))
    first = M._START_LUT[code_p[rows, cols], 0]
    args = (skel_p, code_p, cn_p >= 3, rows, cols, first, 24, 24, 2)
    fused = M._walk(*args)
    monkeypatch.setattr(_crease_kernels, "HAVE_NUMBA", False)
    ref = M._walk(*args)
    assert len(rows) >= 4
    assert np.array_equal(fused[0], ref[0]) and np.array_equal(fused[2], ref[2])
    assert np.array_equal(fused[3], ref[3]) and np.allclose(fused[1], ref[1], equal_nan=True)


def test_a_minutia_set_of_values_that_are_not_numbers_is_refused():
    """NaN or inf positions (a corrupt message, an offset bug) would fail deep in the
    index, or match somewhere: refused where the set is made, naming the field."""
    from terrain_nav_ros.core.features.minutia_set import MinutiaSet

    good = dict(col=[1.0, 2.0], row=[3.0, 4.0], angle=[0.1, 0.2], kind=[ENDING, BIFURCATION],
                quality=[1.0, 1.0])
    MinutiaSet(**good)
    for field, bad in (("col", [np.nan, 2.0]), ("row", [3.0, np.inf]), ("angle", [np.nan, 0]),
                       ("quality", [np.inf, 1.0])):
        with pytest.raises(ValueError, match=f"1 {field} value"):
            MinutiaSet(**{**good, field: bad})
