"""Drainage-pattern (crease) extraction: dissertation chapter 3.2.

Pipeline, array in / arrays out, no ROS:

1. :func:`prepare_input` turns a grey image (uint8/uint16/float) or a DEM into float32 with a
   known scale, fills nodata and estimates the noise level.
2. :func:`crease_diffusion`: crease-enhancing anisotropic diffusion (3.2.1, eq. 3.1-3.6). The
   diffusion tensor shares the eigenvectors of the multilocal normalised Hessian ``H_rho``; it
   diffuses with ``epsilon`` across the crease and ``alpha*mu_r + beta*mu_v`` along it, solved
   by K explicit steps of Weickert's standard 3x3 discretisation.
3. :func:`mlsec_st`: MLSEC-ST creaseness of Lopez et al. (3.2.2): minus the divergence of the
   normalised dominant structure-tensor direction, with the 8-neighbour discrete divergence.
   Positive on ridges (bright lines), negative on valleys (dark lines).
4. :func:`crease_mask` thresholds creaseness of one polarity (with hysteresis) where the
   crease contrast (:func:`crease_contrast`, a depth-like Hessian measure) exceeds a multiple
   of the estimated pixel noise, removes small components and fills small holes, and
   :func:`skeletonize_creases` thins it. Too little skeleton means "no drainage": flat,
   constant, lake, cloud or noise-only inputs give a reason instead of creases.

:class:`CreaseDetector` runs the whole chain with a validated :class:`CreaseParams`.

DEMs are processed directly (``source="dem"``): elevations divided by the GSD so that the
gradient is the slope and eq. 3.1's normalisation is the surface curvature; the terrain's
creases are the valleys of the elevation. When numba is installed the diffusion, MLSEC,
contrast and mask cleaning run on fused kernels (:mod:`._crease_kernels`), otherwise on
OpenCV/numpy passes; both agree to float32 rounding (the masks exactly). A
:class:`CreaseDetector` keeps its work buffers (:class:`Scratch`) from frame to frame.

Axis convention: ``x`` is the column (East), ``y`` the row (South) index; every operator
below is rotation invariant, so the choice only matters for the tensor components.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, fields

import cv2
import numpy as np
from skimage.morphology import skeletonize

from . import _crease_kernels as _kernels

__all__ = [
    "CreaseParams",
    "CreaseResult",
    "CreaseDetector",
    "Scratch",
    "prepare_input",
    "estimate_noise",
    "normalised_hessian",
    "diffusion_tensor",
    "diffusion_step",
    "crease_diffusion",
    "mlsec_st",
    "crease_contrast",
    "crease_mask",
    "skeletonize_creases",
]

POLARITIES = ("valley", "ridge", "both")
SOURCES = ("image", "dem")
# a frame without any contrast: what a camera sees of it
NO_DRAINAGE_CONSTANT = "no drainage: image is constant (cloud, water, haze or a covered lens)"

# Central first / second differences, applied separably by cv2.sepFilter2D.
_D1 = np.array([-0.5, 0.0, 0.5], np.float32)
_D2 = np.array([1.0, -2.0, 1.0], np.float32)
_ID = np.array([0.0, 1.0, 0.0], np.float32)
_K1 = np.array([-1.0, 0.0, 1.0], np.float32)
_BORDER = cv2.BORDER_REFLECT
_TINY = np.float32(1e-30)


def _check(cond: bool, msg: str):
    if not cond:
        raise ValueError(msg)


@dataclass(frozen=True)
class CreaseParams:
    """Settings of the crease extractor (defaults: dissertation Table 3.1).

    Parameters
    ----------
    iterations : int
        K, number of explicit diffusion steps (Table 3.1: 5). 0 disables diffusion.
    sigma, w1 : float, int
        Std and (odd) size of the Gaussian that smooths the image before the Hessian (1, 5).
    rho, w2 : float, int
        Std and (odd) size of the Gaussian that regularises the Hessian field (1, 3).
    epsilon : float
        Diffusivity across creases, in (0, 1) (0.001).
    alpha, beta : float
        Diffusivity along ridges / valleys, in [0, 1] (1, 1).
    time_step : float
        Explicit step tau; the standard discretisation is stable for tau <= 0.25 when the
        diffusivities are <= 1 (default 0.2).
    tensor_update : int
        Rebuild the diffusion tensor every this many steps (1: every step, as in the
        dissertation; larger is faster and slightly less adaptive).
    mlsec_sigma, mlsec_rho : float
        Derivative and integration scales (px) of the MLSEC-ST structure tensor.
    threshold : float
        Minimum creaseness (of the chosen polarity), in (0, 2]; MLSEC-ST lies in [-2, 2].
    threshold_low : float
        Hysteresis: pixels above this creaseness are kept when connected to pixels above
        ``threshold`` (set equal to ``threshold`` to disable), in (0, threshold].
    contrast_sigma : float
        Scale (px) at which crease contrast is compared with noise.
    contrast_snr : float
        A crease pixel needs a depth-like contrast (``contrast_sigma**2`` times the Hessian
        eigenvalue across it) of this many pixel-noise standard deviations. At the default
        of 1, white noise practically never passes (its response has a std of about
        ``0.12 noise`` at sigma 2), nor do one-grey-level quantisation steps (about 0.3);
        higher values also reject real but fine, rough texture (the noise estimate cannot
        tell pixel-scale relief from noise).
    min_area : int
        Crease components with fewer pixels are dropped; holes with fewer pixels are filled.
    min_crease_fraction : float
        If the skeleton is shorter than this fraction of ``rows + cols``, the image is
        declared to have no drainage.
    polarity : {"valley", "ridge", "both"}
        Which creases to extract; ridges are valleys of the inverted image.
    """

    iterations: int = 5
    sigma: float = 1.0
    w1: int = 5
    rho: float = 1.0
    w2: int = 3
    epsilon: float = 0.001
    alpha: float = 1.0
    beta: float = 1.0
    time_step: float = 0.2
    tensor_update: int = 1
    mlsec_sigma: float = 1.0
    mlsec_rho: float = 2.0
    threshold: float = 0.5
    threshold_low: float = 0.2
    contrast_sigma: float = 2.0
    contrast_snr: float = 1.0
    min_area: int = 20
    min_crease_fraction: float = 0.05
    polarity: str = "valley"

    def __post_init__(self):
        _check(isinstance(self.iterations, (int, np.integer)) and 0 <= self.iterations <= 1000,
               f"iterations must be an int in [0, 1000], got {self.iterations!r}")
        for name in ("sigma", "rho", "mlsec_sigma", "mlsec_rho", "contrast_sigma"):
            v = getattr(self, name)
            _check(np.isfinite(v) and 0 < v <= 64, f"{name} must be in (0, 64], got {v!r}")
        for name in ("w1", "w2"):
            v = getattr(self, name)
            _check(isinstance(v, (int, np.integer)) and v >= 1 and v % 2 == 1,
                   f"{name} must be a positive odd int, got {v!r}")
        _check(0 < self.epsilon < 1, f"epsilon must be in (0, 1), got {self.epsilon!r}")
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            _check(0 <= v <= 1, f"{name} must be in [0, 1], got {v!r}")
        _check(0 < self.time_step <= 0.25,
               f"time_step must be in (0, 0.25] for a stable explicit scheme, got "
               f"{self.time_step!r}")
        _check(isinstance(self.tensor_update, (int, np.integer)) and self.tensor_update >= 1,
               f"tensor_update must be an int >= 1, got {self.tensor_update!r}")
        _check(0 < self.threshold <= 2, f"threshold must be in (0, 2], got {self.threshold!r}")
        _check(0 < self.threshold_low <= self.threshold,
               f"threshold_low must be in (0, threshold], got {self.threshold_low!r}")
        _check(self.contrast_snr >= 0, f"contrast_snr must be >= 0, got {self.contrast_snr!r}")
        _check(isinstance(self.min_area, (int, np.integer)) and self.min_area >= 0,
               f"min_area must be an int >= 0, got {self.min_area!r}")
        _check(0 <= self.min_crease_fraction < 10,
               f"min_crease_fraction must be in [0, 10), got {self.min_crease_fraction!r}")
        _check(self.polarity in POLARITIES,
               f"polarity must be one of {POLARITIES}, got {self.polarity!r}")

    @classmethod
    def from_dict(cls, values: dict) -> CreaseParams:
        """Build from a mapping (e.g. ROS parameters), rejecting unknown keys."""
        names = {f.name for f in fields(cls)}
        unknown = set(values) - names
        _check(not unknown, f"unknown crease parameter(s): {sorted(unknown)}")
        return cls(**values)


class Scratch:
    """Whole-image work buffers kept from call to call, by name.

    Fresh memory is page-faulted in on first touch, which can cost more than the passes
    that fill it (tens of ms per 16 MB in some virtual machines); a detector keeps one
    ``Scratch`` so that repeated frames of one size reuse their intermediates. Results are
    never taken from it (the caller keeps them). Not shared between threads: while one
    thread has :meth:`borrow`-ed it, another one gets a fresh, throw-away ``Scratch``.
    """

    def __init__(self):
        self._buffers = {}
        self._lock = threading.Lock()

    def get(self, name: str, shape, dtype=np.float32) -> np.ndarray:
        """The uninitialised buffer ``name`` with this shape and dtype."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape != tuple(shape) or buf.dtype != dtype:
            buf = self._buffers[name] = np.empty(shape, dtype)
        return buf

    @contextmanager
    def borrow(self):
        """This scratch, or a fresh one if another thread is using it."""
        if not self._lock.acquire(blocking=False):
            yield Scratch()
            return
        try:
            yield self
        finally:
            self._lock.release()


# --------------------------------------------------------------------------- preprocessing


def estimate_noise(image: np.ndarray, valid_mask: np.ndarray | None = None, *,
                   scratch: Scratch | None = None) -> float:
    """Robust standard deviation of white noise in ``image``.

    Immerkaer's 3x3 operator (the difference of two Laplacians) cancels planes and most
    smooth structure; the median of its absolute response is robust to edges and creases.

    Parameters
    ----------
    image : (M, N) float array
    valid_mask : (M, N) bool array, optional
    scratch : Scratch, optional
        Reusable work buffers.

    Returns
    -------
    float
        Noise std in image units (0 for a noiseless image).
    """
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    image = np.asarray(image, np.float32)
    resp = cv2.filter2D(image, cv2.CV_32F, kernel, borderType=_BORDER,
                        dst=(scratch or Scratch()).get("noise_response", image.shape))
    # A regular subsample of ~65k responses is plenty for a median.
    k = max(2, int(np.sqrt(resp.size / 65536)))
    resp = np.abs(resp[1:-1:k, 1:-1:k])
    if valid_mask is not None and not valid_mask.all():
        # Only responses whose whole 3x3 support is valid.
        ok = cv2.erode(valid_mask.astype(np.uint8), np.ones((3, 3), np.uint8))[1:-1:k, 1:-1:k]
        resp = resp[ok.astype(bool)]
    if resp.size == 0:
        return 0.0
    # |N|^2 sums to 36, and median|X| = 0.6745 std for Gaussian X.
    return float(_median(resp)) / (0.6745 * 6.0)


def _median(values: np.ndarray) -> np.floating:
    """np.median of a 1-D array (same value), with one partition instead of two."""
    values = np.ravel(values)
    half = values.size // 2
    part = np.partition(values, half)
    if values.size % 2:
        return part[half]
    # np.median averages the two middle values in the array's dtype.
    return (part[:half].max() + part[half]) / values.dtype.type(2)


def _fill_nodata(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid pixels by their nearest valid value (keeps creases out of voids)."""
    from scipy.ndimage import distance_transform_edt

    idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return image[tuple(idx)]


#: Fewest pixels across an image or DEM that creases are looked for in (the diffusion's
#: derivatives need 2; below a few there is no valley to see).
MIN_SIDE = 3


def prepare_input(image, valid_mask=None, source: str = "image", gsd: float = 1.0,
                  nodata=None, *, scratch: Scratch | None = None):
    """Convert an image or DEM to float32 ready for crease extraction.

    Grey images are scaled so that their 1st-99th percentile range maps to [0, 1]; DEMs are
    divided by the ground sample distance so that elevations are in pixel units and the
    gradient is the dimensionless slope, which makes the normalisation of eq. 3.1 the
    curvature of the terrain surface.

    Parameters
    ----------
    image : (M, N) array
        Grey image (uint8, uint16, float) or elevation grid (metres). A colour (M, N, 3/4)
        image is converted to grey.
    valid_mask : (M, N) bool array, optional
        False where there is no data. NaNs and ``nodata`` values are added to it.
    source : {"image", "dem"}
    gsd : float
        Ground sample distance (m/px), only used for DEMs.
    nodata : float, optional
        Value marking voids (e.g. -32768 in SRTM).
    scratch : Scratch, optional
        Reusable work buffers.

    Returns
    -------
    work : (M, N) float32 array
        Scaled image, voids filled with the nearest valid value.
    valid : (M, N) bool array
    noise : float
        Noise std of ``work`` (white noise estimate, floored by the quantisation step).
    reason : str
        Non-empty when the input cannot carry creases (e.g. constant).
    """
    _check(source in SOURCES, f"source must be one of {SOURCES}, got {source!r}")
    _check(np.isfinite(gsd) and gsd > 0, f"gsd must be positive, got {gsd!r}")
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        if img.dtype not in (np.uint8, np.uint16, np.float32):
            img = img.astype(np.float32)
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    _check(img.ndim == 2, f"expected a 2-D image, got shape {img.shape}")
    _check(img.dtype.kind in "uifb", f"unsupported dtype {img.dtype}")
    integer = img.dtype.kind in "uib"
    work = img.astype(np.float32)
    valid = np.isfinite(work)
    if valid_mask is not None:
        vm = np.asarray(valid_mask, bool)
        _check(vm.shape == img.shape, "valid_mask must have the image's shape")
        valid &= vm
    if nodata is not None:
        valid &= work != np.float32(nodata)
    if img.size == 0 or np.count_nonzero(valid) < 16:
        return np.zeros(img.shape, np.float32), valid, 0.0, "no valid pixels"
    if min(img.shape) < MIN_SIDE:
        return (np.zeros(img.shape, np.float32), valid, 0.0,
                f"image of {img.shape[0]}x{img.shape[1]} px: too narrow for creases (at least "
                f"{MIN_SIDE} px each way)")
    if not valid.all():
        work = _fill_nodata(work, valid)
    # Robust range from a subsample: percentiles need no more than ~65k values.
    step = max(1, int(np.sqrt(img.size / 65536)))
    values = work[::step, ::step][valid[::step, ::step]]
    if values.size < 16:
        values = work[valid]
    if source == "dem":
        scale = 1.0 / gsd
        quant = 1.0 if integer else 0.0
    else:
        lo, hi = np.percentile(values, (1.0, 99.0))
        if hi - lo <= 0:
            lo, hi = float(values.min()), float(values.max())
        if hi - lo <= 0:
            return np.zeros(img.shape, np.float32), valid, 0.0, NO_DRAINAGE_CONSTANT
        scale = 1.0 / (hi - lo)
        work -= np.float32(lo)  # work is this function's own copy
        quant = 1.0 if integer else 0.0
    work *= np.float32(scale)
    if source == "image":
        # far outside the stretch: saturated, or an undeclared float sentinel (3e38), whose
        # span would set the noise floor above every crease of the frame
        np.clip(work, -1.0, 2.0, out=work)
    # Voids hold copies of valid values, so the range over all pixels is the valid range.
    span = float(work.max() - work.min())
    if span == 0.0:
        return work, valid, 0.0, NO_DRAINAGE_CONSTANT
    noise = estimate_noise(work, valid, scratch=scratch)
    # Quantisation noise (step/sqrt(12)) is a floor: a smooth integer image is not noiseless.
    noise = max(noise, quant * scale / np.sqrt(12.0), 1e-6 * span)
    return work, valid, float(noise), ""


# --------------------------------------------------------------------------- diffusion


def _derivatives(img: np.ndarray):
    """Central-difference gradient and Hessian (x = column, y = row)."""
    ix = cv2.sepFilter2D(img, cv2.CV_32F, _D1, _ID, borderType=_BORDER)
    iy = cv2.sepFilter2D(img, cv2.CV_32F, _ID, _D1, borderType=_BORDER)
    ixx = cv2.sepFilter2D(img, cv2.CV_32F, _D2, _ID, borderType=_BORDER)
    iyy = cv2.sepFilter2D(img, cv2.CV_32F, _ID, _D2, borderType=_BORDER)
    ixy = cv2.sepFilter2D(img, cv2.CV_32F, _D1, _D1, borderType=_BORDER)
    return ix, iy, ixx, ixy, iyy


def _gauss(img: np.ndarray, sigma: float, size: int | None = None, dst=None) -> np.ndarray:
    if size is None:
        size = 2 * int(np.ceil(3 * sigma)) + 1
    return cv2.GaussianBlur(img, (size, size), sigma, dst=dst, borderType=_BORDER)


def normalised_hessian(img: np.ndarray, params: CreaseParams, out=None):
    """Multilocal normalised Hessian H_rho of eq. 3.2.

    Parameters
    ----------
    img : (M, N) float32 array
    params : CreaseParams
    out : _Workspace, optional
        Preallocated buffers (avoids page faults on large images).

    Returns
    -------
    hxx, hxy, hyy : (M, N) float32 arrays
    """
    ws = out if out is not None else _Workspace(img.shape)
    sm = cv2.GaussianBlur(img, (params.w1, params.w1), params.sigma, dst=ws["sm"],
                          borderType=_BORDER)
    ix = cv2.sepFilter2D(sm, cv2.CV_32F, _D1, _ID, dst=ws["ix"], borderType=_BORDER)
    iy = cv2.sepFilter2D(sm, cv2.CV_32F, _ID, _D1, dst=ws["iy"], borderType=_BORDER)
    # r = sqrt(1 + |grad I_sigma|^2), the normalisation of eq. 3.1.
    r = np.multiply(ix, ix, out=ws["r"])
    cv2.accumulateSquare(iy, r)
    r += 1.0
    cv2.sqrt(r, dst=r)
    hs = []
    for name, kx, ky in (("hxx", _D2, _ID), ("hxy", _D1, _D1), ("hyy", _ID, _D2)):
        h = cv2.sepFilter2D(sm, cv2.CV_32F, kx, ky, dst=ws["tmp"], borderType=_BORDER)
        cv2.divide(h, r, dst=h)
        hs.append(cv2.GaussianBlur(h, (params.w2, params.w2), params.rho, dst=ws[name],
                                   borderType=_BORDER))
    return tuple(hs)


def diffusion_tensor(hxx, hxy, hyy, params: CreaseParams, out=None):
    """Crease diffusion tensor D = [[a, b], [b, c]] from H_rho (eq. 3.3-3.5).

    ``kappa_1`` is the Hessian eigenvalue of largest magnitude and ``v1`` its eigenvector
    (across the crease). With ``s = kappa_+ - kappa_-`` and ``t = kappa_+ + kappa_-``, the
    descriptor of eq. 3.3/3.4 is ``mu = min(s, |t|) / max(s, |t|)``, the sign of ``t`` is the
    sign of ``kappa_1`` (valley where positive) and ``v1 v1^T = (I + sign(t) R / s) / 2`` with
    ``R = [[hxx - hyy, 2 hxy], [2 hxy, hyy - hxx]]``, so no trigonometry is needed:
    ``D = lam2 I + (epsilon - lam2) v1 v1^T``, ``lam2 = alpha mu_r + beta mu_v``.
    """
    ws = out if out is not None else _Workspace(hxx.shape)
    t = np.add(hxx, hyy, out=ws["t"])
    d = np.subtract(hxx, hyy, out=ws["d"])
    h2 = np.multiply(hxy, 2.0, out=ws["h2"])
    s = cv2.magnitude(d, h2, magnitude=ws["s"])
    at = np.abs(t, out=ws["at"])
    mx = np.maximum(s, at, out=ws["mx"])
    np.maximum(mx, _TINY, out=mx)  # mu = 0 where the Hessian vanishes
    mu = cv2.divide(np.minimum(s, at, out=ws["mn"]), mx, dst=ws["mu"])
    if params.alpha != params.beta:
        w = np.where(t > 0, np.float32(params.beta), np.float32(params.alpha))
        lam2 = np.multiply(mu, w, out=mu)
        m = np.multiply(lam2, 0.5, out=ws["m"])
        m += 0.5 * params.epsilon
        g = np.multiply(lam2, -0.5, out=ws["g"])
        g += 0.5 * params.epsilon
    else:
        m = cv2.addWeighted(mu, 0.5 * params.alpha, mu, 0.0, 0.5 * params.epsilon,
                            dst=ws["m"])
        g = cv2.addWeighted(mu, -0.5 * params.alpha, mu, 0.0, 0.5 * params.epsilon,
                            dst=ws["g"])
    # g = (epsilon - lam2) / 2 * sign(t) / s
    np.multiply(g, t, out=g)
    den = np.multiply(at, s, out=at)
    cv2.divide(g, np.maximum(den, _TINY, out=den), dst=g)
    gd = np.multiply(g, d, out=ws["gd"])
    a = np.add(m, gd, out=ws["a"])
    c = np.subtract(m, gd, out=ws["c"])
    b = np.multiply(g, h2, out=ws["b"])
    return a, b, c


def diffusion_step(u: np.ndarray, a, b, c, tau: float, out=None) -> np.ndarray:
    """One explicit step ``u + tau div(D grad u)`` in place, Weickert's standard scheme.

    Pure second-order terms use fluxes through pixel faces with averaged diffusivities;
    mixed terms use central differences of central differences. Fluxes through the image
    border are zero (Neumann), so the mean grey value is preserved.
    """
    ws = out if out is not None else _Workspace(u.shape)
    div = ws["div"]
    cols = u.shape[1]
    # On the flattened (contiguous) arrays a shift by 1 is a shift by one column and a
    # shift by ``cols`` one row: contiguous operands run faster than 2-D slices.
    d, uf, af, cf = div.reshape(-1), u.reshape(-1), a.reshape(-1), c.reshape(-1)
    # x faces: flux (a_i + a_{i+1}) (u_{i+1} - u_i), i.e. twice the true flux; none through
    # the east border (which the flat shift would wrap to the next row).
    fx = np.add(af[1:], af[:-1], out=ws["fx"])
    fx *= np.subtract(uf[1:], uf[:-1], out=ws["gx"])
    fx[cols - 1::cols] = 0.0
    d[-1] = 0.0
    d[:-1] = fx
    d[1:] -= fx
    fy = np.add(cf[cols:], cf[:-cols], out=ws["fy"])
    fy *= np.subtract(uf[cols:], uf[:-cols], out=ws["gy"])
    d[:-cols] += fy
    d[cols:] -= fy
    # Mixed terms, also doubled: D1x(b * 2 u_y) + D1y(b * 2 u_x).
    tmp = ws["tmp"]
    uy2 = cv2.sepFilter2D(u, cv2.CV_32F, _ID, _K1, dst=ws["ux"], borderType=cv2.BORDER_REPLICATE)
    np.multiply(uy2, b, out=uy2)
    div += cv2.sepFilter2D(uy2, cv2.CV_32F, _D1, _ID, dst=tmp, borderType=cv2.BORDER_CONSTANT)
    ux2 = cv2.sepFilter2D(u, cv2.CV_32F, _K1, _ID, dst=ws["ux"], borderType=cv2.BORDER_REPLICATE)
    np.multiply(ux2, b, out=ux2)
    div += cv2.sepFilter2D(ux2, cv2.CV_32F, _ID, _D1, dst=tmp, borderType=cv2.BORDER_CONSTANT)
    return cv2.scaleAdd(div, 0.5 * tau, u, dst=u)


class _Workspace(dict):
    """Lazily allocated float32 buffers of one image shape, reused across iterations."""

    def __init__(self, shape):
        super().__init__()
        self.shape = tuple(shape)

    def __missing__(self, key):
        rows, cols = self.shape
        shape = {"fx": (rows * cols - 1,), "gx": (rows * cols - 1,),
                 "fy": ((rows - 1) * cols,), "gy": ((rows - 1) * cols,)}.get(key, self.shape)
        buf = self[key] = np.empty(shape, np.float32)
        return buf


def crease_diffusion(img: np.ndarray, params: CreaseParams | None = None, *,
                     scratch: Scratch | None = None) -> np.ndarray:
    """K explicit steps of crease-enhancing diffusion dI/dt = div(D grad I) (eq. 3.6).

    The tensor is rebuilt from the evolving image every ``params.tensor_update`` steps
    (1, the default, is the nonlinear diffusion of the dissertation; larger values trade
    fidelity for speed: the tensor costs two thirds of a step). With numba installed the
    default runs on a fused kernel (``_crease_kernels``), otherwise on OpenCV/numpy passes
    in cache-sized strips; both give the same result to float32 rounding.

    Parameters
    ----------
    img : (M, N) array, M, N >= 2
    params : CreaseParams, optional
    scratch : Scratch, optional
        Reusable work buffers (see :class:`Scratch`).

    Returns
    -------
    (M, N) float32 array
    """
    params = params or CreaseParams()
    scratch = scratch or Scratch()
    img = np.asarray(img)
    _check(img.ndim == 2 and min(img.shape) >= 2, f"need a 2-D image of >= 2x2, got {img.shape}")
    if params.tensor_update == 1:
        if _kernels.HAVE_NUMBA and min(img.shape) > max(2, params.w2 // 2):
            return _diffusion_fused(img, params, scratch)
        return _diffusion_in_strips(np.array(img, np.float32, order="C"), params,
                                    scratch=scratch)
    u = np.array(img, dtype=np.float32, copy=True, order="C")
    ws = _Workspace(u.shape)
    for k in range(params.iterations):
        if k % params.tensor_update == 0:
            a, b, c = diffusion_tensor(*normalised_hessian(u, params, ws), params, ws)
        diffusion_step(u, a, b, c, params.time_step, ws)
    return u


def _diffusion_fused(img: np.ndarray, params: CreaseParams, scratch: Scratch | None = None):
    """The same iteration with the fused numba kernel of :mod:`._crease_kernels`."""
    scratch = scratch or Scratch()
    out = np.empty(img.shape, np.float32)
    sm = scratch.get("diffusion_smooth", img.shape)
    # Ping-pong between the result and a scratch buffer, starting where an even number of
    # steps ends in the result.
    pair = [out, scratch.get("diffusion_step", img.shape)]
    cur = params.iterations % 2
    pair[cur][...] = img
    f = np.float32
    # OpenCV's own taps, so that the fused Gaussian matches cv2.GaussianBlur.
    taps = cv2.getGaussianKernel(params.w2, params.rho, cv2.CV_32F).ravel()
    for _ in range(params.iterations):
        u, nxt = pair[cur], pair[1 - cur]
        cv2.GaussianBlur(u, (params.w1, params.w1), params.sigma, dst=sm, borderType=_BORDER)
        _kernels.diffusion_step_kernel(u, sm, taps, f(params.epsilon), f(params.alpha),
                                       f(params.beta), f(params.time_step), nxt)
        cur = 1 - cur
    return out


def _diffusion_in_strips(u: np.ndarray, params: CreaseParams, rows: int | None = None,
                         scratch: Scratch | None = None):
    """Same result as the whole-image iteration, computed in horizontal strips.

    Each step is evaluated strip by strip on the strip plus a halo as wide as the whole
    stencil (Gaussian w1, derivatives, Gaussian w2, the step's mixed terms), so the strip
    rows are exact; strips of ~128k pixels keep the ~20 work buffers in cache, which is
    25-35% faster than whole-image passes from 1024^2 up.
    """
    height, width = u.shape
    halo = params.w1 // 2 + 1 + params.w2 // 2 + 2
    rows = rows or max(32, 131072 // width)
    if rows >= height:
        rows = height
    spaces = {}
    nxt = (scratch or Scratch()).get("diffusion_step", u.shape)
    for _ in range(params.iterations):
        for r0 in range(0, height, rows):
            r1 = min(height, r0 + rows)
            a0, a1 = max(0, r0 - halo), min(height, r1 + halo)
            sub = u[a0:a1]
            ws = spaces.get(sub.shape)
            if ws is None:
                ws = spaces[sub.shape] = _Workspace(sub.shape)
            a, b, c = diffusion_tensor(*normalised_hessian(sub, params, ws), params, ws)
            tmp = ws["u"]
            tmp[...] = sub
            diffusion_step(tmp, a, b, c, params.time_step, ws)
            nxt[r0:r1] = tmp[r0 - a0:r1 - a0]
        u, nxt = nxt, u
    if params.iterations % 2:  # the result is in the scratch buffer
        nxt[...] = u
        u = nxt
    return u


# --------------------------------------------------------------------------- MLSEC


def _scratch_buffers(scratch: Scratch | None, prefix: str, shape, names, dtype=np.float32):
    """Named float32 buffers of one shape from ``scratch`` (fresh ones without it)."""
    scratch = scratch or Scratch()
    return {k: scratch.get(f"{prefix}_{k}", shape, dtype) for k in names}


def _neighbour_kernels():
    """3x3 kernels giving sum_k n_k . w(P_k) over the 8 neighbours (unit normals n_k)."""
    kx = np.zeros((3, 3), np.float32)
    ky = np.zeros((3, 3), np.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx or dy:
                n = np.hypot(dx, dy)
                kx[dy + 1, dx + 1] = dx / n
                ky[dy + 1, dx + 1] = dy / n
    return kx, ky


_NKX, _NKY = _neighbour_kernels()


def mlsec_st(img: np.ndarray, sigma_d: float = 1.0, sigma_i: float = 2.0, *,
             scratch: Scratch | None = None) -> np.ndarray:
    """MLSEC-ST creaseness (Lopez et al. 2000), in [-2, 2].

    The gradient at scale ``sigma_d`` builds a structure tensor smoothed at ``sigma_i``; its
    dominant eigenvector, signed like the local gradient, is a unit field ``w`` that stays
    coherent across creases. Creaseness is ``-(d/r) sum_k n_k . w(P_k)`` over the r = 8
    neighbours (the discrete -div w): positive on ridges (bright lines), negative on valleys.
    ``scratch`` (optional) provides reusable work buffers.
    """
    img = np.asarray(img, np.float32)
    if _kernels.HAVE_NUMBA:
        buf = _scratch_buffers(scratch, "mlsec", img.shape,
                               ("smooth", "gx", "gy", "pxx", "pxy", "pyy", "wy"))
        smooth = _gauss(img, sigma_d, dst=buf["smooth"])
        gx, gy, pxx, pxy, pyy = (buf[k] for k in ("gx", "gy", "pxx", "pxy", "pyy"))
        _kernels.gradient_products_kernel(smooth, gx, gy, pxx, pxy, pyy)
        # Structure tensor in the buffers freed one by one (OpenCV copies the source of an
        # in-place blur); the field's outputs must not alias its inputs, or the kernel
        # does not vectorise.
        sxx = _gauss(pxx, sigma_i, dst=smooth)
        sxy = _gauss(pxy, sigma_i, dst=pxx)
        syy = _gauss(pyy, sigma_i, dst=pxy)
        wx, wy = pyy, buf["wy"]
        _kernels.mlsec_field_kernel(sxx, sxy, syy, gx, gy, wx, wy)
        out = np.empty_like(smooth)
        _kernels.mlsec_divergence_kernel(wx, wy, out)
        return out
    smooth = _gauss(img, sigma_d)
    gx = cv2.sepFilter2D(smooth, cv2.CV_32F, _D1, _ID, borderType=_BORDER)
    gy = cv2.sepFilter2D(smooth, cv2.CV_32F, _ID, _D1, borderType=_BORDER)
    sxx = _gauss(gx * gx, sigma_i)
    sxy = _gauss(gx * gy, sigma_i)
    syy = _gauss(gy * gy, sigma_i)
    dev = sxx - syy
    s = np.sqrt(dev * dev + 4.0 * sxy * sxy)
    # Dominant eigenvector (cos phi, sin phi) via half-angle formulas, no atan2.
    cos2 = dev / np.maximum(s, np.float32(1e-30))
    wx = np.sqrt(np.maximum(0.5 * (1.0 + cos2), 0.0))
    wy = np.sqrt(np.maximum(0.5 * (1.0 - cos2), 0.0))
    wy[sxy < 0] *= -1.0
    sign = np.sign(wx * gx + wy * gy)
    # No orientation where the tensor is numerically zero (flat areas).
    sign[s <= 1e-12 * max(float(s.max()), 1e-30)] = 0.0
    wx = (wx * sign).astype(np.float32)
    wy = (wy * sign).astype(np.float32)
    acc = cv2.filter2D(wx, cv2.CV_32F, _NKX, borderType=_BORDER)
    acc += cv2.filter2D(wy, cv2.CV_32F, _NKY, borderType=_BORDER)
    return np.float32(-2.0 / 8.0) * acc


def crease_contrast(img: np.ndarray, sigma: float = 2.0, *,
                    scratch: Scratch | None = None) -> np.ndarray:
    """Depth-like crease contrast: ``sigma**2`` times the signed Hessian eigenvalue of
    largest magnitude at scale ``sigma``.

    Positive on valleys (dark lines), negative on ridges. For a Gaussian-profile valley of
    depth A and width ``sigma`` it is about ``0.35 A``, so it compares directly with the
    pixel noise. ``scratch`` (optional) provides reusable work buffers.
    """
    img = np.asarray(img, np.float32)
    smooth = _gauss(img, sigma, dst=(scratch or Scratch()).get("contrast_smooth", img.shape))
    if _kernels.HAVE_NUMBA:
        out = np.empty_like(smooth)
        _kernels.contrast_kernel(smooth, np.float32(sigma**2), out)
        return out
    _, _, ixx, ixy, iyy = _derivatives(smooth)
    tr = ixx + iyy
    s = np.sqrt((ixx - iyy) ** 2 + 4.0 * ixy * ixy)
    return np.float32(0.5 * sigma**2) * (tr + np.sign(tr) * s)


def crease_mask(creaseness, contrast, noise: float, params: CreaseParams,
                polarity: str = "valley", valid=None, *,
                scratch: Scratch | None = None) -> np.ndarray:
    """Binary crease mask of one polarity, thresholded and cleaned.

    A pixel is a crease if its MLSEC-ST creaseness of that polarity exceeds
    ``params.threshold`` *and* its contrast (:func:`crease_contrast`) exceeds
    ``contrast_snr`` pixel-noise standard deviations: MLSEC is contrast invariant, so
    without the second test noise, quantisation steps and flat areas would make creases.
    Components smaller than ``min_area`` are dropped and holes smaller than ``min_area``
    filled (they would become loops in the skeleton). ``scratch`` (optional) provides
    reusable work buffers.
    """
    _check(polarity in ("valley", "ridge"), f"polarity must be valley or ridge: {polarity!r}")
    scratch = scratch or Scratch()
    sgn = np.float32(-1.0 if polarity == "valley" else 1.0)
    mask, seed = _thresholds(creaseness, contrast, valid, sgn, params.contrast_snr * noise,
                             params, scratch)
    if not mask.any():
        return mask.view(bool)
    # One labelling for both tests. Hysteresis: weak creases survive where connected to
    # strong ones, which closes the gaps MLSEC leaves at confluences (ambiguous flow
    # direction); and components must have min_area pixels.
    # Block-based labelling (BBDT) is the fastest OpenCV offers for 8-connectivity.
    n, labels = cv2.connectedComponentsWithAlgorithm(
        mask, 8, cv2.CV_32S, cv2.CCL_BBDT, labels=scratch.get("mask_labels", mask.shape, np.int32))
    use_seed = params.threshold_low < params.threshold
    if _kernels.HAVE_NUMBA:
        # The kernel counts the areas itself: labelling without stats is faster.
        mask = _kernels.keep_components_kernel(labels, n, seed, use_seed, params.min_area,
                                               mask)
    else:
        area = np.bincount(labels.reshape(-1), minlength=n)
        keep = area >= params.min_area
        if use_seed:
            keep &= np.bincount(labels[seed.view(bool)], minlength=n) > 0
        keep[0] = False
        mask = keep[labels].view(np.uint8)
    if params.min_area > 1:
        _fill_small_holes(mask, params.min_area, scratch)
    return mask.view(bool)


def _thresholds(creaseness, contrast, valid, sgn, gate: float, params: CreaseParams,
                scratch: Scratch):
    """uint8 masks: candidate crease pixels (contrast above ``gate``, creaseness above
    ``threshold_low``, valid) and, among them, the hysteresis seeds (above ``threshold``)."""
    if _kernels.HAVE_NUMBA:
        mask = np.empty(creaseness.shape, np.uint8)
        seed = scratch.get("mask_seed", creaseness.shape, np.uint8)
        use_valid = valid is not None
        va = np.ascontiguousarray(valid) if use_valid else np.ones((1, 1), bool)
        _kernels.crease_threshold_kernel(np.ascontiguousarray(creaseness),
                                         np.ascontiguousarray(contrast), va, use_valid, sgn,
                                         np.float32(gate), np.float32(params.threshold_low),
                                         np.float32(params.threshold), mask, seed)
        return mask, seed
    strong = -sgn * contrast > gate
    if valid is not None:
        strong &= valid
    score = sgn * creaseness
    mask = strong & (score > params.threshold_low)
    return mask.view(np.uint8), (mask & (score > params.threshold)).view(np.uint8)


def _fill_small_holes(mask: np.ndarray, min_area: int, scratch: Scratch) -> np.ndarray:
    """Set, in place, the 4-connected holes (background components) of a uint8 mask that
    have fewer than ``min_area`` pixels."""
    if _kernels.HAVE_NUMBA:
        state = scratch.get("mask_hole_state", mask.shape, np.uint8)
        state.fill(0)
        return _kernels.fill_small_holes_kernel(mask, min_area, state)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(1 - mask, connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] < min_area
    small[0] = False  # label 0: the mask itself
    mask |= small[labels].view(np.uint8)
    return mask


def skeletonize_creases(mask: np.ndarray) -> np.ndarray:
    """One-pixel-wide 8-connected skeleton of a crease mask (bool)."""
    if not mask.any():
        return np.zeros(mask.shape, bool)
    return skeletonize(mask)


# --------------------------------------------------------------------------- detector


@dataclass
class CreaseResult:
    """Everything the crease stage produced (all arrays have the input's shape).

    ``skeletons`` and ``masks`` map polarity ("valley"/"ridge") to bool arrays; ``reason``
    is non-empty when no drainage was found; ``timings`` are seconds per stage.
    """

    work: np.ndarray
    valid: np.ndarray
    noise: float
    diffused: np.ndarray
    creaseness: np.ndarray
    contrast: np.ndarray
    masks: dict = field(default_factory=dict)
    skeletons: dict = field(default_factory=dict)
    reason: str = ""
    timings: dict = field(default_factory=dict)

    def skeleton(self) -> np.ndarray | None:
        """One-pixel creases of every polarity as one boolean image (a copy: the result's
        buffers are reused by the next frame); None when no crease was found."""
        if not self.skeletons:
            return None
        out = np.zeros(self.work.shape, bool)
        for s in self.skeletons.values():
            out |= s
        return out

    def crease_image(self) -> np.ndarray:
        """uint8 debug image: 255 on skeleton pixels, 128 on other crease pixels."""
        out = np.zeros(self.work.shape, np.uint8)
        for m in self.masks.values():
            out[m] = 128
        for s in self.skeletons.values():
            out[s] = 255
        return out


class CreaseDetector:
    """Crease extraction with fixed settings (scikit-image style: settings in the constructor).

    Parameters
    ----------
    params : CreaseParams, optional

    Examples
    --------
    >>> det = CreaseDetector(CreaseParams(polarity="valley"))
    >>> res = det(np.random.default_rng(0).normal(size=(64, 64)))
    >>> res.reason != ""  # pure noise: no drainage
    True
    """

    def __init__(self, params: CreaseParams | None = None):
        self.params = params or CreaseParams()
        self.scratch = Scratch()

    def __call__(self, image, valid_mask=None, source: str = "image", gsd: float = 1.0,
                 nodata=None, *, scratch: Scratch | None = None) -> CreaseResult:
        """Creases of one raster; ``scratch``: work buffers to use instead of the
        detector's own (e.g. a caller's that it has already borrowed)."""
        if scratch is not None:
            return self._detect(image, valid_mask, source, gsd, nodata, scratch)
        with self.scratch.borrow() as own:
            return self._detect(image, valid_mask, source, gsd, nodata, own)

    def _detect(self, image, valid_mask, source, gsd, nodata, scratch: Scratch):
        p = self.params
        t = {}
        t0 = time.perf_counter()
        work, valid, noise, reason = prepare_input(image, valid_mask, source, gsd, nodata,
                                                   scratch=scratch)
        t["prepare"] = time.perf_counter() - t0
        zeros = np.zeros(work.shape, np.float32)
        if reason:
            return CreaseResult(work, valid, noise, work, zeros, zeros, reason=reason, timings=t)
        t0 = time.perf_counter()
        diffused = crease_diffusion(work, p, scratch=scratch)
        t["diffusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        creaseness = mlsec_st(diffused, p.mlsec_sigma, p.mlsec_rho, scratch=scratch)
        t["mlsec"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        contrast = crease_contrast(work, p.contrast_sigma, scratch=scratch)
        polarities = ("valley", "ridge") if p.polarity == "both" else (p.polarity,)
        masks = {pol: crease_mask(creaseness, contrast, noise, p, pol, valid, scratch=scratch)
                 for pol in polarities}
        t["mask"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        skels = {pol: skeletonize_creases(m) for pol, m in masks.items()}
        t["skeleton"] = time.perf_counter() - t0
        length = sum(int(s.sum()) for s in skels.values())
        if length < p.min_crease_fraction * sum(work.shape):
            reason = (f"no drainage: {length} crease px above {p.contrast_snr:g} x noise "
                      f"(need {p.min_crease_fraction * sum(work.shape):.0f}): flat terrain, "
                      "water, cloud or haze")
        return CreaseResult(work, valid, noise, diffused, creaseness, contrast, masks, skels,
                            reason, t)
