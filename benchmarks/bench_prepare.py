"""Mission index build benchmark (issue 24): ``terrain-nav prepare`` over a whole DEM tile.

For each GSD and each number of Dask workers, builds the mission index of the whole DEM (the
area defaults to its extent) from scratch into a temporary directory, through the same
function as the command (a LocalCluster of that many single-threaded worker processes), and
prints: tiles, suns, layers, build wall time (cluster start-up included), the speed-up over
one worker, the index's size on disk against the size of its renders (8-bit grey, one per
tile and sun), the largest peak resident memory of a worker process, and the time to load
one layer back (:meth:`MissionIndex.load`). The suns are those of a flight window at the
DEM's centre (``--time``, ``--hours``, one every ``max_sun_change`` degrees by default).

Target (issue 24): the 1 x 1 degree N44E005 tile in <= 10 min on the 2-core machine, index
on disk <= the renders. Reports only; asserts nothing. Usage::

    .venv/bin/python benchmarks/bench_prepare.py [--dem ../shared/data/dem/N44E005.hgt]
        [--gsd 90,30] [--workers 1,2] [--time 2024-06-21T08:00:00Z] [--hours 2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrain_nav_ros.core.matching.mission_index import MissionIndex  # noqa: E402
from terrain_nav_ros.tools.prepare import PrepareRequest, run_prepare  # noqa: E402


def load_ms(out: Path, samples: int = 20) -> float:
    """Median milliseconds to load one layer of the index at ``out``."""
    index = MissionIndex(out)
    tiles = index.tiles()
    rng = np.random.default_rng(0)
    times = []
    for _ in range(samples):
        tile = tiles[rng.integers(len(tiles))]
        t0 = time.perf_counter()
        index.load(tile.col, tile.row, int(rng.integers(len(index.suns))))
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dem", default=str(REPO.parent / "shared/data/dem/N44E005.hgt"))
    ap.add_argument("--gsd", default="90", help="comma-separated GSDs [m]")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--time", default="2024-06-21T08:00:00Z")
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--tile", type=int, default=768)
    ap.add_argument("--overlap", type=int, default=256)
    args = ap.parse_args(argv)
    rows = []
    for gsd in (float(g) for g in args.gsd.split(",")):
        base = None
        for workers in (int(w) for w in args.workers.split(",")):
            with tempfile.TemporaryDirectory(prefix="bench_prepare_") as tmp:
                out = Path(tmp) / "index"
                req = PrepareRequest(dems=[args.dem], out=out, gsd=gsd, time=args.time,
                                     hours=args.hours, tile_px=args.tile,
                                     overlap_px=args.overlap, workers=workers)
                t0 = time.perf_counter()
                s = run_prepare(req)
                wall = time.perf_counter() - t0
                base = base or wall
                rows.append((gsd, workers, s["tiles"], s["suns"], s["layers_built"], wall,
                             base / wall, s["index_bytes"], s["render_bytes"],
                             s["peak_rss_mib"], load_ms(out)))
    print(f"\nmission index of {Path(args.dem).name}, suns from {args.time} for "
          f"{args.hours:g} h, tiles {args.tile} px overlapping {args.overlap} px")
    head = ("| GSD | workers | tiles | suns | layers | build wall | speed-up | index on disk "
            "| renders (8-bit) | ratio | peak RSS / worker | load a layer |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for (gsd, w, tiles, suns, layers, wall, speedup, index_b, render_b, rss, ms) in rows:
        print(f"| {gsd:g} m | {w} | {tiles} | {suns} | {layers} | {wall:.1f} s | "
              f"{speedup:.2f}x | {index_b / 1e6:.1f} MB | {render_b / 1e6:.1f} MB | "
              f"{index_b / render_b:.2f} | {rss:.0f} MiB | {ms:.1f} ms |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
