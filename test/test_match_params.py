"""MatchParams validates itself (issue 22): NaN, out-of-range values, unknown choices and
impossible combinations are refused on construction, naming the setting; the matcher node
declares the same ranges."""

import dataclasses
import math
import re

import pytest

from terrain_nav_ros.core.matching.matcher import Matcher
from terrain_nav_ros.core.matching.params import MatchParams


def test_defaults_and_the_studies_settings_are_valid():
    MatchParams()
    MatchParams(threshold=-1e9)  # a study collecting every score
    MatchParams(rescue_below=-math.inf, crease_search_below=0)  # no wider try, no search
    MatchParams(rescue_below=math.inf)  # a benchmark forcing the wider try
    Matcher(MatchParams(), threshold=4.5, max_rotation=math.radians(20))


def test_every_numeric_setting_has_a_range():
    """A new setting without a range would reach the node unchecked."""
    numeric = {f.name for f in dataclasses.fields(MatchParams)
               if isinstance(f.default, int | float) and not isinstance(f.default, bool)}
    assert numeric == set(MatchParams.RANGES)
    assert set(MatchParams.FIX_RANGES) == numeric and MatchParams.FIX_RANGES["threshold"] == (
        0.0, None)


@pytest.mark.parametrize("name,value,says", [
    ("threshold", math.nan, "finite"),
    ("rescue_below", math.nan, "finite"),
    ("pos_tol", 0.0, "> 0"),
    ("k_query", 0, ">= 1"),
    ("k_query", 2.5, "an int"),
    ("max_rotation", 4.0, "in [0, 3.14159]"),
    ("min_support_ratio", 1.5, "in [0, 1]"),
    ("search_scale", 0.7, "in [0, 0.5]"),
    ("view_search_background", -1.0, ">= 0"),
    ("crease_search_proposals", 0, ">= 1"),
    ("crease_search_fine_work", -1, ">= 0"),
    ("seed", -1, ">= 0"),
    ("candidates", "kd", "one of ('auto', 'hash', 'roots')"),
    ("descriptor", "sift", "one of ('shape_context', 'mcc', 'both')"),
    ("edge_min", 500.0, "below edge_max"),
    ("crease_rescue_radii", (8.0, 0.0), "positive radii"),
])
def test_bad_settings_are_refused_naming_them(name, value, says):
    with pytest.raises(ValueError, match=rf"MatchParams\.{name} must be {re.escape(says)}"):
        MatchParams(**{name: value})
    with pytest.raises(ValueError, match=rf"MatchParams\.{name}"):
        Matcher(MatchParams(), **{name: value})  # overrides are checked too

