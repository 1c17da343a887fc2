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

* **A frame projected without any pose** (cold start: its height above the unknown terrain is
  uncertain beyond the search's +-10 % of scale) is searched at a short ladder of scales
  (:func:`scale_ladder`, :func:`rescaled_view`, :func:`relocalise_ladder`): each rung is one
  more search of the area, so the significance pays ``log10(tiles x rungs)``.

The filter still does not trust one relocalisation: it resets only when two frames agree
(:mod:`~terrain_nav_ros.core.estimation.ekf`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..features.creases import skeletonize_creases
from ..features.minutia_set import MinutiaSet
from ..terrain.georef import GeoReference
from .index import MinutiaIndex
from .matcher import Decision, Matcher, MatchResult
from .params import MatchParams

# ratio between the scales of two rungs of a ladder: the view search covers +-10 % of scale
# about each (1.2 = 1.095^2, with a little overlap)
LADDER_STEP = 1.2

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
        ``log10`` of the number of tiles searched times the searches of the same frame (the
        rungs of a ladder of scales; see the module notes).
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
               ambiguity_margin: float = 2.0, same_place_px: float = 10.0,
               searches: int = 1) -> Relocalisation:
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
    searches : int
        The searches of the area this frame gets in all (the rungs of a ladder of scales,
        :func:`relocalise_ladder`): the penalty is ``log10(len(tiles) * searches)``.

    Returns
    -------
    Relocalisation
    """
    if not tiles:
        return Relocalisation(MatchResult(Decision.NO_DECISION, reason="no tiles to search"),
                              reason="no tiles to search")
    penalty = math.log10(len(tiles) * max(int(searches), 1))
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


# --------------------------------------------------------------------------- ladder of scales
def scale_ladder(smallest: float, largest: float, step: float = LADDER_STEP) -> list[float]:
    """Scale factors whose ranges ``f / sqrt(step) .. f * sqrt(step)`` cover ``smallest`` ..
    ``largest``, geometric and centred on the range; ``[1.0]`` when one search's own scale
    range (about +-10 %) around 1 covers it."""
    if not 0 < smallest <= largest or not step > 1:
        raise ValueError(f"scale_ladder: need 0 < {smallest:g} <= {largest:g} and step "
                         f"{step:g} > 1")
    half = math.sqrt(step)
    if smallest >= 1.0 / half and largest <= half:
        return [1.0]
    span = math.log(largest / smallest)
    n = max(1, math.ceil(span / math.log(step) - 1e-9))
    centre = 0.5 * math.log(smallest * largest)
    return [math.exp(centre + (k - 0.5 * (n - 1)) * math.log(step)) for k in range(n)]


def _rescaled_skeleton(skeleton, shape) -> np.ndarray | None:
    if skeleton is None:
        return None
    resized = cv2.resize(np.asarray(skeleton, np.float32), (shape[1], shape[0]),
                         interpolation=cv2.INTER_LINEAR)
    return skeletonize_creases(resized > 0.0)


def rescaled_view(minutiae: MinutiaSet, creases, ridges, factor: float,
                  anchor) -> tuple[MinutiaSet, np.ndarray | None, np.ndarray | None]:
    """A ground-projected camera set as it would be were its ground distances ``factor``
    times larger about the ENU point ``anchor`` (the point under the camera): the minutiae
    moved exactly, the crease and ridge skeletons resampled and thinned again, the raster
    (same GSD) grown or shrunk with them.

    A frame projected from a wrongly assumed height above ground is the true ground image
    shrunk about the nadir point by assumed over true height: ``factor`` = true over assumed
    restores it (:func:`~terrain_nav_ros.core.camera.pose_free.scale_range`)."""
    g = minutiae.georef
    if g is None:
        raise ValueError("rescaled_view: the camera set has no georeference")
    if factor == 1.0:
        return minutiae, creases, ridges
    ax, ay = float(anchor[0]), float(anchor[1])
    width, height = max(1, int(round(g.width * factor))), max(1, int(round(g.height * factor)))
    west, _, _, north = g.extent
    new = GeoReference(ax + (west - ax) * factor, ay + (north - ay) * factor, g.gsd, width,
                       height)
    east, north_ = g.pixel_to_enu(minutiae.col, minutiae.row)
    col, row = new.enu_to_pixel(ax + (east - ax) * factor, ay + (north_ - ay) * factor)
    moved = MinutiaSet(col, row, minutiae.angle, minutiae.kind, minutiae.quality,
                       georef=new, reason=minutiae.reason)
    return (moved, _rescaled_skeleton(creases, new.shape),
            _rescaled_skeleton(ridges, new.shape))


def mirrored_view(minutiae: MinutiaSet, creases, ridges, anchor, axis: float
                  ) -> tuple[MinutiaSet, np.ndarray | None, np.ndarray | None]:
    """A ground-projected camera set mirrored across the ground line through the ENU point
    ``anchor`` at ``axis`` (rad from East, counter-clockwise): the minutiae moved and turned
    exactly, the crease and ridge skeletons resampled and thinned again, on the raster (same
    GSD) that holds the mirrored footprint.

    A camera image flipped left to right (a driver's flip option, a mirror in the optics)
    projects, from a nadir camera, to its ground mirrored across the line along the image's
    columns through the nadir; mirrored back across it, it lies on the terrain again."""
    g = minutiae.georef
    if g is None:
        raise ValueError("mirrored_view: the camera set has no georeference")
    ax, ay = float(anchor[0]), float(anchor[1])
    c2, s2 = math.cos(2.0 * axis), math.sin(2.0 * axis)

    def mirrored(east, north):
        de, dn = np.asarray(east, float) - ax, np.asarray(north, float) - ay
        return ax + c2 * de + s2 * dn, ay + s2 * de - c2 * dn

    west, east_edge, south, north_edge = g.extent
    ce, cn = mirrored([west, east_edge, east_edge, west], [north_edge, north_edge, south, south])
    new = GeoReference(float(ce.min()), float(cn.max()), g.gsd,
                       max(1, int(math.ceil((ce.max() - ce.min()) / g.gsd - 1e-9))),
                       max(1, int(math.ceil((cn.max() - cn.min()) / g.gsd - 1e-9))))
    east, north = g.pixel_to_enu(minutiae.col, minutiae.row)
    col, row = new.enu_to_pixel(*mirrored(east, north))
    moved = MinutiaSet(col, row, 2.0 * axis - minutiae.angle, minutiae.kind,
                       minutiae.quality, georef=new, reason=minutiae.reason)
    # the pixel map of the mirror, from three raster points (its own inverse)
    src = np.float32([[0, 0], [g.width - 1, 0], [0, g.height - 1]])
    dst = np.float32(np.stack(new.enu_to_pixel(*mirrored(*g.pixel_to_enu(src[:, 0],
                                                                         src[:, 1]))), 1))
    warp = cv2.getAffineTransform(src, dst)

    def skeleton(s):
        if s is None:
            return None
        moved_s = cv2.warpAffine(np.asarray(s, np.float32), warp, (new.width, new.height),
                                 flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return skeletonize_creases(moved_s > 0.0)

    return moved, skeleton(creases), skeleton(ridges)


def relocalise_ladder(matcher: Matcher, cameras: Sequence[MinutiaIndex],
                      tiles: Sequence[SearchTile], *, ambiguity_margin: float = 2.0,
                      same_place_px: float = 10.0) -> tuple[Relocalisation, int]:
    """Search one frame's views at several scales (:func:`rescaled_view` at the factors of
    :func:`scale_ladder`) in every tile; the best registration over all of them if it is
    significant and unambiguous, and the index of its view (-1 without one).

    Every view is one more search of the area, so the area score pays ``log10(tiles x
    views)`` (:func:`relocalise`'s ``searches``); registrations at other places in any view
    within ``ambiguity_margin`` decades of the best make the answer ambiguous."""
    if not cameras:
        raise ValueError("relocalise_ladder: no camera views")
    if not tiles:
        return relocalise(matcher, cameras[0], tiles), -1
    n = len(cameras)
    union, rung, searched, best_seen = [], {}, 0, -np.inf
    for i, camera in enumerate(cameras):
        found = relocalise(matcher, camera, tiles, ambiguity_margin=ambiguity_margin,
                           same_place_px=same_place_px, searches=n)
        searched += found.searched
        penalty = found.penalty   # the same for every view: log10(tiles x views)
        best_seen = max(best_seen, found.score)
        for candidate in found.candidates:
            rung[id(candidate[2])] = i
            union.append(candidate)
    if not union:
        reason = (f"no significant match in the mission area (best {best_seen:.1f} < "
                  f"{matcher.params.threshold:g} over {len(tiles)} tiles at {n} scales)")
        return Relocalisation(MatchResult(Decision.NO_MATCH, reason=reason), score=best_seen,
                              penalty=penalty, searched=searched, reason=reason), -1
    found = _verdict(union, tiles, penalty, searched, ambiguity_margin,
                     same_place_px * tiles[0].georef.gsd)
    return found, rung[id(found.result)]
