"""The matcher node's relocalisation helpers (core.matching.relocaliser)."""

import math

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.features.minutiae import FeatureExtractor
from terrain_nav_ros.core.matching.global_search import rescaled_view, scale_ladder
from terrain_nav_ros.core.matching.mission_index import MissionIndex
from terrain_nav_ros.core.matching.params import MatchParams
from terrain_nav_ros.core.matching.relocaliser import MissionSearch, SearchPolicy, tile_in_frame
from terrain_nav_ros.core.terrain.dem_io import open_dem
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.core.terrain.metamap import MetaMap
from terrain_nav_ros.tools import cli
from terrain_nav_ros.tools.evaluation import camera_renders


def test_frames_are_searched_off_the_tiles_and_after_a_run_of_no_fixes():
    policy = SearchPolicy(after_no_fixes=3)
    assert policy.reason_to_search(covered=False).startswith("no landmark tile")
    for _ in range(2):
        assert policy.reason_to_search(covered=True) == ""
        policy.tile_answered(fixed=False)
    policy.tile_answered(fixed=False)
    assert policy.reason_to_search(covered=True) == "3 frames in a row without a fix in the tile"
    # while the run lasts, searches and tries in the tile alternate
    policy.searched()
    assert policy.reason_to_search(covered=True) == ""
    assert policy.reason_to_search(covered=False) != ""
    policy.tile_answered(fixed=False)
    assert policy.reason_to_search(covered=True) == "4 frames in a row without a fix in the tile"
    policy.searched()
    policy.tile_answered(fixed=True)
    assert policy.reason_to_search(covered=True) == ""
    with pytest.raises(ValueError):
        SearchPolicy(after_no_fixes=0)


def test_a_tile_moves_into_another_frame_exactly_at_the_matched_pixel():
    tile_origin = EnuOrigin(44.5, 5.5, 300.0)
    frame_origin = EnuOrigin(44.9, 5.1, 250.0)      # ~55 km away
    georef = GeoReference(-20_000.0, 15_000.0, 30.0, 1024, 1024)
    col, row = 700.0, 300.0
    east, north = map(float, georef.pixel_to_enu(col, row))
    moved = tile_in_frame(georef, east, north, tile_origin, frame_origin)
    assert (moved.gsd, moved.width, moved.height) == (georef.gsd, georef.width, georef.height)
    lat, lon, h = tile_origin.enu_to_geodetic(east, north, tile_origin.surface_up(east, north))
    want = frame_origin.geodetic_to_enu(lat, lon, h)
    got = moved.pixel_to_enu(col, row)
    assert abs(got[0] - want[0]) < 0.5 and abs(got[1] - want[1]) < 0.5
    # 55 km apart: a shift of tens of kilometres
    assert abs(moved.origin_east - georef.origin_east) > 20_000
    assert tile_in_frame(georef, east, north, tile_origin, tile_origin) is georef


# ---------------------------------------------------------------- MissionSearch on a real index
WHEN = 1718960400.0                          # 2024-06-21T09:00:00Z
GRAPH_ORIGIN = EnuOrigin(44.45, 5.42, 0.0)   # the graph's frame, not the index's


@pytest.fixture(scope="module")
def mission(shared_data, tmp_path_factory):
    """A 3 x 3 tile index of N44E005 at 90 m for a flight window at 09:00 UTC, built
    through the command."""
    out = tmp_path_factory.mktemp("relocaliser") / "index"
    dem = shared_data / "dem" / "N44E005.hgt"
    assert cli.main(["prepare", "--dem", str(dem), "--area", "44.30,5.30,44.70,5.70",
                     "--gsd", "90", "--out", str(out), "--time", "2024-06-21T08:50:00Z",
                     "--hours", "0.4", "--tile", "256", "--overlap", "128",
                     "--workers", "1"]) == 0
    return MissionIndex(out), dem


def _camera_view(dem, east, north, degrees, sun, gsd=90.0, side=128, origin=GRAPH_ORIGIN):
    """A camera set of side ``side`` px centred on graph-frame (east, north), turned by
    ``degrees``: another albedo than the landmarks', extracted as camera_ingest's frames
    are, with its georef in the graph's frame."""
    mm = MetaMap(open_dem(dem), origin, interpolation="spline", fill_voids=True)
    big = GeoReference.centred(east, north, gsd, 2 * side, 2 * side)
    elevation = mm.tile(big).elevation
    rgb, = camera_renders(elevation, big, [sun])
    turn = cv2.getRotationMatrix2D((side - 0.5, side - 0.5), degrees, 1.0)
    grey = cv2.cvtColor(cv2.warpAffine(rgb, turn, (2 * side, 2 * side)), cv2.COLOR_RGB2GRAY)
    crop = np.ascontiguousarray(grey[side // 2:side // 2 + side, side // 2:side // 2 + side])
    georef = GeoReference.centred(east, north, gsd, side, side)
    return FeatureExtractor(ridges=True)(crop, georef=georef)


def test_a_camera_set_is_relocalised_in_the_graph_frame(mission):
    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    east, north = 6000.0, -9000.0                 # in the graph's frame
    features = _camera_view(dem, east, north, 40.0, search.sun_at(WHEN))
    camera = search.matcher.index(features.minutiae, features.creases.skeleton(),
                                  features.ridges)
    found, land_georef = search.search(camera, WHEN, GRAPH_ORIGIN)
    assert found.matched, found.reason
    assert search.layer == index.nearest_sun(search.sun_at(WHEN))
    assert found.penalty == pytest.approx(math.log10(len(index.tiles())))
    col, row = found.result.apply(63.5, 63.5)
    got = land_georef.pixel_to_enu(col, row)
    assert math.hypot(got[0] - east, got[1] - north) < 1.5 * index.gsd


def test_the_layer_is_loaded_in_the_background_before_the_first_search(mission):
    """The node has the sun layer of its first frame loaded in a thread: the search that
    comes later uses those tiles without loading them again; a layer loaded or being loaded
    starts nothing, nor does a frame whose sun no layer is near (no search would be made)."""
    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    assert search.prepare_in_background(WHEN + 8 * 3600.0) is None   # the evening sun
    thread = search.prepare_in_background(WHEN)
    assert thread is not None and search.prepare_in_background(WHEN + 1.0) is None
    thread.join(120.0)
    assert not thread.is_alive()
    assert search.layer == index.nearest_sun(search.sun_at(WHEN))
    tiles = search.tiles
    assert len(tiles) == len(index.tiles()) and search.prepare_in_background(WHEN) is None
    features = _camera_view(dem, 6000.0, -9000.0, 40.0, search.sun_at(WHEN))
    found, _ = search.search(search.matcher.index(features.minutiae,
                                                  features.creases.skeleton(),
                                                  features.ridges), WHEN, GRAPH_ORIGIN)
    assert found.matched and search.tiles is tiles


def test_a_camera_set_at_another_gsd_is_refused_with_the_reason(mission):
    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    features = _camera_view(dem, 6000.0, -9000.0, 0.0, search.sun_at(WHEN), gsd=60.0)
    camera = search.matcher.index(features.minutiae, features.creases.skeleton(),
                                  features.ridges)
    found, land_georef = search.search(camera, WHEN, GRAPH_ORIGIN)
    assert not found.matched and land_georef is None
    assert "prepare the index at the graph's gsd" in found.reason


def test_a_search_under_a_sun_the_index_was_not_prepared_for_is_not_made(mission):
    """A view of the index's own terrain in the evening, the index prepared for the
    morning: its creases are shaded otherwise, and relocalisations in it would share a
    bias of 100-200 m (measured with a layer lit 114 deg away): no search, the reason names
    the sun."""
    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    evening = WHEN + 8 * 3600.0                   # 17:00 UTC: the sun in the west
    features = _camera_view(dem, 6000.0, -9000.0, 0.0, search.sun_at(evening))
    camera = search.matcher.index(features.minutiae, features.creases.skeleton(),
                                  features.ridges)
    found, georef = search.search(camera, evening, GRAPH_ORIGIN)
    assert not found.matched and georef is None
    assert "(at most 10): prepare it for the flight's hours" in found.reason
    assert search.layer is None                   # no tile was loaded
    assert search.layer_sun_gap(search.sun_at(evening)) > 90.0


def test_a_view_at_the_wrong_scale_is_found_on_the_ladder_of_scales(mission):
    """A pose-free frame projected from a wrongly assumed height: its ground distances are
    the true ones / 1.35. One search (+-10 % of scale) cannot register it; the ladder's rung
    near 1.35 does, at the true place, and pays for its rungs."""
    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    east, north = 6000.0, -9000.0
    features = _camera_view(dem, east, north, 40.0, search.sun_at(WHEN), gsd=90.0 * 1.35)
    # labelled as the camera_ingest would: 90 m pixels, centred under the camera
    assumed = GeoReference.centred(east + 700.0, north - 400.0, 90.0, 128, 128)
    m = features.minutiae
    shrunk = type(m)(m.col, m.row, m.angle, m.kind, m.quality, georef=assumed)
    anchor = assumed.centre
    factors = scale_ladder(0.8, 1.6)
    assert len(factors) == 4
    views = [rescaled_view(shrunk, features.creases.skeleton(), features.ridges, f, anchor)
             for f in factors]
    found, land_georef, k = search.search_ladder([search.matcher.index(*v) for v in views],
                                                 WHEN, GRAPH_ORIGIN)
    assert found.matched, found.reason
    assert abs(factors[k] * found.result.scale - 1.35) < 0.1, (factors, k, found.result.scale)
    assert found.penalty == pytest.approx(math.log10(len(index.tiles()) * len(factors)))
    # the view's centre (under the camera) at the true place
    view_georef = views[k][0].georef
    c, r = view_georef.enu_to_pixel(*anchor)
    col, row = found.result.apply(c, r)
    got = land_georef.pixel_to_enu(col, row)
    assert math.hypot(got[0] - east, got[1] - north) < 2.0 * index.gsd
    # without the ladder, the shrunk view is not found
    alone, _ = search.search(search.matcher.index(shrunk, features.creases.skeleton(),
                                                  features.ridges), WHEN, GRAPH_ORIGIN)
    assert not alone.matched


# ---------------------------------------------------------------- the matcher node, cold start
def _first_answer_of_a_matcher(mission_dir: str, msg):
    """The first PvaFix a matcher node (with ``mission_dir``) answers ``msg`` with, and its
    log."""
    from ros_helpers import SpinningNode, start_node, stop, wait_until

    from terrain_nav_msgs.msg import MinutiaArray, PvaFix

    node = start_node("matcher", {"mission_dir": mission_dir, "landmark_sigma": 0.0})
    client = SpinningNode("matcher_cold_client")
    fixes = []
    try:
        client.node.create_subscription(PvaFix, "/nav/pva_fix", fixes.append, 10)
        pub = client.node.create_publisher(MinutiaArray, "/camera/minutiae", 10)
        assert wait_until(lambda: pub.get_subscription_count() > 0, 30), stop(node)
        pub.publish(msg)
        assert wait_until(lambda: bool(fixes), 120), stop(node)
    finally:
        client.close()
        log = stop(node)
    return fixes[0], log


def test_the_matcher_relocalises_a_pose_free_frame_on_its_ladder_of_scales(mission):
    """A camera set projected without any pose (camera_ingest's cold start) at the graph's
    origin, heading 0, 3000 m above an assumed plane, the terrain truly 900 m lower (its
    ground distances / 1.3): the matcher node searches it in the mission index at the
    scales the plane range allows and publishes a relocalisation at the true place, its
    height the barometer's, its covariance holding the height above ground x the tilt
    sigma. A matcher without a mission index says why it cannot."""
    from terrain_nav_msgs.msg import MinutiaArray, PvaFix
    from terrain_nav_ros.core.camera.camera_mount import camera_rotation
    from terrain_nav_ros.nodes import conversions as cv

    index, dem = mission
    search = MissionSearch(index, MatchParams(threshold=8.6))
    east, north = 6000.0, -9000.0
    features = _camera_view(dem, east, north, 40.0, search.sun_at(WHEN), gsd=90.0 * 1.3)
    m = features.minutiae
    camera = type(m)(m.col, m.row, m.angle, m.kind, m.quality,
                     georef=GeoReference.centred(0.0, 0.0, 90.0, 128, 128))
    msg = cv.minutiae_to_msg(camera, cv.make_header(int(WHEN * 1e9), "map"),
                             MinutiaArray.SOURCE_CAMERA,
                             (GRAPH_ORIGIN.lat, GRAPH_ORIGIN.lon, GRAPH_ORIGIN.alt),
                             creases=features.creases.skeleton(), ridges=features.ridges)
    cv.set_projection(msg, [0.0, 0.0, 3500.0], camera_rotation([0, 0, 0, 1]), 500.0)
    tilt = math.radians(2.0)
    cv.set_pose_free(msg, -600.0, 1500.0, tilt)
    for mission_dir in (str(index.path), ""):
        fix, log = _first_answer_of_a_matcher(mission_dir, msg)
        if not mission_dir:
            assert fix.status == PvaFix.STATUS_NO_FIX and "mission_dir" in fix.reason, log
            continue
        assert fix.status == PvaFix.STATUS_POSITION_ATTITUDE and fix.relocalisation, \
            f"{fix.reason}\n{log}"
        p = fix.pose.pose.position
        assert math.hypot(p.x - east, p.y - north) < 2.0 * index.gsd, (p, log)
        assert p.z == pytest.approx(3500.0)
        cov = cv.covariance_to_array(fix.pose.covariance, 6)
        # the tilt's allowance at the measured 3900 m above ground, inflated as every fix's
        assert cov[0, 0] > (3500.0 * math.tan(tilt)) ** 2
        assert "at scale" in log and "4 scales" in log
