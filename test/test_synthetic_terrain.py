"""Synthetic terrain: deterministic, drains everywhere, and has valleys to find."""

import numpy as np

from terrain_nav_ros.core.features.minutiae import extract_minutiae
from terrain_nav_ros.core.terrain.synthetic_terrain import (
    d8_receivers,
    fill_depressions,
    synthetic_dem,
    upstream_area,
)


def test_upstream_area_on_a_tilted_plane():
    z = np.add.outer(np.arange(5.0)[::-1], np.zeros(4))  # slopes down to the last row
    area = upstream_area(z, d8_receivers(z))
    # Each column drains straight south: the bottom row collects its whole column.
    np.testing.assert_array_equal(area[-1], [5, 5, 5, 5])
    np.testing.assert_array_equal(area[0], [1, 1, 1, 1])


def test_depressions_are_filled_to_their_spill_level():
    z = np.full((5, 5), 10.0)
    z[2, 2] = 1.0
    z[0, 2] = 5.0  # the outlet
    filled = fill_depressions(z)
    assert filled[2, 2] == 10.0 and filled[0, 2] == 5.0


def test_same_seed_same_terrain_with_drainage_minutiae():
    a = synthetic_dem(256, 5.0, seed=3)
    np.testing.assert_array_equal(a, synthetic_dem(256, 5.0, seed=3))
    assert not np.array_equal(a, synthetic_dem(256, 5.0, seed=4))
    assert len(extract_minutiae(a, source="dem")) >= 10
