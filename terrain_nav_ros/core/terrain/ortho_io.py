"""Georeferenced image ingest (orthoimagery), the twin of :mod:`.dem_io` for images.

The real-imagery study (``terrain-nav evaluate --image``) and the simulator's albedo
(``terrain-nav simulate --albedo``) read satellite and aerial images through
:class:`OrthoImage`, so both see the same pixels:

* **No data** is NaN: the declared nodata value, the dataset's masks and alpha, values that
  are not finite, an image's zeros when it declares none of these (Landsat's DN 0 outside
  its footprint and in Landsat 7's SLC-off gaps; a GDAL warp's border), and an undeclared
  fill value: one value held by many pixels and further from all the others than their own
  spread (-9999 beside reflectances of 0..10000, 65535 beside 12-bit counts), named in
  ``OrthoImage.warning``. An edge of such a fill would be a line of full contrast, the very
  thing read as a valley, and the fill would take the percentile stretch's low end. A
  saturated plateau (snow at 255 beside 254) is data: nothing separates it from the rest.
* **A paletted image** (one band of colour-table indices) reads as its colours, three
  bands red, green, blue: its indices are labels, not brightness.
* **An image georeferenced by ground control points** only (no geotransform: a scanned or
  level-1 product) is warped onto a regular grid of its control points' CRS.

The grid helpers (:func:`ground_cell_metres`, :func:`is_metric_grid`, :func:`utm_crs`) tell
whether a raster's grid is in metres on the ground, as the study and the render need.
"""

from __future__ import annotations

import contextlib
import math
import re
import warnings
from pathlib import Path

import numpy as np

__all__ = ["ImageError", "OrthoImage", "nir_band", "utm_crs", "lonlat", "centre_lonlat",
           "ground_steps", "ground_cell_metres", "is_metric_grid", "rasterio_quiet",
           "undeclared_fill"]

# Band descriptions that name the near infrared: by name, or the NIR band of Landsat TM /
# ETM+ (B4), OLI (B5) and Sentinel-2 MSI (B8, B8A) when the sensor is named with it.
# "nir", "NIR_1", STAC's asset keys "nir08" / "nir09", "near-infrared"
_NIR_NAMES = re.compile(r"\bnir(?:\d*|_\w*)\b|near[- ]?infra[- ]?red", re.IGNORECASE)
# named by sensor and band; Sentinel-2's B8A (narrow NIR) is no other sensor's band
_NIR_BANDS = re.compile(r"\b(?:TM|ETM\+?)\s*B0?4\b|\bOLI\s*B0?5\b|\bMSI\s*B0?8A?\b"
                        r"|\bB8A\b", re.IGNORECASE)
# An undeclared fill covers at least this share of a band's pixels (a plateau, not a tail).
_FILL_SHARE = 0.005
# Pixels whose value statistics judge a fill (every k-th of a larger band).
_FILL_SAMPLE = 1_000_000


class ImageError(ValueError):
    """An image that cannot be read as a georeferenced image of the ground."""


def nir_band(descriptions) -> int | None:
    """The 1-based band whose description names the near infrared, or None.

    Under vegetation the red band is absorbed by chlorophyll and carries little of the
    terrain's shading; the near infrared is bright and shaded like the terrain (Costa Rica's
    forested volcano: 15 of 24 views of 128 px localised in NIR, 2 of 24 in red).
    """
    for pattern in (_NIR_NAMES, _NIR_BANDS):
        for i, text in enumerate(descriptions or ()):
            if text and pattern.search(text):
                return i + 1
    return None


def undeclared_fill(band: np.ndarray) -> list[float]:
    """Values of ``band`` (NaN: no data) that are an undeclared fill: its lowest or highest
    value when at least 0.5 % of the pixels hold it and the gap to the nearest other value
    exceeds the others' 1st-99th percentile span."""
    values = band[np.isfinite(band)].ravel()
    if values.size < 1000:
        return []
    sample = values[::max(1, values.size // _FILL_SAMPLE)]
    found = []
    for value in (float(values.min()), float(values.max())):
        if np.count_nonzero(values == value) < _FILL_SHARE * values.size or value in found:
            continue
        rest = sample[sample != value]
        if rest.size < 100:
            continue   # (nearly) one value: nothing to tell a fill from
        lo, hi = np.percentile(rest, [1.0, 99.0])
        gap = float(rest.min()) - value if value < lo else value - float(rest.max())
        if hi > lo and gap > hi - lo:
            found.append(value)
    return found


class OrthoImage:
    """A georeferenced image file, opened for reading bands (see the module docstring).

    Parameters
    ----------
    path : str or Path
        Any raster rasterio reads.

    Attributes
    ----------
    count : int
        Bands (a paletted image's three colours).
    descriptions : tuple
        The bands' descriptions.
    crs, transform
        The grid of :meth:`read`'s arrays (a GCP image's warped grid).
    shape : (rows, cols)
    warning : str or None
        Undeclared fill values found by the last :meth:`read`.

    Raises
    ------
    ImageError
        Unreadable, or not georeferenced (no CRS, or control points without one).
    """

    def __init__(self, path):
        import rasterio
        from rasterio.enums import ColorInterp

        self.path = Path(path)
        self.name = self.path.name
        self.warning = None
        try:
            self._ds = ds = rasterio.open(self.path)
        except rasterio.errors.RasterioError as err:
            raise ImageError(f"cannot read the image {self.name}: {err}") from err
        self._palette = ds.count == 1 and ds.colorinterp[0] == ColorInterp.palette
        self.count = 3 if self._palette else ds.count
        self.descriptions = ("red", "green", "blue") if self._palette else ds.descriptions
        self.crs, self.transform, self.shape = ds.crs, ds.transform, (ds.height, ds.width)
        self._gcps = None
        gcps, gcp_crs = ds.gcps
        if ds.crs is None and gcps:
            if gcp_crs is None:
                self.close()
                raise ImageError(f"{self.name} has ground control points without a CRS")
            from rasterio.warp import calculate_default_transform
            with rasterio_quiet():
                transform, w, h = calculate_default_transform(gcp_crs, gcp_crs, ds.width,
                                                              ds.height, gcps=gcps)
            self.crs, self.transform, self.shape = gcp_crs, transform, (h, w)
            self._gcps = (gcps, gcp_crs)
        if self.crs is None:
            self.close()
            raise ImageError(f"{self.name} has no CRS: the image must be georeferenced")

    def read(self, bands) -> np.ndarray:
        """Bands (1-based, of :attr:`count`) as float32 ``(len(bands), rows, cols)``, NaN
        where any of them holds no data; :attr:`warning` names undeclared fills. A band
        asked for more than once (one band as three colours) is read and judged once."""
        import rasterio

        wanted = [int(b) for b in bands]
        for b in wanted:
            if not 1 <= b <= self.count:
                raise ImageError(f"{self.name}: band {b} does not exist (the file has "
                                 f"{self.count})")
        bands = sorted(set(wanted))
        try:
            data, nodata = self._colours(bands) if self._palette else self._bands(bands)
        except rasterio.errors.RasterioError as err:
            raise ImageError(f"cannot read the image {self.name}: {err}") from err
        nodata |= ~np.isfinite(data).all(axis=0)
        data[:, nodata] = np.nan
        notes = []
        for k, b in enumerate(bands):
            for value in undeclared_fill(data[k]):
                at = data[k] == value
                notes.append(f"band {b}: {np.count_nonzero(at)} of {at.size} pixels "
                             f"({100 * np.mean(at):.3g} %) hold {value:g}, far outside the "
                             "other values")
                data[:, at] = np.nan
        self.warning = (f"{self.name}: " + "; ".join(notes) + ": an undeclared nodata "
                        "value, read as no data") if notes else None
        data = self._on_grid(data) if self._gcps else data
        return data if wanted == bands else data[[bands.index(b) for b in wanted]]

    def _bands(self, bands):
        a = self._ds.read(bands, masked=True)
        raw = np.ma.getdata(a)
        nodata = np.ma.getmaskarray(a).any(axis=0)
        if self._zero_is_fill():
            nodata |= (raw == 0).all(axis=0)
        return raw.astype(np.float32), nodata

    def _colours(self, bands):
        index = self._ds.read(1, masked=True)
        table = self._ds.colormap(1)
        raw = np.ma.getdata(index).astype(np.intp)
        lut = np.zeros((max(int(raw.max()) + 1, max(table) + 1, 256), 4), np.float32)
        for i, colour in table.items():
            lut[i] = colour
        rgba = lut[raw]
        nodata = np.ma.getmaskarray(index) | (rgba[..., 3] == 0)
        return np.moveaxis(rgba[..., [b - 1 for b in bands]], -1, 0).copy(), nodata

    def _zero_is_fill(self) -> bool:
        """Whether the image's zeros (in every band read) are its fill: it declares no
        nodata, mask or alpha. Landsat's DN products reserve 0 for fill, GDAL's warps fill
        with 0 unless told otherwise, and many exports drop the tag, while exact zeros in a
        natural scene are few."""
        from rasterio.enums import MaskFlags
        return self._ds.nodata is None and all(flags == [MaskFlags.all_valid]
                                               for flags in self._ds.mask_flag_enums)

    def _on_grid(self, data: np.ndarray) -> np.ndarray:
        """A control-point image's bands warped onto :attr:`transform`'s grid."""
        from rasterio.warp import Resampling, reproject
        gcps, crs = self._gcps
        out = np.full((len(data), *self.shape), np.nan, np.float32)
        with rasterio_quiet():
            for k in range(len(data)):
                reproject(data[k], out[k], gcps=gcps, src_crs=crs, src_nodata=np.nan,
                          dst_transform=self.transform, dst_crs=crs, dst_nodata=np.nan,
                          resampling=Resampling.bilinear)
        return out

    def close(self):
        self._ds.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- grids -------------------------------------------------------------------------------
@contextlib.contextmanager
def rasterio_quiet():
    """rasterio 1.4's warp helpers multiply affines with ``*``, which affine 2.4 deprecates:
    a warning about rasterio's code, not this one's."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Use `@` matmul", PendingDeprecationWarning)
        yield


def utm_crs(lon: float, lat: float):
    """The WGS84 UTM zone's CRS at (lon, lat)."""
    from rasterio.crs import CRS
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def lonlat(crs, transform, cols, rows) -> tuple[np.ndarray, np.ndarray]:
    """Longitudes and latitudes of fractional pixel positions (corner convention)."""
    from pyproj import Transformer
    x, y = transform @ (np.asarray(cols, float), np.asarray(rows, float))
    if crs.is_geographic:
        return np.asarray(x, float), np.asarray(y, float)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return np.asarray(lon, float), np.asarray(lat, float)


def centre_lonlat(crs, transform, shape) -> tuple[float, float]:
    """Longitude and latitude of a raster's centre."""
    lon, lat = lonlat(crs, transform, shape[1] / 2.0, shape[0] / 2.0)
    return float(lon), float(lat)


def ground_steps(crs, transform, shape) -> tuple[float, float]:
    """Ground length (m, on the WGS84 ellipsoid) of one pixel step along the rows and along
    the columns at the raster's centre."""
    from pyproj import Geod
    c, r = shape[1] / 2.0, shape[0] / 2.0
    lon, lat = lonlat(crs, transform, [c, c + 1.0, c], [r, r, r + 1.0])
    geod = Geod(ellps="WGS84")
    _, _, steps = geod.inv(lon[[0, 0]], lat[[0, 0]], lon[1:], lat[1:])
    return float(steps[0]), float(steps[1])


def ground_cell_metres(crs, transform, shape) -> float:
    """Side (m) of the square of a raster cell's area: as its transform says on a metric
    grid (:func:`is_metric_grid`), else on the ground at the raster's centre."""
    if is_metric_grid(crs, transform, shape):
        return math.sqrt(abs(transform.a * transform.e))
    return math.sqrt(math.prod(ground_steps(crs, transform, shape)))


def is_metric_grid(crs, transform, shape, tolerance: float = 0.01) -> bool:
    """Whether a raster's grid is north-up with square-metre cells as long on the ground as
    its transform says (UTM, national transverse Mercators). Degrees, feet and Web Mercator
    (1/cos(latitude) too long) are not."""
    if crs.is_geographic or transform.b or transform.d or transform.a <= 0 \
            or transform.e >= 0:
        return False
    along_row, along_col = ground_steps(crs, transform, shape)
    return (abs(along_row / transform.a - 1.0) < tolerance
            and abs(along_col / -transform.e - 1.0) < tolerance)
