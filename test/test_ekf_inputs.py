"""The ekf node's input decisions without ROS (core.estimation.ekf_inputs)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from terrain_nav_ros.core.camera.camera_mount import mount_rotation
from terrain_nav_ros.core.estimation.ekf_inputs import (
    COVARIANCE_TYPE_DIAGONAL_KNOWN,
    COVARIANCE_TYPE_UNKNOWN,
    BaroOffset,
    FixFrame,
    OriginHandshake,
    baro_refusal,
    fix_covariance,
    gnss_covariance,
    gnss_refusal,
)
from terrain_nav_ros.core.estimation.strapdown import quat_from_euler, quat_to_matrix
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin


def _frame(pose_frame="camera_optical", lever_arm=(0.0, 0.0, 0.0)):
    return FixFrame(pose_frame, Rotation.from_matrix(mount_rotation(0.0, 0.0, 0.0)).inv(),
                    lever_arm)


def test_a_fix_frame_is_camera_optical_or_base_link():
    with pytest.raises(ValueError, match="fix_pose_frame"):
        _frame("camera")


def test_a_fix_orientation_must_be_a_unit_quaternion():
    frame = _frame("base_link")
    assert frame.body_quaternion([0.0, 0.0, 0.0, 2.0]) is None
    np.testing.assert_allclose(frame.body_quaternion([0.0, 0.0, 0.0, 1.005]), [0, 0, 0, 1])


def test_a_base_link_fix_is_the_body_pose_as_it_is():
    frame = _frame("base_link", lever_arm=(1.0, 0.0, 0.0))
    q = quat_from_euler(0.0, 0.0, 0.3)
    np.testing.assert_allclose(frame.body_quaternion(q), q)
    np.testing.assert_allclose(frame.body_position([5.0, 6.0, 7.0], q, q), [5.0, 6.0, 7.0])


def test_the_camera_centre_is_moved_back_by_the_turned_lever_arm():
    frame = _frame("camera_optical", lever_arm=(1.0, 0.0, 0.0))
    q_body = quat_from_euler(0.0, 0.0, math.pi / 2)     # nose north
    got = frame.body_position([5.0, 6.0, 7.0], q_body, None)
    np.testing.assert_allclose(got, [5.0, 5.0, 7.0], atol=1e-12)
    # without a fix attitude the estimate's turns it
    got = frame.body_position([5.0, 6.0, 7.0], None, quat_from_euler(0.0, 0.0, 0.0))
    np.testing.assert_allclose(got, [4.0, 6.0, 7.0], atol=1e-12)
    expected = np.array([5.0, 6.0, 7.0]) - quat_to_matrix(q_body) @ [1.0, 0.0, 0.0]
    np.testing.assert_allclose(frame.body_position([5.0, 6.0, 7.0], q_body, None), expected)


def test_fix_covariance_is_in_the_cores_block_order():
    pose = np.arange(36.0).reshape(6, 6)
    velocity = np.diag([7.0, 8.0, 9.0])
    position_only = fix_covariance(pose)
    np.testing.assert_array_equal(position_only, pose[:3, :3])
    full = fix_covariance(pose, velocity, with_attitude=True)
    assert full.shape == (9, 9)
    np.testing.assert_array_equal(full[:3, :3], pose[:3, :3])
    np.testing.assert_array_equal(full[3:6, 3:6], velocity)
    np.testing.assert_array_equal(full[6:, 6:], pose[3:, 3:])
    np.testing.assert_array_equal(full[:3, 6:], pose[:3, 3:])     # position-attitude terms
    np.testing.assert_array_equal(full[3:6, :3], 0.0)              # velocity: unknown terms
    attitude = fix_covariance(pose, None, with_attitude=True)
    np.testing.assert_array_equal(attitude, pose)


def test_gnss_refusals_name_their_reason():
    good = np.array([36.5, -84.3, 300.0])
    origin = EnuOrigin(36.6, -84.2, 0.0)
    assert gnss_refusal(1.0, good, origin) is None
    assert gnss_refusal(1.0, [np.nan, -84.3, 300.0], origin)[0] == "non_finite_value"
    assert gnss_refusal(math.inf, good, origin)[0] == "non_finite_value"
    assert gnss_refusal(1.0, [91.0, 0.0, 0.0], origin)[0] == "latitude_longitude_out_of_range"
    assert gnss_refusal(1.0, good, None) == ("no_enu_origin_yet", "")
    # a receiver's (0, 0) before its first fix, with or without an origin
    assert gnss_refusal(1.0, [0.0, 0.0, 0.0], None)[0] == "zero_latitude_longitude"
    assert gnss_refusal(1.0, [0.0, 0.0, 0.0], EnuOrigin(0.1, 0.1, 0.0))[0] == \
        "zero_latitude_longitude"
    reason, detail = gnss_refusal(1.0, [46.5, 7.0, 300.0], origin)   # the Alps, not Tennessee
    assert reason == "far_from_the_mission" and " km from the ENU origin" in detail
    assert gnss_refusal(1.0, [41.0, -84.3, 300.0], origin) is None    # 500 km: a long flight
    # an altitude in millimetres, or far below any ground
    reason, detail = gnss_refusal(1.0, [36.5, -84.3, 3.5e6], origin)
    assert reason == "altitude_out_of_range" and "in mm or feet?" in detail
    assert gnss_refusal(1.0, [36.5, -84.3, -5000.0], origin)[0] == "altitude_out_of_range"
    assert gnss_refusal(1.0, [36.5, -84.3, -30.0], origin) is None      # the Dead Sea's shore


def test_gnss_covariance_falls_back_or_keeps_what_the_fix_knows():
    cov = np.arange(9.0).reshape(3, 3) + np.eye(3)
    np.testing.assert_array_equal(
        gnss_covariance(cov, COVARIANCE_TYPE_UNKNOWN, [3.0, 3.0, 6.0]), np.diag([9, 9, 36.0]))
    np.testing.assert_array_equal(gnss_covariance(cov, COVARIANCE_TYPE_DIAGONAL_KNOWN, None),
                                  np.diag(np.diag(cov)))
    assert gnss_covariance(cov, 3, None) is cov


def test_baro_samples_need_a_positive_finite_pressure_and_variance():
    assert baro_refusal(1.0, 95000.0, 4.0) is None
    for stamp, pressure, variance in ((1.0, -1.0, 0.0), (1.0, np.nan, 0.0),
                                      (1.0, 95000.0, -1.0), (math.nan, 95000.0, 0.0)):
        assert baro_refusal(stamp, pressure, variance) is not None
    # FluidPressure is in Pa: a driver's hPa or kPa is named
    assert "hPa or mbar, not Pa?" in baro_refusal(1.0, 1013.25, 0.0)
    assert "kPa, not Pa?" in baro_refusal(1.0, 95.0, 0.0)
    assert "outside the 10-115 kPa" in baro_refusal(1.0, 250_000.0, 0.0)
    assert baro_refusal(1.0, 48_000.0, 0.0) is None   # a ScanEagle's ceiling, ~6 km


def _ekf(initialized=True, t=10.0, sigma_z=2.0, z=500.0, vz=1.0, stamp=10.0):
    state = SimpleNamespace(covariance=np.diag([1.0, 1.0, sigma_z ** 2]),
                            position=np.array([0.0, 0.0, z]),
                            velocity=np.array([0.0, 0.0, vz]), stamp=stamp)
    return SimpleNamespace(initialized=initialized, t=t, state=state)


def test_the_baro_offset_is_learnt_once_the_height_is_known_and_forgotten_on_reset():
    offset = BaroOffset(math.nan, max_sigma=10.0)
    assert offset.value is None
    assert not offset.learn(10.0, 480.0, _ekf(initialized=False))
    assert not offset.learn(11.5, 480.0, _ekf(t=10.0))            # another clock
    assert not offset.learn(10.0, 480.0, _ekf(sigma_z=20.0))      # height not known yet
    assert offset.learn(10.15, 480.0, _ekf())                      # a driver's latency
    assert offset.value == pytest.approx(500.0 + 1.0 * 0.15 - 480.0)
    assert offset.learn(11.0, 0.0, _ekf(initialized=False))        # known: stays
    offset.forget()
    assert offset.value is None


def test_a_set_baro_offset_is_never_learnt_or_forgotten():
    offset = BaroOffset(12.5, max_sigma=10.0)
    assert offset.value == 12.5 and offset.learn(0.0, 0.0, _ekf(initialized=False))
    offset.forget()
    assert offset.value == 12.5


def test_the_origin_handshake_adopts_the_first_origin_and_resends_a_lost_request():
    handshake = OriginHandshake(resend_after=5.0)
    assert handshake.request(0.0, pending=False) == "send"
    handshake.sent(0.0)
    assert handshake.request(4.9, pending=True) == "wait"
    assert handshake.request(5.1, pending=True) == "resend"
    with pytest.raises(ValueError):
        handshake.adopt(95.0, 0.0, 0.0)
    assert handshake.adopt(36.5, -84.3, 300.0)
    assert not handshake.adopt(10.0, 10.0, 0.0)                   # the first one wins
    assert handshake.origin.lat == 36.5
    assert handshake.request(6.0, pending=True) == "done"


@pytest.mark.parametrize("accel, words", [
    ((0.3, 0.1, 9.8), None),                     # FLU, level
    ((0.5, 2.0, 11.5), None),                    # FLU, a 30 deg coordinated turn
    ((0.3, -0.1, -9.8), "FRD / NED"),            # z down
    ((0.03, 0.01, 1.0), "in g, not m/s^2"),
    ((3.0, 1.0, 1000.0), "in milli-g"),
    ((9.8, 0.2, 0.3), "not along body z"),       # mounted on its side
    ((0.0, 0.0, 0.0), "far below gravity"),      # a dead accelerometer
])
def test_the_first_second_of_imu_tells_its_axes_and_units(accel, words):
    from terrain_nav_ros.core.estimation.ekf_inputs import ImuConvention

    check = ImuConvention(9.80665, window=1.0)
    rng = np.random.default_rng(0)
    answers = [check.add(100.0 + 0.01 * k, np.asarray(accel) + rng.normal(0, 0.05, 3))
               for k in range(150)]
    assert all(a is None for a in answers[:100])   # nothing said before a whole second
    if words is None:
        assert answers[-1] is None and check.problem is None
    else:
        assert words in answers[-1]
        # for good: later samples that look right do not undo it
        assert words in check.add(200.0, np.array([0.0, 0.0, 9.8]))
    assert check.add(300.0, np.array([np.nan, 0.0, 9.8])) == check.problem


def _gyro_scale_answers(segments, gyro_scale=1.0, wind=(0.0, 0.0), accel_bias=None,
                        bias_learnt=True, seed=0):
    """GyroScale's answers over a simulated flight's IMU (speed, and the accelerometer bias
    when ``bias_learnt``, from the truth)."""
    from terrain_nav_ros.core.estimation.ekf_inputs import GyroScale
    from terrain_nav_ros.core.estimation.ekf_params import EkfParams
    from terrain_nav_ros.core.sim.imu_sim import ImuErrorModel, simulate_imu
    from terrain_nav_ros.core.sim.trajectory_sim import simulate_trajectory

    truth = simulate_trajectory(segments, rate_hz=100.0).in_wind(*wind)
    imu = simulate_imu(truth, ImuErrorModel.from_params(EkfParams()),
                       np.random.default_rng(seed), accel_bias=accel_bias)
    check = GyroScale(9.80665)
    speed = np.linalg.norm(truth.velocity, axis=1)
    answers = []
    for k in range(len(truth)):
        def motion(k=k):
            return speed[k], imu.accel_bias[k] if bias_learnt else np.zeros(3)
        answers.append(check.add(truth.t[k], imu.gyro[k] * gyro_scale, imu.accel[k], motion))
    return answers, check


@pytest.mark.parametrize("turn_deg_s", [3.0, 6.0, 12.0])
def test_a_gyro_in_deg_per_s_is_refused_in_its_first_turn(turn_deg_s):
    from terrain_nav_ros.core.sim.trajectory_sim import Segment

    turn = np.deg2rad(turn_deg_s)
    segments = [Segment(20.0), Segment(20.0, turn), Segment(20.0)]
    answers, check = _gyro_scale_answers(segments, gyro_scale=math.degrees(1.0))
    assert all(a is None for a in answers[:2000])      # straight flight hides the unit
    assert "deg/s, not rad/s" in answers[-1]
    first = next(k for k, a in enumerate(answers) if a is not None)
    assert first < 2000 + 1200                         # within the turn's first 12 s
    assert check.add(100.0, np.zeros(3), np.array([0.0, 0.0, 9.8]), lambda: None) \
        == check.problem                               # for good


@pytest.mark.parametrize("segments_of, wind", [
    ("s_turns", (0.0, 0.0)),
    ("s_turns", (9.0, -4.0)),          # 30 % wind: the ground speed stands in for the air's
    ("climbing_turns", (0.0, 0.0)),
    ("straight", (0.0, 0.0)),
])
def test_a_gyro_in_rad_per_s_passes_in_turns_wind_and_climbs(segments_of, wind):
    from terrain_nav_ros.core.sim.trajectory_sim import Segment, straight_flight, turning_flight

    segments = {
        "s_turns": turning_flight(120.0, np.deg2rad(6.0)),
        "climbing_turns": [Segment(30.0, np.deg2rad(4.0), np.deg2rad(6.0)),
                           Segment(30.0, np.deg2rad(-8.0), np.deg2rad(-4.0))],
        "straight": straight_flight(60.0),
    }[segments_of]
    answers, _ = _gyro_scale_answers(segments, wind=wind)
    assert all(a is None for a in answers)


def test_an_accelerometer_bias_the_filter_has_not_learnt_is_no_turn():
    """0.6 m/s^2 on z reads like a 10 deg bank to |f|; the gyro's few mrad/s are then no
    evidence either way, and a correct gyro is never refused for it."""
    from terrain_nav_ros.core.sim.trajectory_sim import straight_flight

    answers, _ = _gyro_scale_answers(straight_flight(60.0), accel_bias=(0.0, 0.0, 0.6),
                                     bias_learnt=False)
    assert all(a is None for a in answers)
