"""Lambertian hillshade of a DEM (numpy), for development, tests and lighting benchmarks.

The flight renderer is the moderngl landmark renderer; this is the simple reference shading
``I = ambient + (1 - ambient) * max(0, n . s)`` of a north-up DEM, with the surface normal
``n`` from central differences and the sun direction ``s`` from azimuth (clockwise from
North, degrees) and elevation above the horizon (degrees). No cast shadows.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..render.sun import sun_direction_enu
from .creases import _fill_nodata

__all__ = ["sun_vector", "surface_normals", "hillshade", "shading_curvature", "LIGHTINGS",
           "check_lighting", "extractor_input"]

# What the crease extractor sees: the shading itself, or the curvature estimated from it.
LIGHTINGS = ("shading", "compensated")


def sun_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit ENU vector pointing towards the sun.

    Parameters
    ----------
    azimuth_deg : float
        Clockwise from North (0 = N, 90 = E, 315 = NW).
    elevation_deg : float
        Above the horizon, in [0, 90].
    """
    if not (np.isfinite(azimuth_deg) and np.isfinite(elevation_deg)):
        raise ValueError("sun azimuth and elevation must be finite")
    if not 0.0 <= elevation_deg <= 90.0:
        raise ValueError(f"sun elevation must be in [0, 90] deg, got {elevation_deg}")
    return sun_direction_enu(azimuth_deg, elevation_deg)


def surface_normals(dem: np.ndarray, gsd: float = 1.0, z_factor: float = 1.0):
    """Unit ENU normals (east, north, up components) of a north-up DEM.

    Rows grow southwards, so ``dz/dnorth = -dz/drow / gsd``.
    """
    if not (np.isfinite(gsd) and gsd > 0):
        raise ValueError(f"gsd must be positive, got {gsd}")
    z = np.asarray(dem, np.float64) * z_factor
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"dem must be 2-D and at least 2x2, got shape {z.shape}")
    dz_drow, dz_dcol = np.gradient(z, gsd)
    nx, ny = -dz_dcol, dz_drow  # -dz/deast, -dz/dnorth
    norm = np.sqrt(nx * nx + ny * ny + 1.0)
    return nx / norm, ny / norm, 1.0 / norm


def hillshade(dem: np.ndarray, azimuth_deg: float = 315.0, elevation_deg: float = 45.0,
              gsd: float = 1.0, z_factor: float = 1.0, ambient: float = 0.0,
              dtype=np.float32) -> np.ndarray:
    """Lambertian shading of a DEM lit from (azimuth, elevation).

    Parameters
    ----------
    dem : (M, N) array
        Elevations (m); NaN propagates to the output.
    azimuth_deg, elevation_deg : float
        Sun position, degrees (azimuth clockwise from North).
    gsd : float
        Ground sample distance (m/px).
    z_factor : float
        Vertical exaggeration.
    ambient : float
        Light added everywhere, in [0, 1).
    dtype : numpy dtype
        ``np.uint8`` scales [0, 1] to [0, 255]; a float type returns [0, 1].

    Returns
    -------
    (M, N) array of ``dtype``
    """
    if not 0.0 <= ambient < 1.0:
        raise ValueError(f"ambient must be in [0, 1), got {ambient}")
    sx, sy, sz = sun_vector(azimuth_deg, elevation_deg)
    nx, ny, nz = surface_normals(dem, gsd, z_factor)
    shade = ambient + (1.0 - ambient) * np.clip(nx * sx + ny * sy + nz * sz, 0.0, 1.0)
    if np.dtype(dtype) == np.uint8:
        return np.round(np.nan_to_num(shade) * 255.0).astype(np.uint8)
    return shade.astype(dtype)


def shading_curvature(image, azimuth_deg: float, elevation_deg: float, sigma: float = 1.0,
                      epsilon: float = 0.3, valid_mask=None) -> np.ndarray:
    """Terrain curvature across creases, estimated from one shaded image lit by a known sun.

    Creases of a shaded image follow the sun: with the light from one side a valley is a
    dark slope beside its floor, with the light from the other side it is a bright one. The
    floor itself is where the shading gradient is strongest. To first order the brightness
    of a Lambertian surface is ``I = a - b (grad h . s)`` with ``s`` the sun's horizontal
    direction, so ``grad I = -b H s`` (``H`` the Hessian of the terrain height). Across a
    crease the Hessian has one large eigenvalue ``lambda`` with eigenvector ``u``, so
    ``grad I = -b lambda (u . s) u``: the gradient points across the crease and its
    component along the sun gives the sign. With ``c = cos`` of the angle between
    ``grad I`` and ``s``, ``lambda ~ -|grad I| c / (c^2 + epsilon^2)`` is the same whichever
    side the light comes from and peaks on valley floors and ridge lines. Creases running
    towards the sun (``c`` near 0) do not shade and stay faint: ``epsilon`` keeps them from
    amplifying noise.

    Parameters
    ----------
    image : (M, N) array
        Grey shading (uint8 / uint16 / float); any gain and offset.
    azimuth_deg, elevation_deg : float
        Sun position; the azimuth is clockwise from the image's up direction (North for a
        north-up ground image).
    sigma : float
        Gaussian smoothing (px) before the gradient; 0 for none.
    epsilon : float
        Regularisation of ``1 / c``, in (0, 1].
    valid_mask : (M, N) bool array, optional
        False where there is no image; those pixels are filled from their neighbours first so
        that the view's edge makes no gradient.

    Returns
    -------
    (M, N) float32 array
        Curvature estimate, positive on valley floors, negative on ridge lines, in grey
        levels per pixel (scaled like the input). ``-shading_curvature(...)`` is an image
        whose valleys are dark lines, the extractor's input convention.
    """
    img = np.asarray(image)
    if img.ndim != 2 or min(img.shape) < 3:
        raise ValueError(f"image must be 2-D and at least 3x3, got shape {img.shape}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be >= 0, got {sigma!r}")
    if not 0.0 < epsilon <= 1.0:
        raise ValueError(f"epsilon must be in (0, 1], got {epsilon!r}")
    sx, sy, _ = sun_vector(azimuth_deg, elevation_deg)
    horiz = np.hypot(sx, sy)
    if horiz < 1e-6:
        raise ValueError("a sun at the zenith casts no shading gradient")
    work = img.astype(np.float32)
    valid = np.isfinite(work)
    if valid_mask is not None:
        vm = np.asarray(valid_mask, bool)
        if vm.shape != img.shape:
            raise ValueError("valid_mask must have the image's shape")
        valid &= vm
    if not valid.any():
        return np.zeros(img.shape, np.float32)
    if not valid.all():
        work = _fill_nodata(work, valid)
    if sigma > 0:
        work = cv2.GaussianBlur(work, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    # Central differences; image rows grow southwards, so d/dnorth = -d/drow.
    g_east = cv2.Sobel(work, cv2.CV_32F, 1, 0, ksize=1, scale=0.5,
                       borderType=cv2.BORDER_REFLECT)
    g_north = -cv2.Sobel(work, cv2.CV_32F, 0, 1, ksize=1, scale=0.5,
                         borderType=cv2.BORDER_REFLECT)
    along_sun = g_east * np.float32(sx / horiz) + g_north * np.float32(sy / horiz)
    magnitude = np.sqrt(g_east * g_east + g_north * g_north)
    cos_sun = along_sun / np.maximum(magnitude, np.float32(1e-12))
    return (-magnitude * cos_sun / (cos_sun * cos_sun + np.float32(epsilon**2))).astype(
        np.float32, copy=False)



def check_lighting(lighting: str) -> None:
    """Raise ValueError unless ``lighting`` is one of :data:`LIGHTINGS`."""
    if lighting not in LIGHTINGS:
        raise ValueError(f"lighting must be one of {LIGHTINGS}, got {lighting!r}")


def extractor_input(image, lighting: str, sun=None, valid_mask=None) -> np.ndarray:
    """The image the crease extractor sees under a ``lighting`` treatment.

    ``"shading"`` returns ``image``; ``"compensated"`` returns ``-shading_curvature(image,
    *sun)``, whose valleys are dark lines like a shaded image's, and needs the
    ``(azimuth, elevation)`` of the sun that lit it.
    """
    check_lighting(lighting)
    if lighting == "shading":
        return image
    if sun is None:
        raise ValueError("compensated lighting needs the sun that lit the image")
    return -shading_curvature(image, *sun, valid_mask=valid_mask)
