"""camera_ingest node: frames of known geometry land where the geometry says; a frame that
arrives before the calibration, or cannot be decoded, comes out without an image and with the
reason, and does not kill the node."""

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from ros_helpers import SpinningNode, start_node, stop, wait_until
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from terrain_nav_msgs.msg import DemTile, GeoImage
from terrain_nav_ros.core.render.sun import sun_at
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS

F, W, H = 500.0, 400, 300
CAMERA = np.array([1000.0, 2000.0, 1100.0])  # 1000 m above a flat terrain at 100 m


def _frame(stamp_ns):
    image = np.full((H, W), 40, np.uint8)
    image[0, :8] = np.frombuffer(int(stamp_ns).to_bytes(8, "little"), np.uint8)  # frames differ
    image[148:153, 198:203] = 250          # principal point (199.5, 149.5): straight down
    image[148:153, 298:303] = 250          # 100 px right of it: right wing = south (heading E)
    return cv.array_to_image(image, "mono8", cv.make_header(stamp_ns, "camera_optical"))


ORIGIN = (46.5, 7.5, 0.0)


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
    assert got[-2].reason.startswith("frame not projected: camera frozen") and \
        got[-2].image.width == 0
    assert got[-1].reason.startswith("frame not projected: frame repeated or out of order")
    with pytest.raises(cv.ConversionError, match="no CameraInfo"):
        cv.msg_to_geo_image(got[0])
    # ... and the diagnostics count them by reason
    _, values = cv.diagnostic_values(diagnostics[-1].status[0])
    assert 1 <= int(values["projected"]) <= sum(not m.reason for m in got)
    assert 2 <= int(values["not_projected"]) <= sum(bool(m.reason) for m in got)
    assert int(values["not projected: no CameraInfo received yet"]) >= 1
    assert int(values["not projected: unsupported image encoding 'yuv9000'"]) == 1
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
