"""matcher: terrain recognition by minutiae and the PVA fix (dissertation chapter 4).

Subscribes to the camera minutiae (``/camera/minutiae``, from ground-projected frames) and the
landmark minutiae (``/landmark/minutiae``, latched, one set per rendered DEM tile). Each camera
set is localised in the landmark set whose region holds it (:mod:`.core.matching`; when both
sets carry their crease (and ridge) skeletons, the registration is also checked on them); a match
above the calibrated significance threshold becomes a position fix
(:func:`.core.matching.pva_fix.fix_from_ground_match`), published as ``terrain_nav_msgs/PvaFix`` on
``/nav/pva_fix`` with its covariance, similarity and pairings. Every camera set gets an answer:
when there is no fix the message has ``status = STATUS_NO_FIX`` and the reason. A set that
waited more than ``max_queue_wait`` s in the node's queue (behind a slow search of the mission
index; the middleware's receive time) is answered "skipped" at once, so that the matcher
catches up rather than answering every later frame after the ekf's history.
``/matcher/diagnostics`` (diagnostic_msgs/DiagnosticArray, every ``diagnostics_period`` s)
counts fixes and no-fixes (by reason) and times the answers. Every ``flip_check_every``
frames of a run scoring below the threshold, the frame is tried mirrored back across each
line a flipped camera image mirrors it across (:class:`.core.matching.fix_stream.FlipCheck`):
a match is named in the no-fix, the log and the diagnostics, never made a fix (a track
mosaic is not tried: no line mirrors its frames back).

The fix is the aircraft (``base_link``) pose: the camera's lever arm (centimetres) is
neglected and its attitude is the prior's turned back through the camera mount (from
``/tf_static``, ``base_frame`` -> the CameraInfo's frame_id, as camera_ingest's; else
``mount_rpy``). The
registration's rotation is the prior's heading error, so with ``publish_heading`` the heading
is measured too (``STATUS_POSITION_ATTITUDE``, roll and pitch with a 10-degree sigma that
leaves the filter's own untouched); otherwise, and for a track mosaic (whose rotation is the
estimate's past headings), only the position (``STATUS_POSITION``, rotation covariance -1).

A pose-free camera set (camera_ingest's cold start: projected without any navigation pose)
is always searched in the mission index, at the ladder of scales its range of terrain planes
needs (:func:`.core.matching.global_search.relocalise_ladder`), and its fix is a
relocalisation: the position under the camera found, the height the barometer's (the scale
measures the height above the unknown terrain, not the aircraft's), the horizontal
covariance grown by the height above ground x the attitude's assumed sigma, the roll and
pitch camera_ingest's with that sigma (levelled apart from the filter: what the ekf starts
from), the heading the registration's. Without a mission index it is a no-fix saying so.
With a mission index, the tiles of the sun layer nearest the frames' sun are loaded in a
background thread from the first frame on, so that the first search is as quick as the next.

What the node decides around the matcher is ROS-free in
:mod:`terrain_nav_ros.core.matching.fix_stream`: the landmark set a camera set is matched in,
the fix's tilt allowance, attitude and velocity, and the diagnostics' tallies.
"""

from __future__ import annotations

import math
import time

import numpy as np
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo

from terrain_nav_msgs.msg import DemTile, MinutiaArray, PvaFix

from ..core.camera.ground_projection import CameraIntrinsics, CameraPose, ground_to_image
from ..core.camera.pose_free import scale_range
from ..core.matching.fix_stream import (
    UNOBSERVED_TILT_VAR,
    AnswerTally,
    FixVelocity,
    FlipCheck,
    LandmarkSets,
    add_prior_tilt,
    fix_attitude,
)
from ..core.matching.global_search import mirrored_view, rescaled_view, scale_ladder
from ..core.matching.matcher import Decision, Matcher, warm_up
from ..core.matching.params import MatchParams
from ..core.matching.pva_fix import (
    PvaFixEstimate,
    checked_pnp,
    dem_heights,
    fix_from_ground_match,
    fix_from_pnp,
    inflate_covariance,
)
from ..core.matching.relocaliser import MissionSearch, SearchPolicy
from ..core.terrain.geodesy import EnuOrigin
from . import conversions as cv
from .ros_common import (
    DIAG_WARN,
    LATCHED_QOS,
    RELIABLE_QOS,
    SENSOR_QOS,
    CameraMount,
    check_parameters_known,
    contained,
    declare,
    declare_settings,
    new_failures,
    publish_diagnostics,
    reject_all_changes,
    run,
    settings_from_parameters,
)


class MatcherNode(Node):
    """Localises camera minutiae in landmark minutiae and publishes fixes."""

    def __init__(self, **node_kwargs):
        super().__init__("matcher", **node_kwargs)
        # the core's ranges, as a matcher publishing fixes needs them: rclpy refuses a value
        # outside (and NaN) as it is declared; combinations fail in settings_from_parameters
        declare_settings(self, "match", MatchParams(), MatchParams.FIX_RANGES)
        self.landmark_sigma = declare(self, "landmark_sigma", 5.0,
                                      "horizontal error of the DEM that changes from fix to "
                                      "fix [m] (its offset, common to all, is the ekf's map "
                                      "bias)",
                                      min_value=0.0)
        self.tilt_sigma = math.radians(declare(
            self, "prior_tilt_sigma", 0.2,
            "prior attitude error assumed by the ground projection [deg]; times the height "
            "above ground it is added to the covariance of a relocalisation (the ekf models "
            "it for the other ground matches) and allowed for by the PnP check",
            min_value=0.0))
        self.covariance_scale = declare(
            self, "fix_covariance_scale", 1.5,
            "factor on the position and attitude variances of every fix: a margin for errors "
            "that persist from frame to frame, which the ekf takes as independent (3.5 suits "
            "method pnp, whose covariance takes its minutiae's errors as independent)",
            min_value=1.0)
        self.pnp_gate = declare(
            self, "pnp_gate_sigma", 3.0,
            "a PnP pose farther than this from the ground match of the same registration, in "
            "sigma of both, is dropped for the ground match [sigma]", min_value=0.0)
        velocity_gap = declare(self, "velocity_max_gap", 5.0,
                               "largest time between two fixes that give a velocity [s]",
                               min_value=0.0)
        self.method = declare(self, "method", "ground",
                              "ground: the ground point the estimate put below the camera, "
                              "moved by the registration (the ekf models the estimate's tilt "
                              "error in it); pnp: camera pose by PnP over the paired "
                              "minutiae's DEM points where it agrees with the ground match "
                              "(needs CameraInfo and the DEM tile)")
        if self.method not in ("pnp", "ground"):
            raise ValueError(f"method must be 'pnp' or 'ground', not {self.method!r}")
        self.use_heading = declare(self, "publish_heading", True,
                                   "also measure the heading from the registration's rotation "
                                   "(status POSITION_ATTITUDE with roll/pitch unmeasured)")
        self.heading_floor = math.radians(declare(
            self, "heading_sigma_floor", 0.5, "smallest heading sigma reported [deg]",
            min_value=0.0))
        max_landmarks = declare(self, "max_landmarks", 4, "landmark sets kept for pairing",
                                min_value=1, max_value=64)
        mount_rpy = declare(self, "mount_rpy", [0.0, 0.0, 0.0],
                            "camera tilt from the nadir mount, roll/pitch/yaw about body FLU "
                            "[deg], where /tf_static does not link base_frame to the camera")
        base_frame = declare(self, "base_frame", "base_link",
                             "the aircraft's body frame in /tf_static (the camera's mount)")
        self.frame_id = declare(self, "frame_id", "map", "frame of the fixes")
        diagnostics_period = declare(self, "diagnostics_period", 1.0,
                                     "period of /matcher/diagnostics, wall clock [s]",
                                     min_value=0.01)
        self.camera_timeout = declare(self, "camera_timeout", 5.0,
                                      "no camera minutiae for this long is a warning [s]",
                                      min_value=0.0)
        mission_dir = declare(self, "mission_dir", "",
                              "mission index (terrain-nav prepare) searched when lost; "
                              "empty: frames are matched near the estimate only")
        after_no_fixes = declare(self, "relocalise_after_no_fixes", 5,
                                 "no-fixes in a row in the landmark tile after which frames "
                                 "are searched in the whole mission index", min_value=1)
        self.pose_free_height_sigma = declare(
            self, "pose_free_height_sigma", 50.0,
            "cold start: height sigma of a pose-free frame's fix, whose height is the "
            "barometer's [m]", min_value=0.0)
        self.max_queue_wait = declare(
            self, "max_queue_wait", 1.0,
            "a camera set that waited longer than this in the node's queue (behind a slow "
            "search) is answered 'skipped' at once, so that the matcher catches up; its fix "
            "would reach the ekf late, after history_length [s]", min_value=0.0)
        flip_check_every = declare(
            self, "flip_check_every", 10,
            "every this many frames in a row scoring below the threshold, the frame mirrored "
            "back is tried too: a match says the camera image is flipped (0 = never)",
            min_value=0)
        check_parameters_known(self)  # before the matcher is built and its kernels loaded
        self.add_on_set_parameters_callback(reject_all_changes)
        self.mount = CameraMount(self, base_frame, mount_rpy)
        self.camera_frame = ""   # the CameraInfo's frame_id: the mount's end in /tf_static
        self.matcher = Matcher(settings_from_parameters(self, "match", MatchParams()))
        self.mission = self._open_mission(mission_dir)
        self.policy = SearchPolicy(after_no_fixes)
        self.landmarks = LandmarkSets(max_landmarks)
        self.velocity = FixVelocity(velocity_gap)
        self.tally = AnswerTally()
        self.flips = FlipCheck(flip_check_every)
        self.last_camera_wall: float | None = None
        self.pub = self.create_publisher(PvaFix, "nav/pva_fix", RELIABLE_QOS)
        self.dem = None          # (heights, georef) of the latest DEM tile
        self.camera_model: CameraIntrinsics | None = None
        # numba's kernels load on first use (~0.4 s; compiled, tens of seconds): not on the
        # first frame's clock, and before subscribing, so that a node with subscribers
        # answers at speed (a replay waits for them)
        warm_up(self.matcher.params)
        self.create_subscription(MinutiaArray, "landmark/minutiae", self.on_landmark,
                                 LATCHED_QOS)
        self.create_subscription(MinutiaArray, "camera/minutiae", self.on_camera_received,
                                 RELIABLE_QOS)
        self.create_subscription(DemTile, "metamap/tile", self.on_tile, LATCHED_QOS)
        self.create_subscription(CameraInfo, "camera/camera_info", self.on_info, SENSOR_QOS)
        self._started_wall = time.monotonic()
        publish_diagnostics(self, "matcher/diagnostics", diagnostics_period,
                            self.diagnostics)

    def _open_mission(self, mission_dir: str) -> MissionSearch | None:
        """The mission index to search when lost (None without one); a bad index stops the
        node at start-up, not in flight."""
        if not mission_dir:
            return None
        # imported here: a respawned matcher without a mission is up ~0.4 s sooner
        from ..core.matching.mission_index import MissionIndex, MissionIndexError

        mission = MissionSearch(MissionIndex(mission_dir), self.matcher.params)
        missing = mission.mission.missing()
        if missing:
            raise MissionIndexError(f"{mission_dir}: {len(missing)} tile layers missing: run "
                                    "terrain-nav prepare again to complete it")
        damaged = mission.mission.damaged()
        if damaged:
            raise MissionIndexError(f"{mission_dir}: {len(damaged)} tile layer(s) damaged, the "
                                    f"first: {damaged[0]}")
        self.get_logger().info(f"mission index {mission_dir}: {len(mission.mission.tiles())} "
                               f"tiles, {len(mission.mission.suns)} suns")
        return mission

    @contained
    def on_tile(self, msg: DemTile) -> None:
        try:
            self.dem = cv.msg_to_dem_tile(msg)
        except cv.ConversionError as err:
            self.get_logger().error(f"bad DemTile ignored: {err}")

    @contained
    def on_info(self, msg: CameraInfo) -> None:
        self.camera_frame = msg.header.frame_id
        try:
            k, d, model, (width, height) = cv.camera_info_to_intrinsics(msg)
        except cv.ConversionError:
            self.camera_model = None
            return
        self.camera_model = CameraIntrinsics.from_matrix(k, width, height, tuple(d), model)

    @contained
    def on_landmark(self, msg: MinutiaArray) -> None:
        try:
            minutiae = cv.msg_to_minutiae(msg)
            creases, ridges = cv.msg_to_creases(msg), cv.msg_to_ridges(msg)
        except cv.ConversionError as err:
            self.get_logger().error(f"landmark minutiae ignored: {err}")
            return
        index = None
        if len(minutiae):
            index = self.matcher.index(minutiae, creases, ridges).prepare_as_reference()
        self.landmarks.add(minutiae, index, cv.enu_origin_of(msg.georef))
        self.get_logger().info(f"landmark set with {len(minutiae)} minutiae "
                               f"({minutiae.reason or 'ok'})")

    def on_camera_received(self, msg: MinutiaArray, info) -> None:
        """rclpy passes a two-argument callback the message's info: when the middleware
        received it (system clock, ns; 0 where the rmw does not say)."""
        received = info.get("received_timestamp") if isinstance(info, dict) else None
        self.on_camera(msg, received or None)

    @contained
    def on_camera(self, msg: MinutiaArray, received_ns: int | None = None) -> None:
        start = self.last_camera_wall = time.monotonic()
        if self.mission is not None:
            # the layer a search would use, loaded before it is needed (in a thread)
            self.mission.prepare_in_background(cv.stamp_to_sec(msg.header.stamp))
        waited = 0.0 if received_ns is None else (time.time_ns() - received_ns) * 1e-9
        if waited > self.max_queue_wait:
            self.publish_no_fix(msg.header.stamp, f"skipped: waited {waited:.1f} s in the "
                                "queue (the matcher catches up after a slow answer)")
            return
        try:
            self._answer(msg)
            self.tally.answered(1e3 * (time.monotonic() - start))
        except Exception as err:
            # every frame gets an answer: the filter and the recorded bag see this one fail
            self.publish_no_fix(msg.header.stamp,
                                f"matching failed: {type(err).__name__}: {err}")
            raise   # logged and counted by @contained

    def _answer(self, msg: MinutiaArray) -> None:
        """A fix or a no-fix with its reason for one camera minutiae set."""
        if not msg.minutiae:   # flat terrain, or a frame with no minutiae set at all
            self.publish_no_fix(msg.header.stamp,
                                f"no camera minutiae: {msg.reason or 'none found'}")
            return
        try:
            camera = cv.msg_to_minutiae(msg)
            camera_creases, camera_ridges = cv.msg_to_creases(msg), cv.msg_to_ridges(msg)
        except cv.ConversionError as err:
            self.publish_no_fix(msg.header.stamp, f"bad camera minutiae: {err}")
            return
        projection = cv.get_projection(msg)
        if projection is None:
            self.publish_no_fix(msg.header.stamp, "camera minutiae carry no projection pose")
            return
        pose_free = cv.get_pose_free(msg)
        if pose_free is not None:
            self._relocalise_pose_free(msg, camera, camera_creases, camera_ridges, projection,
                                       pose_free)
            return
        landmark = self.landmarks.holding(*camera.georef.centre)
        covered = landmark is not None and landmark[1] is not None
        why = self.policy.reason_to_search(covered) if self.mission is not None else ""
        if why:
            self.policy.searched()
            self._relocalise(msg, camera, camera_creases, camera_ridges, projection, why)
            return
        self.policy.tile_answered(self._answer_in_tile(msg, camera, camera_creases,
                                                       camera_ridges, projection, landmark))

    def _answer_in_tile(self, msg: MinutiaArray, camera, camera_creases, camera_ridges,
                        projection, landmark) -> bool:
        """A fix or a no-fix of a camera set in the landmark tile holding it; whether it
        was a fix."""
        if landmark is None:
            self.publish_no_fix(msg.header.stamp, "no landmark covers the camera footprint")
            return False
        land_minutiae, land_index, origin = landmark
        camera_origin = cv.enu_origin_of(msg.georef)
        if not np.allclose(camera_origin, origin, rtol=0.0, atol=(1e-7, 1e-7, 1e-3)):
            # ENU of two origins are two maps: a match would put the fix at the landmark's
            # coordinates in the camera's map (camera_ingest sends (0, 0, 0) before a tile)
            self.publish_no_fix(msg.header.stamp,
                                f"the camera set's ENU origin {tuple(camera_origin)} is not the "
                                f"landmark's {tuple(origin)}")
            return False
        if land_index is None:
            self.publish_no_fix(msg.header.stamp,
                                f"no landmark minutiae: {land_minutiae.reason}")
            return False
        result = self.matcher.localise(
            self.matcher.index(camera, camera_creases, camera_ridges), land_index)
        # a track mosaic's frames lie where the dead reckoning put them: its scale mixes
        # theirs (the height) with their layout's (the velocity's error), and its minutiae
        # are not all the newest frame's pixels, which PnP would take them for
        mosaic = msg.mosaic_lag > 0.0
        fix = self._ground_fix(result, camera.georef, land_minutiae.georef, projection,
                               height_from_scale=not mosaic)
        if result.matched and self.method == "pnp" and not mosaic:
            position, rotation, _ = projection
            fix = checked_pnp(self.pnp_fix(result, camera, land_minutiae, position, rotation),
                              fix, self.pnp_gate, self.tilt_sigma)
        if self.flips.note(fix.valid, result.decision == Decision.NO_MATCH, mosaic):
            fix.reason += self._flipped(camera, camera_creases, camera_ridges, projection,
                                        land_index)
        if not fix.valid:
            self.publish_no_fix(msg.header.stamp, fix.reason, fix)
            return False
        fix.mosaic_lag = float(msg.mosaic_lag)   # a track mosaic's: the ekf models it
        self.publish_fix(msg.header.stamp, cv.stamp_to_sec(msg.header.stamp), fix, origin)
        return True

    def _flipped(self, camera, camera_creases, camera_ridges, projection, land_index) -> str:
        """What the camera set mirrored back across each flip's line says: "" when neither
        matches, else the flip named (and kept for the diagnostics). The two flips differ by
        a half turn, which a search of every rotation finds: the registration's turn names
        the flip."""
        position, rotation, plane = projection
        intr = self.camera_model    # the image centre's ray (the principal point's without)
        ray = (0.0, 0.0, 1.0) if intr is None else (
            (0.5 * (intr.width - 1) - intr.cx) / intr.fx,
            (0.5 * (intr.height - 1) - intr.cy) / intr.fy, 1.0)
        lines = FlipCheck.mirrors(position, rotation, plane, ray)
        for line, (anchor, axis) in lines.items():
            mirrored = mirrored_view(camera, camera_creases, camera_ridges, anchor, axis)
            result = self.matcher.localise(self.matcher.index(*mirrored), land_index)
            if result.matched:
                turned = result.transform[0, 0] < 0.0    # by more than a quarter turn
                flip = next(f for f in lines if (f != line) == turned)
                self.flips.found = flip
                self.get_logger().warning(
                    f"the camera image looks flipped {flip}: the frame flipped back matches "
                    f"the terrain (score {result.score:.1f}); check the camera driver's flip "
                    "options or the optics", throttle_duration_sec=10.0)
                return (f"; flipped back {flip} it matches (score {result.score:.1f}): is "
                        "the camera image flipped?")
        return ""

    def _relocalise(self, msg: MinutiaArray, camera, camera_creases, camera_ridges,
                    projection, why: str) -> None:
        """A fix marked as a relocalisation, or a no-fix, from a search of the camera set
        in the whole mission index. The ground match only: the DEM tile held for PnP lies
        around the estimate, which is what is in doubt."""
        origin = cv.enu_origin_of(msg.georef)
        stamp = cv.stamp_to_sec(msg.header.stamp)
        found, land_georef = self.mission.search(
            self.mission.matcher.index(camera, camera_creases, camera_ridges), stamp,
            EnuOrigin(*origin))
        if not found.matched:
            self.publish_no_fix(msg.header.stamp, f"relocalisation ({why}): {found.reason}")
            return
        fix = self._ground_fix(found.result, camera.georef, land_georef, projection,
                               height_from_scale=False)
        if not fix.valid:
            self.publish_no_fix(msg.header.stamp, f"relocalisation: {fix.reason}", fix)
            return
        # the ekf holds relocalisations and compares them by their covariances alone
        add_prior_tilt(fix, fix.projection_height, self.tilt_sigma)
        fix.relocalisation = True
        self.get_logger().info(f"relocalised ({why}) in tile {found.tile.key}, area score "
                               f"{found.score:.1f} over {found.searched} tiles")
        self.publish_fix(msg.header.stamp, stamp, fix, origin)

    def _relocalise_pose_free(self, msg: MinutiaArray, camera, camera_creases,
                              camera_ridges, projection, pose_free) -> None:
        """A relocalisation, or a no-fix, of a camera set projected without any pose (cold
        start): searched in the mission index at the scales its terrain range allows."""
        if self.mission is None:
            self.publish_no_fix(msg.header.stamp, "pose-free frame (cold start) without a "
                                "mission index to search: set the matcher's mission_dir")
            return
        position, rotation, plane = projection
        plane_min, plane_max, tilt_sigma = pose_free
        try:
            factors = scale_ladder(*scale_range(position[2], plane, plane_min, plane_max))
        except ValueError as err:
            self.publish_no_fix(msg.header.stamp, f"pose-free frame: {err}")
            return
        views = [rescaled_view(camera, camera_creases, camera_ridges, f, position[:2])
                 for f in factors]
        origin = cv.enu_origin_of(msg.georef)
        stamp = cv.stamp_to_sec(msg.header.stamp)
        found, land_georef, k = self.mission.search_ladder(
            [self.mission.matcher.index(*v) for v in views], stamp, EnuOrigin(*origin))
        if not found.matched:
            self.publish_no_fix(msg.header.stamp,
                                f"relocalisation (pose-free, cold start): {found.reason}")
            return
        # the view at rung k is the frame seen from factors[k] times its assumed height
        agl = factors[k] * (position[2] - plane)
        prior = np.array([position[0], position[1], plane + agl])
        fix = fix_from_ground_match(found.result, views[k][0].georef, land_georef, prior,
                                    rotation, plane, landmark_sigma=self.landmark_sigma)
        if not fix.valid:
            self.publish_no_fix(msg.header.stamp, f"relocalisation: {fix.reason}", fix)
            return
        measured_agl = float(fix.position[2] - plane)
        fix.position[2] = position[2]
        fix.covariance[2, 2] = self.pose_free_height_sigma ** 2
        add_prior_tilt(fix, measured_agl, tilt_sigma)
        fix.relocalisation = True
        self.get_logger().info(
            f"relocalised a pose-free frame in tile {found.tile.key} at scale "
            f"{factors[k]:.2f} ({len(factors)} scales), {measured_agl:.0f} m above ground, "
            f"area score {found.score:.1f} over {found.searched} tile searches")
        # its roll and pitch are camera_ingest's, measured apart from the filter
        self.publish_fix(msg.header.stamp, stamp, fix, origin, tilt_variance=tilt_sigma ** 2)

    def _ground_fix(self, result, camera_georef, landmark_georef, projection,
                    height_from_scale: bool = True) -> PvaFixEstimate:
        """The fix of a registration of the ground-projected camera set in a landmark
        raster. Its shift by the projection attitude's tilt error is left to the ekf, whose
        attitude that is (``projection_height``). Its height is measured by the
        registration's scale unless ``height_from_scale`` is False (a relocalisation, a
        track mosaic)."""
        position, rotation, plane = projection
        return fix_from_ground_match(result, camera_georef, landmark_georef, position,
                                     rotation, plane, landmark_sigma=self.landmark_sigma,
                                     height_from_scale=height_from_scale)

    def pnp_fix(self, result, camera, landmark, position, rotation) -> PvaFixEstimate | None:
        """Camera pose by PnP: raw-frame pixels of the camera minutiae against the DEM points
        of their landmark partners. The raw pixel of a ground-image minutia is recovered
        exactly by projecting its ground point (at the DEM height the orthorectification used)
        through the projection pose; unlike the ground shift, the result does not inherit
        the prior's tilt error (which moves a ground image by height x tilt)."""
        if self.dem is None or self.camera_model is None:
            return None
        heights, dem_georef = self.dem
        intr = self.camera_model
        east, north = camera.enu()
        u, v = ground_to_image(east, north, dem_heights(heights, dem_georef, east, north),
                               intr, CameraPose(position, rotation))
        pixels = np.column_stack([u, v])            # NaN: no DEM height or behind the camera
        dist = intr.dist_coeffs
        if intr.fisheye:     # PnP takes the polynomial models: give it the pinhole's pixels
            ok = np.isfinite(pixels).all(axis=1)
            pixels[ok] = intr.pinhole_pixels(*pixels[ok].T)
            dist = ()
        if np.isfinite(pixels).all(axis=1).sum() < 6:
            return None
        land_east, land_north = landmark.enu()
        land_h = dem_heights(heights, dem_georef, land_east, land_north)
        return fix_from_pnp(result, pixels, (land_east, land_north), land_h, intr.matrix,
                            dist, position, rotation, landmark_sigma=self.landmark_sigma)

    def publish_no_fix(self, stamp, reason: str, fix: PvaFixEstimate | None = None) -> None:
        out = PvaFix(header=cv.make_header(stamp, self.frame_id),
                     status=PvaFix.STATUS_NO_FIX, reason=reason)
        if fix is not None:
            out.similarity = float(fix.similarity) if math.isfinite(fix.similarity) else 0.0
            out.num_pairings = fix.num_pairings
            out.num_camera_minutiae = fix.num_camera_minutiae
            out.num_landmark_minutiae = fix.num_landmark_minutiae
        out.pose.covariance = cv.array_to_covariance(-np.eye(6))
        self.pub.publish(out)
        self.tally.no_fix(reason)
        self.get_logger().info(f"no fix: {reason}", throttle_duration_sec=2.0)

    def publish_fix(self, stamp, stamp_s: float, fix: PvaFixEstimate, origin,
                    tilt_variance: float = UNOBSERVED_TILT_VAR) -> None:
        inflate_covariance(fix, self.covariance_scale)
        r_enu_body = fix_attitude(fix, self.mount.rotation(self.camera_frame), self.use_heading,
                                  self.heading_floor, tilt_variance)
        quaternion = Rotation.from_matrix(r_enu_body).as_quat()
        out = PvaFix(header=cv.make_header(stamp, self.frame_id), status=fix.status,
                     reason=fix.reason, similarity=float(fix.similarity),
                     num_pairings=fix.num_pairings,
                     num_camera_minutiae=fix.num_camera_minutiae,
                     num_landmark_minutiae=fix.num_landmark_minutiae,
                     relocalisation=bool(fix.relocalisation),
                     projection_height=float(fix.projection_height),
                     mosaic_lag=float(fix.mosaic_lag),
                     pose=cv.pose_with_covariance(fix.position, quaternion, fix.covariance))
        lat, lon, alt = EnuOrigin(*origin).enu_to_geodetic(*fix.position)
        out.latitude, out.longitude, out.altitude = float(lat), float(lon), float(alt)
        velocity = self.velocity.update(stamp_s, fix.position, fix.covariance,
                                        mosaic=fix.mosaic_lag > 0.0,
                                        relocalisation=fix.relocalisation)
        if velocity is not None:
            out.velocity_valid = True
            out.velocity.x, out.velocity.y, out.velocity.z = map(float, velocity[0])
            out.velocity_covariance = velocity[1].ravel()
        self.pub.publish(out)
        self.tally.fix(fix.similarity, fix.num_pairings, time.monotonic())
        sigma = math.sqrt(max(fix.covariance[0, 0] + fix.covariance[1, 1], 0.0))
        self.get_logger().info(
            f"fix ({fix.position[0]:.0f}, {fix.position[1]:.0f}) m +- {sigma:.0f} m, "
            f"{fix.num_pairings} pairings, score {fix.similarity:.1f}")

    def diagnostics(self) -> list:
        """Fixes and no-fixes so far (these by reason), the time per camera set since the
        last report; a warning when camera minutiae stop coming or no landmark set is held,
        an error when matching failed since the last report."""
        now = time.monotonic()
        failures, new = new_failures(self)
        level, message, values = self.tally.report(
            now, now - (self.last_camera_wall or self._started_wall), self.camera_timeout,
            self.landmarks.any_with_minutiae, failures, new, len(self.landmarks))
        values["camera_flipped"] = self.flips.found
        if self.flips.found:
            level = max(level, DIAG_WARN)
            message = (f"the camera image looks flipped {self.flips.found} (frames mirrored "
                       f"back match the terrain); {message}")
        return [cv.diagnostic_status("matcher", level, message, values, "terrain_nav")]


def main(args=None):
    return run(MatcherNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
