"""landmark_renderer node: a DemTile from another process becomes a georeferenced, correctly
lit landmark image; voids are masked; a malformed tile does not kill the node."""

from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
from ros_helpers import SpinningNode, call_service, start_node, stop, wait_until
from std_msgs.msg import Header

from terrain_nav_msgs.msg import DemTile, GeoImage
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS


def _peak_tile():
    georef = GeoReference.centred(1000.0, 2000.0, 10.0, 96, 80)
    east, north = georef.pixel_to_enu(np.arange(96)[None, :], np.arange(80)[:, None])
    heights = 500.0 + 300.0 * np.exp(-((east - 1000) ** 2 + (north - 2000) ** 2) / 150.0**2)
    heights = heights.astype(np.float32)
    heights[:, :10] = np.nan  # a void along the west edge
    return heights, georef


def _render_view(client, pose_z, size=(64, 48)):
    from terrain_nav_msgs.srv import RenderView

    w, h = size
    request = RenderView.Request(camera_info=cv.intrinsics_to_camera_info(
        np.array([[100.0 * w / 64, 0, (w - 1) / 2], [0, 100.0 * w / 64, (h - 1) / 2],
                  [0, 0, 1]]), [0] * 5, w, h))
    request.pose = cv.pose_with_covariance([1000.0, 2000.0, pose_z],
                                           [1.0, 0.0, 0.0, 0.0], np.eye(6)).pose  # nadir
    return call_service(client, RenderView, "/landmark_renderer/render_view", request)


@contextmanager
def renderer_node(params):
    """The node in its own process and a client with the tile publisher and the landmark
    subscription; the node's output is in ``log`` after the block."""
    node = start_node("landmark_renderer", params)
    client = SpinningNode("landmark_client")
    s = SimpleNamespace(node=node, client=client, got=[], log="")
    try:
        client.node.create_subscription(GeoImage, "/landmark/image", s.got.append,
                                        LATCHED_QOS)
        s.pub = client.node.create_publisher(DemTile, "/metamap/tile", LATCHED_QOS)
        assert wait_until(lambda: s.pub.get_subscription_count() > 0, 20), stop(node)
        yield s
    finally:
        client.close()
        s.log = stop(node)


def test_tile_becomes_a_lit_georeferenced_landmark():
    with renderer_node({"sun_azimuth": 315.0, "sun_elevation": 45.0}) as s:
        got = s.got
        bad = DemTile(header=Header(frame_id="map"))
        bad.georef.width, bad.georef.height, bad.georef.gsd = 4, 4, 1.0  # no elevations
        s.pub.publish(bad)
        heights, georef = _peak_tile()
        s.pub.publish(cv.dem_tile_to_msg(heights, georef, Header(frame_id="map")))
        assert wait_until(lambda: got, 60), stop(s.node)
        assert s.node.poll() is None, "node died on a malformed tile"
        view = _render_view(s.client, 3000.0)          # looking straight down at the peak
        underground = _render_view(s.client, 100.0)    # below the terrain: refused
        huge = _render_view(s.client, 3000.0, (20000, 20000))   # beyond the GL's buffers
        assert s.node.poll() is None, "node died on a view too large"
    log = s.log
    assert not huge.success and "at most 4096 px a side" in huge.message
    assert view.success, view.message
    heights = cv.image_to_array(view.terrain_height)
    assert heights.shape == (48, 64) and abs(float(heights[24, 32]) - 800.0) < 5.0  # summit
    assert not underground.success and underground.message
    image, out_georef, valid = cv.msg_to_geo_image(got[-1])
    assert out_georef == georef, log
    assert cv.geo_image_sun(got[-1]) == (315.0, 45.0)   # the sun it was lit with
    assert not valid[:, :9].any() and valid[:, 12:].all()
    # Sun from the north-west: the NW flank of the peak is lit, the SE flank in shade.
    row, col = np.round(georef.enu_to_pixel(1000.0, 2000.0)).astype(int)
    assert image[row - 10, col - 10] > image[row, col] > image[row + 10, col + 10]


def test_landmark_is_rendered_again_when_the_sun_has_moved():
    """Stamp policy: a tile stamped 40 minutes ago is lit by the sun of then, and rendered
    again with the sun of now (which has moved ~10 deg) at the next check."""
    import time

    from terrain_nav_ros.core.render.sun import sun_at, sun_separation

    now = time.time()
    # a place where it is about noon now, so that the sun is high then and now
    lon = ((12.0 - (now % 86400.0) / 3600.0) * 15.0 + 180.0) % 360.0 - 180.0
    lat = -20.0
    heights, georef = _peak_tile()
    then = now - 2400.0
    tile = cv.dem_tile_to_msg(heights, georef, cv.make_header(int(then * 1e9), "map"),
                              (lat, lon, 0.0))
    with renderer_node({"sun_policy": "stamp", "max_sun_change": 2.0,
                        "sun_check_period": 0.5}) as s:
        got = s.got
        s.pub.publish(tile)
        assert wait_until(lambda: len(got) >= 2, 60), stop(s.node)
    log = s.log
    first, second = cv.geo_image_sun(got[0]), cv.geo_image_sun(got[1])
    assert sun_separation(first, sun_at(then, lat, lon)) < 0.01, log
    assert sun_separation(first, second) > 2.0
    restamped = cv.stamp_to_sec(got[1].header.stamp)
    assert abs(restamped - now) < 60.0
    assert sun_separation(second, sun_at(restamped, lat, lon)) < 0.01
    assert len(got) == 2 or sun_separation(second, cv.geo_image_sun(got[2])) > 2.0
