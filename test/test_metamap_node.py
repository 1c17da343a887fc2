"""metamap node: a client in another process gets the right tile, an explicit error outside
the DEM, and a latched tile around the aircraft from odometry."""

import numpy as np
import pytest
from ros_helpers import SpinningNode, call_service, start_node, stop, wait_until

from terrain_nav_msgs.msg import DemTile
from terrain_nav_msgs.srv import GetDemTile
from terrain_nav_ros.core.terrain.dem_io import sample_dem
from terrain_nav_ros.core.terrain.metamap import MetaMap
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS


@pytest.fixture(scope="module")
def metamap_process():
    proc = start_node("metamap", {"gsd": 50.0, "interpolation": "bilinear",
                                  "camera_footprint_radius": 1000.0, "min_tile_size": 64})
    client = SpinningNode("metamap_client")
    yield client
    client.close()
    log = stop(proc)
    assert proc.returncode == 0, log


def _call(client, request, timeout=20.0):
    return call_service(client, GetDemTile, "/metamap/get_tile", request, timeout)


def test_service_returns_the_tile_the_core_computes(metamap_process):
    request = GetDemTile.Request(center_frame=GetDemTile.Request.CENTER_ENU, center_x=1000.0,
                                 center_y=-2000.0, width=40, height=30, gsd=50.0)
    response = _call(metamap_process, request)
    assert response.success, response.message
    heights, georef = cv.msg_to_dem_tile(response.tile)
    assert georef.shape == (30, 40) and georef.gsd == 50.0
    assert georef.centre == pytest.approx((1000.0, -2000.0))
    expected = MetaMap(sample_dem(), interpolation="bilinear", fill_voids=True,
                       heights="enu").tile(georef).elevation
    np.testing.assert_allclose(heights, expected, atol=1e-3)
    # Within the Jacksboro DEM range (236..1076 m; orthometric ~ ENU up near the origin).
    assert 230 < np.nanmin(heights) < np.nanmax(heights) < 1080


def test_geodetic_request_and_outside_request(metamap_process):
    response = _call(metamap_process, GetDemTile.Request(
        center_frame=GetDemTile.Request.CENTER_GEODETIC, center_x=36.6, center_y=-84.25,
        width=16, height=16, gsd=100.0))
    assert response.success, response.message
    far = _call(metamap_process, GetDemTile.Request(
        center_frame=GetDemTile.Request.CENTER_ENU, center_x=5e5, center_y=5e5, width=16,
        height=16, gsd=10.0))
    assert not far.success and "outside" in far.message


def test_a_request_beyond_the_service_s_limits_fails_and_the_node_serves_on(metamap_process):
    """A 40000 px side (OpenCV's remap cannot) or a gsd of 1e9 is success=false with the
    reason; the next request is served."""
    for width, height, gsd, words in ((1, 40000, 50.0, "at most 8192 px a side"),
                                      (16, 16, 1e9, "must be within 0.01-1000")):
        response = _call(metamap_process, GetDemTile.Request(
            center_frame=GetDemTile.Request.CENTER_ENU, width=width, height=height, gsd=gsd))
        assert not response.success and words in response.message, response.message
    assert _call(metamap_process, GetDemTile.Request(
        center_frame=GetDemTile.Request.CENTER_ENU, width=16, height=16, gsd=50.0)).success


def test_odometry_triggers_a_latched_tile_around_the_aircraft(metamap_process):
    from nav_msgs.msg import Odometry

    node = metamap_process.node
    tiles = []
    node.create_subscription(DemTile, "/metamap/tile", tiles.append, LATCHED_QOS)
    pub = node.create_publisher(Odometry, "/nav/odometry", 10)
    odom = Odometry()
    odom.header.frame_id = "utm"          # another frame's odometry is ignored
    odom.pose.pose.position.x, odom.pose.pose.position.y = 500.0, 800.0
    odom.twist.twist.linear.x = 30.0
    odom.pose.covariance = cv.array_to_covariance(np.diag([100.0, 100, 100, 1, 1, 1]))
    assert wait_until(lambda: pub.get_subscription_count() > 0, 20)
    # Before any odometry: the latched start-up tile, centred on the ENU origin.
    assert wait_until(lambda: bool(tiles), 10)
    assert cv.msg_to_georef(tiles[0].georef).centre == pytest.approx((0.0, 0.0), abs=1.0)

    def around_aircraft():
        return [t for t in tiles if cv.msg_to_georef(t.georef).centre[0] > 100.0]

    assert not wait_until(lambda: (pub.publish(odom), bool(around_aircraft()))[1], 2,
                          period=0.3)
    odom.header.frame_id = "map"
    assert wait_until(lambda: (pub.publish(odom), bool(around_aircraft()))[1], 20, period=0.3)
    heights, georef = cv.msg_to_dem_tile(around_aircraft()[0])
    west, east, south, north = georef.extent
    # Footprint 1000 m + 3 sigma (30 m) around now and 5 s ahead (150 m east).
    assert west <= 500 - 1030 and east >= 650 + 1030 and south <= 800 - 1030
    assert np.isfinite(heights).mean() > 0.99


def test_impossible_heights_in_a_dem_are_logged_as_a_warning(tmp_path):
    """A GeoTIFF with a few corrupt pixels (3e38): the node serves it, voids them, says so."""
    import rasterio
    from affine import Affine

    z = np.full((64, 64), 500.0, np.float32)
    z[10, 10:13] = 3e38
    path = tmp_path / "spots.tif"
    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1,
                       dtype="float32", crs="EPSG:32611",
                       transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(z, 1)
    # its own service name: the module's metamap node still serves /metamap/get_tile
    proc = start_node("metamap", {"dem_files": [str(path)], "gsd": 30.0,
                                  "initial_tile": False},
                      "-r", "/metamap/get_tile:=/metamap_warning/get_tile")
    client = SpinningNode("metamap_warning_client")
    try:
        response = call_service(client, GetDemTile, "/metamap_warning/get_tile",
                                GetDemTile.Request(center_frame=GetDemTile.Request.CENTER_ENU,
                                                   width=32, height=32, gsd=30.0))
        assert response.success, response.message
        heights, _ = cv.msg_to_dem_tile(response.tile)
        assert np.nanmax(heights) < 600  # no 3e38 spread by the interpolation
    finally:
        client.close()
        log = stop(proc)
    assert proc.returncode == 0, log
    warning = next(line for line in log.splitlines() if "impossible on Earth" in line)
    assert "WARN" in warning and "3 of 4096 heights" in warning and str(path) in warning
