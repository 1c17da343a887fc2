"""Round trips through the one conversions module."""

import math

import numpy as np
import pytest
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from terrain_nav_ros.core.features.minutia_set import BIFURCATION, ENDING, MinutiaSet
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv

RNG = np.random.default_rng(7)

CASES = {
    "mono8": RNG.integers(0, 256, (5, 7), dtype=np.uint8),
    "mono16": RNG.integers(0, 65536, (5, 7), dtype=np.uint16),
    "32FC1": RNG.standard_normal((5, 7)).astype(np.float32),
    "rgb8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "bgr8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
}


@pytest.mark.parametrize("encoding", sorted(CASES))
def test_image_round_trip(encoding):
    arr = CASES[encoding]
    msg = cv.array_to_image(arr, encoding)
    assert (msg.encoding, msg.height, msg.width) == (encoding, 5, 7)
    np.testing.assert_array_equal(cv.image_to_array(msg), arr)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_mosaics_come_back_demosaiced_to_grey(pattern, bits):
    # a smooth colour scene, sampled through each colour filter layout as a camera does
    y, x = np.mgrid[0:40, 0:60]
    scale = 255.0 if bits == 8 else 65535.0
    rgb = np.stack([0.2 + 0.6 * x / 59, 0.3 + 0.4 * y / 39, 0.8 - 0.5 * x / 59], -1) * scale
    rgb = rgb.astype(np.uint8 if bits == 8 else np.uint16)
    mosaic = np.empty(rgb.shape[:2], rgb.dtype)
    for k, colour in enumerate(pattern):   # the 2x2 cell, row by row
        mosaic[k // 2::2, k % 2::2] = rgb[k // 2::2, k % 2::2, "rgb".index(colour)]
    grey = cv.image_to_array(cv.array_to_image(mosaic, f"bayer_{pattern}{bits}"))
    expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    assert grey.shape == mosaic.shape and grey.dtype == mosaic.dtype
    # inside the border the demosaiced grey is the scene's (a wrong layout is 11-24 % off)
    error = np.abs(grey[2:-2, 2:-2].astype(float) - expected[2:-2, 2:-2]) / scale
    assert error.max() < 0.02
    with pytest.raises(cv.ConversionError, match="at least 2x2"):
        cv.image_to_array(cv.array_to_image(mosaic[:1], f"bayer_{pattern}{bits}"))


def test_image_with_row_padding_and_big_endian():
    arr = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    padded = np.zeros((3, 10), dtype=np.uint8)  # step 10 > 4 px * 2 bytes
    padded[:, :8] = arr.astype(">u2").view(np.uint8).reshape(3, 8)
    msg = Image(height=3, width=4, encoding="mono16", is_bigendian=1, step=10,
                data=padded.tobytes())
    np.testing.assert_array_equal(cv.image_to_array(msg), arr)


def test_unsupported_and_truncated_images_raise_clear_errors():
    with pytest.raises(cv.ConversionError, match="unsupported image encoding 'yuv422'"):
        cv.image_to_array(Image(height=1, width=1, encoding="yuv422", step=2, data=b"ab"))
    with pytest.raises(cv.ConversionError, match="too small"):
        cv.image_to_array(Image(height=4, width=4, encoding="mono8", step=4, data=b"abc"))
    with pytest.raises(cv.ConversionError):
        cv.array_to_image(np.zeros((2, 2), np.int64))


def test_colour_to_grey_respects_channel_order():
    red = np.zeros((1, 1, 3), np.uint8)
    red[..., 0] = 200
    assert cv.to_grey(red, "rgb8")[0, 0] == round(200 * 0.299)
    assert cv.to_grey(red, "bgr8")[0, 0] == round(200 * 0.114)


def test_camera_info_round_trip_and_uncalibrated_error():
    k = np.array([[800.0, 0, 320], [0, 810.0, 240], [0, 0, 1]])
    d = [-0.1, 0.01, 0.001, -0.002, 0.0]
    msg = cv.intrinsics_to_camera_info(k, d, 640, 480)
    k2, d2, model, size = cv.camera_info_to_intrinsics(msg)
    np.testing.assert_array_equal(k2, k)
    np.testing.assert_array_equal(d2, d)
    assert (model, size) == ("plumb_bob", (640, 480))
    msg.distortion_model = "equidistant"      # a fisheye calibration: its model goes along
    assert cv.camera_info_to_intrinsics(msg)[2] == "equidistant"
    msg.distortion_model = "kannala_brandt"
    with pytest.raises(cv.ConversionError, match="unsupported distortion model"):
        cv.camera_info_to_intrinsics(msg)
    msg.k = [0.0] * 9
    with pytest.raises(cv.ConversionError, match="not calibrated"):
        cv.camera_info_to_intrinsics(msg)


def test_covariance_and_stamp_round_trips():
    cov = RNG.standard_normal((6, 6))
    cov = cov @ cov.T
    np.testing.assert_array_equal(cv.covariance_to_array(cv.array_to_covariance(cov), 6), cov)
    with pytest.raises(cv.ConversionError):
        cv.covariance_to_array(np.zeros(35), 6)
    for ns in (0, 1, 1_700_000_000_123_456_789, -1_500_000_000):
        assert cv.stamp_to_ns(cv.ns_to_stamp(ns)) == ns
    assert cv.stamp_to_sec(cv.sec_to_stamp(12.25)) == 12.25


def test_dem_tile_and_geo_image_round_trips():
    georef = GeoReference(100.0, 2000.0, 2.5, 4, 3)
    heights = RNG.uniform(0, 3000, georef.shape).astype(np.float32)
    heights[1, 2] = np.nan
    msg = cv.dem_tile_to_msg(heights, georef, Header(frame_id="map"), (40.0, -105.0, 0.0),
                             "EGM96")
    back, georef2 = cv.msg_to_dem_tile(msg)
    np.testing.assert_array_equal(back, heights)
    assert georef2 == georef
    assert msg.void_fraction == pytest.approx(1 / 12)

    image = RNG.integers(0, 256, georef.shape, dtype=np.uint8)
    mask = np.ones(georef.shape, bool)
    mask[0, 0] = False
    image2, georef3, mask2 = cv.msg_to_geo_image(
        cv.geo_image_to_msg(image, georef, Header(frame_id="map"), mask))
    np.testing.assert_array_equal(image2, image)
    np.testing.assert_array_equal(mask2, mask)
    assert georef3 == georef


def test_minutiae_round_trip():
    georef = GeoReference(0.0, 0.0, 5.0, 100, 100)
    m = MinutiaSet([1.0, 50.5], [2.0, 70.25], [0.5, 6.0], [ENDING, BIFURCATION], [0.9, 0.4],
                   georef=georef)
    back = cv.msg_to_minutiae(cv.minutiae_to_msg(m, Header(), 0))
    for name in ("col", "row", "angle", "kind"):
        np.testing.assert_allclose(getattr(back, name), getattr(m, name), rtol=1e-6)
    empty = cv.msg_to_minutiae(cv.minutiae_to_msg(MinutiaSet.empty("flat", georef), Header(), 1))
    assert len(empty) == 0 and empty.reason == "flat"


def test_crease_skeleton_rides_with_the_minutiae():
    georef = GeoReference(0.0, 0.0, 5.0, 40, 30)   # 40 columns, 30 rows
    m = MinutiaSet([1.0], [2.0], [0.5], [ENDING], [0.9], georef=georef)
    creases = np.zeros((30, 40), bool)
    creases[5, 3:30] = True
    creases[29, 39] = True
    msg = cv.minutiae_to_msg(m, Header(), 0, creases=creases)
    assert len(msg.crease_pixels) == creases.sum()
    np.testing.assert_array_equal(cv.msg_to_creases(msg), creases)
    assert cv.msg_to_creases(cv.minutiae_to_msg(m, Header(), 0)) is None   # none sent
    with pytest.raises(cv.ConversionError, match="shape"):
        cv.minutiae_to_msg(m, Header(), 0, creases=creases.T)
    msg.crease_pixels = [40 * 30]   # one past the grid
    with pytest.raises(cv.ConversionError, match="outside"):
        cv.msg_to_creases(msg)


def test_ridge_skeleton_rides_apart_from_the_creases():
    georef = GeoReference(0.0, 0.0, 5.0, 40, 30)
    m = MinutiaSet([1.0], [2.0], [0.5], [ENDING], [0.9], georef=georef)
    creases, ridges = np.zeros((30, 40), bool), np.zeros((30, 40), bool)
    creases[5, 3:30] = True
    ridges[3:25, 20] = True
    msg = cv.minutiae_to_msg(m, Header(), 0, creases=creases, ridges=ridges)
    np.testing.assert_array_equal(cv.msg_to_creases(msg), creases)
    np.testing.assert_array_equal(cv.msg_to_ridges(msg), ridges)
    assert cv.msg_to_ridges(cv.minutiae_to_msg(m, Header(), 0, creases=creases)) is None
    with pytest.raises(cv.ConversionError, match="ridge image"):
        cv.minutiae_to_msg(m, Header(), 0, ridges=ridges[:, :20])
    msg.ridge_pixels = [40 * 30]
    with pytest.raises(cv.ConversionError, match="ridge pixel"):
        cv.msg_to_ridges(msg)


def test_compressed_image_and_odometry():
    import cv2
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CompressedImage

    rgb = RNG.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", rgb)
    arr, enc = cv.compressed_image_to_array(CompressedImage(format="png", data=png.tobytes()))
    assert enc == "bgr8"
    np.testing.assert_array_equal(arr, rgb)
    with pytest.raises(cv.ConversionError, match="cannot decode"):
        cv.compressed_image_to_array(CompressedImage(format="jpeg", data=b"garbage"))
    odom = Odometry()
    odom.header.stamp = cv.ns_to_stamp(5_000_000_123)
    odom.pose = cv.pose_with_covariance([1, 2, 3], [0, 0, 0, 1], np.eye(6) * 2)
    stamp, p, q, cov = cv.odometry_to_arrays(odom)
    assert stamp == 5_000_000_123 and list(p) == [1, 2, 3] and q[3] == 1 and cov[5, 5] == 2


def test_imu_and_fluid_pressure_round_trips():
    from sensor_msgs.msg import FluidPressure

    header = cv.make_header(1_700_000_000_250_000_000, "base_link")
    msg = cv.sample_to_imu(header, [0.1, -0.2, 0.3], [1.0, 2.0, 9.8])
    stamp, gyro, accel = cv.imu_to_sample(msg)
    assert stamp == pytest.approx(1_700_000_000.25, abs=1e-6)
    assert gyro == (0.1, -0.2, 0.3) and accel == (1.0, 2.0, 9.8)
    assert msg.orientation_covariance[0] == -1.0
    baro = FluidPressure(header=header, fluid_pressure=95_000.5, variance=4.0)
    assert cv.fluid_pressure_to_sample(baro)[1:] == (95_000.5, 4.0)


@pytest.mark.parametrize("with_velocity", [False, True])
def test_pva_fix_round_trip(with_velocity):
    from terrain_nav_msgs.msg import PvaFix

    cov = np.diag([4.0, 9.0, 16.0, -1.0, -1.0, -1.0])
    vel, vcov = ([30.0, -1.0, 0.5], np.eye(3) * 0.25) if with_velocity else (None, None)
    msg = cv.arrays_to_pva_fix(cv.make_header(5_000_000_000, "map"), PvaFix.STATUS_POSITION,
                               [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], cov, vel, vcov,
                               relocalisation=with_velocity, projection_height=2500.0,
                               mosaic_lag=12.5)
    fix = cv.pva_fix_to_arrays(msg)
    assert fix.stamp == 5.0 and fix.status == PvaFix.STATUS_POSITION
    assert fix.projection_height == 2500.0 and fix.mosaic_lag == 12.5
    assert msg.relocalisation is with_velocity and fix.relocalisation is with_velocity
    np.testing.assert_array_equal(fix.position, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(fix.quaternion, [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(fix.covariance, cov)
    if with_velocity:
        np.testing.assert_array_equal(fix.velocity, vel)
        np.testing.assert_array_equal(fix.velocity_covariance, vcov)
    else:
        assert fix.velocity is None and fix.velocity_covariance is None


def test_navsatfix_odometry_tf_round_trips():
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    header = cv.make_header(7_500_000_000, "map")
    cov3 = np.array([[4.0, 1.0, 0.0], [1.0, 9.0, 0.5], [0.0, 0.5, 16.0]])
    msg = cv.arrays_to_navsatfix(header, 36.5, -84.25, 812.5, cov3)
    stamp, status, lla, cov, kind = cv.navsatfix_to_arrays(msg)
    assert (stamp, status, kind) == (7.5, NavSatStatus.STATUS_FIX,
                                     NavSatFix.COVARIANCE_TYPE_KNOWN)
    np.testing.assert_array_equal(lla, [36.5, -84.25, 812.5])
    np.testing.assert_array_equal(cov, cov3)

    pose_cov = np.diag(np.arange(1.0, 7.0))
    twist_cov = np.diag(np.arange(7.0, 13.0))
    q = [0.0, 0.0, 0.38268343236508984, 0.9238795325112867]
    odom = cv.odometry_msg(header, "base_link", [1.0, 2.0, 3.0], q, pose_cov,
                           [30.0, 0.1, -0.2], [0.01, 0.02, 0.03], twist_cov)
    t, p, q2, pc, lin, ang, tc = cv.odometry_to_state(odom)
    assert t == 7.5 and odom.child_frame_id == "base_link" and odom.header.frame_id == "map"
    for got, want in ((p, [1, 2, 3]), (q2, q), (pc, pose_cov), (lin, [30.0, 0.1, -0.2]),
                      (ang, [0.01, 0.02, 0.03]), (tc, twist_cov)):
        np.testing.assert_array_equal(got, want)

    tf = cv.tf_message(header, "base_link", [1.0, 2.0, 3.0], q).transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
    tr, r = tf.transform.translation, tf.transform.rotation
    assert (tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w) == (1.0, 2.0, 3.0, *q)


def test_diagnostic_status_round_trip():
    status = cv.diagnostic_status("ekf: filter", 1, "no fix", {"nis": 3.14159265, "n": 7,
                                                               "ok": True, "text": "a b"})
    level, values = cv.diagnostic_values(status)
    assert level == 1 and status.name == "ekf: filter" and status.message == "no fix"
    assert values == {"nis": "3.14159", "n": "7", "ok": "True", "text": "a b"}


def test_projection_fields_round_trip():
    from scipy.spatial.transform import Rotation

    from terrain_nav_msgs.msg import GeoImage, MinutiaArray

    r = Rotation.from_euler("xyz", [170, 5, 30], degrees=True).as_matrix()
    msg = GeoImage()
    assert cv.get_projection(msg) is None
    cv.set_projection(msg, [1.0, 2.0, 3000.0], r, 450.0, mosaic_lag=7.25)
    out = MinutiaArray()
    cv.copy_projection(msg, out)
    position, rotation, plane = cv.get_projection(out)
    np.testing.assert_allclose(position, [1, 2, 3000])
    np.testing.assert_allclose(rotation, r, atol=1e-12)
    assert plane == 450.0 and out.mosaic_lag == 7.25


def test_geo_image_sun_round_trip_and_unknown():
    georef = GeoReference(0.0, 0.0, 5.0, 8, 6)
    image = np.zeros(georef.shape, np.uint8)
    msg = cv.geo_image_to_msg(image, georef, Header(), sun=(135.5, 30.25))
    assert cv.geo_image_sun(msg) == (135.5, 30.25)
    assert cv.geo_image_sun(cv.geo_image_to_msg(image, georef, Header())) is None
    msg.sun_elevation = float("nan")
    assert cv.geo_image_sun(msg) is None
    msg.sun_elevation = -3.0                     # below the horizon: no usable shading
    assert cv.geo_image_sun(msg) is None


def test_sensor_gps_without_a_velocity_says_so_and_stationary_course_is_unknown():
    from px4_msgs.msg import SensorGps

    cov = np.diag([16.0, 9.0, 25.0])
    msg = cv.fill_sensor_gps(SensorGps(), 2_000_000_999, 36.5, -84.3, 400.0,
                             -31.0, cov, None, None, SensorGps.FIX_TYPE_3D)
    # dated by the estimate, not by its sending: PX4 takes timestamp as the sample's time
    assert (msg.timestamp_sample, msg.timestamp) == (2_000_000, 2_000_000)
    assert msg.altitude_msl_m == pytest.approx(431.0)
    assert (msg.eph, msg.epv) == pytest.approx((4.0, 5.0))
    assert not msg.vel_ned_valid and np.isnan(msg.vel_n_m_s) and np.isnan(msg.cog_rad)
    still = cv.fill_sensor_gps(SensorGps(), 0, 0.0, 0.0, 0.0, 0.0, cov, [0.0, 0.0, 0.0],
                               np.eye(3) * 0.04, SensorGps.FIX_TYPE_3D)
    assert still.vel_ned_valid and still.s_variance_m_s == pytest.approx(0.2)
    assert still.c_variance_rad == pytest.approx(np.pi)


def test_an_imu_orientation_is_taken_only_where_there_is_one():
    """REP 145's -1, a driver's untouched identity with an all-zero covariance and a
    quaternion that is no rotation carry none; an estimate with an unknown (zero)
    covariance gets a MEMS AHRS's 3 deg."""
    header = cv.make_header(cv.sec_to_stamp(1.0), "base_link")
    msg = cv.sample_to_imu(header, [0.0, 0.0, 0.0], [0.0, 0.0, 9.8])
    assert cv.imu_orientation(msg) is None                        # covariance[0] = -1
    msg.orientation_covariance = [0.0] * 9
    assert cv.imu_orientation(msg) is None                        # the untouched default
    msg.orientation.x, msg.orientation.w = 0.3, 0.3               # not of unit length
    assert cv.imu_orientation(msg) is None
    msg.orientation.x, msg.orientation.w = math.sin(0.1), math.cos(0.1)
    q, variance = cv.imu_orientation(msg)
    np.testing.assert_allclose(q, [math.sin(0.1), 0.0, 0.0, math.cos(0.1)])
    assert variance == pytest.approx(math.radians(3.0) ** 2)
    msg.orientation_covariance = [1e-4, 0, 0, 0, 2e-4, 0, 0, 0, 1e-3]
    assert cv.imu_orientation(msg)[1] == pytest.approx(2e-4)


def test_a_minutiae_message_beyond_what_a_node_can_hold_or_of_no_place_is_refused():
    """A NaN ENU origin would travel through renderer, extractor and matcher to fail each
    frame there; a set of 10^5 minutiae or a 40000 px square raster would take the matcher
    gigabytes. Each is a ConversionError where the message is read."""
    from terrain_nav_msgs.msg import MinutiaArray
    from terrain_nav_ros.core.features.minutia_set import MinutiaSet

    georef = GeoReference(0.0, 0.0, 10.0, 64, 64)
    n = cv.MAX_MINUTIAE + 1
    many = MinutiaSet(np.full(n, 5.0), np.full(n, 5.0), np.zeros(n), np.ones(n, np.uint8),
                      np.ones(n), georef=georef)
    header = cv.make_header(1, "map")
    with pytest.raises(cv.ConversionError, match=f"{n} minutiae: at most"):
        cv.msg_to_minutiae(cv.minutiae_to_msg(many, header, MinutiaArray.SOURCE_CAMERA))
    few = many.subset(np.arange(3))
    for origin in ((math.nan, 0.0, 0.0), (0.0, 0.0, math.inf), (95.0, 0.0, 0.0)):
        msg = cv.minutiae_to_msg(few, header, MinutiaArray.SOURCE_CAMERA, origin)
        with pytest.raises(cv.ConversionError, match="is no place on Earth"):
            cv.msg_to_minutiae(msg)
    huge = cv.minutiae_to_msg(few, header, MinutiaArray.SOURCE_CAMERA)
    huge.georef.width = huge.georef.height = 40000
    huge.crease_pixels = [5]
    with pytest.raises(cv.ConversionError, match="at most 67 M pixels"):
        cv.msg_to_creases(huge)


def test_static_rotations_leave_out_what_is_no_rotation():
    from tf2_msgs.msg import TFMessage

    def tf(parent, child, q):
        return cv.tf_message(cv.make_header(0, parent), child, (0, 0, 0), q).transforms[0]

    rotations, refused = cv.static_rotations(TFMessage(transforms=[
        tf("base_link", "camera_link", (0, 0, 0, 2.0)),        # not unit: normalised
        tf("base_link", "lidar", (0, 0, 0, 0)),
        tf("base_link", "imu", (float("nan"), 0, 0, 1)),
        tf("", "gps", (0, 0, 0, 1))]))
    assert list(rotations) == ["camera_link"]
    parent, rotation = rotations["camera_link"]
    assert parent == "base_link"
    np.testing.assert_allclose(rotation, np.eye(3))
    assert len(refused) == 3 and "base_link -> lidar: quaternion" in refused[0]


def test_vehicle_odometry_variances_unknown_or_beyond_float32_are_nan():
    """PX4 reads NaN as unknown (and uses its EKF2_EV*_NOISE); REP 103's -1 and a variance
    float32 cannot hold would reach it as a negative or an infinite one."""
    from px4_msgs.msg import VehicleOdometry

    pose_cov = np.diag([4.0, 9.0, 16.0, -1.0, -1.0, -1.0])
    twist_cov = np.diag([1e40, 0.25, 0.0, 0.01, 0.01, 0.01])
    msg = cv.fill_vehicle_odometry(VehicleOdometry(), 10**9, 10**9, [1, 2, 3], [0, 0, 0, 1],
                                   pose_cov, [30, 0, 0], [0, 0, 0], twist_cov, 0, 100)
    np.testing.assert_allclose(msg.position_variance, [9.0, 4.0, 16.0])   # N, E, D
    assert np.isnan(msg.orientation_variance).all()
    # body (FLU, heading east) 1e40, 0.25, 0 -> N 0.25, E 1e40, D 0
    assert msg.velocity_variance[0] == pytest.approx(0.25)
    assert np.isnan(msg.velocity_variance[1:]).all()
