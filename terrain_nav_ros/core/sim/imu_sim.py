"""Seeded sensor error models on top of a :class:`~.trajectory_sim.Truth`.

* IMU: white noise + turn-on bias + bias random walk, per axis, with the same densities the
  EKF takes as parameters (so a filter tuned with the simulator's numbers is consistent).
* Position fixes: Gaussian noise with a given covariance, a fraction of gross outliers
  displaced horizontally by a fixed distance in a random direction, optional attitude.
* Barometric altitude: Gaussian noise on the ENU up coordinate.

All generators take a ``numpy.random.Generator`` so runs are reproducible, and are vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..estimation.strapdown import quat_exp, quat_multiply
from .trajectory_sim import Truth


@dataclass(frozen=True)
class ImuErrorModel:
    """Per-axis IMU error parameters (same meaning and units as in ``EkfParams``).

    Parameters
    ----------
    gyro_noise_density : float
        Angle random walk, rad/s/sqrt(Hz).
    accel_noise_density : float
        Velocity random walk, m/s^2/sqrt(Hz).
    gyro_bias_random_walk : float
        Gyro bias random walk, rad/s^2/sqrt(Hz).
    accel_bias_random_walk : float
        Accelerometer bias random walk, m/s^3/sqrt(Hz).
    gyro_bias_sigma : float
        Standard deviation of the turn-on gyro bias (rad/s).
    accel_bias_sigma : float
        Standard deviation of the turn-on accelerometer bias (m/s^2).
    """

    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_random_walk: float
    accel_bias_random_walk: float
    gyro_bias_sigma: float
    accel_bias_sigma: float

    @classmethod
    def from_params(cls, params) -> ImuErrorModel:
        """Model matching an ``EkfParams`` (noise densities and initial bias sigmas)."""
        return cls(params.gyro_noise_density, params.accel_noise_density,
                   params.gyro_bias_random_walk, params.accel_bias_random_walk,
                   params.init_gyro_bias_sigma, params.init_accel_bias_sigma)


@dataclass(frozen=True)
class ImuData:
    """Measured IMU samples and the biases that were in them (truth for tests).

    Attributes
    ----------
    t : ndarray, (N,)
    gyro, accel : ndarray, (N, 3)
        Measured angular rate (rad/s) and specific force (m/s^2).
    gyro_bias, accel_bias : ndarray, (N, 3)
        True biases contained in each sample.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def _bias_walk(rng, n, dt, sigma0, rw):
    """Turn-on bias plus random walk: (n, 3)."""
    steps = rng.normal(0.0, rw * np.sqrt(dt), size=(n, 3))
    steps[0] = rng.normal(0.0, sigma0, size=3)
    return np.cumsum(steps, axis=0)


def simulate_imu(truth: Truth, model: ImuErrorModel, rng: np.random.Generator,
                 gyro_bias=None, accel_bias=None) -> ImuData:
    """Corrupt the ideal IMU of ``truth`` with noise, turn-on bias and bias random walk.

    Parameters
    ----------
    truth : Truth
        Regular time grid with ideal ``gyro`` and ``accel``.
    model : ImuErrorModel
        Error densities.
    rng : numpy.random.Generator
        Source of randomness.
    gyro_bias, accel_bias : array_like, (3,), optional
        Fixed turn-on biases instead of drawing them from the model's sigmas.

    Returns
    -------
    ImuData
    """
    n = len(truth)
    dt = float(truth.t[1] - truth.t[0])
    bg = _bias_walk(rng, n, dt, model.gyro_bias_sigma, model.gyro_bias_random_walk)
    ba = _bias_walk(rng, n, dt, model.accel_bias_sigma, model.accel_bias_random_walk)
    if gyro_bias is not None:
        bg += np.asarray(gyro_bias, dtype=float) - bg[0]
    if accel_bias is not None:
        ba += np.asarray(accel_bias, dtype=float) - ba[0]
    gyro = truth.gyro + bg + rng.normal(0.0, model.gyro_noise_density / np.sqrt(dt), (n, 3))
    accel = truth.accel + ba + rng.normal(0.0, model.accel_noise_density / np.sqrt(dt), (n, 3))
    return ImuData(truth.t.copy(), gyro, accel, bg, ba)


@dataclass(frozen=True)
class FixData:
    """Simulated position (and optionally attitude) fixes.

    Attributes
    ----------
    t : ndarray, (M,)
        Stamps (s), on the truth grid.
    position : ndarray, (M, 3)
        Measured ENU position (m).
    covariance : ndarray, (M, k, k)
        Covariance reported with each fix: position (3x3), or position then attitude (6x6).
    attitude : ndarray, (M, 4) or None
        Measured body -> ENU quaternion, when simulated.
    outlier : ndarray of bool, (M,)
        True for gross outliers (their covariance does not cover the error).
    index : ndarray of int, (M,)
        Index of each fix on the truth grid.
    """

    t: np.ndarray
    position: np.ndarray
    covariance: np.ndarray
    attitude: np.ndarray | None
    outlier: np.ndarray
    index: np.ndarray


def simulate_fixes(truth: Truth, rng: np.random.Generator, period: float = 2.0,
                   sigma: float = 20.0, vertical_sigma: float | None = None,
                   outlier_rate: float = 0.0, outlier_offset: float = 500.0,
                   attitude_sigma: float | None = None, start: float | None = None) -> FixData:
    """Noisy fixes every ``period`` seconds with a fraction of gross outliers.

    Parameters
    ----------
    truth : Truth
    rng : numpy.random.Generator
    period : float
        Time between fixes (s).
    sigma : float
        Horizontal standard deviation per axis (m).
    vertical_sigma : float, optional
        Vertical standard deviation (m); defaults to ``sigma``.
    outlier_rate : float
        Probability that a fix is a gross outlier.
    outlier_offset : float
        Horizontal displacement of outliers (m), in a uniformly random direction.
    attitude_sigma : float, optional
        If given, fixes also carry attitude with this per-axis error (rad, ENU axes).
    start : float, optional
        First fix time (s); defaults to one period after the start of ``truth``.

    Returns
    -------
    FixData
    """
    t0 = truth.t[0] + period if start is None else start
    idx = truth.at(np.arange(t0, truth.t[-1] + 1e-9, period))
    m = len(idx)
    sd = np.array([sigma, sigma, sigma if vertical_sigma is None else vertical_sigma])
    pos = truth.position[idx] + rng.normal(size=(m, 3)) * sd
    outlier = rng.random(m) < outlier_rate
    ang = rng.uniform(0.0, 2.0 * np.pi, m)
    pos[outlier, :2] += outlier_offset * np.stack([np.cos(ang), np.sin(ang)], -1)[outlier]
    var = list(sd**2)
    att = None
    if attitude_sigma is not None:
        err = rng.normal(0.0, attitude_sigma, size=(m, 3))
        att = quat_multiply(quat_exp(err), truth.quaternion[idx])
        var += [attitude_sigma**2] * 3
    cov = np.broadcast_to(np.diag(var), (m, len(var), len(var))).copy()
    return FixData(truth.t[idx], pos, cov, att, outlier, idx)


def simulate_baro(truth: Truth, rng: np.random.Generator, period: float = 0.1,
                  sigma: float = 1.5):
    """Barometric altitude (ENU up, m) every ``period`` s with white noise ``sigma`` (m).

    Returns
    -------
    t, altitude : ndarray, (M,)
    index : ndarray of int, (M,)
        Indices on the truth grid.
    """
    idx = truth.at(np.arange(truth.t[0] + period, truth.t[-1] + 1e-9, period))
    return truth.t[idx], truth.position[idx, 2] + rng.normal(0.0, sigma, len(idx)), idx
