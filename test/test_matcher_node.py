"""matcher node: a camera minutiae set projected with a wrong prior position is localised in
the landmark set and the fix lands on the true position; unmatchable sets get a no-fix reason."""

import time
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
from ros_helpers import SpinningNode, start_node, stop, wait_until
from std_msgs.msg import Header
from synthetic_minutiae import terrain_minutiae

from terrain_nav_msgs.msg import MinutiaArray, PvaFix
from terrain_nav_ros.core.camera.camera_mount import camera_rotation
from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.nodes import conversions as cv
from terrain_nav_ros.nodes.ros_common import LATCHED_QOS

GSD = 10.0
TRUE_XY = np.array([300.0, -200.0])
PRIOR_ERROR = np.array([60.0, -40.0])  # the estimate the camera frame was projected with


def _sets(with_creases=False):
    ms, skeleton = terrain_minutiae((512, 512), seed=5)
    landmark_georef = GeoReference.centred(0.0, 0.0, GSD, 512, 512)
    landmark = MinutiaSet(ms.col, ms.row, ms.angle, ms.kind, np.ones(len(ms)),
                          georef=landmark_georef)
    # The camera ground image: a 200 x 200 px window around the prior position, in which every
    # ground feature appears shifted by the prior's error.
    prior = TRUE_XY + PRIOR_ERROR
    camera_georef = GeoReference.centred(*prior, GSD, 200, 200)
    east, north = landmark.enu()
    col, row = camera_georef.enu_to_pixel(east + PRIOR_ERROR[0], north + PRIOR_ERROR[1])
    inside = (col > 5) & (col < 194) & (row > 5) & (row < 194)
    camera = MinutiaSet(col[inside], row[inside], ms.angle[inside], ms.kind[inside],
                        np.ones(int(inside.sum())), georef=camera_georef)
    if not with_creases:
        return landmark, camera, prior
    # the crease skeletons, the camera's moved exactly like its minutiae
    rows, cols = np.nonzero(skeleton)
    east, north = landmark_georef.pixel_to_enu(cols, rows)
    col, row = camera_georef.enu_to_pixel(east + PRIOR_ERROR[0], north + PRIOR_ERROR[1])
    col, row = np.rint(col).astype(int), np.rint(row).astype(int)
    inside = (col >= 0) & (col < 200) & (row >= 0) & (row < 200)
    camera_creases = np.zeros((200, 200), bool)
    camera_creases[row[inside], col[inside]] = True
    return landmark, camera, prior, skeleton, camera_creases


@contextmanager
def matcher_node():
    """The node in its own process and a client with both minutiae publishers and the fix
    subscription; the node's output is in ``log`` after the block."""
    node = start_node("matcher", {"prior_tilt_sigma": 0.0, "landmark_sigma": 0.0})
    client = SpinningNode("matcher_client")
    n = client.node
    s = SimpleNamespace(node=node, client=client, fixes=[], log="")
    try:
        n.create_subscription(PvaFix, "/nav/pva_fix", s.fixes.append, 10)
        s.land_pub = n.create_publisher(MinutiaArray, "/landmark/minutiae", LATCHED_QOS)
        s.cam_pub = n.create_publisher(MinutiaArray, "/camera/minutiae", 10)
        assert wait_until(lambda: s.cam_pub.get_subscription_count() > 0, 20), stop(node)
        yield s
    finally:
        client.close()
        s.log = stop(node)


@contextmanager
def matcher_in_process(monkeypatch):
    """The node in this process, its callbacks to be called directly, and the list its
    PvaFix messages are published into."""
    import rclpy

    from terrain_nav_ros.nodes.matcher_node import MatcherNode

    context = rclpy.Context()
    rclpy.init(context=context)
    node = MatcherNode(context=context)
    try:
        published = []
        monkeypatch.setattr(node.pub, "publish", published.append)
        yield node, published
    finally:
        node.destroy_node()
        context.try_shutdown()


ORIGIN = (36.5, -84.2, 0.0)    # the ENU origin of the landmark and camera sets


def _camera_msg(camera, prior, header, creases=None, origin=ORIGIN):
    """Camera minutiae as projected from the prior position, nadir, 3000 m over a 500 m plane."""
    msg = cv.minutiae_to_msg(camera, header, MinutiaArray.SOURCE_CAMERA, origin,
                             creases=creases)
    cv.set_projection(msg, [*prior, 3000.0], camera_rotation([0, 0, 0, 1]), 500.0)
    return msg


def test_matcher_publishes_the_true_position_and_explains_no_fix():
    from diagnostic_msgs.msg import DiagnosticArray

    landmark, camera, prior = _sets()
    header = cv.make_header(5_000_000_000, "map")
    with matcher_node() as s:
        fixes, diagnostics = s.fixes, []
        s.client.node.create_subscription(DiagnosticArray, "/matcher/diagnostics",
                                          diagnostics.append, 10)
        s.land_pub.publish(cv.minutiae_to_msg(landmark, header, MinutiaArray.SOURCE_LANDMARK,
                                              ORIGIN))
        cam_msg = _camera_msg(camera, prior, header)
        sparse = _camera_msg(camera.subset(np.arange(3)), prior, header)
        assert wait_until(lambda: (s.cam_pub.publish(cam_msg),
                                   any(f.status for f in fixes))[1], 30, 0.5)
        # the same set as a track mosaic's (another stamp): its fix says so to the ekf
        mosaic_msg = _camera_msg(camera, prior, cv.make_header(6_000_000_000, "map"))
        mosaic_msg.mosaic_lag = 8.5
        s.cam_pub.publish(mosaic_msg)
        assert wait_until(lambda: any(f.mosaic_lag for f in fixes), 20)
        before = len(fixes)
        s.cam_pub.publish(sparse)
        # a camera set of another ENU origin: another map (camera_ingest before its tile)
        s.cam_pub.publish(_camera_msg(camera, prior, header, origin=(0.0, 0.0, 0.0)))
        s.cam_pub.publish(cv.minutiae_to_msg(MinutiaSet.empty("no drainage: flat",
                                                              camera.georef),
                                             Header(frame_id="map"),
                                             MinutiaArray.SOURCE_CAMERA))
        # a frame that never had minutiae (nor a georeference): upstream said why
        s.cam_pub.publish(cv.empty_minutiae_msg(Header(frame_id="map"),
                                                MinutiaArray.SOURCE_CAMERA,
                                                "frame not projected: no CameraInfo"))
        # (late fixes of the repeated camera set may arrive in between)
        assert wait_until(lambda: sum(f.status == PvaFix.STATUS_NO_FIX
                                      for f in fixes[before:]) >= 4, 20)
        n_reports = len(diagnostics)
        assert wait_until(lambda: len(diagnostics) > n_reports, 10)
        assert s.node.poll() is None
    fix = next(f for f in fixes if f.status)
    assert fix.status == PvaFix.STATUS_POSITION_ATTITUDE, f"{fix.reason}\n{s.log}"
    assert fix.mosaic_lag == 0.0
    # a mosaic's scale is not its height's (its frames' layout is the dead reckoning's):
    # the height is the prior's, barely measured (10 % of the 2500 m above the plane, and
    # the matcher's covariance_scale)
    mosaic = next(f for f in fixes if f.mosaic_lag)
    assert mosaic.mosaic_lag == 8.5 and mosaic.status
    np.testing.assert_allclose(mosaic.pose.pose.position.z, 3000.0)
    assert cv.covariance_to_array(mosaic.pose.covariance, 6)[2, 2] >= 250.0 ** 2
    position = np.array([fix.pose.pose.position.x, fix.pose.pose.position.y])
    np.testing.assert_allclose(position, TRUE_XY, atol=GSD / 2)
    cov = cv.covariance_to_array(fix.pose.covariance, 6)
    assert 0 < cov[0, 0] < GSD**2 and cov[3, 3] > cov[5, 5] > 0  # heading measured, tilt not
    # a ground match: the estimate's tilt error moves it over the 2500 m to the plane, which
    # the ekf models (so the covariance leaves it out)
    assert fix.projection_height == 2500.0
    assert fix.num_pairings >= 10 and abs(fix.latitude - 36.5) < 0.01
    no_fix = [f for f in fixes[before:] if f.status == PvaFix.STATUS_NO_FIX]
    assert len(no_fix) >= 3 and all(f.reason for f in no_fix)
    reasons = [f.reason for f in no_fix]
    assert "no camera minutiae: no drainage: flat" in reasons
    assert "no camera minutiae: frame not projected: no CameraInfo" in reasons
    assert any(r.startswith("the camera set's ENU origin (0.0, 0.0, 0.0) is not the "
                            "landmark's") for r in reasons)
    level, values = cv.diagnostic_values(diagnostics[-1].status[0])
    assert level == 0, diagnostics[-1].status[0].message
    assert int(values["fixes"]) >= 1 and int(values["no_fixes"]) >= 3
    assert values["no_fix: no camera minutiae: no drainage: flat"] == "1"


def test_matcher_checks_the_creases_the_sets_carry():
    """With crease skeletons on both sides the score includes their agreement; a camera set
    without them is matched on minutiae only; a corrupt skeleton is a no-fix with a reason."""
    landmark, camera, prior, land_creases, cam_creases = _sets(with_creases=True)
    # one stamp per variant: the fixes are told apart by it
    messages = {sec: _camera_msg(camera, prior, cv.make_header(sec * 1_000_000_000, "map"),
                                 creases)
                for sec, creases in {6: cam_creases, 7: None, 8: cam_creases}.items()}
    messages[8].crease_pixels = [200 * 200 + 5]   # corrupt: outside the grid
    with matcher_node() as s:
        fixes = s.fixes
        s.land_pub.publish(cv.minutiae_to_msg(landmark, cv.make_header(5_000_000_000, "map"),
                                              MinutiaArray.SOURCE_LANDMARK, ORIGIN,
                                              creases=land_creases))
        assert wait_until(lambda: (s.cam_pub.publish(messages[6]),
                                   any(f.status for f in fixes))[1], 30, 0.5)
        s.cam_pub.publish(messages[7])
        s.cam_pub.publish(messages[8])
        assert wait_until(lambda: {7, 8} <= {f.header.stamp.sec for f in fixes}, 20)
        assert s.node.poll() is None
    log = s.log
    by_stamp = {f.header.stamp.sec: f for f in fixes}
    with_creases, minutiae_only, bad = by_stamp[6], by_stamp[7], by_stamp[8]
    assert with_creases.status and minutiae_only.status, f"{minutiae_only.reason}\n{log}"
    assert with_creases.similarity > minutiae_only.similarity + 10
    for fix in (with_creases, minutiae_only):
        position = np.array([fix.pose.pose.position.x, fix.pose.pose.position.y])
        np.testing.assert_allclose(position, TRUE_XY, atol=GSD / 2)
    assert bad.status == PvaFix.STATUS_NO_FIX and "crease pixel" in bad.reason


def test_a_failure_inside_matching_is_an_explicit_no_fix(monkeypatch):
    """An unexpected error while matching one frame (fault injected: the matcher raises) is
    logged and counted, and the frame still gets its PvaFix: no fix, with the error as the
    reason. The node in this process, its callbacks called directly."""
    landmark, camera, prior = _sets()
    header = cv.make_header(5_000_000_000, "map")
    with matcher_in_process(monkeypatch) as (node, published):
        node.on_landmark(cv.minutiae_to_msg(landmark, header, MinutiaArray.SOURCE_LANDMARK,
                                            ORIGIN))
        node.on_camera(_camera_msg(camera, prior, header))
        assert [f.status for f in published] == [PvaFix.STATUS_POSITION_ATTITUDE]

        def broken(*args, **kwargs):
            raise RuntimeError("injected")

        monkeypatch.setattr(node.matcher, "localise", broken)
        node.on_camera(_camera_msg(camera, prior, header))
        assert published[-1].status == PvaFix.STATUS_NO_FIX
        assert published[-1].reason == "matching failed: RuntimeError: injected"
        assert node.failures == {"on_camera": 1} and node.tally.no_fixes == 1
        # the diagnostics say so once, and count the answers by reason
        (status,) = node.diagnostics()
        level, values = cv.diagnostic_values(status)
        assert level == 2 and "1 message(s) failed" in status.message
        assert values["fixes"] == "1" and values["no_fixes"] == "1"
        assert values["no_fix: matching failed: RuntimeError: injected"] == "1"
        assert float(values["answer_ms_median"]) > 0   # the frame that matched
        assert float(values["last_fix_pairings"]) >= 10
        assert cv.diagnostic_values(node.diagnostics()[0])[0] == 0   # nothing new: OK


def test_a_set_that_waited_behind_a_slow_answer_is_skipped_at_once(monkeypatch):
    """A camera set that waited over max_queue_wait in the node's queue (behind a slow
    search of the mission index; rclpy gives the middleware's receive time to a
    two-argument callback) gets an immediate no-fix saying it was skipped, and a set that
    did not wait is matched: the matcher catches up instead of answering late. The node in
    this process, its callbacks called directly."""
    landmark, camera, prior = _sets()
    header = cv.make_header(5_000_000_000, "map")
    with matcher_in_process(monkeypatch) as (node, published):
        node.on_landmark(cv.minutiae_to_msg(landmark, header, MinutiaArray.SOURCE_LANDMARK,
                                            ORIGIN))
        now = time.time_ns()
        node.on_camera_received(_camera_msg(camera, prior, header),
                                {"received_timestamp": now - 1_600_000_000})
        node.on_camera_received(_camera_msg(camera, prior, header),
                                {"received_timestamp": now - 100_000_000})
        node.on_camera_received(_camera_msg(camera, prior, header), {})   # rmw says nothing
        assert [f.status for f in published] == [PvaFix.STATUS_NO_FIX,
                                                 PvaFix.STATUS_POSITION_ATTITUDE,
                                                 PvaFix.STATUS_POSITION_ATTITUDE]
        waited = float(published[0].reason.split("waited ")[1].split(" s")[0])
        assert 1.6 <= waited < 3.0, published[0].reason
        assert "catches up" in published[0].reason
        assert node.tally.no_fix_kinds == {
            "skipped: waited # s in the queue (the matcher catches up after a slow answer)": 1}
