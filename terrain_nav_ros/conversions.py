"""The one place where ROS messages meet numpy arrays and core types.

Nodes call these functions at their boundaries and hand arrays to
:mod:`terrain_nav_ros.core`. Large arrays are copied with ``tobytes``/``frombuffer``: assigning
an ndarray to a message's sequence field goes element by element (22 ms for a 512^2 image).
"""

from __future__ import annotations

import array

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovariance
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from terrain_nav_msgs.msg import DemTile, GeoImage, Minutia, MinutiaArray
from terrain_nav_msgs.msg import GeoReference as GeoReferenceMsg

from .core.georef import GeoReference
from .core.minutia_set import MinutiaSet

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

    Rows padded beyond ``width * channels * itemsize`` (``step``) are cropped.
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
    return arr[:, :, 0] if channels == 1 else arr


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
    """terrain_nav_msgs/GeoReference -> GeoReference (raises ConversionError if invalid)."""
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
                     source_crs: str = "") -> GeoImage:
    """Ground image (+ boolean validity mask) -> GeoImage."""
    if image.shape[:2] != georef.shape:
        raise ConversionError(f"image shape {image.shape} != georef shape {georef.shape}")
    msg = GeoImage(header=header, georef=georef_to_msg(georef, enu_origin, source_crs),
                   image=array_to_image(image, header=header))
    if valid_mask is not None and not np.all(valid_mask):
        msg.valid_mask = array_to_image(np.where(valid_mask, 255, 0).astype(np.uint8),
                                        "mono8", header)
    return msg


def msg_to_geo_image(msg: GeoImage) -> tuple[np.ndarray, GeoReference, np.ndarray]:
    """GeoImage -> (grey image, GeoReference, boolean validity mask)."""
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


# ---------------------------------------------------------------------------------------------
# Minutiae
# ---------------------------------------------------------------------------------------------

def minutiae_to_msg(minutiae: MinutiaSet, header: Header, source: int,
                    enu_origin=(0.0, 0.0, 0.0), source_crs: str = "") -> MinutiaArray:
    """MinutiaSet (with georef) -> MinutiaArray; positions in both metres and pixels."""
    if minutiae.georef is None:
        raise ConversionError("minutiae_to_msg: the MinutiaSet needs a georeference")
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
                        source=source, minutiae=items, reason=minutiae.reason)


def msg_to_minutiae(msg: MinutiaArray) -> MinutiaSet:
    """MinutiaArray -> MinutiaSet with its georeference."""
    georef = msg_to_georef(msg.georef)
    items = msg.minutiae
    cols = np.fromiter((m.col for m in items), float, len(items))
    rows = np.fromiter((m.row for m in items), float, len(items))
    angles = np.fromiter((m.orientation for m in items), float, len(items))
    kinds = np.fromiter((m.type for m in items), np.uint8, len(items))
    quality = np.fromiter((m.quality for m in items), np.float32, len(items))
    try:
        return MinutiaSet(cols, rows, angles, kinds, quality, georef=georef, reason=msg.reason)
    except ValueError as err:
        raise ConversionError(str(err)) from err
