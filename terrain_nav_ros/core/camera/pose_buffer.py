"""A short history of timestamped poses, interpolated at a sensor's stamp.

Camera frames are stamped when the shutter opened; the navigation estimate arrives at its own
rate. Projecting a frame with the pose of another instant moves it by speed x time offset
(30 m/s x 20 ms = 0.6 m), so the pose is interpolated at the frame's stamp: linearly for the
position, by spherical interpolation for the attitude.

A frame stamped far behind the newest estimate is refused (``max_age``): a camera's frames
reach the graph within a fraction of a second, so a stamp seconds old is a camera clock that
jumped back (or a frame stuck in a queue), and the pose at that stamp is not where the
picture was taken. Projected with it, the fix lands speed x offset away (60 m for 2 s at
30 m/s) and its heading is the one of seconds ago, which the filter then takes in.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


@dataclass(frozen=True)
class StampedPose:
    """Pose in the map frame at ``stamp`` (s)."""

    stamp: float
    position: np.ndarray      # (3,) ENU m
    quaternion: np.ndarray    # (4,) body -> ENU, [x, y, z, w]
    covariance: np.ndarray    # (6, 6) pose covariance (x, y, z, rot x, rot y, rot z)


class PoseBuffer:
    """Keeps the last ``horizon`` seconds of poses.

    Parameters
    ----------
    horizon : float
        How much history to keep (s).
    max_extrapolation : float
        How far past the newest pose (or before the oldest) a query may be answered by the
        nearest pose (s); beyond, :meth:`at` returns None with a reason.
    max_age : float
        How far behind the newest pose a query may be (s); an older one is refused with the
        reason (a late frame or a camera clock fault).
    """

    def __init__(self, horizon: float = 5.0, max_extrapolation: float = 0.2,
                 max_age: float = math.inf):
        self.horizon = float(horizon)
        self.max_extrapolation = float(max_extrapolation)
        self.max_age = float(max_age)
        self._poses: deque[StampedPose] = deque()

    def __len__(self) -> int:
        return len(self._poses)

    def add(self, pose: StampedPose) -> str:
        """Insert a pose; returns a reason when it is refused ("" when stored)."""
        if not (np.isfinite(pose.position).all() and np.isfinite(pose.quaternion).all()):
            return "pose is not finite"
        if self._poses and pose.stamp < self._poses[0].stamp:
            self._poses.clear()  # time went backwards (bag loop): start again
        stamps = [p.stamp for p in self._poses]
        i = bisect.bisect_left(stamps, pose.stamp)
        if i < len(stamps) and stamps[i] == pose.stamp:
            self._poses[i] = pose
        else:
            self._poses.insert(i, pose)
        while self._poses and self._poses[0].stamp < self._poses[-1].stamp - self.horizon:
            self._poses.popleft()
        return ""

    def ahead(self, stamp: float) -> bool:
        """Whether ``stamp`` is past what the poses answer, the estimate still to come
        (False without any pose: there may be none coming)."""
        return bool(self._poses) and stamp > self._poses[-1].stamp + self.max_extrapolation

    def at(self, stamp: float) -> tuple[StampedPose | None, str]:
        """Pose at ``stamp`` and "" or None and why it is unavailable."""
        if not self._poses:
            return None, "no navigation estimate yet"
        first, last = self._poses[0], self._poses[-1]
        if stamp > last.stamp + self.max_extrapolation:
            return None, f"newest estimate is {stamp - last.stamp:.2f} s older than the frame"
        if stamp < last.stamp - self.max_age:
            return None, (f"frame is {last.stamp - stamp:.2f} s older than the newest estimate "
                          f"(max_frame_age {self.max_age:g} s): a late frame or a camera clock "
                          "that jumped back")
        if stamp < first.stamp - self.max_extrapolation:
            return None, f"frame is {first.stamp - stamp:.2f} s older than the pose history"
        if stamp >= last.stamp:
            return last, ""
        if stamp <= first.stamp:
            return first, ""
        stamps = [p.stamp for p in self._poses]
        i = bisect.bisect_right(stamps, stamp)
        a, b = self._poses[i - 1], self._poses[i]
        w = (stamp - a.stamp) / (b.stamp - a.stamp)
        slerp = Slerp([0.0, 1.0], Rotation.from_quat([a.quaternion, b.quaternion]))
        q = slerp([w]).as_quat()[0]
        return StampedPose(stamp, (1 - w) * a.position + w * b.position, q,
                           (1 - w) * a.covariance + w * b.covariance), ""
