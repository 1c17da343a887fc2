"""The minutiae container shared by the feature extractor, the matcher and the messages.

Conventions (REP 103, north-up rasters, see :mod:`terrain_nav_ros.core.terrain.georef`):

* ``col``, ``row``: pixel coordinates in the source raster (float; integer = pixel centre).
* ``angle``: minutia direction in radians, measured from East counter-clockwise towards
  North (so in image terms ``angle = atan2(-d_row, d_col)``), wrapped to [0, 2*pi).
* ``kind``: the crossing number of the skeleton pixel, :data:`ENDING` (1) or
  :data:`BIFURCATION` (3).
* ``quality``: in [0, 1], higher is more reliable.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..terrain.georef import GeoReference

ENDING = 1
BIFURCATION = 3


def _as_1d(values, dtype) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(values, dtype=dtype).reshape(-1))


@dataclass
class MinutiaSet:
    """Minutiae of one raster, as parallel 1-D arrays.

    ``reason`` explains an empty set (e.g. ``"no drainage: image is flat"``) so callers can
    report "no fix" instead of guessing why nothing was found.
    """

    col: np.ndarray
    row: np.ndarray
    angle: np.ndarray
    kind: np.ndarray
    quality: np.ndarray
    georef: GeoReference | None = None
    reason: str = ""
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        self.col = _as_1d(self.col, np.float64)
        self.row = _as_1d(self.row, np.float64)
        self.angle = np.mod(_as_1d(self.angle, np.float64), 2 * np.pi)
        self.kind = _as_1d(self.kind, np.uint8)
        self.quality = _as_1d(self.quality, np.float32)
        n = len(self.col)
        if not all(len(a) == n for a in (self.row, self.angle, self.kind, self.quality)):
            raise ValueError("MinutiaSet: all arrays must have the same length")
        bad = ~np.isin(self.kind, (ENDING, BIFURCATION))
        if bad.any():
            raise ValueError(f"MinutiaSet: unknown minutia kind(s) {np.unique(self.kind[bad])}")
        for name in ("col", "row", "angle", "quality"):
            values = getattr(self, name)
            if not np.isfinite(values).all():
                raise ValueError(f"MinutiaSet: {np.count_nonzero(~np.isfinite(values))} "
                                 f"{name} value(s) are not finite")

    @classmethod
    def empty(cls, reason: str = "", georef: GeoReference | None = None) -> MinutiaSet:
        """A set with no minutiae and the reason why."""
        z = np.zeros(0)
        return cls(z, z, z, z.astype(np.uint8), z, georef=georef, reason=reason)

    def __len__(self) -> int:
        return len(self.col)

    def subset(self, index) -> MinutiaSet:
        """The minutiae selected by a boolean mask or an index array."""
        return MinutiaSet(self.col[index], self.row[index], self.angle[index], self.kind[index],
                          self.quality[index], georef=self.georef, reason=self.reason)

    def enu(self) -> tuple[np.ndarray, np.ndarray]:
        """ENU (east, north) in metres; needs a georeference."""
        if self.georef is None:
            raise ValueError("MinutiaSet.enu: this set has no georeference")
        return self.georef.pixel_to_enu(self.col, self.row)
