"""Registration proposals from the crease skeletons alone, for sets with too few minutiae.

A block of ~60 px holds 3-9 minutiae, of which 0-2 repeat between a camera view and its
landmark: too few for the minutiae's pair votes to propose the transform. Yet its crease
skeleton has a few hundred pixels, and at the true transform 53-86 % of them land on the
landmark's creases against a chance of 7-19 % (gredos 25 m, 58 px blocks). This module finds
such transforms by brute force, cheaply, with FFTs:

* the crease pixels are split into four axial direction channels (0, 45, 90, 135 degrees,
  each pixel shared between its two nearest channels with weights ``max(0, cos 2 d)``);
* for every searched rotation the query's channels are rasterised and cross-correlated with
  the reference's (blurred by the hit radius), all rotations in one batched FFT: the sum over
  channels is the number of direction-consistent hits at every translation;
* a whole-circle search tries rotations in quarter turns of each other (their count is a
  multiple of four): a quarter turn of the query is one of a square reference the other
  way, exactly, so only a quarter of the query's rotations are transformed, against the
  reference turned four ways (a reference that is not square is zero-padded to one first:
  the padding adds no hits, and the shifts searched stay those over its footprint);
* with many rotations, only the few with the most hits at half the resolution (a quarter
  of the product and of the inverse FFT each, from the spectra's lowest frequencies) are
  correlated at full resolution: the inverse FFT of every rotation was the search's
  largest cost; the query's spectra too are completed for those only (the shortlist
  reads their lowest columns, transformed for every rotation);
* the strongest peaks, among the translations that keep at least half of the query's crease
  pixels over the reference, are the proposals. The matcher then refines each on the creases
  and scores it like any other registration (:mod:`.crease_check`).

The search runs at one of five levels (:class:`SearchLevel`): :data:`FINE` (half the pixel
resolution, rotations 3 px apart at the query's reach), :data:`COARSE` (a quarter, 6 px: an
eighth of the work), :data:`COARSER` (an eighth, 12 px; large views), :data:`SIXTEENTH`
(24 px; views of 384 px and more in their 3x regions) or :data:`THIRTY_SECOND` (48 px; 768 px
and more). A coarse level
blurs each peak over its cell, too coarsely to rank them: its strongest few dozen are
searched again near their place at the fine level (:func:`local_peaks`, the next level of
a pyramid: the rotations, scales and shifts of the fine grid within the coarse cell, by
direct look-ups of the fine reference, a few milliseconds for all), and the proposals are
those with the most hits there. The coarser levels' proposals (large views) are placed
at each finer level down to the coarse one likewise, a step of the pyramid each, and go on
to the coarse-to-fine ICP of the matcher.

Geometry in the math frame ``z = col - 1j*row`` of :mod:`.descriptors`; ``z_b = c z_a + t``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import fft as sfft

from . import _matching_kernels as _kernels
from .crease_check import CreaseField, CreaseSamples

_CHANNEL_ANGLES = np.arange(4) * (np.pi / 4.0)
_QUARTER_TURNS = (1, 1j, -1, -1j)   # counterclockwise, exact


@dataclass(frozen=True)
class SearchLevel:
    """Sampling of a crease search."""

    resolution: float           # search pixels per image pixel
    rotation_tolerance: float   # image px a rotation step moves the query's reach by


FINE = SearchLevel(resolution=0.5, rotation_tolerance=3.0)
COARSE = SearchLevel(resolution=0.25, rotation_tolerance=6.0)
# large views (a camera footprint, not a block): an eighth, 12 px; their proposals need the
# coarse-to-fine ICP too
COARSER = SearchLevel(resolution=0.125, rotation_tolerance=12.0)
# views too large for the work bound at an eighth (384 px and more in their 3x regions): a
# sixteenth, 24 px; and at that (768 px and more): a thirty-second, 48 px
SIXTEENTH = SearchLevel(resolution=0.0625, rotation_tolerance=24.0)
THIRTY_SECOND = SearchLevel(resolution=0.03125, rotation_tolerance=48.0)
LEVELS = (FINE, COARSE, COARSER, SIXTEENTH, THIRTY_SECOND)


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
    background : float
        With a positive value, the channels' local mean (Gaussian, this sigma in search px)
        is subtracted: a query then counts the hits above those the reference's local crease
        density gives any transform. A large view over dense creases (albedo edges of
        fields, the noise of an old DEM) otherwise draws its proposals to where the creases
        are densest, not to where they agree.
    """

    def __init__(self, field: CreaseField, blur: float = 1.5, resolution: float = 0.5,
                 background: float = 0.0):
        self.resolution = float(resolution)
        rows, cols = np.nonzero(field.distance == 0)
        w = _channel_weights(field.direction[rows, cols].astype(float))
        h, wd = self.full_shape = field.shape
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
        if background > 0:
            # hits above the local density of creases: where creases are dense (fields,
            # noise of the DEM), any transform scores many hits; only the excess locates
            for k in range(4):
                self.channels[k] -= cv2.GaussianBlur(self.channels[k], (0, 0), background)
        # search pixels that hold the reference image: rows [r0, r1), cols [c0, c1)
        self.footprint = (0, self.shape[0], 0, self.shape[1])
        self._spectra = {}
        self._turns = {0: self}
        self._squared = None

    @property
    def square(self) -> bool:
        return self.shape[0] == self.shape[1] and self.full_shape[0] == self.full_shape[1]

    def _derived(self, channels: np.ndarray, full_shape: tuple[int, int],
                 footprint: tuple[int, int, int, int]) -> CreaseSearchReference:
        """A reference with these channels (a turned or padded copy of this one)."""
        out = object.__new__(CreaseSearchReference)
        out.resolution = self.resolution
        out.full_shape = full_shape
        out.channels = channels
        out.shape = channels.shape[1:]
        out.footprint = footprint
        out._spectra, out._turns, out._squared = {}, {}, None
        return out

    def squared(self) -> CreaseSearchReference:
        """This reference zero-padded at the bottom or right to a square (itself when square;
        cached), with the same footprint: the padding holds no crease, so it adds no hit,
        and a shift over it only is not searched. A square reference can be turned in
        quarter turns (:meth:`turned`) without changing its frame's extent."""
        if self.square:
            return self
        if self._squared is None:
            side = max(self.shape)
            channels = np.zeros((4, side, side), np.float32)
            channels[:, :self.shape[0], :self.shape[1]] = self.channels
            full_side = max(self.full_shape)
            self._squared = self._derived(channels, (full_side, full_side), self.footprint)
        return self._squared

    def turned(self, quarter_turns: int) -> CreaseSearchReference:
        """This reference turned clockwise by ``quarter_turns`` x 90 degrees, its crease
        directions and footprint with it (cached). Math-frame coordinates ``z`` of this
        reference's search pixels become ``z' = (-1j)**quarter_turns * z +
        turn_offset(quarter_turns)``."""
        j = quarter_turns % 4
        if j not in self._turns:
            # a quarter turn swaps the 0 / 90 deg and the 45 / 135 deg channels
            channels = self.channels[[2, 3, 0, 1]] if j % 2 else self.channels
            footprint, h = self.footprint, self.shape[0]
            for k in range(j):
                # one clockwise turn: pixel (row, col) -> (col, h - 1 - row)
                r0, r1, c0, c1 = footprint
                footprint = (c0, c1, h - r1, h - r0)
                h = self.shape[(k + 1) % 2]
            self._turns[j] = self._derived(
                np.ascontiguousarray(np.rot90(channels, -j, axes=(1, 2))),
                self.full_shape[::-1] if j % 2 else self.full_shape, footprint)
        return self._turns[j]

    def turn_offset(self, quarter_turns: int) -> complex:
        """Offset (search px) of :meth:`turned`'s frame: one clockwise turn of an array of
        ``h`` rows maps ``z`` to ``-1j * z + (h - 1)``."""
        offset, h, w = 0j, *self.shape
        for _ in range(quarter_turns % 4):
            offset, h, w = -1j * offset + (h - 1), w, h
        return offset

    def padded(self, margin: int) -> tuple[np.ndarray, int]:
        """The channels with a zero border of at least ``margin`` pixels, and its width
        (cached; :func:`local_peaks` looks them up at offsets without bounds tests)."""
        if getattr(self, "_padded", (None, -1))[1] < margin:
            pad = max(margin, 8)
            self._padded = (np.pad(self.channels, ((0, 0), (pad, pad), (pad, pad))), pad)
        return self._padded

    def turned_spectra(self, shape: tuple[int, int], n_turns: int):
        """Channel spectra, zero-padded to ``shape``, of this reference turned 0 ..
        ``n_turns - 1`` times (n_turns, 4, ...), and their :func:`_low_frequencies`
        (cached for one padded shape at a time)."""
        key = (shape, n_turns)
        if key not in self._spectra:
            channels = np.stack([self.turned(j).channels for j in range(n_turns)])
            full = sfft.rfft2(channels, s=shape, workers=1)
            self._spectra = {key: (full, _low_frequencies(full, shape))}
        return self._spectra[key]


def search_rotations(max_rotation: float, radius: float, tolerance: float = 3.0) -> np.ndarray:
    """Rotations (rad) to search: steps that move a pixel at ``radius`` by <= ``tolerance``.

    The whole circle when ``max_rotation >= pi`` (a multiple of four rotations, in quarter
    turns of each other), else ``[-max_rotation, max_rotation]``.
    """
    step = min(tolerance / max(radius, 1.0), math.radians(15.0))
    if max_rotation >= math.pi:
        # a multiple of four: quarter turns of each other (see CreaseSearchQuery)
        return _whole_circle(4 * int(math.ceil(2.0 * math.pi / step / 4.0)))
    n = int(math.ceil(max_rotation / step))
    return np.linspace(-max_rotation, max_rotation, 2 * n + 1)


def search_scales(max_scale_change: float, radius: float, tolerance: float = 3.0) -> np.ndarray:
    """Scales to search: 1 and steps that move a pixel at ``radius`` by <= ``tolerance``
    (half a step either way is within the tolerance), out to ``1 +- max_scale_change``.

    A scale error of the view (the prior's height above ground) of 10 % moves the edge of a
    256 px view by 13 px: more than a hit's tolerance at any level but the coarsest.
    """
    step = tolerance / max(radius, 1.0)
    k = int(round(max(max_scale_change, 0.0) / step))
    return 1.0 + step * np.arange(-k, k + 1)


def min_search_work(n_transforms: int, reference_shape: tuple[int, int],
                    resolution: float) -> int:
    """A lower bound of :meth:`CreaseSearchQuery.work` for ``n_transforms`` transforms of any
    query (the FFT holds at least the reference): a level it puts above the work bound is
    out without rasterising its query."""
    hb, wb = (max(int(round(n * resolution)), 1) for n in reference_shape)
    return n_transforms * sfft.next_fast_len(hb, real=True) * sfft.next_fast_len(wb, real=True)


def _whole_circle(n: int) -> np.ndarray:
    """``n`` rotations evenly over the circle, from -pi."""
    return np.arange(n) * (2.0 * math.pi / n) - math.pi


class CreaseSearchQuery:
    """The query side of the search: its crease pixels rasterised at every searched rotation.

    Build it once per set: in a block study each camera block is searched against every
    landmark block, and its rotated rasters and their spectra do not change.

    Parameters
    ----------
    samples : CreaseSamples
        Query creases (A).
    rotations : ndarray
        Rotations (rad) to search (:func:`search_rotations`).
    resolution : float
        As the references' (:class:`CreaseSearchReference`).
    quarter_turns : bool
        When the rotations are :func:`search_rotations`' whole circle, rasterise and
        transform only the first quarter: the others are its exact quarter turns, searched
        as the first quarter against the reference turned the other way
        (:meth:`CreaseSearchReference.turned`); a quarter of the query's FFT work.
    scales : sequence of float
        Scales to search (:func:`search_scales`), each at every rotation; the transforms
        searched are ``c = scale * exp(1j * rotation)``.
    """

    def __init__(self, samples: CreaseSamples, rotations: np.ndarray, resolution: float = 0.5,
                 quarter_turns: bool = True, scales=(1.0,)):
        self.n = len(samples)
        self.resolution = float(resolution)
        self.rotations = np.asarray(rotations, float)
        self.scales = np.asarray(scales, float).ravel()
        n_rot = len(self.rotations)
        self.quarter = bool(quarter_turns and n_rot and n_rot % 4 == 0
                            and np.allclose(self.rotations, _whole_circle(n_rot)))
        if self.quarter:
            # exact quarter turns (multiplying by 1j only swaps and negates): their rasters
            # are exact quarter turns of the first quarter's
            first = (self.scales[:, None] * np.exp(1j * self.rotations[:n_rot // 4])).ravel()
            self.c = np.concatenate([first * turn for turn in _QUARTER_TURNS])
        else:
            self.c = (self.scales[:, None] * np.exp(1j * self.rotations)).ravel()
        # transforms rasterised and transformed: the first quarter's, or all
        self.n_rastered = len(self.c) // 4 if self.quarter else len(self.c)
        # the raster's origin per transform and its shape over all of them: from the outline
        # of the pixels alone (rounding is monotonic, and a linear map's extremes are on the
        # boundary of their hull), so that a level's work is known without rasterising
        self.col0, self.row0, self.shape = _raster_extent(samples.z, self.c * 1.0,
                                                          self.resolution)
        self._samples = samples
        self._raster = None
        # footprint counts and searched shifts, for one padded shape at a time
        self._spectra, self._low, self._per_shape = {}, None, {}
        self._margins = {}
        self.centre = complex(samples.z.mean()) if self.n else 0j   # math frame, image px

    @property
    def raster(self) -> np.ndarray:
        """(n_rastered, 5, h, w): the four direction channels and, in channel 4, the pixel
        count (built on first use: choosing a search level needs only the shape)."""
        if self._raster is None:
            n_rot = self.n_rastered
            direction, turn = self._samples.direction, np.angle(self.c[:n_rot])
            z = self._samples.z * self.resolution
            if _kernels.HAVE_NUMBA:
                # the places and the channels in one pass per transform
                self._raster = _kernels.rasterise_transformed(
                    z, np.ascontiguousarray(self.c[:n_rot]), self.col0[:n_rot],
                    self.row0[:n_rot], direction.astype(np.float64), turn, *self.shape)
                return self._raster
            # the pixels' places as the search's other steps compute them (a rounding tie,
            # e.g. at a half turn, must break the same way)
            q = self.c[:n_rot, None] * z[None, :]
            ci = (np.rint(q.real) - self.col0[:n_rot, None]).astype(np.intp)
            ri = (np.rint(-q.imag) - self.row0[:n_rot, None]).astype(np.intp)
            # the outline's extremes are all pixels' (_outline): this only keeps the kernel's
            # writes in bounds whatever the rounding
            np.clip(ri, 0, self.shape[0] - 1, out=ri)
            np.clip(ci, 0, self.shape[1] - 1, out=ci)
            size = self.shape[0] * self.shape[1]
            weights = _channel_weights(np.mod(
                direction[None, :] + turn[:, None], np.pi))   # (4, n_rot, n)
            flat = (np.arange(n_rot)[:, None] * size + ri * self.shape[1] + ci).ravel()
            raster = np.empty((n_rot, 5, size), np.float32)
            for k in range(4):
                raster[:, k] = np.bincount(flat, weights[k].ravel(), n_rot * size).reshape(
                    n_rot, size)
            raster[:, 4] = np.bincount(flat, None, n_rot * size).reshape(n_rot, size)
            self._raster = raster.reshape(n_rot, 5, *self.shape)
        return self._raster

    def padded_shape(self, reference_shape: tuple[int, int],
                     min_inside: float | None = None) -> tuple[int, int]:
        """FFT shape of a search against a reference image of ``reference_shape`` pixels
        (full resolution): room for every shift with any overlap or, with ``min_inside``,
        for the shifts searched (those keeping that fraction of the pixels over the
        reference) without aliases of other shifts with any overlap (~hb + ha / 2 instead
        of hb + ha per side)."""
        hb, wb = (max(int(round(n * self.resolution)), 1) for n in reference_shape)
        ha, wa = self.shape
        if min_inside is None or self.n == 0:
            need_rows, need_cols = ha - 1, wa - 1
        else:
            need_rows, need_cols = self._alias_margins(min_inside)
        return (sfft.next_fast_len(max(hb + min(need_rows, ha - 1), ha), real=True),
                sfft.next_fast_len(max(wb + min(need_cols, wa - 1), wa), real=True))

    def _alias_margins(self, min_inside: float) -> tuple[int, int]:
        """Padding (rows, cols) beyond the reference that keeps a searched shift free of
        aliases: a shift ``s`` keeps ``m`` pixels inside along an axis only between
        ``-x_(n-m+1)`` and ``h_b - 1 - x_(m)`` (``x_(i)``: the i-th smallest pixel
        coordinate), and its alias ``s +- P`` overlaps no pixel when ``P >= h_b +
        max(x_(n-m+1), x_max - x_(m))`` (per rotation; the largest over them)."""
        if min_inside not in self._margins:
            m = min(max(int(math.ceil(min_inside * self.n)), 1), self.n)
            counts = self.raster[:, 4]
            need = [_order_margin(counts.sum(axis=axis), self.n, m) for axis in (2, 1)]
            if self.quarter:
                # a quarter turn swaps the rows and the columns and mirrors one of them, which
                # leaves the margin of each as it was (x_(k) -> x_max - x_(n-1-k))
                need = [max(need)] * 2
            self._margins[min_inside] = tuple(need)
        return self._margins[min_inside]

    def work(self, reference_shape: tuple[int, int]) -> int:
        """Rotations times padded FFT pixels of a search against ``reference_shape``: its
        time and the memory of its spectra (~16 bytes each) grow with it."""
        return len(self.c) * math.prod(self.padded_shape(reference_shape))

    def spectra(self, reference: CreaseSearchReference, min_inside: float | None = 0.5,
                rastered: np.ndarray | None = None):
        """Padded FFT shape (for the shifts that keep ``min_inside`` of the pixels over
        ``reference``, or any with ``None``) and channel spectra, not conjugated (cached for
        one padded shape at a time).

        Only the spectra of the rastered transforms ``rastered`` (indices; all by default)
        are complete: the others hold their lowest columns (:meth:`low_spectra`'s, which
        the shortlist reads) until a later call asks for them. The full-resolution
        correlation of a shortlist needs about half of a view's rasters, and the column
        transforms of the rest were ~40 % of the query's FFT work.
        """
        shape = self.padded_shape(reference.full_shape, min_inside)
        if self._spectra.get("shape") != shape:
            # rfft2 with zero padding, pruned: the row transforms of the all-zero padding
            # rows are skipped (the raster is ~1/3 of the padded height)
            rows = sfft.rfft(self.raster[:, :4], n=shape[1], axis=-1, workers=1)
            # the column transforms in place, in the padded array: ``fft(..., n=)`` would
            # pad into one fresh array and write into another (~10 MB each for a 256 px
            # view's 57 rasters at 1/8, whose first touch in page faults cost as much as
            # the transform); each column's transform is the same, so are its values
            spec = np.zeros((*rows.shape[:2], shape[0], rows.shape[-1]), rows.dtype)
            spec[:, :, :rows.shape[2]] = rows
            _columns_fft(spec[..., :_low_columns(shape)])
            self._spectra = {"shape": shape, "spec": spec,
                             "done": np.zeros(len(spec), bool)}
        spec, done = self._spectra["spec"], self._spectra["done"]
        todo = np.arange(len(spec)) if rastered is None else np.unique(rastered)
        todo = todo[~done[todo]]
        low = _low_columns(shape)
        # runs of consecutive rasters: transformed in place, without a gather and a scatter
        starts = np.flatnonzero(np.diff(todo, prepend=-2) != 1)
        for start, stop in zip(todo[starts], np.r_[todo[starts[1:] - 1], todo[-1:]] + 1,
                               strict=True):
            _columns_fft(spec[start:stop, :, :, low:])
        done[todo] = True
        return shape, spec

    def low_spectra(self, reference: CreaseSearchReference, min_inside: float | None = 0.5):
        """:meth:`spectra`'s channel spectra cut to their :func:`_low_frequencies` (cached
        with them; the rest of the spectra need not be computed)."""
        shape, spec = self.spectra(reference, min_inside, rastered=np.zeros(0, np.intp))
        if self._low is None or self._low[0] is not spec:
            self._low = (spec, _low_frequencies(spec, shape))
        return self._low[1]

    def inside(self, shape: tuple[int, int], reference: CreaseSearchReference) -> np.ndarray:
        """At every shift (FFT index of a correlation padded to ``shape``), the query pixels
        that land on ``reference``'s footprint, per rastered rotation (n_rastered, h, w)
        (cached for one padded shape at a time)."""
        key = (reference.shape, reference.footprint)
        if self._per_shape.get("shape") != shape:
            self._per_shape = {"shape": shape}
        if key not in self._per_shape:
            self._per_shape[key] = self._footprint_counts(shape, *key)
        return self._per_shape[key]

    def searched(self, shape: tuple[int, int], reference: CreaseSearchReference,
                 min_inside: float) -> SearchedShifts:
        """The shifts searched against ``reference`` (cached with :meth:`inside`: a camera
        block in a study meets every landmark block at the same padded shape)."""
        key = (reference.shape, reference.footprint, min_inside)
        if self._per_shape.get("shape") != shape:
            self._per_shape = {"shape": shape}
        if key not in self._per_shape:
            # numpy compares float32 counts with a float threshold cast to float32
            threshold = np.float32(min_inside * self.n)
            if _kernels.HAVE_NUMBA:
                # the mask straight from the prefix sums: the counts themselves (n_rastered
                # padded planes of float32) are not needed
                mask = _kernels.box_mask(self._prefix_sums, *self._footprint_ranges(
                    shape, reference.shape, reference.footprint), threshold)
            else:
                mask = self.inside(shape, reference) >= threshold
            self._per_shape[key] = SearchedShifts.of(mask)
        return self._per_shape[key]

    @functools.cached_property
    def _prefix_sums(self) -> np.ndarray:
        """(n_rastered, h + 1, w + 1) 2-D prefix sums of the count rasters, a zero row and
        column first: one table serves the footprints of every reference turn and padded
        shape (a non-square region's four turns have four footprints)."""
        counts = self.raster[:, 4]
        cum = np.zeros((len(counts), self.shape[0] + 1, self.shape[1] + 1), np.float32)
        np.cumsum(np.cumsum(counts, axis=1), axis=2, out=cum[:, 1:, 1:])
        return cum

    def _footprint_ranges(self, shape: tuple[int, int], reference_shape: tuple[int, int],
                          footprint: tuple[int, int, int, int]):
        """Per FFT row and column index of a correlation padded to ``shape``, the query rows
        ``[row_lo, row_hi)`` and columns ``[col_lo, col_hi)`` that its shift puts on the
        reference's footprint."""
        hb, wb = reference_shape
        r0, r1, c0, c1 = footprint
        ha, wa = self.shape

        def ranges(n_pad, n_ref, n_query, start, stop):
            # signed shift d at FFT index i (d = i - n_pad past the reference), and the
            # query rows/cols [lo, hi) that land inside [start, stop) after it
            i = np.arange(n_pad)
            d = np.where(i <= n_ref - 1, i, i - n_pad)
            lo = np.clip(start - d, 0, n_query)
            return lo, np.maximum(np.clip(stop - d, 0, n_query), lo)

        return (*ranges(shape[0], hb, ha, r0, r1), *ranges(shape[1], wb, wa, c0, c1))

    def _footprint_counts(self, shape: tuple[int, int], reference_shape: tuple[int, int],
                          footprint: tuple[int, int, int, int]) -> np.ndarray:
        """:meth:`inside`: box sums of the count raster (exact; cheaper than its FFT). The
        search itself needs only the shifts they keep (:meth:`searched`)."""
        ha, wa = self.shape
        w_pad = shape[1]
        counts = self.raster[:, 4]
        n_rot = len(counts)
        row_lo, row_hi, col_lo, col_hi = self._footprint_ranges(shape, reference_shape,
                                                                footprint)
        cum = np.zeros((n_rot, ha, wa + 1), np.float32)
        np.cumsum(counts, axis=2, out=cum[:, :, 1:])
        cols = cum[:, :, col_hi] - cum[:, :, col_lo]                 # (n_rot, ha, w_pad)
        cum = np.zeros((n_rot, ha + 1, w_pad), np.float32)
        np.cumsum(cols, axis=1, out=cum[:, 1:])
        return cum[:, row_hi] - cum[:, row_lo]                         # (n_rot, h_pad, w_pad)


def _order_margin(histogram: np.ndarray, n: int, m: int) -> int:
    """``max(x_(n-m), x_max - x_(m-1))`` over the rows of ``histogram`` (n_rot, k): counts
    of ``n`` pixels per coordinate, ``x_(i)`` the i-th smallest coordinate (0-based)
    (:meth:`CreaseSearchQuery._alias_margins`)."""
    cum = np.cumsum(histogram, axis=1)
    # x_(i): the first coordinate whose cumulative count exceeds i
    low, high = np.argmax(cum > m - 1, axis=1), np.argmax(cum > n - m, axis=1)
    x_max = histogram.shape[1] - 1 - np.argmax(histogram[:, ::-1] > 0, axis=1)
    return int(np.maximum(high, x_max - low).max())


def _raster_extent(z: np.ndarray, c: np.ndarray, resolution: float):
    """Origins ``(col0, row0)`` per transform ``c`` and the shape over all of them of the
    rasters of pixels ``z`` (math frame) mapped by ``c`` at ``resolution``, rounded.

    Rounding is monotonic and a linear map's extremes over the pixels are at the vertices of
    their convex hull: those alone are mapped. Where an extreme is within rounding of a
    half pixel, a pixel on a hull edge (mathematically as far out) could round the other
    way: those transforms are redone on the pixels first or last in their row or column,
    which hold every pixel on the hull's boundary.
    """
    if len(z) == 0:
        return np.zeros(len(c)), np.zeros(len(c)), (1, 1)
    lo, hi = _rounded_extremes(c[:, None] * (_hull(z)[None, :] * resolution))
    frac = np.abs(np.concatenate([lo, hi], axis=1))
    tie = (np.abs(frac - np.floor(frac) - 0.5) < 1e-6).any(axis=1)
    if tie.any():
        lo[tie], hi[tie] = _rounded_extremes(c[tie, None] * (_outline(z)[None, :]
                                                               * resolution))
    lo, hi = np.rint(lo), np.rint(hi)
    # columns: the real part; rows: minus the imaginary part
    col0, row0 = lo[:, 0], lo[:, 1]
    shape = (int((hi[:, 1] - row0).max()) + 1, int((hi[:, 0] - col0).max()) + 1)
    return col0, row0, shape


def _rounded_extremes(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``q`` (mapped points, complex), the smallest and largest column
    (``rint(real)``) and row (``rint(-imag)``) as (n, 2) arrays, before the rounding."""
    cols, rows = q.real, -q.imag
    return (np.stack([cols.min(axis=1), rows.min(axis=1)], axis=1),
            np.stack([cols.max(axis=1), rows.max(axis=1)], axis=1))


def _hull(z: np.ndarray) -> np.ndarray:
    """The vertices of the convex hull of points ``z`` (math frame): all of them when few."""
    if len(z) < 64:
        return z
    xy = np.column_stack([z.real, -z.imag]).astype(np.float32)
    return z[cv2.convexHull(xy, returnPoints=False)[:, 0]]


def _outline(z: np.ndarray) -> np.ndarray:
    """The points of ``z`` (math frame) first or last in their row or their column: every
    point on the boundary of their convex hull is (the one beyond it along its row or column
    would be outside), collinear ones included, so a linear map's extremes over them are
    those over all of ``z`` (computed the same way: a rounding tie breaks the same way)."""
    if len(z) < 64:
        return z
    keep = np.zeros(len(z), bool)
    for major, minor in ((z.imag, z.real), (z.real, z.imag)):
        order = np.lexsort((minor, major))
        line = major[order]
        first = np.r_[True, line[1:] != line[:-1]]
        keep[order[first | np.r_[first[1:], True]]] = True
    return z[keep]


@dataclass(frozen=True)
class SearchedShifts:
    """The shifts a search keeps, per rastered rotation: those with at least ``min_inside``
    of the query's pixels over the reference's footprint."""

    mask: np.ndarray    # (n_rastered, h, w) bool
    half: np.ndarray    # float32 0 / 1 at every other row and column (:func:`_half_shape`):
    #                     it masks every plane of the shortlist (a bool would be cast each time)
    count: int          # searched shifts over all rastered rotations

    @classmethod
    def of(cls, mask: np.ndarray) -> SearchedShifts:
        """From the (n_rastered, h, w) mask of the searched shifts."""
        h, w = mask.shape[1:]
        h2, w2 = _half_shape((h, w))
        half = mask[:, np.arange(h2) * h // h2][:, :, np.arange(w2) * w // w2]
        return cls(mask, half.astype(np.float32), int(np.count_nonzero(mask)))


def _correlations(query_ch: np.ndarray, ref_ch: np.ndarray, shape: tuple[int, int],
                  planes: np.ndarray) -> np.ndarray:
    """Direction-consistent hits (len(planes), h, w) of the query's channel spectra
    ``query_ch`` (n_rot, 4, ...) over the references' ``ref_ch`` (n_ref, 4, ...) at every
    shift (circular, ``shape`` padded), for each plane ``p = reference * n_rot + rotation``
    of ``planes``."""
    if _kernels.HAVE_NUMBA:
        product = _kernels.channel_cross_spectra(np.ascontiguousarray(query_ch),
                                                 np.ascontiguousarray(ref_ch), planes)
    else:
        ref, rot = np.divmod(planes, len(query_ch))
        product = np.conj(query_ch[rot, 0]) * ref_ch[ref, 0]
        for k in range(1, 4):
            product += np.conj(query_ch[rot, k]) * ref_ch[ref, k]
    return sfft.irfft2(product, s=shape, workers=1).reshape(-1, *shape)


def _half_shape(shape: tuple[int, int]) -> tuple[int, int]:
    return -(-shape[0] // 2), -(-shape[1] // 2)


def _columns_fft(spec: np.ndarray) -> None:
    """FFT of ``spec`` (a view) along its rows, in place."""
    out = sfft.fft(spec, axis=-2, workers=1, overwrite_x=True)
    if not np.shares_memory(out, spec):   # scipy may not have written into the view
        spec[...] = out


def _low_columns(shape: tuple[int, int]) -> int:
    """The ``rfft2`` columns (of spectra of ``shape``) that :func:`_low_frequencies` keeps."""
    return _half_shape(shape)[1] // 2 + 1


def _low_frequencies(spectra: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The lowest frequencies of ``rfft2`` spectra of ``shape``: the spectra of the same
    signals low-passed and sampled at every other row and column (``_half_shape``)."""
    h2, w2 = _half_shape(shape)
    rows = np.r_[0:(h2 + 1) // 2, shape[0] - h2 // 2:shape[0]]
    return np.ascontiguousarray(spectra[..., rows, :_low_columns(shape)])


def _shortlist(query_low: np.ndarray, ref_low: np.ndarray, shape: tuple[int, int],
               searched: list[SearchedShifts], n_keep: int) -> np.ndarray:
    """The ``n_keep`` planes (see :func:`_correlations`) with the most hits at half the
    resolution, ascending: from the spectra's :func:`_low_frequencies` (a quarter of the
    product and of the inverse FFT), over the searched shifts (per reference) at every
    other row and column."""
    h2, w2 = _half_shape(shape)
    n_planes = len(ref_low) * len(query_low)
    hits = _correlations(query_low, ref_low, (h2, w2), np.arange(n_planes))
    hits = hits.reshape(len(searched), -1, h2, w2)
    for turn, s in enumerate(searched):
        hits[turn] *= s.half
    best = hits.reshape(n_planes, -1).max(axis=1)
    return np.sort(np.argsort(-best, kind="stable")[:n_keep])


def _largest_positive(values: np.ndarray, n: int) -> np.ndarray:
    """Flat indices of the ``n`` largest positive ``values``, largest first (ties by index).

    A selection over every value (``argpartition`` of the ~1e5-1e6 hits of a view search's
    strongest rotations) cost ~10 % of the search; the ``n``-th largest of every 8th value,
    of those positive, bounds it from below instead (those ``n`` are in the array too), and
    only the ~8 n values above the bound are sorted.
    """
    v = values.ravel()
    bound = 0.0
    sample = v[::8]
    # the positive ones: the shifts not searched are zeros, a selection slows on ties
    sample = sample[sample > 0]
    if len(sample) > 2 * n:
        bound = float(np.partition(sample, len(sample) - n)[len(sample) - n])
    # ``>=``: the n-th largest may equal the bound
    candidates = np.flatnonzero(v >= bound) if bound > 0 else np.flatnonzero(v > 0)
    if len(candidates) > n:
        # the n largest, ties at the n-th by index, before sorting only those
        values = v[candidates]
        nth = np.partition(values, len(values) - n)[len(values) - n]
        above = candidates[values > nth]
        candidates = np.concatenate([above, candidates[values == nth][:n - len(above)]])
    return candidates[np.lexsort((candidates, -v[candidates]))[:n]]


@dataclass(frozen=True)
class CreaseSearchResult:
    """Proposals of :func:`search_transforms` and the size of the space they came from."""

    proposals: list          # (c, t, hits): rotation factor, translation, weighted hits
    log10_transforms: float  # log10 of the distinguishable transforms searched


def search_transforms(query: CreaseSearchQuery, reference: CreaseSearchReference,
                      n_best: int = 3, min_inside: float = 0.5,
                      hit_radius: float = 1.5,
                      distinct_rotations: int | None = None,
                      shortlist: int = 16, n_out: int | None = None) -> CreaseSearchResult:
    """Transforms A -> B under which most of A's crease pixels fall on B's creases.

    Parameters
    ----------
    query : CreaseSearchQuery
        Query creases (A) at the rotations to search.
    reference : CreaseSearchReference
        Reference creases (B), at the query's resolution.
    n_best : int
        Proposals returned, strongest first, at least two rotation steps apart or mapping
        the query's centre at least 4 px apart.
    min_inside : float
        Translations that keep less than this fraction of A's crease pixels over B are not
        searched.
    hit_radius : float
        Position tolerance (px) of a crease hit: translations closer than this are not
        distinguishable, which sets the count of transforms searched.
    distinct_rotations : int, optional
        Rotations distinguishable at ``hit_radius`` when the query samples fewer (a coarse
        search whose proposals are refined): the count of transforms is scaled up to them.
    shortlist : int
        With more than ``shortlist * n_best`` rotations, only that many are correlated at
        full resolution: those with the most hits at half the resolution (a quarter of the
        work each). The proposals come from the strongest ``4 * n_best`` of them; in the
        localisations of gredos 25 m blocks, the planes of the proposals ranked at most 18th
        of 64-76 at half the resolution, the full-resolution best at most 12th. Real views
        blur more at half the resolution: a 256 px view's true plane (603 hits in full,
        twice any other) ranked 49th of 228 there, and 8 per proposal lost 7 of ~930 views
        over four draws of the real-imagery study that 16 keep (a correlation of every
        plane keeps one more, for ~12 % more time per view). 0 correlates every rotation
        in full.
    n_out : int, optional
        Proposals returned when more than ``n_best`` (a coarse level's, for
        :func:`local_peaks` to rank): from the same rotations as ``n_best``'s.

    Returns
    -------
    CreaseSearchResult
        Proposals (rotation factor, translation in the math frame, direction-consistent
        hits), strongest first, and ``log10`` of the rotations times the translations (in
        cells of ``pi hit_radius^2``) searched: a score of the best of them must pay for it.
    """
    if query.resolution != reference.resolution:
        raise ValueError("query and reference must be built at the same resolution")
    n_rot = len(query.c)
    if query.n == 0 or n_rot == 0:
        return CreaseSearchResult([], 0.0)
    if query.quarter:
        # quarter turns need a square reference: a padded one has the same hits
        reference = reference.squared()
    scale = query.resolution
    shape = query.padded_shape(reference.full_shape, min_inside)
    # the query's quarter turns: its first quarter against the reference turned back
    turns = range(4) if query.quarter else range(1)
    ref_ch, ref_low = reference.turned_spectra(shape, len(turns))
    # circular correlation: the shift s of A over B is at index s mod shape (the padding
    # leaves every searched shift free of aliases, see CreaseSearchQuery.padded_shape);
    # the shifts searched, per reference turn (the same for the turns of a square footprint)
    searched = [query.searched(shape, reference.turned(j), min_inside) for j in turns]
    planes = np.arange(n_rot)      # rotation r = turn * n_rastered + rastered rotation
    if shortlist and n_rot > shortlist * n_best:
        planes = _shortlist(query.low_spectra(reference, min_inside), ref_low, shape,
                            searched, shortlist * n_best)
    # the query's full spectra: of the shortlisted rasters only
    _, query_ch = query.spectra(reference, min_inside, rastered=planes % query.n_rastered)
    hits = _correlations(query_ch, ref_ch, shape, planes)
    hits *= np.stack([searched[turn].mask[r]
                      for turn, r in zip(*np.divmod(planes, query.n_rastered), strict=True)])
    cells = (sum(s.count for s in searched) / (scale * scale)
             / (math.pi * hit_radius * hit_radius))
    if distinct_rotations:
        cells *= max(distinct_rotations / n_rot, 1.0)
    log10_transforms = math.log10(max(float(cells), 1.0))
    # candidates from the strongest rotations only (a proposal's neighbours are skipped)
    flat = hits.reshape(len(planes), -1)
    strongest = np.argsort(-flat.max(axis=1), kind="stable")[:4 * n_best]
    rots, sub = planes[strongest], flat[strongest]
    step = 2.0 * np.ptp(query.rotations) / max(len(query.rotations) - 1, 1)
    hb, wb = reference.shape
    n_out = max(n_out or n_best, n_best)
    idx = _largest_positive(sub, 50 * n_out)
    i, k = np.divmod(idx, sub.shape[1])
    r = rots[i]
    turn, q = np.divmod(r, query.n_rastered)
    dy, dx = np.divmod(k, shape[1])
    dy = np.where(dy > hb - 1, dy - shape[0], dy)
    dx = np.where(dx > wb - 1, dx - shape[1], dx)
    c = query.c[r]
    # A pixel (ci, ri) of rotation q lands on pixel (ci + dx, ri + dy) of B turned ``turn``
    # times clockwise, in search pixels; turned back: a turn more of A
    t = (dx - query.col0[q]) - 1j * (dy - query.row0[q])
    offsets = np.array([reference.turn_offset(j) for j in range(4)])
    t = np.array(_QUARTER_TURNS)[turn] * (t - offsets[turn]) / scale
    keep = _distinct_peaks(c, t, query.centre, step, n_out)
    out = [(complex(c[j]), complex(t[j]), float(sub[i[j], k[j]])) for j in keep]
    return CreaseSearchResult(out, log10_transforms)


def _distinct_peaks(c: np.ndarray, t: np.ndarray, centre: complex, step: float, n: int) -> list:
    """Indices of the first ``n`` transforms ``(c, t)`` none of which is the same as one
    before it: as close in rotation (``step``), and mapping ``centre`` within 4 px (the
    query's origin, a corner, moves 4 px per rotation step at the query's reach)."""
    angle = np.angle(c)
    placed = c * centre + t    # (c - c') centre + t - t' is the difference of these
    alive = np.ones(len(c), bool)
    keep = []
    for j in range(len(c)):
        if not alive[j]:
            continue
        keep.append(j)
        if len(keep) == n:
            break
        near = np.flatnonzero(np.abs(placed[j + 1:] - placed[j]) <= 4.0) + (j + 1)
        turn = np.abs(np.remainder(angle[near] - angle[j] + math.pi, 2 * math.pi) - math.pi)
        alive[near[turn <= step]] = False
    return keep


def local_peaks(samples: CreaseSamples, reference: CreaseSearchReference, proposals,
                rotation_step: float, scale_step: float = 0.0, steps: int = 1,
                span: int = 3) -> list[tuple[complex, complex, float]]:
    """The next level of the search's pyramid: the best transform near each proposal of a
    coarser level, on a finer ``reference``.

    A coarse level blurs each peak over a cell of its resolution and rotation step (4-12 px),
    too coarsely to rank its peaks: in the 3x regions of real 128 px views the right place
    ranked 4th to 42nd among the coarse proposals, and first once each proposal was searched
    again at half the pixel resolution within its cell. Around each proposal: rotations and
    scales within ``steps`` steps of ``rotation_step`` and ``scale_step`` (turned about the
    query's centroid, which the coarse shift placed), each at the shifts within ``span`` of
    the reference's pixels.

    Parameters
    ----------
    samples : CreaseSamples
        Query creases (A), image pixels.
    reference : CreaseSearchReference
        Reference creases (B) at the finer level's resolution.
    proposals : sequence of (c, t, hits)
        The coarser level's proposals (:func:`search_transforms`).
    rotation_step, scale_step : float
        The finer level's steps (rad; relative scale): 0 searches none.

    Returns
    -------
    list of (c, t, hits)
        Per proposal, in their order, the best transform near it and its direction-consistent
        hits on ``reference``.
    """
    if not proposals or len(samples) == 0:
        return [(c, t, 0.0) for c, t, _ in proposals]
    res = reference.resolution
    centre = complex(samples.z.mean())
    k = np.arange(-steps, steps + 1)
    scales = 1.0 + scale_step * k if scale_step > 0 else np.ones(1)
    turns = np.exp(1j * rotation_step * k) if rotation_step > 0 else np.ones(1)
    near = (scales[:, None] * turns[None, :]).ravel()
    c0 = np.array([p[0] for p in proposals], complex)
    t0 = np.array([p[1] for p in proposals], complex)
    c = (c0[:, None] * near[None, :]).ravel()
    # turned about the centroid: the coarse shift placed it
    t = (t0[:, None] + (c0[:, None] - c.reshape(len(c0), -1)) * centre).ravel()
    hits, dx, dy = _local_shift_hits(reference, samples, c, t * res, span)
    out = []
    for i, best in enumerate(np.argmax(hits.reshape(len(c0), -1), axis=1)):
        m = i * len(near) + best
        out.append((complex(c[m]), complex(t[m] + complex(dx[m], -dy[m]) / res),
                    float(hits[m])))
    return out


def _local_shift_hits(reference: CreaseSearchReference, samples: CreaseSamples,
                      c: np.ndarray, t: np.ndarray, span: int):
    """Per transform ``(c, t)`` (``t`` in search pixels), the most direction-consistent hits
    of ``samples`` on ``reference`` at the shifts within ``span`` search pixels (the first
    of equals, rows then columns), and that shift (dx, dy) in search pixels (columns,
    rows)."""
    padded, pad = reference.padded(span)
    z = samples.z * reference.resolution
    if _kernels.HAVE_NUMBA:
        return _kernels.local_shift_hits(padded, pad, z, samples.direction.astype(np.float64),
                                         c, t, span)
    h, w = reference.shape
    shifts = np.arange(-span, span + 1)
    hits = np.empty(len(c))
    best_dx, best_dy = np.empty(len(c), np.intp), np.empty(len(c), np.intp)
    for m in range(len(c)):
        q = c[m] * z + t[m]
        col, row = np.rint(q.real).astype(np.intp), np.rint(-q.imag).astype(np.intp)
        weights = _channel_weights(np.mod(samples.direction + np.angle(c[m]), np.pi))
        # a sample whose shifts would leave the padding counts none (as the kernel)
        weights[:, (col < span - pad) | (col > w - 1 + pad - span) | (row < span - pad)
                | (row > h - 1 + pad - span)] = 0.0
        col, row = np.clip(col, span - pad, w - 1 + pad - span), \
            np.clip(row, span - pad, h - 1 + pad - span)
        acc = np.array([[sum(float(weights[k] @ padded[k, row + dy + pad, col + dx + pad])
                             for k in range(4)) for dx in shifts] for dy in shifts])
        best = int(np.argmax(acc))
        hits[m] = acc.flat[best]
        best_dy[m], best_dx[m] = divmod(best, 2 * span + 1)
    return hits, best_dx - span, best_dy - span
