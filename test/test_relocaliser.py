"""The matcher node's relocalisation helpers (core.matching.relocaliser)."""

import pytest

from terrain_nav_ros.core.matching.relocaliser import SearchPolicy, tile_in_frame
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
from terrain_nav_ros.core.terrain.georef import GeoReference


def test_frames_are_searched_off_the_tiles_and_after_a_run_of_no_fixes():
    policy = SearchPolicy(after_no_fixes=3)
    assert policy.reason_to_search(covered=False).startswith("no landmark tile")
    for _ in range(2):
        assert policy.reason_to_search(covered=True) == ""
        policy.tile_answered(fixed=False)
    policy.tile_answered(fixed=False)
    assert policy.reason_to_search(covered=True) == "3 frames in a row without a fix in the tile"
    policy.tile_answered(fixed=True)
    assert policy.reason_to_search(covered=True) == ""
    with pytest.raises(ValueError):
        SearchPolicy(after_no_fixes=0)


def test_a_tile_moves_into_another_frame_exactly_at_the_matched_pixel():
    tile_origin = EnuOrigin(44.5, 5.5, 300.0)
    frame_origin = EnuOrigin(44.9, 5.1, 250.0)      # ~55 km away
    georef = GeoReference(-20_000.0, 15_000.0, 30.0, 1024, 1024)
    col, row = 700.0, 300.0
    moved = tile_in_frame(georef, col, row, tile_origin, frame_origin)
    assert (moved.gsd, moved.width, moved.height) == (georef.gsd, georef.width, georef.height)
    east, north = georef.pixel_to_enu(col, row)
    lat, lon, h = tile_origin.enu_to_geodetic(east, north, tile_origin.surface_up(east, north))
    want = frame_origin.geodetic_to_enu(lat, lon, h)
    got = moved.pixel_to_enu(col, row)
    assert abs(got[0] - want[0]) < 0.5 and abs(got[1] - want[1]) < 0.5
    # 55 km apart: a shift of tens of kilometres
    assert abs(moved.origin_east - georef.origin_east) > 20_000
    assert tile_in_frame(georef, col, row, tile_origin, tile_origin) is georef
