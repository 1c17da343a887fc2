"""Relocalisation: a camera view searched in every tile of a mission area (issue 24).

The graph normally searches a camera frame only in the landmark tile around the filter's
estimate. When that estimate is lost (none yet, drifted beyond the tile, or a run of no-fixes),
:func:`relocalise` searches the view in every tile of the mission area (tiles prepared before
flight, see :mod:`.mission_index`) with the same matcher, and keeps the best registration.

Two things differ from a search in one tile:

* **The search space is the whole area.** The matcher's significance already pays for the
  transforms searched inside one tile. Searching ``n`` tiles tries ``n`` times as many places,
  so a relocalisation must beat the threshold by ``log10(n)`` more (Bonferroni over the tiles;
  tiles overlap, so this is conservative). One threshold then keeps one false-match rate
  whatever the size of the area.
* **Another place may match too.** Terrain can repeat (parallel ridges, a view with little
  drainage). Registrations in overlapping tiles that put the view at the same place agree; a
  runner-up at another place within ``ambiguity_margin`` decades of the best makes the answer
  ambiguous, and no relocalisation is claimed.

The filter still does not trust one relocalisation: it resets only when two frames agree
(:mod:`~terrain_nav_ros.core.estimation.ekf`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..terrain.georef import GeoReference
from .index import MinutiaIndex
from .matcher import Decision, Matcher, MatchResult
from .params import MatchParams

# side (px) of the landmark regions the graph's view-search work bound was set for (a
# 256 px camera footprint plus 3 sigma): a mission tile's bound grows with its area
_GRAPH_REGION_SIDE = 768


@dataclass(frozen=True)
class SearchTile:
    """One tile of the mission area: its landmark index and where it lies.

    Parameters
    ----------
    index : MinutiaIndex
        The tile's landmark set, prepared once (``prepare_as_reference()``) for the frames
        searched in it.
    georef : GeoReference
        The tile's raster in the mission's ENU frame (the landmark set's pixel frame).
    key : str
        A name for logs (e.g. the tile's id in the mission index).
    """

    index: MinutiaIndex
    georef: GeoReference
    key: str = ""


@dataclass
class Relocalisation:
    """Outcome of :func:`relocalise`.

    Attributes
    ----------
    result : MatchResult
        The best registration (camera px -> ``tile`` px), with its decision; its ``score`` is
        the matcher's, before the area's penalty.
    tile : SearchTile or None
        The tile of the best registration.
    score : float
        ``result.score - penalty``: the significance over the whole area searched (without
        a relocalisation: the best seen, for logs).
    penalty : float
        ``log10`` of the number of tiles searched (see the module notes).
    position : tuple of float
        ENU (east, north) of the camera view's centre, NaN without a registration.
    runner_up : float
        The best area score of a registration at another place (-inf without one).
    searched : int
        Tiles searched (fewer than given when a certain answer stopped the search).
    reason : str
        Why there is no relocalisation.
    candidates : list
        Every registration significant over the area, as (area score, tile position in the
        list searched, result, east, north), best first: for logs and studies.
    """

    result: MatchResult
    tile: SearchTile | None = None
    score: float = -np.inf
    penalty: float = 0.0
    position: tuple[float, float] = (math.nan, math.nan)
    runner_up: float = -np.inf
    searched: int = 0
    reason: str = ""
    candidates: list = field(default_factory=list, repr=False)

    @property
    def matched(self) -> bool:
        """Whether the view was relocalised (significant over the area and unambiguous)."""
        return self.result.decision == Decision.MATCH and not self.reason


def relocalisation_matcher(params: MatchParams, tile_side: int) -> Matcher:
    """The graph's matcher with the view search's work bound grown from the graph's
    landmark region to a mission tile of ``tile_side`` px (with a tenth to spare), so a
    camera view is searched in a whole tile at the level it is in a region.

    Tiles larger than a region cost less per square kilometre: their overlap, which every
    view must fit in, is a smaller part of them."""
    grown = params.crease_search_max_work * 1.1 * (tile_side / _GRAPH_REGION_SIDE) ** 2
    return Matcher(replace(params, crease_search_max_work=max(
        params.crease_search_max_work, int(grown))))


def _view_centre(camera: MinutiaIndex, centre) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (col, row) of the camera view's centre: ``centre``, else its raster's."""
    if centre is not None:
        return np.array([float(centre[0])]), np.array([float(centre[1])])
    g = camera.set.georef
    if g is None or g.width <= 0 or g.height <= 0:
        raise ValueError("relocalise: the camera set has no raster (georef): give view_centre")
    return np.array([0.5 * (g.width - 1)]), np.array([0.5 * (g.height - 1)])


def _search_order(tiles: Sequence[SearchTile], near) -> list[int]:
    """Tiles nearest ``near`` (east, north) first, else in the given order."""
    if near is None:
        return list(range(len(tiles)))
    centres = np.array([t.georef.centre for t in tiles], float).reshape(-1, 2)
    return list(np.argsort(np.hypot(*(centres - np.asarray(near, float)).T), kind="stable"))


def relocalise(matcher: Matcher, camera: MinutiaIndex, tiles: Sequence[SearchTile], *,
               view_centre=None, near=None, certain_score: float = math.inf,
               ambiguity_margin: float = 2.0, same_place_px: float = 10.0) -> Relocalisation:
    """Search a camera view in every tile of an area; the best registration, if it is
    significant over the whole area and unambiguous.

    Parameters
    ----------
    matcher : Matcher
        The graph's matcher; its ``threshold`` applies to the area score.
    camera : MinutiaIndex
        The camera view's set, in the same GSD as the tiles.
    tiles : sequence of SearchTile
    view_centre : (col, row), optional
        The camera pixel whose place is reported; default the centre of the camera set's
        raster (its ``georef``).
    near : (east, north), optional
        Search the tiles nearest this point first (a stale estimate): a certain answer there
        ends the search early.
    certain_score : float
        An area score at or above which the search stops (the chance of so good a match
        anywhere in the area is below ``10**-certain_score``). The default searches every
        tile, so that terrain repeated elsewhere is seen as ambiguous.
    ambiguity_margin : float
        A registration at another place within this many decades of the best makes the
        answer ambiguous.
    same_place_px : float
        View centres closer than this (px of the tiles' GSD) are the same place.

    Returns
    -------
    Relocalisation
    """
    if not tiles:
        return Relocalisation(MatchResult(Decision.NO_DECISION, reason="no tiles to search"),
                              reason="no tiles to search")
    penalty = math.log10(len(tiles))
    threshold = matcher.params.threshold
    col, row = _view_centre(camera, view_centre)
    found = []   # (area score, tile position, result, east, north)
    searched, best_seen = 0, -np.inf
    for k in _search_order(tiles, near):
        tile = tiles[k]
        result = matcher.localise(camera, tile.index)
        searched += 1
        area_score = result.score - penalty
        best_seen = max(best_seen, area_score)
        if not result.matched or area_score < threshold:
            continue
        c, r = result.apply(col, row)
        east, north = tile.georef.pixel_to_enu(float(c[0]), float(r[0]))
        found.append((area_score, k, result, float(east), float(north)))
        if area_score >= certain_score:
            break
    if not found:
        reason = (f"no significant match in the mission area (best {best_seen:.1f} < "
                  f"{threshold:g} over {searched} tiles)")
        return Relocalisation(MatchResult(Decision.NO_MATCH, reason=reason), score=best_seen,
                              penalty=penalty, searched=searched, reason=reason)
    return _verdict(found, tiles, penalty, searched, ambiguity_margin,
                    same_place_px * tiles[0].georef.gsd)


def _verdict(found, tiles, penalty: float, searched: int, margin: float,
             same_place_m: float) -> Relocalisation:
    """The relocalisation from the registrations found (area score, tile, result, east,
    north), at least one."""
    found.sort(key=lambda f: f[0], reverse=True)
    score, k, result, east, north = found[0]
    elsewhere = [f[0] for f in found[1:]
                 if math.hypot(f[3] - east, f[4] - north) > same_place_m]
    runner_up = max(elsewhere, default=-np.inf)
    reason = ""
    if score - runner_up < margin:
        reason = (f"ambiguous: matches {score:.1f} and {runner_up:.1f} at places "
                  f"more than {same_place_m:.0f} m apart")
    return Relocalisation(result, tiles[k], score, penalty, (east, north), runner_up, searched,
                          reason, candidates=found)
