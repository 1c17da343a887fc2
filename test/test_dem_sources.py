"""Elevation source names."""

import numpy as np
import pytest

from terrain_nav_ros.core.terrain.dem_io import DemError
from terrain_nav_ros.core.terrain.dem_sources import open_dem_source, parse_synthetic


def test_names_resolve_to_dems():
    assert "jacksboro" in open_dem_source("").name
    a = open_dem_source("synthetic:seed=3,size=128,gsd=10")
    b = open_dem_source("synthetic:size=128,gsd=10,seed=3")
    assert a.shape == (128, 128) and a.res == (10.0, 10.0)
    np.testing.assert_array_equal(a.read(), b.read())   # rebuilt identically anywhere
    assert "seed=3" in a.name and str(a.crs) == "EPSG:32613"


def test_bad_names_are_clear_errors():
    with pytest.raises(DemError, match="synthetic:seed=N"):
        parse_synthetic("synthetic:colour=red")
    with pytest.raises(DemError, match="no such DEM file"):
        open_dem_source("/nonexistent/dem.tif")
