"""Mission ENU frame: WGS84 geodetic <-> local East-North-Up, and DEM CRS <-> ENU.

The mission's ``map`` frame (REP 103/105) is the local tangent plane at an :class:`EnuOrigin`:
x east, y north, z up along the WGS84 ellipsoid normal at the origin, metres. The conversion
goes exactly through Earth-centred Earth-fixed (ECEF) coordinates with PROJ's ``cart`` and
``topocentric`` operations, so round trips are exact to floating-point precision (sub-micrometre).

Height datums (say what you have; they differ by tens of metres):

* ``EnuOrigin.alt`` and every geodetic ``h`` here are **WGS84 ellipsoidal heights**, as in
  ``sensor_msgs/NavSatFix.altitude``.
* DEM values are **orthometric** heights, metres above the geoid: SRTM is referenced to EGM96,
  USGS NED/3DEP to NAVD88. ``h = H + N`` with ``N`` the geoid undulation (EGM96 N is between
  about -106 m and +85 m worldwide). Offline PROJ ships no geoid grid, so the mission supplies
  the undulation at its origin, ``EnuOrigin.geoid_undulation``, and it is treated as constant
  over the mission area (it varies by a metre or two over tens of kilometres).
* ENU ``u`` is height above the origin's tangent plane, so it *drops* with distance from the
  origin by about ``d**2 / (2 R)`` (8 m at 10 km): ENU up is not an elevation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError, ProjError

#: WGS84 3-D geographic CRS (lon, lat, ellipsoidal height with always_xy).
WGS84_3D = CRS.from_epsg(4979)
#: Mean Earth radius (m), for small curvature corrections only.
EARTH_RADIUS = 6_371_008.8
#: WGS84 semi-major axis (m) and first eccentricity squared.
WGS84_A = 6_378_137.0
WGS84_E2 = 6.69437999014e-3


@dataclass(frozen=True)
class EnuOrigin:
    """Origin of the mission's local ENU (``map``) frame.

    Parameters
    ----------
    lat, lon : float
        WGS84 geodetic latitude and longitude of the origin (degrees).
    alt : float, optional
        WGS84 ellipsoidal height of the origin (m), default 0.
    geoid_undulation : float, optional
        Geoid height ``N`` (m) at the origin, used to turn the DEM's orthometric heights into
        ellipsoidal ones (``h = H + N``). Default 0: orthometric heights are then taken as
        ellipsoidal, a constant vertical bias of ``-N``.
    """

    lat: float
    lon: float
    alt: float = 0.0
    geoid_undulation: float = 0.0
    _fwd: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        if not (np.isfinite(self.lat) and -90.0 <= self.lat <= 90.0):
            raise ValueError(f"EnuOrigin: latitude {self.lat} is not in [-90, 90]")
        if not (np.isfinite(self.lon) and -180.0 <= self.lon <= 360.0):
            raise ValueError(f"EnuOrigin: longitude {self.lon} is not in [-180, 360]")
        if not (np.isfinite(self.alt) and np.isfinite(self.geoid_undulation)):
            raise ValueError("EnuOrigin: alt and geoid_undulation must be finite")
        pipeline = (
            "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad"
            " +step +proj=cart +ellps=WGS84"
            f" +step +proj=topocentric +ellps=WGS84 +lat_0={self.lat!r} +lon_0={self.lon!r}"
            f" +h_0={self.alt!r}"
        )
        object.__setattr__(self, "_fwd", Transformer.from_pipeline(pipeline))

    def geodetic_to_enu(self, lat, lon, h=0.0):
        """ENU (east, north, up) in metres of WGS84 points (degrees, ellipsoidal metres)."""
        lat, lon, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (lat, lon, h)))
        return self._fwd.transform(lon, lat, h)

    def enu_to_geodetic(self, east, north, up=0.0):
        """WGS84 (lat, lon, h) of ENU points; exact inverse of :meth:`geodetic_to_enu`."""
        east, north, up = np.broadcast_arrays(
            *(np.asarray(v, dtype=float) for v in (east, north, up)))
        lon, lat, h = self._fwd.transform(east, north, up, direction="INVERSE")
        return lat, lon, h

    def orthometric_to_ellipsoidal(self, height):
        """Ellipsoidal height ``h = H + N`` with the origin's constant geoid undulation."""
        return np.asarray(height, dtype=float) + self.geoid_undulation

    def surface_up(self, east, north, height=None):
        """ENU ``u`` of a surface of constant ellipsoidal height around the origin.

        Uses the ellipsoid's radii of curvature at the origin (meridional ``M`` for north,
        prime vertical ``N`` for east) with a quartic correction: within a millimetre or so of
        the exact value to ~10 km, a centimetre to ~30 km. Used to place horizontal ENU
        points at the terrain's height before an inverse transform (the resulting horizontal
        error is the height error times ``d / R``: 0.16 m per 100 m at 10 km) and for the
        Earth-curvature drop of ENU heights. Broadcasts (pass a row and a column for a grid).

        Parameters
        ----------
        east, north : array_like
            ENU horizontal coordinates (m).
        height : float, optional
            Ellipsoidal height (m) of the surface; default the origin's ``alt``.
        """
        height = self.alt if height is None else height
        m, n = self.radii
        east = np.asarray(east, dtype=float)
        north = np.asarray(north, dtype=float)
        q = np.square(east) / (2.0 * (n + height)) + np.square(north) / (2.0 * (m + height))
        return (height - self.alt) - q * (1.0 + q / (2.0 * (EARTH_RADIUS + height)))

    def surface_up_grid(self, east, north, height=None) -> np.ndarray:
        """:meth:`surface_up` on the grid ``east`` (columns) x ``north`` (rows), as float32.

        Separable, so a 1024 x 1024 grid costs a few float32 passes, not float64 ones.
        """
        height = self.alt if height is None else height
        m, n = self.radii
        qe = (np.square(np.asarray(east, dtype=float)) / (2.0 * (n + height))).astype(np.float32)
        qn = (np.square(np.asarray(north, dtype=float)) / (2.0 * (m + height))).astype(np.float32)
        q = np.add.outer(qn, qe)
        up = np.float32(height - self.alt) - q
        q *= q
        q *= np.float32(1.0 / (2.0 * (EARTH_RADIUS + height)))
        up -= q
        return up

    @property
    def radii(self) -> tuple[float, float]:
        """WGS84 radii of curvature (M meridional, N prime vertical) at the origin, metres."""
        s2 = np.sin(np.radians(self.lat)) ** 2
        w = 1.0 - WGS84_E2 * s2
        return WGS84_A * (1.0 - WGS84_E2) / w ** 1.5, WGS84_A / np.sqrt(w)


def as_crs(crs) -> CRS:
    """A :class:`pyproj.CRS` from anything pyproj accepts, or ``ValueError`` naming it."""
    try:
        return CRS.from_user_input(crs)
    except CRSError as exc:
        raise ValueError(f"unknown CRS {crs!r}: {exc}") from exc


def longitude_period(crs) -> float | None:
    """One full turn in the x (longitude) unit of a geographic CRS (360 for degrees), or None
    for a projected CRS, whose x does not wrap."""
    crs = as_crs(crs)
    if not crs.is_geographic:
        return None
    east = [a for a in crs.axis_info if a.direction.lower() == "east"]
    return 2.0 * np.pi / east[0].unit_conversion_factor if east else None


def wrap_longitude(x, centre: float, period: float = 360.0):
    """Longitudes ``x`` wrapped into ``[centre - period / 2, centre + period / 2)``; non-finite
    values (points a CRS cannot represent) are kept as they are."""
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid="ignore"):
        wrapped = np.mod(x - centre + 0.5 * period, period) + (centre - 0.5 * period)
    return np.where(np.isfinite(x), wrapped, x)


class CrsEnuTransform:
    """Vectorised transforms between a DEM's horizontal CRS and the mission ENU frame.

    ``to_enu`` and ``from_enu`` go DEM CRS (x, y) <-> WGS84 geodetic (pyproj's best available
    datum transformation, ``always_xy``) <-> ENU (exact, via ECEF).

    In a geographic CRS, ``from_enu`` gives longitudes within half a turn of the origin's
    (``x_origin``), not PROJ's [-180, 180): across the antimeridian they continue past 180
    (or -180) instead of jumping by 360, so a DEM placed in the same branch
    (:meth:`wrap_x`) is sampled without a seam.

    Parameters
    ----------
    crs : pyproj.CRS or str
        Horizontal CRS of the DEM (geographic or projected).
    origin : EnuOrigin
        Mission origin.
    """

    def __init__(self, crs, origin: EnuOrigin):
        self.crs = as_crs(crs)
        self.origin = origin
        try:
            self._to_geo = Transformer.from_crs(self.crs, WGS84_3D, always_xy=True)
        except ProjError as exc:
            raise ValueError(f"no transformation from {self.crs.name} to WGS84: {exc}") from exc
        #: length of a full turn in x (None: x does not wrap) and the origin's x
        self.period = longitude_period(self.crs)
        self.x_origin = None
        if self.period is not None:
            x, _, _ = self._to_geo.transform(origin.lon, origin.lat, origin.alt,
                                             direction="INVERSE", errcheck=False)
            self.x_origin = float(x)

    def wrap_x(self, x):
        """x (longitude) wrapped to within half a turn of the origin's; unchanged when the
        CRS is projected."""
        if self.period is None:
            return np.asarray(x, dtype=float)
        return wrap_longitude(x, self.x_origin, self.period)

    def __repr__(self):
        return f"CrsEnuTransform({self.crs.to_string()!r}, {self.origin!r})"

    def to_enu(self, x, y, height=None):
        """ENU (east, north, up) of DEM-CRS points.

        Parameters
        ----------
        x, y : array_like
            Coordinates in the DEM CRS (lon/lat degrees for geographic CRSs, always x first).
        height : array_like, optional
            Orthometric heights (m, the DEM's values). Default: the origin's height, i.e.
            points on the ellipsoidal-height surface through the origin.
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        if height is None:
            h = np.full(x.shape, self.origin.alt)
        else:
            h = np.broadcast_to(self.origin.orthometric_to_ellipsoidal(height), x.shape)
        lon, lat, h = self._to_geo.transform(x, y, h, errcheck=False)
        return self.origin.geodetic_to_enu(lat, lon, h)

    def from_enu(self, east, north, height=None):
        """DEM-CRS (x, y) of ENU horizontal points lying at a given terrain height.

        Parameters
        ----------
        east, north : array_like
            ENU horizontal coordinates (m).
        height : float, optional
            Orthometric height (m) at which the points lie; default the origin's height. It
            only matters through the Earth's curvature (see :meth:`EnuOrigin.surface_up`).

        Returns
        -------
        x, y : ndarray
            DEM-CRS coordinates; ``inf`` where the CRS cannot represent the point. Longitudes
            are within half a turn of the origin's (see the class notes).
        """
        east, north = np.broadcast_arrays(
            np.asarray(east, dtype=float), np.asarray(north, dtype=float))
        h = None if height is None else float(self.origin.orthometric_to_ellipsoidal(height))
        up = self.origin.surface_up(east, north, h)
        lat, lon, hh = self.origin.enu_to_geodetic(east, north, up)
        x, y, _ = self._to_geo.transform(lon, lat, hh, direction="INVERSE", errcheck=False)
        return self.wrap_x(x), np.asarray(y)


class LocalEnuTransform:
    """DEM in unreferenced local metres: ENU = (x - x0, y - y0), heights as stored.

    For grids whose CRS is unknown but whose axes are metres east/north (e.g. an ESRI ASCII
    grid without ``.prj``). ``(x0, y0)`` is the DEM coordinate of the ENU origin; nothing ties it
    to WGS84, so such a DEM cannot be combined with geodetic positions.
    """

    crs = None

    def __init__(self, x0: float, y0: float, origin: EnuOrigin | None = None):
        self.x0, self.y0 = float(x0), float(y0)
        self.origin = origin

    def __repr__(self):
        return f"LocalEnuTransform(x0={self.x0!r}, y0={self.y0!r})"

    def to_enu(self, x, y, height=None):
        """ENU (east, north, up) of local points; ``up`` is the height (0 if not given)."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        up = np.zeros(x.shape) if height is None else np.broadcast_to(height, x.shape) * 1.0
        return x - self.x0, y - self.y0, up

    def from_enu(self, east, north, height=None):
        """Local (x, y) of ENU points."""
        east, north = np.broadcast_arrays(
            np.asarray(east, dtype=float), np.asarray(north, dtype=float))
        return east + self.x0, north + self.y0
