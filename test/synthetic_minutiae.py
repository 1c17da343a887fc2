"""Synthetic drainage-like minutia sets for the matcher's tests and benchmarks.

A random fractal surface (1/f^beta spectrum) is smoothed; its valley pixels (largest Hessian
eigenvalue strongly positive: concave up across the valley) are thinned to a skeleton, and
endings / bifurcations are found by the crossing number, as in dissertation chapter 3. The
result is clustered along line networks like real terrain minutiae, which is harder for a
matcher than uniform random points. Independent of the real feature extractor on purpose.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from terrain_nav_ros.core.features.minutia_set import BIFURCATION, ENDING, MinutiaSet
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.core.terrain.synthetic_terrain import fractal_surface


def valley_skeleton(surface: np.ndarray, sigma: float = 3.0, fraction: float = 0.15,
                    min_pixels: int = 20) -> np.ndarray:
    """Skeleton of the most concave-up ``fraction`` of pixels (valley floors).

    Skeleton pieces shorter than ``min_pixels`` are dropped (they are noise, not valleys).
    """
    hxx = ndimage.gaussian_filter(surface, sigma, order=(0, 2))
    hyy = ndimage.gaussian_filter(surface, sigma, order=(2, 0))
    hxy = ndimage.gaussian_filter(surface, sigma, order=(1, 1))
    lam = 0.5 * (hxx + hyy) + np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy ** 2)
    mask = lam > np.quantile(lam, 1.0 - fraction)
    skel = skeletonize(mask)
    lab, n = ndimage.label(skel, np.ones((3, 3)))
    size = np.bincount(lab.ravel(), minlength=n + 1)
    size[0] = 0
    return size[lab] >= min_pixels


def crossing_minutiae(skel: np.ndarray, border: int = 4, window: int = 4) -> MinutiaSet:
    """Endings (crossing number 1) and bifurcations (3) of a skeleton.

    The direction points from the centroid of the skeleton pixels within ``window`` px to
    the minutia (for an ending: outwards along its crease), in the East-CCW convention.
    """
    s = np.pad(skel.astype(np.int8), 1)
    # 8 neighbours in cyclic order around the pixel
    offs = [(-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1)]
    nb = [s[1 + dy:s.shape[0] - 1 + dy, 1 + dx:s.shape[1] - 1 + dx] for dy, dx in offs]
    cn = sum(np.abs(nb[k] - nb[(k + 1) % 8]) for k in range(8)) // 2
    kind = np.where(skel & (cn == 1), ENDING, np.where(skel & (cn == 3), BIFURCATION, 0))
    h, w = skel.shape
    kind[:border] = kind[-border:] = 0
    kind[:, :border] = kind[:, -border:] = 0
    rows, cols = np.nonzero(kind)
    size = 2 * window + 1
    sk = skel.astype(float)
    cnt = ndimage.uniform_filter(sk, size)
    rr, cc = np.mgrid[0:h, 0:w]
    mr = ndimage.uniform_filter(sk * rr, size) / np.maximum(cnt, 1e-9)
    mc = ndimage.uniform_filter(sk * cc, size) / np.maximum(cnt, 1e-9)
    angle = np.arctan2(-(rows - mr[rows, cols]), cols - mc[rows, cols])
    return MinutiaSet(cols.astype(float), rows.astype(float), angle, kind[rows, cols],
                      np.ones(len(rows)), georef=GeoReference(0.0, 0.0, 1.0, w, h))


def terrain_minutiae(shape=(512, 512), seed=0, sigma: float = 3.0,
                     fraction: float = 0.15) -> tuple[MinutiaSet, np.ndarray]:
    """Minutiae and skeleton of a random drainage-like pattern."""
    skel = valley_skeleton(fractal_surface(shape, rng=seed), sigma, fraction)
    return crossing_minutiae(skel), skel


def rigid_transform(rotation: float, tx: float, ty: float, centre=(0.0, 0.0)) -> np.ndarray:
    """2x3 pixel transform: rotate by ``rotation`` (CCW on the map) about ``centre``, shift."""
    c, s = np.cos(rotation), np.sin(rotation)
    m = np.array([[c, s], [-s, c]])
    cc = np.asarray(centre, float)
    return np.column_stack([m, cc - m @ cc + [tx, ty]])


def transform_set(ms: MinutiaSet, m: np.ndarray, out_shape, rng=None, pos_sigma=1.5,
                  angle_sigma=0.1745, missing=0.2, spurious=0.2,
                  flip_kind=0.0) -> tuple[MinutiaSet, np.ndarray]:
    """A perturbed copy of ``ms`` seen through pixel transform ``m`` in a new raster.

    Noise: Gaussian position (``pos_sigma`` px) and angle (``angle_sigma`` rad, default 10
    degrees), a ``missing`` fraction dropped, a ``spurious`` fraction of random minutiae
    added. Returns the new set and, for each of its minutiae, the index of the source minutia
    (-1 for spurious ones).
    """
    rng = np.random.default_rng(rng)
    col = m[0, 0] * ms.col + m[0, 1] * ms.row + m[0, 2]
    row = m[1, 0] * ms.col + m[1, 1] * ms.row + m[1, 2]
    rot = np.arctan2(m[0, 1], m[0, 0])
    src = np.arange(len(ms))
    col = col + rng.normal(0, pos_sigma, len(ms))
    row = row + rng.normal(0, pos_sigma, len(ms))
    ang = ms.angle + rot + rng.normal(0, angle_sigma, len(ms))
    kind = ms.kind.copy()
    flip = rng.random(len(ms)) < flip_kind
    kind[flip] = np.where(kind[flip] == ENDING, BIFURCATION, ENDING)
    h, w = out_shape
    keep = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    keep &= rng.random(len(ms)) >= missing
    col, row, ang, kind, src = col[keep], row[keep], ang[keep], kind[keep], src[keep]
    n_sp = int(round(spurious * len(col)))
    col = np.concatenate([col, rng.uniform(0, w - 1, n_sp)])
    row = np.concatenate([row, rng.uniform(0, h - 1, n_sp)])
    ang = np.concatenate([ang, rng.uniform(0, 2 * np.pi, n_sp)])
    kind = np.concatenate([kind, rng.choice([ENDING, BIFURCATION], n_sp)])
    src = np.concatenate([src, np.full(n_sp, -1)])
    perm = rng.permutation(len(col))
    out = MinutiaSet(col[perm], row[perm], ang[perm], kind[perm], np.ones(len(col)),
                     georef=GeoReference(0.0, 0.0, 1.0, w, h))
    return out, src[perm]


def crop_set(ms: MinutiaSet, col0: int, row0: int, w: int, h: int) -> MinutiaSet:
    """Minutiae inside a window, in the window's pixel frame."""
    keep = (ms.col >= col0) & (ms.col < col0 + w) & (ms.row >= row0) & (ms.row < row0 + h)
    return MinutiaSet(ms.col[keep] - col0, ms.row[keep] - row0, ms.angle[keep], ms.kind[keep],
                      ms.quality[keep], georef=GeoReference(0.0, 0.0, 1.0, w, h))
