"""The one place where ROS messages meet numpy arrays and core types.

Nodes call these functions at their boundaries and hand arrays to
:mod:`terrain_nav_ros.core`. Large arrays are copied with ``tobytes``/``frombuffer``: assigning
an ndarray to a message's sequence field goes element by element (22 ms for a 512^2 image).
"""

from __future__ import annotations

import array
import math
from typing import NamedTuple

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseWithCovariance, PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import (
    CameraInfo,
    CompressedImage,
    FluidPressure,
    Image,
    Imu,
    NavSatFix,
    NavSatStatus,
)
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from terrain_nav_msgs.msg import DemTile, GeoImage, Minutia, MinutiaArray, PvaFix
from terrain_nav_msgs.msg import GeoReference as GeoReferenceMsg

from ..core.estimation import autopilot_frames as af
from ..core.estimation.strapdown import quat_to_matrix
from ..core.features.minutia_set import MinutiaSet
from ..core.terrain.georef import GeoReference

# encoding -> (numpy dtype, channels). Byte order of multi-byte types comes from is_bigendian.
IMAGE_ENCODINGS = {
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
    "64FC1": (np.float64, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "8UC3": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "rgb16": (np.uint16, 3),
    "bgr16": (np.uint16, 3),
}

# Bayer mosaics, the raw output of most machine-vision camera drivers: demosaiced to grey (all
# the matcher uses). OpenCV names a pattern by its second row, so ROS's rggb is its BG (the
# pairs cv_bridge uses).
_BAYER_TO_GREY = {"rggb": "COLOR_BayerBG2GRAY", "bggr": "COLOR_BayerRG2GRAY",
                  "gbrg": "COLOR_BayerGR2GRAY", "grbg": "COLOR_BayerGB2GRAY"}
for _pattern in _BAYER_TO_GREY:
    IMAGE_ENCODINGS[f"bayer_{_pattern}8"] = (np.uint8, 1)
    IMAGE_ENCODINGS[f"bayer_{_pattern}16"] = (np.uint16, 1)

# Default encoding for an array, by (dtype, channels).
_DEFAULT_ENCODING = {
    (np.dtype(np.uint8), 1): "mono8",
    (np.dtype(np.uint16), 1): "mono16",
    (np.dtype(np.float32), 1): "32FC1",
    (np.dtype(np.float64), 1): "64FC1",
    (np.dtype(np.uint8), 3): "rgb8",
    (np.dtype(np.uint8), 4): "rgba8",
    (np.dtype(np.uint16), 3): "rgb16",
}


class ConversionError(ValueError):
    """A message cannot be turned into arrays (unsupported encoding, wrong sizes...)."""


# ---------------------------------------------------------------------------------------------
# Time
# ---------------------------------------------------------------------------------------------

def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time (handles negative values like rclpy)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_to_sec(stamp: Time) -> float:
    """builtin_interfaces/Time -> float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def sec_to_stamp(seconds: float) -> Time:
    """Float seconds -> builtin_interfaces/Time, rounded to the nanosecond."""
    return ns_to_stamp(round(seconds * 1e9))


def make_header(stamp: Time | int, frame_id: str) -> Header:
    """Header from a Time or integer nanoseconds."""
    if not isinstance(stamp, Time):
        stamp = ns_to_stamp(stamp)
    return Header(stamp=stamp, frame_id=frame_id)


# ---------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------

def image_to_array(msg: Image) -> np.ndarray:
    """sensor_msgs/Image -> ndarray of shape (H, W) or (H, W, C), native byte order.

    Rows padded beyond ``width * channels * itemsize`` (``step``) are cropped. A Bayer mosaic
    (``bayer_rggb8``, ...) comes back demosaiced to grey (H, W).
    """
    if msg.encoding not in IMAGE_ENCODINGS:
        raise ConversionError(
            f"unsupported image encoding '{msg.encoding}' (supported: "
            f"{', '.join(sorted(IMAGE_ENCODINGS))})")
    dtype, channels = IMAGE_ENCODINGS[msg.encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.step < row_bytes or len(msg.data) < msg.step * msg.height:
        raise ConversionError(
            f"image {msg.width}x{msg.height} {msg.encoding}: step {msg.step} and "
            f"{len(msg.data)} data bytes are too small (need {row_bytes} per row)")
    raw = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height)
    rows = raw.reshape(msg.height, msg.step)[:, :row_bytes]
    arr = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, channels)
    if not dtype.isnative:
        arr = arr.astype(dtype.newbyteorder("="))
    if msg.encoding.startswith("bayer_"):
        return _demosaiced(arr[:, :, 0], msg.encoding)
    return arr[:, :, 0] if channels == 1 else arr


def _demosaiced(mosaic: np.ndarray, encoding: str) -> np.ndarray:
    """A Bayer mosaic (``bayer_<pattern><bits>``) as a grey image of the same size."""
    import cv2

    if min(mosaic.shape) < 2:
        raise ConversionError(f"{encoding} image of {mosaic.shape[1]}x{mosaic.shape[0]} px: a "
                              "Bayer mosaic needs at least 2x2 pixels")
    pattern = encoding[len("bayer_"):].rstrip("0123456789")
    return cv2.cvtColor(np.ascontiguousarray(mosaic), getattr(cv2, _BAYER_TO_GREY[pattern]))


def array_to_image(arr: np.ndarray, encoding: str | None = None, header: Header | None = None,
                   ) -> Image:
    """ndarray (H, W) or (H, W, C) -> sensor_msgs/Image, little-endian, unpadded rows."""
    arr = np.asarray(arr)
    channels = 1 if arr.ndim == 2 else arr.shape[2] if arr.ndim == 3 else 0
    if channels == 0:
        raise ConversionError(f"image array must be 2-D or 3-D, got shape {arr.shape}")
    if encoding is None:
        encoding = _DEFAULT_ENCODING.get((arr.dtype, channels))
        if encoding is None:
            raise ConversionError(f"no image encoding for dtype {arr.dtype} with {channels} "
                                  "channel(s)")
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(f"unsupported image encoding '{encoding}'")
    dtype, enc_channels = IMAGE_ENCODINGS[encoding]
    if enc_channels != channels or np.dtype(dtype) != arr.dtype:
        raise ConversionError(f"array {arr.dtype} x{channels} does not fit encoding {encoding}")
    data = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<"))
    msg = Image(header=header or Header(), height=arr.shape[0], width=arr.shape[1],
                encoding=encoding, is_bigendian=0, step=arr.shape[1] * channels * data.itemsize)
    msg.data = array.array("B", data.tobytes())
    return msg


def compressed_image_to_array(msg: CompressedImage) -> tuple[np.ndarray, str]:
    """sensor_msgs/CompressedImage (JPEG, PNG) -> (array, encoding of the array).

    Colour images come back as ``bgr8`` (OpenCV's order), grey ones as ``mono8``/``mono16``.
    """
    import cv2

    data = np.frombuffer(msg.data, dtype=np.uint8)
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise ConversionError(f"cannot decode compressed image (format '{msg.format}', "
                              f"{data.size} bytes)")
    if arr.ndim == 2:
        return arr, "mono16" if arr.dtype == np.uint16 else "mono8"
    if arr.shape[2] == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    return arr, "bgr8"


def to_grey(arr: np.ndarray, encoding: str) -> np.ndarray:
    """Colour or grey image array (as decoded from ``encoding``) -> single-channel array.

    Luma weights are ITU-R BT.601, as OpenCV's cvtColor; the dtype is kept.
    """
    if arr.ndim == 2:
        return arr
    rgb_first = encoding.startswith("rgb") or encoding == "8UC3"
    weights = np.array([0.299, 0.587, 0.114] if rgb_first else [0.114, 0.587, 0.299])
    grey = arr[..., :3].astype(np.float32) @ weights.astype(np.float32)
    if np.issubdtype(arr.dtype, np.integer):
        grey = np.clip(np.rint(grey), 0, np.iinfo(arr.dtype).max)
    return grey.astype(arr.dtype)


# ---------------------------------------------------------------------------------------------
# Camera model
# ---------------------------------------------------------------------------------------------

def camera_info_to_intrinsics(msg: CameraInfo) -> tuple[np.ndarray, np.ndarray, str, tuple]:
    """CameraInfo -> (K 3x3, distortion coefficients, distortion model, (width, height)).

    Raises ConversionError for a CameraInfo that cannot describe a camera (zero focal length
    or size), as an uncalibrated driver sends.
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if msg.width == 0 or msg.height == 0 or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ConversionError(
            f"CameraInfo is not calibrated (size {msg.width}x{msg.height}, "
            f"fx={k[0, 0]}, fy={k[1, 1]})")
    model = msg.distortion_model or "plumb_bob"
    if model not in ("plumb_bob", "rational_polynomial", "equidistant"):
        raise ConversionError(f"unsupported distortion model '{model}'")
    return k, np.asarray(msg.d, dtype=np.float64), model, (int(msg.width), int(msg.height))


def intrinsics_to_camera_info(k: np.ndarray, d, width: int, height: int,
                              distortion_model: str = "plumb_bob",
                              header: Header | None = None) -> CameraInfo:
    """(K, D, size) -> CameraInfo with R = identity and P = [K | 0] (monocular)."""
    k = np.asarray(k, dtype=np.float64).reshape(3, 3)
    p = np.zeros((3, 4))
    p[:, :3] = k
    return CameraInfo(header=header or Header(), width=int(width), height=int(height),
                      distortion_model=distortion_model,
                      d=[float(v) for v in np.ravel(d)], k=k.ravel().tolist(),
                      r=np.eye(3).ravel().tolist(), p=p.ravel().tolist())


# ---------------------------------------------------------------------------------------------
# Covariances
# ---------------------------------------------------------------------------------------------

def covariance_to_array(values, n: int) -> np.ndarray:
    """Row-major covariance field (float64[n*n]) -> (n, n) array."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != n * n:
        raise ConversionError(f"covariance has {arr.size} values, expected {n * n}")
    return arr.reshape(n, n).copy()


def array_to_covariance(cov: np.ndarray) -> np.ndarray:
    """(n, n) array -> flat row-major float64 array for a message's covariance field."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
        raise ConversionError(f"covariance must be square, got shape {cov.shape}")
    return np.ascontiguousarray(cov).reshape(-1)


def odometry_to_arrays(msg: Odometry) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Odometry -> (stamp ns, position (3,), quaternion xyzw (4,), pose covariance (6, 6))."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return (stamp_to_ns(msg.header.stamp), np.array([p.x, p.y, p.z]),
            np.array([q.x, q.y, q.z, q.w]), covariance_to_array(msg.pose.covariance, 6))


def odometry_velocity(msg: Odometry) -> np.ndarray:
    """Odometry -> its velocity (3,) in the pose's frame (ENU): the twist is in
    ``child_frame_id`` (REP 105), turned by the pose's orientation."""
    o, v = msg.pose.pose.orientation, msg.twist.twist.linear
    q = np.array([o.x, o.y, o.z, o.w])
    norm = np.linalg.norm(q)
    if not norm > 0:
        return np.full(3, np.nan)
    return quat_to_matrix(q / norm) @ np.array([v.x, v.y, v.z])


def set_pose_to_arrays(msg: PoseWithCovarianceStamped) -> tuple[float, str, np.ndarray,
                                                                 np.ndarray]:
    """PoseWithCovarianceStamped (an operator's re-seed) -> (stamp s, frame_id, position
    (3,), position covariance (3, 3)); the orientation is not used."""
    p = msg.pose.pose.position
    cov = covariance_to_array(msg.pose.covariance, 6)[:3, :3]
    return stamp_to_sec(msg.header.stamp), msg.header.frame_id, np.array([p.x, p.y, p.z]), cov


def pose_with_covariance(position, quaternion_xyzw, cov6: np.ndarray) -> PoseWithCovariance:
    """Position (3,), quaternion (x, y, z, w) and 6x6 covariance -> PoseWithCovariance."""
    msg = PoseWithCovariance()
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, position)
    q = msg.pose.orientation
    q.x, q.y, q.z, q.w = map(float, quaternion_xyzw)
    msg.covariance = array_to_covariance(cov6)
    return msg


# ---------------------------------------------------------------------------------------------
# Georeferenced rasters
# ---------------------------------------------------------------------------------------------

def georef_to_msg(georef: GeoReference, enu_origin=(0.0, 0.0, 0.0),
                  source_crs: str = "") -> GeoReferenceMsg:
    """GeoReference (+ geodetic ENU origin lat, lon, alt) -> terrain_nav_msgs/GeoReference."""
    lat, lon, alt = enu_origin
    return GeoReferenceMsg(
        origin_east=float(georef.origin_east), origin_north=float(georef.origin_north),
        gsd=float(georef.gsd), width=int(georef.width), height=int(georef.height),
        enu_origin_latitude=float(lat), enu_origin_longitude=float(lon),
        enu_origin_altitude=float(alt), source_crs=source_crs)


def msg_to_georef(msg: GeoReferenceMsg) -> GeoReference:
    """terrain_nav_msgs/GeoReference -> GeoReference (raises ConversionError if invalid,
    its ENU origin included: every node that reads the message refuses a NaN origin there,
    not the matcher's fix later)."""
    lat, lon, alt = enu_origin_of(msg)
    if not (math.isfinite(alt) and abs(lat) <= 90.0 and abs(lon) <= 360.0):
        raise ConversionError(f"ENU origin ({lat}, {lon}, {alt}) is no place on Earth")
    try:
        return GeoReference(msg.origin_east, msg.origin_north, msg.gsd, msg.width, msg.height)
    except ValueError as err:
        raise ConversionError(str(err)) from err


def enu_origin_of(msg: GeoReferenceMsg) -> tuple[float, float, float]:
    """Geodetic (lat, lon, alt) of the ENU origin a GeoReference message refers to."""
    return (msg.enu_origin_latitude, msg.enu_origin_longitude, msg.enu_origin_altitude)


def dem_tile_to_msg(heights: np.ndarray, georef: GeoReference, header: Header,
                    enu_origin=(0.0, 0.0, 0.0), vertical_datum: str = "",
                    source_crs: str = "") -> DemTile:
    """Elevation grid (NaN = no data) -> DemTile."""
    heights = np.ascontiguousarray(heights, dtype=np.float32)
    if heights.shape != georef.shape:
        raise ConversionError(f"heights shape {heights.shape} != georef shape {georef.shape}")
    msg = DemTile(header=header, georef=georef_to_msg(georef, enu_origin, source_crs),
                  vertical_datum=vertical_datum,
                  void_fraction=float(np.isnan(heights).mean()) if heights.size else 0.0)
    msg.elevations = array.array("f", heights.tobytes())
    return msg


def msg_to_dem_tile(msg: DemTile) -> tuple[np.ndarray, GeoReference]:
    """DemTile -> (float32 heights (H, W) with NaN voids, GeoReference)."""
    georef = msg_to_georef(msg.georef)
    heights = np.frombuffer(msg.elevations, dtype=np.float32)
    if heights.size != georef.width * georef.height:
        raise ConversionError(f"DemTile has {heights.size} elevations for a "
                              f"{georef.width}x{georef.height} georeference")
    return heights.reshape(georef.shape), georef


def geo_image_to_msg(image: np.ndarray, georef: GeoReference, header: Header,
                     valid_mask: np.ndarray | None = None, enu_origin=(0.0, 0.0, 0.0),
                     source_crs: str = "", sun=None) -> GeoImage:
    """Ground image (+ boolean validity mask, + the sun (azimuth, elevation) that lit it,
    degrees) -> GeoImage."""
    if image.shape[:2] != georef.shape:
        raise ConversionError(f"image shape {image.shape} != georef shape {georef.shape}")
    msg = GeoImage(header=header, georef=georef_to_msg(georef, enu_origin, source_crs),
                   image=array_to_image(image, header=header))
    if sun is not None:
        msg.sun_azimuth, msg.sun_elevation = float(sun[0]), float(sun[1])
    if valid_mask is not None and not np.all(valid_mask):
        msg.valid_mask = array_to_image(np.where(valid_mask, 255, 0).astype(np.uint8),
                                        "mono8", header)
    return msg


def unprojected_frame_msg(header: Header, reason: str) -> GeoImage:
    """The GeoImage of a camera frame that could not be projected: no image, the reason."""
    return GeoImage(header=header, reason=reason or "unknown")


def msg_to_geo_image(msg: GeoImage) -> tuple[np.ndarray, GeoReference, np.ndarray]:
    """GeoImage -> (grey image, GeoReference, boolean validity mask)."""
    if msg.reason:
        raise ConversionError(f"no image: {msg.reason}")
    georef = msg_to_georef(msg.georef)
    image = to_grey(image_to_array(msg.image), msg.image.encoding)
    if image.shape != georef.shape:
        raise ConversionError(f"GeoImage: image {image.shape} != georef {georef.shape}")
    if msg.valid_mask.width == 0:
        mask = np.ones(georef.shape, dtype=bool)
    else:
        mask = image_to_array(msg.valid_mask) > 0
        if mask.shape != georef.shape:
            raise ConversionError(f"GeoImage: mask {mask.shape} != georef {georef.shape}")
    return image, georef, mask


def geo_image_sun(msg: GeoImage) -> tuple[float, float] | None:
    """(azimuth, elevation) of the sun that lit a GeoImage, degrees; None when unknown."""
    az, el = msg.sun_azimuth, msg.sun_elevation
    if not (np.isfinite(az) and np.isfinite(el)) or not 0.0 < el <= 90.0:
        return None
    return float(az), float(el)


def set_projection(msg, position, r_enu_optical, plane_height: float,
                   mosaic_lag: float = 0.0) -> None:
    """Record on a GeoImage/MinutiaArray the camera pose and plane a ground image came from
    (and, for a track mosaic, the mean age of its pixels [s])."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(r_enu_optical, float)).as_quat()
    msg.projected = True
    pose = msg.projection_pose
    pose.position.x, pose.position.y, pose.position.z = map(float, position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = map(
        float, q)
    msg.projection_plane_height = float(plane_height)
    msg.mosaic_lag = float(mosaic_lag)


def get_projection(msg) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(camera position, optical->ENU rotation, plane height) of a projected image, or None."""
    if not msg.projected:
        return None
    from scipy.spatial.transform import Rotation

    p, q = msg.projection_pose.position, msg.projection_pose.orientation
    rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    return np.array([p.x, p.y, p.z]), rotation, float(msg.projection_plane_height)


def set_pose_free(msg, plane_min: float, plane_max: float, tilt_sigma: float) -> None:
    """Mark a projected GeoImage/MinutiaArray as pose-free (cold start), with the range of
    terrain planes and the attitude sigma it leaves open (call after set_projection)."""
    msg.pose_free = True
    msg.projection_plane_min = float(plane_min)
    msg.projection_plane_max = float(plane_max)
    msg.projection_tilt_sigma = float(tilt_sigma)


def get_pose_free(msg) -> tuple[float, float, float] | None:
    """(plane min, plane max, tilt sigma) of a pose-free projection, or None (a frame
    projected with the navigation estimate, or not projected)."""
    if not (msg.projected and msg.pose_free):
        return None
    return (float(msg.projection_plane_min), float(msg.projection_plane_max),
            float(msg.projection_tilt_sigma))


def copy_projection(source, target) -> None:
    """Carry the projection fields from a GeoImage to the MinutiaArray made from it."""
    target.projected = source.projected
    target.projection_pose = source.projection_pose
    target.projection_plane_height = source.projection_plane_height
    target.pose_free = source.pose_free
    target.projection_plane_min = source.projection_plane_min
    target.projection_plane_max = source.projection_plane_max
    target.projection_tilt_sigma = source.projection_tilt_sigma
    target.mosaic_lag = source.mosaic_lag


# ---------------------------------------------------------------------------------------------
# Minutiae
# ---------------------------------------------------------------------------------------------

def minutiae_to_msg(minutiae: MinutiaSet, header: Header, source: int,
                    enu_origin=(0.0, 0.0, 0.0), source_crs: str = "",
                    creases: np.ndarray | None = None,
                    ridges: np.ndarray | None = None) -> MinutiaArray:
    """MinutiaSet (with georef) -> MinutiaArray; positions in both metres and pixels.

    ``creases``, ``ridges``: the crease and ridge skeletons (non-zero = on it) on the
    georeference's grid, sent as their pixels' raster indices.
    """
    if minutiae.georef is None:
        raise ConversionError("minutiae_to_msg: the MinutiaSet needs a georeference")
    shape = (minutiae.georef.height, minutiae.georef.width)
    crease_pixels = _skeleton_pixels(creases, shape, "crease")
    ridge_pixels = _skeleton_pixels(ridges, shape, "ridge")
    east, north = minutiae.enu()
    items = [
        Minutia(x=float(x), y=float(y), col=float(c), row=float(r), orientation=float(a),
                type=int(k), quality=float(q))
        for x, y, c, r, a, k, q in zip(east.tolist(), north.tolist(), minutiae.col.tolist(),
                                       minutiae.row.tolist(), minutiae.angle.tolist(),
                                       minutiae.kind.tolist(), minutiae.quality.tolist(),
                                       strict=True)
    ]
    return MinutiaArray(header=header,
                        georef=georef_to_msg(minutiae.georef, enu_origin, source_crs),
                        source=source, minutiae=items, reason=minutiae.reason,
                        crease_pixels=crease_pixels, ridge_pixels=ridge_pixels)


def empty_minutiae_msg(header: Header, source: int, reason: str) -> MinutiaArray:
    """The MinutiaArray of an image that gave no minutiae set at all (none to extract from,
    or extraction failed): no georeference, the reason."""
    return MinutiaArray(header=header, source=source, reason=reason or "unknown")


def _skeleton_pixels(skeleton: np.ndarray | None, shape, what: str) -> np.ndarray:
    """Raster indices of a skeleton image's pixels (none for None)."""
    if skeleton is None:
        return np.zeros(0, np.uint32)
    if np.shape(skeleton) != shape:
        raise ConversionError(f"minutiae_to_msg: {what} image of shape "
                              f"{np.shape(skeleton)} on a {shape} georeference")
    return np.flatnonzero(skeleton).astype(np.uint32)


#: Most minutiae a MinutiaArray may carry (the landmark extractor keeps 5000 by default).
MAX_MINUTIAE = 10000
#: Largest raster a MinutiaArray's creases may span (a 8192 px square).
MAX_SET_PIXELS = 8192 * 8192


def msg_to_minutiae(msg: MinutiaArray) -> MinutiaSet:
    """MinutiaArray -> MinutiaSet with its georeference (at most :data:`MAX_MINUTIAE`: the
    matcher's work and memory grow with the square of a set's size)."""
    georef = msg_to_georef(msg.georef)
    items = msg.minutiae
    if len(items) > MAX_MINUTIAE:
        raise ConversionError(f"{len(items)} minutiae: at most {MAX_MINUTIAE} in a set (the "
                              "extractor keeps the best by quality)")
    cols = np.fromiter((m.col for m in items), float, len(items))
    rows = np.fromiter((m.row for m in items), float, len(items))
    angles = np.fromiter((m.orientation for m in items), float, len(items))
    kinds = np.fromiter((m.type for m in items), np.uint8, len(items))
    quality = np.fromiter((m.quality for m in items), np.float32, len(items))
    try:
        return MinutiaSet(cols, rows, angles, kinds, quality, georef=georef, reason=msg.reason)
    except ValueError as err:
        raise ConversionError(str(err)) from err


def msg_to_creases(msg: MinutiaArray) -> np.ndarray | None:
    """The crease skeleton a MinutiaArray carries (bool, georef grid), or None without one."""
    return _pixels_skeleton(msg.crease_pixels, msg, "crease")


def msg_to_ridges(msg: MinutiaArray) -> np.ndarray | None:
    """The ridge skeleton a MinutiaArray carries (bool, georef grid), or None without one."""
    return _pixels_skeleton(msg.ridge_pixels, msg, "ridge")


def _pixels_skeleton(pixels, msg: MinutiaArray, what: str) -> np.ndarray | None:
    pixels = np.asarray(pixels, np.int64)
    if pixels.size == 0:
        return None
    width, height = int(msg.georef.width), int(msg.georef.height)
    if width * height > MAX_SET_PIXELS:
        raise ConversionError(f"a {width} x {height} px {what} raster: at most "
                              f"{MAX_SET_PIXELS / 1e6:.0f} M pixels")
    if pixels.min() < 0 or pixels.max() >= width * height:
        raise ConversionError(f"{what} pixel index {pixels.max()} outside the "
                              f"{width} x {height} georeference")
    skeleton = np.zeros(height * width, bool)
    skeleton[pixels] = True
    return skeleton.reshape(height, width)


# ---------------------------------------------------------------------------------------------
# Navigation sensors and outputs (ekf node)
# ---------------------------------------------------------------------------------------------

def imu_to_sample(msg: Imu) -> tuple[float, tuple, tuple]:
    """sensor_msgs/Imu -> (stamp s, gyro (x, y, z) rad/s, accel (x, y, z) m/s^2) as floats.

    Plain tuples: this runs at the IMU rate and the EKF core takes floats.
    """
    w, a = msg.angular_velocity, msg.linear_acceleration
    return stamp_to_sec(msg.header.stamp), (w.x, w.y, w.z), (a.x, a.y, a.z)


#: Variance (rad^2) of an IMU orientation whose covariance is all zero (REP 145: unknown):
#: a MEMS AHRS's 3 deg.
UNKNOWN_ORIENTATION_VARIANCE = math.radians(3.0) ** 2


def imu_orientation(msg: Imu) -> tuple[np.ndarray, float] | None:
    """The orientation an Imu message carries (quaternion ``[x, y, z, w]``, body -> its
    frame) and the larger of its roll and pitch variances (rad^2), or None when it carries
    none: REP 145's ``orientation_covariance[0] == -1``, a quaternion that is no rotation
    (not of unit length), or the identity with an all-zero covariance, which is what many
    drivers that estimate no orientation leave in the message. Another orientation with an
    all-zero (unknown) covariance gets :data:`UNKNOWN_ORIENTATION_VARIANCE`."""
    cov = msg.orientation_covariance
    if cov[0] < 0:
        return None
    o = msg.orientation
    q = np.array([o.x, o.y, o.z, o.w], float)
    if not (np.isfinite(q).all() and abs(np.linalg.norm(q) - 1.0) <= 0.01):
        return None
    if not any(cov):
        return None if tuple(q) == (0.0, 0.0, 0.0, 1.0) else (q, UNKNOWN_ORIENTATION_VARIANCE)
    return q / np.linalg.norm(q), float(max(cov[0], cov[4]))


def sample_to_imu(header: Header, gyro, accel) -> Imu:
    """(header, gyro, accel) -> sensor_msgs/Imu without orientation (covariance[0] = -1)."""
    msg = Imu(header=header)
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = map(float, gyro)
    a = msg.linear_acceleration
    a.x, a.y, a.z = map(float, accel)
    msg.orientation_covariance[0] = -1.0   # REP 145: orientation not provided
    return msg


def fluid_pressure_to_sample(msg: FluidPressure) -> tuple[float, float, float]:
    """sensor_msgs/FluidPressure -> (stamp s, pressure Pa, variance Pa^2; 0 = unknown)."""
    return stamp_to_sec(msg.header.stamp), float(msg.fluid_pressure), float(msg.variance)


class PvaFixArrays(NamedTuple):
    """A PvaFix as arrays (ENU map frame, SI units)."""

    stamp: float
    status: int
    position: np.ndarray               # (3,)
    quaternion: np.ndarray             # (4,) x, y, z, w
    covariance: np.ndarray             # (6, 6) position, rotation about x, y, z
    velocity: np.ndarray | None        # (3,) when velocity_valid
    velocity_covariance: np.ndarray | None
    relocalisation: bool = False       # found by a mission-wide search, independent of the prior
    projection_height: float = 0.0     # m over which the estimate's tilt error moves the fix
    mosaic_lag: float = 0.0            # s over which the estimate's velocity error moves it


def pva_fix_to_arrays(msg: PvaFix) -> PvaFixArrays:
    """terrain_nav_msgs/PvaFix -> :class:`PvaFixArrays` (no validation beyond sizes)."""
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    vel = vcov = None
    if msg.velocity_valid:
        vel = np.array([msg.velocity.x, msg.velocity.y, msg.velocity.z])
        vcov = covariance_to_array(msg.velocity_covariance, 3)
    return PvaFixArrays(stamp_to_sec(msg.header.stamp), int(msg.status),
                        np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]),
                        covariance_to_array(msg.pose.covariance, 6), vel, vcov,
                        bool(msg.relocalisation), float(msg.projection_height),
                        float(msg.mosaic_lag))


def arrays_to_pva_fix(header: Header, status: int, position, quaternion, covariance,
                      velocity=None, velocity_covariance=None, reason: str = "",
                      relocalisation: bool = False, projection_height: float = 0.0,
                      mosaic_lag: float = 0.0) -> PvaFix:
    """Arrays -> terrain_nav_msgs/PvaFix (position-only fixes: -1 on the rotation diagonal)."""
    msg = PvaFix(header=header, status=int(status), reason=reason,
                 relocalisation=bool(relocalisation),
                 projection_height=float(projection_height), mosaic_lag=float(mosaic_lag),
                 pose=pose_with_covariance(position, quaternion, covariance))
    if velocity is not None:
        msg.velocity_valid = True
        msg.velocity.x, msg.velocity.y, msg.velocity.z = map(float, velocity)
        msg.velocity_covariance = array_to_covariance(velocity_covariance)
    return msg


def navsatfix_to_arrays(msg: NavSatFix) -> tuple[float, int, np.ndarray, np.ndarray, int]:
    """NavSatFix -> (stamp s, status, (lat deg, lon deg, ellipsoidal h m), ENU covariance
    (3, 3) m^2, covariance type)."""
    return (stamp_to_sec(msg.header.stamp), int(msg.status.status),
            np.array([msg.latitude, msg.longitude, msg.altitude]),
            covariance_to_array(msg.position_covariance, 3), int(msg.position_covariance_type))


def arrays_to_navsatfix(header: Header, lat: float, lon: float, alt: float, covariance,
                        status: int = NavSatStatus.STATUS_FIX,
                        covariance_type: int = NavSatFix.COVARIANCE_TYPE_KNOWN,
                        service: int = 0) -> NavSatFix:
    """WGS84 (deg, deg, ellipsoidal m) + ENU covariance (3, 3) -> NavSatFix."""
    msg = NavSatFix(header=header, latitude=float(lat), longitude=float(lon),
                    altitude=float(alt), position_covariance_type=int(covariance_type))
    msg.status.status, msg.status.service = int(status), int(service)
    msg.position_covariance = array_to_covariance(covariance)
    return msg


def odometry_msg(header: Header, child_frame_id: str, position, quaternion, pose_covariance,
                 linear, angular, twist_covariance) -> Odometry:
    """nav_msgs/Odometry: pose in ``header.frame_id``, twist in ``child_frame_id`` (REP 105)."""
    msg = Odometry(header=header, child_frame_id=child_frame_id,
                   pose=pose_with_covariance(position, quaternion, pose_covariance))
    t = msg.twist.twist
    t.linear.x, t.linear.y, t.linear.z = map(float, linear)
    t.angular.x, t.angular.y, t.angular.z = map(float, angular)
    msg.twist.covariance = array_to_covariance(twist_covariance)
    return msg


def odometry_to_state(msg: Odometry) -> tuple[float, np.ndarray, np.ndarray, np.ndarray,
                                              np.ndarray, np.ndarray, np.ndarray]:
    """Odometry -> (stamp, position, quaternion xyzw, pose cov 6x6, linear, angular,
    twist cov 6x6)."""
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    return (stamp_to_sec(msg.header.stamp), np.array([p.x, p.y, p.z]),
            np.array([o.x, o.y, o.z, o.w]), covariance_to_array(msg.pose.covariance, 6),
            np.array([lin.x, lin.y, lin.z]), np.array([ang.x, ang.y, ang.z]),
            covariance_to_array(msg.twist.covariance, 6))


def tf_message(header: Header, child_frame_id: str, translation, quaternion) -> TFMessage:
    """One transform ``header.frame_id`` -> ``child_frame_id`` as a tf2_msgs/TFMessage."""
    tf = TransformStamped(header=header, child_frame_id=child_frame_id)
    tr, r = tf.transform.translation, tf.transform.rotation
    tr.x, tr.y, tr.z = map(float, translation)
    r.x, r.y, r.z, r.w = map(float, quaternion)
    return TFMessage(transforms=[tf])


def static_rotations(msg: TFMessage) -> tuple[dict, list[str]]:
    """The rotations of a ``/tf_static`` message: ``{child: (parent, R_parent_child)}``, and
    why any transform was left out (a quaternion of zero or non-finite length, no frame
    names). A quaternion a little off unit length is normalised, as tf2 does."""
    rotations, refused = {}, []
    for tf in msg.transforms:
        r = tf.transform.rotation
        q = np.array([r.x, r.y, r.z, r.w], float)
        norm = float(np.linalg.norm(q))
        if not tf.header.frame_id or not tf.child_frame_id:
            refused.append(f"a transform without frame names ({tf.header.frame_id!r} -> "
                           f"{tf.child_frame_id!r})")
        elif not np.isfinite(norm) or norm < 1e-6:
            refused.append(f"{tf.header.frame_id} -> {tf.child_frame_id}: quaternion "
                           f"{q.tolist()} is no rotation")
        else:
            rotations[tf.child_frame_id] = (tf.header.frame_id, quat_to_matrix(q / norm))
    return rotations, refused


def diagnostic_status(name: str, level: int, message: str, values: dict,
                      hardware_id: str = "") -> DiagnosticStatus:
    """diagnostic_msgs/DiagnosticStatus; ``level`` is 0 OK, 1 WARN, 2 ERROR, 3 STALE; values
    are formatted with ``str`` (floats with 6 significant digits)."""
    kv = [KeyValue(key=str(k), value=f"{v:.6g}" if isinstance(v, float) else str(v))
          for k, v in values.items()]
    return DiagnosticStatus(level=bytes([int(level)]), name=name, message=message,
                            hardware_id=hardware_id, values=kv)


def diagnostic_values(status: DiagnosticStatus) -> tuple[int, dict]:
    """DiagnosticStatus -> (level as int, {key: value string})."""
    level = status.level[0] if isinstance(status.level, bytes | bytearray) else status.level
    return int(level), {kv.key: kv.value for kv in status.values}


# ---------------------------------------------------------------------------------------------
# Autopilot messages (PX4 over uXRCE-DDS). px4_msgs is optional on a ROS install, so the
# message is passed in rather than imported here.
# ---------------------------------------------------------------------------------------------

def fill_vehicle_odometry(out, stamp_ns: int, now_ns: int, position, quaternion, pose_cov,
                          linear, angular, twist_cov, reset_counter: int, quality: int):
    """Fill a ``px4_msgs/VehicleOdometry`` from a REP 103 odometry's arrays; return it.

    ``position``, ``quaternion`` (x, y, z, w, FLU -> ENU) and ``pose_cov`` (6x6, rotation
    about the ENU axes) are the pose, ``linear``, ``angular`` and ``twist_cov`` the twist in
    the FLU body frame (nav_msgs/Odometry, REP 105). PX4 gets NED position, FRD -> NED
    attitude, NED velocity, FRD angular rate and the diagonals of the rotated covariances;
    ``timestamp_sample`` is the estimate's stamp and ``timestamp`` ``now_ns``, in microseconds.
    """
    q = np.asarray(quaternion, float)
    r_world_body = quat_to_matrix(q)
    velocity_enu = r_world_body @ np.asarray(linear, float)
    out.timestamp = af.ns_to_px4_us(now_ns)
    out.timestamp_sample = af.ns_to_px4_us(stamp_ns)
    out.pose_frame = out.POSE_FRAME_NED
    out.position = af.enu_to_ned(position).astype(np.float32)
    out.q = af.quaternion_enu_flu_to_ned_frd(q).astype(np.float32)
    out.velocity_frame = out.VELOCITY_FRAME_NED
    out.velocity = af.enu_to_ned(velocity_enu).astype(np.float32)
    out.angular_velocity = af.flu_to_frd(angular).astype(np.float32)
    pose_ned = af.covariance_enu_to_ned(pose_cov)
    out.position_variance = _px4_variances(np.diag(pose_ned)[:3])
    out.orientation_variance = _px4_variances(np.diag(pose_ned)[3:])
    velocity_cov = af.covariance_enu_to_ned(
        af.body_to_world_covariance(np.asarray(twist_cov, float)[:3, :3], q))
    out.velocity_variance = _px4_variances(np.diag(velocity_cov))
    out.reset_counter = int(reset_counter) % 256
    out.quality = int(quality)
    return out


def _px4_variances(variances) -> np.ndarray:
    """Variances as float32 for PX4, NaN ("unknown": EKF2 then takes its noise parameter)
    where one is not a positive number float32 holds (REP 103's -1 for unknown, a value
    beyond 3.4e38), never a negative or infinite one."""
    v = np.asarray(variances, float)
    good = np.isfinite(v) & (v > 0) & (v <= np.finfo(np.float32).max)
    return np.where(good, v, np.nan).astype(np.float32)


def fill_sensor_gps(out, stamp_ns: int, lat: float, lon: float,
                    ellipsoid_height: float, geoid_undulation: float, position_cov_enu,
                    velocity_enu, velocity_cov_enu, fix_type: int):
    """Fill a ``px4_msgs/SensorGps`` with a fused estimate standing in for a receiver.

    Accuracies are the estimate's own 1-sigma figures (``eph``: long axis of the horizontal
    error ellipse, ``epv``: vertical, ``s_variance_m_s``: speed, despite its name a sigma in
    PX4); what a navigation filter does not have stays unknown: no satellites, DOPs NaN,
    jamming and spoofing unknown, no UTC time, no dual-antenna heading. ``velocity_enu`` None
    leaves the velocity invalid. Both ``timestamp`` and ``timestamp_sample`` are the
    estimate's stamp: PX4 dates a GNSS sample by ``timestamp`` (less ``EKF2_GPS_DELAY``),
    which SensorGps defines as the position's and velocity's time, not the sending's.
    """
    nan = float("nan")
    out.timestamp = out.timestamp_sample = af.ns_to_px4_us(stamp_ns)
    out.latitude_deg, out.longitude_deg = float(lat), float(lon)
    out.altitude_ellipsoid_m = float(ellipsoid_height)
    out.altitude_msl_m = float(ellipsoid_height) - float(geoid_undulation)
    cov = np.asarray(position_cov_enu, float)
    out.eph = af.horizontal_accuracy(cov)
    out.epv = float(np.sqrt(max(cov[2, 2], 0.0)))
    out.hdop = out.vdop = nan
    out.fix_type = int(fix_type)
    out.satellites_used = 0
    out.jamming_state = out.JAMMING_STATE_UNKNOWN
    out.spoofing_state = out.SPOOFING_STATE_UNKNOWN
    out.time_utc_usec = 0
    out.heading = out.heading_offset = out.heading_accuracy = nan
    if velocity_enu is None:
        out.vel_ned_valid = False
        out.vel_m_s = out.vel_n_m_s = out.vel_e_m_s = out.vel_d_m_s = nan
        out.cog_rad = out.s_variance_m_s = out.c_variance_rad = nan
        return out
    vn, ve, vd = (float(x) for x in af.enu_to_ned(velocity_enu))
    speed = float(np.hypot(vn, ve))
    s_acc = float(np.sqrt(max(np.max(np.diag(np.asarray(velocity_cov_enu, float))), 0.0)))
    out.vel_n_m_s, out.vel_e_m_s, out.vel_d_m_s, out.vel_m_s = vn, ve, vd, speed
    out.cog_rad = float(np.arctan2(ve, vn))
    out.s_variance_m_s = s_acc
    out.c_variance_rad = float(min(s_acc / speed, np.pi)) if speed > 0 else float(np.pi)
    out.vel_ned_valid = True
    return out
