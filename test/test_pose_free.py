"""Pose-free projection for a cold start (core.camera.pose_free) and the ladder of scales
its frames are searched at (core.matching.global_search)."""

import math

import numpy as np
import pytest

from terrain_nav_ros.core.camera.ground_projection import (
    CameraIntrinsics,
    footprint_georef,
    ground_to_image,
    image_to_ground,
)
from terrain_nav_ros.core.camera.pose_free import (
    CruiseAttitude,
    levelled,
    pose_free_view,
    scale_range,
)
from terrain_nav_ros.core.estimation.strapdown import quat_from_euler, quat_to_matrix
from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.matching.global_search import rescaled_view, scale_ladder
from terrain_nav_ros.core.terrain.georef import GeoReference

INTR = CameraIntrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)


def test_the_camera_height_is_the_barometers_above_the_areas_median_terrain():
    view, why = pose_free_view(4000.0, 300.0, 900.0, 2100.0, origin_altitude=250.0,
                               altitude_sigma=50.0)
    assert why == "" and view is not None
    np.testing.assert_allclose(view.pose.position, [0.0, 0.0, 3750.0])
    assert view.plane == pytest.approx(650.0)
    assert view.height_above_ground == pytest.approx(3100.0)
    # the terrain's spread widened by twice the barometer's sigma, in the ENU frame
    assert (view.plane_min, view.plane_max) == pytest.approx((-50.0, 1950.0))
    # wings level, heading 0: a nadir view whose image top is the nose (east)
    down = view.pose.rotation @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(down, [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(view.pose.rotation @ np.array([0.0, -1.0, 0.0]), [1.0, 0, 0],
                               atol=1e-12)


def test_a_view_projects_a_ground_point_at_its_scale_for_the_assumed_height():
    """The footprint of the pose-free camera is centred under it, its GSD-for-pixel scale
    that of the assumed height above ground."""
    view, _ = pose_free_view(3000.0, 0.0, 500.0, 1000.0)
    e, n = image_to_ground(np.array([319.5, 419.5]), np.array([239.5, 239.5]), INTR,
                           view.pose, view.plane)
    assert abs(e[0]) < 1e-6 and abs(n[0]) < 1e-6
    assert math.hypot(e[1] - e[0], n[1] - n[0]) == pytest.approx(100.0 * 2500.0 / 500.0)
    g = footprint_georef(INTR, view.pose, view.plane, 30.0, 3 * 2500.0)
    assert g is not None and abs(g.centre[0]) < 60 and abs(g.centre[1]) < 60


def test_roll_and_pitch_tilt_the_view():
    view, _ = pose_free_view(3000.0, 0.0, 500.0, 1000.0, roll=math.radians(5.0))
    u, v = ground_to_image(0.0, 0.0, view.plane, INTR, view.pose)
    # 5 degrees of roll moves the nadir point 500 px x tan(5 deg) across the image
    assert abs(float(u) - 319.5) == pytest.approx(500.0 * math.tan(math.radians(5.0)), rel=1e-6)


@pytest.mark.parametrize("altitude, why", [
    (1150.0, "above the area's high terrain"),     # within 100 m of the high terrain
    (math.nan, "not finite"),
])
def test_a_view_that_cannot_be_made_says_why(altitude, why):
    view, reason = pose_free_view(altitude, 300.0, 600.0, 1100.0)
    assert view is None and why in reason and reason.startswith("cold start")
    view, reason = pose_free_view(3000.0, 700.0, 600.0, 1100.0)
    assert view is None and "not ordered" in reason


def test_the_scale_range_is_true_over_assumed_height_above_ground():
    lo, hi = scale_range(4000.0, 1000.0, 200.0, 2200.0)
    assert (lo, hi) == pytest.approx((1800.0 / 3000.0, 3800.0 / 3000.0))
    with pytest.raises(ValueError):
        scale_range(2000.0, 1000.0, 200.0, 2200.0)


def test_a_ladder_covers_the_range_in_steps_the_search_bridges():
    assert scale_ladder(0.95, 1.05) == [1.0]
    ladder = scale_ladder(0.6, 1.27)
    ratios = np.diff(np.log(ladder))
    np.testing.assert_allclose(ratios, math.log(1.2))
    half = math.sqrt(1.2)
    assert ladder[0] / half <= 0.6 and ladder[-1] * half >= 1.27
    assert len(ladder) == math.ceil(math.log(1.27 / 0.6) / math.log(1.2))
    with pytest.raises(ValueError):
        scale_ladder(1.2, 1.1)


def test_a_rescaled_view_moves_minutiae_exactly_about_the_point_under_the_camera():
    georef = GeoReference.centred(100.0, -50.0, 30.0, 64, 48)
    cols, rows = np.array([3.0, 40.0, 60.5]), np.array([5.0, 20.0, 44.0])
    ms = MinutiaSet(cols, rows, [0.1, 1.0, 2.0], [1, 3, 1], [0.5, 0.6, 0.7], georef=georef)
    creases = np.zeros(georef.shape, bool)
    creases[24, 5:60] = True                       # one east-west crease
    anchor = (130.0, -80.0)
    moved, moved_creases, ridges = rescaled_view(ms, creases, None, 1.5, anchor)
    assert ridges is None
    assert moved.georef.gsd == georef.gsd
    assert (moved.georef.width, moved.georef.height) == (96, 72)
    e0, n0 = georef.pixel_to_enu(cols, rows)
    e1, n1 = moved.georef.pixel_to_enu(moved.col, moved.row)
    np.testing.assert_allclose(e1, anchor[0] + 1.5 * (e0 - anchor[0]), atol=1e-9)
    np.testing.assert_allclose(n1, anchor[1] + 1.5 * (n0 - anchor[1]), atol=1e-9)
    np.testing.assert_array_equal(moved.angle, ms.angle)
    # the crease stays one line, 1.5 times as long, thin
    assert moved_creases.shape == moved.georef.shape
    rows_hit = np.flatnonzero(moved_creases.any(axis=1))
    assert len(rows_hit) <= 2
    assert moved_creases.sum() == pytest.approx(1.5 * creases.sum(), rel=0.1)
    # the one rung of a frame whose scale is known well enough: the set as it is
    same = rescaled_view(ms, creases, None, 1.0, anchor)
    assert same[0] is ms and same[1] is creases


def test_straight_flight_is_levelled_from_the_accelerometers_and_a_turn_is_refused():
    attitude = CruiseAttitude(level_sigma=math.radians(3.0), max_turn_rate=math.radians(3.0),
                              levelled_sigma=math.radians(1.0))
    assert attitude.at(10.0) == ((0.0, 0.0, math.radians(3.0)), "")   # no IMU yet
    # a steady 3 degree climb, nose up (pitch -3 deg in FLU / ENU), right wing 2 deg down
    q = quat_from_euler(math.radians(2.0), math.radians(-3.0), 0.7)
    gravity_reaction = quat_to_matrix(q).T @ np.array([0.0, 0.0, 9.81])
    rng = np.random.default_rng(1)
    for k in range(200):                           # straight flight: noise only
        attitude.add(k * 0.01, rng.normal(0.0, 0.002, 3),
                     gravity_reaction + rng.normal(0.0, 0.05, 3))
    (roll, pitch, sigma), why = attitude.at(1.99)
    assert why == "" and sigma == pytest.approx(math.radians(1.0))
    assert math.degrees(roll) == pytest.approx(2.0, abs=0.1)
    assert math.degrees(pitch) == pytest.approx(-3.0, abs=0.1)
    assert levelled(gravity_reaction) == pytest.approx((math.radians(2.0), math.radians(-3.0)))
    for k in range(200, 400):                      # a 6 deg/s turn
        attitude.add(k * 0.01, [0.0, 0.0, math.radians(6.0)], [0.0, 0.0, 9.81])
    got, why = attitude.at(3.99)
    assert got is None and "turning" in why


def test_an_imu_orientation_gives_roll_and_pitch():
    attitude = CruiseAttitude(floor_sigma=math.radians(0.5))
    q = quat_from_euler(math.radians(4.0), math.radians(-2.0), 1.0)
    attitude.add(5.0, [0.0, 0.0, 0.0], None, q, math.radians(0.2) ** 2)
    (roll, pitch, sigma), why = attitude.at(5.05)
    assert why == ""
    assert (math.degrees(roll), math.degrees(pitch)) == pytest.approx((4.0, -2.0))
    assert sigma == pytest.approx(math.radians(0.5))          # the floor
    # an orientation too old for the frame, no accelerometers: wings level
    assert attitude.at(9.0)[0][:2] == (0.0, 0.0)
