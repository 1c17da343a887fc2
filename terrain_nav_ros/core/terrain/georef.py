"""Georeference of a north-up raster in the mission's local ENU frame.

Every raster that flows through terrain_nav (DEM tile, rendered landmark, ground-projected
camera frame, crease image) is a north-up grid in the local East-North-Up frame of the
mission origin (REP 103). A :class:`GeoReference` says where that grid lies:

* ``origin_east``, ``origin_north``: ENU coordinates (m) of the *outer corner* of pixel
  (row 0, col 0), i.e. the north-west corner of the raster.
* ``gsd``: ground sample distance, metres per pixel, equal in both axes.
* ``width``, ``height``: raster size in pixels (columns, rows).

Pixel centres are at integer coordinates: pixel (col, row) covers
``east in [origin_east + col*gsd, origin_east + (col+1)*gsd)`` and its centre is at
``east = origin_east + (col + 0.5) * gsd``, ``north = origin_north - (row + 0.5) * gsd``.
Rows grow southwards, columns eastwards.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GeoReference:
    """Placement of a north-up raster in local ENU metres.

    Parameters
    ----------
    origin_east, origin_north : float
        ENU coordinates (m) of the north-west corner of pixel (0, 0).
    gsd : float
        Ground sample distance (m/px), > 0.
    width, height : int
        Raster size (columns, rows), >= 0.
    """

    origin_east: float
    origin_north: float
    gsd: float
    width: int
    height: int

    def __post_init__(self):
        if not np.isfinite(self.gsd) or self.gsd <= 0:
            raise ValueError(f"GeoReference: gsd must be a positive finite number, got {self.gsd}")
        if self.width < 0 or self.height < 0:
            raise ValueError(f"GeoReference: negative size {self.width}x{self.height}")
        if not (np.isfinite(self.origin_east) and np.isfinite(self.origin_north)):
            raise ValueError("GeoReference: origin must be finite")

    @classmethod
    def centred(cls, east: float, north: float, gsd: float, width: int, height: int):
        """Raster of ``width`` x ``height`` pixels whose centre lies at (east, north)."""
        return cls(east - 0.5 * width * gsd, north + 0.5 * height * gsd, gsd, width, height)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols), the numpy shape of the raster."""
        return (self.height, self.width)

    @property
    def centre(self) -> tuple[float, float]:
        """ENU (east, north) of the raster centre."""
        return (self.origin_east + 0.5 * self.width * self.gsd,
                self.origin_north - 0.5 * self.height * self.gsd)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(west, east, south, north) bounds in metres (outer pixel edges)."""
        return (self.origin_east, self.origin_east + self.width * self.gsd,
                self.origin_north - self.height * self.gsd, self.origin_north)

    def pixel_to_enu(self, col, row):
        """ENU (east, north) of pixel coordinates; integers are pixel centres."""
        col = np.asarray(col, dtype=float)
        row = np.asarray(row, dtype=float)
        return (self.origin_east + (col + 0.5) * self.gsd,
                self.origin_north - (row + 0.5) * self.gsd)

    def enu_to_pixel(self, east, north):
        """Fractional pixel coordinates (col, row) of ENU points."""
        east = np.asarray(east, dtype=float)
        north = np.asarray(north, dtype=float)
        return ((east - self.origin_east) / self.gsd - 0.5,
                (self.origin_north - north) / self.gsd - 0.5)

    def contains(self, east, north):
        """Boolean mask: which ENU points fall inside the raster's outer edges."""
        west, east_edge, south, north_edge = self.extent
        east = np.asarray(east, dtype=float)
        north = np.asarray(north, dtype=float)
        return (east >= west) & (east < east_edge) & (north > south) & (north <= north_edge)

    def to_affine(self) -> tuple[float, float, float, float, float, float]:
        """GDAL-style geotransform (x0, dx, 0, y0, 0, -dy) in ENU metres."""
        return (self.origin_east, self.gsd, 0.0, self.origin_north, 0.0, -self.gsd)
