"""Make a rendered view look like a real camera frame (for the flight simulator).

A landmark render is clean: the same renderer would make the simulated camera frames
trivially easy to match. A real frame differs by atmosphere, exposure, optics and sensor, so
:func:`apply_camera_effects` adds, in the order light meets them: aerial-perspective haze
(grows with the distance to each surface point), automatic exposure with a little gain error,
a display gamma, optical blur, vignetting, radial-tangential lens distortion (matching the
CameraInfo published with the frame), photon and read noise, and 8-bit quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class CameraEffects:
    """How far a simulated frame departs from the clean render.

    Parameters
    ----------
    haze_per_km : float
        Extinction coefficient of the aerial perspective (1/km); transmittance is
        ``exp(-haze_per_km * distance_km)``.
    haze_colour : tuple of 3 floats
        Linear RGB of the airlight.
    exposure_key : float
        Mean grey level automatic exposure aims for (0-1, before gamma).
    exposure_jitter : float
        Relative standard deviation of the gain error per frame.
    gamma : float
        Display gamma applied to linear radiance.
    blur_sigma : float
        Gaussian optical/motion blur (px).
    vignetting : float
        Relative fall-off at the image corners (0 = none).
    distortion : tuple of 5 floats
        OpenCV plumb_bob coefficients (k1, k2, p1, p2, k3) of the simulated lens.
    read_noise : float
        Standard deviation of additive noise (grey levels of 255).
    photon_gain : float
        Shot-noise variance per grey level (grey levels of 255); 0 disables.
    """

    haze_per_km: float = 0.04
    haze_colour: tuple = (0.75, 0.80, 0.88)
    exposure_key: float = 0.4
    exposure_jitter: float = 0.05
    gamma: float = 2.2
    blur_sigma: float = 0.8
    vignetting: float = 0.25
    distortion: tuple = (-0.12, 0.03, 0.0005, -0.0003, 0.0)
    read_noise: float = 1.5
    photon_gain: float = 0.08


def distortion_maps(k: np.ndarray, distortion, width: int, height: int):
    """cv2.remap maps that take an ideal pinhole image to the distorted lens image.

    For every pixel of the distorted image, ``cv2.undistortPoints`` gives where the ideal
    pinhole ray lands, so sampling the clean render there reproduces the lens; OpenCV's own
    ``cv2.undistort`` then inverts it, which is what the camera_ingest node does.
    """
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], -1)[:, None, :]
    ideal = cv2.undistortPoints(pts, k, np.asarray(distortion, float), P=k)
    return (ideal[:, 0, 0].reshape(height, width).astype(np.float32),
            ideal[:, 0, 1].reshape(height, width).astype(np.float32))


def apply_camera_effects(rgb: np.ndarray, distance_m: np.ndarray, effects: CameraEffects,
                         rng: np.random.Generator, maps=None) -> np.ndarray:
    """Turn a clean linear-RGB render into an 8-bit camera frame.

    Parameters
    ----------
    rgb : ndarray (H, W, 3) float
        Linear radiance in [0, 1].
    distance_m : ndarray (H, W)
        Distance from the camera to each pixel's surface point (m); NaN = sky / no terrain.
    effects : CameraEffects
    rng : numpy Generator
        Source of the exposure jitter and sensor noise (deterministic given a seed).
    maps : tuple of two float32 arrays, optional
        :func:`distortion_maps` for this camera (computed once per camera by the caller).

    Returns
    -------
    ndarray (H, W, 3) uint8
        RGB frame.
    """
    rgb = np.asarray(rgb, np.float32)
    h, w = rgb.shape[:2]
    distance_km = np.nan_to_num(np.asarray(distance_m, np.float32) * 1e-3, nan=1e3)
    transmit = np.exp(-effects.haze_per_km * distance_km)[..., None]
    airlight = np.asarray(effects.haze_colour, np.float32)
    radiance = rgb * transmit + airlight * (1.0 - transmit) * 0.5
    gain = effects.exposure_key / max(float(radiance.mean()), 1e-6)
    gain *= float(np.exp(rng.normal(0.0, effects.exposure_jitter)))
    image = np.clip(radiance * gain, 0.0, 1.0) ** (1.0 / effects.gamma)
    if effects.blur_sigma > 0:
        image = cv2.GaussianBlur(image, (0, 0), effects.blur_sigma)
    if effects.vignetting > 0:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - 0.5 * (w - 1)) ** 2 + (yy - 0.5 * (h - 1)) ** 2) / (0.25 * (w * w + h * h))
        image = image * (1.0 - effects.vignetting * r2)[..., None]
    if maps is not None:
        image = cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
    levels = image * 255.0
    sigma = np.sqrt(effects.read_noise ** 2 + effects.photon_gain * np.maximum(levels, 0.0))
    levels = levels + rng.standard_normal(levels.shape, dtype=np.float32) * sigma
    return np.clip(np.rint(levels), 0, 255).astype(np.uint8)
