"""Relocalising a camera view anywhere in a mission area (issue 24).

Run from the repository root::

    .venv/bin/python benchmarks/bench_relocalise.py [--dem ../shared/data/dem/N44E005.hgt]
        [--gsd 30] [--cases 20] [--controls 10] [--mission DIR]

The mission index of the whole DEM (default: the 1 x 1 deg N44E005 SRTM3 tile, ~80 x 110
km) at ``--gsd`` for one sun is built with ``terrain-nav prepare`` (2 Dask workers) into
``--mission`` unless it is there already, and its tiles are loaded and prepared as the
matcher node does on its first search (:class:`~terrain_nav_ros.core.matching.relocaliser.
MissionSearch`). Camera views of ``--view`` px are cut anywhere in the area from a render
with another albedo and the camera effects of the block study, turned by any heading
(+-180 deg) and scaled by +-10 %, and each is searched in every tile
(:func:`~terrain_nav_ros.core.matching.global_search.relocalise`, the graph's threshold).
Controls: views of another DEM (``--control-dem``) and, with ``--real-controls N``, N views
(160 px, any heading) of each real image of ``benchmarks/real_scenes.yaml`` at the index's
GSD (real albedo: fields, forest, snow, clouds), none of which may be relocalised.

Prints (no assertions): views relocalised within 3 px, 3-10 px off, at a wrong place (more
than 10 px off), not relocalised (with the reasons), controls accepted, the median and p95
CPU time per query on one core (extraction of the view included), the time to load and
prepare the tiles, and the process's peak memory.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
             "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrain_nav_ros.core.features.minutiae import FeatureExtractor  # noqa: E402
from terrain_nav_ros.core.matching.global_search import relocalise  # noqa: E402
from terrain_nav_ros.core.matching.matcher import warm_up  # noqa: E402
from terrain_nav_ros.core.matching.mission_index import MissionIndex  # noqa: E402
from terrain_nav_ros.core.matching.params import MatchParams  # noqa: E402
from terrain_nav_ros.core.matching.relocaliser import MissionSearch  # noqa: E402
from terrain_nav_ros.core.render.camera_effects import apply_camera_effects  # noqa: E402
from terrain_nav_ros.core.terrain.dem_io import open_dem  # noqa: E402
from terrain_nav_ros.core.terrain.georef import GeoReference  # noqa: E402
from terrain_nav_ros.core.terrain.metamap import MetaMap  # noqa: E402
from terrain_nav_ros.tools import cli  # noqa: E402
from terrain_nav_ros.tools.evaluation import (  # noqa: E402
    GROSS_PX,
    CameraModel,
    camera_renders,
)

cv2.setNumThreads(1)
GRAPH_THRESHOLD = 8.6
DATA = REPO.parent / "shared" / "data" / "dem"


def _camera(dem_path: str, georef: GeoReference, sun, origin=None):
    """Camera RGB of ``georef`` (in the ENU frame of ``origin``, default the DEM's centre):
    the graph's renderer with another albedo than the landmarks'."""
    tile = MetaMap(open_dem(dem_path), origin, interpolation="spline",
                   fill_voids=True).tile(georef)
    elev = np.where(tile.nodata, np.nanmedian(tile.elevation), tile.elevation)
    return camera_renders(elev, georef, [sun])[0]


def _dem_extent(dem_path: str, gsd: float) -> GeoReference:
    """The DEM's whole extent at ``gsd``, around its centre."""
    w, e, s, n = MetaMap(open_dem(dem_path)).enu_bounds[0]
    return GeoReference.centred(0.5 * (w + e), 0.5 * (s + n), gsd, int((e - w) / gsd) - 2,
                                int((n - s) / gsd) - 2)


def _mission(args, sun) -> MissionIndex:
    """The mission index of the DEM for ``sun``, built unless it is there."""
    out = Path(args.mission or REPO / "out" / "bench_relocalise" /
               f"{Path(args.dem).stem}_{args.gsd:g}m_{sun[0]:g}_{sun[1]:g}")
    if not (out / "manifest.json").exists():
        t0 = time.perf_counter()
        code = cli.main(["prepare", "--dem", args.dem, "--gsd", f"{args.gsd:g}", "--out",
                         str(out), "--suns", f"{sun[0]:g}/{sun[1]:g}", "--workers", "2"])
        if code != 0:
            raise SystemExit(code)
        print(f"prepared {out} in {time.perf_counter() - t0:.0f} s (2 workers)")
    return MissionIndex(out)


def _views(camera_rgb, n: int, size: int, rng):
    """``n`` camera views: (grey view, true centre (col, row) in the area)."""
    h, w = camera_rgb.shape[:2]
    c = 0.5 * (size - 1)
    effects = CameraModel().effects
    out = []
    for _ in range(n):
        theta = math.radians(rng.uniform(-180.0, 180.0))
        s = 1.0 + rng.uniform(-0.1, 0.1)
        cx, cy = rng.uniform(size, w - size), rng.uniform(size, h - size)
        a, b = s * math.cos(theta), s * math.sin(theta)
        m = np.array([[a, b, 0.0], [-b, a, 0.0]])      # view px -> area px
        m[:, 2] = np.array([cx, cy]) - m[:, :2] @ np.array([c, c])
        view = cv2.warpAffine(camera_rgb, m, (size, size),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        view = apply_camera_effects(view, np.full((size, size), 1500.0, np.float32), effects,
                                    rng)
        out.append((cv2.cvtColor(view, cv2.COLOR_RGB2GRAY), np.array([cx, cy])))
    return out


def _real_views(n: int, gsd: float, rng, size: int = 160):
    """``n`` views of each real image at ``gsd`` (benchmarks/real_scenes.yaml), any
    heading."""
    from terrain_nav_ros.tools import real_imagery as ri

    scenes = ri.load_scenes(REPO / "benchmarks" / "real_scenes.yaml",
                            REPO.parent / "shared" / "data" / "imagery")
    return [case.view for scene in scenes if abs(scene.gsd - gsd) < 0.5
            for case in ri._cut_cases(scene, size, n, False, 1.0, rng)]


def _query(matcher, extractor, grey, tiles):
    """(Relocalisation, CPU seconds) of one view, its extraction included."""
    t0 = time.process_time()
    f = extractor(grey)
    centre = (0.5 * (grey.shape[1] - 1), 0.5 * (grey.shape[0] - 1))
    found = relocalise(matcher, matcher.index(f.minutiae, f.creases.skeleton(), f.ridges),
                       tiles, view_centre=centre)
    return found, time.process_time() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dem", default=str(DATA / "N44E005.hgt"))
    ap.add_argument("--control-dem", default=str(DATA / "front_range_srtm3.asc"))
    ap.add_argument("--gsd", type=float, default=30.0)
    ap.add_argument("--view", type=int, default=256)
    ap.add_argument("--mission", help="mission index directory (built when missing)")
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--controls", type=int, default=10)
    ap.add_argument("--real-controls", type=int, default=0,
                    help="views of each real image (benchmarks/real_scenes.yaml) as controls")
    ap.add_argument("--sun", default="135,45", help="azimuth,elevation (deg)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--verbose", action="store_true", help="one line per view")
    args = ap.parse_args()
    sun = tuple(float(v) for v in args.sun.split(","))
    rng = np.random.default_rng(args.seed)

    params = MatchParams(threshold=GRAPH_THRESHOLD)
    warm_up(params)
    mission = _mission(args, sun)
    search = MissionSearch(mission, params)
    matcher = search.matcher
    t0 = time.process_time()
    tiles = search.tiles_for(sun)
    t1 = time.process_time()
    # the views are cut from the area prepared (the DEMs' extent), not the tiles beyond it
    west, east, south, north = mission.manifest["area"]["enu_extent"]
    georef = GeoReference(west, north, mission.gsd, int((east - west) / mission.gsd),
                          int((north - south) / mission.gsd))
    camera = _camera(args.dem, georef, sun, mission.origin)
    print(f"{Path(args.dem).name}: {georef.width} x {georef.height} px at {mission.gsd:g} m "
          f"({georef.width * mission.gsd / 1e3:.0f} x {georef.height * mission.gsd / 1e3:.0f}"
          f" km), {len(tiles)} tiles of {mission.grid.tile_px} px (overlap "
          f"{mission.grid.overlap_px}); tiles loaded and prepared in {t1 - t0:.1f} s CPU")

    extractor = FeatureExtractor(ridges=True)
    ok = off = wrong = 0
    reasons, times = Counter(), []
    for k, (grey, truth) in enumerate(_views(camera, args.cases, args.view, rng)):
        found, seconds = _query(matcher, extractor, grey, tiles)
        times.append(seconds)
        if found.matched:
            col, row = georef.enu_to_pixel(*found.position)
            err = math.hypot(float(col) - truth[0], float(row) - truth[1])
            ok += err <= 3.0
            off += 3.0 < err <= GROSS_PX
            wrong += err > GROSS_PX
            line = f"score {found.score:.1f} (runner-up {found.runner_up:.1f}) err {err:.1f} px"
        else:
            reasons[found.reason.split(":")[0]] += 1
            line = found.reason
        if args.verbose:
            print(f"  view {k}: {seconds:.2f} s, {line}")

    accepted, control_times, best_control = 0, [], -math.inf
    if args.controls:
        other = _camera(args.control_dem, _dem_extent(args.control_dem, args.gsd), sun)
        for grey, _ in _views(other, args.controls, args.view, rng):
            found, seconds = _query(matcher, extractor, grey, tiles)
            control_times.append(seconds)
            accepted += found.matched
            best_control = max(best_control, found.score)

    real = _real_views(args.real_controls, mission.gsd, rng) if args.real_controls else []
    real_accepted, best_real = 0, -math.inf
    for grey in real:
        found, _ = _query(matcher, extractor, grey, tiles)
        real_accepted += found.matched
        best_real = max(best_real, found.score)

    t = np.array(times)
    print(f"relocalised within 3 px: {ok}/{args.cases}, 3-{GROSS_PX:g} px off: {off}, at a wrong "
          f"place: {wrong}, not relocalised: {args.cases - ok - off - wrong} {dict(reasons)}")
    print(f"CPU per query (one core): median {np.median(t):.2f} s, p95 "
          f"{np.percentile(t, 95):.2f} s, max {t.max():.2f} s")
    if args.controls:
        print(f"controls ({Path(args.control_dem).name} views): {accepted}/{args.controls} "
              f"accepted, best area score {best_control:.1f} (threshold {GRAPH_THRESHOLD})")
    if real:
        print(f"controls (real images): {real_accepted}/{len(real)} accepted, best area score "
              f"{best_real:.1f}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory of the process: {peak:.0f} MB")


if __name__ == "__main__":
    main()
