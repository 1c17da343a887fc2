"""Optional fused (numba) kernels for the crease-enhancing diffusion of :mod:`.creases`.

The numpy/OpenCV implementation in :mod:`.creases` needs ~55 whole-image passes per
diffusion step; these kernels compute the same discretisation in three passes (normalised
Hessian, tensor, step) plus OpenCV's Gaussians, which is several times faster. They are used
when numba is importable and ``TERRAIN_NAV_NO_NUMBA`` is not set; results agree with the
numpy path to float32 rounding (``test_creases.py`` checks it).
"""

from __future__ import annotations

import os

import numpy as np

try:  # numba is optional: the numpy/OpenCV path is the reference
    if os.environ.get("TERRAIN_NAV_NO_NUMBA"):
        raise ImportError("disabled by TERRAIN_NAV_NO_NUMBA")
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - depends on the environment
    HAVE_NUMBA = False

    def njit(*args, **kwargs):
        def wrap(f):
            return f
        return wrap(args[0]) if args and callable(args[0]) else wrap


_JIT = dict(cache=True, fastmath=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _hess_row(s0, sm_, sp, jm, j, jp, hxx, hxy, hyy):
    f = np.float32
    ix = f(0.5) * (s0[jp] - s0[jm])
    iy = f(0.5) * (sp[j] - sm_[j])
    inv = f(1.0) / np.sqrt(f(1.0) + ix * ix + iy * iy)
    hxx[j] = (s0[jp] - f(2.0) * s0[j] + s0[jm]) * inv
    hyy[j] = (sp[j] - f(2.0) * s0[j] + sm_[j]) * inv
    hxy[j] = f(0.25) * (sp[jp] - sp[jm] - sm_[jp] + sm_[jm]) * inv


@njit(**_JIT)
def normalised_hessian_kernel(sm, hxx, hxy, hyy):  # pragma: no cover - compiled
    """H / sqrt(1 + |grad|^2) of a smoothed image by central differences (eq. 3.1).

    Borders reflect like OpenCV's BORDER_REFLECT (pixel -1 is pixel 0).
    """
    f = np.float32
    rows, cols = sm.shape
    for i in range(rows):
        s0 = sm[i]
        sm_ = sm[max(i - 1, 0)]
        sp = sm[min(i + 1, rows - 1)]
        rxx, rxy, ryy = hxx[i], hxy[i], hyy[i]
        # Row views with non-negative indices: the interior loop vectorises.
        for j in range(1, cols - 1):
            ix = f(0.5) * (s0[j + 1] - s0[j - 1])
            iy = f(0.5) * (sp[j] - sm_[j])
            inv = f(1.0) / np.sqrt(f(1.0) + ix * ix + iy * iy)
            rxx[j] = (s0[j + 1] - f(2.0) * s0[j] + s0[j - 1]) * inv
            ryy[j] = (sp[j] - f(2.0) * s0[j] + sm_[j]) * inv
            rxy[j] = f(0.25) * (sp[j + 1] - sp[j - 1] - sm_[j + 1] + sm_[j - 1]) * inv
        _hess_row(s0, sm_, sp, 0, 0, min(1, cols - 1), rxx, rxy, ryy)
        if cols > 1:
            _hess_row(s0, sm_, sp, cols - 2, cols - 1, cols - 1, rxx, rxy, ryy)


@njit(**_JIT)
def tensor_kernel(hxx, hxy, hyy, eps, alpha, beta, a, b, c):  # pragma: no cover - compiled
    """Diffusion tensor of eq. 3.3-3.5 (see :func:`.creases.diffusion_tensor`)."""
    f = np.float32
    xx, xy, yy = hxx.reshape(-1), hxy.reshape(-1), hyy.reshape(-1)
    ra, rb, rc = a.reshape(-1), b.reshape(-1), c.reshape(-1)
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
def _step_border_px(u, a, b, c, i, j, half_tau, out):
    f = np.float32
    rows, cols = u.shape
    uc = u[i, j]
    div = f(0.0)
    if j + 1 < cols:
        div += (a[i, j + 1] + a[i, j]) * (u[i, j + 1] - uc)
    if j > 0:
        div -= (a[i, j] + a[i, j - 1]) * (uc - u[i, j - 1])
    if i + 1 < rows:
        div += (c[i + 1, j] + c[i, j]) * (u[i + 1, j] - uc)
    if i > 0:
        div -= (c[i, j] + c[i - 1, j]) * (uc - u[i - 1, j])
    mixed = f(0.0)
    ip = min(i + 1, rows - 1)
    im = max(i - 1, 0)
    if j + 1 < cols:
        mixed += b[i, j + 1] * (u[ip, j + 1] - u[im, j + 1])
    if j > 0:
        mixed -= b[i, j - 1] * (u[ip, j - 1] - u[im, j - 1])
    jp = min(j + 1, cols - 1)
    jm = max(j - 1, 0)
    if i + 1 < rows:
        mixed += b[i + 1, j] * (u[i + 1, jp] - u[i + 1, jm])
    if i > 0:
        mixed -= b[i - 1, j] * (u[i - 1, jp] - u[i - 1, jm])
    out[i, j] = uc + half_tau * (div + f(0.5) * mixed)


@njit(**_JIT)
def step_kernel(u, a, b, c, tau, out):  # pragma: no cover - compiled
    """One explicit step of Weickert's standard scheme (see :func:`.creases.diffusion_step`).

    Zero flux through the border for the pure terms; for the mixed terms the inner
    derivative replicates the border and the outer one sees zeros outside, as the
    OpenCV implementation does. Border pixels take a general (branching) path, the
    interior a branch-free loop over row views that vectorises.
    """
    f = np.float32
    rows, cols = u.shape
    half_tau = f(0.5) * tau
    for i in range(rows):
        if i == 0 or i == rows - 1:
            for j in range(cols):
                _step_border_px(u, a, b, c, i, j, half_tau, out)
            continue
        u0, um, up = u[i], u[i - 1], u[i + 1]
        a0, c0, cm, cp = a[i], c[i], c[i - 1], c[i + 1]
        b0, bm, bp = b[i], b[i - 1], b[i + 1]
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
        _step_border_px(u, a, b, c, i, 0, half_tau, out)
        if cols > 1:
            _step_border_px(u, a, b, c, i, cols - 1, half_tau, out)


@njit(**_JIT)
def gradient_products_kernel(sm, gx, gy, pxx, pxy, pyy):  # pragma: no cover - compiled
    """Central-difference gradient (reflecting border) and its outer products."""
    f = np.float32
    rows, cols = sm.shape
    for i in range(rows):
        s0, sm_, sp = sm[i], sm[max(i - 1, 0)], sm[min(i + 1, rows - 1)]
        rx, ry, rxx, rxy, ryy = gx[i], gy[i], pxx[i], pxy[i], pyy[i]
        for j in range(cols):
            x = f(0.5) * (s0[min(j + 1, cols - 1)] - s0[max(j - 1, 0)])
            y = f(0.5) * (sp[j] - sm_[j])
            rx[j] = x
            ry[j] = y
            rxx[j] = x * x
            rxy[j] = x * y
            ryy[j] = y * y


@njit(**_JIT)
def mlsec_field_kernel(sxx, sxy, syy, gx, gy, wx, wy):  # pragma: no cover - compiled
    """Unit dominant structure-tensor direction, signed like the gradient (MLSEC-ST)."""
    f = np.float32
    a, b, c = sxx.reshape(-1), sxy.reshape(-1), syy.reshape(-1)
    x, y = gx.reshape(-1), gy.reshape(-1)
    ox, oy = wx.reshape(-1), wy.reshape(-1)
    smax = f(0.0)
    for k in range(a.size):
        d = a[k] - c[k]
        smax = max(smax, np.sqrt(d * d + f(4.0) * b[k] * b[k]))
    tiny = f(1e-12) * max(smax, f(1e-30))
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
def mlsec_divergence_kernel(wx, wy, out):  # pragma: no cover - compiled
    """-(2/8) sum_k n_k . w(P_k) over the 8 neighbours, reflecting border."""
    f = np.float32
    r = f(0.70710678)
    q = f(-0.25)
    rows, cols = wx.shape
    for i in range(rows):
        xm, x0, xp = wx[max(i - 1, 0)], wx[i], wx[min(i + 1, rows - 1)]
        ym, yp = wy[max(i - 1, 0)], wy[min(i + 1, rows - 1)]
        o = out[i]
        for j in range(cols):
            jm = max(j - 1, 0)
            jp = min(j + 1, cols - 1)
            # n_k = (dx, dy)/|.|; x = column, y = row (down).
            acc = (x0[jp] - x0[jm]
                   + r * (xm[jp] - xm[jm] + xp[jp] - xp[jm])
                   + yp[j] - ym[j]
                   + r * (yp[jm] + yp[jp] - ym[jm] - ym[jp]))
            o[j] = q * acc


@njit(**_JIT)
def contrast_kernel(sm, scale, out):  # pragma: no cover - compiled
    """scale * signed Hessian eigenvalue of largest magnitude (reflecting border)."""
    f = np.float32
    rows, cols = sm.shape
    for i in range(rows):
        s0, sm_, sp = sm[i], sm[max(i - 1, 0)], sm[min(i + 1, rows - 1)]
        o = out[i]
        for j in range(cols):
            jm = max(j - 1, 0)
            jp = min(j + 1, cols - 1)
            xx = s0[jp] - f(2.0) * s0[j] + s0[jm]
            yy = sp[j] - f(2.0) * s0[j] + sm_[j]
            xy = f(0.25) * (sp[jp] - sp[jm] - sm_[jp] + sm_[jm])
            t = xx + yy
            d = xx - yy
            s = np.sqrt(d * d + f(4.0) * xy * xy)
            sg = f(1.0) if t > 0 else (f(-1.0) if t < 0 else f(0.0))
            o[j] = f(0.5) * scale * (t + sg * s)


@njit(**_JIT)
def sobel_products_kernel(img, pxy, pdd):  # pragma: no cover - compiled
    """Sobel gradients (OpenCV's default BORDER_REFLECT_101) -> gx*gy and gx^2 - gy^2."""
    f = np.float32
    rows, cols = img.shape
    for i in range(rows):
        im = 1 if i == 0 else i - 1
        ip = rows - 2 if i == rows - 1 else i + 1
        r0, rm, rp = img[i], img[im], img[ip]
        oxy, odd = pxy[i], pdd[i]
        for j in range(cols):
            jm = 1 if j == 0 else j - 1
            jp = cols - 2 if j == cols - 1 else j + 1
            gx = (rm[jp] - rm[jm]) + f(2.0) * (r0[jp] - r0[jm]) + (rp[jp] - rp[jm])
            gy = (rp[jm] - rm[jm]) + f(2.0) * (rp[j] - rm[j]) + (rp[jp] - rm[jp])
            oxy[j] = gx * gy
            odd[j] = gx * gx - gy * gy


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
