"""The matcher node's decisions between camera sets and fixes without ROS
(core.matching.fix_stream)."""

import math

import numpy as np
from scipy.spatial.transform import Rotation

from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.matching.fix_stream import (
    ERROR,
    OK,
    UNOBSERVED_TILT_VAR,
    WARN,
    AnswerTally,
    FixVelocity,
    FlipCheck,
    LandmarkSets,
    add_prior_tilt,
    fix_attitude,
)
from terrain_nav_ros.core.matching.pva_fix import (
    STATUS_NO_FIX,
    STATUS_POSITION,
    STATUS_POSITION_ATTITUDE,
    PvaFixEstimate,
)
from terrain_nav_ros.core.terrain.georef import GeoReference


def _landmark(west: float, south: float, size: float = 100.0):
    georef = GeoReference(west, south + size, 1.0, int(size), int(size))
    return MinutiaSet(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, np.uint8),
                      np.zeros(0, np.float32), georef)


def test_the_newest_landmark_set_holding_the_point_is_chosen():
    sets = LandmarkSets(max_sets=2)
    assert sets.holding(0.0, 0.0) is None and not sets.any_with_minutiae
    first, second, third = _landmark(0, 0), _landmark(50, 0), _landmark(500, 500)
    sets.add(first, None, (1, 2, 3))
    sets.add(second, "index", (4, 5, 6))
    assert sets.holding(60.0, 50.0)[0] is second          # both hold it: the newest
    assert sets.holding(10.0, 50.0)[0] is first
    assert sets.any_with_minutiae
    sets.add(third, None, (7, 8, 9))                      # the oldest is dropped
    assert len(sets) == 2 and sets.holding(10.0, 50.0) is None
    assert sets.holding(550.0, 550.0)[2] == (7, 8, 9)


def _fix(status=STATUS_POSITION, yaw_variance=0.01, yaw_correction=0.1):
    cov = np.diag([4.0, 4.0, 9.0, -1.0, -1.0, -1.0])
    return PvaFixEstimate(status, "", np.array([1.0, 2.0, 300.0]), np.eye(3), cov,
                          yaw_correction=yaw_correction, yaw_variance=yaw_variance)


def test_the_prior_tilt_widens_a_valid_fix_only():
    fix = _fix()
    fix.projection_height = 500.0
    add_prior_tilt(fix, 500.0, math.radians(0.2))
    expected = 4.0 + (500.0 * math.radians(0.2)) ** 2
    np.testing.assert_allclose(np.diag(fix.covariance)[:3], [expected, expected, 9.0])
    assert fix.projection_height == 0.0     # the filter must not model it a second time
    none = PvaFixEstimate(STATUS_NO_FIX, "no match")
    add_prior_tilt(none, 500.0, 1.0)                      # nothing to widen, no error
    assert np.isnan(none.covariance).all()


def test_a_measured_heading_turns_the_prior_and_makes_an_attitude_fix():
    fix = _fix(yaw_correction=0.1)
    mount = Rotation.from_euler("x", 0.05).as_matrix()
    r = fix_attitude(fix, mount, use_heading=True, heading_floor=math.radians(0.5))
    np.testing.assert_allclose(r, Rotation.from_rotvec([0, 0, 0.1]).as_matrix() @ mount.T)
    assert fix.status == STATUS_POSITION_ATTITUDE
    np.testing.assert_allclose(np.diag(fix.covariance)[3:], [
        UNOBSERVED_TILT_VAR, UNOBSERVED_TILT_VAR, 0.01 + math.radians(0.5) ** 2])
    assert not fix.covariance[:3, 3:].any() and not fix.covariance[3:, :3].any()


def test_without_a_heading_the_fix_keeps_the_prior_attitude_and_its_status():
    """No heading asked for, none measured, one already given, or a track mosaic's."""
    mosaic = _fix(yaw_correction=0.1)
    mosaic.mosaic_lag = 12.0   # a track mosaic's rotation is the estimate's past headings
    for fix, use_heading in ((_fix(), False), (_fix(yaw_variance=-1.0), True),
                             (_fix(status=STATUS_POSITION_ATTITUDE), True), (mosaic, True)):
        before = fix.covariance.copy()
        status = fix.status
        r = fix_attitude(fix, np.eye(3), use_heading, 0.0)
        np.testing.assert_array_equal(r, fix.rotation)
        assert fix.status == status
        np.testing.assert_array_equal(fix.covariance, before)


def test_velocity_comes_from_fixes_close_enough_in_time():
    velocity = FixVelocity(max_gap=5.0)
    cov = np.eye(6)
    assert velocity.update(10.0, [0.0, 0.0, 0.0], cov) is None
    v, v_cov = velocity.update(12.0, [20.0, 10.0, 0.0], cov)
    np.testing.assert_allclose(v, [10.0, 5.0, 0.0])
    np.testing.assert_allclose(v_cov, 2.0 * np.eye(3) / 4.0)
    assert velocity.update(20.0, [0.0, 0.0, 0.0], cov) is None      # 8 s: too far apart
    assert velocity.update(20.0, [0.0, 0.0, 0.0], cov) is None      # same stamp: none


def test_a_track_mosaic_s_fix_neither_gives_nor_starts_a_velocity():
    velocity = FixVelocity(max_gap=5.0)
    cov = np.eye(6)
    assert velocity.update(10.0, [0.0, 0.0, 0.0], cov) is None
    assert velocity.update(11.0, [30.0, 0.0, 0.0], cov, mosaic=True) is None
    assert velocity.update(12.0, [60.0, 0.0, 0.0], cov, mosaic=True) is None
    # the frame after mosaics pairs with no mosaic: it waits for the next frame's fix
    assert velocity.update(13.0, [90.0, 0.0, 0.0], cov) is None
    v, _ = velocity.update(14.0, [120.0, 0.0, 0.0], cov)
    np.testing.assert_allclose(v, [30.0, 0.0, 0.0])


def test_a_relocalisation_gives_no_velocity_but_the_next_fix_pairs_with_it():
    velocity = FixVelocity(max_gap=5.0)
    cov = np.eye(6)
    assert velocity.update(10.0, [0.0, 0.0, 0.0], cov) is None
    assert velocity.update(11.0, [900.0, 0.0, 0.0], cov, relocalisation=True) is None
    v, _ = velocity.update(12.0, [930.0, 0.0, 0.0], cov)
    np.testing.assert_allclose(v, [30.0, 0.0, 0.0])


def test_the_tally_reports_counts_times_and_problems():
    tally = AnswerTally()
    tally.no_fix("no terrain match: score 1.25 below threshold 3.00")
    tally.no_fix("no terrain match: score 2.5 below threshold 3.00")
    tally.fix(7.5, 12, now=100.0)
    tally.answered(20.0)
    tally.answered(40.0)
    level, message, values = tally.report(101.0, 0.5, 5.0, True, 0, 0, 2)
    assert level == OK and message == "2 camera set(s) answered since the last report"
    assert values["fixes"] == 1 and values["no_fixes"] == 2
    assert values["no_fix: no terrain match: score # below threshold #"] == 2
    assert values["answer_ms_median"] == 30.0 and values["answer_ms_max"] == 40.0
    assert values["time_since_last_fix"] == 1.0 and values["last_fix_pairings"] == 12
    # the times restart; a stalled camera and no landmark warn, a failure is an error
    level, message, values = tally.report(110.0, 9.0, 5.0, False, 3, 1, 0)
    assert level == ERROR and values["camera_sets_since_last_report"] == 0
    assert message == ("1 message(s) failed in a callback: see the log; no camera minutiae "
                       "for 9 s; no landmark set with minutiae")
    assert math.isnan(values["answer_ms_median"]) and values["failures"] == 3
    assert tally.report(110.0, 9.0, 5.0, True, 3, 0, 1)[0] == WARN


def test_a_run_below_the_threshold_tries_the_flips_every_so_many_frames():
    check = FlipCheck(every=3)
    tries = [check.note(False, True) for _ in range(7)]
    assert tries == [False, False, True, False, False, True, False]
    # a frame with too little drainage says nothing of a flip and ends the run
    assert not check.note(False, False) and check.run == 0
    check.found = "left to right"
    assert not check.note(True, False) and check.found == "" and check.run == 0
    assert not any(FlipCheck(0).note(False, True) for _ in range(30))


def test_a_track_mosaic_is_never_tried_mirrored_and_leaves_the_run_as_it_was():
    check = FlipCheck(every=2)
    assert not check.note(False, True)
    # mosaics below the threshold: no line mirrors their frames back, so neither a try nor
    # a count (nor the end of the run: they say nothing of a flip)
    assert not any(check.note(False, True, mosaic=True) for _ in range(5))
    assert check.run == 1 and check.note(False, True)
    check.found = "top to bottom"
    assert not check.note(True, False, mosaic=True) and check.run == 0 and check.found == ""


def test_the_flips_mirror_across_the_image_s_middle_column_and_row_on_the_ground():
    """A camera heading east (image top = nose = east, right = south), 1000 m above the
    plane, the aircraft 3 deg nose down: the image's columns run east-west on the ground,
    its rows north-south, both through the centre's ground point, 52 m behind the nadir
    (the belly faces back)."""
    # optical x (right) -> south, y (down the image, to the tail) -> west, z -> down
    level = np.column_stack([(0, -1, 0), (-1, 0, 0), (0, 0, -1)]).astype(float)
    nose_down = Rotation.from_euler("y", 3.0, degrees=True).as_matrix()   # about north
    lines = FlipCheck.mirrors((500.0, 200.0, 1100.0), nose_down @ level, 100.0)
    for flip, east_west in (("left to right", True), ("top to bottom", False)):
        centre, axis = lines[flip]
        np.testing.assert_allclose(centre, (500.0 - 1000.0 * math.tan(math.radians(3.0)),
                                            200.0), atol=1e-6)
        trig = abs(math.cos(axis)) if east_west else abs(math.sin(axis))
        assert math.isclose(trig, 1.0, abs_tol=2e-3), (flip, axis)
