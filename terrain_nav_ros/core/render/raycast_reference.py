"""CPU reference ray caster for the landmark renderer (small images only).

Same height field (exact bilinear interpolation between pixel centres, clamped at the edges),
same cameras, same box and same shading formula as :mod:`terrain_nav_ros.core.render.renderer`, but
found by brute force: every ray is marched in fine fixed steps (default 0.1 DEM cell) from
where it enters the tile's box to where it leaves, and the first sample below the surface is
refined by the same secant + bisection + secant steps. Vectorised over pixels with numpy, float64.
It exists to test the GPU renderer, not to be fast.
"""

from __future__ import annotations

import numpy as np

from ..terrain.georef import GeoReference
from .renderer import (
    AlbedoRamp,
    NoTerrainVisibleError,
    PinholeCamera,
    RenderResult,
    TerrainFrame,
    albedo_lookup,
    bilinear_local,
    normal_map,
    resolve_sun,
    validate_pose,
    validate_terrain,
)

__all__ = ["ReferenceRaycaster", "bilinear_local"]


def _secant(lo, hi, g_lo, g_hi):
    """Secant estimate of the crossing in brackets [lo (above), hi (below)]."""
    denom = g_lo - g_hi
    ok = denom > 0
    return np.where(ok, lo + (hi - lo) * g_lo / np.where(ok, denom, 1.0), hi)


def _box_interval(o: np.ndarray, d: np.ndarray, box: np.ndarray):
    """Slab test: entry and exit ray parameters of the box [0, box] (arrays (N,))."""
    safe = np.where(np.abs(d) < 1e-12, 1e-12, d)
    ta = -o / safe
    tb = (box - o) / safe
    return np.minimum(ta, tb).max(axis=-1), np.maximum(ta, tb).min(axis=-1)


class ReferenceRaycaster:
    """Brute-force numpy counterpart of
    :class:`~terrain_nav_ros.core.render.renderer.LandmarkRenderer`.

    Parameters
    ----------
    heights : array_like (rows, cols)
    georef : GeoReference
    step_cells : float
        Fixed marching step along each ray, in DEM cells.
    refine_steps, hit_eps_cells, ambient, albedo
        As in the GPU renderer (same defaults).
    shadow_offset_cells : float
        Start of the shadow ray above the hit point, towards the sun (DEM cells); keep it
        equal to the GPU renderer's ``min_step_cells``.
    """

    def __init__(self, heights, georef: GeoReference, *, step_cells: float = 0.1,
                 refine_steps: int = 8, hit_eps_cells: float = 1e-3, ambient: float = 0.25,
                 albedo: AlbedoRamp | None = None,
                 shadow_offset_cells: float = 0.25):
        h = validate_terrain(heights, georef)
        self.frame = TerrainFrame.from_heights(h, georef)
        self.h_local = h - self.frame.z0
        self.normals = normal_map(h, georef.gsd)
        self.step = step_cells * georef.gsd
        self.refine_steps = refine_steps
        self.hit_eps = hit_eps_cells * georef.gsd
        self.ambient = ambient
        self.albedo_table = (albedo or AlbedoRamp()).table()
        # The shadow ray starts this far towards the sun; the GPU uses its min step.
        self.shadow_offset = shadow_offset_cells * georef.gsd

    def gap(self, p: np.ndarray) -> np.ndarray:
        """Height of points above the surface (tile-local), negative below."""
        return p[..., 2] - bilinear_local(self.h_local, self.frame.georef.gsd, p[..., :2])

    def trace(self, o: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        """First surface crossing of rays o + t d within [t0, t1]; NaN where none.

        Same decision rules as the shader: a ray starting below the surface hits at t0, a
        later sample within ``hit_eps`` above the surface is a hit, and the first sample
        below it is refined against the previous (above) sample.
        """
        n = len(o)
        t_hit = np.full(n, np.nan)
        lo, hi = np.full(n, np.nan), np.full(n, np.nan)
        g_lo, g_hi = np.full(n, np.nan), np.full(n, np.nan)
        t = t0.astype(float).copy()
        t_prev, g_prev = t.copy(), np.zeros(n)
        active = t0 <= t1
        first = True
        while active.any():
            idx = np.flatnonzero(active)
            g = self.gap(o[idx] + t[idx, None] * d[idx])
            below = g <= 0
            near = ~below & (g < self.hit_eps) & (not first)
            if first:
                t_hit[idx[below]] = t[idx[below]]
            else:
                b = idx[below]
                lo[b], hi[b], g_lo[b], g_hi[b] = t_prev[b], t[b], g_prev[b], g[below]
            t_hit[idx[near]] = t[idx[near]]
            done = below | near | (t[idx] >= t1[idx])
            active[idx[done]] = False
            keep = ~done
            idx, g = idx[keep], g[keep]
            t_prev[idx], g_prev[idx] = t[idx], g
            t[idx] = np.minimum(t[idx] + self.step, t1[idx])
            first = False
        todo = np.isfinite(lo)
        if todo.any():
            t_hit[todo] = self._refine(o[todo], d[todo], lo[todo], hi[todo], g_lo[todo],
                                       g_hi[todo])
        return t_hit

    def _refine(self, o, d, lo, hi, g_lo, g_hi):
        """Secant guess, bisection until within ``hit_eps``, final secant (as the shader)."""
        result = np.full(len(o), np.nan)
        open_ = np.ones(len(o), bool)
        for k in range(self.refine_steps):
            mid = _secant(lo, hi, g_lo, g_hi) if k == 0 else 0.5 * (lo + hi)
            g = self.gap(o + mid[:, None] * d)
            close = open_ & (np.abs(g) < self.hit_eps)
            result[close] = mid[close]
            open_ &= ~close
            above = g > 0
            lo, g_lo = np.where(above, mid, lo), np.where(above, g, g_lo)
            hi, g_hi = np.where(above, hi, mid), np.where(above, g_hi, g)
        result[open_] = _secant(lo, hi, g_lo, g_hi)[open_]
        return result

    def shade(self, p: np.ndarray, sun_local: np.ndarray, shadows: bool) -> np.ndarray:
        """Lambert shading of tile-local surface points with the elevation albedo."""
        n = bilinear_local(self.normals, self.frame.georef.gsd, p[:, :2])
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        diffuse = np.maximum(n @ sun_local, 0.0) if sun_local[2] > 0 else np.zeros(len(p))
        if shadows:
            lit = diffuse > 0
            s0 = p[lit] + sun_local * self.shadow_offset
            d = np.broadcast_to(sun_local, s0.shape)
            _, t1 = _box_interval(s0, d, self.frame.size)
            occluded = np.isfinite(self.trace(s0, d, np.zeros(len(s0)), np.maximum(t1, 0.0)))
            diffuse[np.flatnonzero(lit)[occluded]] = 0.0
        table, lo, hi = self.albedo_table
        alb = albedo_lookup(table, lo, hi, p[:, 2] + self.frame.z0)
        return alb * (self.ambient + (1 - self.ambient) * diffuse)[:, None]

    def _render(self, o, d, t0, t1, shape, sun, shadows, georef) -> RenderResult:
        t = self.trace(o, d, t0, t1)
        hit = np.isfinite(t)
        if not hit.any():
            raise NoTerrainVisibleError("the view sees no terrain")
        p = o[hit] + t[hit, None] * d[hit]
        rgb = np.zeros((len(o), 3))
        rgb[hit] = self.shade(p, resolve_sun(sun), shadows)
        hit_local = np.full((len(o), 3), np.nan)
        hit_local[hit] = p
        return RenderResult(rgb.reshape(*shape, 3).astype(np.float32),
                            hit_local.reshape(*shape, 3), self.frame.offset, 0, georef)

    def render_nadir(self, georef: GeoReference | None = None, sun=(315.0, 45.0), *,
                     shadows: bool = False) -> RenderResult:
        """Nadir orthographic image, pixel (r, c) = ``georef`` pixel (r, c)."""
        out = georef or self.frame.georef
        col, row = np.meshgrid(np.arange(out.width), np.arange(out.height))
        east, north = out.pixel_to_enu(col, row)
        xy = np.stack([east.ravel(), north.ravel()], -1) - self.frame.offset[:2]
        o = np.concatenate([xy, np.full((len(xy), 1), self.frame.top)], axis=1)
        d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
        t0, t1 = _box_interval(o, d, self.frame.size)
        inside = (xy >= 0).all(-1) & (xy <= self.frame.size[:2]).all(-1)
        t1 = np.where(inside, t1, -np.inf)
        return self._render(o, d, np.maximum(t0, 0.0), t1, out.shape, sun, shadows, out)

    def render_perspective(self, camera: PinholeCamera, position_enu, r_enu_optical,
                           sun=(315.0, 45.0), *, shadows: bool = False) -> RenderResult:
        """Pinhole view (optical frame x right, y down, z forward; R maps optical -> ENU)."""
        p, r = validate_pose(position_enu, r_enu_optical)
        d = camera.rays_optical().reshape(-1, 3) @ r.T
        o = np.broadcast_to(self.frame.to_local(p), d.shape)
        t0, t1 = _box_interval(o, d, self.frame.size)
        return self._render(o, d, np.maximum(t0, 0.0), t1, (camera.height, camera.width),
                            sun, shadows, None)
