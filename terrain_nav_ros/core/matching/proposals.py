"""Candidates: edge correspondences voting for a transform (dissertation chapter 4, step 1
of :mod:`.matcher`).

A pair of minutiae in A matched to a pair in B whose length and two relative angles agree
(:mod:`.descriptors`) is a minimal sample: two point correspondences fix a similarity
transform. ``"hash"`` looks every edge of A up in B's edge hash (complete, best for blocks);
``"roots"`` compares only the local edges of the ``k_roots`` minutiae of B with the most
similar shape context (the reference-pair selection of dissertation 4.2.2). Each vote is
weighted by the descriptor similarity of both correspondences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _matching_kernels as _kernels
from .descriptors import wrap_angle
from .index import MinutiaIndex
from .params import MatchParams, _length_tol


@dataclass
class _Votes:
    """Candidate edge correspondences: (ia -> ib) and (ja -> jb), rotation, weight."""

    ia: np.ndarray
    ja: np.ndarray
    ib: np.ndarray
    jb: np.ndarray
    theta: np.ndarray
    weight: np.ndarray


def _similarity_matrix(a: MinutiaIndex, b: MinutiaIndex, with_creases: bool = True):
    s = a.descriptor @ b.descriptor.T
    if with_creases and a.crease is not None and b.crease is not None:
        # 0.5 (s + max(crease products, 0)), in place (~18k entries a block pair)
        crease = a.crease @ b.crease.T
        s += np.maximum(crease, 0.0, out=crease)
        s *= 0.5
    return s


def _hash_votes(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> _Votes:
    hb = b.edge_hash()
    _, _, _, _, qi, qj, qdir = a.edge_query()
    q, e = hb.lookup_prepared(a.prepared_query(hb), p.edge_angle_tol)
    if _kernels.HAVE_NUMBA:
        ia, ja, ib, jb, theta = _kernels.hash_votes(q, e, qi, qj, qdir, hb.rows, hb.j,
                                                    hb.direction)
    else:
        ia, ja, ib, jb = qi[q], qj[q], hb.rows[e], hb.j[e]
        theta = wrap_angle(hb.direction[e] - qdir[q])
    if p.use_descriptors:
        s = _similarity_matrix(a, b)
        s = np.maximum(s, 0.0, out=s).ravel()
        if _kernels.HAVE_NUMBA and s.dtype == np.float32:
            w = _kernels.vote_weights(s, b.n, ia, ja, ib, jb)
        else:
            w = s[ia * b.n + ib] * s[ja * b.n + jb] + 0.05
    else:
        w = np.ones(len(ia))
    return _Votes(ia, ja, ib, jb, theta, w)


def _root_votes(a: MinutiaIndex, b: MinutiaIndex, p: MatchParams) -> _Votes:
    # shape contexts only: the crease descriptor's product over a region's thousands of
    # minutiae would triple the localisation time (the hash generator for blocks keeps it)
    s = _similarity_matrix(a, b, with_creases=False)
    k = min(p.k_roots, b.n)
    top = np.argpartition(-s, k - 1, axis=1)[:, :k] if k < b.n else np.tile(
        np.arange(b.n), (a.n, 1))
    ra = np.repeat(np.arange(a.n), k)
    rb = top.ravel()
    ea, eb = a.edges, b.edges
    kq, kr = min(p.k_query, ea.k), min(p.k_ref, eb.k)
    la = ea.length[ra, :kq, None]
    lb = eb.length[rb, None, :kr]
    tol = _length_tol(p, la)
    ok = (ea.valid[ra, :kq, None] & eb.valid[rb, None, :kr] & (np.abs(la - lb) <= tol)
          & (np.abs(wrap_angle(ea.beta_i[ra, :kq, None] - eb.beta_i[rb, None, :kr]))
             <= p.edge_angle_tol)
          & (np.abs(wrap_angle(ea.beta_j[ra, :kq, None] - eb.beta_j[rb, None, :kr]))
             <= p.edge_angle_tol))
    r, qa, qb = np.nonzero(ok)
    ia, ib = ra[r], rb[r]
    ja, jb = ea.j[ia, qa], eb.j[ib, qb]
    theta = wrap_angle(eb.direction[ib, qb] - ea.direction[ia, qa])
    w = np.maximum(s[ia, ib], 0.0) * np.maximum(s[ja, jb], 0.0) + 0.05
    return _Votes(ia, ja, ib, jb, theta, w)
