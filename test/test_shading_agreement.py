"""An image's agreement with its DEM's shading (core.features.hillshade.shading_agreement)."""

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.features.hillshade import (
    hillshade,
    registration_offset,
    shading_agreement,
)
from terrain_nav_ros.core.terrain.synthetic_terrain import synthetic_dem

GSD = 30.0


@pytest.fixture(scope="module")
def terrain():
    return synthetic_dem(200, gsd=GSD, seed=5).astype(np.float32)


def _photo(z, azimuth, elevation=40.0, seed=0):
    """The terrain shaded from ``azimuth`` under fields of another albedo, with noise."""
    rng = np.random.default_rng(seed)
    fields = cv2.resize(rng.uniform(0.6, 1.0, (8, 8)).astype(np.float32), z.shape[::-1],
                        interpolation=cv2.INTER_NEAREST)
    shade = hillshade(z, azimuth, elevation, gsd=GSD, ambient=0.2)
    return fields * shade * 200.0 + rng.normal(0.0, 3.0, z.shape).astype(np.float32)


def _off(a, b):
    return abs((a - b + 180.0) % 360.0 - 180.0)


@pytest.mark.parametrize("azimuth", [40.0, 160.0, 290.0])
def test_the_azimuth_the_shading_follows_is_found(terrain, azimuth):
    found = shading_agreement(_photo(terrain, azimuth), terrain, GSD, (azimuth, 40.0))
    assert _off(found.best_azimuth, azimuth) <= 5.0
    assert found.r_best > 0.3 and found.r_at_sun > 0.95 * found.r_best
    assert found.warning((azimuth, 40.0)) is None
    assert np.hypot(found.offset_east, found.offset_north) < 0.6 * GSD
    assert found.registration_warning() is None


def test_a_stated_sun_far_from_the_image_s_is_doubtful(terrain):
    photo = _photo(terrain, 160.0)
    found = shading_agreement(photo, terrain, GSD, (250.0, 40.0))
    assert _off(found.best_azimuth, 160.0) <= 5.0 and found.r_at_sun < 0.8 * found.r_best
    assert "azimuth 16" in found.warning((250.0, 40.0))
    # 20 deg off is within what the check lets pass
    assert shading_agreement(photo, terrain, GSD, (180.0, 40.0)).warning((180.0, 40.0)) is None


def test_an_image_without_its_terrain_s_shading_is_said_to_show_little(terrain):
    other = synthetic_dem(200, gsd=GSD, seed=6).astype(np.float32)   # another place
    found = shading_agreement(_photo(other, 160.0), terrain, GSD, (160.0, 40.0))
    assert found.r_best < 0.1
    assert "little of its terrain's shading" in found.warning((160.0, 40.0))


def test_a_grid_finer_than_the_dem_is_compared_at_the_dem_s_cell(terrain):
    photo = _photo(terrain, 160.0)
    fine = [cv2.resize(x, (600, 600), interpolation=cv2.INTER_CUBIC) for x in (photo, terrain)]
    fine[0] += np.random.default_rng(1).normal(0.0, 20.0, fine[0].shape).astype(np.float32)
    found = shading_agreement(fine[0], fine[1], GSD / 3, (160.0, 40.0), cell=3.0)
    assert _off(found.best_azimuth, 160.0) <= 5.0 and found.r_best > 0.3
    assert found.pixels == pytest.approx(200 * 200, rel=0.05)


def test_no_data_is_not_compared_and_too_little_is_not_judged(terrain):
    photo = _photo(terrain, 160.0)
    valid = np.ones(photo.shape, bool)
    valid[:, :100] = False
    photo[:, :100] = 0.0   # fill, not ground
    found = shading_agreement(photo, terrain, GSD, (160.0, 40.0), valid_mask=valid)
    assert _off(found.best_azimuth, 160.0) <= 8.0 and found.pixels < 100 * 200
    valid[:] = False
    valid[:5, :5] = True
    tiny = shading_agreement(photo, terrain, GSD, (160.0, 40.0), valid_mask=valid)
    assert np.isnan(tiny.r_best) and tiny.warning((160.0, 40.0)) is None
    with pytest.raises(ValueError, match="one shape"):
        shading_agreement(photo, terrain[:10], GSD)


def _shifted(image, east, north):
    """``image`` with its content moved ``east`` and ``north`` cells (north-up rows)."""
    m = np.float32([[1, 0, east], [0, 1, -north]])
    return cv2.warpAffine(image, m, image.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


@pytest.mark.parametrize("east, north", [(2.5, -1.0), (-1.0, 2.2), (0.4, 0.3)])
def test_an_image_off_its_dem_is_placed_and_named_misregistered(terrain, east, north):
    """A pair misregistered (the image's terrain ``east`` and ``north`` cells from the
    DEM's, as Costa Rica's ASTER DEM is by ~2) is placed to ~half a cell under the fields'
    edges, and named misregistered from 1.5 cells on: a fix in the DEM's frame carries the
    offset."""
    photo = _shifted(_photo(terrain, 160.0), east, north)
    found = shading_agreement(photo, terrain, GSD, (160.0, 40.0))
    assert found.offset_east == pytest.approx(east * GSD, abs=0.7 * GSD)
    assert found.offset_north == pytest.approx(north * GSD, abs=0.7 * GSD)
    warning = found.registration_warning()
    if np.hypot(east, north) > 2:
        assert "misregistered" in warning and f"{found.offset_east:+.0f} m east" in warning
    else:
        assert warning is None


def test_an_offset_beyond_the_search_or_on_another_place_s_dem_is_not_named(terrain):
    photo = _photo(terrain, 160.0)
    east, north, _ = registration_offset(_shifted(photo, 9.0, 0.0) - photo.mean(),
                                         hillshade(terrain, 160.0, 40.0, gsd=GSD) - 0.5)
    assert np.isnan(east) and np.isnan(north)
    other = synthetic_dem(200, gsd=GSD, seed=6).astype(np.float32)
    assert shading_agreement(_photo(other, 160.0), terrain, GSD,
                             (160.0, 40.0)).registration_warning() is None
