"""Registration proposals from the crease skeletons (core.crease_search) and their use by the
matcher for sets with too few minutiae."""

import math

import cv2
import numpy as np
import pytest
from scipy import fft as sfft
from skimage.morphology import skeletonize
from synthetic_minutiae import crop_set, rigid_transform, transform_set

from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.matching.crease_check import CreaseField, CreaseSamples, crease_covariance
from terrain_nav_ros.core.matching.crease_search import (
    CreaseSearchQuery,
    CreaseSearchReference,
    search_rotations,
    search_scales,
    search_transforms,
)
from terrain_nav_ros.core.matching.matcher import Decision, Matcher
from terrain_nav_ros.core.matching.pva_fix import fix_from_ground_match
from terrain_nav_ros.core.matching.registration import _covariance
from terrain_nav_ros.core.terrain.georef import GeoReference

SIZE = 64


def _turned_view(ms, skel, x0, y0, rotation_deg, shift):
    """A SIZE px view of the region at (x0, y0), turned and shifted: its minutiae, its
    re-thinned skeleton, and the pixel transform view -> region block at (x0, y0)."""
    c = 0.5 * (SIZE - 1)
    # block px -> view px
    m = rigid_transform(math.radians(rotation_deg), *shift, centre=(c, c))
    block = skel[y0:y0 + SIZE, x0:x0 + SIZE].astype(np.float32)
    view = cv2.warpAffine(block, m, (SIZE, SIZE), flags=cv2.INTER_LINEAR)
    view_skel = skeletonize(view > 0.3)
    view_ms, _ = transform_set(crop_set(ms, x0, y0, SIZE, SIZE), m, (SIZE, SIZE), rng=0,
                               pos_sigma=1.0, missing=0.0, spurious=0.0)
    return view_ms, view_skel, cv2.invertAffineTransform(m)


def _centre_error(result_or_ct, truth) -> float:
    c = 0.5 * (SIZE - 1)
    if isinstance(result_or_ct, tuple):
        rot, t = result_or_ct
        z = rot * complex(c, -c) + t
        got = np.array([z.real, -z.imag])
    else:
        got = np.array(result_or_ct.apply(c, c))
    return float(np.hypot(*(got - truth @ np.array([c, c, 1.0]))))


def test_rotations_cover_the_circle_or_the_prior():
    full = search_rotations(math.pi, radius=30.0, tolerance=3.0)
    steps = np.diff(full)
    assert np.allclose(steps, steps[0]) and steps[0] * 30.0 <= 3.0 + 1e-9
    assert full[0] == -math.pi and full[-1] + steps[0] == pytest.approx(math.pi)
    prior = search_rotations(math.radians(15.0), radius=30.0, tolerance=3.0)
    assert prior[0] == pytest.approx(-math.radians(15.0)) and prior[-1] == pytest.approx(
        math.radians(15.0)) and 0.0 in prior


@pytest.mark.parametrize("rotation_deg", [-8.0, 37.0, 150.0])
def test_search_finds_a_turned_and_shifted_view(region, rotation_deg):
    ms, skel = region
    _, view_skel, truth = _turned_view(ms, skel, 200, 180, rotation_deg, (5.0, -4.0))
    samples = CreaseSamples.from_image(view_skel)
    reference = CreaseSearchReference(CreaseField(skel[180:180 + SIZE, 200:200 + SIZE]))
    reach = float(np.percentile(np.abs(samples.z - samples.z.mean()), 90))
    query = CreaseSearchQuery(samples, search_rotations(math.pi, reach))
    found = search_transforms(query, reference, n_best=3)
    c, t, _ = found.proposals[0]
    # a proposal is on the search's coarse grid: within a couple of pixels at the centre
    assert _centre_error((c, t), truth) < 3.0
    assert abs(math.degrees(np.angle(c)) - (-rotation_deg)) < 6.0 or abs(
        math.remainder(math.degrees(np.angle(c)) + rotation_deg, 360.0)) < 6.0
    # the transforms searched: ~100 rotations times a few hundred translation cells
    assert 4.0 < found.log10_transforms < 6.0
    # the query's spectra serve the next reference of the same size unchanged
    again = search_transforms(query, reference, n_best=3)
    assert again == found
    with pytest.raises(ValueError, match="resolution"):
        search_transforms(CreaseSearchQuery(samples, [0.0], resolution=1.0), reference)


def test_search_kernels_agree_with_the_numpy_path(region, monkeypatch):
    """The fused channel product and footprint counts give the numpy path's proposals and
    counts of transforms (the product's sums may round differently: equal to ~1e-6)."""
    from terrain_nav_ros.core.matching import _matching_kernels

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    ms, skel = region
    _, view_skel, _ = _turned_view(ms, skel, 200, 180, 37.0, (5.0, -4.0))
    samples = CreaseSamples.from_image(view_skel)
    reference = CreaseSearchReference(CreaseField(skel[120:312, 140:332]))

    def run():
        query = CreaseSearchQuery(samples, search_rotations(math.pi, 28.0))
        shape, _ = query.spectra(reference)
        return query.inside(shape, reference), search_transforms(query, reference, n_best=4)

    fast_inside, fast = run()
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow_inside, slow = run()
    np.testing.assert_array_equal(fast_inside, slow_inside)
    assert fast.log10_transforms == slow.log10_transforms
    assert len(fast.proposals) == len(slow.proposals) == 4
    for (c, t, h), (c2, t2, h2) in zip(fast.proposals, slow.proposals, strict=True):
        assert c == c2 and t == t2 and h == pytest.approx(h2, rel=1e-5)


@pytest.mark.parametrize("rotation_deg", [-8.0, 37.0, 150.0])
def test_shortlist_keeps_the_proposals_of_the_full_search(region, rotation_deg):
    """Correlating in full only the rotations with the most hits at half the resolution
    gives the proposals of correlating every rotation in full: a view of the same place
    leads at both resolutions."""
    ms, skel = region
    _, view_skel, _ = _turned_view(ms, skel, 200, 180, rotation_deg, (5.0, -4.0))
    samples = CreaseSamples.from_image(view_skel)
    reference = CreaseSearchReference(CreaseField(skel[120:312, 140:332]))
    query = CreaseSearchQuery(samples, search_rotations(math.pi, 28.0))
    assert len(query.c) > 8 * 3          # the shortlist is in use
    found = search_transforms(query, reference, n_best=3)
    assert found == search_transforms(query, reference, n_best=3, shortlist=0)
    assert len(found.proposals) == 3


def test_quarter_turns_search_as_every_rotation(region):
    """A whole-circle search transforms a quarter of the query's rotations, against the
    reference turned four ways: the same proposals as rasterising every rotation (their
    hits differ only where a rotated pixel sits on a rounding tie), also for a reference
    that is not square (zero-padded to one for the quarter turns)."""
    ms, skel = region
    _, view_skel, truth = _turned_view(ms, skel, 200, 180, 150.0, (5.0, -4.0))
    samples = CreaseSamples.from_image(view_skel)
    rotations = search_rotations(math.pi, 28.0)
    assert len(rotations) % 4 == 0
    quarter = CreaseSearchQuery(samples, rotations)
    whole = CreaseSearchQuery(samples, rotations, quarter_turns=False)
    assert quarter.quarter and not whole.quarter
    assert quarter.raster.shape[0] == len(rotations) // 4
    np.testing.assert_allclose(quarter.c, whole.c, atol=1e-12)
    for reference, region_origin in [
            (CreaseSearchReference(CreaseField(skel[120:312, 140:332])), (140, 120)),
            (CreaseSearchReference(CreaseField(skel[150:278, 110:350])), (110, 150))]:
        got = search_transforms(quarter, reference, n_best=4)
        want = search_transforms(whole, reference, n_best=4)
        assert got.log10_transforms == pytest.approx(want.log10_transforms, abs=1e-3)
        for (c, t, h), (c2, t2, h2) in zip(got.proposals, want.proposals, strict=True):
            assert abs(c - c2) < 1e-9 and abs(t - t2) < 1e-9
            assert h == pytest.approx(h2, rel=0.1)
        c, t, _ = got.proposals[0]
        in_block = t - complex(200 - region_origin[0], -(180 - region_origin[1]))
        assert _centre_error((c, in_block), truth) < 3.0
    assert not reference.square and reference.squared().square


def test_a_turned_reference_maps_its_pixels_by_turn_offset():
    field = np.zeros((12, 12), bool)
    field[2, 3:9] = True               # a horizontal crease
    field[4:10, 9] = True              # a vertical one
    ref = CreaseSearchReference(CreaseField(field), resolution=1.0)
    for turns in range(4):
        turned = ref.turned(turns)
        rows, cols = np.nonzero(ref.channels.sum(axis=0) > 0.5)
        z = cols - 1j * rows
        moved = (-1j) ** turns * z + ref.turn_offset(turns)
        got = turned.channels.sum(axis=0)[np.rint(-moved.imag).astype(int),
                                          np.rint(moved.real).astype(int)]
        np.testing.assert_allclose(got, ref.channels.sum(axis=0)[rows, cols], rtol=1e-6)
        # directions turn with it: the horizontal crease lands in the 90 deg channel
        if turns % 2:
            assert turned.channels[2].sum() == pytest.approx(ref.channels[0].sum())
    assert ref.turned(4) is ref and ref.turned(1) is ref.turned(1)


def test_search_without_creases_proposes_nothing(region):
    reference = CreaseSearchReference(CreaseField(region[1][:SIZE, :SIZE]))
    empty = CreaseSamples.from_image(np.zeros((SIZE, SIZE), bool))
    found = search_transforms(CreaseSearchQuery(empty, search_rotations(math.pi, 30.0)),
                              reference)
    assert found.proposals == []


def test_matcher_registers_a_block_with_almost_no_minutiae(region):
    """Two minutiae cannot propose a transform; the crease search does, and the creases carry
    the match (the minimum-minutiae rule becomes one on the drainage)."""
    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 200, 180, 23.0, (6.0, 3.0))
    few = view_ms.subset(np.arange(min(2, len(view_ms))))
    block_ms = crop_set(ms, 200, 180, SIZE, SIZE)
    block_skel = skel[180:180 + SIZE, 200:200 + SIZE]
    matcher = Matcher()
    r = matcher.compare(matcher.index(few, view_skel), matcher.index(block_ms, block_skel))
    assert r.decision == Decision.MATCH, r.reason
    assert _centre_error(r, truth) < 1.5
    assert r.creases.fraction > 0.5
    # with too few pairings for a minutiae covariance, the creases give one
    cov = r.covariance
    assert np.isfinite(cov).all() and np.all(np.linalg.eigvalsh(cov) > 0)
    assert r.point_covariance(31.5, 31.5).trace() < 1.0
    # without the search, the old rule holds: too few minutiae to decide
    no_search = Matcher(crease_search_below=0)
    r = no_search.compare(no_search.index(few, view_skel),
                          no_search.index(block_ms, block_skel))
    assert r.decision == Decision.NO_DECISION and "too few minutiae" in r.reason


def test_searched_registrations_pay_for_the_search(region, other_region):
    """Unrelated small blocks stay below the default threshold although the search tries
    every rotation and translation."""
    ms, skel = region
    oms, oskel = other_region
    matcher = Matcher()
    for x0, y0 in [(200, 180), (60, 300), (330, 90)]:
        a = matcher.index(crop_set(oms, x0, y0, SIZE, SIZE), oskel[y0:y0 + SIZE, x0:x0 + SIZE])
        b = matcher.index(crop_set(ms, x0, y0, SIZE, SIZE), skel[y0:y0 + SIZE, x0:x0 + SIZE])
        assert matcher.compare(a, b).decision != Decision.MATCH


def test_too_little_drainage_is_no_decision(region):
    ms, skel = region
    block_ms = crop_set(ms, 200, 180, SIZE, SIZE)
    block_skel = skel[180:180 + SIZE, 200:200 + SIZE]
    lake = np.zeros_like(block_skel)
    lake[30, 20:40] = True                 # one short crease: 20 px
    matcher = Matcher()
    r = matcher.compare(matcher.index(block_ms.subset(np.arange(3)), lake),
                        matcher.index(block_ms, block_skel))
    assert r.decision == Decision.NO_DECISION and "too little drainage" in r.reason


def test_localisation_by_creases_and_its_size_bounds(region):
    """A 64 px view with two minutiae is found in a 512 px landmark region by the search
    (at the coarse level); a search beyond ``crease_search_max_work`` (rotations x FFT
    pixels, which grow with the region's area) is not run, so the minimum-minutiae rule
    applies there."""
    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 330, 90, 12.0, (3.0, -2.0))
    few = view_ms.subset(np.arange(2))
    truth_in_region = truth + np.array([[0, 0, 330], [0, 0, 90]])
    matcher = Matcher()
    r = matcher.localise(matcher.index(few, view_skel), matcher.index(ms, skel))
    assert r.decision == Decision.MATCH, r.reason
    assert _centre_error(r, truth_in_region) < 1.5
    bounded = Matcher(crease_search_max_work=500_000)
    r = bounded.localise(bounded.index(few, view_skel), bounded.index(ms, skel))
    assert r.decision == Decision.NO_DECISION and "too few minutiae" in r.reason


def test_a_view_of_terrain_the_region_holds_twice_is_ambiguous_not_a_fix():
    """Repeated terrain (a region tiled from one 256 px drainage pattern): every copy
    registers the view as well, so the matcher answers no fix and says why, where the region
    holding it once localises it."""
    from synthetic_minutiae import crossing_minutiae, terrain_minutiae

    skel = terrain_minutiae((256, 256), seed=13)[1]
    matcher = Matcher()
    once = np.zeros((512, 512), bool)
    once[:256, :256] = skel
    for region_skel in (once, np.tile(skel, (2, 2))):
        region_ms = crossing_minutiae(region_skel)
        view_ms, view_skel, truth = _turned_view(region_ms, region_skel, 60, 160, 30.0,
                                                 (2.0, -1.0))
        r = matcher.localise(matcher.index(view_ms, view_skel),
                             matcher.index(region_ms, region_skel))
        if region_skel is once:
            assert r.decision == Decision.MATCH, r.reason
            assert _centre_error(r, truth + np.array([[0, 0, 60], [0, 0, 160]])) < 1.5
        else:
            assert r.decision == Decision.NO_MATCH and r.reason.startswith("ambiguous: "), \
                (r.decision, r.score, r.reason)
            assert "256 px away" in r.reason or "362 px away" in r.reason


@pytest.mark.parametrize("scale, found", [(0.92, True), (1.08, True), (1.25, False)])
def test_a_view_whose_scale_is_off_the_prior_is_no_fix(region, scale, found):
    """The prior's height above ground sets the view's scale within +-10 %: a view at 0.92
    or 1.08 is fitted at its scale; one at 1.25 (a wrong height) stops at the fit's bound
    and is refused, not a fix at the wrong scale."""
    from synthetic_minutiae import crossing_minutiae

    _, skel = region
    size, x0, y0 = 128, 300, 180
    c = 0.5 * (size - 1)
    # view px -> region px: the view sees 1/scale region px per px, turned 15 deg
    m = cv2.getRotationMatrix2D((c, c), 15.0, 1.0 / scale)
    m[:, 2] += [x0 + c - c, y0 + c - c]
    view = cv2.warpAffine(skel.astype(np.float32), m, (size, size),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    view_skel = skeletonize(view > 0.3)
    matcher = Matcher()
    r = matcher.localise(matcher.index(crossing_minutiae(view_skel), view_skel),
                         matcher.index(crossing_minutiae(skel), skel))
    if found:
        assert r.decision == Decision.MATCH, r.reason
        assert r.scale == pytest.approx(1.0 / scale, rel=0.02)
        assert np.hypot(*(np.array(r.apply(c, c)) - (m @ [c, c, 1.0]))) < 2.0
    else:
        assert r.decision == Decision.NO_MATCH and "at the edge of the fit" in r.reason, \
            (r.decision, r.scale, r.reason)


@pytest.mark.parametrize("scale", [0.97, 1.0, 1.04])
def test_a_localisation_measures_its_scale_on_the_creases(region, scale):
    """Whatever fitted the transform (the minutiae's rigid fit keeps the prior's scale), a
    localisation measures the view's scale on the creases with the scale free: the height
    above ground the view was seen from. A comparison of blocks (no scale prior) does not."""
    from synthetic_minutiae import crossing_minutiae

    _, skel = region
    view, _ = _scaled_view(skel, 200, 150, 192, 25.0, scale)
    matcher = Matcher()
    a, b = (matcher.index(crossing_minutiae(s), s) for s in (view, skel))
    r = matcher.localise(a, b)
    assert r.decision == Decision.MATCH, r.reason
    sigma = math.sqrt(r.scale_variance)
    assert abs(r.scale_measured - 1.0 / scale) < max(3.0 * sigma, 0.004), \
        (r.scale_measured, sigma, r.scale)
    assert 1e-4 < sigma < 0.01
    block = matcher.compare(a, matcher.index(crossing_minutiae(view), view))
    assert block.decision == Decision.MATCH and math.isnan(block.scale_measured)


def test_a_large_search_runs_coarse_and_registers_as_the_fine_one(region):
    """The view's search in the 512 px region is over the fine level's budget: it runs at
    the coarse level (an eighth of the work) and the coarse-to-fine ICP pulls its proposals
    onto the creases, as exactly as the fine search's; both count the fine level's
    transforms. Against its own block the search stays fine."""
    from terrain_nav_ros.core.matching.crease_proposals import (
        _crease_search_registrations,
        _search_level,
    )
    from terrain_nav_ros.core.matching.crease_search import COARSE, FINE

    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 330, 90, -17.0, (4.0, 2.0))
    truth_in_region = truth + np.array([[0, 0, 330], [0, 0, 90]])
    few = view_ms.subset(np.arange(2))
    found = {}
    for name, matcher in [("default", Matcher()),
                          ("fine", Matcher(crease_search_fine_work=10**12))]:
        a, b = matcher.index(few, view_skel), matcher.index(ms, skel)
        block = matcher.index(crop_set(ms, 330, 90, SIZE, SIZE),
                              skel[90:90 + SIZE, 330:330 + SIZE])
        assert _search_level(a, block, matcher.params) == FINE
        found[name] = (_search_level(a, b, matcher.params),
                       *_crease_search_registrations(a, b, matcher.params))
    assert found["default"][0] == COARSE and found["fine"][0] == FINE
    for level, registrations, _ in found.values():
        c, t, _ = registrations[0]
        assert _centre_error((c, t), truth_in_region) < 1.0, level
    assert found["default"][2] == pytest.approx(found["fine"][2], abs=0.2)


def test_crease_covariance_shrinks_with_agreement(region):
    skel = region[1]
    block = skel[100:228, 100:228]
    samples = CreaseSamples.from_image(block)
    field = CreaseField(block)
    cov = crease_covariance(samples, field, 1 + 0j, 0j)
    assert np.isfinite(cov).all()
    # exact agreement: only the pixel quantisation floor, spread over hundreds of pixels
    assert np.sqrt(cov[2, 2]) < 0.1 and np.sqrt(cov[3, 3]) < 0.1
    empty = CreaseField(np.zeros_like(block))
    assert np.isnan(crease_covariance(samples, empty, 1 + 0j, 0j)).all()


def test_moving_a_searched_registration_keeps_its_search_penalty(region):
    """The final ICP of the best registration re-scores it; a searched one must still pay
    for the search (a regression: the moved copy used to drop the penalty)."""
    from dataclasses import replace

    from terrain_nav_ros.core.matching.registration import _pair
    from terrain_nav_ros.core.matching.scoring import _refined_on_creases, _scored

    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 330, 90, 10.0, (2.0, 1.0))
    matcher = Matcher()
    p = matcher.params
    a = matcher.index(view_ms, view_skel)
    b = matcher.index(crop_set(ms, 330, 90, SIZE, SIZE), skel[90:90 + SIZE, 330:330 + SIZE])
    # the true transform, put 1.5 px off so that the ICP moves it
    c = complex(truth[0, 0], truth[0, 1])
    t = complex(truth[0, 2], -truth[1, 2]) + 1.5
    search_area, radius = 4.0 * b.area, a.radius
    start = _scored(a, b, c, t, _pair(a, b, c, t, p), search_area, radius, p, True)
    start = replace(start, score=start.score - 3.0, search_penalty=3.0)
    moved = _refined_on_creases(a, b, start, search_area, radius, p)
    assert (moved.c, moved.t) != (c, t) and moved.search_penalty == 3.0
    fresh = _scored(a, b, moved.c, moved.t, moved.pairs, search_area, radius, p, True)
    assert moved.score == pytest.approx(fresh.score - 3.0)


@pytest.mark.parametrize("numba", [True, False])
def test_query_raster_and_margins_are_those_of_every_pixel(monkeypatch, numba):
    """The query's shape and origins (from the outline of its pixels), its rasters (the
    kernel's or numpy's) and its alias margins (from the count rasters) are those of every
    pixel mapped by every transform, ties of a half turn included."""
    from terrain_nav_ros.core.matching import _matching_kernels
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", numba and _matching_kernels.HAVE_NUMBA)
    rng = np.random.default_rng(5)
    img = np.zeros((90, 70), np.uint8)
    for x0, y0, x1, y1 in rng.integers(0, 70, (12, 4)):
        cv2.line(img, (int(x0), int(y0)), (int(x1), int(y1)), 1, 1)
    samples = CreaseSamples.from_image(img)
    for rotations, scales in ((search_rotations(math.pi, 35.0, 6.0), (0.95, 1.0, 1.05)),
                              (np.linspace(-0.3, 0.3, 5), (1.0,))):
        query = CreaseSearchQuery(samples, rotations, resolution=0.125, scales=scales)
        q = query.c[:, None] * (samples.z[None, :] * 0.125)
        cols, rows = np.rint(q.real), np.rint(-q.imag)
        np.testing.assert_array_equal(query.col0, cols.min(axis=1))
        np.testing.assert_array_equal(query.row0, rows.min(axis=1))
        ri = (rows - query.row0[:, None]).astype(int)
        ci = (cols - query.col0[:, None]).astype(int)
        assert query.shape == (ri.max() + 1, ci.max() + 1)
        turn = np.angle(query.c)
        for r in range(query.n_rastered):
            want = np.zeros((5, *query.shape))
            d = np.mod(samples.direction + turn[r], np.pi)
            for k in range(4):
                np.add.at(want[k], (ri[r], ci[r]), np.maximum(np.cos(2 * (d - k * np.pi / 4)), 0))
            np.add.at(want[4], (ri[r], ci[r]), 1.0)
            np.testing.assert_allclose(query.raster[r], want, atol=1e-5)
        m = int(math.ceil(0.5 * query.n))
        for x, axis in ((ri, 0), (ci, 1)):
            x = np.sort(x, axis=1)
            need = int(np.maximum(x[:, query.n - m], x[:, -1] - x[:, m - 1]).max())
            assert query._alias_margins(0.5)[axis] == need


def test_footprint_counts_are_the_query_pixels_over_the_reference():
    """At every shift of the correlation (negative ones wrap to the end of each axis), the
    count the search keeps shifts by is the number of query pixels landing on B's footprint
    (all of B, or the part a squared and turned B holds of the original); the search's
    tighter padding keeps every shift with half the pixels on B unaliased."""
    rng = np.random.default_rng(4)
    query_img = rng.random((23, 17)) < 0.2
    samples = CreaseSamples.from_image(query_img)
    original = CreaseSearchReference(CreaseField(rng.random((40, 31)) < 0.1), resolution=1.0)
    # the original's 40 rows x 31 cols, padded to 40 x 40 and turned clockwise: cols 0-39,
    # rows 0-30 from the top
    turned = original.squared().turned(1)
    assert turned.shape == (40, 40) and turned.footprint == (0, 31, 0, 40)
    query = CreaseSearchQuery(samples, [0.0, 0.7], resolution=1.0)
    for reference in (original, turned):
        full_shape, _ = query.spectra(reference, min_inside=None)
        full_inside = query.inside(full_shape, reference)
        shape, _ = query.spectra(reference)
        inside = query.inside(shape, reference)
        assert shape[0] < full_shape[0] and shape[1] < full_shape[1]
        hb, wb = reference.shape
        r0, r1, c0, c1 = reference.footprint
        ha, wa = query.shape
        for r in range(2):
            counts = query.raster[r, 4]
            rows, cols = np.nonzero(counts)
            for dy in range(1 - ha, hb):
                for dx in range(1 - wa, wb):
                    on_b = ((rows + dy >= r0) & (rows + dy < r1) & (cols + dx >= c0)
                            & (cols + dx < c1))
                    expected = counts[rows[on_b], cols[on_b]].sum()
                    assert full_inside[r, dy % full_shape[0], dx % full_shape[1]] == expected
                    if expected >= 0.5 * query.n:
                        assert inside[r, dy % shape[0], dx % shape[1]] == expected, (r, dy, dx)


def test_query_spectra_are_completed_for_the_rasters_asked_for():
    """The shortlist reads the query's lowest frequencies of every raster, the correlation
    the full spectra of a few: those asked for equal the zero-padded rfft2 of their raster
    (the same values, not only close), and asking for more completes them in place."""
    rng = np.random.default_rng(7)
    samples = CreaseSamples.from_image(rng.random((29, 21)) < 0.2)
    reference = CreaseSearchReference(CreaseField(rng.random((50, 43)) < 0.1), resolution=1.0)
    query = CreaseSearchQuery(samples, np.linspace(-1.0, 1.0, 6), resolution=1.0,
                              quarter_turns=False)
    shape = query.padded_shape(reference.full_shape, 0.5)
    full = sfft.fft(sfft.rfft(query.raster[:, :4], n=shape[1], axis=-1),
                    n=shape[0], axis=-2)
    low = query.low_spectra(reference)
    h2, w2 = -(-shape[0] // 2), -(-shape[1] // 2)
    rows = np.r_[0:(h2 + 1) // 2, shape[0] - h2 // 2:shape[0]]
    np.testing.assert_array_equal(low, full[..., rows, :w2 // 2 + 1])
    got_shape, spec = query.spectra(reference, rastered=np.array([4, 1, 4]))
    assert got_shape == shape
    np.testing.assert_array_equal(spec[[1, 4]], full[[1, 4]])
    _, spec = query.spectra(reference)
    np.testing.assert_array_equal(spec, full)
    # the low frequencies the shortlist read are unchanged by completing the rest
    np.testing.assert_array_equal(query.low_spectra(reference), low)


def test_searched_shifts_are_those_with_enough_of_the_query_over_the_reference():
    """The shifts searched (built from the prefix sums without the counts) are exactly
    those whose footprint count reaches the fraction, for every turn of a non-square
    reference and for fractions whose threshold is not a whole count."""
    rng = np.random.default_rng(11)
    samples = CreaseSamples.from_image(rng.random((27, 19)) < 0.2)
    original = CreaseSearchReference(CreaseField(rng.random((45, 33)) < 0.1), resolution=1.0)
    query = CreaseSearchQuery(samples, _whole_circle_rotations(8), resolution=1.0)
    for turns in range(4):
        reference = original.squared().turned(turns)
        for min_inside in (0.5, 0.3, 0.77):
            shape = query.padded_shape(reference.full_shape, min_inside)
            searched = query.searched(shape, reference, min_inside)
            expected = query.inside(shape, reference) >= min_inside * query.n
            np.testing.assert_array_equal(searched.mask, expected)
            assert searched.count == np.count_nonzero(expected) > 0


def _whole_circle_rotations(n):
    return np.arange(n) * (2.0 * math.pi / n) - math.pi


def _scaled_view(skel, x0, y0, size, rotation_deg, scale):
    """A ``size`` px view of the skeleton around block (x0, y0), turned and scaled about its
    centre, re-thinned; and the pixel transform view -> skeleton."""
    c = 0.5 * (size - 1)
    m = cv2.getRotationMatrix2D((c, c), rotation_deg, scale)   # block px -> view px
    block = skel[y0:y0 + size, x0:x0 + size].astype(np.float32)
    view = skeletonize(cv2.warpAffine(block, m, (size, size), flags=cv2.INTER_LINEAR) > 0.3)
    back = cv2.invertAffineTransform(m)
    back[:, 2] += (x0, y0)
    return view, back


def test_scales_step_by_the_tolerance_at_the_reach():
    scales = search_scales(0.1, radius=100.0, tolerance=3.0)
    assert 1.0 in scales and np.allclose(np.diff(scales), 0.03)
    assert scales[0] <= 0.9 + 0.015 and scales[-1] >= 1.1 - 0.015
    assert list(search_scales(0.0, radius=100.0)) == [1.0]


def test_search_over_scales_finds_a_scaled_view(region):
    """A view 8 % larger than the reference is found, with its scale, only when scales are
    searched: at its reach 8 % is more than a hit's tolerance."""
    _, skel = region
    view, truth = _scaled_view(skel, 120, 140, 160, 30.0, 1.08)
    samples = CreaseSamples.from_image(view)
    reach = float(np.percentile(np.abs(samples.z - samples.z.mean()), 90))
    reference = CreaseSearchReference(CreaseField(skel), resolution=0.25)
    rotations = search_rotations(math.pi, reach, 6.0)
    scaled = search_transforms(CreaseSearchQuery(samples, rotations, 0.25,
                                                 scales=search_scales(0.1, reach, 6.0)),
                               reference, n_best=3)
    c, t, _ = scaled.proposals[0]
    centre = 0.5 * (160 - 1)
    z = c * complex(centre, -centre) + t
    expected = truth @ np.array([centre, centre, 1.0])
    assert np.hypot(z.real - expected[0], -z.imag - expected[1]) < 6.0
    assert abs(abs(c) - 1 / 1.08) < 0.04
    # more transforms searched: the scales are paid for
    fixed = search_transforms(CreaseSearchQuery(samples, rotations, 0.25), reference, n_best=3)
    assert scaled.log10_transforms > fixed.log10_transforms


def test_background_draws_proposals_to_agreement_not_density(region):
    """Where the reference's creases are dense (a patch of random lines, like the albedo
    edges of fields), raw hits draw the proposals there; counting hits above the local
    density finds the view's true place."""
    _, skel = region
    view, truth = _scaled_view(skel, 300, 300, 128, 0.0, 1.0)
    noisy = skel.copy()
    rng = np.random.default_rng(3)
    for x0, y0 in rng.integers(20, 230, (300, 2)):   # ~18 % of the patch's pixels
        a = rng.uniform(0.0, np.pi)
        cv2.line(noisy, (int(x0), int(y0)), (int(x0 + 30 * np.cos(a)), int(y0 + 30 * np.sin(a))),
                 1, 1)
    samples = CreaseSamples.from_image(view)
    query = CreaseSearchQuery(samples, [0.0], resolution=0.25)
    centre = 0.5 * (128 - 1)
    expected = truth @ np.array([centre, centre, 1.0])

    def error(background):
        ref = CreaseSearchReference(CreaseField(noisy), resolution=0.25,
                                    background=background)
        c, t, _ = search_transforms(query, ref, n_best=1).proposals[0]
        z = c * complex(centre, -centre) + t
        return np.hypot(z.real - expected[0], -z.imag - expected[1])

    assert error(0.0) > 20.0
    assert error(3.0) < 6.0


def test_a_large_view_is_found_by_the_view_search(region):
    """A 192 px view, turned and 7 % larger, with its minutiae gone (a real image's albedo
    minutiae repeat none of the render's): the minutiae's tries find nothing, the view
    search over rotations and scales does."""
    ms, skel = region
    view, truth = _scaled_view(skel, 150, 160, 192, 140.0, 1.07)
    centre = 0.5 * (192 - 1)
    expected = truth @ np.array([centre, centre, 1.0])
    rng = np.random.default_rng(5)
    n = 40
    unrelated = MinutiaSet(rng.uniform(0, 191, n), rng.uniform(0, 191, n),
                           rng.uniform(-np.pi, np.pi, n), rng.choice([1, 3], n).astype(np.uint8),
                           np.ones(n, np.float32))
    for view_search, found in [(True, True), (False, False)]:
        matcher = Matcher(view_search=view_search)
        region_index = matcher.index(ms, skel).prepare_as_reference(search=True)
        r = matcher.localise(matcher.index(unrelated, view), region_index)
        err = np.hypot(*(np.array(r.apply(centre, centre)) - expected)) \
            if np.isfinite(r.transform).all() else np.inf
        assert (r.decision == Decision.MATCH and err < 3.0) == found, (view_search, r.reason,
                                                                       err)
        if found:
            assert abs(r.scale - 1 / 1.07) < 0.03


def test_the_view_search_comes_first_for_a_view_it_fits(region, other_region, monkeypatch):
    """A view the view search fits is searched densely first; the minutiae's votes are
    tried only when that is not clear (a view from elsewhere), and their sweep never (it
    would only add chances); a view it does not fit (the search off here) gets the votes
    and their sweep."""
    from terrain_nav_ros.core.matching import matcher as matching
    ms, skel = region
    view, _ = _scaled_view(skel, 150, 160, 192, 140.0, 1.07)
    elsewhere, _ = _scaled_view(other_region[1], 150, 160, 192, 140.0, 1.07)
    rng = np.random.default_rng(5)
    n = 40
    unrelated = MinutiaSet(rng.uniform(0, 191, n), rng.uniform(0, 191, n),
                           rng.uniform(-np.pi, np.pi, n), rng.choice([1, 3], n).astype(np.uint8),
                           np.ones(n, np.float32))
    calls = []

    def counted(tag, f):
        return lambda *a, **k: calls.append(tag) or f(*a, **k)

    for name, tag in (("_sweep_try", "sweep"), ("_view_try", "view"), ("_vote_try", "votes")):
        monkeypatch.setattr(matching, name, counted(tag, getattr(matching, name)))
    for view_search, creases, expected in [(True, view, ["view"]),
                                           (True, elsewhere, ["view", "votes"]),
                                           (False, view, ["votes", "sweep"])]:
        calls.clear()
        matcher = Matcher(view_search=view_search)
        region_index = matcher.index(ms, skel).prepare_as_reference(search=True)
        r = matcher.localise(matcher.index(unrelated, creases), region_index)
        assert calls == expected, (view_search, r.score)


def test_a_small_set_is_localised_by_agreement_not_density(region):
    """The crease search of a set with few minutiae in its localisation region counts hits
    above the region's local crease density, as the view search does: a patch of dense
    lines elsewhere in the region (fields' edges) does not draw the registration."""
    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 330, 90, 12.0, (3.0, -2.0))
    few = view_ms.subset(np.arange(2))
    truth_in_region = truth + np.array([[0, 0, 330], [0, 0, 90]])
    noisy = skel.copy()
    rng = np.random.default_rng(3)
    for x0, y0 in rng.integers(20, 260, (500, 2)):
        a = rng.uniform(0.0, np.pi)
        cv2.line(noisy, (int(x0), int(y0 + 220)),
                 (int(x0 + 30 * np.cos(a)), int(y0 + 220 + 30 * np.sin(a))), 1, 1)

    def error(matcher):
        r = matcher.localise(matcher.index(few, view_skel), matcher.index(ms, noisy))
        return _centre_error(r, truth_in_region) if r.decision == Decision.MATCH else np.inf

    assert error(Matcher()) < 1.5
    assert error(Matcher(view_search_background=0.0)) > 20.0


def _coarse_miss(truth: np.ndarray, turn: float, shift: complex) -> tuple[complex, complex]:
    """The math-frame transform ``truth`` (pixel affine, view -> region) turned by ``turn``
    (rad) about the view's centre and shifted by ``shift`` px: a coarse level's peak."""
    c = complex(truth[0, 0], -truth[1, 0])
    t = complex(truth[0, 2], -truth[1, 2])
    centre = complex(0.5 * (SIZE - 1), -0.5 * (SIZE - 1))
    c2 = c * np.exp(1j * turn)
    return c2, t + (c - c2) * centre + shift


@pytest.mark.parametrize("numba", [True, False])
def test_local_peaks_move_a_coarse_peak_onto_the_view(region, monkeypatch, numba):
    """A coarse peak a rotation step and a few pixels off the view's place is moved onto it
    by the fine level's local search, with more hits than where it was."""
    from terrain_nav_ros.core.matching import _matching_kernels
    from terrain_nav_ros.core.matching.crease_search import local_peaks

    if not numba:
        monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    ms, skel = region
    _, view_skel, truth = _turned_view(ms, skel, 200, 180, 37.0, (5.0, -4.0))
    truth_in_region = truth + np.array([[0, 0, 60], [0, 0, 60]])
    samples = CreaseSamples.from_image(view_skel)
    reference = CreaseSearchReference(CreaseField(skel[120:312, 140:332]), resolution=0.5)
    step = 3.0 / 28.0
    missed = _coarse_miss(truth_in_region, step, complex(3.0, 2.0))
    stay = local_peaks(samples, reference, [(*missed, 0.0)], 0.0, span=0)
    (c, t, hits), = local_peaks(samples, reference, [(*missed, 0.0)], step, span=3)
    assert _centre_error(missed, truth_in_region) > 3.0
    assert _centre_error((c, t), truth_in_region) < 1.5
    assert hits > 1.2 * stay[0][2]


def test_local_peaks_kernel_agrees_with_the_numpy_path(region, monkeypatch):
    """The kernel's hits are the numpy path's (summed in another order: equal to ~1e-9),
    at the same transforms."""
    from terrain_nav_ros.core.matching import _matching_kernels
    from terrain_nav_ros.core.matching.crease_search import local_peaks

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    ms, skel = region
    _, view_skel, truth = _turned_view(ms, skel, 200, 180, -20.0, (2.0, 3.0))
    samples = CreaseSamples.from_image(view_skel)
    reference = CreaseSearchReference(CreaseField(skel[120:312, 140:332]), resolution=0.5,
                                      background=6.0)
    truth_in_region = truth + np.array([[0, 0, 60], [0, 0, 60]])
    # near the view, and off the reference's edge (its shifts cross the padding)
    proposals = [(*_coarse_miss(truth_in_region, 0.1, complex(-2.0, 1.0)), 0.0),
                 (1j, complex(-20.0, 10.0), 0.0)]
    fast = local_peaks(samples, reference, proposals, 0.1, 0.05, span=3)
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow = local_peaks(samples, reference, proposals, 0.1, 0.05, span=3)
    for (c, t, h), (c2, t2, h2) in zip(fast, slow, strict=True):
        assert c == c2 and t == t2 and h == pytest.approx(h2, rel=1e-9)


def test_the_fine_level_ranks_a_coarse_search_s_candidates(region):
    """Among a coarse level's candidates, the one near the view's place comes first once
    each is searched again at the fine level, though it came last; places far from the
    view's are not kept twice."""
    from terrain_nav_ros.core.matching.crease_proposals import _finer_proposals

    ms, skel = region
    view_ms, view_skel, truth = _turned_view(ms, skel, 330, 90, -17.0, (4.0, 2.0))
    truth_in_region = truth + np.array([[0, 0, 330], [0, 0, 90]])
    matcher = Matcher()
    a, b = matcher.index(view_ms, view_skel), matcher.index(ms, skel)
    rng = np.random.default_rng(3)
    chance = [(np.exp(1j * rng.uniform(-np.pi, np.pi)),
               complex(rng.uniform(50, 450), -rng.uniform(50, 450)), 100.0) for _ in range(20)]
    near = (*_coarse_miss(truth_in_region, 0.08, complex(-3.0, 2.5)), 1.0)
    found = _finer_proposals(a, b, matcher.params, chance + [near], 0.1, 3.0, 3)
    assert len(found) == 3
    # on the fine level's grid (2 px): the crease ICP takes it from there
    assert _centre_error(found[0][:2], truth_in_region) < 2.5
    assert all(_centre_error(f[:2], truth_in_region) > 10.0 for f in found[1:])


def test_a_registration_the_creases_place_takes_their_covariance(region):
    """A long strip (a track mosaic's shape) whose minutiae sit 2.5 px off their creases
    (albedo moves them on real imagery) while its creases are exact: the transform is the
    creases' fit, and so is its doubt. At the strip's far end the few pairings' residuals
    would claim 5-20 x the error; the creases' covariance holds the error within 3 sigma
    (with the pixel quantisation the fix adds)."""
    ms, skel = region
    x0, y0, w, h = 120, 200, 240, 48
    bx, by = 60, 150
    block = crop_set(ms, bx, by, 360, 150), skel[by:by + 150, bx:bx + 360]
    far = (w - 1.0, 0.5 * (h - 1))
    truth = np.array([far[0] + x0 - bx, far[1] + y0 - by])
    lever = np.array([[far[0], far[1], 1.0, 0.0], [far[1], -far[0], 0.0, 1.0]])
    matcher = Matcher()
    for seed in range(4):
        view_ms, _ = transform_set(crop_set(ms, x0, y0, w, h), np.eye(3)[:2], (h, w),
                                   rng=seed, pos_sigma=2.5, missing=0.3, spurious=0.3)
        a, b = matcher.index(view_ms, skel[y0:y0 + h, x0:x0 + w]), matcher.index(*block)
        r = matcher.compare(a, b)
        assert r.decision == Decision.MATCH, r.reason
        error = float(np.hypot(*(np.array(r.apply(*far)) - truth)))
        sigma = math.sqrt(np.trace(r.point_covariance(*far)))
        c = complex(r.transform[0, 0], r.transform[0, 1])
        t = complex(r.transform[0, 2], -r.transform[1, 2])
        pairing_cov, _ = _covariance(a.z[r.pairings[:, 0]], b.z[r.pairings[:, 1]], c, t,
                                     True, matcher.params.pos_tol)
        pairing_sigma = math.sqrt(np.trace(lever @ pairing_cov @ lever.T))
        assert error < 1.5 and pairing_sigma > 3 * sigma, (seed, error, sigma, pairing_sigma)
        assert error <= 3.0 * math.sqrt(sigma ** 2 + 2.0 / 12.0), (seed, error, sigma)


def test_a_view_s_fix_does_not_lean_on_its_prior(region):
    """Where a prior puts a view (its ground raster's placement and the camera under it)
    moves its fix not at all: the view search covers every translation in the region, and
    the fix is the registration of the prior's nadir pixel. Priors 0, 37 and 95 m off (a
    fraction of a cell and a few cells) give one fix, the true one; a search seeded or
    weighted at the prior would follow it."""
    ms, skel = region
    gsd, size = 30.0, 192
    land_geo = GeoReference(0.0, 512 * gsd, gsd, 512, 512)
    view, back = _scaled_view(skel, 150, 160, size, 140.0, 1.0)
    matcher = Matcher()
    region_index = matcher.index(ms, skel).prepare_as_reference(search=True)
    centre = 0.5 * (size - 1)
    truth = np.array(land_geo.pixel_to_enu(*(back @ np.array([centre, centre, 1.0]))))
    rng = np.random.default_rng(5)
    n = 40
    albedo = MinutiaSet(rng.uniform(0, size - 1, n), rng.uniform(0, size - 1, n),
                        rng.uniform(-np.pi, np.pi, n), rng.choice([1, 3], n).astype(np.uint8),
                        np.ones(n, np.float32))
    fixes = []
    for prior_error in ((0.0, 0.0), (37.0, 0.0), (-60.0, 73.0)):
        prior = np.array([*(truth + prior_error), 1000.0])
        cam_geo = GeoReference.centred(prior[0], prior[1], gsd, size, size)
        placed = MinutiaSet(albedo.col, albedo.row, albedo.angle, albedo.kind,
                            albedo.quality, georef=cam_geo)
        r = matcher.localise(matcher.index(placed, view), region_index)
        assert r.decision == Decision.MATCH, r.reason
        fix = fix_from_ground_match(r, cam_geo, land_geo, prior, np.eye(3), 0.0,
                                    height_from_scale=False)
        fixes.append(fix.position[:2])
    fixes = np.array(fixes)
    np.testing.assert_allclose(fixes, fixes[0][None].repeat(3, 0), atol=1e-6)
    assert np.hypot(*(fixes[0] - truth)) < 1.5 * gsd, (fixes[0], truth)
