"""A registration scored and moved onto the creases (steps 5 and 6 of :mod:`.matcher`).

The minutiae significance (:mod:`.significance`) of the pairings in the overlap of the two
footprints, plus the crease agreement of the crease check (:mod:`.crease_check`) and the
ridges' given it; and the registration refined on the reference's creases (point-to-line
ICP), kept when it scores better.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from . import _matching_kernels as _kernels
from .crease_check import CreaseEvidence, conditioned_on, crease_evidence, refine_on_creases
from .index import MinutiaIndex
from .params import MatchParams
from .registration import _pair, _residuals
from .significance import _significance, pairing_evidence


def _overlap(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex):
    """Minutiae of A inside B's footprint, of B inside A's (mapped), and the overlap area."""
    in_b = _inside(c * a.z + t, b.footprint_box)
    in_a = _inside((b.z - t) / c, a.footprint_box)
    return int(in_b.sum()), int(in_a.sum()), _overlap_area(a, b, c, t)


def _overlap_area(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex) -> float:
    """Area of A's footprint mapped into B, inside B's footprint."""
    fa_b = c * a.footprint_z + t
    # complex128 is (re, im) pairs in memory: the (n, 2) corner array without a stack
    area, _ = cv2.intersectConvexConvex(fa_b.view(np.float64).reshape(-1, 2)
                                        .astype(np.float32), b.footprint32)
    return float(area)


def _inside(z, box) -> np.ndarray:
    # footprints are axis-aligned rectangles in their own frame: box (x0, x1, y0, y1)
    x0, x1, y0, y1 = box
    return (z.real >= x0) & (z.real <= x1) & (z.imag >= y0) & (z.imag <= y1)


@dataclass(frozen=True)
class _Scored:
    """A refined registration and its score."""

    c: complex
    t: complex
    pairs: np.ndarray
    score: float
    lam: float
    n_overlap: tuple[int, int]
    creases: CreaseEvidence | None
    search_penalty: float = 0.0   # log10 of extra transforms searched, already in score
    ridges: CreaseEvidence | None = None


def _scored(a: MinutiaIndex, b: MinutiaIndex, c, t, pairs, search_area: float,
            radius_a: float, p: MatchParams, with_creases: bool) -> _Scored:
    """Minutiae significance of a registration, plus its crease evidence when asked."""
    if _kernels.HAVE_NUMBA:
        n_ao, n_bo, evidence = _kernels.registration_terms(
            a.z, b.z, a.angle, b.angle, pairs[:, 0], pairs[:, 1], complex(c), complex(t),
            float(np.angle(c)), a.footprint_box, b.footprint_box, float(p.pos_tol),
            float(p.angle_tol), float(p.pos_floor), float(p.angle_floor))
        area = _overlap_area(a, b, c, t)
    else:
        n_ao, n_bo, area = _overlap(a, b, c, t)
        evidence = float(np.sum(pairing_evidence(*_residuals(a, b, c, t, pairs), p)))
    n_ao, n_bo = max(n_ao, len(pairs)), max(n_bo, len(pairs))
    score, lam = _significance(evidence, n_ao, n_bo, area, search_area, radius_a, p)
    creases = ridges = None
    if with_creases:
        creases = crease_evidence(a.crease_samples, b.crease_field, c, t,
                                  skip=a.crease_samples_around(pairs[:, 0]),
                                  **p.crease_tolerances)
        score += creases.score
        ridge_channel = _ridge_channel(a, b, p)
        if ridge_channel is not None:
            ridges = conditioned_on(crease_evidence(*ridge_channel, c, t,
                                                    **p.crease_tolerances), creases)
            score += ridges.score
    return _Scored(c, t, pairs, score, lam, (n_ao, n_bo), creases, ridges=ridges)


def _has_ridges(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> bool:
    """Whether the ridge check can score this pair (on, and both sets with ridges)."""
    return p.ridge_check and a.ridge_image is not None and b.ridge_image is not None


def _ridge_channel(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams):
    """A's ridge samples and B's ridge field when the ridge check scores every registration
    (a small set), else None."""
    if _has_ridges(a, b, p) and min(a.n, b.n) < p.ridge_check_below:
        return a.ridge_samples, b.ridge_field
    return None


def with_ridge_evidence(a: MinutiaIndex, b: MinutiaIndex, best: _Scored,
                        p: MatchParams) -> _Scored:
    """``best`` with its ridge agreement added to its score, when the ridges did not score
    it already (a set of ``ridge_check_below`` minutiae or more).

    Minutiae counts stand in for the evidence a set carries, and on real imagery they do not:
    albedo edges (fields, roads, forest margins) add minutiae that pair with nothing in a
    render, while the valleys' and ridges' skeletons still agree. The chosen registration
    was picked on the other evidence alone, so its ridge agreement (given the valleys') is a
    check that adds no search (no Bonferroni term), at the cost of one evaluation (~0.2 ms).
    """
    if best.ridges is not None or not _has_ridges(a, b, p):
        return best
    ridges = conditioned_on(crease_evidence(a.ridge_samples, b.ridge_field, best.c, best.t,
                                            **p.crease_tolerances), best.creases)
    return replace(best, score=best.score + ridges.score, ridges=ridges)


def _refined_on_creases(a: MinutiaIndex, b: MinutiaIndex, best: _Scored, search_area: float,
                        radius_a: float, p: MatchParams, radii=(3.0,)) -> _Scored:
    """The registration moved onto B's creases (point-to-line ICP at each pairing radius in
    turn), kept if it scores better: a transform fitted to a few minutiae pairings is off by
    a pixel or two, the creases have hundreds of pixels. With the ridge check, the ICP on
    the valleys alone and the one on valleys and ridges together both try (parallel ridges
    can pull a joint ICP a ridge spacing off where the valleys alone would not)."""
    ridges = _ridge_channel(a, b, p)
    moved = best
    for channel in (None, ridges) if ridges is not None else (None,):
        c, t = best.c, best.t
        for radius in radii:
            c, t = refine_on_creases(a.crease_samples, b.crease_field, c, t, radius=radius,
                                     angle_tol=p.crease_angle_tol, ridges=channel)
        if c == best.c and t == best.t:
            continue
        pairs = _pair(a, b, c, t, p)
        if len(pairs) < 2:
            continue
        tried = _scored(a, b, c, t, pairs, search_area, radius_a, p, True)
        tried = replace(tried, score=tried.score - best.search_penalty,
                        search_penalty=best.search_penalty)
        if tried.score > moved.score:
            moved = tried
    return moved
