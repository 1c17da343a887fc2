"""The simulator's cloud sheet: the cover asked for, drift with the wind, cloud seen only
from above it, shadows cast away from the sun, and a clear sky that changes nothing."""

import numpy as np
import pytest

from terrain_nav_ros.core.render.cloud_layer import CloudLayer

GRID = np.mgrid[-3000:3000:40.0, -3000:3000:40.0]   # 150 x 150 points, 6 km square


def _ground(height=0.0):
    east, north = GRID[1], -GRID[0]
    return np.stack([east, north, np.full(east.shape, height)], axis=-1)


@pytest.mark.parametrize("cover", [0.2, 0.6])
def test_the_sheet_covers_what_was_asked(cover):
    layer = CloudLayer(cover=cover, seed=4)
    opacity = layer.opacity_field()
    assert abs((opacity > 0.5).mean() - cover) < 0.05
    assert opacity.min() == 0.0 and opacity.max() == 1.0


def test_the_sheet_drifts_with_the_wind():
    layer = CloudLayer(cover=0.5, wind=(8.0, -3.0), seed=1)
    e, n = GRID[1], -GRID[0]
    later = layer.opacity(e + 8.0 * 30.0, n - 3.0 * 30.0, t=30.0)
    assert np.allclose(later, layer.opacity(e, n, t=0.0), atol=1e-4)


def test_seen_from_above_it_hides_the_ground_and_from_below_only_its_shadow_falls():
    layer = CloudLayer(cover=0.5, base=1500.0, seed=2, brightness=0.9)
    ground = _ground()
    rgb = np.full(ground.shape, 0.2, np.float32)
    sun = (135.0, 90.0)                               # overhead: shadows right below
    above, cloud = layer.apply(rgb, (0.0, 0.0, 3000.0), ground, sun)
    below, no_cloud = layer.apply(rgb, (0.0, 0.0, 1000.0), ground, sun)
    assert 0.3 < (cloud > 0.5).mean() < 0.7
    assert not no_cloud.any()
    thick = cloud > 0.99
    assert np.allclose(above[thick], 0.9, atol=0.01)  # the cloud top, not the ground
    # below the sheet: the ground, dimmed where the sun is blocked, never brightened
    shade = layer.opacity(ground[..., 0], ground[..., 1])
    expected = 0.2 * (1.0 - layer.shadow_depth * shade)
    assert np.allclose(below[..., 0], expected, atol=1e-4)


def test_shadows_are_cast_away_from_the_sun():
    layer = CloudLayer(cover=0.4, base=1000.0, seed=3)
    ground = _ground()
    rgb = np.full(ground.shape, 0.3, np.float32)
    elevation = 45.0
    lit, _ = layer.apply(rgb, (0.0, 0.0, 500.0), ground, (90.0, elevation))   # sun in the east
    # a ground point's shadow comes from the sheet 1000 m east of it (tan 45 deg = 1)
    shade = layer.opacity(ground[..., 0] + 1000.0, ground[..., 1])
    assert np.allclose(lit[..., 0], 0.3 * (1.0 - layer.shadow_depth * shade), atol=1e-3)


def test_a_clear_sky_changes_nothing_and_bad_settings_are_refused():
    ground = _ground()
    rgb = np.random.default_rng(0).random(ground.shape).astype(np.float32)
    out, cloud = CloudLayer(cover=0.0).apply(rgb, (0.0, 0.0, 3000.0), ground, (180.0, 40.0))
    assert np.array_equal(out, rgb) and not cloud.any()
    for bad in ({"cover": 1.0}, {"cover": -0.1}, {"size": 0.0}, {"base": float("nan")}):
        with pytest.raises(ValueError):
            CloudLayer(**bad)
