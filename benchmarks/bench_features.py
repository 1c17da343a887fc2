#!/usr/bin/env python3
"""Feature-extractor benchmark: speed per image size and repeatability across lighting.

Reports (never asserts):

* single-thread time per image at 512^2, 1024^2, 2048^2 (targets 40 / 160 / 700 ms median)
  with the share of each stage, on hillshades of the real SRTM tile N44E005;
* repeatability on real DEMs (../shared/data/dem): the same patch shaded with the sun at
  az 315 / el 45 and at az 135 / el 30, and DEM-direct creases vs the shaded image, with
  controls (DEM vs DEM + GSD/30 noise; sun elevation 45 vs 40 deg) that show the detector's
  own stability. A minutia is repeated when the other set has one within 2 px and 20 deg
  (one-to-one, kinds ignored: a crease end seen with the opposite polarity can be a fork);
  the rate is matches / min(n_a, n_b) (Mikolajczyk's repeatability), also given as
  matches / mean;
* the same rate against the size of the sun change (``--sun-sweep``: azimuth +0 ... +180 deg
  at elevation 45, elevation 45 vs 40 ... 20) for raw shading and the compensated input;
* DEM-direct vs shaded-image creases at the crease level (``--crease-agreement``): how much
  of each skeleton lies within 1 / 2 px of the other, the best-fitting shift, and minutia
  matches by position only.

* equivalence of two versions of the extractor (``--save-minutiae`` with the old code,
  ``--compare-minutiae`` with the new): the minutiae of real hillshades and DEMs are matched
  one-to-one within 1 px and the same type; reports counts, the matched share and the
  count change.

Usage::

    .venv/bin/python benchmarks/bench_features.py              # everything
    .venv/bin/python benchmarks/bench_features.py --no-timing  # repeatability only
    .venv/bin/python benchmarks/bench_features.py --sun-sweep  # vs size of the sun change
    .venv/bin/python benchmarks/bench_features.py --crease-agreement  # DEM vs shaded creases
    .venv/bin/python benchmarks/bench_features.py --save-minutiae /tmp/before.npz
    .venv/bin/python benchmarks/bench_features.py --compare-minutiae /tmp/before.npz
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from terrain_nav_ros.core.features import _crease_kernels as _kernels  # noqa: E402
from terrain_nav_ros.core.features.creases import CreaseParams, crease_contrast  # noqa: E402
from terrain_nav_ros.core.features.hillshade import (  # noqa: E402
    LIGHTINGS,
    extractor_input,
    hillshade,
)
from terrain_nav_ros.core.features.minutiae import FeatureExtractor, MinutiaParams  # noqa: E402
from terrain_nav_ros.core.terrain.georef import GeoReference  # noqa: E402

cv2.setNumThreads(1)

DATA = Path(os.environ.get("TERRAIN_NAV_DATA", REPO.parent / "shared" / "data"))
STAGES = ("prepare", "diffusion", "mlsec", "mask", "skeleton", "orientation", "minutiae")
SUN_A = (315.0, 45.0)
SUN_B = (135.0, 30.0)


def read_dem(name):
    """Elevations (float64, NaN voids) and ground sample distance (m) of a shared DEM."""
    import rasterio

    with rasterio.open(DATA / "dem" / name) as ds:
        band = ds.read(1, masked=True)
        res = abs(ds.res[0])
        # CRS-less grids: degrees if the cell is tiny (front_range), else metres (halffork).
        geographic = ds.crs.is_geographic if ds.crs is not None else res < 0.01
    dem = np.ma.filled(band.astype(np.float64), np.nan)
    if geographic:  # 3 arc-second tiles: about 90 m north-south
        res = res * 111_320.0
    return dem, res


def fill_voids(dem):
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(dem)
    if bad.any():
        idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
        dem = dem[tuple(idx)]
    return dem


# --------------------------------------------------------------------------- timing


def timing(sizes, repeats, extractors):
    dem, gsd = read_dem("N44E005.hgt")
    shaded = hillshade(fill_voids(dem), *SUN_A, gsd=gsd, dtype=np.uint8)
    print(f"\n## Time per image (single thread), hillshade of N44E005 "
          f"({shaded.shape[1]}x{shaded.shape[0]}, crops; 2048 = cubic upsampling)")
    print("Wall = median wall-clock; CPU = median process CPU time (robust to other load on "
          "this shared machine). Stage shares are of the wall time.")
    print("| settings | size | wall ms | CPU ms | target ms | minutiae | "
          + " | ".join(STAGES) + " |")
    print("|---|---|---|---|---|---|" + "---|" * len(STAGES))
    targets = {512: 40, 1024: 160, 2048: 700}
    for label, extractor in extractors.items():
        for n in sizes:
            if n <= min(shaded.shape):
                img = np.ascontiguousarray(shaded[:n, :n])
            else:
                img = cv2.resize(shaded, (n, n), interpolation=cv2.INTER_CUBIC)
            extractor(img)  # warm-up
            totals, cpus, shares = [], [], {s: [] for s in STAGES}
            for _ in range(repeats.get(n, 3)):
                c0, t0 = time.process_time(), time.perf_counter()
                feats = extractor(img)
                totals.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
                for s in STAGES:
                    shares[s].append(feats.timings.get(s, 0.0))
            med = statistics.median(totals)
            cells = " | ".join(f"{100 * statistics.median(shares[s]) / med:.0f}%"
                               for s in STAGES)
            print(f"| {label} | {n} | {1000 * med:.0f} | {1000 * statistics.median(cpus):.0f} "
                  f"| {targets.get(n, '-')} | {len(feats.minutiae)} | {cells} |", flush=True)


# --------------------------------------------------------------------------- repeatability


def _close_pairs(a_xy, b_xy, max_px):
    """Index pairs (i, j) and distances of points of a and b within max_px."""
    if len(a_xy) == 0 or len(b_xy) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    pairs = cKDTree(a_xy).sparse_distance_matrix(cKDTree(b_xy), max_px, output_type="ndarray")
    return pairs["i"], pairs["j"], pairs["v"]


def _one_to_one(i, j, d):
    """Greedy one-to-one assignment of candidate pairs, closest first; the kept pairs."""
    used_a, used_b, kept = set(), set(), []
    for k in np.argsort(d, kind="stable"):
        if i[k] not in used_a and j[k] not in used_b:
            used_a.add(i[k])
            used_b.add(j[k])
            kept.append(k)
    return np.array(kept, int)


def match_count(a, b, max_px=2.0, max_deg=20.0):
    """One-to-one matches (greedy by distance) within max_px and max_deg."""
    i, j, d = _close_pairs(np.column_stack([a.col, a.row]), np.column_stack([b.col, b.row]),
                           max_px)
    dang = np.abs(np.angle(np.exp(1j * (a.angle[i] - b.angle[j]))))
    ok = dang <= np.deg2rad(max_deg)
    return len(_one_to_one(i[ok], j[ok], d[ok]))


def rates(a, b):
    m = match_count(a, b)
    lo = min(len(a), len(b))
    mean = 0.5 * (len(a) + len(b))
    return (m / lo if lo else float("nan")), (m / mean if mean else float("nan")), m


PATCHES = [
    ("gredos", "gredos_25m_epsg23030.tif", (slice(None), slice(None))),
    ("bigtujunga W", "bigtujunga_srtm30m_utm11.tif", (slice(0, 512), slice(0, 512))),
    ("bigtujunga E", "bigtujunga_srtm30m_utm11.tif", (slice(0, 512), slice(600, 1112))),
    ("halffork", "halffork_5m.asc", (slice(None), slice(None))),
]


def patches():
    """The repeatability patches: (name, DEM with NaN voids, void-filled DEM, georef, valid)."""
    for pname, fname, window in PATCHES:
        dem, gsd = read_dem(fname)
        dem = dem[window]
        geo = GeoReference(0.0, 0.0, gsd, dem.shape[1], dem.shape[0])
        yield pname, dem, fill_voids(dem), geo, np.isfinite(dem)


def shaded_features(extractor, filled, geo, valid, sun, lighting="shading"):
    """Features of the patch shaded with ``sun`` (azimuth, elevation), as the extractor
    sees it under ``lighting`` ("compensated": curvature estimated with the known sun)."""
    shaded = hillshade(filled, *sun, gsd=geo.gsd, dtype=np.uint8)
    return extractor(extractor_input(shaded, lighting, sun, valid_mask=valid), geo, valid)


def repeatability(configs):
    print("\n## Repeatability across lighting (2 px, 20 deg; matches/min and matches/mean)")
    print("Controls: DEM vs DEM + white noise of GSD/30 (1 m at 30 m); shade 315/45 vs "
          "315/40 (5 deg elevation).")
    print("| settings | patch | n(315/45) | n(135/30) | 315/45 vs 135/30 | n(DEM) | "
          "DEM vs 315/45 | DEM vs 135/30 | control DEM+noise | control 315/40 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = {}
    rng = np.random.default_rng(0)
    for label, (cp, mp, dem_cp, lighting) in configs.items():
        ext_img = FeatureExtractor(cp, mp)
        ext_dem = FeatureExtractor(dem_cp, mp)
        acc = []
        for pname, dem, filled, geo, valid in patches():
            a, b, a2 = (shaded_features(ext_img, filled, geo, valid, sun, lighting).minutiae
                        for sun in (SUN_A, SUN_B, (315.0, 40.0)))
            d = ext_dem(dem, geo, valid, source="dem").minutiae
            # Noise scaled to the grid: 1 m at 30 m GSD (SRTM's order of magnitude).
            dn = ext_dem(dem + rng.normal(0.0, geo.gsd / 30.0, dem.shape), geo, valid,
                         source="dem").minutiae
            r = [rates(a, b), rates(d, a), rates(d, b), rates(d, dn), rates(a, a2)]
            acc.append(r)
            cells = " | ".join(f"{x[0]:.0%} / {x[1]:.0%}" for x in r[:1])
            print(f"| {label} | {pname} | {len(a)} | {len(b)} | {cells} | {len(d)} | "
                  + " | ".join(f"{x[0]:.0%} / {x[1]:.0%}" for x in r[1:]) + " |", flush=True)
        summary[label] = [np.nanmean([x[k][0] for x in acc]) for k in range(5)]
    print("\nMean repeatability (matches/min) over the patches: 315/45 vs 135/30, "
          "DEM vs 315/45, DEM vs 135/30, control DEM+noise, control 315/40")
    for label, vals in summary.items():
        print(f"- {label}: " + ", ".join(f"{v:.0%}" for v in vals))


# Sun changes of the sweep, from the reference sun SUN_A (az 315, el 45).
SWEEP_AZIMUTH = (0, 2, 5, 10, 20, 30, 45, 60, 90, 135, 180)
SWEEP_ELEVATION = (40, 35, 30, 20)


def sun_sweep(target=0.70):
    """Repeatability against the size of the sun change, raw shading and compensated input
    (Table 3.1 valleys; same patches and matching rule as :func:`repeatability`)."""
    cp = configs()
    settings = {"raw shading": cp["Table 3.1, valleys (default)"],
                "compensated": cp["compensated (known sun), Table 3.1 valleys"]}
    changes = ([(f"az +{d}", (SUN_A[0] + d, SUN_A[1])) for d in SWEEP_AZIMUTH]
               + [(f"el {e}", (SUN_A[0], float(e))) for e in SWEEP_ELEVATION])
    # rate[setting][change, patch]: matches / min(n), reference sun vs changed sun.
    rate = {}
    for label, (icp, mp, _, lighting) in settings.items():
        ext = FeatureExtractor(icp, mp)
        cols = []
        for _, _, filled, geo, valid in patches():
            ref = shaded_features(ext, filled, geo, valid, SUN_A, lighting).minutiae
            cols.append([rates(ref, shaded_features(ext, filled, geo, valid, sun,
                                                    lighting).minutiae)[0]
                         for _, sun in changes])
        rate[label] = np.array(cols).T
    names = [p[0] for p in PATCHES]
    print(f"\n## Sun-change sweep: reference sun {SUN_A[0]:g}/{SUN_A[1]:g} vs changed sun "
          "(2 px, 20 deg, matches/min); mean over the patches (min-max)")
    print("| sun change | " + " | ".join(rate) + " | " + " | ".join(
        f"{lab}: {n}" for lab in rate for n in names) + " |")
    print("|---|" + "---:|" * (len(rate) * (1 + len(names))))
    for k, (name, sun) in enumerate(changes):
        means = [f"{r[k].mean():.0%} ({r[k].min():.0%}-{r[k].max():.0%})"
                 for r in rate.values()]
        per = [f"{v:.0%}" for r in rate.values() for v in r[k]]
        print(f"| {name} ({sun[0] % 360:g}/{sun[1]:g}) | " + " | ".join(means + per) + " |")
    naz = len(SWEEP_AZIMUTH)
    for label, r in rate.items():
        mean = r.mean(axis=1)
        # Largest change up to which every smaller one keeps the mean at the target.
        az_ok = np.cumprod(mean[:naz] >= target).astype(bool)
        el_ok = np.cumprod(mean[naz:] >= target).astype(bool)
        az = SWEEP_AZIMUTH[int(az_ok.sum()) - 1] if az_ok.any() else None
        el = SWEEP_ELEVATION[int(el_ok.sum()) - 1] if el_ok.any() else None
        print(f"- {label}: mean >= {target:.0%} up to an azimuth change of "
              f"{'-' if az is None else f'{az} deg'} and down to elevation "
              f"{'-' if el is None else f'{el} deg'} (from {SUN_A[1]:g})")


def _skeleton(features):
    """Union of the crease skeletons of a Features (all False when there are none)."""
    sk = features.creases.skeleton()
    return np.zeros(features.creases.work.shape, bool) if sk is None else sk


def _near(skel_a, skel_b, radius, where):
    """Share of the pixels of skel_a (inside ``where``) within ``radius`` px of skel_b."""
    dist = cv2.distanceTransform((~skel_b).view(np.uint8), cv2.DIST_L2, 5)
    sel = skel_a & where
    return float((dist[sel] <= radius).mean()) if sel.any() else float("nan")


def crease_agreement(shifts=(-3.0, -2.5, -2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5,
                             3.0)):
    """DEM-direct vs shaded-image creases at the crease level (Table 3.1 valleys).

    Per patch and image (raw shading / compensated, both suns, and the DEM's own curvature
    through the image path: ``-crease_contrast`` of elevation / GSD at sigma 1, the quantity
    the compensated input estimates, without any shading): skeleton lengths, the share
    of DEM skeleton pixels within 1 and 2 px of the image skeleton and vice versa, the chance
    level (share of all interior pixels within 1 px of the image skeleton), the shift (dx, dy
    px, image moved onto the DEM) that maximises the DEM-to-image share at 1 px, and minutia
    matches/min with position only and with the 20 deg rule.
    """
    cp = configs()
    dem_ext = FeatureExtractor(*cp["Table 3.1, valleys (default)"][:2])
    grid = np.array([(dx, dy) for dy in shifts for dx in shifts])
    print("\n## DEM-direct vs shaded creases at the crease level (Table 3.1 valleys; "
          "image skeleton length as a multiple of the DEM's)")
    print("| patch | image | skeleton px DEM / image | DEM->image <=1 px, <=2 px | "
          "image->DEM <=1 px, <=2 px | chance <=1 px | best shift (dx, dy) px: DEM->image | "
          "minutiae n DEM / image | matches/min position only, 20 deg |")
    print("|---|---|---|---|---|---|---|---|---|")
    for pname, dem, filled, geo, valid in patches():
        inner = cv2.erode(valid.view(np.uint8), np.ones((21, 21), np.uint8)).view(bool)
        inner[:10], inner[-10:], inner[:, :10], inner[:, -10:] = False, False, False, False
        fd = dem_ext(dem, geo, valid, source="dem")
        sd = _skeleton(fd)
        dist_d = cv2.distanceTransform((~sd).view(np.uint8), cv2.DIST_L2, 5)
        curvature = -crease_contrast((filled / geo.gsd).astype(np.float32), 1.0)
        images = [(f"{lighting} {sun[0]:g}/{sun[1]:g}", lighting, sun)
                  for lighting in LIGHTINGS for sun in (SUN_A, SUN_B)]
        for name, lighting, sun in images + [("DEM curvature", None, None)]:
            if lighting is None:
                fi = dem_ext(curvature, geo, valid)
            else:
                fi = shaded_features(dem_ext, filled, geo, valid, sun, lighting)
            si = _skeleton(fi)
            # Shifted image skeleton points against the DEM's distance map (bilinear).
            rows, cols = np.nonzero(si & inner)
            q = np.column_stack([cols, rows])[None, :, :] + grid[:, None, :]
            dq = cv2.remap(dist_d, q[..., 0].astype(np.float32),
                           q[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                           borderValue=1e9)
            best = grid[np.argmax((dq <= 1.0).mean(axis=1))]
            chance = _near(inner, si, 1.0, inner)
            pos = match_count(fd.minutiae, fi.minutiae, max_deg=180.0)
            ang = match_count(fd.minutiae, fi.minutiae)
            lo = max(min(len(fd.minutiae), len(fi.minutiae)), 1)
            print(f"| {pname} | {name} | {sd.sum()} / {si.sum()} "
                  f"({si.sum() / max(sd.sum(), 1):.1f}x) | "
                  f"{_near(sd, si, 1, inner):.0%}, {_near(sd, si, 2, inner):.0%} | "
                  f"{_near(si, sd, 1, inner):.0%}, {_near(si, sd, 2, inner):.0%} | "
                  f"{chance:.0%} | {best[0]:+g}, {best[1]:+g} | "
                  f"{len(fd.minutiae)} / {len(fi.minutiae)} | "
                  f"{pos / lo:.0%}, {ang / lo:.0%} |", flush=True)


# --------------------------------------------------------------------------- equivalence


def equivalence_cases():
    """(name, extractor call) pairs on real data for the before/after minutiae check.

    Uncapped minutiae (``max_minutiae=0``) so that the comparison sees every minutia, not
    the quality ranking at the cap.
    """
    mp = MinutiaParams(max_minutiae=0)
    valleys = FeatureExtractor(CreaseParams(), mp)
    both = FeatureExtractor(CreaseParams(polarity="both"), mp)
    dem, gsd = read_dem("N44E005.hgt")
    ventoux = fill_voids(dem)
    cases = []
    for sun in (SUN_A, SUN_B):
        shaded = hillshade(ventoux, *sun, gsd=gsd, dtype=np.uint8)
        for n in (512, 1024):
            crop = np.ascontiguousarray(shaded[:n, :n])
            cases.append((f"N44E005 {n} sun {sun[0]:g}/{sun[1]:g}",
                          lambda img=crop: valleys(img)))
        big = cv2.resize(shaded, (2048, 2048), interpolation=cv2.INTER_CUBIC)
        cases.append((f"N44E005 2048 sun {sun[0]:g}/{sun[1]:g}", lambda img=big: valleys(img)))
    for pname, fname, window in PATCHES + [("front_range", "front_range_srtm3.asc",
                                            (slice(None), slice(None)))]:
        z, g = read_dem(fname)
        z = z[window]
        valid = np.isfinite(z)
        geo = GeoReference(0.0, 0.0, g, z.shape[1], z.shape[0])
        shaded = hillshade(fill_voids(z), *SUN_A, gsd=g, dtype=np.uint8)
        cases.append((f"{pname} shaded, valleys+ridges",
                      lambda img=shaded, geo=geo, v=valid: both(img, geo, v)))
        cases.append((f"{pname} DEM", lambda z=z, geo=geo, v=valid: valleys(z, geo, v,
                                                                           source="dem")))
    return cases


def _minutia_table(ms):
    """(n, 5) float array: col, row, kind, ridge flag, angle."""
    if len(ms) == 0:
        return np.zeros((0, 5))
    ridge = ms.extras.get("ridge", np.zeros(len(ms), bool))
    return np.column_stack([ms.col, ms.row, ms.kind, ridge, ms.angle]).astype(float)


def save_minutiae(path):
    tables = {name: _minutia_table(run().minutiae) for name, run in equivalence_cases()}
    np.savez_compressed(path, **tables)
    print(f"saved minutiae of {len(tables)} cases to {path}")


def compare_minutiae(path, max_px=1.0):
    """Match saved (before) and current (after) minutiae: same type and polarity, <= max_px."""
    before = np.load(path)
    print(f"\n## Minutiae before ({path}) vs now: one-to-one within {max_px:g} px, same type "
          "and polarity")
    print("| case | n before | n after | count change | matched | matched / max(n) | "
          "median angle change deg |")
    print("|---|---|---|---|---|---|---|")
    worst_match, worst_count = 1.0, 0.0
    for name, run in equivalence_cases():
        a, b = before[name], _minutia_table(run().minutiae)
        i, j, d = _close_pairs(a[:, :2], b[:, :2], max_px)
        same = (a[i, 2] == b[j, 2]) & (a[i, 3] == b[j, 3])
        kept = _one_to_one(i[same], j[same], d[same])
        m = len(kept)
        ii, jj = i[same][kept], j[same][kept]
        dang = np.degrees(np.abs(np.angle(np.exp(1j * (a[ii, 4] - b[jj, 4])))))
        n = max(len(a), len(b), 1)
        change = (len(b) - len(a)) / max(len(a), 1)
        worst_match, worst_count = min(worst_match, m / n), max(worst_count, abs(change))
        print(f"| {name} | {len(a)} | {len(b)} | {change:+.1%} | {m} | {m / n:.1%} | "
              f"{np.median(dang) if m else float('nan'):.1f} |", flush=True)
    print(f"\nWorst case: {worst_match:.1%} of minutiae matched, count change "
          f"{worst_count:.1%}.")


def configs():
    """Settings compared: (image crease params, minutia params, DEM crease params, lighting).

    ``lighting`` as the nodes' parameter (:data:`LIGHTINGS`): ``"compensated"`` makes the
    extractor see the terrain curvature estimated from the shaded image with the known sun
    (:func:`~terrain_nav_ros.core.features.hillshade.shading_curvature`).
    """
    mp = MinutiaParams(max_minutiae=0)
    default = CreaseParams()
    both = CreaseParams(polarity="both")
    coarse = CreaseParams(polarity="both", sigma=2.0, w1=9, rho=2.0, w2=7, mlsec_sigma=2.0,
                          mlsec_rho=4.0)
    coarse_v = replace(coarse, polarity="valley")
    return {
        "Table 3.1, valleys (default)": (default, mp, default, "shading"),
        "Table 3.1, valleys+ridges": (both, mp, both, "shading"),
        "sigma=rho=2, MLSEC 2/4, valleys+ridges": (coarse, mp, coarse, "shading"),
        "compensated (known sun), Table 3.1 valleys": (default, mp, default, "compensated"),
        "compensated (known sun), sigma=rho=2, MLSEC 2/4, valleys": (coarse_v, mp, coarse_v,
                                                                     "compensated"),
    }


def _without_numba(extractor):
    """The extractor with the optional numba kernels switched off."""

    def run(*args, **kwargs):
        saved, _kernels.HAVE_NUMBA = _kernels.HAVE_NUMBA, False
        try:
            return extractor(*args, **kwargs)
        finally:
            _kernels.HAVE_NUMBA = saved

    return run


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--no-repeatability", action="store_true")
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    ap.add_argument("--sun-sweep", action="store_true",
                    help="only the repeatability against the size of the sun change")
    ap.add_argument("--crease-agreement", action="store_true",
                    help="only DEM-direct vs shaded creases at the crease level")
    ap.add_argument("--save-minutiae", metavar="NPZ",
                    help="only save the minutiae of the equivalence cases")
    ap.add_argument("--compare-minutiae", metavar="NPZ",
                    help="only compare the equivalence cases with minutiae saved earlier")
    args = ap.parse_args(argv)
    if not (DATA / "dem").is_dir():
        sys.exit(f"real data not found at {DATA} (set TERRAIN_NAV_DATA)")
    print(f"# bench_features  (cv2 threads {cv2.getNumThreads()}, OMP threads "
          f"{os.environ['OMP_NUM_THREADS']}, numba kernels {_kernels.HAVE_NUMBA})")
    if args.save_minutiae:
        return save_minutiae(args.save_minutiae)
    if args.compare_minutiae:
        return compare_minutiae(args.compare_minutiae)
    if args.sun_sweep or args.crease_agreement:
        if args.sun_sweep:
            sun_sweep()
        if args.crease_agreement:
            crease_agreement()
        return None
    if not args.no_timing:
        extractors = {"Table 3.1, numba kernels" if _kernels.HAVE_NUMBA
                      else "Table 3.1, OpenCV/numpy (numba not installed)": FeatureExtractor()}
        if _kernels.HAVE_NUMBA:
            extractors["Table 3.1, OpenCV/numpy reference path"] = _without_numba(
                FeatureExtractor())
        timing(args.sizes, {512: 15, 1024: 7, 2048: 5}, extractors)
    if not args.no_repeatability:
        repeatability(configs())


if __name__ == "__main__":
    main()
