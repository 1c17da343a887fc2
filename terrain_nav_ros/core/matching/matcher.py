"""Minutiae-based terrain matching and localisation (dissertation chapter 4).

Pipeline (same for block-vs-block :func:`compare` and camera-in-region :func:`localise`):

1. **Candidates.** Edge correspondences (a pair of minutiae in A matched to a pair in B whose
   length and two relative angles agree; see :mod:`.descriptors`). Two generators:
   ``"hash"`` looks every edge of A up in a hash of B's edges (complete, best for blocks);
   ``"roots"`` first picks, for each minutia of A, the ``k_roots`` minutiae of B with the most
   similar shape context descriptor and compares only their local edges (the
   reference-pair selection of dissertation 4.2.2; bounded cost for a large landmark region).
   Every candidate is a minimal sample: two point correspondences fix a similarity transform.
   Its vote is weighted by the descriptor similarity of both correspondences.
2. **Consensus.** Hough voting of the candidate rotations, then of the translations at each
   rotation peak; the strongest (rotation, translation) cells give hypotheses with their
   supporting correspondences.
3. **Registration.** Vectorised 2-point RANSAC over each hypothesis' correspondences, least
   squares (complex Procrustes) on the inliers, then guided pairing over all minutiae and a
   final least-squares fit on the pairings, with a covariance from the residuals (from the
   creases' fit instead where the crease check placed the transform, step 6).
4. **Pairings** are one-to-one minutiae that agree within ``pos_tol`` px and ``angle_tol`` after
   the transform.
5. **Score** (see :func:`~.significance.significance`): ``-log10`` of the chance of pairings this
   many and this close (position and direction residuals) between unrelated minutiae, given the
   densities in the overlap, the tolerances and the size of the searched transform space.
   One threshold then means one false-match rate at any minutia count and any search area,
   which ``pairings`` or ``pairings**2/(n1*n2)`` do not give (both are inflated for small
   sets). :func:`~.significance.calibrate_threshold` sets the threshold from non-PVA scores.
6. **Crease check** (when both sets come with their crease skeletons,
   :mod:`.crease_check`): every registered hypothesis is refined and scored, the agreement of
   the crease pixels outside the paired minutiae's surroundings is added to its score (a
   binomial tail against the local chance of agreement), and the best total wins.
7. **Crease search** (:mod:`.crease_search`): when the smaller set has too few minutiae for
   their pair votes to propose the transform (a ~60 px block: 3-9 minutiae, 0-2 of them
   repeating), a brute-force FFT search over rotations and translations of the crease
   skeletons proposes more registrations, refined and scored by the crease check like the
   others. A search too large for the fine level (a block in its localisation region) runs
   at the coarse one, its proposals pulled onto the creases by the coarse-to-fine ICP. In a
   localisation it counts hits above the region's local crease density, as the view search
   does.
8. **Ridges** (when both sets carry ridge skeletons): the leader and its runners-up get their
   ridges' agreement added, and the best total wins; the best-of-n term pays for the choice.
   The ridges count given the valleys (:func:`~.crease_check.conditioned_on`): ridges lie
   between valleys, and in parallel drainage one alignment moves both.

All internal geometry is in the math frame ``z = col - 1j*row`` (see :mod:`.descriptors`);
results are reported in pixel coordinates.

This module is the front end (:class:`Matcher`, :func:`compare`, :func:`localise`) and the
choice among registrations; the steps live beside it: the settings in :mod:`.params`, the
prepared sets in :mod:`.index`, step 1 in :mod:`.proposals`, 2 in :mod:`.consensus`, 3 and 4
in :mod:`.registration`, 5 in :mod:`.significance` and :mod:`.scoring` (with 6 and 8), 7 in
:mod:`.crease_proposals`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

import cv2
import numpy as np

from ..features.minutia_set import MinutiaSet
from .consensus import _hypotheses
from .crease_check import CreaseEvidence, crease_covariance
from .crease_proposals import (
    SCALE_FIT_MARGIN,
    _crease_search,
    _crease_search_registrations,
    _fine_level_registrations,
    _n_proposals,
    _placed_finer,
    _registered,
    _same_transform,
    _search_level,
    _searches_creases,
    _view_search_level,
    measured_scale,
)
from .crease_search import COARSE, FINE, LEVELS, SearchLevel
from .index import MinutiaIndex, _as_index, _generator
from .params import MatchParams
from .proposals import _hash_votes, _root_votes, _Votes
from .registration import _covariance, _pixel_transform, _refine, _register
from .scoring import _has_ridges, _refined_on_creases, _Scored, _scored, with_ridge_evidence
from .significance import _best_possible_score, _log10_transforms


class Decision(StrEnum):
    """Outcome of a comparison."""

    MATCH = "match"
    NO_MATCH = "no_match"
    NO_DECISION = "no_decision"


@dataclass
class MatchResult:
    """Outcome of :func:`compare` or :func:`localise`.

    Attributes
    ----------
    decision : Decision
    score : float
        Significance score (see :func:`~.significance.significance`); -inf when nothing was
        registered.
    n_pairings : int
    pairings : ndarray, shape (m, 2)
        Index in A and index in B of each pairing.
    transform : ndarray, shape (2, 3)
        Pixel transform A -> B: ``[col', row'] = transform @ [col, row, 1]``; the form is
        ``[[a, b, tx], [-b, a, ty]]`` with ``a = s cos(theta)``, ``b = s sin(theta)``.
    rotation : float
        theta (rad), CCW in the north-up map (minutia angles grow by theta).
    scale : float
    scale_estimated : bool
        Whether the scale was fitted (else it is 1 by construction).
    scale_measured, scale_variance : float
        A localisation's scale with the scale free on the creases, whatever fitted the
        transform (:func:`~.crease_proposals.measured_scale`), and its variance: the height
        above ground the view was seen from, relative to the prior's. NaN when not measured.
    covariance : ndarray, shape (4, 4)
        Covariance of (a, b, tx, ty) from the fit residuals.
    rms : float
        RMS pairing residual (px).
    n_a, n_b : int
        Minutiae in each set.
    n_overlap : tuple of int
        Minutiae of A inside B's footprint and of B inside A's, after the transform.
    expected_chance : float
        Pairings expected by chance at this transform (Poisson mean).
    pairing_ratio : float
        ``n_pairings**2 / (n_overlap_a * n_overlap_b)``, the classical normalised count.
    creases : CreaseEvidence or None
        Agreement of the crease skeletons at the transform (its ``score`` is included in
        ``score``), when both sets came with crease images and the crease check is on.
    ridges : CreaseEvidence or None
        The same for the ridge skeletons, when the ridge check applied.
    reason : str
        Why the decision is "no decision" or "no match", for logs and messages.
    """

    decision: Decision
    score: float = -np.inf
    n_pairings: int = 0
    pairings: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.intp))
    transform: np.ndarray = field(default_factory=lambda: np.full((2, 3), np.nan))
    rotation: float = np.nan
    scale: float = np.nan
    scale_estimated: bool = False
    scale_measured: float = np.nan
    scale_variance: float = np.nan
    covariance: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    rms: float = np.nan
    n_a: int = 0
    n_b: int = 0
    n_overlap: tuple[int, int] = (0, 0)
    expected_chance: float = np.nan
    pairing_ratio: float = 0.0
    creases: CreaseEvidence | None = None
    ridges: CreaseEvidence | None = None
    reason: str = ""

    @property
    def matched(self) -> bool:
        """True when the decision is a match."""
        return self.decision == Decision.MATCH

    def apply(self, col, row) -> tuple[np.ndarray, np.ndarray]:
        """Map pixel coordinates of A into B."""
        col = np.asarray(col, float)
        row = np.asarray(row, float)
        m = self.transform
        return m[0, 0] * col + m[0, 1] * row + m[0, 2], m[1, 0] * col + m[1, 1] * row + m[1, 2]

    def point_covariance(self, col: float, row: float) -> np.ndarray:
        """2x2 covariance (px^2) of the image in B of pixel (col, row) of A."""
        j = np.array([[col, row, 1.0, 0.0], [row, -col, 0.0, 1.0]])
        return j @ self.covariance @ j.T


def _low(best: _Scored | None, n_scored: int, p: MatchParams) -> bool:
    """Whether a try is not clear enough, on the evidence the wider tries were tuned for
    (the ridges add to chance registrations too)."""
    return best is None or (best.score - (best.ridges.score if best.ridges else 0.0)
                            - math.log10(max(n_scored, 1))) < p.rescue_below


def _vote_try(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, rng, search_area: float,
              use_creases: bool):
    """The minutiae's first try: their votes for transforms (by root pairs or edge hashes,
    as B is indexed), and the best of the registrations the votes' hypotheses give with the
    registrations scored: ``(votes, best, scored)``."""
    votes = _root_votes(a, b, p) if _generator(b, p) == "roots" else _hash_votes(a, b, p)
    registered = _registrations(_hypotheses(votes, a, b, p), a, b, p, rng)
    best, scored = _best_registration(a, b, registered, search_area, p, use_creases)
    return votes, best, scored


def _registrations(hyps, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, rng):
    """Registrations (c, t, pairings) of the hypotheses that come near the strongest, with
    at least two pairings."""
    registered = []
    for h in hyps:
        if h.support < p.min_support_ratio * hyps[0].support:
            break   # a clear winner: weak cells cannot beat it
        registered.append(_register(h, a, b, p, rng))
    return [r for r in registered if len(r[2]) >= 2]


def _best_registration(a: MinutiaIndex, b: MinutiaIndex, registered, search_area: float,
                       p: MatchParams, use_creases: bool, searched=(),
                       search_trials: float = 0.0, scored=()) -> tuple[_Scored | None, list]:
    """The best registration, refined, and the scored ones it was chosen from (``scored``,
    already scored, among them): (None, []) without any."""
    if not use_creases:
        if not registered:
            return None, []
        # the first registration with the most pairings (hypotheses come strongest first)
        r = max(registered, key=lambda r: len(r[2]))
        best = _scored(a, b, *_refine(a, b, *r, p), search_area, a.radius, p, False)
        return best, [best]
    # every registration refined and scored with its crease agreement (the searched ones
    # are already on B's creases: a refit to their few minutiae pairings would undo that);
    # the search over them is paid for like any other (Bonferroni)
    scored = list(scored) + [_scored(a, b, *_refine(a, b, *r, p), search_area, a.radius, p,
                                     True) for r in registered]
    # a searched registration was picked among the search's transforms at the crease
    # resolution, not the minutiae's: it pays for those instead
    trials = search_trials - _log10_transforms(search_area, a.radius, p)
    scored += [replace(s, score=s.score - trials, search_penalty=trials) for s in (
        _scored(a, b, *r, search_area, a.radius, p, True) for r in searched)]
    if not scored:
        return None, []
    best = max(scored, key=lambda s: s.score)
    return _refined_on_creases(a, b, best, search_area, a.radius, p), scored


def _sweep_try(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, votes: _Votes, rng,
               best: _Scored | None, scored: list, search_area: float,
               use_creases: bool) -> _Scored | None:
    """The wider try of the minutiae's votes: hypotheses from every rotation cell, and the
    coarse-to-fine crease ICP of the best so far. Returns the best registration; the ones
    scored are added to ``scored``."""
    wider = _registrations(_hypotheses(votes, a, b, p, sweep=True), a, b, p, rng)
    other, other_scored = _best_registration(a, b, wider, search_area, p, use_creases)
    scored += other_scored
    best = _better(best, other)
    if best is not None and use_creases:
        best = _refined_on_creases(a, b, best, search_area, a.radius, p,
                                   radii=p.crease_rescue_radii)
    return best


# Registrations whose ridge agreement is weighed before the best is chosen: the leader on
# the other evidence and this many runners-up.
_RIDGE_RUNNERS_UP = 3


def _with_ridges_chosen(a: MinutiaIndex, b: MinutiaIndex, best: _Scored, scored: list,
                        search_area: float, p: MatchParams) -> _Scored:
    """``best`` or one of the runners-up among ``scored`` (refined on B's creases), whichever
    scores most with its ridge agreement added (:func:`~.scoring.with_ridge_evidence`).

    On real imagery the ridges often carry what the valleys and minutiae of a view lack
    (albedo edges dilute both), so a registration at the right place can trail a chance one
    on those alone and lead once its ridges count. The choice stays among the registrations
    scored, which the best-of-n term pays for. Nothing changes where the ridges scored every
    registration already (small sets) or are not there.
    """
    if best.ridges is not None or not _has_ridges(a, b, p):
        return best
    chosen = [best]
    for other in sorted(scored, key=lambda s: -s.score):
        if len(chosen) > _RIDGE_RUNNERS_UP:
            break
        if not any(_same_transform(a, other.c, other.t, c.c, c.t, 2.0) for c in chosen):
            chosen.append(other)
    top, plain = max(((with_ridge_evidence(a, b, c, p), c) for c in chosen),
                     key=lambda weighed: weighed[0].score)
    if plain is best:
        return top
    # a runner-up that leads: moved onto B's creases as the leader was, and weighed again
    moved = _refined_on_creases(a, b, plain, search_area, a.radius, p)
    return max(top, with_ridge_evidence(a, b, moved, p), key=lambda s: s.score)


def _view_try(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, level: SearchLevel,
              scored: list, search_area: float) -> _Scored | None:
    """The view search's try at ``level`` (:func:`_view_search_level`): its proposals, moved
    onto B's creases and scored (added to ``scored``). Returns the best registration.

    A coarse level's proposals get the coarse-to-fine ICP: a view's thousands of crease
    pixels rank its coarse peaks well enough, most of the time, and the fine level's
    ranking of its candidates (as a small set's search has) would add ~10 ms to every
    camera frame. It runs only when the ICP's best is not clear: a view of a hundred pixels
    with as many minutiae as a large one may place its coarse peak at the truth behind
    chance peaks, or a few pixels off, out of the ICP's reach."""
    found = _crease_search(a, b, p, level, p.search_scale, p.view_search_background)
    proposals = found.proposals[:_n_proposals(level, p)]
    # a coarser level's proposals placed at each finer level down to the coarse one first
    # (~1 ms a step): a proposal between two of the coarser level's scales (8 % apart) can
    # lead the ICP to a scale a few percent off along parallel creases (a 256 px view: 8.5
    # there, 77 at its truth)
    for coarser, finer in _pyramid_steps(level, COARSE):
        proposals = _placed_finer(a, b, p, proposals, coarser, finer, p.search_scale,
                                  p.view_search_background)
    searched = _registered(a, b, p, proposals, level, p.search_scale)
    view, view_scored = _best_registration(a, b, [], search_area, p, True, searched,
                                           found.log10_transforms)
    scored += view_scored
    if level == COARSE and _low(view, len(scored), p):
        finer = _fine_level_registrations(a, b, p, found, p.search_scale,
                                          p.view_search_background)
        other, other_scored = _best_registration(a, b, [], search_area, p, True, finer,
                                                 found.log10_transforms)
        scored += other_scored
        view = _better(view, other)
    return view


def _pyramid_steps(level: SearchLevel, down_to: SearchLevel) -> list:
    """The (coarser, finer) pairs of :data:`~.crease_search.LEVELS` from ``level`` down to
    ``down_to``, coarsest first (none when ``level`` is not coarser)."""
    i, j = LEVELS.index(level), LEVELS.index(down_to)
    return [(LEVELS[k], LEVELS[k - 1]) for k in range(i, j, -1)]


#: log10 of the likelihood ratio within which a registration at another place makes the best
#: ambiguous: a look-alike of the view's terrain (repeated relief, a ridge along its strike).
LOOK_ALIKE_MARGIN = 1.0
#: Registrations at other places (the strongest, as scored) weighed as the best was before
#: the best is taken for unambiguous.
_LOOK_ALIKE_CANDIDATES = 3


def _look_alike(a: MinutiaIndex, b: MinutiaIndex, best: _Scored, scored: list,
                search_area: float, p: MatchParams) -> tuple[_Scored, float] | None:
    """The strongest registration that puts the view at another place (its creases' centre
    a quarter of their reach or more from ``best``'s) and, weighed as ``best`` was, scores
    within :data:`LOOK_ALIKE_MARGIN` of it; with that distance (px). None if there is none.

    ``scored`` holds the registrations as the search scored them; ``best`` has since been
    moved onto B's creases and, on a large set, had its ridges weighed, which can add tens
    to a score. So the strongest at other places are moved and weighed too before they are
    compared with it: like with like (compared as scored, two chance registrations at -1
    would veto one at 19)."""
    apart = max(5.0, 0.25 * a.crease_reach)

    def distance(s: _Scored) -> float:
        return abs((s.c - best.c) * a.crease_centre + s.t - best.t)

    candidates = []
    for s in sorted(scored, key=lambda s: -s.score):
        if len(candidates) == _LOOK_ALIKE_CANDIDATES:
            break
        if distance(s) > apart and \
                not any(_same_transform(a, s.c, s.t, c.c, c.t, 2.0) for c in candidates):
            candidates.append(s)
    strongest = None
    for s in candidates:
        weighed = _refined_on_creases(a, b, s, search_area, a.radius, p)
        if best.ridges is not None:
            weighed = with_ridge_evidence(a, b, weighed, p)
        if distance(weighed) > apart and weighed.score >= best.score - LOOK_ALIKE_MARGIN \
                and (strongest is None or weighed.score > strongest.score):
            strongest = weighed
    return None if strongest is None else (strongest, distance(strongest))


def _better(best: _Scored | None, other: _Scored | None) -> _Scored | None:
    """The one of two registrations (either may be None) that scores more."""
    if other is not None and (best is None or other.score > best.score):
        return other
    return best


class Matcher:
    """Minutiae matcher (settings in the constructor, scikit-image style).

    Parameters
    ----------
    params : MatchParams, optional
    **overrides
        Fields of :class:`MatchParams` to change, e.g. ``Matcher(threshold=4.0)``.
    """

    def __init__(self, params: MatchParams | None = None, **overrides):
        self.params = replace(params or MatchParams(), **overrides)
        # every comparison draws the same RANSAC samples: one generator, rewound to its
        # seeded state (a new default_rng per comparison costs ~15 us)
        self._rng = np.random.default_rng(self.params.seed)
        self._rng_start = self._rng.bit_generator.state

    def index(self, ms: MinutiaSet, crease: np.ndarray | None = None,
              ridges: np.ndarray | None = None) -> MinutiaIndex:
        """Prepare a set (with its crease and ridge skeletons) for repeated matching."""
        return MinutiaIndex(ms, self.params, crease, ridges)

    def compare(self, a, b, crease_a=None, crease_b=None) -> MatchResult:
        """Block-vs-block similarity.

        Parameters
        ----------
        a, b : MinutiaSet or MinutiaIndex
        crease_a, crease_b : ndarray, optional
            Crease images (used only when building indexes here; ridge skeletons come
            with indexes, :meth:`index`).

        Returns
        -------
        MatchResult
            Transform maps A pixels to B pixels.
        """
        a = _as_index(a, self.params, crease_a)
        b = _as_index(b, self.params, crease_b)
        ra = float(np.sqrt(a.area / math.pi))
        rb = float(np.sqrt(b.area / math.pi))
        search = math.pi * (ra + rb) ** 2   # centre offsets with any overlap
        return self._match(a, b, search, localising=False)

    def localise(self, camera, landmark, crease_camera=None,
                 crease_landmark=None) -> MatchResult:
        """Find a camera minutia set inside a (much larger) landmark region.

        Parameters
        ----------
        camera : MinutiaSet or MinutiaIndex
        landmark : MinutiaSet or MinutiaIndex
            Build a :class:`~.index.MinutiaIndex` once when the same region serves several frames.

        Returns
        -------
        MatchResult
            Transform maps camera pixels to landmark pixels, with covariance; use
            :meth:`MatchResult.point_covariance` for e.g. the image centre.
        """
        a = _as_index(camera, self.params, crease_camera)
        b = _as_index(landmark, self.params, crease_landmark)
        if a.n == 0 and a.set.reason and (a.crease_image is None or not a.crease_image.any()):
            # nothing to match, and the extractor has said why (cloud, no drainage)
            return MatchResult(Decision.NO_DECISION, n_b=b.n,
                               reason=f"no camera minutiae: {a.set.reason}")
        return self._match(a, b, max(b.area, 1.0), localising=True)

    def score_at(self, camera, landmark, transform) -> MatchResult:
        """What :meth:`localise` would answer had its crease search proposed ``transform``
        alone: the transform moved onto the landmark's creases by the fine ICP and scored
        as a searched registration, paying for every transform the search covers.

        A diagnostic: the evidence a view holds at a place (its true one), apart from
        whether the search finds it. A view lost although it scores above the threshold
        here is lost by the search; one below it, by its evidence.

        Parameters
        ----------
        camera, landmark : MinutiaSet or MinutiaIndex
            With creases (the crease search's input).
        transform : array_like, shape (2, 3)
            Camera px -> landmark px, of the form of :attr:`MatchResult.transform`.
        """
        p = self.params
        a = _as_index(camera, p)
        b = _as_index(landmark, p)
        base = MatchResult(Decision.NO_DECISION, n_a=a.n, n_b=b.n)
        if a.crease_image is None or b.crease_image is None or not len(a.crease_samples):
            base.reason = "no creases to score"
            return base
        m = np.asarray(transform, float)
        c, t = complex(m[0, 0], m[0, 1]), complex(m[0, 2], -m[1, 2])
        # the transforms the search covers (its proposals are not wanted here)
        level = _search_level(a, b, p, p.search_scale)
        trials = _crease_search(a, b, p, level, p.search_scale,
                                p.view_search_background).log10_transforms
        moved = _registered(a, b, p, [(c, t, 0.0)], FINE, p.search_scale)
        search_area = max(b.area, 1.0)
        best, scored = _best_registration(a, b, [], search_area, p, True, moved, trials)
        return self._result(a, b, base, best, scored, True, search_area)

    def _match(self, a: MinutiaIndex, b: MinutiaIndex, search_area: float,
               localising: bool) -> MatchResult:
        p = self.params
        base = MatchResult(Decision.NO_DECISION, n_a=a.n, n_b=b.n)
        use_creases = (p.crease_check and a.crease_image is not None
                       and b.crease_image is not None)
        # a view in its region: its scale is the prior's height above ground's, +-10 %
        scale_change = p.search_scale if localising else 0.0
        search = use_creases and _searches_creases(a, b, p, scale_change)
        if search:
            # the creases propose and carry the match: the rule is on their extent
            n_crease = (len(a.crease_samples), b.crease_field.n)
            if min(n_crease) < p.min_crease_pixels:
                base.reason = (f"too little drainage ({n_crease[0]}, {n_crease[1]} crease "
                               f"px; at least {p.min_crease_pixels} needed in each set): flat "
                               "terrain, water, cloud or haze")
                return base
        else:
            needed = max(p.min_minutiae_creases if use_creases else p.min_minutiae, 2)
            if min(a.n, b.n) < needed:
                base.reason = (f"too few minutiae ({a.n}, {b.n}); at least {needed} needed "
                               "in each set")
                return base
        radius_a = a.radius
        if not use_creases:   # with creases, the crease evidence can add what minutiae lack
            # B's minutiae that can fall under A (all of them for blocks of equal size)
            n_b_under_a = b.n * min(1.0, a.area / max(b.area, 1.0))
            best_possible = _best_possible_score(int(min(a.n, n_b_under_a)), a.n,
                                                 n_b_under_a, a.area, search_area, radius_a,
                                                 p, p.threshold)
            if best_possible < p.threshold:
                base.reason = ("too few minutiae: even a perfect match would score "
                               f"{best_possible:.2f} < threshold {p.threshold:.2f}")
                return base
        rng = self._rng
        rng.bit_generator.state = self._rng_start
        level = _view_search_level(a, b, p) if (
            localising and use_creases and p.view_search and not search) else None
        if level is not None:
            # a view the view search fits: the dense registration of the creases first (it
            # covers every rotation, scale and translation at the creases' resolution; on
            # real images the minutiae of albedo edges rarely repeat a render's), the
            # minutiae's votes only when it is not clear
            scored = []
            best = _view_try(a, b, p, level, scored, search_area)
            if _low(best, len(scored), p):
                _, other, vote_scored = _vote_try(a, b, p, rng, search_area, use_creases)
                scored += vote_scored
                best = _better(best, other)
            return self._result(a, b, base, best, scored, use_creases, search_area,
                                scale_change)
        votes, best, scored = _vote_try(a, b, p, rng, search_area, use_creases)
        low = _low(best, len(scored), p)
        if low and search:
            # the wider try of a set small enough for the crease search: it covers every
            # rotation and translation at the crease resolution (a sweep or a wide ICP would
            # only add chances to unrelated pairs); chosen together with the first try's
            # (a localisation counts hits above the region's local crease density, as the
            # view search does: dense drainage elsewhere in the region would outvote it)
            background = p.view_search_background if localising else 0.0
            searched, trials = _crease_search_registrations(a, b, p, None, scale_change,
                                                            background)
            best, scored = _best_registration(a, b, [], search_area, p, use_creases,
                                              searched, trials, scored=scored)
        elif low:
            # (a view the view search fits was searched above: the sweep of the votes would
            # only add chances to it)
            best = _sweep_try(a, b, p, votes, rng, best, scored, search_area, use_creases)
        return self._result(a, b, base, best, scored, use_creases, search_area,
                            scale_change)

    def _result(self, a: MinutiaIndex, b: MinutiaIndex, base: MatchResult,
                best: _Scored | None, scored: list, use_creases: bool,
                search_area: float, scale_change: float = 0.0) -> MatchResult:
        """The decision on the best registration of the ``scored`` ones, with its
        covariance."""
        p = self.params
        base.decision = Decision.NO_MATCH
        if best is None:
            base.reason = "no consistent transform"
            return base
        of_n = math.log10(max(len(scored), 1))   # the best of n registrations scored
        chosen = best       # as weighed, before the correction, to compare look-alikes with
        if use_creases:
            chosen = _with_ridges_chosen(a, b, best, scored, search_area, p)
            best = replace(chosen, score=chosen.score - of_n)
        c, t, pairs, score = best.c, best.t, best.pairs, best.score
        n_ao, n_bo = best.n_overlap
        cov, rms = _covariance(a.z[pairs[:, 0]], b.z[pairs[:, 1]], c, t, p.estimate_scale,
                               p.pos_tol)
        if use_creases:
            cov = _doubt_on_creases(a, b, c, t, cov, len(pairs), p)
        ok = score >= p.threshold
        reason = "" if ok else f"score {score:.2f} below threshold {p.threshold:.2f}"
        fitted_scale = abs(c)
        if ok and scale_change > 0 and \
                abs(fitted_scale - 1.0) >= scale_change + SCALE_FIT_MARGIN - 1e-3:
            # stopped at the fit's bound: the view's scale is off the prior by more than it
            # allows (a wrong height above ground), or the fit is of nothing
            ok = False
            reason = (f"scale {fitted_scale:.3f} at the edge of the fit (the prior's "
                      f"+-{scale_change:.0%} and {SCALE_FIT_MARGIN:.0%} more): the height "
                      "above ground is off, or the view is not of this place")
        look_alike = _look_alike(a, b, chosen, scored, search_area, p) \
            if ok and use_creases else None
        if look_alike is not None:
            ok, (other, distance) = False, look_alike
            reason = (f"ambiguous: another place {distance:.0f} px away scores "
                      f"{other.score - of_n:.1f}, within {LOOK_ALIKE_MARGIN:g} of the best "
                      f"({score:.1f}): repeated terrain")
        measured = measured_scale(a, b, p, c, t, scale_change) \
            if ok and use_creases and scale_change > 0 else (np.nan, np.nan)
        return MatchResult(
            decision=Decision.MATCH if ok else Decision.NO_MATCH, score=score,
            n_pairings=len(pairs), pairings=pairs, transform=_pixel_transform(c, t),
            rotation=float(np.angle(c)), scale=float(abs(c)),
            scale_estimated=p.estimate_scale, scale_measured=measured[0],
            scale_variance=measured[1], covariance=cov, rms=rms,
            n_a=a.n, n_b=b.n, n_overlap=(n_ao, n_bo), expected_chance=best.lam,
            pairing_ratio=len(pairs) ** 2 / max(n_ao * n_bo, 1), creases=best.creases,
            ridges=best.ridges, reason=reason)


def _doubt_on_creases(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex,
                      pairing_cov: np.ndarray, n_pairings: int, p: MatchParams) -> np.ndarray:
    """Covariance of a registration that the creases placed: their point-to-line fit's.

    With the crease check, the transform is the one B's creases agree with (moved onto them
    by their ICP, chosen by their agreement), so its doubt is theirs: hundreds of skeleton
    pixels that hold rotation and scale along the whole overlap. The few minutiae pairings'
    residuals against it (up to the pairing radius, on real imagery where albedo shifts the
    minutiae) made a covariance 5-10 x the fixes' errors on a long track mosaic, its rotation
    doubt times the lever to the newest nadir at the mosaic's end. The pairings' covariance
    stays where the creases do not fix the transform (too few agree, or all along one line)
    and there are pairings enough for one.
    """
    on_creases = crease_covariance(a.crease_samples, b.crease_field, c, t,
                                   **p.crease_tolerances)
    if np.isfinite(on_creases).all() or n_pairings < 3:
        return on_creases
    return pairing_cov


def compare(a, b, params: MatchParams | None = None, **overrides) -> MatchResult:
    """Block-vs-block comparison with default or given settings (see :class:`Matcher`)."""
    return Matcher(params, **overrides).compare(a, b)


def localise(camera, landmark, params: MatchParams | None = None,
             **overrides) -> MatchResult:
    """Camera-in-landmark-region localisation (see :meth:`Matcher.localise`)."""
    return Matcher(params, **overrides).localise(camera, landmark)


def warm_up(params: MatchParams | None = None) -> None:
    """Run every matching path once on small synthetic sets.

    With numba installed the kernels load from numba's cache (or compile) on first use,
    ~0.4 s in all; a node calls this at start-up so that its first frame is not late.
    """
    rng = np.random.default_rng(0)

    def random_set():
        crease = np.zeros((96, 96), np.uint8)
        for x0, y0, x1, y1 in rng.integers(0, 96, (14, 4)):
            cv2.line(crease, (int(x0), int(y0)), (int(x1), int(y1)), 1, 1)
        rows, cols = np.nonzero(crease)
        pick = rng.choice(len(rows), 40, replace=False)
        ms = MinutiaSet(cols[pick].astype(float), rows[pick].astype(float),
                        rng.uniform(-np.pi, np.pi, 40), rng.choice([1, 3], 40).astype(np.uint8),
                        np.ones(40, np.float32))
        return ms, crease

    matcher = Matcher(params)
    (ms, crease), other = random_set(), random_set()
    full = matcher.index(ms, crease)
    matcher.compare(full, full)                               # the first try
    matcher.compare(full, matcher.index(*other))              # the wider try
    few = matcher.index(ms.subset(np.arange(2)), crease)
    matcher.compare(few, full)          # the crease search and the crease covariance
    matcher.localise(few, full)         # ... over scales, and the ICP with the scale
    # ... at the coarse level, whose peaks the fine level ranks again
    coarse = Matcher(matcher.params, crease_search_fine_work=0)
    coarse.localise(coarse.index(ms.subset(np.arange(2)), crease), coarse.index(ms, crease))
    # the sweep of the votes: the wider try of sets too large for the crease search
    wide = Matcher(matcher.params, crease_search_below=0)
    wide.compare(wide.index(ms, crease), wide.index(*other))
