"""Pressure altitude in the ICAO standard atmosphere (troposphere, below 11 km).

Barometers report static pressure (``sensor_msgs/FluidPressure``, Pa); the EKF wants an
altitude. Both directions use the same standard-atmosphere constants so the simulator and the
filter agree; the unknown sea-level pressure of the day is the filter's baro bias to absorb.
"""

from __future__ import annotations

import numpy as np

SEA_LEVEL_PRESSURE = 101_325.0   # Pa
_LAPSE_RATE = 0.0065              # K/m
_SEA_LEVEL_TEMPERATURE = 288.15   # K
_EXPONENT = 5.255877              # g M / (R L)


def altitude_to_pressure(altitude, sea_level_pressure: float = SEA_LEVEL_PRESSURE):
    """Static pressure (Pa) at a geopotential altitude (m)."""
    ratio = 1.0 - _LAPSE_RATE * np.asarray(altitude, float) / _SEA_LEVEL_TEMPERATURE
    return sea_level_pressure * ratio ** _EXPONENT


def pressure_to_altitude(pressure, sea_level_pressure: float = SEA_LEVEL_PRESSURE):
    """Pressure altitude (m) of a static pressure (Pa)."""
    ratio = (np.asarray(pressure, float) / sea_level_pressure) ** (1.0 / _EXPONENT)
    return _SEA_LEVEL_TEMPERATURE / _LAPSE_RATE * (1.0 - ratio)


def altitude_sigma(pressure_sigma: float, pressure: float) -> float:
    """Altitude standard deviation (m) for a pressure standard deviation (Pa) at ``pressure``."""
    dp = 1.0
    slope = abs(float(pressure_to_altitude(pressure + dp) - pressure_to_altitude(pressure)))
    return pressure_sigma * slope / dp
