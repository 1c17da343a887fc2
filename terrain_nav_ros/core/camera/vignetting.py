"""A lens's vignetting, learnt from the same ground seen at different places in the lens.

A lens passes less light towards the edge of its field (the cos^4 law, the aperture's
shadow), so a frame darkens outwards from its principal point unless the camera flat-fields
it. That slow radial slope moves every valley's darkest line outwards by its gradient over
the valley's curvature, so the creases of a frame lie farther from its centre than those of
the landmark render: the view's measured scale comes out small, and with it the height that
the fix takes from it. The simulator's lens (25 % darker in the corners) gave -0.39 % in
scale, -13 m at 3.3 km, in every fix of the short bag.

The terrain itself cannot be assumed no brighter at a frame's centre than at its edge, even
over many frames: a flight along a ridge, a river or a field boundary keeps that line in the
middle of every frame (over PA's ridges from 900 m, a mean radial profile put the corner at
0.56-0.69 where the lens had 0.75). So the falloff is learnt as in panorama calibration
(Goldman and Chen's vignette and exposure calibration): a ground point seen in two overlapping
frames, at radii ``r1`` and ``r2`` from the principal point, has the log brightness ratio
``f(r1) - f(r2)`` plus the two frames' exposure difference, whatever the ground is. Each
projected frame is put beside the frame before it on their common ground raster (the offset
checked by phase correlation, which absorbs a filter update between them), and
``f(r) = a1 r^2 + a2 r^4`` (``r`` over the half diagonal) is fitted by robust least squares
over the pixels both see, the exposure difference taken out per pair. :class:`Vignetting`
divides the fit out of each raw frame once :data:`MIN_PAIRS` pairs have taught it. A camera
that flat-fields already gives a flat fit and frames unchanged.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["Vignetting", "MIN_PAIRS"]

# Frame pairs learnt from before the falloff is divided out
MIN_PAIRS = 5
# The fit's memory in pairs (a lens's falloff changes with its aperture only)
MEMORY_PAIRS = 200
# Pixels near the ends of the sensor's range say nothing of the falloff (saturated cloud,
# snow; black shadow)
_LEVELS = (0.02, 0.98)
# A pair sharing fewer ground pixels than this teaches nothing worth its noise (a frame
# from 900 m sees ~1300 cells of 30 m)
_MIN_OVERLAP = 500
# Pixels of a pair used, at most (a stride over the overlap; the fit needs no more)
_MAX_SAMPLES = 20000
# A pair whose ground the phase correlation puts farther apart than this (px) is not
# trusted to be registered (a jump of the estimate, a frame of another place)
_MAX_SHIFT_PX = 3.0
# OpenCV's depth for the integer frame types (float frames are multiplied in numpy)
_CV_DEPTH = {"u1": cv2.CV_8U, "u2": cv2.CV_16U, "i1": cv2.CV_8S, "i2": cv2.CV_16S}
# A fitted falloff darker than this at the frame's corner is not applied (no survey lens
# is; a wrong fit would wreck every frame)
_MAX_CORNER_FALLOFF = 0.5


class Vignetting:
    """The running estimate of a camera's radial falloff, and frames corrected by it.

    Parameters
    ----------
    enabled : bool
        False leaves every frame as it is and learns nothing.
    """

    def __init__(self, enabled: bool = True):
        self.enabled = bool(enabled)
        self.pairs = 0
        self._normal = np.zeros((2, 2))    # decayed normal equations of (a1, a2)
        self._rhs = np.zeros(2)
        self._applied = (0.0, 0.0)         # the fit divided out of the last frame corrected
        self._full = 255.0                 # and its dtype's full scale
        self._lens = None                  # and its (cx, cy, width, height)
        self._last = None                  # (log raw level, usable, radius^2, georef)
        self._grid = None                  # (key, radius^2 per raw pixel)
        self._gain_cache = None            # (radius^2 grid, shape, fit, gain)

    def correct(self, image: np.ndarray, centre=None) -> np.ndarray:
        """Return ``image`` with the falloff learnt so far divided out.

        Parameters
        ----------
        image : (H, W) or (H, W, C) array
            A raw camera frame (uint8, uint16 or float), before undistortion.
        centre : (cx, cy), optional
            The principal point (px); default the image's centre.

        Returns
        -------
        ndarray
            Of ``image``'s shape and dtype (``image`` itself while the falloff is not known
            or is flat). Pass the frame's ground image to :meth:`learn` before the next
            frame is corrected.
        """
        self._applied = (0.0, 0.0)
        if not self.enabled or image.ndim not in (2, 3) or min(image.shape[:2]) < 8:
            return image
        self._full = float(np.iinfo(image.dtype).max) \
            if np.issubdtype(image.dtype, np.integer) else 1.0
        h, w = image.shape[:2]
        self._lens = (*(centre if centre is not None else (0.5 * (w - 1), 0.5 * (h - 1))),
                      w, h)
        fit = self.applicable()
        if fit is None:
            return image
        self._applied, gain = self._gain(image.shape, centre, fit)
        depth = _CV_DEPTH.get(image.dtype.str[1:])
        if depth is None:
            out = image * gain   # float32 frames stay float32; wider integers go to float64
            if np.issubdtype(image.dtype, np.integer):   # rounded and saturated, as OpenCV's
                info = np.iinfo(image.dtype)
                out = np.clip(np.rint(out), info.min, info.max)
            return out.astype(image.dtype, copy=False)
        return cv2.multiply(image, gain, dtype=depth)   # one pass, rounded and saturated

    def _gain(self, shape, centre, fit):
        """The fit divided out and, per raw pixel (and channel), the factor that undoes it:
        kept while the fit moves less than a thousandth (it is refitted after every pair)."""
        rho = self.radius2(shape[:2], centre)
        cached = self._gain_cache
        if cached is None or cached[0] is not rho or cached[1] != shape or \
                max(abs(cached[2][0] - fit[0]), abs(cached[2][1] - fit[1])) > 1e-3:
            gain = np.exp(-(fit[0] * rho + fit[1] * rho * rho)).astype(np.float32)
            if len(shape) == 3:
                gain = np.repeat(gain[..., None], shape[2], axis=2)
            self._gain_cache = cached = (rho, shape, fit, gain)
        return cached[2], cached[3]

    def learn(self, ground) -> None:
        """Learn from the ground image of the frame :meth:`correct` returned last.

        Parameters
        ----------
        ground : GroundImage or None
            Its ``frame_pixels`` say where in the lens each ground pixel was seen (None, or
            none: nothing is learnt, and the next frame has no pair).
        """
        if not self.enabled or ground is None or ground.image is None or \
                ground.frame_pixels is None or self._lens is None:
            self._last = None
            return
        level = np.asarray(ground.image, np.float32)
        usable = ground.valid & (level > _LEVELS[0] * self._full) & \
            (level < _LEVELS[1] * self._full)
        a1, a2 = self._applied
        rho = frame_radius2(*ground.frame_pixels, *self._lens)
        # the raw frame's log level: what was divided out is put back
        log_raw = np.log(np.maximum(level, 1e-6)) + a1 * rho + a2 * rho * rho
        current = (log_raw.astype(np.float32), usable, rho, ground.georef)
        if self._last is not None:
            self._add_pair(self._last, current)
        self._last = current

    def falloff(self) -> tuple[float, float] | None:
        """The fitted ``(a1, a2)``: the falloff is ``exp(a1 r^2 + a2 r^4)``; None before
        any pair."""
        if self.pairs == 0 or abs(np.linalg.det(self._normal)) < 1e-12 * max(
                np.trace(self._normal) ** 2, 1e-300):
            return None
        a1, a2 = np.linalg.solve(self._normal, self._rhs)
        return float(a1), float(a2)

    def applicable(self) -> tuple[float, float] | None:
        """The fit that :meth:`correct` divides out: None before :data:`MIN_PAIRS` pairs,
        or when its corner is no lens's."""
        fit = self.falloff() if self.pairs >= MIN_PAIRS else None
        if fit is None or not _MAX_CORNER_FALLOFF <= math.exp(sum(fit)) <= \
                1.0 / _MAX_CORNER_FALLOFF:
            return None
        return fit

    def corner(self) -> float:
        """The brightness the fitted falloff leaves in a frame's corner (1: none; NaN
        before any pair), for the diagnostics."""
        fit = self.falloff()
        return float(math.exp(sum(fit))) if fit else float("nan")

    def radius2(self, shape, centre=None) -> np.ndarray:
        """Per raw pixel, its squared distance from the principal point over the half
        diagonal's (0 at the principal point, ~1 in a corner)."""
        h, w = shape
        cx, cy = centre if centre is not None else (0.5 * (w - 1), 0.5 * (h - 1))
        key = (tuple(shape), round(float(cx), 3), round(float(cy), 3))
        if self._grid is None or self._grid[0] != key:
            self._grid = (key, frame_radius2(*np.meshgrid(np.arange(w, dtype=np.float32),
                                                          np.arange(h, dtype=np.float32)),
                                             cx, cy, w, h))
        return self._grid[1]

    def _add_pair(self, older, newer) -> None:
        """Add the normal equations of one pair of overlapping ground images."""
        overlap = _overlap(older[3], newer[3])
        if overlap is None:
            return
        a, b = ([x[s] for x in frame[:3]] for frame, s in zip((older, newer), overlap,
                                                               strict=True))
        both = a[1] & b[1]
        if np.count_nonzero(both) < _MIN_OVERLAP:
            return
        shift = _registration(a[0], b[0], both)
        if shift is None:
            return
        if shift != (0.0, 0.0):   # the newer frame's estimate moved: bring it onto the older
            b = _shifted(b, shift)
            both = a[1] & b[1]
        step = max(1, math.isqrt(int(both.size // _MAX_SAMPLES)))   # (a stride: fewer samples)
        both = both[::step, ::step]
        ra, rb = a[2][::step, ::step][both], b[2][::step, ::step][both]
        if ra.size < _MIN_OVERLAP // step ** 2:
            return
        d = (a[0][::step, ::step][both] - b[0][::step, ::step][both]).astype(float)
        x1, x2 = (ra - rb).astype(float), (ra * ra - rb * rb).astype(float)
        for v in (d, x1, x2):
            v -= v.mean()             # (of d: the two frames' exposure difference)
        keep = slice(None)
        for _ in range(2):            # robust: refit without the pixels far off the fit
            normal, rhs = _normal_equations(x1[keep], x2[keep], d[keep])
            coef = np.linalg.lstsq(normal, rhs, rcond=None)[0]
            residual = d - coef[0] * x1 - coef[1] * x2
            sigma = 1.4826 * np.median(np.abs(residual[keep])) + 1e-6
            keep = np.abs(residual) < 3.0 * sigma
        if np.count_nonzero(keep) < ra.size // 2:
            return
        normal, rhs = _normal_equations(x1[keep], x2[keep], d[keep])
        decay = 1.0 - 1.0 / min(self.pairs + 1, MEMORY_PAIRS)
        self._normal = decay * self._normal + normal / sigma ** 2
        self._rhs = decay * self._rhs + rhs / sigma ** 2
        self.pairs += 1


def _normal_equations(x1, x2, d):
    """``X^T X`` and ``X^T d`` of the design ``X = [x1 x2]`` (1-D dot products: fast)."""
    x12 = float(np.dot(x1, x2))
    return (np.array([[np.dot(x1, x1), x12], [x12, np.dot(x2, x2)]]),
            np.array([np.dot(x1, d), np.dot(x2, d)]))


def frame_radius2(u, v, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """Squared distance of raw frame pixels ``(u, v)`` from the principal point over the
    half diagonal's (float32): where in the lens a pixel was seen."""
    with np.errstate(over="ignore", invalid="ignore"):   # (rays that miss: inf, NaN)
        return (((np.asarray(u, np.float32) - cx) ** 2 + (np.asarray(v, np.float32) - cy) ** 2)
                / np.float32(0.25 * (width * width + height * height))).astype(np.float32)


def _overlap(g1, g2):
    """The slices of two north-up rasters on one grid that cover their common ground."""
    if not math.isclose(g1.gsd, g2.gsd):
        return None
    dc = round((g2.origin_east - g1.origin_east) / g1.gsd)    # g2's column 0 in g1
    dr = round((g1.origin_north - g2.origin_north) / g1.gsd)  # g2's row 0 in g1
    c0, c1 = max(0, dc), min(g1.width, dc + g2.width)
    r0, r1 = max(0, dr), min(g1.height, dr + g2.height)
    if c1 - c0 < 12 or r1 - r0 < 12:
        return None
    return (np.s_[r0:r1, c0:c1], np.s_[r0 - dr:r1 - dr, c0 - dc:c1 - dc])


def _registration(log_a, log_b, both):
    """The shift (dx, dy) px that brings ``log_b`` onto ``log_a`` by phase correlation,
    (0, 0) when under half a pixel; None when it is far or the correlation is weak."""
    fill_a = np.where(both, log_a, float(log_a[both].mean())).astype(np.float32)
    fill_b = np.where(both, log_b, float(log_b[both].mean())).astype(np.float32)
    window = cv2.createHanningWindow(fill_a.shape[::-1], cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(fill_b, fill_a, window)
    if response < 0.05 or math.hypot(dx, dy) > _MAX_SHIFT_PX:
        return None
    return (0.0, 0.0) if math.hypot(dx, dy) < 0.5 else (float(dx), float(dy))


def _shifted(frame, shift):
    """``frame``'s (log level, usable, radius^2) moved by ``shift`` px on its raster."""
    dx, dy = shift
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    h, w = frame[0].shape
    log_level = cv2.warpAffine(frame[0], m, (w, h), flags=cv2.INTER_LINEAR)
    rho = cv2.warpAffine(frame[2], m, (w, h), flags=cv2.INTER_LINEAR)
    usable = cv2.warpAffine(frame[1].astype(np.uint8), m, (w, h), flags=cv2.INTER_NEAREST,
                            borderValue=0)
    return log_level, cv2.erode(usable, np.ones((3, 3), np.uint8)).astype(bool), rho
