"""Solar position (azimuth, elevation) from date, time and place, and the ENU sun vector.

The formulae are NOAA's solar calculator (the "NOAA Solar Calculations" spreadsheet of the
Global Monitoring Laboratory), a low-precision form of Meeus, *Astronomical Algorithms*
(ch. 25): geometric mean longitude and anomaly of the sun, equation of centre, apparent
longitude with the nutation/aberration term, corrected obliquity, declination and the
equation of time, then the local hour angle. They are evaluated vectorised in numpy.

Accuracy: Meeus gives about 0.01 deg for these low-precision solar coordinates within a few
centuries of 2000, i.e. a few hundredths of a degree in azimuth and elevation at most; on
the NREL SPA reference case (Reda & Andreas 2008: Golden, CO, 2003-10-17 12:30:30 -07:00)
this module is within 0.003 deg of SPA's azimuth and zenith (checked by the tests).
Refraction uses NOAA's piecewise standard-atmosphere model (~0.5 deg at the horizon, where
real refraction varies by tenths of a degree with the weather). ``Delta T`` (TT - UT, ~69 s) is
ignored, which costs < 0.001 deg. For terrain shading this is far below what matters.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

__all__ = ["parse_utc", "solar_position", "sun_at", "sun_direction_enu",
           "sun_direction_from_time", "sun_separation", "suns_over_window"]

_J2000 = 2451545.0
_UNIX_EPOCH_JD = 2440587.5


def parse_utc(text) -> _dt.datetime:
    """An aware datetime from ISO 8601 text (``2002-11-25T15:35:00Z``, an offset, or none:
    UTC); ValueError names the text when it is not ISO 8601."""
    try:
        t = _dt.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(f"time {text!r} is not ISO 8601 (e.g. 2002-11-25T15:35:00Z)") \
            from None
    return t if t.tzinfo else t.replace(tzinfo=_dt.UTC)


def _julian_day(when) -> np.ndarray:
    """Julian day (UT) of datetimes; naive datetimes and datetime64 are taken as UTC."""
    if isinstance(when, _dt.datetime):
        when = [when]
    if isinstance(when, (list, tuple)) and when and isinstance(when[0], _dt.datetime):
        # Aware datetimes are converted to UTC; numpy would reject or misread them.
        when = [w.astimezone(_dt.UTC).replace(tzinfo=None) if w.tzinfo else w
                for w in when]
    t = np.asarray(when, dtype="datetime64[us]")
    seconds = t.astype("int64") / 1e6
    return _UNIX_EPOCH_JD + seconds / 86400.0


def _refraction_deg(elev_deg: np.ndarray) -> np.ndarray:
    """NOAA's approximate atmospheric refraction (deg) for a true elevation (deg)."""
    e = np.asarray(elev_deg, dtype=float)
    te = np.tan(np.radians(np.clip(e, -89.0, 89.0)))
    high = 58.1 / te - 0.07 / te**3 + 0.000086 / te**5
    mid = 1735.0 + e * (-518.2 + e * (103.4 + e * (-12.79 + e * 0.711)))
    low = -20.774 / te
    arcsec = np.where(e > 5.0, high, np.where(e > -0.575, mid, low))
    return np.where(e > 85.0, 0.0, arcsec / 3600.0)


def solar_position(when, lat_deg, lon_deg, refraction: bool = True):
    """Solar azimuth and elevation seen from a place on Earth.

    Parameters
    ----------
    when : datetime.datetime, numpy.datetime64 or array of them
        Time of observation. Naive datetimes and datetime64 values are UTC; aware datetimes
        are converted to UTC.
    lat_deg, lon_deg : float or array_like
        Geodetic latitude (north positive) and longitude (east positive), degrees.
    refraction : bool, optional
        Add NOAA's standard-atmosphere refraction to the elevation (apparent sun).

    Returns
    -------
    azimuth_deg, elevation_deg : numpy.ndarray
        Azimuth clockwise from true north in [0, 360) and elevation above the horizon, degrees,
        broadcast over the inputs (0-d arrays for scalar input).
    """
    jd = _julian_day(when)
    if np.ndim(when) == 0 or isinstance(when, _dt.datetime):
        jd = jd.reshape(())
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.asarray(lon_deg, dtype=float)
    jc = (jd - _J2000) / 36525.0

    l0 = np.mod(280.46646 + jc * (36000.76983 + jc * 0.0003032), 360.0)
    m = np.radians(357.52911 + jc * (35999.05029 - 0.0001537 * jc))
    ecc = 0.016708634 - jc * (0.000042037 + 0.0000001267 * jc)
    centre = (np.sin(m) * (1.914602 - jc * (0.004817 + 0.000014 * jc))
              + np.sin(2 * m) * (0.019993 - 0.000101 * jc) + np.sin(3 * m) * 0.000289)
    omega = np.radians(125.04 - 1934.136 * jc)
    app_long = np.radians(l0 + centre - 0.00569 - 0.00478 * np.sin(omega))
    obliq0 = 23.0 + (26.0 + (21.448 - jc * (46.815 + jc * (0.00059 - jc * 0.001813))) / 60.0) / 60.0
    obliq = np.radians(obliq0 + 0.00256 * np.cos(omega))
    decl = np.arcsin(np.sin(obliq) * np.sin(app_long))

    y = np.tan(obliq / 2) ** 2
    l0r = np.radians(l0)
    eot_min = 4.0 * np.degrees(
        y * np.sin(2 * l0r) - 2 * ecc * np.sin(m) + 4 * ecc * y * np.sin(m) * np.cos(2 * l0r)
        - 0.5 * y * y * np.sin(4 * l0r) - 1.25 * ecc * ecc * np.sin(2 * m))

    minutes_utc = np.mod(jd - 0.5, 1.0) * 1440.0  # JD days start at noon
    true_solar_min = np.mod(minutes_utc + eot_min + 4.0 * lon, 1440.0)
    hour_angle = np.radians(true_solar_min / 4.0 - 180.0)

    sin_el = np.sin(lat) * np.sin(decl) + np.cos(lat) * np.cos(decl) * np.cos(hour_angle)
    elev = np.degrees(np.arcsin(np.clip(sin_el, -1.0, 1.0)))
    az = np.degrees(np.arctan2(-np.cos(decl) * np.sin(hour_angle),
                               np.sin(decl) * np.cos(lat)
                               - np.cos(decl) * np.cos(hour_angle) * np.sin(lat)))
    az = np.mod(az, 360.0)
    if refraction:
        elev = elev + _refraction_deg(elev)
    return az, elev


def sun_direction_enu(azimuth_deg, elevation_deg) -> np.ndarray:
    """Unit vector pointing from the ground towards the sun in local ENU.

    Parameters
    ----------
    azimuth_deg : float
        Clockwise from north, degrees.
    elevation_deg : float
        Above the horizon, degrees.

    Returns
    -------
    numpy.ndarray, shape (3,)
        (east, north, up) components.
    """
    az = np.radians(float(azimuth_deg))
    el = np.radians(float(elevation_deg))
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


def sun_separation(a, b) -> float:
    """Angle (degrees) between two sun positions given as (azimuth, elevation) in degrees."""
    cos = float(np.dot(sun_direction_enu(*a), sun_direction_enu(*b)))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def sun_at(unix_seconds: float, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(azimuth, elevation) in degrees at a POSIX time (a ROS stamp) and place."""
    when = _dt.datetime.fromtimestamp(float(unix_seconds), _dt.UTC)
    az, el = solar_position(when, lat_deg, lon_deg)
    return float(az), float(el)


def sun_direction_from_time(when, lat_deg: float, lon_deg: float,
                            refraction: bool = True) -> np.ndarray:
    """ENU unit vector towards the sun for one time and place (see :func:`solar_position`)."""
    az, el = solar_position(when, lat_deg, lon_deg, refraction=refraction)
    return sun_direction_enu(float(az), float(el))


def suns_over_window(start, hours: float, lat_deg: float, lon_deg: float, step_deg: float,
                     min_elevation: float = 5.0, sample_s: float = 60.0) -> np.ndarray:
    """Suns at most ``step_deg`` apart along the sun's path over a time window.

    The sun is sampled every ``sample_s`` seconds from ``start`` for ``hours``; samples
    below ``min_elevation`` are dropped (the landmark renderer then falls back to a fixed
    sun); the kept path is cut into equal arcs no longer than ``step_deg`` and the sun at
    each cut is returned, both ends included. Every sun of the window above
    ``min_elevation`` is thus within ``step_deg / 2`` (of path) of a returned one.

    Parameters
    ----------
    start : datetime.datetime
        Start of the window (naive: UTC).
    hours : float
        Length of the window, >= 0.
    lat_deg, lon_deg : float
        Where the sun is seen (degrees).
    step_deg : float
        Largest angle between consecutive suns (degrees), > 0.
    min_elevation : float
        Suns lower than this (degrees) are left out.
    sample_s : float
        Sampling period of the path (seconds).

    Returns
    -------
    ndarray, shape (n, 2)
        (azimuth, elevation) in degrees, in time order; n = 0 when the sun stays below
        ``min_elevation`` all window.
    """
    if not step_deg > 0 or not hours >= 0:
        raise ValueError(f"need step_deg > 0 and hours >= 0, got {step_deg}, {hours}")
    if isinstance(start, _dt.datetime) and start.tzinfo:
        start = start.astimezone(_dt.UTC).replace(tzinfo=None)
    seconds = np.arange(0.0, hours * 3600.0 + 0.5 * sample_s, sample_s)
    when = np.datetime64(start, "us") + (seconds * 1e6).astype("timedelta64[us]")
    az, el = solar_position(when, lat_deg, lon_deg)
    keep = el >= min_elevation
    if keep.sum() < 2:
        return np.column_stack([az[keep], el[keep]])
    a, e = np.radians(az[keep]), np.radians(el[keep])
    unit = np.column_stack([np.sin(a) * np.cos(e), np.cos(a) * np.cos(e), np.sin(e)])
    steps = np.degrees(np.arccos(np.clip((unit[1:] * unit[:-1]).sum(axis=1), -1.0, 1.0)))
    path = np.r_[0.0, np.cumsum(steps)]
    n = max(int(np.ceil(path[-1] / step_deg - 1e-9)), 1) + 1
    # the time of each cut along the path (the sun is smooth between samples), then its sun
    cut_s = np.interp(np.linspace(0.0, path[-1], n), path, seconds[keep])
    az, el = solar_position(np.datetime64(start, "us") + (cut_s * 1e6).astype("timedelta64[us]"),
                            lat_deg, lon_deg)
    keep = el >= min_elevation   # a cut inside a night the window spans
    return np.column_stack([az[keep], el[keep]])
