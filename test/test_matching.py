"""Behaviour of the minutiae descriptors and matcher on synthetic drainage-like sets."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic_minutiae import (
    crop_set,
    rigid_transform,
    terrain_minutiae,
    transform_set,
)

from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.matching.descriptors import (
    EdgeHash,
    crease_descriptor,
    cylinder_code,
    neighbour_edges,
    shape_context,
    wrap_angle,
)
from terrain_nav_ros.core.matching.matcher import Decision, Matcher, compare, localise
from terrain_nav_ros.core.matching.significance import calibrate_threshold
from terrain_nav_ros.core.terrain.georef import GeoReference

BLOCK = 256


@pytest.fixture(scope="module")
def block(region):
    return crop_set(region[0], 128, 128, BLOCK, BLOCK)


def _corner_error(result, m_true, w, h):
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [w / 2, h / 2]], float)
    col, row = result.apply(corners[:, 0], corners[:, 1])
    ref = corners @ m_true[:, :2].T + m_true[:, 2]
    return float(np.max(np.hypot(col - ref[:, 0], row - ref[:, 1])))


def _rotated_copy(ms, degrees, seed, **noise):
    m = rigid_transform(np.radians(degrees), 7.0, -4.0, centre=(BLOCK / 2, BLOCK / 2))
    out, src = transform_set(ms, m, (BLOCK, BLOCK), rng=seed, **noise)
    return out, src, m


def test_synthetic_block_is_realistic(block):
    # the blocks hold about 150 minutiae of both kinds
    assert 100 <= len(block) <= 220
    assert set(np.unique(block.kind)) == {1, 3}


@pytest.mark.parametrize("degrees", [0.0, 37.0, 90.0, 180.0, -123.0])
def test_perturbed_copy_matched_with_right_transform(block, degrees):
    b, src, m = _rotated_copy(block, degrees, seed=int(degrees) % 7)
    r = compare(block, b, descriptor="both" if degrees == 90.0 else "shape_context")
    assert r.decision == Decision.MATCH, r.reason
    assert _corner_error(r, m, BLOCK, BLOCK) < 1.0
    assert abs(wrap_angle(r.rotation - np.radians(degrees))) < np.radians(1.0)
    # pairings are one-to-one and mostly the true correspondences
    assert len(np.unique(r.pairings[:, 0])) == len(np.unique(r.pairings[:, 1])) == r.n_pairings
    correct = src[r.pairings[:, 1]] == r.pairings[:, 0]
    assert correct.mean() > 0.9
    assert r.n_pairings > 0.6 * min(r.n_overlap)
    assert np.all(np.isfinite(r.covariance)) and r.rms < 3.0


def test_score_is_rotation_invariant(block):
    # a rotated square crop loses its corners, so compare the paired fraction of the overlap
    for deg in (0.0, 61.0, 150.0, 270.0):
        b, _, m = _rotated_copy(block, deg, seed=3, pos_sigma=0.0, angle_sigma=0.0,
                                missing=0.0, spurious=0.0)
        r = compare(block, b)
        assert r.decision == Decision.MATCH
        assert r.n_pairings >= 0.98 * min(r.n_overlap)
        assert _corner_error(r, m, BLOCK, BLOCK) < 0.05


def test_unrelated_blocks_rejected():
    scores = []
    sets = [crop_set(terrain_minutiae((384, 384), seed=100 + k)[0], 64, 64, BLOCK, BLOCK)
            for k in range(5)]
    matcher = Matcher()
    idx = [matcher.index(s) for s in sets]
    for i in range(len(idx)):
        for j in range(i + 1, len(idx)):
            r = matcher.compare(idx[i], idx[j])
            assert r.decision == Decision.NO_MATCH, (i, j, r.score, r.n_pairings)
            scores.append(r.score)
    assert max(scores) < matcher.params.threshold


def test_localise_rotated_crop_in_region(region):
    ms = region[0]
    # camera: a 128x128 view of the region rotated by 25 degrees, centred at (300, 210)
    theta = np.radians(25.0)
    centre_cam = np.array([64.0, 64.0])
    target = np.array([300.0, 210.0])
    # camera -> region transform, and its inverse applied to the region minutiae
    c, s = np.cos(theta), np.sin(theta)
    cam_to_reg = np.column_stack([[[c, s], [-s, c]], target - np.array([[c, s], [-s, c]])
                                  @ centre_cam])
    inv = np.linalg.inv(np.vstack([cam_to_reg, [0, 0, 1]]))[:2]
    cam, _ = transform_set(ms, inv, (128, 128), rng=5)
    assert len(cam) >= 15
    r = localise(cam, ms)
    assert r.decision == Decision.MATCH, r.reason
    col, row = r.apply(64.0, 64.0)
    assert np.hypot(col - target[0], row - target[1]) < 1.0
    assert _corner_error(r, cam_to_reg, 128, 128) < 1.5
    cov = r.point_covariance(64.0, 64.0)
    assert np.all(np.linalg.eigvalsh(cov) > 0) and np.trace(cov) < 1.0


def test_localise_rejects_a_view_from_elsewhere(region):
    other = terrain_minutiae((256, 256), seed=999)[0]
    cam = crop_set(other, 64, 64, 128, 128)
    r = localise(cam, region[0])
    assert r.decision != Decision.MATCH


def test_too_few_minutiae_is_no_decision(block):
    few = block.subset(np.arange(6))
    r = compare(few, block)
    assert r.decision == Decision.NO_DECISION and "too few" in r.reason
    assert compare(MinutiaSet.empty("flat"), block).decision == Decision.NO_DECISION
    # a camera set the extractor emptied says why, and localise passes that on
    clouded = localise(MinutiaSet.empty("mostly cloud: 90 % of the frame"), block)
    assert clouded.decision == Decision.NO_DECISION
    assert clouded.reason == "no camera minutiae: mostly cloud: 90 % of the frame"


def test_a_set_without_edges_is_no_match_not_a_crash(block):
    """Twelve minutiae within 2 px: enough in number, but every edge is shorter than
    ``edge_min``, so the edge hash is empty (it raised on reshaping its empty key table,
    first met in a study of the embedded DEM under the raw shading)."""
    rng = np.random.default_rng(0)
    tight = MinutiaSet(100 + rng.uniform(0, 2, 12), 100 + rng.uniform(0, 2, 12),
                       rng.uniform(-3, 3, 12), np.ones(12, np.uint8), np.ones(12, np.float32))
    assert len(Matcher().index(tight).edge_hash()) == 0
    for a, b in ((block, tight), (tight, block), (tight, tight)):
        r = compare(a, b)
        assert r.decision != Decision.MATCH and r.reason
    assert localise(tight, block).decision != Decision.MATCH


def test_too_few_to_ever_reach_threshold_is_no_decision(block):
    # enough minutiae for the floor, but a perfect match could not be significant
    r = compare(block.subset(np.arange(12)), block, threshold=40.0)
    assert r.decision == Decision.NO_DECISION


def test_calibrate_threshold_empirical_and_extrapolated():
    rng = np.random.default_rng(0)
    scores = rng.exponential(1.0, 2000)
    thr = calibrate_threshold(scores, 0.01)
    assert np.mean(scores >= thr) <= 0.01
    assert np.mean(scores >= np.nextafter(thr, -np.inf) - 0.05) > 0.005
    # beyond the sample: extrapolated above the maximum, near the exponential quantile
    thr_rare = calibrate_threshold(scores, 1e-5)
    assert thr_rare > scores.max()
    assert abs(thr_rare - np.log(1e5)) < 2.0
    with pytest.raises(ValueError):
        calibrate_threshold(scores, 0.0)


@pytest.mark.parametrize("describe", [shape_context, cylinder_code])
def test_local_descriptors_rotation_invariant(block, describe):
    b, _, _ = _rotated_copy(block, 90.0, seed=0, pos_sigma=0.0, angle_sigma=0.0,
                            missing=0.0, spurious=0.0)
    # compare descriptors of minutiae far from the border (no neighbours lost)
    inner = np.hypot(block.col - 128, block.row - 128) < 40
    da = describe(block)[inner]
    b_sorted = b.subset(np.lexsort((b.row, b.col)))
    # find each inner minutia's image in b
    m = rigid_transform(np.radians(90.0), 7.0, -4.0, centre=(128, 128))
    col = m[0, 0] * block.col + m[0, 1] * block.row + m[0, 2]
    row = m[1, 0] * block.col + m[1, 1] * block.row + m[1, 2]
    d = np.hypot(b_sorted.col[None] - col[inner, None], b_sorted.row[None] - row[inner, None])
    db = describe(b_sorted)[np.argmin(d, axis=1)]
    assert np.median(np.sum(da * db, axis=1)) > 0.999
    # and they tell minutiae apart: a minutia is most similar to its own image
    sim = da @ describe(b_sorted).T
    assert np.mean(np.argmax(sim, axis=1) == np.argmin(d, axis=1)) > 0.9


def test_crease_descriptor_rotation_invariant(region):
    ms, skel = region
    inner = ms.subset((np.abs(ms.col - 256) < 150) & (np.abs(ms.row - 256) < 150))
    da = crease_descriptor(inner, skel)
    # np.rot90 turns the map 90 degrees CCW: (col, row) -> (row, W-1-col)
    rot = MinutiaSet(inner.row, 511 - inner.col, inner.angle + np.pi / 2, inner.kind,
                     inner.quality)
    db = crease_descriptor(rot, np.rot90(skel))
    assert np.median(np.sum(da * db, axis=1)) > 0.99


@pytest.mark.parametrize("subdivision", [1, 2])
def test_edge_hash_equals_brute_force(block, subdivision):
    e = neighbour_edges(block, k=8)
    h = EdgeHash(e, 4.0, np.radians(25), subdivision=subdivision)
    rows, cols = np.nonzero(e.valid)
    rng = np.random.default_rng(1)
    ql = e.length[rows, cols] + rng.normal(0, 2, len(rows))
    qb1 = e.beta_i[rows, cols] + rng.normal(0, 0.2, len(rows))
    qb2 = e.beta_j[rows, cols] + rng.normal(0, 0.2, len(rows))
    q, r2, c2 = h.query(ql, np.mod(qb1, 2 * np.pi), np.mod(qb2, 2 * np.pi), 4.0,
                        np.radians(25))
    got = set(zip(q.tolist(), (r2 * e.k + c2).tolist(), strict=True))
    ok = ((np.abs(ql[:, None] - e.length[rows, cols][None]) <= 4.0)
          & (np.abs(wrap_angle(qb1[:, None] - e.beta_i[rows, cols][None])) <= np.radians(25))
          & (np.abs(wrap_angle(qb2[:, None] - e.beta_j[rows, cols][None])) <= np.radians(25)))
    qi, si = np.nonzero(ok)
    want = set(zip(qi.tolist(), (rows[si] * e.k + cols[si]).tolist(), strict=True))
    assert got == want


def test_georeferenced_sets_keep_their_footprint(block):
    geo = GeoReference(1000.0, 2000.0, 2.5, BLOCK, BLOCK)
    a = MinutiaSet(block.col, block.row, block.angle, block.kind, block.quality, georef=geo)
    r = compare(a, a)
    assert r.decision == Decision.MATCH
    assert r.n_pairings == len(a)
    assert np.allclose(r.transform, [[1, 0, 0], [0, 1, 0]], atol=1e-6)


def test_localise_with_descriptor_roots(region):
    # the generator used for large landmark regions: descriptor-nearest root pairs
    ms = region[0]
    theta, size, target = np.radians(-70.0), 256, np.array([250.0, 260.0])
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, s], [-s, c]])
    cam_to_reg = np.column_stack([rot, target - rot @ np.array([size / 2, size / 2])])
    inv = np.linalg.inv(np.vstack([cam_to_reg, [0, 0, 1]]))[:2]
    cam, _ = transform_set(ms, inv, (size, size), rng=8)
    r = Matcher(candidates="roots").localise(cam, ms)
    assert r.decision == Decision.MATCH, r.reason
    assert _corner_error(r, cam_to_reg, size, size) < 1.0


def test_crease_descriptor_in_matching(region, block):
    ms, skel = region
    crease_block = skel[128:128 + BLOCK, 128:128 + BLOCK]
    m = rigid_transform(np.radians(90.0), 0.0, 0.0, centre=((BLOCK - 1) / 2, (BLOCK - 1) / 2))
    b, _ = transform_set(block, m, (BLOCK, BLOCK), rng=2)
    crease_b = np.rot90(crease_block)   # the same 90-degree CCW turn as m
    matcher = Matcher()
    r = matcher.compare(matcher.index(block, crease_block), matcher.index(b, crease_b))
    assert r.decision == Decision.MATCH
    assert _corner_error(r, m, BLOCK, BLOCK) < 1.0


def test_index_must_match_the_matcher_settings(block):
    idx = Matcher().index(block)
    with pytest.raises(ValueError, match="other settings"):
        Matcher(k_ref=14).compare(idx, idx)
    assert Matcher(threshold=5.0).compare(idx, idx).decision == Decision.MATCH


def test_fit_similarity_exact_and_degenerate():
    from terrain_nav_ros.core.matching.registration import fit_similarity

    rng = np.random.default_rng(0)
    za = rng.normal(size=20) + 1j * rng.normal(size=20)
    c_true, t_true = 1.1 * np.exp(0.7j), 3 - 2j
    c, t = fit_similarity(za, c_true * za + t_true, scale=True)
    assert abs(c - c_true) < 1e-12 and abs(t - t_true) < 1e-12
    c, _ = fit_similarity(za, c_true * za + t_true)
    assert abs(c - np.exp(0.7j)) < 1e-12
    # two A points on one B point (Hough correspondences are not one-to-one): no rotation
    c, _ = fit_similarity(za[:2], np.array([5 + 5j, 5 + 5j]))
    assert np.isnan(c)


def test_significance_null_is_the_compound_poisson_tail():
    from terrain_nav_ros.core.matching.significance import compound_log10_sf

    # chance pairings: Poisson(lam) of them, each adding -ln(u) - ln(v), u, v uniform
    rng = np.random.default_rng(0)
    lam, n = 3.0, 100000
    k = rng.poisson(lam, n)
    owner = np.repeat(np.arange(n), k)
    uv = rng.random((len(owner), 2))
    s = np.bincount(owner, -np.log(uv).sum(axis=1), minlength=n)
    for level in (5.0, 10.0, 20.0):
        assert abs(compound_log10_sf(level, lam) - np.log10(np.mean(s >= level))) < 0.05
    assert compound_log10_sf(0.0, lam) == 0.0
    # far tail stays finite and monotone
    assert -np.inf < compound_log10_sf(3000.0, lam) < compound_log10_sf(2000.0, lam) < 0


def test_compound_tail_kernel_agrees_with_the_numpy_path(monkeypatch):
    from terrain_nav_ros.core.matching import _matching_kernels
    from terrain_nav_ros.core.matching.significance import compound_log10_sf

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    # small and huge evidence (the log-space path), rare and plentiful chance pairings
    cases = [(e, lam) for e in (1e-6, 0.7, 12.0, 150.0, 2500.0, 20000.0)
             for lam in (1e-6, 0.05, 3.0, 90.0, 600.0)]
    fast = [compound_log10_sf(e, lam) for e, lam in cases]
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow = [compound_log10_sf(e, lam) for e, lam in cases]
    np.testing.assert_allclose(fast, slow, rtol=1e-13, atol=1e-13)


def test_closer_pairings_are_more_significant():
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.significance import significance

    p = MatchParams()
    args = (60, 60, 190.0 ** 2, 4 * 190.0 ** 2, 60.0, p)
    loose, _ = significance(np.full(12, 4.0), np.full(12, np.radians(20)), *args)
    tight, _ = significance(np.full(12, 1.0), np.full(12, np.radians(3)), *args)
    more, _ = significance(np.full(16, 4.0), np.full(16, np.radians(20)), *args)
    assert tight > loose and more > loose
    # below the floors residuals carry no extra evidence
    exact, _ = significance(np.zeros(12), np.zeros(12), *args)
    floor, _ = significance(np.full(12, p.pos_floor), np.full(12, p.angle_floor), *args)
    assert exact == floor


def test_heading_prior_searches_only_the_votes_inside_it(block):
    from dataclasses import fields

    from terrain_nav_ros.core.matching.consensus import _hypotheses
    from terrain_nav_ros.core.matching.index import MinutiaIndex
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.proposals import _hash_votes, _Votes

    b, _, _ = _rotated_copy(block, 6.0, seed=4, pos_sigma=1.5, angle_sigma=np.radians(10),
                            missing=0.3, spurious=0.3)
    prior = MatchParams(max_rotation=np.radians(20))
    ia, ib = MinutiaIndex(block, prior), MinutiaIndex(b, prior)
    votes = _hash_votes(ia, ib, prior)
    keep = np.abs(wrap_angle(votes.theta)) <= prior.max_rotation + prior.rot_bin
    assert 0 < keep.sum() < len(keep)
    inside = _Votes(*(getattr(votes, f.name)[keep] for f in fields(votes)))
    with_prior = _hypotheses(votes, ia, ib, prior)
    searched = _hypotheses(inside, ia, ib, MatchParams())
    assert len(with_prior) == len(searched) > 0
    for h, g in zip(with_prior, searched, strict=True):
        assert abs(h.c - g.c) < 1e-12 and abs(h.t - g.t) < 1e-9 and h.support == g.support


def test_numba_kernels_give_the_numpy_results(region, block, monkeypatch):
    """The optional numba kernels must not change a decision, pairing or transform, nor a
    score beyond rounding (the compound tail sums in another order)."""
    from terrain_nav_ros.core.matching import _matching_kernels

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    pva, _, _ = _rotated_copy(block, 35.0, 3)
    other = crop_set(region[0], 0, 256, BLOCK, BLOCK)
    view, _ = transform_set(region[0], rigid_transform(np.radians(-20.0), -100.0, -60.0),
                            (BLOCK, BLOCK), rng=4)
    cases = [(compare, block, pva), (compare, block, other), (localise, view, region[0])]

    def run():
        return [fn(a, b) for fn, a, b in cases]

    fast = run()
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow = run()
    for f, s in zip(fast, slow, strict=True):
        assert f.decision == s.decision and f.n_pairings == s.n_pairings
        assert f.score == pytest.approx(s.score, rel=1e-12, nan_ok=True)
        if f.n_pairings:
            np.testing.assert_array_equal(f.apply(10.0, 20.0), s.apply(10.0, 20.0))
    assert fast[0].decision == Decision.MATCH and fast[2].decision == Decision.MATCH


def test_pairings_in_a_large_region_by_brute_force_are_the_k_d_trees(region, monkeypatch):
    """A view's pairings in a region of more than _BRUTE_PAIR_MAX minutiae: brute force
    over the region's minutiae within reach of the view (numba) and the k-d tree query
    give the same pairings, at the true transform and off it."""
    from terrain_nav_ros.core.matching import _matching_kernels
    from terrain_nav_ros.core.matching.index import MinutiaIndex
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.registration import _BRUTE_PAIR_MAX, _pair

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    p = MatchParams()
    b = MinutiaIndex(region[0], p)
    assert b.n > _BRUTE_PAIR_MAX
    truth = rigid_transform(np.radians(-20.0), -100.0, -60.0)
    view, _ = transform_set(region[0], truth, (BLOCK, BLOCK), rng=4)
    a = MinutiaIndex(view, p)
    rng = np.random.default_rng(3)
    found = 0
    for k in range(30):
        c = complex(np.exp(1j * (np.radians(20.0) + rng.normal(0, 0.02 * (k % 3)))))
        t = complex(100 + rng.normal(0, 3 * (k % 3)), -(60 + rng.normal(0, 3 * (k % 3))))
        fast = _pair(a, b, c, t, p)
        monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
        slow = _pair(a, b, c, t, p)
        monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", True)
        np.testing.assert_array_equal(fast, slow)
        found += len(fast)
    assert found > 30   # the cases pair something


def test_scoring_and_ransac_kernels_agree_with_the_numpy_path(region, block, monkeypatch):
    """The fused minutiae terms of a registration's score, the RANSAC inlier counts and the
    crease samples around minutiae, against the numpy path, on registrations near and far
    from the truth (partial overlaps, few and many pairings, a turned and shrunk frame)."""
    from terrain_nav_ros.core.matching import _matching_kernels
    from terrain_nav_ros.core.matching.index import MinutiaIndex
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.registration import _pair, _ransac
    from terrain_nav_ros.core.matching.scoring import _scored

    if not _matching_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the numpy path is the only one")
    pva, _, _ = _rotated_copy(block, 35.0, 3)
    p = MatchParams()
    a = MinutiaIndex(block, p, region[1][128:128 + BLOCK, 128:128 + BLOCK])
    b = MinutiaIndex(pva, p)
    truth = complex(np.exp(1j * np.radians(-35.0)))
    rng = np.random.default_rng(7)
    cases = []
    for k in range(40):
        c = truth * np.exp(1j * rng.normal(0, 0.05 * (k % 4))) * (1 + 0.02 * (k == 3))
        t = complex(*rng.normal(0, 40, 2))
        pairs = _pair(a, b, c, t, p)
        if len(pairs) < 2:
            pairs = np.column_stack([rng.choice(a.n, 5, replace=False),
                                     rng.choice(b.n, 5, replace=False)])
        cases.append((c, t, pairs))
    cases += [(truth, 0j, np.zeros((0, 2), np.intp)),   # a searched registration may have
              (truth, 0j, np.array([[0, 1]]))]            # no or one minutiae pairing
    # 60 correspondences, 40 of them true (to ~1 px and ~3 degrees)
    za = a.z[:60]
    zb = truth * za + (5 - 3j) + rng.normal(0, 1, 60) + 1j * rng.normal(0, 1, 60)
    zb[40:] = b.z[:20]
    dang = np.angle(truth) + rng.normal(0, 0.05, 60)
    ransac_in = [(za, zb, dang, c, t) for c, t, _ in cases[:10]]

    def run():
        scored = [_scored(a, b, c, t, pairs, 4e5, a.radius, p, False)
                  for c, t, pairs in cases]
        ransac = [_ransac(za, zb, dang, p, np.random.default_rng(1), c, t)
                  for za, zb, dang, c, t in ransac_in]
        around = [a.crease_samples_around(pairs[:, 0]) for _, _, pairs in cases]
        return scored, ransac, around

    fast = run()
    monkeypatch.setattr(_matching_kernels, "HAVE_NUMBA", False)
    slow = run()
    for f, s in zip(fast[0], slow[0], strict=True):
        assert f.n_overlap == s.n_overlap
        assert f.score == pytest.approx(s.score, rel=1e-12, abs=1e-12)
    assert len({sc.n_overlap for sc in fast[0]}) > 10   # partial overlaps among them
    for f, s in zip(fast[1], slow[1], strict=True):   # the same sample pair chosen
        assert abs(f[0] - s[0]) < 1e-12 and abs(f[1] - s[1]) < 1e-9
        np.testing.assert_array_equal(f[2], s[2])
    assert all(f[2].sum() >= 35 for f in fast[1])
    for f, s in zip(fast[2], slow[2], strict=True):
        np.testing.assert_array_equal(f, s)
    assert fast[2][-2].size == 0


def test_rotation_sweep_finds_the_rotation_the_histogram_buries(block):
    """Where the drainage runs one way, edges of unrelated minutiae agree on a rotation and
    bury the true one in the rotation histogram: its peaks then miss the transform, while
    the sweep (the wider try below ``rescue_below``) ranks rotations by their strongest
    joint translation cell and finds it."""
    from dataclasses import fields

    from terrain_nav_ros.core.matching.consensus import _hypotheses, _rotation_support
    from terrain_nav_ros.core.matching.index import MinutiaIndex
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.proposals import _hash_votes, _Votes

    b, _, m = _rotated_copy(block, 30.0, seed=2, pos_sigma=1.0)
    p = MatchParams()
    ia, ib = MinutiaIndex(block, p), MinutiaIndex(b, p)
    votes = _hash_votes(ia, ib, p)
    # three times as many unrelated edge pairs whose directions agree near -60 degrees
    rng = np.random.default_rng(0)
    n = 3 * len(votes.ia)
    edge_a, edge_b = np.argwhere(ia.edges.valid), np.argwhere(ib.edges.valid)
    ka, kb = edge_a[rng.integers(0, len(edge_a), n)], edge_b[rng.integers(0, len(edge_b), n)]
    clutter = {"ia": ka[:, 0], "ja": ia.edges.j[ka[:, 0], ka[:, 1]],
               "ib": kb[:, 0], "jb": ib.edges.j[kb[:, 0], kb[:, 1]],
               "theta": rng.normal(np.radians(-60.0), np.radians(8.0), n),
               "weight": rng.choice(votes.weight, n)}
    votes = _Votes(*(np.concatenate([getattr(votes, f.name),
                                        clutter[f.name].astype(getattr(votes, f.name).dtype)])
                        for f in fields(votes)))
    col, row = ia.centroid.real, -ia.centroid.imag
    true_col, true_row = m @ np.array([col, row, 1.0])
    truth, turn = complex(true_col, -true_row), complex(m[0, 0], -m[1, 0])

    def found(hyps):   # a hypothesis within 5 px at A's centroid and 5 degrees
        return any(abs(h.c * ia.centroid + h.t - truth) < 5.0
                   and abs(np.angle(h.c / turn)) < np.radians(5.0) for h in hyps)

    assert not found(_hypotheses(votes, ia, ib, p))
    assert found(_hypotheses(votes, ia, ib, p, sweep=True))
    # the numpy path ranks the same rotations
    from terrain_nav_ros.core.matching import _matching_kernels

    cells = (np.arange(72) + 0.5) * (2 * np.pi / 72) - np.pi
    fast = _rotation_support(votes, ia, ib, p, cells)
    if _matching_kernels.HAVE_NUMBA:
        _matching_kernels.HAVE_NUMBA = False
        try:
            slow = _rotation_support(votes, ia, ib, p, cells)
        finally:
            _matching_kernels.HAVE_NUMBA = True
        np.testing.assert_allclose(fast, slow, rtol=1e-6)


def test_warm_up_loads_every_kernel():
    """In a fresh process (this one's kernels may have run in other tests already): a node
    that warms up meets no kernel to load or compile at its first frame."""
    code = """
from terrain_nav_ros.core.matching import _matching_kernels
from terrain_nav_ros.core.matching.matcher import warm_up
warm_up()
kernels = {k: getattr(_matching_kernels, k) for k in dir(_matching_kernels)
           if not k.startswith("_") and hasattr(getattr(_matching_kernels, k), "signatures")}
assert not _matching_kernels.HAVE_NUMBA or kernels
print(sorted(k for k, f in kernels.items() if not f.signatures))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == "[]", out.stdout


def test_prepare_as_reference_builds_what_matching_builds_lazily(region, block):
    index = Matcher().index(block, region[1][128:384, 128:384]).prepare_as_reference()
    assert index._hash is not None and index._crease_field is not None
    big = Matcher(candidates="roots").index(region[0]).prepare_as_reference()
    assert big._hash is None   # the roots generator never asks for the hash
