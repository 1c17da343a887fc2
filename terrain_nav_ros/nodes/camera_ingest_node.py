"""camera_ingest: camera frames -> north-up ground images at the landmark GSD.

Subscribes to the camera (``/camera/image_raw`` as sensor_msgs/Image in any common encoding,
or ``/camera/image_raw/compressed`` with ``image_transport: compressed``), its
``/camera/camera_info``, the navigation estimate ``/nav/odometry``, the DEM tile
``/metamap/tile`` and ``/tf_static`` (the camera's mount: ``base_frame`` -> the images'
frame_id, else the ``mount_rpy`` parameter; the diagnostics' ``mount`` says which). Each
frame has its lens's vignetting divided out (learnt from the same ground seen at other
places in the lens by consecutive frames, :mod:`..core.camera.vignetting`;
``vignetting_correction``), is undistorted with the CameraInfo
lens model and projected onto the mean terrain
plane under the view (homography from the pose interpolated at the frame's stamp), then
published as a ``terrain_nav_msgs/GeoImage`` on ``/camera/image_ground``
with a validity mask. A frame that observes fewer ground pixels than ``mosaic_pixels`` (a
low camera: too few DEM cells for its drainage to be told from chance) is published as a
track mosaic (:mod:`..core.camera.track_mosaic`): composed with the frames of the last
``mosaic_max_age`` s, each moved by the steps the estimate took since it, under the newest
frame's projection pose. A frame that cannot be projected (no estimate or tile yet, no
calibration, camera above the horizon, undecodable image, a frozen camera repeating its
last image or a stamp that does not move forward; three frames in a row that go forward
behind the last one are a new clock, taken with a warning) is still published, as a GeoImage
without an image whose ``reason`` says why, so that the matcher answers it with a no-fix; a
throttled log line says so too, and ``/camera_ingest/diagnostics`` counts each reason
(and the frames received: a bag's others were lost on the way, e.g. by a best-effort link).
A frame newer than the newest estimate (a filter short of CPU lags behind the camera) waits
for it, up to ``max_estimate_wait`` s of wall time, and is projected as it arrives; frames
behind it wait in order.

Cold start (``cold_start: true``, with the ``mission_dir`` the matcher searches): while
there is no estimate at a frame's stamp (the ekf publishes none before it is initialised),
the frame is projected without a pose (:mod:`..core.camera.pose_free`): at the ENU origin,
heading 0, the roll and pitch of ``/imu/data``'s orientation when it carries one, else of
its accelerometers levelled in straight flight (frames in a turn are not projected), the
camera at the barometer's altitude (``/baro/pressure``, ISA), on a plane at the mission
area's median terrain height (no orthorectification: the place is unknown). The GeoImage is
marked ``pose_free`` with the range of planes the area's terrain allows and the attitude's
sigma, so the matcher searches it in the whole mission index at the scales they allow. As
soon as the ekf publishes odometry, frames are projected with it (and pose-free again only
when it stops for ``COLD_START_GAP`` s). Without a barometer sample, the mission index, its
terrain heights or a DEM tile (it carries the ENU origin), the frame is a no-fix saying
which.
"""

from __future__ import annotations

import math
import re
import time
from collections import Counter, deque

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, FluidPressure, Image, Imu

from terrain_nav_msgs.msg import DemTile, GeoImage

from ..core.camera.camera_mount import camera_rotation
from ..core.camera.frame_guard import FrameGuard
from ..core.camera.ground_projection import (
    CameraIntrinsics,
    CameraPose,
    check_view,
    footprint_georef,
    project_to_ground,
    projection_plane,
)
from ..core.camera.orthorectify import heights_on, orthorectify
from ..core.camera.pose_buffer import PoseBuffer, StampedPose
from ..core.camera.pose_free import CruiseAttitude, pose_free_view
from ..core.camera.track_mosaic import FilterSteps, TrackMosaic
from ..core.camera.vignetting import Vignetting
from ..core.estimation.baro import SEA_LEVEL_PRESSURE, pressure_to_altitude
from ..core.matching.pva_fix import reason_kind
from ..core.render.sun import sun_at
from ..core.terrain.georef import GeoReference
from . import conversions as cv
from .ros_common import (
    DIAG_OK,
    DIAG_WARN,
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    CameraMount,
    contained,
    declare,
    publish_diagnostics,
    run,
)

# cold start: frames this long after the last odometry are projected pose-free again (the
# filter was reset); within it, a frame without a pose is a no-fix as without cold start (s)
COLD_START_GAP = 2.0
# a frame is projected where the DEM covers at least this share of its footprint raster (its
# other pixels are not observed: beyond the DEM there is no landmark to match them against)
MIN_DEM_COVER = 0.1
# Frames waiting for the estimate at most (raw frames are megabytes; at 1-10 Hz a second's)
_MAX_WAITING = 10


class CameraIngestNode(Node):
    """Projects camera frames onto the ground for the feature extractor."""

    def __init__(self):
        super().__init__("camera_ingest")
        self.gsd = declare(self, "gsd", 20.0, "ground image GSD; use the landmark GSD [m/px]",
                           min_value=0.01)
        self.max_size = declare(self, "max_size", 1024, "largest ground image side [px]",
                                min_value=16, max_value=8192)
        self.max_range_factor = declare(
            self, "max_range_factor", 3.0,
            "ground farther than this x height above ground is not projected [-]",
            min_value=0.1)
        transport = declare(self, "image_transport", "raw", "raw | compressed")
        mount_rpy = declare(self, "mount_rpy", [0.0, 0.0, 0.0],
                            "camera tilt from the nadir mount, roll/pitch/yaw about body FLU "
                            "[deg], where /tf_static does not link base_frame to the camera")
        base_frame = declare(self, "base_frame", "base_link",
                             "the aircraft's body frame in /tf_static (the camera's mount)")
        self.max_pose_gap = declare(self, "max_pose_gap", 0.25,
                                    "largest time between a frame and the estimate [s]",
                                    min_value=0.0)
        self.max_frame_age = declare(self, "max_frame_age", 1.0,
                                     "largest time a frame's stamp may lag the newest "
                                     "estimate (older: a late frame or a camera clock that "
                                     "jumped back) [s]", min_value=0.0)
        self.max_estimate_wait = declare(
            self, "max_estimate_wait", 1.0,
            "a frame newer than the newest estimate waits this long for it (a filter short "
            "of CPU lags), wall clock [s]; 0 = not held", min_value=0.0)
        self.frame_id = declare(self, "frame_id", "map", "frame of the ground images")
        self.orthorectify = declare(self, "orthorectify", True,
                                    "use the DEM tile's height for every ground pixel (true "
                                    "ortho) instead of one mean terrain plane")
        self.vignetting = Vignetting(declare(
            self, "vignetting_correction", False,
            "learn the lens's radial falloff from overlapping frames and divide it out (a "
            "frame darker towards its edge shifts its creases outwards: a small scale, a "
            "low height); a flat-fielded camera's frames stay as they are"))
        self.cold_start = declare(
            self, "cold_start", False,
            "project frames without a navigation pose while there is none (a live graph "
            "started without GNSS; needs mission_dir, the barometer and init_mode fix)")
        mission_dir = declare(self, "mission_dir", "",
                              "cold start: the mission index (terrain-nav prepare) whose "
                              "terrain heights a pose-free frame assumes; the matcher's")
        tilt_sigma = declare(self, "cold_start_tilt_sigma", 3.0,
                             "cold start: 1-sigma of the wings-level attitude assumed "
                             "before any IMU message [deg]", min_value=0.0)
        levelled_sigma = declare(self, "cold_start_levelled_sigma", 1.0,
                                 "cold start: 1-sigma of the roll and pitch levelled from "
                                 "the accelerometers in straight flight [deg]",
                                 min_value=0.0)
        turn_rate = declare(self, "cold_start_max_turn_rate", 3.0,
                            "cold start: frames whose last second turned faster than this "
                            "are not projected (bank unknown) [deg/s]", min_value=0.0)
        self.sea_level_pressure = declare(self, "sea_level_pressure", SEA_LEVEL_PRESSURE,
                                          "cold start: ISA reference pressure [Pa]",
                                          min_value=1.0)
        self.baro_altitude_sigma = declare(
            self, "baro_altitude_sigma", 50.0,
            "cold start: 1-sigma of the pressure altitude against the DEM's heights (the "
            "day's sea-level pressure) [m]", min_value=0.0)
        self.max_baro_age = declare(self, "max_baro_age", 2.0,
                                    "cold start: largest time between a frame and the "
                                    "barometer sample used [s]", min_value=0.0)
        mosaic_pixels = declare(
            self, "mosaic_pixels", 9216,
            "a projected frame that observes fewer ground pixels than this (a low camera: "
            "few DEM cells, too little drainage alone) is published as a mosaic with the "
            "frames before it, placed in its estimate, until they observe this many; 0 = "
            "every frame alone [px]", min_value=0)
        mosaic_max_age = declare(self, "mosaic_max_age", 60.0,
                                 "oldest frame in a mosaic, behind the newest: the "
                                 "estimate's drift over it distorts the mosaic [s]",
                                 min_value=0.0)
        self.mosaic = TrackMosaic(mosaic_pixels, mosaic_max_age, self.max_size)
        self.steps = FilterSteps(horizon=mosaic_max_age + 5.0)
        self.mosaics = Counter()   # mosaics published, frames in them
        self.mount = CameraMount(self, base_frame, mount_rpy)
        self.attitude = CruiseAttitude(math.radians(tilt_sigma), math.radians(turn_rate),
                                       levelled_sigma=math.radians(levelled_sigma))
        self.baro: tuple[float, float] | None = None     # (stamp s, pressure Pa)
        self._odometry_span: tuple[float, float] | None = None   # first, last stamp (s)
        self.pose_free_published = 0
        self.terrain, self.terrain_problem = None, ""
        if self.cold_start:
            self.terrain, self.terrain_problem = self._area_terrain(mission_dir)
        self.poses = PoseBuffer(horizon=5.0, max_extrapolation=self.max_pose_gap,
                                max_age=self.max_frame_age)
        self.frames = FrameGuard()
        self.waiting: deque = deque()   # (wall s, image, encoding, header) for the estimate
        self.waited = Counter()         # frames that waited: "reached", "in vain"
        self.intrinsics: CameraIntrinsics | None = None
        self.calibration_problem = "no CameraInfo received yet"
        self.tile: tuple[np.ndarray, GeoReference] | None = None
        self.tile_origin = (0.0, 0.0, 0.0)
        diagnostics_period = declare(self, "diagnostics_period", 1.0,
                                     "period of /camera_ingest/diagnostics, wall clock [s]",
                                     min_value=0.01)
        self.camera_timeout = declare(self, "camera_timeout", 5.0,
                                      "no camera frame for this long is a warning [s]",
                                      min_value=0.0)
        self.drops: Counter = Counter()
        self.received = 0   # frames that reached the node (the rest were lost on the way)
        self.published = 0
        self._reported = (0, 0)   # projected and not projected at the last report
        self._started_wall = time.monotonic()
        self.last_frame_wall: float | None = None
        self.pub = self.create_publisher(GeoImage, "camera/image_ground", RELIABLE_QOS)
        if transport == "compressed":
            self.create_subscription(CompressedImage, "camera/image_raw/compressed",
                                     self.on_compressed, SENSOR_QOS)
        elif transport == "raw":
            self.create_subscription(Image, "camera/image_raw", self.on_image, SENSOR_QOS)
        else:
            raise ValueError(f"image_transport must be 'raw' or 'compressed', not {transport!r}")
        self.create_subscription(CameraInfo, "camera/camera_info", self.on_info, SENSOR_QOS)
        self.create_subscription(Odometry, "nav/odometry", self.on_odometry, RELIABLE_QOS)
        self.create_subscription(DemTile, "metamap/tile", self.on_tile, LATCHED_QOS)
        if self.cold_start:
            self.create_subscription(FluidPressure, "baro/pressure", self.on_baro, SENSOR_QOS)
            self.create_subscription(Imu, "imu/data", self.on_imu, SENSOR_QOS)
        publish_diagnostics(self, "camera_ingest/diagnostics", diagnostics_period,
                            self.diagnostics)
        if self.max_estimate_wait > 0:
            self.create_timer(0.1, self._release_waiting,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _area_terrain(self, mission_dir: str):
        """The mission area's terrain heights for a cold start, or None and why not (said
        for every pose-free frame, not a failure at start-up: the graph still runs once the
        ekf has a pose)."""
        if not mission_dir:
            return None, ("cold start: no mission index (camera_ingest's mission_dir) for the "
                          "area's terrain heights")
        from ..core.matching.mission_index import MissionIndex, MissionIndexError

        try:
            terrain = MissionIndex(mission_dir).terrain()
        except MissionIndexError as err:
            self.get_logger().error(f"cold start impossible: {err}")
            return None, f"cold start: {err}"
        if terrain is None:
            self.get_logger().error(f"cold start impossible: {mission_dir} records no terrain "
                                    "heights and its DEMs cannot be read")
            return None, ("cold start: the mission index holds no terrain heights and its DEMs "
                          "cannot be read: prepare it again")
        self.get_logger().info(
            f"cold start: terrain of the mission area {terrain.low:.0f} / {terrain.median:.0f}"
            f" / {terrain.high:.0f} m (2nd percentile / median / 98th)")
        return terrain, ""

    # -- inputs ----------------------------------------------------------------------------
    @contained
    def on_baro(self, msg: FluidPressure) -> None:
        stamp, pressure, _ = cv.fluid_pressure_to_sample(msg)
        if math.isfinite(pressure) and pressure > 0 and math.isfinite(stamp):
            self.baro = (stamp, pressure)

    @contained
    def on_imu(self, msg: Imu) -> None:
        stamp, gyro, accel = cv.imu_to_sample(msg)
        orientation = cv.imu_orientation(msg)
        self.attitude.add(stamp, gyro, accel, *(orientation or (None, None)))

    @contained
    def on_info(self, msg: CameraInfo) -> None:
        try:
            k, d, model, (w, h) = cv.camera_info_to_intrinsics(msg)
        except cv.ConversionError as err:
            self.intrinsics, self.calibration_problem = None, str(err)
            return
        self.intrinsics = CameraIntrinsics.from_matrix(k, w, h, tuple(d), model)
        self.calibration_problem = self.intrinsics.problem()

    @contained
    def on_odometry(self, msg: Odometry) -> None:
        stamp, p, q, cov = cv.odometry_to_arrays(msg)
        reason = self.poses.add(StampedPose(stamp * 1e-9, p, q, cov))
        if not reason:
            t = stamp * 1e-9
            self.steps.add(t, p, cv.odometry_velocity(msg))
            first, last = self._odometry_span or (t, t)
            if t < last - self.poses.horizon:      # time went backwards: start again
                first, last = t, t
            self._odometry_span = (min(first, t), max(last, t))
        if reason:
            self.get_logger().warning(f"odometry ignored: {reason}", throttle_duration_sec=5.0)
        self._release_waiting()

    @contained
    def on_tile(self, msg: DemTile) -> None:
        try:
            self.tile = cv.msg_to_dem_tile(msg)
            self.tile_origin = cv.enu_origin_of(msg.georef)
        except cv.ConversionError as err:
            self.get_logger().error(f"bad DemTile ignored: {err}")

    @contained
    def on_image(self, msg: Image) -> None:
        self.last_frame_wall = time.monotonic()
        self.received += 1
        try:
            arr = cv.image_to_array(msg)
        except cv.ConversionError as err:
            self.drop(str(err), msg.header)
            return
        self.ingest(arr, msg.encoding, msg.header)

    @contained
    def on_compressed(self, msg: CompressedImage) -> None:
        self.last_frame_wall = time.monotonic()
        self.received += 1
        try:
            arr, encoding = cv.compressed_image_to_array(msg)
        except cv.ConversionError as err:
            self.drop(str(err), msg.header)
            return
        self.ingest(arr, encoding, msg.header)

    # -- projection ------------------------------------------------------------------------
    def drop(self, reason: str, header) -> None:
        """Tell the graph why this frame has no ground image (and count the reason)."""
        # the reason without its details or numbers (a lag's seconds: one key per value
        # grew the diagnostics without bound over a long flight)
        key = reason_kind(re.split(r"[:(]", reason)[0].strip())[:60]
        self.drops[key] += 1
        self.pub.publish(cv.unprojected_frame_msg(cv.make_header(header.stamp, self.frame_id),
                                                  f"frame not projected: {reason}"))
        self.get_logger().warning(f"frame not projected: {reason}", throttle_duration_sec=2.0)

    def ingest(self, image: np.ndarray, encoding: str, header) -> None:
        """Project one frame; every frame comes out, projected or with the reason why not."""
        restarts = self.frames.restarts
        refused = self.frames.check(cv.stamp_to_sec(header.stamp), image)
        if self.frames.restarts > restarts:
            self.get_logger().warning(
                f"camera clock went back (a loop, a restart) or the last frame's stamp was "
                f"wrong: {FrameGuard.CONFIRM} frames in a row go on from "
                f"{cv.stamp_to_sec(header.stamp):.3f} s; taking that clock")
        if refused:
            self.drop(refused, header)
            return
        self._project_or_drop(image, encoding, header, may_wait=True)

    def _project_or_drop(self, image: np.ndarray, encoding: str, header, may_wait: bool):
        try:
            self._project(image, encoding, header, may_wait)
        except Exception as err:
            self.drop(f"projection failed: {type(err).__name__}: {err}", header)
            raise   # logged and counted by @contained

    @contained   # (also the wait timer's callback: a frame that fails is counted there)
    def _release_waiting(self) -> None:
        """Project the frames that waited for the estimate, in order, as it reaches them or
        their wait runs out (then they are no-fixes saying how far behind it was)."""
        now = time.monotonic()
        while self.waiting:
            since, image, encoding, header = self.waiting[0]
            ahead = self.poses.ahead(cv.stamp_to_sec(header.stamp))
            if ahead and now - since < self.max_estimate_wait and \
                    len(self.waiting) <= _MAX_WAITING:
                return
            self.waiting.popleft()
            self.waited["in vain" if ahead else "reached"] += 1
            self._project_or_drop(image, encoding, header, may_wait=False)

    def _flat_fielded(self, image: np.ndarray) -> np.ndarray:
        """The raw frame with the lens's falloff learnt so far divided out, about the
        principal point (:class:`Vignetting`; learnt from its ground image after)."""
        return self.vignetting.correct(image, (self.intrinsics.cx, self.intrinsics.cy))

    def _project(self, image: np.ndarray, encoding: str, header, may_wait: bool) -> None:
        if self.intrinsics is None or self.calibration_problem:
            self.drop(self.calibration_problem or "no CameraInfo", header)
            return
        stamp = cv.stamp_to_sec(header.stamp)
        pose, reason = self.poses.at(stamp)
        if pose is None and self.cold_start and self._without_odometry(stamp):
            image = self._flat_fielded(image)
            self.vignetting.learn(None)   # (the heading unknown: no pair to learn from)
            self._project_pose_free(image, encoding, header)
            return
        if may_wait and self.max_estimate_wait > 0 and (self.waiting or (
                pose is None and self.poses.ahead(stamp))):
            self.waiting.append((time.monotonic(), image, encoding, header))
            self._release_waiting()   # (more than _MAX_WAITING: the oldest goes)
            return
        if pose is None:
            self.drop(reason + (f" (after waiting {self.max_estimate_wait:g} s for it)"
                                if not may_wait and self.poses.ahead(stamp) else ""), header)
            return
        camera = CameraPose(pose.position, camera_rotation(
            pose.quaternion, self.mount.rotation(header.frame_id)))
        if self.tile is None:
            self.drop("no DEM tile under the aircraft yet", header)
            return
        plane, georef, max_range, why = projection_plane(
            *self.tile, self.intrinsics, camera, self.gsd, self.max_range_factor)
        if georef is None:
            self.drop(why, header)
            return
        georef = self._capped(georef)
        bgr = encoding.startswith("bgr")
        image = self._flat_fielded(image)
        if self.orthorectify:
            # each pixel at its own DEM height; beyond the DEM (its edge, a void) not observed
            heights = heights_on(georef, *self.tile)
            cover = float(np.isfinite(heights).mean())
            if cover < MIN_DEM_COVER:
                self.drop(f"the DEM covers {cover:.0%} of the view (at least "
                          f"{MIN_DEM_COVER:.0%} needed)", header)
                return
            ground = orthorectify(image, self.intrinsics, camera, heights, georef, bgr,
                                  max_range)
        else:
            ground = project_to_ground(image, self.intrinsics, camera, plane, georef, bgr=bgr,
                                       max_range=max_range)
        self.vignetting.learn(ground)
        lag = 0.0
        if ground.image is not None:
            ground, n, lag = self.mosaic.compose(ground, stamp, self.steps.at(stamp),
                                                 self.steps.epoch)
            if n > 1:
                self.mosaics["published"] += 1
                self.mosaics["frames"] += n
        self._publish_ground(ground, camera, plane, header, mosaic_lag=lag)

    def _publish_ground(self, ground, camera: CameraPose, plane: float, header,
                        pose_free: tuple[float, float, float] | None = None,
                        mosaic_lag: float = 0.0) -> bool:
        """Publish a projected frame as a GeoImage with its projection (and, for a cold
        start, ``pose_free``: the range of planes and the tilt sigma it leaves open; for a
        track mosaic, the mean age of its pixels), or drop it with the projection's reason;
        whether it was published."""
        if ground.image is None:
            self.drop(ground.reason, header)
            return False
        out = cv.geo_image_to_msg(ground.image, ground.georef,
                                  cv.make_header(header.stamp, self.frame_id),
                                  ground.valid, self.tile_origin,
                                  sun=self.sun_at_frame(header.stamp))
        cv.set_projection(out, camera.position, camera.rotation, plane, mosaic_lag)
        if pose_free is not None:
            cv.set_pose_free(out, *pose_free)
        self.pub.publish(out)
        self.published += 1
        return True

    def _without_odometry(self, stamp: float) -> bool:
        """Whether a frame at ``stamp`` has no navigation estimate to wait for: none yet, the
        frame taken before the filter started, or the odometry stopped (a filter reset)
        ``COLD_START_GAP`` s before it. A shorter gap is a no-fix, as without cold start."""
        if self._odometry_span is None:
            return True
        first, last = self._odometry_span
        return stamp < first or stamp > last + COLD_START_GAP

    def _project_pose_free(self, image: np.ndarray, encoding: str, header) -> None:
        """A frame with no navigation pose at its stamp, projected pose-free (cold start)."""
        stamp = cv.stamp_to_sec(header.stamp)
        if self.terrain is None:
            self.drop(self.terrain_problem, header)
            return
        if self.tile is None:
            self.drop("cold start: no DEM tile yet (it carries the graph's ENU origin)", header)
            return
        if self.baro is None:
            self.drop("cold start: no barometer pressure yet (/baro/pressure)", header)
            return
        if abs(self.baro[0] - stamp) > self.max_baro_age:
            self.drop(f"cold start: the last barometer sample is {self.baro[0] - stamp:+.1f} s "
                      "from the frame", header)
            return
        attitude, why = self.attitude.at(stamp)
        if attitude is None:
            self.drop(why, header)
            return
        roll, pitch, tilt_sigma = attitude
        t = self.terrain
        view, why = pose_free_view(
            float(pressure_to_altitude(self.baro[1], self.sea_level_pressure)), t.low,
            t.median, t.high, self.tile_origin[2], roll=roll, pitch=pitch,
            tilt_sigma=tilt_sigma, altitude_sigma=self.baro_altitude_sigma,
            r_body_optical=self.mount.rotation(header.frame_id))
        if view is None:
            self.drop(why, header)
            return
        camera, plane = view.pose, view.plane
        max_range = self.max_range_factor * view.height_above_ground
        georef = footprint_georef(self.intrinsics, camera, plane, self.gsd, max_range)
        if georef is None:
            self.drop(check_view(self.intrinsics, camera, plane), header)
            return
        georef = self._capped(georef)
        ground = project_to_ground(image, self.intrinsics, camera, plane, georef,
                                   bgr=encoding.startswith("bgr"), max_range=max_range)
        if not self._publish_ground(ground, camera, plane, header,
                                    (view.plane_min, view.plane_max, view.tilt_sigma)):
            return
        self.pose_free_published += 1
        self.get_logger().info(
            f"frame projected pose-free (cold start): {view.height_above_ground:.0f} m above "
            f"the area's median terrain, planes {view.plane_min:.0f}..{view.plane_max:.0f} m",
            throttle_duration_sec=5.0)

    def sun_at_frame(self, stamp) -> tuple[float, float] | None:
        """The sun over the tile's origin at the frame's stamp; None before a tile (no
        origin yet) or with the sun below the horizon."""
        lat, lon, _ = self.tile_origin
        if (lat, lon) == (0.0, 0.0):
            return None
        az, el = sun_at(cv.stamp_to_sec(stamp), lat, lon)
        return (az, el) if el > 0.0 else None

    def _capped(self, georef: GeoReference) -> GeoReference:
        """Same centre, at most max_size pixels a side."""
        if max(georef.width, georef.height) <= self.max_size:
            return georef
        return GeoReference.centred(*georef.centre, georef.gsd,
                                    min(georef.width, self.max_size),
                                    min(georef.height, self.max_size))

    def diagnostics(self) -> list:
        """Frames projected and not (these by reason) so far; a warning when frames stop
        coming or none of those since the last report could be projected."""
        level, problems = DIAG_OK, []
        not_projected = sum(self.drops.values())
        new_projected = self.published - self._reported[0]
        new_dropped = not_projected - self._reported[1]
        self._reported = (self.published, not_projected)
        since = time.monotonic() - (self.last_frame_wall or self._started_wall)
        if since > self.camera_timeout:
            level = DIAG_WARN
            problems.append(f"no camera frame for {since:.0f} s")
        if new_dropped and not new_projected:
            level = DIAG_WARN
            problems.append(f"{new_dropped} frame(s) not projected, none projected: "
                            f"{self.drops.most_common(1)[0][0]}")
        values = {"frames_received": self.received,
                  "projected": self.published, "projected_pose_free": self.pose_free_published,
                  "waited_for_estimate": sum(self.waited.values()),
                  "waited_in_vain": self.waited["in vain"],
                  "not_projected": not_projected,
                  "mosaics": self.mosaics["published"],
                  "frames_per_mosaic": self.mosaics["frames"] / max(self.mosaics["published"], 1),
                  "frames_since_last_report": new_projected + new_dropped,
                  "time_since_last_frame": since, "mount": self.mount.describe(),
                  "vignetting_corner": self.vignetting.corner()}
        values.update({f"not projected: {k}": n for k, n in self.drops.most_common()})
        message = "; ".join(problems) or f"{new_projected} frame(s) projected since the last report"
        return [cv.diagnostic_status("camera_ingest", level, message, values, "terrain_nav")]


def main(args=None):
    return run(CameraIngestNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
