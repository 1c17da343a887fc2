"""Baseline image matchers the minutiae matcher is compared with (design notes, "Baselines").

Both locate a camera image inside a larger landmark image and return where the camera
image's centre falls, so their error is measured exactly like the minutiae matcher's:

* :func:`ncc_locate`: normalised cross-correlation of gradient-magnitude images (Gaussian
  blur, Sobel magnitude, ``cv2.matchTemplate`` with ``TM_CCOEFF_NORMED``), the DSMAC / JPL-LVS
  family. The gradient magnitude ignores the sign of shading contrast, so it survives a sun
  from the other side far better than NCC on intensities. Optionally a brute-force rotation
  search (the template rotated in ``n_rotations`` steps; only its inscribed square is used so
  that no rotated-in border enters the correlation).
* :func:`keypoint_locate`: ORB or SIFT keypoints, ratio-test matches and a RANSAC
  homography.

The module is ROS-free and uses only numpy and OpenCV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Located", "gradient_magnitude", "ncc_locate", "keypoint_features",
           "keypoint_locate", "has_sift"]


@dataclass
class Located:
    """Where a baseline put the camera image's centre in the landmark image.

    Attributes
    ----------
    col, row : float
        Landmark pixel coordinates of the camera centre (NaN when nothing was found).
    score : float
        Peak correlation (NCC) or RANSAC inlier count (keypoints).
    rotation : float
        Rotation (rad, CCW in the north-up image) found by the search; 0 without one.
    reason : str
        Why nothing was found.
    """

    col: float = math.nan
    row: float = math.nan
    score: float = math.nan
    rotation: float = 0.0
    reason: str = ""

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.col) and np.isfinite(self.row))


def _grey_f32(image) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


def gradient_magnitude(image, sigma: float = 1.5) -> np.ndarray:
    """Sobel gradient magnitude of a Gaussian-blurred grey image (float32).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
    sigma : float
        Gaussian blur (px) before the derivatives; suppresses sensor noise.
    """
    g = _grey_f32(image)
    if sigma > 0:
        g = cv2.GaussianBlur(g, (0, 0), sigma)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def _subpixel_peak(res: np.ndarray, loc) -> tuple[float, float]:
    """Quadratic (3-point) refinement of a correlation peak in each axis."""
    x, y = loc
    dx = dy = 0.0
    if 0 < x < res.shape[1] - 1:
        a, b, c = res[y, x - 1], res[y, x], res[y, x + 1]
        den = a - 2 * b + c
        dx = 0.5 * (a - c) / den if den < 0 else 0.0
    if 0 < y < res.shape[0] - 1:
        a, b, c = res[y - 1, x], res[y, x], res[y + 1, x]
        den = a - 2 * b + c
        dy = 0.5 * (a - c) / den if den < 0 else 0.0
    return x + float(np.clip(dx, -0.5, 0.5)), y + float(np.clip(dy, -0.5, 0.5))


def ncc_locate(camera, landmark, *, n_rotations: int = 0, sigma: float = 1.5,
               landmark_gradient: np.ndarray | None = None) -> Located:
    """Find the camera image in the landmark image by NCC of gradient magnitudes.

    Parameters
    ----------
    camera : (h, w) or (h, w, 3) array
        Camera image (smaller than the landmark).
    landmark : (H, W) or (H, W, 3) array
    n_rotations : int
        0: no rotation search (the full camera image is the template). Otherwise the
        template is rotated by ``k * 360 / n_rotations`` degrees, k = 0..n-1, and only its
        inscribed square (side ``min(h, w) / sqrt(2)``) is correlated; the best peak wins.
    sigma : float
        Gaussian blur (px) before the Sobel derivatives.
    landmark_gradient : ndarray, optional
        Precomputed :func:`gradient_magnitude` of ``landmark`` (same ``sigma``).

    Returns
    -------
    Located
        Landmark pixel of the camera image's centre (pixel centres at integers).
    """
    gl = gradient_magnitude(landmark, sigma) if landmark_gradient is None else landmark_gradient
    gc = gradient_magnitude(camera, sigma)
    h, w = gc.shape
    cx, cy = 0.5 * (w - 1), 0.5 * (h - 1)
    if n_rotations <= 0:
        if h > gl.shape[0] or w > gl.shape[1]:
            return Located(reason="camera image larger than the landmark")
        res = cv2.matchTemplate(gl, gc, cv2.TM_CCOEFF_NORMED)
        _, peak, _, loc = cv2.minMaxLoc(res)
        x, y = _subpixel_peak(res, loc)
        return Located(x + cx, y + cy, float(peak))
    side = int(min(h, w) / math.sqrt(2.0)) - 2
    if side < 8 or side > min(gl.shape):
        return Located(reason=f"inscribed template of {side} px unusable")
    best = Located(reason="no peak")
    half = 0.5 * (side - 1)
    for k in range(n_rotations):
        deg = 360.0 * k / n_rotations
        # rotate the camera image about its centre, then cut the inscribed square
        m = cv2.getRotationMatrix2D((cx, cy), deg, 1.0)
        m[:, 2] += half - np.array([cx, cy])
        tpl = cv2.warpAffine(gc, m, (side, side), flags=cv2.INTER_LINEAR)
        res = cv2.matchTemplate(gl, tpl, cv2.TM_CCOEFF_NORMED)
        _, peak, _, loc = cv2.minMaxLoc(res)
        if np.isfinite(best.score) and peak <= best.score:
            continue
        x, y = _subpixel_peak(res, loc)
        # getRotationMatrix2D(+deg) turns the image CCW on screen: the camera is rotated
        # -deg with respect to the landmark
        best = Located(x + half, y + half, float(peak), rotation=-math.radians(deg))
    return best


def has_sift() -> bool:
    """Whether this OpenCV build has SIFT."""
    return hasattr(cv2, "SIFT_create")


def _detector(kind: str, n_features: int):
    if kind == "orb":
        return cv2.ORB_create(nfeatures=n_features), cv2.NORM_HAMMING
    if kind == "sift":
        if not has_sift():
            raise ValueError("this OpenCV has no SIFT")
        return cv2.SIFT_create(nfeatures=n_features), cv2.NORM_L2
    raise ValueError(f"unknown keypoint detector {kind!r}; use 'orb' or 'sift'")


def keypoint_features(image, kind: str = "orb", n_features: int = 2000):
    """Keypoints and descriptors of an image (e.g. a landmark region, computed once)."""
    det, _ = _detector(kind, n_features)
    return det.detectAndCompute(np.clip(_grey_f32(image), 0, 255).astype(np.uint8), None)


def keypoint_locate(camera, landmark, *, kind: str = "orb", n_features: int = 2000,
                    ratio: float = 0.8, ransac_px: float = 3.0,
                    landmark_features=None) -> Located:
    """Find the camera image in the landmark image with keypoints and a RANSAC homography.

    Parameters
    ----------
    camera, landmark : 2-D or RGB uint8 arrays
    kind : {"orb", "sift"}
    n_features : int
        Keypoints kept per image.
    ratio : float
        Lowe's ratio test on the two nearest descriptors.
    ransac_px : float
        RANSAC reprojection threshold (px).
    landmark_features : (keypoints, descriptors), optional
        Precomputed detection on ``landmark`` with the same settings.

    Returns
    -------
    Located
        ``score`` is the number of RANSAC inliers.
    """
    det, norm = _detector(kind, n_features)
    cam = np.clip(_grey_f32(camera), 0, 255).astype(np.uint8)
    kc, dc = det.detectAndCompute(cam, None)
    if landmark_features is None:
        land = np.clip(_grey_f32(landmark), 0, 255).astype(np.uint8)
        landmark_features = det.detectAndCompute(land, None)
    kl, dl = landmark_features
    if dc is None or dl is None or len(kc) < 4 or len(kl) < 4:
        return Located(reason="too few keypoints")
    pairs = cv2.BFMatcher(norm).knnMatch(dc, dl, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if len(good) < 4:
        return Located(reason=f"{len(good)} ratio-test matches")
    src = np.float32([kc[m.queryIdx].pt for m in good])
    dst = np.float32([kl[m.trainIdx].pt for m in good])
    hmat, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px)
    if hmat is None:
        return Located(reason="no homography")
    h, w = cam.shape
    c = hmat @ np.array([0.5 * (w - 1), 0.5 * (h - 1), 1.0])
    if abs(c[2]) < 1e-9:
        return Located(reason="degenerate homography")
    rot = math.atan2(-hmat[1, 0], hmat[0, 0])
    return Located(float(c[0] / c[2]), float(c[1] / c[2]), float(inl.sum()), rotation=rot)
