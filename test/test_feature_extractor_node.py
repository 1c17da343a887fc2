"""feature_extractor node: minutiae of a drainage image in another process, an explicit empty
result for a flat image and for a clouded one, and parameter changes validated by the core."""

from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from ros_helpers import SpinningNode, call_service, start_node, stop, wait_until
from std_msgs.msg import Header
from synthetic_minutiae import fractal_surface

from terrain_nav_msgs.msg import GeoImage, MinutiaArray
from terrain_nav_ros.core.features.hillshade import hillshade
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS

DEM = fractal_surface((256, 256), beta=3.2, rng=3) * 150.0
GEOREF = GeoReference.centred(0.0, 0.0, 5.0, 256, 256)
HEADER = Header(frame_id="map")


def _drainage_image(azimuth=315.0, elevation=45.0):
    return (255 * hillshade(DEM, azimuth, elevation, gsd=5.0)).astype(np.uint8)


def _clouded(image):
    """``image`` under a thick cloud on all but a 10 % strip (the sensor clips it)."""
    out = image.copy()
    out[:, 26:] = 250
    return out


@contextmanager
def extractor_node(params=None):
    """The node in its own process, a client with both image publishers and both minutiae
    subscriptions; the node's output is in ``log`` after the block."""
    node = start_node("feature_extractor", params)
    client = SpinningNode("extractor_client")
    n = client.node
    s = SimpleNamespace(node=node, client=client, camera=[], landmark=[], log="")
    try:
        n.create_subscription(MinutiaArray, "/camera/minutiae", s.camera.append, 10)
        n.create_subscription(MinutiaArray, "/landmark/minutiae", s.landmark.append,
                              LATCHED_QOS)
        s.cam_pub = n.create_publisher(GeoImage, "/camera/image_ground", 10)
        s.land_pub = n.create_publisher(GeoImage, "/landmark/image", LATCHED_QOS)
        assert wait_until(lambda: s.cam_pub.get_subscription_count() > 0, 20), stop(node)
        yield s
    finally:
        client.close()
        s.log = stop(node)


def _set(client, name, value):
    if isinstance(value, bool):
        typed = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    elif isinstance(value, str):
        typed = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    else:
        typed = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    param = Parameter(name=name, value=typed)
    return call_service(client, SetParameters, "/feature_extractor/set_parameters",
                        SetParameters.Request(parameters=[param])).results[0]


def test_minutiae_empty_reasons_and_parameter_validation():
    with extractor_node() as s:
        s.land_pub.publish(cv.geo_image_to_msg(_drainage_image(), GEOREF, HEADER))
        assert wait_until(lambda: bool(s.landmark), 30)
        flat = cv.geo_image_to_msg(np.full((256, 256), 120, np.uint8), GEOREF, HEADER)
        assert wait_until(lambda: (s.cam_pub.publish(flat), bool(s.camera))[1], 30,
                          period=0.5)
        s.cam_pub.publish(cv.geo_image_to_msg(_clouded(_drainage_image()), GEOREF, HEADER))
        n_flat = len(s.camera)   # the flat frame may have gone out more than once
        assert wait_until(lambda: len(s.camera) > n_flat, 20)
        bad = _set(s.client, "crease.epsilon", 5.0)        # must be in (0, 1)
        good = _set(s.client, "crease.epsilon", 0.01)
        bad_cloud = _set(s.client, "cloud.max_fraction", 1.5)
        assert s.node.poll() is None
    found = cv.msg_to_minutiae(s.landmark[0])
    assert len(found) >= 10 and found.reason == "", s.log
    assert s.landmark[0].source == MinutiaArray.SOURCE_LANDMARK
    assert found.georef == GEOREF
    assert len(s.camera[0].minutiae) == 0 and "no drainage" in s.camera[0].reason
    assert not bad.successful and "epsilon" in bad.reason
    assert good.successful
    # a frame 90 % under a bright, featureless cloud: no minutiae, and the reason is the cloud
    assert len(s.camera[-1].minutiae) == 0 and s.camera[-1].reason.startswith("mostly cloud")
    assert not bad_cloud.successful and "max_fraction" in bad_cloud.reason
    # the crease skeleton rides along (attach_creases): every minutia ends or forks one
    creases = cv.msg_to_creases(s.landmark[0])
    assert creases is not None and creases.shape == (256, 256)
    rows, cols = np.nonzero(creases)
    assert _repeated(found, SimpleNamespace(col=cols, row=rows), px=1.5) == 1.0
    assert cv.msg_to_creases(s.camera[0]) is None   # flat: no creases
    assert cv.msg_to_ridges(s.landmark[0]) is not None   # attach_ridges by default


def test_creases_stay_home_when_not_asked_for_and_ridges_come_when_asked():
    """... and the switches changed at runtime apply to the next image."""
    image = cv.geo_image_to_msg(_drainage_image(), GEOREF, HEADER)
    with extractor_node({"attach_creases": False, "attach_ridges": True}) as s:
        s.land_pub.publish(image)
        assert wait_until(lambda: bool(s.landmark), 30)
        switched = [_set(s.client, "attach_creases", True),
                    _set(s.client, "attach_ridges", False)]
        bad_lighting = _set(s.client, "lighting", "moonlight")
        s.land_pub.publish(image)
        assert wait_until(lambda: len(s.landmark) > 1, 30)
    assert len(s.landmark[0].minutiae) >= 10 and len(s.landmark[0].crease_pixels) == 0
    ridges = cv.msg_to_ridges(s.landmark[0])
    assert ridges is not None and ridges.sum() > 50
    assert all(r.successful for r in switched)
    assert not bad_lighting.successful and "lighting" in bad_lighting.reason
    assert len(s.landmark[1].crease_pixels) > 0 and cv.msg_to_ridges(s.landmark[1]) is None


def _repeated(a, b, px=2.0):
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(np.column_stack([b.col, b.row])).query(
        np.column_stack([a.col, a.row]), distance_upper_bound=px)
    return np.isfinite(dist).mean()


def test_compensated_lighting_agrees_across_opposite_suns():
    """Landmark lit from 315/45, camera from 135/30: curvature creases land on each other."""
    with extractor_node({"lighting": "compensated"}) as s:
        s.land_pub.publish(cv.geo_image_to_msg(_drainage_image(315.0, 45.0), GEOREF, HEADER,
                                               sun=(315.0, 45.0)))
        assert wait_until(lambda: bool(s.landmark), 30)
        cam = cv.geo_image_to_msg(_drainage_image(135.0, 30.0), GEOREF, HEADER,
                                  sun=(135.0, 30.0))
        assert wait_until(lambda: (s.cam_pub.publish(cam), bool(s.camera))[1], 30,
                          period=0.5)
        # stamped apart: the sets of frames sent again while waiting may come after it
        no_sun = cv.geo_image_to_msg(_drainage_image(135.0, 30.0), GEOREF,
                                     cv.make_header(9_000_000_000, "map"))

        def raw_sets():
            return [m for m in s.camera if m.header.stamp == no_sun.header.stamp]
        assert wait_until(lambda: (s.cam_pub.publish(no_sun), bool(raw_sets()))[1], 30,
                          period=0.5)
    land, cam, raw = (cv.msg_to_minutiae(m) for m in (s.landmark[0], s.camera[0],
                                                      raw_sets()[0]))
    assert len(land) >= 20 and len(cam) >= 20, s.log
    # the shading itself moves with the sun; the compensated input does not
    # measured: 21% of the camera minutiae within 2 px of a landmark one, raw shading 5%
    assert _repeated(cam, land) > 2 * _repeated(raw, land)
    assert _repeated(cam, land) >= 0.15
    assert "carries no sun" in s.log


def test_every_camera_frame_gets_a_set_and_a_bad_landmark_is_only_logged():
    """A frame the camera ingest could not project, and one the extractor cannot read, both
    come out as empty sets that say why (with their stamps); a bad landmark image does not
    displace anything."""
    unprojected = cv.unprojected_frame_msg(cv.make_header(7_000_000_000, "map"),
                                           "frame not projected: no CameraInfo")
    garbled = cv.geo_image_to_msg(_drainage_image(), GEOREF, cv.make_header(8_000_000_000,
                                                                            "map"))
    garbled.image.data = garbled.image.data[:100]   # truncated in transit
    from diagnostic_msgs.msg import DiagnosticArray

    with extractor_node({"diagnostics_period": 0.3}) as s:
        diagnostics = []
        s.client.node.create_subscription(DiagnosticArray, "/feature_extractor/diagnostics",
                                          diagnostics.append, 10)
        s.land_pub.publish(garbled)
        assert wait_until(lambda: (s.cam_pub.publish(unprojected), bool(s.camera))[1], 30,
                          period=0.5)
        s.cam_pub.publish(garbled)
        assert wait_until(lambda: len(s.camera) >= 2 and s.camera[-1].reason != s.camera[0]
                          .reason, 20)
        n_reports = len(diagnostics)
        assert wait_until(lambda: len(diagnostics) > n_reports, 10)
        assert s.node.poll() is None
    first, last = s.camera[0], s.camera[-1]
    assert (len(first.minutiae), first.reason) == (0, "frame not projected: no CameraInfo")
    assert cv.stamp_to_sec(first.header.stamp) == 7.0
    assert len(last.minutiae) == 0 and last.reason.startswith("unusable camera image")
    assert cv.stamp_to_sec(last.header.stamp) == 8.0
    assert s.landmark == [] and "landmark image without minutiae" in s.log
    # the diagnostics count them by stream and reason
    level, values = cv.diagnostic_values(diagnostics[-1].status[0])
    assert level == 0 and values["landmark_images"] == "1"
    assert int(values["camera_images"]) == len(s.camera)
    assert values["no minutiae: camera: frame not projected: no CameraInfo"] == str(
        len(s.camera) - 1)
    assert [values[k] for k in values if k.startswith("no minutiae: landmark: unusable")] == [
        "1"]
