"""Registrations proposed by the crease search (step 7 of :mod:`.matcher`).

When the search runs (a set with too few minutiae for the pair votes; the view search of a
view in its region), at which level (:mod:`.crease_search`), and its proposals moved onto the
reference's creases.
"""

from __future__ import annotations

from .crease_check import CreaseSamples, refine_on_creases
from .crease_search import (
    COARSE,
    FINE,
    LEVELS,
    SearchLevel,
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
    ``background`` are the view search's (:class:`~.params.MatchParams`)."""
    level = level or _search_level(a, b, p, scale_change)
    coarse = level != FINE
    fine_rotations, fine_scales = a.crease_search_transforms(p.max_rotation, FINE,
                                                             scale_change)
    found = search_transforms(
        a.crease_search_query(p.max_rotation, level, scale_change),
        b.crease_search(level, background),
        n_best=p.crease_search_proposals * (2 if coarse else 1), hit_radius=p.crease_radius,
        distinct_rotations=len(fine_rotations) * len(fine_scales))
    out, reached = [], []
    ridges = _ridge_channel(a, b, p)
    scale = (1.0 - scale_change, 1.0 + scale_change) if scale_change > 0 else None
    radii = p.crease_rescue_radii if coarse else (3.0,)
    for c, t, _ in found.proposals:
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
    return out, found.log10_transforms


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
    centre = a.crease_samples.z.mean()
    return abs(c - c2) * a.crease_reach + abs((c - c2) * centre + t - t2) <= tolerance
