"""``terrain-nav prepare``: the mission index of a whole area, built before flight on Dask.

The area (``--area`` or the DEMs' extent) is cut into overlapping tiles
(:class:`~.core.matching.mission_index.TileGrid`); every tile is rendered under each sun of
the flight window and reduced to its landmark features
(:class:`~.core.matching.mission_index.TileBuilder`), one ``.npz`` per tile and sun in the
mission directory, beside its ``manifest.json``.

The tiles are independent, so they are Dask tasks: one task per tile, holding all its sun
layers (the tile's DEM sampling and terrain upload are shared by its suns). A
``dask.distributed`` LocalCluster of ``--workers`` processes with one thread each runs them,
or an existing cluster (``--scheduler ADDRESS``: its workers need this package, the DEM
paths and the mission directory). Each worker process keeps one headless GL context, one
renderer and the DEMs open for all its tasks (:func:`_worker_state`): a context costs
seconds. A tile whose layers are all on disk is not submitted again, so an interrupted
preparation resumes where it stopped; a different request into the same directory is
refused unless ``--overwrite``.
"""

from __future__ import annotations

import json
import logging
import math
import resource
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..core.features.creases import CreaseParams
from ..core.features.minutiae import MinutiaParams
from ..core.matching import mission_index as mi
from ..core.render.sun import parse_utc, suns_over_window
from ..core.terrain.dem_io import dem_files, open_dem
from ..core.terrain.geodesy import EnuOrigin
from ..core.terrain.metamap import MetaMap
from .errors import InputError

__all__ = ["IndexPlan", "PrepareRequest", "build_tile_job", "graph_settings",
           "interrupted_message", "parse_area", "parse_suns", "plan_index",
           "request_from_args", "run_prepare"]

REPO = Path(__file__).resolve().parents[2]
GRAPH_PARAMETERS = REPO / "config" / "terrain_nav.yaml"
# Suns lower than this are left out of a flight window: the landmark renderer falls back to
# its fixed sun below it.
MIN_SUN_ELEVATION = 5.0
# Coverage of an --area is checked on this many points per side (plus its edges).
COVERAGE_SAMPLES = 65


@dataclass
class PrepareRequest:
    """What ``terrain-nav prepare`` was asked (see its ``--help``)."""

    dems: list[str]
    out: Path
    gsd: float
    area: tuple[float, float, float, float] | None = None   # lat, lon, lat, lon
    suns: list[tuple[float, float]] | None = None
    time: str | None = None
    hours: float = 2.0
    sun_step: float | None = None
    tile_px: int = 1024
    overlap_px: int = 256
    scheduler: str | None = None
    workers: int | None = None
    overwrite: bool = False


# --------------------------------------------------------------------------- settings
def graph_settings(path=GRAPH_PARAMETERS) -> tuple[mi.IndexSettings, float]:
    """The graph's landmark render, landmark extraction and DEM sampling settings from its
    parameters file, as index settings (with a landmark region's minutia cap), and the
    landmark renderer's ``max_sun_change`` (the default sun step)."""
    import yaml

    doc = yaml.safe_load(Path(path).read_text())

    def block(node):
        return doc.get(node, {}).get("ros__parameters", {})

    metamap, renderer, extractor = block("metamap"), block("landmark_renderer"), \
        block("feature_extractor")
    prefixed = {k: v for k, v in extractor.items() if k.startswith(("crease.", "minutia."))}
    crease = CreaseParams.from_dict({k[len("crease."):]: v for k, v in prefixed.items()
                                     if k.startswith("crease.")})
    minutia = MinutiaParams.from_dict({k[len("minutia."):]: v for k, v in prefixed.items()
                                       if k.startswith("minutia.")})
    default = mi.IndexSettings()
    settings = mi.IndexSettings(
        crease=crease, minutia=replace(minutia, max_minutiae=default.minutia.max_minutiae),
        ridges=bool(extractor.get("attach_ridges", default.ridges)),
        lighting=str(extractor.get("lighting", default.lighting)),
        max_steps=int(renderer.get("max_steps", default.max_steps)),
        shadows=bool(renderer.get("shadows", default.shadows)),
        tree_line=float(renderer.get("tree_line", default.tree_line)),
        snow_line=float(renderer.get("snow_line", default.snow_line)),
        interpolation=str(metamap.get("interpolation", default.interpolation)),
        fill_voids=bool(metamap.get("fill_voids", default.fill_voids)))
    return settings, float(renderer.get("max_sun_change", 2.0))


# --------------------------------------------------------------------------- the plan
@dataclass
class IndexPlan:
    """Everything a preparation needs, decided before any work: the manifest, and what the
    workers need to rebuild the DEM sampling."""

    manifest: dict
    grid: mi.TileGrid
    suns: np.ndarray
    dem_paths: list[str]
    origin: EnuOrigin
    settings: mi.IndexSettings


def _open_dems(specs) -> list:
    paths = dem_files(specs)
    if not paths:
        raise InputError(f"no DEM file in {' '.join(map(str, specs))}: give DEM files "
                         "(GeoTIFF, ESRI ASCII grid, SRTM .hgt) with --dem")
    dems = [open_dem(p) for p in paths]
    local = [d.name for d in dems if d.local_metres]
    if local:
        raise InputError(f"{local[0]} has no CRS: the mission index needs georeferenced DEMs")
    return dems


def _geodetic_bounds(dems) -> tuple[float, float, float, float]:
    """(south, west, north, east) in degrees of the DEMs' union: their edges in longitude
    and latitude, unwrapped about the first one's centre, so that a union across the
    antimeridian is one box with east beyond 180 (pyproj's own bounds of such a DEM are
    west > east, or the whole circle)."""
    from pyproj import Transformer

    t = np.linspace(0.0, 1.0, 65)
    lats, lons, centre = [], [], None
    for d in dems:
        left, bottom, right, top = d.bounds
        xs = np.r_[left + t * (right - left), np.full_like(t, right),
                   right - t * (right - left), np.full_like(t, left)]
        ys = np.r_[np.full_like(t, bottom), bottom + t * (top - bottom), np.full_like(t, top),
                   top - t * (top - bottom)]
        to_lonlat = Transformer.from_crs(d.crs, "EPSG:4326", always_xy=True)
        lon, lat = to_lonlat.transform(xs, ys)
        if centre is None:
            centre = to_lonlat.transform(0.5 * (left + right), 0.5 * (bottom + top))[0]
        lons.append(centre + (np.asarray(lon) - centre + 180.0) % 360.0 - 180.0)
        lats.append(np.asarray(lat))
    lon, lat = np.concatenate(lons), np.concatenate(lats)
    return float(lat.min()), float(lon.min()), float(lat.max()), float(lon.max())


def _area_points(area, n: int = COVERAGE_SAMPLES):
    """Latitudes and longitudes of an n x n grid over the box (its edges included)."""
    south, west, north, east = area
    lat, lon = np.meshgrid(np.linspace(south, north, n), np.linspace(west, east, n))
    return lat.ravel(), lon.ravel()


def _check_covered(metamap: MetaMap, origin: EnuOrigin, area, dems) -> None:
    """InputError, one line, when part of the area lies outside every DEM."""
    lat, lon = _area_points(area)
    e, n, _ = origin.geodetic_to_enu(lat, lon, origin.alt)
    covered = metamap.covers(e, n)
    if covered.all():
        return
    k = int(np.flatnonzero(~covered)[0])
    s, w, nn, ee = _geodetic_bounds(dems)
    raise InputError(
        f"the DEMs do not cover the area: {1 - covered.mean():.0%} of it (e.g. lat "
        f"{lat[k]:.4f}, lon {lon[k]:.4f}) is outside them; they span lat {s:.4f}..{nn:.4f}, "
        f"lon {w:.4f}..{ee:.4f}: give DEMs that cover it, or a smaller --area")


def _area_box(area) -> tuple[float, float, float, float]:
    """(south, west, north, east) of --area's two corners, checked."""
    lat0, lon0, lat1, lon1 = area
    south, north, west, east = min(lat0, lat1), max(lat0, lat1), min(lon0, lon1), max(lon0,
                                                                                       lon1)
    if east - west > 180.0:   # corners either side of the antimeridian: the box across it
        west, east = east, west + 360.0
    if not (-90 <= south < north <= 90 and -180 <= west < east <= 360):
        raise InputError(f"--area {','.join(f'{v:g}' for v in area)}: give two opposite "
                         "corners LAT,LON,LAT,LON of a box with some extent (degrees)")
    return south, west, north, east


def _enu_extent(origin: EnuOrigin, area) -> tuple[float, float, float, float]:
    """ENU (west, east, south, north) bounding the geodetic box (its edges sampled)."""
    south, west, north, east = area
    t = np.linspace(0.0, 1.0, COVERAGE_SAMPLES)
    lat = np.r_[south + t * (north - south), np.full_like(t, north),
                north - t * (north - south), np.full_like(t, south)]
    lon = np.r_[np.full_like(t, west), west + t * (east - west), np.full_like(t, east),
                east - t * (east - west)]
    e, n, _ = origin.geodetic_to_enu(lat, lon, origin.alt)
    return float(e.min()), float(e.max()), float(n.min()), float(n.max())


MIN_SUN_STEP = 0.1   # deg: finer, the index's layers repeat each other (2 deg is the default)
MAX_HOURS = 48.0     # a flight window of two days at most


def _suns(req: PrepareRequest, origin: EnuOrigin, default_step: float):
    """The index's suns and how they were chosen."""
    if req.suns and req.time:
        raise InputError("give either --suns or --time (with --hours), not both")
    if req.suns:
        for az, el in req.suns:
            if not (math.isfinite(az) and 0 < el <= 90):
                raise InputError(f"--suns: elevation {el:g} must be in (0, 90] deg")
        return np.array([[az % 360.0, el] for az, el in req.suns]), {"from": "--suns"}
    if not req.time:
        raise InputError("the index needs its suns: give --suns AZ/EL,... (degrees) or "
                         "--time ISO8601 --hours H (the flight window)")
    step = default_step if req.sun_step is None else req.sun_step
    if not (MIN_SUN_STEP <= step <= 90.0 and 0 <= req.hours <= MAX_HOURS):
        raise InputError(f"--sun-step {step:g} must be {MIN_SUN_STEP:g}-90 deg and --hours "
                         f"{req.hours:g} 0-{MAX_HOURS:g} (a mission's daylight)")
    try:
        start = parse_utc(req.time)
    except ValueError as err:
        raise InputError(f"--time: {err}") from None
    suns = suns_over_window(start, req.hours, origin.lat, origin.lon, step,
                            MIN_SUN_ELEVATION)
    if not len(suns):
        raise InputError(f"the sun stays below {MIN_SUN_ELEVATION:g} deg over the area from "
                         f"{req.time} for {req.hours:g} h: give a daytime --time")
    return suns, {"from": "--time", "time": start.isoformat(), "hours": req.hours,
                  "step_deg": step, "min_elevation_deg": MIN_SUN_ELEVATION}


def _area(req: PrepareRequest, dems):
    """The area's geodetic box, the ENU origin at its centre and the ENU extent to tile;
    InputError when ``--area`` reaches beyond the DEMs."""
    area = _area_box(req.area) if req.area else _geodetic_bounds(dems)
    origin = EnuOrigin(0.5 * (area[0] + area[2]), 0.5 * (area[1] + area[3]))
    metamap = MetaMap(dems, origin)
    if req.area:
        _check_covered(metamap, origin, area, dems)
        return area, origin, _enu_extent(origin, area)
    # the DEMs' own footprints (their geodetic box reaches beyond them)
    bounds = np.array(metamap.enu_bounds)
    extent = (bounds[:, 0].min(), bounds[:, 1].max(), bounds[:, 2].min(), bounds[:, 3].max())
    return area, origin, tuple(float(v) for v in extent)


def plan_index(req: PrepareRequest, parameters=GRAPH_PARAMETERS) -> IndexPlan:
    """Check a request and decide the index: area, origin, grid, suns, manifest.

    Raises InputError (the user's input) before any tile is built: DEMs that do not cover
    the area, bad options, no suns.
    """
    if not (math.isfinite(req.gsd) and req.gsd > 0):
        raise InputError(f"--gsd {req.gsd:g}: must be > 0 m")
    if not (64 <= req.tile_px <= 4096 and 0 <= req.overlap_px < req.tile_px):
        raise InputError(f"--tile {req.tile_px} must be 64..4096 px and --overlap "
                         f"{req.overlap_px} in [0, tile)")
    settings, default_step = graph_settings(parameters)
    dems = _open_dems(req.dems)
    try:
        area, origin, extent = _area(req, dems)
        terrain = mi.area_terrain(MetaMap(dems, origin), extent)
    finally:
        for d in dems:
            d.close()
    if terrain is None:   # an index of nothing: no tile would hold a minutia
        raise InputError("the DEMs hold no heights over the area (all voids or nodata): "
                         "nothing to index")
    grid = mi.TileGrid.covering(extent, req.gsd, req.tile_px, req.overlap_px)
    suns, sun_source = _suns(req, origin, default_step)
    # absolute: the workers may run elsewhere (another cwd, another machine's shared disk)
    paths = [str(Path(d.name).resolve()) for d in dems]
    area_record = dict(zip(("south", "west", "north", "east"), map(float, area), strict=True))
    area_record.update({"from": "--area" if req.area else "DEM extent",
                        "enu_extent": [float(v) for v in extent]})
    manifest = mi.make_manifest(area=area_record, origin=origin, grid=grid, suns=suns,
                                dems=paths, settings=settings, sun_source=sun_source,
                                terrain=terrain)
    return IndexPlan(manifest, grid, np.asarray(suns, float), paths, origin, settings)


# --------------------------------------------------------------------------- the directory
def _claim_directory(out: Path, manifest: dict, overwrite: bool) -> None:
    """Make ``out`` this index's directory: new, the same index (resume), or, with
    ``overwrite``, another index's emptied; anything else is refused."""
    manifest_path = out / mi.MANIFEST
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file: give a directory")
    if out.is_dir() and any(out.iterdir()) and not manifest_path.exists():
        raise InputError(f"--out {out} is not empty and holds no mission index: give a new "
                         "or empty directory")
    if manifest_path.exists():
        try:
            old = json.loads(manifest_path.read_text())
        except json.JSONDecodeError:
            old = {}
        differ = mi.manifest_differences(old, manifest)
        if differ and not overwrite:
            raise InputError(f"{out} holds another mission index (its {', '.join(differ)} "
                             "differ from this request's): give another --out, or "
                             "--overwrite to replace it")
        if differ:
            shutil.rmtree(out / mi.TILES, ignore_errors=True)
            manifest_path.unlink()
    out.mkdir(parents=True, exist_ok=True)
    for stale in (out / mi.TILES).glob(f".*{mi.TEMPORARY}"):   # a killed run's half files
        stale.unlink(missing_ok=True)
    mi.write_manifest(out, manifest)


# --------------------------------------------------------------------------- on a worker
_STATE: dict = {}   # per worker process: the GL context, builder and metamap, made once


def _worker_state(job: dict):
    """The worker process's (metamap, builder) for this index, made on its first task: a
    GL context and the DEMs are opened once per process, not per tile."""
    key = json.dumps([job["dems"], job["origin"], job["settings"]], sort_keys=True)
    if _STATE.get("key") != key:
        from ..core.render.renderer import create_headless_context

        if "builder" in _STATE:
            _STATE["builder"].release()
        settings = mi.IndexSettings.from_dict(job["settings"])
        ctx = _STATE.get("ctx") or create_headless_context()
        metamap = MetaMap([open_dem(p) for p in job["dems"]], EnuOrigin(**job["origin"]),
                          interpolation=settings.interpolation,
                          fill_voids=settings.fill_voids)
        _STATE.update(key=key, ctx=ctx, metamap=metamap,
                      builder=mi.TileBuilder(ctx, settings))
    return _STATE["metamap"], _STATE["builder"]


def build_tile_job(job: dict) -> dict:
    """One Dask task: the missing sun layers of one tile, written to the mission directory.

    Returns what the progress line and the summary need: the tile, layers written, seconds
    and the worker's peak resident memory (MiB).
    """
    start = time.perf_counter()
    metamap, builder = _worker_state(job)
    grid = mi.TileGrid.from_dict(job["grid"])
    col, row, todo = job["col"], job["row"], job["sun_indices"]
    suns = [job["suns"][k] for k in todo]
    layers = mi.build_tile(metamap, grid.georef(col, row), suns, builder)
    out = Path(job["out"])
    for k, layer in zip(todo, layers, strict=True):
        mi.save_tile(out / mi.layer_name(col, row, k), layer)
    return {"col": col, "row": row, "layers": len(layers),
            "minutiae": int(sum(len(layer.minutiae) for layer in layers)),
            "seconds": time.perf_counter() - start,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


# --------------------------------------------------------------------------- on the client
def _jobs(plan: IndexPlan, out: Path) -> list[dict]:
    """One job per tile with layers still missing."""
    todo: dict = {}
    for col, row, k in mi.MissionIndex(out).missing():
        todo.setdefault((col, row), []).append(k)
    common = {"dems": plan.dem_paths, "out": str(out.resolve()), "grid": plan.grid.to_dict(),
              "suns": plan.suns.tolist(), "settings": plan.settings.to_dict(),
              "origin": plan.manifest["origin"]}
    return [{**common, "col": c, "row": r, "sun_indices": ks} for (c, r), ks in todo.items()]


def _client(req: PrepareRequest):
    """A Dask client: on the cluster at ``--scheduler``, else on a new LocalCluster of
    ``--workers`` single-threaded processes (no dashboard)."""
    from dask.distributed import Client, LocalCluster

    if req.scheduler:
        return _connect(req.scheduler), None
    # The workers inherit an ignored SIGINT: a Ctrl-C reaches the terminal's whole process
    # group, and a worker stopped by it prints its traceback; the client stops them instead.
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        cluster = LocalCluster(n_workers=req.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.CRITICAL)
    finally:
        signal.signal(signal.SIGINT, previous)
    return Client(cluster), cluster


# s a scheduler has to answer in: the connection, then the handshake (a peer that is no Dask
# scheduler, an HTTP server, never completes it, or answers bytes read as a 3 EiB frame)
_SCHEDULER_TIMEOUT = 20.0


def _connect(address: str):
    """A client of the Dask scheduler at ``address``; TimeoutError (a ConnectionError for
    what the peer sent) when nothing there answers as one within :data:`_SCHEDULER_TIMEOUT`
    s, instead of waiting for ever."""
    from dask.distributed import Client

    result = {}

    def connect():
        try:
            result["client"] = Client(address, timeout=f"{_SCHEDULER_TIMEOUT:g}s")
        except BaseException as err:   # noqa: BLE001 - MemoryError from a stranger's bytes
            result["error"] = err

    thread = threading.Thread(target=connect, name="dask-connect", daemon=True)
    thread.start()
    thread.join(_SCHEDULER_TIMEOUT + 5.0)
    if "client" in result:
        return result["client"]
    err = result.get("error")
    if isinstance(err, TimeoutError | ConnectionError) or err is None:
        raise TimeoutError(f"--scheduler {address}: no Dask scheduler answered within "
                           f"{_SCHEDULER_TIMEOUT:g} s: is it a Dask scheduler's address?")
    raise ConnectionError(f"--scheduler {address}: not a Dask scheduler's answer "
                          f"({type(err).__name__}: {str(err)[:80]})")


def _directory_bytes(out: Path) -> int:
    return sum(p.stat().st_size for p in (out / mi.TILES).glob("*.npz"))


def _say(text: str) -> None:
    print(f"terrain-nav prepare: {text}", file=sys.stderr, flush=True)


def run_prepare(req: PrepareRequest) -> dict:
    """Plan, claim the directory and build the missing tiles on Dask.

    Returns the summary (also printed): tiles, suns, layers built, wall time, sizes. A
    KeyboardInterrupt stops the cluster and propagates; the tiles written so far are kept.
    """
    plan = plan_index(req)
    out = Path(req.out)
    _claim_directory(out, plan.manifest, req.overwrite)
    grid, n_suns = plan.grid, len(plan.suns)
    n_tiles = grid.cols * grid.rows
    jobs = _jobs(plan, out)
    _say(f"{n_tiles} tiles ({grid.cols} x {grid.rows}, {grid.tile_px} px overlapping "
         f"{grid.overlap_px} px at {grid.gsd:g} m) x {n_suns} suns; {len(jobs)} to build, "
         f"{n_tiles - len(jobs)} already done")
    summary = {"tiles": n_tiles, "suns": n_suns, "tiles_built": 0, "layers_built": 0,
               "peak_rss_mib": 0.0}
    start = time.perf_counter()
    if jobs:
        _run_jobs(req, jobs, summary)
    summary["wall_s"] = time.perf_counter() - start
    summary["index_bytes"] = _directory_bytes(out) + (out / mi.MANIFEST).stat().st_size
    summary["render_bytes"] = n_tiles * n_suns * grid.tile_px ** 2
    print(f"{out}: {n_tiles} tiles x {n_suns} suns; built {summary['tiles_built']} tiles "
          f"({summary['layers_built']} layers) in {summary['wall_s']:.1f} s; index "
          f"{summary['index_bytes'] / 1e6:.1f} MB on disk, the renders (8-bit grey) "
          f"{summary['render_bytes'] / 1e6:.1f} MB")
    return summary


def _run_jobs(req: PrepareRequest, jobs: list[dict], summary: dict) -> None:
    from dask.distributed import as_completed

    client, cluster = _client(req)
    try:
        futures = [client.submit(build_tile_job, job, key=f"tile-r{job['row']}-c{job['col']}",
                                 pure=False) for job in jobs]
        for done, future in enumerate(as_completed(futures), 1):
            r = future.result()
            summary["tiles_built"] += 1
            summary["layers_built"] += r["layers"]
            summary["peak_rss_mib"] = max(summary["peak_rss_mib"], r["peak_rss_mib"])
            _say(f"tile {done}/{len(jobs)} (row {r['row']}, col {r['col']}): {r['layers']} "
                 f"layers, {r['minutiae']} minutiae, {r['seconds']:.1f} s")
    finally:
        client.close(timeout=10)
        if cluster is not None:
            cluster.close(timeout=10)


def parse_suns(text: str) -> list[tuple[float, float]]:
    """``--suns 120/35,135/40`` -> [(120.0, 35.0), (135.0, 40.0)]."""
    out = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        try:
            az, el = (float(v) for v in item.split("/"))
        except ValueError:
            raise InputError(f"--suns {text}: give AZ/EL pairs in degrees, comma separated "
                             "(e.g. 120/35,135/40)") from None
        out.append((az, el))
    if not out:
        raise InputError("--suns: no sun given")
    return out


def parse_area(text: str) -> tuple[float, float, float, float]:
    """``--area 44.2,5.2,44.6,5.8`` -> (44.2, 5.2, 44.6, 5.8)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(map(math.isfinite, values)):
        raise InputError(f"--area {text}: give LAT,LON,LAT,LON (two opposite corners, "
                         "degrees)")
    return values


def request_from_args(args) -> PrepareRequest:
    """The request of parsed ``prepare`` options."""
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers {args.workers}: must be >= 1")
    return PrepareRequest(
        dems=list(args.dem), out=Path(args.out), gsd=args.gsd,
        area=parse_area(args.area) if args.area else None,
        suns=parse_suns(args.suns) if args.suns else None, time=args.time, hours=args.hours,
        sun_step=args.sun_step, tile_px=args.tile, overlap_px=args.overlap,
        scheduler=args.scheduler, workers=args.workers, overwrite=args.overwrite)


def interrupted_message(out: Path) -> str:
    """What an interrupted preparation says: what is kept and how to finish."""
    try:
        index = mi.MissionIndex(out)
        left = len({(c, r) for c, r, _ in index.missing()})
        done = index.grid.cols * index.grid.rows - left
        kept = f"{done} finished tiles kept in {out}, {left} to go"
    except (mi.MissionIndexError, OSError):
        kept = "nothing built yet"
    return f"interrupted: {kept}; run the same command again to resume"

