"""Crease-skeleton verification of registrations (core.crease_check) and its use by the matcher."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from skimage.morphology import skeletonize
from synthetic_minutiae import crop_set

from terrain_nav_ros.core.matching.crease_check import (
    CreaseEvidence,
    CreaseField,
    CreaseSamples,
    conditioned_on,
    crease_directions,
    crease_evidence,
    refine_on_creases,
)
from terrain_nav_ros.core.matching.matcher import Decision, Matcher


def test_directions_follow_a_straight_crease():
    img = np.zeros((64, 64), np.uint8)
    # 30 degrees above East in the math frame: rows decrease as columns increase
    c0, r0 = 10, 50
    c1, r1 = c0 + int(round(40 * math.cos(math.radians(30)))), r0 - int(round(40 * math.sin(
        math.radians(30))))
    cv2.line(img, (c0, r0), (c1, r1), 1, 1)
    rows, cols = np.nonzero(img)
    mid = (cols > c0 + 5) & (cols < c1 - 5)
    got = np.degrees(crease_directions(img != 0)[rows[mid], cols[mid]])
    assert np.all(np.abs(got - 30.0) < 4.0)


def test_evidence_is_high_at_the_true_transform_only(region, other_region):
    skel = region[1]
    big = skel[100:356, 100:356]
    small = skel[150:278, 160:288]            # (col, row) -> (col + 60, row + 50) in big
    field = CreaseField(big)
    samples = CreaseSamples.from_image(small)
    t_true = 60 - 50j                         # math frame: z = col - 1j * row
    right = crease_evidence(samples, field, 1 + 0j, t_true)
    assert right.fraction > 0.9 and right.score > 20
    wrong = crease_evidence(samples, field, 1 + 0j, t_true + (15 + 15j))
    assert wrong.score < 2
    unrelated = crease_evidence(CreaseSamples.from_image(other_region[1][150:278, 160:288]),
                                field, 1 + 0j, t_true)
    assert unrelated.score < 2


def test_evidence_under_rotation(region):
    skel = region[1]
    block = skel[150:278, 160:288]
    turned = np.rot90(block)                  # 90 deg CCW: z_block = -1j * z_turned + 127
    field = CreaseField(block)
    r = crease_evidence(CreaseSamples.from_image(turned), field, -1j, 127 + 0j)
    assert r.fraction > 0.9 and r.score > 20
    # the same points with the directions not turned would miss: the directions are checked
    wrong_turn = crease_evidence(CreaseSamples.from_image(turned), field, 1j, 0j)
    assert wrong_turn.score < 2


def test_excluded_surroundings_do_not_count(region):
    block = region[1][150:278, 160:288]
    samples = CreaseSamples.from_image(block)
    field = CreaseField(block)
    full = crease_evidence(samples, field, 1 + 0j, 0j)
    around_first = samples.around(samples.z[:1], 1.5)[0]
    assert 0 in around_first and np.all(np.abs(samples.z[around_first] - samples.z[0]) < 1.5)
    everything = crease_evidence(samples, field, 1 + 0j, 0j,
                                 skip=np.concatenate(samples.around(samples.z, 1.0)))
    assert full.n_inside == len(samples) and everything.n_inside == 0
    assert everything.score == 0.0


def test_empty_and_bad_crease_images():
    empty = np.zeros((32, 32), bool)
    r = crease_evidence(CreaseSamples.from_image(empty), CreaseField(empty), 1 + 0j, 0j)
    assert r.score == 0.0 and r.n_inside == 0
    with pytest.raises(ValueError, match="2-D"):
        CreaseField(np.zeros((4, 4, 3)))


def test_crease_check_separates_small_blocks(region, other_region):
    """A 96 px block with few minutiae: the creases add the evidence the minutiae lack, and
    an unrelated block gains nothing."""
    ms, skel = region
    x0, y0, size, dx, dy = 200, 180, 96, 7, -5
    a = crop_set(ms, x0, y0, size, size)
    b = crop_set(ms, x0 + dx, y0 + dy, size, size)
    crease_a = skel[y0:y0 + size, x0:x0 + size]
    crease_b = skel[y0 + dy:y0 + dy + size, x0 + dx:x0 + dx + size]
    without = Matcher(crease_check=False, crease_descriptor=False).compare(a, b)
    matcher = Matcher()
    with_creases = matcher.compare(matcher.index(a, crease_a), matcher.index(b, crease_b))
    assert with_creases.decision == Decision.MATCH
    assert with_creases.creases is not None and with_creases.creases.fraction > 0.8
    assert with_creases.score > without.score + 10
    col, row = with_creases.apply(10.0, 20.0)
    assert abs(col - (10 - dx)) < 1.0 and abs(row - (20 - dy)) < 1.0
    oms, oskel = other_region
    u = crop_set(oms, x0, y0, size, size)
    unrelated = matcher.compare(matcher.index(u, oskel[y0:y0 + size, x0:x0 + size]),
                                matcher.index(b, crease_b))
    assert unrelated.decision != Decision.MATCH


def test_creases_decide_where_the_minutiae_alone_cannot(region):
    """13 minutiae cannot reach a high threshold even if they all pair ("no decision"); the
    crease check is not refused on that ground, and its evidence carries the match."""
    ms, skel = region
    x0, y0, size, dx, dy = 200, 180, 64, 7, -5
    a = crop_set(ms, x0, y0, size, size)
    b = crop_set(ms, x0 + dx, y0 + dy, size, size)
    minutiae_only = Matcher(crease_check=False, crease_descriptor=False, threshold=25.0)
    assert minutiae_only.compare(a, b).decision == Decision.NO_DECISION
    matcher = Matcher(threshold=25.0)
    r = matcher.compare(matcher.index(a, skel[y0:y0 + size, x0:x0 + size]),
                        matcher.index(b, skel[y0 + dy:y0 + dy + size, x0 + dx:x0 + dx + size]))
    assert r.decision == Decision.MATCH, r.reason


def test_refinement_brings_the_creases_together(region):
    skel = region[1]
    big = skel[100:356, 100:356]
    small = skel[150:278, 160:288]            # true transform: c = 1, t = 60 - 50j
    samples, field = CreaseSamples.from_image(small), CreaseField(big)
    c0 = np.exp(1j * np.radians(1.0))          # 1 degree and ~2 px off
    t0 = 60 - 50j + (1.5 - 1.2j)
    c, t = refine_on_creases(samples, field, c0, t0)
    centre = 64 - 64j                          # the small block's centre, math frame
    before = abs(c0 * centre + t0 - (centre + 60 - 50j))
    after = abs(c * centre + t - (centre + 60 - 50j))
    assert before > 1.5 and after < 0.3
    assert abs(np.degrees(np.angle(c))) < 0.3
    assert crease_evidence(samples, field, c, t).fraction > 0.9
    # nothing to pair (empty reference): the transform is returned unchanged
    empty = CreaseField(np.zeros_like(big))
    assert refine_on_creases(samples, empty, c0, t0) == (c0, t0)


def test_refinement_with_scale_recovers_a_scaled_view(region):
    """A view 6 % larger, started at scale 1 and 1 degree off: the ICP with the scale brings
    it onto the creases and recovers the scale; without it, the view stays off at its
    edges; with bounds that exclude the truth, the scale stops at the bound."""
    skel = region[1]
    big = skel[100:356, 100:356]
    small = skel[130:290, 140:300].astype(np.float32)
    m = cv2.getRotationMatrix2D((79.5, 79.5), 0.0, 1.06)     # block px -> view px
    view = skeletonize(cv2.warpAffine(small, m, (160, 160)) > 0.3)
    samples, field = CreaseSamples.from_image(view), CreaseField(big)
    # truth: view -> block (1 / 1.06 about the centre), block -> big (+40, +30 px)
    c_true = 1 / 1.06
    t_true = complex(79.5, -79.5) * (1 - c_true) + (40 - 30j)
    c0, t0 = np.exp(1j * np.radians(1.0)), t_true + (1.0 - 1.0j)
    corner = 0j                                             # the view's corner: far out
    for scale in [(0.9, 1.1), None, (0.97, 1.03)]:
        c, t = refine_on_creases(samples, field, c0, t0, scale=scale)
        err = abs(c * corner + t - (c_true * corner + t_true))
        if scale is None:
            assert abs(c) == pytest.approx(1.0) and err > 3.0
        elif scale[0] < c_true:
            assert abs(abs(c) - c_true) < 0.01 and err < 1.0
        else:   # the truth is outside the bounds: the scale stops at the bound
            assert abs(c) == pytest.approx(0.97)


def test_ridges_fix_the_shift_that_parallel_valleys_leave_free():
    """Valleys that all run East-West cannot say where along them the block lies (the ICP
    solve is singular and leaves the transform alone); ridges running North-South beside
    them fix it."""
    valleys = np.zeros((128, 128), np.uint8)
    ridges = np.zeros((128, 128), np.uint8)
    for k in range(12, 128, 20):
        cv2.line(valleys, (0, k), (127, k), 1, 1)
        cv2.line(ridges, (k + 3, 0), (k + 3 + k // 10, 127), 1, 1)   # not quite parallel
    window = (slice(30, 94), slice(30, 94))   # block px (col, row) -> (col + 30, row + 30)
    samples, field = CreaseSamples.from_image(valleys[window]), CreaseField(valleys)
    ridge_channel = (CreaseSamples.from_image(ridges[window]), CreaseField(ridges))
    t_true = 30 - 30j
    start = t_true + (2.0 - 1.5j)
    c, t = refine_on_creases(samples, field, 1 + 0j, start)
    assert abs(t - t_true) > 2.0
    c, t = refine_on_creases(samples, field, 1 + 0j, start, ridges=ridge_channel)
    assert abs(t - t_true) < 0.2 and abs(np.angle(c)) < 0.01


def test_ridges_count_given_the_valleys():
    """Ridge evidence whose hit fraction rose and fell with the valleys' over the shifted
    transforms adds only what the valleys do not already say; evidence that varied apart
    keeps its score; valleys at or below chance lend nothing."""
    k = np.arange(24)
    swing = 0.1 + 0.04 * np.cos(2 * np.pi * k / 12)
    valleys = CreaseEvidence(10.0, 0.4, 0.1, 300, swing)
    following = CreaseEvidence(8.0, 0.4, 0.1, 250, swing + 0.005 * np.sin(2 * np.pi * k / 5))
    apart = CreaseEvidence(8.0, 0.4, 0.1, 250, 0.1 + 0.04 * np.sin(2 * np.pi * k / 12))
    given = conditioned_on(following, valleys)
    assert given.dependence > 0.8 and given.score < 1.0
    assert conditioned_on(apart, valleys) == apart
    assert conditioned_on(following, CreaseEvidence(0.0, 0.1, 0.1, 300, swing)) == following
    assert conditioned_on(following, None) == following
    # fewer than 8 shifts seen by both: no dependence can be measured
    sparse = np.where(k < 6, swing, np.nan)
    assert conditioned_on(replace(following, null_fractions=sparse), valleys) == following


def test_ridges_midway_between_parallel_valleys_add_little(region):
    """Valleys all running East-West with ridges midway: wherever the valleys align the
    ridges do too, so given the valleys the ridges' agreement adds little; an unrelated
    ridge pattern beside the same valleys keeps most of its own."""
    valleys = np.zeros((160, 160), np.uint8)
    ridges = np.zeros((160, 160), np.uint8)
    for row in range(12, 160, 20):
        cv2.line(valleys, (0, row), (159, row), 1, 1)
        cv2.line(ridges, (0, row + 10), (159, row + 10), 1, 1)
    window = (slice(40, 104), slice(30, 94))   # view px (col, row) -> (col + 30, row + 40)
    t_true = 30 - 40j

    def agreement(skeleton):
        return crease_evidence(CreaseSamples.from_image(skeleton[window]),
                               CreaseField(skeleton), 1 + 0j, t_true)

    v, r = agreement(valleys), agreement(ridges)
    assert v.score > 20 and r.score > 20
    given = conditioned_on(r, v)
    assert given.dependence > 0.8 and given.score < 0.5 * r.score
    unrelated = agreement(region[1][:160, :160])
    assert unrelated.score > 10
    assert conditioned_on(unrelated, v).score > 0.75 * unrelated.score


def test_with_creases_a_few_minutiae_are_enough_to_decide(region):
    ms, skel = region
    x0, y0, size, dx, dy = 200, 180, 64, 7, -5
    a = crop_set(ms, x0, y0, size, size)
    a = a.subset(np.arange(6))                # 6 minutiae: below min_minutiae (10)
    b = crop_set(ms, x0 + dx, y0 + dy, size, size)
    r = Matcher().compare(a, b)
    assert r.decision == Decision.NO_DECISION and "too few minutiae" in r.reason
    matcher = Matcher()
    r = matcher.compare(matcher.index(a, skel[y0:y0 + size, x0:x0 + size]),
                        matcher.index(b, skel[y0 + dy:y0 + dy + size, x0 + dx:x0 + dx + size]))
    assert r.decision == Decision.MATCH, r.reason
    col, row = r.apply(10.0, 20.0)
    assert abs(col - (10 - dx)) < 1.0 and abs(row - (20 - dy)) < 1.0
    # below min_minutiae_creases: without the crease search (core.crease_search) that is
    # "no decision"; with it the creases propose the transform too
    no_search = Matcher(crease_search_below=0)
    tiny = no_search.compare(no_search.index(a.subset(np.arange(3)),
                                             skel[y0:y0 + size, x0:x0 + size]),
                             no_search.index(b, skel[y0 + dy:y0 + dy + size,
                                                     x0 + dx:x0 + dx + size]))
    assert tiny.decision == Decision.NO_DECISION
    assert "at least 4" in tiny.reason
    tiny = matcher.compare(matcher.index(a.subset(np.arange(3)),
                                         skel[y0:y0 + size, x0:x0 + size]),
                           matcher.index(b, skel[y0 + dy:y0 + dy + size,
                                                 x0 + dx:x0 + dx + size]))
    assert tiny.decision == Decision.MATCH, tiny.reason


def test_field_nearest_crease_pixel_agrees_with_an_exact_transform(region):
    from scipy import ndimage

    skel = region[1][:200, :300]
    field = CreaseField(skel)
    exact, (ri, ci) = ndimage.distance_transform_edt(~skel, return_indices=True)
    near = exact <= 1.5
    assert np.array_equal(field.distance <= 1.5, near)   # the hit radius sees the same pixels
    assert np.all(np.abs(field.distance - exact) <= 0.03 * exact + 1e-6)
    # the nearest crease pixel it names is a crease pixel at the exact nearest distance
    z = field.crease_z[field.label]
    rows, cols = -z.imag, z.real
    assert skel[rows.astype(int), cols.astype(int)].all()
    named = np.hypot(rows - np.arange(200)[:, None], cols - np.arange(300)[None, :])
    assert np.all(named <= exact + 0.05 * exact + 1e-6)


def test_numba_kernels_agree_with_the_numpy_path(region, other_region, monkeypatch):
    """The fused crease kernels count the same hits and move the transform as the numpy
    path does (the ICP's sums run in another order: equal to rounding)."""
    from terrain_nav_ros.core.matching import _matching_kernels

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    skel = region[1]
    samples = CreaseSamples.from_image(skel[150:278, 160:288])
    field = CreaseField(skel[100:356, 100:356])
    skip = np.concatenate(samples.around(samples.z[::40], 4.0))
    ridges = (CreaseSamples.from_image(other_region[1][150:278, 160:288]),
              CreaseField(other_region[1][100:356, 100:356]))
    starts = [(1 + 0j, 60 - 50j), (np.exp(0.02j), 61.5 - 48.8j), (np.exp(2j), 10 - 200j),
              (-1j, 300 + 30j)]                 # true, near, unrelated, mostly outside

    def run():
        out = []
        for c, t in starts:
            out.append((crease_evidence(samples, field, c, t),
                        crease_evidence(samples, field, c, t, skip=skip),
                        refine_on_creases(samples, field, c, t),
                        refine_on_creases(samples, field, c, t, ridges=ridges),
                        refine_on_creases(samples, field, c, t, ridges=ridges, scale=(0.9, 1.1)),
                        field.correspondences(c * samples.z + t, samples.direction, 1.5,
                                              0.35)))
        return out

    fast = run()
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow = run()
    for f, s in zip(fast, slow, strict=True):
        assert f[0] == s[0] and f[1] == s[1]
        for k in (0, 1):   # the local null shift by shift, which the ridges are conditioned on
            np.testing.assert_array_equal(f[k].null_fractions, s[k].null_fractions)
        for k in (2, 3, 4):
            assert abs(f[k][0] - s[k][0]) < 1e-12 and abs(f[k][1] - s[k][1]) < 1e-9
        for got, want in zip(f[5], s[5], strict=True):
            np.testing.assert_array_equal(got, want)
    assert fast[0][0].score > 20 and fast[1][2] != starts[1]   # the cases do something
    assert fast[1][3] != fast[1][2]                              # and the ridges pull too


def test_samples_around_points_from_the_grid_are_the_k_d_trees(region, monkeypatch):
    """The numba grid lists the same samples strictly within the radius of each point as
    the k-d tree, at pixel places and between them, at and beside the radius."""
    from terrain_nav_ros.core.matching import _matching_kernels

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    samples = CreaseSamples.from_image(region[1][150:278, 160:288])
    points = np.concatenate([samples.z[::7], samples.z[::11] + (0.5 - 0.37j),
                             np.array([-20 + 20j, 64.25 - 64.75j])])
    for radius in (6.0, 3.0, 2.5):
        start, flat = samples.around_lists(points, radius)
        monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
        want_start, want_flat = samples.around_lists(points, radius)
        monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", True)
        np.testing.assert_array_equal(start, want_start)
        for k in range(len(points)):
            assert (sorted(flat[start[k]:start[k + 1]])
                    == sorted(want_flat[want_start[k]:want_start[k + 1]]))
    assert start[-1] > len(points)   # the lists are not empty


def test_the_kernels_axial_remainder_is_numpys_bit_for_bit():
    """The crease look-ups' remainder by pi, branches instead of fmod, rounds as np.mod
    does: at random direction differences, at the branch edges and beyond them."""
    from terrain_nav_ros.core.matching import _matching_kernels

    x = np.random.default_rng(0).uniform(-2.5 * np.pi, 3.5 * np.pi, 200_000)
    edges = np.array([k * np.pi for k in (-3, -2, -1, 0, 1, 2, 3)] + [-0.0, 1e-300, -1e-300])
    x = np.concatenate([x, edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf)])
    got = np.array([_matching_kernels._mod_pi(v) for v in x])
    np.testing.assert_array_equal(got, np.mod(x, np.pi))


def test_coarse_to_fine_icp_pulls_in_what_the_fine_one_cannot(region):
    """A registration 5 degrees and ~13 px off (a few wrong minutiae pairings) is beyond
    the 3 px ICP; the matcher's wider try (``MatchParams.crease_rescue_radii``) brings it
    onto the creases."""
    from terrain_nav_ros.core.matching.params import MatchParams

    skel = region[1]
    samples = CreaseSamples.from_image(skel[150:278, 160:288])
    field = CreaseField(skel[100:356, 100:356])   # truth: c = 1, t = 60 - 50j
    centre = 64 - 64j
    for degrees, off in [(5.0, 7 - 6j), (-5.0, -8 + 3j), (3.0, 9 + 0j)]:
        c0, t0 = np.exp(1j * np.radians(degrees)), 60 - 50j + off
        c, t = refine_on_creases(samples, field, c0, t0)
        assert abs(c * centre + t - (centre + 60 - 50j)) > 5.0
        c, t = c0, t0
        for radius in MatchParams().crease_rescue_radii:
            c, t = refine_on_creases(samples, field, c, t, radius=radius)
        assert abs(c * centre + t - (centre + 60 - 50j)) < 0.1


def test_ridge_check_adds_the_ridges_agreement(region, other_region):
    """A 96 px block with ridge skeletons: the ridges' agreement at the registration adds
    to the score where they are the same place's, and nothing where they are not."""
    ms, skel = region
    ridges = other_region[1]       # any other line pattern serves as the ridges here
    x0, y0, size, dx, dy = 200, 180, 96, 7, -5

    def window(image, x, y):
        return image[y:y + size, x:x + size]

    a = crop_set(ms, x0, y0, size, size)
    b = crop_set(ms, x0 + dx, y0 + dy, size, size)
    matcher = Matcher()
    b_index = matcher.index(b, window(skel, x0 + dx, y0 + dy), window(ridges, x0 + dx, y0 + dy))
    valleys = matcher.compare(matcher.index(a, window(skel, x0, y0)), b_index)
    same = matcher.compare(matcher.index(a, window(skel, x0, y0), window(ridges, x0, y0)),
                           b_index)
    assert valleys.ridges is None
    assert same.ridges is not None and same.ridges.fraction > 0.8
    assert same.score == pytest.approx(valleys.score + same.ridges.score)
    assert same.ridges.score > 10
    elsewhere = matcher.compare(
        matcher.index(a, window(skel, x0, y0), window(ridges, x0 + 150, y0 + 120)), b_index)
    assert elsewhere.ridges.score < 2
    assert elsewhere.score < valleys.score + 2
    def compared(m: Matcher):
        return m.compare(m.index(a, window(skel, x0, y0), window(ridges, x0, y0)),
                         m.index(b, window(skel, x0 + dx, y0 + dy),
                                 window(ridges, x0 + dx, y0 + dy)))

    off = compared(Matcher(ridge_check=False))
    assert off.ridges is None and off.score == pytest.approx(valleys.score)
    # a set too large for the ridges at every registration (real images' albedo edges add
    # minutiae): the registration chosen on the valleys gets its ridge agreement added
    large = compared(Matcher(ridge_check_below=0))
    np.testing.assert_allclose(large.transform, valleys.transform)
    assert large.ridges is not None and large.ridges.fraction > 0.8
    assert large.score == pytest.approx(valleys.score + large.ridges.score)


def test_ridges_that_disagree_neither_pull_far_nor_lower_the_score(region, other_region):
    """B's ridges ~3.6 px off from A's (a ridge line read aside under another sun): the
    registration may give a little towards them, but stays on the valleys within 2 px, and
    the comparison scores at least what the valleys alone give (the valleys' own ICP is
    among the candidates, and the wider try is decided without the ridges' evidence)."""
    ms, skel = region
    ridges = other_region[1]
    x0, y0, size, dx, dy = 200, 180, 96, 7, -5

    def window(image, x, y):
        return image[y:y + size, x:x + size]

    a = crop_set(ms, x0, y0, size, size)
    b = crop_set(ms, x0 + dx, y0 + dy, size, size)
    results = []
    for check in (True, False):
        matcher = Matcher(ridge_check=check)
        results.append(matcher.compare(
            matcher.index(a, window(skel, x0, y0), window(ridges, x0, y0)),
            matcher.index(b, window(skel, x0 + dx, y0 + dy),
                          window(ridges, x0 + dx + 3, y0 + dy + 2))))
    with_ridges, valleys = results
    col, row = with_ridges.apply(48.0, 48.0)
    assert math.hypot(col - (48 - dx), row - (48 - dy)) < 2.0
    assert with_ridges.score >= valleys.score
    assert with_ridges.creases.fraction > 0.9


def test_a_runner_up_whose_ridges_agree_is_chosen_over_a_leader_whose_do_not(region,
                                                                             other_region):
    """The choice among the registrations scored weighs the ridges of the leader and its
    runners-up: the right registration, trailing on the valleys and minutiae (as albedo
    edges make it on real images), leads once its ridges count; the leader's ridges add
    nothing."""
    from dataclasses import replace

    from terrain_nav_ros.core.matching.matcher import _with_ridges_chosen
    from terrain_nav_ros.core.matching.registration import _pair
    from terrain_nav_ros.core.matching.scoring import _scored

    ms, skel = region
    ridges = other_region[1]
    x0, y0, size, dx, dy = 200, 180, 96, 7, -5
    big = 2 * size

    def window(image, x, y, side=size):
        return image[y:y + side, x:x + side]

    matcher = Matcher(ridge_check_below=16)   # the ridges score only the chosen one
    p = matcher.params
    a = matcher.index(crop_set(ms, x0, y0, size, size), window(skel, x0, y0),
                      window(ridges, x0, y0))
    bx, by = x0 - dx - 40, y0 - dy - 40
    b = matcher.index(crop_set(ms, bx, by, big, big), window(skel, bx, by, big),
                      window(ridges, bx, by, big))
    assert min(a.n, b.n) >= p.ridge_check_below
    t_true = complex(x0 - bx, -(y0 - by))          # math frame: z = col - 1j * row
    right = _scored(a, b, 1 + 0j, t_true, _pair(a, b, 1 + 0j, t_true, p), b.area, a.radius,
                    p, True)
    t_wrong = t_true + (23 - 31j)
    wrong = _scored(a, b, 1 + 0j, t_wrong, _pair(a, b, 1 + 0j, t_wrong, p), b.area,
                    a.radius, p, True)
    leader = replace(wrong, score=right.score + 5.0)   # ahead on the other evidence
    chosen = _with_ridges_chosen(a, b, leader, [leader, right], b.area, p)
    assert abs(chosen.t - t_true) < 1.5 and chosen.ridges.score > 10
    assert chosen.score >= right.score + chosen.ridges.score - 1e-9
    alone = _with_ridges_chosen(a, b, leader, [leader], b.area, p)   # no runner-up to weigh
    assert alone.t == t_wrong and alone.ridges.score < 2
