"""Crease extraction (dissertation 3.2): diffusion, MLSEC-ST, masks, skeleton."""

import numpy as np
import pytest

from terrain_nav_ros.core.features.creases import (
    CreaseDetector,
    CreaseParams,
    crease_contrast,
    crease_diffusion,
    diffusion_tensor,
    estimate_noise,
    mlsec_st,
    prepare_input,
)


def line_image(n=128, width=3.0, depth=100.0, row=None, bright=False):
    """Horizontal Gaussian-profile line (dark valley unless ``bright``) on grey 150."""
    rr = np.arange(n, dtype=float)[:, None] - (n / 2 if row is None else row)
    profile = depth * np.exp(-(rr**2) / (2 * width**2))
    return np.broadcast_to(150.0 + (profile if bright else -profile), (n, n)).copy()


def test_defaults_are_table_3_1():
    p = CreaseParams()
    assert (p.iterations, p.sigma, p.w1, p.rho, p.w2) == (5, 1.0, 5, 1.0, 3)
    assert (p.epsilon, p.alpha, p.beta) == (0.001, 1.0, 1.0)


@pytest.mark.parametrize("bad", [
    dict(iterations=-1), dict(iterations=2.5), dict(sigma=0), dict(rho=-1.0),
    dict(w1=4), dict(w2=0), dict(epsilon=0.0), dict(epsilon=1.0), dict(alpha=1.5),
    dict(beta=-0.1), dict(time_step=0.3), dict(threshold=0.0), dict(threshold=2.5),
    dict(threshold_low=0.9), dict(min_area=-1), dict(polarity="creek"),
    dict(contrast_snr=-1.0), dict(mlsec_sigma=float("nan")), dict(tensor_update=0),
])
def test_bad_params_raise(bad):
    with pytest.raises(ValueError):
        CreaseParams(**bad)


def test_from_dict_rejects_unknown_keys():
    assert CreaseParams.from_dict({"iterations": 3}).iterations == 3
    with pytest.raises(ValueError, match="unknown"):
        CreaseParams.from_dict({"kappa": 1})


def test_tensor_eigenvalues_follow_eq_3_5():
    p = CreaseParams(alpha=0.7, beta=0.9)
    one, zero = np.ones((1, 1), np.float32), np.zeros((1, 1), np.float32)
    # Valley along y: positive curvature across (x): D = diag(epsilon, beta).
    a, b, c = diffusion_tensor(one, zero, zero, p)
    assert np.allclose([a[0, 0], b[0, 0], c[0, 0]], [p.epsilon, 0, p.beta], atol=1e-6)
    # Ridge along x: D = diag(alpha, epsilon).
    a, b, c = diffusion_tensor(zero, zero, -one, p)
    assert np.allclose([a[0, 0], b[0, 0], c[0, 0]], [p.alpha, 0, p.epsilon], atol=1e-6)
    # Random Hessians: D is positive semidefinite, epsilon is one eigenvalue, the other
    # (alpha mu_r + beta mu_v) lies in [0, 1].
    rng = np.random.default_rng(1)
    h = rng.normal(size=(3, 50, 50)).astype(np.float32)
    a, b, c = diffusion_tensor(h[0], h[1], h[2], p)
    tr, det = a + c, a * c - b * b
    disc = np.sqrt(np.maximum(tr**2 / 4 - det, 0))
    assert (tr / 2 - disc >= -1e-6).all()
    assert (tr / 2 + disc <= 1 + 1e-5).all()
    assert np.allclose((a - p.epsilon) * (c - p.epsilon) - b * b, 0, atol=1e-5)


def test_diffusion_is_stable_and_conserves_mean():
    rng = np.random.default_rng(0)
    u = rng.normal(0, 1, (96, 80)).astype(np.float32)
    out = crease_diffusion(u, CreaseParams(iterations=100, time_step=0.25))
    assert np.isfinite(out).all()
    assert np.abs(out).max() <= np.abs(u).max()
    assert out.mean() == pytest.approx(u.mean(), abs=1e-3)
    assert out.std() < u.std()


def test_diffusion_keeps_crease_and_smooths_along_it():
    img = line_image(64).astype(np.float32)
    rng = np.random.default_rng(2)
    noisy = img + rng.normal(0, 10, img.shape).astype(np.float32)
    out = crease_diffusion(noisy, CreaseParams(iterations=20))
    # Still a valley at the same row, and smoother along the line than before.
    assert abs(int(np.argmin(out[8:-8, 8:-8].mean(1))) + 8 - 32) <= 1
    assert np.std(np.diff(out[32, 8:-8])) < 0.7 * np.std(np.diff(noisy[32, 8:-8]))


def test_mlsec_sign_and_rotation_invariance():
    # Off-centre line: at an exactly symmetric centre the gradient sign is float noise.
    valley = line_image(64, row=32.3).astype(np.float32)
    k = mlsec_st(valley)
    assert k[32, 32] < -0.5                   # valleys negative
    assert mlsec_st(-valley)[32, 32] > 0.5    # ridges positive
    assert np.all(np.abs(k) <= 2 + 1e-5)
    rot = mlsec_st(np.rot90(valley).copy())
    # Rotation invariant away from the (reflecting) border.
    assert np.allclose(np.rot90(k)[8:-8, 8:-8], rot[8:-8, 8:-8], atol=1e-4)


def test_estimate_noise_recovers_sigma():
    rng = np.random.default_rng(3)
    img = line_image(128) + rng.normal(0, 5, (128, 128))
    assert estimate_noise(img.astype(np.float32)) == pytest.approx(5.0, rel=0.1)


def test_skeleton_of_straight_valley_is_the_valley_line():
    res = CreaseDetector()(line_image(128, row=50.0).astype(np.uint8))
    assert res.reason == ""
    rows, cols = np.nonzero(res.skeletons["valley"])
    assert np.all(np.abs(rows - 50) <= 1)
    assert cols.max() - cols.min() > 100
    assert "ridge" not in res.skeletons


def test_ridges_are_valleys_of_the_inverted_image():
    img = line_image(96, row=40.0, bright=True).astype(np.uint8)
    ridge = CreaseDetector(CreaseParams(polarity="ridge"))(img).skeletons["ridge"]
    valley = CreaseDetector()(255 - img).skeletons["valley"]
    # Same creases up to the skeleton's tie-breaking on a symmetric profile (1 px).
    from scipy.ndimage import distance_transform_edt

    assert ridge.any() and abs(int(ridge.sum()) - int(valley.sum())) <= 2
    assert distance_transform_edt(~valley)[ridge].max() <= 1.0
    both = CreaseDetector(CreaseParams(polarity="both"))(img)
    assert both.skeletons["ridge"].any() and not both.skeletons["valley"].any()


@pytest.mark.parametrize("name,image", [
    ("constant", np.full((64, 64), 42, np.uint8)),
    ("flat float", np.zeros((64, 64))),
    ("white noise", np.random.default_rng(4).normal(100, 20, (128, 128))),
    ("faint noise", np.random.default_rng(5).integers(120, 123, (128, 128)).astype(np.uint8)),
    ("smooth slope", np.add.outer(np.arange(96.0), np.arange(96.0))),
])
def test_no_drainage_gives_a_reason(name, image):
    res = CreaseDetector()(image)
    assert res.reason, name
    assert not any(s.any() for s in res.skeletons.values())


def test_prepare_input_dem_and_nodata():
    dem = np.add.outer(np.arange(32.0), np.zeros(32)) * 10.0
    dem[5:8, 5:8] = -32768
    work, valid, noise, reason = prepare_input(dem, source="dem", gsd=10.0, nodata=-32768)
    assert reason == "" and not valid[6, 6] and valid.sum() == 32 * 32 - 9
    assert np.isfinite(work).all() and 4.0 <= work[6, 6] <= 8.0
    assert work[1, 0] - work[0, 0] == pytest.approx(1.0)   # elevation in pixel units
    with pytest.raises(ValueError):
        prepare_input(dem, source="lidar")
    with pytest.raises(ValueError):
        prepare_input(np.zeros((4, 4, 4, 4)))
    colour = np.dstack([line_image(32)] * 3).astype(np.uint8)
    assert prepare_input(colour)[0].shape == (32, 32)


def test_an_image_too_narrow_or_with_a_sentinel_pixel_is_read_for_what_it_is():
    """1 x N frames are a no-fix with the reason (not an error deep in the diffusion); one
    undeclared float sentinel (3e38) neither sets the noise floor nor hides the creases."""
    rng = np.random.default_rng(0)
    for shape in ((1, 300), (300, 1), (2, 50)):
        reason = prepare_input(rng.integers(0, 255, shape).astype(np.uint8))[3]
        assert reason.startswith(f"image of {shape[0]}x{shape[1]} px: too narrow")
    image = line_image(64).astype(np.float32) + rng.normal(0.0, 3.0, (64, 64)).astype(
        np.float32)
    clean = prepare_input(image)
    image[5, 5] = 3e38
    spiked = prepare_input(image)
    assert spiked[3] == "" and spiked[2] == pytest.approx(clean[2], rel=0.05)


def test_strip_processing_is_exact():
    from terrain_nav_ros.core.features.creases import (
        _diffusion_in_strips,
        _Workspace,
        diffusion_step,
        normalised_hessian,
    )

    rng = np.random.default_rng(6)
    img = rng.normal(0, 20, (90, 61)).astype(np.float32)
    p = CreaseParams(w1=7, sigma=1.5)
    ref, ws = img.copy(), _Workspace(img.shape)
    for _ in range(p.iterations):
        diffusion_step(ref, *diffusion_tensor(*normalised_hessian(ref, p, ws), p, ws),
                       p.time_step, ws)
    # Equal up to float rounding (OpenCV's SIMD tails depend on the strip size).
    for rows in (5, 32, None):
        assert np.allclose(_diffusion_in_strips(img.copy(), p, rows), ref, rtol=0, atol=1e-4)
    assert np.allclose(crease_diffusion(img, p), ref, rtol=0, atol=1e-4)


def test_fused_kernels_match_the_reference():
    from terrain_nav_ros.core.features import _crease_kernels
    from terrain_nav_ros.core.features.creases import _diffusion_fused, _diffusion_in_strips

    if not _crease_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the reference path is the only one")
    rng = np.random.default_rng(7)
    img = rng.normal(0, 20, (70, 53)).astype(np.float32)
    for p in (CreaseParams(), CreaseParams(alpha=0.3, beta=0.8, w1=7, sigma=1.5, rho=2.0,
                                           w2=5)):
        ref = _diffusion_in_strips(img.copy(), p)
        assert np.allclose(_diffusion_fused(img.copy(), p), ref, rtol=0, atol=1e-3)


def test_fused_mlsec_and_contrast_match_the_reference(monkeypatch):
    from terrain_nav_ros.core.features import _crease_kernels, creases

    if not _crease_kernels.HAVE_NUMBA:
        pytest.skip("numba not installed: the reference path is the only one")
    rng = np.random.default_rng(8)
    img = (line_image(80, row=30.3) + rng.normal(0, 5, (80, 80))).astype(np.float32)
    fused = mlsec_st(img, 1.0, 2.0), creases.crease_contrast(img, 2.0)
    monkeypatch.setattr(_crease_kernels, "HAVE_NUMBA", False)
    ref = mlsec_st(img, 1.0, 2.0), creases.crease_contrast(img, 2.0)
    assert np.allclose(fused[0], ref[0], atol=1e-3)
    assert np.allclose(fused[1], ref[1], rtol=1e-4, atol=1e-4 * np.abs(ref[1]).max())


def _with_and_without_numba(monkeypatch, run):
    """``run()`` with the numba kernels (when installed) and on the numpy/OpenCV path."""
    from terrain_nav_ros.core.features import _crease_kernels

    out = [run()]
    if _crease_kernels.HAVE_NUMBA:
        monkeypatch.setattr(_crease_kernels, "HAVE_NUMBA", False)
        out.append(run())
    return out


def test_mask_drops_small_and_unseeded_components_and_fills_small_holes(monkeypatch):
    from terrain_nav_ros.core.features.creases import crease_mask

    p = CreaseParams(threshold=0.5, threshold_low=0.2, min_area=20)
    score = np.zeros((40, 60), np.float32)
    score[5:12, 5:14] = 1.0        # 7x9 blob, strong
    score[7:9, 7:9] = 0.0          # with a 2x2 hole: filled
    score[20:34, 5:20] = 0.3       # weak ring (hysteresis) seeded by one strong pixel
    score[23:31, 8:17] = 0.0       # its 8x9 hole is large: kept
    score[20, 5] = 1.0
    score[20:34, 30:45] = 0.3      # the same ring without a seed: dropped
    score[23:31, 33:42] = 0.0
    score[3:6, 50:53] = 1.0        # 9 strong pixels: too small
    score[0:6, 20:26] = 1.0        # 6x6 at the border with a 2-pixel notch open only to the
    score[0, 22:24] = 0.0          # image border: a small hole (the border encloses it)
    contrast = np.ones_like(score)
    for mask in _with_and_without_numba(monkeypatch, lambda: crease_mask(
            -score, contrast, 0.1, p, "valley")):
        assert mask.dtype == bool
        assert mask[5:12, 5:14].all()
        assert mask[20:34, 5:20].sum() == 14 * 15 - 8 * 9
        assert not mask[20:34, 30:45].any()
        assert not mask[3:6, 50:53].any()
        assert mask[0:6, 20:26].all()


def test_fused_mask_matches_the_reference(monkeypatch):
    from terrain_nav_ros.core.features.creases import crease_mask

    rng = np.random.default_rng(9)
    img = (line_image(120, row=40.2) + line_image(120, row=90.7, width=5.0, bright=True)
           + rng.normal(0, 12, (120, 120))).astype(np.float32)
    p = CreaseParams()
    work, valid, noise, _ = prepare_input(img)
    valid[:, :7] = False
    cr, co = mlsec_st(work, 1.0, 2.0), crease_contrast(work, 2.0)
    masks = _with_and_without_numba(
        monkeypatch, lambda: [crease_mask(cr, co, noise, p, pol, valid)
                              for pol in ("valley", "ridge")])
    assert masks[0][0].any() and masks[0][1].any()
    for fused, ref in zip(masks[0], masks[-1], strict=True):
        assert np.array_equal(fused, ref)


@pytest.mark.parametrize("size", [1, 2, 7, 1000, 65535])
def test_fast_median_is_numpys(size):
    from terrain_nav_ros.core.features.creases import _median

    values = np.random.default_rng(size).normal(size=size).astype(np.float32)
    assert _median(values) == np.median(values)
    assert _median(values.astype(np.float64)) == np.median(values.astype(np.float64))
