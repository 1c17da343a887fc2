"""camera_ingest node: frames of known geometry land where the geometry says; a frame that
arrives before the calibration, or cannot be decoded, comes out without an image and with the
reason, and does not kill the node."""

import time

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from ros_helpers import SpinningNode, start_node, stop, wait_until
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from terrain_nav_msgs.msg import DemTile, GeoImage
from terrain_nav_ros.core.render.sun import sun_at
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS

F, W, H = 500.0, 400, 300
CAMERA = np.array([1000.0, 2000.0, 1100.0])  # 1000 m above a flat terrain at 100 m


def _frame(stamp_ns, tail_mark=False):
    image = np.full((H, W), 40, np.uint8)
    image[0, :8] = np.frombuffer(int(stamp_ns).to_bytes(8, "little"), np.uint8)  # frames differ
    image[148:153, 198:203] = 250          # principal point (199.5, 149.5): straight down
    image[148:153, 298:303] = 250          # 100 px right of it: right wing = south (heading E)
    if tail_mark:                          # 145.5 px below it: 291 m behind from 1000 m up
        image[293:298, 198:203] = 250
    return cv.array_to_image(image, "mono8", cv.make_header(stamp_ns, "camera_optical"))


ORIGIN = (46.5, 7.5, 0.0)


def _inputs(node, heights=None):
    """Publishers of camera_ingest's inputs, once it listens, with the flat terrain's tile
    (or ``heights`` on its grid) published (latched); and the camera's CameraInfo."""
    pubs = {t: node.create_publisher(m, t, q) for t, m, q in (
        ("/camera/image_raw", Image, 10), ("/camera/camera_info", CameraInfo, 10),
        ("/nav/odometry", Odometry, 10), ("/metamap/tile", DemTile, LATCHED_QOS))}
    assert wait_until(lambda: all(p.get_subscription_count() for p in pubs.values()), 20)
    tile = GeoReference.centred(1000.0, 2000.0, 20.0, 200, 200)
    pubs["/metamap/tile"].publish(cv.dem_tile_to_msg(
        np.full(tile.shape, 100.0, np.float32) if heights is None else heights, tile,
        Header(frame_id="map"), enu_origin=ORIGIN))
    info = cv.intrinsics_to_camera_info(np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2],
                                                  [0, 0, 1]]), [0] * 5, W, H)
    return pubs, info


def _odometry(at_ns):
    """The camera's pose, heading east, at ``at_ns``."""
    odom = Odometry(header=cv.make_header(at_ns, "map"))
    odom.pose = cv.pose_with_covariance(CAMERA, [0, 0, 0, 1], np.eye(6))
    return odom


def test_frames_are_projected_to_the_right_place_and_bad_frames_explained():
    from diagnostic_msgs.msg import DiagnosticArray

    node = start_node("camera_ingest", {"gsd": 5.0, "diagnostics_period": 0.3})
    client = SpinningNode("ingest_client")
    got, diagnostics = [], []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        n.create_subscription(DiagnosticArray, "/camera_ingest/diagnostics",
                              diagnostics.append, 10)
        pubs = {t: n.create_publisher(m, t, q) for t, m, q in (
            ("/camera/image_raw", Image, 10), ("/camera/camera_info", CameraInfo, 10),
            ("/nav/odometry", Odometry, 10), ("/metamap/tile", DemTile, LATCHED_QOS))}
        assert wait_until(lambda: all(p.get_subscription_count() for p in pubs.values()), 20)
        stamp = 1_750_000_000 * 10**9          # 2025-06-15 15:06 UTC: daylight in the Alps
        sent = [stamp - 10**8]                 # frames go out 1 ms apart (stamps must move on)

        def next_frame():
            sent.append(sent[-1] + 10**6)
            return _frame(sent[-1])

        # no calibration yet: the frame comes out without an image (sent until one does:
        # the camera topic is best effort)
        assert wait_until(lambda: (pubs["/camera/image_raw"].publish(next_frame()),
                                   bool(got))[1], 20, period=0.3), stop(node)
        info = cv.intrinsics_to_camera_info(np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2],
                                                      [0, 0, 1]]), [0] * 5, W, H)
        pubs["/camera/camera_info"].publish(info)
        tile = GeoReference.centred(1000.0, 2000.0, 20.0, 200, 200)
        pubs["/metamap/tile"].publish(cv.dem_tile_to_msg(
            np.full(tile.shape, 100.0, np.float32), tile, Header(frame_id="map"),
            enu_origin=ORIGIN))
        odom = Odometry(header=cv.make_header(stamp, "map"))
        odom.pose = cv.pose_with_covariance(CAMERA, [0, 0, 0, 1], np.eye(6))  # heading east

        def publish_and_check():
            frame = next_frame()
            odom.header.stamp = frame.header.stamp
            pubs["/camera/camera_info"].publish(info)
            pubs["/nav/odometry"].publish(odom)
            pubs["/camera/image_raw"].publish(frame)
            return any(not m.reason for m in got)

        assert wait_until(publish_and_check, 30, period=0.3), stop(node)
        garbled = _frame(stamp + 1)
        garbled.encoding = "yuv9000"
        pubs["/camera/image_raw"].publish(garbled)
        assert wait_until(lambda: got[-1].header.stamp.nanosec == 1, 10), stop(node)
        # a frozen camera: the last image again under a new stamp; and a stamp repeated
        last = _frame(sent[-1])
        frozen = _frame(sent[-1])
        frozen.header = cv.make_header(sent[-1] + 10**6, "camera_optical")
        for msg in (frozen, last):
            pubs["/camera/image_raw"].publish(msg)
            assert wait_until(lambda m=msg: got[-1].header.stamp == m.header.stamp, 10), \
                stop(node)
        guarded = list(got)
        # a camera clock 3 s behind the navigation estimate (max_frame_age 1 s): refused
        late = Odometry(header=cv.make_header(sent[-1] + 3 * 10**9, "map"), pose=odom.pose)

        def publish_late_and_check():
            pubs["/nav/odometry"].publish(late)
            pubs["/camera/image_raw"].publish(next_frame())
            return any("older than the newest estimate" in m.reason for m in got)

        assert wait_until(publish_late_and_check, 10, period=0.3), stop(node)
        n_reports = len(diagnostics)
        assert wait_until(lambda: len(diagnostics) > n_reports, 10), stop(node)
        assert node.poll() is None
    finally:
        client.close()
        log = stop(node)
    # every frame comes out: those that could not be projected without an image, saying why
    garbled_out = next(m for m in got if m.header.stamp.nanosec == 1)
    assert "no CameraInfo" in got[0].reason and got[0].image.width == 0
    assert "yuv9000" in garbled_out.reason and garbled_out.image.width == 0
    assert guarded[-2].reason.startswith("frame not projected: camera frozen") and \
        guarded[-2].image.width == 0
    assert guarded[-1].reason.startswith("frame not projected: frame repeated or out of order")
    late_out = next(m for m in got if "older than the newest estimate" in m.reason)
    assert "3.00 s older" in late_out.reason and late_out.image.width == 0
    with pytest.raises(cv.ConversionError, match="no CameraInfo"):
        cv.msg_to_geo_image(got[0])
    # ... and the diagnostics count them by reason
    _, values = cv.diagnostic_values(diagnostics[-1].status[0])
    assert 1 <= int(values["projected"]) <= sum(not m.reason for m in got)
    assert int(values["frames_received"]) == int(values["projected"]) + \
        int(values["not_projected"])   # every frame received is projected or says why not
    assert 2 <= int(values["not_projected"]) <= sum(bool(m.reason) for m in got)
    assert int(values["not projected: no CameraInfo received yet"]) >= 1
    assert int(values["not projected: unsupported image encoding 'yuv#'"]) == 1
    # counted by kind, without the numbers (one key per lag grew without bound)
    assert int(values["not projected: frame is # s older than the newest estimate"]) >= 1
    projected = next(m for m in got if not m.reason)
    image, georef, valid = cv.msg_to_geo_image(projected)
    assert georef.gsd == 5.0
    lab = image > 150
    from scipy import ndimage

    labels, count = ndimage.label(lab)
    assert count == 2, log
    centres = ndimage.center_of_mass(lab, labels, [1, 2])
    ground = sorted(zip(*georef.pixel_to_enu([c for _, c in centres], [r for r, _ in centres]),
                        strict=True), key=lambda p: -p[1])
    # Straight down and 100 px * 1000 m / 500 px = 200 m south; within half a pixel.
    np.testing.assert_allclose(ground[0], (1000.0, 2000.0), atol=2.5)
    np.testing.assert_allclose(ground[1], (1000.0, 1800.0), atol=2.5)
    assert valid.mean() > 0.9
    # the sun over the tile's origin at the frame's time, for the extractor's lighting option
    at = cv.stamp_to_sec(projected.header.stamp)
    assert abs(at - 1.75e9) < 1.0
    assert cv.geo_image_sun(projected) == pytest.approx(sun_at(at, *ORIGIN[:2]))


def _mission_without_tiles(path, terrain):
    """A mission index manifest (no tiles: camera_ingest reads only its terrain heights)."""
    from terrain_nav_ros.core.matching import mission_index as mi
    from terrain_nav_ros.core.terrain.geodesy import EnuOrigin

    grid = mi.TileGrid.covering((-5000.0, 5000.0, -5000.0, 5000.0), 30.0, 256, 64)
    manifest = mi.make_manifest(area={"from": "--area"}, origin=EnuOrigin(*ORIGIN), grid=grid,
                                suns=[(120.0, 40.0)], dems=[], settings=mi.IndexSettings(),
                                terrain=mi.TerrainHeights(*terrain))
    path.mkdir()
    mi.write_manifest(path, manifest)
    return path


def test_a_cold_start_projects_frames_pose_free_until_there_is_odometry(tmp_path):
    """cold_start: no odometry yet, so each frame is projected at the ENU origin, heading 0,
    wings level, its height the barometer's above the mission area's median terrain, and
    marked pose-free with the area's range of terrain planes; without a barometer sample it
    says so; once odometry comes, frames are projected with it, and pose-free again only
    when it has stopped for a while."""
    from sensor_msgs.msg import FluidPressure

    from terrain_nav_ros.core.estimation.baro import altitude_to_pressure

    mission = _mission_without_tiles(tmp_path / "index", (50.0, 100.0, 300.0))
    node = start_node("camera_ingest", {"gsd": 5.0, "cold_start": True,
                                        "mission_dir": str(mission),
                                        "baro_altitude_sigma": 0.0})
    client = SpinningNode("ingest_cold_client")
    got = []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        pubs = {t: n.create_publisher(m, t, q) for t, m, q in (
            ("/camera/image_raw", Image, 10), ("/camera/camera_info", CameraInfo, 10),
            ("/nav/odometry", Odometry, 10), ("/metamap/tile", DemTile, LATCHED_QOS),
            ("/baro/pressure", FluidPressure, 10))}
        assert wait_until(lambda: all(p.get_subscription_count() for p in pubs.values()), 20)
        stamp = 1_750_000_000 * 10**9
        info = cv.intrinsics_to_camera_info(np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2],
                                                      [0, 0, 1]]), [0] * 5, W, H)
        tile = GeoReference.centred(0.0, 0.0, 20.0, 200, 200)
        pubs["/metamap/tile"].publish(cv.dem_tile_to_msg(
            np.full(tile.shape, 100.0, np.float32), tile, Header(frame_id="map"),
            enu_origin=ORIGIN))

        sent = [stamp]                         # frames go out 1 ms apart (stamps move on)

        def frame_answered(check, extra=()):
            """Send frames (and ``extra`` messages at their stamps) until one answer
            passes ``check``."""
            def publish():
                sent.append(sent[-1] + 10**6)
                frame = _frame(sent[-1])
                pubs["/camera/camera_info"].publish(info)
                for topic, msg in extra:
                    msg.header.stamp = frame.header.stamp
                    pubs[topic].publish(msg)
                pubs["/camera/image_raw"].publish(frame)
                return any(check(m) for m in got)
            return publish

        assert wait_until(frame_answered(lambda m: "no barometer" in m.reason), 30,
                          period=0.3), stop(node)
        baro = FluidPressure(header=Header(frame_id="base_link"),
                             fluid_pressure=float(altitude_to_pressure(1100.0)))
        assert wait_until(frame_answered(lambda m: m.pose_free, [("/baro/pressure", baro)]),
                          30, period=0.3), stop(node)
        odom = Odometry(header=Header(frame_id="map"))
        odom.pose = cv.pose_with_covariance(CAMERA, [0, 0, 0, 1], np.eye(6))
        assert wait_until(frame_answered(lambda m: m.projected and not m.pose_free,
                                         [("/nav/odometry", odom)]), 30, period=0.3), stop(node)
        # frames 1 s after the last odometry: a short gap, a no-fix as without cold start;
        # 3 s after (the filter was reset): pose-free again
        sent.append(sent[-1] + 10**9)
        assert wait_until(frame_answered(lambda m: "older than the frame" in m.reason), 30,
                          period=0.3), stop(node)
        sent.append(sent[-1] + 2 * 10**9)
        restarted = sent[-1]
        assert wait_until(frame_answered(
            lambda m: m.pose_free and cv.stamp_to_sec(m.header.stamp) > restarted * 1e-9,
            [("/baro/pressure", baro)]), 30, period=0.3), stop(node)
        assert node.poll() is None
    finally:
        client.close()
        log = stop(node)
    cold = next(m for m in got if m.pose_free)
    position, rotation, plane = cv.get_projection(cold)
    np.testing.assert_allclose(position, [0.0, 0.0, 1100.0], atol=0.5)
    assert plane == pytest.approx(100.0)
    assert cv.get_pose_free(cold) == pytest.approx((50.0, 300.0, np.radians(3.0)))
    image, georef, _ = cv.msg_to_geo_image(cold)
    from scipy import ndimage

    labels, count = ndimage.label(image > 150)
    assert count == 2, log
    centres = ndimage.center_of_mass(image > 150, labels, [1, 2])
    ground = sorted(zip(*georef.pixel_to_enu([c for _, c in centres], [r for r, _ in centres]),
                        strict=True), key=lambda p: -p[1])
    # under the camera at the origin; 100 px right (the right wing, heading 0 = east) is
    # 100 px x 1000 m / 500 px = 200 m south
    np.testing.assert_allclose(ground[0], (0.0, 0.0), atol=2.5)
    np.testing.assert_allclose(ground[1], (0.0, -200.0), atol=2.5)
    warm = next(m for m in got if m.projected and not m.pose_free)
    np.testing.assert_allclose(cv.get_projection(warm)[0], CAMERA)


def test_a_cold_start_without_a_mission_index_says_so_for_every_frame():
    node = start_node("camera_ingest", {"gsd": 5.0, "cold_start": True})
    client = SpinningNode("ingest_cold_client2")
    got = []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        image_pub = n.create_publisher(Image, "/camera/image_raw", 10)
        info_pub = n.create_publisher(CameraInfo, "/camera/camera_info", 10)
        assert wait_until(lambda: image_pub.get_subscription_count()
                          and info_pub.get_subscription_count(), 20)
        info = cv.intrinsics_to_camera_info(np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2],
                                                      [0, 0, 1]]), [0] * 5, W, H)

        sent = [10**9]

        def publish():
            sent.append(sent[-1] + 10**6)
            info_pub.publish(info)
            image_pub.publish(_frame(sent[-1]))
            return any("no mission index" in m.reason for m in got)

        assert wait_until(publish, 30, period=0.3), stop(node)
        assert node.poll() is None
    finally:
        client.close()
        stop(node)


def test_the_camera_mount_comes_from_tf_static_through_the_frames_between():
    """A robot description's mount (``base_link -> camera_link -> camera_optical`` on
    /tf_static, the camera rolled 15 deg) beats ``mount_rpy``: the image
    centre lands where that tilt puts it, and the diagnostics say where the mount came from."""
    import math

    from diagnostic_msgs.msg import DiagnosticArray
    from tf2_msgs.msg import TFMessage

    from terrain_nav_ros.core.camera.camera_mount import R_BODY_OPTICAL_NADIR, mount_rotation
    from terrain_nav_ros.nodes.ros_common import TF_STATIC_QOS

    roll = math.radians(15.0)
    tilt = Rotation.from_matrix(mount_rotation(roll, 0, 0) @ R_BODY_OPTICAL_NADIR.T).as_quat()
    optical = Rotation.from_matrix(R_BODY_OPTICAL_NADIR).as_quat()
    static = TFMessage(transforms=[
        *cv.tf_message(cv.make_header(0, "base_link"), "camera_link", (0, 0, 0), tilt).transforms,
        *cv.tf_message(cv.make_header(0, "camera_link"), "camera_optical", (0, 0, 0),
                       optical).transforms])
    node = start_node("camera_ingest", {"gsd": 5.0, "diagnostics_period": 0.3,
                                        "mount_rpy": [0.0, 3.0, 0.0]})
    client = SpinningNode("ingest_tf_client")
    got, diagnostics = [], []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground",
                              lambda m: got.append(m) if not m.reason else None, 10)
        n.create_subscription(DiagnosticArray, "/camera_ingest/diagnostics",
                              diagnostics.append, 10)
        n.create_publisher(TFMessage, "/tf_static", TF_STATIC_QOS).publish(static)
        pubs, info = _inputs(n)
        stamp = [1_750_000_000 * 10**9]

        def publish_and_check():
            stamp[0] += 10**6
            frame = _frame(stamp[0])
            pubs["/camera/camera_info"].publish(info)
            pubs["/nav/odometry"].publish(_odometry(stamp[0]))
            pubs["/camera/image_raw"].publish(frame)
            return bool(got) and bool(diagnostics)

        assert wait_until(publish_and_check, 30, period=0.3), stop(node)
        assert wait_until(lambda: "camera_optical" in str(diagnostics[-1]), 10), \
            (stop(node), str(diagnostics[-1]))
    finally:
        client.close()
        log = stop(node)
    image, georef, _ = cv.msg_to_geo_image(got[-1])
    from scipy import ndimage

    labels, count = ndimage.label(image > 150)
    assert count == 2, log
    centres = ndimage.center_of_mass(image > 150, labels, [1, 2])
    ground = sorted(zip(*georef.pixel_to_enu([c for _, c in centres], [r for r, _ in centres]),
                        strict=True), key=lambda p: -p[1])
    # Heading east, the mount rolled 15 deg (right wing down, FLU): the optical axis leans
    # to the left wing, north, by 1000 m x tan(15 deg) = 268 m (mount_rpy's 3 deg pitch
    # would have put it 52 m east).
    np.testing.assert_allclose(ground[0], (1000.0, 2000.0 + 1000.0 * math.tan(roll)),
                               atol=3.0)
    _, values = cv.diagnostic_values(diagnostics[-1].status[0])
    assert values["mount"] == ("/tf_static base_link -> camera_optical: roll 15.0, "
                               "pitch 0.0, yaw 0.0 deg")
    assert "differs by 15.3 deg from /tf_static's base_link -> camera_optical" in log


def test_a_frame_ahead_of_the_estimate_waits_for_it():
    """A filter short of CPU publishes its estimate after the camera's frame: the frame
    waits (max_estimate_wait) and is projected with the estimate that comes, not refused
    as "newest estimate is ... older than the frame"; one the estimate never reaches is
    answered when its wait runs out, saying so."""
    node = start_node("camera_ingest", {"gsd": 5.0, "max_estimate_wait": 3.0})
    client = SpinningNode("ingest_wait_client")
    got = []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        pubs, info = _inputs(n)
        stamp = 1_750_000_000 * 10**9
        # the calibration and a first estimate, 2 s before the frames
        sent = [stamp - 2 * 10**9]

        def first_frames():
            sent.append(sent[-1] + 10**6)
            pubs["/camera/camera_info"].publish(info)
            pubs["/nav/odometry"].publish(_odometry(sent[-1]))
            pubs["/camera/image_raw"].publish(_frame(sent[-1]))
            return any(not m.reason for m in got)

        assert wait_until(first_frames, 20, period=0.3), stop(node)
        time.sleep(0.5)
        count = len(got)
        pubs["/camera/image_raw"].publish(_frame(stamp))
        time.sleep(1.0)
        assert len(got) == count, "the frame did not wait for its estimate"
        pubs["/nav/odometry"].publish(_odometry(stamp + 5 * 10**7))
        assert wait_until(lambda: len(got) > count, 5), stop(node)
        waited = got[count]
        # a frame no estimate reaches: answered once its wait runs out
        pubs["/camera/image_raw"].publish(_frame(stamp + 10**9))
        assert wait_until(lambda: len(got) > count + 1, 10), stop(node)
        abandoned = got[count + 1]
    finally:
        client.close()
        stop(node)
    assert cv.stamp_to_ns(waited.header.stamp) == stamp and not waited.reason
    assert "older than the frame (after waiting 3 s for it)" in abandoned.reason


def test_a_frame_taken_past_the_dem_s_edge_shows_the_ground_the_dem_holds():
    """The aircraft 100 m past the DEM's eastern edge (its tile nodata there): the frame is
    projected on the ground west of the edge that the DEM holds, observed there only, not
    refused for want of heights under the aircraft."""
    heights = np.full((200, 200), 100.0, np.float32)    # the tile of _inputs: E -1000..3000
    heights[:, 95:] = np.nan                            # nodata east of E = 900
    node = start_node("camera_ingest", {"gsd": 5.0})
    client = SpinningNode("ingest_edge_client")
    got = []
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        pubs, info = _inputs(n, heights)
        sent = [1_750_000_000 * 10**9]

        def publish_and_check():
            sent.append(sent[-1] + 10**6)
            pubs["/camera/camera_info"].publish(info)
            pubs["/nav/odometry"].publish(_odometry(sent[-1]))
            pubs["/camera/image_raw"].publish(_frame(sent[-1]))
            return any(m.image.width for m in got)

        assert wait_until(publish_and_check, 20, period=0.3), stop(node)
    finally:
        client.close()
        stop(node)
    image, georef, valid = cv.msg_to_geo_image(next(m for m in got if m.image.width))
    east = georef.pixel_to_enu(np.arange(georef.width, dtype=float), 0.0)[0]
    # heading east, the view spans E 700..1300 (150 px x 1000 m / 500 px each side of nadir)
    assert east.min() < 710.0 and east.max() > 1290.0
    assert valid[:, east < 890.0].mean() > 0.9 and not valid[:, east > 910.0].any()


def test_frames_from_low_up_are_published_as_a_mosaic_of_the_track():
    """From 1000 m at 20 m a frame observes 30 x 40 px, fewer than mosaic_pixels: each is
    published composed with the frames before it, placed where the estimate put them, so the
    marks 291 m behind each frame's nadir (heading east at 60 m/s) lie in one ground image,
    60 m apart: behind the newest frame, which lies on top."""
    node = start_node("camera_ingest", {"gsd": 20.0, "mosaic_pixels": 3000,
                                        "mosaic_max_age": 30.0})
    client = SpinningNode("ingest_mosaic_client")
    got = []
    speed = 60.0
    try:
        n = client.node
        n.create_subscription(GeoImage, "/camera/image_ground", got.append, 10)
        pubs, info = _inputs(n)
        t0 = 1_750_000_000 * 10**9

        def odometry(at_ns):
            odom = _odometry(at_ns)
            odom.pose.pose.position.x = CAMERA[0] + speed * (at_ns - t0) * 1e-9
            odom.twist.twist.linear.x = speed     # body x = east (heading east)
            return odom

        for k in range(12):
            stamp = t0 + k * 10**9
            pubs["/camera/camera_info"].publish(info)
            for at in (stamp - 5 * 10**8, stamp):
                pubs["/nav/odometry"].publish(odometry(at))
            time.sleep(0.05)
            pubs["/camera/image_raw"].publish(_frame(stamp, tail_mark=True))
            # each frame's answer before the next: a first projection compiling its kernels
            # (a fresh set-up) once overflowed the camera's queue with the frames behind it
            wait_until(lambda k=k: len(got) > k, 20)
        assert wait_until(lambda: sum(bool(m.image.width) for m in got) >= 10, 20), stop(node)
    finally:
        client.close()
        stop(node)
    last = [m for m in got if m.image.width][-1]
    image, georef, valid = cv.msg_to_geo_image(last)
    assert georef.width > 30 + 3 * 5, georef          # a frame is 30 px along the track
    row = int(round(float(georef.enu_to_pixel(0.0, CAMERA[1])[1])))   # the nadir's track
    track = image[row - 1:row + 2].max(axis=0)
    cols = np.nonzero(track > 40)[0]     # the marks, blurred to 41-43 over the 40
    east = georef.pixel_to_enu(cols, 0.0)[0]
    newest = CAMERA[0] + speed * (last.header.stamp.sec - t0 * 1e-9)
    assert abs(east.max() - newest) < 30.0            # the newest frame's nadir
    tails = east[east < newest - 250.0]               # the frames' tail marks, 60 m apart
    assert tails.max() - tails.min() > 5 * speed, east
    # its pixels' mean age goes with it, for the ekf (frames 1 s apart: a few seconds)
    assert 1.0 < last.mosaic_lag < 6.0, last.mosaic_lag
    assert got[0].mosaic_lag == 0.0                   # the first frame went alone
