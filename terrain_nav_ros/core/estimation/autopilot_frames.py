"""Frame conventions of the autopilots: REP 103 (ENU / FLU) to and from PX4's NED / FRD.

ROS (REP 103, what every terrain_nav node uses):

* world frame East-North-Up (ENU), body frame x forward, y left, z up (FLU);
* quaternions ``[x, y, z, w]`` rotating body vectors into the world frame;
* the rotational part of a pose covariance is about the fixed (world) axes, twist
  covariances are in the body frame (REP 105: the twist is in ``child_frame_id``).

PX4 (``px4_msgs/VehicleOdometry``):

* world frame North-East-Down (NED), body frame x forward, y right, z down (FRD);
* quaternions ``[w, x, y, z]`` (scalar first) rotating FRD vectors into NED;
* timestamps in integer microseconds.

Both changes of axes are proper rotations (determinant +1), so rotation vectors, angular
rates and covariances transform like ordinary vectors:

* ``ENU -> NED``: swap x and y, negate z (a half turn about the horizontal axis halfway between
  east and north);
* ``FLU -> FRD``: negate y and z (a half turn about x).

Each is its own inverse. The attitude relation is
``R_ned_frd = R_NED_ENU @ R_enu_flu @ R_FLU_FRD``. MAVROS takes ENU / FLU as it is and does this
conversion itself, so only PX4's direct uXRCE-DDS bridge needs it.

Everything here is vectorised over leading axes where noted, and free of ROS imports.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

R_NED_ENU = np.array([[0.0, 1.0, 0.0],
                      [1.0, 0.0, 0.0],
                      [0.0, 0.0, -1.0]])
"""Rotation taking ENU world vectors to NED (and NED to ENU: it is its own inverse)."""

R_FLU_FRD = np.diag([1.0, -1.0, -1.0])
"""Rotation taking FRD body vectors to FLU (and FLU to FRD: it is its own inverse)."""


def _apply(matrix: np.ndarray, v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.shape[-1] != 3:
        raise ValueError(f"vectors need 3 components, got shape {v.shape}")
    return v @ matrix.T


def enu_to_ned(v) -> np.ndarray:
    """World vectors (positions, velocities, rotation vectors) from ENU to NED, or back.

    The change of axes is its own inverse, so :func:`ned_to_enu` is this same function.

    Parameters
    ----------
    v : array_like, shape (..., 3)
        East, north, up components (or north, east, down).

    Returns
    -------
    ndarray, shape (..., 3)
        North, east, down components (or east, north, up).
    """
    return _apply(R_NED_ENU, v)


def flu_to_frd(v) -> np.ndarray:
    """Body vectors (velocities, angular rates) from FLU to FRD, or back.

    The change of axes is its own inverse, so :func:`frd_to_flu` is this same function.

    Parameters
    ----------
    v : array_like, shape (..., 3)
        Forward, left, up components (or forward, right, down).

    Returns
    -------
    ndarray, shape (..., 3)
        Forward, right, down components (or forward, left, up).
    """
    return _apply(R_FLU_FRD, v)


ned_to_enu = enu_to_ned
frd_to_flu = flu_to_frd


def quaternion_enu_flu_to_ned_frd(q_xyzw) -> np.ndarray:
    """Attitude FLU -> ENU as a ROS quaternion to FRD -> NED as a PX4 quaternion.

    Parameters
    ----------
    q_xyzw : array_like, shape (..., 4)
        Unit quaternion ``[x, y, z, w]`` rotating FLU body vectors into ENU.

    Returns
    -------
    ndarray, shape (..., 4)
        Unit quaternion ``[w, x, y, z]`` rotating FRD body vectors into NED, with ``w >= 0``.

    Examples
    --------
    A level aircraft with its nose to the north has a ROS yaw of +90 deg and the identity as
    PX4 attitude:

    >>> q = quaternion_enu_flu_to_ned_frd([0.0, 0.0, 2 ** -0.5, 2 ** -0.5])
    >>> np.allclose(q, [1.0, 0.0, 0.0, 0.0])
    True
    """
    r = Rotation.from_matrix(R_NED_ENU @ Rotation.from_quat(q_xyzw).as_matrix() @ R_FLU_FRD)
    x, y, z, w = np.moveaxis(r.as_quat(), -1, 0)
    q = np.stack([w, x, y, z], axis=-1)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_ned_frd_to_enu_flu(q_wxyz) -> np.ndarray:
    """Attitude FRD -> NED as a PX4 quaternion to FLU -> ENU as a ROS quaternion.

    Parameters
    ----------
    q_wxyz : array_like, shape (..., 4)
        Unit quaternion ``[w, x, y, z]`` rotating FRD body vectors into NED.

    Returns
    -------
    ndarray, shape (..., 4)
        Unit quaternion ``[x, y, z, w]`` rotating FLU body vectors into ENU, with ``w >= 0``.
    """
    q = np.asarray(q_wxyz, dtype=float)
    r = Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))
    out = Rotation.from_matrix(R_NED_ENU @ r.as_matrix() @ R_FLU_FRD).as_quat()
    return np.where(out[..., 3:] < 0, -out, out)


def rotate_covariance(cov, rotation) -> np.ndarray:
    """A 3x3 covariance, or each 3x3 block of a 6x6 one, expressed in rotated axes.

    Parameters
    ----------
    cov : array_like, shape (3, 3) or (6, 6)
        Covariance of a vector (3x3), or of two stacked vectors such as position and rotation
        of a pose, or linear and angular velocity of a twist (6x6, cross terms included).
    rotation : array_like, shape (3, 3)
        Rotation matrix ``R`` with ``v_new = R @ v_old`` for both vectors.

    Returns
    -------
    ndarray
        ``R C R^T`` for 3x3, ``blkdiag(R, R) C blkdiag(R, R)^T`` for 6x6.
    """
    cov = np.asarray(cov, dtype=float)
    r = np.asarray(rotation, dtype=float)
    if cov.shape == (6, 6):
        r = np.block([[r, np.zeros((3, 3))], [np.zeros((3, 3)), r]])
    elif cov.shape != (3, 3):
        raise ValueError(f"covariance must be 3x3 or 6x6, got {cov.shape}")
    return r @ cov @ r.T


def covariance_enu_to_ned(cov) -> np.ndarray:
    """World-axis covariance (position, velocity, or a pose's position + rotation about the
    world axes) from ENU to NED; its own inverse. See :func:`rotate_covariance`."""
    return rotate_covariance(cov, R_NED_ENU)


def covariance_flu_to_frd(cov) -> np.ndarray:
    """Body-axis covariance (a twist's, REP 105) from FLU to FRD; its own inverse.
    See :func:`rotate_covariance`."""
    return rotate_covariance(cov, R_FLU_FRD)


def body_to_world_covariance(cov, q_xyzw) -> np.ndarray:
    """A body-frame 3x3 covariance (FLU) in world axes (ENU) at attitude ``q_xyzw``.

    Parameters
    ----------
    cov : array_like, shape (3, 3)
        Covariance in the body axes, e.g. of the twist's linear velocity.
    q_xyzw : array_like, shape (4,)
        Body -> world quaternion ``[x, y, z, w]``.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    return rotate_covariance(cov, Rotation.from_quat(q_xyzw).as_matrix())


def ns_to_px4_us(ns: int) -> int:
    """Nanoseconds (ROS time) to PX4's integer microseconds, rounded down.

    Parameters
    ----------
    ns : int
        Time in nanoseconds (``builtin_interfaces/Time`` as one integer).

    Returns
    -------
    int
        Microseconds; 0 for times before 0 (PX4's "unknown").
    """
    return max(int(ns) // 1000, 0)


def px4_us_to_ns(us: int) -> int:
    """PX4 microseconds to nanoseconds (exact)."""
    return int(us) * 1000


class RateLimiter:
    """Let samples through at no more than a given rate, on the samples' own clock.

    A sample passes when its time reaches the next due time; the due times advance by one
    period from the previous one, so a 50 Hz input limited to 30 Hz averages 30 Hz (not the
    25 Hz of "at least one period since the last"). After a gap, or when time goes backwards
    (a bag loop), the schedule restarts at the sample. Never faster than the input.

    Parameters
    ----------
    rate : float
        Largest rate [Hz]; 0 or less lets everything through.
    tolerance : float
        Slack on the due time [s], for stamps carried as float seconds.
    """

    def __init__(self, rate: float, tolerance: float = 1e-6):
        self.period = 1.0 / rate if rate > 0 else 0.0
        self.tolerance = tolerance
        self._due: float | None = None
        self._last: float | None = None

    def reset(self) -> None:
        """Forget the schedule: the next sample passes."""
        self._due = self._last = None

    def ready(self, t: float) -> bool:
        """Whether the sample at time ``t`` [s] passes (and, if so, the schedule moves on)."""
        if self._last is not None and t < self._last:
            self.reset()
        if self._due is not None and t < self._due - self.tolerance:
            return False
        if self._due is None or t - self._due >= self.period:
            self._due = t + self.period          # first sample, or after a gap
        else:
            self._due += self.period
        self._last = t
        return True


# Estimate times this close are the same estimate's (stamps carried as float seconds) [s].
_SAME_TIME = 1e-6


class ResetCounter:
    """PX4's ``reset_counter``: a uint8 that moves on whenever the estimate jumps.

    The consumer (PX4 EKF2) resets its external-vision states instead of rejecting the new
    data when the counter changes, so it must change on the first estimate after a
    discontinuity, and only then (each change is a reset in EKF2). It moves on:

    * when consecutive estimates jump by more than ``jump_threshold`` beyond what the
      velocity explains (:meth:`observe_pose`; a relocalisation by a fix);
    * when they are more than ``max_gap`` apart in estimate time (nothing vouches for the
      estimate's continuity across a gap: a respawned filter resuming from its checkpoint,
      output held back for a while), or time runs backwards (a new clock);
    * when the source filter counts a reset (:meth:`observe_filter_resets`) that no jump or
      gap at or after its stamp has already announced (a filter reports its resets beside
      its estimates, in diagnostics, which may come before or after the estimate after the
      reset: the one counter change serves both);
    * on :meth:`bump`.

    Parameters
    ----------
    jump_threshold : float
        Position step beyond the velocity prediction that counts as a reset [m]; 0 disables
        the check.
    max_gap : float
        Largest estimate-time step between consecutive estimates that is not a reset [s];
        0 disables the check.
    """

    def __init__(self, jump_threshold: float = 0.0, max_gap: float = 0.0):
        self.jump_threshold = jump_threshold
        self.max_gap = max_gap
        self.value = 0
        self.count = 0
        self._filter_resets: int | None = None
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None
        self._bumped_at: float | None = None   # estimate time of the last bump by a pose
        self._announced: float | None = None   # a filter reset counted before its estimate

    def bump(self) -> int:
        """Move the counter on (wrapping at 256); return the new value."""
        self.count += 1
        self.value = (self.value + 1) % 256
        return self.value

    def observe_filter_resets(self, total: int, at: float | None = None) -> bool:
        """Take the source's running count of resets, the last of them at estimate time
        ``at`` (None or NaN: unknown); bump if it grew, unless a jump or gap at or after
        ``at`` already did. A count that drops is a new filter process, announced by the
        gap before its first estimate (with ``max_gap`` set). True if bumped."""
        previous, self._filter_resets = self._filter_resets, int(total)
        if previous is None or self._filter_resets == previous:
            return False
        if self._filter_resets < previous and self.max_gap > 0:
            return False
        if at is not None and math.isfinite(at):
            if self._bumped_at is not None and self._bumped_at >= at - _SAME_TIME:
                return False
            if self._last is None or self._last[0] < at - _SAME_TIME:
                self._announced = at   # its estimate is still to come: no second bump then
        self.bump()
        return True

    def observe_pose(self, t: float, position, velocity) -> bool:
        """Take one estimate; bump if it jumped, came after a gap, or time ran backwards.
        True if bumped."""
        position = np.asarray(position, dtype=float)
        velocity = np.asarray(velocity, dtype=float)
        last, self._last = self._last, (t, position, velocity)
        if last is None:
            return False
        t0, p0, v0 = last
        dt = t - t0
        jumped = dt < 0 or (self.max_gap > 0 and dt > self.max_gap)
        if not jumped and self.jump_threshold > 0:
            predicted = p0 + 0.5 * (v0 + velocity) * dt
            jumped = float(np.linalg.norm(position - predicted)) > self.jump_threshold
        if self._announced is not None and t >= self._announced - _SAME_TIME:
            self._announced = None   # the filter's reset, already counted
            return False
        if jumped:
            self.bump()
            self._bumped_at = t
        return bool(jumped)


def horizontal_accuracy(cov_enu) -> float:
    """1-sigma horizontal accuracy [m] of a 3x3 ENU position covariance: the square root of
    the larger eigenvalue of its horizontal block (the long axis of the error ellipse)."""
    cov = np.asarray(cov_enu, dtype=float)[:2, :2]
    return math.sqrt(max(float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[-1]), 0.0))
