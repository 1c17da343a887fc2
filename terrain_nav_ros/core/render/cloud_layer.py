"""A layer of broken cloud between a simulated camera and the terrain, and its shadows.

The flight simulator's frames must meet what a real flight meets, and scattered cumulus is
the commonest thing between a camera and the ground: it hides the drainage, puts bright
edges of its own into the frame and throws shadows that take the sun's shading off the
ground beneath. :class:`CloudLayer` is a horizontal sheet ``base`` metres up, whose opacity
is a periodic fractal field (power-law spectrum, the look of cumulus fields from above)
thresholded to the wanted ``cover``, with soft edges, drifting with the wind.
:meth:`CloudLayer.apply` composites it into a linear-radiance render from the per-pixel
ground points the renderer returns: a pixel's ray meets the sheet where the camera is above
it and the ground below, and a ground point is shadowed where its ray to the sun meets it.
A camera below the sheet sees only the shadows. A shadow dims the ground by
``shadow_depth`` and keeps its shading, a simplification: under a real one only the sky's
diffuse light is left, and the sun's shading goes with the direct light.

Geometry in the simulator's ENU metres (z up); the sun as (azimuth from north clockwise,
elevation) in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["CloudLayer"]

_GRID = 1024          # cells per side of the periodic opacity field
_CELLS_PER_CLOUD = 48  # field cells per cloud diameter (the field repeats every 21 clouds)


@dataclass
class CloudLayer:
    """Broken cloud at one height.

    Parameters
    ----------
    cover : float
        Fraction of the sheet that is cloud, in [0, 1): 0 = clear sky.
    base : float
        Height of the sheet, ENU metres (the simulator sets it above the terrain).
    size : float
        Typical cloud diameter (m): the field's spectrum is cut off below it.
    wind : (float, float)
        Drift of the sheet, m/s east and north.
    brightness : float
        Linear radiance of a sunlit cloud top (a render's terrain is 0.05-0.5).
    shadow_depth : float
        Share of the ground's radiance a full shadow takes away (the direct sun's share).
    seed : int
    """

    cover: float = 0.0
    base: float = 1500.0
    size: float = 1500.0
    wind: tuple = (0.0, 0.0)
    brightness: float = 0.9
    shadow_depth: float = 0.6
    seed: int = 0
    _field: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if not 0.0 <= self.cover < 1.0:
            raise ValueError(f"cloud cover must be in [0, 1), got {self.cover!r}")
        if not (math.isfinite(self.size) and self.size > 0):
            raise ValueError(f"cloud size must be > 0 m, got {self.size!r}")
        if not math.isfinite(self.base):
            raise ValueError(f"cloud base must be finite, got {self.base!r}")

    @property
    def cell(self) -> float:
        """Metres per cell of the opacity field."""
        return self.size / _CELLS_PER_CLOUD

    def opacity_field(self) -> np.ndarray:
        """The periodic opacity field (``_GRID`` x ``_GRID`` float32 in [0, 1]), made once."""
        if self._field is None:
            self._field = _fractal_cover(self.cover, self.seed)
        return self._field

    def opacity(self, east, north, t: float = 0.0) -> np.ndarray:
        """Opacity of the sheet at ENU ``east``, ``north`` (m) and time ``t`` (s)."""
        if self.cover <= 0.0:
            return np.zeros(np.shape(east), np.float32)
        f = self.opacity_field()
        col = (np.asarray(east, np.float64) - self.wind[0] * t) / self.cell
        row = -(np.asarray(north, np.float64) - self.wind[1] * t) / self.cell
        col, row = np.mod(col, _GRID).astype(np.float32), np.mod(row, _GRID).astype(np.float32)
        return cv2.remap(f, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def apply(self, rgb: np.ndarray, camera, ground: np.ndarray, sun, t: float = 0.0):
        """Composite the sheet and its shadows into a linear render.

        Parameters
        ----------
        rgb : (H, W, 3) float array
            Linear radiance of the terrain.
        camera : (3,) array
            Camera position, ENU m.
        ground : (H, W, 3) array
            Each pixel's ground point, ENU m (NaN: no terrain).
        sun : (float, float)
            Azimuth and elevation, degrees.
        t : float
            Time (s) for the drift.

        Returns
        -------
        rgb : (H, W, 3) float32 array
        cloud : (H, W) float32 array
            The sheet's opacity in front of each pixel (0 where the view is clear).
        """
        rgb = np.asarray(rgb, np.float32)
        if self.cover <= 0.0:
            return rgb, np.zeros(rgb.shape[:2], np.float32)
        cam = np.asarray(camera, float)
        g = np.asarray(ground, float)
        finite = np.isfinite(g).all(axis=-1)
        g = np.where(finite[..., None], g, cam - [0.0, 0.0, 1.0])   # straight down
        az, el = np.radians(sun[0]), np.radians(sun[1])
        to_sun = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el),
                           math.sin(el)])
        up = (self.base - g[..., 2]) / max(to_sun[2], 1e-3)
        shade = self.opacity(g[..., 0] + up * to_sun[0], g[..., 1] + up * to_sun[1], t)
        shade = np.where(g[..., 2] < self.base, shade, 0.0).astype(np.float32)
        out = rgb * (1.0 - self.shadow_depth * shade)[..., None]
        crosses = (cam[2] > self.base) & (g[..., 2] < self.base)
        s = (cam[2] - self.base) / np.maximum(cam[2] - g[..., 2], 1e-6)
        cloud = self.opacity(cam[0] + s * (g[..., 0] - cam[0]),
                             cam[1] + s * (g[..., 1] - cam[1]), t)
        cloud = np.where(crosses, cloud, 0.0).astype(np.float32)
        out = out * (1.0 - cloud[..., None]) + cloud[..., None] * np.float32(self.brightness)
        return out.astype(np.float32), cloud


def _fractal_cover(cover: float, seed: int) -> np.ndarray:
    """Opacity in [0, 1] of a periodic power-law field (flat beyond a cloud's size, no
    detail finer than an eighth of it) thresholded at its ``1 - cover`` quantile, with soft
    edges."""
    rng = np.random.default_rng(seed)
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(_GRID), np.fft.fftfreq(_GRID)))
    k_cloud = 1.0 / _CELLS_PER_CLOUD
    amplitude = np.maximum(k, k_cloud) ** -1.8 * np.exp(-(k / (8.0 * k_cloud)) ** 2)
    amplitude[0, 0] = 0.0
    noise = rng.standard_normal((_GRID, _GRID))
    f = np.fft.ifft2(np.fft.fft2(noise) * amplitude).real   # filtered white noise: periodic
    f = (f - f.mean()) / f.std()
    threshold = np.quantile(f, 1.0 - cover)
    return np.clip((f - threshold) / 0.25, 0.0, 1.0).astype(np.float32)
