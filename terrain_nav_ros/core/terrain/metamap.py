"""The metamap: north-up local-ENU elevation tiles sampled from DEMs (dissertation 2.1).

:class:`MetaMap` is what the ``metamap`` tile-server node calls. Given DEMs (any CRS) and the
mission :class:`~.geodesy.EnuOrigin`, :meth:`MetaMap.tile` returns the elevations on a
:class:`~.georef.GeoReference` grid (north-up, ENU metres, any GSD and size) with a nodata mask.

How a tile is sampled, per DEM:

1. ENU -> DEM CRS is exact (pyproj) on a coarse control grid of tile pixels (every
   ``control_step`` px) and bilinearly interpolated in between (one ``cv2.resize``). The map
   is smooth (projection scale and meridian convergence vary slowly): against per-pixel exact
   transforms the sample positions differ by <= 2e-4 cell for a 1024^2 tile at 8.5 m and
   <= 1e-3 cell for a 61 km tile (float32). Rotation by meridian convergence is kept.
2. Only the DEM window under the tile footprint is read (memory-mapped where possible), then
   ``cv2.remap`` samples it (bilinear by default). OpenCV quantises sample positions to 1/32
   cell, the dominant position error (<= 1/64 cell, 0.15 m on a 10 m grid). Voids are handled
   by normalised convolution (:func:`remap_masked`). Coarser-than-native requests are first
   box-averaged by the integer part of the scale to avoid aliasing.
3. Several DEMs: aligned tiles of one CRS become one :func:`~.dem_io.mosaic` (no seams); the
   rest fill the remaining NaN cells in the order given.

Longitudes: geographic DEMs are placed within half a turn of the origin's longitude, where the
ENU -> CRS transform puts its samples (:meth:`~.geodesy.CrsEnuTransform.wrap_x`), so a DEM
across the antimeridian (179.5..180.5, -180.5..-179.5 or tiles either side) is sampled as one
continuous grid; a DEM reaching more than half a turn from the origin (a global one) is also
placed one turn over, so it covers both sides of the antimeridian too.

Horizontal placement: a tile pixel (e, n) is taken at the ENU point on the surface of constant
ellipsoidal height ``reference_height`` (default: the origin's), not on the tangent plane. For
terrain at another height the true ENU position differs by ``dh * d / R`` (0.16 m per 100 m of
height difference at 10 km from the origin), far below DEM accuracy.

Heights: ``heights="orthometric"`` (default) returns the DEM's own values, metres above the
geoid (EGM96 for SRTM, NAVD88 for USGS), what a barometric altimeter and most maps use.
``heights="enu"`` returns the ENU ``u`` coordinate of the terrain point (ellipsoidal height
``H + N`` with the origin's constant geoid undulation, minus the Earth's curvature drop),
for 3-D work in the ``map`` frame.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace

import cv2
import numpy as np
from affine import Affine
from scipy import ndimage as ndi

from .dem_io import Dem, DemError, fill_voids, mosaic
from .geodesy import CrsEnuTransform, EnuOrigin, LocalEnuTransform
from .georef import GeoReference
from .interpolation import idw_grid

__all__ = ["DemTile", "MetaMap", "OutsideDemError", "remap_masked"]

_REMAP = {"nearest": cv2.INTER_NEAREST, "bilinear": cv2.INTER_LINEAR,
          "bicubic": cv2.INTER_CUBIC}
_PAD = {"nearest": 1, "bilinear": 2, "bicubic": 3, "spline": 4, "idw": 3}


class OutsideDemError(DemError):
    """The requested tile does not overlap any loaded DEM."""


@dataclass(frozen=True)
class DemTile:
    """Elevations on a north-up ENU grid.

    Attributes
    ----------
    elevation : ndarray of float32, shape ``georef.shape``
        Heights in metres (see ``heights``); NaN where ``nodata``.
    nodata : ndarray of bool
        True where no DEM value is available (outside coverage or large void).
    georef : GeoReference
        Where the grid lies in the mission ENU frame.
    heights : str
        ``"orthometric"`` (metres above the DEM's geoid) or ``"enu"`` (ENU up).
    """

    elevation: np.ndarray
    nodata: np.ndarray
    georef: GeoReference
    heights: str = "orthometric"

    @property
    def valid_fraction(self) -> float:
        """Share of cells holding data."""
        return float(1.0 - self.nodata.mean()) if self.nodata.size else 0.0


def _control_nodes(n: int, step: int) -> np.ndarray:
    """Pixel positions of control nodes: cell centres of ``step``-pixel blocks, one extra
    block beyond each end, so that ``cv2.resize`` by ``step`` interpolates them linearly at
    every pixel (its sample-centre convention) and the crop never reaches the clamped border."""
    return (np.arange(-1, -(-n // step) + 1) + 0.5) * step - 0.5


def _expand(ctrl: np.ndarray, step: int, h: int, w: int) -> np.ndarray:
    """Bilinear expansion of a control grid (see :func:`_control_nodes`) to h x w float32.

    ``ctrl`` may have a trailing channel axis (up to 4 channels)."""
    big = cv2.resize(ctrl.astype(np.float32), (ctrl.shape[1] * step, ctrl.shape[0] * step),
                     interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(big[step:step + h, step:step + w])


class _Layer:
    """One DEM (or aligned mosaic) with its ENU transform."""

    def __init__(self, dem: Dem, transform):
        self.dem = dem
        self.transform = transform
        # metres per cell near the DEM centre, for IDW distances and native GSD
        cx, cy = dem.pixel_to_crs([dem.width / 2, dem.width / 2 + 1, dem.width / 2],
                                  [dem.height / 2, dem.height / 2, dem.height / 2 + 1])
        e, n, _ = transform.to_enu(cx, cy)
        self.cell_m = (float(np.hypot(e[1] - e[0], n[1] - n[0])),
                       float(np.hypot(e[2] - e[0], n[2] - n[0])))
        left, bottom, right, top = dem.bounds
        t = np.linspace(0.0, 1.0, 33)
        bx = np.r_[left + t * (right - left), np.full(33, right), right - t * (right - left),
                   np.full(33, left)]
        by = np.r_[np.full(33, bottom), bottom + t * (top - bottom), np.full(33, top),
                   top - t * (top - bottom)]
        be, bn, _ = transform.to_enu(bx, by)
        self.enu_bounds = (float(be.min()), float(be.max()), float(bn.min()), float(bn.max()))


class MetaMap:
    """Elevation tiles on north-up ENU grids from one or more DEMs.

    Parameters
    ----------
    dems : Dem or sequence of Dem
        Elevation sources, highest priority first.
    origin : EnuOrigin, optional
        Mission origin. Default: the first DEM's centre at ellipsoidal height 0.
    interpolation : {"bilinear", "bicubic", "spline", "nearest", "idw"}
        How cells are sampled between DEM posts. ``bicubic`` is OpenCV's (a = -0.75: sharp and
        fast, but it bends sloping planes by up to ~5 % of the per-cell slope); ``spline`` is
        the exact cubic B-spline (``scipy.ndimage.map_coordinates``, order 3), several times
        slower; ``idw`` uses :func:`~.interpolation.idw_grid` (slowest).
    fill_voids : bool
        Fill voids of at most ``max_void_area`` cells (:func:`~.dem_io.fill_voids`) before
        sampling: DEMs up to ``prefill_max_cells`` once, whole, at construction; bigger ones
        in each read window (voids cut by the window edge then stay void).
    max_void_area : int
        Largest void (DEM cells) that is filled.
    idw_power, idw_k : float, int
        IDW exponent and neighbourhood when ``interpolation="idw"``.
    heights : {"orthometric", "enu"}
        What tile values mean (see module notes). DEMs in local metres always give their
        stored heights.
    reference_height : float, optional
        Orthometric height (m) of the surface on which tile pixels are placed. Default the
        origin's (``origin.alt - origin.geoid_undulation``).
    local_origin : (x0, y0), optional
        For DEMs in unreferenced local metres: the DEM coordinate of the ENU origin
        (default the first such DEM's centre).
    control_step : int
        Spacing (tile pixels) of the exact-transform control grid.
    max_window_cells : int
        Refuse requests needing a larger DEM window (coarse GSD over a huge area).
    prefill_max_cells : int
        With ``fill_voids``, DEMs up to this many cells are filled once, whole, at
        construction (in memory); larger ones are filled per read window.

    Notes
    -----
    :meth:`tile` is serialised by a lock, so one instance can serve several executor threads.
    """

    def __init__(self, dems, origin: EnuOrigin | None = None, *, interpolation="bilinear",
                 fill_voids=False, max_void_area=256, idw_power=2.0, idw_k=8,
                 heights="orthometric", reference_height=None, local_origin=None,
                 control_step=32, max_window_cells=64_000_000, prefill_max_cells=16_000_000):
        dems = [dems] if isinstance(dems, Dem) else list(dems)
        if not dems:
            raise DemError("MetaMap: no DEM given")
        if interpolation not in _PAD:
            raise ValueError(f"MetaMap: unknown interpolation {interpolation!r}; "
                             f"use one of {tuple(_PAD)}")
        if heights not in ("orthometric", "enu"):
            raise ValueError(f"MetaMap: heights must be 'orthometric' or 'enu', not {heights!r}")
        local = [d for d in dems if d.local_metres]
        if local and len(local) != len(dems):
            raise DemError("MetaMap: cannot mix DEMs in local metres with georeferenced ones")
        if origin is None:
            origin = self._default_origin(dems[0])
        self.origin = origin
        self.interpolation = interpolation
        self.fill_voids = bool(fill_voids)
        self.max_void_area = int(max_void_area)
        self.idw_power, self.idw_k = float(idw_power), int(idw_k)
        self.heights = heights
        self.reference_height = (origin.alt - origin.geoid_undulation
                                 if reference_height is None else float(reference_height))
        self.control_step = max(int(control_step), 2)
        self.max_window_cells = int(max_window_cells)
        if local:
            if local_origin is None:
                left, bottom, right, top = dems[0].bounds
                local_origin = (0.5 * (left + right), 0.5 * (bottom + top))
            self.local_origin = tuple(map(float, local_origin))
        else:
            self.local_origin = None
        merged = _merge_aligned([p for d in dems for p in self._in_origin_branch(d)])
        # small DEMs are void-filled once, whole (consistent across tiles, and no per-tile
        # cost); big ones window by window
        self._window_fill = []
        for i, d in enumerate(merged):
            small = d.width * d.height <= prefill_max_cells
            if self.fill_voids and small:
                merged[i] = d.filled(self.max_void_area)
            self._window_fill.append(self.fill_voids and not small)
        self.layers = [_Layer(d, self._transform_for(d)) for d in merged]
        self._lock = threading.Lock()  # GDAL handles and PROJ contexts are not thread-safe

    @staticmethod
    def _default_origin(dem: Dem) -> EnuOrigin:
        if dem.local_metres:
            return EnuOrigin(0.0, 0.0, 0.0)
        from pyproj import Transformer

        left, bottom, right, top = dem.bounds
        to_geo = Transformer.from_crs(dem.crs, "EPSG:4326", always_xy=True)
        lon, lat = to_geo.transform(0.5 * (left + right), 0.5 * (bottom + top))
        return EnuOrigin(lat, lon, 0.0)

    def _transform_for(self, dem: Dem):
        if dem.local_metres:
            return LocalEnuTransform(*self.local_origin, self.origin)
        try:
            return CrsEnuTransform(dem.crs, self.origin)
        except ValueError as exc:
            raise DemError(f"{dem.name}: {exc}") from exc

    def _in_origin_branch(self, dem: Dem) -> list[Dem]:
        """``dem`` with its longitudes in the branch :meth:`CrsEnuTransform.from_enu` samples
        (within half a turn of the origin), so a DEM across the antimeridian, or tiles either
        side of it, are one continuous grid; plus a copy one turn over for the part of a DEM
        (a global one) that reaches past half a turn from the origin."""
        t = None if dem.local_metres else self._transform_for(dem)
        if t is None or t.period is None:
            return [dem]
        left, _, right, _ = dem.bounds
        centre = 0.5 * (left + right)
        shift = t.period * round(float(t.wrap_x(centre) - centre) / t.period)
        out = [_shifted(dem, shift)]
        if left + shift < t.x_origin - 0.5 * t.period:
            out.append(_shifted(dem, shift + t.period))
        if right + shift > t.x_origin + 0.5 * t.period:
            out.append(_shifted(dem, shift - t.period))
        return out

    # -- coverage ---------------------------------------------------------------------
    @property
    def enu_bounds(self) -> list[tuple[float, float, float, float]]:
        """ENU (west, east, south, north) bounding box of each DEM layer."""
        return [layer.enu_bounds for layer in self.layers]

    @property
    def native_gsd(self) -> float:
        """Finest cell size (m) of the first DEM near its centre (min of east/north sizes)."""
        return min(self.layers[0].cell_m)

    def covers(self, east, north) -> np.ndarray:
        """Which ENU points lie on some DEM's footprint (its outer cell edges).

        The footprint, not the data: a void inside a DEM counts as covered. Points are placed
        at ``reference_height``, as tile pixels are.

        Parameters
        ----------
        east, north : array_like
            ENU horizontal coordinates (m), broadcast together.

        Returns
        -------
        ndarray of bool
        """
        east, north = np.broadcast_arrays(np.asarray(east, float), np.asarray(north, float))
        inside = np.zeros(east.shape, bool)
        for layer in self.layers:
            x, y = layer.transform.from_enu(east, north, self.reference_height)
            col, row = layer.dem.crs_to_pixel(x, y)
            with np.errstate(invalid="ignore"):
                inside |= ((col >= -0.5) & (col <= layer.dem.width - 0.5)
                           & (row >= -0.5) & (row <= layer.dem.height - 0.5))
        return inside

    # -- tiles --------------------------------------------------------------------------
    def tile_at(self, east: float, north: float, gsd: float, width: int, height: int) -> DemTile:
        """Tile of ``width x height`` cells of ``gsd`` metres centred on ENU (east, north)."""
        return self.tile(GeoReference.centred(east, north, gsd, width, height))

    def tile_at_geodetic(self, lat: float, lon: float, gsd: float, width: int,
                         height: int) -> DemTile:
        """Tile centred on a WGS84 position (degrees), placed at ``reference_height``."""
        if self.local_origin is not None:
            raise DemError("MetaMap: DEMs in local metres have no geodetic position")
        h = self.origin.orthometric_to_ellipsoidal(self.reference_height)
        e, n, _ = self.origin.geodetic_to_enu(lat, lon, h)
        return self.tile_at(float(e), float(n), gsd, width, height)

    def tile(self, georef: GeoReference) -> DemTile:
        """Sample the DEMs on ``georef`` (thread-safe).

        Raises
        ------
        OutsideDemError
            The tile footprint overlaps no DEM. Partial overlap is not an error: the cells
            outside are flagged in ``DemTile.nodata``.
        DemError
            A DEM window cannot be read, or the request needs an unreasonably large window.
        """
        with self._lock:
            return self._tile(georef)

    def _tile(self, georef: GeoReference) -> DemTile:
        h, w = georef.shape
        if h == 0 or w == 0:
            return DemTile(np.zeros((h, w), np.float32), np.ones((h, w), bool), georef,
                           self.heights)
        out = None
        rn, cn = _control_nodes(h, self.control_step), _control_nodes(w, self.control_step)
        ne, nn = georef.pixel_to_enu(cn[None, :], rn[:, None])
        ne, nn = np.broadcast_arrays(ne, nn)
        west, east_edge, south, north_edge = georef.extent
        hit = False
        for layer, window_fill in zip(self.layers, self._window_fill, strict=True):
            lw, le, ls, ln = layer.enu_bounds
            if le <= west or lw >= east_edge or ln <= south or ls >= north_edge:
                continue
            hit = True
            z = self._sample_layer(layer, ne, nn, h, w, window_fill)
            if z is None:
                continue
            if out is None:
                out = z
            else:
                np.copyto(out, z, where=np.isnan(out))
            nodata = np.isnan(out)
            if not nodata.any():
                break
        if not hit:
            raise OutsideDemError(
                f"tile centred at ENU ({georef.centre[0]:.1f}, {georef.centre[1]:.1f}) m, "
                f"{w}x{h} px at {georef.gsd} m/px, is outside every loaded DEM "
                f"(ENU bounds {[tuple(round(v) for v in b) for b in self.enu_bounds]})")
        if out is None:
            out, nodata = np.full((h, w), np.nan, dtype=np.float32), np.ones((h, w), bool)
        if self.heights == "enu" and self.local_origin is None:
            # u = ellipsoidal height above the origin + the curvature drop of that surface
            east, north = georef.pixel_to_enu(np.arange(w), np.arange(h))
            out += self.origin.surface_up_grid(east, north)
            out += np.float32(self.origin.geoid_undulation - self.origin.alt)
        return DemTile(out, nodata, georef, self.heights)

    def _sample_layer(self, layer: _Layer, ne, nn, h: int, w: int, window_fill: bool):
        dem = layer.dem
        x, y = layer.transform.from_enu(ne, nn, self.reference_height)
        cols, rows = dem.crs_to_pixel(x, y)
        if not (np.isfinite(cols).all() and np.isfinite(rows).all()):
            return None  # tile reaches where the DEM's CRS is undefined
        # DEM cells per tile pixel along tile rows / columns: box-average first when the tile
        # is much coarser than the DEM, so coarse tiles are not aliased
        step = self.control_step
        span_c, span_r = step * (cols.shape[1] - 1), step * (cols.shape[0] - 1)
        kx = int(np.hypot(cols[0, -1] - cols[0, 0], rows[0, -1] - rows[0, 0]) / span_c)
        ky = int(np.hypot(cols[-1, 0] - cols[0, 0], rows[-1, 0] - rows[0, 0]) / span_r)
        kx, ky = (max(kx, 1), max(ky, 1)) if self.interpolation != "nearest" else (1, 1)
        pad = _PAD[self.interpolation]
        c0, c1 = _span(cols, pad * kx, dem.width)
        r0, r1 = _span(rows, pad * ky, dem.height)
        if c1 <= c0 or r1 <= r0:
            return None
        # start the averaging blocks where the first tile pixel's footprint starts
        f = 0.5 + 0.5 / step  # tile pixel (0, 0) in control-node units
        wts = np.array([[(1 - f) * (1 - f), (1 - f) * f], [f * (1 - f), f * f]])
        col00, row00 = (wts * cols[:2, :2]).sum(), (wts * rows[:2, :2]).sum()
        c0 -= (c0 - round(col00 + 0.5 - kx / 2)) % kx
        r0 -= (r0 - round(row00 + 0.5 - ky / 2)) % ky
        if (c1 - c0) * (r1 - r0) > self.max_window_cells:
            raise DemError(f"{dem.name}: request needs a {r1 - r0}x{c1 - c0} cell window; "
                           f"use a finer GSD or a pre-decimated DEM")
        if window_fill:
            margin = int(np.ceil(np.sqrt(self.max_void_area)))
            big = dem.read_window(r0 - margin, c0 - margin, r1 - r0 + 2 * margin,
                                  c1 - c0 + 2 * margin)
            if np.isnan(big).any():
                big = fill_voids(big, self.max_void_area)[0]
            window = big[margin:-margin, margin:-margin]
        else:
            window = dem.read_window(r0, c0, r1 - r0, c1 - c0)
        if kx > 1 or ky > 1:
            hh, ww = window.shape[0] // ky, window.shape[1] // kx
            window = cv2.resize(window[:hh * ky, :ww * kx], (ww, hh),
                                interpolation=cv2.INTER_AREA)
        # bilinear expansion of the control grid: relative float32 maps (1e-4 px precision)
        cols = (cols - c0 + 0.5) / kx - 0.5
        rows = (rows - r0 + 0.5) / ky - 0.5
        # one 2-channel map (x, y): a single resize and copy, and cv2.remap takes it as is
        maps = _expand(np.dstack([cols, rows]), step, h, w)
        map_x, map_y = maps[..., 0], maps[..., 1]
        if self.interpolation == "idw":
            aspect = (layer.cell_m[0] * kx) / (layer.cell_m[1] * ky)
            return idw_grid(window, map_x, map_y, power=self.idw_power, k=self.idw_k,
                            aspect=aspect)
        if self.interpolation == "spline":
            return _spline_sample(window, maps)
        return remap_masked(window, maps, None, self.interpolation)


def _spline_sample(z, maps) -> np.ndarray:
    """Cubic B-spline samples; voids filled by nearest for the fit, then masked as bilinear."""
    map_x, map_y = maps[..., 0], maps[..., 1]
    holes = np.isnan(z)
    mask = np.isnan(remap_masked(z, maps, None, "bilinear")) if holes.any() else None
    if holes.any():
        if holes.all():
            return np.full(map_x.shape, np.nan, np.float32)
        idx = ndi.distance_transform_edt(holes, return_distances=False, return_indices=True)
        z = z[tuple(idx)]
    out = ndi.map_coordinates(z, [map_y, map_x], order=3, mode="nearest", output=np.float32)
    outside = (map_x < -0.5) | (map_y < -0.5) | (map_x > z.shape[1] - 0.5) | (
        map_y > z.shape[0] - 0.5)
    out[outside] = np.nan
    if mask is not None:
        out[mask] = np.nan
    return out


def _span(coords, pad: int, n: int) -> tuple[int, int]:
    """Window [start, stop) of DEM cells covering ``coords`` plus ``pad``, clipped near 0..n."""
    lo = max(int(np.floor(coords.min())) - pad, -pad)
    hi = min(int(np.ceil(coords.max())) + pad + 1, n + pad)
    return lo, hi


def remap_masked(z, map_x, map_y=None, interpolation: str = "bilinear") -> np.ndarray:
    """``cv2.remap`` of a raster with NaN holes, NaN-aware.

    Plain remap turns a sample NaN as soon as any neighbour is NaN, even with weight 0. Here
    bilinear is normalised over the valid neighbours (normalised convolution) and kept where
    they carry at least half the weight, i.e. within half a cell of data; bicubic is used
    where its whole 4 x 4 support is valid and falls back to that bilinear value elsewhere.
    Outside ``z`` is NaN.

    Parameters
    ----------
    z : ndarray of float32, shape (rows, cols)
    map_x, map_y : ndarray of float32
        Sample positions in ``z`` pixel coordinates (integers are cell centres); or ``map_x``
        of shape (h, w, 2) holding (x, y) and ``map_y=None``.
    interpolation : {"nearest", "bilinear", "bicubic"}
    """
    kind = _REMAP[interpolation]
    nan = float("nan")
    # OpenCV (4.x Python bindings) misreads strided map views: always pass contiguous maps
    map_x = np.ascontiguousarray(map_x)
    map_y = None if map_y is None else np.ascontiguousarray(map_y)
    width = map_x.shape[1]
    if interpolation == "bicubic" and 0 < width < 8:
        # OpenCV's bicubic remap answers NaN everywhere for maps under 8 px wide with a NaN
        # border value (a coarse DEM's route box in simulate): sample 8 columns, keep ours
        def widen(m):
            return None if m is None else np.pad(
                m, ((0, 0), (0, 8 - width)) + ((0, 0),) * (m.ndim - 2), mode="edge")
        return remap_masked(z, widen(map_x), widen(map_y), interpolation)[:, :width]
    holes = np.isnan(z)
    if interpolation == "nearest" or not holes.any():
        return cv2.remap(z, map_x, map_y, kind, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=nan)
    z0 = np.where(holes, np.float32(0), z)
    valid = (~holes).astype(np.float32)
    args = dict(borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    num = cv2.remap(z0, map_x, map_y, cv2.INTER_LINEAR, **args)
    den = cv2.remap(valid, map_x, map_y, cv2.INTER_LINEAR, **args)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den >= 0.5 - 1e-6, num / den, np.float32(nan)).astype(np.float32)
    if interpolation == "bicubic":
        # the 4 x 4 support of a sample lies within 2 cells of its nearest cell
        support = cv2.erode(valid, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT,
                            borderValue=0)
        ok = cv2.remap(support, map_x, map_y, cv2.INTER_NEAREST, **args) > 0.5
        cubic = cv2.remap(z0, map_x, map_y, cv2.INTER_CUBIC, **args)
        out = np.where(ok, cubic, out)
    return out


def _shifted(dem: Dem, dx: float) -> Dem:
    """``dem`` (same pixels, no copy) with its x coordinates moved by ``dx``."""
    if dx == 0:
        return dem
    return replace(dem, transform=Affine.translation(dx, 0.0) @ dem.transform)


def _merge_aligned(dems: list[Dem]) -> list[Dem]:
    """Combine same-CRS, same-resolution, grid-aligned DEMs into mosaics (keeps order)."""
    if len(dems) < 2:
        return dems
    groups: list[list[Dem]] = []
    for d in dems:
        for g in groups:
            ref = g[0]
            same_crs = (d.crs is None and ref.crs is None) or (
                d.crs is not None and ref.crs is not None and d.crs == ref.crs)
            if same_crs and np.allclose(d.res, ref.res, rtol=1e-9, atol=0):
                g.append(d)
                break
        else:
            groups.append([d])
    out = []
    for g in groups:
        if len(g) == 1:
            out.append(g[0])
            continue
        try:
            out.append(mosaic(g))
        except DemError:
            out.extend(g)
    return out
