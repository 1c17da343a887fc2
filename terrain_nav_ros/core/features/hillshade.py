"""Lambertian hillshade of a DEM (numpy), for development, tests and lighting benchmarks.

The flight renderer is the moderngl landmark renderer; this is the simple reference shading
``I = ambient + (1 - ambient) * max(0, n . s)`` of a north-up DEM, with the surface normal
``n`` from central differences and the sun direction ``s`` from azimuth (clockwise from
North, degrees) and elevation above the horizon (degrees). No cast shadows.

:func:`shading_agreement` measures how far a real image's brightness follows that shading:
a check of an image's stated sun, band and registration before it is studied.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..render.sun import sun_direction_enu
from .creases import _fill_nodata

__all__ = ["sun_vector", "surface_normals", "hillshade", "shading_curvature", "LIGHTINGS",
           "check_lighting", "extractor_input", "ShadingAgreement", "shading_agreement"]

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


# The shading compared, as a band of scales in DEM cells: a DEM holds no shading finer than
# its cell, and beyond a few slopes' width land cover and snow outweigh the shading.
SHADING_BAND_CELLS = (1.0, 8.0)
# An image whose correlation with its DEM's shading stays below this at every sun azimuth
# shows little of its terrain (canopy, cloud, haze, or not the DEM's place).
FAINT_SHADING_R = 0.1
# A stated sun is doubtful when some azimuth this far from it or farther agrees better than
# its own by this factor: for shading that follows the sun's horizontal direction as a
# cosine, about 37 deg of error.
DOUBTFUL_SUN_RATIO = 0.8
DOUBTFUL_SUN_DEG = 30.0
# The image and its DEM are told misregistered from this shift of the shading on (DEM
# cells): a fix in the DEM's frame is off the image's ground by as much. The shift is found
# to ~0.5 cell under a patchwork of fields (0.2 on bare slopes), so less is not named. Shifts
# are searched up to REGISTRATION_SEARCH_CELLS.
MISREGISTERED_CELLS = 1.5
REGISTRATION_SEARCH_CELLS = 5
# ... when the shifted shading correlates with the image at least this well (below, its
# peak is as much the land cover's as the terrain's)
REGISTRATION_MIN_R = 0.2
# ... in this band of scales (DEM cells): the slopes' own, where the land cover's edges (a
# field's, a forest's) weigh least against the shading's
REGISTRATION_BAND_CELLS = (0.7, 3.0)


@dataclass(frozen=True)
class ShadingAgreement:
    """How far an image's brightness follows the Lambertian shading of its DEM.

    Attributes
    ----------
    r_at_sun : float
        Correlation of the band-passed image and shading at the stated sun (NaN if none).
    best_azimuth : float
        The sun azimuth (deg, at the stated sun's elevation) whose shading agrees best.
    r_best : float
        The correlation at ``best_azimuth``.
    pixels : int
        Pixels compared, at the DEM's cell.
    offset_east, offset_north : float
        Where the image's terrain lies from its DEM's (m; the shift of the DEM's shading,
        at the stated sun or else the best azimuth's, that the image correlates with best,
        to ~0.5 cell). NaN when not measured, or when it is
        :data:`REGISTRATION_SEARCH_CELLS` cells or more.
    r_offset : float
        The correlation at that shift.
    cell : float
        The DEM's cell the offset was measured at (m).
    """

    r_at_sun: float
    best_azimuth: float
    r_best: float
    pixels: int
    offset_east: float = math.nan
    offset_north: float = math.nan
    r_offset: float = math.nan
    cell: float = math.nan

    @property
    def judged(self) -> bool:
        """Whether there is enough to judge the image by: 100 pixels and a correlation."""
        return self.pixels >= 100 and math.isfinite(self.r_best)

    @property
    def faint(self) -> bool:
        """Whether the image follows its DEM's shading at no sun azimuth (canopy, cloud,
        haze, or not the DEM's place)."""
        return self.judged and self.r_best < FAINT_SHADING_R

    def warning(self, sun=None) -> str | None:
        """What looks wrong with the image or its stated ``sun`` (azimuth, elevation), or
        None. The image is not judged on fewer than 100 pixels."""
        if not self.judged:
            return None
        if self.faint:
            return (f"the image shows little of its terrain's shading at any sun azimuth "
                    f"(correlation {self.r_best:.2f} at best): expect few fixes (canopy, "
                    f"cloud, haze, another band, or an image and DEM of different places)")
        off = abs((self.best_azimuth - sun[0] + 180.0) % 360.0 - 180.0) if sun else 0.0
        if (sun and off >= DOUBTFUL_SUN_DEG
                and not self.r_at_sun >= DOUBTFUL_SUN_RATIO * self.r_best):
            return (f"its shading agrees better with a sun from azimuth "
                    f"{self.best_azimuth:.0f} deg (correlation {self.r_best:.2f}) than with "
                    f"the stated {sun[0]:.1f} deg ({self.r_at_sun:.2f}): check the sun (the "
                    f"acquisition time) and the band")
        return None

    @property
    def offset_judged(self) -> bool:
        """Whether the offset places the terrain: not on a faint image, whose shading shows
        no terrain to place, nor at a correlation below :data:`REGISTRATION_MIN_R`."""
        return self.judged and not self.faint and self.r_offset >= REGISTRATION_MIN_R

    def registration_warning(self) -> str | None:
        """That the image's terrain lies 1.5 DEM cells or more from its DEM's, or None
        (nor when the offset is not :attr:`offset_judged`)."""
        if not self.offset_judged:
            return None
        off = math.hypot(self.offset_east, self.offset_north)
        if not off >= MISREGISTERED_CELLS * self.cell:   # (NaN: not within the search)
            return None
        return (f"the image's terrain lies {self.offset_east:+.0f} m east and "
                f"{self.offset_north:+.0f} m north of its DEM's (the shift at which its "
                f"shading agrees best, {off / self.cell:.1f} DEM cells): the image and DEM "
                "are misregistered, and a fix in the DEM's frame is off the image's ground "
                "by as much")


def shading_agreement(image, elevation, gsd: float, sun=None, valid_mask=None,
                      cell: float = 1.0) -> ShadingAgreement:
    """Correlate an image with the Lambertian shading of its co-registered DEM.

    Both are band-passed to :data:`SHADING_BAND_CELLS` DEM cells. Band-passed shading is
    linear in the sun vector ``s``, ``S(s) = s . B`` with ``B`` the band-passed normals,
    so the correlation at every sun is ``s . c / sqrt(s' G s)`` from the image's products
    with ``B`` (``c``) and those of ``B`` (``G``): one pass over the pixels for all suns.
    The elevation changes it little (the shading of gentle slopes scales with its cosine,
    which a correlation ignores), the azimuth much.

    Parameters
    ----------
    image : (M, N) array
        The image (any gain and offset), north-up.
    elevation : (M, N) array
        Its DEM on the same grid (m).
    gsd : float
        Grid cell (m).
    sun : (azimuth, elevation), optional
        The stated sun (deg); without it the azimuths are scanned at 45 deg of elevation.
    valid_mask : (M, N) bool array, optional
        The image's observed pixels.
    cell : float
        The DEM's own cell in grid pixels (> 1 when the grid is finer than the DEM): both
        are compared at the DEM's cell.

    Returns
    -------
    ShadingAgreement
    """
    img = np.asarray(image, np.float32)
    z = np.asarray(elevation, np.float32)
    if img.ndim != 2 or img.shape != z.shape:
        raise ValueError(f"image and elevation must be 2-D of one shape, got {img.shape} "
                         f"and {z.shape}")
    valid = np.isfinite(img) & np.isfinite(z)
    if valid_mask is not None:
        valid &= np.asarray(valid_mask, bool)
    if not valid.any():
        return ShadingAgreement(math.nan, math.nan, math.nan, 0)
    if not np.isfinite(z).all():   # voids: no slope there (they are not compared either)
        z = _fill_nodata(z, np.isfinite(z))
    cell = max(float(cell), 1.0)
    if cell > 1.0:   # to the DEM's cell: the finer pixels hold no more of its shading
        size = (max(int(round(img.shape[1] / cell)), 2), max(int(round(img.shape[0] / cell)), 2))
        weight = cv2.resize(valid.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        img = cv2.resize(np.where(valid, img, 0), size, interpolation=cv2.INTER_AREA)
        img /= np.maximum(weight, 1e-6)
        z = cv2.resize(z, size, interpolation=cv2.INTER_AREA)
        valid = weight > 0.999
    # the band's edge within a pixel of no data is the fill's, not the image's
    compared = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    azimuths = np.arange(0.0, 360.0, 1.0)
    if compared.sum() < 100 or min(img.shape) < 3:
        return ShadingAgreement(math.nan, math.nan, math.nan, int(compared.sum()))
    def band(x, cells=SHADING_BAND_CELLS):
        return cv2.GaussianBlur(x, (0, 0), cells[0]) - cv2.GaussianBlur(x, (0, 0), cells[1])

    filled = _fill_nodata(img, valid) if not valid.all() else img
    a = band(filled)[compared]
    a -= a.mean()
    normals = surface_normals(z, gsd * cell)
    b = np.stack([band(n.astype(np.float32))[compared] for n in normals]).astype(np.float64)
    b -= b.mean(axis=1, keepdims=True)
    c, gram, norm_a = b @ a, b @ b.T, float(np.sqrt(a @ a))

    def correlation(s):
        energy = float(s @ gram @ s)
        return float(s @ c) / math.sqrt(energy) / norm_a if energy > 0 and norm_a > 0 \
            else math.nan

    sun_elevation = sun[1] if sun is not None else 45.0
    scan = [correlation(sun_vector(az, sun_elevation)) for az in azimuths]
    k = int(np.nanargmax(scan)) if np.isfinite(scan).any() else 0
    r_at = correlation(sun_vector(*sun)) if sun is not None else math.nan
    lit = sun_vector(*sun) if sun is not None else sun_vector(azimuths[k], sun_elevation)
    fine = REGISTRATION_BAND_CELLS
    shading = np.tensordot(lit, np.stack([band(n.astype(np.float32), fine) for n in normals]),
                           1)
    image_band = band(filled, fine)
    # (away from the edges of no data by the band's reach: the fill's slopes are no terrain)
    reach = 2 * int(math.ceil(2.0 * fine[1])) + 1
    inner = cv2.erode(compared.astype(np.uint8), np.ones((reach, reach), np.uint8)) > 0
    east, north, r_offset = registration_offset(image_band, shading,
                                                inner if inner.sum() >= 100 else compared)
    cell_m = gsd * cell
    return ShadingAgreement(r_at, float(azimuths[k]), float(scan[k]), int(compared.sum()),
                            east * cell_m, north * cell_m, r_offset, cell_m)


def registration_offset(image, shading, valid=None,
                        search: int = REGISTRATION_SEARCH_CELLS
                        ) -> tuple[float, float, float]:
    """Where an image's pattern lies from a reference's on the same north-up grid, east and
    north in cells: the shift of ``shading`` whose normalised correlation with ``image``
    peaks (a parabola through the peak's neighbours gives the fraction of a cell).

    Parameters
    ----------
    image, shading : (M, N) arrays
        Band-passed, zero-mean fields (the image's brightness, its DEM's shading).
    valid : (M, N) bool array, optional
        The image's pixels compared (others weigh nothing).
    search : int
        Largest shift tried, cells; a peak at it means the offset is not within it.

    Returns
    -------
    (east, north, r) : floats
        The offset (NaN when the peak lies at the searched edge or the fields are too
        small) and the correlation at it.
    """
    img = np.asarray(image, np.float32)
    ref = np.asarray(shading, np.float32)
    m = int(search)
    if valid is not None:   # both only where the image is (a DEM's edge is a cliff there)
        valid = np.asarray(valid, bool)
        rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
        if not len(rows):
            return math.nan, math.nan, math.nan
        box = (slice(max(rows[0] - m, 0), rows[-1] + m + 1),
               slice(max(cols[0] - m, 0), cols[-1] + m + 1))
        img, ref, valid = img[box], ref[box], valid[box]
        img = np.where(valid, img, 0.0).astype(np.float32)
        ref = np.where(valid, ref, 0.0).astype(np.float32)
    if min(img.shape) <= 4 * m:
        return math.nan, math.nan, math.nan
    # the image's inner part slid over the whole reference: result[m + dy, m + dx] pairs
    # image pixel p with reference pixel p + (dy, dx)
    score = cv2.matchTemplate(ref, img[m:-m, m:-m], cv2.TM_CCORR_NORMED)
    dy, dx = np.unravel_index(int(np.argmax(score)), score.shape)
    peak = float(score[dy, dx])
    if not (0 < dy < 2 * m and 0 < dx < 2 * m):
        return math.nan, math.nan, peak

    def vertex(lo, mid, hi):
        curve = lo - 2.0 * mid + hi
        return 0.5 * (lo - hi) / curve if curve < 0 else 0.0

    fx = vertex(*score[dy, dx - 1:dx + 2])
    fy = vertex(*score[dy - 1:dy + 2, dx])
    # the image at p shows the reference's p + d: its pattern lies -d from the reference's
    # (columns east, rows south)
    return float(-(dx + fx - m)), float(dy + fy - m), peak
