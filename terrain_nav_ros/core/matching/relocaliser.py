"""When the matcher searches the whole mission area, and how its answer meets the graph's frame.

The matcher node's ROS-free helpers for relocalisation (issue 24): :class:`SearchPolicy`
decides, frame by frame, whether the camera set is matched in the landmark tile around the
estimate or searched in the mission index; :class:`MissionSearch` holds the index's tiles
for the frame's sun, prepared, and searches them (:func:`.global_search.relocalise`);
:func:`tile_in_frame` moves a mission tile's georeference into the graph's ENU frame.
"""

from __future__ import annotations

import threading
from dataclasses import replace
from typing import TYPE_CHECKING

from ..render.sun import sun_at, sun_separation
from ..terrain.geodesy import EnuOrigin
from ..terrain.georef import GeoReference
from .global_search import (
    Relocalisation,
    SearchTile,
    relocalisation_matcher,
    relocalise,
    relocalise_ladder,
)
from .index import MinutiaIndex
from .matcher import Decision, MatchResult
from .params import MatchParams

if TYPE_CHECKING:   # imported when a search opens a tile: a node without one starts sooner
    from .mission_index import MissionIndex

# a layer lit this far from the frame's sun shades the creases otherwise (they repeat within
# a few degrees: the landmark renderer re-renders after 2): say so when nothing was found
_SUN_GAP_WARNING = 5.0
# beyond this the search is not made: the creases of a layer lit that far from the frame's
# sun have moved by a good part of their width, and agreeing relocalisations would share
# that bias (a layer lit 114 deg away gave relocalisations 120-160 m off, scoring 20-67)
_SUN_GAP_LIMIT = 10.0


class SearchPolicy:
    """Whether the next camera frame is searched in the whole mission area.

    A frame is searched when no landmark tile around the estimate covers it (no estimate
    yet, or it moved off the tiles served), or after ``after_no_fixes`` frames in a row got
    no fix in the tile (the estimate may have drifted out of it). While that run lasts,
    frames alternate between a search and a try in the tile: the filter moves its estimate
    only when two relocalisations agree, and the try in the tile around the moved estimate
    is what ends the run (a fix there counts it again from zero).

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
        self.searched_last = False

    def reason_to_search(self, covered: bool) -> str:
        """Why this frame is searched in the mission area; empty when it is matched in the
        tile around the estimate."""
        if not covered:
            return "no landmark tile covers the camera footprint"
        if self.no_fixes >= self.after_no_fixes and not self.searched_last:
            return f"{self.no_fixes} frames in a row without a fix in the tile"
        return ""

    def searched(self) -> None:
        """Count a frame searched in the mission area."""
        self.searched_last = True

    def tile_answered(self, fixed: bool) -> None:
        """Count a frame matched in the tile around the estimate."""
        self.no_fixes = 0 if fixed else self.no_fixes + 1
        self.searched_last = False


def tile_in_frame(georef: GeoReference, east: float, north: float, tile_origin: EnuOrigin,
                  frame_origin: EnuOrigin) -> GeoReference:
    """``georef`` (a raster in the ENU frame of ``tile_origin``) moved into the ENU frame of
    ``frame_origin``, exactly at the point (``east``, ``north``) of the tile's frame.

    The two frames' east-north planes are tangent at different places: between origins tens
    of kilometres apart their axes turn by a fraction of a degree and their planes drift
    apart with the Earth's curvature. A shift that puts the matched pixel (the camera view's
    centre) at its true place keeps the fix's position exact; the turn (under ~1 deg for
    origins 100 km apart) is within what the fix's heading covariance holds.
    """
    if tile_origin == frame_origin:
        return georef
    # on the ellipsoid's surface, not the tangent plane (which rises above it, ~200 m at 50 km)
    up = tile_origin.surface_up(east, north)
    lat, lon, h = tile_origin.enu_to_geodetic(east, north, float(up))
    e2, n2, _ = frame_origin.geodetic_to_enu(lat, lon, h)
    return replace(georef, origin_east=georef.origin_east + float(e2) - east,
                   origin_north=georef.origin_north + float(n2) - north)


class MissionSearch:
    """A mission index as the matcher searches it.

    The tiles of one sun layer (the one nearest the frame's sun, computed from the frame's
    time at the area's centre) are loaded and prepared as landmark regions, and kept until
    the sun has moved nearer another layer (~85 MB a 1024 px tile once searched). The node
    has them prepared in a background thread from the first frame on
    (:meth:`prepare_in_background`): loading them made the first search of a lost flight
    5-8 s slower than the next, too late for the filter to take its fix.

    Parameters
    ----------
    mission : MissionIndex
    params : MatchParams
        The graph's matcher settings; the tiles' view-search bound is grown to their size
        (:func:`~.global_search.relocalisation_matcher`).
    """

    def __init__(self, mission: MissionIndex, params: MatchParams):
        self.mission = mission
        self.matcher = relocalisation_matcher(params, mission.grid.tile_px)
        self.layer: int | None = None
        self.tiles: list[SearchTile] = []
        self.damaged: list[str] = []     # the layer's tiles that could not be read
        self._loading = threading.Lock()
        self._preparing: threading.Thread | None = None
        self._failed_layer: int | None = None   # not tried again in the background

    def sun_at(self, unix_seconds: float) -> tuple[float, float]:
        """(azimuth, elevation) of the sun at the area's centre at a time (deg)."""
        return sun_at(unix_seconds, self.mission.origin.lat, self.mission.origin.lon)

    def tiles_for(self, sun) -> list[SearchTile]:
        """The prepared tiles of the layer nearest ``sun`` (loaded on first use, or waited
        for while a background preparation loads them)."""
        k = self.mission.nearest_sun(sun)
        with self._loading:
            if k != self.layer:
                damaged: list[str] = []
                tiles = [self._prepared(t.col, t.row, k, damaged) for t in self.mission.tiles()]
                self.tiles = [t for t in tiles if t is not None]
                self.damaged, self.layer = damaged, k
            return self.tiles

    def prepare_in_background(self, unix_seconds: float) -> threading.Thread | None:
        """Start loading the layer a search at ``unix_seconds`` would use, in a daemon
        thread, unless it is loaded, being loaded, or too far from the frame's sun to be
        searched; the thread, or None. A search meanwhile waits for it. A failure is left
        to the search, which loads the layer again and meets it."""
        sun = self.sun_at(unix_seconds)
        k = self.mission.nearest_sun(sun)
        if k in (self.layer, self._failed_layer) or self._sun_refusal(sun) is not None \
                or (self._preparing is not None and self._preparing.is_alive()):
            return None
        self._preparing = threading.Thread(target=self._prepare_quietly, args=(sun, k),
                                           name="mission-layer", daemon=True)
        self._preparing.start()
        return self._preparing

    def _prepare_quietly(self, sun, layer: int) -> None:
        try:
            self.tiles_for(sun)
        except Exception:   # noqa: BLE001 - the search meets it again, in the node's callback
            self._failed_layer = layer

    def _prepared(self, col: int, row: int, layer: int, damaged: list[str]
                  ) -> SearchTile | None:
        from .mission_index import MissionIndexError

        try:
            found = self.mission.load(col, row, layer)
        except MissionIndexError as err:   # damaged in flight: its area is lost, once
            damaged.append(str(err))
            return None
        if not len(found.minutiae):
            return None     # a tile without drainage (lake, plain): nothing to search
        index = self.matcher.index(found.minutiae, found.creases, found.ridges)
        # the crease search's rasters are left to the first search, which builds only the
        # level and turns a view needs: ~45 MB a 1024 px tile less than all of them
        return SearchTile(index.prepare_as_reference(), found.georef,
                          f"r{row}_c{col}_s{layer}")

    def layer_sun_gap(self, sun) -> float:
        """Degrees between ``sun`` and the nearest layer's sun: beyond a few, shaded creases
        stop repeating and the search will find little."""
        return sun_separation(sun, self.mission.suns[self.mission.nearest_sun(sun)])

    def _refusal(self, camera: MinutiaIndex) -> Relocalisation | None:
        """A no-relocalisation when the camera set is not at the index's GSD."""
        gsd = camera.set.georef.gsd if camera.set.georef is not None else float("nan")
        if abs(gsd / self.mission.gsd - 1.0) < 0.01:
            return None
        reason = (f"the camera set's GSD {gsd:g} m is not the mission index's "
                  f"{self.mission.gsd:g} m: prepare the index at the graph's gsd")
        return Relocalisation(MatchResult(Decision.NO_DECISION, reason=reason), reason=reason)

    def _sun_refusal(self, sun) -> Relocalisation | None:
        """A no-relocalisation when the index holds no layer lit near the frame's sun."""
        gap = self.layer_sun_gap(sun)
        if gap <= _SUN_GAP_LIMIT:
            return None
        reason = (f"the index's nearest sun is {gap:.0f} deg from the frame's (at most "
                  f"{_SUN_GAP_LIMIT:g}): prepare it for the flight's hours")
        return Relocalisation(MatchResult(Decision.NO_DECISION, reason=reason), reason=reason)

    def _answer(self, found: Relocalisation, sun,
                frame_origin: EnuOrigin) -> tuple[Relocalisation, GeoReference | None]:
        if not found.matched:
            gap = self.layer_sun_gap(sun)
            if gap > _SUN_GAP_WARNING:
                found.reason += (f"; the index's nearest sun is {gap:.0f} deg from the "
                                 "frame's: prepare it for the flight's hours")
            if self.damaged:
                found.reason += (f"; {len(self.damaged)} damaged tile(s) not searched: "
                                 f"{self.damaged[0]}")
            return found, None
        return found, tile_in_frame(found.tile.georef, *found.position, self.mission.origin,
                                    frame_origin)

    def search(self, camera: MinutiaIndex, unix_seconds: float,
               frame_origin: EnuOrigin) -> tuple[Relocalisation, GeoReference | None]:
        """Relocalise a camera set (built with :attr:`matcher`) taken at ``unix_seconds``;
        with a relocalisation, its tile's georeference in the ENU frame of
        ``frame_origin`` (the camera set's)."""
        refused = self._refusal(camera)
        if refused is not None:
            return refused, None
        sun = self.sun_at(unix_seconds)
        refused = self._sun_refusal(sun)
        if refused is not None:
            return refused, None
        return self._answer(relocalise(self.matcher, camera, self.tiles_for(sun)), sun,
                            frame_origin)

    def search_ladder(self, cameras: list[MinutiaIndex], unix_seconds: float,
                      frame_origin: EnuOrigin
                      ) -> tuple[Relocalisation, GeoReference | None, int]:
        """:meth:`search` for the views of one frame at several scales
        (:func:`~.global_search.relocalise_ladder`): also the index of the view found
        (-1 without a relocalisation)."""
        for camera in cameras:
            refused = self._refusal(camera)
            if refused is not None:
                return refused, None, -1
        sun = self.sun_at(unix_seconds)
        refused = self._sun_refusal(sun)
        if refused is not None:
            return refused, None, -1
        found, k = relocalise_ladder(self.matcher, cameras, self.tiles_for(sun))
        found, georef = self._answer(found, sun, frame_origin)
        return found, georef, (k if georef is not None else -1)
