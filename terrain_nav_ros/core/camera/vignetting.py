"""A lens's vignetting, learnt from the flight's own frames and divided out.

A lens passes less light towards the edge of its field (the cos^4 law, the aperture's
shadow), so a frame darkens outwards from its principal point unless the camera flat-fields
it. That slow radial slope moves every valley's darkest line outwards by its gradient over
the valley's curvature, so the creases of a frame lie farther from its centre than those of
the landmark render: the view's measured scale comes out small, and with it the height that
the fix takes from it. The simulator's lens (25 % darker in the corners) gave -0.39 % in
scale, -13 m at 3.3 km, in every fix of the short bag.

Terrain is no brighter at the edge of a frame than at its centre once many frames are
averaged: the log brightness by distance from the principal point, over the flight's
frames (each frame's own exposure taken out), is the lens's falloff; the log of each
frame's mean level by radius, as the falloff multiplies it. :class:`Vignetting`
keeps that radial profile, fits it with an even polynomial ``a1 r^2 + a2 r^4`` (``r`` over
the half diagonal) and divides it out of each frame once :data:`MIN_FRAMES` frames have
been seen. A camera that flat-fields already gives a flat profile and frames unchanged.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Vignetting", "MIN_FRAMES"]

# Frames seen before the falloff is divided out: one frame's terrain can be brighter at
# its centre by chance (a snowfield, a lake at the edge); the mean of several cannot.
MIN_FRAMES = 5
# The profile's memory in frames (a lens's falloff changes with its aperture only)
MEMORY_FRAMES = 200
# Radial bins of r^2 over the half diagonal squared (0 at the principal point, ~1 in a corner)
_BINS = 32
_BIN_CENTRES = (np.arange(_BINS) + 0.5) / _BINS
# Pixels near the ends of the sensor's range say nothing of the falloff (saturated cloud,
# snow; black shadow)
_LEVELS = (0.02, 0.98)
# A fitted falloff darker than this at the frame's corner is not a lens's (a frame sequence
# over one bright feature): nothing is divided out
_MAX_CORNER_FALLOFF = 0.6


class Vignetting:
    """The running estimate of a camera's radial falloff, and frames corrected by it.

    Parameters
    ----------
    enabled : bool
        False leaves every frame as it is.
    """

    def __init__(self, enabled: bool = True):
        self.enabled = bool(enabled)
        self.frames = 0
        self._sum = np.zeros(_BINS)      # weighted sums of the mean log level per bin
        self._weight = np.zeros(_BINS)
        self._grid = None                # (shape, centre) and its bin index per pixel

    def correct(self, image: np.ndarray, centre=None) -> np.ndarray:
        """Learn from ``image`` and return it with the falloff learnt so far divided out.

        Parameters
        ----------
        image : (H, W) or (H, W, C) array
            A raw camera frame (uint8, uint16 or float), before undistortion.
        centre : (cx, cy), optional
            The principal point (px); default the image's centre.

        Returns
        -------
        ndarray
            Of ``image``'s shape and dtype (``image`` itself while fewer than
            :data:`MIN_FRAMES` frames are seen or the falloff is flat).
        """
        if not self.enabled or image.ndim not in (2, 3) or min(image.shape[:2]) < 8:
            return image
        bins = self._bins(image.shape[:2], centre)
        self._learn(image, bins)
        gain = self.gain(bins) if self.frames >= MIN_FRAMES else None
        if gain is None:
            return image
        out = image.astype(np.float32) * (gain if image.ndim == 2 else gain[..., None])
        if np.issubdtype(image.dtype, np.integer):
            info = np.iinfo(image.dtype)
            return np.clip(np.rint(out), info.min, info.max).astype(image.dtype)
        return out.astype(image.dtype, copy=False)

    def falloff(self) -> tuple[float, float] | None:
        """The fitted ``(a1, a2)``: the falloff is ``exp(a1 r^2 + a2 r^4)``; None before
        any frame."""
        seen = self._weight > 0
        if seen.sum() < 3:
            return None
        rho = _BIN_CENTRES[seen]
        profile = self._sum[seen] / self._weight[seen]
        design = np.column_stack([np.ones(seen.sum()), rho, rho ** 2])
        w = np.sqrt(self._weight[seen])
        coef, *_ = np.linalg.lstsq(design * w[:, None], profile * w, rcond=None)
        return float(coef[1]), float(coef[2])

    def corner(self) -> float:
        """The brightness the fitted falloff leaves in a frame's corner (1: none; NaN
        before any frame), for the diagnostics."""
        fit = self.falloff()
        return float(np.exp(sum(fit))) if fit else float("nan")

    def gain(self, bins: np.ndarray) -> np.ndarray | None:
        """Per pixel, the factor that undoes the falloff (None: nothing to undo)."""
        fit = self.falloff()
        if fit is None:
            return None
        a1, a2 = fit
        if not _MAX_CORNER_FALLOFF <= np.exp(a1 + a2) <= 1.0 / _MAX_CORNER_FALLOFF:
            return None
        per_bin = np.exp(-(a1 * _BIN_CENTRES + a2 * _BIN_CENTRES ** 2)).astype(np.float32)
        return per_bin[bins]

    def _bins(self, shape, centre) -> np.ndarray:
        h, w = shape
        cx, cy = centre if centre is not None else (0.5 * (w - 1), 0.5 * (h - 1))
        key = (shape, round(float(cx), 3), round(float(cy), 3))
        if self._grid is None or self._grid[0] != key:
            y, x = np.ogrid[0:h, 0:w]
            rho = ((x - cx) ** 2 + (y - cy) ** 2) / (0.25 * (w * w + h * h))
            self._grid = (key, np.minimum((rho * _BINS).astype(np.intp), _BINS - 1))
        return self._grid[1]

    def _learn(self, image: np.ndarray, bins: np.ndarray) -> None:
        """Add the frame's mean log level per radial bin, its own mean taken out."""
        level = image.astype(np.float32)
        if level.ndim == 3:
            level = level.mean(axis=2)
        full = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) \
            else 1.0
        ok = np.isfinite(level) & (level > _LEVELS[0] * full) & (level < _LEVELS[1] * full)
        if ok.mean() < 0.5:
            return     # mostly saturated or black: says nothing of the lens
        count = np.bincount(bins[ok], minlength=_BINS).astype(float)
        total = np.bincount(bins[ok], weights=level[ok], minlength=_BINS)
        seen = count > 0
        mean = np.zeros(_BINS)
        # the log of the mean level, not the mean of the logs: that would also fall where
        # the contrast is higher (the log is concave), the falloff's product would not
        mean[seen] = np.log(total[seen] / count[seen])
        mean[seen] -= np.average(mean[seen], weights=count[seen])   # the frame's exposure
        keep = 1.0 - 1.0 / min(self.frames + 1, MEMORY_FRAMES)
        share = count / max(count.sum(), 1.0)     # each frame weighs one, spread over bins
        self._sum = keep * self._sum + (1.0 - keep) * mean * share
        self._weight = keep * self._weight + (1.0 - keep) * share
        self.frames += 1
