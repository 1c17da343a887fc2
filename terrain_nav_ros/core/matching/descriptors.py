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
  on a quantised grid so that candidate edge correspondences come from table look-ups
  instead of an all-pairs comparison.

Geometry is done in the *math frame* ``z = col - 1j * row`` (x east, y north), where the
minutia angle of :mod:`terrain_nav_ros.core.features.minutia_set` (CCW from East) is an ordinary
polar angle and a rotation is a multiplication by ``exp(1j * theta)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree

from ..features.minutia_set import BIFURCATION, MinutiaSet
from . import _matching_kernels as _kernels

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


def cylinder_code(ms: MinutiaSet, radius: float = 48.0, n_spatial: int = 8,
                  n_directional: int = 6, sigma_s: float = 6.0,
                  sigma_d: float = np.radians(40.0), chunk: int = 20000) -> np.ndarray:
    """Minutia Cylinder-Code style descriptor (Cappelli, Ferrara & Maltoni 2010).

    A cylinder of ``n_spatial`` x ``n_spatial`` cells (radius ``radius`` px, aligned with the
    minutia direction) by ``n_directional`` direction sections; each cell sums, over the
    neighbouring minutiae, a Gaussian of the distance to the cell centre times a Gaussian of
    the neighbour's direction relative to the minutia, compared with the section's direction.
    Unlike the original there is no per-cell validity mask and no sigmoid: cells outside the
    disc are dropped and the code is square-rooted and L2-normalised, so that a dot product
    compares two codes like the other descriptors here.

    Parameters
    ----------
    ms : MinutiaSet
    radius : float
        Cylinder radius (px).
    n_spatial, n_directional : int
        Cells across the cylinder and direction sections.
    sigma_s, sigma_d : float
        Spatial (px) and directional (rad) Gaussian widths.
    chunk : int
        Neighbour pairs processed at once (bounds memory on large regions).

    Returns
    -------
    ndarray, shape (n, n_cells_in_disc * n_directional), float32
    """
    n = len(ms)
    step = 2.0 * radius / n_spatial
    g = (np.arange(n_spatial) - (n_spatial - 1) / 2.0) * step
    cx, cy = np.meshgrid(g, g)
    disc = np.hypot(cx, cy) <= radius
    cells = (cx[disc] + 1j * cy[disc])                       # in the minutia's own frame
    dirs = -np.pi + (np.arange(n_directional) + 0.5) * (TWO_PI / n_directional)
    size = cells.size * n_directional
    if n < 2:
        return np.zeros((n, size), np.float32)
    z = to_complex(ms.col, ms.row)
    tree = cKDTree(np.column_stack([z.real, z.imag]))
    pairs = tree.query_pairs(radius + 3.0 * sigma_s, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    out = np.zeros((n, size))
    for k in range(0, len(i), chunk):
        ii, jj = i[k:k + chunk], j[k:k + chunk]
        rel = (z[jj] - z[ii]) * np.exp(-1j * ms.angle[ii])   # neighbour in i's frame
        ws = np.exp(-np.abs(rel[:, None] - cells[None]) ** 2 / (2 * sigma_s ** 2))
        dth = wrap_angle(ms.angle[jj] - ms.angle[ii])
        wd = np.exp(-wrap_angle(dth[:, None] - dirs[None]) ** 2 / (2 * sigma_d ** 2))
        contrib = (ws[:, :, None] * wd[:, None, :]).reshape(len(ii), size)
        # sum the contributions per minutia: a sparse row-selection matrix times them
        sel = sparse.csr_matrix((np.ones(len(ii)), (ii, np.arange(len(ii)))),
                                shape=(n, len(ii)))
        out += sel @ contrib
    return _unit_rows(np.sqrt(out))


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
    """Query edges prepared for :meth:`EdgeHash.lookup_prepared` (see
    :meth:`EdgeHash.prepare`): cell keys and compact invariants of the edges that fall inside
    the hash's length range; ``rows`` are their indices in the caller's query arrays."""

    geometry: tuple
    rows: np.ndarray
    key: np.ndarray
    length: np.ndarray
    length_tol: np.ndarray
    beta_i: np.ndarray
    beta_j: np.ndarray


class EdgeHash:
    """Hash table of edge invariants for fast candidate edge correspondences.

    Edges are keyed by their quantised (length, beta_i, beta_j). Each stored edge is filed
    under every cell within ``reach`` cells of its own, so that a query visits the single
    cell of each query edge: the stored side pays the tolerance once, at build time, and a
    look-up is one table read per query edge. The key space is small (length cells x angle
    cells^2), so the table is dense (direct indexing, no binary search). Candidates are then
    cut to the continuous tolerances; each (query, stored) pair is reported at most once.

    Parameters
    ----------
    edges : EdgeTable
        The stored (reference) edges.
    length_step : float
        Length cell size (px); use the length tolerance.
    angle_step : float
        Angle cell size (rad); use the angle tolerance (rounded down to divide 2 pi).
    max_length : float
        Longest edge length (px) to hash; longer stored edges are dropped.
    length_reach : int
        Neighbouring length cells each edge is filed under: queries may use a length
        tolerance up to ``length_reach * length_step`` (raise it for scale-tolerant queries).
    subdivision : int
        Cells of ``1 / subdivision`` of the steps (each edge filed ``subdivision`` times as
        far): the cells a query reads then hug its tolerance box more closely, so fewer
        candidates fail the cut (27/8 of the needed volume at 1, 125/64 at 2), at the cost
        of ~5x the entries. Worth it for small sets (a block) matched many times.
    """

    def __init__(self, edges: EdgeTable, length_step: float, angle_step: float,
                 max_length: float = 160.0, length_reach: int = 1, subdivision: int = 1):
        sub = int(subdivision)
        self.length_step = float(length_step) / sub
        self.angle_reach = sub
        self.n_angle = max(2 * sub + 1, int(np.floor(sub * TWO_PI / angle_step)))
        self.angle_step = TWO_PI / self.n_angle
        self.n_length = int(np.floor(max_length / self.length_step)) + 1
        self.length_reach = int(length_reach) * sub
        self.edges = edges
        rows, cols = np.nonzero(edges.valid & (edges.length <= max_length))
        # per stored edge, contiguous 1-D arrays for the tolerance cut and the caller
        self.rows, self.cols = rows, cols
        self.length = edges.length[rows, cols]
        self.beta_i = edges.beta_i[rows, cols]
        self.beta_j = edges.beta_j[rows, cols]
        self.j = edges.j[rows, cols]
        self.direction = edges.direction[rows, cols]
        ql, q1, q2 = self._cells(self.length, self.beta_i, self.beta_j)
        dl = np.arange(-self.length_reach, self.length_reach + 1)
        da = np.arange(-self.angle_reach, self.angle_reach + 1)
        kl = ql[:, None, None, None] + dl[None, :, None, None]
        k1 = (q1[:, None, None, None] + da[None, None, :, None]) % self.n_angle
        k2 = (q2[:, None, None, None] + da[None, None, None, :]) % self.n_angle
        n_cells = len(dl) * len(da) * len(da)   # cells per edge (no edge: no -1 to infer)
        inside = np.broadcast_to((kl >= 0) & (kl < self.n_length), k1.shape[:1] + (
            len(dl), len(da), len(da))).reshape(len(ql), n_cells)
        keys = ((kl * self.n_angle + k1) * self.n_angle + k2).reshape(len(ql), n_cells)[inside]
        entry = np.broadcast_to(np.arange(len(ql))[:, None], inside.shape)[inside]
        n_keys = self.n_length * self.n_angle ** 2
        # small key space: numpy's stable sort of 16-bit integers is a radix sort
        order = np.argsort(keys.astype(np.uint16 if n_keys <= 2 ** 16 else np.int32),
                           kind="stable")
        self.entry = entry[order]
        self.start = np.concatenate([[0], np.cumsum(np.bincount(keys, minlength=n_keys))])
        # the invariants in entry order, compact, for the tolerance cut of a look-up
        self._entry_length = self.length[self.entry]
        self._entry_beta_i = self.beta_i[self.entry]
        self._entry_beta_j = self.beta_j[self.entry]

    def __len__(self) -> int:
        return len(self.length)

    @property
    def geometry(self) -> tuple:
        """Cell layout; hashes with the same geometry accept the same prepared queries."""
        return self.length_step, self.n_angle, self.n_length

    def _cells(self, length, beta_i, beta_j):
        ql = np.floor(np.asarray(length) / self.length_step).astype(np.intp)
        q1 = np.floor(np.asarray(beta_i) / self.angle_step).astype(np.intp) % self.n_angle
        q2 = np.floor(np.asarray(beta_j) / self.angle_step).astype(np.intp) % self.n_angle
        return ql, q1, q2

    def prepare(self, length, beta_i, beta_j, length_tol) -> EdgeQuery:
        """Query edges in this hash's cell layout (reusable with any hash of the same
        :attr:`geometry`, e.g. one camera set against many landmark blocks)."""
        length = np.asarray(length, float)
        length_tol = np.broadcast_to(np.asarray(length_tol, float), length.shape)
        if length_tol.max(initial=0.0) > self.length_reach * self.length_step + 1e-9:
            raise ValueError("EdgeHash: length tolerance wider than the hash was built for")
        ql, q1, q2 = self._cells(length, beta_i, beta_j)
        inside = ql < self.n_length
        key = ((ql * self.n_angle + q1) * self.n_angle + q2)[inside]
        return EdgeQuery(self.geometry, np.flatnonzero(inside), key, length[inside],
                         length_tol[inside], np.asarray(beta_i, float)[inside],
                         np.asarray(beta_j, float)[inside])

    def lookup(self, length, beta_i, beta_j, length_tol, angle_tol):
        """Stored edges within tolerance of each query edge.

        Parameters
        ----------
        length, beta_i, beta_j : ndarray, shape (m,)
            Query edge invariants.
        length_tol : float or ndarray (m,)
            Absolute length tolerance (px) per query edge, at most
            ``length_reach * length_step``.
        angle_tol : float
            Tolerance (rad) on each of the two relative angles, at most the ``angle_step``
            the hash was built with.

        Returns
        -------
        q : ndarray of intp
            Index of the query edge.
        e : ndarray of intp
            Index of the stored edge in this hash's per-edge arrays (``rows``, ``cols``,
            ``j``, ``direction``, ``length``, ...).
        """
        return self.lookup_prepared(self.prepare(length, beta_i, beta_j, length_tol),
                                    angle_tol)

    def lookup_prepared(self, query: EdgeQuery, angle_tol: float):
        """:meth:`lookup` for query edges from :meth:`prepare` (same returns)."""
        if query.geometry != self.geometry:
            raise ValueError("EdgeHash.lookup_prepared: query prepared for another layout")
        if angle_tol > self.angle_reach * self.angle_step + 1e-12:
            raise ValueError("EdgeHash.lookup: tolerance wider than the hash was built for")
        if _kernels.HAVE_NUMBA:
            return _kernels.edge_lookup(self.start, self.entry, self._entry_length,
                                        self._entry_beta_i, self._entry_beta_j, query.rows,
                                        query.key, query.length, query.length_tol,
                                        query.beta_i, query.beta_j, float(angle_tol),
                                        TWO_PI - angle_tol)
        lo = self.start[query.key]
        counts = self.start[query.key + 1] - lo
        ends = np.cumsum(counts)
        total = int(ends[-1]) if len(ends) else 0
        q = np.repeat(np.arange(len(counts)), counts)
        pos = np.arange(total) + np.repeat(lo - (ends - counts), counts)
        keep = np.abs(self._entry_length[pos] - query.length[q]) <= query.length_tol[q]
        # both angles lie in [0, 2 pi): the wrapped difference is within tol exactly when the
        # plain one is within tol of 0 or of +-2 pi (cheaper than wrapping)
        for stored, queried in ((self._entry_beta_i, query.beta_i),
                                (self._entry_beta_j, query.beta_j)):
            d = np.abs(stored[pos] - queried[q])
            keep &= (d <= angle_tol) | (d >= TWO_PI - angle_tol)
        return query.rows[q[keep]], self.entry[pos[keep]]

    def query(self, length, beta_i, beta_j, length_tol, angle_tol):
        """Like :meth:`lookup`, returning the stored edges as (minutia, slot) of the table.

        Returns
        -------
        q, rows, cols : ndarray of intp
        """
        q, e = self.lookup(length, beta_i, beta_j, length_tol, angle_tol)
        return q, self.rows[e], self.cols[e]
