"""autopilot_bridge: the fused estimate to the flight controller, PX4 or ArduPilot (issue 25).

Off in ``config/graph.yaml`` by default (``enabled: false``): start it with
``./tn graph --enable autopilot_bridge`` (``./tn replay --enable autopilot_bridge``,
``ros2 launch ... enable:=autopilot_bridge``) or on its own. ``target`` picks the autopilot.
The frame conversions are :mod:`terrain_nav_ros.core.estimation.autopilot_frames`; the README's
"Flying it" section gives the autopilot's parameters.

Topics
------
Subscribed:

* ``/nav/odometry`` (nav_msgs/Odometry, reliable): the ekf's estimate, pose in ``map``
  (ENU) with the rotation covariance about the map axes, twist in ``base_link`` (FLU).
* ``/nav/ekf/diagnostics`` (diagnostic_msgs/DiagnosticArray): the ekf's ``ekf: filter``
  status tells whether it is initialised, its health (ERROR = lost: no IMU, no fix for too
  long, position sigma too large) and its reset counts.
* ``/nav/fix`` (sensor_msgs/NavSatFix), with ``target: px4`` and ``px4_sensor_gps`` only:
  the same estimate in WGS84 for ``SensorGps``.

Nothing is published while the ekf has not said it is initialised, while its last
diagnostics are older than ``diagnostics_timeout`` or say ERROR (``stop_on_error``), or while
the position sigma (square root of the covariance trace, as the ekf reports it) exceeds
``max_position_sigma``. Nor is an odometry that is not ``map_frame`` -> ``base_frame``, older
than ``max_estimate_age`` by the node's clock, not finite, with a quaternion not of unit
length, a position covariance that is not positive (unknown: zeros or -1) or a position
beyond 10 000 km. Each estimate that is held back is counted by reason in the bridge's
diagnostics.

Published with ``target: px4`` (best effort, transient local, depth 1: PX4's ``/fmu/in``
QoS):

* ``/fmu/in/vehicle_visual_odometry`` (px4_msgs/VehicleOdometry) at up to ``rate`` Hz of
  estimate time: NED position, FRD -> NED quaternion ``[w, x, y, z]``, NED velocity, FRD
  angular rate, position / orientation (about N, E, D) / velocity variances, ``quality``
  100 while the ekf says OK and 50 while it warns, ``timestamp_sample`` = the estimate's
  stamp and ``timestamp`` = the node's clock, both in microseconds. ``reset_counter``
  moves on when the ekf counts a reset (time jump) or position reset, when the position
  jumps by more than ``reset_jump_threshold`` beyond what the velocity explains (a fix
  relocalised the filter), when estimate time runs backwards, and when output resumes
  after being held back.
* ``/fmu/in/sensor_gps`` (px4_msgs/SensorGps), with ``px4_sensor_gps``, at up to
  ``gps_rate`` Hz: the estimate as a GNSS substitute, with its own 1-sigma accuracies,
  ``FIX_TYPE_3D`` while the horizontal accuracy is within ``gps_max_eph`` and
  ``FIX_TYPE_NONE`` beyond, no satellites and unknown DOPs (see
  :func:`~terrain_nav_ros.nodes.conversions.fill_sensor_gps`).

Published with ``target: mavros`` (reliable):

* ``/mavros/odometry/out`` (nav_msgs/Odometry) at up to ``rate`` Hz: the estimate in ENU /
  FLU as MAVROS expects it (MAVROS converts to NED / FRD itself), relabelled
  ``mavros_frame_id`` -> ``mavros_child_frame_id`` (``odom`` -> ``base_link``).
* ``/mavros/vision_pose/pose_cov`` (geometry_msgs/PoseWithCovarianceStamped), with
  ``mavros_vision_pose``: the pose alone, same rate and frame.

Always: ``/autopilot_bridge/diagnostics`` (diagnostic_msgs/DiagnosticArray), every
``diagnostics_period`` s: messages sent per topic, estimates held back by reason, the reset
counter.

Usage::

    .venv/bin/autopilot_bridge --ros-args -p target:=px4
    ./tn graph --config config/graph.yaml --enable autopilot_bridge
"""

from __future__ import annotations

import math
import time
from collections import Counter

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix, NavSatStatus

from ..core.estimation.autopilot_frames import RateLimiter, ResetCounter, horizontal_accuracy
from ..core.estimation.strapdown import quat_to_matrix
from ..core.stamp_order import Order, StampOrder
from . import conversions as cv
from .ros_common import (
    DIAG_ERROR,
    DIAG_OK,
    DIAG_WARN,
    RELIABLE_QOS,
    contained,
    declare,
    new_failures,
    publish_diagnostics,
    reject_all_changes,
    run,
)

TARGETS = ("px4", "mavros")
# What PX4's uXRCE-DDS client subscribes with (PX4's ROS 2 examples publish with it).
PX4_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST)
# VehicleOdometry.quality by the ekf's health (EKF2_EV_QMIN can refuse the lower one).
QUALITY = {DIAG_OK: 100, DIAG_WARN: 50}
# SensorGps velocity taken from an odometry at most this far from the NavSatFix's stamp.
_GPS_VELOCITY_MAX_AGE_S = 0.5
# An estimate further than this from the ENU origin is no position (float32 would not even
# hold it in PX4's message).
_MAX_DISTANCE = 1e7


class AutopilotBridge(Node):
    """/nav/odometry (+ /nav/fix) in the autopilot's messages and frames, when healthy."""

    def __init__(self, **kwargs):
        super().__init__("autopilot_bridge", **kwargs)
        self.target = declare(self, "target", "px4",
                              "px4 (uXRCE-DDS, px4_msgs) | mavros (ArduPilot or PX4 "
                              "through MAVROS)", read_only=True)
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {', '.join(TARGETS)}, "
                             f"not {self.target!r}")
        rate = declare(self, "rate", 30.0, "largest output rate, estimate time [Hz]; "
                       "0 = every odometry", min_value=0.0, max_value=1000.0)
        self.require_diagnostics = declare(
            self, "require_diagnostics", True,
            "send nothing until the ekf's diagnostics say it is initialised")
        self.diagnostics_timeout = declare(
            self, "diagnostics_timeout", 3.0,
            "ekf diagnostics older than this (wall clock) count as missing [s]",
            min_value=0.1)
        self.stop_on_error = declare(self, "stop_on_error", True,
                                     "send nothing while the ekf reports ERROR (lost)")
        self.max_position_sigma = declare(
            self, "max_position_sigma", 200.0,
            "send nothing above this position sigma, sqrt of the covariance trace [m]; "
            "0 = no limit", min_value=0.0)
        jump = declare(self, "reset_jump_threshold", 50.0,
                       "a position step this far beyond the velocity's prediction bumps "
                       "the PX4 reset_counter [m]; 0 = never", min_value=0.0)
        gap = declare(self, "reset_after_gap", 0.5,
                      "estimates further apart than this in estimate time (a respawned ekf, "
                      "output held back) bump the PX4 reset_counter [s]; 0 = never",
                      min_value=0.0)
        self.px4_sensor_gps = declare(self, "px4_sensor_gps", False,
                                      "px4: also publish SensorGps on /fmu/in/sensor_gps")
        gps_rate = declare(self, "gps_rate", 5.0, "px4: largest SensorGps rate [Hz]",
                           min_value=0.0, max_value=100.0)
        self.gps_max_eph = declare(self, "gps_max_eph", 30.0,
                                   "px4: SensorGps says FIX_TYPE_NONE above this horizontal "
                                   "1-sigma accuracy [m]", min_value=0.0)
        self.geoid_undulation = declare(self, "geoid_undulation", 0.0,
                                        "px4: geoid height N, altitude_msl = ellipsoidal - N "
                                        "[m] (the Earth's are within +-110 m)",
                                        min_value=-150.0, max_value=150.0)
        self.mavros_frame_id = declare(self, "mavros_frame_id", "odom",
                                       "mavros: frame of the pose (ENU)")
        self.mavros_child_frame_id = declare(self, "mavros_child_frame_id", "base_link",
                                             "mavros: body frame of the twist (FLU)")
        self.mavros_vision_pose = declare(
            self, "mavros_vision_pose", False,
            "mavros: also publish /mavros/vision_pose/pose_cov")
        self.map_frame = declare(self, "map_frame", "map",
                                 "the frame /nav/odometry must be in (the ekf's map frame)")
        self.base_frame = declare(self, "base_frame", "base_link",
                                  "the child frame /nav/odometry must be of")
        self.max_estimate_age = declare(
            self, "max_estimate_age", 2.0,
            "send nothing older than this by the node's clock (sim time in a replay) [s]; "
            "0 = no limit", min_value=0.0)
        self.max_estimate_lead = declare(
            self, "max_estimate_lead", 0.5,
            "send nothing stamped further than this ahead of the node's clock [s]; 0 = no "
            "limit", min_value=0.0)
        diag_period = declare(self, "diagnostics_period", 1.0,
                              "diagnostics period, wall clock [s]", min_value=0.01,
                              max_value=3600.0)
        self.add_on_set_parameters_callback(reject_all_changes)

        self.limiter = RateLimiter(rate)
        self.gps_limiter = RateLimiter(gps_rate)
        self.resets = ResetCounter(jump, gap)
        self.order = StampOrder()   # odometry stamps: a late one is dropped, a new clock taken
        self.ekf_status = None          # (level, message, values) of "ekf: filter"
        self._ekf_status_wall = None
        self._sending = False           # the last estimate went out
        self._last_odometry = None      # (stamp s, ENU velocity, 3x3 ENU velocity covariance)
        self.sent = Counter()
        self.held_back = Counter()
        self._started_wall = time.monotonic()

        self.pubs = {}
        if self.target == "px4":
            from px4_msgs.msg import SensorGps, VehicleOdometry

            self._odometry_type, self._gps_type = VehicleOdometry, SensorGps
            self.pubs["odometry"] = self.create_publisher(
                VehicleOdometry, "fmu/in/vehicle_visual_odometry", PX4_QOS)
            if self.px4_sensor_gps:
                self.pubs["gps"] = self.create_publisher(SensorGps, "fmu/in/sensor_gps",
                                                         PX4_QOS)
                self.create_subscription(NavSatFix, "nav/fix", self.on_navsatfix,
                                         RELIABLE_QOS)
        else:
            self.pubs["odometry"] = self.create_publisher(Odometry, "mavros/odometry/out",
                                                          RELIABLE_QOS)
            if self.mavros_vision_pose:
                self.pubs["vision_pose"] = self.create_publisher(
                    PoseWithCovarianceStamped, "mavros/vision_pose/pose_cov", RELIABLE_QOS)
        self.create_subscription(Odometry, "nav/odometry", self.on_odometry, RELIABLE_QOS)
        self.create_subscription(DiagnosticArray, "nav/ekf/diagnostics", self.on_diagnostics,
                                 RELIABLE_QOS)
        publish_diagnostics(self, "autopilot_bridge/diagnostics", diag_period,
                            self.diagnostics)
        self.get_logger().info(
            f"target {self.target}: {', '.join(p.topic_name for p in self.pubs.values())} "
            f"at up to {rate:g} Hz")

    # ------------------------------------------------------------------ inputs
    @contained
    def on_diagnostics(self, msg: DiagnosticArray):
        for status in msg.status:
            if status.name == "ekf: filter":
                level, values = cv.diagnostic_values(status)
                self.ekf_status = (level, status.message, values)
                self._ekf_status_wall = time.monotonic()
                resets = sum(int(values.get(key, 0)) for key in (
                    "resets", "position_resets", "relocalisation_resets"))
                at = float(values.get("last_reset_stamp", "nan"))
                if self.resets.observe_filter_resets(resets, at):
                    self.get_logger().info(f"ekf reset (count {resets}): reset_counter "
                                           f"now {self.resets.value}")

    def _health_reason(self) -> str | None:
        """Why the ekf's own word holds every output back (None: it does not)."""
        if self.ekf_status is None:
            missing = "no ekf diagnostics yet"
        elif time.monotonic() - self._ekf_status_wall > self.diagnostics_timeout:
            missing = "ekf diagnostics stale"
        else:
            missing = None
        if missing is not None:   # (without require_diagnostics, no word is no ERROR)
            return missing if self.require_diagnostics else None
        level, _message, values = self.ekf_status
        if self.require_diagnostics and values.get("initialized") != "True":
            return "ekf not initialised"
        if self.stop_on_error and level >= DIAG_ERROR:
            return "ekf reports " + ("ERROR" if level == DIAG_ERROR else "STALE")
        return None

    def _hold_back_reason(self, msg: Odometry, t: float, pose_cov: np.ndarray, position,
                          quaternion, *twist) -> str | None:
        """Why this estimate must not reach the autopilot (None: it may)."""
        if (msg.header.frame_id, msg.child_frame_id) != (self.map_frame, self.base_frame):
            return (f"odometry in {msg.header.frame_id or '(none)'} -> "
                    f"{msg.child_frame_id or '(none)'}, not {self.map_frame} -> "
                    f"{self.base_frame}")
        if not all(np.isfinite(a).all() for a in (position, quaternion, pose_cov, *twist)):
            return "non-finite estimate"
        if abs(float(np.linalg.norm(quaternion)) - 1.0) > 1e-3:
            return "quaternion not of unit length"
        if not (np.diag(pose_cov)[:3] > 0).all():
            return "position covariance not positive (unknown)"
        if float(np.max(np.abs(position))) > _MAX_DISTANCE:
            return "position beyond 10 000 km"
        now = self.get_clock().now().nanoseconds * 1e-9
        if self.max_estimate_age > 0 and now > 0 and now - t > self.max_estimate_age:
            return "estimate older than max_estimate_age"
        if self.max_estimate_lead > 0 and now > 0 and t - now > self.max_estimate_lead:
            return "estimate stamped ahead of the node's clock (max_estimate_lead)"
        health = self._health_reason()
        if health is not None:
            return health
        sigma = math.sqrt(max(float(np.trace(pose_cov[:3, :3])), 0.0))
        if self.max_position_sigma > 0 and not sigma <= self.max_position_sigma:
            return "position sigma above max_position_sigma"
        return None

    @contained
    def on_odometry(self, msg: Odometry):
        t, position, q, pose_cov, linear, angular, twist_cov = cv.odometry_to_state(msg)
        reason = self._hold_back_reason(msg, t, pose_cov, position, q, linear, angular,
                                        twist_cov)
        if reason is not None:
            self.held_back[reason] += 1
            if self._sending:
                self.get_logger().warning(f"output stopped: {reason}")
            self._sending = False
            self._last_odometry = None
            return
        if self.order.check(t) == Order.BEHIND:
            # a late one (PX4 drops a sample older than its newest, and the next would then
            # be a reset): not sent, and it stops nothing; three in a row that go on are a
            # new clock (a bag loop), taken
            self.held_back["estimate not after the last one (late, out of order)"] += 1
            return
        if not self._sending:   # (a gap or jump since the last one sent bumps the counter)
            self.limiter.reset()
            self.get_logger().info(f"output to {self.target} (re)started, reset_counter "
                                   f"{self.resets.value}")
            self._sending = True
        r = quat_to_matrix(q)
        velocity_enu = r @ linear
        self._last_odometry = (t, velocity_enu, r @ twist_cov[:3, :3] @ r.T)
        if self.resets.observe_pose(t, position, velocity_enu):
            self.get_logger().info(f"estimate jumped at {t:.3f} s: reset_counter now "
                                   f"{self.resets.value}")
        if not self.limiter.ready(t):
            return
        stamp_ns = cv.stamp_to_ns(msg.header.stamp)
        if self.target == "px4":
            out = cv.fill_vehicle_odometry(
                self._odometry_type(), stamp_ns, self.get_clock().now().nanoseconds, position,
                q, pose_cov, linear, angular, twist_cov, self.resets.value,
                QUALITY.get(self.ekf_status[0] if self.ekf_status else DIAG_WARN, 50))
            self._publish("odometry", out)
            return
        header = cv.make_header(msg.header.stamp, self.mavros_frame_id)
        self._publish("odometry", Odometry(header=header,
                                           child_frame_id=self.mavros_child_frame_id,
                                           pose=msg.pose, twist=msg.twist))
        if "vision_pose" in self.pubs:
            self._publish("vision_pose", PoseWithCovarianceStamped(header=header,
                                                                   pose=msg.pose))

    @contained
    def on_navsatfix(self, msg: NavSatFix):
        """SensorGps from the ekf's NavSatFix, while the odometry goes out."""
        # the ekf's word counts at once: a NavSatFix may come before the next odometry
        if not self._sending or self._last_odometry is None or self._health_reason():
            return
        stamp, status, lla, cov, cov_type = cv.navsatfix_to_arrays(msg)
        if not (np.isfinite(lla).all() and np.isfinite(cov).all()):
            self.held_back["non-finite NavSatFix"] += 1
            return
        if status < NavSatStatus.STATUS_FIX or cov_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN:
            # (the ekf always sends a fix with its covariance: another publisher's is not
            # passed on as a 3D fix of zero error)
            self.held_back["NavSatFix without a fix or its covariance"] += 1
            return
        if not self.gps_limiter.ready(stamp):
            return
        t_odom, velocity, velocity_cov = self._last_odometry
        fresh = abs(stamp - t_odom) <= _GPS_VELOCITY_MAX_AGE_S
        gps = self._gps_type
        fix_type = gps.FIX_TYPE_3D if horizontal_accuracy(cov) <= self.gps_max_eph \
            else gps.FIX_TYPE_NONE
        out = cv.fill_sensor_gps(gps(), cv.stamp_to_ns(msg.header.stamp), *lla,
                                 self.geoid_undulation, cov, velocity if fresh else None,
                                 velocity_cov, fix_type)
        self._publish("gps", out)

    def _publish(self, key: str, msg):
        self.pubs[key].publish(msg)
        self.sent[self.pubs[key].topic_name] += 1

    # ------------------------------------------------------------------ health
    def diagnostics(self) -> list:
        """Messages sent and estimates held back so far; WARN while nothing goes out."""
        level, problems = DIAG_OK, []
        failures, new = new_failures(self)
        if new:
            level = DIAG_ERROR
            problems.append(f"{new} message(s) failed in a callback: see the log")
        if not self._sending:
            level = max(level, DIAG_WARN)
            last = self.held_back.most_common(1)
            problems.append("not sending" + (f": {last[0][0]}" if last else
                                             ": no /nav/odometry yet"))
        values = {"target": self.target, "sending": self._sending,
                  "reset_counter": self.resets.value, "resets": self.resets.count,
                  "failures": failures}
        values.update({f"sent: {topic}": n for topic, n in sorted(self.sent.items())})
        values.update({f"held back: {why}": n for why, n in self.held_back.most_common()})
        return [cv.diagnostic_status("autopilot_bridge", level,
                                     "; ".join(problems) or f"sending to {self.target}",
                                     values, "terrain_nav")]


def main(args=None):
    return run(AutopilotBridge, args)


if __name__ == "__main__":
    raise SystemExit(main())
