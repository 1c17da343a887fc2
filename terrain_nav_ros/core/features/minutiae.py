"""Minutiae of drainage patterns: dissertation chapter 3.3, with fingerprint-style validation.

:func:`extract_features` runs the crease stage (:mod:`terrain_nav_ros.core.features.creases`)
and then

1. crossing numbers (eq. 3.7) of every skeleton pixel through a 256-entry look-up table on the
   8-neighbour code (one convolution): CN = 1 endings, CN = 3 bifurcations;
2. the pixel-wise orientation field of 3.3.2 (Sobel gradients, W x W least squares, doubled
   angle Gaussian smoothing) and its coherence;
3. the branches leaving every minutia, followed along the skeleton by vectorised walkers (all
   minutiae step together): their directions disambiguate the 180 degree ambiguity of the
   field and give the crease direction (ending: along its crease; bifurcation: along the
   stem, the branch that is not part of the narrowest fork), their lengths reveal spurs;
4. validation as fingerprint matchers do: margin to the image border and to nodata, spurs
   (one short branch from a junction to a free end: the ending and the bifurcation go), blunt
   crease ends (two short branches: one ending), short isolated creases, broken creases (two
   facing endings close together), duplicates and dense clusters;
5. a quality per minutia, ``coherence x (1 - exp(-SNR / (4 contrast_snr))) x support``: the
   orientation coherence at the minutia, its crease contrast over the pixel noise and the
   fraction of the trace length its branches actually run; and a cap on the count by quality.

Angles follow :mod:`terrain_nav_ros.core.features.minutia_set`: radians from East towards North.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..terrain.georef import GeoReference
from . import _crease_kernels as _kernels
from .creases import (
    CreaseDetector,
    CreaseParams,
    CreaseResult,
    Scratch,
    crease_mask,
    skeletonize_creases,
)
from .minutia_set import BIFURCATION, ENDING, MinutiaSet

__all__ = [
    "MinutiaParams",
    "Features",
    "FeatureExtractor",
    "crossing_number",
    "orientation_field",
    "doubled_angle_field",
    "normalised_coordinates",
    "extract_features",
    "extract_minutiae",
    "warm_up",
]

# 8 neighbours in anticlockwise order P1..P8 (Fig. 3.3), starting East; (d_row, d_col).
_RING = [(0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1), (1, 0), (1, 1)]


def _ring_kernel() -> np.ndarray:
    k = np.zeros((3, 3), np.float32)
    for bit, (dr, dc) in enumerate(_RING):
        k[1 + dr, 1 + dc] = 2**bit
    return k


def _cn_lut() -> np.ndarray:
    codes = np.arange(256)
    bits = (codes[:, None] >> np.arange(8)) & 1
    return (0.5 * np.abs(bits - np.roll(bits, -1, axis=1)).sum(1)).astype(np.uint8)


_RING_KERNEL = _ring_kernel()
_CN_LUT = _cn_lut()


def _check(cond: bool, msg: str):
    if not cond:
        raise ValueError(msg)


@dataclass(frozen=True)
class MinutiaParams:
    """Settings of minutia extraction and validation (orientation defaults: Table 3.1).

    Parameters
    ----------
    block_size : int
        W, the least-squares orientation block (16).
    orient_sigma : float
        sigma_s of the Gaussian smoothing the doubled-angle field (3).
    orient_size : int
        w_phi, its window (18 = 6 sigma_s; rounded up to odd for OpenCV).
    border_margin : float
        Minutiae closer than this (px) to the image border or to nodata are dropped: creases
        that leave the image end there without being endings.
    spur_length : int
        A branch from an ending to a junction shorter than this (px) is a spur: both its
        ending and its bifurcation are dropped.
    min_crease_length : int
        Isolated creases shorter than this (px) are dropped with their endings.
    break_distance : float
        Two endings closer than this (px) that face each other are one broken crease.
    break_angle : float
        Tolerance (degrees) for "facing each other".
    duplicate_distance : float
        Of two minutiae closer than this (px), only the better one is kept.
    cluster_radius, cluster_size : float, int
        A minutia with ``cluster_size`` or more others within ``cluster_radius`` px sits in a
        noisy tangle and is dropped.
    trace_length : int
        Radius (px) over which a minutia's branches are followed to get its direction.
    field_tolerance : float
        Degrees; when the orientation field disagrees more than this with the traced branch
        (junctions, curved creases) the traced direction is used.
    max_minutiae : int
        Keep at most this many minutiae, best quality first (0: no cap).
    min_quality : float
        Drop minutiae with lower quality.
    """

    block_size: int = 16
    orient_sigma: float = 3.0
    orient_size: int = 18
    border_margin: float = 10.0
    spur_length: int = 8
    min_crease_length: int = 12
    break_distance: float = 10.0
    break_angle: float = 35.0
    duplicate_distance: float = 3.0
    cluster_radius: float = 8.0
    cluster_size: int = 4
    trace_length: int = 12
    field_tolerance: float = 45.0
    max_minutiae: int = 400
    min_quality: float = 0.0

    def __post_init__(self):
        for name in ("block_size", "orient_size", "spur_length", "min_crease_length",
                     "trace_length", "cluster_size", "max_minutiae"):
            v = getattr(self, name)
            _check(isinstance(v, (int, np.integer)) and v >= 0,
                   f"{name} must be an int >= 0, got {v!r}")
        _check(self.block_size >= 2, f"block_size must be >= 2, got {self.block_size}")
        _check(self.orient_size >= 1, f"orient_size must be >= 1, got {self.orient_size}")
        _check(self.trace_length >= 2, f"trace_length must be >= 2, got {self.trace_length}")
        _check(self.cluster_size >= 1, f"cluster_size must be >= 1, got {self.cluster_size}")
        for name in ("orient_sigma",):
            v = getattr(self, name)
            _check(np.isfinite(v) and v > 0, f"{name} must be > 0, got {v!r}")
        for name in ("border_margin", "break_distance", "duplicate_distance",
                     "cluster_radius"):
            v = getattr(self, name)
            _check(np.isfinite(v) and v >= 0, f"{name} must be finite and >= 0, got {v!r}")
        for name in ("break_angle", "field_tolerance"):
            v = getattr(self, name)
            _check(0 <= v <= 180, f"{name} must be in [0, 180] degrees, got {v!r}")
        _check(0 <= self.min_quality <= 1, f"min_quality must be in [0, 1]: {self.min_quality}")

    @classmethod
    def from_dict(cls, values: dict) -> MinutiaParams:
        """Build from a mapping (e.g. ROS parameters), rejecting unknown keys."""
        names = {f.name for f in fields(cls)}
        unknown = set(values) - names
        _check(not unknown, f"unknown minutia parameter(s): {sorted(unknown)}")
        return cls(**values)


# --------------------------------------------------------------------------- primitives


def _neighbour_code(skeleton: np.ndarray) -> np.ndarray:
    """8-bit code of the 8 neighbours (bit k: ring neighbour P_{k+1} is set), uint8."""
    code = cv2.filter2D(skeleton.astype(np.uint8), cv2.CV_32F, _RING_KERNEL,
                        borderType=cv2.BORDER_CONSTANT)
    return code.astype(np.uint8)


def crossing_number(skeleton: np.ndarray) -> np.ndarray:
    """Crossing number (eq. 3.7) of every skeleton pixel; 0 off the skeleton.

    Parameters
    ----------
    skeleton : (M, N) bool array

    Returns
    -------
    (M, N) uint8 array
    """
    cn = _CN_LUT[_neighbour_code(skeleton)]
    cn[~skeleton] = 0
    return cn


def orientation_field(image: np.ndarray, block_size: int = 16, sigma: float = 3.0,
                      size: int = 18):
    """Pixel-wise crease orientation (3.3.2, eq. 3.10-3.18) and its coherence.

    Sobel gradients give the least-squares gradient orientation over a W x W block; the
    crease runs perpendicular to it. The orientation is smoothed as the doubled-angle unit
    vector field with a Gaussian (sigma_s, w_phi) and halved back.

    Returns
    -------
    angle : (M, N) float32 array
        Crease orientation in [0, pi), radians from East towards North (image rows point
        South, hence the sign flip).
    coherence : (M, N) float32 array
        Length of the smoothed doubled-angle vector, in [0, 1]: 1 for parallel creases.
    """
    phx, phy = doubled_angle_field(image, block_size, sigma, size)
    angle = np.mod(0.5 * np.arctan2(phy, phx), np.pi).astype(np.float32)
    return angle, cv2.magnitude(phx, phy)


def doubled_angle_field(image: np.ndarray, block_size: int = 16, sigma: float = 3.0,
                        size: int = 18, *, scratch: Scratch | None = None):
    """Smoothed doubled-angle unit field (cos 2 theta, sin 2 theta) of the crease orientation.

    The intermediate of :func:`orientation_field` (eq. 3.14-3.17); theta is measured from
    East towards North. Evaluate ``0.5 * arctan2`` only where the angle is needed.
    ``scratch`` (optional) provides reusable work buffers.
    """
    img = np.ascontiguousarray(image, np.float32)
    size = size + 1 - size % 2
    k = (block_size, block_size)
    if _kernels.HAVE_NUMBA and min(img.shape) >= 2:
        scratch = scratch or Scratch()
        pxy, pdd = (scratch.get(name, img.shape) for name in ("orient_pxy", "orient_pdd"))
        _kernels.sobel_products_kernel(img, pxy, pdd)
        cv2.boxFilter(pxy, -1, k, dst=pxy)
        cv2.boxFilter(pdd, -1, k, dst=pdd)
        phx, phy = np.empty_like(img), np.empty_like(img)
        _kernels.doubled_angle_kernel(pxy, pdd, phx, phy)
        return (cv2.GaussianBlur(phx, (size, size), sigma, dst=phx),
                cv2.GaussianBlur(phy, (size, size), sigma, dst=phy))
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    sxy = cv2.boxFilter(gx * gy, -1, k)
    sdd = cv2.boxFilter(gx * gx - gy * gy, -1, k)
    norm = cv2.magnitude(sdd, 2.0 * sxy)
    np.maximum(norm, np.float32(1e-30), out=norm)
    # Crease = gradient + 90 deg; doubled angle adds 180 deg: negate. North-up: y flips.
    phx = -sdd / norm
    phy = 2.0 * sxy / norm
    return cv2.GaussianBlur(phx, (size, size), sigma), cv2.GaussianBlur(phy, (size, size), sigma)


def normalised_coordinates(col, row, width: int, height: int):
    """Eq. 3.8-3.9: x = j / W, y = (H + 1 - i) / H with 1-based row i and column j.

    Returns values in (0, 1]; y grows northwards.
    """
    col = np.asarray(col, float)
    row = np.asarray(row, float)
    return (col + 1.0) / width, (height - row) / height


# --------------------------------------------------------------------------- branches


@dataclass
class _Candidates:
    row: np.ndarray
    col: np.ndarray
    kind: np.ndarray
    angle: np.ndarray = None
    quality: np.ndarray = None
    keep: np.ndarray = None


def _branch_start_lut() -> np.ndarray:
    """For each 8-neighbour code, the ring index starting each branch (-1: none), up to 4.

    A branch is a run of consecutive set neighbours; its start is the run's 4-neighbour
    when it has one (the skeleton continues straight from there), else its first pixel.
    """
    lut = np.full((256, 4), -1, np.int8)
    for code in range(1, 255):  # 0: isolated, 255: interior; neither starts branches
        bits = [(code >> k) & 1 for k in range(8)]
        z = bits.index(0)
        runs, cur = [], []
        for k in range(1, 9):
            i = (z + k) % 8
            if bits[i]:
                cur.append(i)
            elif cur:
                runs.append(cur)
                cur = []
        if cur:
            runs.append(cur)
        for j, run in enumerate(runs[:4]):
            even = [i for i in run if i % 2 == 0]
            lut[code, j] = even[0] if even else run[0]
    return lut


_START_LUT = _branch_start_lut()
_OFFS = np.array(_RING, np.int64)
FREE_END, JUNCTION = 1, 2


def _next_lut() -> np.ndarray:
    """Walker's next ring index for [neighbour code, ring index of the previous pixel,
    ring index of the one before (8: not adjacent)]; -1 where the branch ends.

    The next pixel is the set neighbour farthest from the previous pixel, never one of the
    last two pixels: this runs straight through the redundant corner pixels of 8-connected
    skeletons.
    """
    bits = ((np.arange(256)[:, None] >> np.arange(8)) & 1).astype(bool)      # (256, 8)
    offs = np.vstack([_OFFS, [[0, 0]]])                                    # 8: none
    score = ((offs[:, None, :] - _OFFS[None, :, :]) ** 2).sum(-1)         # (9 from, 8)
    k = np.arange(8)
    ok = (bits[:, None, None, :] & (k != np.arange(9)[:, None, None])[None]
          & (k != np.arange(9)[None, :, None])[None])                      # (256, 9, 9, 8)
    sc = np.where(ok, score[None, :, None, :], 0)
    best = sc.argmax(-1).astype(np.int8)
    best[sc.max(-1) == 0] = -1
    return best


def _ring_index5() -> np.ndarray:
    idx = np.full((5, 5), 8, np.int8)
    for k, (dr, dc) in enumerate(_RING):
        idx[dr + 2, dc + 2] = k
    return idx


_NEXT_LUT = _next_lut()
_RING5 = _ring_index5()


def _walk(skel_p, code_p, junc_p, r0, c0, first, steps, upto, skip=0):
    """Follow skeleton branches from (r0, c0) through neighbour ``first``, all at once.

    Works on the skeleton padded by one pixel (coordinates already shifted); ``code_p`` is
    the 8-neighbour code of every pixel. The first step away from the start looks at the
    actual neighbours and never comes back next to the start (the neighbours of a junction
    touch each other); later steps use a look-up table (:func:`_next_lut`). Walkers stop at
    a free end or on reaching a junction pixel farther than ``skip`` pixels (Chebyshev)
    from their start: junction clusters are a few pixels wide.

    Returns
    -------
    tip : (n, 2) int array
        Last pixel reached (row, col), padded coordinates.
    direction : (n, 2) float array
        Unit (d_row, d_col) of the branch: the mean offset of the walker at 1/3, 2/3 and 3/3
        of ``upto`` steps (or of its tip, when the branch is shorter); NaN if none.
    length : (n,) int
        Steps taken.
    stop : (n,) int
        0 still running after ``steps``, FREE_END, or JUNCTION.
    """
    n = len(r0)
    sr, sc = np.asarray(r0, np.int64), np.asarray(c0, np.int64)
    if _kernels.HAVE_NUMBA and n:
        tip = np.empty((n, 2), np.int64)
        direction = np.empty((n, 2))
        length = np.empty(n, np.int64)
        stop = np.empty(n, np.int8)
        _kernels.walk_kernel(skel_p, code_p, junc_p, sr, sc, np.asarray(first, np.int64),
                             steps, upto, skip, _NEXT_LUT, _RING5, _OFFS, tip, direction,
                             length, stop)
        return tip, direction, length, stop
    dr, dc = _OFFS[:, 0], _OFFS[:, 1]
    tr, tc = sr + dr[first], sc + dc[first]          # tip (last pixel) of every walker
    length = np.ones(n, np.int64)
    stop = np.zeros(n, np.int8)
    checkpoints = sorted({max(1, upto // 3), max(1, 2 * upto // 3), max(1, upto)})
    acc = np.zeros((n, 2))
    done = []

    def record(t):
        if t in checkpoints:
            acc[:, 0] += tr - sr
            acc[:, 1] += tc - sc
            done.append(t)

    record(1)
    # A branch leaving a junction may start on another junction pixel of the same cluster.
    stop[junc_p[tr, tc] & ~junc_p[sr, sc]] = JUNCTION
    act = np.flatnonzero(stop == 0)
    if steps >= 2 and len(act):
        # Step 2 on the real neighbours, excluding the start's own neighbourhood.
        cr, cc = tr[act], tc[act]
        nr, nc = cr[:, None] + dr, cc[:, None] + dc                            # (m, 8)
        cand = skel_p[nr, nc] & (np.maximum(np.abs(nr - sr[act, None]),
                                            np.abs(nc - sc[act, None])) > 1)
        score = np.where(cand, (nr - sr[act, None]) ** 2 + (nc - sc[act, None]) ** 2, 0)
        k = score.argmax(1)
        moved = score[np.arange(len(act)), k] > 0
        stop[act[~moved]] = FREE_END
        act, k, cr, cc = act[moved], k[moved], cr[moved], cc[moved]
        # Ring index of the previous pixel (and the one before) seen from the current one.
        frm = (k + 4) % 8
        frm2 = _RING5[sr[act] - cr - dr[k] + 2, sc[act] - cc - dc[k] + 2]
        cr, cc = cr + dr[k], cc + dc[k]
        length[act] += 1
        tr[act], tc[act] = cr, cc
        record(2)
        for step in range(2, steps + 1):
            hit = junc_p[cr, cc] & (np.maximum(np.abs(cr - sr[act]),
                                               np.abs(cc - sc[act])) > skip)
            stop[act[hit]] = JUNCTION
            if step == steps:
                break
            k = _NEXT_LUT[code_p[cr, cc], frm, frm2].astype(np.int64)
            moved = (k >= 0) & ~hit
            stop[act[(k < 0) & ~hit]] = FREE_END
            act, k, cr, cc, frm = act[moved], k[moved], cr[moved], cc[moved], frm[moved]
            if len(act) == 0:
                break
            # The previous pixel seen from the new one: old "from" offset minus the move.
            frm2 = _RING5[dr[frm] - dr[k] + 2, dc[frm] - dc[k] + 2]
            frm = (k + 4) % 8
            cr, cc = cr + dr[k], cc + dc[k]
            length[act] += 1
            tr[act], tc[act] = cr, cc
            record(step + 1)
    for t in checkpoints:  # walkers that stopped early count their tip
        if t not in done:
            acc[:, 0] += tr - sr
            acc[:, 1] += tc - sc
    norm = np.hypot(acc[:, 0], acc[:, 1])
    direction = acc / np.where(norm == 0, 1.0, norm)[:, None]
    direction[norm == 0] = np.nan
    return np.column_stack([tr, tc]), direction, length, stop


def _enu_angle(vec):
    """ENU angle (from East towards North) of (d_row, d_col) vectors."""
    return np.mod(np.arctan2(-vec[..., 0], vec[..., 1]), 2 * np.pi)


def _stem_direction(ang):
    """Stem of each bifurcation: the branch outside the narrowest pair of branches."""
    pairs = np.array([[1, 2], [0, 2], [0, 1]])  # pair opposite to stem candidate k
    gaps = np.stack([_angdiff(ang[:, a], ang[:, b]) for a, b in pairs], axis=1)
    gaps = np.where(np.isnan(gaps), np.inf, gaps)
    out = ang[np.arange(len(ang)), np.argmin(gaps, axis=1)]
    missing = np.isnan(ang).any(axis=1)
    out[missing] = np.nan
    return out


def _trace_minutiae(skel_p, code_p, junc_p, c: _Candidates, p: MinutiaParams):
    """Trace the branches of every candidate; set directions, support and spur decisions.

    * Ending: one branch. Reaching a junction within ``spur_length`` makes it a spur (the
      ending is dropped; the bifurcation it hangs from is handled from its side), a free
      end within ``min_crease_length`` a short isolated crease (dropped).
    * Bifurcation: three branches; the stem is the one outside the narrowest fork. One
      branch running to a free end within ``spur_length`` is a spur: the bifurcation and that
      ending go. Two or more are the blunt end of a crease split by skeletonisation: the
      bifurcation becomes one ending pointing along its long branch, the short ends go.

    Returns the traced ENU angle and the support (traced length / trace length, <= 1).
    """
    n = len(c.row)
    starts = _START_LUT[code_p[c.row + 1, c.col + 1]]
    traced = np.full(n, np.nan)
    support = np.zeros(n)
    end = np.flatnonzero(c.kind == ENDING)
    L = p.trace_length
    if len(end):
        steps = max(L, p.spur_length, p.min_crease_length)
        _, vec, length, stop = _walk(skel_p, code_p, junc_p, c.row[end] + 1,
                                     c.col[end] + 1, starts[end, 0], steps, L)
        traced[end] = _enu_angle(vec)
        support[end] = np.minimum(length, L) / L
        spur = (stop == JUNCTION) & (length < p.spur_length)
        short = (stop == FREE_END) & (length < p.min_crease_length)
        c.keep[end[spur | short]] = False
    bif = np.flatnonzero(c.kind == BIFURCATION)
    if len(bif):
        steps = 2 * L  # skeletons bend and widen next to junctions: look further
        ang = np.full((len(bif), 3), np.nan)
        lens = np.zeros((len(bif), 3), np.int64)
        free_short = np.zeros((len(bif), 3), bool)
        tips = np.zeros((len(bif), 3, 2), np.int64)
        for j in range(3):
            has = starts[bif, j] >= 0
            if not has.any():
                continue
            tip, vec, length, stop = _walk(skel_p, code_p, junc_p, c.row[bif[has]] + 1,
                                           c.col[bif[has]] + 1, starts[bif[has], j], steps,
                                           steps, 2)
            ang[has, j] = _enu_angle(vec)
            lens[has, j] = length
            free_short[has, j] = (stop == FREE_END) & (length < p.spur_length)
            tips[has, j] = tip
        traced[bif] = _stem_direction(ang)
        support[bif] = np.minimum(lens.min(1), steps) / steps
        n_short = free_short.sum(1)
        c.keep[bif[n_short == 1]] = False
        blunt = n_short >= 2
        if blunt.any():
            longest = np.argmax(np.where(free_short, -1, lens), axis=1)
            c.kind[bif[blunt]] = ENDING
            traced[bif[blunt]] = ang[blunt, longest[blunt]]
            support[bif[blunt]] = np.minimum(lens[blunt, longest[blunt]], L) / L
        # Padded pixels at the free ends of those short branches: endings there go.
        short_tips = tips[free_short & (n_short >= 1)[:, None]]
        if len(short_tips) and len(end):
            width = skel_p.shape[1]  # compare flat padded indices
            at_tip = np.isin((c.row[end] + 1) * width + c.col[end] + 1,
                             short_tips[:, 0] * width + short_tips[:, 1])
            c.keep[end[at_tip]] = False
    return traced, support


def _angdiff(a, b):
    """Absolute angle difference in [0, pi]."""
    return np.abs(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b)))))


def _combine_angles(field_a, traced, p: MinutiaParams):
    """Orientation field (mod pi) disambiguated by the traced branch direction.

    The traced direction wins where the two disagree by more than ``field_tolerance``
    (junctions, sharp bends) and NaN stays NaN (nothing traced).
    """
    cand = np.where(_angdiff(field_a, traced) <= np.pi / 2, field_a, field_a + np.pi)
    use_field = _angdiff(cand, traced) <= np.deg2rad(p.field_tolerance)
    ang = np.where(use_field, cand, traced)
    return np.mod(np.where(np.isnan(traced), np.nan, ang), 2 * np.pi)


def _drop_broken_pairs(c: _Candidates, p: MinutiaParams):
    """Two endings that face each other across a small gap are one broken crease."""
    idx = np.flatnonzero(c.keep & (c.kind == ENDING))
    if len(idx) < 2 or p.break_distance <= 0:
        return
    tree = cKDTree(np.column_stack([c.row[idx], c.col[idx]]))
    pairs = tree.query_pairs(p.break_distance, output_type="ndarray")
    if len(pairs) == 0:
        return
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    tol = np.deg2rad(p.break_angle)
    # Direction i -> j (ENU) must be opposite to i's crease and equal to... j's reversed.
    dir_ij = np.arctan2(-(c.row[j] - c.row[i]), c.col[j] - c.col[i])
    opposite = _angdiff(c.angle[i], c.angle[j] + np.pi) < tol
    facing = (_angdiff(dir_ij, c.angle[i] + np.pi) < 1.5 * tol) & \
             (_angdiff(dir_ij, c.angle[j]) < 1.5 * tol)
    bad = opposite & facing
    c.keep[i[bad]] = False
    c.keep[j[bad]] = False


def _drop_duplicates_and_clusters(c: _Candidates, p: MinutiaParams):
    idx = np.flatnonzero(c.keep)
    if len(idx) < 2:
        return
    radius = max(p.cluster_radius, p.duplicate_distance)
    if radius <= 0:
        return
    pts = np.column_stack([c.row[idx], c.col[idx]])
    # One neighbour search for both tests; pixel coordinates: exact squared distances.
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    d2 = ((pts[pairs[:, 0]] - pts[pairs[:, 1]]) ** 2).sum(1)
    if p.cluster_radius > 0:
        near = pairs[d2 <= p.cluster_radius**2]
        n_near = np.bincount(near.reshape(-1), minlength=len(idx))
        c.keep[idx[n_near >= p.cluster_size]] = False
    if p.duplicate_distance > 0:
        dup = pairs[d2 <= p.duplicate_distance**2]
        i, j = idx[dup[:, 0]], idx[dup[:, 1]]
        worse = np.where(c.quality[i] >= c.quality[j], j, i)
        c.keep[worse] = False


def _border_distance(valid: np.ndarray):
    """Distance (px) to the nearest invalid pixel or the image outside, as a function of
    (rows, cols): a distance transform only when there is nodata."""
    if valid.all():
        h, w = valid.shape

        def dist(rows, cols):
            return np.minimum(np.minimum(rows + 1, cols + 1), np.minimum(h - rows, w - cols))

        return dist
    padded = np.pad(valid.astype(np.uint8), 1)
    table = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
    return lambda rows, cols: table[rows, cols]


# --------------------------------------------------------------------------- extraction


@dataclass
class Features:
    """Result of :func:`extract_features`.

    ``minutiae`` is the validated set; ``creases`` the crease-stage result (use
    ``creases.crease_image()`` for the debug topic); ``phi`` the smoothed doubled-angle
    orientation field (``orientation``/``coherence`` derive the angle and its coherence on
    demand); ``ridges`` the ridge skeleton when the extractor was asked for it (bool, no
    minutiae: the matcher's ridge check); ``timings`` seconds per stage.
    """

    minutiae: MinutiaSet
    creases: CreaseResult
    phi: tuple | None = None
    timings: dict = field(default_factory=dict)
    ridges: np.ndarray | None = None

    @property
    def orientation(self) -> np.ndarray | None:
        """Crease orientation in [0, pi) from East towards North (see orientation_field)."""
        if self.phi is None:
            return None
        return np.mod(0.5 * np.arctan2(self.phi[1], self.phi[0]), np.pi).astype(np.float32)

    @property
    def coherence(self) -> np.ndarray | None:
        """Orientation coherence in [0, 1]."""
        return None if self.phi is None else cv2.magnitude(*self.phi)

    def crease_image(self) -> np.ndarray:
        """uint8 debug image of the creases (255 skeleton, 128 crease mask)."""
        return self.creases.crease_image()


def _skeleton_maps(skel: np.ndarray, scratch: Scratch | None = None):
    """Skeleton, neighbour codes, crossing numbers and junctions (CN >= 3) with a one-pixel
    frame, so that walkers never index outside, and the (row, col) of the CN 1 and CN 3
    pixels (row-major order)."""
    if _kernels.HAVE_NUMBA:
        scratch = scratch or Scratch()
        shape = (skel.shape[0] + 2, skel.shape[1] + 2)
        skel_p, junc_p = (scratch.get(k, shape, bool) for k in ("min_skel_p", "min_junc_p"))
        code_p, cn_p = (scratch.get(k, shape, np.uint8) for k in ("min_code_p", "min_cn_p"))
        found = np.empty(np.count_nonzero(skel), np.int64)
        n = _kernels.skeleton_maps_kernel(np.ascontiguousarray(skel).view(np.uint8), _CN_LUT,
                                          skel_p.view(np.uint8), code_p, cn_p,
                                          junc_p.view(np.uint8), found)
        rows, cols = np.divmod(found[:n], skel.shape[1])
        return skel_p, code_p, cn_p, junc_p, rows, cols
    skel_p = np.pad(skel, 1)
    code_p = _neighbour_code(skel_p)
    cn_p = _CN_LUT[code_p]
    cn_p[~skel_p] = 0
    cn = cn_p[1:-1, 1:-1]
    rows, cols = np.nonzero((cn == 1) | (cn == 3))
    return skel_p, code_p, cn_p, cn_p >= 3, rows, cols


def _minutiae_of_skeleton(skel, cres: CreaseResult, phi, dist_border, cp: CreaseParams,
                          p: MinutiaParams, scratch: Scratch | None = None):
    skel_p, code_p, cn_p, junc_p, rows, cols = _skeleton_maps(skel, scratch)
    # Minutiae near the border or nodata are dropped anyway: do not trace them.
    inside = dist_border(rows, cols) >= p.border_margin
    rows, cols = rows[inside], cols[inside]
    kind = cn_p[rows + 1, cols + 1]
    c = _Candidates(rows, cols, kind)
    n = len(rows)
    c.keep = np.ones(n, bool)
    if n == 0:
        c.angle = c.quality = np.zeros(0)
        return c
    traced, support = _trace_minutiae(skel_p, code_p, junc_p, c, p)
    phx, phy = phi[0][rows, cols].astype(float), phi[1][rows, cols].astype(float)
    field_a = np.mod(0.5 * np.arctan2(phy, phx), np.pi)
    c.angle = _combine_angles(field_a, traced, p)
    # Quality: field coherence x crease contrast (SNR) x traced branch support.
    snr = np.abs(cres.contrast[rows, cols]) / max(cres.noise, 1e-12)
    q_snr = 1.0 - np.exp(-snr / (4.0 * max(cp.contrast_snr, 1.0)))
    c.quality = (np.hypot(phx, phy) * q_snr * support).astype(float)
    c.keep &= ~np.isnan(c.angle)
    _drop_broken_pairs(c, p)
    _drop_duplicates_and_clusters(c, p)
    c.keep &= c.quality >= p.min_quality
    return c


class FeatureExtractor:
    """Creases and minutiae of grey images and DEMs, with fixed settings.

    Parameters
    ----------
    crease_params : CreaseParams, optional
    minutia_params : MinutiaParams, optional
    ridges : bool
        Also return the ridge skeleton (:attr:`Features.ridges`), thresholded from the same
        creaseness as the valleys: the ridge lines between the valleys are a second,
        independent check of a registration for a matcher (see
        :attr:`~.matching.params.MatchParams.ridge_check`); they give no minutiae.
    """

    def __init__(self, crease_params: CreaseParams | None = None,
                 minutia_params: MinutiaParams | None = None, ridges: bool = False):
        self.crease_params = crease_params or CreaseParams()
        self.minutia_params = minutia_params or MinutiaParams()
        self.ridges = bool(ridges)
        self._creases = CreaseDetector(self.crease_params)

    def __call__(self, image, georef: GeoReference | None = None, valid_mask=None,
                 source: str = "image", nodata=None) -> Features:
        """Extract features; see :func:`extract_features`."""
        img = np.asarray(image)
        if georef is not None:
            _check(georef.shape == img.shape[:2],
                   f"georef shape {georef.shape} != image shape {img.shape[:2]}")
        gsd = georef.gsd if georef is not None else 1.0
        with self._creases.scratch.borrow() as scratch:
            return self._extract(img, georef, valid_mask, source, gsd, nodata, scratch)

    def _extract(self, img, georef, valid_mask, source, gsd, nodata, scratch):
        cp, p = self.crease_params, self.minutia_params
        cres = self._creases(img, valid_mask, source, gsd, nodata, scratch=scratch)
        timings = dict(cres.timings)
        if cres.reason:
            return Features(MinutiaSet.empty(cres.reason, georef), cres, timings=timings)
        ridges = None
        if self.ridges:
            t0 = time.perf_counter()
            ridges = self._ridge_skeleton(cres, scratch)
            timings["ridges"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        phi = doubled_angle_field(cres.diffused, p.block_size, p.orient_sigma, p.orient_size,
                                  scratch=scratch)
        timings["orientation"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        dist_border = _border_distance(cres.valid)
        parts = []
        for pol, skel in cres.skeletons.items():
            c = _minutiae_of_skeleton(skel, cres, phi, dist_border, cp, p, scratch)
            k = c.keep
            parts.append((c.col[k], c.row[k], c.angle[k], c.kind[k], c.quality[k],
                          np.full(int(k.sum()), pol == "ridge")))
        col, row, ang, kind, qual, ridge = (np.concatenate(a) for a in zip(*parts, strict=True))
        order = np.argsort(-qual, kind="stable")
        if p.max_minutiae:
            order = order[:p.max_minutiae]
        col, row, ang, kind, qual, ridge = (a[order] for a in (col, row, ang, kind, qual,
                                                               ridge))
        timings["minutiae"] = time.perf_counter() - t0
        if len(col) == 0:
            ms = MinutiaSet.empty("no minutiae survived validation", georef)
        else:
            ms = MinutiaSet(col.astype(float), row.astype(float), ang, kind, qual,
                            georef=georef)
            h, w = img.shape[:2]
            x, y = normalised_coordinates(col, row, w, h)
            ms.extras.update(x_norm=x, y_norm=y, ridge=ridge)
            if georef is not None:
                ms.extras["east"], ms.extras["north"] = georef.pixel_to_enu(col, row)
        return Features(ms, cres, phi, timings, ridges)

    def _ridge_skeleton(self, cres: CreaseResult, scratch) -> np.ndarray:
        """The ridge skeleton of an extraction (a copy: scratch buffers are reused)."""
        if "ridge" in cres.skeletons:
            return cres.skeletons["ridge"].copy()
        mask = crease_mask(cres.creaseness, cres.contrast, cres.noise, self.crease_params,
                           "ridge", cres.valid, scratch=scratch)
        return skeletonize_creases(mask).copy()


def extract_features(image, georef: GeoReference | None = None, valid_mask=None,
                     crease_params: CreaseParams | None = None,
                     params: MinutiaParams | None = None, source: str = "image",
                     nodata=None) -> Features:
    """Creases, orientation field and validated minutiae of one raster.

    Parameters
    ----------
    image : (M, N) array
        Grey image (uint8, uint16, float; colour is converted) or, with ``source="dem"``, an
        elevation grid in metres (its valleys are the terrain's creases).
    georef : GeoReference, optional
        Placement of the raster; gives the DEM's gsd and the minutiae's ENU metres.
    valid_mask : (M, N) bool array, optional
        False on nodata (outside the camera view, DEM voids).
    crease_params, params : CreaseParams, MinutiaParams, optional
    source : {"image", "dem"}
    nodata : float, optional
        Void value of a DEM.

    Returns
    -------
    Features
        ``features.minutiae`` is empty with a ``reason`` when there is no drainage.
    """
    return FeatureExtractor(crease_params, params)(image, georef, valid_mask, source, nodata)


def extract_minutiae(image, georef: GeoReference | None = None, valid_mask=None,
                     params: MinutiaParams | None = None,
                     crease_params: CreaseParams | None = None, source: str = "image",
                     nodata=None) -> MinutiaSet:
    """Validated minutiae of one raster; see :func:`extract_features`."""
    return extract_features(image, georef, valid_mask, crease_params, params, source,
                            nodata).minutiae


def warm_up() -> None:
    """Run the whole chain once on a small synthetic valley.

    With numba installed the fused kernels are compiled (or loaded from numba's cache) on
    first use, which takes seconds; a node calls this at start-up so that the first real
    frame is not late.
    """
    rr, cc = np.mgrid[0:96, 0:96]
    dist = np.minimum(np.abs(cc - 48) + np.where(rr < 48, 0, 96), np.hypot(rr - 48, cc - 48))
    dist = np.minimum(dist, np.abs(rr - 48) + np.where(cc > 20, 0, 96))
    image = (200 - 120 * np.exp(-dist.astype(float) ** 2 / 18.0)).astype(np.uint8)
    extract_features(image)
