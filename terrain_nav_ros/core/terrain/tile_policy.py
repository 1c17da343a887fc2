"""When and where the metamap publishes a new tile around the aircraft.

The tile must hold the camera footprint wherever the aircraft may be: around the estimated
position, widened by ``sigma_scale`` horizontal standard deviations, now and ``lookahead``
seconds ahead. A new tile is cut when that area is no longer inside the last one (the aircraft
nears its edge, or the uncertainty has grown), centred between now and the predicted position
so the aircraft flies into it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .georef import GeoReference


@dataclass
class TilePolicy:
    """Decides the region of interest of the next DEM tile.

    Parameters
    ----------
    min_size, max_size : int
        Bounds of the tile size (px, square tiles).
    footprint_radius : float
        Radius of the camera's ground footprint (m).
    sigma_scale : float
        Horizontal position standard deviations added to the footprint.
    lookahead : float
        How far ahead the position is predicted with the current velocity (s).
    margin : float
        A new tile covers this many times the needed radius, so that slowly growing
        uncertainty or a turn does not cut a new tile at every update (hysteresis).
    """

    min_size: int = 256
    max_size: int = 1024
    footprint_radius: float = 600.0
    sigma_scale: float = 3.0
    lookahead: float = 5.0
    margin: float = 1.5
    current: GeoReference | None = field(default=None, init=False)

    def __post_init__(self):
        if not 0 < self.min_size <= self.max_size:
            raise ValueError(f"TilePolicy: need 0 < min_size <= max_size, got "
                             f"{self.min_size}, {self.max_size}")
        if self.footprint_radius < 0 or self.sigma_scale < 0 or self.lookahead < 0:
            raise ValueError("TilePolicy: footprint_radius, sigma_scale and lookahead must "
                             "be >= 0")
        if self.margin < 1.0:
            raise ValueError(f"TilePolicy: margin must be >= 1, got {self.margin}")

    def needed_radius(self, cov_xy) -> float:
        """Footprint radius plus the scaled horizontal position uncertainty (m)."""
        sigma = math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(cov_xy, float))[-1]), 0.0))
        return self.footprint_radius + self.sigma_scale * sigma

    def _covers(self, tile: GeoReference, point, radius: float) -> bool:
        west, east, south, north = tile.extent
        x, y = point
        return (x - radius >= west and x + radius <= east and y - radius >= south
                and y + radius <= north)

    def update(self, position, velocity, cov_xy, gsd: float) -> GeoReference | None:
        """The next tile's georeference, or None while the current tile still suffices."""
        position = np.asarray(position, float)
        ahead = position + np.asarray(velocity, float) * self.lookahead
        radius = self.needed_radius(cov_xy)
        if self.current is not None and self.current.gsd == gsd and all(
                self._covers(self.current, p, radius) for p in (position, ahead)):
            return None
        centre = 0.5 * (position + ahead)
        half = self.margin * radius + 0.5 * float(np.linalg.norm(ahead - position))
        size = int(np.clip(math.ceil(2 * half / gsd), self.min_size, self.max_size))
        self.current = GeoReference.centred(float(centre[0]), float(centre[1]), gsd, size, size)
        return self.current

    def forget(self) -> None:
        """Drop the current tile (it could not be served): the next update cuts a new one."""
        self.current = None
