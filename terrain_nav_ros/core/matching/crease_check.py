"""Verification of a registration by the crease skeletons themselves, not only their minutiae.

A small block (a hundred pixels, 20-40 minutiae) registers on 5-10 minutiae pairings, which
chance coincidences between unrelated blocks can match. The creases those minutiae end or
fork carry far more of the pattern: a few hundred skeleton pixels whose positions and
directions must agree after the same transform. This module scores that agreement:

* :class:`CreaseField` (reference side, built once per block or region): distance from every
  pixel to the nearest crease pixel, and that pixel's crease direction;
* :class:`CreaseSamples` (query side): the crease pixels with their directions;
* :func:`crease_evidence`: the query crease pixels are mapped by the transform and counted as
  hits when they land within ``radius`` px of a reference crease running within
  ``angle_tol`` of their own direction. The chance of a hit is measured locally, at the same
  transform shifted by 6-10 px in 12 directions (so the density and the dominant directions of
  this pair's drainage set the null, not a global assumption), and the hit count is scored by
  a binomial tail over ``n / spacing`` effectively independent samples (neighbouring skeleton
  pixels of one crease are not independent);
* :func:`conditioned_on`: a second skeleton's evidence (the ridges) given the first's (the
  valleys), with their dependence measured over the same shifted transforms.

Geometry in the math frame ``z = col - 1j*row`` of :mod:`.descriptors`; crease directions are
axial (mod pi).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import betainc, log_ndtr, ndtri

from . import _matching_kernels as _kernels
from .descriptors import to_complex

# local null: the transform shifted by these radii (px) in 12 directions
_NULL_SHIFTS = np.concatenate([r * np.exp(1j * np.arange(12) * (np.pi / 6.0)) for r in (6.0, 10.0)])


def crease_directions(skeleton: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Axial direction (rad, math frame, in [0, pi)) of a skeleton at every pixel.

    The principal axis of the blurred skeleton's structure tensor: the gradient across a
    crease, turned by 90 degrees.
    """
    img = cv2.GaussianBlur(skeleton.astype(np.float32), (0, 0), sigma)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = -cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)   # math frame: y grows northwards
    jxx_yy = cv2.GaussianBlur(gx * gx - gy * gy, (0, 0), sigma)
    jxy2 = cv2.GaussianBlur(2.0 * gx * gy, (0, 0), sigma)
    normal = 0.5 * np.arctan2(jxy2, jxx_yy)
    return np.mod(normal + 0.5 * np.pi, np.pi).astype(np.float32)


def _skeleton(crease: np.ndarray) -> np.ndarray:
    crease = np.asarray(crease)
    if crease.ndim != 2:
        raise ValueError(f"crease image must be 2-D, got shape {crease.shape}")
    return crease != 0


@dataclass(frozen=True)
class CreaseSamples:
    """Crease pixels of the query side: positions (math frame) and axial directions."""

    z: np.ndarray
    direction: np.ndarray

    @classmethod
    def from_image(cls, crease: np.ndarray) -> CreaseSamples:
        """Samples of a crease skeleton image (non-zero = crease)."""
        sk = _skeleton(crease)
        rows, cols = np.nonzero(sk)
        return cls(to_complex(cols, rows), crease_directions(sk)[rows, cols])

    def __len__(self) -> int:
        return len(self.z)

    def around(self, points, radius: float) -> list[np.ndarray]:
        """Indices of the samples closer than ``radius`` to each of ``points`` (complex,
        math frame): one array per point."""
        points = np.asarray(points)
        if len(self) == 0 or points.size == 0 or radius <= 0:
            return [np.zeros(0, np.intp) for _ in range(points.size)]
        tree = cKDTree(np.column_stack([self.z.real, self.z.imag]))
        near = tree.query_ball_point(np.column_stack([points.real, points.imag]),
                                     np.nextafter(radius, 0.0))   # strictly closer
        return [np.asarray(i, np.intp) for i in near]

    def around_lists(self, points, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`around`'s lists stored end to end: ``flat[start[k]:start[k + 1]]`` for
        point ``k`` (in another order within a list with numba: by sample, not as the k-d
        tree visits them)."""
        points = np.asarray(points)
        cols, rows = self.z.real, -self.z.imag
        if (_kernels.HAVE_NUMBA and len(self) and points.size and radius > 0
                and np.array_equal(cols, np.rint(cols)) and np.array_equal(rows, np.rint(rows))):
            # pixel places (a skeleton's): a grid of them instead of the k-d tree, the same
            # squared distances against the same bound
            r = float(np.nextafter(radius, 0.0))
            return _kernels.pixels_within(cols, rows, points.real, -points.imag, r * r)
        near = self.around(points, radius)
        start = np.zeros(len(near) + 1, np.intp)
        np.cumsum([len(i) for i in near], out=start[1:])
        return start, (np.concatenate(near) if near else np.zeros(0, np.intp)).astype(np.intp)


class CreaseField:
    """Reference side: distance to and direction of the nearest crease pixel, everywhere.

    Parameters
    ----------
    crease : ndarray, shape (rows, cols)
        Crease skeleton image in the pixel frame of the reference minutiae (non-zero = crease).
    """

    def __init__(self, crease: np.ndarray):
        sk = _skeleton(crease)
        self.shape = sk.shape
        self.n = int(sk.sum())
        self.label = None   # index of the nearest crease pixel (raster order), everywhere
        self._near = {}
        if self.n:
            # OpenCV's labelled distance transform (5x5 mask: exact at 0, 1, sqrt 2, 2 px,
            # within 2 % beyond) is ~10x faster than an exact one with indices: a 2048^2
            # landmark region costs ~0.2 s instead of ~1 s. Each label is a crease pixel, in
            # raster order.
            dist, label = cv2.distanceTransformWithLabels(
                (~sk).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5,
                labelType=cv2.DIST_LABEL_PIXEL)
            rows, cols = np.nonzero(sk)
            label -= 1
            crease_direction = crease_directions(sk)[rows, cols]
            self.distance = dist
            self.direction = crease_direction[label]
            self.label = label
            # per crease pixel, for the ICP's correspondences: its position (math frame)
            # and unit normal (sin and cos once per pixel, not once per correspondence)
            self.crease_z = to_complex(cols, rows)
            self.crease_normal = 1j * np.exp(1j * crease_direction.astype(float))
        else:
            self.distance = np.full(sk.shape, np.inf, np.float32)
            self.direction = np.zeros(sk.shape, np.float32)
            self.crease_z = self.crease_normal = np.zeros(0, complex)

    def near(self, radius: float) -> np.ndarray:
        """Where a crease is within ``radius`` (cached per radius; numba kernels only)."""
        radius = float(radius)
        if radius not in self._near:
            self._near[radius] = _kernels.near_mask(self.distance, radius)
        return self._near[radius]

    def _lookup(self, z: np.ndarray, direction: np.ndarray):
        """Inside mask, pixel (row, col) and axial direction difference of mapped samples."""
        h, w = self.shape
        col, row = np.rint(z.real), np.rint(-z.imag)
        inside = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
        ci, ri = col[inside].astype(np.intp), row[inside].astype(np.intp)
        dang = np.abs(np.mod(direction[inside] - self.direction[ri, ci] + 0.5 * np.pi, np.pi)
                      - 0.5 * np.pi)
        return inside, ri, ci, dang

    def hits(self, z: np.ndarray, direction: np.ndarray, radius: float, angle_tol: float):
        """Which mapped samples lie inside the field, and which of those are hits."""
        inside, ri, ci, dang = self._lookup(z, direction)
        return inside, (self.distance[ri, ci] <= radius) & (dang <= angle_tol)

    def correspondences(self, z: np.ndarray, direction: np.ndarray, radius: float,
                        angle_tol: float):
        """Samples with a crease within ``radius`` and ``angle_tol``: their index, the
        nearest crease point (math frame) and that crease's unit normal."""
        if _kernels.HAVE_NUMBA:
            idx, flat = _kernels.crease_matches(z, direction, self.distance, self.direction,
                                                radius, angle_tol)
            ri, ci = np.divmod(flat, self.shape[1])
        else:
            inside, ri, ci, dang = self._lookup(z, direction)
            ok = (self.distance[ri, ci] <= radius) & (dang <= angle_tol)
            idx, ri, ci = np.flatnonzero(inside)[ok], ri[ok], ci[ok]
        nearest = self.label[ri, ci]
        return idx, self.crease_z[nearest], self.crease_normal[nearest]


@dataclass(frozen=True)
class CreaseEvidence:
    """Agreement of two crease skeletons at one transform."""

    score: float = 0.0        # -log10 of the chance of this many hits (>= 0)
    fraction: float = 0.0     # hits / samples inside the reference
    chance: float = 0.0       # hit fraction at the shifted transforms (the local null)
    n_inside: int = 0
    # hit fraction at each shifted transform (NaN where no sample fell inside)
    null_fractions: np.ndarray | None = dataclass_field(default=None, repr=False,
                                                        compare=False)
    dependence: float = 0.0   # correlation with the evidence it is conditioned on


def conditioned_on(evidence: CreaseEvidence, given: CreaseEvidence | None) -> CreaseEvidence:
    """``evidence`` with its score given the agreement ``given`` already scored.

    Ridges lie between valleys: where a view's valleys are aligned with a region's, its
    ridges often are too, most of all in parallel drainage, and a sum of the two scores
    counts one alignment twice. The dependence is measured at the local null's shifted
    transforms (the correlation of the two hit fractions over them), and the two agreements
    are taken as jointly normal z-scores with that correlation: the ridges' z-score given the
    valleys' is ``(z_r - rho z_v) / sqrt(1 - rho^2)``. Independent channels keep their score;
    a valley agreement below chance (z_v < 0) lends the ridges nothing.
    """
    if given is None or evidence.score <= 0.0 or given.score <= 0.0:
        return evidence
    rho = _shift_correlation(evidence.null_fractions, given.null_fractions)
    if rho <= 0.0:
        return evidence
    z = _z_score(evidence.score)
    z_given = _z_score(given.score)
    z_left = (z - rho * z_given) / math.sqrt(1.0 - rho * rho)
    score = max(0.0, float(-log_ndtr(-z_left) / math.log(10.0)))
    return replace(evidence, score=min(score, evidence.score), dependence=rho)


def _z_score(score: float) -> float:
    """The standard normal deviate with upper tail ``10**-score``."""
    return float(-ndtri(10.0 ** -min(score, 300.0)))


def _shift_correlation(x, y, max_rho: float = 0.95) -> float:
    """Correlation of two channels' hit fractions over the shifted transforms both see, at
    its one-sigma lower bound (Fisher's z; 0 below it): a dependence the few shifts cannot
    tell from noise is not discounted."""
    if x is None or y is None:
        return 0.0
    both = np.isfinite(x) & np.isfinite(y)
    n = int(both.sum())
    if n < 8:
        return 0.0
    x, y = x[both] - x[both].mean(), y[both] - y[both].mean()
    norm = math.sqrt(float(x @ x) * float(y @ y))
    if norm <= 0.0:
        return 0.0
    r = min(float(x @ y) / norm, max_rho)
    return max(0.0, math.tanh(math.atanh(r) - 1.0 / math.sqrt(n - 3)))


def crease_evidence(samples: CreaseSamples, field: CreaseField, c: complex, t: complex, *,
                    radius: float = 1.5, angle_tol: float = math.radians(20.0),
                    spacing: float = 4.0, min_samples: int = 20,
                    skip=None) -> CreaseEvidence:
    """How unlikely the crease agreement at transform ``z -> c z + t`` is by chance.

    Parameters
    ----------
    samples : CreaseSamples
        Query creases (A).
    field : CreaseField
        Reference creases (B).
    c, t : complex
        Similarity transform A -> B in the math frame.
    radius : float
        Position tolerance (px) of a hit.
    angle_tol : float
        Direction tolerance (rad) of a hit.
    spacing : float
        Skeleton pixels per effectively independent sample (along-crease correlation).
    min_samples : int
        Fewer mapped samples than this inside the reference give no evidence.
    skip : array_like of int, optional
        Samples that do not count, e.g. those around the paired minutiae
        (:meth:`CreaseSamples.around`), whose crease stubs agree by construction of the
        transform and are already scored.

    Returns
    -------
    CreaseEvidence
    """
    if len(samples) == 0 or field.n == 0:
        return CreaseEvidence()
    keep = np.ones(len(samples), bool)
    if skip is not None and len(skip):
        keep[np.asarray(skip, np.intp)] = False
    n_in, n_hit, null_in, null_hit = _hit_counts(field, samples, keep, c, t, radius,
                                                 angle_tol)
    if n_in < min_samples:
        return CreaseEvidence(n_inside=n_in)
    chance = float(np.clip((null_hit.sum() + 1.0) / (null_in.sum() + 2.0), 1e-3, 0.999))
    fraction = n_hit / n_in
    with np.errstate(invalid="ignore", divide="ignore"):
        null_fractions = np.where(null_in > 0, null_hit / null_in, np.nan)
    n_eff = n_in / spacing
    k = fraction * n_eff
    score = 0.0
    if fraction > chance:
        # continuous binomial upper tail P(K >= k), K ~ Bin(n_eff, chance)
        tail = betainc(k, n_eff - k + 1.0, chance)
        score = float(-math.log10(max(tail, 1e-300)))
    return CreaseEvidence(score, fraction, chance, n_in, null_fractions)


def _hit_counts(field: CreaseField, samples: CreaseSamples, keep, c, t, radius, angle_tol):
    """Kept samples mapped inside the field and hits among them; per shifted transform the
    same for every 4th inside sample (the local null: one sample per crease spacing is
    plenty for a rate over 24 shifts, at a quarter of the cost)."""
    if _kernels.HAVE_NUMBA:
        n_in, n_hit, null_in, null_hit = _kernels.crease_hit_counts(
            samples.z, samples.direction, keep, complex(c), complex(t), float(np.angle(c)),
            field.near(radius), field.direction, angle_tol, _NULL_SHIFTS, 4)
        return int(n_in), int(n_hit), null_in, null_hit
    z = c * samples.z[keep] + t
    direction = samples.direction[keep] + np.angle(c)
    inside, hit = field.hits(z, direction, radius, angle_tol)
    z_in, dir_in = z[inside][::4], direction[inside][::4]
    shifted = (z_in[None, :] + _NULL_SHIFTS[:, None]).ravel()
    ins, hs = field.hits(shifted, np.tile(dir_in, len(_NULL_SHIFTS)), radius, angle_tol)
    per_shift = np.repeat(np.arange(len(_NULL_SHIFTS)), len(z_in))[ins]
    return (int(inside.sum()), int(hit.sum()),
            np.bincount(per_shift, minlength=len(_NULL_SHIFTS)),
            np.bincount(per_shift, weights=hs, minlength=len(_NULL_SHIFTS)).astype(np.int64))


def refine_on_creases(samples: CreaseSamples, field: CreaseField, c: complex, t: complex, *,
                      radius: float = 3.0, angle_tol: float = math.radians(20.0),
                      iterations: int = 4, min_matches: int = 20,
                      ridges: tuple[CreaseSamples, CreaseField] | None = None,
                      scale: tuple[float, float] | None = None) -> tuple[complex, complex]:
    """Rotation and translation (and with ``scale = (lo, hi)`` the scale, by at most 5 % a
    step and within ``[lo, hi]``) that bring A's creases onto B's (point-to-line ICP).

    Each iteration pairs the mapped crease pixels of A with B's nearest crease pixel (within
    ``radius`` and ``angle_tol``) and solves the linearised least squares for a small
    rotation about their centroid and a shift that minimise the distances *across* B's
    creases (along a crease a pixel carries no position information). ``ridges``, A's
    ridge samples and B's ridge field, add their own correspondences to the same solve (a
    ridge only pairs with a ridge). Returns the input transform when fewer than
    ``min_matches`` pixels pair.
    """
    if len(samples) == 0 or field.n == 0:
        return c, t
    channels = [(samples, field)]
    if ridges is not None and len(ridges[0]) and ridges[1].n:
        channels.append(ridges)
    if _kernels.HAVE_NUMBA:
        second = channels[1] if len(channels) > 1 else (_NO_SAMPLES, field)
        return _kernels.crease_icp(*_icp_arrays(*channels[0]), *_icp_arrays(*second),
                                   complex(c), complex(t), radius, angle_tol, iterations,
                                   min_matches, scale is not None,
                                   *(scale if scale is not None else (1.0, 1.0)))
    for _ in range(iterations):
        matched = [f.correspondences(c * s.z + t, s.direction + np.angle(c), radius,
                                     angle_tol) + (s,) for s, f in channels]
        if sum(len(idx) for idx, *_ in matched) < min_matches:
            break
        p = np.concatenate([c * s.z[idx] + t for idx, _, _, s in matched])
        q = np.concatenate([q for _, q, _, _ in matched])
        normal = np.concatenate([n for _, _, n, _ in matched])
        p0 = p.mean()
        # residual across the crease and its derivatives by (rotation, shift east, north)
        residual = (np.conj(normal) * (p - q)).real
        columns = [(np.conj(normal) * 1j * (p - p0)).real, normal.real, normal.imag]
        if scale is not None:
            columns.insert(1, (np.conj(normal) * (p - p0)).real)
        jac = np.column_stack(columns)
        # normal equations: a 3x3 solve is several times cheaper than an SVD of (m, 3), and
        # the rotation is taken about the centroid, so the system is well conditioned
        try:
            step = np.linalg.solve(jac.T @ jac, -(jac.T @ residual))
        except np.linalg.LinAlgError:
            break   # all correspondences on parallel creases: the shift along them is free
        ds = 0.0
        if scale is not None:
            ds = float(np.clip(step[1], -0.05, 0.05))
            ds = float(np.clip((1.0 + ds) * abs(c), *scale)) / abs(c) - 1.0
        shift = complex(step[-2], step[-1])
        turn = (1.0 + ds) * np.exp(1j * step[0])
        c, t = turn * c, turn * t + p0 * (1.0 - turn) + shift
        if (abs(step[0]) + abs(ds)) * 100.0 + abs(shift) < 0.01:
            break   # settled: < 0.01 px at 100 px from the centroid
    return c, t


_NO_SAMPLES = CreaseSamples(np.zeros(0, complex), np.zeros(0, np.float32))


def _icp_arrays(samples: CreaseSamples, field: CreaseField) -> tuple:
    """One channel's arrays for the ICP kernel."""
    return (samples.z, samples.direction, field.distance, field.direction, field.label,
            field.crease_z, field.crease_normal)


def crease_covariance(samples: CreaseSamples, field: CreaseField, c: complex, t: complex, *,
                      radius: float = 1.5, angle_tol: float = math.radians(20.0),
                      spacing: float = 4.0, min_matches: int = 20) -> np.ndarray:
    """Covariance of the pixel transform ``(a, b, tx, ty)`` from the crease agreement.

    The form of :class:`~.matching.matcher.MatchResult` (``col' = a col + b row + tx``,
    ``row' = -b col + a row + ty``), from the distances across B's creases of A's agreeing
    crease pixels: ``sigma^2 (J^T J)^-1`` with ``J`` their derivatives, inflated by
    ``spacing`` because neighbouring skeleton pixels of one crease are not independent.
    All NaN when fewer than ``min_matches`` pixels agree or they do not fix the transform.
    """
    nan = np.full((4, 4), np.nan)
    if len(samples) == 0 or field.n == 0:
        return nan
    idx, q, normal = field.correspondences(c * samples.z + t, samples.direction + np.angle(c),
                                           radius, angle_tol)
    if len(idx) < min_matches:
        return nan
    z = samples.z[idx]
    across = np.conj(normal)
    residual = (across * (c * z + t - q)).real
    # z_b = c z + t with c = a + ib and t = tx - i ty
    jac = np.column_stack([(across * z).real, (across * 1j * z).real, normal.real,
                           -normal.imag])
    # pixel quantisation keeps the variance from vanishing on a perfect fit
    sigma2 = max(float(np.mean(residual ** 2)), 1.0 / 12.0)
    normal_matrix = jac.T @ jac
    if np.linalg.cond(normal_matrix) > 1e12:
        return nan
    return sigma2 * spacing * np.linalg.inv(normal_matrix)
