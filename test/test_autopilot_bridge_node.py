"""autopilot_bridge in its own process, once per target, fed by a stand-in ekf (issue 25).

The test process plays the ekf: /nav/odometry at 50 Hz of estimate time (played ~2x real
time), /nav/fix at 10 Hz and /nav/ekf/diagnostics every 0.2 s of wall time. Phases:

1. odometry without diagnostics: nothing may go out;
2. healthy (initialised, OK): outputs at 30 Hz, in the target's frames;
3. the estimate jumps 300 m (a relocalising fix), then the ekf counts a reset: the PX4
   reset_counter moves on twice;
4. the ekf reports ERROR: nothing goes out; OK again: output resumes, reset_counter + 1.

Both bridges (px4 with SensorGps, mavros with the vision pose) run at once on the same
inputs; everything they publish is recorded once (module fixture).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from ros_helpers import SpinningNode, start_node, stop, wait_until

from terrain_nav_ros.core.estimation.autopilot_frames import (
    body_to_world_covariance,
    covariance_enu_to_ned,
    quaternion_enu_flu_to_ned_frd,
)
from terrain_nav_ros.core.estimation.strapdown import quat_from_euler, quat_to_matrix
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
from terrain_nav_ros.nodes import conversions as cv

T0_NS = 1_700_000_000_000_000_000
ODOM_HZ = 50.0
SPEEDUP = 2.0
ORIGIN = EnuOrigin(36.5, -84.3, 300.0)
GEOID = -31.0
# nose 30 deg east of north, 0.1 rad right wing down, 0.05 rad nose up (REP 103 angles)
Q = quat_from_euler(0.1, -0.05, math.radians(60.0))
V_ENU = np.array([15.0, 25.0, 1.0])                 # east, north, up [m/s]
POSE_COV = np.diag([4.0, 9.0, 16.0, 0.01, 0.02, 0.03])
POSE_COV[0, 1] = POSE_COV[1, 0] = 1.5
TWIST_COV = np.diag([0.25, 0.36, 0.49, 1e-4, 1e-4, 1e-4])
OMEGA = np.array([0.01, -0.02, 0.03])               # FLU [rad/s]
JUMP = np.array([300.0, 0.0, 0.0])
PHASES = {"no_diag": (0.0, 1.0), "healthy": (1.0, 5.0), "jump": (5.0, 7.0),
          "lost": (7.0, 8.0), "back": (8.0, 10.0)}


def _position(t):
    p = np.array([100.0, 200.0, 1500.0]) + V_ENU * t
    return p + JUMP if t >= PHASES["jump"][0] + 0.5 else p


def _odometry(t):
    header = cv.make_header(T0_NS + round(t * 1e9), "map")
    v_body = quat_to_matrix(Q).T @ V_ENU
    return cv.odometry_msg(header, "base_link", _position(t), Q, POSE_COV, v_body, OMEGA,
                           TWIST_COV)


def _navsatfix(t):
    lat, lon, h = ORIGIN.enu_to_geodetic(*_position(t))
    return cv.arrays_to_navsatfix(cv.make_header(T0_NS + round(t * 1e9), "map"), float(lat),
                                  float(lon), float(h), POSE_COV[:3, :3])


class Ekf:
    """Publishes what the ekf would, diagnostics from a timer with the current state."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import NavSatFix

        from terrain_nav_ros.nodes.ros_common import RELIABLE_QOS

        self.state = None        # None = no diagnostics; else (level, initialized, resets)
        self.odom = node.create_publisher(Odometry, "/nav/odometry", RELIABLE_QOS)
        self.fix = node.create_publisher(NavSatFix, "/nav/fix", RELIABLE_QOS)
        self.diag = node.create_publisher(DiagnosticArray, "/nav/ekf/diagnostics",
                                          RELIABLE_QOS)
        self._type = DiagnosticArray
        node.create_timer(0.2, self.tick)

    def tick(self):
        if self.state is None:
            return
        level, initialized, resets = self.state
        self.diag.publish(self._type(status=[cv.diagnostic_status(
            "ekf: filter", level, "test", {"initialized": initialized, "resets": resets,
                                           "position_resets": 0})]))

    def set(self, state):
        self.state = state
        self.tick()
        time.sleep(0.5)           # reaches the bridges before the next odometry


@pytest.fixture(scope="module")
def bridges():
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from px4_msgs.msg import SensorGps, VehicleOdometry

    from terrain_nav_ros.nodes.autopilot_bridge_node import PX4_QOS
    from terrain_nav_ros.nodes.ros_common import RELIABLE_QOS

    procs = {
        # (estimates stamped from T0, a fixed date: their age by the wall clock is not
        # what these phases test; max_estimate_age is tested on its own)
        "px4": start_node("autopilot_bridge", {
            "target": "px4", "px4_sensor_gps": True, "geoid_undulation": GEOID,
            "diagnostics_period": 0.5, "max_estimate_age": 0.0}),
        "mavros": start_node("autopilot_bridge", {
            "target": "mavros", "mavros_vision_pose": True, "diagnostics_period": 0.5,
            "max_estimate_age": 0.0},
            "-r", "__node:=autopilot_bridge_mavros"),
    }
    client = SpinningNode("autopilot_bridge_test")
    node = client.node
    ekf = Ekf(node)
    got = {"px4": [], "gps": [], "mavros": [], "pose": [], "diag": []}
    subs = [
        node.create_subscription(VehicleOdometry, "/fmu/in/vehicle_visual_odometry",
                                 got["px4"].append, PX4_QOS),
        node.create_subscription(SensorGps, "/fmu/in/sensor_gps", got["gps"].append, PX4_QOS),
        node.create_subscription(Odometry, "/mavros/odometry/out", got["mavros"].append,
                                 RELIABLE_QOS),
        node.create_subscription(PoseWithCovarianceStamped, "/mavros/vision_pose/pose_cov",
                                 got["pose"].append, RELIABLE_QOS),
        node.create_subscription(DiagnosticArray, "/autopilot_bridge/diagnostics",
                                 got["diag"].append, RELIABLE_QOS),
    ]
    try:
        assert wait_until(lambda: ekf.odom.get_subscription_count() == 2
                          and ekf.diag.get_subscription_count() == 2
                          and ekf.fix.get_subscription_count() == 1
                          and all(s.get_publisher_count() >= 1 for s in subs[:4]), 30), \
            "the bridges never came up:\n" + "\n".join(stop(p) for p in procs.values())
        marks = {}
        start, t_played = time.monotonic(), 0.0
        for phase, (t0, t1) in PHASES.items():
            if phase == "healthy":
                ekf.set((0, True, 0))
            elif phase == "lost":
                ekf.set((2, True, 1))
            elif phase == "back":
                ekf.set((0, True, 1))
            start, t_played = time.monotonic(), t0
            for k in range(round(t0 * ODOM_HZ), round(t1 * ODOM_HZ)):
                t = k / ODOM_HZ
                lag = (t - t_played) / SPEEDUP - (time.monotonic() - start)
                if lag > 0.002:
                    time.sleep(lag)
                ekf.odom.publish(_odometry(t))
                if k % 5 == 0:
                    ekf.fix.publish(_navsatfix(t))
                if phase == "jump" and t == t0 + 1.0:
                    ekf.set((0, True, 1))        # the ekf counts a reset
                    start, t_played = time.monotonic(), t
            time.sleep(0.5)
            marks[phase] = {key: len(v) for key, v in got.items()}
        time.sleep(0.6)                          # a last diagnostics report
        alive = {k: p.poll() is None for k, p in procs.items()}
    finally:
        client.close()
        logs = {k: stop(p) for k, p in procs.items()}
    return {"got": got, "marks": marks, "alive": alive, "logs": logs}


def _between(bridges, key, after, upto):
    """Messages of ``key`` received during the phases after ``after`` up to ``upto``."""
    marks = bridges["marks"]
    return bridges["got"][key][marks[after][key] if after else 0:marks[upto][key]]


def _sample_s(msg) -> float:
    return (msg.timestamp_sample * 1000 - T0_NS) * 1e-9


def _sent_while_lost(bridges, key):
    """PX4 messages of estimates from the lost phase (by their sample time: on a loaded
    machine one sent at the end of the jump phase may arrive after its mark)."""
    return [m for m in _between(bridges, key, "jump", "lost")
            if _sample_s(m) >= PHASES["lost"][0]]


def test_nothing_goes_out_before_the_ekf_says_it_is_initialised(bridges):
    assert bridges["alive"] == {"px4": True, "mavros": True}, bridges["logs"]
    for key in ("px4", "gps", "mavros", "pose"):
        assert _between(bridges, key, None, "no_diag") == [], key
    # and the bridges say why
    held = [v for m in bridges["got"]["diag"] for s in m.status
            for v in (cv.diagnostic_values(s)[1],) if "held back: no ekf diagnostics yet" in v]
    assert {v["target"] for v in held} == {"px4", "mavros"}


def test_px4_odometry_is_ned_frd_with_rotated_variances_at_30_hz(bridges):
    msgs = _between(bridges, "px4", "no_diag", "healthy")
    t = np.array([_sample_s(m) for m in msgs])
    # 4 s of 50 Hz estimates at 30 Hz (best effort: allow a lost sample or two)
    assert 110 <= len(msgs) <= 121, len(msgs)
    # never faster than the limit; spaced 1-2 estimates apart but where a sample was lost
    steps = np.diff(t)
    assert steps.min() >= 0.02 - 1e-6 and (steps > 0.04 + 1e-6).sum() <= 3, steps
    m = msgs[10]
    ts = _sample_s(m)
    p = _position(ts)
    assert m.pose_frame == m.POSE_FRAME_NED and m.velocity_frame == m.VELOCITY_FRAME_NED
    assert m.timestamp_sample == (T0_NS + round(ts * 1e9)) // 1000
    assert m.timestamp > 0
    assert np.allclose(m.position, [p[1], p[0], -p[2]], atol=1e-3 * np.abs(p).max())
    assert np.allclose(m.velocity, [V_ENU[1], V_ENU[0], -V_ENU[2]], atol=1e-4)
    q = np.asarray(m.q, float)
    assert np.allclose(q, quaternion_enu_flu_to_ned_frd(Q), atol=1e-6)
    assert np.allclose(m.angular_velocity, [OMEGA[0], -OMEGA[1], -OMEGA[2]], atol=1e-7)
    assert np.allclose(m.position_variance, [9.0, 4.0, 16.0])
    assert np.allclose(m.orientation_variance, [0.02, 0.01, 0.03])
    v_cov = covariance_enu_to_ned(body_to_world_covariance(TWIST_COV[:3, :3], Q))
    assert np.allclose(m.velocity_variance, np.diag(v_cov), rtol=1e-5)
    assert m.reset_counter == 0 and m.quality == 100


def test_px4_reset_counter_moves_on_for_jumps_resets_and_resumption(bridges):
    jump = _between(bridges, "px4", "healthy", "jump")
    counters = [(round(_sample_s(m), 2), m.reset_counter) for m in jump]
    before = [c for t, c in counters if t < PHASES["jump"][0] + 0.5]
    after_jump = [c for t, c in counters if PHASES["jump"][0] + 0.5 <= t < PHASES["jump"][0] + 1]
    after_reset = [c for t, c in counters if t > PHASES["jump"][0] + 1.1]
    assert set(before) == {0} and set(after_jump) == {1} and set(after_reset) == {2}, counters
    # lost: nothing; back: resumes with the counter moved on
    assert _sent_while_lost(bridges, "px4") == []
    back = _between(bridges, "px4", "lost", "back")
    assert len(back) > 50 and {m.reset_counter for m in back} == {3}
    assert min(_sample_s(m) for m in back) >= PHASES["back"][0]


def test_px4_sensor_gps_reports_the_estimates_own_accuracy(bridges):
    msgs = _between(bridges, "gps", "no_diag", "healthy")
    assert 17 <= len(msgs) <= 21, len(msgs)             # 4 s at 5 Hz from 10 Hz fixes
    m = msgs[5]
    ts = _sample_s(m)
    lat, lon, h = ORIGIN.enu_to_geodetic(*_position(ts))
    assert m.latitude_deg == pytest.approx(lat, abs=1e-9)
    assert m.longitude_deg == pytest.approx(lon, abs=1e-9)
    assert m.altitude_ellipsoid_m == pytest.approx(h, abs=1e-6)
    assert m.altitude_msl_m == pytest.approx(h - GEOID, abs=1e-6)
    assert m.fix_type == m.FIX_TYPE_3D
    long_axis = math.sqrt(np.linalg.eigvalsh(POSE_COV[:2, :2])[-1])
    assert m.eph == pytest.approx(long_axis, rel=1e-5) and m.epv == pytest.approx(4.0)
    assert m.satellites_used == 0 and math.isnan(m.hdop) and math.isnan(m.vdop)
    assert m.vel_ned_valid
    assert [m.vel_n_m_s, m.vel_e_m_s, m.vel_d_m_s] == pytest.approx([25.0, 15.0, -1.0],
                                                                   abs=1e-4)
    assert m.cog_rad == pytest.approx(math.atan2(15.0, 25.0), abs=1e-5)
    assert _sent_while_lost(bridges, "gps") == []


def test_mavros_odometry_is_the_enu_estimate_in_odom_and_base_link(bridges):
    msgs = _between(bridges, "mavros", "no_diag", "healthy")
    assert 118 <= len(msgs) <= 121, len(msgs)            # reliable: none lost
    t = np.array([(cv.stamp_to_ns(m.header.stamp) - T0_NS) * 1e-9 for m in msgs])
    assert np.diff(t).min() >= 0.02 - 1e-6
    m = msgs[3]
    assert (m.header.frame_id, m.child_frame_id) == ("odom", "base_link")
    src = _odometry(t[3])
    assert m.pose == src.pose and m.twist == src.twist
    poses = _between(bridges, "pose", "no_diag", "healthy")
    assert len(poses) == len(msgs)
    assert poses[3].header == m.header and poses[3].pose == m.pose
    assert _between(bridges, "mavros", "jump", "lost") == []
    assert len(_between(bridges, "mavros", "lost", "back")) > 50


def test_estimates_the_autopilot_must_not_get_are_held_back_with_the_reason(monkeypatch):
    """Odometry in another frame, an hour old, with a quaternion not of unit length, a NaN
    velocity, an unknown (zero) covariance or a position 40 000 km off never reaches the
    autopilot, however healthy the ekf says it is; each is counted by its reason. The node
    in this process, its callbacks called directly."""
    import rclpy

    from terrain_nav_ros.nodes.autopilot_bridge_node import AutopilotBridge

    context = rclpy.Context()
    rclpy.init(context=context)
    node = AutopilotBridge(context=context)
    try:
        sent = []
        monkeypatch.setattr(node, "_publish", lambda key, msg: sent.append(key))
        node.ekf_status, node._ekf_status_wall = (0, "ok", {"initialized": "True"}), \
            time.monotonic()
        now_ns = node.get_clock().now().nanoseconds
        v_body = quat_to_matrix(Q).T @ V_ENU

        def odometry(frame="map", child="base_link", age=0.0, q=Q, v=v_body, cov=POSE_COV,
                     position=(100.0, 200.0, 1500.0)):
            header = cv.make_header(now_ns - round(age * 1e9), frame)
            return cv.odometry_msg(header, child, np.array(position), q, cov, v, OMEGA,
                                   TWIST_COV)

        bad = {
            "odometry in utm -> base_link, not map -> base_link": odometry(frame="utm"),
            "odometry in map -> (none), not map -> base_link": odometry(child=""),
            "estimate older than max_estimate_age": odometry(age=3600.0),
            "estimate stamped ahead of the node's clock (max_estimate_lead)":
                odometry(age=-3600.0),
            "quaternion not of unit length": odometry(q=2.0 * Q),
            "non-finite estimate": odometry(v=np.array([np.nan, 0.0, 0.0])),
            "position covariance not positive (unknown)": odometry(cov=np.zeros((6, 6))),
            "position beyond 10 000 km": odometry(position=(4e7, 0.0, 0.0)),
        }
        for msg in bad.values():
            node.on_odometry(msg)
        assert sent == [] and dict(node.held_back) == {reason: 1 for reason in bad}
        node.on_odometry(odometry())
        assert sent == ["odometry"]
        # a late one (PX4 would drop it, and take the next for a reset) is not sent and
        # stops nothing: the counter stays
        node.on_odometry(odometry(age=0.5))
        node.on_odometry(odometry(age=-0.05))
        assert sent == ["odometry"] * 2 and node.resets.value == 0
        assert node.held_back["estimate not after the last one (late, out of order)"] == 1
    finally:
        node.destroy_node()
        context.try_shutdown()


def test_the_reset_counter_moves_once_at_a_respawn_or_a_reset_and_not_for_a_glitch(
        monkeypatch):
    """What PX4 takes for a reset of its vision states: a respawned ekf resuming 30 m off
    after a second's silence (below the 50 m jump threshold), and an ekf reset it reports
    at once with the estimate time of its first estimate after it, each move the counter
    once, at that estimate; one held-back glitch (a NaN rate variance) does not. The node
    in this process, its callbacks called directly."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    from terrain_nav_ros.nodes.autopilot_bridge_node import AutopilotBridge

    context = rclpy.Context()
    rclpy.init(context=context)
    node = AutopilotBridge(context=context, parameter_overrides=[
        rclpy.parameter.Parameter("max_estimate_age", value=0.0),
        rclpy.parameter.Parameter("rate", value=0.0)])
    try:
        sent = []
        monkeypatch.setattr(node, "_publish", lambda key, msg: sent.append(msg.reset_counter))
        v_body = quat_to_matrix(Q).T @ V_ENU

        def diagnostics(resets, at):
            node.on_diagnostics(DiagnosticArray(status=[cv.diagnostic_status(
                "ekf: filter", 0, "ok", {"initialized": True, "resets": 0,
                                         "position_resets": resets,
                                         "last_reset_stamp": f"{at:.6f}"})]))

        def fly(t0, t1, offset=0.0, twist_cov=TWIST_COV):
            for t in np.arange(t0, t1 - 1e-9, 0.02):
                header = cv.make_header(T0_NS + round(t * 1e9), "map")
                node.on_odometry(cv.odometry_msg(header, "base_link", _position(0.0) + V_ENU * t
                                                 + [offset, 0, 0], Q, POSE_COV, v_body, OMEGA,
                                                 twist_cov))

        diagnostics(0, math.nan)
        fly(0.0, 2.0)
        bad_rate = TWIST_COV.copy()
        bad_rate[4, 4] = np.nan
        fly(2.0, 2.02, twist_cov=bad_rate)                 # held back: a glitch
        fly(2.02, 3.0)
        assert set(sent) == {0}
        # the ekf re-seeded 30 m east at 3.0 s: reported before that estimate
        diagnostics(1, 3.0 + T0_NS * 1e-9)
        fly(3.0, 4.0, 30.0)
        assert sent[-50:] == [1] * 50
        # it dies, and its respawn resumes from the checkpoint 1 s later, 30 m further
        fly(5.0, 6.0, 60.0)
        diagnostics(0, math.nan)                           # a new process's count
        fly(6.0, 7.0, 60.0)
        assert sent[-100:] == [2] * 100 and node.resets.count == 2
        # an ekf without diagnostics: require_diagnostics false is enough to send
        node.ekf_status = None
        assert node._health_reason() == "no ekf diagnostics yet"
        node.require_diagnostics = False
        assert node._health_reason() is None
    finally:
        node.destroy_node()
        context.try_shutdown()
