"""Cloud in a camera frame: bright, featureless regions that are not terrain.

A cloud between the camera and the ground hides the drainage; a snowfield or glare that
drives the sensor to full scale does the same. In one grey band the two cannot be told apart
(that needs a short-wave infrared band), but both are *bright and featureless*: near the top
of the sensor's range, and without texture at the scale of the creases. :func:`cloud_mask`
finds bright regions of at least ``min_area`` pixels with a featureless core and grows them
by ``margin`` (the soft fringe of a cloud); :func:`cloud_cover` says when so much of a frame
is covered that it must be answered with a no-fix ("mostly cloud") rather than matched.

The cover is not taken out of the frame's valid pixels: inside a featureless region there
are no creases to lose, and along its edge, masking measured worse. Over real Landsat
views of the Athabasca icefield, masking the clipped snow cost 3 of 18 views localised (its
edges follow the valleys), and over views with synthetic clouds it did not help (18 of 36
against 19 unmasked). Thin cloud, haze and small or dim clouds are not found here: they lower
the contrast or add a few albedo edges, and the matcher's significance test, calibrated on
real non-PVA pairs, keeps them from becoming wrong fixes. Nor are a frame's gain and offset
taken for cloud: texture is judged against the frame's own, and brightness against its
terrain's, so a frame under bright haze or under-exposed is no cloudier than a clear one.
Only camera frames are checked; a landmark render has no cloud.

Levels are fractions of the frame's full scale: the integer range of its dtype (uint8 255,
uint16 65535), and 1.0 for float frames (the ROS ``32FC1`` convention for intensity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .creases import _check, estimate_noise

__all__ = ["CloudParams", "CloudCover", "full_scale", "cloud_mask", "cloud_cover"]

# A cloud's core outshines this percentile of the frame's textured pixels (the ground and
# the cloud's edges: an auto-exposed camera makes a frame that is mostly cloud mid-grey).
_CLOUD_PERCENTILE = 90.0
# The ground's level: this percentile of the textured pixels (the darker quarter: under
# overcast, most textured pixels are the cloud's own edges).
_GROUND_PERCENTILE = 25.0
# A frame with fewer than this share of its valid pixels textured is mostly featureless:
# overcast frames are 8-25 % textured (simulated, raw and ground-projected), real views of
# 128 px and more at least 48 %, the demo's frames under bright haze at least 69 %.
_FEATURELESS_FRAME = 1.0 / 3.0
# Its ground beyond its cloud-like regions' edges: found again at most this many times,
# from at least this share of the frame (a gap in overcast).
_GROUND_ITERATIONS = 4
_MIN_AWAY_SHARE = 0.002


@dataclass(frozen=True)
class CloudParams:
    """Settings of the cloud mask.

    Parameters
    ----------
    enabled : bool
        False: no pixel is taken for cloud.
    bright_level : float
        A cloud's core is at least this fraction of the full scale, in (0, 1], or
        ``min_ratio`` times the frame's ground when that is lower (an auto-exposed camera
        makes a frame that is mostly cloud mid-grey), and in any case at least as bright as
        90 % of the frame's textured pixels (the terrain of a frame under bright haze, or
        over-exposed, is as bright as a cloud, but a cloud outshines it). The rest of the
        cloud is featureless and connected to such a core, and its edge, bright but
        textured, is the bright pixels within the texture window's reach of it.
    min_ratio : float
        How many times brighter than the frame's ground (the darker quarter of its textured
        pixels) a cloud's core is at least, >= 1; the rest of the cloud the square root of
        it. Clouds reflect 0.6-0.9 of the light, terrain 0.05-0.3: 3-10 times more, 1.6-2.8
        times the grey level after a display gamma of 2.2. A hazy frame of smooth terrain
        (oversampled, or under a low sun) is featureless at the creases' scale too, but its
        bright slopes are not twice its dark ones.
    max_texture : float
        ... and its local standard deviation (Gaussian window ``texture_sigma``) at most this
        fraction of the full scale: terrain under the sun shows shading at the crease scale,
        a cloud top or a clipped snowfield does not.
    relative_texture : float
        ... or, when that is lower, at most this share of the frame's own texture (the
        98th percentile of its local standard deviation), in (0, 1]: haze and
        under-exposure lower the texture of the whole frame, a cloud only its own.
    texture_sigma : float
        Window (px) of the local standard deviation, about the creases' scale.
    min_area : int
        A cloud is a bright region of at least this many pixels with a featureless core:
        smaller ones are left (a bright roof, a sunlit rock).
    margin : int
        Pixels added around each region: a cloud's soft fringe is neither cloud-bright nor
        terrain.
    max_fraction : float
        A frame whose valid pixels are at least this fraction cloud is answered with a
        no-fix ("mostly cloud"), in (0, 1]: what is left of it is too small a view to be
        localised without a wrong fix becoming likelier than a right one.
    """

    enabled: bool = True
    bright_level: float = 0.78
    min_ratio: float = 2.0
    max_texture: float = 0.025
    relative_texture: float = 0.2
    texture_sigma: float = 2.0
    min_area: int = 64
    margin: int = 2
    max_fraction: float = 0.75

    def __post_init__(self):
        _check(0.0 < self.bright_level <= 1.0, "bright_level must be in (0, 1]")
        _check(self.min_ratio >= 1.0, "min_ratio must be >= 1")
        _check(0.0 < self.max_texture < 1.0, "max_texture must be in (0, 1)")
        _check(0.0 < self.relative_texture <= 1.0, "relative_texture must be in (0, 1]")
        _check(0.3 <= self.texture_sigma <= 20.0, "texture_sigma must be in [0.3, 20] px")
        _check(self.min_area >= 1, "min_area must be >= 1 px")
        _check(0 <= self.margin <= 50, "margin must be in [0, 50] px")
        _check(0.0 < self.max_fraction <= 1.0, "max_fraction must be in (0, 1]")


@dataclass(frozen=True)
class CloudCover:
    """How much of a frame :func:`cloud_cover` found cloud.

    Attributes
    ----------
    fraction : float
        Share of the frame's valid pixels that is cloud.
    reason : str
        "" when the frame can be matched; otherwise why not ("mostly cloud ...").
    """

    fraction: float
    reason: str = ""


def full_scale(image: np.ndarray) -> float:
    """The level of a fully exposed pixel of ``image``: its integer dtype's maximum, or 1.0
    for a float image."""
    dtype = np.asarray(image).dtype
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return 1.0


def cloud_mask(image: np.ndarray, valid: np.ndarray | None = None,
               params: CloudParams | None = None) -> np.ndarray:
    """Pixels of a grey camera frame that are cloud (or clipped snow or glare).

    Parameters
    ----------
    image : (M, N) array
        Grey frame, uint8, uint16 or float (levels as fractions of :func:`full_scale`).
    valid : (M, N) bool array, optional
        Observed pixels; the mask is only ever True on them.
    params : CloudParams, optional

    Returns
    -------
    (M, N) bool array
    """
    p = params or CloudParams()
    img = np.asarray(image)
    _check(img.ndim == 2, f"cloud_mask needs a grey (M, N) image, not {img.shape}")
    ok = np.ones(img.shape, bool) if valid is None else np.asarray(valid, bool)
    _check(ok.shape == img.shape, "valid must have the image's shape")
    if not p.enabled or img.size == 0:
        return np.zeros(img.shape, bool)
    level = img.astype(np.float32) * np.float32(1.0 / full_scale(img))
    ok = ok & np.isfinite(level)
    level[~ok] = 0.0
    variance = _local_variance(level, ok, p.texture_sigma)
    quantum = 1.0 / full_scale(img) if np.issubdtype(img.dtype, np.integer) else 0.0
    featureless = ok & (variance <= _featureless_variance(level, variance, ok, quantum, p))
    reach = int(math.ceil(4.0 * p.texture_sigma))   # cv2's window for float
    ground, outshone = _terrain_levels(level, ok, featureless, reach, p)
    high = min(p.bright_level, p.min_ratio * ground)
    if math.isfinite(outshone):   # a hazy or over-exposed frame's terrain is bright too
        high = max(high, outshone)
    low = min(p.bright_level, math.sqrt(p.min_ratio) * ground)
    bright = ok & (level >= high)
    core = bright & featureless
    if not core.any():
        return core
    # A cloud is a featureless region with a bright core; the rest of it may be dimmer
    # (vignetting, a thinner part) but stays above most of the ground. Its edge, where the
    # texture window straddles the ground, is bright but not featureless: the bright pixels
    # within the window's reach join it, and only those (a bright frame, hazy or
    # over-exposed, is not one cloud for its clipped patches).
    body = core | (featureless & (level >= low))
    cloudy = body | (_dilated(body, reach) & bright)
    n, labels = cv2.connectedComponents(cloudy.astype(np.uint8), connectivity=8)
    area = np.bincount(labels.ravel(), minlength=n)
    cored = np.bincount(labels[core], minlength=n) > 0
    keep = cored & (area >= p.min_area)
    keep[0] = False   # not cloud
    return _dilated(keep[labels], p.margin) & ok


# Local variance up to this many times the pixel noise's is noise alone (the estimate over a
# sigma-2 window spreads by ~20 %: its 98th percentile is ~1.4 times the noise's variance).
_NOISE_VARIANCE_MARGIN = 2.25


def _featureless_variance(level: np.ndarray, variance: np.ndarray, ok: np.ndarray,
                          quantum: float, p: CloudParams) -> float:
    """The local variance at or below which a pixel is featureless: ``max_texture``
    squared, or less in a frame of little contrast (haze, under-exposure), where it is the
    share ``relative_texture`` of the frame's own texture (its 98th percentile: the ground
    and the clouds' edges), but never below what the pixel noise alone gives (a frame that
    is all cloud has only noise for texture). A frame's gain and offset then do not decide
    what is cloud."""
    if not ok.any():
        return 0.0
    own = float(np.percentile(variance[ok][:: max(1, int(ok.sum()) // 50000)], 98.0))
    noise = max(estimate_noise(level, ok), quantum / math.sqrt(12.0))
    return min(p.max_texture ** 2, max(p.relative_texture ** 2 * own,
                                       _NOISE_VARIANCE_MARGIN * noise ** 2))


def _dilated(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    size = 2 * radius + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def _local_variance(level: np.ndarray, ok: np.ndarray, sigma: float) -> np.ndarray:
    """Variance of ``level`` in a Gaussian window, over the valid pixels only (the edge of
    the camera's footprint is not texture)."""
    w = cv2.GaussianBlur(ok.astype(np.float32), (0, 0), sigma)
    w = np.maximum(w, np.float32(1e-6))
    mean = cv2.GaussianBlur(level, (0, 0), sigma) / w
    return cv2.GaussianBlur(level * level, (0, 0), sigma) / w - mean * mean


def _terrain_levels(level, ok, featureless, reach, p) -> tuple[float, float]:
    """The frame's ground (the darker quarter of its terrain's textured pixels) and the
    level its clouds outshine (their 90th percentile); infinite when too few are textured
    to say.

    In a frame mostly featureless (:data:`_FEATURELESS_FRAME`: the frames a "mostly
    cloud" decision is about), most textured pixels are the edges of its featureless
    regions, whose levels span the ground's to the cloud's and would raise the ground
    toward the cloud (under 95 % auto-exposed overcast, above half the cloud's level: none
    of it was found). Its terrain is then the textured pixels beyond the texture window's
    reach of the featureless regions brighter than that ground, found in turn while that
    lowers it; a gap in the overcast is enough. Frames with more texture keep all of it:
    in real views fields and snow are featureless too, and their edges are terrain (taken
    beyond them, PA July's NIR-bright fields beside cloud shadows became cloud)."""
    textured = ok & ~featureless
    terrain, min_share = textured, 0.02
    ground = _terrain_level(level, terrain, _GROUND_PERCENTILE, min_share)
    if np.count_nonzero(textured) < _FEATURELESS_FRAME * np.count_nonzero(ok):
        for _ in range(_GROUND_ITERATIONS):
            if not math.isfinite(ground):
                break
            cloud_like = featureless & (level > ground)
            away = textured & ~_dilated(cloud_like, reach)
            lower = _terrain_level(level, away, _GROUND_PERCENTILE, _MIN_AWAY_SHARE)
            if not lower < ground:
                break
            terrain, min_share, ground = away, _MIN_AWAY_SHARE, lower
    return ground, _terrain_level(level, terrain, _CLOUD_PERCENTILE, min_share)


def _terrain_level(level: np.ndarray, textured: np.ndarray, percentile: float,
                   min_share: float = 0.02) -> float:
    """The ``percentile`` of the frame's textured pixels (its ground, and a cloud's edges);
    infinite when fewer than ``min_share`` of the frame are textured, too few to say."""
    n = int(np.count_nonzero(textured))
    if n < min_share * level.size:
        return math.inf
    return float(np.percentile(level[textured][:: max(1, n // 20000)], percentile))


def cloud_cover(image: np.ndarray, valid: np.ndarray | None = None,
                params: CloudParams | None = None) -> CloudCover:
    """The share of a frame's valid pixels that is cloud, and a no-fix reason when it is
    at least ``max_fraction`` (see the module docstring)."""
    p = params or CloudParams()
    ok = np.ones(np.shape(image), bool) if valid is None else np.asarray(valid, bool)
    n_valid = int(np.count_nonzero(ok))
    if not n_valid:
        return CloudCover(0.0)
    fraction = float(np.count_nonzero(cloud_mask(image, ok, p))) / n_valid
    if fraction < p.max_fraction:
        return CloudCover(fraction)
    return CloudCover(fraction, f"mostly cloud: {100.0 * fraction:.0f} % of the frame is "
                                "bright and featureless (cloud, snow or glare)")
