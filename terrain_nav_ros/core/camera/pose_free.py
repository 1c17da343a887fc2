"""Pose-free projection: a camera frame put on the ground before there is any estimate.

A live graph started with GNSS already jammed has no navigation estimate until the matcher
has relocalised it in the mission index (issue 24), and the matcher needs ground-projected
frames to do so. A pose-free projection makes one from what is known without a position:

* **Place and heading**: a nominal place (the graph's ENU origin) and heading 0. The mission
  search covers every place and every rotation, so neither is needed.
* **Attitude**: roll and pitch from the IMU's orientation when its messages carry one, else
  from its accelerometers levelled in straight flight (they measure the reaction to gravity:
  a climb's pitch shows), else wings level (before any IMU message); the
  attitude assumed is off by ``tilt_sigma``, which moves the matched ground point by the
  height above ground x tilt (the matcher adds it to the fix's covariance). A frame taken in
  a turn (the gyro's rate above a few degrees per second) is not projected: the bank is
  unknown there (:class:`CruiseAttitude`).
* **Height above ground**: the barometer's pressure altitude minus the mission area's median
  terrain height (:func:`pose_free_view`). The terrain under the aircraft lies anywhere in the
  area's spread of heights, so the height above ground, hence the ground image's scale, is
  uncertain: the view carries the range of planes the true ground may lie in, and the matcher
  searches the scales it allows.

Heights: the barometer's pressure altitude (ISA) and the DEM's heights are above the geoid
(mean sea level); the graph's ENU ``up`` is taken as that minus the ENU origin's altitude
(the geoid undulation and the Earth's curvature over the area are left to the fix's height
sigma; the height above ground does not depend on them).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..estimation.strapdown import quat_from_euler, quat_to_euler
from .camera_mount import R_BODY_OPTICAL_NADIR, camera_rotation
from .ground_projection import CameraPose

__all__ = ["CruiseAttitude", "PoseFreeView", "levelled", "pose_free_view", "scale_range"]

# a pose-free view needs at least this height above the area's highest terrain (m): below
# it the height above ground, hence the image's scale, is unknown by more than any ladder of
# scales covers
MIN_CLEARANCE = 100.0


@dataclass(frozen=True)
class PoseFreeView:
    """Where a pose-free projection puts the camera, and what it leaves uncertain.

    Attributes
    ----------
    pose : CameraPose
        The camera at the nominal place, its height from the barometer (graph ENU).
    plane : float
        Height of the terrain plane the frame is projected on: the area's median (ENU up).
    plane_min, plane_max : float
        The range of planes the true ground may lie in (the area's 2nd-98th percentile
        heights, widened by the barometer's altitude sigma twice).
    tilt_sigma : float
        1-sigma of the attitude assumed (rad).
    """

    pose: CameraPose
    plane: float
    plane_min: float
    plane_max: float
    tilt_sigma: float

    @property
    def height_above_ground(self) -> float:
        """The height above the projection plane (m)."""
        return float(self.pose.position[2] - self.plane)


def pose_free_view(pressure_altitude: float, terrain_low: float, terrain_median: float,
                   terrain_high: float, origin_altitude: float = 0.0, *, roll: float = 0.0,
                   pitch: float = 0.0, tilt_sigma: float = math.radians(3.0),
                   altitude_sigma: float = 0.0, nominal=(0.0, 0.0),
                   r_body_optical=R_BODY_OPTICAL_NADIR) -> tuple[PoseFreeView | None, str]:
    """The camera pose and terrain plane of a frame projected without a navigation pose.

    Parameters
    ----------
    pressure_altitude : float
        The barometer's ISA pressure altitude at the frame (m).
    terrain_low, terrain_median, terrain_high : float
        The mission area's terrain heights (2nd percentile, median, 98th percentile; m above
        the geoid), e.g. :meth:`~..matching.mission_index.MissionIndex.terrain`'s.
    origin_altitude : float
        The graph's ENU origin altitude (m).
    roll, pitch : float
        Attitude assumed (rad; REP 103 body FLU, ENU); the heading is 0 (body x east).
    tilt_sigma : float
        Its 1-sigma (rad).
    altitude_sigma : float
        1-sigma of the pressure altitude against the DEM's heights (the day's sea-level
        pressure), m; widens the range of planes by twice that.
    nominal : (east, north)
        The nominal place (graph ENU).
    r_body_optical : (3, 3) array
        The camera mount (:func:`~.camera_mount.mount_rotation`).

    Returns
    -------
    (PoseFreeView or None, str)
        The view, or None and why not (empty reason with a view).
    """
    values = (pressure_altitude, terrain_low, terrain_median, terrain_high, origin_altitude,
              roll, pitch, tilt_sigma, altitude_sigma)
    if not all(math.isfinite(float(v)) for v in values):
        return None, "cold start: the barometric altitude or the area's terrain heights " \
                     "are not finite"
    if not terrain_low <= terrain_median <= terrain_high:
        return None, (f"cold start: the area's terrain heights are not ordered (low "
                      f"{terrain_low:.0f}, median {terrain_median:.0f}, high "
                      f"{terrain_high:.0f} m)")
    spread = 2.0 * abs(altitude_sigma)
    clearance = pressure_altitude - (terrain_high + spread)
    if clearance < MIN_CLEARANCE:
        return None, (f"cold start: the barometric altitude {pressure_altitude:.0f} m is "
                      f"{clearance:.0f} m above the area's high terrain ({terrain_high:.0f} m"
                      f"{f' + {spread:.0f} m for the barometer' if spread else ''}): the "
                      f"height above ground is unknown (needs {MIN_CLEARANCE:.0f} m)")
    q_enu_body = quat_from_euler(float(roll), float(pitch), 0.0)
    position = np.array([float(nominal[0]), float(nominal[1]),
                         pressure_altitude - origin_altitude])
    pose = CameraPose(position, camera_rotation(q_enu_body, r_body_optical))
    return PoseFreeView(pose, terrain_median - origin_altitude,
                        terrain_low - spread - origin_altitude,
                        terrain_high + spread - origin_altitude, float(tilt_sigma)), ""


def scale_range(camera_height: float, plane: float, plane_min: float,
                plane_max: float) -> tuple[float, float]:
    """The factors by which a frame projected on ``plane`` from ``camera_height`` must be
    rescaled to be at its true scale, over the range of true planes ``plane_min`` ..
    ``plane_max``: (smallest, largest) of ``(camera_height - true plane) / (camera_height -
    plane)``. Ground distances in the projected image are the true ones times the assumed
    over the true height above ground, so the factor is the true over the assumed."""
    agl = camera_height - plane
    if not agl > 0 or not camera_height > plane_max >= plane_min:
        raise ValueError(f"scale_range: camera {camera_height:g} m must be above the planes "
                         f"{plane_min:g}..{plane_max:g} m and {plane:g} m")
    return (camera_height - plane_max) / agl, (camera_height - plane_min) / agl


def levelled(specific_force) -> tuple[float, float]:
    """Roll and pitch (rad; REP 103 body FLU in ENU, :func:`~..estimation.strapdown.
    quat_from_euler`'s convention) of a body whose accelerometers measure
    ``specific_force`` (m/s^2, body) in unaccelerated flight: the reaction to gravity, along
    the ENU up axis (an INS's coarse levelling)."""
    fx, fy, fz = (float(v) for v in np.asarray(specific_force, float).reshape(3))
    return math.atan2(fy, fz), math.atan2(-fx, math.hypot(fy, fz))


class CruiseAttitude:
    """Roll and pitch for a pose-free projection, from the IMU's messages.

    In order of preference: the IMU messages' orientation (an AHRS), its sigma at least
    ``floor_sigma``; the accelerometers levelled over the last ``window`` s (unaccelerated
    straight flight: they measure the reaction to gravity; a climb's pitch shows), with
    ``levelled_sigma`` (speed changes and turbulence); wings level with ``level_sigma``
    before any IMU message. A frame whose last ``window`` s turned faster than
    ``max_turn_rate`` (the norm of the mean gyro vector) is in a turn: no attitude (the bank
    of a coordinated turn shows neither in the accelerometers nor, without a heading, in the
    gyros alone).

    Parameters
    ----------
    level_sigma : float
        1-sigma of the wings-level assumption (rad).
    max_turn_rate : float
        Largest gyro rate (norm, rad/s) of straight flight.
    window : float
        IMU samples this long before a frame are used (s).
    floor_sigma : float
        Smallest sigma taken from an orientation's covariance (rad).
    levelled_sigma : float
        1-sigma of the accelerometers' levelling (rad).
    """

    def __init__(self, level_sigma: float = math.radians(3.0),
                 max_turn_rate: float = math.radians(3.0), window: float = 1.0,
                 floor_sigma: float = math.radians(0.5),
                 levelled_sigma: float = math.radians(1.0)):
        self.level_sigma = level_sigma
        self.max_turn_rate = max_turn_rate
        self.window = window
        self.floor_sigma = floor_sigma
        self.levelled_sigma = levelled_sigma
        self._rates: deque = deque()          # (stamp, gyro vector, accel vector or None)
        self._orientation = None              # (stamp, roll, pitch, sigma)

    def add(self, stamp: float, gyro, accel=None, orientation=None,
            orientation_variance=None) -> None:
        """One IMU message: its gyro (rad/s, body), accelerometers (m/s^2, body; None
        without) and, if it has one, its orientation quaternion ``[x, y, z, w]`` (body ->
        ENU) with the variance of its roll and pitch (rad^2; None or negative: no
        orientation)."""
        gyro = np.asarray(gyro, float).reshape(3)
        accel = None if accel is None else np.asarray(accel, float).reshape(3)
        if np.isfinite(gyro).all():
            self._rates.append((float(stamp), gyro,
                                accel if accel is not None and np.isfinite(accel).all()
                                else None))
        while self._rates and self._rates[0][0] < self._rates[-1][0] - 4.0 * self.window:
            self._rates.popleft()
        if orientation is not None and orientation_variance is not None \
                and orientation_variance >= 0 and np.isfinite(orientation).all():
            roll, pitch, _ = quat_to_euler(np.asarray(orientation, float))
            sigma = max(math.sqrt(orientation_variance), self.floor_sigma)
            self._orientation = (float(stamp), float(roll), float(pitch), sigma)

    def at(self, stamp: float) -> tuple[tuple[float, float, float] | None, str]:
        """(roll, pitch, sigma) for a frame at ``stamp``, or None and why not."""
        recent = [(g, a) for t, g, a in self._rates if stamp - self.window <= t <= stamp + 0.1]
        rate = float(np.linalg.norm(np.mean([g for g, _ in recent], axis=0))) if recent \
            else 0.0
        if rate > self.max_turn_rate:
            return None, (f"cold start: the aircraft is turning ({math.degrees(rate):.1f}"
                          f" deg/s > {math.degrees(self.max_turn_rate):.1f}): its bank is "
                          "unknown without a navigation estimate")
        o = self._orientation
        if o is not None and abs(o[0] - stamp) <= self.window:
            return (o[1], o[2], o[3]), ""
        accels = [a for _, a in recent if a is not None]
        if accels:
            return (*levelled(np.mean(accels, axis=0)), self.levelled_sigma), ""
        return (0.0, 0.0, self.level_sigma), ""
