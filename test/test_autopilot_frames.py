"""REP 103 (ENU / FLU) <-> PX4 (NED / FRD) conversions, with poses worked out by hand."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from terrain_nav_ros.core.estimation.autopilot_frames import (
    RateLimiter,
    ResetCounter,
    body_to_world_covariance,
    covariance_enu_to_ned,
    covariance_flu_to_frd,
    enu_to_ned,
    flu_to_frd,
    frd_to_flu,
    horizontal_accuracy,
    ned_to_enu,
    ns_to_px4_us,
    px4_us_to_ns,
    quaternion_enu_flu_to_ned_frd,
    quaternion_ned_frd_to_enu_flu,
    rotate_covariance,
)
from terrain_nav_ros.core.estimation.strapdown import quat_from_euler

S = 2 ** -0.5


def _px4_matrix(q_wxyz):
    """FRD -> NED rotation matrix of a PX4 quaternion."""
    w, x, y, z = q_wxyz
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def _px4_euler(roll, pitch, yaw):
    """PX4 quaternion [w, x, y, z] of FRD -> NED Euler angles (yaw clockwise from north,
    pitch nose up, roll right wing down), R = Rz(yaw) Ry(pitch) Rx(roll)."""
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def test_positions_and_velocities_swap_east_north_and_negate_up():
    assert np.allclose(enu_to_ned([10.0, 20.0, 30.0]), [20.0, 10.0, -30.0])
    assert np.allclose(ned_to_enu([20.0, 10.0, -30.0]), [10.0, 20.0, 30.0])
    # vectorised over leading axes
    v = np.arange(12.0).reshape(2, 2, 3)
    assert enu_to_ned(v).shape == (2, 2, 3)
    assert np.allclose(ned_to_enu(enu_to_ned(v)), v)


def test_body_vectors_negate_y_and_z():
    # a roll rate right wing down is +x in both; a yaw to the left is +z in FLU, -z in FRD
    assert np.allclose(flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    assert np.allclose(frd_to_flu(flu_to_frd([0.1, -0.2, 0.3])), [0.1, -0.2, 0.3])
    with pytest.raises(ValueError):
        enu_to_ned([1.0, 2.0])


def test_nose_north_level_aircraft_is_px4_identity():
    q_ros = quat_from_euler(0.0, 0.0, math.pi / 2)         # ROS yaw CCW from east
    assert np.allclose(q_ros, [0, 0, S, S])
    q = quaternion_enu_flu_to_ned_frd(q_ros)
    assert np.allclose(q, [1.0, 0.0, 0.0, 0.0])
    assert np.allclose(quaternion_ned_frd_to_enu_flu(q), q_ros)


@pytest.mark.parametrize(("ros_yaw_deg", "px4_yaw_deg"), [
    (0.0, 90.0),        # nose east
    (90.0, 0.0),        # nose north
    (180.0, -90.0),     # nose west
    (-90.0, 180.0),     # nose south
    (30.0, 60.0),
])
def test_yaw_is_ninety_degrees_minus_the_ros_yaw(ros_yaw_deg, px4_yaw_deg):
    q_ros = quat_from_euler(0.0, 0.0, math.radians(ros_yaw_deg))
    q = quaternion_enu_flu_to_ned_frd(q_ros)
    assert np.allclose(q, _px4_euler(0.0, 0.0, math.radians(px4_yaw_deg)), atol=1e-12) or \
        np.allclose(q, -_px4_euler(0.0, 0.0, math.radians(px4_yaw_deg)), atol=1e-12)
    # the nose points the same way in both worlds
    nose_enu = Rotation.from_quat(q_ros).apply([1.0, 0.0, 0.0])
    assert np.allclose(_px4_matrix(q) @ [1.0, 0.0, 0.0], enu_to_ned(nose_enu))


def test_nose_north_pitched_up_and_rolled_right_by_hand():
    # Nose north, 30 deg nose up, then 45 deg right wing down: PX4 Euler (45, 30, 0) deg.
    # REP 103: positive pitch is nose DOWN, positive roll is right wing down (about +x).
    q_ros = quat_from_euler(math.radians(45.0), math.radians(-30.0), math.pi / 2)
    q = quaternion_enu_flu_to_ned_frd(q_ros)
    assert np.allclose(q, _px4_euler(math.radians(45.0), math.radians(30.0), 0.0))
    r = _px4_matrix(q)
    c30, s30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    # nose: north and up (NED down negative)
    assert np.allclose(r @ [1, 0, 0], [c30, 0.0, -s30])
    # right wing (FRD +y): east and 45 deg down, tilted by the pitch
    assert np.allclose(r @ [0, 1, 0], [s30 * S, S, c30 * S])
    # and the same for FLU's left wing in ENU: west and up
    left = Rotation.from_quat(q_ros).apply([0.0, 1.0, 0.0])
    assert np.allclose(enu_to_ned(left), -(r @ [0, 1, 0]))
    assert np.allclose(quaternion_ned_frd_to_enu_flu(q), q_ros)


def test_general_attitudes_match_the_euler_convention_of_each_side():
    rng = np.random.default_rng(3)
    for _ in range(20):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2, 3)
        q = quaternion_enu_flu_to_ned_frd(quat_from_euler(roll, pitch, yaw))
        expected = _px4_euler(roll, -pitch, math.pi / 2 - yaw)
        assert np.allclose(q, expected, atol=1e-12)


def test_quaternion_round_trips_vectorised_and_scalar_first_positive():
    q_ros = Rotation.random(50, random_state=5).as_quat()
    q_px4 = quaternion_enu_flu_to_ned_frd(q_ros)
    assert q_px4.shape == (50, 4) and (q_px4[:, 0] >= 0).all()
    assert np.allclose(np.linalg.norm(q_px4, axis=1), 1.0)
    back = quaternion_ned_frd_to_enu_flu(q_px4)
    same = np.abs(np.einsum("ij,ij->i", back, q_ros))       # q and -q are one attitude
    assert np.allclose(same, 1.0)
    # and from the PX4 side
    q2 = quaternion_enu_flu_to_ned_frd(quaternion_ned_frd_to_enu_flu(q_px4))
    assert np.allclose(q2, q_px4)


def test_position_covariance_swaps_axes_and_flips_the_vertical_cross_terms():
    cov = np.array([[1.0, 0.5, 0.3],
                    [0.5, 4.0, -0.2],
                    [0.3, -0.2, 9.0]])            # E, N, U
    ned = covariance_enu_to_ned(cov)
    assert np.allclose(np.diag(ned), [4.0, 1.0, 9.0])
    assert math.isclose(ned[0, 1], 0.5)            # N-E = E-N
    assert math.isclose(ned[1, 2], -0.3)           # E-D = -(E-U)
    assert math.isclose(ned[0, 2], 0.2)            # N-D = -(N-U)
    assert np.allclose(ned, ned.T)
    assert np.allclose(covariance_enu_to_ned(ned), cov)


def test_pose_covariance_6x6_rotates_position_and_rotation_blocks():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T
    ned = covariance_enu_to_ned(cov)
    perm = [1, 0, 2, 4, 3, 5]
    sign = np.array([1, 1, -1, 1, 1, -1])
    assert np.allclose(ned, cov[np.ix_(perm, perm)] * np.outer(sign, sign))
    # yaw variance about up = yaw variance about down
    assert math.isclose(ned[5, 5], cov[5, 5])
    assert np.allclose(covariance_enu_to_ned(ned), cov)
    # linear transformation of samples gives the same covariance
    samples = rng.multivariate_normal(np.zeros(6), cov, size=200)
    moved = np.hstack([enu_to_ned(samples[:, :3]), enu_to_ned(samples[:, 3:])])
    assert np.allclose(np.cov(moved.T), covariance_enu_to_ned(np.cov(samples.T)))
    with pytest.raises(ValueError):
        rotate_covariance(np.eye(4), np.eye(3))


def test_body_covariances_flu_to_frd_and_to_the_world():
    cov = np.diag([1.0, 2.0, 3.0])
    cov[0, 1] = cov[1, 0] = 0.4
    frd = covariance_flu_to_frd(cov)
    assert np.allclose(np.diag(frd), [1.0, 2.0, 3.0]) and math.isclose(frd[0, 1], -0.4)
    # nose north: body forward variance becomes north variance
    world = body_to_world_covariance(np.diag([1.0, 4.0, 9.0]), quat_from_euler(0, 0, math.pi / 2))
    assert np.allclose(np.diag(world), [4.0, 1.0, 9.0])


def test_px4_timestamps_are_microseconds():
    assert ns_to_px4_us(1_700_000_000_123_456_789) == 1_700_000_000_123_456
    assert ns_to_px4_us(999) == 0 and ns_to_px4_us(-5) == 0
    assert px4_us_to_ns(ns_to_px4_us(12_345_678_000)) == 12_345_678_000


def test_rate_limiter_averages_the_rate_and_restarts_on_time_jumps():
    limiter = RateLimiter(30.0)
    t0 = 1.7e9                                       # epoch stamps as float seconds
    passed = [t0 + k * 0.02 for k in range(500) if limiter.ready(t0 + k * 0.02)]  # 50 Hz, 10 s
    assert 299 <= len(passed) <= 301
    assert min(np.diff(passed)) >= 0.02 - 1e-6      # never two in a row at the same time
    slow = RateLimiter(30.0)
    assert all(slow.ready(k * 0.1) for k in range(20))   # 10 Hz passes whole
    assert not slow.ready(1.9 + 0.001)
    assert slow.ready(0.5)                                # time went back: bag loop
    assert all(RateLimiter(0.0).ready(1.0) for _ in range(3))
    # after a gap the schedule restarts instead of letting a burst through
    gap = RateLimiter(10.0)
    assert gap.ready(0.0) and gap.ready(5.0) and not gap.ready(5.05) and gap.ready(5.1)


def test_reset_counter_counts_filter_resets_jumps_and_wraps():
    rc = ResetCounter(jump_threshold=50.0)
    assert not rc.observe_filter_resets(0)
    assert not rc.observe_filter_resets(0)
    assert rc.observe_filter_resets(1) and rc.value == 1
    v = np.array([30.0, 0.0, 0.0])
    assert not rc.observe_pose(0.0, [0, 0, 0], v)
    assert not rc.observe_pose(1.0, [31.0, 5.0, 0], v)         # 30 m/s: 5 m off, fine
    assert rc.observe_pose(2.0, [61.0, 80.0, 0], v)             # relocalised by 80 m
    assert rc.value == 2
    assert rc.observe_pose(1.0, [61.0, 80.0, 0], v)             # time ran backwards
    for _ in range(300):
        rc.bump()
    assert rc.value == (3 + 300) % 256 and rc.count == 303
    assert not ResetCounter(0.0).observe_pose(0.0, [0, 0, 0], v) and \
        not ResetCounter(0.0).observe_pose(1.0, [1e6, 0, 0], v)


def test_horizontal_accuracy_is_the_long_axis():
    assert math.isclose(horizontal_accuracy(np.diag([9.0, 4.0, 100.0])), 3.0)
    cov = np.array([[5.0, 4.0, 0.0], [4.0, 5.0, 0.0], [0.0, 0.0, 1.0]])
    assert math.isclose(horizontal_accuracy(cov), 3.0)


def test_a_reset_counter_moves_once_per_discontinuity_whoever_tells_it_first():
    """PX4 EKF2 resets its vision states at each change of the counter: a filter reset
    must change it once, at its first estimate, whether the filter's count (diagnostics)
    or the estimate's jump comes first; a gap in the estimates (a respawned filter resuming
    from its checkpoint) is a reset though the position moved less than the threshold."""
    v = np.array([30.0, 0.0, 0.0])

    def flight(rc, t0, t1, x0=0.0):
        return [rc.observe_pose(t, [x0 + 30.0 * (t - t0), 0, 0], v)
                for t in np.arange(t0, t1, 0.02)]

    # a 300 m relocalisation: the jump first, then the count that reports it
    rc = ResetCounter(jump_threshold=50.0, max_gap=0.5)
    rc.observe_filter_resets(0, float("nan"))
    flight(rc, 0.0, 1.0)
    assert rc.observe_pose(1.0, [330.0, 0, 0], v) and rc.value == 1
    assert not rc.observe_filter_resets(1, 1.0) and rc.value == 1
    # ... the count first (the ekf reports at once), then the jump of that estimate
    assert rc.observe_filter_resets(2, 2.0) and rc.value == 2
    flight(rc, 1.02, 2.0, 330.6)
    assert not rc.observe_pose(2.0, [700.0, 0, 0], v) and rc.value == 2
    assert not any(flight(rc, 2.02, 3.0, 700.6)) and rc.value == 2
    # a 30 m re-seed (below the jump threshold): the count alone moves it, once
    assert rc.observe_filter_resets(3, 3.0) and rc.value == 3
    assert not any(flight(rc, 3.0, 4.0, 730.0)) and rc.value == 3
    # the filter dies; its respawn resumes 1.5 s later 30 m off, its count back at 0
    assert rc.observe_pose(5.5, [790.0, 0, 0], v) and rc.value == 4
    assert not rc.observe_filter_resets(0, float("nan")) and rc.value == 4
    # a count with no stamp (another filter) still moves it
    assert rc.observe_filter_resets(1) and rc.value == 5
    # without the gap rule, a new process's count is all there is to go by
    no_gap = ResetCounter(50.0)
    no_gap.observe_filter_resets(4)
    assert no_gap.observe_filter_resets(0) and no_gap.value == 1
