#!/usr/bin/env python3
"""Fault cases through the real commands (issue 22): prints a GOOD / POOR / BAD table.

Each case makes one bad input (a DEM, an image, a bag, an option, a parameter, an IMU stamp), feeds
it to the real ``terrain-nav`` command, node executable or EKF core and judges the answer:

* GOOD: the expected clear answer (exit status, one line naming the fault, no traceback) in
  time;
* POOR: refused, but with a traceback, several lines, another exit status or a message
  that does not name the fault;
* BAD: accepted as if nothing were wrong, a hang, or navigation lost.

Usage::

    .venv/bin/python scripts/fault_cases.py            # every case (~31 min on 2 cores)
    .venv/bin/python scripts/fault_cases.py --ci       # the subset ./tn test runs
    .venv/bin/python scripts/fault_cases.py -k bag     # cases whose name holds "bag"

Exit status 1 when any case is BAD. ``test/test_commands.py`` runs the ``--ci`` subset.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
GOOD, POOR, BAD = "GOOD", "POOR", "BAD"
ASC_HEADER = "ncols {c}\nnrows {r}\nxllcorner 0\nyllcorner 0\ncellsize 30\n"


# ----------------------------------------------------------------------------- fault makers
def make_bag(path: Path, n: int = 3000) -> Path:
    """A small zstd bag on /imu/data with several chunks (std_msgs/String payloads)."""
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    from terrain_nav_ros.tools import bags

    with bags.BagWriter(path, compress=True) as writer:
        for i in range(n):
            writer.write_message("/imu/data", i * 10_000_000,
                                 String(data=f"{i:06d}" + "x" * 1000), "std_msgs/msg/String")
    return path


def cut_half(data: bytes) -> bytes:
    """An MCAP recording cut short."""
    return data[: len(data) // 2]


def corrupt_chunk(data: bytes) -> bytes:
    """Bytes flipped inside the compressed data of the second chunk."""
    from mcap.reader import make_reader

    chunks = make_reader(io.BytesIO(data)).get_summary().chunk_indexes
    start = chunks[1].chunk_start_offset + chunks[1].chunk_length // 2
    return data[:start] + bytes(b ^ 0x5A for b in data[start:start + 64]) + data[start + 64:]


def damaged_copy(bag: Path, dest: Path, change: Callable[[bytes], bytes] | None) -> Path:
    """A copy of ``bag`` with ``change`` applied to its MCAP file (None: no metadata.yaml)."""
    dest.mkdir()
    for f in bag.iterdir():
        data = f.read_bytes()
        if f.suffix == ".mcap" and change is not None:
            data = change(data)
        if f.suffix == ".mcap" or change is not None:
            (dest / f.name).write_bytes(data)
    return dest


def with_mission(bag: Path, dest: Path, text: str) -> Path:
    """A copy of ``bag`` with ``text`` as its mission.yaml."""
    dest.mkdir()
    for f in bag.iterdir():
        (dest / f.name).write_bytes(f.read_bytes())
    (dest / "mission.yaml").write_text(text)
    return dest


CAMERA_TOPICS = ("/camera/image_raw", "/camera/image_raw/compressed")


def frozen_camera(start: float, seconds: float) -> Callable:
    """A :func:`~terrain_nav_ros.tools.bags.changed_copy` change: the camera republishes,
    from ``start`` s for ``seconds``, the frame it took at ``start`` under new stamps (a
    hung driver)."""
    frozen = []

    def change(topic, at, decode):
        if topic not in CAMERA_TOPICS or not start <= at < start + seconds:
            return None
        msg = decode()
        if not frozen:
            frozen.append(msg.data)
            return None
        msg.data = frozen[0]
        return msg

    return change


def nan_imu(topic, at, decode):
    """IMU samples of 30.0-30.5 s with NaN in an acceleration and a rate (a driver fault)."""
    if topic != "/imu/data" or not 30.0 <= at < 30.5:
        return None
    msg = decode()
    msg.linear_acceleration.x = msg.angular_velocity.z = float("nan")
    return msg


def imu_gap(topic, at, _decode):
    """No IMU samples for 3 s (30-33 s): a stalled driver."""
    return "drop" if topic == "/imu/data" and 30.0 <= at < 33.0 else None


def uncalibrated_camera(topic, at, decode):
    """CameraInfo of 30-40 s with an all-zero K (a driver that lost its calibration)."""
    if topic != "/camera/camera_info" or not 30.0 <= at < 40.0:
        return None
    import numpy as np

    msg = decode()
    msg.k = np.zeros(9)
    return msg


def focal_length_off(factor: float) -> Callable:
    """A :func:`~terrain_nav_ros.tools.bags.changed_copy` change: every CameraInfo's focal
    length ``factor`` times the lens's (a calibration of another lens, a zoom's step). The
    ground projection is ``1 / factor`` too large, its nadir point where it was: the
    registration's scale, which measures the height above ground, is off by the factor."""
    def change(topic, at, decode):
        if topic != "/camera/camera_info":
            return None
        import numpy as np

        msg = decode()
        msg.k, msg.p = np.array(msg.k, float), np.array(msg.p, float)
        msg.k[[0, 4]] *= factor
        msg.p[[0, 5]] *= factor
        return msg
    return change


def camera_clock_back(topic, at, decode):
    """Camera frames and CameraInfo of 30-40 s stamped 2 s early: a camera clock that jumped
    back (the first two are out of order; the rest move on, 2 s behind the navigation)."""
    if topic not in (*CAMERA_TOPICS, "/camera/camera_info") or not 30.0 <= at < 40.0:
        return None
    msg = decode()
    msg.header.stamp.sec -= 2
    return msg


def camera_stamp_ahead(topic, at, decode):
    """One camera frame (and its CameraInfo) of 30-31 s stamped an hour ahead: a driver's
    glitch, a PTP step. The frames after it must not all be "out of order" for an hour."""
    if topic not in (*CAMERA_TOPICS, "/camera/camera_info") or not 30.0 <= at < 31.0:
        return None
    msg = decode()
    msg.header.stamp.sec += 3600
    return msg


def gnss_at_zero_first(topic, at, decode):
    """The receiver's first second of fixes at latitude and longitude 0 (its placeholder
    before a fix, with the fix status already set): the filter must not start there."""
    if topic != "/gnss/fix" or at >= 1.0:
        return None
    msg = decode()
    msg.latitude = msg.longitude = 0.0
    return msg


def frozen_baro(topic, at, decode):
    """Barometer stuck at 90 kPa (~990 m, the aircraft is near 3.8 km) from 25 s on."""
    if topic != "/baro/pressure" or at < 25.0:
        return None
    msg = decode()
    msg.fluid_pressure = 90_000.0
    return msg


def baro_in_hpa(topic, at, decode):
    """Every barometer sample in hPa, not the Pa FluidPressure is in."""
    if topic != "/baro/pressure":
        return None
    msg = decode()
    msg.fluid_pressure /= 100.0
    msg.variance /= 1e4
    return msg


def frozen_baro_reading(start: float) -> Callable:
    """A :func:`~terrain_nav_ros.tools.bags.changed_copy` change: the barometer repeats
    its reading of ``start`` s from then on (a hung driver) while the aircraft climbs on."""
    held = []

    def change(topic, at, decode):
        if topic != "/baro/pressure" or at < start:
            return None
        msg = decode()
        if not held:
            held.append(msg.fluid_pressure)
        msg.fluid_pressure = held[0]
        return msg

    return change


def accelerometer_bias_step(axis: str) -> Callable:
    """Accelerometer ``axis`` reading 0.5 m/s^2 (50 mg) high from 30 s on: a bias step far
    beyond the IMU's random walk. Along z it carries the inertial height away unless the
    baro holds it; along x or y it leans every levelling by 2.9 deg, as a tilt would."""
    return _imu_step("linear_acceleration", axis, 0.5)


def _imu_step(vector: str, axis: str, offset: float) -> Callable:
    """The IMU's ``vector`` (``angular_velocity`` or ``linear_acceleration``) reading
    ``offset`` high along ``axis`` from 30 s on."""
    def change(topic, at, decode):
        if topic != "/imu/data" or at < 30.0:
            return None
        msg = decode()
        reading = getattr(msg, vector)
        setattr(reading, axis, getattr(reading, axis) + offset)
        return msg

    return change


def vibrating_accelerometer(sigma: float):
    """White noise of ``sigma`` m/s^2 on each accelerometer axis of every IMU sample from
    15 s on (the GNSS denial): an engine shaking a soft mount, which each levelling's 1 s
    mean of the specific force does not average away."""
    import numpy as np

    rng = np.random.default_rng(7)

    def change(topic, at, decode):
        if topic != "/imu/data" or at < 15.0:
            return None
        msg = decode()
        a = msg.linear_acceleration
        a.x, a.y, a.z = np.r_[a.x, a.y, a.z] + rng.normal(0.0, sigma, 3)
        return msg

    return change


def gyro_bias_step(axis: str, deg_per_s: float):
    """Gyro ``axis`` (x roll, y pitch, z yaw) reading ``deg_per_s`` high from 30 s on: the
    attitude drifts by up to 15 deg by the end unless something other than the ground
    matches (which carry the filter's own tilt) levels it, or, for the yaw, the fixes'
    headings are let move the bias the filter is sure of."""
    return _imu_step("angular_velocity", axis, math.radians(deg_per_s))


def spoofed_gnss(topic, at, decode):
    """GNSS moved 200 m north for its last 4 s before the denial (11-15 s), while the
    terrain fixes have begun: a spoofer taking over."""
    if topic != "/gnss/fix" or not 11.0 <= at < 15.0:
        return None
    msg = decode()
    msg.latitude += 200.0 / 111_320.0
    return msg


def covered_lens(topic, at, decode):
    """Camera frames of 30-40 s all black (a lens cap, a night frame): each one says it is
    constant, none is taken for a frozen camera."""
    if topic not in CAMERA_TOPICS or not 30.0 <= at < 40.0:
        return None
    import cv2
    import numpy as np

    msg = decode()
    if topic.endswith("compressed"):
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        msg.data = np.frombuffer(cv2.imencode(".jpg", np.zeros_like(image))[1].tobytes(),
                                 np.uint8)
    else:
        msg.data = np.zeros(len(msg.data), np.uint8)
    return msg


def _frames_changed(topic, at, decode, start: float, end: float, change: Callable):
    """The camera frame of ``topic`` at ``at`` s with its pixels (uint8, as decoded) put
    through ``change`` when ``start`` <= at < ``end``; None for any other message."""
    if topic not in CAMERA_TOPICS or not start <= at < end:
        return None
    import cv2
    import numpy as np

    msg = decode()
    compressed = topic.endswith("compressed")
    image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED) \
        if compressed else np.frombuffer(bytes(msg.data), np.uint8).reshape(
            msg.height, msg.width, -1)
    changed = np.clip(change(image.astype(np.float32)), 0, 255).astype(np.uint8)
    msg.data = np.frombuffer(cv2.imencode(".jpg", changed)[1].tobytes() if compressed
                             else changed.tobytes(), np.uint8)
    return msg


def banded_frames(topic, at, decode):
    """Camera frames of 25-45 s with a sensor's row banding (+-40 grey levels every 16
    rows, a clock coupling into the readout): matched as they were, the stripes found
    ridges parallel to them kilometres off; taken off, the frames are fixes as before."""
    import numpy as np

    def banded(image):
        rows = 40.0 * np.sin(2 * np.pi * np.arange(image.shape[0]) / 16)
        return image + rows.reshape(-1, *[1] * (image.ndim - 1))
    return _frames_changed(topic, at, decode, 25.0, 45.0, banded)


def hazy_frames(topic, at, decode):
    """Camera frames of 25-45 s under haze toward a bright sky (85 % of each pixel the
    airlight, 230): the terrain keeps its relative contrast, and the cloud check once
    refused such frames as "mostly cloud"."""
    return _frames_changed(topic, at, decode, 25.0, 45.0,
                           lambda image: 0.15 * image + 0.85 * 230.0)


def underexposed_frames(topic, at, decode):
    """Camera frames of 25-45 s exposed 0.15 x as long (the brightest pixel ~38 of 255):
    once refused as "mostly cloud" too."""
    import numpy as np

    return _frames_changed(topic, at, decode, 25.0, 45.0, lambda image: np.floor(0.15 * image))


def defocused_frames(topic, at, decode):
    """Camera frames of 25-45 s out of focus (a Gaussian blur of 3 px sigma: a lens
    fogged or shaken loose): the valleys the matcher uses are tens of pixels wide, so the
    fixes go on."""
    import cv2

    return _frames_changed(topic, at, decode, 25.0, 45.0,
                           lambda image: cv2.GaussianBlur(image, (0, 0), 3.0))


def noisy_frames(topic, at, decode):
    """Camera frames of 25-45 s with a sensor's noise at high gain (Gaussian, 25 grey levels
    per pixel, new in each frame): no crease of the noise may become a fix elsewhere."""
    import numpy as np

    noise = np.random.default_rng(int(at * 1000))
    return _frames_changed(topic, at, decode, 25.0, 45.0,
                           lambda image: image + noise.normal(0.0, 25.0, image.shape))


def overexposed_frames(topic, at, decode):
    """Camera frames of 25-45 s exposed 1.5 x too long: the brightest 13-22 % of each
    clipped at full scale, the rest of the terrain as it was."""
    return _frames_changed(topic, at, decode, 25.0, 45.0, lambda image: 1.5 * image)


def saturated_frames(topic, at, decode):
    """Camera frames of 25-45 s exposed 3 x too long: every pixel clipped white (glare, an
    exposure control that failed). Each says it is bright and featureless, none is a fix."""
    return _frames_changed(topic, at, decode, 25.0, 45.0, lambda image: 3.0 * image)


def cloud_bank(topic, at, decode):
    """Camera frames of 25-40 s under a bank of cloud (90 % of the sky, ~600 m clouds whose
    gaps drift across at 15 m/s), composited in linear radiance (a display gamma of 2.2):
    a cloud top six times the frame's mean radiance (~0.9 against a hazy ground's ~0.15),
    the frame auto-exposed to its mean level again, so the cloud is mid-grey. Each frame
    says "mostly cloud", the filter coasts and the fixes resume after it. (Simulated
    overcast so exposed at 95 % was found 0 % cloud before session 36.)"""
    import numpy as np

    from terrain_nav_ros.core.render.cloud_layer import CloudLayer

    sheet = CloudLayer(cover=0.9, size=600.0, wind=(15.0, 0.0), seed=5)
    gamma = 2.2

    def clouded(image):
        rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]].astype(np.float32)
        opacity = sheet.opacity(5.0 * cols, -5.0 * rows, at)   # the bag's ~5 m pixels
        if image.ndim == 3:
            opacity = opacity[..., None]
        ground = (image / 255.0) ** gamma
        out = ground * (1.0 - opacity) + 6.0 * float(ground.mean()) * opacity
        out *= float(ground.mean()) / max(float(out.mean()), 1e-6)   # the auto-exposure
        return 255.0 * np.clip(out, 0.0, 1.0) ** (1.0 / gamma)
    return _frames_changed(topic, at, decode, 25.0, 40.0, clouded)


def camera_turned_180(topic, at, decode):
    """Every camera frame turned 180 deg (a camera mounted the other way round, its mount
    not declared): its fixes' heading is 180 deg off from the first and must never be
    taken for a gyro drift."""
    if topic not in CAMERA_TOPICS:
        return None
    import cv2
    import numpy as np

    msg = decode()
    image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
    msg.data = np.frombuffer(cv2.imencode(".jpg", cv2.rotate(image, cv2.ROTATE_180))[1]
                             .tobytes(), np.uint8)
    return msg


def camera_mirrored(topic, at, decode):
    """Every camera frame mirrored left to right (a driver's flip option, a camera mounted
    through a mirror): no turn of the frame lies on the terrain, so none may become a fix;
    the matcher, trying the frames mirrored back, names the flip."""
    return _frames_changed(topic, at, decode, 0.0, math.inf, lambda image: image[:, ::-1])


def camera_flipped_vertically(topic, at, decode):
    """Every camera frame flipped top to bottom: as :func:`camera_mirrored`, a mirror image
    (this one across the image's rows), named as such."""
    return _frames_changed(topic, at, decode, 0.0, math.inf, lambda image: image[::-1])


def camera_tilted(pitch_deg: float, roll_deg: float = 0.0, yaw_deg: float = 0.0,
                  bag: str = "jacksboro_short") -> Callable:
    """Every camera frame of ``bag`` as a camera mounted ``pitch_deg`` forward and
    ``roll_deg`` to the right of its declared mount, turned ``yaw_deg`` about its optical
    axis, would see it (not declared): the
    frames' ground points move by the height above ground times the tilt (2 deg: 116 m at
    the short bag's 3300 m), turning with the heading. The filter, taking that for its own
    tilt error, once ended 110 m off; it estimates the mount's tilt now."""
    maps = {}

    def tilted(image):
        import cv2

        from terrain_nav_ros.tools import bags
        from terrain_nav_ros.tools.cli import REPO

        if "xy" not in maps:
            info = bags.decode(next(iter(bags.read(REPO / "bags" / bag,
                                                   ["/camera/camera_info"]))))
            maps["xy"] = _tilted_camera_maps(info, pitch_deg, roll_deg, yaw_deg)
        return cv2.remap(image, *maps["xy"], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT_101)

    return lambda topic, at, decode: _frames_changed(topic, at, decode, 0.0, math.inf, tilted)


def _tilted_camera_maps(info, pitch_deg: float, roll_deg: float, yaw_deg: float = 0.0):
    """cv2.remap maps that turn a frame of the camera of ``info`` (sensor_msgs/CameraInfo,
    plumb_bob) into the frame of that camera turned about its x axis (image right: the
    aircraft's right for a nadir camera whose image up is forward) by ``pitch_deg`` and its
    y axis by ``roll_deg`` (and its z axis, the optical one, by ``yaw_deg``): each pixel's
    ray, undistorted, turned back into the declared camera and projected with its
    distortion."""
    import cv2
    import numpy as np
    from scipy.spatial.transform import Rotation

    K, D = np.reshape(info.k, (3, 3)), np.asarray(info.d, float)
    cols, rows = np.meshgrid(np.arange(info.width, dtype=np.float64),
                             np.arange(info.height, dtype=np.float64))
    pixels = np.stack([cols.ravel(), rows.ravel()], -1).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(pixels, K, D, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    turn = Rotation.from_euler("xyz", [pitch_deg, roll_deg, yaw_deg],
                               degrees=True).as_matrix()
    declared = np.c_[rays, np.ones(len(rays))] @ turn.T
    seen, _ = cv2.projectPoints(declared.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    seen = seen.reshape(info.height, info.width, 2).astype(np.float32)
    return seen[..., 0], seen[..., 1]


def gnss_on_gps_time(topic, at, decode):
    """Every GNSS fix stamped 18 s ahead (GPS time with the IMU in UTC): the filter must
    not start at those stamps (it started 540 m off and refused every later GNSS)."""
    if topic != "/gnss/fix":
        return None
    msg = decode()
    msg.header.stamp.sec += 18
    return msg


def geotiff(path: Path) -> Path:
    """A valid 64 x 64 GeoTIFF (UTM 11N)."""
    import numpy as np
    import rasterio
    from affine import Affine

    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1, dtype="int16",
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(np.ones((64, 64), np.int16), 1)
    return path


def relief_geotiff(path: Path, garbage=None, cells=slice(None)) -> Path:
    """An uncompressed 128 x 128 float32 GeoTIFF of gentle relief (UTM 11N, 30 m), its pixel
    bytes for ``cells`` (row-major) then overwritten with ``garbage(n)``."""
    import numpy as np
    import rasterio
    from affine import Affine

    rows, cols = np.mgrid[0:128, 0:128]
    z = (1000 + 80 * np.sin(cols / 9.0) * np.cos(rows / 13.0)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=128, height=128, count=1,
                       dtype="float32", crs="EPSG:32611",
                       transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(z, 1)
        offset = int(ds.get_tag_item("BLOCK_OFFSET_0_0", "TIFF", bidx=1))
    if garbage is not None:
        pixels = np.memmap(path, dtype=np.float32, mode="r+", offset=offset, shape=z.size)
        raw = pixels.view(np.uint8) if garbage == "random bytes" else pixels
        raw[cells] = (np.random.default_rng(5).integers(0, 256, raw[cells].size, np.uint8)
                      if garbage == "random bytes" else garbage)
        pixels.flush()
    return path


def antimeridian_geotiff(path: Path) -> Path:
    """A 1 x 1 degree GeoTIFF in EPSG:4326 over longitudes 179.5..180.5 (30", relief)."""
    import numpy as np
    import rasterio
    from affine import Affine

    rows, cols = np.mgrid[0:120, 0:120]
    z = (800 + 300 * np.sin(cols / 7.0) * np.cos(rows / 11.0)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=120, height=120, count=1,
                       dtype="float32", crs="EPSG:4326",
                       transform=Affine(1 / 120, 0, 179.5, 0, -1 / 120, 45.5)) as ds:
        ds.write(z, 1)
    return path


def nodata_geotiff(path: Path) -> Path:
    """A 64 x 64 GeoTIFF (UTM 11N) holding nothing but its nodata value."""
    import numpy as np
    import rasterio
    from affine import Affine

    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1, dtype="int16",
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6),
                       nodata=-9999) as ds:
        ds.write(np.full((64, 64), -9999, np.int16), 1)
    return path


def jacksboro_cut_east_of(path: Path, bag: Path, east: float) -> Path:
    """The embedded Jacksboro DEM as a GeoTIFF ending ``east`` m east of ``bag``'s mission
    origin (the columns beyond cut off): a mission DEM the flight leaves."""
    import math

    import rasterio
    import yaml

    from terrain_nav_ros.core.terrain.dem_io import sample_dem

    lat, lon, _ = yaml.safe_load((bag / "mission.yaml").read_text())["origin"]
    dem = sample_dem()
    z, t = dem.read(), dem.transform
    edge = lon + east / (111_320.0 * math.cos(math.radians(lat)))
    cols = int((edge - t.c) / t.a)
    with rasterio.open(path, "w", driver="GTiff", width=cols, height=z.shape[0], count=1,
                       dtype=str(z.dtype), crs="EPSG:4326", transform=t) as ds:
        ds.write(z[:, :cols], 1)
    return path


def scene_image(path: Path, dem: Path, *, crs: str | None = "EPSG:32611",
                east: float = 0.0) -> Path:
    """A uint8 image of ``dem`` (a :func:`relief_geotiff`): its hillshade, in ``crs`` (None:
    none), moved ``east`` metres."""
    import numpy as np
    import rasterio
    from affine import Affine

    from terrain_nav_ros.core.features.hillshade import hillshade

    with rasterio.open(dem) as ds:
        z = np.nan_to_num(ds.read(1).astype(np.float32).clip(0, 9000))
    grey = (hillshade(z, 160.0, 40.0, gsd=30.0) * 200.0 + 20.0).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=128, height=128, count=1,
                       dtype="uint8", crs=crs, nodata=255,
                       transform=Affine(30, 0, 4e5 + east, 0, -30, 3.8e6)) as ds:
        ds.write(grey, 1)
    return path


def image_variant(path: Path, dem: Path, kind: str) -> Path:
    """A :func:`scene_image` of ``dem`` made faulty: ``"fill"``, int16 reflectances with an
    undeclared -9999 fill over a third of it; ``"only fill"``, nothing but that fill;
    ``"gcps"``, georeferenced by control points only; ``"tiny"``, 12 x 12 px."""
    import numpy as np
    import rasterio
    from affine import Affine
    from rasterio.control import GroundControlPoint

    scene_image(path, dem)
    with rasterio.open(path) as ds:
        profile, grey, transform = ds.profile, ds.read(1), ds.transform
    if kind in ("fill", "only fill"):
        grey = grey.astype(np.int16) * 40
        grey[:40 if kind == "fill" else None] = -9999
        profile.update(dtype="int16", nodata=None)
    elif kind == "tiny":
        grey = grey[:12, :12]
        profile.update(width=12, height=12)
    elif kind == "gcps":
        profile.update(crs=None, transform=Affine.identity())
    with warnings.catch_warnings():
        # a file without a geotransform is what the "gcps" case is about
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        ds = rasterio.open(path, "w", **profile)
    with ds:
        ds.write(grey, 1)
        if kind == "gcps":
            h, w = grey.shape
            ds.gcps = ([GroundControlPoint(r, c, *(transform @ (c, r)))
                        for r, c in ((0, 0), (0, w), (h, 0), (h, w))], "EPSG:32611")
    return path


def corrupt_header(path: Path) -> Path:
    data = bytearray(path.read_bytes())
    data[8:200] = bytes((i * 37) % 256 for i in range(192))
    path.write_bytes(bytes(data))
    return path


# ----------------------------------------------------------------------------- judging
@dataclass
class Case:
    """One fault: ``run(tmp)`` returns (verdict, detail)."""

    name: str
    fault: str
    run: Callable[[Path], tuple[str, str]]
    ci: bool = False


def _written(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def judge(cmd: list, expect: int, words: tuple[str, ...], timeout: float = 60.0,
          stream: str = "stderr", one_line: bool = True) -> tuple[str, str]:
    """Run ``cmd`` and judge its answer against the exit status and words expected."""
    try:
        proc = subprocess.run([str(c) for c in cmd], text=True, capture_output=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return BAD, f"no answer within {timeout:.0f} s"
    out = getattr(proc, stream)
    lines = [line for line in out.strip().splitlines() if line.strip()]
    last = lines[-1][:110] if lines else "(no output)"
    if proc.returncode == 0 and expect != 0:
        return BAD, f"exit 0: {last}"
    if "Traceback" in proc.stdout + proc.stderr:
        return POOR, f"traceback, exit {proc.returncode}"
    missing = [w for w in words if w not in out]
    if proc.returncode != expect or missing or (one_line and len(lines) != 1):
        return POOR, f"exit {proc.returncode}, {len(lines)} lines, missing {missing}: {last}"
    return GOOD, f"exit {proc.returncode}: {last}"


def terrain_nav(*args) -> list:
    return [BIN / "terrain-nav", *args]


def _simulate_dem(make: Callable[[Path], Path], *words) -> Callable:
    return lambda tmp: judge(terrain_nav("simulate", "-o", tmp / "out", "--duration", 5,
                                         "--dem", make(tmp)), 2, words, timeout=30)


def _simulate_ok(make: Callable[[Path], Path], extra: tuple, stream: str, *words) -> Callable:
    """simulate must succeed, ``words`` in ``stream`` (a warning on stderr, or stdout's
    'wrote')."""
    return lambda tmp: judge(terrain_nav("simulate", "-o", tmp / "out", "--duration", 5,
                                         "--dem", make(tmp), *extra), 0, words, timeout=120,
                             stream=stream, one_line=False)


def _bag_info(change, *words) -> Callable:
    return lambda tmp: judge(terrain_nav("bag", "info", damaged_copy(
        make_bag(tmp / "whole"), tmp / "bag", change)), 1, ("DAMAGED", *words),
        stream="stdout", one_line=False)


def _replay(make_bag_dir: Callable[[Path], Path], extra: tuple, *words) -> Callable:
    return lambda tmp: judge(terrain_nav("replay", "--bag", make_bag_dir(tmp), "--out",
                                         tmp / "replay", *extra), 2, words)


def _evaluate(image: Callable[[Path, Path], Path], dem: Callable[[Path], Path], expect: int,
              *words, stream: str = "stderr") -> Callable:
    """``evaluate --image`` of a scene made by ``image(tmp, dem_path)`` and ``dem(tmp)``."""
    def run(tmp: Path):
        dem_path = dem(tmp)
        return judge(terrain_nav("evaluate", "--image", image(tmp, dem_path), "--dem", dem_path,
                                 "--sun", "160,40", "--sizes", 32, "--cases", 2, "--controls",
                                 0, "--no-baselines", "--heading", "unknown", "--out",
                                 tmp / "study"), expect, words, timeout=120, stream=stream,
                     one_line=expect != 0)
    return run


def _evaluate_scenes(text: str, *words) -> Callable:
    """``evaluate --scenes`` of a scenes file ``text`` naming a good image and DEM."""
    def run(tmp: Path):
        scene_image(tmp / "image.tif", relief_geotiff(tmp / "dem.tif"))
        (tmp / "scenes.yaml").write_text(text)
        return judge(terrain_nav("evaluate", "--scenes", tmp / "scenes.yaml", "--sizes", 32,
                                 "--cases", 2, "--no-baselines", "--out", tmp / "study"), 2,
                     words, timeout=120)
    return run


def _node_params(yaml_text: str, *words, node: str = "ekf") -> Callable:
    def run(tmp: Path):
        params = tmp / "params.yaml"
        params.write_text(f"{node}:\n  ros__parameters:\n{yaml_text}")
        # the node may log its start before it checks its parameters: not one line
        return judge([BIN / node, "--ros-args", "--params-file", params], 1, words,
                     one_line=False)
    return run


def _ekf_stamp(offset: float) -> Callable:
    def run(_tmp: Path):
        import numpy as np

        from terrain_nav_ros.core.estimation.ekf import EkfParams, TerrainEkf
        from terrain_nav_ros.core.sim.imu_sim import ImuErrorModel, simulate_imu
        from terrain_nav_ros.core.sim.trajectory_sim import simulate_trajectory, straight_flight

        params = EkfParams(init_mode="gnss")
        truth = simulate_trajectory(straight_flight(8.0), rate_hz=100.0)
        imu = simulate_imu(truth, ImuErrorModel.from_params(params), np.random.default_rng(1))
        ekf = TerrainEkf(params)
        ekf.initialize(truth.t[0], truth.position[0], truth.velocity[0], truth.quaternion[0])
        for k in range(1, len(truth)):   # GNSS gone: IMU only, one bad stamp at 4 s
            ekf.process_imu(truth.t[k], imu.gyro[k], imu.accel[k])
            if k == 400:
                ekf.process_imu(truth.t[k] + offset, imu.gyro[k], imu.accel[k])
        d = ekf.diagnostics
        err = float(np.linalg.norm(ekf.state.position - truth.position[-1]))
        detail = (f"refused {d.imu_stamps_refused}, resets {d.resets}, final error "
                  f"{err:.1f} m, filter at {ekf.t:.2f} s")
        if not ekf.initialized or abs(ekf.t - truth.t[-1]) > 1e-6 or err > 50.0:
            return BAD, detail
        return (GOOD if d.imu_stamps_refused == 1 and d.resets == 0 else POOR), detail
    return run


def cases() -> list[Case]:
    """Every fault case, in table order."""
    asc = ASC_HEADER.format
    return [
        Case("truncated ESRI ASCII grid (100x100, 4 values)", "dem", _simulate_dem(
            lambda t: _write(t / "cut.asc", asc(c=100, r=100) + "1 2 3 4\n"),
            "truncated ESRI ASCII grid")),
        Case("ESRI ASCII header promising 1e18 cells", "dem", _simulate_dem(
            lambda t: _write(t / "huge.asc", asc(c=10**9, r=10**9) + "1 2 3\n"),
            "truncated ESRI ASCII grid"), ci=True),
        Case("ESRI ASCII grid with 9/10 of its values", "dem", _simulate_dem(
            lambda t: _write(t / "short.asc", asc(c=100, r=100) + "1234.5 " * 9000),
            "holds 9000 values")),
        Case("SRTM .hgt cut short", "dem", _simulate_dem(
            lambda t: _write(t / "N44E005.hgt", bytes(2 * 1201 * 1201 - 100)), "truncated?")),
        Case("GeoTIFF with a corrupt header", "dem", _simulate_dem(
            lambda t: corrupt_header(geotiff(t / "bad.tif")), "corrupt header")),
        Case("empty GeoTIFF", "dem", _simulate_dem(
            lambda t: _write(t / "empty.tif", b""), "not a readable DEM")),
        Case("DEM file missing", "dem", _simulate_dem(
            lambda t: t / "nope.tif", "no such DEM file")),
        Case("ESRI ASCII grid with a value that is not a number", "dem", _simulate_dem(
            lambda t: _write(t / "garbled.asc", asc(c=4, r=3) + "1 2 3 4\n5 abc 7 8\n9 1 2 3\n"),
            "value 6 (row 2, column 2) is 'abc', not a number"), ci=True),
        Case("GeoTIFF pixels overwritten with -1e30", "dem", _simulate_dem(
            lambda t: relief_geotiff(t / "garbage.tif", -1e30),
            "16384 of 16384 heights (100 %) are impossible on Earth")),
        Case("GeoTIFF pixels overwritten with random bytes", "dem", _simulate_dem(
            lambda t: relief_geotiff(t / "random.tif", "random bytes"),
            "are impossible on Earth")),
        Case("GeoTIFF with a few 3e38 pixels", "dem", _simulate_ok(
            lambda t: relief_geotiff(t / "spots.tif", 3e38, slice(650, 654)), (), "stderr",
            "warning", "4 of 16384 heights", "read as voids")),
        Case("DEM all nodata under the route", "dem", _simulate_dem(
            lambda t: nodata_geotiff(t / "void.tif"), "no heights under the route")),
        Case("DEM across the antimeridian (179.5..180.5)", "dem", _simulate_ok(
            lambda t: antimeridian_geotiff(t / "am.tif"),
            ("--start-time", "2024-06-21T00:00:00Z"), "stdout", "wrote")),
        Case("evaluate: image and DEM of different places", "imagery", _evaluate(
            lambda t, d: scene_image(t / "far.tif", d, east=50_000.0),
            lambda t: relief_geotiff(t / "dem.tif"), 2, "are they of the same place?")),
        Case("evaluate: image without a CRS", "imagery", _evaluate(
            lambda t, d: scene_image(t / "nocrs.tif", d, crs=None),
            lambda t: relief_geotiff(t / "dem.tif"), 2, "has no CRS")),
        Case("evaluate: DEM pixels overwritten with -1e30", "imagery", _evaluate(
            lambda t, d: scene_image(t / "image.tif", d),
            lambda t: relief_geotiff(t / "garbage.tif", -1e30), 2, "impossible on Earth"),
             ci=True),
        Case("evaluate: DEM with undeclared -32768 voids", "imagery", _evaluate(
            lambda t, d: scene_image(t / "image.tif", d),
            lambda t: relief_geotiff(t / "voids.tif", -32768.0, slice(4000, 4400)), 0,
            "warning", "400 of 16384 heights", "read as voids")),
        Case("evaluate: image with an undeclared -9999 fill", "imagery", _evaluate(
            lambda t, d: image_variant(t / "fill.tif", d, "fill"),
            lambda t: relief_geotiff(t / "dem.tif"), 0, "warning", "hold -9999",
            "read as no data")),
        Case("evaluate: image of fill only", "imagery", _evaluate(
            lambda t, d: image_variant(t / "fill.tif", d, "only fill"),
            lambda t: relief_geotiff(t / "dem.tif"), 2, "every valid pixel holds -9999")),
        Case("evaluate: image georeferenced by control points only", "imagery", _evaluate(
            lambda t, d: image_variant(t / "gcps.tif", d, "gcps"),
            lambda t: relief_geotiff(t / "dem.tif"), 0, "wrote", stream="stdout")),
        Case("evaluate: image smaller than every view", "imagery", _evaluate(
            lambda t, d: image_variant(t / "tiny.tif", d, "tiny"),
            lambda t: relief_geotiff(t / "dem.tif"), 2, "no view of 32 px fits")),
        Case("evaluate: scenes file with a misspelt key", "imagery", _evaluate_scenes(
            "scenes: [{image: image.tif, dem: dem.tif, sun: [160, 40], bnad: 1}]",
            "unknown key bnad")),
        Case("evaluate: scenes file with a sun of one number", "imagery", _evaluate_scenes(
            "scenes: [{image: image.tif, dem: dem.tif, sun: [160]}]",
            "the sun must be two numbers")),
        Case("bag cut to 50 %", "bag", _bag_info(cut_half, "cut short"), ci=True),
        Case("bag with corrupted bytes", "bag", _bag_info(corrupt_chunk, "corrupt data")),
        Case("bag without metadata.yaml", "bag", _bag_info(None, "metadata.yaml")),
        Case("bag play of a corrupt bag", "bag", lambda tmp: judge(terrain_nav(
            "bag", "play", damaged_copy(make_bag(tmp / "whole"), tmp / "bag", corrupt_chunk),
            "--rate", 100), 1, ("DAMAGED", "stopped after"), one_line=False)),
        Case("replay of an empty folder", "replay", _replay(
            lambda t: t, (), "no .mcap file")),
        Case("replay with a broken mission.yaml", "replay", _replay(
            lambda t: with_mission(make_bag(t / "whole"), t / "bag", "dem: [unclosed\n"), (),
            "mission.yaml is not valid YAML")),
        Case("replay with a mission origin of two numbers", "replay", _replay(
            lambda t: with_mission(make_bag(t / "whole"), t / "bag", "origin: [36.5, -84]\n"),
            (), "origin must be [lat, lon, height]"), ci=True),
        Case("replay of a mission naming a missing DEM", "replay", _replay(
            lambda t: with_mission(make_bag(t / "whole"), t / "bag", "dem: /no/dem.tif\n"), (),
            "no such DEM file")),
        Case("replay of a bag whose /imu/data is not sensor_msgs/Imu", "replay", _replay(
            lambda t: make_bag(t / "whole"), (),
            "/imu/data is std_msgs/msg/String, not sensor_msgs/msg/Imu"), ci=True),
        Case("replay --rate 0", "replay", _replay(
            lambda t: make_bag(t / "whole"), ("--rate", 0), "--rate 0.0: must be > 0")),
        Case("replay --rate nan", "replay", _replay(
            lambda t: make_bag(t / "whole"), ("--rate", "nan"), "must be > 0")),
        Case("simulate --duration -5", "options", lambda tmp: judge(terrain_nav(
            "simulate", "-o", tmp / "out", "--duration", -5), 2, ("--duration",))),
        Case("simulate --cloud-cover 1.5", "options", lambda tmp: judge(terrain_nav(
            "simulate", "-o", tmp / "out", "--duration", 5, "--cloud-cover", 1.5), 2,
            ("cloud cover",))),
        Case("simulate over an existing output", "options", lambda tmp: judge(terrain_nav(
            "simulate", "-o", tmp, "--duration", 5), 2, ("exists already",))),
        Case("prepare of an area beyond its DEM", "options", _prepare(
            ("--area", "34.30,-118.06,34.40,-117.90", "--suns", "120/40"),
            "the DEMs do not cover the area")),
        Case("prepare without suns", "options", _prepare(
            (), "give --suns AZ/EL,... (degrees) or --time ISO8601")),
        Case("prepare --hours 1e9", "options", _prepare(
            ("--time", "2024-06-21T08:00:00Z", "--hours", "1e9"), "--hours 1e+09 0-48")),
        Case("simulate --camera-hfov 120", "options", lambda tmp: judge(terrain_nav(
            "simulate", "-o", tmp / "out", "--camera-hfov", 120), 2, ("below 90 deg",))),
        Case("simulate --duration 0.5 (no camera frame)", "options", lambda tmp: judge(
            terrain_nav("simulate", "-o", tmp / "out", "--duration", 0.5), 2,
            ("--duration 0.5: must be 2 s",))),
        Case("simulate --camera-width 10000 --camera-height 10000", "options", lambda tmp:
             judge(terrain_nav("simulate", "-o", tmp / "out", "--camera-width", 10000,
                               "--camera-height", 10000), 2, ("100 M pixels, at most",))),
        Case("replay --lost 1e9 0", "options", _replay(
            lambda t: make_bag(t / "whole"), ("--lost", "1e9", "0"), "within 1000 km")),
        Case("prepare --area of three numbers", "options", _prepare(
            ("--area", "34.3,-118.1,34.4", "--suns", "120/40"), "give LAT,LON,LAT,LON")),
        Case("graph --config missing", "options", lambda tmp: judge(terrain_nav(
            "graph", "--config", tmp / "nope.yaml"), 2, ("cannot read graph file",))),
        Case('graph file with enabled: "false" quoted', "options", lambda tmp: judge(
            terrain_nav("graph", "--config", _written(
                tmp / "g.yaml", 'nodes:\n  - {name: autopilot_bridge, enabled: "false"}\n')),
            2, ("enabled 'false' must be true or false",)), ci=True),
        Case("graph --only a node not in the graph", "options", lambda tmp: judge(terrain_nav(
            "graph", "--only", "nosuchnode"), 2, ("cannot enable nosuchnode",))),
        Case("graph --duration nan", "options", lambda tmp: judge(terrain_nav(
            "graph", "--duration", "nan"), 2, ("--duration nan: must be > 0",))),
        Case("bag play --topics of a topic not in the bag", "options", lambda tmp: judge(
            terrain_nav("bag", "play", make_bag(tmp / "whole"), "--topics", "/nope"), 2,
            ("--topics /nope: not in bag",))),
        Case("misspelt parameter (time_jump_reste)", "parameters", _node_params(
            "    time_jump_reste: 2.0\n",
            "unknown parameter(s) time_jump_reste (did you mean time_jump_reset?)")),
        Case("NaN parameter (gravity: .nan)", "parameters", _node_params(
            "    gravity: .nan\n", "gravity out of range"), ci=True),
        Case("matcher: misspelt match.thresold", "parameters", _node_params(
            "    match.thresold: 9.0\n", "unknown parameter(s) match.thresold (did you mean "
            "match.threshold?)", node="matcher")),
        Case("matcher: match.search_scale 0.7", "parameters", _node_params(
            "    match.search_scale: 0.7\n", "match.search_scale out of range",
            node="matcher")),
        Case("matcher: match.candidates kd", "parameters", _node_params(
            "    match.candidates: kd\n", "MatchParams.candidates must be one of",
            node="matcher")),
        Case("matcher: mission_dir that holds no index", "parameters", _node_params(
            "    mission_dir: /nonexistent/mission\n", "holds no mission index",
            node="matcher")),
        Case("matcher: mission index with a tile layer missing", "parameters",
             _partial_mission),
        Case("matcher: mission index with a tile cut short", "parameters",
             _damaged_mission),
        Case("IMU in FRD axes (z down)", "flight", _refused_imu(frd_imu, "FRD / NED")),
        Case("IMU acceleration in g", "flight", _refused_imu(imu_in_g, "in g, not m/s^2")),
        Case("gyro in deg/s (demo bag to 80 s: a turn from 61 s)", "flight",
             _refused_imu(gyro_in_deg_until_80_s, "deg/s, not rad/s", "jacksboro_demo")),
        Case("matcher killed 20 s into the flight (SIGKILL)", "flight", _flight(
            None, kill="matcher")),
        Case("landmark renderer killed 20 s into the flight (SIGKILL)", "flight", _flight(
            None, kill="landmark_renderer")),
        Case("ekf killed 20 s into the flight (SIGKILL)", "flight", _flight(
            None, kill="ekf")),
        Case("camera frozen for 15 s mid-flight", "flight", _flight(
            frozen_camera(25.0, 15.0), "camera frozen", 12)),
        Case("camera clock 2 s back for 10 s", "flight", _flight(
            camera_clock_back, "older than the newest estimate", 8)),
        Case("one camera frame stamped 1 h ahead at 30 s", "flight", _flight(
            camera_stamp_ahead)),
        Case("camera mounted 2 deg off in pitch (not declared)", "flight",
             _flight(camera_tilted(2.0))),
        Case("camera mounted 2 deg off in roll (not declared)", "flight",
             _flight(camera_tilted(0.0, 2.0))),
        Case("camera mounted 3 deg off in yaw (not declared)", "flight",
             _flight(camera_tilted(0.0, 0.0, 3.0))),
        Case("GNSS at (0, 0) for its first second", "flight", _flight(gnss_at_zero_first)),
        Case("GNSS stamped 18 s ahead (GPS time, IMU in UTC)", "flight",
             _refused_imu(gnss_on_gps_time, "another clock, GPS time against UTC?")),
        Case("camera frames turned 180 deg (mount not declared)", "flight",
             _flight(camera_turned_180)),
        Case("camera frames mirrored left to right (a driver's flip)", "flight",
             _flight(camera_mirrored, "flipped back left to right it matches", 2)),
        Case("camera frames flipped top to bottom (a driver's flip)", "flight",
             _flight(camera_flipped_vertically, "flipped back top to bottom it matches", 2),
             ci=True),
        Case("camera lens covered for 10 s (black frames)", "flight", _flight(
            covered_lens, "image is constant", 10)),
        Case("camera frames banded for 20 s (a sensor's row banding)", "flight",
             _fixes_near_truth(banded_frames, 25.0, 45.0)),
        Case("camera frames under bright haze for 20 s", "flight",
             _fixes_near_truth(hazy_frames, 25.0, 45.0)),
        Case("camera frames under-exposed (x0.15) for 20 s", "flight",
             _fixes_near_truth(underexposed_frames, 25.0, 45.0)),
        Case("camera frames under a cloud bank for 15 s (auto-exposed)", "flight",
             _flight(cloud_bank, "mostly cloud", 12)),
        Case("camera frames out of focus (3 px blur) for 20 s", "flight",
             _fixes_near_truth(defocused_frames, 25.0, 45.0)),
        Case("camera frames with sensor noise (25 grey levels) for 20 s", "flight",
             _fixes_near_truth(noisy_frames, 25.0, 45.0)),
        Case("camera frames over-exposed (x1.5, highlights clipped) for 20 s", "flight",
             _fixes_near_truth(overexposed_frames, 25.0, 45.0)),
        Case("camera frames saturated white (x3) for 20 s", "flight",
             _flight(saturated_frames, "bright and featureless", 18)),
        Case("barometer stuck at 90 kPa from 25 s", "flight", _flight(frozen_baro)),
        Case("barometer in hPa", "flight", _flight(baro_in_hpa)),
        Case("barometer frozen at its 25 s reading in a climb", "flight",
             _flight(frozen_baro_reading(25.0))),
        Case("accelerometer bias step of 0.5 m/s^2 up from 30 s", "flight",
             _flight(accelerometer_bias_step("z"))),
        Case("accelerometer bias step of 0.5 m/s^2 forward from 30 s", "flight",
             _flight(accelerometer_bias_step("x"))),
        Case("roll gyro bias step of 0.5 deg/s from 30 s", "flight",
             _flight(gyro_bias_step("x", 0.5))),
        Case("pitch gyro bias step of 0.2 deg/s from 30 s", "flight",
             _flight(gyro_bias_step("y", 0.2))),
        Case("pitch gyro bias step of 0.1 deg/s from 30 s", "flight",
             _flight(gyro_bias_step("y", 0.1))),
        Case("accelerometer vibrating at 2 m/s^2 from 15 s", "flight",
             _flight(vibrating_accelerometer(2.0))),
        Case("yaw gyro bias step of 0.5 deg/s from 30 s", "flight",
             _flight(gyro_bias_step("z", 0.5))),
        Case("GNSS spoofed 200 m north for 4 s before the denial", "flight",
             _flight(spoofed_gnss)),
        Case("IMU samples with NaN for 0.5 s", "flight", _flight(nan_imu)),
        Case("IMU silent for 3 s", "flight", _flight(imu_gap)),
        Case("CameraInfo with a zero K for 10 s", "flight", _flight(
            uncalibrated_camera, "not calibrated", 8)),
        Case("CameraInfo focal length 10 % long (not declared)", "flight",
             _flight(focal_length_off(1.1))),
        Case("CameraInfo focal length 10 % short (not declared)", "flight",
             _flight(focal_length_off(0.9))),
        Case("mission DEM ending 1 km east of the start (the flight leaves it)", "flight",
             _past_the_dem_s_edge(1000.0, 40.0)),
        Case("GNSS jammed from the start (replay --lost 0 0)", "flight",
             _flight(None, options=("--lost", "0", "0"))),
        Case("IMU stamp 5 s in the past, GNSS gone", "ekf", _ekf_stamp(-5.0)),
        Case("IMU stamp 1 h ahead, GNSS gone", "ekf", _ekf_stamp(3600.0), ci=True),
    ]


def _prepare(options: tuple, words: str):
    """``prepare`` over the small relief GeoTIFF (UTM 11N, around 34.3 N 118.1 W) with
    ``options``: refused with exit 2 and ``words`` before any work."""
    return lambda tmp: judge(terrain_nav(
        "prepare", "--dem", relief_geotiff(tmp / "relief.tif"), "--gsd", 30, "--out",
        tmp / "index", *options), 2, (words,))


def _flight(change: Callable | None, reason: str = "", at_least: int = 0,
            kill: str = "", options: tuple = (), bag: str | Path = "jacksboro_short"
            ) -> Callable:
    """The short bag changed by ``change`` (:func:`~terrain_nav_ros.tools.bags.changed_copy`)
    and replayed: GOOD when the fused error, horizontal and height, stays bounded (3 x 20
    m), every frame that reached camera_ingest is answered (one of the bag's may be lost on
    the way: the camera topic is best effort) and, with ``reason``, at least ``at_least``
    frames get a no-fix saying it. With ``kill``, that node is killed (SIGKILL) 20 s into
    the flight: GOOD also needs it respawned, and the frames of its restart (up to 8: the
    respawn delay and the node's start-up, 2-5 s) may go unanswered. ``options`` go to
    ``replay``; ``bag`` names one of bags/ or is a bag's folder."""
    def run(tmp: Path):
        report, failed = _replayed(tmp, change, kill, bag=bag, options=options)
        if report is None:
            return BAD, failed
        fixes, fused = report["fixes"], report["fused_error"]
        height = report["fused_height_error"]
        said = sum(n for text, n in fixes["reasons"] if reason and reason in text)
        respawns = report["usage"].get(kill, {}).get("respawns", 0) if kill else 0
        detail = (f"{fixes['fixes']} fixes, {fixes['frames']} of {fixes['in_bag']} frames "
                  f"answered{f', {said} {reason!r}' if reason else ''}, fused RMS "
                  f"{fused['rms']:.1f} m, final {fused['final']:.1f} m, height final "
                  f"{height['final']:.1f} m, died {report['died']}"
                  + (f", {kill} respawned {respawns}x" if kill else ""))
        crashed = [n for n, u in report["usage"].items() if u.get("respawns") and n != kill]
        if crashed:   # respawned, but a crash all the same
            detail += f", {', '.join(crashed)} crashed and respawned"
        if max(fused["final"], fused["rms"], height["final"], height["rms"]) > 3 * 20.0 \
                or report["died"] or crashed or (kill and not respawns):
            return BAD, detail
        unanswered = fixes["in_bag"] - fixes["frames"]
        if kill:
            answered = unanswered <= 8
        else:   # every frame that reached the graph; the camera's best-effort link may drop one
            lost = fixes.get("lost_on_the_way") or 0
            answered = fixes["frames"] >= fixes["in_bag"] - lost and lost <= 1
            if lost:
                detail += f", {lost} frame(s) lost before camera_ingest"
        if not answered and fixes.get("unanswered_at"):
            detail += f", unanswered at {fixes['unanswered_at']} s"
        return (GOOD if said >= at_least and answered else POOR), detail
    return run


def _fixes_near_truth(change: Callable | None, start: float, end: float,
                      bag: str | Path = "jacksboro_short") -> Callable:
    """As :func:`_flight`, and BAD when any fix is off the truth by more than 3 landmark
    pixels (60 m), POOR when the frames of ``start``-``end`` s made fewer than half the
    fixes they would: what the change does to a frame must not become a wrong fix."""
    flight = _flight(change, bag=bag)

    def run(tmp: Path):
        verdict, detail = flight(tmp)
        report = _last_report(tmp)
        if report is None:
            return verdict, detail
        worst = (report.get("fix_error") or {}).get("max", 0.0)   # none without fixes
        made = _fixes_between(tmp, start, end)
        detail += f", fix error max {worst:.1f} m, {made} fixes in {start:g}-{end:g} s"
        if worst > 3 * 20.0:
            return BAD, detail
        return (verdict if made >= 0.5 * (end - start) else POOR), detail
    return run


def _past_the_dem_s_edge(east: float, after: float) -> Callable:
    """The short bag replayed over its DEM cut off ``east`` m east of the start: the flight
    (heading east) leaves it ``after`` s in. As :func:`_fixes_near_truth` over the frames
    past the edge: they must still be fixed on the ground the DEM holds, and rightly."""
    def run(tmp: Path):
        import shutil

        import yaml

        from terrain_nav_ros.tools.cli import REPO

        bag = Path(shutil.copytree(REPO / "bags" / "jacksboro_short", tmp / "bag"))
        mission = yaml.safe_load((bag / "mission.yaml").read_text())
        mission["dem"] = str(jacksboro_cut_east_of(tmp / "cut.tif", bag, east))
        (bag / "mission.yaml").write_text(yaml.safe_dump(mission))
        return _fixes_near_truth(None, after, 60.0, bag=bag)(tmp)
    return run


def _last_report(tmp: Path) -> dict | None:
    import yaml

    path = tmp / "out" / "report.yaml"
    return yaml.safe_load(path.read_text()) if path.exists() else None


def _fixes_between(tmp: Path, start: float, end: float) -> int:
    """Fixes (status not NO_FIX) of the replay's frames stamped ``start``-``end`` s after
    its first camera frame."""
    from terrain_nav_ros.tools import bags

    stamps = [bags.decode(m) for m in bags.read(tmp / "out" / "outputs", ["/nav/pva_fix"])]
    if not stamps:
        return 0
    first = min(s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in stamps)
    return sum(1 for s in stamps if s.status != 0 and start <= s.header.stamp.sec
               + 1e-9 * s.header.stamp.nanosec - first < end)


def _refused_imu(change: Callable, words: str, bag: str = "jacksboro_short") -> Callable:
    """``bag`` with its IMU changed by ``change`` and replayed: GOOD when the ekf publishes
    no estimate, or stops publishing one, and its diagnostics say why (``words``), BAD when
    it navigates on the wrong IMU (or says nothing)."""
    def run(tmp: Path):
        report, failed = _replayed(tmp, change, bag=bag)
        if report is None:
            return BAD, failed
        stopped = report.get("odometry_stopped")
        said = report.get("no_odometry") or (stopped or {}).get("why")
        if said and words in said:
            when = f"estimate stopped at {stopped['at']:.1f} s: " if stopped else "no estimate: "
            return GOOD, when + said[:150]
        return BAD, f"navigated on it: {said or 'no reason given'}"
    return run


def frd_imu(topic, at, decode):
    """Every IMU sample in FRD axes (y and z negated), as PX4 and many drivers give it."""
    if topic != "/imu/data":
        return None
    msg = decode()
    for vector in (msg.angular_velocity, msg.linear_acceleration):
        vector.y, vector.z = -vector.y, -vector.z
    return msg


def imu_in_g(topic, at, decode):
    """Every IMU acceleration in g, not m/s^2."""
    if topic != "/imu/data":
        return None
    msg = decode()
    a = msg.linear_acceleration
    a.x, a.y, a.z = a.x / 9.80665, a.y / 9.80665, a.z / 9.80665
    return msg


def gyro_in_deg_until_80_s(topic, at, decode):
    """Every gyro rate in deg/s, not rad/s; the bag cut at 80 s."""
    if at > 80.0:
        return "drop"
    if topic != "/imu/data":
        return None
    msg = decode()
    w = msg.angular_velocity
    w.x, w.y, w.z = math.degrees(w.x), math.degrees(w.y), math.degrees(w.z)
    return msg


def _replayed(tmp: Path, change: Callable | None, kill: str = "",
              bag: str | Path = "jacksboro_short",
              options: tuple = ()) -> tuple[dict | None, str]:
    """``bag`` (of bags/, or a bag's folder) changed by ``change`` (None: as it is) replayed
    with ``options``, ``kill`` killed in it (:func:`_replay_killing`): its report.yaml, or
    None and why there is none."""
    import yaml

    from terrain_nav_ros.tools import bags
    from terrain_nav_ros.tools.cli import REPO

    bag = REPO / "bags" / bag
    if change is not None:
        bag = bags.changed_copy(bag, tmp / "bag", change)
    cmd = terrain_nav("replay", "--bag", bag, "--out", tmp / "out", *options)
    try:
        code, err = _replay_killing(cmd, tmp, kill) if kill else _replay_plain(cmd)
    except subprocess.TimeoutExpired:
        return None, "replay did not finish within 400 s"
    if code != 0:
        return None, f"replay exit {code}: {err.strip()[-110:]}"
    return yaml.safe_load((tmp / "out" / "report.yaml").read_text()), ""


def _replay_plain(cmd: list) -> tuple[int, str]:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=400)
    return proc.returncode, proc.stderr


def _replay_killing(cmd: list, tmp: Path, node: str, after: float = 20.0) -> tuple[int, str]:
    """Run a replay and SIGKILL its ``node`` ``after`` s once the graph is up."""
    import time

    import psutil

    out = tmp / "replay.out"
    with open(out, "w") as sink:
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, text=True)
        try:
            deadline = time.monotonic() + 120.0
            while "nodes up" not in out.read_text() and time.monotonic() < deadline \
                    and proc.poll() is None:
                time.sleep(0.5)
            time.sleep(after)
            for child in psutil.Process(proc.pid).children(recursive=True):
                if f"__node:={node}" in child.cmdline():
                    child.kill()
            proc.wait(timeout=400)
        finally:
            if proc.poll() is None:
                proc.kill()
    return proc.returncode, out.read_text()


def _partial_mission(tmp: Path):
    """A mission index of the small relief GeoTIFF with one tile layer deleted (a prepare
    cut short): the matcher refuses it at start-up, naming the fix."""
    index = tmp / "index"
    subprocess.run(terrain_nav("prepare", "--dem", relief_geotiff(tmp / "relief.tif"), "--gsd",
                               "60", "--tile", "128", "--overlap", "32", "--suns", "135/45",
                               "--workers", "1", "--out", index), capture_output=True,
                   check=True, timeout=300)
    next((index / "tiles").glob("*.npz")).unlink()
    return _node_params(f"    mission_dir: {index}\n", "tile layers missing: run "
                        "terrain-nav prepare again", node="matcher")(tmp)


def _damaged_mission(tmp: Path):
    """A mission index of the small relief GeoTIFF with one tile layer cut to half (a disk
    that filled, a copy stopped): the matcher refuses it at start-up, naming the file."""
    index = tmp / "index"
    subprocess.run(terrain_nav("prepare", "--dem", relief_geotiff(tmp / "relief.tif"), "--gsd",
                               "60", "--tile", "128", "--overlap", "32", "--suns", "135/45",
                               "--workers", "1", "--out", index), capture_output=True,
                   check=True, timeout=300)
    layer = next((index / "tiles").glob("*.npz"))
    layer.write_bytes(layer.read_bytes()[: layer.stat().st_size // 2])
    return _node_params(f"    mission_dir: {index}\n", "tile layer(s) damaged",
                        node="matcher")(tmp)


def _write(path: Path, data) -> Path:
    (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)
    return path


def run_cases(selected: list[Case], report: Callable | None = None
              ) -> list[tuple[Case, str, str]]:
    """Run each case in its own temporary folder; (case, verdict, detail) rows, each also
    handed to ``report`` as it is answered (a long run killed part way keeps what it did)."""
    rows = []
    for case in selected:
        with tempfile.TemporaryDirectory(prefix="fault-") as tmp:
            try:
                verdict, detail = case.run(Path(tmp))
            except Exception as err:  # noqa: BLE001 - a case that breaks is a finding
                verdict, detail = BAD, f"the case itself failed: {type(err).__name__}: {err}"
        rows.append((case, verdict, detail))
        if report is not None:
            report(rows[-1])
    return rows


TABLE_HEADER = f"{'class':10s} {'case':48s} {'verdict':7s} answer"


def table_row(row) -> str:
    case, verdict, detail = row
    return f"{case.fault:10s} {case.name:48s} {verdict:7s} {detail}"


def tally(rows) -> str:
    counts = {v: sum(1 for _, got, _ in rows if got == v) for v in (GOOD, POOR, BAD)}
    return ", ".join(f"{n} {v}" for v, n in counts.items()) + f" of {len(rows)}"


def main(argv=None) -> int:
    # the nodes started here must not meet another graph on this machine (as in the tests)
    os.environ.setdefault("ROS_DOMAIN_ID", str(101 + os.getpid() % 100))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ci", action="store_true", help="only the subset ./tn test runs")
    parser.add_argument("-k", default="", help="only cases whose name holds this")
    args = parser.parse_args(argv)
    selected = [c for c in cases() if (c.ci or not args.ci) and args.k in c.name]
    print(TABLE_HEADER, flush=True)
    rows = run_cases(selected, lambda row: print(table_row(row), flush=True))
    print(tally(rows))
    return 1 if any(v == BAD for _, v, _ in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
