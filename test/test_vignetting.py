"""The lens falloff learnt from a flight's frames and divided out (core.camera.vignetting)."""

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.camera.vignetting import MIN_FRAMES, Vignetting

H, W = 192, 256


def _terrain(rng) -> np.ndarray:
    """A frame's worth of terrain-like texture, mid-grey, different each time."""
    noise = rng.standard_normal((H, W)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), 4.0)
    return 110.0 + 40.0 * texture / texture.std()


def _falloff(strength: float, centre=(0.5 * (W - 1), 0.5 * (H - 1))) -> np.ndarray:
    """The simulator's lens: ``1 - strength r^2``, r over the half diagonal."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    r2 = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (0.25 * (W * W + H * H))
    return 1.0 - strength * r2


def _radial_ratio(frames, centre=None) -> float:
    """Mean brightness beyond 0.8 of the half diagonal over that within 0.3, over frames."""
    cx, cy = centre or (0.5 * (W - 1), 0.5 * (H - 1))
    y, x = np.mgrid[0:H, 0:W]
    r = np.sqrt(((x - cx) ** 2 + (y - cy) ** 2) / (0.25 * (W * W + H * H)))
    mean = np.mean([f.astype(float) for f in frames], axis=0)
    return float(mean[r > 0.8].mean() / mean[r < 0.3].mean())


def test_a_lens_darker_at_its_edge_is_learnt_and_divided_out():
    rng = np.random.default_rng(0)
    vignetting = Vignetting()
    lens = _falloff(0.25)
    frames = [np.clip(_terrain(rng) * lens, 0, 255).astype(np.uint8) for _ in range(40)]
    out = [vignetting.correct(f) for f in frames]
    # until enough frames are seen, frames pass as they are
    assert all(o is f for o, f in zip(out[:MIN_FRAMES - 1], frames, strict=False))
    assert _radial_ratio(frames) < 0.85
    corrected = out[MIN_FRAMES + 5:]
    assert all(f.dtype == np.uint8 and f.shape == (H, W) for f in corrected)
    assert _radial_ratio(corrected) == pytest.approx(1.0, abs=0.02)
    assert vignetting.corner() == pytest.approx(0.75, abs=0.04)


def test_a_flat_fielded_camera_s_frames_are_left_as_they_are():
    rng = np.random.default_rng(1)
    vignetting = Vignetting()
    frames = [np.clip(_terrain(rng), 0, 255).astype(np.uint8) for _ in range(80)]
    out = [vignetting.correct(f) for f in frames]
    assert vignetting.corner() == pytest.approx(1.0, abs=0.03)
    diff = np.abs(out[-1].astype(int) - frames[-1].astype(int))
    assert diff.mean() < 1.0


def test_the_falloff_is_about_the_principal_point_and_colour_frames_keep_their_type():
    rng = np.random.default_rng(2)
    centre = (0.5 * (W - 1) + 30.0, 0.5 * (H - 1) - 20.0)
    lens = _falloff(0.3, centre)[..., None]
    vignetting = Vignetting()
    out = []
    for _ in range(30):
        rgb = np.repeat(_terrain(rng)[..., None], 3, axis=2) * lens
        out.append(vignetting.correct(np.clip(rgb / 255.0, 0, 1).astype(np.float32), centre))
    assert out[-1].dtype == np.float32 and out[-1].shape == (H, W, 3)
    assert _radial_ratio([f.mean(axis=2) for f in out[10:]], centre) == \
        pytest.approx(1.0, abs=0.03)


def test_saturated_or_disabled_frames_teach_nothing():
    vignetting = Vignetting()
    white = np.full((H, W), 255, np.uint8)
    for _ in range(10):
        assert vignetting.correct(white) is white
    assert vignetting.frames == 0 and np.isnan(vignetting.corner())
    off = Vignetting(enabled=False)
    frame = (_terrain(np.random.default_rng(3)) * _falloff(0.25)).astype(np.uint8)
    assert all(off.correct(frame) is frame for _ in range(10))
