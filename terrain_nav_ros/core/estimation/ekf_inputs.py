"""What the ``ekf`` node decides about its inputs before they reach the filter, without ROS.

The node (:mod:`terrain_nav_ros.nodes.ekf_node`) converts messages to arrays and calls these;
:class:`~.ekf.TerrainEkf` then fuses the result (dissertation chapter 4's fix fused with the
strapdown solution of chapter 2's INS model).

* Terrain fixes: the pose of the camera optical frame or of ``base_link``
  (:class:`FixFrame`), and the covariance in the core's block order
  (:func:`fix_covariance`).
* GNSS: which fixes are refused (:func:`gnss_refusal`) and the covariance a fix without one
  gets (:func:`gnss_covariance`).
* Barometer: which samples are refused (:func:`baro_refusal`) and the offset from pressure
  altitude to ENU up, set or learnt once (:class:`BaroOffset`).
* The ENU origin: adopted from the first metamap georeference, asked for again when a request
  goes unanswered (:class:`OriginHandshake`).
* The IMU's axes and units: its first second of specific force against gravity
  (:class:`ImuConvention`), and its gyro's scale in turns against the turn rate the
  specific force and the speed imply (:class:`GyroScale`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from ..terrain.geodesy import EnuOrigin
from .ekf import Reason
from .strapdown import quat_to_matrix

# sensor_msgs/NavSatFix position_covariance_type values the node treats specially
COVARIANCE_TYPE_UNKNOWN = 0
COVARIANCE_TYPE_DIAGONAL_KNOWN = 2
FIX_POSE_FRAMES = ("camera_optical", "base_link")


def body_attitude(q_enu_optical, optical_to_body: Rotation) -> np.ndarray:
    """Body -> ENU quaternion ``[x, y, z, w]`` from the camera optical frame's attitude.

    ``optical_to_body`` is the inverse of the body -> optical mount rotation
    (:func:`~terrain_nav_ros.core.camera.camera_mount.mount_rotation`), so that
    ``R_enu_body = R_enu_optical @ R_body_optical^T``. An attitude error expressed as a small
    rotation about the ENU axes is the same for both frames, so the covariance carries over.
    """
    return (Rotation.from_quat(q_enu_optical) * optical_to_body).as_quat()


class FixFrame:
    """What a terrain fix's pose is of, and how to get ``base_link``'s from it.

    Parameters
    ----------
    pose_frame : {"camera_optical", "base_link"}
        The frame whose pose the fix gives.
    optical_to_body : scipy.spatial.transform.Rotation
        Camera optical -> body rotation (the inverse of the mount rotation).
    lever_arm : array_like, shape (3,)
        Camera optical centre in ``base_link`` (m).
    """

    def __init__(self, pose_frame: str, optical_to_body: Rotation, lever_arm):
        self.pose_frame = self.checked_pose_frame(pose_frame)
        self.optical_to_body = optical_to_body
        self.lever_arm = np.asarray(lever_arm, float)

    @staticmethod
    def checked_pose_frame(pose_frame: str) -> str:
        """``pose_frame`` if it is one of :data:`FIX_POSE_FRAMES`; else ValueError."""
        if pose_frame not in FIX_POSE_FRAMES:
            raise ValueError("fix_pose_frame must be camera_optical or base_link, not "
                             f"{pose_frame!r}")
        return pose_frame

    def body_quaternion(self, q_fix) -> np.ndarray | None:
        """Body attitude from the fix orientation (None if not a unit quaternion)."""
        norm = float(np.linalg.norm(q_fix))
        if not abs(norm - 1.0) < 0.01:
            return None
        q = np.asarray(q_fix, float) / norm
        if self.pose_frame == "base_link":
            return q
        return body_attitude(q, self.optical_to_body)

    def body_position(self, p_fix, q_body, q_estimate) -> np.ndarray:
        """``base_link`` position from the fixed point (camera centre minus the lever arm,
        turned by the fix's body attitude ``q_body`` or, without one, the estimate's)."""
        if self.pose_frame == "base_link" or not self.lever_arm.any():
            return np.asarray(p_fix, float)
        q = q_body if q_body is not None else q_estimate
        return np.asarray(p_fix, float) - quat_to_matrix(q) @ self.lever_arm


def fix_covariance(covariance, velocity_covariance=None,
                   with_attitude: bool = False) -> np.ndarray:
    """A fix's covariance in the core's order ``[position, velocity?, attitude?]``.

    Parameters
    ----------
    covariance : ndarray, shape (6, 6)
        Pose covariance (position, then rotation about the ENU axes).
    velocity_covariance : ndarray, shape (3, 3), optional
        When the fix has a velocity; its cross terms with the pose are unknown (zero).
    with_attitude : bool
        Whether the fix's attitude is used.
    """
    covariance = np.asarray(covariance, float)
    blocks = [covariance[:3, :3]]
    if velocity_covariance is not None:
        blocks.append(np.asarray(velocity_covariance, float))
    if with_attitude:
        blocks.append(covariance[3:, 3:])
    n = 3 * len(blocks)
    cov = np.zeros((n, n))
    for i, b in enumerate(blocks):
        cov[3 * i:3 * i + 3, 3 * i:3 * i + 3] = b
    if with_attitude:
        cov[:3, -3:] = covariance[:3, 3:]
        cov[-3:, :3] = covariance[3:, :3]
    return cov


MAX_GNSS_RANGE = 1000e3   # m from the ENU origin: beyond, a fix is of another mission
# m above the ellipsoid: no aircraft flies outside (a receiver's mm reads 1000 times out)
GNSS_ALTITUDE_RANGE = (-1000.0, 30000.0)


def gnss_refusal(stamp: float, lla, origin: EnuOrigin | None) -> tuple[str, str] | None:
    """Why a GNSS fix (with a fix status) is refused, as ``(reason, detail)``, or None.

    Besides values no fix can hold: latitude and longitude both exactly 0, which receivers
    and drivers put out before their first fix (status already set, or not gated), an
    altitude outside :data:`GNSS_ALTITUDE_RANGE`, and a fix over :data:`MAX_GNSS_RANGE`
    from the mission's origin. Either would start or reset
    the filter thousands of kilometres off.
    """
    if not (np.isfinite(lla).all() and math.isfinite(stamp)):
        return Reason.NON_FINITE.value, ""
    if abs(lla[0]) > 90.0 or abs(lla[1]) > 360.0:
        return "latitude_longitude_out_of_range", f" {lla[:2]}"
    if lla[0] == 0.0 and lla[1] == 0.0:
        return "zero_latitude_longitude", " (0, 0): a receiver's placeholder before its fix"
    if not GNSS_ALTITUDE_RANGE[0] <= lla[2] <= GNSS_ALTITUDE_RANGE[1]:
        return "altitude_out_of_range", (f" {lla[2]:.6g} m, not within {GNSS_ALTITUDE_RANGE[0]:g}"
                                         f"..{GNSS_ALTITUDE_RANGE[1]:g} m (in mm or feet?)")
    if origin is None:
        return "no_enu_origin_yet", ""
    distance = float(np.linalg.norm(origin.geodetic_to_enu(lla[0], lla[1], origin.alt)))
    if distance > MAX_GNSS_RANGE:
        return "far_from_the_mission", (f" ({lla[0]:.5f}, {lla[1]:.5f}) is {distance / 1e3:.0f} "
                                        "km from the ENU origin")
    return None



def gnss_covariance(covariance, covariance_type: int, fallback_sigma) -> np.ndarray:
    """The ENU covariance to fuse a GNSS fix with: ``fallback_sigma`` squared when the fix
    gives none, the diagonal when only that is known, else the fix's own.

    NavSatFix covariance is ENU at the receiver; at mission distances (tens of km) its axes
    differ from the map's by < 0.5 deg, which is ignored.
    """
    if covariance_type == COVARIANCE_TYPE_UNKNOWN:
        return np.diag(np.square(fallback_sigma))
    if covariance_type == COVARIANCE_TYPE_DIAGONAL_KNOWN:
        return np.diag(np.diag(covariance))
    return covariance


# Static pressures of flight (Pa): 16 km up to below the Dead Sea. FluidPressure is in Pa;
# a driver's hPa, mbar, kPa or psi fall far below.
FLIGHT_PRESSURE_RANGE = (10_000.0, 115_000.0)


def baro_refusal(stamp: float, pressure: float, variance: float) -> str | None:
    """Why a pressure sample is refused (the detail of ``bad_pressure``), or None."""
    if not (math.isfinite(pressure) and math.isfinite(variance) and pressure > 0
            and variance >= 0 and math.isfinite(stamp)):
        return f" {pressure} Pa (variance {variance})"
    low, high = FLIGHT_PRESSURE_RANGE
    if not low <= pressure <= high:
        unit = " (hPa or mbar, not Pa?)" if 100.0 <= pressure <= 1150.0 else \
            " (kPa, not Pa?)" if 10.0 <= pressure <= 115.0 else ""
        return (f" {pressure:g} Pa: outside the {low / 1000:g}-{high / 1000:g} kPa of "
                f"flight{unit}")
    return None


class BaroOffset:
    """ENU up minus pressure altitude: set, or learnt once from the filter's own height.

    The offset is constant (what it gets wrong, the filter's baro-bias state takes up):
    ``fixed`` when finite, else
    learnt at the first sample after the filter's vertical sigma fell below ``max_sigma``
    (from GNSS, the initial pose or fixes), and forgotten after a time-jump reset.

    Parameters
    ----------
    fixed : float
        The offset (m); NaN to learn it.
    max_sigma : float
        Learn once the filter's vertical sigma is below this (m).
    """

    # s between a sample and the filter's time over which the offset is still learnt from
    # the filter's height carried along its vertical speed: a driver's latency of a few
    # tenths, not a sample from another clock
    MAX_LAG = 1.0

    def __init__(self, fixed: float, max_sigma: float):
        self.fixed = fixed
        self.max_sigma = max_sigma
        self.value = fixed if math.isfinite(fixed) else None

    def learn(self, stamp: float, altitude: float, ekf) -> bool:
        """Set the offset from ``ekf``'s estimate (a :class:`~.ekf.TerrainEkf`) at a baro
        sample of pressure altitude ``altitude`` if its height is known well enough and its
        time is within MAX_LAG of the sample's; returns whether the offset is known now."""
        if self.value is not None:
            return True
        if not ekf.initialized or abs(stamp - ekf.t) > self.MAX_LAG:
            return False
        if math.sqrt(ekf.state.covariance[2, 2]) > self.max_sigma:
            return False
        s = ekf.state
        self.value = float(s.position[2] + s.velocity[2] * (stamp - s.stamp)) - altitude
        return True

    def forget(self):
        """After a filter reset: learn again (a set offset stays)."""
        if not math.isfinite(self.fixed):
            self.value = None


class OriginHandshake:
    """The ENU origin from the metamap: the first georeference wins; a request for it that
    goes unanswered ``resend_after`` s is sent again.

    A request sent just as the metamap appears can be lost (the client sees the service
    before the service has matched the client, ros2/rclcpp#625).
    """

    def __init__(self, origin: EnuOrigin | None = None, resend_after: float = 5.0):
        self.origin = origin
        self.resend_after = resend_after
        self.asked_at = -math.inf

    def adopt(self, lat: float, lon: float, alt: float) -> bool:
        """Take this origin unless one is known; raises ValueError for an unusable one.
        Returns whether it was adopted."""
        if self.origin is not None:
            return False
        self.origin = EnuOrigin(lat, lon, alt)
        return True

    def request(self, now: float, pending: bool) -> str:
        """What to do about the request now: "done" (origin known), "wait" (an answer may
        still come), "resend" (the pending one is lost: drop it and ask again) or "send"."""
        if self.origin is not None:
            return "done"
        if pending:
            return "wait" if now - self.asked_at < self.resend_after else "resend"
        return "send"

    def sent(self, now: float):
        """A request went out at ``now``."""
        self.asked_at = now


class ImuConvention:
    """Checks an IMU stream's first ``window`` s against what the filter takes: specific
    force in m/s^2 in a z-up body frame (REP 103 FLU), where gravity reads about +g on z.

    A driver that publishes FRD / NED axes (-g on z), or the acceleration in g (about 1)
    or in milli-g (about 1000), would be integrated into an estimate kilometres and
    kilometres off within a minute, with nothing but gate rejections to show for it. Over
    the window the mean specific force of an aircraft at rest or in flight without negative
    load is within :data:`FORCE_RANGE` g of magnitude and within 60 deg of body z (in a
    coordinated turn it stays on z); anything else is the problem :meth:`add` returns, for
    good: a stream's convention does not change.

    Parameters
    ----------
    gravity : float
        The filter's gravity (m/s^2).
    window : float
        Seconds of samples judged.
    """

    FORCE_RANGE = (0.4, 4.0)

    def __init__(self, gravity: float, window: float = 1.0):
        self.gravity = gravity
        self.window = window
        self.problem: str | None = None
        self._first: float | None = None
        self._sum = np.zeros(3)
        self._count = 0
        self._judged = False

    def add(self, stamp: float, accel) -> str | None:
        """Take one sample's specific force; returns the problem once one is found."""
        if self._judged or not (math.isfinite(stamp) and np.isfinite(accel).all()):
            return self.problem
        self._first = stamp if self._first is None else self._first
        self._sum += accel
        self._count += 1
        if stamp - self._first >= self.window and self._count >= 10:
            self._judged = True
            self.problem = self._judge(self._sum / self._count)
        return self.problem

    def _judge(self, mean: np.ndarray) -> str | None:
        g = self.gravity
        size = float(np.linalg.norm(mean))
        low, high = self.FORCE_RANGE
        said = f"its mean specific force over the first {self.window:g} s is " \
               f"({mean[0]:.3g}, {mean[1]:.3g}, {mean[2]:.3g}) m/s^2"
        if size < low * g:
            unit = " (in g, not m/s^2?)" if low < size < high else ""
            return f"{said}, |f| {size:.3g}: far below gravity{unit}"
        if size > high * g:
            unit = " (in milli-g, not m/s^2?)" if low * 1000 < size < high * 1000 else ""
            return f"{said}, |f| {size:.3g}: far above gravity{unit}"
        if mean[2] < -0.5 * size:
            return (f"{said}: gravity reads down the body z axis, an FRD / NED frame (z down); "
                    "the filter takes FLU (REP 103: z up, +g on z at rest)")
        if mean[2] < 0.5 * size:
            return (f"{said}: gravity is not along body z; rotate the IMU's axes to base_link "
                    "(FLU, REP 103) in its driver or a transform")
        return None


class GyroScale:
    """Checks an IMU's rates against the turns its specific force tells, in rad/s.

    A gyro in deg/s reads 57 times its rates: in straight flight that is hidden in the
    noise, in the first turn the attitude spins 57 times too fast. Whatever the flight path
    bends with, its normal acceleration is the speed times the rate the path turns at:
    ``a_n = V |w|``. In a turn, coordinated or not, level or climbing, the body's rate is that
    turn rate, and the specific force ``f`` grows to ``|f|^2 = g^2 + a_n^2``. So over a turn
    ``V |w| / sqrt(|f|^2 - g^2)`` is about 1 (0.85-1.1 with 30 % wind, the ground speed
    standing in for the air speed) and about 57 for deg/s. A ratio over
    :attr:`MAX_RATIO` over the first :attr:`TURN_BLOCKS` half-seconds of a turn is the
    problem :meth:`add` returns, for good; :attr:`TURNS_TO_TRUST` turns under it settle the
    question. Roll rates into a turn and pull-ups keep the ratio within a few, far below.

    Parameters
    ----------
    gravity : float
        The filter's gravity (m/s^2).
    """

    BLOCK = 0.5             # s averaged: vibration out, a turn's rates kept
    MIN_TURN_FORCE = 1.5    # m/s^2 of normal acceleration: a bank of ~9 deg
    MIN_SPEED = 8.0         # m/s: below, the ratio says nothing
    TURN_BLOCKS = 6         # 3 s of turn judged
    MAX_RATIO = 15.0        # sqrt(57) * 2: rad/s and deg/s far on either side
    TURNS_TO_TRUST = 2

    def __init__(self, gravity: float):
        self.gravity = gravity
        self.problem: str | None = None
        self._trusted_turns = 0
        self._block_start: float | None = None
        self._gyro = np.zeros(3)
        self._accel = np.zeros(3)
        self._count = 0
        self._turn: list[tuple[float, float]] = []   # (V |w|, a_n) of the turn's blocks

    @property
    def _settled(self) -> bool:
        """A problem found, or enough turns trusted: no more checking."""
        return self.problem is not None or self._trusted_turns >= self.TURNS_TO_TRUST

    def add(self, stamp: float, gyro, accel,
            motion: Callable[[], tuple[float, np.ndarray] | None]) -> str | None:
        """Take one sample; returns the problem once one is found.

        ``motion`` gives the estimate's speed (m/s) and accelerometer bias (m/s^2, body), or
        None before there is an estimate; it is called once a block.
        """
        if self._settled or not (math.isfinite(stamp) and np.isfinite(gyro).all()
                                 and np.isfinite(accel).all()):
            return self.problem
        if self._block_start is None or not 0.0 <= stamp - self._block_start < 10 * self.BLOCK:
            self._start_block(stamp)
        self._gyro += gyro
        self._accel += accel
        self._count += 1
        if stamp - self._block_start >= self.BLOCK:
            self._close_block(motion())
            self._start_block(stamp)
        return self.problem

    def _start_block(self, stamp: float):
        self._block_start = stamp
        self._gyro[:] = 0.0
        self._accel[:] = 0.0
        self._count = 0

    def _close_block(self, motion):
        if motion is None or self._count == 0:
            self._turn.clear()
            return
        speed, accel_bias = motion
        rate = float(np.linalg.norm(self._gyro / self._count))
        force = float(np.linalg.norm(self._accel / self._count - accel_bias))
        normal = math.sqrt(max(force * force - self.gravity ** 2, 0.0))
        if speed < self.MIN_SPEED or normal < self.MIN_TURN_FORCE:
            self._turn.clear()
            return
        self._turn.append((speed * rate, normal))
        if len(self._turn) == self.TURN_BLOCKS:
            self._judge()

    def _judge(self):
        turning, normal = np.sum(self._turn, axis=0)
        ratio = turning / normal
        seconds = self.TURN_BLOCKS * self.BLOCK
        if ratio > self.MAX_RATIO:
            self.problem = (
                f"in a {seconds:g} s turn the gyro reads {ratio:.3g} times the turn rate its "
                f"normal acceleration and speed imply ({turning / len(self._turn):.3g} against "
                f"{normal / len(self._turn):.3g} m/s^2 on average, V |w| against a_n): rates "
                + ("in deg/s, not rad/s?" if 30 < ratio < 200 else "in another unit?"))
            return
        self._trusted_turns += 1
