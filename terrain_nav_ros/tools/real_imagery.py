"""The real-imagery study (``terrain-nav evaluate --image`` / ``--scenes``).

Every other study renders its "camera" from the DEM it matches against. This one cuts the
camera views from a real satellite or aerial image and localises them in the project's own
landmark render of a co-registered DEM, lit by the image's sun, the way the graph would:

1. **Scene.** The image (one band, or a grey mix of the first three) and the DEM are put on
   one north-up metric grid: the DEM, read as the graph's metamap reads it (impossible
   heights are voids, small voids filled), is reprojected onto the image's grid (both onto
   the local UTM zone first when the image's grid is not in metres on the ground: degrees,
   feet, Web Mercator), then both are resampled to the study GSD. The image's pixels
   without data (as :class:`~.core.terrain.ortho_io.OrthoImage` reads them: nodata, masks,
   an undeclared fill value) and pixels over the DEM's large voids are invalid; a paletted
   image reads as its colours, and one georeferenced by control points only is warped onto
   a grid first. A scene finer than its DEM's cell is matched at that cell
   (views and regions area averaged): the render holds no terrain finer, and the camera's
   albedo detail (fields, roads, tree crowns) would outnumber the drainage the two share.
2. **Landmark.** :class:`~.core.render.renderer.LandmarkRenderer` renders the DEM nadir with the
   scene's sun (given, or from the acquisition time and the scene's centre). The image's
   correlation with the DEM's shading (:func:`~.core.features.hillshade.shading_agreement`)
   checks that sun: a stated sun far from the azimuth the image's shading follows, or an
   image that follows its terrain's shading at no sun, is warned of and reported; without a
   sun the error suggests the azimuth the shading follows. The same shading, shifted up to
   5 DEM cells, places the image's terrain against its DEM's: a pair 1.5 cells or more
   apart is warned of as misregistered (its views' errors carry that offset; Costa Rica's DEM,
   ~2 cells).
3. **Cases.** For each view size, views are cut from the image at random places, with a
   random rotation (within +-180 degrees with the heading unknown; within +-2 degrees, and
   the matcher told so, with it known) and scale (+-10 %); a view must lie on >= 95 % valid
   pixels. Each is localised in the landmark region ``region_factor`` times its side around
   its true place (clipped to the scene) with :meth:`~.core.matching.matcher.Matcher.localise`; a
   fix within ``success_px`` of the truth is a success, one further off is wrong (pixels of the
   GSD the scene is matched at: a view finer than its DEM is localised to the DEM's cell).
4. **Controls (non-PVA).** The same views against landmark regions that do not contain them:
   the regions of the other places' cases (a scene of the same DEM is the same place), and
   regions of the same scene at least a region
   apart where the scene is large enough. Their scores calibrate the threshold for the stated
   false-match rate (:func:`~.core.matching.significance.calibrate_threshold`), and the accepted
   ones are counted at the threshold used.
5. **Baselines** on the same cases: gradient NCC (without rotation search with the heading
   known, with 36 rotations without it) and ORB (SIFT with ``--sift``) with RANSAC; they
   always answer, so every answer off the truth is wrong.

A view with too little drainage, or mostly cloud (:mod:`~.core.features.clouds`, as the
graph's feature_extractor finds it in a camera frame), is answered with a no-fix and its
reason; it is counted apart, not dropped. Outputs: ``report.md``, ``results.json`` and a PNG
per scene (image beside its landmark render).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from affine import Affine

from ..core.camera.destripe import destripe
from ..core.features.clouds import CloudParams, cloud_cover
from ..core.features.hillshade import (
    FAINT_SHADING_R,
    ShadingAgreement,
    extractor_input,
    shading_agreement,
)
from ..core.features.minutia_set import MinutiaSet
from ..core.features.minutiae import FeatureExtractor, MinutiaParams
from ..core.matching.baselines import keypoint_locate, ncc_locate
from ..core.matching.matcher import Matcher
from ..core.matching.params import MatchParams
from ..core.matching.significance import calibrate_threshold
from ..core.render.sun import parse_utc, solar_position
from ..core.terrain.dem_io import fill_voids, open_dem
from ..core.terrain.georef import GeoReference
from ..core.terrain.ortho_io import (
    OrthoImage,
    centre_lonlat,
    ground_cell_metres,
    is_metric_grid,
    nir_band,
    rasterio_quiet,
    utm_crs,
)

__all__ = ["Scene", "load_scene", "load_scenes", "run_real_imagery_study"]

# A view must lie on at least this fraction of valid image pixels.
MIN_VALID = 0.95
# Rotation of the views with the heading known (deg), and what the matcher is told.
KNOWN_HEADING_DEG = 2.0
KNOWN_HEADING_PRIOR_DEG = 10.0
# Reasons of a no-fix that mean "this view holds too little drainage" (or shows too little
# ground), counted apart.
_TOO_LITTLE = ("too little drainage", "no drainage", "too few minutiae", "mostly cloud")


@dataclass
class Scene:
    """A real image and its DEM on one north-up metric grid.

    ``image`` is 8-bit grey (0 where invalid), ``valid`` its mask, ``elevation`` the DEM on
    the same grid (voids inpainted), ``sun`` (azimuth, elevation) in degrees.
    """

    name: str
    image: np.ndarray
    valid: np.ndarray
    elevation: np.ndarray
    gsd: float
    sun: tuple[float, float]
    centre_latlon: tuple[float, float]
    place: str = ""   # scenes of one place (one DEM) are never each other's controls
    dem_cell: float = math.nan   # the DEM's own cell [m] (before resampling to ``gsd``)
    dem_warning: str | None = None   # what is wrong with the DEM's heights (read as voids)
    image_warning: str | None = None   # the image's undeclared fill (read as no data)
    shading: ShadingAgreement | None = None   # the image against its DEM's shading
    landmark: np.ndarray | None = field(default=None, repr=False)

    @property
    def georef(self) -> GeoReference:
        h, w = self.image.shape
        return GeoReference(0.0, 0.0, self.gsd, w, h)

    @property
    def sun_warning(self) -> str | None:
        """What the image's shading says against its sun (see :class:`ShadingAgreement`)."""
        return self.shading.warning(self.sun) if self.shading else None

    @property
    def registration_warning(self) -> str | None:
        """That the image's terrain lies 1.5 DEM cells or more off its DEM's (see
        :meth:`ShadingAgreement.registration_warning`): its views' errors carry the offset."""
        return self.shading.registration_warning() if self.shading else None


def _dem_window(d, dem_crs, crs, transform, shape, margin: int = 4) -> tuple[slice, slice]:
    """Rows and columns of the DEM ``d`` under an image's footprint (``crs``, ``transform``,
    ``shape``), and ``margin`` cells around it for the resampling kernels."""
    from rasterio.warp import transform_bounds
    h, w = shape
    xs, ys = transform @ (np.array([0, w, 0, w]), np.array([0, 0, h, h]))
    with rasterio_quiet():
        left, bottom, right, top = transform_bounds(crs, dem_crs, xs.min(), ys.min(),
                                                    xs.max(), ys.max(), densify_pts=21)
    if not left < right:   # across the antimeridian: the whole DEM
        return slice(0, d.height), slice(0, d.width)
    cols, rows = ~d.transform @ (np.array([left, right, left, right]),
                                 np.array([bottom, bottom, top, top]))
    r0, r1 = int(np.floor(rows.min())) - margin, int(np.ceil(rows.max())) + margin
    c0, c1 = int(np.floor(cols.min())) - margin, int(np.ceil(cols.max())) + margin
    r0, r1, c0, c1 = max(r0, 0), min(r1, d.height), max(c0, 0), min(c1, d.width)
    if r0 >= r1 or c0 >= c1:
        raise ValueError(f"{Path(d.name).name} does not reach under the image: are they of "
                         "the same place?")
    return slice(r0, r1), slice(c0, c1)


def _scene_band(src: OrthoImage, band) -> np.ndarray:
    """One band (1-based) of ``src``, NaN where it holds no data; ``band=None``: the
    near-infrared band if the file's band descriptions name one (:func:`nir_band`), else as
    "grey": the mean of the first three (the only one of a single-band file)."""
    if band is None:
        band = nir_band(src.descriptions) or "grey"
    bands = range(1, min(src.count, 3) + 1) if band in ("grey", "gray") else [band]
    return src.read(bands).mean(axis=0)


def _reproject(src, src_transform, src_crs, dst_shape, dst_transform, dst_crs, resampling):
    from rasterio.warp import reproject
    out = np.full(dst_shape, np.nan, np.float32)
    with rasterio_quiet():
        reproject(np.asarray(src, np.float32), out, src_transform=src_transform,
                  src_crs=src_crs,
                  src_nodata=np.nan, dst_transform=dst_transform, dst_crs=dst_crs,
                  dst_nodata=np.nan, resampling=resampling)
    return out


def _parse_sun(sun, when, lat: float, lon: float) -> tuple[float, float]:
    if sun is not None:
        try:
            az, el = (float(x) for x in sun)
        except (TypeError, ValueError):
            raise ValueError(f"the sun must be two numbers, azimuth and elevation in degrees; "
                             f"got {sun!r}") from None
        if not math.isfinite(az):
            raise ValueError(f"sun azimuth must be a finite number of degrees, got {az}")
        if not 0.0 < el <= 90.0:
            raise ValueError(f"sun elevation must be in (0, 90] deg, got {el}")
        return az % 360.0, el
    t = when if isinstance(when, _dt.datetime) else parse_utc(when)
    az, el = solar_position(t, lat, lon)
    if not float(el) > 0:
        raise ValueError(f"the sun is below the horizon at {t.isoformat()} "
                         f"({lat:.3f}, {lon:.3f})")
    return float(az), float(el)


MAX_SCENE_PIXELS = 64 * 1024 * 1024   # 256 MB a float32 layer: a scene, not a mission area


def _check_scene_size(image: Path, shape, cell: float, gsd: float | None):
    """Refuse a GSD that would resample the image into more than MAX_SCENE_PIXELS."""
    if gsd is None:
        return
    pixels = shape[0] * shape[1] * (cell / gsd) ** 2
    if pixels > MAX_SCENE_PIXELS:
        raise ValueError(f"{image.name}: at a GSD of {gsd:g} m its {cell:.3g} m cells would "
                         f"be {pixels / 1e6:.3g} M pixels (at most {MAX_SCENE_PIXELS / 1e6:.0f} "
                         f"M): study it at a GSD nearer its own cell")


def load_scene(image, dem, *, band=None, gsd: float | None = None, sun=None, when=None,
               name: str | None = None) -> Scene:
    """Read an image and its DEM onto one metric grid (see the module docstring).

    Parameters
    ----------
    image, dem : str or Path
        Any raster rasterio reads, each with its CRS (the image may instead have ground
        control points; a paletted image reads as its colours).
    band : int, "grey" or None
        1-based band of the image; "grey": the mean of the first three bands; None: the
        near-infrared band where the file names one, else "grey".
    gsd : float, optional
        Study GSD (m); default the image's own (its UTM cell when it is in degrees).
    sun : (azimuth, elevation), optional
        Degrees; else computed from ``when`` (ISO 8601 or datetime, UTC unless stated).
    name : str, optional
        Default: the image's file stem.
    """
    from rasterio.crs import CRS
    from rasterio.warp import Resampling, calculate_default_transform

    image, dem = Path(image), Path(dem)
    for path in (image, dem):
        if not path.is_file():
            raise ValueError(f"no such file: {path}")
    if gsd is not None and not (math.isfinite(gsd) and gsd > 0):
        raise ValueError(f"the study GSD must be a number of metres > 0, got {gsd}")
    with OrthoImage(image) as src:
        img = _scene_band(src, band)
        transform, crs, image_warning = src.transform, src.crs, src.warning
    _check_scene_size(image, img.shape, ground_cell_metres(crs, transform, img.shape), gsd)
    # the DEM as the graph's metamap reads it: impossible heights (undeclared nodata) are
    # voids, and the small voids are filled
    with open_dem(dem) as d:
        if d.crs is None:
            raise ValueError(f"{dem.name} has no CRS: the image and DEM must be georeferenced "
                             "to be co-registered")
        z_crs = CRS.from_wkt(d.crs.to_wkt())
        # only the DEM under the image (a scene of a large mosaic reads a scene's worth)
        rows, cols = _dem_window(d, z_crs, crs, transform, img.shape)
        z_src, _ = fill_voids(d.read((rows, cols)))
        z_transform = d.transform @ Affine.translation(cols.start, rows.start)
        # the DEM's own cell, at its centre
        dem_warning, dem_cell = d.warning, ground_cell_metres(z_crs, d.transform, d.shape)
    seen = img[np.isfinite(img)]
    if not seen.size:
        raise ValueError(f"{image.name}: no valid pixels (every one is nodata, fill or not a "
                         "number)")
    if seen.min() == seen.max():
        raise ValueError(f"{image.name}: every valid pixel holds {seen[0]:g}: nothing to "
                         "study (an undeclared fill value?)")
    lon, lat = centre_lonlat(crs, transform, img.shape)
    if not is_metric_grid(crs, transform, img.shape):
        utm = utm_crs(lon, lat)
        h, w = img.shape
        xs, ys = transform @ (np.array([0, w, 0, w]), np.array([0, 0, h, h]))
        # the image's own ground cell, unless a GSD is asked for
        cell = gsd or ground_cell_metres(crs, transform, img.shape)
        with rasterio_quiet():
            dst_transform, w, h = calculate_default_transform(
                crs, utm, w, h, xs.min(), ys.min(), xs.max(), ys.max(), resolution=cell)
        img = _reproject(img, transform, crs, (h, w), dst_transform, utm, Resampling.bilinear)
        transform, crs = dst_transform, utm
    native = abs(transform.a)
    z = _reproject(z_src, z_transform, z_crs, img.shape, transform, crs, Resampling.cubic)
    gsd = float(gsd or native)
    if abs(gsd - native) > 1e-6 * native:
        f = native / gsd
        shape = (max(int(round(img.shape[1] * f)), 1), max(int(round(img.shape[0] * f)), 1))
        down = cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR
        valid_src = np.isfinite(img).astype(np.float32)
        img = cv2.resize(np.nan_to_num(img), shape, interpolation=down)
        valid_f = cv2.resize(valid_src, shape, interpolation=down)
        img[valid_f < 0.999] = np.nan
        z = cv2.resize(z, shape, interpolation=down if f < 1 else cv2.INTER_CUBIC)
    valid = np.isfinite(img) & np.isfinite(z)
    if valid.mean() < 0.2:
        raise ValueError(f"{image.name}: image and DEM overlap on {100 * valid.mean():.0f} % "
                         "of the image: are they of the same place?")
    lo, hi = np.percentile(img[valid], [1.0, 99.0])
    grey = np.where(valid, np.clip((img - lo) / max(hi - lo, 1e-6) * 255.0, 0, 255), 0)
    # the DEM's large voids and the land beyond it: inpainted smooth, so the render makes no
    # cliffs there (no creases), and never observed
    elevation = fill_voids(z, max_area=z.size, fill_border=True)[0]
    grey = grey.astype(np.uint8)
    per_cell = dem_cell / gsd if math.isfinite(dem_cell) else 1.0
    if sun is None and when is None:
        hint = shading_agreement(grey, elevation, gsd, None, valid, per_cell)
        raise ValueError("the scene's sun is needed: give --sun AZ,EL or --time ISO8601 (the "
                         "acquisition time)" + (
                             f"; its shading follows a sun from azimuth "
                             f"{hint.best_azimuth:.0f} deg best"
                             if hint.r_best >= FAINT_SHADING_R else ""))
    sun = _parse_sun(sun, when, lat, lon)
    return Scene(name or image.stem, grey, valid, elevation, gsd, sun, (lat, lon),
                 place=str(dem.resolve()), dem_cell=dem_cell,
                 dem_warning=dem_warning, image_warning=image_warning,
                 shading=shading_agreement(grey, elevation, gsd, sun, valid, per_cell))


def dem_camera_scene(path, sun=(315.0, 45.0)) -> Scene:
    """A scene of the DEM at ``path`` whose "image" is its nadir render by the DEM-only
    study's camera at ``sun`` (another albedo, the camera's degradations): its largest
    void-free square at the native cell. The dev image pairs hold no 3x region of 384 px
    views and more; a DEM of 1000+ cells does (e.g. ``N44E005.hgt``)."""
    from ..core.terrain.metamap import MetaMap
    from . import evaluation

    mm = MetaMap(open_dem(path), interpolation="spline", fill_voids=True)
    gsd = mm.native_gsd
    ce, cn, side = evaluation.valid_area(mm, gsd)
    tile = mm.tile(GeoReference.centred(ce, cn, gsd, side, side))
    elevation = np.where(tile.nodata, np.nanmedian(tile.elevation), tile.elevation)
    rgb, = evaluation.camera_renders(elevation, tile.georef, [sun])
    # 8-bit grey as a scene's image is (the camera render is quantised to 8 bits already)
    grey = np.clip(np.rint(255.0 * cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)), 0, 255)
    grey = grey.astype(np.uint8)
    return Scene(Path(path).stem + "(render)", grey, np.ones(grey.shape, bool),
                 elevation.astype(np.float32), gsd, tuple(sun),
                 (mm.origin.lat, mm.origin.lon), place=str(Path(path).resolve()),
                 dem_cell=gsd)


def load_scenes(path, data_dir=None) -> list[Scene]:
    """Scenes listed in a YAML file (``scenes: [{name, image, dem, band, gsd, sun, time}]``),
    file names relative to ``data_dir`` (default: the YAML file's folder). A scene without
    ``name`` is named after its image; a list of ``gsd`` studies it at each. ``image:
    render`` makes the scene's image the DEM's camera render at ``sun``
    (:func:`dem_camera_scene`: views of 384 px and more, which the real pairs cannot
    hold)."""
    import yaml
    path = Path(path)
    doc = yaml.safe_load(path.read_text())
    entries = doc.get("scenes") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path.name}: expected 'scenes:' and a list of scenes, each with image, "
                         "dem and the sun (sun or time)")
    base = Path(data_dir) if data_dir else path.parent
    scenes = []
    for k, entry in enumerate(entries):
        where = f"{path.name}: scene {k + 1}"
        entry = _scene_entry(entry, where)
        gsds = entry.get("gsd")
        render = entry["image"] == RENDER_IMAGE
        name = entry.get("name") or (Path(entry["dem"]).stem + "(render)" if render
                                     else Path(entry["image"]).stem)
        for g in gsds if isinstance(gsds, list) else [gsds]:
            try:
                if render:
                    # the sun's checks are the image scenes' (its place is not needed)
                    sun = _parse_sun(entry["sun"], None, math.nan, math.nan)
                    scenes.append(replace(dem_camera_scene(base / entry["dem"], sun),
                                          name=name))
                    continue
                scenes.append(load_scene(
                    base / entry["image"], base / entry["dem"], band=entry.get("band"), gsd=g,
                    sun=entry.get("sun"), when=entry.get("time"),
                    name=name + (f"@{g:g}m" if isinstance(gsds, list) else "")))
            except ValueError as err:
                raise ValueError(f"{where} ({name}): {err}") from err
    return scenes


_SCENE_KEYS = ("name", "image", "dem", "band", "gsd", "sun", "time")
# ``image:`` of a scene whose image is its DEM's camera render (load_scenes)
RENDER_IMAGE = "render"


def _scene_entry(entry, where: str) -> dict:
    """One scene of a scenes file, checked: the keys it may have, their types."""
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: expected a mapping of {', '.join(_SCENE_KEYS)}")
    where += f" ({entry['name']})" if entry.get("name") else ""
    unknown = sorted(set(map(str, entry)) - set(_SCENE_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key {', '.join(unknown)} (known: "
                         f"{', '.join(_SCENE_KEYS)})")
    for key in ("image", "dem"):
        if not isinstance(entry.get(key), str) or not entry[key]:
            raise ValueError(f"{where}: '{key}' (a file name) is missing")
    if entry["image"] == RENDER_IMAGE:
        if entry.get("sun") is None:
            raise ValueError(f"{where}: a render's scene needs its sun as [azimuth, "
                             "elevation] in degrees")
        extra = sorted(k for k in ("band", "gsd", "time") if k in entry)
        if extra:
            raise ValueError(f"{where}: {', '.join(extra)} do not apply to a render's scene "
                             "(the DEM's own cell, its sun)")
        return entry
    band = entry.get("band")
    if band is not None and band not in ("grey", "gray") and not (
            isinstance(band, int) and not isinstance(band, bool) and band >= 1):
        raise ValueError(f"{where}: band must be a band number (1-based) or 'grey', got "
                         f"{band!r}")
    gsds = entry.get("gsd")
    for g in gsds if isinstance(gsds, list) else [] if gsds is None else [gsds]:
        if isinstance(g, bool) or not isinstance(g, int | float) or not g > 0:
            raise ValueError(f"{where}: gsd must be a number of metres > 0 or a list of them, "
                             f"got {gsds!r}")
    return entry


# Side (px) of the blocks a large scene's landmark is rendered in: the renderer holds ~100
# bytes per output pixel (a 9000 x 9000 px scene in one piece peaked at 9.6 GB).
RENDER_BLOCK = 2048


def render_landmark(scenes: list[Scene], shadows: bool = True) -> None:
    """Render each scene's landmark (nadir, its sun, with cast shadows unless ``shadows``
    is False, as the graph's landmark_renderer) into ``scene.landmark``: in blocks of
    :data:`RENDER_BLOCK` px, each with the terrain around it that can shade it."""
    from ..core.render.renderer import LandmarkRenderer, create_headless_context
    ctx = create_headless_context()
    for s in scenes:
        renderer = LandmarkRenderer(ctx, shadows=shadows)
        try:
            s.landmark = np.empty(s.elevation.shape, np.uint8)
            margin = _shadow_reach(s) if shadows else 1
            for rows, cols in _blocks(s.elevation.shape, RENDER_BLOCK):
                # the block and its margin (clipped to the scene): normals and cast shadows
                # as the whole scene's
                around = tuple(slice(max(r.start - margin, 0), r.stop + margin)
                               for r in (rows, cols))
                renderer.set_terrain(s.elevation[around], _sub_georef(s, *around))
                s.landmark[rows, cols] = renderer.render_nadir(
                    _sub_georef(s, rows, cols), sun=s.sun).grey_u8
        finally:
            renderer.release()


def _shadow_reach(scene: Scene) -> int:
    """How far (px) the scene's relief can cast a shadow at its sun."""
    relief = float(np.ptp(scene.elevation))
    reach = relief / math.tan(math.radians(scene.sun[1])) / scene.gsd
    return int(min(math.ceil(reach) + 2, max(scene.elevation.shape)))


def _blocks(shape, side: int):
    """Row and column slices of ``side`` px blocks covering ``shape``."""
    for r0 in range(0, shape[0], side):
        for c0 in range(0, shape[1], side):
            yield slice(r0, min(r0 + side, shape[0])), slice(c0, min(c0 + side, shape[1]))


def _sub_georef(scene: Scene, rows: slice, cols: slice) -> GeoReference:
    """The georeference of ``scene``'s pixels ``rows`` x ``cols`` (clipped to the scene)."""
    h, w = scene.elevation.shape
    r0, r1, _ = rows.indices(h)
    c0, c1, _ = cols.indices(w)
    return GeoReference(c0 * scene.gsd, -r0 * scene.gsd, scene.gsd, c1 - c0, r1 - r0)


@dataclass
class _Case:
    view: np.ndarray                  # camera view, 8-bit grey
    region: tuple[int, int, int, int]  # x0, y0, x1, y1 in the scene
    truth: np.ndarray                 # the view's centre in region pixels (col, row)
    valid: np.ndarray | None = None   # the view's observed pixels (nodata, cloud masks)
    cut: np.ndarray | None = None     # 2 x 3: view px -> scene px (:func:`view_at`)

    def true_transform(self, f_view, f_region) -> np.ndarray:
        """The view's true place as a matcher's transform (2 x 3, view px -> region px, at
        the matching pixels: ``f_view`` and ``f_region`` scene px each, per axis)."""
        fv, fr = np.broadcast_to(f_view, 2), np.broadcast_to(f_region, 2)
        rot = self.cut[:, :2] * fv[None, :] / fr[:, None]
        shift = (self.cut[:, :2] @ (0.5 * fv - 0.5) + self.cut[:, 2]
                 - np.asarray(self.region[:2], float) + 0.5) / fr - 0.5
        return np.column_stack([rot, shift])


def _cut_cases(scene: Scene, size: int, n: int, heading_known: bool, region_factor: float,
               rng: np.random.Generator, max_scale_change: float = 0.1) -> list[_Case]:
    """Up to ``n`` views of ``size`` px on valid pixels (fewer if the scene cannot hold
    them)."""
    h, w = scene.image.shape
    c = 0.5 * (size - 1)
    corners = np.array([[0, 0, 1], [size - 1, 0, 1], [0, size - 1, 1], [size - 1, size - 1, 1]],
                       float)
    half = int(round(0.5 * region_factor * size))
    cases = []
    for _ in range(200 * n):
        if len(cases) == n:
            break
        limit = KNOWN_HEADING_DEG if heading_known else 180.0
        theta = math.radians(rng.uniform(-limit, limit))
        s = 1.0 + rng.uniform(-max_scale_change, max_scale_change)
        cx, cy = rng.uniform(0, w - 1), rng.uniform(0, h - 1)
        a, b = s * math.cos(theta), s * math.sin(theta)
        m = np.array([[a, b, 0.0], [-b, a, 0.0]])    # view px -> scene px
        m[:, 2] = np.array([cx, cy]) - m[:, :2] @ np.array([c, c])
        xy = corners @ m.T
        if xy.min() < 0 or (xy[:, 0] > w - 1).any() or (xy[:, 1] > h - 1).any():
            continue
        view, valid = view_at(scene, m, size)
        if valid.mean() < MIN_VALID:
            continue
        x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
        x1, y1 = min(int(cx) + half, w), min(int(cy) + half, h)
        cases.append(_Case(view, (x0, y0, x1, y1), np.array([cx - x0, cy - y0]), valid, m))
    return cases


def view_at(scene: Scene, m: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``size`` px view of ``scene`` that the affine ``m`` (2 x 3, view px -> scene px)
    cuts, and its observed pixels (bool)."""
    flags = cv2.WARP_INVERSE_MAP
    valid = cv2.warpAffine(scene.valid.view(np.uint8), m, (size, size),
                           flags=flags | cv2.INTER_NEAREST)
    view = cv2.warpAffine(scene.image, m, (size, size), flags=flags | cv2.INTER_LINEAR)
    return view, valid.astype(bool)


def _decimated(grey: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """``grey`` area-averaged ``factor`` times coarser, and the exact factor per axis (x, y)
    (the pixel centres map as x = (x' + 0.5) f - 0.5)."""
    h, w = grey.shape
    if factor <= 1.0 + 1e-3:
        return grey, np.ones(2)
    shape = (max(int(round(w / factor)), 1), max(int(round(h / factor)), 1))
    out = cv2.resize(grey, shape, interpolation=cv2.INTER_AREA)
    return out, np.array([w / shape[0], h / shape[1]])


class _Extractor:
    """The graph's extraction of a camera view and of a landmark region (a region's index
    is kept: the controls meet the same regions many times), at the matching GSD: a scene
    finer than it is area-averaged first, as camera_ingest resamples a camera to its GSD."""

    def __init__(self, params: MatchParams, match_gsd=None):
        ridges = params.crease_check and params.ridge_check
        self.view = FeatureExtractor(ridges=ridges)
        self.region = FeatureExtractor(minutia_params=MinutiaParams(max_minutiae=100000),
                                       ridges=ridges)
        self.match_gsd = match_gsd
        self.cloud_params = CloudParams()   # the graph's defaults
        self._regions = {}

    def factor(self, scene: Scene) -> float:
        """How many times coarser than ``scene.gsd`` the scene is matched."""
        if self.match_gsd is None:
            return 1.0
        target = scene.dem_cell if self.match_gsd == "dem" else float(self.match_gsd)
        return max(1.0, target / scene.gsd) if math.isfinite(target) else 1.0

    def index(self, matcher: Matcher, grey, scene: Scene, region: bool = False, valid=None):
        """The index of ``grey`` (a view or a landmark region of ``scene``, observed where
        ``valid``, as camera_ingest's mask tells the extractor) and the factor per axis of
        its decimation."""
        if not region:          # a view plays the camera's frame: its sensor's stripes
            grey = destripe(grey, valid)
        grey, f = _decimated(grey, self.factor(scene))
        if valid is not None:   # a decimated pixel is observed when all it averages are
            valid = _decimated(valid.astype(np.float32), self.factor(scene))[0] > 0.999
        if not region:          # as feature_extractor does with a camera frame
            cover = cloud_cover(grey, valid, self.cloud_params)
            if cover.reason:
                return matcher.index(MinutiaSet.empty(cover.reason)), f
        feats = (self.region if region else self.view)(
            extractor_input(grey, "shading", scene.sun), valid_mask=valid)
        ix = matcher.index(feats.minutiae, feats.creases.skeleton(), feats.ridges)
        return (ix.prepare_as_reference(search=True) if region else ix), f

    def region_index(self, matcher: Matcher, scene: Scene, box):
        """The index of the landmark region ``box`` (x0, y0, x1, y1) of ``scene`` and its
        decimation factor per axis."""
        key = (scene.name, tuple(box), id(matcher))
        if key not in self._regions:
            x0, y0, x1, y1 = box
            self._regions[key] = self.index(matcher, scene.landmark[y0:y1, x0:x1], scene,
                                            region=True)
        return self._regions[key]


def _summary(err, accepted, times, success_px, no_fix_few=None) -> dict:
    err, acc = np.asarray(err, float), np.asarray(accepted, bool)
    ok = acc & (err <= success_px)
    out = {"cases": int(len(err)), "success": int(ok.sum()),
           "success_rate": float(ok.mean()) if len(err) else math.nan,
           "wrong": int((acc & ~(err <= success_px)).sum()),
           "err_median_ok_px": float(np.median(err[ok])) if ok.any() else math.nan,
           "time_ms_median": 1e3 * float(np.median(times)) if len(times) else math.nan}
    if no_fix_few is not None:
        out["no_fix_too_little_drainage"] = int(np.sum(no_fix_few))
    return out


def _localise(matcher: Matcher, extractor: _Extractor, scene: Scene, case: _Case,
              region_index) -> dict:
    t0 = time.perf_counter()
    view, f_view = extractor.index(matcher, case.view, scene, valid=case.valid)
    ref, f_region = region_index
    r = matcher.localise(view, ref)
    dt = time.perf_counter() - t0
    offset = view_offset(r, case, f_view, f_region)
    return {"score": float(r.score), "err": _length(offset), "offset": offset,
            "time": dt, "reason": r.reason, "vetoed": _vetoed(r),
            "too_little": any(k in r.reason for k in _TOO_LITTLE), "view_index": view,
            "creases": r.creases, "ridges": r.ridges}


def _vetoed(result) -> bool:
    """Whether the matcher refused ``result`` for all its score: the study's matcher has no
    threshold of its own, so a refusal is one of the graph's vetoes (another place scoring
    as well, a scale at the edge of the fit), and the graph would give no fix."""
    return not result.matched and math.isfinite(result.score)


def _accepted(score: float, vetoed: bool, thr: float) -> bool:
    """What the graph would do with a registration of ``score``: a fix at ``thr``, unless
    vetoed."""
    return score >= thr and not vetoed


def _refused(score: float, vetoed: bool, thr: float) -> bool:
    """A registration over ``thr`` that the graph's vetoes would refuse (no fix)."""
    return score >= thr and vetoed


def _evidence_parts(creases, ridges) -> dict:
    """A case's crease and ridge scores (the ridges' given the valleys', with the
    dependence measured between them) for ``results.json``; None where not scored."""
    return {"valleys_score": creases.score if creases else None,
            "ridges_score": ridges.score if ridges else None,
            "ridges_dependence": ridges.dependence if ridges else None}


def view_error(result, case: _Case, f_view: float, f_region: float) -> float:
    """Distance (scene pixels; inf without a transform) from the case's true place of the
    view's centre where ``result`` (a localisation in the region's matching pixels) puts
    it. ``f_view`` and ``f_region`` are the matching pixels' sizes in scene pixels."""
    return _length(view_offset(result, case, f_view, f_region))


def _length(offset) -> float:
    e = float(np.hypot(*offset))
    return e if math.isfinite(e) else math.inf


def view_offset(result, case: _Case, f_view: float, f_region: float) -> np.ndarray:
    """As :func:`view_error`, the offset itself: (east, north) scene pixels from the true
    place to the found one (NaN without a transform). Its mean over a scene's localised
    views is the pair's misregistration as the matcher sees it (about minus
    :attr:`ShadingAgreement.offset_east`, ``offset_north``)."""
    centre = 0.5 * (np.array(case.view.shape[::-1]) / f_view - 1.0)   # in matching pixels
    est = np.array(result.apply(*centre), float) if np.isfinite(result.transform).all() \
        else np.full(2, np.nan)
    est = (est + 0.5) * f_region - 0.5           # matching pixels -> scene pixels
    col, row = est - case.truth
    return np.array([col, -row])                 # the scene is north-up


def _baseline(method: str, case: _Case, region: np.ndarray, heading_known: bool,
              n_rotations: int) -> tuple[float, float]:
    t0 = time.perf_counter()
    if method == "ncc":
        loc = ncc_locate(case.view, region, n_rotations=0 if heading_known else n_rotations)
    else:
        loc = keypoint_locate(case.view, region, kind=method)
    dt = time.perf_counter() - t0
    e = float(np.hypot(loc.col - case.truth[0], loc.row - case.truth[1])) if loc.found \
        else math.inf
    return e, dt


def _far_regions(case: _Case, scene: Scene, size: int, region_factor: float,
                 rng: np.random.Generator, n: int) -> list[tuple[int, int, int, int]]:
    """Regions of the scene that do not contain the case's view (its centre at least the
    region's half side plus the view's reach away): none in a small scene."""
    h, w = scene.image.shape
    side = int(round(region_factor * size))
    if side >= min(h, w):
        return []
    x0c, y0c = case.region[:2]
    centre = np.array([x0c, y0c]) + case.truth
    out = []
    for _ in range(50 * n):
        if len(out) == n:
            break
        x0, y0 = int(rng.integers(0, w - side + 1)), int(rng.integers(0, h - side + 1))
        near = np.abs(centre - (x0 + side / 2, y0 + side / 2)).max()
        if near > side / 2 + size * 0.75:
            out.append((x0, y0, x0 + side, y0 + side))
    return out


def run_real_imagery_study(scenes: list[Scene], *, sizes=(64, 128, 256, 512), cases: int = 20,
                           out_dir="out/real-imagery", seed: int = 0,
                           region_factor: float = 3.0, success_px: float = 3.0,
                           false_match_rate: float = 1e-3, threshold: float | None = None,
                           headings=("unknown", "known"), baselines=("ncc", "orb"),
                           controls_per_case: int = 2, n_rotations: int = 36,
                           match_params: MatchParams | None = None, match_gsd="dem",
                           shadows: bool = True, log=print) -> dict:
    """Localise views of real images in landmark renders of their DEMs (module docstring).

    Parameters
    ----------
    scenes : list of Scene
    sizes : sequence of int
        View sides (px); a size a scene cannot hold (with the rotation) is skipped, said so.
    cases : int
        Views per scene, size and heading condition.
    threshold : float, optional
        Acceptance threshold; default :class:`~.core.matching.params.MatchParams`'. The command
        passes the graph's (``match.threshold`` of ``config/terrain_nav.yaml``).
    headings : sequence of {"unknown", "known"}
    baselines : sequence of {"ncc", "orb", "sift"}
    controls_per_case : int
        Non-PVA regions of other places per view, distinct (:func:`_control_regions`: fewer
        when they run out), and a far part of the view's own scene where it holds one.
    match_gsd : float, "dem" or None
        GSD (m) at which views and regions are matched when a scene is finer (area
        averaged, as camera_ingest resamples a camera to its GSD); "dem" (default): each
        scene's DEM cell, since a render holds no terrain finer than it, while the camera's
        albedo detail grows finer; None: each scene's own GSD.
    shadows : bool
        Landmarks with cast shadows (the graph's landmark_renderer ``shadows``; the command
        passes the graph's): a real image has them where the terrain is steeper than the
        sun is high.

    Returns
    -------
    dict
        Summary (also written to ``results.json``); ``report`` is the markdown text.
    """
    t_all = time.perf_counter()
    params = match_params or MatchParams()
    thr = params.threshold if threshold is None else float(threshold)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    render_landmark(scenes, shadows)
    extractor = _Extractor(params, match_gsd)
    rng = np.random.default_rng(seed)
    study = _StudyRun(scenes, extractor, thr, success_px, region_factor, controls_per_case,
                      tuple(baselines), n_rotations, rng)
    rows, pva_scores, skipped = [], [], []
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)   # single-thread times, comparable across methods
    try:
        for heading in headings:
            known = heading == "known"
            max_rot = math.radians(KNOWN_HEADING_PRIOR_DEG) if known else math.pi
            matcher = Matcher(params, threshold=-1e9, max_rotation=max_rot)
            for size in sizes:
                per_scene = {s.name: _cut_cases(s, size, cases, known, region_factor, rng)
                             for s in scenes}
                for scene in scenes:
                    if not per_scene[scene.name]:
                        log(f"  {scene.name}: no {size} px view fits ({heading} heading)")
                        skipped.append({"scene": scene.name, "size": size,
                                        "heading": heading})
                        continue
                    row = _study_cases(study, scene, per_scene, size, heading, matcher)
                    pva_scores += row.pop("pva_scores")
                    rows.append(row)
                    m = row["minutiae"]
                    log(f"  {scene.name} {size} px, heading {heading}: {m['success']}/"
                        f"{m['cases']} localised, {m['wrong']} wrong, "
                        f"{m['no_fix_too_little_drainage']} too little drainage, "
                        f"{m['vetoed']} vetoed, "
                        f"{m['time_ms_median']:.0f} ms")
    finally:
        cv2.setNumThreads(cv_threads)
    if not rows:
        raise ValueError("no view of " + ", ".join(f"{x:g}" for x in sizes) + " px fits in "
                         + ", ".join(f"{s.name} ({s.image.shape[1]}x{s.image.shape[0]} px)"
                                     for s in scenes)
                         + f": a view must lie, turned, on >= {100 * MIN_VALID:.0f} % valid "
                         "pixels; give smaller --sizes")
    non_pva = study.non_pva
    non = np.array([x["score"] for x in non_pva], float)
    calibrated = calibrate_threshold(non, false_match_rate) \
        if len(non) and np.isfinite(non).any() else math.nan
    summary = {
        "setup": {"scenes": [{"name": s.name, "shape": list(s.image.shape), "gsd_m": s.gsd,
                              "dem_cell_m": s.dem_cell,
                              "sun": list(s.sun), "centre_latlon": list(s.centre_latlon),
                              "valid": float(s.valid.mean()),
                              "dem_warning": s.dem_warning,
                              "image_warning": s.image_warning,
                              "shading": _shading_json(s.shading),
                              "sun_warning": s.sun_warning,
                              "registration_warning": s.registration_warning}
                             for s in scenes],
                  "sizes": list(sizes), "cases": cases, "seed": seed,
                  "region_factor": region_factor, "success_px": success_px,
                  "threshold": thr, "false_match_rate": false_match_rate,
                  "headings": list(headings), "baselines": list(baselines),
                  "n_rotations": n_rotations, "match_gsd": match_gsd,
                  "match_gsd_m": {s.name: s.gsd * extractor.factor(s) for s in scenes},
                  "shadows": bool(shadows)},
        "rows": rows,
        "skipped": skipped,
        "non_pva": {"comparisons": int(len(non)),
                    "accepted": sum(_accepted(x["score"], x["vetoed"], thr) for x in non_pva),
                    "vetoed": sum(_refused(x["score"], x["vetoed"], thr) for x in non_pva),
                    "max_score": float(non.max()) if len(non) else math.nan,
                    "calibrated_threshold": float(calibrated),
                    "calibrated_threshold_1e-4": float(calibrate_threshold(non, 1e-4))
                    if len(non) and np.isfinite(non).any() else math.nan,
                    "scores": [float(x) for x in non],
                    "by_size": _non_pva_by_size(non_pva, thr),
                    "pva_success_at_calibrated": _success_at(rows, pva_scores, calibrated),
                    "accepted_cases": [x for x in non_pva if x["score"] >= thr]},   # vetoed too
        "seconds": time.perf_counter() - t_all,
    }
    summary["totals"] = _totals(rows, range(128, 513))
    summary["by_cells"] = _totals_by_cells(rows, summary["setup"])
    pngs = _scene_pngs(out, scenes) + [_score_histogram(out, rows, non, thr, success_px)]
    report = _report(summary, pngs)
    (out / "report.md").write_text(report)
    (out / "results.json").write_text(json.dumps(summary, indent=1, default=_json_default))
    summary["report"] = report
    return summary


@dataclass
class _StudyRun:
    """What every case of one study run shares, and the control scores it gathers."""

    scenes: list
    extractor: _Extractor
    threshold: float
    success_px: float
    region_factor: float
    controls_per_case: int
    baselines: tuple
    n_rotations: int
    rng: np.random.Generator
    non_pva: list = field(default_factory=list)


def _study_cases(study: _StudyRun, scene: Scene, per_scene: dict, size: int, heading: str,
                 matcher: Matcher) -> dict:
    """Localise the cases of one scene, size and heading, with their baselines and controls
    (appended to ``study.non_pva``): the scene's row of the report."""
    cs, known, thr = per_scene[scene.name], heading == "known", study.threshold
    extractor, success_px = study.extractor, study.success_px
    rec = {"err": [], "acc": [], "time": [], "few": [], "vetoed": [], "cases": [],
           "offset_m": []}
    base = {m: {"err": [], "time": []} for m in study.baselines}
    pva_scores = []
    # errors in matching pixels: a view finer than its DEM is localised to the DEM's cell
    per_px = extractor.factor(scene)
    for k, case in enumerate(cs):
        x0, y0, x1, y1 = case.region
        region = scene.landmark[y0:y1, x0:x1]
        region_index = extractor.region_index(matcher, scene, case.region)
        r = _localise(matcher, extractor, scene, case, region_index)
        r["err"] /= per_px
        rec["err"].append(r["err"])
        accepted = _accepted(r["score"], r["vetoed"], thr)
        rec["acc"].append(accepted)
        rec["time"].append(r["time"])
        rec["few"].append(r["too_little"] and not accepted)
        rec["vetoed"].append(_refused(r["score"], r["vetoed"], thr))
        rec["offset_m"].append(r["offset"] * scene.gsd)
        rec["cases"].append({"err_px": r["err"], "err_m": r["err"] * per_px * scene.gsd,
                             "offset_m": [float(v) for v in r["offset"] * scene.gsd],
                             "score": r["score"], "reason": r["reason"],
                             "vetoed": r["vetoed"],
                             **_evidence_parts(r["creases"], r["ridges"])})
        pva_scores.append((scene.name, size, heading, r["score"], r["vetoed"],
                           r["err"] <= success_px))
        for method in study.baselines:
            e, dt = _baseline(method, case, region, known, study.n_rotations)
            base[method]["err"].append(e / per_px)
            base[method]["time"].append(dt)
        _controls(study, scene, per_scene, case, k, size, heading, matcher, r["view_index"])
    row = {"scene": scene.name, "size": size, "heading": heading,
           "minutiae": {**_summary(rec["err"], rec["acc"], rec["time"], success_px, rec["few"]),
                        "vetoed": int(np.sum(rec["vetoed"])),
                        "vetoed_at_truth": int(np.sum(np.asarray(rec["vetoed"], bool)
                                                      & (np.asarray(rec["err"])
                                                         <= success_px))),
                        "mean_offset_m": _mean_offset(rec["offset_m"], rec["acc"],
                                                      rec["err"], success_px)},
           "pva_scores": pva_scores, "cases": rec["cases"]}
    for method, b in base.items():
        row[method] = _summary(b["err"], np.isfinite(b["err"]), b["time"], success_px)
    return row


def _mean_offset(offsets, accepted, err, success_px) -> list[float] | None:
    """(east, north) m: the mean offset of the views localised (None without any)."""
    ok = np.asarray(accepted, bool) & (np.asarray(err, float) <= success_px)
    return [float(v) for v in np.mean(np.asarray(offsets)[ok], axis=0)] if ok.any() else None


def _controls(study: _StudyRun, scene: Scene, per_scene: dict, case: _Case, k: int,
              size: int, heading: str, matcher: Matcher, view_index) -> None:
    """Score the ``k``-th view of ``scene`` against regions that do not hold it: those of
    other places' cases (:func:`_control_regions`) and a far part of its own scene; into
    ``study.non_pva``."""
    regions = _control_regions(study.scenes, scene, per_scene, k, study.controls_per_case)
    regions += [(scene, box) for box in _far_regions(case, scene, size, study.region_factor,
                                                     study.rng, 1)]
    for other, box in regions:
        ref, _ = study.extractor.region_index(matcher, other, box)
        r = matcher.localise(view_index, ref)
        study.non_pva.append({"view_scene": scene.name, "region_scene": other.name,
                              "size": size, "heading": heading, "score": float(r.score),
                              "vetoed": _vetoed(r), "reason": r.reason})


def _control_regions(scenes, scene: Scene, per_scene: dict, k: int, n: int) -> list:
    """Up to ``n`` distinct (scene, region) pairs of other places' cases for the ``k``-th
    view of ``scene``: one scene after another, each scene's regions in turn from its
    ``k``-th. A scene smaller than a region has one (the whole scene: all its cases share
    it), so a view meets each such region once: asked for more, it gets fewer, rather than
    the same comparison scored again as if it were another."""
    pools = []
    for other in scenes:
        if other.place != scene.place and per_scene[other.name]:
            boxes = list(dict.fromkeys(tuple(c.region) for c in per_scene[other.name]))
            start = k % len(boxes)
            pools.append([(other, box) for box in boxes[start:] + boxes[:start]])
    if not pools:
        return []
    first = k % len(pools)
    pools = pools[first:] + pools[:first]
    interleaved = [pool[i] for i in range(max(map(len, pools))) for pool in pools
                   if i < len(pool)]
    return interleaved[:n]


def _non_pva_by_size(non_pva: list[dict], thr: float) -> dict:
    """Comparisons, accepts and the highest score of the controls per view size."""
    out = {}
    for size in sorted({x["size"] for x in non_pva}):
        of_size = [x for x in non_pva if x["size"] == size]
        out[str(size)] = {"comparisons": len(of_size),
                          "accepted": sum(_accepted(x["score"], x["vetoed"], thr)
                                          for x in of_size),
                          "vetoed": sum(_refused(x["score"], x["vetoed"], thr)
                                        for x in of_size),
                          "max_score": max(x["score"] for x in of_size)}
    return out


def _success_at(rows, pva_scores, thr) -> dict:
    if not math.isfinite(thr):
        return {}
    ok = sum(1 for *_, score, vetoed, right in pva_scores
             if right and _accepted(score, vetoed, thr))
    wrong = sum(1 for *_, score, vetoed, right in pva_scores
                if not right and _accepted(score, vetoed, thr))
    return {"success": ok, "wrong": wrong, "cases": len(pva_scores)}


def _totals(rows, sizes) -> dict:
    """Success over all scenes for views of ``sizes`` (the issue's 128-512 px, any side
    between), per heading condition and method."""
    out = {}
    for heading in {r["heading"] for r in rows}:
        sel = [r for r in rows if r["heading"] == heading and r["size"] in sizes]
        for method in ("minutiae", "ncc", "orb", "sift"):
            have = [r[method] for r in sel if method in r]
            if have:
                n = sum(x["cases"] for x in have)
                out[f"{heading}/{method}"] = {
                    "cases": n, "success": sum(x["success"] for x in have),
                    "wrong": sum(x["wrong"] for x in have),
                    "no_fix_too_little_drainage": sum(x.get("no_fix_too_little_drainage", 0)
                                                      for x in have),
                    "vetoed": sum(x.get("vetoed", 0) for x in have)}
    return out


def _totals_by_cells(rows, setup: dict) -> list[dict]:
    """The project's views over all scenes by their side in the cells they are matched at
    (view px x GSD / matched-at m: the drainage a view can hold) and by whether the scene's
    shading is faint (:attr:`ShadingAgreement.faint`: canopy, cloud), per heading
    condition."""
    scenes = {s["name"]: s for s in setup["scenes"]}
    groups: dict = {}
    for r in rows:
        scene = scenes[r["scene"]]
        cells = round(r["size"] * scene["gsd_m"] / setup["match_gsd_m"][r["scene"]])
        faint = bool((scene.get("shading") or {}).get("faint"))
        g = groups.setdefault((r["heading"], faint, cells), {
            "heading": r["heading"], "faint_shading": faint, "cells": cells, "cases": 0,
            "success": 0, "wrong": 0, "no_fix_too_little_drainage": 0})
        m = r["minutiae"]
        for key in ("cases", "success", "wrong", "no_fix_too_little_drainage"):
            g[key] += m.get(key, 0)
    return [groups[k] for k in sorted(groups)]


def _scene_pngs(out: Path, scenes: list[Scene]) -> list[str]:
    names = []
    for s in scenes:
        name = f"scene_{s.name.replace('@', '_')}.png"
        cv2.imwrite(str(out / name), np.hstack([s.image, np.full((s.image.shape[0], 4), 255,
                                                                 np.uint8), s.landmark]))
        names.append(name)
    return names


def _score_histogram(out: Path, rows, non: np.ndarray, thr: float, success_px: float) -> str:
    """Scores of the views at their place (localised or not) and of the controls, with the
    threshold: how far the two populations stand apart on real images."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .evaluation import save_figure

    cases = [c for r in rows for c in r["cases"]]
    right = [c["score"] for c in cases if c["err_px"] <= success_px]
    off = [c["score"] for c in cases if not c["err_px"] <= success_px]
    finite = [x for x in [*right, *off, *non] if np.isfinite(x)]
    bins = np.linspace(min(finite, default=-5.0), max(max(finite, default=30.0), thr + 1), 60)
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for values, label in ((non, "controls (non-PVA)"), (off, "views, not at their place"),
                          (right, f"views within {success_px:g} px of their place")):
        ax.hist(np.clip([v for v in values if np.isfinite(v)], bins[0], bins[-1]), bins,
                histtype="step", lw=1.5, label=f"{label} ({len(values)})")
    ax.axvline(thr, color="k", ls="--", lw=1, label=f"threshold {thr:g}")
    ax.set_xlabel("score")
    ax.set_ylabel("count")
    if finite:   # (a log axis of no counts warns)
        ax.set_yscale("log")
    ax.legend(fontsize=8)
    return save_figure(fig, out / "scores.png")


def _shading_json(shading: ShadingAgreement | None) -> dict | None:
    return None if shading is None else {
        "r_at_sun": shading.r_at_sun, "best_azimuth_deg": shading.best_azimuth,
        "r_best": shading.r_best, "pixels": shading.pixels, "faint": shading.faint,
        "offset_east_m": shading.offset_east, "offset_north_m": shading.offset_north,
        "r_offset": shading.r_offset, "offset_judged": shading.offset_judged}


def _shading_cell(shading: dict | None) -> str:
    if not shading or not math.isfinite(shading["r_best"]):
        return "-"
    return (f"{shading['r_at_sun']:.2f} ({shading['best_azimuth_deg']:.0f} deg, "
            f"{shading['r_best']:.2f})")


def _registration_cell(shading: dict | None, scene: str, rows) -> str:
    """The pair's misregistration two ways: the shading's shift, and minus the mean offset
    of the views the matcher localised (weighted by their number over sizes and headings)."""
    shading = shading or {}
    by_shading = f"{shading['offset_east_m']:+.0f}, {shading['offset_north_m']:+.0f}" \
        if shading.get("offset_judged") and math.isfinite(shading["offset_east_m"]) else "-"
    found = [(r["minutiae"]["mean_offset_m"], r["minutiae"]["success"]) for r in rows
             if r["scene"] == scene and r["minutiae"].get("mean_offset_m")]
    n = sum(k for _, k in found)
    if not n:
        return f"{by_shading} / -"
    mean = np.sum([np.asarray(m) * k for m, k in found], axis=0) / n
    return f"{by_shading} / {-mean[0]:+.0f}, {-mean[1]:+.0f} ({n} views)"


def _fmt(x, spec=".0f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else \
        format(x, spec)


def _report(summary: dict, pngs: list[str]) -> str:
    st = summary["setup"]
    methods = [m for m in ("minutiae", "ncc", "orb", "sift")
               if any(m in r for r in summary["rows"])]
    lines = ["# Real-imagery study", "",
             f"Views cut from real images, localised in a region {st['region_factor']:g}x "
             f"their side of the landmark render of the scene's DEM at the scene's sun "
             f"({'with' if st['shadows'] else 'without'} cast shadows); "
             f"success = centre within {st['success_px']:g} px of the GSD matched at; threshold "
             f"{st['threshold']:g}; scale +-10 %; heading unknown = rotation +-180 deg "
             f"(NCC with {st['n_rotations']} rotations), known = +-{KNOWN_HEADING_DEG:g} deg "
             f"(matcher told +-{KNOWN_HEADING_PRIOR_DEG:g}, NCC without rotations). "
             "Baselines always answer: every answer off the truth is wrong.", "",
             "| scene | GSD m | DEM cell m | matched at m | size px | sun az/el | valid "
             "| shading r at the sun (best azimuth, its r) | image's terrain from the DEM's, "
             "by the shading / minus the localised views' mean offset (m east, north) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in st["scenes"]:
        lines.append(f"| {s['name']} | {s['gsd_m']:g} | {s['dem_cell_m']:.0f} | "
                     f"{st['match_gsd_m'][s['name']]:.0f} | {s['shape'][1]}x{s['shape'][0]} | "
                     f"{s['sun'][0]:.1f} / {s['sun'][1]:.1f} | {100 * s['valid']:.0f} % | "
                     f"{_shading_cell(s.get('shading'))} | "
                     f"{_registration_cell(s.get('shading'), s['name'], summary['rows'])} |")
    notes = [f"- {s['name']}: {s[key]}" for s in st["scenes"]
             for key in ("image_warning", "dem_warning", "sun_warning",
                         "registration_warning") if s.get(key)]
    if notes:
        lines += ["", "Input warnings (what was read as no data, and why; a doubtful sun):",
                  ""] + notes
    head = "| scene | view px | heading | cases | " + " | ".join(
        f"{m} ok / wrong / ms" for m in methods) + (" | minutiae: too little drainage | "
                                                     "minutiae: vetoed (at their place) |")
    lines += ["", "## Localisation", "",
              "A view over the threshold that the graph's vetoes refuse (another place "
              "scoring as well; a scale at the edge of the fit) is not localised.", "",
              head, "|" + "---|" * (6 + len(methods))]
    for r in summary["rows"]:
        cells = [f"{r[m]['success']} / {r[m]['wrong']} / {_fmt(r[m]['time_ms_median'])}"
                 if m in r else "-" for m in methods]
        lines.append(f"| {r['scene']} | {r['size']} | {r['heading']} | "
                     f"{r['minutiae']['cases']} | " + " | ".join(cells)
                     + f" | {r['minutiae']['no_fix_too_little_drainage']} | "
                     f"{r['minutiae'].get('vetoed', 0)} "
                     f"({r['minutiae'].get('vetoed_at_truth', 0)}) |")
    if summary["skipped"]:
        lines += ["", "Not studied (no view of the size fits in the scene, turned, on valid "
                  "pixels): " + ", ".join(f"{x['scene']} {x['size']} px ({x['heading']})"
                                          for x in summary["skipped"]) + "."]
    lines += ["", "Over all scenes, views of 128-512 px:", "",
              "| heading / method | cases | localised | wrong | too little drainage | vetoed |",
              "|---|---|---|---|---|---|"]
    for key, t in sorted(summary["totals"].items()):
        rate = 100.0 * t["success"] / max(t["cases"], 1)
        lines.append(f"| {key} | {t['cases']} | {t['success']} ({rate:.0f} %) | "
                     f"{t['wrong']} | {t['no_fix_too_little_drainage']} | "
                     f"{t['vetoed'] if key.endswith('minutiae') else '-'} |")
    lines += ["", "The project's views by their side in the cells they are matched at (view px "
              "x GSD / matched-at m: the drainage a view can hold), the scenes whose image "
              f"follows its DEM's shading at no sun azimuth (r < {FAINT_SHADING_R:g}: canopy, "
              "cloud) apart; localised of those with drainage enough:", "",
              "| heading | shading | view side, cells | cases | too little drainage | "
              "localised | wrong |", "|---|---|---|---|---|---|---|"]
    for g in summary["by_cells"]:
        judged = g["cases"] - g["no_fix_too_little_drainage"]
        rate = f" ({100.0 * g['success'] / judged:.0f} %)" if judged else ""
        lines.append(f"| {g['heading']} | {'faint' if g['faint_shading'] else 'seen'} | "
                     f"{g['cells']} | {g['cases']} | {g['no_fix_too_little_drainage']} | "
                     f"{g['success']}{rate} | {g['wrong']} |")
    nv = summary["non_pva"]
    at = nv["pva_success_at_calibrated"]
    lines += ["", "## Controls (non-PVA)", "",
              f"{nv['comparisons']} comparisons of views with regions that do not hold them "
              f"(other places' regions, each once a view, and far parts of the same scene): "
              f"**{nv['accepted']} accepted** "
              f"at threshold {st['threshold']:g} ({nv['vetoed']} more over it, vetoed); "
              f"highest score {_fmt(nv['max_score'], '.2f')}. "
              f"Threshold calibrated on them for a false-match rate of "
              f"{st['false_match_rate']:g}: {_fmt(nv['calibrated_threshold'], '.2f')} "
              f"(1e-4, from the fitted tail: {_fmt(nv['calibrated_threshold_1e-4'], '.2f')})"
              + (f", at which {at['success']} of {at['cases']} views are localised and "
                 f"{at['wrong']} accepted wrong." if at else "."), "",
              "", "| view px | comparisons | accepted | vetoed | highest score |",
              "|---|---|---|---|---|"]
    lines += [f"| {size} | {b['comparisons']} | {b['accepted']} | {b['vetoed']} | "
              f"{b['max_score']:.2f} |" for size, b in nv["by_size"].items()]
    lines += ["", f"Run time {summary['seconds']:.0f} s.", ""]
    lines += [f"![{p}]({p})" for p in pngs]
    return "\n".join(lines) + "\n"


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")

