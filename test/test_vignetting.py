"""The lens falloff learnt from overlapping frames and divided out (core.camera.vignetting)."""

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.camera.ground_projection import GroundImage
from terrain_nav_ros.core.camera.vignetting import MIN_PAIRS, Vignetting, frame_radius2
from terrain_nav_ros.core.terrain.georef import GeoReference

H, W = 192, 256
GSD = 10.0


def _scene(rng, side=900, strip=0.0) -> np.ndarray:
    """Terrain-like texture, mid-grey; ``strip`` brightens a band along the rows' middle,
    where the flight below goes (a ridge or a river the track follows)."""
    noise = rng.standard_normal((side, side)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), 4.0)
    scene = 110.0 + 40.0 * texture / texture.std()
    rows = np.arange(side, dtype=np.float32)[:, None]
    return scene * (1.0 + strip * np.exp(-0.5 * ((rows - side / 2) / 40.0) ** 2))


def _lens(strength: float, centre=None) -> np.ndarray:
    """The simulator's lens: ``1 - strength r^2``, r over the half diagonal."""
    cx, cy = centre or (0.5 * (W - 1), 0.5 * (H - 1))
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return 1.0 - strength * frame_radius2(u, v, cx, cy, W, H)


def _fly(vignetting, scene, lens, frames=30, step=(9, 1), centre=None, jump=None,
         colour=False, dtype=np.uint8):
    """A straight flight over ``scene`` seen nadir by a camera whose raw pixel is a ground
    pixel (the identity projection), each frame corrected, then learnt from as camera_ingest
    does. ``jump`` = (frame, px): from that frame on the estimate is off by px columns.
    Returns the raw and corrected frames."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    raws, outs = [], []
    top = scene.shape[0] // 2 - H // 2
    full = 255.0 if dtype == np.uint8 else 1.0
    for k in range(frames):
        col, row = 20 + k * step[0], top + k * step[1]
        grey = scene[row:row + H, col:col + W] * lens
        raw = np.clip(grey * full / 255.0, 0, full)
        raw = np.repeat(raw[..., None], 3, axis=2) if colour else raw
        raw = np.rint(raw).astype(dtype) if dtype == np.uint8 else raw.astype(dtype)
        out = vignetting.correct(raw, centre)
        off = jump[1] if jump and k >= jump[0] else 0
        georef = GeoReference((col + off) * GSD, -row * GSD, GSD, W, H)
        grey_out = out.mean(axis=2) if colour else out
        vignetting.learn(GroundImage(grey_out.astype(np.float32), np.ones((H, W), bool),
                                     georef, frame_pixels=(u, v)))
        raws.append(raw)
        outs.append(out)
    return raws, outs


def _radial_ratio(frames, centre=None) -> float:
    """Mean brightness beyond 0.8 of the half diagonal over that within 0.3, over frames
    (each frame over its own ground, so the scene's own brightness averages out slowly)."""
    cx, cy = centre or (0.5 * (W - 1), 0.5 * (H - 1))
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    r = np.sqrt(frame_radius2(u, v, cx, cy, W, H))
    mean = np.mean([f.astype(float) for f in frames], axis=0)
    mean = mean.mean(axis=2) if mean.ndim == 3 else mean
    return float(mean[r > 0.8].mean() / mean[r < 0.3].mean())


def test_a_lens_darker_at_its_edge_is_learnt_from_overlapping_frames_and_divided_out():
    rng = np.random.default_rng(0)
    vignetting = Vignetting()
    raws, outs = _fly(vignetting, _scene(rng), _lens(0.25), frames=40)
    # until enough pairs are learnt, frames pass as they are
    assert all(o is r for o, r in zip(outs[:MIN_PAIRS + 1], raws, strict=False))
    assert vignetting.corner() == pytest.approx(0.75, abs=0.02)
    last = outs[-1].astype(float) / _lens(0.0)
    truth = raws[-1].astype(float) / _lens(0.25)
    assert outs[-1].dtype == np.uint8 and outs[-1].shape == (H, W)
    assert np.abs(last - truth).mean() < 1.5      # within the 8 bits' rounding


def test_a_flight_along_a_bright_ridge_is_not_taken_for_a_lens():
    """A track that keeps a bright band in the middle of every frame: the mean frame is
    brighter at its centre though the camera is flat-fielded (the radial profile of the
    frames' mean put the corner at 0.84 here); pairs of frames see no falloff."""
    rng = np.random.default_rng(1)
    vignetting = Vignetting()
    raws, outs = _fly(vignetting, _scene(rng, strip=0.4), _lens(0.0), frames=60, step=(9, 0))
    assert _radial_ratio(raws) < 0.9
    assert vignetting.corner() == pytest.approx(1.0, abs=0.02)
    assert np.abs(outs[-1].astype(int) - raws[-1].astype(int)).mean() < 1.0


def test_a_jump_of_the_estimate_between_frames_is_registered_away():
    rng = np.random.default_rng(2)
    vignetting = Vignetting()
    _fly(vignetting, _scene(rng), _lens(0.25), frames=30, jump=(12, 2))
    assert vignetting.corner() == pytest.approx(0.75, abs=0.02)


def test_the_falloff_is_about_the_principal_point_and_colour_frames_keep_their_type():
    rng = np.random.default_rng(3)
    centre = (0.5 * (W - 1) + 30.0, 0.5 * (H - 1) - 20.0)
    vignetting = Vignetting()
    raws, outs = _fly(vignetting, _scene(rng), _lens(0.3, centre), frames=30, centre=centre,
                      colour=True, dtype=np.float32)
    assert outs[-1].dtype == np.float32 and outs[-1].shape == (H, W, 3)
    assert vignetting.corner() == pytest.approx(0.7, abs=0.03)
    assert _radial_ratio(outs[-10:], centre) == pytest.approx(
        _radial_ratio([r / _lens(0.3, centre)[..., None] for r in raws[-10:]], centre),
        abs=0.02)


def test_saturated_frames_and_a_disabled_correction_teach_nothing():
    rng = np.random.default_rng(4)
    white = Vignetting()
    _fly(white, np.full((900, 900), 400.0, np.float32) + _scene(rng) * 0.01, _lens(0.25))
    assert white.pairs == 0 and np.isnan(white.corner())
    off = Vignetting(enabled=False)
    raws, outs = _fly(off, _scene(rng), _lens(0.25), frames=10)
    assert all(o is r for o, r in zip(outs, raws, strict=True)) and off.pairs == 0


def test_integer_frames_of_every_type_are_rounded_and_saturated():
    rng = np.random.default_rng(5)
    vignetting = Vignetting()
    raws, _ = _fly(vignetting, _scene(rng), _lens(0.25), frames=20)
    frame = raws[-1].astype(np.int64)
    frame[:4, :4] = 255                       # the gain at the corner pushes these past 255
    gain = vignetting.correct(np.ones((H, W), np.float64))
    assert gain[:4, :4].min() > 1.2
    for dtype in (np.uint8, np.int8, np.int16, np.int32, np.uint32):
        info = np.iinfo(dtype)
        expected = np.clip(np.rint(frame * gain), info.min, info.max)
        out = vignetting.correct(np.clip(frame, info.min, info.max).astype(dtype))
        assert out.dtype == dtype
        # (OpenCV's float32 gain may round a half the other way)
        assert np.abs(out.astype(np.int64) - expected).max() <= 1, dtype
        assert (out[:4, :4] == info.max).any() == (info.max < 255 * gain[:4, :4].max()), dtype
