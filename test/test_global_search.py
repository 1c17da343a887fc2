"""Relocalisation over the tiles of a mission area (core.matching.global_search)."""

import math

import numpy as np
import pytest
from synthetic_minutiae import crop_set, rigid_transform, transform_set

from terrain_nav_ros.core.matching.global_search import SearchTile, relocalise
from terrain_nav_ros.core.matching.matcher import Matcher
from terrain_nav_ros.core.terrain.georef import GeoReference

TILE, STRIDE = 320, 192
GSD = 30.0


def _tiles(matcher, ms, origin=(0.0, 0.0)):
    """The region cut into overlapping tiles, each placed in ENU (origin = the region's NW
    corner)."""
    out = []
    for row0 in (0, STRIDE):
        for col0 in (0, STRIDE):
            tile = crop_set(ms, col0, row0, TILE, TILE)
            georef = GeoReference(origin[0] + col0 * GSD, origin[1] - row0 * GSD, GSD, TILE,
                                  TILE)
            out.append(SearchTile(matcher.index(tile).prepare_as_reference(), georef,
                                  f"{row0}_{col0}"))
    return out


def _view(ms, target, degrees, seed):
    """A 128 px view of ``ms`` centred on region pixel ``target``, turned by ``degrees``."""
    to_region = rigid_transform(math.radians(degrees), *(np.asarray(target) - 63.5),
                                centre=(63.5, 63.5))
    inv = np.linalg.inv(np.vstack([to_region, [0, 0, 1]]))[:2]
    return transform_set(ms, inv, (128, 128), rng=seed)[0]


@pytest.fixture(scope="module")
def matcher():
    return Matcher(threshold=5.0)


@pytest.fixture(scope="module")
def tiles(matcher, region):
    return _tiles(matcher, region[0])


def test_a_view_is_relocalised_at_its_place_in_the_area(matcher, tiles, region):
    target = (380.0, 150.0)     # only in the tiles at column 192
    found = relocalise(matcher, matcher.index(_view(region[0], target, 140.0, seed=3)), tiles)
    assert found.matched, (found.reason, found.candidates)
    assert found.searched == len(tiles)
    assert found.penalty == pytest.approx(math.log10(len(tiles)))
    assert found.score == pytest.approx(found.result.score - found.penalty)
    east, north = found.position
    assert math.hypot(east - (target[0] + 0.5) * GSD, north + (target[1] + 0.5) * GSD) < 1.5 * GSD
    assert found.tile.key.endswith("_192")


def test_a_view_of_other_terrain_is_not_relocalised(matcher, tiles, other_region):
    found = relocalise(matcher, matcher.index(_view(other_region[0], (250.0, 250.0), 30.0, 4)),
                       tiles)
    assert not found.matched
    assert "no significant match" in found.reason


def test_the_area_penalty_can_refuse_what_one_tile_accepts(region):
    # a threshold just below the best one-tile score: the view is accepted in its tile's
    # search, and refused when it had to be found among four tiles (penalty log10(4) = 0.6)
    ms = region[0]
    view = _view(ms, (200.0, 200.0), 10.0, seed=5)
    loose = Matcher(threshold=5.0)
    best = max(loose.localise(loose.index(view), t.index).score for t in _tiles(loose, ms))
    strict = Matcher(threshold=best - 0.3)
    many = _tiles(strict, ms)
    assert any(strict.localise(strict.index(view), t.index).matched for t in many)
    found = relocalise(strict, strict.index(view), many)
    assert not found.matched and "no significant match" in found.reason


def test_the_same_terrain_at_two_places_is_ambiguous(matcher, tiles, region):
    twin = _tiles(matcher, region[0], origin=(50_000.0, 0.0))
    found = relocalise(matcher, matcher.index(_view(region[0], (250.0, 250.0), 60.0, 6)),
                       tiles + twin)
    assert not found.matched
    assert found.reason.startswith("ambiguous")
    assert found.runner_up > matcher.params.threshold


def test_a_certain_match_near_the_estimate_ends_the_search(matcher, tiles, region):
    target = (100.0, 100.0)     # in tile 0_0 only
    near = ((target[0] + 0.5) * GSD, -(target[1] + 0.5) * GSD)
    found = relocalise(matcher, matcher.index(_view(region[0], target, 0.0, seed=7)), tiles,
                       near=near, certain_score=6.0)
    assert found.matched and found.searched == 1 and found.tile.key == "0_0"


def test_no_tiles_is_an_explicit_no_relocalisation(matcher, region):
    found = relocalise(matcher, matcher.index(region[0]), [])
    assert not found.matched and found.reason == "no tiles to search"


def test_a_camera_set_without_a_raster_needs_its_view_centre(matcher, tiles, region):
    view = _view(region[0], (380.0, 150.0), 140.0, seed=3)
    bare = matcher.index(type(view)(view.col, view.row, view.angle, view.kind, view.quality))
    with pytest.raises(ValueError, match="view_centre"):
        relocalise(matcher, bare, tiles)
    found = relocalise(matcher, bare, tiles, view_centre=(63.5, 63.5))
    assert found.matched and found.tile.key.endswith("_192")
