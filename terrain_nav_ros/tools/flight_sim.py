"""Flight simulator: a GPS-denied flight over any supported DEM, written as a rosbag2 MCAP bag.

``terrain-nav simulate`` flies a ScanEagle-class aircraft (trajectory and IMU kinematics from
:mod:`.core.sim.trajectory_sim`) over a DEM and records what its sensors would have produced, on
standard topics so any ROS tool reads the bag:

=========================================  ==================================  ===============
topic                                      type                                frame
=========================================  ==================================  ===============
/imu/data                                  sensor_msgs/Imu                     base_link
/baro/pressure                             sensor_msgs/FluidPressure           base_link
/gnss/fix                                  sensor_msgs/NavSatFix               gnss_link
/camera/image_raw[/compressed]             sensor_msgs/Image|CompressedImage   camera_optical
/camera/camera_info                        sensor_msgs/CameraInfo              camera_optical
/ground_truth/odometry                     nav_msgs/Odometry                   map->base_link
/tf_static                                 tf2_msgs/TFMessage (latched)        base->camera
=========================================  ==================================  ===============

Camera frames are rendered in perspective from the true pose by the landmark renderer, but
made to look like a camera rather than a landmark: another sun, another albedo, haze, auto
exposure, blur, vignetting, lens distortion (published in CameraInfo) and sensor noise
(:mod:`.core.render.camera_effects`). With ``albedo`` a real orthoimage is draped over the terrain
instead and shown as it is (its own sun, snow, forest, fields and roads), and ``start_time``
puts the bag at the image's acquisition, so the landmarks are lit by its sun. With
``cloud_cover`` a sheet of broken cloud drifts with the wind between the camera and the
ground, shadows included (:mod:`.core.render.cloud_layer`). GNSS is denied
from a configurable time. Everything is deterministic given the seed. A ``mission.yaml``
beside the MCAP file records the DEM, the ENU origin and the camera mount, so the replay
configures the graph to match.
"""

from __future__ import annotations

import heapq
import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from ..core.camera.camera_mount import R_BODY_OPTICAL_NADIR, camera_rotation
from ..core.estimation.baro import altitude_to_pressure
from ..core.estimation.ekf_params import EkfParams, map_bias_sigma
from ..core.estimation.strapdown import quat_conjugate, quat_rotate
from ..core.render.camera_effects import CameraEffects, apply_camera_effects, distortion_maps
from ..core.render.cloud_layer import CloudLayer
from ..core.render.renderer import (
    AlbedoRamp,
    LandmarkRenderer,
    PinholeCamera,
    create_headless_context,
)
from ..core.sim.imu_sim import ImuErrorModel, simulate_imu
from ..core.sim.trajectory_sim import Segment, simulate_trajectory, survey_flight, turning_flight
from ..core.terrain.dem_io import Dem
from ..core.terrain.dem_sources import open_dem_source
from ..core.terrain.geodesy import EnuOrigin
from ..core.terrain.georef import GeoReference
from ..core.terrain.metamap import MetaMap, OutsideDemError
from . import bags
from .report import plain

EPOCH_NS = 1_782_048_600_000_000_000  # 2026-06-21T13:30:00Z: bag time of t = 0 (a morning
#                                         flight over North America: the sun low in the east)


@dataclass
class SimConfig:
    """Everything that defines a simulated flight (all SI units, angles in degrees)."""

    dem: str = ""                    # DEM file or source name (see core/terrain/dem_sources.py);
    #                                  "" = the embedded Jacksboro DEM
    origin_latitude: float = math.nan   # ENU origin; NaN = the DEM centre
    origin_longitude: float = math.nan
    duration: float = 120.0          # s
    pattern: str = "survey"          # survey | turns | straight
    leg_duration: float = 60.0       # s, straight legs of the survey pattern
    speed: float = 30.0              # m/s airspeed
    heading: float = 0.0             # deg, initial heading from East, counter-clockwise
    start_east: float = 0.0          # m, start position in ENU
    start_north: float = 0.0
    # A multi-kilometre footprint: a 3" (~90 m) DEM has a few valleys per kilometre, and the
    # matcher needs tens of minutiae per frame (see README, "Flight geometry").
    agl: float = 3000.0              # m above the highest terrain under the route
    wind: tuple = (3.0, -2.0)        # m/s, east/north
    imu_rate: float = 100.0          # Hz
    camera_rate: float = 1.0         # Hz
    camera_width: int = 512
    camera_height: int = 384
    camera_hfov: float = 80.0        # deg
    image_format: str = "jpeg"       # jpeg (CompressedImage) | rgb8 | mono8 (Image)
    jpeg_quality: int = 90
    render_gsd: float = 0.0          # m, terrain grid for rendering; 0 = native DEM GSD / 2
    sun: tuple = ()                  # deg (azimuth from north clockwise, elevation);
    #                                  empty = the solar position at the flight's time and place
    gnss_rate: float = 5.0           # Hz
    gnss_sigma: float = 2.0          # m horizontal (vertical x2)
    gnss_denied_after: float = 20.0  # s; the GNSS is lost from then on
    gnss_denial: str = "stop"        # stop (no messages) | nofix (STATUS_NO_FIX messages)
    baro_rate: float = 10.0          # Hz
    baro_sigma: float = 10.0         # Pa (about 0.9 m)
    truth_rate: float = 20.0         # Hz
    seed: int = 1
    landmark_gsd: float = 20.0       # m/px the replay's metamap and camera_ingest should use
    dem_ce90: float = 0.0            # m, the DEM's stated horizontal accuracy (circular
    #                                  error at 90 %), written into mission.yaml for the
    #                                  replay's ekf; 0 = not stated (the ekf's default)
    albedo: str = ""                 # a real orthoimage (any georeferenced raster) draped
    #                                  over the terrain for the camera frames, shown as it
    #                                  is (it holds its own sun); "" = the rendered albedo
    albedo_band: str = ""            # its band (1-based) as grey; "" = bands 1-3 as RGB
    albedo_shift: str = "none"       # where the image is draped: "none" = at its
    #                                  georeference, "measured" = shifted back by the offset
    #                                  its shading shows from the DEM's (when that is
    #                                  judged), "E,N" = by E, N m
    start_time: str = ""             # ISO 8601 UTC bag time of t = 0 (with --albedo: the
    #                                  image's acquisition, so landmarks get its sun);
    #                                  "" = 2026-06-21T13:30:00Z
    cloud_cover: float = 0.0         # fraction of the sky under broken cloud, [0, 1)
    cloud_base: float = 1500.0       # m, height of the cloud sheet above the median terrain
    #                                  under the flight (drifts with the wind)
    cloud_size: float = 1500.0       # m, typical cloud diameter
    effects: CameraEffects = field(default_factory=CameraEffects)


# Camera albedo: greener valleys and browner slopes than the landmark ramp, another season.
CAMERA_ALBEDO = AlbedoRamp(tree_line=850.0, vegetation=(0.16, 0.22, 0.10),
                           lowland=(0.30, 0.30, 0.16), rock=(0.42, 0.36, 0.30), blend=120.0)


def _segments(cfg: SimConfig) -> list[Segment]:
    if cfg.pattern == "survey":
        return survey_flight(cfg.duration, cfg.leg_duration)
    if cfg.pattern == "turns":
        return turning_flight(cfg.duration)
    if cfg.pattern == "straight":
        return [Segment(cfg.duration)]
    raise ValueError(f"unknown flight pattern {cfg.pattern!r} (survey, turns, straight)")


def _open_metamap(cfg: SimConfig) -> tuple[MetaMap, str]:
    dem = open_dem_source(cfg.dem)
    origin = None
    if math.isfinite(cfg.origin_latitude) and math.isfinite(cfg.origin_longitude):
        origin = EnuOrigin(cfg.origin_latitude, cfg.origin_longitude, 0.0)
    return MetaMap(dem, origin, interpolation="bicubic", fill_voids=True, heights="enu"), \
        dem.name


def fly(cfg: SimConfig, metamap: MetaMap):
    """Truth trajectory at ``agl`` above the highest point under the route, and the lowest
    terrain height under the route (m)."""
    segs = _segments(cfg)
    truth = simulate_trajectory(segs, cfg.imu_rate, cfg.speed,
                                (cfg.start_east, cfg.start_north, 0.0),
                                math.radians(cfg.heading))
    truth = truth.in_wind(*cfg.wind)
    pos = truth.position.copy()
    west, east = pos[:, 0].min() - 500.0, pos[:, 0].max() + 500.0
    south, north = pos[:, 1].min() - 500.0, pos[:, 1].max() + 500.0
    gsd = max(metamap.native_gsd, (east - west) / 2000.0)
    box = GeoReference(west, north, gsd, int((east - west) / gsd) + 1,
                       int((north - south) / gsd) + 1)
    ground = metamap.tile(box).elevation
    if np.isnan(ground).all():
        raise SimInputError("the DEM has no heights under the route: it is all nodata (voids) "
                         "there; give a DEM with elevations")
    if np.isnan(ground).any():
        raise SimInputError(f"the route leaves the DEM (ENU box {west:.0f}..{east:.0f} E, "
                         f"{south:.0f}..{north:.0f} N); move start_east/start_north")
    pos[:, 2] += float(np.nanmax(ground)) + cfg.agl
    return replace(truth, position=pos), float(np.nanmin(ground))


def pinhole(cfg: SimConfig) -> PinholeCamera:
    f = 0.5 * cfg.camera_width / math.tan(math.radians(cfg.camera_hfov) / 2)
    return PinholeCamera(f, f, (cfg.camera_width - 1) / 2, (cfg.camera_height - 1) / 2,
                         cfg.camera_width, cfg.camera_height)


class _Messages:
    """rosbags message objects for the standard types the bag holds."""

    def __init__(self):
        self.t = bags.typestore().types

    def header(self, t_ns: int, frame: str):
        sec, nanosec = divmod(int(t_ns), 1_000_000_000)
        return self.t["std_msgs/msg/Header"](
            stamp=self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id=frame)

    def vec(self, v):
        return self.t["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, q):
        return self.t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]),
                                                      z=float(q[2]), w=float(q[3]))

    def imu(self, t_ns, gyro, accel, gyro_var, accel_var):
        cov_o = np.zeros(9)
        cov_o[0] = -1.0  # no orientation estimate in this message
        return self.t["sensor_msgs/msg/Imu"](
            header=self.header(t_ns, "base_link"), orientation=self.quat((0, 0, 0, 1)),
            orientation_covariance=cov_o, angular_velocity=self.vec(gyro),
            angular_velocity_covariance=np.eye(3).ravel() * gyro_var,
            linear_acceleration=self.vec(accel),
            linear_acceleration_covariance=np.eye(3).ravel() * accel_var)

    def navsat(self, t_ns, lat, lon, alt, status, sigma_h):
        fix = self.t["sensor_msgs/msg/NavSatFix"]
        cov = np.diag([sigma_h ** 2, sigma_h ** 2, (2 * sigma_h) ** 2]).ravel()
        return fix(header=self.header(t_ns, "gnss_link"),
                   status=self.t["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
                   latitude=float(lat), longitude=float(lon), altitude=float(alt),
                   position_covariance=cov, position_covariance_type=2)

    def pressure(self, t_ns, pascal, variance):
        return self.t["sensor_msgs/msg/FluidPressure"](
            header=self.header(t_ns, "base_link"), fluid_pressure=float(pascal),
            variance=float(variance))

    def odometry(self, t_ns, p, q, v_enu):
        msgs = self.t
        pose = msgs["geometry_msgs/msg/Pose"](
            position=msgs["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]),
                                                     z=float(p[2])),
            orientation=self.quat(q))
        v_body = quat_rotate(quat_conjugate(q), v_enu)  # twist is in the child frame
        twist = msgs["geometry_msgs/msg/Twist"](linear=self.vec(v_body),
                                                angular=self.vec((0, 0, 0)))
        return msgs["nav_msgs/msg/Odometry"](
            header=self.header(t_ns, "map"), child_frame_id="base_link",
            pose=msgs["geometry_msgs/msg/PoseWithCovariance"](pose=pose,
                                                              covariance=np.zeros(36)),
            twist=msgs["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                covariance=np.zeros(36)))

    def camera_info(self, t_ns, cam: PinholeCamera, dist):
        k = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], float)
        p = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0], float)
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                         width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(t_ns, "camera_optical"), height=cam.height, width=cam.width,
            distortion_model="plumb_bob", d=np.asarray(dist, float), k=k,
            r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0, roi=roi)

    def image(self, t_ns, rgb: np.ndarray, fmt: str, quality: int):
        header = self.header(t_ns, "camera_optical")
        if fmt == "jpeg":
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                                    [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
            if not ok:
                raise RuntimeError("JPEG encoding failed")
            return "sensor_msgs/msg/CompressedImage", self.t["sensor_msgs/msg/CompressedImage"](
                header=header, format="rgb8; jpeg compressed bgr8",
                data=np.frombuffer(data.tobytes(), np.uint8))
        if fmt == "mono8":
            rgb = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        elif fmt != "rgb8":
            raise ValueError(f"unknown image_format {fmt!r} (jpeg, rgb8, mono8)")
        channels = 1 if rgb.ndim == 2 else 3
        return "sensor_msgs/msg/Image", self.t["sensor_msgs/msg/Image"](
            header=header, height=rgb.shape[0], width=rgb.shape[1], encoding=fmt,
            is_bigendian=0, step=rgb.shape[1] * channels,
            data=np.ascontiguousarray(rgb).reshape(-1))

    def static_tf(self, t_ns, parent, child, r_parent_child):
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(r_parent_child).as_quat()  # x, y, z, w
        tf = self.t["geometry_msgs/msg/TransformStamped"](
            header=self.header(t_ns, parent), child_frame_id=child,
            transform=self.t["geometry_msgs/msg/Transform"](
                translation=self.vec((0, 0, -0.1)), rotation=self.quat(q)))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=[tf])


def _say(text: str) -> None:
    print(f"[simulate] {text}", file=sys.stderr, flush=True)


def _progress(done: int, total: int, started: float, what: str) -> None:
    """One line per tenth of the work, so long runs show progress in logs too."""
    if done == total or done % max(1, total // 10) == 0:
        rate = done / max(time.monotonic() - started, 1e-9)
        _say(f"{what}: {done}/{total} ({rate:.1f}/s)")


def simulate(cfg: SimConfig, output: str | Path) -> dict:
    """Fly ``cfg`` and write the bag to ``output`` (a new directory); return a summary.

    The messages are made as they are written, in stamp order, so memory does not grow with
    the flight's length; a flight that fails part-way leaves no bag.
    """
    output = Path(output)
    _cloud_layer(cfg, 0.0)   # bad cloud settings fail before the flight is flown
    parse_albedo_shift(cfg.albedo_shift)   # and a bad shift
    if cfg.dem_ce90:                       # and a bad accuracy
        try:
            map_bias_sigma(cfg.dem_ce90)
        except ValueError as err:
            raise SimInputError(f"the DEM's horizontal accuracy: {err}") from None
    rng = np.random.default_rng(cfg.seed)
    metamap, dem_name = _open_metamap(cfg)
    truth, ground_low = fly(cfg, metamap)
    t_ns = _epoch_ns(cfg.start_time) + np.rint(truth.t * 1e9).astype(np.int64)
    params = EkfParams()
    imu = simulate_imu(truth, ImuErrorModel.from_params(params), rng)
    msgs = _Messages()
    # every random draw but the camera's is made here, the camera's frame by frame after
    # them: the bag is the same whatever order the streams are merged in
    streams = [_imu_messages(cfg, params, imu, t_ns, msgs),
               _truth_messages(cfg, truth, t_ns, msgs),
               _baro_messages(cfg, truth, metamap.origin, t_ns, msgs, rng),
               _gnss_messages(cfg, truth, metamap.origin, t_ns, msgs, rng)]
    sun = tuple(cfg.sun) if cfg.sun else _solar(metamap.origin, t_ns[0])
    camera = _CameraFrames(cfg, metamap, truth, t_ns, msgs, sun)
    streams.append(camera.messages(rng))
    try:
        writer = bags.BagWriter(output, compress=True)   # refuses an existing one
    except BaseException:
        camera.release()
        raise
    try:
        with writer:
            writer.add_topic("/tf_static", "tf2_msgs/msg/TFMessage",
                             bags.qos_profile(reliable=True, transient_local=True, depth=1))
            writer.write_message("/tf_static", t_ns[0], msgs.static_tf(
                t_ns[0], "base_link", "camera_optical", R_BODY_OPTICAL_NADIR),
                "tf2_msgs/msg/TFMessage")
            for stamp, topic, msgtype, msg in heapq.merge(*streams, key=lambda m: m[0]):
                writer.write_message(topic, stamp, msg, msgtype)
    except BaseException:
        shutil.rmtree(output, ignore_errors=True)
        raise
    finally:
        camera.release()
    summary = {
        "dem": dem_name, "origin": [metamap.origin.lat, metamap.origin.lon, metamap.origin.alt],
        "duration_s": float(truth.t[-1]), "camera_frames": len(camera.idx),
        "gnss_denied_after_s": cfg.gnss_denied_after,
        "altitude_m": float(truth.position[0, 2]),
        "camera_mount": "nadir", "landmark_gsd": cfg.landmark_gsd,
        "sun_azimuth_elevation": [float(sun[0]), float(sun[1])],
        # ground radius the camera sees from the cruise height (half-diagonal of the view)
        "camera_footprint_radius": float((truth.position[:, 2].max() - ground_low)
                                         * math.tan(math.radians(cfg.camera_hfov) / 2) * 1.3),
        "config": plain(asdict(cfg)),
    }
    if cfg.dem_ce90:
        summary["dem_horizontal_ce90"] = float(cfg.dem_ce90)
    if cfg.albedo:   # the offset the image was draped shifted back by (0, 0: as it is)
        summary["albedo_shift_m"] = list(camera.albedo_shift)
    (output / "mission.yaml").write_text(yaml.safe_dump(summary, sort_keys=False))
    return summary


def _imu_messages(cfg: SimConfig, params: EkfParams, imu, t_ns, msgs: _Messages):
    dt = 1.0 / cfg.imu_rate
    gyro_var = params.gyro_noise_density ** 2 / dt
    accel_var = params.accel_noise_density ** 2 / dt
    for k in range(1, len(t_ns)):
        yield (t_ns[k], "/imu/data", "sensor_msgs/msg/Imu",
               msgs.imu(t_ns[k], imu.gyro[k], imu.accel[k], gyro_var, accel_var))


def _truth_messages(cfg: SimConfig, truth, t_ns, msgs: _Messages):
    for k in truth.at(np.arange(0.0, truth.t[-1], 1.0 / cfg.truth_rate)):
        yield (t_ns[k], "/ground_truth/odometry", "nav_msgs/msg/Odometry",
               msgs.odometry(t_ns[k], truth.position[k], truth.quaternion[k],
                             truth.velocity[k]))


def _baro_messages(cfg: SimConfig, truth, origin: EnuOrigin, t_ns, msgs: _Messages, rng):
    """The barometer's messages (its noise drawn now, not as they are made)."""
    idx = truth.at(np.arange(0.0, truth.t[-1], 1.0 / cfg.baro_rate))
    # Pressure altitude ~ orthometric height; the ENU up differs by a constant the EKF learns.
    pressure = altitude_to_pressure(truth.position[idx, 2] + origin.alt)
    pressure += rng.normal(0.0, cfg.baro_sigma, len(idx))
    return ((t_ns[k], "/baro/pressure", "sensor_msgs/msg/FluidPressure",
             msgs.pressure(t_ns[k], p, cfg.baro_sigma ** 2))
            for k, p in zip(idx, pressure, strict=True))


def _gnss_messages(cfg: SimConfig, truth, origin: EnuOrigin, t_ns, msgs: _Messages, rng):
    """The GNSS receiver's messages (its noise drawn now, not as they are made)."""
    idx = truth.at(np.arange(0.0, truth.t[-1], 1.0 / cfg.gnss_rate))
    noise = rng.normal(0.0, 1.0, (len(idx), 3)) * [cfg.gnss_sigma, cfg.gnss_sigma,
                                                   2 * cfg.gnss_sigma]

    def messages():
        for k, e in zip(idx, noise, strict=True):
            denied = truth.t[k] >= cfg.gnss_denied_after
            if denied and cfg.gnss_denial == "stop":
                continue
            lat, lon, alt = origin.enu_to_geodetic(*(truth.position[k] + e))
            status = -1 if denied else 0
            if denied:
                lat = lon = alt = math.nan
            yield (t_ns[k], "/gnss/fix", "sensor_msgs/msg/NavSatFix",
                   msgs.navsat(t_ns[k], lat, lon, alt, status, cfg.gnss_sigma))

    return messages()


class SimInputError(ValueError):
    """Bad simulator input: an albedo image that cannot be draped (unreadable, no CRS, no
    such band, elsewhere), a start time that is not ISO 8601 or falls at night there, or a
    route the DEM does not cover with heights."""


def _epoch_ns(start_time: str) -> int:
    """Bag time (ns) of t = 0: ``start_time`` (ISO 8601, UTC unless stated) or EPOCH_NS."""
    if not start_time:
        return EPOCH_NS
    from ..core.render.sun import parse_utc
    try:
        return int(round(parse_utc(start_time).timestamp() * 1e9))
    except ValueError as err:
        raise SimInputError(f"start {err}") from None


def drape_photo(path: str, band: str, metamap: MetaMap, box: GeoReference
                ) -> tuple[np.ndarray, np.ndarray]:
    """A real orthoimage sampled on the render grid ``box``: (rows, cols, 3) in [0, 1],
    stretched between its 1st and 99th percentiles (raw DN or reflectance alike), and the
    (rows, cols) cells it covers; cells it does not cover are its median grey.

    The image is read as the real-imagery study reads it
    (:class:`~.core.terrain.ortho_io.OrthoImage`: nodata, undeclared fill, palettes, control
    points). Each band goes through a :class:`MetaMap` of its own with the terrain's origin,
    the same reprojection as the heights; an image much finer than the grid is first
    averaged down to it (no aliasing of 2.5 m detail on a 45 m grid).
    """
    from affine import Affine

    from ..core.terrain.ortho_io import ImageError, OrthoImage, ground_cell_metres

    try:
        with OrthoImage(path) as src:
            # one band as grey, or the first three as colours
            bands = [int(band)] * 3 if band else [min(k, src.count) for k in (1, 2, 3)]
            data = src.read(bands)
            transform, crs = src.transform, src.crs
            if src.warning:
                _say(f"warning: {src.warning}")
    except ImageError as err:
        raise SimInputError(f"the albedo image: {err}") from err
    cell_m = ground_cell_metres(crs, transform, data.shape[1:])
    factor = int(box.gsd // max(cell_m, 1e-9))
    if factor >= 2:   # average down: the render grid cannot hold finer detail
        rows, cols = data.shape[1:]
        data = np.stack([cv2.resize(np.nan_to_num(b, nan=float(np.nanmedian(b))), None,
                                    fx=1.0 / factor, fy=1.0 / factor,
                                    interpolation=cv2.INTER_AREA) for b in data])
        transform = transform @ Affine.scale(cols / data.shape[2], rows / data.shape[1])
    rgb = np.empty((*box.shape, 3), np.float32)
    for k in range(3):
        dem = Dem.from_array(data[k], transform, crs, name=f"{Path(path).name} band {k}")
        try:
            tile = MetaMap(dem, metamap.origin, interpolation="bilinear").tile(box)
        except OutsideDemError:
            tile = None
        if tile is None or tile.nodata.all():
            raise SimInputError(f"{path}: the albedo image does not cover the flight's terrain")
        rgb[..., k] = np.where(tile.nodata, np.nan, tile.elevation)
    covered = np.isfinite(rgb).all(axis=-1)
    lo, hi = np.percentile(rgb[covered], [1.0, 99.0])
    rgb = np.clip((rgb - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    rgb[~covered] = np.median(rgb[covered], axis=0)
    return rgb, covered


def albedo_registration(photo: np.ndarray, covered: np.ndarray, heights: np.ndarray,
                        box: GeoReference, sun, dem_cell: float):
    """Where the draped ``photo``'s terrain lies from the terrain ``heights`` (both on
    ``box``), by its shading (:class:`~.core.features.hillshade.ShadingAgreement`): the
    camera sees the photo's ground while the truth is the DEM's, so a fix is off by the
    offset. ``heights`` are NaN beyond the DEM; ``sun`` is the photo's (its acquisition's)."""
    from ..core.features.hillshade import shading_agreement

    return shading_agreement(photo.mean(axis=-1), heights, box.gsd, sun, covered,
                             cell=dem_cell / box.gsd)


def parse_albedo_shift(text: str) -> str | tuple[float, float]:
    """``SimConfig.albedo_shift``: "measured", "none" or (east, north) m."""
    if text in ("measured", "none"):
        return text
    try:
        east, north = (float(v) for v in text.split(","))
    except ValueError:
        raise SimInputError(f"albedo shift {text!r}: 'measured', 'none' or 'E,N' in metres"
                            ) from None
    if not (math.isfinite(east) and math.isfinite(north)):
        raise SimInputError(f"albedo shift {text!r}: not finite")
    return east, north


def drape_registered(cfg: SimConfig, metamap: MetaMap, box: GeoReference,
                     heights: np.ndarray, sun) -> tuple[np.ndarray, tuple[float, float]]:
    """``cfg.albedo`` draped on ``box`` (:func:`drape_photo`), shifted by
    ``cfg.albedo_shift``, and the shift (east, north m; the image's terrain moved by
    minus it). "measured" takes the offset the image's shading shows from ``heights``
    (:func:`albedo_registration`), so that a pair out of register (Costa Rica's, ~2 DEM
    cells) still gives a camera that sees the DEM's ground and fixes true to the truth; an
    offset not judged (a faint image) is no shift. Each choice is said on stderr."""
    shift = parse_albedo_shift(cfg.albedo_shift)
    photo, covered = drape_photo(cfg.albedo, cfg.albedo_band, metamap, box)
    if shift == "measured":
        found = albedo_registration(photo, covered, heights, box, sun, metamap.native_gsd)
        if not (found.offset_judged and np.isfinite([found.offset_east,
                                                      found.offset_north]).all()):
            _say("the albedo image's registration to its DEM is not judged by its shading "
                 f"(correlation {found.r_offset:.2f}): draped at its georeference")
            return photo, (0.0, 0.0)
        shift = found.offset_east, found.offset_north
        _say(f"the albedo image's terrain lies {shift[0]:+.0f} m east and {shift[1]:+.0f} m "
             f"north of its DEM's ({math.hypot(*shift) / metamap.native_gsd:.1f} DEM cells, "
             "by its shading): draped shifted back by that")
    elif shift == "none":
        found = albedo_registration(photo, covered, heights, box, sun, metamap.native_gsd)
        if warning := found.registration_warning():
            _say(f"warning: the albedo image: {warning}")
        return photo, (0.0, 0.0)
    east, north = shift
    if east or north:   # the grid moved by the offset samples the image's terrain where
        #                 the DEM has it
        photo, _ = drape_photo(cfg.albedo, cfg.albedo_band, metamap, replace(
            box, origin_east=box.origin_east + east, origin_north=box.origin_north + north))
    return photo, (float(east), float(north))


def _solar(origin: EnuOrigin, t_ns: int) -> tuple[float, float]:
    from ..core.render.sun import sun_at

    az, el = sun_at(t_ns * 1e-9, origin.lat, origin.lon)
    if el < 5.0:
        raise SimInputError(f"the sun is {el:.1f} deg high at the flight's time there: "
                            "night; give a daytime --start-time")
    return az, el


def _cloud_layer(cfg: SimConfig, ground_height: float) -> CloudLayer:
    """The flight's cloud sheet, ``cloud_base`` m above ``ground_height`` (ENU m)."""
    try:
        return CloudLayer(cover=cfg.cloud_cover, base=ground_height + cfg.cloud_base,
                          size=cfg.cloud_size, wind=tuple(cfg.wind), seed=cfg.seed)
    except ValueError as err:
        raise SimInputError(str(err)) from None


class _CameraFrames:
    """The camera's frames, rendered one by one as they are asked for (the renderer, the
    draped image and the clouds are set up at once, so that their errors come before any
    bag is written)."""

    def __init__(self, cfg: SimConfig, metamap: MetaMap, truth, t_ns, msgs: _Messages, sun):
        self.cfg, self.truth, self.t_ns, self.msgs, self.sun = cfg, truth, t_ns, msgs, sun
        self.albedo_shift = (0.0, 0.0)
        self.cam = cam = pinhole(cfg)
        self.maps = distortion_maps(
            np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]]),
            cfg.effects.distortion, cam.width, cam.height)
        self.idx = truth.at(np.arange(1.0 / cfg.camera_rate, truth.t[-1], 1.0 / cfg.camera_rate))
        pos = truth.position[self.idx]
        margin = 1.5 * (pos[:, 2].max()) * math.tan(math.radians(cfg.camera_hfov))
        gsd = cfg.render_gsd or metamap.native_gsd / 2
        west, east = pos[:, 0].min() - margin, pos[:, 0].max() + margin
        south, north = pos[:, 1].min() - margin, pos[:, 1].max() + margin
        gsd = max(gsd, (east - west) / 4096, (north - south) / 4096)
        box = GeoReference(west, north, gsd, int((east - west) / gsd) + 1,
                           int((north - south) / gsd) + 1)
        tile = metamap.tile(box)
        heights = np.where(tile.nodata, np.nanmin(tile.elevation), tile.elevation)
        self.renderer = LandmarkRenderer(create_headless_context(), albedo=CAMERA_ALBEDO,
                                         shadows=True)
        try:
            self.renderer.set_terrain(heights, box)
            if cfg.albedo:
                photo, self.albedo_shift = drape_registered(
                    cfg, metamap, box, np.where(tile.nodata, np.nan, tile.elevation), sun)
                self.renderer.set_photo(photo)
        except BaseException:
            self.release()
            raise
        self.clouds = _cloud_layer(cfg, float(np.median(heights)))

    def messages(self, rng):
        """Each frame's image and CameraInfo messages, in time order."""
        cfg, truth, msgs = self.cfg, self.truth, self.msgs
        topic = "/camera/image_raw/compressed" if cfg.image_format == "jpeg" \
            else "/camera/image_raw"
        started = time.monotonic()
        for n, k in enumerate(self.idx):
            stamp = self.t_ns[k]
            r = camera_rotation(truth.quaternion[k])
            result = self.renderer.render_perspective(self.cam, truth.position[k], r,
                                                      sun=self.sun)
            ground = result.hit_enu
            distance = np.linalg.norm(ground - truth.position[k], axis=-1)
            radiance, _ = self.clouds.apply(result.rgb, truth.position[k], ground, self.sun,
                                            truth.t[k])
            rgb = apply_camera_effects(radiance, distance, cfg.effects, rng, self.maps)
            msgtype, image = msgs.image(stamp, rgb, cfg.image_format, cfg.jpeg_quality)
            yield stamp, topic, msgtype, image
            yield (stamp, "/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                   msgs.camera_info(stamp, self.cam, cfg.effects.distortion))
            _progress(n + 1, len(self.idx), started, "camera frames")

    def release(self):
        if self.renderer is not None:
            self.renderer.release()
            self.renderer = None
