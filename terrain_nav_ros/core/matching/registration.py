"""Registration (dissertation chapter 4, steps 3 and 4 of :mod:`.matcher`).

Vectorised 2-point RANSAC over a hypothesis' correspondences, least squares (complex
Procrustes) on the inliers, guided one-to-one pairing of all minutiae within ``pos_tol`` and
``angle_tol``, alternate refits and re-pairings, and the covariance of the fitted transform
from the pairing residuals (corrected for the pairing radius' truncation).
"""

from __future__ import annotations

import math

import numpy as np

from . import _matching_kernels as _kernels
from .consensus import _Hypothesis
from .descriptors import from_complex, wrap_angle
from .index import MinutiaIndex
from .params import MatchParams


def fit_similarity(za, zb, w=None, scale: bool = False) -> tuple[complex, complex]:
    """Least-squares transform ``zb ~ c * za + t`` (complex Procrustes / Umeyama).

    Parameters
    ----------
    za, zb : ndarray of complex
        Corresponding points in the math frame.
    w : ndarray, optional
        Weights.
    scale : bool
        Estimate a scale (``|c|`` free) or a rigid motion (``|c| = 1``).

    Returns
    -------
    c, t : complex
        ``c`` is NaN when the points do not fix a rotation (e.g. all A or all B points
        coincide).
    """
    w = np.ones(len(za)) if w is None else np.asarray(w, float)
    ma = np.sum(w * za) / w.sum()
    mb = np.sum(w * zb) / w.sum()
    num = complex(np.sum(w * np.conj(za - ma) * (zb - mb)))
    if abs(num) < 1e-9:
        return complex(np.nan, np.nan), complex(np.nan, np.nan)
    if scale:
        c = num / float(np.sum(w * np.abs(za - ma) ** 2))
    else:
        c = num / abs(num)
    return complex(c), complex(mb - c * ma)


def _ransac(za, zb, dang, p: MatchParams, rng, c0: complex, t0: complex):
    """Best transform over 2-point samples (and the Hough guess); inlier mask."""
    m = len(za)
    n_it = min(p.ransac_iterations, m * (m - 1) // 2)
    i = j = np.zeros(0, np.int64)
    if n_it > 0:
        i = rng.integers(0, m, n_it)
        j = (i + rng.integers(1, m, n_it)) % m
    if _kernels.HAVE_NUMBA:
        return _kernels.ransac(za, zb, dang, i, j, complex(c0), complex(t0),
                               float(p.edge_min), bool(p.estimate_scale),
                               float(p.max_scale_change), float(p.pos_tol),
                               float(p.angle_tol))
    dz = za[j] - za[i]
    ok = (np.abs(dz) > p.edge_min) & (np.abs(zb[j] - zb[i]) > p.edge_min)
    c = (zb[j] - zb[i])[ok] / dz[ok]
    if not p.estimate_scale:
        c = c / np.abs(c)
    t = 0.5 * (zb[i] + zb[j])[ok] - c * 0.5 * (za[i] + za[j])[ok]
    cs, ts = np.concatenate([[c0], c]), np.concatenate([[t0], t])
    if p.estimate_scale:
        keep = np.abs(np.log(np.abs(cs))) <= p.max_scale_change
        keep[0] = True
        cs, ts = cs[keep], ts[keep]
    res = np.abs(cs[:, None] * za[None, :] + ts[:, None] - zb[None, :])
    ang = np.abs(wrap_angle(dang[None, :] - np.angle(cs)[:, None]))
    inl = (res <= p.pos_tol) & (ang <= p.angle_tol)
    best = int(np.argmax(inl.sum(axis=1)))
    return cs[best], ts[best], inl[best]


# reference sets up to this size are paired by brute force (numba) instead of the k-d tree
_BRUTE_PAIR_MAX = 400


def _pair(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex, p: MatchParams,
          k: int = 3):
    """One-to-one pairings (ia, ib) within tolerance after ``z -> c z + t``."""
    zt = c * a.z + t
    k = min(k, b.n)
    if _kernels.HAVE_NUMBA and b.n <= _BRUTE_PAIR_MAX:
        # a block-sized B: brute force in one loop beats the tree query and the filtering
        i, j, cost = _kernels.pair_candidates(zt.real, zt.imag, b.z.real, b.z.imag, a.angle,
                                              b.angle, float(np.angle(c)), k,
                                              float(p.pos_tol), float(p.angle_tol))
        return _greedy_one_to_one(i, j, cost)
    if _kernels.HAVE_NUMBA and a.n:
        # a view in a large region: B's points within reach of A's box (in B's order), by
        # brute force; a point of B out of the box by pos_tol or more is no candidate
        x, y, tol = zt.real, zt.imag, float(p.pos_tol)
        bx, by = b.z.real, b.z.imag
        near = np.flatnonzero((bx > x.min() - tol) & (bx < x.max() + tol)
                              & (by > y.min() - tol) & (by < y.max() + tol))
        if len(near) <= _BRUTE_PAIR_MAX:
            i, j, cost = _kernels.pair_candidates(x, y, bx[near], by[near], a.angle,
                                                  b.angle[near], float(np.angle(c)), k,
                                                  tol, float(p.angle_tol))
            return _greedy_one_to_one(i, near[j], cost)
    # complex128 is (re, im) pairs in memory: the (n, 2) point array without a copy
    d, j = b.tree.query(zt.view(np.float64).reshape(-1, 2), k=k,
                        distance_upper_bound=p.pos_tol)
    d, j = d.reshape(a.n, k), j.reshape(a.n, k)
    i = np.repeat(np.arange(a.n), k)
    d, j = d.ravel(), j.ravel()
    ok = np.isfinite(d)
    i, j, d = i[ok], j[ok], d[ok]
    dang = np.abs(wrap_angle(b.angle[j] - a.angle[i] - np.angle(c)))
    ok = dang <= p.angle_tol
    i, j = i[ok], j[ok]
    cost = d[ok] / p.pos_tol + dang[ok] / p.angle_tol
    return _greedy_one_to_one(i, j, cost)


def _residuals(a: MinutiaIndex, b: MinutiaIndex, c: complex, t: complex, pairs):
    """Leave-one-out position (px) and direction (rad) residuals of the pairings.

    ``c, t`` are a least-squares fit to these pairings, which pulls each pairing towards
    itself: with few pairings a chance coincidence would look tighter than it is. The
    position residual is therefore divided by ``1 - h`` (``h`` the pairing's leverage in
    the linear fit ``zb = c za + t``), which is the residual under the fit without it.
    """
    ia, ib = pairs[:, 0], pairs[:, 1]
    za = a.z[ia]
    dist = np.abs(c * za + t - b.z[ib])
    dang = np.abs(wrap_angle(b.angle[ib] - a.angle[ia] - np.angle(c)))
    m = len(za)
    if m > 2:
        spread = np.abs(za - za.mean()) ** 2
        leverage = 1.0 / m + spread / max(float(spread.sum()), 1e-12)
        dist = dist / np.maximum(1.0 - leverage, 1e-3)
    return dist, dang


def _greedy_one_to_one(i, j, cost, rounds: int = 3):
    """Greedy one-to-one matching by increasing cost, vectorised as rounds of mutual bests.

    In each round a candidate is taken when it is the cheapest remaining one of both its
    ends; taken ends are then removed. On these sparse graphs three rounds are the greedy
    result in practice.
    """
    if _kernels.HAVE_NUMBA:
        return _kernels.greedy_one_to_one(i, j, cost, rounds)
    n_i = int(i.max(initial=-1)) + 1
    n_j = int(j.max(initial=-1)) + 1
    if len(i) == 0 or (np.bincount(i, minlength=n_i).max() == 1
                       and np.bincount(j, minlength=n_j).max() == 1):
        return np.column_stack([i, j])   # already one-to-one (common at these densities)
    order = np.argsort(cost, kind="stable")
    i, j = i[order], j[order]
    out_i, out_j = [], []
    for _ in range(rounds):
        if len(i) == 0:
            break
        k = np.arange(len(i))
        first_i = np.empty(n_i, np.intp)
        first_i[i[::-1]] = k[::-1]      # the last write wins: first occurrence of each i
        first_j = np.empty(n_j, np.intp)
        first_j[j[::-1]] = k[::-1]
        take = (first_i[i] == k) & (first_j[j] == k)
        out_i.append(i[take])
        out_j.append(j[take])
        used_i = np.zeros(n_i, bool)
        used_i[i[take]] = True
        used_j = np.zeros(n_j, bool)
        used_j[j[take]] = True
        keep = ~used_i[i] & ~used_j[j]
        i, j = i[keep], j[keep]
    if not out_i:
        return np.zeros((0, 2), np.intp)
    return np.column_stack([np.concatenate(out_i), np.concatenate(out_j)])


def _register(h: _Hypothesis, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams, rng):
    """RANSAC + least squares on a hypothesis' correspondences; pairings over all minutiae."""
    key = np.unique(h.ia * b.n + h.ib)
    ia, ib = key // b.n, key % b.n
    c, t = h.c, h.t
    if len(ia) >= 2:
        c, t, inl = _ransac(a.z[ia], b.z[ib], b.angle[ib] - a.angle[ia], p, rng, h.c, h.t)
        if inl.sum() >= 2:
            c1, t1 = fit_similarity(a.z[ia[inl]], b.z[ib[inl]], scale=p.estimate_scale)
            if np.isfinite(c1):   # degenerate inliers (one point each side): keep RANSAC's
                c, t = c1, t1
    return c, t, _pair(a, b, c, t, p)


def _refine(a: MinutiaIndex, b: MinutiaIndex, c, t, pairs, p: MatchParams, iterations=2):
    """Alternate least squares on the pairings and guided re-pairing."""
    for _ in range(iterations):
        if len(pairs) < 2:
            break
        c1, t1 = fit_similarity(a.z[pairs[:, 0]], b.z[pairs[:, 1]], scale=p.estimate_scale)
        if not np.isfinite(c1) or (p.estimate_scale
                                   and abs(math.log(abs(c1))) > p.max_scale_change):
            break
        new = _pair(a, b, c1, t1, p)
        if len(new) < len(pairs):
            break
        grown = len(new) > len(pairs)
        c, t, pairs = c1, t1, new
        if not grown:
            break   # same pairing count: the fit has settled
    return c, t, pairs


def truncated_sigma2(mean_r2: float, radius: float) -> float:
    """Per-axis variance of isotropic 2-D Gaussian errors seen only within ``radius``.

    Pairings exist only where the residual is below the pairing radius, so the mean squared
    residual underestimates the noise when the noise is not small against the radius. For a
    truncated Rayleigh radius ``E[r^2 | r < T] = 2 s - T^2 e^(-T^2/2s) / (1 - e^(-T^2/2s))``
    (``s`` the per-axis variance), increasing in ``s`` up to ``T^2 / 2``; solved by bisection.
    """
    t2 = radius * radius
    if mean_r2 <= 0:
        return 0.0
    if mean_r2 >= 0.5 * t2 * 0.999:
        return t2   # residuals uniform over the disc: the noise is at least the radius

    def mean_r2_of(s):
        q = math.exp(-t2 / (2 * s))
        return 2 * s - t2 * q / (1 - q)

    lo, hi = 0.5 * mean_r2, t2
    for _ in range(30):   # relative precision ~1e-9
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean_r2_of(mid) < mean_r2 else (lo, mid)
    return 0.5 * (lo + hi)


def _covariance(za, zb, c: complex, t: complex, scale: bool,
                radius: float) -> tuple[np.ndarray, float]:
    """Covariance of pixel-frame (a, b, tx, ty) from the residuals of the fit."""
    m = len(za)
    r = zb - (c * za + t)
    n_par = 4 if scale else 3
    sum_r2 = float(np.dot(r.real, r.real) + np.dot(r.imag, r.imag))
    rms = math.sqrt(sum_r2 / m) if m else np.nan
    if m * 2 <= n_par:
        return np.full((4, 4), np.nan), rms
    # unbiased for the fitted parameters, then corrected for the pairing-radius truncation
    sigma2 = truncated_sigma2(sum_r2 * 2.0 / (2 * m - n_par), radius)
    col, row = from_complex(za)
    # pixel model: col' = a col + b row + tx ; row' = -b col + a row + ty; the Jacobian rows
    # [col, row, 1, 0] and [row, -col, 0, 1] give the normal matrix [[s2 I, B], [B, m I]]
    # with B = [[sc, sr], [sr, -sc]], B @ B = q I: its inverse in closed form (Schur
    # complement (m - q / s2) I)
    sc, sr = float(col.sum()), float(row.sum())
    s2 = float(np.dot(col, col) + np.dot(row, row))
    q = sc * sc + sr * sr
    schur = m - q / s2 if s2 > 0 else 0.0
    if schur <= 1e-12 * m:
        return np.full((4, 4), np.nan), rms   # all points coincide: no rotation
    u = -1.0 / (s2 * schur)
    corner = 1.0 / s2 + q / (s2 * s2 * schur)
    inv = np.array([[corner, 0.0, u * sc, u * sr], [0.0, corner, u * sr, -u * sc],
                    [u * sc, u * sr, 1.0 / schur, 0.0], [u * sr, -u * sc, 0.0, 1.0 / schur]])
    return sigma2 * inv, rms


def _pixel_transform(c: complex, t: complex) -> np.ndarray:
    a, b = c.real, c.imag
    return np.array([[a, b, t.real], [-b, a, -t.imag]])
