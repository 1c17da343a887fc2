"""Where and when the metamap cuts a new tile."""

import numpy as np
import pytest

from terrain_nav_ros.core.terrain.tile_policy import TilePolicy


def test_first_update_cuts_a_tile_covering_now_and_ahead():
    policy = TilePolicy(min_size=64, max_size=4096, footprint_radius=500, sigma_scale=3,
                        lookahead=10)
    tile = policy.update((0, 0), (30, 0), np.diag([400.0, 100.0]), gsd=5.0)
    west, east, south, north = tile.extent
    need = 500 + 3 * 20
    assert west <= -need and east >= 300 + need and south <= -need and north >= need


def test_no_new_tile_until_the_aircraft_nears_the_edge():
    policy = TilePolicy(min_size=512, max_size=512, footprint_radius=300, lookahead=5)
    first = policy.update((0, 0), (30, 0), np.eye(2), gsd=5.0)  # 2560 m square tile
    assert policy.update((100, 0), (30, 0), np.eye(2), gsd=5.0) is None
    moved = policy.update((1200, 0), (30, 0), np.eye(2), gsd=5.0)  # ahead: 1350 + 300 m
    assert moved is not None and moved.centre[0] > first.centre[0]


def test_growing_uncertainty_grows_the_tile_up_to_the_maximum():
    policy = TilePolicy(min_size=64, max_size=1024, footprint_radius=200, lookahead=0)
    small = policy.update((0, 0), (0, 0), np.eye(2), gsd=5.0)
    big = policy.update((0, 0), (0, 0), np.eye(2) * 1000.0**2, gsd=5.0)
    assert big.width > small.width and big.width == 1024


def test_invalid_settings_are_rejected():
    with pytest.raises(ValueError):
        TilePolicy(min_size=100, max_size=50)
    with pytest.raises(ValueError):
        TilePolicy(footprint_radius=-1)
