"""The researcher's evaluation (``terrain-nav evaluate``): dissertation chapter 5 study + baselines.

:func:`run_evaluation` does, on any DEM (a file, or the embedded default):

1. **Blocks.** One square study area, as large as the DEM's void-free ENU coverage allows, is
   sampled at the requested GSD exactly as the metamap node does
   (:class:`~.core.terrain.metamap.MetaMap`, cubic spline, voids filled) and cut into ``n x n``
   blocks (9 / 36 / 144 in the dissertation). A margin around the grid keeps every camera view and
   localisation region on terrain.
2. **Landmarks.** The area is rendered nadir (:class:`~.core.render.renderer.LandmarkRenderer`,
   default albedo, sun ``sun``); each block's crop goes through the feature extractor.
3. **Camera versions.** The same area is rendered again with a different albedo ramp (its
   transitions placed inside this DEM's height range so the change shows), and each block is
   re-cut with a random small rotation, scale and offset, then degraded like a camera frame
   (:func:`~.core.render.camera_effects.apply_camera_effects`: haze, exposure, gamma, blur,
   vignetting, sensor noise, 8 bits). The *same-sun* condition uses the landmark's sun: shaded-image
   creases move with the sun (crease repeatability ~4 % between sun 315/45 and 135/30), so a
   changed sun is reported separately as the hard case (``sun_change``). With
   ``lighting="compensated"`` every image goes through
   :func:`~.core.features.hillshade.shading_curvature` with its own (nominal) sun before extraction.
4. **PVA / non-PVA.** Every camera block is compared
   (:meth:`~.core.matching.matcher.Matcher.compare`) with every landmark block: the diagonal are PVA
   matches (same place), the rest non-PVA. The threshold is calibrated
   (:func:`~.core.matching.significance.calibrate_threshold`) for the stated false-match rate on a
   random half of the non-PVA scores and applied to the other half (and the other way round); PVA
   misses are counted at that threshold.
5. **Fix error.** For PVA matches the registration maps the camera block's centre into the
   landmark block; its distance to the true position is the fix error (px and m). The
   navigation use is measured too: each camera block is localised
   (:meth:`~.core.matching.matcher.Matcher.localise`) inside a landmark region ``region_factor``
   times the block's side around it.
6. **Baselines** on the same localisation cases: NCC of gradient-magnitude images without and
   with a 36-step rotation search, and ORB (and SIFT when OpenCV has it) with a RANSAC
   homography (:mod:`~.core.matching.baselines`); success = centre within ``success_px`` px.

Outputs in ``out_dir``: ``report.md`` (dissertation-style tables), ``blocks_<condition>.md``
(per-block match results), ``results.json``, and PNGs (score histograms, similarity matrices,
minutiae per block, a sample of landmark/camera blocks). Times are single-thread wall times
per case on this machine, with what each includes stated in the tables.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from ..core.features.hillshade import check_lighting, extractor_input
from ..core.features.minutia_set import MinutiaSet
from ..core.features.minutiae import FeatureExtractor, MinutiaParams
from ..core.matching.baselines import (
    gradient_magnitude,
    has_sift,
    keypoint_features,
    keypoint_locate,
    ncc_locate,
)
from ..core.matching.matcher import Decision, Matcher
from ..core.matching.params import MatchParams
from ..core.matching.significance import calibrate_threshold
from ..core.render.camera_effects import CameraEffects, apply_camera_effects
from ..core.terrain.dem_io import Dem, open_dem, sample_dem
from ..core.terrain.georef import GeoReference
from ..core.terrain.metamap import MetaMap

__all__ = ["CameraModel", "run_evaluation", "parse_gsd", "score_bins_table", "camera_albedo",
           "camera_renders", "valid_area"]

# score bins of the distribution tables (Tables 4.2/4.3, 5.3/5.4 of the dissertation)
SCORE_BINS = (-np.inf, 0.0, 2.0, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0, np.inf)
# localisation error (px) above which an accepted fix is at a wrong place, not just biased
GROSS_PX = 10.0


@dataclass(frozen=True)
class CameraModel:
    """How a "camera" block departs from its landmark block.

    Parameters
    ----------
    max_rotation_deg : float
        Rotation drawn uniformly in +-this (degrees).
    max_scale_change : float
        Relative scale drawn uniformly in +-this.
    max_offset_px : float
        Offset of the view centre drawn uniformly in +-this per axis (px).
    effects : CameraEffects
        Atmosphere, exposure, optics and sensor (no lens distortion: the camera frame is
        already ground-projected in the pipeline).
    distance_m : float
        Range used for the haze.
    """

    max_rotation_deg: float = 10.0
    max_scale_change: float = 0.03
    max_offset_px: float = 8.0
    effects: CameraEffects = CameraEffects(blur_sigma=0.7, vignetting=0.1, read_noise=1.0,
                                           photon_gain=0.04,
                                           distortion=(0.0, 0.0, 0.0, 0.0, 0.0))
    distance_m: float = 1500.0


def parse_gsd(gsd, native: float) -> float:
    """GSD in metres from ``None``/"native", "x2"/"2x" (native / 2) or a number of metres."""
    if gsd is None or (isinstance(gsd, str) and gsd.strip().lower() == "native"):
        return float(native)
    if isinstance(gsd, str):
        s = gsd.strip().lower()
        if s.startswith("x") or s.endswith("x"):
            factor = float(s.strip("x"))
            if factor <= 0:
                raise ValueError(f"gsd factor must be positive, got {gsd!r}")
            return float(native) / factor
        gsd = float(s)
    gsd = float(gsd)
    if not gsd > 0:
        raise ValueError(f"gsd must be positive, got {gsd}")
    return gsd


def camera_albedo(elevation: np.ndarray):
    """Another albedo ramp, its transitions inside this terrain's height range.

    The colours differ by at most ~30 % in brightness and blend over a wide band: a season
    or land-cover change, not sharp contour lines (which would draw false creases)."""
    from ..core.render.renderer import AlbedoRamp

    lo, mid, hi = np.percentile(elevation, [5, 50, 95])
    blend = max(0.3 * (hi - lo), 1.0)
    return AlbedoRamp(tree_line=float(mid), snow_line=float(hi), blend=float(blend),
                      vegetation=(0.22, 0.28, 0.16), lowland=(0.27, 0.30, 0.19),
                      rock=(0.30, 0.29, 0.26), snow=(0.34, 0.35, 0.36))


def camera_renders(elevation: np.ndarray, georef: GeoReference, suns,
                   renderer=None) -> list[np.ndarray]:
    """The DEM-only studies' camera: RGB nadir renders of a DEM tile by the graph's renderer
    under :func:`camera_albedo` (not the landmarks'), one per (azimuth, elevation) in
    ``suns``.

    Parameters
    ----------
    elevation : (H, W) array
        Heights without voids (fill them first).
    georef : GeoReference
    suns : sequence of (azimuth, elevation)
    renderer : LandmarkRenderer, optional
        One already holding this terrain (its albedo is replaced); default a new headless
        one, released after.
    """
    from ..core.render.renderer import LandmarkRenderer, create_headless_context

    own = renderer is None
    if own:
        renderer = LandmarkRenderer(create_headless_context())
        renderer.set_terrain(elevation, georef)
    try:
        renderer.set_albedo(camera_albedo(elevation))
        return [renderer.render_nadir(georef, sun=tuple(sun)).rgb for sun in suns]
    finally:
        if own:
            renderer.release()


def valid_area(mm: MetaMap, gsd: float) -> tuple[float, float, int]:
    """Centre (east, north) and side (px at ``gsd``) of the largest void-free centred square.

    Checked on a 4x coarser grid (cheap), then shrunk by a safety cell."""
    w, e, s, n = mm.enu_bounds[0]
    ce, cn = 0.5 * (w + e), 0.5 * (s + n)
    coarse = 4.0 * max(gsd, mm.native_gsd)
    side_m = min(e - w, n - s)
    for _ in range(60):
        k = int(side_m / coarse)
        tile = mm.tile(GeoReference.centred(ce, cn, coarse, k, k))
        if not tile.nodata.any():
            break
        side_m *= 0.97
    else:
        raise ValueError("no void-free square area found in the DEM")
    return ce, cn, int(side_m / gsd) - 8


def _warp_block(rgb: np.ndarray, m: np.ndarray, size: int) -> np.ndarray:
    """Camera view: pixel (u, v) of the result is area pixel ``m @ [u, v, 1]``."""
    return cv2.warpAffine(rgb, m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def _grey(rgb_u8: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb_u8, cv2.COLOR_RGB2GRAY)


def _percentiles(x, qs=(50, 95)):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return [math.nan] * len(qs)
    return [float(np.percentile(x, q)) for q in qs]


def score_bins_table(scores, title: str) -> str:
    """Markdown distribution table of similarity scores over :data:`SCORE_BINS`."""
    s = np.asarray(scores, float)
    s = np.where(np.isfinite(s), s, -1e9)   # "nothing registered" counts in the lowest bin
    counts, _ = np.histogram(s, bins=np.array(SCORE_BINS))
    lines = [f"**{title}** ({len(s)} comparisons)", "",
             "| score | " + " | ".join(_bin_label(a, b) for a, b in
                                        zip(SCORE_BINS[:-1], SCORE_BINS[1:], strict=True))
             + " |",
             "|---|" + "---:|" * len(counts),
             "| count | " + " | ".join(str(int(c)) for c in counts) + " |",
             "| % | " + " | ".join(f"{100 * c / max(len(s), 1):.1f}" for c in counts) + " |"]
    return "\n".join(lines)


def _bin_label(a, b) -> str:
    if not np.isfinite(a):
        return f"< {b:g}"
    if not np.isfinite(b):
        return f">= {a:g}"
    return f"{a:g}-{b:g}"


# --------------------------------------------------------------------------- the study
class _Extracted(NamedTuple):
    """What the matcher needs of one image: ``Matcher.index(*extracted)``."""

    minutiae: MinutiaSet
    creases: np.ndarray | None
    ridges: np.ndarray | None


class _Study:
    """State shared by both camera conditions (landmark side, cases, matchers)."""

    def __init__(self, n, bs, margin, area_grey, extractor, region_extractor, matcher,
                 region_factor, sun, lighting):
        self.n, self.bs, self.margin = n, bs, margin
        self.area_grey = area_grey
        self.fx, self.fx_region = extractor, region_extractor
        self.lighting = lighting
        self.matcher = matcher
        self.origins = [(margin + c * bs, margin + r * bs) for r in range(n) for c in range(n)]
        side = area_grey.shape[0]
        rm = int(round(0.5 * (region_factor - 1.0) * bs))
        self.regions = [(max(x - rm, 0), max(y - rm, 0), min(x + bs + rm, side),
                         min(y + bs + rm, side)) for x, y in self.origins]
        self.blocks = [self.minutiae(area_grey[y:y + bs, x:x + bs], sun)
                       for x, y in self.origins]
        self.block_index = [matcher.index(*b) for b in self.blocks]
        self.region_features, self.region_prep = [], []
        for x0, y0, x1, y1 in self.regions:
            t0 = time.perf_counter()
            self.region_features.append(self.minutiae(area_grey[y0:y1, x0:x1], sun, region=True))
            self.region_prep.append(time.perf_counter() - t0)

    def minutiae(self, grey: np.ndarray, sun, region: bool = False) -> _Extracted:
        """Minutiae, crease and ridge skeletons (None without creases) of a grey image lit
        by ``sun``, after the study's lighting treatment."""
        feats = (self.fx_region if region else self.fx)(
            extractor_input(grey, self.lighting, sun))
        return _Extracted(feats.minutiae, feats.creases.skeleton(), feats.ridges)


def _camera_blocks(study: _Study, cam_rgb: np.ndarray, sun, transforms, cm: CameraModel,
                   seed: int):
    """Degraded camera views of every block, their extractions and extraction times."""
    rng = np.random.default_rng(seed)
    bs = study.bs
    dist = np.full((bs, bs), cm.distance_m, np.float32)
    greys, cams, times = [], [], []
    for m in transforms:
        view = _warp_block(cam_rgb, m, bs)
        grey = _grey(apply_camera_effects(view, dist, cm.effects, rng))
        t0 = time.perf_counter()
        cams.append(study.minutiae(grey, sun))
        times.append(time.perf_counter() - t0)
        greys.append(grey)
    return greys, cams, np.array(times)


def _compare_row(matcher: Matcher, block_index, cam: _Extracted):
    """One camera block against every landmark block: its results and times."""
    ci = matcher.index(*cam)
    results, times = [], []
    for bj in block_index:
        t0 = time.perf_counter()
        results.append(matcher.compare(ci, bj))
        times.append(time.perf_counter() - t0)
    return results, times


# What forked workers of _compare_all read (set just before the fork: nothing is pickled)
_FORKED_STUDY = None


def _compare_forked_row(i: int):
    matcher, block_index, cams = _FORKED_STUDY
    return _compare_row(matcher, block_index, cams[i])


def _compare_all(study: _Study, cams: list[_Extracted], jobs: int = 1,
                 progress=lambda done, n: None):
    """Scores, pairings and PVA results of every camera block against every landmark block,
    the rows in ``jobs`` forked processes (each comparison is seeded: the same results);
    ``progress(rows done, rows)`` after each row."""
    global _FORKED_STUDY
    n = len(cams)
    rows = []
    if jobs > 1 and n > 1:
        _FORKED_STUDY = (study.matcher, study.block_index, cams)
        try:
            with multiprocessing.get_context("fork").Pool(min(jobs, n)) as pool:
                for row in pool.imap(_compare_forked_row, range(n), chunksize=1):
                    rows.append(row)
                    progress(len(rows), n)
        finally:
            _FORKED_STUDY = None
    else:
        for cam in cams:
            rows.append(_compare_row(study.matcher, study.block_index, cam))
            progress(len(rows), n)
    score = np.array([[r.score for r in row] for row, _ in rows], float)
    pairings = np.array([[r.n_pairings for r in row] for row, _ in rows], int)
    undecided = np.array([[r.decision == Decision.NO_DECISION for r in row] for row, _ in rows],
                         bool)
    pva = [row[i] for i, (row, _) in enumerate(rows)]
    times = np.array([t for _, row_times in rows for t in row_times])
    return score, pairings, undecided, pva, times


def _calibrate(score: np.ndarray, rate: float, seed: int) -> dict:
    """Two-fold calibration of the threshold on the non-PVA scores."""
    n = len(score)
    off = ~np.eye(n, dtype=bool)
    non = score[off]
    perm = np.random.default_rng(seed).permutation(len(non))
    h1, h2 = non[perm[: len(non) // 2]], non[perm[len(non) // 2:]]
    out = {"n_non_pva": int(len(non))}
    folds = []
    for cal, held in ((h1, h2), (h2, h1)):
        if not np.isfinite(cal).any():
            thr = 0.0   # nothing registered at all among unrelated pairs: any score matches
        else:
            thr = calibrate_threshold(cal, rate)
        folds.append({"threshold": float(thr), "n_cal": int(len(cal)),
                      "held_out": int(len(held)), "held_out_accepted": int((held >= thr).sum())})
    out["folds"] = folds
    out["threshold"] = folds[0]["threshold"]
    return out


def _localise_cases(study: _Study, cam_greys, cams: list[_Extracted], cam_times, truths,
                    threshold, success_px, methods, n_rotations):
    """Locate every camera block inside its landmark region with each method."""
    bs = study.bs
    c = 0.5 * (bs - 1)
    matcher = Matcher(study.matcher.params, threshold=threshold)
    rows = {m: {"err": [], "time": [], "prep": [], "found": [], "accepted": []}
            for m in methods}
    for k, (x0, y0, x1, y1) in enumerate(study.regions):
        m_true = truths[k].copy()
        m_true[:, 2] -= (x0, y0)
        true_c = m_true @ np.array([c, c, 1.0])
        region = study.area_grey[y0:y1, x0:x1]
        for method in methods:
            rec = rows[method]
            if method == "minutiae":
                t0 = time.perf_counter()
                # the region is prepared before the frames it serves, as NCC's gradient is
                ri = matcher.index(*study.region_features[k]).prepare_as_reference(search=True)
                prep = study.region_prep[k] + time.perf_counter() - t0
                t0 = time.perf_counter()
                r = matcher.localise(matcher.index(*cams[k]), ri)
                dt = time.perf_counter() - t0 + cam_times[k]
                accepted = r.decision == Decision.MATCH
                est = r.apply(c, c) if np.isfinite(r.transform).all() else (math.nan, math.nan)
            else:
                t0 = time.perf_counter()
                if method.startswith("ncc"):
                    land = gradient_magnitude(region)
                    prep = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    loc = ncc_locate(cam_greys[k], region, landmark_gradient=land,
                                     n_rotations=n_rotations if method == "ncc_rot" else 0)
                else:
                    feats = keypoint_features(region, method)
                    prep = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    loc = keypoint_locate(cam_greys[k], region, kind=method,
                                          landmark_features=feats)
                dt = time.perf_counter() - t0
                accepted = loc.found
                est = (loc.col, loc.row)
            e = float(np.hypot(est[0] - true_c[0], est[1] - true_c[1]))
            rec["err"].append(e if np.isfinite(e) else math.inf)
            rec["time"].append(dt)
            rec["prep"].append(prep)
            rec["found"].append(bool(np.isfinite(e)))
            rec["accepted"].append(bool(accepted))
    out = {}
    for method, rec in rows.items():
        err = np.array(rec["err"])
        acc = np.array(rec["accepted"])
        ok = acc & (err <= success_px)
        fin = err[acc & np.isfinite(err)]
        out[method] = {
            "cases": len(err), "success": int(ok.sum()),
            "success_rate": float(ok.mean()) if len(err) else math.nan,
            "accepted": int(acc.sum()),
            "wrong_accepted": int((acc & (err > success_px)).sum()),
            # gross errors (a wrong place) vs small biases (e.g. creases moved by the sun)
            "gross_wrong_accepted": int((acc & (err > GROSS_PX)).sum()),
            "err_median_px": _percentiles(fin)[0], "err_p95_px": _percentiles(fin)[1],
            "err_median_ok_px": _percentiles(err[ok])[0],
            "time_ms_median": 1e3 * float(np.median(rec["time"])),
            # the minutiae's time varies with the case (a failed first try adds the crease
            # search), NCC's does not: the mean is the throughput
            "time_ms_mean": 1e3 * float(np.mean(rec["time"])),
            "landmark_prep_ms_median": 1e3 * float(np.median(rec["prep"])),
            "errors_px": [float(x) for x in err],
        }
    return out


def _quarterly_progress(log, what: str, unit: str):
    """A ``progress(done, n)`` that logs at a quarter, half and three quarters of the work,
    with the time so far and an estimate of the rest (a 144-block study compares for
    minutes)."""
    t0 = time.perf_counter()

    def progress(done: int, n: int) -> None:
        if done < n and done in {n * q // 4 for q in (1, 2, 3)} - {0}:
            spent = time.perf_counter() - t0
            log(f"{what} {done}/{n} {unit}, {spent:.0f} s (~{spent * (n - done) / done:.0f} s "
                "to go)")
    return progress


def _condition(study, name, cam_rgb, sun, transforms, cm, rate, seed, success_px, methods,
               n_rotations, gsd, log, jobs=1):
    t_start = time.perf_counter()
    greys, cams, ext_times = _camera_blocks(study, cam_rgb, sun, transforms, cm, seed + 17)
    score, pairings, undecided, pva, cmp_times = _compare_all(
        study, cams, jobs, _quarterly_progress(log, f"  [{name}] compared", "camera blocks"))
    cal = _calibrate(score, rate, seed)
    thr = cal["threshold"]
    n = len(score)
    off = ~np.eye(n, dtype=bool)
    diag = np.diag(score)
    missed = [int(i) for i in np.flatnonzero(diag < thr)]
    c = 0.5 * (study.bs - 1)
    fix_err = []
    for k, r in enumerate(pva):
        m_true = transforms[k].copy()
        m_true[:, 2] -= study.origins[k]
        if r.score >= thr and np.isfinite(r.transform).all():
            est = np.array(r.apply(c, c))
            fix_err.append(float(np.hypot(*(est - m_true @ np.array([c, c, 1.0])))))
        else:
            fix_err.append(math.nan)
    fix_err = np.array(fix_err)
    log(f"  [{name}] {n} blocks compared ({n * n} pairs), threshold {thr:.2f}; "
        f"misses {len(missed)}; localising")
    loc = _localise_cases(study, greys, cams, ext_times, transforms, thr,
                          success_px, methods, n_rotations)
    med, p95 = _percentiles(fix_err)
    return {
        "name": name,
        "threshold": thr, "calibration": cal,
        "score": score, "pairings": pairings, "undecided_pva": int(np.diag(undecided).sum()),
        "pva_scores": diag, "non_pva_scores": score[off],
        "missed_blocks": missed, "miss_rate": len(missed) / n,
        "non_pva_accepted": int((score[off] >= thr).sum()),
        "non_pva_accepted_default": int((score[off] >= MatchParams().threshold).sum()),
        "pva_missed_default": int((diag < MatchParams().threshold).sum()),
        "non_pva_max": float(np.max(score[off])) if n > 1 else math.nan,
        # the dissertation's criterion: misses when no non-PVA pair at all may be accepted
        "pva_missed_zero_fa": int((diag <= np.max(score[off])).sum()) if n > 1 else 0,
        "fix_err_px": fix_err, "fix_err_median_px": med, "fix_err_p95_px": p95,
        "fix_err_median_m": med * gsd, "fix_err_p95_m": p95 * gsd,
        "camera_counts": np.array([len(c.minutiae) for c in cams]),
        "extract_ms_median": 1e3 * float(np.median(ext_times)),
        "compare_ms_median": 1e3 * float(np.median(cmp_times)),
        "localisation": loc, "greys": greys, "seconds": time.perf_counter() - t_start,
    }


def run_evaluation(dem=None, gsd=None, blocks: int = 9, out_dir="out/evaluation", *,
                   block_size: int = 256, sun=(315.0, 45.0), sun_change: float = 180.0,
                   changed_sun_elevation: float = 30.0, false_match_rate: float = 1e-3,
                   seed: int = 0, quick: bool = False, region_factor: float = 3.0,
                   success_px: float = 2.0, baselines: bool = True,
                   camera: CameraModel | None = None, match_params: MatchParams | None = None,
                   lighting: str = "shading", jobs: int = 1, log=print) -> dict:
    """Run the PVA / non-PVA granularity study with baselines and write its report.

    Parameters
    ----------
    dem : str, Path, Dem or None
        DEM file (any format :func:`~.core.terrain.dem_io.open_dem` reads) or ``None`` for the
        embedded default.
    gsd : None, "native", "x2", float
        Block GSD: the DEM's native cell size, a refinement factor ("x2" = half the native
        cell, interpolated by the metamap's cubic spline), or metres.
    blocks : int
        Number of blocks, a square (9, 36, 144).
    out_dir : str or Path
        Where the report, JSON and PNGs go (created).
    block_size : int
        Largest block side (px); smaller when the DEM's void-free area cannot hold
        ``sqrt(blocks)`` blocks of this size plus the margin.
    sun : (azimuth, elevation)
        Landmark sun (degrees); the same-sun camera uses it too.
    sun_change : float
        Azimuth change (degrees) of the hard-case camera sun, whose elevation is
        ``changed_sun_elevation``; 0 skips the hard case.
    false_match_rate : float
        Rate the threshold is calibrated for on non-PVA scores.
    seed : int
        Seeds the camera transforms, degradations and calibration split.
    quick : bool
        Fewer cases for a smoke run: no hard case, no SIFT, 12-step rotation search.
    region_factor : float
        Localisation region side / block side.
    success_px : float
        A localisation is a success when the centre error is within this (px).
    baselines : bool
        Also run the NCC and keypoint baselines.
    camera : CameraModel, optional
    match_params : MatchParams, optional
        Matcher settings (threshold is replaced by the calibrated one).
    lighting : {"shading", "compensated"}
        What the extractor sees: the shaded grey image, or the terrain curvature estimated
        from it with the image's own sun (:func:`~.core.features.hillshade.shading_curvature`; the
        camera's sun is taken as known, as it is in flight from time and place).
    jobs : int
        Processes for the N x N comparisons (forked; the results do not depend on it). The
        localisation and the baselines stay in one process, as their times are reported.
    log : callable
        Progress messages.

    Returns
    -------
    dict
        Summary (also written to ``results.json``); ``report`` is the markdown text.
    """
    from ..core.render.renderer import LandmarkRenderer, create_headless_context

    t_all = time.perf_counter()
    n = math.isqrt(int(blocks))
    if n * n != int(blocks) or n < 2:
        raise ValueError(f"blocks must be a square number >= 4, got {blocks}")
    check_lighting(lighting)
    if int(jobs) < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    cm = camera or CameraModel()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(dem, Dem):
        dem_obj = dem
    elif dem is None:
        dem_obj = sample_dem()
    else:
        dem_obj = open_dem(dem)
    mm = MetaMap(dem_obj, interpolation="spline", fill_voids=True)
    native = mm.native_gsd
    gsd_m = parse_gsd(gsd, native)
    ce, cn, side_avail = valid_area(mm, gsd_m)
    pad = cm.max_offset_px + 2
    # margin: room for the rotated, scaled, offset view of the edge blocks
    rot = math.radians(cm.max_rotation_deg)
    grow = (1 + cm.max_scale_change) * (abs(math.cos(rot)) + abs(math.sin(rot))) - 1
    bs = int(min(block_size, (side_avail - 2 * pad) / (n + grow)))
    if bs < 48:
        raise ValueError(f"the DEM's void-free area ({side_avail} px at {gsd_m:.2f} m) "
                         f"cannot hold {n}x{n} blocks of >= 48 px")
    margin = int(math.ceil(0.5 * grow * bs + pad))
    side = n * bs + 2 * margin
    t0 = time.perf_counter()
    tile = mm.tile(GeoReference.centred(ce, cn, gsd_m, side, side))
    elev = np.where(tile.nodata, np.nanmedian(tile.elevation), tile.elevation)
    log(f"evaluate: {dem_obj.name}: {n}x{n} blocks of {bs} px at {gsd_m:.2f} m "
        f"(native {native:.2f} m), area {side} px ({side * gsd_m / 1e3:.1f} km), "
        f"tile {time.perf_counter() - t0:.1f} s")

    # renders: landmark, then the camera albedo with the same and the changed sun
    ctx = create_headless_context()
    renderer = LandmarkRenderer(ctx)
    renderer.set_terrain(elev, tile.georef)
    land = renderer.render_nadir(tile.georef, sun=tuple(sun))
    area_grey = land.grey_u8
    conditions = [("same sun", tuple(sun))]
    if sun_change and not quick:
        conditions.append(("changed sun", ((sun[0] + sun_change) % 360.0,
                                            changed_sun_elevation)))
    cam_rgbs = camera_renders(elev, tile.georef, [s for _, s in conditions], renderer)
    renderer.release()

    params = replace(match_params or MatchParams(), threshold=-1e9)   # collect every score
    # ridges for the matcher's ridge check of small blocks (cheap: the valleys' creaseness)
    ridge_check = params.crease_check and params.ridge_check
    fx = FeatureExtractor(ridges=ridge_check)
    fx_region = FeatureExtractor(minutia_params=MinutiaParams(max_minutiae=100000),
                                 ridges=ridge_check)
    study = _Study(n, bs, margin, area_grey, fx, fx_region, Matcher(params), region_factor,
                   tuple(sun), lighting)

    rng = np.random.default_rng(seed)
    transforms = []
    c = 0.5 * (bs - 1)
    for x, y in study.origins:
        theta = math.radians(rng.uniform(-cm.max_rotation_deg, cm.max_rotation_deg))
        s = 1.0 + rng.uniform(-cm.max_scale_change, cm.max_scale_change)
        t = rng.uniform(-cm.max_offset_px, cm.max_offset_px, 2)
        a, b = s * math.cos(theta), s * math.sin(theta)
        # camera px -> area px: rotate/scale about the block centre, then offset
        m = np.array([[a, b, 0.0], [-b, a, 0.0]])
        m[:, 2] = np.array([x + c, y + c]) + t - m[:, :2] @ np.array([c, c])
        transforms.append(m)

    methods = ["minutiae"]
    if baselines:
        methods += ["ncc", "ncc_rot", "orb"]
        if has_sift() and not quick:
            methods.append("sift")
    n_rot = 12 if quick else 36
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)   # single-thread times, comparable across methods
    try:
        results = [_condition(study, name, rgb, cam_sun, transforms, cm, false_match_rate,
                              seed, success_px, methods, n_rot, gsd_m, log, jobs)
                   for (name, cam_sun), rgb in zip(conditions, cam_rgbs, strict=True)]
    finally:
        cv2.setNumThreads(cv_threads)

    setup = {
        "dem": dem_obj.name, "native_gsd_m": native, "gsd_m": gsd_m, "blocks": n * n,
        "grid": n, "block_px": bs, "block_m": bs * gsd_m, "area_px": side,
        "margin_px": margin, "sun": list(sun), "lighting": lighting,
        "conditions": {name: list(s) for name, s in conditions},
        "camera": asdict(cm), "false_match_rate": false_match_rate, "seed": seed,
        "region_factor": region_factor, "success_px": success_px, "methods": methods,
        "rotation_steps": n_rot, "landmark_counts": [len(b.minutiae) for b in study.blocks],
        "region_counts": [len(r.minutiae) for r in study.region_features],
        "matcher_max_rotation_deg": math.degrees(params.max_rotation),
        "matcher_crease_check": params.crease_check,
        "matcher_ridge_check": ridge_check,
        "matcher_ridge_check_below": params.ridge_check_below, "jobs": int(jobs),
    }
    pngs = _plots(out, study, results, setup)
    report = _report(setup, study, results, pngs, time.perf_counter() - t_all)
    (out / "report.md").write_text(report)
    for r in results:
        (out / f"blocks_{r['name'].replace(' ', '_')}.md").write_text(_block_table(study, r))
    summary = {"setup": setup, "conditions": [_jsonable(r) for r in results],
               "seconds": time.perf_counter() - t_all, "report": report,
               "files": sorted(p.name for p in out.iterdir())}
    (out / "results.json").write_text(json.dumps({k: v for k, v in summary.items()
                                                   if k != "report"}, indent=1))
    return summary


def _jsonable(r: dict) -> dict:
    skip = {"greys", "score", "pairings"}
    out = {}
    for k, v in r.items():
        if k in skip:
            continue
        if isinstance(v, np.ndarray):
            v = [None if not np.isfinite(x) else float(x) for x in v.astype(float)]
        out[k] = v
    out["score_matrix"] = [[None if not np.isfinite(x) else round(float(x), 3) for x in row]
                           for row in r["score"]]
    return out


# --------------------------------------------------------------------------- outputs
def save_figure(fig, path: Path, dpi: int = 90) -> str:
    """Lay out, write and close a figure; its file name."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path.name


def _plots(out: Path, study: _Study, results, setup) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    n = study.n
    for r in results:
        tag = r["name"].replace(" ", "_")
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
        pva = r["pva_scores"][np.isfinite(r["pva_scores"])]
        non = r["non_pva_scores"][np.isfinite(r["non_pva_scores"])]
        hi = max(np.max(pva, initial=1.0), np.max(non, initial=1.0), r["threshold"]) + 1
        lo = min(np.min(non, initial=0.0), np.min(pva, initial=0.0), 0.0) - 1
        bins = np.linspace(lo, hi, 40)
        for a, data, title in ((ax[0], pva, "PVA"), (ax[1], non, "Non-PVA")):
            a.hist(data, bins=bins, color="tab:blue" if title == "PVA" else "tab:red")
            a.axvline(r["threshold"], color="k", ls="--", label=f"threshold {r['threshold']:.2f}")
            a.set_xlabel("similarity score")
            a.set_ylabel("frequency")
            a.set_title(f"{title} similarity scores ({r['name']}, {len(data)})")
            a.legend(fontsize=8)
        files.append(save_figure(fig, out / f"hist_{tag}.png"))
        fig, a = plt.subplots(figsize=(5, 4.2))
        s = np.where(np.isfinite(r["score"]), r["score"], np.nan)
        im = a.imshow(s, cmap="viridis")
        fig.colorbar(im, ax=a, label="score")
        a.set_xlabel("landmark block")
        a.set_ylabel("camera block")
        a.set_title(f"Similarity scores between {n * n} blocks ({r['name']})")
        files.append(save_figure(fig, out / f"similarity_{tag}.png"))
    fig, a = plt.subplots(figsize=(7, 3.2))
    idx = np.arange(n * n)
    a.bar(idx - 0.2, setup["landmark_counts"], 0.4, label="landmark")
    a.bar(idx + 0.2, results[0]["camera_counts"], 0.4, label=f"camera ({results[0]['name']})")
    a.set_xlabel("block")
    a.set_ylabel("minutiae")
    a.set_title(f"Numbers of minutiae in {n * n} terrain blocks")
    a.legend(fontsize=8)
    files.append(save_figure(fig, out / "minutiae_counts.png"))
    k = min(4, n * n)
    fig, ax = plt.subplots(1 + len(results), k, figsize=(2.2 * k, 2.3 * (1 + len(results))),
                           squeeze=False)
    bs = study.bs
    for j in range(k):
        x, y = study.origins[j]
        ax[0, j].imshow(study.area_grey[y:y + bs, x:x + bs], cmap="gray")
        ax[0, j].set_title(f"landmark {j}", fontsize=8)
        for i, r in enumerate(results):
            ax[1 + i, j].imshow(r["greys"][j], cmap="gray")
            ax[1 + i, j].set_title(f"camera {j} ({r['name']})", fontsize=8)
    for a in ax.ravel():
        a.axis("off")
    files.append(save_figure(fig, out / "blocks_sample.png", dpi=80))
    return files


_METHOD_NAMES = {"minutiae": "minutiae (this work)", "ncc": "NCC gradient magnitude",
                 "ncc_rot": "NCC gradient magnitude + rotation search", "orb": "ORB + RANSAC",
                 "sift": "SIFT + RANSAC"}


def _rotation_search(max_rotation_deg: float) -> str:
    if max_rotation_deg >= 180.0:
        return "any rotation"
    return f"+-{max_rotation_deg:g} deg (heading prior, MatchParams.max_rotation)"


def _fmt(x, spec=".2f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def _report(setup, study, results, pngs, seconds) -> str:
    n = setup["blocks"]
    lc = np.array(setup["landmark_counts"])
    rc = np.array(setup["region_counts"])
    cm = setup["camera"]
    lines = [
        f"# Evaluation: {setup['dem']}, {n} blocks at {setup['gsd_m']:.2f} m", "",
        "## Setup", "",
        "| item | value |", "|---|---|",
        f"| DEM | {setup['dem']} (native {setup['native_gsd_m']:.2f} m) |",
        f"| GSD | {setup['gsd_m']:.3f} m/px (metamap cubic spline) |",
        f"| blocks | {setup['grid']} x {setup['grid']} = {n}, {setup['block_px']} px = "
        f"{setup['block_m']:.0f} m each |",
        f"| landmark sun (az, el) | {setup['sun'][0]:g}, {setup['sun'][1]:g} deg |",
        f"| extractor input | {setup['lighting']} |",
        "| camera conditions | " + "; ".join(f"{k}: sun {v[0]:g}/{v[1]:g}" for k, v in
                                            setup["conditions"].items()) + " |",
        f"| camera degradation | other albedo ramp, rotation +-{cm['max_rotation_deg']:g} deg, "
        f"scale +-{100 * cm['max_scale_change']:g} %, offset +-{cm['max_offset_px']:g} px, "
        f"blur {cm['effects']['blur_sigma']:g} px, noise {cm['effects']['read_noise']:g} + "
        f"shot, haze, vignetting, 8 bit |",
        f"| false-match rate | {setup['false_match_rate']:g} (two-fold calibration on "
        "non-PVA halves) |",
        f"| minutiae per landmark block | min {lc.min()}, median {np.median(lc):.0f}, "
        f"max {lc.max()} |",
        f"| localisation region | {setup['region_factor']:g} x block side ({np.median(rc):.0f} "
        "minutiae median) |",
        f"| matcher rotation search | {_rotation_search(setup['matcher_max_rotation_deg'])} |",
        "| crease check | " + ("on: crease skeletons score and refine each registration"
                               if setup["matcher_crease_check"]
                               else "off: minutiae alone (the dissertation)") + " |",
        "| ridge check | " + (f"on below {setup['matcher_ridge_check_below']} minutiae: ridge "
                               "skeletons score each registration too"
                               if setup["matcher_ridge_check"] else "off") + " |",
        f"| seed | {setup['seed']} |", "",
    ]
    lines += ["## Match results (PVA = same place, non-PVA = different places)", "",
              "| condition | threshold (fold 1 / 2) | PVA misses | miss rate | no-decision "
              "(min. minutiae or drainage) | non-PVA accepted held-out (fold 1 / 2) | "
              "non-PVA accepted, all pairs | max non-PVA score | PVA misses at zero non-PVA "
              "accepted (threshold just above the max) | at default threshold 3.0: misses / "
              "non-PVA accepted |", "|---|---|---:|---:|---:|---|---:|---:|---:|---|"]
    for r in results:
        f1, f2 = r["calibration"]["folds"]
        lines.append(
            f"| {r['name']} | {f1['threshold']:.2f} / {f2['threshold']:.2f} | "
            f"{len(r['missed_blocks'])} / {n} | {100 * r['miss_rate']:.1f} % | "
            f"{r['undecided_pva']} | {f1['held_out_accepted']}/{f1['held_out']} / "
            f"{f2['held_out_accepted']}/{f2['held_out']} | {r['non_pva_accepted']} / "
            f"{n * (n - 1)} | {_fmt(r['non_pva_max'])} | {r['pva_missed_zero_fa']} | "
            f"{r['pva_missed_default']} / "
            f"{r['non_pva_accepted_default']} |")
    lines.append("")
    for r in results:
        if r["missed_blocks"]:
            lines.append(f"Missed blocks ({r['name']}): "
                         + ", ".join(str(b) for b in r["missed_blocks"]) + "  ")
    lines += ["", "## Distribution of similarity scores", ""]
    for r in results:
        lines += [score_bins_table(r["pva_scores"], f"PVA matches, {r['name']}"), "",
                  score_bins_table(r["non_pva_scores"], f"Non-PVA matches, {r['name']}"), ""]
    lines += ["## Fix error of the accepted PVA matches (block vs block)", "",
              "| condition | accepted | median px | p95 px | max px | median m | p95 m | "
              "compare ms (median, prebuilt indexes) | camera extraction ms |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        e = r["fix_err_px"]
        fin = e[np.isfinite(e)]
        lines.append(
            f"| {r['name']} | {len(fin)} / {n} | {_fmt(r['fix_err_median_px'])} | "
            f"{_fmt(r['fix_err_p95_px'])} | {_fmt(np.max(fin) if len(fin) else math.nan)} | "
            f"{_fmt(r['fix_err_median_m'], '.1f')} | {_fmt(r['fix_err_p95_m'], '.1f')} | "
            f"{r['compare_ms_median']:.2f} | {r['extract_ms_median']:.1f} |")
    lines += ["", f"## Localisation of each camera block in a {setup['region_factor']:g}x "
              "landmark region, with the baselines", "",
              f"Success = accepted and centre error <= {setup['success_px']:g} px. Minutiae "
              "accept only above the calibrated threshold; the baselines always answer with "
              "their best peak (accepted = found). Errors are over accepted cases. Time per "
              "case = camera-side processing + matching (minutiae: camera extraction + "
              "localise; NCC: camera gradient + matchTemplate; keypoints: camera detection + "
              "matching + RANSAC), single thread; the landmark side (region extraction and "
              "index / gradient / detection) is done once per region and listed apart.", "",
              "| condition | method | success | accepted | wrong accepted (> 10 px) | "
              "median err px | "
              "p95 err px | median err m | ms per case (median / mean) | landmark prep ms |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for m, s in r["localisation"].items():
            lines.append(
                f"| {r['name']} | {_METHOD_NAMES[m]} | {s['success']}/{s['cases']} "
                f"({100 * s['success_rate']:.0f} %) | {s['accepted']} | {s['wrong_accepted']} "
                f"({s['gross_wrong_accepted']}) | {_fmt(s['err_median_px'])} | "
                f"{_fmt(s['err_p95_px'])} | "
                f"{_fmt(s['err_median_px'] * setup['gsd_m'], '.1f')} | "
                f"{s['time_ms_median']:.1f} / {s['time_ms_mean']:.1f} | "
                f"{s['landmark_prep_ms_median']:.1f} |")
    lines += ["", "## Figures", ""] + [f"![{p}]({p})" for p in pngs]
    lines += ["", f"Total time {seconds:.0f} s.", ""]
    return "\n".join(lines)


def _block_table(study: _Study, r: dict) -> str:
    """Per-block match results (the dissertation's Tables 5.1/5.2 layout)."""
    s = r["score"]
    n = len(s)
    lines = [f"# Match results per block ({r['name']}, threshold {r['threshold']:.2f})", "",
             "| block | landmark minutiae | camera minutiae | PVA score | PVA pairings | "
             "best non-PVA score (row) | fix error px | result |",
             "|---:|---:|---:|---:|---:|---:|---:|---|"]
    for i in range(n):
        row = np.delete(s[i], i)
        best = float(np.max(row)) if len(row) else math.nan
        res = "match" if s[i, i] >= r["threshold"] else "MISS"
        lines.append(f"| {i} | {len(study.blocks[i].minutiae)} | {r['camera_counts'][i]} | "
                     f"{_fmt(s[i, i])} | {r['pairings'][i, i]} | {_fmt(best)} | "
                     f"{_fmt(r['fix_err_px'][i])} | {res} |")
    return "\n".join(lines) + "\n"
