"""Registrations proposed by the crease search (step 7 of :mod:`.matcher`).

When the search runs (a set with too few minutiae for the pair votes; the view search of a
view in its region), at which level (:mod:`.crease_search`), and its proposals moved onto the
reference's creases.
"""

from __future__ import annotations

import math

import numpy as np

from .crease_check import CreaseSamples, crease_covariance, refine_on_creases
from .crease_search import (
    COARSE,
    FINE,
    LEVELS,
    CreaseSearchResult,
    SearchLevel,
    local_peaks,
    min_search_work,
    search_transforms,
)
from .index import MinutiaIndex
from .params import MatchParams
from .registration import _pair
from .scoring import _ridge_channel


def _search_level(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                  scale_change: float = 0.0) -> SearchLevel:
    """The crease search's level: fine unless its work there exceeds the fine budget."""
    fine = a.crease_search_query(p.max_rotation, FINE, scale_change).work(b.crease_image.shape)
    return FINE if fine <= p.crease_search_fine_work else COARSE


def _searches_creases(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                      scale_change: float = 0.0) -> bool:
    """Whether the crease search runs: too few minutiae for the pair votes, a query small
    enough for its rotations, and a search within the work bound."""
    if min(a.n, b.n) >= p.crease_search_below or max(a.crease_image.shape) \
            > p.crease_search_max_side:
        return False
    level = _search_level(a, b, p, scale_change)
    return a.crease_search_query(p.max_rotation, level, scale_change).work(
        b.crease_image.shape) <= p.crease_search_max_work


# rotations x scales the view search rasterises at one level at most: a 256 px view's fine
# level (~300 rotations x 11 scales of ~5000 crease pixels) would take ~0.5 GB
_VIEW_SEARCH_MAX_TRANSFORMS = 4096


def _view_search_level(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> SearchLevel | None:
    """The finest level at which the view search (``MatchParams.view_search``) of A in B
    fits the work bound, or None."""
    for level in LEVELS:
        rotations, scales = a.crease_search_transforms(p.max_rotation, level,
                                                       p.search_scale)
        n_transforms = len(rotations) * len(scales)
        if n_transforms > _VIEW_SEARCH_MAX_TRANSFORMS or min_search_work(
                n_transforms, b.crease_image.shape, level.resolution) \
                > p.crease_search_max_work:
            continue   # too many rasters or too much work for this level: try a coarser one
        query = a.crease_search_query(p.max_rotation, level, p.search_scale)
        if query.work(b.crease_image.shape) <= p.crease_search_max_work:
            return level
    return None


def _crease_search_registrations(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                                 level: SearchLevel | None = None,
                                 scale_change: float = 0.0, background: float = 0.0):
    """Registrations (c, t, pairings) proposed by the crease search, each moved onto B's
    creases (they may have fewer than two minutiae pairings), and log10 of the transforms
    searched (at the fine level's rotations and scales: a coarse proposal is refined over
    them). ``level`` defaults to :func:`_search_level`'s; ``scale_change`` and
    ``background`` are the view search's (:class:`~.params.MatchParams`). A COARSE level's
    candidates are ranked again at the fine level (:func:`_fine_level_registrations`)."""
    level = level or _search_level(a, b, p, scale_change)
    found = _crease_search(a, b, p, level, scale_change, background)
    if level == COARSE:
        registered = _fine_level_registrations(a, b, p, found, scale_change, background)
    else:
        registered = _registered(a, b, p, found.proposals, level, scale_change)
    return registered, found.log10_transforms


def _crease_search(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, level: SearchLevel,
                   scale_change: float, background: float) -> CreaseSearchResult:
    """The crease search of A in B at ``level``: its proposals, strongest first (a coarse
    level's twice as many; at the COARSE level ``crease_search_candidates`` of them, the
    first of which are those, for the fine level to rank)."""
    fine_rotations, fine_scales = a.crease_search_transforms(p.max_rotation, FINE,
                                                             scale_change)
    return search_transforms(
        a.crease_search_query(p.max_rotation, level, scale_change),
        b.crease_search(level, background),
        n_best=_n_proposals(level, p), hit_radius=p.crease_radius,
        distinct_rotations=len(fine_rotations) * len(fine_scales),
        n_out=p.crease_search_candidates if level == COARSE else None)


def _fine_level_registrations(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                              found: CreaseSearchResult, scale_change: float,
                              background: float) -> list:
    """A COARSE search's candidates (``found``) ranked again at the fine level
    (:func:`_finer_proposals`), the best moved onto B's creases by the fine ICP."""
    proposals = _finer_proposals(a, b, p, found.proposals, scale_change, background,
                                 _n_proposals(COARSE, p))
    return _registered(a, b, p, proposals, FINE, scale_change)


def _n_proposals(level: SearchLevel, p: MatchParams) -> int:
    """Proposals a search at ``level`` refines: twice as many at a coarse level."""
    return p.crease_search_proposals * (2 if level != FINE else 1)


#: How far beyond the searched scales the crease ICP may fit a registration's scale.
SCALE_FIT_MARGIN = 0.05


def _registered(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, proposals,
                level: SearchLevel, scale_change: float) -> list:
    """``proposals`` (c, t, hits), placed at ``level``, moved onto B's creases with their
    pairings: by the fine ICP, after the wider radii when placed at a coarse level."""
    radii = p.crease_rescue_radii if level != FINE else (3.0,)
    out, reached = [], []
    ridges = _ridge_channel(a, b, p)
    # the ICP may fit a little beyond the search: a view the prior put at the search's edge
    # is fitted where it is, and one further off stops at this bound, where the matcher
    # refuses it (SCALE_FIT_MARGIN)
    reach = scale_change + SCALE_FIT_MARGIN
    scale = (1.0 - reach, 1.0 + reach) if scale_change > 0 else None
    for c, t, _ in proposals:
        for k, radius in enumerate(radii):
            c, t = refine_on_creases(_icp_samples(a, radius), b.crease_field, c, t,
                                     radius=radius, angle_tol=p.crease_angle_tol,
                                     ridges=ridges, scale=scale)
            if k == 0 and len(radii) > 1:
                # proposals the first radius brings to the same place would go on alike:
                # one is refined and scored (and counted in the best-of-n), not each
                if any(_same_transform(a, c, t, c2, t2) for c2, t2 in reached):
                    break
                reached.append((c, t))
        else:
            out.append((c, t, _pair(a, b, c, t, p)))
    return out


# A registration's scale is known to no better than this many pixels over the RMS radius
# of the view's creases (measured_scale).
CREASE_SCALE_FLOOR_PX = 0.25


def measured_scale(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, c: complex, t: complex,
                   scale_change: float) -> tuple[float, float]:
    """The view's scale against the region and its variance: the fine crease ICP from the
    registration ``(c, t)`` with the scale free (within the search's reach), and the crease
    covariance there. A registration fitted rigidly (the minutiae's) carries the prior's
    scale; this one measures the height above ground. NaN when the creases do not fix it."""
    reach = scale_change + SCALE_FIT_MARGIN
    c, t = refine_on_creases(_icp_samples(a, 3.0), b.crease_field, c, t, radius=3.0,
                             angle_tol=p.crease_angle_tol, ridges=_ridge_channel(a, b, p),
                             scale=(1.0 - reach, 1.0 + reach))
    cov = crease_covariance(a.crease_samples, b.crease_field, c, t, **p.crease_tolerances)
    if not np.isfinite(cov).all() or abs(abs(c) - 1.0) >= reach - 1e-3:
        return math.nan, math.nan      # not fixed by the creases, or stopped at the bound
    gradient = np.array([c.real, c.imag]) / abs(c)      # d|c| / d(a, b)
    # at least a quarter pixel across the view: its crease pixels are not independent (the
    # render's shading and the camera's albedo move whole creases), which the covariance
    # takes them for (the short bag's 512 px frames: 0.1 % scatter against 0.04 % claimed)
    z = a.crease_samples.z
    floor = (CREASE_SCALE_FLOOR_PX / max(float(np.sqrt(np.mean(np.abs(z - z.mean()) ** 2))),
                                         1.0)) ** 2
    return float(abs(c)), max(float(gradient @ cov[:2, :2] @ gradient), floor)


def _finer_proposals(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, proposals,
                     scale_change: float, background: float, n_best: int):
    """A COARSE search's ``n_best`` proposals: its candidates searched again near their
    place at the fine level (:func:`_placed_finer`), the most hits first, one per place.

    Every candidate over the fine rotations and scales next to its own and the shifts
    within half a coarse cell, then the best few again around their best, within a fine
    pixel (the two steps reach two fine steps of rotation and scale off).
    """
    placed = _placed_finer(a, b, p, proposals, COARSE, FINE, scale_change, background)
    best = _strongest_distinct(a, placed, _FINE_RECHECKED * n_best)
    return _strongest_distinct(a, _placed_finer(a, b, p, best, COARSE, FINE, scale_change,
                                                background, span=1), n_best)


def _placed_finer(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, proposals,
                  level: SearchLevel, finer: SearchLevel, scale_change: float,
                  background: float, span: int | None = None) -> list:
    """Each of the proposals of a search at ``level`` at the best transform near it at the
    ``finer`` level (:func:`~.crease_search.local_peaks`): the finer level's rotations and
    scales next to its own, at the shifts within half of ``level``'s cell (or within
    ``span`` of the finer level's pixels). A large query's samples are thinned to a few
    hundred, evenly along its creases; the background (in ``level``'s pixels, as the
    search's) keeps its extent in image pixels."""
    rotations, scales = a.crease_search_transforms(p.max_rotation, finer, scale_change)
    stride = math.ceil(len(a.crease_samples) / _FINE_LEVEL_SAMPLES)
    samples = a.crease_samples_strided(stride) if stride > 1 else a.crease_samples
    reference = b.crease_search(finer, background * finer.resolution / level.resolution)
    if span is None:
        span = int(math.ceil(0.5 * level.rotation_tolerance * finer.resolution))
    return local_peaks(samples, reference, proposals, _step(rotations), _step(scales),
                       span=span)


# Candidates per proposal that the fine level's second step searches again.
_FINE_RECHECKED = 2
# The fine level looks up at most about this many of a query's crease samples (every k-th):
# a few hundred place a view (the ICP and the score then take them all), and the hits of 48
# candidates at 225 transforms each cost ~1 ns a sample; fewer vary too much from one
# thinning to the next.
_FINE_LEVEL_SAMPLES = 600


def _step(values: np.ndarray) -> float:
    """The step of evenly spaced ``values`` (0 for one)."""
    return float(np.ptp(values)) / max(len(values) - 1, 1)


def _strongest_distinct(a: MinutiaIndex, proposals, n: int) -> list:
    """The ``n`` proposals with the most hits, one per place (2 px apart)."""
    out = []
    for c, t, hits in sorted(proposals, key=lambda f: -f[2]):
        if not any(_same_transform(a, c, t, c2, t2, 2.0) for c2, t2, _ in out):
            out.append((c, t, hits))
            if len(out) == n:
                break
    return out


# The crease ICP at a pairing radius of at least _SPARSE_ICP_RADIUS px (the wide radii that
# only bring a coarse proposal within the fine radii's reach) uses every other crease pixel
# of a view with more than _SPARSE_ICP_ABOVE: neighbouring skeleton pixels put the same
# constraint on the transform, and a few thousand place it as well as twice as many.
_SPARSE_ICP_RADIUS = 8.0
_SPARSE_ICP_ABOVE = 2000


def _icp_samples(a: MinutiaIndex, radius: float) -> CreaseSamples:
    """A's crease samples for the crease ICP at ``radius`` (see _SPARSE_ICP_RADIUS)."""
    if radius >= _SPARSE_ICP_RADIUS and len(a.crease_samples) > _SPARSE_ICP_ABOVE:
        return a.crease_samples_strided(2)
    return a.crease_samples


def _same_transform(a: MinutiaIndex, c: complex, t: complex, c2: complex, t2: complex,
                    tolerance: float = 1.0) -> bool:
    """Whether two transforms of A map its crease pixels within ``tolerance`` px of each
    other (at the crease reach from their mean)."""
    return abs(c - c2) * a.crease_reach + abs((c - c2) * a.crease_centre + t - t2) \
        <= tolerance
