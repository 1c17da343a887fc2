"""Optional fused (numba) kernels for the hot loops of :mod:`.matching` and
:mod:`.descriptors`.

* :func:`edge_lookup`: the tolerance cut of :meth:`.EdgeHash.lookup_prepared` in one pass
  over the visited hash cells (the numpy path gathers ~10 temporaries of all candidates);
* :func:`hash_votes`, :func:`vote_weights`: the votes of ``matching._hash_votes`` from the
  look-up, in one pass each;
* :func:`pair_candidates`: the candidate pairings of ``matching._pair`` for a small
  reference set, by brute force instead of a k-d tree query plus numpy filtering;
* :func:`greedy_one_to_one`: ``matching._greedy_one_to_one`` as one loop;
* :func:`listed_segments`: the crease samples around given minutiae, from their stored
  lists, without the index arithmetic of the numpy path; :func:`pixels_within`: those
  lists, from a grid of the samples instead of a k-d tree;
* :func:`ransac`: ``matching._ransac`` from its random samples, transform by transform,
  without its (transforms x correspondences) arrays;
* :func:`registration_terms`: the minutiae terms of ``matching._scored`` (overlap counts,
  leave-one-out residuals, pairing evidence) in one pass each;
* :func:`rotation_histogram`, :func:`near_angles`: the rotation Hough histogram and the
  votes near a rotation peak in ``matching._rotation_peaks`` / ``matching._hypotheses``;
* :func:`translation_grid`, :func:`cell_members`: the translation Hough cells of
  ``matching._translation_peaks``;
* :func:`crease_hit_counts` (on a :func:`near_mask`), :func:`crease_matches`: the
  crease-field look-ups of :mod:`.crease_check` (evidence and its local null, ICP
  correspondences) in one pass;
* :func:`crease_icp`: ``crease_check.refine_on_creases`` with its normal equations
  accumulated in the loop;
* :func:`compound_log10_sf`: the compound Poisson-Gamma tail of ``matching.significance``;
* :func:`channel_cross_spectra`, :func:`box_mask`: the channel product and the shifts the
  footprint counts keep, of :mod:`.crease_search`, without numpy's whole-array
  temporaries;
* :func:`rasterise_transformed`: the crease search query's direction-channel rasters, one
  transform at a time, with the pixels' places;
* :func:`local_shift_hits`: the fine level's look-ups around a coarse peak
  (``crease_search.local_peaks``), each sample placed once per transform.

They are used when numba is importable and ``TERRAIN_NAV_NO_NUMBA`` is not set, and compute
the same floating-point operations in the same order as the numpy path (no ``fastmath``:
no reassociation or fused multiply-adds), so results are identical, not merely close (run
with ``TERRAIN_NAV_NO_NUMBA=1`` for the numpy path). Exceptions: :func:`crease_icp`,
:func:`compound_log10_sf` and :func:`registration_terms` sum in another order than numpy's
pairwise sums, and numpy's own complex products, quotients, moduli and logarithms (SIMD,
with fused multiply-adds where the CPU has them) round differently from the scalar code of
those and of :func:`ransac`, so values that go through them agree to rounding (~1e-15
relative), and a comparison of such a value with a tolerance could only differ at the
tolerance itself; and two minutiae of B at exactly the same distance from a mapped minutia
of A may be ranked in another order than the k-d tree ranks them; :func:`rasterise_transformed`
turns the direction weights by angle sums instead of numpy's cosines (~1e-16 apart), and its
scalar complex products of the pixels' places may round differently from numpy's (fused
multiply-adds): a pixel could land on the next search pixel only where its place is within
~1e-13 px of a half pixel; :func:`local_shift_hits` sums its samples in their order, not
numpy's pairwise order (hits equal to ~1e-12), and turns their weights as
:func:`rasterise_transformed` does.
"""

from __future__ import annotations

import numpy as np

from .. import _numba
from .._numba import njit

# This module's switch: the callers test it, and tests turn it off per module.
HAVE_NUMBA = _numba.HAVE_NUMBA


# no fastmath: the kernels must round exactly like the numpy path they replace
_JIT = dict(cache=True, nogil=True, error_model="numpy")

TWO_PI = 2.0 * np.pi
_INV_TWO_PI = 1.0 / TWO_PI


@njit(**_JIT)
def edge_lookup(start, entry, e_length, e_beta_i, e_beta_j, rows, key, q_length, q_tol,
                q_beta_i, q_beta_j, angle_tol, wrap_tol):
    """Stored edges within tolerance of each prepared query edge (see
    :meth:`.EdgeHash.lookup_prepared`): ``(rows[query], entry[pos])`` of every kept
    candidate, in query order then cell order."""
    total = 0
    for r in range(key.size):
        total += start[key[r] + 1] - start[key[r]]
    q_out = np.empty(total, np.intp)
    e_out = np.empty(total, np.intp)
    m = 0
    for r in range(key.size):
        ql = q_length[r]
        tol = q_tol[r]
        b1 = q_beta_i[r]
        b2 = q_beta_j[r]
        row = rows[r]
        for pos in range(start[key[r]], start[key[r] + 1]):
            # branch-free (write always, advance when kept): the cells are scattered over
            # a table larger than the cache, and without mispredicted branches the CPU
            # overlaps the loads of many cells (~1.7x faster on a cold table)
            d1 = abs(e_beta_i[pos] - b1)
            d2 = abs(e_beta_j[pos] - b2)
            keep = ((abs(e_length[pos] - ql) <= tol)
                    & ((d1 <= angle_tol) | (d1 >= wrap_tol))
                    & ((d2 <= angle_tol) | (d2 >= wrap_tol)))
            q_out[m] = row
            e_out[m] = entry[pos]
            m += keep
    return q_out[:m], e_out[:m]


@njit(**_JIT)
def pair_candidates(zx, zy, bx, by, a_angle, b_angle, rot, k, pos_tol, angle_tol):
    """Candidate pairings of ``matching._pair``: for each point ``i`` of A (mapped to
    ``(zx, zy)``) its ``k`` nearest points of B strictly within ``pos_tol`` (as
    ``cKDTree.query(..., distance_upper_bound=pos_tol)``: squared distance below
    ``pos_tol**2``, nearest first), kept when the direction residual is within
    ``angle_tol``. Returns (i, j, cost) in the numpy path's order."""
    n_a = zx.size
    n_b = bx.size
    tol2 = pos_tol * pos_tol
    out_i = np.empty(n_a * k, np.intp)
    out_j = np.empty(n_a * k, np.intp)
    out_c = np.empty(n_a * k)
    best_d = np.empty(k)
    best_j = np.empty(k, np.intp)
    m = 0
    for i in range(n_a):
        cnt = 0
        xi = zx[i]
        yi = zy[i]
        for j in range(n_b):
            dx = xi - bx[j]
            dy = yi - by[j]
            d2 = dx * dx + dy * dy
            if d2 < tol2 and (cnt < k or d2 < best_d[cnt - 1]):
                # insertion into the sorted k best (ties keep the lower index first)
                s = cnt if cnt < k else k - 1
                while s > 0 and best_d[s - 1] > d2:
                    best_d[s] = best_d[s - 1]
                    best_j[s] = best_j[s - 1]
                    s -= 1
                best_d[s] = d2
                best_j[s] = j
                if cnt < k:
                    cnt += 1
        for r in range(cnt):
            j = best_j[r]
            dang = abs(_wrap_angle(b_angle[j] - a_angle[i] - rot))
            if dang <= angle_tol:
                out_i[m] = i
                out_j[m] = j
                out_c[m] = np.sqrt(best_d[r]) / pos_tol + dang / angle_tol
                m += 1
    return out_i[:m], out_j[:m], out_c[:m]


@njit(**_JIT)
def ransac(za, zb, dang, si, sj, c0, t0, edge_min, estimate_scale, max_scale_change,
           pos_tol, angle_tol):
    """``matching._ransac`` from its samples ``(si, sj)``: the transform of each sample pair
    (those with both edges longer than ``edge_min``; a rotation unless ``estimate_scale``,
    then within ``max_scale_change``), after the Hough guess ``(c0, t0)``; the one with the
    most inliers among the correspondences ``za -> zb``, the first of equals, and its inlier
    mask. Without the (transforms x correspondences) arrays of the numpy path."""
    cs = np.empty(si.size + 1, np.complex128)
    ts = np.empty(si.size + 1, np.complex128)
    cs[0], ts[0] = c0, t0
    n = 1
    for k in range(si.size):
        i, j = si[k], sj[k]
        dz = za[j] - za[i]
        dw = zb[j] - zb[i]
        if not (abs(dz) > edge_min and abs(dw) > edge_min):
            continue
        c = dw / dz
        if not estimate_scale:
            c = c / abs(c)
        elif abs(np.log(abs(c))) > max_scale_change:
            continue
        cs[n] = c
        ts[n] = 0.5 * (zb[i] + zb[j]) - c * 0.5 * (za[i] + za[j])
        n += 1
    best = 0
    best_count = -1
    for h in range(n):
        count = _inliers(za, zb, dang, cs[h], ts[h], pos_tol, angle_tol, None)
        if count > best_count:
            best, best_count = h, count
    inliers = np.empty(za.size, np.bool_)
    _inliers(za, zb, dang, cs[best], ts[best], pos_tol, angle_tol, inliers)
    return cs[best], ts[best], inliers


@njit(**_JIT)
def _inliers(za, zb, dang, c, t, pos_tol, angle_tol, out):
    """Correspondences within the tolerances under ``z -> c z + t`` (counted, and marked in
    ``out`` unless None)."""
    turn = np.arctan2(c.imag, c.real)
    count = 0
    for i in range(za.size):
        ok = (abs(c * za[i] + t - zb[i]) <= pos_tol
              and abs(_wrap_angle(dang[i] - turn)) <= angle_tol)
        count += ok
        if out is not None:
            out[i] = ok
    return count


@njit(**_JIT)
def registration_terms(za, zb, angle_a, angle_b, ia, ib, c, t, turn, box_a, box_b, pos_tol,
                       angle_tol, pos_floor, angle_floor):
    """The minutiae terms of ``matching._scored`` in one pass each: A's minutiae mapped by
    ``c z + t`` into B's footprint box, B's mapped back into A's (``matching._overlap``),
    and the summed ``matching.pairing_evidence`` of the pairings ``(ia, ib)`` with their
    leave-one-out position residuals (``matching._residuals``)."""
    n_ao = 0
    for i in range(za.size):
        z = c * za[i] + t
        n_ao += (box_b[0] <= z.real <= box_b[1]) and (box_b[2] <= z.imag <= box_b[3])
    n_bo = 0
    for j in range(zb.size):
        z = (zb[j] - t) / c
        n_bo += (box_a[0] <= z.real <= box_a[1]) and (box_a[2] <= z.imag <= box_a[3])
    m = ia.size
    mean = 0j
    spread_sum = 1e-12
    if m > 2:   # the leverage of each pairing: about their mean
        for k in range(m):
            mean += za[ia[k]]
        mean /= m
        spread = 0.0
        for k in range(m):
            spread += abs(za[ia[k]] - mean) ** 2
        spread_sum = max(spread, 1e-12)
    evidence = 0.0
    for k in range(m):
        z = za[ia[k]]
        dist = abs(c * z + t - zb[ib[k]])
        if m > 2:
            leverage = 1.0 / m + abs(z - mean) ** 2 / spread_sum
            dist = dist / max(1.0 - leverage, 1e-3)
        dang = abs(_wrap_angle(angle_b[ib[k]] - angle_a[ia[k]] - turn))
        u = max(dist, pos_floor) ** 2 / pos_tol ** 2
        v = max(dang, angle_floor) / angle_tol
        evidence += -np.log(min(u, 1.0)) - np.log(min(v, 1.0))
    return n_ao, n_bo, evidence


@njit(**_JIT)
def listed_segments(start, flat, lists):
    """The concatenation of the lists ``flat[start[k]:start[k + 1]]`` for ``k`` in ``lists``
    (``MinutiaIndex.crease_samples_around``)."""
    n = 0
    for k in lists:
        n += start[k + 1] - start[k]
    out = np.empty(n, flat.dtype)
    n = 0
    for k in lists:
        for i in range(start[k], start[k + 1]):
            out[n] = flat[i]
            n += 1
    return out


@njit(**_JIT)
def pixels_within(cols, rows, px, py, bound):
    """For each point ``(px[k], py[k])`` the indices of the pixels ``(cols, rows)``
    (integers, distinct) at a squared distance ``(col - px)**2 + (row - py)**2 <= bound``,
    as lists stored end to end ``flat[start[k]:start[k + 1]]``, each in the pixels' order:
    ``crease_check.CreaseSamples.around`` from a grid of the pixels' indices instead of a
    k-d tree (the same sums of squares, compared with the same bound)."""
    n = cols.size
    c0, c1, r0, r1 = cols.min(), cols.max(), rows.min(), rows.max()
    w = np.intp(c1 - c0) + 1
    grid = np.full((np.intp(r1 - r0) + 1, w), -1, np.intp)
    for i in range(n):
        grid[np.intp(rows[i] - r0), np.intp(cols[i] - c0)] = i
    reach = np.sqrt(bound) + 1.0
    start = np.zeros(px.size + 1, np.intp)
    flat = np.empty(0, np.intp)
    for fill in range(2):   # count, then fill
        m = 0
        for k in range(px.size):
            lo_r = max(np.intp(np.floor(py[k] - reach - r0)), 0)
            hi_r = min(np.intp(np.ceil(py[k] + reach - r0)), grid.shape[0] - 1)
            lo_c = max(np.intp(np.floor(px[k] - reach - c0)), 0)
            hi_c = min(np.intp(np.ceil(px[k] + reach - c0)), w - 1)
            for r in range(lo_r, hi_r + 1):
                for c in range(lo_c, hi_c + 1):
                    i = grid[r, c]
                    if i < 0:
                        continue
                    dx = cols[i] - px[k]
                    dy = rows[i] - py[k]
                    if dx * dx + dy * dy <= bound:
                        if fill:
                            flat[m] = i
                        m += 1
            start[k + 1] = m
        if not fill:
            flat = np.empty(m, np.intp)
    return start, flat


@njit(**_JIT)
def _wrap_angle(x):
    """``descriptors.wrap_angle`` of one angle."""
    return x - TWO_PI * np.rint(x * _INV_TWO_PI)


@njit(**_JIT)
def greedy_one_to_one(i, j, cost, rounds):
    """``matching._greedy_one_to_one`` (rounds of mutual cheapest candidates) in loops;
    returns the (m, 2) pairings in the same order."""
    n = i.size
    n_i = 0
    n_j = 0
    for r in range(n):
        n_i = max(n_i, i[r] + 1)
        n_j = max(n_j, j[r] + 1)
    out = np.empty((n, 2), np.intp)
    if n == 0:
        return out
    cnt_i = np.zeros(n_i, np.intp)
    cnt_j = np.zeros(n_j, np.intp)
    multi = False
    for r in range(n):
        cnt_i[i[r]] += 1
        cnt_j[j[r]] += 1
        if cnt_i[i[r]] > 1 or cnt_j[j[r]] > 1:
            multi = True
    if not multi:   # already one-to-one
        for r in range(n):
            out[r, 0] = i[r]
            out[r, 1] = j[r]
        return out
    order = np.argsort(cost, kind="mergesort")   # stable, like the numpy path
    ci = i[order]
    cj = j[order]
    alive = np.ones(n, np.bool_)
    first_i = np.empty(n_i, np.intp)
    first_j = np.empty(n_j, np.intp)
    used_i = np.zeros(n_i, np.bool_)
    used_j = np.zeros(n_j, np.bool_)
    m = 0
    for _ in range(rounds):
        first_i[:] = -1
        first_j[:] = -1
        left = 0
        for r in range(n):
            if alive[r]:
                left += 1
                if first_i[ci[r]] < 0:
                    first_i[ci[r]] = r
                if first_j[cj[r]] < 0:
                    first_j[cj[r]] = r
        if left == 0:
            break
        for r in range(n):
            if alive[r] and first_i[ci[r]] == r and first_j[cj[r]] == r:
                out[m, 0] = ci[r]
                out[m, 1] = cj[r]
                m += 1
                used_i[ci[r]] = True
                used_j[cj[r]] = True
        for r in range(n):
            if alive[r] and (used_i[ci[r]] or used_j[cj[r]]):
                alive[r] = False
    return out[:m]


@njit(**_JIT)
def near_angles(theta, th0, limit):
    """Indices of the angles within ``limit`` of ``th0`` (wrapped difference, as
    ``descriptors.wrap_angle``) and those differences."""
    idx = np.empty(theta.size, np.intp)
    out = np.empty(theta.size)
    m = 0
    for r in range(theta.size):
        d = _wrap_angle(theta[r] - th0)
        idx[m] = r
        out[m] = d
        m += abs(d) <= limit
    return idx[:m], out[:m]


@njit(**_JIT)
def translation_grid(t_re, t_im, w, inv_bin):
    """Translation Hough cells of ``matching._translation_peaks``: each vote's cell
    ``(gx, gy)`` from the lowest translation, the grid size and the vote weight per cell
    (summed in vote order, in float64, like ``np.bincount``)."""
    n = t_re.size
    x0 = t_re[0]
    y0 = t_im[0]
    for r in range(1, n):
        x0 = min(x0, t_re[r])
        y0 = min(y0, t_im[r])
    gx = np.empty(n, np.intp)
    gy = np.empty(n, np.intp)
    nx = 0
    ny = 0
    for r in range(n):
        gx[r] = np.intp((t_re[r] - x0) * inv_bin)
        gy[r] = np.intp((t_im[r] - y0) * inv_bin)
        nx = max(nx, gx[r] + 1)
        ny = max(ny, gy[r] + 1)
    h = np.zeros(nx * ny)
    for r in range(n):
        h[gy[r] * nx + gx[r]] += np.float64(w[r])
    return gx, gy, nx, ny, h


@njit(**_JIT)
def cell_members(gx, gy, px, py):
    """Indices of the votes in the 3 x 3 cells about ``(px, py)``."""
    idx = np.empty(gx.size, np.intp)
    m = 0
    for r in range(gx.size):
        idx[m] = r
        m += (abs(gx[r] - px) <= 1) & (abs(gy[r] - py) <= 1)
    return idx[:m]


@njit(**_JIT)
def rotation_histogram(theta, w, nb, scale):
    """Vote weight per rotation cell of ``matching._rotation_peaks`` (cell
    ``floor((theta + pi) * scale) % nb``, summed in vote order in float64 like
    ``np.bincount``)."""
    h = np.zeros(nb)
    for r in range(theta.size):
        k = np.intp(np.floor((theta[r] + np.pi) * scale)) % nb
        h[k] += np.float64(w[r])
    return h


@njit(**_JIT)
def hash_votes(q, e, qi, qj, qdir, rows, j, direction):
    """Votes of ``matching._hash_votes`` from the look-up's (query, stored) edge pairs:
    both minutiae of each edge and the rotation (wrapped like ``descriptors.wrap_angle``)."""
    n = q.size
    ia = np.empty(n, np.intp)
    ja = np.empty(n, np.intp)
    ib = np.empty(n, np.intp)
    jb = np.empty(n, np.intp)
    theta = np.empty(n)
    for r in range(n):
        ia[r] = qi[q[r]]
        ja[r] = qj[q[r]]
        ib[r] = rows[e[r]]
        jb[r] = j[e[r]]
        theta[r] = _wrap_angle(direction[e[r]] - qdir[q[r]])
    return ia, ja, ib, jb, theta


@njit(**_JIT)
def vote_weights(s, n_b, ia, ja, ib, jb):
    """``s[ia, ib] * s[ja, jb] + 0.05`` in float32, ``s`` the flattened float32 descriptor
    similarity clipped at 0 (as numpy computes it: float32 product, then the float32 sum)."""
    w = np.empty(ia.size, np.float32)
    c = np.float32(0.05)
    for r in range(ia.size):
        w[r] = s[ia[r] * n_b + ib[r]] * s[ja[r] * n_b + jb[r]] + c
    return w


@njit(**_JIT)
def _mod_pi(x):
    """``np.mod(x, pi)``, bit for bit, without its ``fmod`` (a third of a crease look-up's
    time): over ``[-2 pi, 3 pi)``, where the look-ups' direction differences lie, ``fmod``
    subtracts 0, 1 or 2 pi exactly (Sterbenz), and so do these branches; a negative
    remainder then gets the same rounded ``+ pi`` as numpy's."""
    if x >= TWO_PI:
        return x - TWO_PI if x < 3.0 * np.pi else np.mod(x, np.pi)
    if x >= np.pi:
        return x - np.pi
    if x >= 0.0:
        return x
    if x >= -np.pi:
        return x + np.pi
    return (x + np.pi) + np.pi if x >= -TWO_PI else np.mod(x, np.pi)


@njit(**_JIT)
def _field_test(z, direction, distance, field_dir, radius, angle_tol):
    """One mapped crease sample against a :class:`.crease_check.CreaseField`: -1 outside the
    field, else its flat pixel index, negated minus 2 when it is not a hit (as
    ``CreaseField._lookup`` / ``hits``)."""
    ri, ci = _field_pixel(z, distance.shape)
    if ri < 0:
        return -1
    flat = ri * distance.shape[1] + ci
    if distance[ri, ci] > radius:   # most samples: no need for the direction
        return -flat - 2
    return flat if _axial_hit(direction, field_dir[ri, ci], angle_tol) else -flat - 2


@njit(**_JIT)
def _field_pixel(z, shape):
    """The field pixel (row, col) a mapped sample (math frame) falls on; (-1, -1) outside."""
    col = np.rint(z.real)
    row = np.rint(-z.imag)
    if not (col >= 0 and col <= shape[1] - 1 and row >= 0 and row <= shape[0] - 1):
        return -1, -1
    return np.intp(row), np.intp(col)


@njit(**_JIT)
def _axial_hit(direction, field_direction, angle_tol):
    """Whether two axial directions (rad) agree within ``angle_tol``."""
    return abs(_mod_pi(direction - field_direction + 0.5 * np.pi) - 0.5 * np.pi) <= angle_tol


@njit(**_JIT)
def near_mask(distance, radius):
    """Where a crease is within ``radius``: the first test of :func:`_field_test`, once per
    field and radius (a byte per pixel to read instead of a float)."""
    out = np.empty(distance.shape, np.bool_)
    for r in range(distance.shape[0]):
        for c in range(distance.shape[1]):
            out[r, c] = not distance[r, c] > radius
    return out


@njit(**_JIT)
def _near_test(z, direction, near, field_dir, angle_tol):
    """:func:`_field_test` on a :func:`near_mask`: -1 outside the field, 1 a hit, 0 not."""
    ri, ci = _field_pixel(z, near.shape)
    if ri < 0:
        return -1
    if not near[ri, ci]:   # most samples: no need for the direction
        return 0
    return 1 if _axial_hit(direction, field_dir[ri, ci], angle_tol) else 0


@njit(**_JIT)
def crease_hit_counts(z, direction, keep, c, t, turn, near, field_dir, angle_tol, shifts,
                      stride):
    """Counts of ``crease_check.crease_evidence``: the kept samples mapped by ``c z + t``
    (directions turned by ``turn``) inside the field and hits among them (``near``: the
    field's :func:`near_mask` at the hit radius), then the same per shift for every
    ``stride``-th inside sample moved by each of ``shifts`` (the local null)."""
    n_in = 0
    n_hit = 0
    null_in = np.zeros(shifts.size, np.int64)
    null_hit = np.zeros(shifts.size, np.int64)
    for i in range(z.size):
        if not keep[i]:
            continue
        zi = c * z[i] + t
        di = direction[i] + turn
        f = _near_test(zi, di, near, field_dir, angle_tol)
        if f == -1:
            continue
        if n_in % stride == 0:
            for s in range(shifts.size):
                g = _near_test(zi + shifts[s], di, near, field_dir, angle_tol)
                null_in[s] += g != -1
                null_hit[s] += g == 1
        n_in += 1
        n_hit += f
    return n_in, n_hit, null_in, null_hit


@njit(**_JIT)
def crease_matches(z, direction, distance, field_dir, radius, angle_tol):
    """``crease_check.CreaseField.correspondences`` up to the nearest crease points: the
    index of each mapped sample that is a hit, and its flat pixel index in the field."""
    idx = np.empty(z.size, np.intp)
    flat = np.empty(z.size, np.intp)
    m = 0
    for i in range(z.size):
        f = _field_test(z[i], direction[i], distance, field_dir, radius, angle_tol)
        if f >= 0:
            idx[m] = i
            flat[m] = f
            m += 1
    return idx[:m], flat[:m]


@njit(**_JIT)
def _icp_correspondences(z, direction, distance, field_dir, label, crease_z, crease_normal,
                         c, t, turn_now, radius, angle_tol, p, q, normal, m):
    """Append one channel's correspondences at ``c z + t`` to ``p``, ``q``, ``normal`` from
    position ``m``: the new count and the sum of the mapped points appended."""
    w = distance.shape[1]
    total = 0j
    for i in range(z.size):
        pi = c * z[i] + t
        f = _field_test(pi, direction[i] + turn_now, distance, field_dir, radius, angle_tol)
        if f >= 0:
            ri = f // w
            nearest = label[ri, f - ri * w]
            p[m] = pi
            q[m] = crease_z[nearest]
            normal[m] = crease_normal[nearest]
            total += pi
            m += 1
    return m, total


@njit(**_JIT)
def crease_icp(z, direction, distance, field_dir, label, crease_z, crease_normal,
               z2, direction2, distance2, field_dir2, label2, crease_z2, crease_normal2,
               c, t, radius, angle_tol, iterations, min_matches, with_scale=False,
               scale_lo=1.0, scale_hi=1.0):
    """``crease_check.refine_on_creases`` in one pass per iteration: the correspondences of
    both channels (the second, e.g. the ridges, may have no samples), the 3x3 normal
    equations (accumulated, not from the (m, 3) Jacobian) and their solve (Cramer's rule);
    ``with_scale``: the 4x4 system with the scale too (solved by LU), ``|c|`` kept within
    ``[scale_lo, scale_hi]``.
    Sums in another order than numpy's: agrees to rounding."""
    n = z.size + z2.size
    p = np.empty(n, np.complex128)
    q = np.empty(n, np.complex128)
    normal = np.empty(n, np.complex128)
    for _ in range(iterations):
        turn_now = np.arctan2(c.imag, c.real)
        m, centroid = _icp_correspondences(z, direction, distance, field_dir, label,
                                           crease_z, crease_normal, c, t, turn_now, radius,
                                           angle_tol, p, q, normal, 0)
        if z2.size:
            m, more = _icp_correspondences(z2, direction2, distance2, field_dir2, label2,
                                           crease_z2, crease_normal2, c, t, turn_now,
                                           radius, angle_tol, p, q, normal, m)
            centroid += more
        if m < min_matches:
            break
        p0 = centroid / m
        if with_scale:
            c, t, settled = _scaled_icp_step(p, q, normal, m, p0, c, t, scale_lo, scale_hi)
            if settled:
                break
            continue
        # rotation, shift east, shift north: the terms without the scale's
        a00, _, a01, a02, _, _, _, a11, a12, a22, b0, _, b1, b2 = _icp_normal_sums(
            p, q, normal, m, p0, False)
        # Cramer's rule on the symmetric 3x3 system
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        if det == 0.0:
            break   # all correspondences on parallel creases: the shift along them is free
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        s0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
        s1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
        s2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
        turn = complex(np.cos(s0), np.sin(s0))
        shift = complex(s1, s2)
        c, t = turn * c, turn * t + p0 * (1.0 - turn) + shift
        if abs(s0) * 100.0 + abs(shift) < 0.01:
            break   # settled: < 0.01 px at 100 px from the centroid
    return c, t


@njit(**_JIT)
def _icp_normal_sums(p, q, normal, m, p0, with_scale):
    """The point-to-line ICP's normal equations ``J^T J`` (upper triangle, row by row) and
    ``-J^T r`` over the first ``m`` correspondences, the unknowns rotation, scale (zero
    without ``with_scale``), shift east and north about ``p0``: summed in registers, each
    in the order of the correspondences (as the 4x4 array's entries were; ``j[u] * j[v]``
    is ``j[v] * j[u]`` exactly, so the triangle gives the whole matrix)."""
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    for k in range(m):
        nc = normal[k].conjugate()
        r = (nc * (p[k] - q[k])).real
        j0 = (nc * 1j * (p[k] - p0)).real
        j1 = (nc * (p[k] - p0)).real if with_scale else 0.0
        j2 = normal[k].real
        j3 = normal[k].imag
        b0 -= j0 * r
        b1 -= j1 * r
        b2 -= j2 * r
        b3 -= j3 * r
        a00 += j0 * j0
        a01 += j0 * j1
        a02 += j0 * j2
        a03 += j0 * j3
        a11 += j1 * j1
        a12 += j1 * j2
        a13 += j1 * j3
        a22 += j2 * j2
        a23 += j2 * j3
        a33 += j3 * j3
    return a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3


@njit(**_JIT)
def _scaled_icp_step(p, q, normal, m, p0, c, t, scale_lo, scale_hi):
    """One point-to-line step for rotation, scale and shift about ``p0``: the new (c, t) and
    whether it settled. The scale step is bounded to 5 % and ``|c|`` to [scale_lo,
    scale_hi] (a few wrong pairings on parallel creases must not shrink the view onto
    them, nor a chance registration stretch to fit)."""
    a = np.empty((4, 4))
    b = np.empty(4)
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, b0, b1, b2, b3 = _icp_normal_sums(
        p, q, normal, m, p0, True)
    a[0, 0], a[0, 1], a[0, 2], a[0, 3] = a00, a01, a02, a03
    a[1, 0], a[1, 1], a[1, 2], a[1, 3] = a01, a11, a12, a13
    a[2, 0], a[2, 1], a[2, 2], a[2, 3] = a02, a12, a22, a23
    a[3, 0], a[3, 1], a[3, 2], a[3, 3] = a03, a13, a23, a33
    b[0], b[1], b[2], b[3] = b0, b1, b2, b3
    if abs(np.linalg.det(a)) < 1e-12:
        return c, t, True
    s = np.linalg.solve(a, b)
    ds = min(max(s[1], -0.05), 0.05)
    size = abs(c)
    ds = min(max((1.0 + ds) * size, scale_lo), scale_hi) / size - 1.0
    factor = (1.0 + ds) * complex(np.cos(s[0]), np.sin(s[0]))
    shift = complex(s[2], s[3])
    c, t = factor * c, factor * t + p0 * (1.0 - factor) + shift
    return c, t, abs(s[0]) * 100.0 + abs(ds) * 100.0 + abs(shift) < 0.01


@njit(**_JIT)
def compound_log10_sf(evidence, lam, k_max, log_fact):
    """``matching.compound_log10_sf`` after its bounds (``evidence > 0``, ``lam > 0``, the
    first ``k_max``): the same terms as loops. Sums in another order than numpy's: agrees to
    rounding."""
    log_lam = np.log(lam)
    log_pois = np.empty(k_max)
    for i in range(k_max):
        k = i + 1.0
        log_pois[i] = k * log_lam - lam - log_fact[i + 1]
    first = log_pois[0] - evidence + np.log1p(evidence)
    for i in range(k_max):
        if log_pois[i] < first - 40.0 and i + 1.0 > lam:
            k_max = i + 1
            break
    log_ev = np.log(evidence)
    n_j = 2 * k_max
    log_pmf = np.empty(n_j)
    for j in range(n_j):
        log_pmf[j] = j * log_ev - evidence - log_fact[j]
    top = log_pmf.max()
    log_terms = np.empty(k_max)
    cum = 0.0
    lost_pois = -np.inf   # the largest Poisson(lam) weight of a term whose Q underflowed
    for j in range(n_j):
        cum += np.exp(log_pmf[j] - top)
        if j % 2 == 1:
            log_terms[j // 2] = np.log(cum) + top + log_pois[j // 2]
            if cum == 0.0:
                lost_pois = max(lost_pois, log_pois[j // 2])
    if lost_pois + top - 745.0 > log_terms.max() - 40.0:
        # the underflowed terms might matter (huge evidence): the same sums in log space
        acc = -np.inf
        for j in range(n_j):
            acc = np.logaddexp(acc, log_pmf[j])
            if j % 2 == 1:
                log_terms[j // 2] = acc + log_pois[j // 2]
    peak = log_terms.max()
    total = 0.0
    for i in range(k_max):
        total += np.exp(log_terms[i] - peak)
    return (peak + np.log(total)) / np.log(10.0)


@njit(**_JIT)
def rotation_support(theta, w, mid_a, mid_b, rotations, limit, inv_bin):
    """Weight of the strongest translation cell at each of ``rotations`` (``matching.
    _rotation_support``): the votes within ``limit`` of the rotation, their translations at
    its weighted mean rotation, binned, and the heaviest 3 x 3 block of cells centred on a
    voted cell."""
    out = np.zeros(rotations.size)
    for k in range(rotations.size):
        sel, d = near_angles(theta, rotations[k], limit)
        if sel.size == 0:
            continue
        wsum = 0.0
        wd = 0.0
        for r in range(sel.size):
            wsum += w[sel[r]]
            wd += w[sel[r]] * d[r]
        if wsum <= 0.0:
            continue
        ang = rotations[k] + wd / wsum
        c = complex(np.cos(ang), np.sin(ang))
        t_re = np.empty(sel.size)
        t_im = np.empty(sel.size)
        ws = np.empty(sel.size)
        for r in range(sel.size):
            t = mid_b[sel[r]] - c * mid_a[sel[r]]
            t_re[r] = t.real
            t_im[r] = t.imag
            ws[r] = w[sel[r]]
        gx, gy, nx, ny, h = translation_grid(t_re, t_im, ws, inv_bin)
        best = 0.0
        for r in range(sel.size):
            s = 0.0
            for y in range(max(gy[r] - 1, 0), min(gy[r] + 2, ny)):
                for x in range(max(gx[r] - 1, 0), min(gx[r] + 2, nx)):
                    s += h[y * nx + x]
            best = max(best, s)
        out[k] = best
    return out


@njit(**_JIT)
def channel_cross_spectra(query, references, planes):
    """``sum_k conj(query[r, k]) * references[j, k]`` for each plane ``p = j * n_rot + r``
    of ``planes`` (``crease_search._correlations``), accumulated plane by plane
    (contiguous, so the loops vectorise) without numpy's temporary per channel: ``query``
    (n_rot, n_ch, h, w), ``references`` (n_ref, n_ch, h, w), complex64; out
    (len(planes), h, w)."""
    n_rot, n_ch, h, w = query.shape
    n_ref = references.shape[0]
    size = h * w
    q = query.reshape(n_rot, n_ch, size)
    ref = references.reshape(n_ref, n_ch, size)
    out = np.empty((planes.size, size), np.complex64)
    for i in range(planes.size):
        m, r = divmod(planes[i], n_rot)
        o = out[i]
        a = q[r, 0]
        b = ref[m, 0]
        for p in range(size):
            o[p] = np.conj(a[p]) * b[p]
        for k in range(1, n_ch):
            a = q[r, k]
            b = ref[m, k]
            for p in range(size):
                o[p] += np.conj(a[p]) * b[p]
    return out.reshape(planes.size, h, w)


@njit(**_JIT)
def box_mask(cum, row_lo, row_hi, col_lo, col_hi, threshold):
    """``out[r, i, j]``: whether the sum of rows ``[row_lo[i], row_hi[i])`` and cols
    ``[col_lo[j], col_hi[j])`` of raster ``r``, from its 2-D prefix sums ``cum`` (n_rot,
    h + 1, w + 1), reaches ``threshold`` (float32): ``crease_search.CreaseSearchQuery.
    searched`` without the (n_rot, h_pad, w_pad) counts."""
    n_rot = cum.shape[0]
    out = np.empty((n_rot, row_lo.size, col_lo.size), np.bool_)
    rows = np.empty(cum.shape[2], cum.dtype)
    for r in range(n_rot):
        for i in range(row_lo.size):
            a, b = row_lo[i], row_hi[i]
            if i and a == row_lo[i - 1] and b == row_hi[i - 1]:
                out[r, i] = out[r, i - 1]   # the same rows of the query (most shifts)
                continue
            # the row band's column sums: the prefix sums hold integer counts, exact in
            # float32 (< 2**24), so any order of the four terms gives the same sum
            for k in range(rows.size):
                rows[k] = cum[r, b, k] - cum[r, a, k]
            for j in range(col_lo.size):
                out[r, i, j] = rows[col_hi[j]] - rows[col_lo[j]] >= threshold
    return out


@njit(**_JIT)
def rasterise_transformed(z, c, col0, row0, direction, turn, h, w):
    """``crease_search.CreaseSearchQuery.raster``: the query's pixels ``z`` (math frame,
    search pixels) mapped by each transform ``c[r]`` (its angle ``turn[r]``), at column
    ``rint(Re(c z)) - col0`` and row ``rint(-Im(c z)) - row0`` (clipped to the raster),
    accumulated on (n_rot, 5, h, w): their direction channels (crease directions
    ``direction`` turned by ``turn``) and their count, one pass per transform without the
    numpy path's (n_rot, n) positions, indices and (4, n_rot, n) weights.
    The weights ``max(0, cos 2(d - k pi/4))`` are ``max(0, +-cos 2d)`` and ``max(0,
    +-sin 2d)``, turned by the angle-sum formulas: they agree with the numpy path's
    cosines to rounding."""
    n_rot, n = c.size, z.size
    c2d, s2d = np.cos(2.0 * direction), np.sin(2.0 * direction)
    acc = np.zeros((5, h, w))
    out = np.empty((n_rot, 5, h, w), np.float32)
    for r in range(n_rot):
        acc[:] = 0.0
        c2t, s2t = np.cos(2.0 * turn[r]), np.sin(2.0 * turn[r])
        cr = c[r]
        for i in range(n):
            q = cr * z[i]
            col = min(max(np.intp(np.rint(q.real) - col0[r]), 0), w - 1)
            row = min(max(np.intp(np.rint(-q.imag) - row0[r]), 0), h - 1)
            cos2 = c2d[i] * c2t - s2d[i] * s2t
            sin2 = s2d[i] * c2t + c2d[i] * s2t
            acc[0, row, col] += max(cos2, 0.0)
            acc[1, row, col] += max(sin2, 0.0)
            acc[2, row, col] += max(-cos2, 0.0)
            acc[3, row, col] += max(-sin2, 0.0)
            acc[4, row, col] += 1.0
        for k in range(5):
            for y in range(h):
                for x in range(w):
                    out[r, k, y, x] = acc[k, y, x]
    return out


@njit(**_JIT)
def local_shift_hits(padded, pad, z, direction, c, t, span):
    """``crease_search.local_peaks``' hits: per transform ``(c[m], t[m])`` (search pixels),
    the direction-consistent hits of the samples ``z`` (math frame, search pixels) on the
    reference's channels ``padded`` (4, h + 2 pad, w + 2 pad; zero beyond the reference) at
    every shift within ``span`` (<= ``pad``) search pixels, the best (the first of equals)
    and its shift ``(dx, dy)``. A sample weighs on two channels, ``max(0, +-cos 2d)`` and
    ``max(0, +-sin 2d)`` (turned by angle sums, as :func:`rasterise_transformed`'s
    weights): its two look-ups are placed once per transform, and each shift is then a sum
    over the samples at an offset of those places (sample order, float64; a sample whose
    shifts would leave the padding counts none)."""
    h, w = padded.shape[1] - 2 * pad, padded.shape[2] - 2 * pad
    row_len = padded.shape[2]
    plane = padded.shape[1] * row_len
    flat = padded.ravel()
    n = z.size
    c2d, s2d = np.cos(2.0 * direction), np.sin(2.0 * direction)
    side = 2 * span + 1
    best = np.empty(c.size)
    best_dx = np.empty(c.size, np.intp)
    best_dy = np.empty(c.size, np.intp)
    at_cos = np.empty(n, np.intp)
    at_sin = np.empty(n, np.intp)
    w_cos = np.empty(n)
    w_sin = np.empty(n)
    for m in range(c.size):
        turn = np.angle(c[m])
        c2t, s2t = np.cos(2.0 * turn), np.sin(2.0 * turn)
        for i in range(n):
            q = c[m] * z[i] + t[m]
            col = np.intp(np.rint(q.real))
            row = np.intp(np.rint(-q.imag))
            if col < span - pad or col > w - 1 + pad - span or row < span - pad \
                    or row > h - 1 + pad - span:
                # no weight, at a place whose shifts stay in the array
                at_cos[i] = at_sin[i] = pad * row_len + pad
                w_cos[i] = w_sin[i] = 0.0
                continue
            base = (row + pad) * row_len + col + pad
            cos2 = c2d[i] * c2t - s2d[i] * s2t
            sin2 = s2d[i] * c2t + c2d[i] * s2t
            if cos2 >= 0.0:
                at_cos[i], w_cos[i] = base, cos2
            else:
                at_cos[i], w_cos[i] = 2 * plane + base, -cos2
            if sin2 >= 0.0:
                at_sin[i], w_sin[i] = plane + base, sin2
            else:
                at_sin[i], w_sin[i] = 3 * plane + base, -sin2
        top = 0.0
        k_best = -1
        for dy in range(-span, span + 1):
            for dx in range(-span, span + 1):
                offset = dy * row_len + dx
                hits = 0.0
                for i in range(n):
                    hits += w_cos[i] * flat[at_cos[i] + offset] \
                        + w_sin[i] * flat[at_sin[i] + offset]
                if k_best < 0 or hits > top:
                    top = hits
                    k_best = (dy + span) * side + dx + span
        best[m] = top
        best_dy[m] = k_best // side - span
        best_dx[m] = k_best % side - span
    return best, best_dx, best_dy
