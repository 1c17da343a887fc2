"""Deterministic aircraft trajectories with consistent truth and IMU kinematics.

A flight is a list of :class:`Segment` commands (duration, turn rate, flight-path angle) at a
constant airspeed. Commands change smoothly (raised-cosine ramps) so body rates stay finite.
From the commands the simulator builds, on the IMU time grid:

* heading ``psi`` (counter-clockwise from East) by integrating the turn rate;
* ENU velocity ``V [cos g cos psi, cos g sin psi, sin g]`` with flight-path angle ``g``;
* position as the trapezoidal integral of velocity;
* attitude ``Rz(psi) Ry(-g) Rx(phi)`` with zero angle of attack and sideslip, and the bank of
  a coordinated turn (zero lateral specific force; about ``atan(-V psi' / g0)`` when level, so
  a right turn gives right wing down, ``phi > 0`` in FLU);
* ideal IMU angular rate and specific force by :func:`~.estimation.strapdown.inverse_mechanisation`,
  so that integrating them with the filter's mechanisation reproduces the truth exactly.

Everything is vectorised over time; nothing is random here (noise lives in
:mod:`terrain_nav_ros.core.sim.imu_sim`). The same truth is meant to drive the flight simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..estimation.strapdown import GRAVITY, inverse_mechanisation, quat_from_euler


@dataclass(frozen=True)
class Segment:
    """One commanded flight leg.

    Parameters
    ----------
    duration : float
        Length of the leg (s), > 0.
    turn_rate : float
        Heading rate (rad/s), positive = left turn (counter-clockwise seen from above).
    flight_path_angle : float
        Climb angle (rad), positive = climbing.
    """

    duration: float
    turn_rate: float = 0.0
    flight_path_angle: float = 0.0


@dataclass(frozen=True)
class Truth:
    """Truth states and ideal IMU on a regular time grid (all arrays share axis 0).

    Attributes
    ----------
    t : ndarray, (N,)
        Time (s).
    position, velocity : ndarray, (N, 3)
        ENU position (m) and velocity (m/s).
    quaternion : ndarray, (N, 4)
        Body -> ENU attitude ``[x, y, z, w]``.
    gyro, accel : ndarray, (N, 3)
        Ideal body angular rate (rad/s) and specific force (m/s^2); sample ``k`` acts over
        ``(t[k-1], t[k]]``.
    """

    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def in_wind(self, east: float, north: float) -> Truth:
        """The same flight through air that moves at ``(east, north)`` (m/s): the ground track
        drifts with it, while the attitude (the nose along the air velocity, no sideslip)
        and the IMU stay, as a constant wind changes no acceleration."""
        wind = np.array([east, north, 0.0])
        return replace(self, position=self.position + self.t[:, None] * wind,
                       velocity=self.velocity + wind)

    def at(self, times) -> np.ndarray:
        """Indices of the grid epochs nearest to ``times`` (s)."""
        idx = np.searchsorted(self.t, np.asarray(times, dtype=float))
        idx = np.clip(idx, 1, len(self.t) - 1)
        left_closer = np.abs(self.t[idx - 1] - times) <= np.abs(self.t[idx] - times)
        return np.where(left_closer, idx - 1, idx)


def _smooth_schedule(t, segments, values, ramp):
    """Piecewise-constant ``values`` per segment, with raised-cosine ramps of ``ramp`` s."""
    starts = np.cumsum([0.0] + [s.duration for s in segments[:-1]])
    vals = np.asarray(values, dtype=float)
    out = np.full_like(t, vals[0])
    if len(vals) > 1 and ramp > 0:
        # Ramp centred on each boundary; (N, n_boundaries) is small enough to vectorise.
        u = np.clip((t[:, None] - starts[1:] + 0.5 * ramp) / ramp, 0.0, 1.0)
        out = out + (0.5 - 0.5 * np.cos(np.pi * u)) @ np.diff(vals)
    elif len(vals) > 1:
        out = out + (t[:, None] >= starts[1:]) @ np.diff(vals)
    return out


def _cumtrapz(y, dt):
    """Cumulative trapezoid along axis 0 starting at 0 (regular grid)."""
    out = np.zeros_like(y)
    out[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * dt, axis=0)
    return out


def _coordinated_bank(heading, gamma, turn_rate, gamma_rate, speed, gravity):
    """Bank angle that puts the specific force in the body x-z plane (no sideslip force).

    With body x along the velocity, ``y0`` the horizontal left axis and ``z0 = x0 x y0``,
    the body y axis after banking by ``phi`` is ``cos(phi) y0 + sin(phi) z0``; zero lateral
    specific force gives ``phi = atan2(-f.y0, f.z0)`` with ``f = a + g z_up``.
    """
    cg = np.cos(gamma)
    f_y0 = speed * cg * turn_rate              # lateral (centripetal) acceleration
    f_z0 = speed * gamma_rate + gravity * cg   # normal acceleration plus gravity component
    return np.arctan2(-f_y0, f_z0)


def simulate_trajectory(segments, rate_hz: float = 200.0, speed: float = 30.0,
                        start_position=(0.0, 0.0, 500.0), start_heading: float = 0.0,
                        ramp_s: float = 4.0, gravity: float = GRAVITY) -> Truth:
    """Truth and ideal IMU for a sequence of commanded legs.

    Parameters
    ----------
    segments : sequence of Segment
        Flight legs flown back to back.
    rate_hz : float
        IMU rate (Hz); the grid is ``t = k / rate_hz``.
    speed : float
        Constant airspeed = ground speed (m/s, no wind).
    start_position : array_like, (3,)
        ENU position at t = 0 (m).
    start_heading : float
        Initial heading (rad, counter-clockwise from East).
    ramp_s : float
        Duration of the smooth transition between legs (s).
    gravity : float
        Gravity used for the coordinated-turn bank and the specific force (m/s^2).

    Returns
    -------
    Truth
    """
    segments = list(segments)
    if not segments:
        raise ValueError("simulate_trajectory: need at least one segment")
    dt = 1.0 / rate_hz
    n = int(round(sum(s.duration for s in segments) * rate_hz)) + 1
    t = np.arange(n) * dt
    turn_rate = _smooth_schedule(t, segments, [s.turn_rate for s in segments], ramp_s)
    gamma = _smooth_schedule(t, segments, [s.flight_path_angle for s in segments], ramp_s)
    heading = start_heading + _cumtrapz(turn_rate, dt)
    cg = np.cos(gamma)
    velocity = speed * np.stack([cg * np.cos(heading), cg * np.sin(heading), np.sin(gamma)], -1)
    position = np.asarray(start_position, dtype=float) + _cumtrapz(velocity, dt)
    bank = _coordinated_bank(heading, gamma, turn_rate, np.gradient(gamma, dt), speed, gravity)
    quaternion = quat_from_euler(bank, -gamma, heading)
    gyro, accel = inverse_mechanisation(t, velocity, quaternion, gravity)
    return Truth(t, position, velocity, quaternion, gyro, accel)


# --------------------------------------------------------------------------------------
# Canned scenarios used by tests, benchmarks and the flight simulator
# --------------------------------------------------------------------------------------

def straight_flight(duration: float = 120.0) -> list[Segment]:
    """Straight and level."""
    return [Segment(duration)]


def turning_flight(duration: float = 120.0, turn_rate: float = np.deg2rad(3.0)) -> list[Segment]:
    """Alternating left and right standard-rate-ish turns (S-turns), 30 s per leg."""
    n = max(1, int(round(duration / 30.0)))
    return [Segment(duration / n, turn_rate * (1 if i % 2 == 0 else -1)) for i in range(n)]


def climbing_flight(duration: float = 120.0, angle: float = np.deg2rad(5.0)) -> list[Segment]:
    """Climb, level, descend, level, in equal parts, with a gentle turn while climbing."""
    q = duration / 4.0
    return [Segment(q, np.deg2rad(1.5), angle), Segment(q), Segment(q, 0.0, -angle), Segment(q)]


def survey_flight(duration: float = 600.0, leg_s: float = 60.0) -> list[Segment]:
    """Lawn-mower survey: straight legs joined by 180-degree turns at 6 deg/s (30 s each).

    Includes a climb and a descent so all axes are exercised.
    """
    turn = np.deg2rad(6.0)
    segs: list[Segment] = []
    elapsed, sign = 0.0, 1.0
    while elapsed < duration - 1e-9:
        climb = np.deg2rad(3.0) * (1 if len(segs) % 8 == 0 else -1 if len(segs) % 8 == 4 else 0)
        for seg in (Segment(leg_s, 0.0, climb), Segment(np.pi / turn, sign * turn)):
            d = min(seg.duration, duration - elapsed)
            if d > 1e-9:
                segs.append(Segment(d, seg.turn_rate, seg.flight_path_angle))
                elapsed += d
        sign = -sign
    return segs
