"""Pose interpolation at a frame's stamp."""

import numpy as np
from scipy.spatial.transform import Rotation

from terrain_nav_ros.core.camera.pose_buffer import PoseBuffer, StampedPose


def _pose(t, yaw_deg):
    q = Rotation.from_euler("z", yaw_deg, degrees=True).as_quat()
    return StampedPose(t, np.array([30.0 * t, 0.0, 1000.0]), q, np.eye(6))


def test_interpolates_position_and_attitude():
    buf = PoseBuffer()
    for t, yaw in ((0.0, 0.0), (0.1, 10.0), (0.2, 20.0)):
        assert buf.add(_pose(t, yaw)) == ""
    pose, reason = buf.at(0.15)
    assert reason == ""
    np.testing.assert_allclose(pose.position, [4.5, 0, 1000])
    yaw = Rotation.from_quat(pose.quaternion).as_euler("xyz", degrees=True)[2]
    assert abs(yaw - 15.0) < 1e-6


def test_refuses_stale_and_future_queries_with_reasons():
    buf = PoseBuffer(horizon=1.0, max_extrapolation=0.2)
    assert buf.at(0.0)[1] == "no navigation estimate yet"
    buf.add(_pose(10.0, 0))
    assert buf.at(10.1)[0] is not None
    pose, reason = buf.at(11.0)
    assert pose is None and "older than the frame" in reason
    assert buf.add(StampedPose(11.0, np.array([np.nan, 0, 0]), np.array([0, 0, 0, 1.0]),
                               np.eye(6))) == "pose is not finite"


def test_time_going_backwards_restarts_the_history():
    buf = PoseBuffer()
    buf.add(_pose(100.0, 0))
    buf.add(_pose(100.1, 0))
    buf.add(_pose(5.0, 0))
    assert len(buf) == 1 and buf.at(5.0)[0].stamp == 5.0


def test_a_frame_far_behind_the_newest_estimate_is_refused_with_its_age():
    # a camera clock that jumped 2 s back: the pose of the stamp is not where the picture
    # was taken, though the history still holds it
    buf = PoseBuffer(horizon=5.0, max_extrapolation=0.2, max_age=1.0)
    for k in range(31):
        buf.add(_pose(10.0 + 0.1 * k, 0))
    assert buf.at(12.6)[0] is not None                # 0.4 s behind: a normal lag
    pose, reason = buf.at(11.0)
    assert pose is None and "2.00 s older than the newest estimate" in reason
    assert "clock" in reason
    assert PoseBuffer(horizon=5.0).at(11.0)[0] is None  # (empty)
    unlimited = PoseBuffer(horizon=5.0)
    unlimited.add(_pose(10.0, 0))
    unlimited.add(_pose(13.0, 0))
    assert unlimited.at(11.0)[0] is not None          # without max_age: the history's reach
