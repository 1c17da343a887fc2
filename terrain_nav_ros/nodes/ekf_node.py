"""ekf: IMU dead reckoning fused with terrain fixes, barometer and (optionally) GNSS (issue 7).

A thin adapter around :class:`terrain_nav_ros.core.estimation.ekf.TerrainEkf` (error-state strapdown
EKF with position, velocity, attitude, gyro and accelerometer biases; chi-square gating; delayed
fixes). Every stamp comes from the messages, so the node behaves the same live, from a bag played at
any rate, and with ``use_sim_time``. What the node decides is ROS-free beside the filter: the
inputs (fix pose and covariance, GNSS and baro refusals, the baro offset, the ENU origin
handshake) in :mod:`terrain_nav_ros.core.estimation.ekf_inputs`, the diagnostics' content and
the throttled refusal logs in :mod:`terrain_nav_ros.core.estimation.ekf_health`.

Topics
------
Subscribed:

* ``/imu/data`` (sensor_msgs/Imu, best effort, depth ``imu_queue_depth``): angular velocity
  and specific force in ``base_link`` (FLU; an IMU mounted otherwise must be rotated first).
  Every sample is integrated; NaN samples, duplicates and small backward steps are refused.
  The first second's mean specific force must look like gravity in FLU (+g on z): an FRD /
  NED frame, the acceleration in g or milli-g, or axes turned off body z refuse the stream
  for good, with the reason logged and in the diagnostics (ERROR), the filter reset
  (:class:`~terrain_nav_ros.core.estimation.ekf_inputs.ImuConvention`). So does a gyro
  that reads many times the turn rate the specific force and speed imply in a turn (deg/s
  for rad/s: :class:`~terrain_nav_ros.core.estimation.ekf_inputs.GyroScale`).
  A stamp more than ``time_jump_reset`` from the previous one, back or ahead, is refused and
  counted (one bad stamp must not end navigation); when ``time_jump_confirm`` samples in a
  row go on from it (bag loop, simulator restart) the filter resets and re-initialises per
  ``init_mode``, or from its last good state when that source stays silent for
  ``reinit_timeout`` s (GNSS denied).
* ``/nav/pva_fix`` (terrain_nav_msgs/PvaFix, reliable): the position always, the attitude
  when ``status == STATUS_POSITION_ATTITUDE``, the velocity when ``velocity_valid``.
  ``STATUS_NO_FIX`` messages are counted (diagnostics), not fused. The pose is the body's
  (``fix_pose_frame: base_link``, what the matcher publishes), or a camera's
  (``camera_optical``: optical centre, optical-frame orientation) moved to ``base_link`` with
  ``camera_mount_rpy`` and ``camera_lever_arm``, for matchers that publish camera poses.
  A fix from a frame projected onto the ground (``projection_height`` > 0) moves with the
  attitude's error and with the camera mount's, which the filter estimates
  (``init_camera_mount_sigma``; ``camera_mount_*_deg`` in the diagnostics). Its height,
  measured by the registration's scale, carries the camera's scale error, estimated too
  (``init_camera_scale_sigma``; ``camera_scale_*percent``). A fix from a track mosaic
  (``mosaic_lag`` > 0: its frames' mean age) carries the velocity's error over that time,
  which the update models. A terrain fix is where the DEM puts the aircraft: it carries the
  DEM's georeferencing error, the map bias, which the filter estimates where GNSS meets the
  fixes and then takes out of them (``init_map_bias_sigma``; ``map_bias_*_m`` in the
  diagnostics).
  Late and out-of-order fixes are applied at their own stamp by the core (state history of
  ``history_length`` s). A fix marked ``relocalisation`` (found by a search of the whole
  mission area) is fused when the gate accepts it; otherwise it is held, and the position
  is reset onto it (or, with ``init_mode: fix`` and no estimate yet, the filter starts from
  it) only when another relocalisation from a frame ``relocalisation_min_interval`` s or
  more apart agrees with the IMU's motion between them
  (:mod:`~terrain_nav_ros.core.estimation.relocalisation`).
* ``/ekf/set_pose`` (geometry_msgs/PoseWithCovarianceStamped, reliable, ``map_frame``): an
  operator's re-seed of the position (robot_localization's ``set_pose``; the orientation is
  not used), applied at its stamp without a gate.
* ``/baro/pressure`` (sensor_msgs/FluidPressure): ISA pressure altitude
  (:mod:`~terrain_nav_ros.core.estimation.baro`, ``sea_level_pressure``) plus an offset to
  ENU up: ``baro_offset`` or, when that is NaN, learnt once: the filter's own height at the
  first baro sample after its vertical sigma fell below ``baro_offset_max_sigma`` (from GNSS,
  the initial pose or fixes). It is forgotten and learnt again after a time-jump reset. What
  the offset gets wrong, and the weather's drift, the filter estimates as its baro-bias state
  (``init_baro_bias_sigma``, ``baro_bias_random_walk``; ``baro_bias_m`` in the
  diagnostics). The filter refuses a baro height repeated bit for bit ten times in a row (a
  stuck sensor) and takes the jump of a baro that steps off its later heights (logged;
  ``baro_step_m`` in the diagnostics).
* ``/gnss/fix`` (sensor_msgs/NavSatFix, optional): to initialise (``init_mode: gnss``), fused
  while available (``fuse_gnss: true``) or only scored against the estimate
  (``fuse_gnss: false``: NIS in the diagnostics). ``STATUS_NO_FIX`` and NaN are refused.
  Converted to the mission ENU frame with :class:`~terrain_nav_ros.core.terrain.geodesy.EnuOrigin`.
* ``/metamap/tile`` (terrain_nav_msgs/DemTile, latched), only while the ENU origin is
  unknown: with ``origin_latitude``/``origin_longitude`` NaN the origin is taken from the
  first tile's georeference (the metamap's origin, so both agree by construction) and the
  subscription is dropped. The metamap publishes tiles only around an odometry, so the node
  also asks its ``/metamap/get_tile`` service once a second for a 1-pixel tile at the ENU
  origin (whose georeference carries the origin): with ``init_mode: gnss`` there would be no
  odometry without the origin otherwise. Until then GNSS is refused and no NavSatFix is
  published; fixes, IMU and baro need no origin.

Published:

* ``/nav/odometry`` (nav_msgs/Odometry): pose of ``base_frame`` in ``map_frame`` with the
  6x6 covariance (position, rotation about the map axes), twist in ``base_frame`` (REP 105:
  body-frame velocity, bias-corrected angular rate), every ``1/odometry_rate`` s of filter
  time (0 = every IMU sample).
* ``/tf`` (tf2_msgs/TFMessage): ``map_frame`` -> ``base_frame`` with each odometry
  (``publish_tf``). No ``odom`` frame: this filter is the absolute (map) estimator.
* ``/nav/fix`` (sensor_msgs/NavSatFix): the estimate in WGS84 with its ENU position
  covariance, every ``1/navsatfix_rate`` s of filter time.
* ``/nav/ekf/diagnostics`` (diagnostic_msgs/DiagnosticArray), every
  ``diagnostics_period`` s of wall time: ``ekf: filter`` (health OK/WARN/ERROR, time since
  the last fix, position sigma, covariance trace, the wind estimate, resets, tilt and
  heading drifts found, input rejections per
  ``source:reason``, the navigation state ``lost`` / ``searching`` / ``found`` / ``tracking``
  with when and by how much the last reset onto relocalisations moved the position; each
  change of state is logged once) and one status per measurement source (``ekf: fix``,
  ``ekf: baro``, ``ekf: gnss``, ``ekf: level``, ``ekf: sideslip``) with accepted/rejected
  counts, the NIS of every update
  since the previous report (``nis``), the last NIS, the gate and the mean NIS over the
  recent window (consistent filter: about the measurement dimension ``dof``).

Checkpoint (:mod:`~terrain_nav_ros.core.estimation.checkpoint`): every ``checkpoint_period``
s of filter time the estimate is written to ``checkpoint_file`` (default: the graph run's
folder, ``$TERRAIN_NAV_RUN_DIR``; "none": never). A node started again after a crash that
finds one at most ``checkpoint_max_age`` s older than its first IMU sample resumes from it
(carried across the gap, its covariance grown for a manoeuvre in it) before its
``init_mode`` source is considered; the baro offset comes with it. One from another run
(older, later, or of another ENU origin) is left alone, said once in the log.

Parameters: every :class:`~terrain_nav_ros.core.estimation.ekf_params.EkfParams` field under its own
name, plus the node's own (frames, rates, origin, baro, mount, initial pose, health
thresholds, checkpoint, ``executor``); ``config/ekf.yaml`` explains each. Parameters apply
at start-up only. The node is spun by rclpy's ``EventsExecutor`` by default (``executor:
events``): with the default executor, rclpy's per-message wait-set work alone used more CPU
than the target of 10 % of a core at a 200 Hz IMU (``benchmarks/bench_ekf_node.py``).

Usage::

    .venv/bin/ekf --ros-args --params-file config/ekf.yaml
    ./tn graph --config config/graph.yaml          # with the rest of the graph
    .venv/bin/ekf --ros-args -p init_mode:=pose -p initial_position:=[0.,0.,500.] \\
        -p initial_velocity:=[30.,0.,0.] -p initial_rpy:=[0.,0.,0.] -p use_sim_time:=true
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import fields

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import FluidPressure, Imu, NavSatFix, NavSatStatus
from tf2_msgs.msg import TFMessage

from terrain_nav_msgs.msg import DemTile, PvaFix
from terrain_nav_msgs.srv import GetDemTile

from ..core.camera.camera_mount import mount_rotation
from ..core.estimation.baro import SEA_LEVEL_PRESSURE, altitude_sigma, pressure_to_altitude
from ..core.estimation.checkpoint import (
    Checkpoint,
    CheckpointError,
    checkpoint_path,
    load_checkpoint,
    resume_from,
    save_checkpoint,
)
from ..core.estimation.ekf import (
    EkfParams,
    Outcome,
    Reason,
    TerrainEkf,
    is_positive_definite,
)
from ..core.estimation.ekf_health import (
    SOURCES,
    HealthLimits,
    NavigationLog,
    NewRecords,
    RefusalLog,
    SourceUse,
    filter_health,
    filter_values,
    gated_records,
    navigation_state,
    source_report,
)
from ..core.estimation.ekf_inputs import (
    BaroOffset,
    FixFrame,
    GyroScale,
    ImuConvention,
    OriginHandshake,
    baro_refusal,
    fix_covariance,
    gnss_covariance,
    gnss_refusal,
)
from ..core.estimation.strapdown import quat_from_euler, quat_to_matrix
from ..core.terrain.geodesy import EnuOrigin
from . import conversions as cv
from .ros_common import (
    DIAG_OK,
    EVENTS_EXECUTOR,
    LATCHED_QOS,
    RELIABLE_QOS,
    contained,
    declare,
    declare_executor,
    new_failures,
    publish_diagnostics,
    reject_all_changes,
    run,
)

# EkfParams field -> (description with unit, min, max); mapped 1:1 to ROS parameters.
EKF_PARAMETERS = {
    "gravity": ("magnitude of gravity, along -z of the map frame [m/s^2]", 9.7, 9.9),
    "gyro_noise_density": ("gyro white noise (angle random walk) [rad/s/sqrt(Hz)]", 1e-9, 1.0),
    "accel_noise_density": ("accelerometer white noise (velocity random walk) "
                            "[m/s^2/sqrt(Hz)]", 1e-9, 10.0),
    "gyro_bias_random_walk": ("gyro bias random walk [rad/s^2/sqrt(Hz)]", 0.0, 1.0),
    "accel_bias_random_walk": ("accelerometer bias random walk [m/s^3/sqrt(Hz)]", 0.0, 10.0),
    "init_position_sigma": ("1-sigma initial position uncertainty (pose init) [m]", 1e-3, 1e5),
    "init_velocity_sigma": ("1-sigma initial velocity uncertainty [m/s]", 1e-3, 1e3),
    "init_roll_pitch_sigma": ("1-sigma initial roll/pitch uncertainty [rad]", 1e-5, 3.2),
    "init_yaw_sigma": ("1-sigma initial yaw uncertainty [rad]", 1e-5, 3.2),
    "init_gyro_bias_sigma": ("1-sigma gyro turn-on bias [rad/s]", 0.0, 1.0),
    "init_accel_bias_sigma": ("1-sigma accelerometer turn-on bias [m/s^2]", 0.0, 10.0),
    "init_mode": ("pose | gnss | fix: what starts the filter", None, None),
    "init_min_fix_interval": ("init from fixes without velocity: time between the two "
                              "fixes used [s]", 0.0, 600.0),
    "init_max_speed": ("init from fixes without velocity: a pair further apart than this "
                       "speed allows starts nothing [m/s]", 1.0, 1e4),
    "fix_gate_probability": ("chi-square gate probability for terrain fixes; 1 = no gate",
                             1e-6, 1.0),
    "baro_gate_probability": ("chi-square gate probability for baro altitude", 1e-6, 1.0),
    "gnss_gate_probability": ("chi-square gate probability for GNSS", 1e-6, 1.0),
    "fuse_gnss": ("fuse GNSS (true) or only initialise from it and score it (false)",
                  None, None),
    "reset_after_rejections": ("consecutive gated-out fixes (or GNSS) before a position "
                               "reset to the next one; 0 = never", 0, 1000),
    "history_length": ("state/IMU history for delayed measurements [s]", 0.01, 60.0),
    "max_future": ("measurements up to this far ahead of the IMU are queued [s]", 0.0, 10.0),
    "time_jump_reset": ("an IMU stamp this far from the previous one (either way) is "
                        "refused, or resets the filter when the stream goes on from it [s]",
                        1e-3, 3600.0),
    "time_jump_confirm": ("consecutive samples that confirm a time jump", 1, 1000),
    "max_imu_outage": ("a confirmed jump ahead up to this long is integrated as an IMU gap, "
                       "not a reset [s]", 0.0, 3600.0),
    "reinit_timeout": ("after a reset without the init source for this long, restart from "
                       "the last good state [s]", 0.0, 600.0),
    "max_imu_dt": ("IMU intervals longer than this are flagged as gaps [s]", 1e-4, 10.0),
    "nis_history_length": ("NIS records kept for the diagnostics", 1, 100000),
    "relocalisation_agreement_probability": (
        "two relocalisations agree when their displacement minus the dead-reckoned one is "
        "inside this chi-square probability (3 dof); only then does the filter move onto them",
        1e-6, 0.999999999),
    "relocalisation_timeout": ("a held relocalisation expires this long after its stamp [s]",
                               0.01, 3600.0),
    "relocalisation_min_interval": ("relocalisations closer in time than this never agree "
                                    "with each other [s]", 0.0, 600.0),
    "relocalisation_fuse_max_sigma": ("a relocalisation inside the gate is fused on its own "
                                      "only while the horizontal sigma is at most this [m]",
                                      1e-3, 1e7),
    "level_sigma": ("1-sigma of the tilt the accelerometer levelling measures (the specific "
                    "force less the turn, over level_period) beyond the samples' own noise, "
                    "which is measured and added; 0 = no levelling [rad]",
                    0.0, 1.0),
    "level_period": ("the levelling sums the specific force over this long [s]", 0.01, 60.0),
    "level_gate_probability": ("chi-square gate probability for the levelling", 1e-6, 1.0),
    "init_wind_sigma": ("1-sigma of each horizontal wind component at start; the wind "
                        "starts at zero [m/s]", 1e-3, 100.0),
    "wind_random_walk": ("how fast the wind may change, per component [m/s/sqrt(s)]",
                         0.0, 10.0),
    "init_baro_bias_sigma": ("1-sigma of the baro bias at start: the error of the offset "
                             "that puts pressure altitude into ENU up [m]", 1e-3, 1e4),
    "init_camera_mount_sigma": ("1-sigma of the camera mount's error about body x and y at "
                                "start: how well camera_mount_rpy points the camera [rad]",
                                1e-6, 0.5),
    "camera_mount_random_walk": ("how fast the camera mount's error may change "
                                 "[rad/sqrt(s)]", 0.0, 0.01),
    "init_camera_scale_sigma": ("1-sigma of the camera's scale error at start: how far a "
                                "ground match's height above its plane may be off, in "
                                "proportion [-]", 1e-6, 0.5),
    "camera_scale_random_walk": ("how fast the camera's scale error may change [1/sqrt(s)]",
                                 0.0, 0.01),
    "init_map_bias_sigma": ("1-sigma of the map bias per horizontal axis at start: how far "
                            "the DEM, and so every terrain fix, may be off its true place "
                            "[m]", 1e-3, 1e4),
    "map_bias_random_walk": ("how fast the map bias may change over the area flown "
                             "[m/sqrt(s)]", 0.0, 100.0),
    "baro_bias_random_walk": ("how fast the baro bias may change (weather: ~8 m per hPa) "
                              "[m/sqrt(s)]", 0.0, 100.0),
    "sideslip_sigma": ("1-sigma of the sideslip, measured as zero (coordinated flight of a "
                       "fixed wing); 0 = not measured [m/s]", 0.0, 100.0),
    "sideslip_gate_probability": ("chi-square gate probability for the sideslip", 1e-6, 1.0),
    "relocalisation_speed_sigma": ("cold start: sigma of the speed prior the displacement "
                                   "between two relocalisations is tested against [m/s]",
                                   1e-3, 1e4),
}
assert set(EKF_PARAMETERS) == {f.name for f in fields(EkfParams)}, "map every EkfParams field"

# An origin request unanswered this long is sent again (core.estimation.ekf_inputs).
_ORIGIN_RESEND_S = 5.0
# Depth of the best-effort baro and GNSS subscriptions: 1 s of a 10 Hz baro, 2 s of 5 Hz GNSS.
_AIDING_QUEUE_DEPTH = 10
# Reasons that are normal operation, not worth a warning.
_QUIET = {Reason.OK, Reason.INITIALIZED, Reason.QUEUED, Reason.WAITING_FOR_INIT,
          Reason.IMU_GAP, Reason.POSITION_RESET, Reason.COMPARED_ONLY, Reason.NOT_INITIALIZED,
          Reason.GATED,   # gate rejections are logged from the diagnostics records (queued
                          # fixes are gated later, when the IMU reaches their stamp)
          Reason.RELOCALISATION_HELD, Reason.RELOCALISATION_RESET}   # navigation state log


class EkfNode(Node):
    """ROS adapter of :class:`TerrainEkf`: messages in, odometry/TF/NavSatFix/diagnostics out."""

    def __init__(self):
        super().__init__("ekf")
        defaults = EkfParams()
        values = {}
        for name, (text, lo, hi) in EKF_PARAMETERS.items():
            values[name] = declare(self, name, getattr(defaults, name), text,
                                   min_value=lo, max_value=hi)
        self.params = EkfParams(**values)

        self.map_frame = declare(self, "map_frame", "map", "frame of the pose (REP 105)")
        self.base_frame = declare(self, "base_frame", "base_link", "body frame (FLU)")
        self.publish_tf = declare(self, "publish_tf", True, "broadcast map_frame -> base_frame")
        odom_rate = declare(self, "odometry_rate", 50.0,
                            "odometry/TF rate in filter time [Hz]; 0 = every IMU sample",
                            min_value=0.0, max_value=10000.0)
        navsat_rate = declare(self, "navsatfix_rate", 10.0,
                              "NavSatFix rate in filter time [Hz]; 0 = never",
                              min_value=0.0, max_value=10000.0)
        diag_period = declare(self, "diagnostics_period", 1.0,
                              "diagnostics period, wall clock [s]", min_value=0.01)
        imu_depth = declare(self, "imu_queue_depth", 100,
                            "IMU subscription depth (best effort) [messages]; the baro's and "
                            "GNSS's are 10",
                            min_value=1, max_value=10000)
        lat = declare(self, "origin_latitude", math.nan,
                      "ENU origin latitude [deg WGS84]; NaN = the metamap's (tile/service)")
        lon = declare(self, "origin_longitude", math.nan, "ENU origin longitude [deg WGS84]")
        alt = declare(self, "origin_altitude", 0.0, "ENU origin ellipsoidal height [m]")
        self.sea_level_pressure = declare(self, "sea_level_pressure", SEA_LEVEL_PRESSURE,
                                          "ISA reference pressure for baro altitude [Pa]",
                                          min_value=80000.0, max_value=110000.0)
        self.baro_offset_param = declare(self, "baro_offset", math.nan,
                                         "ENU up minus pressure altitude [m]; NaN = learn")
        self.baro_offset_max_sigma = declare(self, "baro_offset_max_sigma", 10.0,
                                             "learn the baro offset once the filter's "
                                             "vertical sigma is below this [m]", min_value=0.0)
        self.baro_sigma = declare(self, "baro_altitude_sigma", 2.0,
                                  "floor of the baro altitude sigma [m]", min_value=0.01)
        self.gnss_fallback_sigma = declare(
            self, "gnss_fallback_sigma", [3.0, 3.0, 6.0],
            "GNSS E/N/U sigma when the fix says COVARIANCE_TYPE_UNKNOWN [m]")
        self.fix_pose_frame = declare(self, "fix_pose_frame", "base_link",
                                      "camera_optical | base_link: what the PvaFix pose is of")
        mount_rpy = declare(self, "camera_mount_rpy", [0.0, 0.0, 0.0],
                            "nadir camera mount tilt roll, pitch, yaw (FLU) [rad]")
        self.lever_arm = np.array(declare(self, "camera_lever_arm", [0.0, 0.0, 0.0],
                                          "camera optical centre in base_link [m]"), float)
        init_pos = declare(self, "initial_position", [0.0, 0.0, 0.0],
                           "init_mode=pose: ENU position [m]")
        init_vel = declare(self, "initial_velocity", [0.0, 0.0, 0.0],
                           "init_mode=pose: ENU velocity [m/s]")
        init_rpy = declare(self, "initial_rpy", [0.0, 0.0, 0.0],
                           "init_mode=pose: roll, pitch, yaw (ENU, yaw CCW from east) [rad]")
        self.health_limits = HealthLimits(
            fix_warn=declare(self, "diag_fix_timeout_warn", 30.0,
                             "WARN after this long without an accepted fix/GNSS "
                             "(filter time) [s]", min_value=0.0),
            fix_error=declare(self, "diag_fix_timeout_error", 120.0,
                              "ERROR after this long without an accepted fix [s]",
                              min_value=0.0),
            sigma_warn=declare(self, "diag_position_sigma_warn", 50.0,
                               "WARN above this position sigma [m]", min_value=0.0),
            sigma_error=declare(self, "diag_position_sigma_error", 200.0,
                                "ERROR above this position sigma [m]", min_value=0.0),
            imu_timeout=declare(self, "diag_imu_timeout", 1.0,
                                "ERROR when no IMU arrived for this long (wall) [s]",
                                min_value=0.0),
            lost_sigma=declare(self, "diag_lost_horizontal_sigma", 1000.0,
                               "navigation state 'lost' above this horizontal position sigma "
                               "[m]", min_value=0.0))
        checkpoint_file = declare(self, "checkpoint_file", "",
                                  "where the estimate is kept for a restarted node; '' = the "
                                  "graph run's folder ($TERRAIN_NAV_RUN_DIR), 'none' = nowhere")
        self.checkpoint_period = declare(self, "checkpoint_period", 0.2,
                                         "checkpoint every this long of filter time [s]",
                                         min_value=0.01)
        self.checkpoint_max_age = declare(self, "checkpoint_max_age", 10.0,
                                          "resume from a checkpoint at most this old at the "
                                          "first IMU sample [s]", min_value=0.0)
        log_throttle = declare(self, "log_throttle", 5.0,
                               "minimum time between two logs of one reason [s]",
                               min_value=0.0)
        # rclpy's default executor costs more CPU per IMU message than the filter (issue 7).
        declare_executor(self, EVENTS_EXECUTOR)
        self.add_on_set_parameters_callback(reject_all_changes)
        FixFrame.checked_pose_frame(self.fix_pose_frame)
        for name, vec in (("initial_position", init_pos), ("initial_velocity", init_vel),
                          ("initial_rpy", init_rpy), ("camera_mount_rpy", mount_rpy),
                          ("camera_lever_arm", self.lever_arm),
                          ("gnss_fallback_sigma", self.gnss_fallback_sigma)):
            if len(vec) != 3 or not np.isfinite(vec).all():
                raise ValueError(f"{name} needs 3 finite values, got {list(vec)}")

        # Camera optical -> body: R_enu_body = R_enu_optical @ R_body_optical^T.
        self.fix_frame = FixFrame(self.fix_pose_frame,
                                  Rotation.from_matrix(mount_rotation(*mount_rpy)).inv(),
                                  self.lever_arm)
        self.ekf = TerrainEkf(self.params)
        if self.params.init_mode == "pose":
            self.ekf.set_initial_pose(np.array(init_pos, float), np.array(init_vel, float),
                                      quat_from_euler(*init_rpy))
        self._origin = OriginHandshake(
            EnuOrigin(lat, lon, alt) if math.isfinite(lat) and math.isfinite(lon) else None,
            resend_after=_ORIGIN_RESEND_S)
        self._tile_sub = self._origin_client = self._origin_timer = None
        self._origin_future = None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if self.origin is None:
            self._tile_sub = self.create_subscription(DemTile, "metamap/tile", self.on_tile,
                                                      LATCHED_QOS)
            self._origin_client = self.create_client(GetDemTile, "metamap/get_tile")
            self._origin_timer = self.create_timer(1.0, self._ask_origin, clock=steady)
        self.baro = BaroOffset(self.baro_offset_param, self.baro_offset_max_sigma)
        self.baro_use = SourceUse()
        self._baro_steps_logged = 0

        # 0.1 ms slack: epoch stamps as float seconds carry ~0.2 us of rounding, and a 20 ms
        # period over 10 ms samples must not turn into every third sample.
        self._odom_period = 1.0 / odom_rate - 1e-4 if odom_rate > 0 else 0.0
        self._navsat_period = 1.0 / navsat_rate - 1e-4 if navsat_rate > 0 else math.inf
        self._last_odom = self._last_navsat = -math.inf
        self._gyro = (0.0, 0.0, 0.0)
        self._imu_dt = 0.01      # running mean of the IMU period, for the twist covariance
        self._prev_imu_t = None
        self._imu_count = 0
        self._imu_span = None    # (first, last) IMU stamp since start or reset
        self._last_imu_wall = None
        self._started_wall = time.monotonic()
        self.rejections = Counter()        # refused by the node before reaching the core
        self.no_fix_count = 0
        self._refusal_log = RefusalLog(log_throttle)
        self._new_records = NewRecords()
        self._stamps_reported = 0
        self._init_stamp = None
        self._navigation = NavigationLog()
        self._checkpoint_path = checkpoint_path(checkpoint_file)
        self._last_checkpoint = -math.inf
        self._checkpoint_failed = False
        self._resume = self._read_checkpoint()
        self.imu_convention = ImuConvention(self.params.gravity)
        self.gyro_scale = GyroScale(self.params.gravity)

        imu_qos = QoSProfile(depth=imu_depth, reliability=ReliabilityPolicy.BEST_EFFORT,
                             history=HistoryPolicy.KEEP_LAST)
        # No default QoS-event handlers on the outputs: each is one more waitable the
        # executor polls per IMU sample (~1 % of a core at 200 Hz for the four), and an
        # incompatible subscriber logs the mismatch on its own side.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self.odom_pub = self.create_publisher(Odometry, "nav/odometry", RELIABLE_QOS,
                                              event_callbacks=quiet)
        self.tf_pub = self.create_publisher(TFMessage, "/tf", 100, event_callbacks=quiet) \
            if self.publish_tf else None
        self.navsat_pub = self.create_publisher(NavSatFix, "nav/fix", RELIABLE_QOS,
                                                event_callbacks=quiet)
        self.create_subscription(Imu, "imu/data", self.on_imu, imu_qos)
        self.create_subscription(PvaFix, "nav/pva_fix", self.on_pva_fix, RELIABLE_QOS)
        self.create_subscription(PoseWithCovarianceStamped, "ekf/set_pose", self.on_set_pose,
                                 RELIABLE_QOS)
        # The aiding sensors' queues hold about as long as the IMU's, not 10-20 s: a node
        # short of CPU follows the IMU, and baro heights or GNSS fixes queued longer than
        # the history would all come too late and be refused as stale.
        aiding_qos = QoSProfile(depth=_AIDING_QUEUE_DEPTH,
                                reliability=ReliabilityPolicy.BEST_EFFORT,
                                history=HistoryPolicy.KEEP_LAST)
        self.create_subscription(FluidPressure, "baro/pressure", self.on_baro, aiding_qos)
        self.create_subscription(NavSatFix, "gnss/fix", self.on_gnss, aiding_qos)
        self.publish_diagnostics_now = publish_diagnostics(self, "nav/ekf/diagnostics",
                                                           diag_period, self.diagnostics)
        self._resets_published = 0            # resets counted up to the last odometry
        self._last_reset_stamp = math.nan     # estimate time of the first one after a reset
        origin = "from the metamap (tile or get_tile)" if self.origin is None else \
            f"{self.origin.lat:.6f}, {self.origin.lon:.6f}, {self.origin.alt:.1f} m"
        self.get_logger().info(f"init_mode={self.params.init_mode}, ENU origin {origin}, "
                               f"fuse_gnss={self.params.fuse_gnss}")

    # ------------------------------------------------------------------ logging
    @property
    def origin(self) -> EnuOrigin | None:
        """The mission's ENU origin (None until the metamap gave it)."""
        return self._origin.origin

    @property
    def baro_offset(self) -> float | None:
        """ENU up minus pressure altitude (None until learnt)."""
        return self.baro.value

    def _log_refusal(self, key: str, text: str, level: str = "warning"):
        """Log at most once per ``log_throttle`` s per key, saying how many were skipped."""
        text = self._refusal_log.text(key, text, time.monotonic())
        if text is None:
            return
        # rclpy fixes the severity per call site: one call per severity.
        if level == "info":
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    def _refuse(self, source: str, reason: str, detail: str = ""):
        self.rejections[f"{source}:{reason}"] += 1
        self._log_refusal(f"{source}:{reason}", f"{source} refused: {reason}{detail}")

    def _report(self, source: str, out: Outcome, stamp: float | None = None):
        """Log a core refusal (throttled per reason)."""
        if out.reason == Reason.INITIALIZED:
            self._init_stamp = stamp
            self.get_logger().info(f"initialised from {source} at {stamp:.3f} s")
            return
        if out.reason in _QUIET:
            if out.reason == Reason.NOT_INITIALIZED:
                # a warning once it takes longer than a fix may: GNSS lost before the
                # second fix leaves the filter waiting for good
                waited = self._imu_span[1] - self._imu_span[0] if self._imu_span else 0.0
                self._log_refusal("not_initialized",
                                  f"not initialised after {waited:.0f} s of IMU: waiting for "
                                  f"{self.ekf.waiting_for()}",
                                  "warning" if waited > self.health_limits.fix_warn
                                  else "info")
            return
        self._log_refusal(f"{source}:{out.reason.value}",
                          f"{source} refused: {out.reason.value}")

    # ------------------------------------------------------------------ inputs
    @contained
    def on_tile(self, msg: DemTile):
        """Learn the ENU origin from the metamap's first tile."""
        self._set_origin(msg.georef, "/metamap/tile")

    @contained
    def _ask_origin(self):
        """While the origin is unknown, ask the metamap for a 1-px tile (it carries it)."""
        pending = self._origin_future is not None and not self._origin_future.done()
        action = self._origin.request(time.monotonic(), pending)
        if action == "done":
            self._origin_timer.cancel()
            self.destroy_timer(self._origin_timer)
            self.destroy_client(self._origin_client)
            if self._tile_sub is not None:
                self.destroy_subscription(self._tile_sub)
            self._tile_sub = self._origin_client = self._origin_timer = None
            return
        if action == "wait":
            return
        if action == "resend":
            self._origin_client.remove_pending_request(self._origin_future)
        if not self._origin_client.service_is_ready():
            return
        request = GetDemTile.Request(center_frame=GetDemTile.Request.CENTER_ENU,
                                     center_x=0.0, center_y=0.0, width=1, height=1, gsd=1.0)
        self._origin.sent(time.monotonic())
        self._origin_future = self._origin_client.call_async(request)
        self._origin_future.add_done_callback(self._on_origin_response)

    @contained
    def _on_origin_response(self, future):
        response = future.result()
        if response is None or not response.success:
            why = "no response" if response is None else response.message
            self._log_refusal("origin_service", f"/metamap/get_tile gave no origin: {why}")
            return
        self._set_origin(response.tile.georef, "/metamap/get_tile")

    def _set_origin(self, georef, source: str):
        """Adopt the ENU origin of a metamap georeference (first one wins)."""
        if self.origin is None:
            self._adopt_origin(*cv.enu_origin_of(georef), source)

    def _adopt_origin(self, lat: float, lon: float, alt: float, source: str):
        try:
            self._origin.adopt(lat, lon, alt)
        except ValueError as err:
            self._log_refusal("tile_origin", f"{source}: no usable ENU origin: {err}")
            return
        self.get_logger().info(f"ENU origin from {source}: {lat:.6f}, {lon:.6f}, {alt:.1f} m")

    @contained
    def on_imu(self, msg: Imu):
        stamp, gyro, accel = cv.imu_to_sample(msg)
        if self.imu_problem is None and self._imu_refused(stamp, gyro, accel):
            self.get_logger().error(f"IMU refused for good: {self.imu_problem}")
            self.ekf.reset()   # what it integrated so far is wrong too
        if self.imu_problem is not None:
            self.rejections["imu:axes_or_units"] += 1
            return
        if self._resume is not None:
            self._resume_at(stamp)
        self._imu_count += 1
        self._imu_span = (self._imu_span or (stamp, stamp))[:1] + (stamp,)
        self._last_imu_wall = time.monotonic()
        prev = self._prev_imu_t
        out = self.ekf.process_imu(stamp, gyro, accel)
        if out.reason == Reason.INITIALIZED:
            self._report("initial pose", out, stamp)
        elif out.reason == Reason.REINITIALIZED:
            self.get_logger().warning(
                f"no {self.params.init_mode} within {self.params.reinit_timeout:.1f} s of the "
                f"reset: re-initialised from the last good state at {stamp:.3f} s, "
                "covariance inflated")
        elif out.reason == Reason.TIME_JUMP_RESET:
            self._on_reset(stamp, prev)
            return
        if not out.accepted:
            # The sample at the stamp a measurement initialised the filter at is no news.
            if not (out.reason == Reason.DUPLICATE and stamp == self._init_stamp):
                self._report("imu", out)
            return
        if self._prev_imu_t is not None and 0.0 < stamp - self._prev_imu_t < 1.0:
            self._imu_dt += 0.01 * (stamp - self._prev_imu_t - self._imu_dt)
        self._prev_imu_t = stamp
        self._gyro = gyro
        t = self.ekf.t
        if t - self._last_odom >= self._odom_period:
            self._last_odom = t
            self.publish_state(msg.header.stamp, t)
        if self._checkpoint_path is not None and t - self._last_checkpoint >= \
                self.checkpoint_period:
            self._last_checkpoint = t
            self._write_checkpoint()

    @property
    def imu_problem(self) -> str | None:
        """Why the IMU stream is refused for good (its axes, units or gyro scale), if it is."""
        return self.imu_convention.problem or self.gyro_scale.problem

    def _imu_refused(self, stamp: float, gyro, accel) -> bool:
        return bool(self.imu_convention.add(stamp, accel)
                    or self.gyro_scale.add(stamp, gyro, accel, self._motion))

    def _motion(self) -> tuple[float, np.ndarray] | None:
        """The estimate's speed and accelerometer bias, for the gyro's scale in turns."""
        if not self.ekf.initialized:
            return None
        s = self.ekf.state
        return float(np.linalg.norm(s.velocity)), s.accel_bias

    # ------------------------------------------------------------------ checkpoint
    def _read_checkpoint(self) -> Checkpoint | None:
        """The checkpoint a crashed predecessor left, if any (resumed at the first IMU)."""
        if self._checkpoint_path is None or not self._checkpoint_path.exists():
            return None
        try:
            return load_checkpoint(self._checkpoint_path)
        except CheckpointError as err:
            self.get_logger().warning(f"not resuming: {err}")
            return None

    def _resume_at(self, stamp: float):
        """Start the filter from the checkpoint carried to ``stamp`` (once, if it fits)."""
        checkpoint, self._resume = self._resume, None
        o = checkpoint.origin
        try:
            if o is not None and self.origin is not None and not np.allclose(
                    (o.lat, o.lon, o.alt), (self.origin.lat, self.origin.lon, self.origin.alt),
                    atol=1e-9):
                raise CheckpointError("the checkpoint is of another ENU origin")
            s = resume_from(checkpoint, stamp, self.checkpoint_max_age)
        except CheckpointError as err:
            self.get_logger().warning(f"not resuming from {self._checkpoint_path}: {err}")
            return
        out = self.ekf.initialize(stamp, s.position, s.velocity, s.quaternion, s.covariance,
                                  s.gyro_bias, s.accel_bias, s.wind, s.baro_bias,
                                  s.camera_mount, s.camera_scale, s.map_bias)
        if not out.accepted:
            self.get_logger().warning(f"not resuming: the filter refused the checkpoint "
                                      f"({out.reason.value})")
            return
        if o is not None and self.origin is None:
            self._adopt_origin(o.lat, o.lon, o.alt, "the checkpoint")
        if checkpoint.baro_offset is not None and self.baro.value is None:
            self.baro.value = checkpoint.baro_offset
        self._init_stamp = stamp
        self.get_logger().warning(
            f"resumed from the checkpoint of {checkpoint.state.stamp:.3f} s, "
            f"{stamp - checkpoint.state.stamp:.1f} s old, carried across the gap at "
            f"({s.position[0]:.0f}, {s.position[1]:.0f}, {s.position[2]:.0f}) m, "
            f"horizontal sigma {math.sqrt(s.covariance[0, 0] + s.covariance[1, 1]):.0f} m")

    def _write_checkpoint(self):
        try:
            save_checkpoint(self._checkpoint_path,
                            Checkpoint(self.ekf.state, self.origin, self.baro.value))
        except OSError as err:
            if not self._checkpoint_failed:   # once: a full or read-only disk stays so
                self.get_logger().error(f"cannot write the checkpoint: {err}")
            self._checkpoint_failed = True

    def _on_reset(self, stamp: float, prev: float | None):
        way = "back" if prev is None or stamp < prev else "ahead"
        self.get_logger().warning(
            f"IMU time jumped {way} to {stamp:.3f} s and the stream went on from there (bag "
            f"loop, simulator restart?): filter reset, re-initialising with init_mode="
            f"{self.params.init_mode}")
        self._last_odom = self._last_navsat = -math.inf
        self._prev_imu_t = self._imu_span = None
        self.baro.forget()

    @contained
    def on_pva_fix(self, msg: PvaFix):
        if msg.status == PvaFix.STATUS_NO_FIX:
            self.no_fix_count += 1
            return
        try:
            fix = cv.pva_fix_to_arrays(msg)
        except cv.ConversionError as err:
            self._refuse("fix", "bad_message", f": {err}")
            return
        if msg.status not in (PvaFix.STATUS_POSITION, PvaFix.STATUS_POSITION_ATTITUDE):
            self._refuse("fix", "unknown_status", f" {msg.status}")
            return
        if msg.header.frame_id != self.map_frame:
            self._refuse("fix", "wrong_frame",
                         f": {msg.header.frame_id!r}, not {self.map_frame!r}")
            return
        with_attitude = msg.status == PvaFix.STATUS_POSITION_ATTITUDE
        if not (np.isfinite(fix.position).all() and np.isfinite(fix.quaternion).all()):
            self._refuse("fix", Reason.NON_FINITE.value)
            return
        q_body = None
        if with_attitude:
            q_body = self.fix_frame.body_quaternion(fix.quaternion)
            if q_body is None:
                self._refuse("fix", Reason.BAD_QUATERNION.value)
                return
        position = self.fix_frame.body_position(fix.position, q_body, self.ekf.q)
        velocity = fix.velocity
        if velocity is not None and (fix.relocalisation
                                     or not is_positive_definite(fix.velocity_covariance)):
            # a relocalisation's velocity is never used; one of unknown covariance (-1 or
            # zeros) is left out, and the position taken as the fix has it
            if not fix.relocalisation:
                self.rejections["fix:velocity_without_covariance"] += 1
            velocity = None
        cov = fix_covariance(fix.covariance,
                             fix.velocity_covariance if velocity is not None else None,
                             with_attitude)
        out = self.ekf.process_fix(fix.stamp, position, cov, velocity=velocity,
                                   quaternion=q_body, source="fix",
                                   relocalisation=fix.relocalisation,
                                   projection_height=fix.projection_height,
                                   mosaic_lag=fix.mosaic_lag)
        self._report("fix", out, fix.stamp)
        self._navigation_state(self.ekf.diagnostics)

    @contained
    def on_set_pose(self, msg: PoseWithCovarianceStamped):
        """An operator's re-seed of the position (robot_localization's ``set_pose``; the
        orientation is not used): applied at its stamp, not gated."""
        try:
            stamp, frame, position, cov = cv.set_pose_to_arrays(msg)
        except cv.ConversionError as err:
            self._refuse("set_pose", "bad_message", f": {err}")
            return
        if frame != self.map_frame:
            self._refuse("set_pose", "wrong_frame", f": {frame!r}, not {self.map_frame!r}")
            return
        out = self.ekf.set_position(stamp, position, cov)
        if out.accepted:
            self.get_logger().warning(f"position set by /ekf/set_pose at {stamp:.3f} s: "
                                      f"({position[0]:.0f}, {position[1]:.0f}, "
                                      f"{position[2]:.0f}) m")
        self._report("set_pose", out, stamp)
        self._navigation_state(self.ekf.diagnostics)

    def _navigation_state(self, d) -> tuple[str, str]:
        """Lost / searching / found / tracking now; logged when it changes."""
        state, detail = navigation_state(d, self.health_limits.lost_sigma)
        line = self._navigation.change(state, detail)
        if line is not None:
            self.get_logger().info(line)
        return state, detail

    @contained
    def on_baro(self, msg: FluidPressure):
        stamp, pressure, variance = cv.fluid_pressure_to_sample(msg)
        self.baro_use.arrived()
        refused = baro_refusal(stamp, pressure, variance)
        if refused is not None:
            self._refuse("baro", "bad_pressure", refused)
            self.baro_use.refused(f"bad pressure{refused}")
            return
        altitude = float(pressure_to_altitude(pressure, self.sea_level_pressure))
        if self.baro.value is None:
            if not self.baro.learn(stamp, altitude, self.ekf):
                self.rejections["baro:waiting_for_offset"] += 1
                self.baro_use.refused(self._baro_offset_wait(stamp))
                return
            self.get_logger().info(
                f"baro offset learnt: ENU up = pressure altitude {self.baro.value:+.1f} m "
                f"(vertical sigma {math.sqrt(self.ekf.state.covariance[2, 2]):.1f} m)")
        sigma = altitude_sigma(math.sqrt(variance), pressure) if variance > 0 else 0.0
        out = self.ekf.process_baro(stamp, altitude + self.baro_offset,
                                    max(sigma, self.baro_sigma) ** 2)
        self._report("baro", out)
        if out.accepted:
            self.baro_use.used()
        else:
            self.baro_use.refused(out.reason.value)
        d = self.ekf.diagnostics
        if d.baro_steps != self._baro_steps_logged:
            self._baro_steps_logged = d.baro_steps
            self.get_logger().warning(
                f"baro jumped ({d.baro_steps} so far): {d.baro_step:+.1f} m in all taken off "
                "its heights (a static port that iced or cleared, a sensor fault?)")

    def _baro_offset_wait(self, stamp: float) -> str:
        """Why the baro offset is not learnt yet."""
        if not self.ekf.initialized:
            return "waiting for the filter to start"
        if abs(stamp - self.ekf.t) > self.baro.MAX_LAG:
            return (f"its stamps are {stamp - self.ekf.t:+.1f} s from the IMU's: another "
                    "clock?")
        return (f"waiting for a vertical sigma under {self.baro.max_sigma:g} m to learn its "
                "offset")

    @contained
    def on_gnss(self, msg: NavSatFix):
        stamp, status, lla, cov, cov_type = cv.navsatfix_to_arrays(msg)
        if status < NavSatStatus.STATUS_FIX:
            self._refuse("gnss", "no_fix_status")
            return
        refused = gnss_refusal(stamp, lla, self.origin)
        if refused is not None:
            self._refuse("gnss", *refused)
            return
        cov = gnss_covariance(cov, cov_type, self.gnss_fallback_sigma)
        enu = np.array(self.origin.geodetic_to_enu(*lla), float)
        out = self.ekf.process_gnss(stamp, enu, cov)
        self._report("gnss", out, stamp)

    # ------------------------------------------------------------------ outputs
    def publish_state(self, stamp_msg, t: float):
        """Odometry (+ TF, + NavSatFix when due) of the current estimate."""
        s = self.ekf.state
        P = s.covariance
        R = quat_to_matrix(s.quaternion)            # body -> ENU
        v_body = R.T @ s.velocity
        w = np.asarray(self._gyro) - s.gyro_bias
        twist_cov = np.zeros((6, 6))
        twist_cov[:3, :3] = R.T @ P[3:6, 3:6] @ R
        twist_cov[3:, 3:] = P[9:12, 9:12] + np.eye(3) * (
            self.params.gyro_noise_density ** 2 / self._imu_dt)
        header = cv.make_header(stamp_msg, self.map_frame)
        d = self.ekf.diagnostics
        resets = d.resets + d.position_resets + d.relocalisation_resets
        if resets != self._resets_published:
            # said before the estimate it moved: the autopilot bridge marks that estimate a
            # reset (PX4's reset_counter), not one a report period later
            self._resets_published, self._last_reset_stamp = resets, t
            self.publish_diagnostics_now()
        self.odom_pub.publish(cv.odometry_msg(header, self.base_frame, s.position,
                                              s.quaternion, s.pose_covariance(), v_body, w,
                                              twist_cov))
        if self.tf_pub is not None:
            self.tf_pub.publish(cv.tf_message(header, self.base_frame, s.position,
                                              s.quaternion))
        if self.origin is not None and t - self._last_navsat >= self._navsat_period:
            self._last_navsat = t
            lat, lon, h = self.origin.enu_to_geodetic(*s.position)
            self.navsat_pub.publish(cv.arrays_to_navsatfix(
                header, float(lat), float(lon), float(h), P[:3, :3]))

    def diagnostics(self) -> list:
        """The filter's health and each measurement source's updates since the last report."""
        d = self.ekf.diagnostics
        since_imu = time.monotonic() - (self._last_imu_wall or self._started_wall)
        refused_now = d.imu_stamps_refused - self._stamps_reported
        self._stamps_reported = d.imu_stamps_refused
        new = self._new_records(d.records)
        gated = gated_records(new, self.params.fuse_gnss)
        failures, new_failed = new_failures(self)
        baro_unused = self.baro_use.report()   # (before the start: waiting is expected)
        health = filter_health(d, since_imu, self.ekf.waiting_for(), self.health_limits,
                               refused_now, len(gated), self.imu_problem, new_failed,
                               baro_unused if self.ekf.initialized else "")
        for r in gated:
            self._log_refusal(f"{r.source}:{Reason.GATED.value}",
                              f"{r.source} at {r.stamp:.3f} s rejected by the "
                              f"chi-square gate: NIS {r.nis:.1f} > {r.gate:.1f}")
        values = filter_values(d, self.params.init_mode, self._imu_count, self._imu_dt,
                               self.no_fix_count, self.baro.value, self.origin,
                               self.rejections)
        values["navigation_state"], values["navigation"] = self._navigation_state(d)
        values["failures"] = failures
        values["last_reset_stamp"] = f"{self._last_reset_stamp:.6f}"   # (a stamp's digits)
        statuses = [cv.diagnostic_status("ekf: filter", health.level, health.message, values,
                                         "terrain_nav")]
        for source in SOURCES:
            message, source_values = source_report(d, source, new)
            statuses.append(cv.diagnostic_status(f"ekf: {source}", DIAG_OK, message,
                                                 source_values, "terrain_nav"))
        return statuses


def main(args=None):
    return run(EkfNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
