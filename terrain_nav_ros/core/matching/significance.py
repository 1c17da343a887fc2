"""Score of a registration (dissertation chapter 4, step 5 of :mod:`.matcher`).

``-log10`` of the chance of pairings this many and this close (position and direction
residuals) between unrelated minutiae, given the densities in the overlap, the tolerances and
the size of the searched transform space: one threshold then means one false-match rate at
any minutia count and any search area. :func:`calibrate_threshold` sets the threshold from
non-PVA scores.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaln

from . import _matching_kernels as _kernels
from .descriptors import TWO_PI
from .params import MatchParams


def pairing_evidence(dist, dang, p: MatchParams) -> np.ndarray:
    """Evidence of each pairing: ``-ln`` of the chance of a pairing at least this close.

    A chance pairing lies uniformly in the pairing disc and angle window, so
    ``u = (dist / pos_tol)**2`` and ``v = dang / angle_tol`` are uniform on (0, 1) and
    ``-ln u - ln v`` is Gamma(2, 1)-distributed. Residuals below ``pos_floor`` /
    ``angle_floor`` count as those floors (finer agreement is not evidence).
    """
    u = np.maximum(np.asarray(dist, float), p.pos_floor) ** 2 / p.pos_tol ** 2
    v = np.maximum(np.asarray(dang, float), p.angle_floor) / p.angle_tol
    return -np.log(np.minimum(u, 1.0)) - np.log(np.minimum(v, 1.0))


_LOG_FACTORIAL = gammaln(np.arange(4096) + 1.0)   # ln j!, grown on demand


def _log_factorial(n: int) -> np.ndarray:
    global _LOG_FACTORIAL
    if n > len(_LOG_FACTORIAL):
        _LOG_FACTORIAL = gammaln(np.arange(2 * n) + 1.0)
    return _LOG_FACTORIAL[:n]


def compound_log10_sf(evidence: float, lam: float) -> float:
    """log10 P(S >= evidence) for S the summed evidence of chance pairings.

    The number of chance pairings is Poisson(lam) and each adds an independent Gamma(2, 1)
    (see :func:`pairing_evidence`), so ``P(S >= s) = sum_k Pois(k; lam) Q(2k, s)`` with Q the
    regularised upper incomplete gamma function. For integer ``2k``, ``Q(2k, s)`` is the
    Poisson(s) distribution function at ``2k - 1``, so all of them come from one cumulative
    sum of Poisson(s) probabilities: exact, and cheap.
    """
    if evidence <= 0:
        return 0.0
    if lam <= 0:
        return -np.inf
    # terms beyond both the Poisson bulk and k ~ evidence / 2 (where Q -> 1) are negligible
    k_max = int(max(2.0 * lam + 10.0 * math.sqrt(lam),
                    0.5 * evidence + 5.0 * math.sqrt(evidence))) + 20
    log_fact = _log_factorial(2 * k_max + 2)
    if _kernels.HAVE_NUMBA:
        return float(_kernels.compound_log10_sf(float(evidence), float(lam), k_max, log_fact))
    # ... and so are those whose Poisson(lam) weight alone is e^-40 below the k = 1 term
    k = np.arange(1.0, k_max + 1.0)
    log_pois = k * math.log(lam) - lam - log_fact[1:k_max + 1]
    first = log_pois[0] - evidence + math.log1p(evidence)          # ln of the k = 1 term
    beyond = np.flatnonzero((log_pois < first - 40.0) & (k > lam))
    if len(beyond):
        k_max = int(beyond[0]) + 1
        k, log_pois = k[:k_max], log_pois[:k_max]
    j = np.arange(2 * k_max, dtype=float)
    log_pmf = j * math.log(evidence) - evidence - log_fact[:2 * k_max]   # Poisson(s) at j
    top = float(log_pmf.max())
    with np.errstate(divide="ignore"):
        log_q = np.log(np.cumsum(np.exp(log_pmf - top))[1::2]) + top  # Q(2k, s), k = 1..
    log_terms = log_pois + log_q
    lost = ~np.isfinite(log_q)   # Q below exp(-745) of the largest Poisson(s) term
    if lost.any() and np.max(log_pois[lost]) + top - 745.0 > np.max(log_terms) - 40.0:
        # the underflowed terms might matter (huge evidence): the same sums in log space
        log_q = np.logaddexp.accumulate(log_pmf)[1::2]
        log_terms = log_pois + log_q
    peak = float(np.max(log_terms))
    return (peak + math.log(float(np.sum(np.exp(log_terms - peak))))) / math.log(10.0)


def significance(dist, dang, n_a: float, n_b: float, area: float, search_area: float,
                 radius_a: float, p: MatchParams) -> tuple[float, float]:
    """Score of a registration: how unlikely its pairings are between unrelated sets.

    Under the null hypothesis (different places) the ``n_b`` minutiae of B in the overlap of
    ``area`` px^2 are unrelated to A's ``n_a``; each of A's minutiae then finds a partner
    within ``pos_tol`` and ``angle_tol`` with probability ``n_b * pi pos_tol^2 / area *
    angle_tol / pi``, so the number of chance pairings is about Poisson with mean ``lam``,
    and each lands uniformly in the pairing disc and angle window. The test statistic is the
    summed :func:`pairing_evidence` of the pairings (a likelihood-ratio form: many pairings,
    and pairings much closer than the tolerances, both count; true pairings have residuals
    of ~1-2 px and a few degrees, chance ones fill the tolerances). The matcher tried many
    transforms, so the tail probability is multiplied by the number of distinguishable
    transforms in the search space (``search_area / (pi pos_tol^2)`` translations times
    ``2 pi / (pos_tol / radius_a)`` rotations, a Bonferroni bound).

    Parameters
    ----------
    dist, dang : array_like
        Position (px) and direction (rad) residual of each pairing.
    n_a, n_b : float
        Minutiae of A and of B in the overlap.
    area, search_area : float
        Overlap area and area of the searched translations (px^2).
    radius_a : float
        RMS radius of A's minutiae about their centroid (px): sets the rotation resolution.
    p : MatchParams

    Returns
    -------
    score : float
        ``-log10(P(S >= s) * n_transforms)``: about the base-10 logarithm of how many
        comparisons of unrelated terrain it takes to see one this good by chance.
    lam : float
        The expected number of chance pairings.
    """
    return _significance(float(np.sum(pairing_evidence(dist, dang, p))), n_a, n_b, area,
                         search_area, radius_a, p)


def _significance(evidence: float, n_a, n_b, area, search_area, radius_a, p: MatchParams):
    """:func:`significance` from the summed pairing evidence."""
    lam, log_trials = _chance_model(n_a, n_b, area, search_area, radius_a, p)
    return -compound_log10_sf(evidence, lam) - log_trials, lam


def _chance_model(n_a, n_b, area, search_area, radius_a, p: MatchParams):
    """Chance pairings expected at one transform, and log10 of the transforms searched."""
    cell = math.pi * p.pos_tol ** 2
    lam = n_a * n_b * cell / max(area, cell) * min(1.0, p.angle_tol / math.pi)
    lam = min(lam, float(min(n_a, n_b)))
    return lam, _log10_transforms(search_area, radius_a, p)


def _log10_transforms(search_area, radius_a, p: MatchParams) -> float:
    """log10 of the transforms distinguishable at the pairing tolerance in the search."""
    cell = math.pi * p.pos_tol ** 2
    # rotations searched: the whole circle, or the prior's window (max_rotation)
    n_rot = min(TWO_PI, 2.0 * p.max_rotation + p.rot_bin) / min(
        math.pi, p.pos_tol / max(radius_a, p.pos_tol))
    n_rot = max(n_rot, 1.0)
    return math.log10(max(search_area / cell, 1.0) * n_rot)


def _best_possible_score(m: int, n_a, n_b, area, search_area, radius_a, p: MatchParams,
                         enough: float) -> float:
    """Score of ``m`` exact pairings, or a lower bound of it when that is ``>= enough``.

    The Chernoff bound ``P(S >= s) <= exp(-s / 2 + 3 lam)`` (the compound Poisson-Gamma(2)
    tail at exponent 1/2) spares the exact tail when the answer is clearly yes.
    """
    lam, log_trials = _chance_model(n_a, n_b, area, search_area, radius_a, p)
    evidence = m * float(pairing_evidence(0.0, 0.0, p))
    bound = (0.5 * evidence - 3.0 * lam) / math.log(10.0) - log_trials
    if bound >= enough:
        return bound
    return -compound_log10_sf(evidence, lam) - log_trials


def calibrate_threshold(non_pva_scores, false_match_rate: float) -> float:
    """Score threshold giving at most ``false_match_rate`` accepted non-PVA comparisons.

    With enough samples (``n * rate >= 1``) this is the empirical upper quantile (the
    smallest threshold with at most ``rate * n`` scores at or above it). Rarer rates are
    extrapolated with an exponential tail fitted to the top 10% of scores (peaks over
    threshold, generalised Pareto with zero shape), which the significance score follows
    when its chance model is right (P(score > s) ~ 10**-s).

    Parameters
    ----------
    non_pva_scores : array_like
        Scores of comparisons between different places (non-finite ones are ignored as
        "no registration").
    false_match_rate : float
        Accepted fraction of non-PVA comparisons, in (0, 1).

    Returns
    -------
    float
        The threshold (a score must be >= it to match).
    """
    s = np.sort(np.asarray(non_pva_scores, float))
    s = s[np.isfinite(s)]
    if not 0 < false_match_rate < 1:
        raise ValueError("calibrate_threshold: false_match_rate must be in (0, 1)")
    if len(s) == 0:
        raise ValueError("calibrate_threshold: no finite non-PVA scores")
    n = len(s)
    allowed = int(math.floor(false_match_rate * n))
    if allowed >= 1:
        return float(np.nextafter(s[n - allowed - 1], np.inf))
    n_tail = max(5, n // 10)
    if n < n_tail + 1:
        return float(np.nextafter(s[-1], np.inf))
    u = s[n - n_tail - 1]
    beta = max(float(np.mean(s[n - n_tail:] - u)), 1e-6)
    thr = u + beta * math.log((n_tail / n) / false_match_rate)
    return float(max(thr, np.nextafter(s[-1], np.inf)))
