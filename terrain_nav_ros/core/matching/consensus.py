"""Consensus: Hough voting of the candidates (dissertation chapter 4, step 2 of
:mod:`.matcher`).

The candidates' rotations are voted first, then the translations at each rotation peak (a
two-stage Hough keeps the translation cells sharp); the strongest (rotation, translation)
cells become hypotheses with their supporting correspondences. The sweep of the wider try
ranks every rotation cell by its strongest translation cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import cv2
import numpy as np

from . import _matching_kernels as _kernels
from .descriptors import TWO_PI, wrap_angle
from .index import MinutiaIndex
from .params import MatchParams
from .proposals import _Votes


@dataclass
class _Hypothesis:
    c: complex          # rotation (and scale) as a complex factor
    t: complex          # translation: z_b = c * z_a + t
    ia: np.ndarray      # supporting correspondences
    ib: np.ndarray
    support: float


def _rotation_peaks(theta, w, p: MatchParams, n_peaks: int) -> np.ndarray:
    """Centres of the strongest rotation cells (circular histogram, 3-cell smoothing)."""
    nb = max(4, int(round(TWO_PI / p.rot_bin)))
    if _kernels.HAVE_NUMBA:
        h = _kernels.rotation_histogram(theta, w, nb, nb / TWO_PI)
    else:
        k = (np.floor((theta + np.pi) * (nb / TWO_PI)).astype(np.intp)) % nb
        h = np.bincount(k, w, nb)
    h = np.concatenate([h[-1:], h, h[:1]])            # circular: pad one cell each side
    h = h[:-2] + h[1:-1] + h[2:]
    pad = np.concatenate([h[-1:], h, h[:1]])
    idx = np.flatnonzero((h >= pad[:-2]) & (h > pad[2:]) & (h > 0))
    idx = idx[np.argsort(-h[idx])][:n_peaks]
    # weak rotation peaks beside a dominant one are not worth a translation search
    idx = idx[h[idx] >= p.min_support_ratio * h[idx[0]]] if len(idx) else idx
    return (idx + 0.5) * (TWO_PI / nb) - np.pi


def _vote_midpoints(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, sel=slice(None)):
    """The edge midpoints in A (from A's centroid) and in B of the votes ``sel``: the
    translation of A's centroid at rotation ``c`` is ``mid_b - c * mid_a``."""
    return (0.5 * (a.z[v.ia[sel]] + a.z[v.ja[sel]]) - a.centroid,
            0.5 * (b.z[v.ib[sel]] + b.z[v.jb[sel]]))


def _rotation_support(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                      rotations: np.ndarray, midpoints=None) -> np.ndarray:
    """Weight of the strongest translation cell (3 x 3 cells centred on a voted one) at each
    rotation: the joint rotation-translation Hough, one rotation at a time, as
    :func:`_hypotheses` builds it at a rotation peak."""
    mid_a, mid_b = midpoints if midpoints is not None else _vote_midpoints(v, a, b)
    if _kernels.HAVE_NUMBA:
        return _kernels.rotation_support(v.theta, v.weight, mid_a, mid_b, rotations,
                                         2.0 * p.rot_bin, 1.0 / p.trans_bin)
    out = np.zeros(len(rotations))
    for k, th0 in enumerate(rotations):
        sel, d_sel = _near_rotation(v.theta, th0, p)
        w = v.weight[sel].astype(float)
        if len(sel) == 0 or w.sum() <= 0:
            continue
        c = np.exp(1j * (th0 + np.dot(w, d_sel) / w.sum()))
        gx, gy, nx, ny, h = _translation_grid(mid_b[sel] - c * mid_a[sel], w, p)
        h = np.pad(h, 1)
        box = sum(h[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
                  for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        out[k] = box[gy, gx].max()
    return out


def _hypotheses(v: _Votes, a: MinutiaIndex, b: MinutiaIndex, p: MatchParams,
                sweep: bool = False):
    """Strongest (rotation, translation) Hough cells, best first: at the rotation
    histogram's peaks, or with ``sweep`` at the rotation cells whose strongest translation
    cell is heaviest, among those the peaks leave out."""
    if len(v.ia) == 0:
        return []
    hyps = []
    best = 0.0
    if p.max_rotation < math.pi:
        # a heading prior: only rotations within max_rotation of zero are searched
        keep = np.abs(wrap_angle(v.theta)) <= p.max_rotation + p.rot_bin
        v = _Votes(*(getattr(v, f.name)[keep] for f in fields(v)))
        if len(v.ia) == 0:
            return []
    peaks = _rotation_peaks(v.theta, v.weight, p, n_peaks=p.n_rotation_peaks)
    rotations = peaks
    midpoints = None   # of all votes, when the sweep needs them anyway
    if sweep:
        # the strongest joint cells among the rotations the peaks did not try (a peak is a
        # cell centre of the same grid: its hypotheses would come out the same)
        midpoints = _vote_midpoints(v, a, b)
        nb = max(4, int(round(TWO_PI / p.rot_bin)))
        cells = (np.arange(nb) + 0.5) * (TWO_PI / nb) - np.pi
        support = _rotation_support(v, a, b, p, cells, midpoints)
        support[np.rint((peaks + np.pi) * (nb / TWO_PI) - 0.5).astype(np.intp) % nb] = 0.0
        strongest = np.argsort(-support, kind="stable")[:p.n_rotation_peaks]
        rotations = cells[strongest[support[strongest] > 0]]
    for th0 in rotations:
        sel, d_sel = _near_rotation(v.theta, th0, p)
        w = v.weight[sel]
        if len(sel) == 0 or w.sum() < p.min_support_ratio * best:
            continue   # none of its cells could pass the verification cut in _match
        c = np.exp(1j * (th0 + np.dot(w, d_sel) / w.sum()))
        # translation of A's centroid at this rotation: a two-stage Hough keeps the
        # translation cells sharp (a per-vote rotation error would smear them)
        mid_a, mid_b = ((midpoints[0][sel], midpoints[1][sel]) if midpoints is not None
                        else _vote_midpoints(v, a, b, sel))
        t = mid_b - c * mid_a
        hyps.extend(_translation_peaks(t, sel, w, c, v, a, p, n_peaks=2,
                                       min_support=p.min_support_ratio * best))
        best = max(h.support for h in hyps) if hyps else 0.0
    hyps.sort(key=lambda h: -h.support)
    return hyps[:p.n_hypotheses]


def _near_rotation(theta, th0: float, p: MatchParams):
    """Votes within two rotation cells of ``th0``: their indices and angle differences."""
    if _kernels.HAVE_NUMBA:
        return _kernels.near_angles(theta, float(th0), 2.0 * p.rot_bin)
    d = wrap_angle(theta - th0)
    sel = np.flatnonzero(np.abs(d) <= 2.0 * p.rot_bin)
    return sel, d[sel]


def _translation_grid(t, w, p: MatchParams):
    """Translation Hough cells: each vote's cell ``(gx, gy)`` from the lowest translation,
    the grid size and the float64 weight per cell, shape ``(ny, nx)``."""
    if _kernels.HAVE_NUMBA:
        gx, gy, nx, ny, h = _kernels.translation_grid(t.real, t.imag, w, 1.0 / p.trans_bin)
        return gx, gy, nx, ny, h.reshape(ny, nx)
    x0, y0 = t.real.min(), t.imag.min()
    gx = ((t.real - x0) * (1.0 / p.trans_bin)).astype(np.intp)
    gy = ((t.imag - y0) * (1.0 / p.trans_bin)).astype(np.intp)
    nx, ny = int(gx.max()) + 1, int(gy.max()) + 1
    return gx, gy, nx, ny, np.bincount(gy * nx + gx, w, nx * ny).reshape(ny, nx)


def _translation_peaks(t, sel, w, c, v: _Votes, a: MinutiaIndex, p: MatchParams, n_peaks,
                       min_support: float = 0.0):
    """Strongest translation cells at rotation ``c``; cells weaker than ``min_support``
    (which :meth:`~.matcher.Matcher._match` would not verify) are not built."""
    gx, gy, nx, ny, h = _translation_grid(t, w, p)
    h = h.astype(np.float32)
    # 3x3 box sum so that a cluster split over cell borders still counts as one
    box = cv2.boxFilter(h, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    out = []
    for _ in range(n_peaks):
        k = int(np.argmax(box))
        # (float32 box sums: a hair of slack so that no cell at the cut is lost)
        if box.flat[k] <= 0 or box.flat[k] < min_support * (1.0 - 1e-4):
            break
        py, px = divmod(k, nx)
        box[max(0, py - 2):py + 3, max(0, px - 2):px + 3] = 0
        if _kernels.HAVE_NUMBA:
            m = _kernels.cell_members(gx, gy, px, py)
        else:
            m = np.flatnonzero((np.abs(gx - px) <= 1) & (np.abs(gy - py) <= 1))
        wm = w[m]
        tc = complex(np.dot(wm, t[m]) / wm.sum())
        s = sel[m]
        ia = np.concatenate([v.ia[s], v.ja[s]])
        ib = np.concatenate([v.ib[s], v.jb[s]])
        out.append(_Hypothesis(c, tc - c * a.centroid, ia, ib, float(wm.sum())))
    return out
