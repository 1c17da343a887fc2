"""Track mosaics: a low camera's recent ground frames composed into one larger view.

A view's evidence grows with the drainage it holds, and a frame from low above the terrain
holds few DEM cells: from 900 m a 70 deg camera sees ~42 x 31 cells of a 30 m DEM, where real
views of fewer than ~64 cells a side lose their matches for want of creases (RESULTS, issue
21). Over the last tens of seconds the navigation estimate's error changes little (dead
reckoning drifts metres, not cells), so the ground frames projected with it over that time
lie where one frame of the strip the aircraft flew would: composed, they are one view of
several times a frame's area, localised as one frame would be. The registration then moves
the newest frame's camera (its pose is the mosaic's), as for a single frame.

What moves a past frame against the newest is the filter's own correction between the two:
a fix steps the estimate by metres while its velocity stays smooth. :class:`FilterSteps`
integrates the estimate's velocity and keeps what its position did beyond that; each past
frame is moved by the steps taken since it was projected, into the estimate the newest
frame was projected with. What is left is the velocity's error times each frame's age: a fix
from the mosaic measures the position less the estimate's velocity error times the mosaic's
mean age (its ``lag``, which the ekf models).

Frames are laid newest on top, each faded out over its last pixels to its border, so that
the mosaic is as recent as its pixels allow (under the newest frame, the newest frame alone:
an average of the frames that saw a place would carry their older estimates' errors) and
exposure differences between frames leave no step for the crease detector to take for
terrain.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ..terrain.georef import GeoReference
from .ground_projection import GroundImage

# Pixels of a frame's border over which its weight in the blend rises from 0 to 1.
FEATHER_PX = 6.0
# A past frame that adds less than this share of its pixels to the mosaic is left out (10
# frames a second overlap by 99.5 %: one in ten is as good as all ten).
MIN_NEW_SHARE = 0.02


class FilterSteps:
    """The position steps of a navigation estimate that its velocity does not explain.

    Fed the estimate's samples in time order, it integrates their velocity (trapezoids)
    and accumulates the horizontal difference between that and the position: a fix's
    correction, an operator's re-seed. :meth:`at` is that sum at a stamp, so ``at(t1) -
    at(t0)`` is how far the filter moved its estimate between ``t0`` and ``t1``.

    Parameters
    ----------
    horizon : float
        History kept (s).
    max_gap : float
        A longer gap between samples (s) breaks the history: the velocity cannot be
        integrated across it, and stamps before it have no answer.

    Attributes
    ----------
    epoch : int
        Counts the breaks: sums of two epochs are not comparable (each starts at zero).
    """

    def __init__(self, horizon: float = 120.0, max_gap: float = 1.0):
        self.horizon = float(horizon)
        self.max_gap = float(max_gap)
        self._stamps: deque[float] = deque()
        self._sums: deque[np.ndarray] = deque()
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None
        self.epoch = 0

    def add(self, stamp: float, position, velocity) -> None:
        """One estimate: ``stamp`` (s), ENU ``position`` and ``velocity`` (m, m/s)."""
        p = np.asarray(position, float)[:2]
        v = np.asarray(velocity, float)[:2]
        if not (math.isfinite(stamp) and np.isfinite(p).all() and np.isfinite(v).all()):
            return
        last = self._last
        if last is not None and stamp <= last[0]:
            if stamp < last[0]:          # time went back (a bag loop): start again
                self._clear()
            else:
                return
        if last is None or stamp - last[0] > self.max_gap or not self._stamps:
            self._clear()
            total = np.zeros(2)
        else:
            t0, p0, v0 = last
            total = self._sums[-1] + (p - p0) - 0.5 * (v + v0) * (stamp - t0)
        self._last = (stamp, p, v)
        self._stamps.append(stamp)
        self._sums.append(total)
        while self._stamps[0] < stamp - self.horizon:
            self._stamps.popleft()
            self._sums.popleft()

    def at(self, stamp: float) -> np.ndarray | None:
        """The steps' sum (east, north, m) at ``stamp``, interpolated; None outside the
        unbroken history."""
        if not self._stamps or not self._stamps[0] <= stamp <= self._stamps[-1] + self.max_gap:
            return None
        i = bisect.bisect_right(self._stamps, stamp)
        if i >= len(self._stamps):
            return self._sums[-1].copy()
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        w = (stamp - t0) / (t1 - t0)
        return (1.0 - w) * self._sums[i - 1] + w * self._sums[i]

    def _clear(self) -> None:
        if self._stamps:
            self.epoch += 1
        self._stamps.clear()
        self._sums.clear()
        self._last = None


class Composed(NamedTuple):
    """What :meth:`TrackMosaic.compose` gives to match."""

    ground: GroundImage   # the frame itself, or the mosaic placed in its estimate
    frames: int           # frames in it
    lag: float            # mean age of its pixels behind the newest frame (s); 0 for one


@dataclass
class _Frame:
    ground: GroundImage
    stamp: float
    steps: np.ndarray        # FilterSteps.at(stamp) when it was projected
    epoch: int               # and FilterSteps.epoch
    observed: int            # its valid pixels


class TrackMosaic:
    """Composes the ground frames of the last ``max_age`` s while each is too small alone.

    Parameters
    ----------
    min_pixels : int
        A frame observing at least this many ground pixels is matched alone (and the frames
        before it are forgotten); a smaller one gets the frames before it added, newest
        first, until the mosaic observes this many or ``max_age`` runs out. 0 turns
        mosaics off.
    max_age : float
        Oldest frame in a mosaic, behind the newest (s): the estimate's drift over it is
        the mosaic's distortion.
    max_side : int
        Largest side of a mosaic (px); older frames that would widen it further are left out.
    """

    def __init__(self, min_pixels: int, max_age: float = 30.0, max_side: int = 1024):
        self.min_pixels = int(min_pixels)
        self.max_age = float(max_age)
        self.max_side = int(max_side)
        self._frames: deque[_Frame] = deque()

    def __len__(self) -> int:
        return len(self._frames)

    def compose(self, ground: GroundImage, stamp: float, steps: np.ndarray | None,
                epoch: int = 0) -> Composed:
        """Add a projected frame and return what to match: the frame itself, or the mosaic
        of it and the frames before it, placed in its estimate (:class:`Composed`).

        ``steps`` is :meth:`FilterSteps.at` the frame's stamp (None: unknown, the frame is
        matched alone and starts a new mosaic), ``epoch`` :attr:`FilterSteps.epoch` (frames
        of another epoch are forgotten: their steps do not compare)."""
        observed = int(np.count_nonzero(ground.valid))
        if self.min_pixels <= 0 or observed >= self.min_pixels or steps is None:
            self._frames.clear()
            return Composed(ground, 1, 0.0)
        gsd = ground.georef.gsd
        if self._frames and (self._frames[-1].stamp >= stamp or
                             self._frames[-1].epoch != epoch or
                             not math.isclose(self._frames[-1].ground.georef.gsd, gsd)):
            self._frames.clear()     # a replay started again, the odometry broke, a new GSD
        while self._frames and self._frames[0].stamp < stamp - self.max_age:
            self._frames.popleft()
        self._frames.append(_Frame(ground, stamp, np.asarray(steps, float), epoch, observed))
        chosen = self._chosen()
        if len(chosen) == 1:
            return Composed(ground, 1, 0.0)
        mosaic, lag = self._blend(chosen)
        return Composed(mosaic, len(chosen), lag)

    def _chosen(self) -> list[tuple[_Frame, GeoReference]]:
        """Newest first, each with its georef moved into the newest frame's estimate, until
        their pixels (overlaps counted once, roughly: the union is measured at the end) reach
        ``min_pixels`` or the mosaic's side would pass ``max_side``."""
        newest = self._frames[-1]
        chosen, bounds, total = [], None, 0
        for frame in reversed(self._frames):
            de, dn = newest.steps - frame.steps
            g = frame.ground.georef
            moved = GeoReference(g.origin_east + de, g.origin_north + dn, g.gsd, g.width,
                                 g.height)
            west, east, south, north = moved.extent
            b = (west, east, south, north) if bounds is None else (
                min(bounds[0], west), max(bounds[1], east), min(bounds[2], south),
                max(bounds[3], north))
            if max(b[1] - b[0], b[3] - b[2]) / g.gsd > self.max_side:
                break
            # a frame adds the pixels it sees beyond the one after it (frames overlap most
            # with their neighbours along the track); one that adds almost none is left
            # out, so that a fast camera's mosaic costs what a slow one's does
            new = frame.observed if not chosen else _new_pixels(chosen[-1][1], moved,
                                                                frame.observed)
            if chosen and new < MIN_NEW_SHARE * frame.observed:
                continue
            bounds = b
            chosen.append((frame, moved))
            total += new
            if total >= self.min_pixels:
                break
        return chosen

    def _blend(self, chosen) -> tuple[GroundImage, float]:
        """The chosen frames resampled onto one grid (the newest frame's pixel lattice), laid
        newest on top, each faded out towards its border (front-to-back compositing); and
        the mean age of its pixels (each frame's age weighted by its share of the blend)."""
        newest = chosen[0][1]
        newest_stamp = chosen[0][0].stamp
        gsd = newest.gsd
        west = min(m.extent[0] for _, m in chosen)
        north = max(m.extent[3] for _, m in chosen)
        east = max(m.extent[1] for _, m in chosen)
        south = min(m.extent[2] for _, m in chosen)
        # on the newest frame's lattice: its pixels are copied, not resampled
        c0 = math.floor((west - newest.origin_east) / gsd + 1e-9)
        r0 = math.floor((newest.origin_north - north) / gsd + 1e-9)
        c1 = math.ceil((east - newest.origin_east) / gsd - 1e-9)
        r1 = math.ceil((newest.origin_north - south) / gsd - 1e-9)
        grid = GeoReference(newest.origin_east + c0 * gsd, newest.origin_north - r0 * gsd, gsd,
                            c1 - c0, r1 - r0)
        acc = np.zeros(grid.shape, np.float32)
        wsum = np.zeros(grid.shape, np.float32)
        free = np.ones(grid.shape, np.float32)   # what the newer frames left of each pixel
        share_age = 0.0
        for frame, moved in chosen:              # newest first: it lies on top
            weight = _feather(frame.ground.valid)
            # ground -> grid: a translation by the moved origin's offset in grid pixels
            dx = (moved.origin_east - grid.origin_east) / gsd
            dy = (grid.origin_north - moved.origin_north) / gsd
            shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
            weighted, weight = (cv2.warpAffine(a, shift, grid.shape[::-1],
                                               flags=cv2.INTER_LINEAR,
                                               borderMode=cv2.BORDER_CONSTANT)
                                for a in (frame.ground.image.astype(np.float32) * weight,
                                          weight))
            acc += free * weighted
            share = free * weight
            wsum += share
            share_age += float(share.sum()) * (newest_stamp - frame.stamp)
            free *= 1.0 - weight
        valid = wsum > 1e-3
        out = np.zeros(grid.shape, np.float32)
        np.divide(acc, wsum, out=out, where=valid)
        dtype = chosen[0][0].ground.image.dtype
        if dtype.kind in "ui":
            info = np.iinfo(dtype)
            out = np.clip(np.rint(out), info.min, info.max)
        lag = share_age / max(float(wsum.sum()), 1e-9)
        return GroundImage(out.astype(dtype), valid, grid), lag


def _feather(valid: np.ndarray) -> np.ndarray:
    """Blend weights: 0 off the frame, rising to 1 over ``FEATHER_PX`` from its border (the
    raster's edge too: the padding makes it a border)."""
    padded = cv2.copyMakeBorder(valid.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, 0)
    distance = cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1]
    return np.minimum(distance / FEATHER_PX, 1.0).astype(np.float32)


def _new_pixels(later: GeoReference, earlier: GeoReference, observed: int) -> int:
    """Roughly the pixels of a frame (``earlier``) that the frame after it does not cover:
    its observed count times the share of its raster outside the later one's."""
    w0, e0, s0, n0 = earlier.extent
    w1, e1, s1, n1 = later.extent
    overlap = max(0.0, min(e0, e1) - max(w0, w1)) * max(0.0, min(n0, n1) - max(s0, s1))
    area = (e0 - w0) * (n0 - s0)
    return round(observed * (1.0 - overlap / area)) if area > 0 else 0
