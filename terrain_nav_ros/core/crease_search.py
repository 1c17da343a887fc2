"""Registration proposals from the crease skeletons alone, for sets with too few minutiae.

A block of ~60 px holds 3-9 minutiae, of which 0-2 repeat between a camera view and its
landmark: too few for the minutiae's pair votes to propose the transform. Yet its crease
skeleton has a few hundred pixels, and at the true transform 55-85 % of them land on the
landmark's creases against a chance of 10-20 % (gredos 25 m, 58 px blocks). This module finds
such transforms by brute force, cheaply, with FFTs:

* the crease pixels are split into four axial direction channels (0, 45, 90, 135 degrees,
  each pixel shared between its two nearest channels with weights ``max(0, cos 2 d)``);
* for every searched rotation the query's channels are rasterised and cross-correlated with
  the reference's (blurred by the hit radius), all rotations in one batched FFT: the sum over
  channels is the number of direction-consistent hits at every translation;
* the strongest peaks, among the translations that keep at least half of the query's crease
  pixels over the reference, are the proposals. The matcher then refines each on the creases
  and scores it like any other registration (:mod:`.crease_check`).

Geometry in the math frame ``z = col - 1j*row`` of :mod:`.descriptors`; ``z_b = c z_a + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import fft as sfft

from .crease_check import CreaseField, CreaseSamples

_CHANNEL_ANGLES = np.arange(4) * (np.pi / 4.0)


def _channel_weights(direction: np.ndarray) -> np.ndarray:
    """(4, ...) weights of axial directions (rad) on the four direction channels."""
    d = np.asarray(direction, float)
    return np.maximum(np.cos(2.0 * (d[None] - _CHANNEL_ANGLES.reshape((4,) + (1,) * d.ndim))),
                      0.0)


class CreaseSearchReference:
    """The reference side of the search: its direction channels, ready for correlation.

    Parameters
    ----------
    field : CreaseField
        The reference creases (the skeleton is where the distance is zero).
    blur : float
        Gaussian sigma (px) of the channels: the position tolerance of a hit.
    resolution : float
        The search runs at this fraction of the pixel resolution (0.5: a quarter of the FFT
        work); its proposals are refined at full resolution on the creases afterwards.
    """

    def __init__(self, field: CreaseField, blur: float = 1.5, resolution: float = 0.5):
        self.resolution = float(resolution)
        rows, cols = np.nonzero(field.distance == 0)
        w = _channel_weights(field.direction[rows, cols].astype(float))
        h, wd = field.shape
        self.shape = (max(int(round(h * resolution)), 1), max(int(round(wd * resolution)), 1))
        self.channels = np.zeros((4, *self.shape), np.float32)
        full = np.zeros(field.shape, np.float32)
        for k in range(4):
            full[:] = 0.0
            full[rows, cols] = w[k]
            # a crease within the blur counts (nearly) fully: kernel peak scaled to 1
            cv2.GaussianBlur(full, (0, 0), blur, dst=full)
            self.channels[k] = cv2.resize(full, self.shape[::-1], interpolation=cv2.INTER_AREA)
        self.channels *= 2.0 * math.pi * blur * blur
        self._spectra = {}

    def spectra(self, shape: tuple[int, int]):
        """Channel spectra and the footprint's spectrum, zero-padded to ``shape`` (cached)."""
        if shape not in self._spectra:
            ch = sfft.rfft2(self.channels, s=shape, workers=1)
            ones = sfft.rfft2(np.ones(self.shape, np.float32), s=shape, workers=1)
            self._spectra = {shape: (ch, ones)}   # one padded size in use at a time
        return self._spectra[shape]


def search_rotations(max_rotation: float, radius: float, tolerance: float = 3.0) -> np.ndarray:
    """Rotations (rad) to search: steps that move a pixel at ``radius`` by <= ``tolerance``.

    The whole circle when ``max_rotation >= pi``, else ``[-max_rotation, max_rotation]``.
    """
    step = min(tolerance / max(radius, 1.0), math.radians(15.0))
    if max_rotation >= math.pi:
        n = int(math.ceil(2.0 * math.pi / step))
        return np.arange(n) * (2.0 * math.pi / n) - math.pi
    n = int(math.ceil(max_rotation / step))
    return np.linspace(-max_rotation, max_rotation, 2 * n + 1)


@dataclass(frozen=True)
class CreaseSearchResult:
    """Proposals of :func:`search_transforms` and the size of the space they came from."""

    proposals: list          # (c, t, hits): rotation factor, translation, weighted hits
    log10_transforms: float  # log10 of the distinguishable transforms searched


def search_transforms(samples: CreaseSamples, reference: CreaseSearchReference,
                      rotations: np.ndarray, n_best: int = 3, min_inside: float = 0.5,
                      hit_radius: float = 1.5) -> CreaseSearchResult:
    """Transforms A -> B under which most of A's crease pixels fall on B's creases.

    Parameters
    ----------
    samples : CreaseSamples
        Query creases (A).
    reference : CreaseSearchReference
        Reference creases (B).
    rotations : ndarray
        Rotations (rad) to search (:func:`search_rotations`).
    n_best : int
        Proposals returned, strongest first, at least ``2 * rotation step`` or 4 px apart.
    min_inside : float
        Translations that keep less than this fraction of A's crease pixels over B are not
        proposed.

    hit_radius : float
        Position tolerance (px) of a crease hit: translations closer than this are not
        distinguishable, which sets the count of transforms searched.

    Returns
    -------
    CreaseSearchResult
        Proposals (rotation factor, translation in the math frame, direction-consistent
        hits), strongest first, and ``log10`` of the rotations times the translations (in
        cells of ``pi hit_radius^2``) searched: a score of the best of them must pay for it.
    """
    n = len(samples)
    if n == 0 or len(rotations) == 0:
        return CreaseSearchResult([], 0.0)
    cs = np.exp(1j * np.asarray(rotations, float))
    scale = reference.resolution
    q = cs[:, None] * (samples.z[None, :] * scale)              # (n_rot, n), search pixels
    cols, rows = np.rint(q.real), np.rint(-q.imag)
    col0, row0 = cols.min(axis=1, keepdims=True), rows.min(axis=1, keepdims=True)
    ci, ri = (cols - col0).astype(np.intp), (rows - row0).astype(np.intp)
    ha, wa = int(ri.max()) + 1, int(ci.max()) + 1
    hb, wb = reference.shape
    shape = (sfft.next_fast_len(hb + ha - 1, real=True),
             sfft.next_fast_len(wb + wa - 1, real=True))
    n_rot = len(cs)
    # the query rasterised per rotation and channel: (n_rot, 5, ha, wa), channel 4 = count
    weights = _channel_weights(np.mod(samples.direction[None, :] + np.angle(cs)[:, None],
                                      np.pi))                 # (4, n_rot, n)
    flat = (np.arange(n_rot)[:, None] * (ha * wa) + ri * wa + ci).ravel()
    query = np.empty((n_rot, 5, ha * wa), np.float32)
    for k in range(4):
        query[:, k] = np.bincount(flat, weights[k].ravel(), n_rot * ha * wa).reshape(
            n_rot, ha * wa)
    query[:, 4] = np.bincount(flat, None, n_rot * ha * wa).reshape(n_rot, ha * wa)
    spec = sfft.rfft2(query.reshape(n_rot, 5, ha, wa), s=shape, workers=1)
    ref_ch, ref_ones = reference.spectra(shape)
    hits = sfft.irfft2(np.einsum("rkij,kij->rij", np.conj(spec[:, :4]), ref_ch), s=shape,
                       workers=1)
    inside = sfft.irfft2(np.conj(spec[:, 4]) * ref_ones, s=shape, workers=1)
    # circular correlation: shift s of A over B lives at index s mod shape; the shifts with
    # any overlap are -(ha - 1) .. hb - 1 (rows) and -(wa - 1) .. wb - 1 (cols)
    searched = inside >= min_inside * n
    hits = np.where(searched, hits, 0.0)
    cells = searched.sum() / (scale * scale) / (math.pi * hit_radius * hit_radius)
    log10_transforms = math.log10(max(float(cells), 1.0))
    out = []
    step = 2.0 * (np.ptp(rotations) / max(len(rotations) - 1, 1) if len(rotations) > 1 else 0.0)
    flat_hits = hits.reshape(n_rot, -1)
    n_top = min(50 * n_best, flat_hits.size)
    top = np.argpartition(-flat_hits, n_top - 1, axis=None)[:n_top]
    for idx in top[np.argsort(-flat_hits.ravel()[top], kind="stable")]:
        r, k = divmod(int(idx), flat_hits.shape[1])
        h = float(flat_hits[r, k])
        if h <= 0:
            break
        dy, dx = divmod(k, shape[1])
        dy = dy - shape[0] if dy > hb - 1 else dy
        dx = dx - shape[1] if dx > wb - 1 else dx
        c = complex(cs[r])
        # A pixel (ci, ri) lands on B pixel (ci + dx, ri + dy), in search pixels
        t = complex(dx - col0[r, 0], -(dy - row0[r, 0])) / scale
        if any(abs(math.remainder(np.angle(c) - np.angle(c2), 2 * math.pi)) <= step
               and abs(t - t2) <= 4.0 for c2, t2, _ in out):
            continue
        out.append((c, t, h))
        if len(out) == n_best:
            break
    return CreaseSearchResult(out, log10_transforms)
