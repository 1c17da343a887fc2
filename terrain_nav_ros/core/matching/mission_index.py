"""The mission index: a whole mission area's landmark features, prepared before flight.

The graph's landmark tile follows the estimate; to relocalise anywhere in the mission area
(issue 24) the matcher needs the landmark features of all of it. They are prepared once,
before flight (``terrain-nav prepare``), tile by tile:

* **Tiles.** The area's ENU extent is cut into square tiles of ``tile_px`` pixels at the
  mission GSD, overlapping by ``overlap_px`` (:class:`TileGrid`): any view of at most
  ``overlap_px`` pixels inside the grid lies wholly inside some tile, so a view is never
  searched across a tile seam.
* **Layers.** Each tile is rendered nadir once per sun (shaded creases repeat only within a
  few degrees of sun azimuth, so the index holds one layer per sun) and reduced to the
  features the graph extracts from a landmark region (:class:`TileBuilder`): the minutiae,
  the crease skeleton and the ridge skeleton. The render itself is not kept.
* **On disk** (a ``MISSION_DIR``): ``manifest.json`` (:func:`make_manifest`: format version,
  area, ENU origin, GSD, tile grid, suns, the DEM files with size and mtime, the render and
  extractor settings) and one compressed ``.npz`` per tile and sun under ``tiles/``
  (:func:`save_tile`: the minutia arrays, both skeletons bit-packed, the tile's georeference
  and sun), each written atomically (temporary file, then ``os.replace``), so an interrupted
  preparation resumes where it stopped.
* **Reading it**: :class:`MissionIndex` opens a ``MISSION_DIR``, checks its manifest, lists
  the tiles and their ENU bounds, picks the sun layer nearest a given sun and loads a layer
  (:func:`load_tile`) when asked.
* **The area's terrain heights** (:class:`TerrainHeights`, the manifest's ``terrain``): the
  median and the 2nd and 98th percentiles of the DEM over the area, for a cold start that
  projects its first frames without any estimate (camera_ingest's ``cold_start``). Manifests
  written before they were recorded are still read: :meth:`MissionIndex.terrain` then samples
  the DEMs the manifest names.

This module only builds and reads; the parallel preparation over tiles (Dask) is the
``prepare`` tool's.
"""

from __future__ import annotations

import json
import math
import os
import uuid
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..features.creases import CreaseParams
from ..features.hillshade import extractor_input
from ..features.minutia_set import MinutiaSet
from ..features.minutiae import FeatureExtractor, MinutiaParams, normalised_coordinates
from ..render.renderer import AlbedoRamp, LandmarkRenderer, display_u8
from ..render.sun import sun_separation
from ..terrain.geodesy import EnuOrigin
from ..terrain.georef import GeoReference
from ..terrain.metamap import DemTile, MetaMap, OutsideDemError

__all__ = ["FORMAT_VERSION", "IndexSettings", "MissionIndex", "MissionIndexError",
           "TerrainHeights", "TileBuilder", "TileGrid", "TileLayer", "area_terrain",
           "build_tile", "file_fingerprint",
           "layer_name", "load_tile", "make_manifest", "manifest_differences", "save_tile",
           "write_manifest"]

FORMAT = "terrain_nav mission index"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
TILES = "tiles"
TEMPORARY = ".tmp"   # suffix of a file being written
LAYER_FILE = TILES + "/r{row:03d}_c{col:03d}_s{sun:02d}.npz"
# the area's terrain is summarised from this many samples a side (at most one per DEM cell
# matters: the spread of heights, not their detail)
TERRAIN_SAMPLES = 256
# manifest keys derived from the DEMs, not asked for: an index prepared before they were
# recorded is the same request
_DERIVED_KEYS = ("terrain",)


class MissionIndexError(ValueError):
    """A mission directory that cannot be used: no manifest, another format or version, a
    manifest that does not match what is asked."""


# --------------------------------------------------------------------------- the tile grid
@dataclass(frozen=True)
class TileGrid:
    """Square tiles overlapping by ``overlap_px`` on a north-up ENU grid.

    Tile (col, row) has its north-west corner at ``(origin_east + col * stride * gsd,
    origin_north - row * stride * gsd)``, with ``stride = tile_px - overlap_px``.

    Parameters
    ----------
    origin_east, origin_north : float
        ENU (m) of the north-west corner of tile (0, 0).
    gsd : float
        Metres per pixel.
    tile_px, overlap_px : int
        Tile side and overlap of neighbouring tiles (pixels); ``0 <= overlap_px < tile_px``.
    cols, rows : int
        Tiles from west to east and from north to south.
    """

    origin_east: float
    origin_north: float
    gsd: float
    tile_px: int
    overlap_px: int
    cols: int
    rows: int

    def __post_init__(self):
        if not 0 <= self.overlap_px < self.tile_px:
            raise ValueError(f"tile overlap must be in [0, {self.tile_px}) px, got "
                             f"{self.overlap_px}")
        if not (math.isfinite(self.gsd) and self.gsd > 0):
            raise ValueError(f"gsd must be > 0 m, got {self.gsd}")

    @classmethod
    def covering(cls, extent, gsd: float, tile_px: int = 1024, overlap_px: int = 256):
        """The fewest tiles that cover ``extent`` (west, east, south, north), centred on it."""
        west, east, south, north = (float(v) for v in extent)
        stride = tile_px - overlap_px
        if stride <= 0:
            raise ValueError(f"tile overlap {overlap_px} px must be smaller than the tile "
                             f"({tile_px} px)")

        def count(span_m: float) -> int:
            # a hair of tolerance, so an extent of exactly n tiles is not n + 1
            return max(1, math.ceil((span_m / gsd - tile_px) / stride - 1e-9) + 1)

        cols, rows = count(east - west), count(north - south)
        width, height = (((n - 1) * stride + tile_px) * gsd for n in (cols, rows))
        return cls(0.5 * (west + east - width), 0.5 * (south + north + height), float(gsd),
                   int(tile_px), int(overlap_px), cols, rows)

    @property
    def stride_px(self) -> int:
        """Pixels from one tile's corner to the next one's."""
        return self.tile_px - self.overlap_px

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(west, east, south, north) of the whole grid (m)."""
        step = self.stride_px * self.gsd
        width = (self.cols - 1) * step + self.tile_px * self.gsd
        height = (self.rows - 1) * step + self.tile_px * self.gsd
        return (self.origin_east, self.origin_east + width, self.origin_north - height,
                self.origin_north)

    def georef(self, col: int, row: int) -> GeoReference:
        """The georeference of tile (col, row)."""
        if not (0 <= col < self.cols and 0 <= row < self.rows):
            raise IndexError(f"tile ({col}, {row}) is outside the {self.cols} x {self.rows} grid")
        step = self.stride_px * self.gsd
        return GeoReference(self.origin_east + col * step, self.origin_north - row * step,
                            self.gsd, self.tile_px, self.tile_px)

    def cells(self) -> list[tuple[int, int]]:
        """Every tile's (col, row), row by row from the north-west."""
        return [(c, r) for r in range(self.rows) for c in range(self.cols)]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> TileGrid:
        return cls(**values)


# --------------------------------------------------------------------------- the terrain
@dataclass(frozen=True)
class TerrainHeights:
    """The spread of terrain heights over a mission area (metres above the geoid, the
    DEM's own heights).

    Attributes
    ----------
    low, median, high : float
        The 2nd percentile, the median and the 98th percentile of the DEM over the area.
    """

    low: float
    median: float
    high: float

    def to_dict(self) -> dict:
        return {"low": self.low, "median": self.median, "high": self.high}

    @classmethod
    def from_dict(cls, values: dict) -> TerrainHeights:
        return cls(float(values["low"]), float(values["median"]), float(values["high"]))


def area_terrain(metamap: MetaMap, extent,
                 samples: int = TERRAIN_SAMPLES) -> TerrainHeights | None:
    """The :class:`TerrainHeights` of the ENU ``extent`` (west, east, south, north) from a
    ``samples`` x ``samples`` grid of ``metamap``'s heights (its ``heights`` convention);
    None when the DEMs hold no height there."""
    west, east, south, north = map(float, extent)
    gsd = max(east - west, north - south) / samples
    if not gsd > 0:
        return None
    georef = GeoReference(west, north, gsd, max(1, int(round((east - west) / gsd))),
                          max(1, int(round((north - south) / gsd))))
    try:
        tile = metamap.tile(georef)
    except OutsideDemError:
        return None
    heights = tile.elevation[~tile.nodata & np.isfinite(tile.elevation)]
    if not heights.size:
        return None
    low, median, high = np.percentile(heights, [2.0, 50.0, 98.0])
    return TerrainHeights(float(low), float(median), float(high))


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class IndexSettings:
    """How the layers are made: the graph's landmark render and landmark-region extraction.

    The defaults are the graph's (``config/terrain_nav.yaml``), with the minutia cap of a
    landmark region (a large tile holds thousands of minutiae).
    """

    crease: CreaseParams = field(default_factory=CreaseParams)
    minutia: MinutiaParams = field(default_factory=lambda: MinutiaParams(max_minutiae=100000))
    ridges: bool = True
    lighting: str = "shading"
    max_steps: int = 256
    shadows: bool = True
    tree_line: float = 2400.0
    snow_line: float = 3400.0
    interpolation: str = "spline"
    fill_voids: bool = True

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> IndexSettings:
        values = dict(values)
        values["crease"] = CreaseParams.from_dict(values["crease"])
        values["minutia"] = MinutiaParams.from_dict(values["minutia"])
        return cls(**values)


# --------------------------------------------------------------------------- one tile
@dataclass
class TileLayer:
    """The features of one tile under one sun.

    Attributes
    ----------
    minutiae : MinutiaSet
        With its ``georef`` and ``extras`` as the extractor returns them; empty with a
        ``reason`` over a tile without drainage or DEM.
    creases, ridges : ndarray of bool, shape ``georef.shape``, or None
        The crease (valley) and ridge skeletons.
    georef : GeoReference
    sun : (float, float)
        (azimuth, elevation) in degrees of the render's sun.
    """

    minutiae: MinutiaSet
    creases: np.ndarray | None
    ridges: np.ndarray | None
    georef: GeoReference
    sun: tuple[float, float]


class TileBuilder:
    """Renders a DEM tile under several suns and extracts each render's landmark features.

    One renderer and one extractor serve every tile: a worker keeps one builder (and its GL
    context) for all the tiles it prepares.

    Parameters
    ----------
    ctx : moderngl.Context
        A headless OpenGL context (:func:`~.render.renderer.create_headless_context`); the
        caller's to release.
    settings : IndexSettings
    """

    def __init__(self, ctx, settings: IndexSettings | None = None):
        self.settings = s = settings or IndexSettings()
        self.renderer = LandmarkRenderer(ctx, max_steps=s.max_steps, shadows=s.shadows,
                                         albedo=AlbedoRamp(tree_line=s.tree_line,
                                                           snow_line=s.snow_line))
        self.extractor = FeatureExtractor(s.crease, s.minutia, ridges=s.ridges)

    def layers(self, tile: DemTile, suns) -> list[TileLayer]:
        """One :class:`TileLayer` per sun of the heights ``tile``, rendered and extracted as
        the graph's landmark_renderer and feature_extractor do."""
        georef = tile.georef
        void = tile.nodata | ~np.isfinite(tile.elevation)
        if void.all():
            return [_empty_layer("no DEM under the tile", georef, sun) for sun in suns]
        # voids rendered at the lowest height and masked out of the extraction, as the node
        self.renderer.set_terrain(np.where(void, np.nanmin(tile.elevation), tile.elevation),
                                  georef)
        out = []
        for sun in suns:
            sun = (float(sun[0]), float(sun[1]))
            render = self.renderer.render_nadir(georef, sun=sun)
            valid = render.mask & ~void
            image = extractor_input(display_u8(render.grey), self.settings.lighting, sun,
                                    valid)
            feats = self.extractor(image, georef, valid)
            out.append(TileLayer(feats.minutiae, feats.creases.skeleton(), feats.ridges,
                                 georef, sun))
        return out

    def release(self) -> None:
        """Free the renderer's GL objects (the context stays the caller's)."""
        self.renderer.release()


def _empty_layer(reason: str, georef: GeoReference, sun) -> TileLayer:
    return TileLayer(MinutiaSet.empty(reason, georef), None, None, georef,
                     (float(sun[0]), float(sun[1])))


def build_tile(metamap: MetaMap, georef: GeoReference, suns,
               builder: TileBuilder) -> list[TileLayer]:
    """The layers of one tile, one per sun: its heights sampled once from ``metamap``, then
    rendered and extracted by ``builder`` under each sun."""
    try:
        heights = metamap.tile(georef)
    except OutsideDemError:
        return [_empty_layer("no DEM under the tile", georef, sun) for sun in suns]
    return builder.layers(heights, suns)


# --------------------------------------------------------------------------- tile files
def layer_name(col: int, row: int, sun_index: int) -> str:
    """File name of a tile's layer, relative to the mission directory."""
    return LAYER_FILE.format(row=row, col=col, sun=sun_index)


def _atomic_write(path: Path, write) -> None:
    """``write(file)`` into a temporary file beside ``path``, then rename it over ``path``:
    a reader (or a resumed run) never sees half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a name of its own per writer (not mkstemp's: its files are private, 0600)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{TEMPORARY}")
    try:
        with open(tmp, "xb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# minutia extras the extractor derives from the positions: recomputed on loading, not stored
_DERIVED_EXTRAS = ("x_norm", "y_norm", "east", "north")


def _derive_extras(ms: MinutiaSet) -> None:
    """The extras :class:`~.features.minutiae.FeatureExtractor` computes from the positions
    and the georeference, computed the same way (so they are equal to the bit)."""
    g = ms.georef
    x, y = normalised_coordinates(ms.col, ms.row, g.width, g.height)
    ms.extras.update(x_norm=x, y_norm=y)
    ms.extras["east"], ms.extras["north"] = g.pixel_to_enu(ms.col, ms.row)


def save_tile(path, layer: TileLayer) -> None:
    """Write a layer as a compressed ``.npz`` (atomically).

    Keys: ``georef`` (origin_east, origin_north, gsd, width, height), ``sun`` (azimuth,
    elevation), ``col``, ``row``, ``angle``, ``kind``, ``quality`` (the minutiae),
    ``extra_<name>`` (``minutiae.extras`` but those derived from the positions, recomputed
    when loaded), ``reason``, and ``creases`` / ``ridges``
    (``np.packbits`` of the skeleton, row-major; absent when there is none).
    """
    ms, g = layer.minutiae, layer.georef
    arrays = {"georef": np.array([g.origin_east, g.origin_north, g.gsd, g.width, g.height]),
              "sun": np.asarray(layer.sun, float), "col": ms.col, "row": ms.row,
              "angle": ms.angle, "kind": ms.kind, "quality": ms.quality,
              "reason": np.array(ms.reason)}
    arrays.update({f"extra_{k}": np.asarray(v) for k, v in ms.extras.items()
                   if k not in _DERIVED_EXTRAS})
    for name, skeleton in (("creases", layer.creases), ("ridges", layer.ridges)):
        if skeleton is not None:
            arrays[name] = np.packbits(skeleton, axis=None)
    _atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


# what reading a layer's file that is cut short, empty or not a layer raises
_UNREADABLE = (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile)


def _opened_layer(path):
    """The ``.npz`` of a layer, open; MissionIndexError when it cannot be read as one."""
    try:
        return np.load(path, allow_pickle=False)
    except _UNREADABLE as err:
        raise MissionIndexError(f"{path} is damaged ({type(err).__name__}: {err}): run "
                                "terrain-nav prepare again with --overwrite") from None


def _stored_place(z) -> tuple[GeoReference, tuple]:
    """The georeference and sun a layer's file holds."""
    oe, on, gsd, w, h = z["georef"]
    return (GeoReference(float(oe), float(on), float(gsd), int(w), int(h)),
            tuple(float(v) for v in z["sun"]))


def _georef_values(g: GeoReference) -> tuple:
    return (g.origin_east, g.origin_north, g.gsd, g.width, g.height)


def load_tile(path) -> TileLayer:
    """Read a layer written by :func:`save_tile`; MissionIndexError when the file is not
    one (cut short, empty, damaged inside)."""
    with _opened_layer(path) as z:
        try:
            return _read_layer(z)
        except _UNREADABLE as err:
            raise MissionIndexError(f"{path} is damaged ({type(err).__name__}: {err}): run "
                                    "terrain-nav prepare again with --overwrite") from None


def _read_layer(z) -> TileLayer:
    """The layer an open ``.npz`` holds (KeyError, ValueError when it is not one)."""
    georef, sun = _stored_place(z)
    ms = MinutiaSet(z["col"], z["row"], z["angle"], z["kind"], z["quality"],
                    georef=georef, reason=str(z["reason"]))
    if len(ms):
        _derive_extras(ms)
    ms.extras.update({k[len("extra_"):]: z[k] for k in z.files if k.startswith("extra_")})

    def skeleton(name):
        if name not in z.files:
            return None
        bits = np.unpackbits(z[name], count=georef.width * georef.height)
        return bits.reshape(georef.shape).astype(bool)

    return TileLayer(ms, skeleton("creases"), skeleton("ridges"), georef, sun)


# --------------------------------------------------------------------------- the manifest
def file_fingerprint(path) -> dict:
    """A DEM file as the manifest records it: absolute path, size and modification time
    (a changed DEM makes another index)."""
    st = os.stat(path)
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def make_manifest(*, area: dict, origin: EnuOrigin, grid: TileGrid, suns, dems,
                  settings: IndexSettings, sun_source: dict | None = None,
                  terrain: TerrainHeights | None = None) -> dict:
    """The manifest of a mission index (JSON-ready).

    Parameters
    ----------
    area : dict
        What was asked for: the geodetic box (``south``, ``west``, ``north``, ``east``,
        degrees) and how it was given (``from``: "--area" or "DEM extent").
    origin : EnuOrigin
        The ENU origin of every georeference in the index.
    grid : TileGrid
    suns : sequence of (azimuth, elevation)
        One layer per sun, in this order (degrees).
    dems : sequence of path
        The DEM files (recorded with :func:`file_fingerprint`).
    settings : IndexSettings
    sun_source : dict, optional
        How the suns were chosen (the flight window, the step), for the record.
    terrain : TerrainHeights, optional
        The area's terrain heights (:func:`area_terrain`), for a cold start.
    """
    manifest = {
        "format": FORMAT, "version": FORMAT_VERSION,
        "area": area,
        "origin": {"lat": origin.lat, "lon": origin.lon, "alt": origin.alt,
                   "geoid_undulation": origin.geoid_undulation},
        "gsd": grid.gsd,
        "grid": grid.to_dict(),
        "suns": [[float(az), float(el)] for az, el in suns],
        "sun_source": sun_source or {},
        "dems": [file_fingerprint(p) for p in dems],
        "settings": settings.to_dict(),
        "layer_files": LAYER_FILE,
    }
    if terrain is not None:
        manifest["terrain"] = terrain.to_dict()
    return json.loads(json.dumps(manifest))   # as it reads back: lists, not tuples


def write_manifest(mission_dir, manifest: dict) -> None:
    """Write ``manifest.json`` atomically."""
    text = json.dumps(manifest, indent=1) + "\n"
    _atomic_write(Path(mission_dir) / MANIFEST, lambda f: f.write(text.encode()))


def manifest_differences(old: dict, new: dict) -> list[str]:
    """The top-level keys in which two manifests differ (empty: the same index); keys
    derived from the DEMs (the terrain heights) count only when both have them."""
    keys = sorted((set(old) | set(new)) - {k for k in _DERIVED_KEYS
                                           if k not in old or k not in new})
    return [k for k in keys if old.get(k) != new.get(k)]


def read_manifest(mission_dir) -> dict:
    """The manifest of ``mission_dir``; MissionIndexError when there is none usable."""
    path = Path(mission_dir) / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise MissionIndexError(f"{mission_dir} holds no mission index ({MANIFEST} "
                                "missing): prepare one with terrain-nav prepare") from None
    except json.JSONDecodeError as err:
        raise MissionIndexError(f"{path} is not valid JSON ({err})") from None
    if manifest.get("format") != FORMAT or manifest.get("version") != FORMAT_VERSION:
        raise MissionIndexError(
            f"{path}: not a mission index of version {FORMAT_VERSION} (format "
            f"{manifest.get('format')!r}, version {manifest.get('version')!r}); prepare it "
            "again")
    return manifest


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class IndexTile:
    """One tile of the index: its place in the grid and on the ground."""

    col: int
    row: int
    georef: GeoReference

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """ENU (west, east, south, north) in metres."""
        return self.georef.extent


class MissionIndex:
    """A prepared mission index, opened from its directory.

    Parameters
    ----------
    mission_dir : path
        The directory ``terrain-nav prepare --out`` wrote.

    Raises
    ------
    MissionIndexError
        No manifest, or one of another format or version.
    """

    def __init__(self, mission_dir):
        self.path = Path(mission_dir)
        self.manifest = read_manifest(self.path)
        self.grid = TileGrid.from_dict(self.manifest["grid"])
        self.suns = np.array(self.manifest["suns"], float).reshape(-1, 2)
        o = self.manifest["origin"]
        self.origin = EnuOrigin(o["lat"], o["lon"], o["alt"], o["geoid_undulation"])
        self.settings = IndexSettings.from_dict(self.manifest["settings"])

    @property
    def gsd(self) -> float:
        return self.grid.gsd

    def terrain(self) -> TerrainHeights | None:
        """The area's terrain heights: the manifest's, else (an index prepared before they
        were recorded) sampled from the DEMs it names; None when those are gone too."""
        if "terrain" in self.manifest:
            return TerrainHeights.from_dict(self.manifest["terrain"])
        from ..terrain.dem_io import DemError, open_dem

        try:
            dems = [open_dem(d["path"]) for d in self.manifest.get("dems", [])]
        except (DemError, OSError):
            return None
        if not dems:
            return None
        try:
            extent = self.manifest.get("area", {}).get("enu_extent") or self.grid.extent
            return area_terrain(MetaMap(dems, self.origin), extent)
        finally:
            for d in dems:
                d.close()

    def tiles(self) -> list[IndexTile]:
        """Every tile, row by row from the north-west."""
        return [IndexTile(c, r, self.grid.georef(c, r)) for c, r in self.grid.cells()]

    def nearest_sun(self, sun) -> int:
        """Index of the layer whose sun is nearest ``sun`` (azimuth, elevation; degrees),
        by the angle between the two sun directions."""
        return int(np.argmin([sun_separation(sun, s) for s in self.suns]))

    def layer_path(self, col: int, row: int, sun_index: int) -> Path:
        return self.path / layer_name(col, row, sun_index)

    def missing(self) -> list[tuple[int, int, int]]:
        """(col, row, sun index) of every layer not on disk yet."""
        return [(c, r, k) for c, r in self.grid.cells() for k in range(len(self.suns))
                if not self.layer_path(c, r, k).exists()]

    def damaged(self) -> list[str]:
        """What is wrong with each layer on disk that cannot be this index's: unreadable
        (cut short, empty, not a layer), or of another tile or sun (a file copied from
        another index). Reads only each file's directory and its georeference and sun, so
        it is quick for a whole area; a layer damaged inside is found when loaded."""
        problems = []
        for c, r in self.grid.cells():
            for k in range(len(self.suns)):
                path = self.layer_path(c, r, k)
                if not path.exists():
                    continue
                try:
                    with _opened_layer(path) as z:
                        place = _stored_place(z)
                except MissionIndexError as err:
                    problems.append(str(err))
                    continue
                except _UNREADABLE as err:
                    problems.append(f"{path} is damaged ({type(err).__name__}: {err})")
                    continue
                try:
                    self._check_layer(path, c, r, k, *place)
                except MissionIndexError as err:
                    problems.append(str(err))
        return problems

    def _check_layer(self, path: Path, col: int, row: int, k: int, georef: GeoReference,
                     sun) -> None:
        """MissionIndexError unless a layer's georeference and sun are its tile's and
        layer's in this index."""
        expected = self.grid.georef(col, row)
        if not np.allclose(_georef_values(georef), _georef_values(expected), rtol=0.0,
                           atol=1e-6 * expected.gsd):
            raise MissionIndexError(
                f"{path} is of another tile or index: it covers {_georef_values(georef)}, "
                f"not {_georef_values(expected)}; run terrain-nav prepare again")
        if not np.allclose(sun, self.suns[k], atol=1e-6):
            raise MissionIndexError(f"{path} is lit by the sun {tuple(sun)}, not the index's "
                                    f"{tuple(self.suns[k])}; run terrain-nav prepare again")

    def load(self, col: int, row: int, sun) -> TileLayer:
        """The layer of tile (col, row) for ``sun``: a layer index, or (azimuth, elevation)
        for the nearest layer's. Read from disk on each call."""
        k = sun if isinstance(sun, (int, np.integer)) else self.nearest_sun(sun)
        if not 0 <= k < len(self.suns):
            raise IndexError(f"sun layer {k} does not exist (the index has {len(self.suns)})")
        self.grid.georef(col, row)   # IndexError outside the grid
        path = self.layer_path(col, row, k)
        if not path.exists():
            raise MissionIndexError(f"{path} is missing: the preparation did not finish; "
                                    "run terrain-nav prepare again to complete it")
        layer = load_tile(path)
        self._check_layer(path, col, row, k, layer.georef, layer.sun)
        return layer
