"""Metamap benchmark: DEM refinement accuracy/speed and ROI serving from a 10812^2 tile.

(a) Each real DEM (../shared/data, plus matplotlib's embedded one) is decimated 2x and 4x by
    block mean and refined back by each method; prints RMSE against the original and the time
    per output megapixel.
(b) A 10812 x 10812 float32 tile (a USGS 1/3 arc-second tile's size, 1/10800 deg cells in
    EPSG:4326) is generated once in /tmp by upsampling a real DEM, stored three ways (striped
    GeoTIFF -> numpy memmap, tiled GeoTIFF -> rasterio windowed reads, raw .npy memmap). Each
    is opened in a fresh process, which serves 1024 x 1024 ROIs at native GSD around random
    centres; prints the median/p90 time per ROI and the process's resident memory.

Reports only; asserts nothing. Usage::

    .venv/bin/python benchmarks/bench_metamap.py [--data ../shared/data] [--repeats 40]
        [--skip-rmse] [--skip-serve] [--tile-dir /tmp]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrain_nav_ros.core.terrain.dem_io import open_dem, sample_dem  # noqa: E402
from terrain_nav_ros.core.terrain.interpolation import decimate, refine  # noqa: E402

TILE = 10812
CELL_DEG = 1.0 / 10800  # 1/3 arc-second
TILE_WEST, TILE_NORTH = -119.0 - 6 * CELL_DEG, 35.0 + 6 * CELL_DEG  # USGS-style 6-cell overlap

REAL = [("dem/N44E005.hgt", 0.72), ("dem/bigtujunga_srtm30m_utm11.tif", 1.0),
        ("dem/front_range_srtm3.asc", 0.76), ("dem/gredos_25m_epsg23030.tif", 1.0),
        ("dem/halffork_5m.asc", 1.0), ("imagery/rmnp_dem_4326.tif", 1.0),
        ("imagery/swellendam_srtm3_4326.tif", 0.83)]
METHODS = ("nearest", "bilinear", "bicubic", "spline", "idw")


# -- (a) refinement ---------------------------------------------------------------------
def bench_refinement(data: Path, idw_k: int, idw_power: float):
    dems = [("jacksboro_fault_dem.npz", sample_dem().read(), 0.80)]
    if (data / "dem").is_dir():
        dems += [(rel.split("/")[1], open_dem(data / rel).read(), a) for rel, a in REAL]
    else:
        print(f"(real DEMs not found at {data}: matplotlib DEM only)")
    print(f"\n(a) decimate (block mean) then refine back; RMSE in metres vs the original, "
          f"time in ms per output megapixel; IDW k={idw_k}, power={idw_power}")
    head = f"{'DEM':34s} {'x':>2s} " + " ".join(f"{m:>15s}" for m in METHODS)
    print(head)
    print("-" * len(head))
    totals = {m: [] for m in METHODS}
    for name, z, aspect in dems:
        for f in (2, 4):
            coarse = decimate(z, f)
            truth = z[:coarse.shape[0] * f, :coarse.shape[1] * f]
            cells = []
            for m in METHODS:
                t0 = time.perf_counter()
                out = refine(coarse, f, m, k=idw_k, power=idw_power, aspect=aspect)
                dt = time.perf_counter() - t0
                ok = ~np.isnan(out) & ~np.isnan(truth)
                rmse = float(np.sqrt(np.mean((out[ok] - truth[ok]) ** 2)))
                ms_per_mp = 1e3 * dt / (out.size / 1e6)
                totals[m].append((rmse, ms_per_mp))
                cells.append(f"{rmse:6.2f} {ms_per_mp:7.0f}ms")
            print(f"{name:34s} {f:2d} " + " ".join(f"{c:>15s}" for c in cells))
    print("-" * len(head))
    print(f"{'median over DEMs and factors':37s} " + " ".join(
        f"{np.median([r for r, _ in totals[m]]):6.2f} {np.median([t for _, t in totals[m]]):7.0f}ms"
        for m in METHODS))


# -- (b) serving ------------------------------------------------------------------------
def _generate(tile_dir: str, data: str):
    """Child process: build the 10812^2 float32 tile (once) in three storage layouts."""
    import cv2
    import rasterio
    from affine import Affine

    tile_dir = Path(tile_dir)
    paths = {"striped GeoTIFF (memmap)": tile_dir / "tn_bench_10812_striped.tif",
             "tiled GeoTIFF (rasterio)": tile_dir / "tn_bench_10812_tiled.tif",
             "raw .npy (np.load mmap)": tile_dir / "tn_bench_10812.npy"}
    if all(p.exists() for p in paths.values()):
        return {k: str(v) for k, v in paths.items()}
    src = Path(data) / "dem/bigtujunga_srtm30m_utm11.tif"
    base = open_dem(src).read() if src.exists() else sample_dem().read()
    # mirror-tile to 2 x 2 (seamless) and upsample: real relief at 1/3" density
    quad = np.block([[base, base[:, ::-1]], [base[::-1], base[::-1, ::-1]]])
    z = cv2.resize(quad, (TILE, TILE), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    del quad
    transform = Affine(CELL_DEG, 0, TILE_WEST, 0, -CELL_DEG, TILE_NORTH)
    common = dict(driver="GTiff", width=TILE, height=TILE, count=1, dtype="float32",
                  crs="EPSG:4326", transform=transform, nodata=-9999.0, BIGTIFF="YES")
    with rasterio.open(paths["striped GeoTIFF (memmap)"], "w", **common) as ds:
        ds.write(z, 1)
    with rasterio.open(paths["tiled GeoTIFF (rasterio)"], "w", tiled=True, blockxsize=256,
                       blockysize=256, **common) as ds:
        ds.write(z, 1)
    np.save(paths["raw .npy (np.load mmap)"], z)
    return {k: str(v) for k, v in paths.items()}


def _serve(label: str, path: str, repeats: int, interpolation: str, seed: int, env: dict,
           options: dict):
    """Child process: open one tile, serve ROIs, report timings and memory."""
    import psutil

    os.environ.update(env)  # before GDAL's block cache is first used

    from terrain_nav_ros.core.terrain.dem_io import Dem
    from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
    from terrain_nav_ros.core.terrain.metamap import MetaMap

    proc = psutil.Process()
    rss0 = proc.memory_info().rss
    if path.endswith(".npy"):
        from affine import Affine

        dem = Dem.from_array(np.load(path, mmap_mode="r"),
                             Affine(CELL_DEG, 0, TILE_WEST, 0, -CELL_DEG, TILE_NORTH),
                             "EPSG:4326", -9999.0, path)
    else:
        dem = open_dem(path)
    centre_lon, centre_lat = TILE_WEST + TILE * CELL_DEG / 2, TILE_NORTH - TILE * CELL_DEG / 2
    mm = MetaMap(dem, EnuOrigin(centre_lat, centre_lon, 1000.0), interpolation=interpolation,
                 **options)
    gsd = mm.native_gsd
    rss_open = proc.memory_info().rss
    rng = np.random.default_rng(seed)
    half = 0.4 * TILE * gsd  # keep the 1024^2 ROI inside the tile
    times = []
    t0 = time.perf_counter()
    first = mm.tile_at(0.0, 0.0, gsd, 1024, 1024)
    first_ms = 1e3 * (time.perf_counter() - t0)
    cpu = []
    for _ in range(repeats):
        e, n = rng.uniform(-half, half, 2)
        t0, c0 = time.perf_counter(), time.process_time()
        tile = mm.tile_at(e, n, gsd, 1024, 1024)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    if first.valid_fraction < 0.99 or tile.valid_fraction < 0.99:
        print(f"warning: ROI not fully inside the tile ({tile.valid_fraction:.3f})")
    return dict(label=label, interpolation=interpolation, gsd=gsd, first_ms=first_ms,
                median_ms=1e3 * np.median(times), p90_ms=1e3 * np.percentile(times, 90),
                min_ms=1e3 * np.min(times), cpu_ms=1e3 * np.median(cpu), rss0=rss0 / 2**20,
                rss_open=rss_open / 2**20, rss=proc.memory_info().rss / 2**20,
                anon=_anonymous_mb())


def _anonymous_mb() -> float:
    """Anonymous (heap, not file-backed) resident memory of this process, MB (Linux)."""
    try:
        for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
            if line.startswith("Anonymous:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def bench_serving(data: Path, tile_dir: str, repeats: int):
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    with ctx.Pool(1) as pool:
        paths = pool.apply(_generate, (tile_dir, str(data)))
    print(f"\n(b) 1024 x 1024 ROI at native GSD from a {TILE} x {TILE} float32 tile "
          f"({TILE * TILE * 4 / 2**20:.0f} MB; tiles ready in {time.perf_counter() - t0:.1f} s); "
          f"{repeats} random centres, each layout in a fresh process; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    head = (f"{'storage':26s} {'interp':9s} {'GSD m':>6s} {'first ms':>9s} {'min ms':>7s} "
            f"{'median ms':>10s} {'p90 ms':>7s} {'CPU ms':>7s} {'RSS idle':>9s} {'RSS open':>9s} "
            f"{'RSS end':>8s} {'anon end':>9s}")
    print(head)
    print("-" * len(head))
    tiled = "tiled GeoTIFF (rasterio)"
    striped = "striped GeoTIFF (memmap)"
    node = {"fill_voids": True, "heights": "enu"}  # what the metamap node asks for
    runs = [(label, "bilinear", {}, {}, label) for label in paths] + [
        (tiled, "bilinear", {"GDAL_CACHEMAX": "64"}, {}, "tiled, GDAL_CACHEMAX=64MB"),
        (striped, "nearest", {}, {}, striped), (striped, "bicubic", {}, {}, striped),
        (striped, "spline", {}, {}, striped),
        (striped, "bilinear", {}, node, "striped, fill_voids+ENU up"),
        (striped, "bicubic", {}, node, "striped, fill_voids+ENU up")]
    for i, (label, interp, env, options, shown) in enumerate(runs):
        with ctx.Pool(1) as pool:
            r = pool.apply(_serve, (label, paths[label], repeats, interp, i, env, options))
        r["label"] = shown
        print(f"{r['label']:26s} {r['interpolation']:9s} {r['gsd']:6.2f} {r['first_ms']:9.1f} "
              f"{r['min_ms']:7.1f} {r['median_ms']:10.1f} {r['p90_ms']:7.1f} {r['cpu_ms']:7.1f} "
              f"{r['rss0']:8.0f}M "
              f"{r['rss_open']:8.0f}M {r['rss']:7.0f}M {r['anon']:8.0f}M")
    print("Wall times share 2 cores with whatever else runs; 'CPU ms' is the median process CPU "
          "time per ROI (all threads).")
    print("RSS: resident set (memmap windows are released after each read with "
          "MADV_DONTNEED);\n'anon' is the process's own heap (numpy buffers, GDAL block "
          f"cache). Load average at end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path(
        os.environ.get("TERRAIN_NAV_DATA", REPO.parent / "shared" / "data")))
    parser.add_argument("--tile-dir", default="/tmp")
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--idw-k", type=int, default=8)
    parser.add_argument("--idw-power", type=float, default=2.0)
    parser.add_argument("--skip-rmse", action="store_true")
    parser.add_argument("--skip-serve", action="store_true")
    args = parser.parse_args(argv)
    if not args.skip_rmse:
        bench_refinement(args.data, args.idw_k, args.idw_power)
    if not args.skip_serve:
        bench_serving(args.data, args.tile_dir, args.repeats)


if __name__ == "__main__":
    main()
