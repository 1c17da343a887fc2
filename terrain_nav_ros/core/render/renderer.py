"""GPU landmark renderer: per-pixel displacement mapping with sphere tracing (dissertation 2.2).

Pipeline (one draw call per frame):

* Macro-geometry: the tile's bounding box (12 triangles) in *tile-local* metres
  ``x = east - west_edge``, ``y = north - south_edge``, ``z = up - z0`` (``z0`` a little below
  the lowest height). Its tangent frame is the ENU axes, so tangent space and tile-local space
  coincide; the TBN matrix is still applied in the vertex shader so a curved macro-surface can
  plug in. Only back faces are drawn: every pixel the box covers gets exactly one fragment,
  also when the camera is inside the box.
* Textures: the height map (R32F), a tangent-space normal map (central differences, RGBA32F),
  a 3-D distance map (R32F, lower bound of the Euclidean distance from each voxel centre to
  the terrain, :func:`build_distance_map`), a per-voxel-column Lipschitz map (largest
  terrain slope near the column, R32F) and an elevation albedo ramp (vegetation, rock, snow).
* Vertex shader: projects the box, passes tangent-space eye and light vectors.
* Fragment shader: sphere-traces the view ray. Each step is the largest *safe* one: the
  distance-map bound, or the slope (Lipschitz) bound for the current column, whichever is
  larger, never less than ``min_step`` (the march samples heights with hardware bilinear
  filtering). The first sample below the surface is refined by a
  secant step, bisection and a final secant step against the exactly bilinear height map,
  then shaded with normal-mapped Lambert lighting of a directional sun and the albedo
  ramp; optionally a second trace towards the sun casts shadows.
* Render targets: RGBA32F colour (alpha: 1 hit, 0 miss, -1 step budget exhausted) and RGBA32F
  tile-local hit position, read back as numpy arrays.

The GL context is injected (:func:`create_headless_context` makes one with EGL, which on a
CPU-only machine is Mesa llvmpipe). moderngl is imported lazily, so the numpy helpers here are
usable (e.g. by :mod:`terrain_nav_ros.core.render.raycast_reference`) without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage

from ..camera.ground_projection import CameraIntrinsics
from ..terrain.georef import GeoReference
from .sun import sun_direction_enu

__all__ = [
    "AlbedoRamp", "DistanceMap", "EGLUnavailableError", "InvalidTerrainError",
    "LandmarkRenderer", "NoTerrainVisibleError", "PinholeCamera", "RenderResult",
    "RendererError", "TerrainFrame", "bilinear_local", "build_distance_map", "build_lipschitz_map",
    "create_headless_context", "display_u8", "normal_map", "resolve_sun",
]


# Framebuffers kept, one per render size, the sizes used last (see ``_fbo``).
_KEPT_FRAMEBUFFERS = 4


# ----------------------------------------------------------------------------- errors
class RendererError(RuntimeError):
    """A rendering request that cannot be carried out."""


class EGLUnavailableError(RendererError):
    """No headless OpenGL 3.3 context could be created through EGL."""


class NoTerrainVisibleError(RendererError):
    """The requested view sees no terrain at all."""


class InvalidTerrainError(ValueError):
    """Heights or georeference that cannot be rendered (NaN, empty, mismatched)."""


# ----------------------------------------------------------------------------- context
def create_headless_context(require: int = 330):
    """Create a standalone OpenGL context through EGL (no display needed).

    Parameters
    ----------
    require : int, optional
        Minimum OpenGL version code (330 = 3.3 core).

    Returns
    -------
    moderngl.Context

    Raises
    ------
    EGLUnavailableError
        moderngl is missing, or EGL/the driver cannot give such a context (e.g. no libEGL or
        Mesa on the machine: install libegl-mesa0 and libgl1-mesa-dri on Debian).
    """
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - environment problem
        raise EGLUnavailableError("moderngl is not installed") from exc
    try:
        return moderngl.create_standalone_context(backend="egl", require=require)
    except Exception as exc:  # moderngl raises plain Exception for driver failures
        raise EGLUnavailableError(
            f"cannot create a headless EGL OpenGL {require // 100}.{require % 100 // 10} "
            f"context ({exc}); install Mesa's EGL (libegl-mesa0, libgl1-mesa-dri) or a GPU "
            "driver") from exc


# ----------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class PinholeCamera(CameraIntrinsics):
    """Pinhole intrinsics (:class:`~.camera.ground_projection.CameraIntrinsics`, OpenCV convention)
    that must be usable: checked at construction, since a render has no "no frame" answer.
    Lens distortion, if given, is ignored: renders are ideal pinhole images.
    """

    def __post_init__(self):
        super().__post_init__()
        problem = self.problem()
        if problem:
            raise ValueError(f"PinholeCamera: {problem} ({self})")

    def rays_optical(self) -> np.ndarray:
        """Unit ray directions in the optical frame, shape (height, width, 3)."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(float)
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy,
                      np.ones_like(u)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class AlbedoRamp:
    """Elevation-dependent surface colour: vegetation below the tree line, rock, then snow.

    Parameters
    ----------
    tree_line, snow_line : float
        Elevations (m, same datum as the heights) where vegetation gives way to rock and rock
        to snow; each transition is blended over ``blend`` metres.
    vegetation, rock, snow : tuple of float
        Linear RGB albedo of each class.
    lowland : tuple of float
        Colour at the lowest vegetation elevations (blends into ``vegetation`` by
        ``tree_line - 2 * blend``) so valleys and slopes differ a little.
    blend : float
        Width (m) of each transition.
    size : int
        Number of entries of the lookup table the GPU reads.
    """

    tree_line: float = 2400.0
    snow_line: float = 3400.0
    vegetation: tuple = (0.18, 0.30, 0.14)
    lowland: tuple = (0.32, 0.38, 0.20)
    rock: tuple = (0.45, 0.40, 0.36)
    snow: tuple = (0.90, 0.92, 0.95)
    blend: float = 150.0
    size: int = 256

    def table(self) -> tuple[np.ndarray, float, float]:
        """Lookup table (size, 3) and the elevations of its first and last entries."""
        lo = min(self.tree_line - 3 * self.blend, self.snow_line - 3 * self.blend)
        hi = max(self.snow_line + 2 * self.blend, self.tree_line + 2 * self.blend)
        z = np.linspace(lo, hi, self.size)
        veg_w = np.clip((z - lo) / max(self.tree_line - 2 * self.blend - lo, 1e-9), 0, 1)
        veg = np.outer(1 - veg_w, self.lowland) + np.outer(veg_w, self.vegetation)
        rock_w = np.clip((z - (self.tree_line - 0.5 * self.blend)) / self.blend, 0, 1)[:, None]
        snow_w = np.clip((z - (self.snow_line - 0.5 * self.blend)) / self.blend, 0, 1)[:, None]
        rgb = veg * (1 - rock_w) + np.asarray(self.rock) * rock_w
        rgb = rgb * (1 - snow_w) + np.asarray(self.snow) * snow_w
        return rgb.astype(np.float32), float(lo), float(hi)


def albedo_lookup(table: np.ndarray, lo: float, hi: float, elevation: np.ndarray) -> np.ndarray:
    """Linear interpolation in the albedo table, the same arithmetic as the shader."""
    n = table.shape[0]
    f = np.clip((np.asarray(elevation, float) - lo) / (hi - lo) * (n - 1), 0, n - 1)
    i0 = np.minimum(np.floor(f).astype(int), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (f - i0)[..., None]
    return table[i0] * (1 - w) + table[i1] * w


def resolve_sun(sun) -> np.ndarray:
    """Unit ENU vector towards the sun from ``(azimuth_deg, elevation_deg)`` or a 3-vector."""
    s = np.asarray(sun, dtype=float).ravel()
    if s.size == 2:
        s = sun_direction_enu(s[0], s[1])
    if s.size != 3 or not np.isfinite(s).all() or np.linalg.norm(s) == 0:
        raise ValueError(f"sun must be (azimuth_deg, elevation_deg) or a nonzero ENU vector, "
                         f"got {sun!r}")
    return s / np.linalg.norm(s)


# ----------------------------------------------------------------------------- terrain data
@dataclass(frozen=True)
class TerrainFrame:
    """Tile-local metric frame of a height tile and the box that bounds it.

    ``local = (east - west, north - south, up - z0)``; the box is
    ``[0, size_x] x [0, size_y] x [0, top]``.
    """

    georef: GeoReference
    z0: float
    top: float

    @classmethod
    def from_heights(cls, heights: np.ndarray, georef: GeoReference) -> TerrainFrame:
        """Frame with a margin of 1 % of the relief (>= 0.1 m) above and below the heights."""
        hmin, hmax = float(heights.min()), float(heights.max())
        pad = max(0.01 * (hmax - hmin), 0.1)
        return cls(georef, hmin - pad, hmax - hmin + 2 * pad)

    @property
    def size(self) -> np.ndarray:
        """(size_x, size_y, top): box extent in metres."""
        g = self.georef
        return np.array([g.width * g.gsd, g.height * g.gsd, self.top])

    @property
    def offset(self) -> np.ndarray:
        """ENU coordinates of the tile-local origin."""
        west, _, south, _ = self.georef.extent
        return np.array([west, south, self.z0])

    def to_local(self, enu) -> np.ndarray:
        return np.asarray(enu, dtype=float) - self.offset

    def to_enu(self, local) -> np.ndarray:
        return np.asarray(local, dtype=float) + self.offset


def validate_terrain(heights, georef: GeoReference) -> np.ndarray:
    """Check a height tile against its georeference; return it as float64.

    Raises
    ------
    InvalidTerrainError
        Empty tile, wrong shape, or non-finite heights.
    """
    h = np.asarray(heights, dtype=float)
    if h.ndim != 2 or h.size == 0:
        raise InvalidTerrainError(f"heights must be a non-empty 2-D array, got shape {h.shape}")
    if min(h.shape) < 2:
        raise InvalidTerrainError(f"heights must be at least 2x2, got shape {h.shape}")
    if h.shape != georef.shape:
        raise InvalidTerrainError(f"heights shape {h.shape} != georeference shape "
                                  f"{georef.shape}")
    bad = ~np.isfinite(h)
    if bad.any():
        raise InvalidTerrainError(f"heights contain {int(bad.sum())} NaN/inf values; fill "
                                  "voids (e.g. IDW interpolation) before rendering")
    return h


def bilinear_local(grid: np.ndarray, gsd: float, xy: np.ndarray) -> np.ndarray:
    """Bilinear sample of a north-up raster at tile-local (x east, y north) metres.

    Pixel centres are the samples; outside them the edge values are held (clamp to edge).
    The shader's ``bilinear`` does the same arithmetic.

    Parameters
    ----------
    grid : ndarray (rows, cols) or (rows, cols, k)
    gsd : float
    xy : ndarray (..., 2)

    Returns
    -------
    ndarray (...) or (..., k)
    """
    rows, cols = grid.shape[:2]
    fc = xy[..., 0] / gsd - 0.5
    fr = rows - xy[..., 1] / gsd - 0.5
    c0, r0 = np.floor(fc), np.floor(fr)
    wc, wr = fc - c0, fr - r0
    a_c = np.clip(c0, 0, cols - 1).astype(int)
    b_c = np.clip(c0 + 1, 0, cols - 1).astype(int)
    a_r = np.clip(r0, 0, rows - 1).astype(int)
    b_r = np.clip(r0 + 1, 0, rows - 1).astype(int)
    if grid.ndim == 3:
        wc, wr = wc[..., None], wr[..., None]
    top = grid[a_r, a_c] * (1 - wc) + grid[a_r, b_c] * wc
    bot = grid[b_r, a_c] * (1 - wc) + grid[b_r, b_c] * wc
    return top * (1 - wr) + bot * wr


def normal_map(heights: np.ndarray, gsd: float) -> np.ndarray:
    """Unit surface normals in tangent space (east, north, up), shape (rows, cols, 3).

    Central differences (one-sided at the border) of the north-up raster; rows grow
    southwards, hence the sign of the north derivative.
    """
    dh_drow, dh_dcol = np.gradient(np.asarray(heights, float), gsd)
    n = np.stack([-dh_dcol, dh_drow, np.ones_like(dh_dcol)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@dataclass(frozen=True)
class DistanceMap:
    """Conservative 3-D distance map over a tile's box (see :func:`build_distance_map`).

    ``values[k, j, i]`` (z, north, east order) is a lower bound of the distance (m) from
    voxel centre ``((i, j, k) + 0.5) * voxel`` to the terrain solid; so for any point ``p``,
    ``values[nearest voxel] - |p - centre|`` bounds its distance to the terrain from below.
    """

    values: np.ndarray
    voxel: np.ndarray

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        nz, ny, nx = self.values.shape
        return nx, ny, nz


def _column_ranges(n_vox: int, n_cells: int, vox: float, gsd: float):
    """Inclusive DEM index ranges of the samples whose bilinear patches touch each voxel."""
    lo = np.arange(n_vox) * vox / gsd - 0.5
    hi = (np.arange(n_vox) + 1) * vox / gsd - 0.5
    return (np.clip(np.floor(lo), 0, n_cells - 1).astype(int),
            np.clip(np.ceil(hi), 0, n_cells - 1).astype(int))


def _footprint_reduce(field: np.ndarray, frame: TerrainFrame, nx: int, ny: int,
                      reduce=np.max) -> np.ndarray:
    """Reduce a DEM-sized field over each voxel column's footprint, shape (ny, nx), y north-up."""
    g = frame.georef
    size = frame.size
    c_lo, c_hi = _column_ranges(nx, g.width, size[0] / nx, g.gsd)
    # Voxel rows count northwards from the south edge; DEM rows southwards from the north.
    r_lo_s, r_hi_s = _column_ranges(ny, g.height, size[1] / ny, g.gsd)
    r_lo, r_hi = g.height - 1 - r_hi_s, g.height - 1 - r_lo_s
    cols = np.stack([reduce(field[:, a:b + 1], axis=1) for a, b in zip(c_lo, c_hi, strict=True)],
                    axis=1)
    return np.stack([reduce(cols[a:b + 1], axis=0) for a, b in zip(r_lo, r_hi, strict=True)])


def distance_map_shape(frame: TerrainFrame, cells_per_voxel: float = 4.0,
                       max_size: int = 256) -> tuple[int, int, int]:
    """Default (nx, ny, nz): about ``cells_per_voxel`` DEM cells per voxel, cubic-ish voxels."""
    g = frame.georef
    nx = int(np.clip(np.ceil(g.width / cells_per_voxel), 1, max_size))
    ny = int(np.clip(np.ceil(g.height / cells_per_voxel), 1, max_size))
    vox = max(frame.size[0] / nx, frame.size[1] / ny)
    nz = int(np.clip(np.ceil(frame.top / vox), 4, 128))
    return nx, ny, nz


def _envelope_distance(col_max: np.ndarray, voxel: np.ndarray, nz: int,
                       radius: int) -> np.ndarray:
    """Exact distance from voxel centres to the columns ``footprint x (-inf, col_max]``.

    Only columns within ``radius`` voxels are searched; farther ones are at least
    ``(radius + 0.5)`` voxels away, which caps the result (still a lower bound).
    """
    ny, nx = col_max.shape
    z = ((np.arange(nz) + 0.5) * voxel[2]).astype(np.float32)[:, None, None]
    padded = np.pad(col_max.astype(np.float32), radius, constant_values=-np.inf)
    best = np.full((nz, ny, nx), np.inf, np.float32)
    for dj in range(-radius, radius + 1):
        for di in range(-radius, radius + 1):
            # From a column centre to the nearest edge of the column (di, dj) away.
            h2 = ((max(abs(di) - 0.5, 0.0) * voxel[0]) ** 2
                  + (max(abs(dj) - 0.5, 0.0) * voxel[1]) ** 2)
            m = padded[radius + dj:radius + dj + ny, radius + di:radius + di + nx]
            dz = np.maximum(z - m, 0.0)
            np.minimum(best, dz * dz + np.float32(h2), out=best)
    return np.minimum(np.sqrt(best), np.float32((radius + 0.5) * min(voxel[0], voxel[1])))


def build_distance_map(heights: np.ndarray, frame: TerrainFrame,
                       shape_xyz: tuple[int, int, int] | None = None,
                       near_radius: int = 3) -> DistanceMap:
    """Lower bounds of the distance from each voxel centre to the terrain.

    The terrain solid lies inside the *envelope*: each voxel column's footprint from below up
    to the highest height sample touching it (a bilinear patch never exceeds its corners).
    Two bounds are combined, taking the larger:

    * far field: mark voxels whose bottom is below their column's envelope, take scipy's
      Euclidean distance transform between voxel centres and subtract half a voxel diagonal
      (every solid point is that close to a marked centre);
    * near field: the exact distance to the envelope columns within ``near_radius`` voxels,
      which is much tighter close to the surface, where sphere tracing spends its steps.

    Parameters
    ----------
    heights : ndarray (rows, cols)
        Heights (m), row 0 north, matching ``frame.georef``.
    frame : TerrainFrame
    shape_xyz : (nx, ny, nz), optional
        Voxel counts; default :func:`distance_map_shape`.
    near_radius : int, optional
        Search radius (voxels) of the near-field bound; 0 uses the EDT bound alone.

    Returns
    -------
    DistanceMap
    """
    nx, ny, nz = shape_xyz or distance_map_shape(frame)
    voxel = frame.size / np.array([nx, ny, nz])
    col_max = _footprint_reduce(heights - frame.z0, frame, nx, ny)
    z_bottom = np.arange(nz) * voxel[2]
    solid = z_bottom[:, None, None] <= col_max[None, :, :]
    edt = ndimage.distance_transform_edt(~solid, sampling=(voxel[2], voxel[1], voxel[0]))
    values = (edt - 0.5 * float(np.linalg.norm(voxel))).astype(np.float32)
    if near_radius > 0:
        np.maximum(values, _envelope_distance(col_max, voxel, nz, near_radius), out=values)
    return DistanceMap(values, voxel)


def build_lipschitz_map(heights: np.ndarray, frame: TerrainFrame, nx: int, ny: int) -> np.ndarray:
    """Largest slope of the bilinear surface around each voxel column, shape (ny, nx).

    The bound covers the column's footprint dilated by one voxel in every direction, so it
    holds along any ray step that moves at most one voxel horizontally (the shader caps slope
    steps to that).
    """
    g = frame.georef
    h = np.asarray(heights, float)
    # Per-sample max |difference| to its east/south neighbours, then to both sides.
    dx = np.abs(np.diff(h, axis=1)) / g.gsd
    dy = np.abs(np.diff(h, axis=0)) / g.gsd
    sx = np.maximum(np.pad(dx, ((0, 0), (0, 1))), np.pad(dx, ((0, 0), (1, 0))))
    sy = np.maximum(np.pad(dy, ((0, 1), (0, 0))), np.pad(dy, ((1, 0), (0, 0))))
    lip = np.hypot(_footprint_reduce(sx, frame, nx, ny), _footprint_reduce(sy, frame, nx, ny))
    return ndimage.maximum_filter(lip, size=3, mode="nearest").astype(np.float32)


# ----------------------------------------------------------------------------- camera maths
def ortho_nadir_mvp(frame: TerrainFrame, out: GeoReference) -> np.ndarray:
    """Clip transform of the nadir view: framebuffer row r is exactly ``out``'s row r."""
    west, east, south, north = out.extent
    off = frame.offset
    m = np.zeros((4, 4))
    m[0, 0] = 2.0 / (east - west)
    m[0, 3] = -1.0 - 2.0 * (west - off[0]) / (east - west)
    # Row 0 (north) goes to framebuffer y = 0 (bottom), i.e. NDC y = -1 at the north edge.
    m[1, 1] = -2.0 / (north - south)
    m[1, 3] = -1.0 + 2.0 * (north - off[1]) / (north - south)
    m[3, 3] = 1.0  # clip z = 0: depth is unused
    return m


def pinhole_mvp(camera: PinholeCamera, frame: TerrainFrame, position_enu,
                r_enu_optical, near: float = 1e-3, far: float = 1e7) -> np.ndarray:
    """Clip transform tile-local -> camera; framebuffer row v is image row v (y down)."""
    r = np.asarray(r_enu_optical, float)
    t_local = frame.to_local(position_enu)
    view = np.eye(4)
    view[:3, :3] = r.T
    view[:3, 3] = -r.T @ t_local
    w, h = camera.width, camera.height
    proj = np.zeros((4, 4))
    proj[0, 0] = 2 * camera.fx / w
    proj[0, 2] = 2 * (camera.cx + 0.5) / w - 1
    proj[1, 1] = 2 * camera.fy / h
    proj[1, 2] = 2 * (camera.cy + 0.5) / h - 1
    proj[2, 2] = (far + near) / (far - near)
    proj[2, 3] = -2 * far * near / (far - near)
    proj[3, 2] = 1.0
    return proj @ view


def validate_pose(position_enu, r_enu_optical) -> tuple[np.ndarray, np.ndarray]:
    """Finite position and a proper rotation matrix (orthonormal, det +1), else ValueError."""
    p = np.asarray(position_enu, float).reshape(-1)
    r = np.asarray(r_enu_optical, float)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"camera position must be a finite ENU 3-vector, got {position_enu!r}")
    if r.shape != (3, 3) or not np.isfinite(r).all() or \
            not np.allclose(r.T @ r, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
        raise ValueError("camera attitude must be a 3x3 rotation matrix (optical -> ENU)")
    return p, r


# ----------------------------------------------------------------------------- results
@dataclass
class RenderResult:
    """One rendered frame.

    Attributes
    ----------
    rgb : ndarray (H, W, 3) float32
        Linear RGB radiance in [0, 1]; 0 where no terrain.
    hit_local : ndarray (H, W, 3) float32
        Tile-local position (m) of the surface point each pixel sees; NaN where none.
    origin : ndarray (3,)
        ENU coordinates of the tile-local origin (kept apart for float32 precision).
    unresolved : int
        Pixels whose ray ran out of steps before hitting or leaving the tile (NaN too).
    georef : GeoReference or None
        Placement of the image for nadir renders.
    """

    rgb: np.ndarray
    hit_local: np.ndarray
    origin: np.ndarray
    unresolved: int = 0
    georef: GeoReference | None = None

    @cached_property
    def hit_enu(self) -> np.ndarray:
        """(H, W, 3) float64 ENU position (m) of each pixel's surface point; NaN where none."""
        return self.hit_local.astype(np.float64) + self.origin

    @property
    def mask(self) -> np.ndarray:
        """True where the pixel sees terrain."""
        return np.isfinite(self.hit_local[..., 0])

    @property
    def grey(self) -> np.ndarray:
        """Luminance (Rec. 601 weights), float32 in [0, 1]."""
        return self.rgb @ np.array([0.299, 0.587, 0.114], np.float32)

    @property
    def grey_u8(self) -> np.ndarray:
        return np.clip(np.rint(self.grey * 255), 0, 255).astype(np.uint8)

    @property
    def rgb_u8(self) -> np.ndarray:
        return np.clip(np.rint(self.rgb * 255), 0, 255).astype(np.uint8)


def display_u8(grey: np.ndarray) -> np.ndarray:
    """Linear grey in [0, 1] -> uint8 with the display gamma (1/2.2) a camera applies: the
    landmark image the graph publishes and extracts features from."""
    return np.clip(np.rint(255.0 * np.clip(grey, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- shaders
VERTEX_SHADER = """
#version 330
uniform mat4 u_mvp;        // tile-local metres -> clip space
uniform mat3 u_tbn;        // macro-surface tangent frame (columns T, B, N) in tile-local axes
uniform bool u_ortho;
uniform vec3 u_cam;        // perspective eye, tile-local
uniform vec3 u_view_dir;   // orthographic view direction, tile-local
uniform vec3 u_sun;        // towards the sun, tile-local (ENU)
in vec3 in_pos;
out vec3 v_pos;            // tangent-space position of this back-face point
out vec3 v_eye;            // tangent-space eye vector (eye -> point)
flat out vec3 v_light;     // tangent-space light vector
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    mat3 to_tangent = transpose(u_tbn);
    v_pos = to_tangent * in_pos;
    v_eye = to_tangent * (u_ortho ? u_view_dir : in_pos - u_cam);
    v_light = to_tangent * u_sun;
}
"""

FRAGMENT_SHADER = """
#version 330
uniform sampler2D u_height;    // R32F heights - z0, texel (col, row), row 0 north; linear
uniform sampler2D u_normal;    // RGBA32F tangent-space normals
uniform sampler3D u_dist;      // R32F conservative distance (m), texel (x, y, z)
uniform sampler2D u_lip;       // R32F max slope around each voxel column
uniform sampler2D u_albedo;    // RGBA32F elevation ramp, one row
uniform sampler2D u_photo;     // RGBA32F draped orthophoto on the DEM grid (set_photo)
uniform bool u_use_photo;      // show the photo as it is (it holds its own sun)
uniform ivec2 u_dem_size;      // (cols, rows)
uniform float u_gsd;
uniform vec3 u_box;            // box extent (m)
uniform vec3 u_voxel;          // distance-map voxel size (m)
uniform ivec3 u_dm_size;
uniform float u_z0;
uniform vec2 u_albedo_range;   // elevations of the first and last ramp entries
uniform int u_albedo_n;
uniform float u_min_step;
uniform float u_lod_step;     // extra min step per metre from the eye (pixel footprint)
uniform int u_max_steps;
uniform int u_refine_steps;
uniform float u_hit_eps;      // gap (m) that counts as on the surface
uniform float u_ambient;
uniform bool u_shadows;
uniform bool u_slope_steps;
uniform bool u_ortho;
uniform vec3 u_cam;
in vec3 v_pos;
in vec3 v_eye;
flat in vec3 v_light;
layout(location = 0) out vec4 out_color;   // rgb, a: 1 hit, 0 miss, -1 unresolved
layout(location = 1) out vec4 out_hit;     // tile-local hit position, w = ray parameter

// Exact bilinear interpolation between pixel centres, clamped at the edges (what the CPU
// reference does); texelFetch avoids the reduced weight precision of hardware filtering.
vec2 dem_coord(vec2 xy) {
    return vec2(xy.x / u_gsd - 0.5, float(u_dem_size.y) - xy.y / u_gsd - 0.5);
}
vec4 bilinear(sampler2D tex, vec2 xy) {
    vec2 f = dem_coord(xy);
    vec2 i0 = floor(f);
    vec2 w = f - i0;
    ivec2 a = clamp(ivec2(i0), ivec2(0), u_dem_size - 1);
    ivec2 b = clamp(ivec2(i0) + 1, ivec2(0), u_dem_size - 1);
    vec4 top = mix(texelFetch(tex, a, 0), texelFetch(tex, ivec2(b.x, a.y), 0), w.x);
    vec4 bot = mix(texelFetch(tex, ivec2(a.x, b.y), 0), texelFetch(tex, b, 0), w.x);
    return mix(top, bot, w.y);
}
float gap(vec3 p) { return p.z - bilinear(u_height, p.xy).r; }
// The march uses one hardware-filtered fetch instead (~20 % faster on llvmpipe, which
// filters float textures exactly; GPUs may round the weights to 8 bits, harmless there).
float gap_fast(vec3 p) {
    return p.z - texture(u_height, vec2(p.x / u_box.x, 1.0 - p.y / u_box.y)).r;
}

// Largest step along d from p that cannot cross the surface.
float safe_step(vec3 p, vec3 d, float g, float min_step) {
    ivec3 idx = clamp(ivec3(floor(p / u_voxel)), ivec3(0), u_dm_size - 1);
    vec3 centre = (vec3(idx) + 0.5) * u_voxel;
    float s = texelFetch(u_dist, idx, 0).r - length(p - centre);
    // Slope bound: the gap shrinks at most by (L |d_xy| - d_z) per metre, valid while the
    // step stays within one voxel horizontally (the Lipschitz map covers the neighbours).
    if (!u_slope_steps) return max(s, min_step);
    float l = texelFetch(u_lip, idx.xy, 0).r;
    float dxy = length(d.xy);
    float rate = l * dxy - d.z;
    float cap = dxy > 1e-6 ? min(u_voxel.x, u_voxel.y) / dxy : 1e30;
    float s_lip = rate > 0.0 ? min(g / rate, cap) : cap;
    return max(max(s, s_lip), min_step);
}

// Secant estimate of the crossing in a bracket [lo (above), hi (below)].
float secant(float lo, float hi, float g_lo, float g_hi) {
    return g_lo - g_hi > 0.0 ? lo + (hi - lo) * g_lo / (g_lo - g_hi) : hi;
}

// Refine a bracket: a secant guess first (exact where the surface is locally planar, e.g.
// after a slope step landed on it), then bisection until the gap is within u_hit_eps,
// then a final secant step.
float refine(vec3 o, vec3 d, float lo, float hi, float g_lo, float g_hi) {
    for (int k = 0; k < u_refine_steps; ++k) {
        float mid = k == 0 ? secant(lo, hi, g_lo, g_hi) : 0.5 * (lo + hi);
        float g = gap(o + mid * d);
        if (abs(g) < u_hit_eps) return mid;
        if (g > 0.0) { lo = mid; g_lo = g; } else { hi = mid; g_hi = g; }
    }
    return secant(lo, hi, g_lo, g_hi);
}

// First crossing of the ray o + t d, t in [t0, t1]: t >= 0 hit, -1 miss, -2 out of steps.
// A ray starting below the surface hits at t0; one that converges to within u_hit_eps
// above it (slope steps approach the surface from above) hits there. The smallest step
// grows with the distance from the eye, eye_dist + t, to a fraction of a pixel footprint.
float trace(vec3 o, vec3 d, float t0, float t1, float eye_dist) {
    float t_prev = t0;
    float g_prev = 0.0;
    float t = t0;
    for (int i = 0; i < u_max_steps; ++i) {
        vec3 p = o + t * d;
        float g = gap_fast(p);
        if (g <= 0.0) return i == 0 ? t : refine(o, d, t_prev, t, g_prev, g);
        if (g < u_hit_eps && i > 0) return t;
        if (t >= t1) return -1.0;
        t_prev = t;
        g_prev = g;
        float min_step = max(u_min_step, u_lod_step * (eye_dist + t));
        t = min(t + safe_step(p, d, g, min_step), t1);
    }
    return -2.0;
}

// Ray parameter interval inside the box (slab test).
vec2 box_interval(vec3 o, vec3 d) {
    vec3 safe_d = mix(d, vec3(1e-12), lessThan(abs(d), vec3(1e-12)));
    vec3 ta = -o / safe_d;
    vec3 tb = (u_box - o) / safe_d;
    vec3 tmin = min(ta, tb);
    vec3 tmax = max(ta, tb);
    return vec2(max(max(tmin.x, tmin.y), tmin.z), min(min(tmax.x, tmax.y), tmax.z));
}

vec3 albedo(float elevation) {
    float f = clamp((elevation - u_albedo_range.x) / (u_albedo_range.y - u_albedo_range.x)
                    * float(u_albedo_n - 1), 0.0, float(u_albedo_n - 1));
    int i0 = min(int(floor(f)), u_albedo_n - 1);
    int i1 = min(i0 + 1, u_albedo_n - 1);
    return mix(texelFetch(u_albedo, ivec2(i0, 0), 0).rgb,
               texelFetch(u_albedo, ivec2(i1, 0), 0).rgb, f - float(i0));
}

void main() {
    vec3 d = normalize(v_eye);
    vec3 o;
    float t0;
    float t1;
    if (u_ortho) {
        // Start on the box top above the back-face point (d points down), so t stays small
        // and float32 keeps millimetre precision.
        o = v_pos - d * ((u_box.z - v_pos.z) / max(-d.z, 1e-6));
        t0 = max(box_interval(o, d).x, 0.0);
        t1 = dot(v_pos - o, d);
    } else {
        o = u_cam;
        t0 = max(box_interval(o, d).x, 0.0);
        t1 = dot(v_pos - o, d);
    }
    float t = trace(o, d, t0, t1, 0.0);
    if (t < 0.0) {
        out_color = vec4(0.0, 0.0, 0.0, t < -1.5 ? -1.0 : 0.0);
        out_hit = vec4(0.0);
        return;
    }
    vec3 p = o + t * d;
    if (u_use_photo) {
        // a real orthophoto already shows the terrain lit by its sun: draped, not relit
        out_color = vec4(bilinear(u_photo, p.xy).rgb, 1.0);
        out_hit = vec4(p, t);
        return;
    }
    vec3 n = normalize(bilinear(u_normal, p.xy).xyz);
    vec3 l = normalize(v_light);
    float diffuse = l.z > 0.0 ? max(dot(n, l), 0.0) : 0.0;  // no direct light at night
    if (u_shadows && diffuse > 0.0) {
        vec3 s0 = p + l * u_min_step;
        float ts = trace(s0, l, 0.0, max(box_interval(s0, l).y, 0.0), t);
        if (ts >= 0.0) diffuse = 0.0;  // an unresolved shadow ray (-2) counts as lit
    }
    vec3 rgb = albedo(p.z + u_z0) * (u_ambient + (1.0 - u_ambient) * diffuse);
    out_color = vec4(rgb, 1.0);
    out_hit = vec4(p, t);
}
"""


def _box_triangles(size: np.ndarray) -> np.ndarray:
    """The 12 triangles of the box [0, size], counter-clockwise seen from outside."""
    x, y, z = size
    v = np.array([[0, 0, 0], [x, 0, 0], [x, y, 0], [0, y, 0],
                  [0, 0, z], [x, 0, z], [x, y, z], [0, y, z]], dtype=np.float32)
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    idx = [i for a, b, c, e in quads for i in (a, b, c, a, c, e)]
    return v[idx]


# ----------------------------------------------------------------------------- renderer
class LandmarkRenderer:
    """Reusable GPU renderer for one height tile at a time.

    Parameters
    ----------
    ctx : moderngl.Context
        OpenGL >= 3.3 context (see :func:`create_headless_context`).
    max_steps : int
        Sphere-tracing iteration budget per ray.
    min_step_cells : float
        Smallest tracing step, in DEM cells; features thinner than this along a grazing ray
        may be stepped over.
    lod_pixels : float
        Perspective views: the smallest step also grows to this fraction of the pixel
        footprint at the ray's distance (0 disables), which keeps far, grazing rays cheap.
    refine_steps : int
        Most refinement steps (secant, then bisection) after the first sample below the
        surface.
    hit_eps_cells : float
        A gap below this many DEM cells counts as on the surface.
    cells_per_voxel : float
        Distance-map resolution: DEM cells per voxel (at most ``max_voxels`` per axis).
    max_voxels : int
    ambient : float
        Fraction of the albedo seen in full shadow.
    shadows : bool
        Default for cast shadows (can be overridden per call).
    slope_steps : bool
        Also take slope-bound (Lipschitz) steps where they are longer than the distance-map
        step; off gives plain distance-map sphere tracing.
    albedo : AlbedoRamp
    """

    def __init__(self, ctx, *, max_steps: int = 256, min_step_cells: float = 0.25,
                 lod_pixels: float = 0.5,
                 refine_steps: int = 8, hit_eps_cells: float = 1e-3,
                 cells_per_voxel: float = 4.0, max_voxels: int = 256,
                 ambient: float = 0.25, shadows: bool = False, slope_steps: bool = True,
                 albedo: AlbedoRamp | None = None):
        if ctx.version_code < 330:
            raise EGLUnavailableError(f"OpenGL 3.3 needed, context has {ctx.version_code}")
        self.ctx = ctx
        self.max_steps = int(max_steps)
        self.min_step_cells = float(min_step_cells)
        self.lod_pixels = float(lod_pixels)
        self.refine_steps = int(refine_steps)
        self.hit_eps_cells = float(hit_eps_cells)
        self.cells_per_voxel = float(cells_per_voxel)
        self.max_voxels = int(max_voxels)
        self.ambient = float(ambient)
        self.shadows = bool(shadows)
        self.slope_steps = bool(slope_steps)
        self.albedo = albedo or AlbedoRamp()
        self.program = ctx.program(vertex_shader=VERTEX_SHADER,
                                   fragment_shader=FRAGMENT_SHADER)
        self._textures: dict = {}
        self._fbos: dict = {}
        self._vbo = None
        self._vao = None
        self.frame: TerrainFrame | None = None
        self.heights: np.ndarray | None = None
        self.distance_map: DistanceMap | None = None
        self._set_albedo(self.albedo)
        self._photo = False
        self._texture("photo", np.zeros((1, 1, 4), np.float32))

    # -- resources
    def _texture(self, name: str, data: np.ndarray, *, dims: int = 2):
        """(Re)upload a float32 texture; reuse the GL object when the size is unchanged."""
        import moderngl

        data = np.ascontiguousarray(data, dtype=np.float32)
        comps = 1 if data.ndim == dims else data.shape[-1]
        size = tuple(reversed(data.shape[:dims]))
        tex = self._textures.get(name)
        if tex is None or tex.size != size or tex.components != comps:
            if tex is not None:
                tex.release()
            make = self.ctx.texture3d if dims == 3 else self.ctx.texture
            tex = make(size, comps, dtype="f4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)  # exact texelFetch sampling
            self._textures[name] = tex
        tex.write(data.tobytes())
        return tex

    def _set_albedo(self, ramp: AlbedoRamp):
        table, lo, hi = ramp.table()
        rgba = np.concatenate([table, np.ones((len(table), 1), np.float32)], axis=1)
        self._texture("albedo", rgba[None])
        self._albedo_range = (lo, hi, len(table))

    def set_albedo(self, ramp: AlbedoRamp):
        """Replace the elevation albedo ramp."""
        self.albedo = ramp
        self._set_albedo(ramp)

    def set_photo(self, rgb: np.ndarray | None):
        """Drape a real orthophoto over the terrain, or remove it (``None``).

        Parameters
        ----------
        rgb : ndarray (rows, cols, 3) or None
            Linear RGB in [0, 1] on the grid of the heights of :meth:`set_terrain` (pixel
            (r, c) at height (r, c)). The photo already holds its own sun's shading and
            shadows: it is shown as it is, not lit again (the sun of a render then only
            matters for its absence of effect). Set after :meth:`set_terrain`; a new
            terrain removes it.
        """
        if rgb is None:
            self._photo = False
            return
        if self.heights is None:
            raise RendererError("set_terrain() must be called before set_photo()")
        rgb = np.asarray(rgb, np.float32)
        if rgb.shape != (*self.heights.shape, 3) or not np.isfinite(rgb).all():
            raise ValueError(f"photo must be finite, shaped {(*self.heights.shape, 3)} like "
                             f"the terrain; got {rgb.shape}")
        self._texture("photo", np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=-1))
        self._photo = True

    def set_terrain(self, heights, georef: GeoReference, *, distance_map_voxels=None):
        """Upload a height tile and build its normal, distance and slope maps.

        Parameters
        ----------
        heights : array_like (rows, cols)
            Heights (m), north-up, matching ``georef``.
        georef : GeoReference
        distance_map_voxels : (nx, ny, nz), optional
            Override the distance-map resolution.

        Raises
        ------
        InvalidTerrainError
            Empty, mismatched or non-finite heights, or larger than a GL texture.
        """
        import moderngl

        h = validate_terrain(heights, georef)
        limit = int(self.ctx.info["GL_MAX_TEXTURE_SIZE"])
        if max(h.shape) > limit:
            raise InvalidTerrainError(f"tile {h.shape} exceeds the GL texture limit {limit}; "
                                      "split it into smaller tiles")
        frame = TerrainFrame.from_heights(h, georef)
        shape = distance_map_voxels or distance_map_shape(frame, self.cells_per_voxel,
                                                          self.max_voxels)
        dmap = build_distance_map(h, frame, shape)
        lip = build_lipschitz_map(h, frame, shape[0], shape[1])
        normals = normal_map(h, georef.gsd)
        height_tex = self._texture("height", h - frame.z0)
        height_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        height_tex.repeat_x = height_tex.repeat_y = False  # clamp to edge, like the reference
        self._texture("normal", np.concatenate([normals, np.zeros_like(normals[..., :1])], -1))
        self._texture("dist", dmap.values, dims=3)
        self._texture("lip", lip)
        box = _box_triangles(frame.size)
        if self._vbo is None:
            self._vbo = self.ctx.buffer(box.tobytes())
            self._vao = self.ctx.vertex_array(self.program, [(self._vbo, "3f", "in_pos")])
        else:
            self._vbo.write(box.tobytes())
        self.frame, self.heights, self.distance_map = frame, h, dmap
        self._h_local = h - frame.z0
        self._photo = False

    def _fbo(self, width: int, height: int):
        """The framebuffer of a size, kept for the next render of it; only the
        :data:`_KEPT_FRAMEBUFFERS` sizes used last are kept (a landmark tile's size follows
        the position's uncertainty: a long flight renders hundreds, 10-34 MB each)."""
        key = (width, height)
        if key in self._fbos:
            self._fbos[key] = self._fbos.pop(key)   # (now the last used)
        else:
            while len(self._fbos) >= _KEPT_FRAMEBUFFERS:
                oldest = self._fbos.pop(next(iter(self._fbos)))
                for texture in oldest.color_attachments:
                    texture.release()
                oldest.release()
            attachments = [self.ctx.texture((width, height), 4, dtype="f4") for _ in range(2)]
            self._fbos[key] = self.ctx.framebuffer(color_attachments=attachments)
        return self._fbos[key]

    # -- rendering
    def _draw(self, width: int, height: int, mvp: np.ndarray, uniforms: dict,
              georef: GeoReference | None) -> RenderResult:
        if self.frame is None:
            raise RendererError("set_terrain() must be called before rendering")
        frame = self.frame
        g = frame.georef
        dm = self.distance_map
        lo, hi, n = self._albedo_range
        values = {
            "u_mvp": mvp.T.astype("f4").tobytes(),
            "u_tbn": np.eye(3, dtype="f4").tobytes(),
            "u_dem_size": (g.width, g.height), "u_gsd": g.gsd,
            "u_box": tuple(frame.size), "u_voxel": tuple(dm.voxel),
            "u_dm_size": dm.shape_xyz, "u_z0": frame.z0,
            "u_albedo_range": (lo, hi), "u_albedo_n": n,
            "u_min_step": self.min_step_cells * g.gsd, "u_max_steps": self.max_steps,
            "u_refine_steps": self.refine_steps, "u_ambient": self.ambient,
            "u_slope_steps": self.slope_steps, "u_hit_eps": self.hit_eps_cells * g.gsd,
            "u_use_photo": self._photo,
            **uniforms,
        }
        prog = self.program
        for name, value in values.items():
            if name not in prog:
                continue
            if isinstance(value, bytes):
                prog[name].write(value)
            else:
                prog[name].value = value
        for unit, name in enumerate(("height", "normal", "dist", "lip", "albedo", "photo")):
            self._textures[name].use(unit)
            if f"u_{name}" in prog:
                prog[f"u_{name}"].value = unit

        import moderngl
        fbo = self._fbo(width, height)
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx = self.ctx
        ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
        ctx.enable(moderngl.CULL_FACE)
        ctx.cull_face = "front"
        # Both projections flip y (row 0 at the framebuffer bottom), which flips winding.
        ctx.front_face = "cw"
        self._vao.render(moderngl.TRIANGLES)
        # Fresh, writable arrays each frame (results must not alias the next frame's).
        color = np.empty((height, width, 4), np.float32)
        hit = np.empty((height, width, 4), np.float32)
        fbo.read_into(color, components=4, attachment=0, dtype="f4")
        fbo.read_into(hit, components=4, attachment=1, dtype="f4")
        flag = color[..., 3]
        unresolved = int(np.count_nonzero(flag < -0.5))
        miss = flag < 0.5
        if miss.all():
            if unresolved:
                raise RendererError(f"no ray resolved: {unresolved} ran out of max_steps="
                                    f"{self.max_steps} before hitting or leaving the tile")
            raise NoTerrainVisibleError(
                "the view sees no terrain (camera outside or facing away from the tile)")
        hit_local = hit[..., :3]
        hit_local[miss] = np.nan
        # The shader writes black for misses, so rgb needs no masking; contiguous for OpenCV.
        return RenderResult(np.ascontiguousarray(color[..., :3]), hit_local, frame.offset,
                            unresolved, georef)

    def render_nadir(self, georef: GeoReference | None = None, sun=(315.0, 45.0), *,
                     shadows: bool | None = None) -> RenderResult:
        """Orthographic north-up nadir landmark image.

        Parameters
        ----------
        georef : GeoReference, optional
            Output raster (any GSD, size and placement); pixel (r, c) of the result is exactly
            pixel (r, c) of ``georef``. Defaults to the tile's own georeference.
        sun : (azimuth_deg, elevation_deg) or ENU vector towards the sun
        shadows : bool, optional
            Cast shadows; default the renderer's setting.

        Returns
        -------
        RenderResult
        """
        if self.frame is None:
            raise RendererError("set_terrain() must be called before rendering")
        out = georef or self.frame.georef
        if out.width == 0 or out.height == 0:
            raise ValueError(f"empty output raster {out.width}x{out.height}")
        uniforms = {"u_ortho": True, "u_view_dir": (0.0, 0.0, -1.0), "u_cam": (0.0, 0.0, 0.0),
                    "u_lod_step": 0.0,
                    "u_sun": tuple(resolve_sun(sun)),
                    "u_shadows": self.shadows if shadows is None else bool(shadows)}
        return self._draw(out.width, out.height, ortho_nadir_mvp(self.frame, out), uniforms,
                          out)

    def render_perspective(self, camera: PinholeCamera, position_enu, r_enu_optical,
                           sun=(315.0, 45.0), *, shadows: bool | None = None) -> RenderResult:
        """Perspective pinhole view of the tile.

        Parameters
        ----------
        camera : PinholeCamera
        position_enu : array_like (3,)
            Camera centre in ENU metres (same frame as the tile's georeference).
        r_enu_optical : array_like (3, 3)
            Rotation from the camera optical frame (x right, y down, z forward) to ENU.
        sun, shadows
            As in :meth:`render_nadir`.

        Raises
        ------
        ValueError
            Bad pose, or camera below the terrain surface.
        NoTerrainVisibleError
            No pixel sees the tile.
        """
        if self.frame is None:
            raise RendererError("set_terrain() must be called before rendering")
        p, r = validate_pose(position_enu, r_enu_optical)
        local = self.frame.to_local(p)
        if self._inside_xy(local) and local[2] <= self._height_local(local[:2]):
            raise ValueError(f"camera at {p} is below the terrain surface")
        uniforms = {"u_ortho": False, "u_view_dir": (0.0, 0.0, -1.0),
                    "u_cam": tuple(local), "u_sun": tuple(resolve_sun(sun)),
                    "u_lod_step": self.lod_pixels / max(camera.fx, camera.fy),
                    "u_shadows": self.shadows if shadows is None else bool(shadows)}
        return self._draw(camera.width, camera.height,
                          pinhole_mvp(camera, self.frame, p, r), uniforms, None)

    def _inside_xy(self, local) -> bool:
        size = self.frame.size
        return bool(0 <= local[0] <= size[0] and 0 <= local[1] <= size[1])

    def _height_local(self, xy) -> float:
        return float(bilinear_local(self._h_local, self.frame.georef.gsd,
                                    np.asarray(xy, float)[None])[0])

    def release(self):
        """Free the GL objects (the context stays the caller's)."""
        attachments = [t for f in self._fbos.values() for t in f.color_attachments]
        for obj in [*self._textures.values(), *self._fbos.values(), *attachments, self._vbo,
                    self._vao, self.program]:
            if obj is not None:
                obj.release()
        self._textures.clear()
        self._fbos.clear()
        self._vbo = self._vao = None
