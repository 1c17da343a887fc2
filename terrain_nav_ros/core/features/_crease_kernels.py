"""Optional fused (numba) kernels for the crease-enhancing diffusion of :mod:`.creases`.

The numpy/OpenCV implementation in :mod:`.creases` needs ~55 whole-image passes per
diffusion step; these kernels compute the same discretisation in one pass (normalised
Hessian, its Gaussian, tensor and step, strip by strip) after OpenCV's first Gaussian,
which is several times faster. They are used
when numba is importable and ``TERRAIN_NAV_NO_NUMBA`` is not set; results agree with the
numpy path to float32 rounding (``test_creases.py`` checks it).
"""

from __future__ import annotations

import numpy as np

from .. import _numba
from .._numba import njit

# This module's switch: the callers test it, and tests turn it off per module.
HAVE_NUMBA = _numba.HAVE_NUMBA

_JIT = dict(cache=True, fastmath=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _hess_px(s0, sm_, sp, jm, j, jp, hxx, hxy, hyy):
    f = np.float32
    ix = f(0.5) * (s0[jp] - s0[jm])
    iy = f(0.5) * (sp[j] - sm_[j])
    inv = f(1.0) / np.sqrt(f(1.0) + ix * ix + iy * iy)
    hxx[j] = (s0[jp] - f(2.0) * s0[j] + s0[jm]) * inv
    hyy[j] = (sp[j] - f(2.0) * s0[j] + sm_[j]) * inv
    hxy[j] = f(0.25) * (sp[jp] - sp[jm] - sm_[jp] + sm_[jm]) * inv


@njit(**_JIT)
def _hessian_row(sm, i, rxx, rxy, ryy):
    """Row ``i`` of H / sqrt(1 + |grad|^2) of a smoothed image by central differences
    (eq. 3.1); borders reflect like OpenCV's BORDER_REFLECT (pixel -1 is pixel 0)."""
    f = np.float32
    rows, cols = sm.shape
    s0 = sm[i]
    sm_ = sm[max(i - 1, 0)]
    sp = sm[min(i + 1, rows - 1)]
    # Row views with non-negative indices: the interior loop vectorises.
    for j in range(1, cols - 1):
        ix = f(0.5) * (s0[j + 1] - s0[j - 1])
        iy = f(0.5) * (sp[j] - sm_[j])
        inv = f(1.0) / np.sqrt(f(1.0) + ix * ix + iy * iy)
        rxx[j] = (s0[j + 1] - f(2.0) * s0[j] + s0[j - 1]) * inv
        ryy[j] = (sp[j] - f(2.0) * s0[j] + sm_[j]) * inv
        rxy[j] = f(0.25) * (sp[j + 1] - sp[j - 1] - sm_[j + 1] + sm_[j - 1]) * inv
    _hess_px(s0, sm_, sp, 0, 0, min(1, cols - 1), rxx, rxy, ryy)
    if cols > 1:
        _hess_px(s0, sm_, sp, cols - 2, cols - 1, cols - 1, rxx, rxy, ryy)


@njit(**_JIT)
def _gauss_row(src, t, g, pad, out):
    """Row of the separable Gaussian ``g`` (odd length w) of the rows ``src[t:t + w]``,
    reflecting at the row ends (BORDER_REFLECT); ``pad`` holds cols + w - 1 values."""
    w = g.size
    r = w // 2
    cols = out.size
    mid = pad[r:r + cols]
    if w == 3:  # the default (Table 3.1): one pass per direction
        g0, g1, g2 = g[0], g[1], g[2]
        r0, r1, r2 = src[t], src[t + 1], src[t + 2]
        for x in range(cols):
            mid[x] = g0 * r0[x] + g1 * r1[x] + g2 * r2[x]
        pad[0] = mid[0]
        pad[cols + 1] = mid[cols - 1]
        for x in range(cols):
            out[x] = g0 * pad[x] + g1 * pad[x + 1] + g2 * pad[x + 2]
        return
    row = src[t]
    for x in range(cols):
        mid[x] = g[0] * row[x]
    for k in range(1, w):
        row, gk = src[t + k], g[k]
        for x in range(cols):
            mid[x] += gk * row[x]
    for q in range(r):
        pad[r - 1 - q] = mid[q]
        pad[r + cols + q] = mid[cols - 1 - q]
    for x in range(cols):
        out[x] = g[0] * pad[x]
    for k in range(1, w):
        gk = g[k]
        for x in range(cols):
            out[x] += gk * pad[x + k]


@njit(**_JIT)
def _tensor_row(xx, xy, yy, eps, alpha, beta, ra, rb, rc):
    """Diffusion tensor of eq. 3.3-3.5 (see :func:`.creases.diffusion_tensor`), one row."""
    f = np.float32
    for k in range(xx.size):
        t = xx[k] + yy[k]
        d = xx[k] - yy[k]
        h2 = f(2.0) * xy[k]
        s = np.sqrt(d * d + h2 * h2)
        at = abs(t)
        mu = min(s, at) / max(max(s, at), f(1e-30))
        lam2 = mu * (beta if t > 0 else alpha)
        m = f(0.5) * (lam2 + eps)
        g = f(0.5) * (eps - lam2) * t / max(at * s, f(1e-30))
        ra[k] = m + g * d
        rc[k] = m - g * d
        rb[k] = g * h2


@njit(**_JIT)
def _step_border_px(u, a, b, c, i, k, j, half_tau, out):
    """The explicit step at pixel (i, j) with every neighbour test; the tensor rows of
    image row ``i`` are ``a[k]``, ``b[k]``, ``c[k]`` (a strip buffer)."""
    f = np.float32
    rows, cols = u.shape
    uc = u[i, j]
    div = f(0.0)
    if j + 1 < cols:
        div += (a[k, j + 1] + a[k, j]) * (u[i, j + 1] - uc)
    if j > 0:
        div -= (a[k, j] + a[k, j - 1]) * (uc - u[i, j - 1])
    if i + 1 < rows:
        div += (c[k + 1, j] + c[k, j]) * (u[i + 1, j] - uc)
    if i > 0:
        div -= (c[k, j] + c[k - 1, j]) * (uc - u[i - 1, j])
    mixed = f(0.0)
    ip = min(i + 1, rows - 1)
    im = max(i - 1, 0)
    if j + 1 < cols:
        mixed += b[k, j + 1] * (u[ip, j + 1] - u[im, j + 1])
    if j > 0:
        mixed -= b[k, j - 1] * (u[ip, j - 1] - u[im, j - 1])
    jp = min(j + 1, cols - 1)
    jm = max(j - 1, 0)
    if i + 1 < rows:
        mixed += b[k + 1, j] * (u[i + 1, jp] - u[i + 1, jm])
    if i > 0:
        mixed -= b[k - 1, j] * (u[i - 1, jp] - u[i - 1, jm])
    out[i, j] = uc + half_tau * (div + f(0.5) * mixed)


@njit(**_JIT)
def _step_row(u, a, b, c, i, k, half_tau, out):
    """Row ``i`` of one explicit step of Weickert's standard scheme (see
    :func:`.creases.diffusion_step`); the tensor rows of image row ``i`` are ``a[k]`` etc.

    Zero flux through the border for the pure terms; for the mixed terms the inner
    derivative replicates the border and the outer one sees zeros outside, as the
    OpenCV implementation does. Border pixels take a general (branching) path, the
    interior a branch-free loop over row views that vectorises.
    """
    f = np.float32
    rows, cols = u.shape
    if i == 0 or i == rows - 1:
        for j in range(cols):
            _step_border_px(u, a, b, c, i, k, j, half_tau, out)
        return
    u0, um, up = u[i], u[i - 1], u[i + 1]
    a0, c0, cm, cp = a[k], c[k], c[k - 1], c[k + 1]
    b0, bm, bp = b[k], b[k - 1], b[k + 1]
    o = out[i]
    for j in range(1, cols - 1):
        uc = u0[j]
        div = ((a0[j + 1] + a0[j]) * (u0[j + 1] - uc)
               - (a0[j] + a0[j - 1]) * (uc - u0[j - 1])
               + (cp[j] + c0[j]) * (up[j] - uc)
               - (c0[j] + cm[j]) * (uc - um[j]))
        mixed = (b0[j + 1] * (up[j + 1] - um[j + 1])
                 - b0[j - 1] * (up[j - 1] - um[j - 1])
                 + bp[j] * (up[j + 1] - up[j - 1])
                 - bm[j] * (um[j + 1] - um[j - 1]))
        o[j] = uc + half_tau * (div + f(0.5) * mixed)
    _step_border_px(u, a, b, c, i, k, 0, half_tau, out)
    if cols > 1:
        _step_border_px(u, a, b, c, i, k, cols - 1, half_tau, out)


@njit(**_JIT)
def diffusion_step_kernel(u, sm, g, eps, alpha, beta, tau, out):  # pragma: no cover
    """One crease-diffusion step from the Gaussian-smoothed image ``sm``, in row strips.

    Per strip: the normalised Hessian (eq. 3.1) of the rows the strip needs, its Gaussian
    ``g`` (the rho / w2 smoothing of eq. 3.2, reflecting border), the tensor (eq. 3.3-3.5)
    and the explicit step into ``out``. Everything between ``sm`` and ``out`` stays in
    strip-sized buffers that fit in cache instead of six whole-image arrays. Needs
    ``len(g) // 2 < min(u.shape)`` (one reflection at the border).
    """
    f = np.float32
    rows, cols = u.shape
    r = g.size // 2
    strip = 32
    hess = np.empty((3, strip + 2 + 2 * r, cols), np.float32)
    pad = np.empty(cols + 2 * r, np.float32)
    smooth = np.empty((3, cols), np.float32)
    tens = np.empty((3, strip + 2, cols), np.float32)
    half_tau = f(0.5) * tau
    for i0 in range(0, rows, strip):
        i1 = min(rows, i0 + strip)
        t0, t1 = max(i0 - 1, 0), min(i1 + 1, rows)   # tensor rows the step reads
        for q in range(t1 - t0 + 2 * r):              # Hessian rows their Gaussian reads
            row = t0 - r + q
            row = -row - 1 if row < 0 else (2 * rows - row - 1 if row >= rows else row)
            _hessian_row(sm, row, hess[0, q], hess[1, q], hess[2, q])
        for q in range(t1 - t0):
            for ch in range(3):
                _gauss_row(hess[ch], q, g, pad, smooth[ch])
            _tensor_row(smooth[0], smooth[1], smooth[2], eps, alpha, beta, tens[0, q],
                        tens[1, q], tens[2, q])
        for i in range(i0, i1):
            _step_row(u, tens[0], tens[1], tens[2], i, i - t0, half_tau, out)
    return out


@njit(**_JIT)
def _grad_px(s0, sm_, sp, jm, j, jp, rx, ry, rxx, rxy, ryy):
    f = np.float32
    x = f(0.5) * (s0[jp] - s0[jm])
    y = f(0.5) * (sp[j] - sm_[j])
    rx[j] = x
    ry[j] = y
    rxx[j] = x * x
    rxy[j] = x * y
    ryy[j] = y * y


@njit(**_JIT)
def gradient_products_kernel(sm, gx, gy, pxx, pxy, pyy):  # pragma: no cover - compiled
    """Central-difference gradient (reflecting border) and its outer products."""
    rows, cols = sm.shape
    for i in range(rows):
        s0, sm_, sp = sm[i], sm[max(i - 1, 0)], sm[min(i + 1, rows - 1)]
        rx, ry, rxx, rxy, ryy = gx[i], gy[i], pxx[i], pxy[i], pyy[i]
        # Interior with affine indices (vectorises), then the two border columns.
        for j in range(1, cols - 1):
            _grad_px(s0, sm_, sp, j - 1, j, j + 1, rx, ry, rxx, rxy, ryy)
        _grad_px(s0, sm_, sp, 0, 0, min(1, cols - 1), rx, ry, rxx, rxy, ryy)
        if cols > 1:
            _grad_px(s0, sm_, sp, cols - 2, cols - 1, cols - 1, rx, ry, rxx, rxy, ryy)


@njit(**_JIT)
def mlsec_field_kernel(sxx, sxy, syy, gx, gy, wx, wy):  # pragma: no cover - compiled
    """Unit dominant structure-tensor direction, signed like the gradient (MLSEC-ST)."""
    f = np.float32
    a, b, c = sxx.reshape(-1), sxy.reshape(-1), syy.reshape(-1)
    x, y = gx.reshape(-1), gy.reshape(-1)
    ox, oy = wx.reshape(-1), wy.reshape(-1)
    smax2 = f(0.0)  # max of s^2: one square root instead of one per pixel
    for k in range(a.size):
        d = a[k] - c[k]
        smax2 = max(smax2, d * d + f(4.0) * b[k] * b[k])
    tiny = f(1e-12) * max(np.sqrt(smax2), f(1e-30))
    for k in range(a.size):
        d = a[k] - c[k]
        s = np.sqrt(d * d + f(4.0) * b[k] * b[k])
        cos2 = d / max(s, f(1e-30))
        ex = np.sqrt(max(f(0.5) * (f(1.0) + cos2), f(0.0)))
        ey = np.sqrt(max(f(0.5) * (f(1.0) - cos2), f(0.0)))
        if b[k] < 0:
            ey = -ey
        dot = ex * x[k] + ey * y[k]
        sg = f(1.0) if dot > 0 else (f(-1.0) if dot < 0 else f(0.0))
        if s <= tiny:
            sg = f(0.0)
        ox[k] = ex * sg
        oy[k] = ey * sg


@njit(**_JIT)
def _divergence_px(xm, x0, xp, ym, yp, jm, j, jp, o):
    f = np.float32
    r = f(0.70710678)
    # n_k = (dx, dy)/|.|; x = column, y = row (down).
    acc = (x0[jp] - x0[jm]
           + r * (xm[jp] - xm[jm] + xp[jp] - xp[jm])
           + yp[j] - ym[j]
           + r * (yp[jm] + yp[jp] - ym[jm] - ym[jp]))
    o[j] = f(-0.25) * acc


@njit(**_JIT)
def mlsec_divergence_kernel(wx, wy, out):  # pragma: no cover - compiled
    """-(2/8) sum_k n_k . w(P_k) over the 8 neighbours, reflecting border."""
    rows, cols = wx.shape
    for i in range(rows):
        xm, x0, xp = wx[max(i - 1, 0)], wx[i], wx[min(i + 1, rows - 1)]
        ym, yp = wy[max(i - 1, 0)], wy[min(i + 1, rows - 1)]
        o = out[i]
        for j in range(1, cols - 1):
            _divergence_px(xm, x0, xp, ym, yp, j - 1, j, j + 1, o)
        _divergence_px(xm, x0, xp, ym, yp, 0, 0, min(1, cols - 1), o)
        if cols > 1:
            _divergence_px(xm, x0, xp, ym, yp, cols - 2, cols - 1, cols - 1, o)


@njit(**_JIT)
def _contrast_px(s0, sm_, sp, jm, j, jp, half_scale, o):
    f = np.float32
    xx = s0[jp] - f(2.0) * s0[j] + s0[jm]
    yy = sp[j] - f(2.0) * s0[j] + sm_[j]
    xy = f(0.25) * (sp[jp] - sp[jm] - sm_[jp] + sm_[jm])
    t = xx + yy
    d = xx - yy
    s = np.sqrt(d * d + f(4.0) * xy * xy)
    sg = f(1.0) if t > 0 else (f(-1.0) if t < 0 else f(0.0))
    o[j] = half_scale * (t + sg * s)


@njit(**_JIT)
def contrast_kernel(sm, scale, out):  # pragma: no cover - compiled
    """scale * signed Hessian eigenvalue of largest magnitude (reflecting border)."""
    rows, cols = sm.shape
    half_scale = np.float32(0.5) * scale
    for i in range(rows):
        s0, sm_, sp = sm[i], sm[max(i - 1, 0)], sm[min(i + 1, rows - 1)]
        o = out[i]
        for j in range(1, cols - 1):
            _contrast_px(s0, sm_, sp, j - 1, j, j + 1, half_scale, o)
        _contrast_px(s0, sm_, sp, 0, 0, min(1, cols - 1), half_scale, o)
        if cols > 1:
            _contrast_px(s0, sm_, sp, cols - 2, cols - 1, cols - 1, half_scale, o)


@njit(**_JIT)
def crease_threshold_kernel(creaseness, contrast, valid, use_valid, sgn, gate, low, high,
                            mask, seed):  # pragma: no cover - compiled
    """Thresholds of :func:`.creases.crease_mask` in one pass (uint8 outputs).

    ``mask``: contrast of the polarity above ``gate`` (and valid) and creaseness above
    ``low``; ``seed``: mask pixels whose creaseness is also above ``high``.
    """
    cr, co, va = creaseness.reshape(-1), contrast.reshape(-1), valid.reshape(-1)
    m, sd = mask.reshape(-1), seed.reshape(-1)
    for k in range(cr.size):
        score = sgn * cr[k]
        on = (-sgn * co[k] > gate) and (score > low) and (va[k] or not use_valid)
        m[k] = on
        sd[k] = on and score > high
    return mask


@njit(**_JIT)
def keep_components_kernel(labels, n, seed, use_seed, min_area, out):  # pragma: no cover
    """``out`` = pixels of components with >= ``min_area`` pixels and, if ``use_seed``, at
    least one ``seed`` pixel (hysteresis); label 0 is the background."""
    lab, sd, o = labels.reshape(-1), seed.reshape(-1), out.reshape(-1)
    # Areas and seeds in four interleaved tables: consecutive pixels of one component (and
    # the background, most pixels) then update different memory, not one counter in a
    # store-to-load chain, which halves the time.
    area4 = np.zeros((4, n), np.int32)
    seed4 = np.zeros((4, n), np.uint8)
    size = lab.size
    top = size - size % 4
    for k in range(0, top, 4):
        for q in range(4):
            area4[q, lab[k + q]] += 1
            seed4[q, lab[k + q]] |= sd[k + q]
    for k in range(top, size):
        area4[0, lab[k]] += 1
        seed4[0, lab[k]] |= sd[k]
    keep = np.zeros(n, np.uint8)
    for i in range(1, n):
        area = area4[0, i] + area4[1, i] + area4[2, i] + area4[3, i]
        seeded = (seed4[0, i] | seed4[1, i] | seed4[2, i] | seed4[3, i]) != 0
        keep[i] = area >= min_area and (seeded or not use_seed)
    for k in range(size):
        o[k] = keep[lab[k]]
    return out


@njit(**_JIT)
def fill_small_holes_kernel(mask, min_area, state):  # pragma: no cover - compiled
    """Set, in place, the 4-connected background components of fewer than ``min_area``
    pixels (holes; the image border does not make a component large).

    Bounded search instead of labelling: from each unvisited background pixel, collect its
    component until it has ``min_area`` pixels or meets a pixel already known to be in a
    large component (then all collected pixels are large too); only a search that runs
    out of pixels first has found a small hole. A background pixel whose left or upper
    neighbour is known large is large at once, so most pixels cost one look-up.
    ``state`` is a zeroed uint8 work array of the mask's shape.
    """
    rows, cols = mask.shape
    m = mask.reshape(-1)
    unseen, collected, large = 0, 1, 2
    state = state.reshape(-1)
    found = np.empty(max(min_area, 1), np.int64)
    for r in range(rows):
        for c in range(cols):
            k = r * cols + c
            if m[k] or state[k] != unseen:
                continue
            if (c > 0 and state[k - 1] == large) or (r > 0 and state[k - cols] == large):
                state[k] = large
                continue
            state[k] = collected
            found[0] = k
            count, head, big = 1, 0, min_area <= 1
            while head < count and not big:
                q = found[head]
                head += 1
                qr, qc = q // cols, q - (q // cols) * cols
                # Rows above are settled: look up first to meet a large pixel early.
                for d in range(4):
                    if d == 0:
                        nb = q - cols if qr > 0 else -1
                    elif d == 1:
                        nb = q - 1 if qc > 0 else -1
                    elif d == 2:
                        nb = q + 1 if qc + 1 < cols else -1
                    else:
                        nb = q + cols if qr + 1 < rows else -1
                    if nb < 0 or m[nb] or state[nb] == collected:
                        continue
                    if state[nb] == large or count == min_area - 1:
                        big = True
                        break
                    state[nb] = collected
                    found[count] = nb
                    count += 1
            for i in range(count):
                if big:
                    state[found[i]] = large
                else:
                    m[found[i]] = 1
    return mask


@njit(**_JIT)
def _sobel_px(rm, r0, rp, jm, j, jp, oxy, odd):
    f = np.float32
    gx = (rm[jp] - rm[jm]) + f(2.0) * (r0[jp] - r0[jm]) + (rp[jp] - rp[jm])
    gy = (rp[jm] - rm[jm]) + f(2.0) * (rp[j] - rm[j]) + (rp[jp] - rm[jp])
    oxy[j] = gx * gy
    odd[j] = gx * gx - gy * gy


@njit(**_JIT)
def sobel_products_kernel(img, pxy, pdd):  # pragma: no cover - compiled
    """Sobel gradients (OpenCV's default BORDER_REFLECT_101) -> gx*gy and gx^2 - gy^2.

    Needs at least 2 rows and 2 columns.
    """
    rows, cols = img.shape
    for i in range(rows):
        im = 1 if i == 0 else i - 1
        ip = rows - 2 if i == rows - 1 else i + 1
        r0, rm, rp = img[i], img[im], img[ip]
        oxy, odd = pxy[i], pdd[i]
        for j in range(1, cols - 1):
            _sobel_px(rm, r0, rp, j - 1, j, j + 1, oxy, odd)
        _sobel_px(rm, r0, rp, 1, 0, 1, oxy, odd)
        _sobel_px(rm, r0, rp, cols - 2, cols - 1, cols - 2, oxy, odd)


@njit(**_JIT)
def doubled_angle_kernel(sxy, sdd, phx, phy):  # pragma: no cover - compiled
    """Unit doubled-angle vector of the crease (gradient + 90 deg, North-up)."""
    f = np.float32
    a, b = sxy.reshape(-1), sdd.reshape(-1)
    ox, oy = phx.reshape(-1), phy.reshape(-1)
    for k in range(a.size):
        norm = max(np.sqrt(b[k] * b[k] + f(4.0) * a[k] * a[k]), f(1e-30))
        ox[k] = -b[k] / norm
        oy[k] = f(2.0) * a[k] / norm


@njit(**_JIT)
def _ring_code(sp, i, j):
    """8-neighbour code of padded pixel (i, j), zeros outside (bit k: ring neighbour k,
    anticlockwise from East as in :mod:`.minutiae`)."""
    rows, cols = sp.shape
    code = 0
    for k, (dr, dc) in enumerate(((0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1),
                                  (1, 0), (1, 1))):
        r, c = i + dr, j + dc
        if 0 <= r < rows and 0 <= c < cols and sp[r, c]:
            code |= 1 << k
    return code


@njit(**_JIT)
def skeleton_maps_kernel(skel, cn_lut, skel_p, code_p, cn_p, junc_p, found):  # pragma: no cover
    """Padded skeleton maps for the minutia tracer, in one pass.

    ``skel_p``: the skeleton with a one-pixel zero frame; ``code_p``: 8-neighbour code of
    every padded pixel; ``cn_p``: crossing number (``cn_lut`` of the code) on the skeleton,
    0 elsewhere; ``junc_p``: CN >= 3. ``found`` receives the flat (unpadded) index of every
    CN 1 or CN 3 pixel in row-major order; returns how many. All uint8 except ``found``.
    """
    rows, cols = skel.shape
    skel_p[0, :] = 0
    skel_p[rows + 1, :] = 0
    skel_p[:, 0] = 0
    skel_p[:, cols + 1] = 0
    skel_p[1:rows + 1, 1:cols + 1] = skel
    for j in range(cols + 2):  # the frame: codes of the outer neighbours of the skeleton
        code_p[0, j] = _ring_code(skel_p, 0, j)
        code_p[rows + 1, j] = _ring_code(skel_p, rows + 1, j)
    for i in range(rows + 2):
        code_p[i, 0] = _ring_code(skel_p, i, 0)
        code_p[i, cols + 1] = _ring_code(skel_p, i, cols + 1)
    cn_p[0, :] = 0
    cn_p[rows + 1, :] = 0
    cn_p[:, 0] = 0
    cn_p[:, cols + 1] = 0
    junc_p[0, :] = 0
    junc_p[rows + 1, :] = 0
    junc_p[:, 0] = 0
    junc_p[:, cols + 1] = 0
    n = 0
    for i in range(1, rows + 1):
        up, mid, dn = skel_p[i - 1], skel_p[i], skel_p[i + 1]
        code, cn, junc = code_p[i], cn_p[i], junc_p[i]
        for j in range(1, cols + 1):  # branch-free: vectorises
            code[j] = (mid[j + 1] | (up[j + 1] << 1) | (up[j] << 2) | (up[j - 1] << 3)
                       | (mid[j - 1] << 4) | (dn[j - 1] << 5) | (dn[j] << 6)
                       | (dn[j + 1] << 7))
        for j in range(1, cols + 1):
            if mid[j]:
                v = cn_lut[code[j]]
                cn[j] = v
                junc[j] = v >= 3
                if v == 1 or v == 3:
                    found[n] = (i - 1) * cols + j - 1
                    n += 1
            else:
                cn[j] = 0
                junc[j] = 0
    return n


@njit(**_JIT)
def walk_kernel(skel_p, code_p, junc_p, sr, sc, first, steps, upto, skip, next_lut, ring5,
                offs, tip, direction, length, stop):  # pragma: no cover - compiled
    """Skeleton walkers of :func:`.minutiae._walk`, one after the other (same rules).

    ``stop``: 0 running, 1 free end, 2 junction. ``direction`` is NaN when undefined.
    """
    n = sr.size
    c1 = max(1, upto // 3)
    c2 = max(1, 2 * upto // 3)
    c3 = max(1, upto)
    for w in range(n):
        r0, q0 = sr[w], sc[w]
        cr = r0 + offs[first[w], 0]
        cc = q0 + offs[first[w], 1]
        ln = 1
        st = 0
        acc_r = 0.0
        acc_c = 0.0
        if junc_p[cr, cc] and not junc_p[r0, q0]:
            st = 2
        frm = 0
        frm2 = 8
        t = 1
        if st == 0 and steps >= 2:
            # Step 2 on the real neighbours, away from the start's neighbourhood.
            best = -1
            best_score = 0
            for k in range(8):
                nr = cr + offs[k, 0]
                nc = cc + offs[k, 1]
                if skel_p[nr, nc] and max(abs(nr - r0), abs(nc - q0)) > 1:
                    score = (nr - r0) ** 2 + (nc - q0) ** 2
                    if score > best_score:
                        best_score = score
                        best = k
            if best < 0:
                st = 1
            else:
                frm = (best + 4) % 8
                frm2 = ring5[r0 - cr - offs[best, 0] + 2, q0 - cc - offs[best, 1] + 2]
                cr += offs[best, 0]
                cc += offs[best, 1]
                ln += 1
                t = 2
        # Checkpoints add the walker's offset at that step (the tip if it stopped before).
        if c1 == 1 or c2 == 1 or c3 == 1:
            p1r = r0 + offs[first[w], 0]
            p1c = q0 + offs[first[w], 1]
            m = (c1 == 1) + (c2 == 1) + (c3 == 1)
            acc_r += m * (p1r - r0)
            acc_c += m * (p1c - q0)
        if t == 2:
            m = (c1 == 2) + (c2 == 2) + (c3 == 2)
            acc_r += m * (cr - r0)
            acc_c += m * (cc - q0)
            step = 2
            while True:
                if junc_p[cr, cc] and max(abs(cr - r0), abs(cc - q0)) > skip:
                    st = 2
                    break
                if step == steps:
                    break
                k = next_lut[code_p[cr, cc], frm, frm2]
                if k < 0:
                    st = 1
                    break
                frm2 = ring5[offs[frm, 0] - offs[k, 0] + 2, offs[frm, 1] - offs[k, 1] + 2]
                frm = (k + 4) % 8
                cr += offs[k, 0]
                cc += offs[k, 1]
                ln += 1
                step += 1
                m = (c1 == step) + (c2 == step) + (c3 == step)
                acc_r += m * (cr - r0)
                acc_c += m * (cc - q0)
            t = step
        # Checkpoints beyond the last step reached count the tip.
        m = (c1 > t) + (c2 > t) + (c3 > t)
        acc_r += m * (cr - r0)
        acc_c += m * (cc - q0)
        tip[w, 0] = cr
        tip[w, 1] = cc
        length[w] = ln
        stop[w] = st
        norm = np.sqrt(acc_r * acc_r + acc_c * acc_c)
        if norm == 0:
            direction[w, 0] = np.nan
            direction[w, 1] = np.nan
        else:
            direction[w, 0] = acc_r / norm
            direction[w, 1] = acc_c / norm
