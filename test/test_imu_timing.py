"""IMU stamp screening (issue 22): glitches refused, real time jumps confirmed."""

from __future__ import annotations

import pytest

from terrain_nav_ros.core.estimation.imu_timing import ImuTiming, ImuTimingGuard

PASS, SUSPECT, JUMP = ImuTiming.PASS, ImuTiming.SUSPECT, ImuTiming.JUMP


def _guard():
    g = ImuTimingGuard(max_step=1.0, max_period=0.1, confirm=3)
    for i in range(10):
        assert g.check(100.0 + 0.01 * i) == PASS
    return g


@pytest.mark.parametrize("bad", [95.0, 3700.0, -1e9])
def test_a_single_stamp_far_either_way_is_refused(bad):
    g = _guard()
    assert g.check(bad) == SUSPECT
    assert g.check(100.10) == PASS and g.last == 100.10
    assert (g.refused, g.jumps, g.pending) == (1, 0, [])


def test_a_stream_going_on_from_the_new_time_is_a_jump_with_its_samples():
    g = _guard()
    run = [5.00, 5.01, 5.02]
    verdicts = [g.check(t, ("imu", t)) for t in run]
    assert verdicts == [SUSPECT, SUSPECT, JUMP]
    assert g.take_pending() == [("imu", t) for t in run] and g.pending == []
    assert g.check(5.03) == PASS and (g.refused, g.jumps) == (2, 1)


def test_scattered_bad_stamps_never_confirm_a_jump():
    """Bad stamps that do not follow each other at the IMU period (repeated, too far apart,
    backwards) each start a new suspect run instead of adding up."""
    g = _guard()
    for t in (5.0, 5.0, 5.5, 5.4, 3700.0, 5.45):
        assert g.check(t) == SUSPECT
    assert g.jumps == 0 and g.refused == 6 and len(g.pending) == 1


def test_small_steps_pass_for_the_filter_to_judge():
    """Duplicates and small backward steps are the filter's business (out of order)."""
    g = _guard()
    assert [g.check(t) for t in (100.09, 100.5, 101.4)] == [PASS, PASS, PASS]


def test_bad_settings_raise():
    with pytest.raises(ValueError):
        ImuTimingGuard(max_step=1.0, max_period=0.1, confirm=0)
