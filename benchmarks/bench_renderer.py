"""Landmark renderer benchmark: frame rates, distance-map build time, steps vs agreement.

Run: ``.venv/bin/python benchmarks/bench_renderer.py`` (prints; asserts nothing).

DEMs: a 512^2 window of ``bigtujunga_srtm30m_utm11.tif`` (UTM, 30 m) and a 1024^2 tile from
``N44E005.hgt`` (SRTM3, 3 arc-seconds) resampled to a square 66 m grid (the E-W spacing at
44.5 N), both from ``$TERRAIN_NAV_DATA/dem`` (default ../shared/data/dem). Without them it
falls back to matplotlib's Jacksboro fault sample DEM, tiled/zoomed to size.
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial
from pathlib import Path

import numpy as np
from scipy import ndimage

from terrain_nav_ros.core.render.raycast_reference import ReferenceRaycaster
from terrain_nav_ros.core.render.renderer import (
    LandmarkRenderer,
    PinholeCamera,
    RendererError,
    TerrainFrame,
    build_distance_map,
    create_headless_context,
    distance_map_shape,
)
from terrain_nav_ros.core.terrain.georef import GeoReference

DATA = Path(os.environ.get("TERRAIN_NAV_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data")) / "dem"


def _jacksboro(size: int) -> tuple[np.ndarray, float]:
    from matplotlib import cbook
    dem = cbook.get_sample_data("jacksboro_fault_dem.npz")["elevation"].astype(float)
    return ndimage.zoom(dem, (size / dem.shape[0], size / dem.shape[1]), order=1), 10.0


def load_dem_512() -> tuple[np.ndarray, float, str]:
    path = DATA / "bigtujunga_srtm30m_utm11.tif"
    if path.exists():
        import rasterio
        with rasterio.open(path) as src:
            h = src.read(1, window=((0, 512), (300, 812))).astype(float)
            return h, float(src.res[0]), path.name
    h, gsd = _jacksboro(512)
    return h, gsd, "jacksboro_fault_dem (zoomed)"


def load_dem_1024() -> tuple[np.ndarray, float, str]:
    path = DATA / "N44E005.hgt"
    if path.exists():
        import rasterio
        with rasterio.open(path) as src:
            a = src.read(1).astype(float)
        a[a < -1000] = np.nan  # SRTM voids
        if np.isnan(a).any():
            a[np.isnan(a)] = np.nanmedian(a)
        ns, ew = 3 / 3600 * 111_320.0, 3 / 3600 * 111_320.0 * np.cos(np.radians(44.5))
        rows = int(np.ceil(1024 * ew / ns)) + 1
        h = ndimage.zoom(a[:rows, :1024], (ns / ew, 1.0), order=1)[:1024, :1024]
        return h, float(ew), f"{path.name} (resampled to {ew:.1f} m)"
    h, gsd = _jacksboro(1024)
    return h, gsd, "jacksboro_fault_dem (zoomed)"


def look_at(position, target) -> np.ndarray:
    """Optical -> ENU rotation of a level-roll camera aimed at ``target``."""
    f = np.asarray(target, float) - position
    f /= np.linalg.norm(f)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(f, x), f], axis=1)


def oblique_pose(h: np.ndarray, g: GeoReference, back: float, above: float):
    """Camera ``back`` x tile size south-west of the centre, ``above`` m over the highest peak."""
    cx, cy = g.centre
    span = g.width * g.gsd
    pos = np.array([cx - back * span, cy - back * span, h.max() + above])
    return pos, look_at(pos, [cx, cy, float(h.mean())])


def fps(fn, min_time: float = 1.5, min_frames: int = 5) -> tuple[float, float]:
    """(median, best) frames per second of ``fn``; the best frame is the least disturbed by
    other processes on a shared machine."""
    fn()  # warm-up: shader compile, FBO allocation
    times, t_start = [], time.perf_counter()
    while len(times) < min_frames or time.perf_counter() - t_start < min_time:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1.0 / float(np.median(times)), 1.0 / min(times)


def agreement(gpu, ref, cell: float) -> float:
    dist = np.linalg.norm(gpu.hit_enu - ref.hit_enu, axis=-1)
    both = gpu.mask & ref.mask
    return float(((gpu.mask == ref.mask) & (~both | (dist <= 0.5 * cell))).mean())


def bench_frame_rates(ctx) -> None:
    print("== frame rates (llvmpipe)" if "llvmpipe" in ctx.info["GL_RENDERER"]
          else f"== frame rates ({ctx.info['GL_RENDERER']})")
    for size, loader in ((512, load_dem_512), (1024, load_dem_1024)):
        h, gsd, name = loader()
        g = GeoReference(0.0, size * gsd, gsd, size, size)
        r = LandmarkRenderer(ctx)
        t0 = time.perf_counter()
        r.set_terrain(h, g)
        t_set = time.perf_counter() - t0
        print(f"{size}^2 tile from {name}: relief {np.ptp(h):.0f} m, set_terrain {t_set:.3f} s,"
              f" distance map {r.distance_map.shape_xyz} voxels")
        for shadows in (False, True):
            med, best = fps(partial(r.render_nadir, sun=(315.0, 35.0), shadows=shadows))
            print(f"  nadir {size}x{size} shadows={shadows!s:5}: {med:6.1f} fps median, "
                  f"{best:6.1f} best")
        cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
        pos, rot = oblique_pose(h, g, 0.3, 1500.0)
        for shadows in (False, True):
            view = partial(r.render_perspective, cam, pos, rot, (315.0, 35.0), shadows=shadows)
            med, best = fps(view)
            res = view()
            print(f"  perspective 640x480 oblique shadows={shadows!s:5}: {med:6.1f} fps median, "
                  f"{best:6.1f} best ({res.mask.mean():.0%} terrain, {res.unresolved} unresolved)")
        r.release()


def bench_distance_map() -> None:
    print("== distance map build (CPU, scipy EDT), 1024^2 tile")
    h, gsd, _ = load_dem_1024()
    g = GeoReference(0.0, 1024 * gsd, gsd, 1024, 1024)
    frame = TerrainFrame.from_heights(h, g)
    for cells in (2, 4, 8):
        shape = distance_map_shape(frame, cells, max_size=512)
        t0 = time.perf_counter()
        build_distance_map(h, frame, shape)
        print(f"  {cells} cells/voxel -> {shape} voxels: {time.perf_counter() - t0:.3f} s")


def bench_tradeoff(ctx) -> None:
    """Steps budget x distance-map resolution x slope steps vs speed and reference agreement."""
    h, gsd, name = load_dem_512()
    h = h[128:384, 128:384]
    g = GeoReference(0.0, 256 * gsd, gsd, 256, 256)
    cam = PinholeCamera(200.0, 200.0, 127.5, 95.5, 256, 192)
    pos, rot = oblique_pose(h, g, 0.25, 300.0)  # low: long grazing rays
    t0 = time.perf_counter()
    ref = ReferenceRaycaster(h, g).render_perspective(cam, pos, rot, (315.0, 35.0))
    print(f"== steps / distance-map resolution vs speed and agreement ({name}, 256^2 tile, "
          f"256x192 low oblique view, {ref.mask.mean():.0%} terrain; reference "
          f"{time.perf_counter() - t0:.1f} s)")
    print("  slope  cells/voxel  voxels        max_steps  best fps  agree(<=0.5 cell)  unresolved")
    for slope in (True, False):
        for cells in (2, 4, 8, 16):
            r = LandmarkRenderer(ctx, cells_per_voxel=cells, slope_steps=slope)
            r.set_terrain(h, g)
            for steps in (16, 32, 64, 128, 256):
                r.max_steps = steps
                view = partial(r.render_perspective, cam, pos, rot, (315.0, 35.0))
                try:
                    f = fps(view, min_time=0.5)[1]
                except RendererError as exc:  # every ray out of steps
                    print(f"  {slope!s:5}  {cells:11}  {'':13} {steps:9}  {exc}")
                    continue
                gpu = view()
                print(f"  {slope!s:5}  {cells:11}  {str(r.distance_map.shape_xyz):13} {steps:9}"
                      f" {f:9.1f}  {agreement(gpu, ref, gsd):17.4f}  {gpu.unresolved:10}")
            r.release()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-table", action="store_true", help="skip the trade-off table")
    args = parser.parse_args()
    ctx = create_headless_context()
    print(f"GL: {ctx.info['GL_RENDERER']} / {ctx.info['GL_VERSION']}, cpus: {os.cpu_count()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    bench_frame_rates(ctx)
    bench_distance_map()
    if not args.skip_table:
        bench_tradeoff(ctx)


if __name__ == "__main__":
    main()
