"""When relocalisations agree: the filter's guard against one wrong mission-wide fix (ROS-free).

A relocalisation is a fix the matcher found by searching the whole mission area, independent
of the navigation estimate (``PvaFix.relocalisation``). One that the estimate's chi-square gate
accepts is fused like any fix; one it rejects is held here as a :class:`Candidate`. The filter
moves onto a relocalisation only when two of them, from frames at least ``min_interval`` apart,
agree with the motion between their stamps (:func:`agreement_nis`):

* once the filter runs, that motion is its own dead reckoning: the displacement of the
  estimate between the two stamps, with the covariance the IMU errors give it over that time
  (:func:`dead_reckoning_covariance`);
* before it runs (cold start), there is no dead reckoning: the displacement is tested
  against a speed prior (zero mean, ``speed_sigma`` per axis), which rules out pairs that no
  aircraft could fly between, not a wrong place found twice.

The test is chi-square with 3 degrees of freedom on the difference between the two
relocalisations' displacement and the predicted one, over the sum of both fixes' position
covariances and the prediction's. Candidates older than ``timeout`` (filter time) expire: the
dead-reckoning covariance grows with the cube of the interval, so old pairs test little.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .strapdown import IDX_BA, IDX_BG, IDX_TH, IDX_V, process_noise, quat_to_matrix, skew

__all__ = ["Candidate", "Found", "RelocalisationCandidates", "agreement_nis",
           "dead_reckoning_covariance"]


@dataclass(frozen=True)
class Candidate:
    """A relocalisation the filter holds until another agrees with it.

    Attributes
    ----------
    stamp : float
        Time of the fix (s).
    position : ndarray, (3,)
        Relocalised ENU position (m).
    covariance : ndarray, (3, 3)
        Its covariance (m^2).
    estimate : ndarray, (3,) or None
        The filter's position at ``stamp`` (None before the filter runs).
    state_covariance : ndarray, (23, 23) or None
        The filter's error covariance at ``stamp``.
    quaternion : ndarray, (4,) or None
        The filter's body -> ENU attitude at ``stamp``.
    measurement : object
        What the filter needs to act on the candidate later (its logged measurement).
    """

    stamp: float
    position: np.ndarray
    covariance: np.ndarray
    estimate: np.ndarray | None = None
    state_covariance: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    measurement: Any = None

    @property
    def dead_reckoned(self) -> bool:
        """True when the filter ran at the candidate's stamp."""
        return self.estimate is not None


@dataclass(frozen=True)
class Found:
    """The filter moved onto agreeing relocalisations.

    Attributes
    ----------
    stamp : float
        Stamp of the relocalisation it moved onto (s).
    jump : ndarray, (3,) or None
        New minus old position (ENU, m); None when it started from them (no estimate before).
    """

    stamp: float
    jump: np.ndarray | None = None

    def describe(self) -> str:
        """One line: when, and by how much the position jumped."""
        if self.jump is None:
            return f"started from agreeing relocalisations at {self.stamp:.3f} s"
        return (f"position reset onto agreeing relocalisations at {self.stamp:.3f} s: jumped "
                f"{float(np.hypot(self.jump[0], self.jump[1])):.0f} m horizontally, "
                f"{float(self.jump[2]):+.0f} m vertically")


def dead_reckoning_covariance(state_covariance: np.ndarray, quaternion, dt: float, gravity: float,
                              accel_noise_density: float,
                              gyro_noise_density: float) -> np.ndarray:
    """Covariance (3, 3) of the dead-reckoned displacement over ``dt`` from a state.

    Linearised error propagation of the strapdown solution in level, unaccelerated flight
    (specific force ``(0, 0, g)`` in ENU; turns are ignored): a displacement error
    ``dt dv - dt^2/2 ([a]x dtheta + C dba) + dt^3/6 [a]x C dbg`` from the velocity, attitude
    and bias errors at the start (their covariance ``state_covariance``), plus the
    accelerometer white noise (``dt^3/3``) and the gyro white noise through the tilt
    (``g^2 dt^5/20``). Position error at the start cancels in a displacement.

    Parameters
    ----------
    state_covariance : ndarray, (23, 23)
        Error covariance at the start, in the filter's state order.
    quaternion : array_like, (4,)
        Body -> ENU attitude at the start.
    dt : float
        Interval (s).
    gravity, accel_noise_density, gyro_noise_density : float
        As in :class:`~.ekf_params.EkfParams`.
    """
    a_skew = skew(np.array([0.0, 0.0, gravity]))
    C = quat_to_matrix(np.asarray(quaternion, float))
    J = np.zeros((3, state_covariance.shape[0]))
    J[:, IDX_V] = dt * np.eye(3)
    J[:, IDX_TH] = -0.5 * dt**2 * a_skew
    J[:, IDX_BA] = -0.5 * dt**2 * C
    J[:, IDX_BG] = dt**3 / 6.0 * a_skew @ C
    noise = process_noise(dt, 0.0, accel_noise_density, 0.0, 0.0)[:3, :3]
    noise += gyro_noise_density**2 * dt**5 / 20.0 * (a_skew @ a_skew.T)
    return J @ state_covariance @ J.T + noise


def agreement_nis(a: Candidate, b: Candidate, gravity: float, accel_noise_density: float,
                  gyro_noise_density: float, speed_sigma: float) -> float:
    """Chi-square (3 dof) of two relocalisations against the motion between their stamps.

    The residual is ``(p_b - p_a) - d``, where ``d`` is the dead-reckoned displacement when
    the filter ran at both stamps (zero, with the speed prior's covariance, when it did not);
    its covariance is both fixes' plus the prediction's.
    """
    first, second = sorted((a, b), key=lambda c: c.stamp)
    dt = second.stamp - first.stamp
    if first.dead_reckoned and second.dead_reckoned:
        predicted = second.estimate - first.estimate
        cov = dead_reckoning_covariance(first.state_covariance, first.quaternion, dt, gravity,
                                        accel_noise_density, gyro_noise_density)
    else:
        predicted = np.zeros(3)
        cov = np.eye(3) * (speed_sigma * dt) ** 2
    residual = (second.position - first.position) - predicted
    S = cov + first.covariance + second.covariance
    return float(residual @ np.linalg.solve(S, residual))


class RelocalisationCandidates:
    """The relocalisations held, and which of them a new one agrees with.

    Parameters
    ----------
    threshold : float
        Chi-square threshold (3 dof) of the agreement test.
    timeout : float
        A candidate expires this long after its stamp (s).
    motion : dict
        Keyword arguments of :func:`agreement_nis` besides the candidates (``gravity``,
        ``accel_noise_density``, ``gyro_noise_density``, ``speed_sigma``).
    """

    def __init__(self, threshold: float, timeout: float, **motion):
        self.threshold = threshold
        self.timeout = timeout
        self.motion = motion
        self._held: dict[Any, Candidate] = {}

    def __len__(self) -> int:
        return len(self._held)

    @property
    def held(self) -> list[Candidate]:
        """The candidates held, oldest stamp first."""
        return sorted(self._held.values(), key=lambda c: c.stamp)

    def hold(self, key, candidate: Candidate):
        """Hold ``candidate`` under ``key`` (the same key replaces: a re-evaluated fix)."""
        self._held[key] = candidate

    def discard(self, key):
        """Stop holding the candidate under ``key`` (a re-evaluated fix the gate took)."""
        self._held.pop(key, None)

    def expire(self, now: float):
        """Drop the candidates stamped more than ``timeout`` before ``now``."""
        for key in [k for k, c in self._held.items() if c.stamp < now - self.timeout]:
            del self._held[key]

    def clear(self):
        """Forget every candidate (after a reset or initialisation)."""
        self._held.clear()

    def agreeing(self, candidate: Candidate, min_interval: float) -> Candidate | None:
        """The held candidate that agrees best with ``candidate`` (lowest NIS under the
        threshold), among those at least ``min_interval`` s from it; None if none does."""
        best, best_nis = None, self.threshold
        for other in self._held.values():
            if abs(other.stamp - candidate.stamp) < max(min_interval, 1e-9):
                continue
            nis = agreement_nis(candidate, other, **self.motion)
            if nis <= best_nis:
                best, best_nis = other, nis
        return best
