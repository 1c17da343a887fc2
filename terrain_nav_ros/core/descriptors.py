"""Rotation- and translation-invariant local descriptors of minutiae (dissertation 4.1).

Three families, all computed for every minutia at once with numpy broadcasting and
``scipy.spatial.cKDTree``:

* :func:`shape_context`: the *minutiae shape descriptor*, a log-polar histogram of the
  neighbouring minutiae (one histogram per minutia kind) measured relative to the minutia's
  own position and direction (Belongie, Malik & Puzicha 2002). Square-rooted and L2-normalised
  so that a dot product is the Hellinger (Bhattacharyya) affinity of two histograms.
* :func:`crease_descriptor`: the *crease shape descriptor*, samples of a (blurred) binary
  crease/skeleton image on concentric circles around the minutia, starting at its direction;
  zero-mean and unit-norm so that a dot product is a normalised cross-correlation.
* :func:`neighbour_edges` and :class:`EdgeHash`: pair invariants in the style of SourceAFIS
  edges (edge length and the two angles between the edge and each end's direction), hashed
  on a quantised grid so that candidate edge correspondences come from sorted-key look-ups
  instead of an all-pairs comparison.

Geometry is done in the *math frame* ``z = col - 1j * row`` (x east, y north), where the
minutia angle of :mod:`terrain_nav_ros.core.minutia_set` (CCW from East) is an ordinary
polar angle and a rotation is a multiplication by ``exp(1j * theta)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .minutia_set import BIFURCATION, MinutiaSet

TWO_PI = 2.0 * np.pi


def wrap_angle(a):
    """Angles wrapped to [-pi, pi] (either end for odd multiples of pi)."""
    a = np.asarray(a)
    return a - TWO_PI * np.rint(a * (1.0 / TWO_PI))   # rint: much faster than np.mod


def to_complex(col, row) -> np.ndarray:
    """Pixel coordinates as complex numbers in the math frame (x = col, y = -row)."""
    return np.asarray(col, dtype=float) - 1j * np.asarray(row, dtype=float)


def from_complex(z) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`to_complex`: (col, row)."""
    z = np.asarray(z)
    return z.real, -z.imag


def shape_context(ms: MinutiaSet, n_radial: int = 4, n_angular: int = 8,
                  r_inner: float = 8.0, r_outer: float = 64.0,
                  by_kind: bool = True) -> np.ndarray:
    """Log-polar minutiae shape context of every minutia.

    Parameters
    ----------
    ms : MinutiaSet
        The minutiae.
    n_radial, n_angular : int
        Number of log-radius and angle bins. Angles are measured from each minutia's own
        direction, which makes the descriptor rotation invariant; neighbours are spread
        linearly over the two nearest angle bins so that a 10-20 degree error in the
        minutia direction changes the descriptor smoothly instead of flipping bins.
    r_inner, r_outer : float
        Radius (px) of the first log-radius bin edge and of the outer edge; neighbours closer
        than ``r_inner`` go to the first bin, farther than ``r_outer`` are ignored.
    by_kind : bool
        One histogram per neighbour kind (ending, bifurcation), as in the dissertation's
        Fig. 4.2; False pools them (use when the kinds are unreliable).

    Returns
    -------
    ndarray, shape (n, n_kinds * n_radial * n_angular), float32
        Square-rooted, unit-L2 histograms (all zeros for a minutia without neighbours).
    """
    n = len(ms)
    n_ch = 2 if by_kind else 1
    size = n_ch * n_radial * n_angular
    if n < 2:
        return np.zeros((n, size), np.float32)
    x, y = ms.col, -ms.row
    tree = cKDTree(np.column_stack([x, y]))
    pairs = tree.query_pairs(r_outer, output_type="ndarray")
    p, q = pairs[:, 0], pairs[:, 1]
    dx, dy = x[q] - x[p], y[q] - y[p]
    # each unordered pair serves both directions: same radius, direction + pi
    edges2 = (r_inner * (r_outer / r_inner) ** (np.arange(n_radial) / (n_radial - 1))) ** 2
    rb = np.minimum(np.searchsorted(edges2, dx * dx + dy * dy, side="right"), n_radial - 1)
    direction = np.arctan2(dy, dx)
    i = np.concatenate([p, q])
    j = np.concatenate([q, p])
    rb = np.concatenate([rb, rb])
    phi = np.concatenate([direction, direction + np.pi]) - ms.angle[i]
    # phi is in (-3 pi, 2 pi]: shift u positive so that truncation is floor
    u = phi * (n_angular / TWO_PI) + (3 * n_angular - 0.5)
    a0 = u.astype(np.intp)
    f = u - a0
    a0 %= n_angular
    a1 = (a0 + 1) % n_angular
    ch = (ms.kind[j] == BIFURCATION).astype(np.intp) if by_kind else 0
    base = ((i * n_ch + ch) * n_radial + rb) * n_angular
    hist = (np.bincount(base + a0, 1.0 - f, minlength=n * size)
            + np.bincount(base + a1, f, minlength=n * size)).reshape(n, size)
    return _unit_rows(np.sqrt(hist))


def crease_descriptor(ms: MinutiaSet, crease: np.ndarray,
                      radii=(6.0, 12.0, 18.0, 24.0), n_samples: int = 24,
                      sigma: float = 1.5) -> np.ndarray:
    """Crease shape descriptor: the crease image sampled on circles around each minutia.

    Parameters
    ----------
    ms : MinutiaSet
        Minutiae in the pixel frame of ``crease``.
    crease : ndarray, shape (rows, cols)
        Binary crease / skeleton image (any dtype; non-zero = crease).
    radii : sequence of float
        Circle radii (px), the dissertation's concentric circles (Fig. 4.3).
    n_samples : int
        Samples per circle; the first sample lies along the minutia direction, so the
        descriptor is rotation invariant.
    sigma : float
        Gaussian blur (px) of the crease image, so that a crease displaced by a pixel or two
        still correlates.

    Returns
    -------
    ndarray, shape (n, len(radii) * n_samples), float32
        Zero-mean, unit-L2 rows: the dot product of two rows is their normalised
        cross-correlation. Samples outside the image read as "no crease".
    """
    n = len(ms)
    radii = np.asarray(radii, dtype=float)
    if n == 0:
        return np.zeros((0, radii.size * n_samples), np.float32)
    img = ndimage.gaussian_filter((np.asarray(crease) != 0).astype(np.float32), sigma)
    phi = ms.angle[:, None, None] + np.arange(n_samples) * (TWO_PI / n_samples)
    cols = ms.col[:, None, None] + radii[None, :, None] * np.cos(phi)
    rows = ms.row[:, None, None] - radii[None, :, None] * np.sin(phi)
    v = ndimage.map_coordinates(img, [rows.ravel(), cols.ravel()], order=1, mode="constant",
                                cval=0.0).reshape(n, -1)
    return _unit_rows(v - v.mean(axis=1, keepdims=True))


def _unit_rows(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return (v / np.where(norm > 0, norm, 1.0)).astype(np.float32)


@dataclass
class EdgeTable:
    """The k nearest-neighbour edges of every minutia, as (n, k) arrays.

    Row ``i`` holds the edges from minutia ``i`` to its neighbours ``j[i]`` sorted by length,
    so the first ``k'`` columns are the ``k'``-nearest-neighbour edges. Invalid slots (too
    short, too long, or fewer than k neighbours) have ``valid`` False.

    Attributes
    ----------
    j : ndarray of intp
        Neighbour index.
    length : ndarray of float
        Edge length (px).
    direction : ndarray of float
        Edge direction (rad, math frame, CCW from East).
    beta_i, beta_j : ndarray of float
        Edge direction minus the direction of minutia i (resp. j), wrapped to [0, 2 pi):
        the two rotation-invariant angles of the SourceAFIS edge shape.
    valid : ndarray of bool
    """

    j: np.ndarray
    length: np.ndarray
    direction: np.ndarray
    beta_i: np.ndarray
    beta_j: np.ndarray
    valid: np.ndarray

    @property
    def k(self) -> int:
        """Edges per minutia (columns)."""
        return self.j.shape[1]


def neighbour_edges(ms: MinutiaSet, k: int = 12, min_length: float = 6.0,
                    max_length: float = 160.0, tree: cKDTree | None = None) -> EdgeTable:
    """Pair invariants of each minutia with its ``k`` nearest neighbours.

    Parameters
    ----------
    ms : MinutiaSet
    k : int
        Neighbours per minutia.
    min_length, max_length : float
        Edges outside this length range (px) are marked invalid: very short edges have an
        unreliable direction, very long ones rarely survive into another view.
    tree : cKDTree, optional
        A tree over ``(col, -row)`` of ``ms`` (reused when the caller has one).

    Returns
    -------
    EdgeTable
    """
    n = len(ms)
    k_eff = max(0, min(k, n - 1))
    z = to_complex(ms.col, ms.row)
    if k_eff == 0:
        e = np.zeros((n, 0))
        return EdgeTable(e.astype(np.intp), e, e, e, e, e.astype(bool))
    if tree is None:
        tree = cKDTree(np.column_stack([z.real, z.imag]))
    dist, idx = tree.query(np.column_stack([z.real, z.imag]), k=k_eff + 1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    valid = (dist >= min_length) & (dist <= max_length)
    d = z[idx] - z[:, None]
    direction = np.mod(np.angle(d), TWO_PI)
    beta_i = np.mod(direction - ms.angle[:, None], TWO_PI)
    beta_j = np.mod(direction - ms.angle[idx], TWO_PI)
    return EdgeTable(idx, dist, direction, beta_i, beta_j, valid)


@dataclass
class EdgeQuery:
    """Query edges prepared for :meth:`EdgeHash.lookup` (reusable across hashes).

    Attributes
    ----------
    grid : tuple
        (length_step, n_angle, n_length) of the hashes this query fits.
    keys : ndarray, shape (m, n_cells)
        Keys of the cells within tolerance of each query edge.
    inside : ndarray of bool, same shape
        False for cells outside the length range.
    owner : ndarray of intp, shape (m * n_cells,)
        Query edge of each flattened cell.
    length, beta_i, beta_j, length_tol : ndarray, shape (m,)
    angle_tol : float
    """

    grid: tuple
    keys: np.ndarray
    inside: np.ndarray
    owner: np.ndarray
    length: np.ndarray
    beta_i: np.ndarray
    beta_j: np.ndarray
    length_tol: np.ndarray
    angle_tol: float


class EdgeHash:
    """Hash table of edge invariants for fast candidate edge correspondences.

    Edges are keyed by their quantised (length, beta_i, beta_j). The key space is small
    (length cells x angle cells^2), so the table is dense: a cell's entries are found by
    direct indexing. A query visits the cells within tolerance of each query edge and keeps
    the stored edges within the continuous tolerances; every stored edge lies in one cell,
    so each (query, stored) pair is reported at most once.

    Parameters
    ----------
    edges : EdgeTable
        The stored (reference) edges.
    length_step : float
        Length cell size (px); use the length tolerance.
    angle_step : float
        Angle cell size (rad); use the angle tolerance.
    max_length : float
        Longest edge length (px) to hash; longer stored edges are dropped. Hashes built with
        the same three settings accept the same :class:`EdgeQuery`.
    """

    def __init__(self, edges: EdgeTable, length_step: float, angle_step: float,
                 max_length: float = 160.0):
        self.length_step = float(length_step)
        self.n_angle = max(3, int(np.floor(TWO_PI / angle_step)))
        self.angle_step = TWO_PI / self.n_angle
        self.n_length = int(np.floor(max_length / self.length_step)) + 1
        self.grid = (self.length_step, self.n_angle, self.n_length)
        self.edges = edges
        rows, cols = np.nonzero(edges.valid & (edges.length <= max_length))
        length = edges.length[rows, cols]
        keys = self._keys(length, edges.beta_i[rows, cols], edges.beta_j[rows, cols])
        order = np.argsort(keys, kind="stable")
        self.rows = rows[order]
        self.cols = cols[order]
        self.j = edges.j[rows, cols][order]
        self.direction = edges.direction[rows, cols][order]
        # invariants in key order, so the tolerance filter reads contiguous 1-D arrays
        self.length = length[order]
        self.beta_i = edges.beta_i[rows, cols][order]
        self.beta_j = edges.beta_j[rows, cols][order]
        n_keys = self.n_length * self.n_angle ** 2
        self.start = np.concatenate([[0], np.cumsum(np.bincount(keys, minlength=n_keys))])

    def _cells(self, length, beta_i, beta_j):
        ql = np.floor(np.asarray(length) / self.length_step).astype(np.intp)
        q1 = np.floor(np.asarray(beta_i) / self.angle_step).astype(np.intp) % self.n_angle
        q2 = np.floor(np.asarray(beta_j) / self.angle_step).astype(np.intp) % self.n_angle
        return ql, q1, q2

    def _keys(self, length, beta_i, beta_j):
        ql, q1, q2 = self._cells(length, beta_i, beta_j)
        return (ql * self.n_angle + q1) * self.n_angle + q2

    def prepare(self, length, beta_i, beta_j, length_tol, angle_tol) -> EdgeQuery:
        """Cells to visit for each query edge (see :meth:`query` for the arguments)."""
        length = np.asarray(length, float)
        beta_i = np.asarray(beta_i, float)
        beta_j = np.asarray(beta_j, float)
        length_tol = np.broadcast_to(np.asarray(length_tol, float), length.shape)
        ml = int(np.ceil(length_tol.max(initial=0.0) / self.length_step))
        ma = min(int(np.ceil(angle_tol / self.angle_step)), (self.n_angle - 1) // 2)
        ql, q1, q2 = self._cells(length, beta_i, beta_j)
        dl = np.arange(-ml, ml + 1)
        da = np.arange(-ma, ma + 1)
        # all neighbouring cells of every query edge, shape (m, n_l, n_a, n_a)
        kl = ql[:, None, None, None] + dl[None, :, None, None]
        k1 = (q1[:, None, None, None] + da[None, None, :, None]) % self.n_angle
        k2 = (q2[:, None, None, None] + da[None, None, None, :]) % self.n_angle
        m = len(length)
        inside = ((kl >= 0) & (kl < self.n_length) & (k1 >= 0) & (k2 >= 0)).reshape(m, -1)
        keys = ((np.clip(kl, 0, self.n_length - 1) * self.n_angle + k1) * self.n_angle
                + k2).reshape(m, -1)
        owner = np.repeat(np.arange(m), keys.shape[1])
        return EdgeQuery(self.grid, keys, inside, owner, length, beta_i, beta_j,
                         np.ascontiguousarray(length_tol), float(angle_tol))

    def lookup(self, eq: EdgeQuery):
        """Stored edges within tolerance of prepared query edges.

        Returns
        -------
        q : ndarray of intp
            Index of the query edge.
        pos : ndarray of intp
            Position of the stored edge in this hash's key-ordered arrays (``rows``,
            ``cols``, ``j``, ``direction``, ...).
        """
        if eq.grid != self.grid:
            raise ValueError("EdgeHash.lookup: query prepared for a different grid")
        lo = self.start[eq.keys]
        counts = np.where(eq.inside, self.start[eq.keys + 1] - lo, 0).ravel()
        total = int(counts.sum())
        q = np.repeat(eq.owner, counts)
        pos = np.repeat(lo.ravel() - (np.cumsum(counts) - counts), counts) + np.arange(total)
        ok = ((np.abs(self.length[pos] - eq.length[q]) <= eq.length_tol[q])
              & (np.abs(wrap_angle(self.beta_i[pos] - eq.beta_i[q])) <= eq.angle_tol)
              & (np.abs(wrap_angle(self.beta_j[pos] - eq.beta_j[q])) <= eq.angle_tol))
        return q[ok], pos[ok]

    def query(self, length, beta_i, beta_j, length_tol, angle_tol):
        """Stored edges within tolerance of each query edge.

        Parameters
        ----------
        length, beta_i, beta_j : ndarray, shape (m,)
            Query edge invariants.
        length_tol : float or ndarray (m,)
            Absolute length tolerance (px) per query edge.
        angle_tol : float
            Tolerance (rad) on each of the two relative angles.

        Returns
        -------
        q : ndarray of intp
            Index of the query edge.
        rows, cols : ndarray of intp
            The matching stored edge as (minutia, neighbour slot) of the stored EdgeTable.
        """
        q, pos = self.lookup(self.prepare(length, beta_i, beta_j, length_tol, angle_tol))
        return q, self.rows[pos], self.cols[pos]
