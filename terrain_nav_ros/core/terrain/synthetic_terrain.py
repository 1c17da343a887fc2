"""Synthetic high-resolution terrain with a drainage network, deterministic from a seed.

Real 1-5 m DEMs of mountains are rarely free to ship, so the demo and the tests also fly over
a made-up landscape that has what the method needs: dendritic valleys at every scale.
:func:`synthetic_dem` builds it in three vectorised steps:

1. a fractional-Brownian surface (power spectrum ~ 1/f^beta) sets the relief;
2. for routing only, depressions are filled (grey-scale morphological reconstruction) and
   every cell drains to its steepest downhill neighbour (D8); the upstream area of each cell
   is the solution of a sparse triangular system (cells sorted from high to low);
3. valleys are carved in proportion to ``area**m`` (the stream-power law's equilibrium
   incision), then lightly smoothed so slopes stay plausible.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.linalg import spsolve_triangular
from skimage.morphology import reconstruction

# The 8 neighbours and their distances (D8).
_OFFSETS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
_DIST = np.array([np.hypot(dr, dc) for dr, dc in _OFFSETS])


def fractal_surface(shape, beta: float = 3.2, rng=None) -> np.ndarray:
    """Zero-mean, unit-std random surface with power spectrum ~ 1/f^beta."""
    rng = np.random.default_rng(rng)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    spectrum = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) * f ** (-beta / 2)
    spectrum[0, 0] = 0.0
    z = np.fft.irfft2(spectrum, s=shape)
    return (z - z.mean()) / z.std()


def fill_depressions(z: np.ndarray) -> np.ndarray:
    """Raise every closed depression to its spill level (water exits at the border)."""
    seed = np.full_like(z, z.max())
    seed[0, :], seed[-1, :], seed[:, 0], seed[:, -1] = z[0, :], z[-1, :], z[:, 0], z[:, -1]
    return reconstruction(seed, z, method="erosion")


def d8_receivers(z: np.ndarray) -> np.ndarray:
    """Flat index of each cell's steepest-descent neighbour (itself at outlets and flats)."""
    rows, cols = z.shape
    padded = np.pad(z, 1, mode="constant", constant_values=np.inf)
    slopes = np.stack([(z - padded[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]) / d
                       for (dr, dc), d in zip(_OFFSETS, _DIST, strict=True)])
    best = np.argmax(slopes, axis=0)
    has_descent = np.take_along_axis(slopes, best[None], 0)[0] > 0
    r, c = np.mgrid[0:rows, 0:cols]
    dr = np.array([o[0] for o in _OFFSETS])[best]
    dc = np.array([o[1] for o in _OFFSETS])[best]
    receiver = np.where(has_descent, (r + dr) * cols + (c + dc), r * cols + c)
    return receiver.ravel()


def upstream_area(z: np.ndarray, receivers: np.ndarray) -> np.ndarray:
    """Number of cells draining through each cell (itself included)."""
    n = z.size
    order = np.argsort(-z.ravel(), kind="stable")      # donors before receivers
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    donors = np.flatnonzero(receivers != np.arange(n))
    # In rank order, area[recv] = 1 + sum(area[donors]) is lower-triangular: (I - A) a = 1.
    a = sparse.csr_matrix((-np.ones(len(donors)), (rank[receivers[donors]], rank[donors])),
                          shape=(n, n)) + sparse.identity(n, format="csr")
    area_ranked = spsolve_triangular(a, np.ones(n), lower=True)
    return area_ranked[rank].reshape(z.shape)


def synthetic_dem(size: int = 1024, gsd: float = 5.0, relief: float = 120.0,
                  seed: int = 7, beta: float = 4.0, incision: float = 6.0,
                  exponent: float = 0.5, base: float = 1500.0,
                  smoothing: float = 6.0, valley_width: float = 3.0) -> np.ndarray:
    """A ``size`` x ``size`` DEM (m) with a carved drainage network.

    Parameters
    ----------
    size : int
        Cells per side.
    gsd : float
        Cell size (m); only scales the valley carving with the drained area in m^2.
    relief : float
        Standard deviation of the initial relief (m).
    seed : int
        Random seed: the same seed gives the same terrain.
    beta : float
        Spectral exponent of the initial surface (3 = smooth hills, 2 = rough).
    incision : float
        Valley depth per unit ``(area / 1e4 m^2) ** exponent``, relative to ``relief / 100``.
    exponent : float
        Stream-power area exponent m.
    base : float
        Mean elevation (m).
    smoothing : float
        Gaussian smoothing (cells) of the initial surface.
    valley_width : float
        Gaussian width (cells) of the carved valley cross-section.

    Returns
    -------
    ndarray of float32, shape (size, size)
    """
    # Hills smoother than a pure power law at the cell scale: the valleys carved below are
    # then the dominant small-scale relief, as in a real eroded landscape.
    z = ndimage.gaussian_filter(fractal_surface((size, size), beta, seed), smoothing)
    z = (z - z.mean()) / z.std() * relief
    filled = fill_depressions(z)
    # Break ties on flats with a little of the original surface so every cell drains.
    routing = filled + 1e-6 * relief * ndimage.gaussian_filter(z, 2.0)
    area = upstream_area(routing, d8_receivers(routing)) * gsd * gsd
    depth = incision * relief / 100.0 * (area / 1e4) ** exponent
    # Carve the unfilled surface: filled depressions would be flat lakes without drainage.
    carved = z - ndimage.gaussian_filter(depth, valley_width)
    return (ndimage.gaussian_filter(carved, 0.7) + base).astype(np.float32)
