"""When the matcher searches the whole mission area, and how its answer meets the graph's frame.

The matcher node's ROS-free helpers for relocalisation (issue 24): :class:`SearchPolicy`
decides, frame by frame, whether the camera set is matched in the landmark tile around the
estimate or searched in the mission index (:func:`.global_search.relocalise`);
:func:`tile_in_frame` moves a mission tile's georeference into the graph's ENU frame.
"""

from __future__ import annotations

from dataclasses import replace

from ..terrain.geodesy import EnuOrigin
from ..terrain.georef import GeoReference


class SearchPolicy:
    """Whether the next camera frame is searched in the whole mission area.

    A frame is searched when no landmark tile around the estimate covers it (no estimate
    yet, or it moved off the tiles served), or after ``after_no_fixes`` frames in a row got
    no fix in the tile (the estimate may have drifted out of it). The run is counted again
    from zero after a fix in the tile; a search that finds nothing keeps searching the next
    frames, since the tile has not become more likely to hold them.

    Parameters
    ----------
    after_no_fixes : int
        No-fixes in a row that start the searches (>= 1).
    """

    def __init__(self, after_no_fixes: int):
        if after_no_fixes < 1:
            raise ValueError(f"after_no_fixes must be >= 1, got {after_no_fixes}")
        self.after_no_fixes = after_no_fixes
        self.no_fixes = 0

    def reason_to_search(self, covered: bool) -> str:
        """Why this frame is searched in the mission area; empty when it is matched in the
        tile around the estimate."""
        if not covered:
            return "no landmark tile covers the camera footprint"
        if self.no_fixes >= self.after_no_fixes:
            return f"{self.no_fixes} frames in a row without a fix in the tile"
        return ""

    def tile_answered(self, fixed: bool) -> None:
        """Count a frame matched in the tile around the estimate."""
        self.no_fixes = 0 if fixed else self.no_fixes + 1


def tile_in_frame(georef: GeoReference, col: float, row: float, tile_origin: EnuOrigin,
                  frame_origin: EnuOrigin) -> GeoReference:
    """``georef`` (a raster in the ENU frame of ``tile_origin``) moved into the ENU frame of
    ``frame_origin``, exactly at pixel (``col``, ``row``).

    The two frames' east-north planes are tangent at different places: between origins tens
    of kilometres apart their axes turn by a fraction of a degree and their planes drift
    apart with the Earth's curvature. A shift that puts the matched pixel (the camera view's
    centre) at its true place keeps the fix's position exact; the turn (under ~1 deg for
    origins 100 km apart) is within what the fix's heading covariance holds.
    """
    if tile_origin == frame_origin:
        return georef
    east, north = georef.pixel_to_enu(col, row)
    # on the ellipsoid's surface, not the tangent plane (which rises above it, ~200 m at 50 km)
    up = tile_origin.surface_up(east, north)
    lat, lon, h = tile_origin.enu_to_geodetic(float(east), float(north), float(up))
    e2, n2, _ = frame_origin.geodetic_to_enu(lat, lon, h)
    return replace(georef, origin_east=georef.origin_east + float(e2) - float(east),
                   origin_north=georef.origin_north + float(n2) - float(north))
