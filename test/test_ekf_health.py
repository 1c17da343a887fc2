"""The ekf node's health report and refusal logs without ROS (core.estimation.ekf_health)."""

import math
from collections import Counter

from terrain_nav_ros.core.estimation.ekf import EkfDiagnostics, UpdateRecord
from terrain_nav_ros.core.estimation.ekf_health import (
    ERROR,
    OK,
    WARN,
    HealthLimits,
    NewRecords,
    RefusalLog,
    SourceUse,
    filter_health,
    filter_values,
    gated_records,
    source_report,
)
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin

LIMITS = HealthLimits(fix_warn=30.0, fix_error=120.0, sigma_warn=50.0, sigma_error=200.0,
                      imu_timeout=1.0)


def _diagnostics(**kwargs):
    d = EkfDiagnostics(initialized=True, stamp=100.0, position_sigma=10.0,
                       covariance_trace=1.0)
    d.last_accepted["fix"] = 95.0
    for key, value in kwargs.items():
        setattr(d, key, value)
    return d


def test_a_healthy_filter_is_ok():
    health = filter_health(_diagnostics(), 0.1, "", LIMITS)
    assert (health.level, health.message) == (OK, "ok")


def test_each_problem_raises_the_level_and_is_named():
    cases = [
        (dict(), 5.0, ERROR, "no IMU for 5.0 s"),
        (dict(initialized=False), 0.0, WARN, "not initialised: waiting for gnss"),
        (dict(last_accepted={}), 0.0, WARN, "no fix accepted yet"),
        (dict(last_accepted={"fix": 60.0}), 0.0, WARN, "no accepted fix for 40 s"),
        (dict(last_accepted={"gnss": -30.0}), 0.0, ERROR, "no accepted fix for 130 s"),
        (dict(position_sigma=60.0), 0.0, WARN, "position sigma 60 m"),
        (dict(position_sigma=250.0), 0.0, ERROR, "position sigma 250 m"),
        (dict(heights_left_out_in_a_row=5), 0.0, WARN, "check the CameraInfo's focal length"),
    ]
    for changes, since_imu, level, text in cases:
        health = filter_health(_diagnostics(**changes), since_imu, "gnss", LIMITS)
        assert health.level == level and text in health.message, (changes, health)


def test_a_few_fixes_fused_without_their_height_are_no_warning():
    assert filter_health(_diagnostics(heights_left_out_in_a_row=4), 0.0, "", LIMITS).level == OK


def test_the_latest_of_fix_and_gnss_counts_as_the_last_fix():
    d = _diagnostics(last_accepted={"fix": 0.0, "gnss": 90.0})
    assert filter_health(d, 0.0, "", LIMITS).level == OK


def test_refused_stamps_and_gated_updates_warn():
    health = filter_health(_diagnostics(), 0.0, "", LIMITS, refused_stamps=2, gated=3)
    assert health.level == WARN
    assert health.problems == ["2 IMU stamp(s) far from the expected period refused",
                               "3 measurement(s) rejected by the gate"]


def test_failed_callbacks_are_an_error_until_the_next_report():
    health = filter_health(_diagnostics(), 0.0, "", LIMITS, failed=2)
    assert health.level == ERROR
    assert health.problems == ["2 message(s) failed in a callback: see the log"]


def test_held_relocalisations_warn_and_the_report_says_what_was_found():
    import numpy as np

    from terrain_nav_ros.core.estimation.relocalisation import Found

    health = filter_health(_diagnostics(relocalisation_candidates=2), 0.0, "", LIMITS)
    assert health.level == WARN
    assert health.problems == ["searching: 2 relocalisation(s) held, none agreed yet"]
    d = _diagnostics(relocalisation_resets=1, found=Found(90.0, np.array([-3000.0, 4000.0, 12.0])))
    values = filter_values(d, "fix", 0, 0.01, 0, None, None, Counter())
    assert values["relocalisation_resets"] == 1 and values["relocalisation_candidates"] == 0
    assert values["found"] == ("position reset onto agreeing relocalisations at 90.000 s: "
                               "jumped 5000 m horizontally, +12 m vertically")
    assert filter_values(_diagnostics(), "fix", 0, 0.01, 0, None, None,
                         Counter())["found"] == "never"


def test_gnss_gate_rejections_count_only_when_gnss_is_fused():
    records = [UpdateRecord(1.0, "gnss", 3, 30.0, 11.3, False),
               UpdateRecord(2.0, "fix", 2, 30.0, 9.2, False),
               UpdateRecord(3.0, "fix", 2, 1.0, 9.2, True)]
    assert [r.stamp for r in gated_records(records, fuse_gnss=True)] == [1.0, 2.0]
    assert [r.stamp for r in gated_records(records, fuse_gnss=False)] == [2.0]


def test_filter_values_join_the_cores_and_the_nodes_refusals():
    d = _diagnostics()
    d.input_rejections["imu:non_finite_value"] = 2
    values = filter_values(d, "gnss", 1000, 0.01, 3, None, EnuOrigin(36.5, -84.3, 300.0),
                           Counter({"baro:bad_pressure": 1, "imu:non_finite_value": 1}))
    assert values["rejected_input/imu:non_finite_value"] == 3
    assert values["rejected_input/baro:bad_pressure"] == 1
    assert values["imu_rate_hz"] == 100.0 and values["time_since_last_fix"] == 5.0
    assert math.isnan(values["baro_offset_m"])
    assert values["enu_origin"] == "36.5000000,-84.3000000,300.00"
    assert filter_values(d, "gnss", 0, 0.01, 0, 1.5, None, Counter())["enu_origin"] == "unknown"


def test_source_reports_list_the_nis_since_the_last_report():
    d = _diagnostics()
    old = UpdateRecord(1.0, "fix", 2, 1.5, 9.2, True)
    new = [UpdateRecord(2.0, "fix", 2, 20.0, 9.2, False), UpdateRecord(2.5, "baro", 1, 0.5,
                                                                       6.6, True)]
    d.records.extend([old, *new])
    d.accepted["fix"], d.rejected["fix"] = 1, 1
    message, values = source_report(d, "fix", new)
    assert message == "1 update(s) since the last report"
    assert values["nis"] == "20!" and values["last_nis"] == 20.0 and values["dof"] == 2
    assert values["mean_nis"] == (1.5 + 20.0) / 2
    assert values["last_accepted_stamp"] == "95.000"
    message, values = source_report(d, "gnss", new)
    assert message.startswith("0 ") and math.isnan(values["last_nis"])


def test_new_records_are_those_since_the_previous_call():
    new_records = NewRecords()
    a, b, c = (UpdateRecord(float(t), "fix", 2, 1.0, 9.2, True) for t in range(3))
    assert new_records([a, b]) == [a, b]
    assert new_records([a, b]) == []
    assert new_records([b, c]) == [c]       # the oldest dropped from the bounded history


def test_refusal_logs_are_throttled_per_key_and_count_what_they_skipped():
    log = RefusalLog(period=5.0)
    assert log.text("gnss:x", "gnss refused: x", 0.0) == "gnss refused: x"
    assert log.text("gnss:x", "gnss refused: x", 1.0) is None
    assert log.text("gnss:x", "gnss refused: x", 2.0) is None
    assert log.text("baro:y", "baro refused: y", 2.0) == "baro refused: y"
    assert log.text("gnss:x", "gnss refused: x", 5.5) == \
        "gnss refused: x (2 more since the last report)"


def test_a_baro_that_arrives_and_is_never_used_warns():
    """A baro in kPa, on another clock or never given its offset is refused whole: the
    height then drifts, so the filter's health says so, with the last reason."""
    use = SourceUse()
    assert use.report() == ""                      # no baro: nothing to say
    for _ in range(10):
        use.arrived()
        use.refused("bad pressure: 96.3 Pa")
    assert use.report() == "none of 10 since the last report (bad pressure: 96.3 Pa)"
    use.arrived()
    use.used()
    use.arrived()
    use.refused("gated")
    assert use.report() == ""                      # one of two used: it is fused
    health = filter_health(_diagnostics(), 0.0, "", LIMITS,
                           baro_unused="none of 10 since the last report (x)")
    assert health.level == WARN
    assert health.problems == ["baro unused: none of 10 since the last report (x)"]
