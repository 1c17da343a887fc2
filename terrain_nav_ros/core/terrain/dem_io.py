"""Lazy DEM ingest: ESRI ASCII grids, GeoTIFF, SRTM ``.hgt``, mosaics and the embedded default.

:func:`open_dem` returns a :class:`Dem`: the georeference (affine transform, CRS, size, nodata)
is read at once, elevations only on demand, window by window. Uncompressed single-band
GeoTIFFs with contiguous strips and SRTM ``.hgt`` tiles are memory-mapped with numpy (a
1024 x 1024 window of a 10812 x 10812 tile touches ~4 MB); everything else goes through
rasterio/GDAL windowed reads. Windows come back as float32 with NaN for nodata/voids.
GDAL keeps read blocks in its own cache (default 5 % of RAM): a long-running process reading
tiled or compressed files should set ``GDAL_CACHEMAX`` (e.g. 64 MB) in its environment.

Pixel convention (as in :mod:`.georef`): ``Dem.transform`` is the GDAL affine transform of
pixel *corners*; integer pixel coordinates (col, row) are pixel *centres*.

Heights are orthometric metres (SRTM: EGM96 geoid; USGS: NAVD88); see :mod:`.geodesy` for
what that means in ENU. A GeoTIFF's stored values go through its band scale and offset, and
heights in feet (the band's unit, or the vertical axis of a compound CRS such as US
state-plane lidar's ``EPSG:2229+6360``) are converted; cells under a GDAL mask (internal,
``.msk`` or alpha) are voids like nodata. A file's heights outside
:data:`EARTH_ELEVATIONS` are impossible for the surface a camera sees (corrupt pixels, an
undeclared nodata value such as -9999, sea floor, or heights not in metres), and so are
nonzero ones within :data:`TINY_HEIGHT` of 0 (random bytes read as floats): they are read as
voids, with a warning in ``Dem.warning``, and a file where most are impossible is refused.

Embedded default (:func:`sample_dem`): ``jacksboro_fault_dem.npz`` from matplotlib's sample
data, a 344 x 403 int16 USGS DEM of the Jacksboro fault / Pine Mountain area (Cumberland
Mountains, Tennessee), 3 arc-second cells (``dx = dy = 1/1200`` deg). Its keys are
``elevation, dx, dy, xmin, xmax, ymin, ymax``; the extent is exactly ``403 dx`` by ``344 dy``,
so the bounds are the outer cell edges. ``ymin`` (36.7329) and ``ymax`` (36.4463) are stored
swapped; we take row 0 as the northern edge (the raster convention, and how matplotlib shows
it). That orientation is consistent with the mapped geology: Pine Mountain then strikes NE and
the Jacksboro tear fault NW, as they do (flipped, both would be wrong). The absolute position
is the file's own and has not been checked against an independent source. The file names no
datum: we use EPSG:4326; if it is NAD83 (as USGS products are) the horizontal difference is
about 1 m, 1 % of a cell. Heights are metres above the geoid (NAVD88 or EGM96).
"""

from __future__ import annotations

import glob
import math
import mmap
import os
import re
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS, Transformer
from pyproj.exceptions import ProjError
from rasterio.enums import MaskFlags
from rasterio.errors import RasterioError, RasterioIOError
from rasterio.windows import Window
from scipy import ndimage as ndi

__all__ = [
    "DemError", "Dem", "open_dem", "sample_dem", "mosaic", "fill_voids", "dem_files", "SRTM_VOID",
    "EARTH_ELEVATIONS", "TINY_HEIGHT",
]

#: SRTM void marker.
SRTM_VOID = -32768
#: Heights (m) the visible surface can have: the lowest dry land is the Dead Sea shore
#: (-430 m), the highest summit Everest (8849 m).
EARTH_ELEVATIONS = (-500.0, 9000.0)
#: Heights nearer 0 than this, but not 0, are impossible too: no survey resolves them, and
#: random bytes read as float32 are mostly such tiny numbers (or huge ones).
TINY_HEIGHT = 1e-6
_SCAN_CELLS = 1 << 22  # cells open_dem reads to judge the heights (a small DEM: all of them)
_SCAN_BAND = 1 << 18  # cells it reads at once
# N44E005.hgt, and LP DAAC's N44E005.SRTMGL1.hgt; GDAL reads them zipped too (.hgt.zip)
_HGT_NAME = re.compile(r"^([NS])(\d{2})([EW])(\d{3})(\.SRTMGL[13])?\.hgt(\.zip)?$",
                       re.IGNORECASE)
# (rows, cols) of SRTM3, SRTM1 and of SRTM1-style tiles at 50-60 deg that halve the columns
_HGT_SHAPES = ((1201, 1201), (3601, 3601), (3601, 1801))
# metres per foot, per US survey foot
_FOOT, _US_SURVEY_FOOT = 0.3048, 1200.0 / 3937.0
_ASC_KEYS = {b"ncols", b"nrows", b"xllcorner", b"yllcorner", b"xllcenter", b"yllcenter",
             b"cellsize", b"dx", b"dy", b"nodata_value"}
_CHUNK = 1 << 22


class DemError(ValueError):
    """A DEM cannot be used; the message names the file and the problem."""


@dataclass(eq=False)
class Dem:
    """A DEM raster opened lazily: georeference now, elevations window by window.

    Build one with :func:`open_dem`, :func:`sample_dem`, :func:`mosaic` or
    :meth:`Dem.from_array`.

    Attributes
    ----------
    name : str
        File path or description, used in messages.
    transform : affine.Affine
        Pixel-corner (col, row) -> CRS (x, y), GDAL convention.
    width, height : int
        Raster size in pixels.
    crs : pyproj.CRS or None
        Horizontal CRS; None when the grid is in unreferenced local metres.
    crs_guessed : bool
        True when the CRS was inferred from the header (ESRI grid without ``.prj``).
    dtype : numpy.dtype
        Storage dtype of the elevations.
    nodata : float or None
        Storage value marking missing cells (NaN nodata is always honoured).
    valid_range : (float, float) or None
        Heights outside it, or nonzero below :data:`TINY_HEIGHT`, are read as voids (files:
        :data:`EARTH_ELEVATIONS`).
    warning : str or None
        What is wrong with the heights, for the caller to show (impossible ones voided), and
        a CRS guessed from an ESRI grid's header.
    """

    name: str
    transform: Affine
    width: int
    height: int
    crs: CRS | None
    dtype: np.dtype
    nodata: float | None
    _read: Callable[[int, int, int, int], np.ndarray] = field(repr=False)
    crs_guessed: bool = False
    _close: Callable[[], None] | None = field(default=None, repr=False)
    valid_range: tuple[float, float] | None = None
    warning: str | None = None

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_array(cls, array, transform, crs=None, nodata=None, name="<array>",
                   crs_guessed=False):
        """Wrap a 2-D array (ndarray or ``np.memmap``) as a DEM.

        Windows are float32 copies. For a ``np.memmap`` the pages read are released from the
        process's resident set after each window (``MADV_DONTNEED``), so RSS stays near the
        working set instead of growing towards the file size.

        Parameters
        ----------
        array : array_like, shape (rows, cols)
            Elevations; any real dtype.
        transform : affine.Affine or sequence of 6 floats
            Pixel-corner affine transform (``Affine`` order or a GDAL geotransform tuple).
        crs : pyproj.CRS, str or None
            Horizontal CRS; None for local metres.
        nodata : float, optional
            Storage value of missing cells.
        """
        if array.ndim != 2:
            raise DemError(f"{name}: elevation array must be 2-D, got shape {array.shape}")
        if not isinstance(transform, Affine):
            transform = Affine.from_gdal(*transform)
        crs = None if crs is None else CRS.from_user_input(crs)

        mapping = getattr(array, "_mmap", None) if isinstance(array, np.memmap) else None

        def read(r0, r1, c0, c1):
            block = _to_float(array[r0:r1, c0:c1], nodata)
            if mapping is not None:
                # unmap the pages just copied: they stay in the page cache (the next read is a
                # cheap minor fault) but no longer count in this process's resident set
                mapping.madvise(mmap.MADV_DONTNEED)
            return block

        return cls(name, transform, array.shape[1], array.shape[0], crs, np.dtype(array.dtype),
                   nodata, read, crs_guessed)

    # -- georeference -------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return (self.height, self.width)

    @property
    def local_metres(self) -> bool:
        """True when the grid has no CRS and is taken as local metres east/north."""
        return self.crs is None

    @property
    def res(self) -> tuple[float, float]:
        """Cell size (x, y) in CRS units, both positive."""
        return (abs(self.transform.a), abs(self.transform.e))

    @property
    def is_north_up(self) -> bool:
        """True when the transform has no rotation and rows grow southwards."""
        t = self.transform
        return t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) outer edges in CRS units."""
        xs, ys = self.transform @ (np.array([0, self.width, 0, self.width]),
                                   np.array([0, 0, self.height, self.height]))
        return (float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max()))

    def pixel_to_crs(self, col, row):
        """CRS (x, y) of fractional pixel coordinates; integers are pixel centres."""
        col = np.asarray(col, dtype=float) + 0.5
        row = np.asarray(row, dtype=float) + 0.5
        return self.transform @ (col, row)

    def crs_to_pixel(self, x, y):
        """Fractional pixel coordinates (col, row) of CRS points; integers are centres."""
        col, row = ~self.transform @ (np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        return col - 0.5, row - 0.5

    # -- pixels -------------------------------------------------------------------------
    def read(self, window=None) -> np.ndarray:
        """Elevations as float32 with NaN for nodata.

        Parameters
        ----------
        window : tuple of slices (rows, cols), optional
            Region to read, ``np.s_[r0:r1, c0:c1]``; default the whole raster. Unbounded or
            negative slice ends behave as in numpy; steps are not supported.
        """
        if window is None:
            return self.read_window(0, 0, self.height, self.width)
        rows, cols = window
        r0, r1, _ = rows.indices(self.height)
        c0, c1, _ = cols.indices(self.width)
        return self.read_window(r0, c0, max(r1 - r0, 0), max(c1 - c0, 0))

    def read_window(self, row0: int, col0: int, nrows: int, ncols: int) -> np.ndarray:
        """Read ``nrows x ncols`` cells from (row0, col0); cells outside the DEM are NaN."""
        r0, r1 = max(row0, 0), min(row0 + nrows, self.height)
        c0, c1 = max(col0, 0), min(col0 + ncols, self.width)
        block = None
        if r1 > r0 and c1 > c0:
            try:
                block = self._read(r0, r1, c0, c1)
            except (RasterioError, OSError) as exc:
                raise DemError(f"{self.name}: cannot read rows {r0}:{r1}, cols {c0}:{c1} "
                               f"(truncated or corrupt data?): {exc}") from exc
            if self.valid_range is not None:
                block[_impossible(block, self.valid_range)] = np.nan
            if block.shape == (nrows, ncols):  # wholly inside: already a fresh float32 array
                return block
        out = np.full((nrows, ncols), np.nan, dtype=np.float32)
        if block is not None:
            out[r0 - row0:r1 - row0, c0 - col0:c1 - col0] = block
        return out

    def filled(self, max_area: int = 256) -> Dem:
        """An in-memory copy with small voids filled (see :func:`fill_voids`).

        Loads the whole raster: meant for small DEMs (SRTM3/SRTM1 tiles, ASCII grids).
        """
        z, _ = fill_voids(self.read(), max_area=max_area)
        return Dem.from_array(z, self.transform, self.crs, None, self.name + " (filled)",
                              self.crs_guessed)

    def close(self):
        """Release the file handle (idempotent)."""
        if self._close is not None:
            self._close()
            self._close = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _impossible(z: np.ndarray, valid_range: tuple[float, float]) -> np.ndarray:
    """Where heights are outside ``valid_range`` or nonzero below :data:`TINY_HEIGHT` (NaN,
    nodata, is neither)."""
    lo, hi = valid_range
    return (z < lo) | (z > hi) | ((np.abs(z) < TINY_HEIGHT) & (z != 0))


def _to_float(block, nodata) -> np.ndarray:
    """float32 copy of a storage block with nodata -> NaN (one copy, one compare)."""
    out = np.array(block, dtype=np.float32, copy=True)  # never hand out the source's memory
    if nodata is not None and not np.isnan(nodata):
        if np.float32(nodata) == nodata:
            out[out == np.float32(nodata)] = np.nan
        else:  # nodata not representable in float32 (e.g. an int32 sentinel): compare raw
            out[np.asarray(block) == nodata] = np.nan
    return out


# -- opening files ----------------------------------------------------------------------
def open_dem(path, crs=None, *, validate: bool = True) -> Dem:
    """Open a DEM file lazily.

    Parameters
    ----------
    path : str or Path
        ``.asc`` (ESRI ASCII grid, optional ``.prj``), ``.tif``/``.tiff`` (GeoTIFF), ``.hgt``
        (SRTM tile named like ``N44E005.hgt``, or zipped: ``N44E005.hgt.zip``), ``.npz``
        (matplotlib sample-DEM layout), or
        anything else GDAL reads.
    crs : pyproj.CRS, str, or "local", optional
        Override the file's CRS; ``"local"`` forces unreferenced local metres.
    validate : bool
        Read the last cell at once, so truncated files fail here rather than mid-mission, and
        judge the heights (all of them, or every k-th row of a DEM over 4 M cells): when
        some are outside :data:`EARTH_ELEVATIONS` ``Dem.warning`` says so; when most are,
        the file is refused. Either way such heights are read as voids.

    Returns
    -------
    Dem

    Raises
    ------
    DemError
        Missing file, unreadable or wrong header, truncated data, values that are not
        numbers (ESRI ASCII), mostly impossible heights, unknown CRS.

    Notes
    -----
    An ESRI ASCII grid without ``.prj`` gets its CRS from the header: if the cell size is
    below 0.1 (6 arc-minutes) and the extent lies within [-180, 180] x [-90, 90] it is taken
    as WGS84 lon/lat (EPSG:4326), otherwise as local metres (``Dem.local_metres``); both set
    ``Dem.crs_guessed``. A GeoTIFF without CRS, or a ``.prj`` GDAL cannot parse, is an error
    unless ``crs`` is given.
    """
    path = Path(path)
    if not path.is_file():
        raise DemError(f"{path}: no such DEM file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        dem = _open_npz(path)
    else:
        if suffix == ".hgt" or path.name.lower().endswith(".hgt.zip"):
            _check_hgt(path)
        _check_ascii_grid(path)
        dem = _open_gdal(path, crs is not None)
    if crs is not None:
        dem.crs = None if str(crs).lower() == "local" else _parse_crs(crs, path)
        dem.crs_guessed = False
    try:
        _check_georeference(dem)
    except DemError:
        dem.close()
        raise
    if validate and dem.width and dem.height:
        try:
            dem.read_window(dem.height - 1, dem.width - 1, 1, 1)
            dem.warning = _judge_heights(dem)
        except DemError:
            dem.close()
            raise
    if dem.crs_guessed:   # say so: a wrong guess puts the DEM at another place
        guess = "WGS84 longitude and latitude" if dem.crs else "local metres"
        dem.warning = "; ".join(w for w in (
            f"{path}: no .prj: its CRS is taken as {guess} from its header's cell size and "
            f"extent; put the right .prj beside it if that is wrong", dem.warning) if w)
    dem.valid_range = EARTH_ELEVATIONS
    return dem


def _judge_heights(dem: Dem) -> str | None:
    """None when every height read is possible on Earth, else a warning; raises DemError when
    most are impossible. Reads at most ``_SCAN_CELLS`` cells (every k-th row of a big DEM),
    a band of rows at a time so memory stays small."""
    step = -(-dem.width * dem.height // _SCAN_CELLS)
    band = max(1, _SCAN_BAND // dem.width) if step == 1 else 1
    lo, hi = EARTH_ELEVATIONS
    n_bad = n = 0
    first = None
    for r0 in range(0, dem.height, step * band):
        z = dem.read_window(r0, 0, min(band, dem.height - r0), dem.width)
        bad = _impossible(z, EARTH_ELEVATIONS)
        n += np.count_nonzero(~np.isnan(z))
        if bad.any():
            n_bad += np.count_nonzero(bad)
            if first is None:
                r, c = np.argwhere(bad)[0]
                first = (z[r, c], r0 + r, c)
    if not n_bad:
        return None
    what = (f"{dem.name}: {n_bad} of {n} heights{' sampled' if step > 1 else ''} "
            f"({100 * n_bad / n:.3g} %) are impossible on Earth (outside {lo:g}..{hi:g} m, "
            f"or nonzero within {TINY_HEIGHT:g} m of 0; first {first[0]:.6g} at row "
            f"{first[1]}, column {first[2]})")
    if n_bad > n / 2:
        raise DemError(f"{what}: corrupt pixel data, an undeclared nodata value or heights "
                       "not in metres; export or copy it again")
    return f"{what}; they are read as voids"


def _check_georeference(dem: Dem):
    """Refuse a transform no point can be located with, and lon/lat that are not degrees
    (projected coordinates labelled EPSG:4326 would put the origin at latitude 3.8e6)."""
    t = dem.transform
    if not all(np.isfinite(t[:6])) or t.determinant == 0:
        raise DemError(f"{dem.name}: the geotransform {tuple(t[:6])} has a cell size of 0 "
                       "or is not finite: no cell can be located")
    if dem.crs is None or not dem.crs.is_geographic:
        return
    left, bottom, right, top = dem.bounds
    if bottom < -90.5 or top > 90.5 or left < -540.0 or right > 540.0:
        raise DemError(f"{dem.name}: its coordinates ({left:.6g}..{right:.6g}, {bottom:.6g}.."
                       f"{top:.6g}) are not degrees, as its CRS ({dem.crs.name}) says: "
                       "projected coordinates labelled lon/lat? Give the right CRS")


def _parse_crs(crs, path) -> CRS:
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:  # pyproj raises several types
        raise DemError(f"{path}: unknown CRS {crs!r}: {exc}") from exc


def _check_hgt(path: Path):
    """Reject .hgt files whose name or size is not an SRTM tile (GDAL's errors are vague)."""
    name = _HGT_NAME.match(path.name)
    if not name:
        raise DemError(f"{path}: SRTM .hgt name must give the SW corner, like N44E005.hgt")
    lat, lon = int(name[2]), int(name[4])
    if lat > 89 or lon > 179:
        raise DemError(f"{path}: {path.name} names a tile at latitude {lat}, longitude {lon}: "
                       "the SW corner must be within 89 deg of latitude, 179 of longitude")
    if name[6]:     # zipped: GDAL checks the size inside
        return
    size = path.stat().st_size
    if size in [2 * rows * cols for rows, cols in _HGT_SHAPES]:
        return
    raise DemError(f"{path}: {size} bytes is not an SRTM tile (expected {2 * 1201 ** 2} for "
                   f"3\" 1201x1201, {2 * 3601 ** 2} for 1\" 3601x3601 or {2 * 3601 * 1801} "
                   "for 1\" 3601x1801 at 50-60 deg): truncated?")


def _check_ascii_grid(path: Path):
    """Check that an ESRI ASCII grid holds the ``ncols x nrows`` numbers its header promises,
    before GDAL sees it: GDAL's AAIGrid driver allocates per promised row and, on a short
    file, searches for the missing values forever (100x100 with four values hung and grew
    to 24 GB, issue 22); and it reads a token that is not a number as 0 (``abc``) or as its
    numeric start (``1.2.3`` as 1.2), without a word. Any other file is left alone."""
    with open(path, "rb") as f:
        header = _ascii_grid_header(f)
        if not header:
            return
        try:
            ncols, nrows = int(header[b"ncols"]), int(header[b"nrows"])
        except (KeyError, ValueError):
            raise DemError(f"{path}: ESRI ASCII grid header needs integer ncols and nrows, "
                           f"got {header}") from None
        if ncols <= 0 or nrows <= 0:
            raise DemError(f"{path}: ESRI ASCII grid header gives {ncols} x {nrows} cells")
        _check_cell_size(path, header)
        promised = ncols * nrows
        # every value takes a character and a separator: a short file fails without a scan
        room = path.stat().st_size - f.tell()
        held = (_count_values(f, promised, lambda k, tok: _not_a_number(path, ncols, k, tok))
                if room >= 2 * promised - 1 else None)
    if held is None or held < promised:
        what = f"{held} values" if held is not None else f"only {room} bytes of values"
        raise DemError(f"{path}: truncated ESRI ASCII grid: the header promises {nrows} x "
                       f"{ncols} = {promised} values, the file holds {what}; export or copy "
                       "it again")


def _check_cell_size(path: Path, header: dict):
    """An ESRI ASCII grid's cellsize (or dx, dy) must be a number > 0: GDAL takes a negative
    one as a grid mirrored in both axes, a zero one as a grid no cell can be located in."""
    for key in (b"cellsize", b"dx", b"dy"):
        if key not in header:
            continue
        try:
            size = float(header[key])
        except ValueError:
            size = math.nan
        if not size > 0 or not math.isfinite(size):
            raise DemError(f"{path}: ESRI ASCII grid {key.decode()} is "
                           f"{header[key].decode(errors='replace')!r}: it must be a number "
                           "> 0 (the lower-left corner and the cell size place the grid)")


def _ascii_grid_header(f) -> dict:
    """The ``key value`` lines an ESRI ASCII grid starts with (empty if none); ``f`` is
    left at the first value."""
    header = {}
    while True:
        pos = f.tell()
        parts = f.readline(256).split()
        if len(parts) != 2 or parts[0].lower() not in _ASC_KEYS:
            f.seek(pos)
            return header
        header[parts[0].lower()] = parts[1]


def _count_values(f, enough: int, bad: Callable[[int, bytes], None]) -> int:
    """Whitespace-separated tokens from ``f``'s position, counted in chunks (stops at
    ``enough``): memory stays at one chunk whatever the file's size. ``bad(k, token)`` is
    called for the first of the ``enough`` tokens that is not a number (it should raise)."""
    count, tail = 0, b""
    while count < enough and (chunk := f.read(_CHUNK)):
        tokens = (tail + chunk).split()
        tail = tokens.pop() if tokens and not chunk[-1:].isspace() else b""
        _check_numbers(tokens[:enough - count], count, bad)
        count += len(tokens)
    if tail and count < enough:
        _check_numbers([tail], count, bad)
    return count + (1 if tail else 0)


def _check_numbers(tokens: list, first: int, bad: Callable[[int, bytes], None]):
    """Call ``bad(first + k, token)`` for the first token float() cannot read."""
    try:
        deque(map(float, tokens), maxlen=0)  # C-speed parse, nothing kept
    except ValueError:
        for k, token in enumerate(tokens):
            try:
                float(token)
            except ValueError:
                bad(first + k, token)
                return


def _not_a_number(path: Path, ncols: int, k: int, token: bytes):
    """Raise: value ``k`` (0-based, row-major) of an ESRI ASCII grid is not a number."""
    text = token[:20].decode("ascii", "backslashreplace") + ("..." if len(token) > 20 else "")
    raise DemError(f"{path}: ESRI ASCII grid value {k + 1} (row {k // ncols + 1}, column "
                   f"{k % ncols + 1}) is {text!r}, not a number: the file is corrupt; "
                   "export or copy it again")


def _open_gdal(path: Path, crs_given: bool = False) -> Dem:
    try:
        ds = rasterio.open(path)
    except RasterioIOError as exc:
        raise DemError(f"{path}: not a readable DEM (wrong or corrupt header?): {exc}") from exc
    try:
        if ds.count < 1:
            raise DemError(f"{path}: raster has no bands")
        if ds.transform == Affine.identity() and not ds.crs:
            raise DemError(f"{path}: raster has no georeference (no geotransform)")
        crs, guessed = (None, False) if crs_given else _dataset_crs(ds, path)
        nodata = ds.nodata
        if ds.driver == "SRTMHGT" and nodata is None:
            nodata = float(SRTM_VOID)
        scale, offset = _height_scaling(ds, path)
        masked = _has_mask(ds)
        plain = (scale, offset) == (1.0, 0.0) and not masked
        array = _memmap_if_possible(ds, path) if plain else None
    except BaseException:
        ds.close()
        raise
    if array is not None:
        dem = Dem.from_array(array, ds.transform, crs, nodata, str(path), guessed)
        ds.close()
        return dem

    lock = threading.Lock()  # a GDAL dataset handle must not be used by two threads at once

    def read(r0, r1, c0, c1):
        window = Window(c0, r0, c1 - c0, r1 - r0)
        with lock:
            block = ds.read(1, window=window)
            valid = ds.read_masks(1, window=window) if masked else None
        z = _to_float(block, nodata)
        if not plain:
            z *= np.float32(scale)
            z += np.float32(offset)
        if valid is not None:
            z[valid == 0] = np.nan
        return z

    return Dem(str(path), ds.transform, ds.width, ds.height, crs, np.dtype(ds.dtypes[0]),
               nodata, read, guessed, ds.close)


def _height_scaling(ds, path: Path) -> tuple[float, float]:
    """(scale, offset) from stored values to metres: the band's scale and offset (packed
    products: int16 with an offset, decimetres in int32), times the metres per height unit
    the band or the CRS's vertical axis gives (US lidar DEMs store feet)."""
    scale = ds.scales[0] if ds.scales and ds.scales[0] is not None else 1.0
    offset = ds.offsets[0] if ds.offsets and ds.offsets[0] is not None else 0.0
    if not (math.isfinite(scale) and math.isfinite(offset)) or scale == 0:
        raise DemError(f"{path}: band scale {scale} and offset {offset}: no heights follow")
    metres = _metres_per_height_unit(ds, path)
    return scale * metres, offset * metres


def _metres_per_height_unit(ds, path: Path) -> float:
    unit = (ds.units[0] or "").strip() if ds.units else ""
    if not unit:
        return _vertical_crs_unit(ds.crs)
    name = unit.lower().replace("_", " ").replace("-", " ")
    if name in ("m", "metre", "meter", "metres", "meters", "metre (m)", "meters (m)"):
        return 1.0
    if any(word in name.split() for word in ("ft", "foot", "feet", "ftus", "us")):
        return _US_SURVEY_FOOT if ("us" in name.split() or "survey" in name
                                   or "ftus" in name) else _FOOT
    raise DemError(f"{path}: its heights are in {unit!r}: give a DEM in metres or feet")


def _vertical_crs_unit(crs) -> float:
    """Metres per unit of a compound CRS's vertical axis (1 without one)."""
    if not crs:
        return 1.0
    try:
        crs = CRS.from_wkt(crs.to_wkt())
    except Exception:     # an unparsable CRS is _dataset_crs's to refuse
        return 1.0
    vertical = [c for c in crs.sub_crs_list if c.is_vertical]
    return float(vertical[0].axis_info[0].unit_conversion_factor) if vertical else 1.0


def _has_mask(ds) -> bool:
    """True when band 1 has a GDAL mask of its own (internal, .msk, alpha), not nodata's."""
    flags = ds.mask_flag_enums[0]
    return MaskFlags.per_dataset in flags or MaskFlags.alpha in flags


def _dataset_crs(ds, path: Path):
    """(crs, guessed) for a rasterio dataset, applying the ESRI-grid header rule. A local
    (engineering) CRS in metres is local metres; any other CRS must relate to lon/lat."""
    if ds.crs:
        try:
            crs = CRS.from_wkt(ds.crs.to_wkt())
        except Exception as exc:
            raise DemError(f"{path}: unknown CRS in file: {exc}") from exc
        if crs.type_name == "Engineering CRS":
            if all(a.unit_name in ("metre", "meter") for a in crs.axis_info):
                return None, False
            raise DemError(f"{path}: a local CRS ({crs.name}) not in metres")
        try:
            Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True)
        except ProjError as exc:
            raise DemError(f"{path}: its CRS ({crs.name}) cannot be related to longitude "
                           f"and latitude: {exc}") from exc
        return crs, False
    prj = path.with_suffix(".prj")
    if prj.exists():
        raise DemError(f"{path}: unknown CRS: GDAL cannot parse {prj.name}")
    if ds.driver != "AAIGrid":
        raise DemError(f"{path}: unknown CRS: the file stores none (pass crs=...)")
    left, bottom, right, top = ds.bounds
    cell = max(abs(ds.transform.a), abs(ds.transform.e))
    lonlat = (cell < 0.1 and -180.0 <= left < right <= 360.0 and -90.0 <= bottom < top <= 90.0)
    return (CRS.from_epsg(4326) if lonlat else None), True


def _memmap_if_possible(ds, path: Path):
    """np.memmap over an uncompressed, single-band, contiguous-strip raster, else None."""
    if ds.count != 1 or ds.driver not in ("GTiff", "SRTMHGT"):
        return None
    h, w, dtype = ds.height, ds.width, np.dtype(ds.dtypes[0])
    if ds.driver == "SRTMHGT":     # a plain tile only, not one GDAL reads inside a .zip
        if path.suffix.lower() != ".hgt" or path.stat().st_size != 2 * h * w:
            return None
        return np.memmap(path, dtype=">i2", mode="r", shape=(h, w))
    if ds.compression is not None or ds.profile.get("tiled") or dtype.kind not in "iuf" or \
            ds.tags(1, ns="IMAGE_STRUCTURE").get("NBITS"):  # packed sub-byte samples
        return None
    rows_per_strip = ds.block_shapes[0][0]
    nstrips = -(-h // rows_per_strip)
    try:
        first = int(ds.get_tag_item("BLOCK_OFFSET_0_0", "TIFF", bidx=1))
        last = int(ds.get_tag_item(f"BLOCK_OFFSET_0_{nstrips - 1}", "TIFF", bidx=1))
    except (TypeError, ValueError):
        return None
    if last - first != (nstrips - 1) * rows_per_strip * w * dtype.itemsize:
        return None
    if first + h * w * dtype.itemsize > path.stat().st_size:
        raise DemError(f"{path}: truncated data: the file ends before its last row")
    with open(path, "rb") as f:
        order = f.read(2)
    dtype = dtype.newbyteorder("<" if order == b"II" else ">")
    return np.memmap(path, dtype=dtype, mode="r", offset=first, shape=(h, w))


def _open_npz(path: Path, name=None) -> Dem:
    """matplotlib sample-DEM layout: elevation + dx, dy, xmin, xmax, ymin, ymax (degrees)."""
    name = name or str(path)
    try:
        with np.load(path) as z:
            elevation = z["elevation"]
            dx, dy = float(z["dx"]), float(z["dy"])
            xmin, xmax = float(z["xmin"]), float(z["xmax"])
            north = max(float(z["ymin"]), float(z["ymax"]))
            south = min(float(z["ymin"]), float(z["ymax"]))
    except (OSError, KeyError, ValueError) as exc:
        raise DemError(f"{name}: not a DEM .npz (needs elevation, dx, dy, xmin, xmax, ymin, "
                       f"ymax): {exc}") from exc
    rows, cols = elevation.shape
    if not (np.isclose(cols * dx, xmax - xmin, rtol=1e-3)
            and np.isclose(rows * dy, north - south, rtol=1e-3)):
        raise DemError(f"{name}: extent does not match {rows}x{cols} cells of {dx}x{dy}")
    return Dem.from_array(elevation, Affine(dx, 0, xmin, 0, -dy, north), CRS.from_epsg(4326),
                          None, name)


def sample_dem() -> Dem:
    """The embedded default DEM: matplotlib's ``jacksboro_fault_dem.npz`` (see module notes)."""
    from matplotlib import cbook

    path = cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False)
    return _open_npz(Path(path), f"matplotlib:jacksboro_fault_dem.npz ({path})")


# -- mosaics ----------------------------------------------------------------------------
def mosaic(dems, name: str | None = None) -> Dem:
    """One lazy DEM over adjacent, grid-aligned tiles (e.g. neighbouring SRTM tiles).

    Tiles must share CRS, cell size and grid phase; overlapping cells (SRTM tiles repeat
    their shared edge) come from the first tile holding valid data there.

    Parameters
    ----------
    dems : sequence of Dem
    name : str, optional

    Raises
    ------
    DemError
        Different CRSs, cell sizes, rotated grids, or misaligned grids.
    """
    dems = list(dems)
    if not dems:
        raise DemError("mosaic: no tiles")
    name = name or "mosaic(" + ", ".join(d.name for d in dems) + ")"
    ref = dems[0]
    for d in dems:
        if not d.is_north_up:
            raise DemError(f"{d.name}: mosaic needs north-up grids")
        if (d.crs is None) != (ref.crs is None) or (d.crs is not None and d.crs != ref.crs):
            raise DemError(f"{d.name}: CRS differs from {ref.name}")
        if not np.allclose(d.res, ref.res, rtol=1e-9, atol=0):
            raise DemError(f"{d.name}: cell size {d.res} differs from {ref.res} ({ref.name})")
    dx, dy = ref.res
    offsets = []
    for d in dems:
        oc, orow = (d.transform.c - ref.transform.c) / dx, (ref.transform.f - d.transform.f) / dy
        if abs(oc - round(oc)) > 1e-3 or abs(orow - round(orow)) > 1e-3:
            raise DemError(f"{d.name}: grid is not aligned with {ref.name}")
        offsets.append((round(orow), round(oc)))
    r_min = min(o[0] for o in offsets)
    c_min = min(o[1] for o in offsets)
    offsets = [(r - r_min, c - c_min) for r, c in offsets]
    height = max(o[0] + d.height for o, d in zip(offsets, dems, strict=True))
    width = max(o[1] + d.width for o, d in zip(offsets, dems, strict=True))
    transform = ref.transform @ Affine.translation(c_min, r_min)

    def read(r0, r1, c0, c1):
        out = np.full((r1 - r0, c1 - c0), np.nan, dtype=np.float32)
        for (orow, ocol), d in zip(offsets, dems, strict=True):
            a0, a1 = max(r0, orow), min(r1, orow + d.height)
            b0, b1 = max(c0, ocol), min(c1, ocol + d.width)
            if a1 <= a0 or b1 <= b0:
                continue
            dst = out[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
            block = d.read_window(a0 - orow, b0 - ocol, a1 - a0, b1 - b0)
            np.copyto(dst, block, where=np.isnan(dst))
        return out

    def close():
        for d in dems:
            d.close()

    return Dem(name, transform, width, height, ref.crs, np.dtype(np.float32), None, read,
               ref.crs_guessed, close)


# -- voids ------------------------------------------------------------------------------
def fill_voids(z, max_area: int = 256, fill_border: bool = False, radius: int = 3):
    """Fill small voids (NaN) by inpainting from their rims; report the large ones.

    Each connected void (8-connectivity) of at most ``max_area`` cells is filled with OpenCV's
    Navier-Stokes inpainting (``cv2.INPAINT_NS``), which propagates the surrounding surface
    smoothly inwards; on SRTM holes its error is within a few percent of linear interpolation
    over the rim, at a tenth of the cost. Voids touching the raster edge are treated as outside
    the survey (e.g. a clipped catchment) and never filled unless ``fill_border``.

    Parameters
    ----------
    z : ndarray, shape (rows, cols)
        Elevations with NaN voids.
    max_area : int
        Largest void (cells) that is filled.
    fill_border : bool
        Also fill small voids that touch the raster edge.
    radius : int
        Inpainting neighbourhood radius (cells).

    Returns
    -------
    filled : ndarray of float32
        Copy of ``z`` with small voids filled.
    large : ndarray of bool
        Cells still void (large or edge voids).
    """
    z = np.asarray(z, dtype=np.float32)
    void = np.isnan(z)
    if not void.any() or void.all():
        return z.copy(), void
    labels, n = ndi.label(void, structure=np.ones((3, 3), bool))
    areas = np.bincount(labels.ravel(), minlength=n + 1)
    small = areas <= max_area
    small[0] = False
    if not fill_border:
        edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        small[edge] = False
    target = small[labels]
    if not target.any():
        return z.copy(), void
    # inpainting reads every unmasked cell: give the large voids their nearest valid value
    # (then NaN again) so they neither leak NaN nor count as data beyond their edge
    idx = ndi.distance_transform_edt(void, return_distances=False, return_indices=True)
    filled = cv2.inpaint(z[tuple(idx)], target.astype(np.uint8), radius, cv2.INPAINT_NS)
    large = void & ~target
    filled[large] = np.nan
    return filled, large


def dem_files(paths) -> list[str]:
    """Expand a list of files/directories/globs into DEM file paths (sorted, unique)."""
    out = []
    for p in paths:
        p = os.fspath(p)
        if os.path.isdir(p):
            out += [str(q) for q in Path(p).iterdir()
                    if q.suffix.lower() in (".asc", ".tif", ".tiff", ".hgt", ".npz")
                    or q.name.lower().endswith(".hgt.zip")]
        elif any(ch in p for ch in "*?["):
            out += glob.glob(p)
        else:
            out.append(p)
    return sorted(set(out))
