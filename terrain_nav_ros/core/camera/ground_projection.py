"""Camera frame -> north-up ground image (the core of the ``camera_ingest`` node).

Model:

* Pinhole intrinsics ``K`` plus the OpenCV lens model (``plumb_bob``/``rational_polynomial``
  coefficients k1, k2, p1, p2[, k3[, k4, k5, k6]]), or a fisheye's (``equidistant``: OpenCV's
  ``cv2.fisheye`` model, ``r = f theta_d``, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 +
  k3 theta^6 + k4 theta^8)``), as in ``sensor_msgs/CameraInfo``.
* Camera pose in the mission's local ENU frame: optical centre ``position`` (m) and rotation
  ``R`` taking camera-optical vectors to ENU (REP 103 ``*_optical`` frame: z forward along the
  optical axis, x right, y down in the image).
* Terrain approximated by the horizontal plane ``z = plane_height`` (the mean terrain height
  under the view). Then ground -> image is the homography ``K R^T [e1, e2, h e3 - C]``; with
  the output raster's pixel -> ENU affine map it becomes one 3x3 matrix from output pixels to
  undistorted image pixels.

:func:`project_to_ground` resamples the frame once: ``cv2.warpPerspective`` when there is no
lens distortion, otherwise ``cv2.remap`` through the homography followed by the OpenCV
distortion model (the same as ``cv2.undistort`` then warping, without resampling twice).
Output pixels whose ray points above the horizon or misses the frame are invalid in the mask.
Views that cannot be projected at all come back with a ``reason``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..terrain.georef import GeoReference
from .destripe import destripe

__all__ = [
    "CameraIntrinsics",
    "CameraPose",
    "GroundImage",
    "look_at_rotation",
    "nadir_rotation",
    "check_view",
    "mean_height_near",
    "image_to_ground",
    "ground_to_image",
    "ground_homography",
    "footprint_georef",
    "project_to_ground",
    "grey_frame",
]

_MIN_DEPTH = 1e-6  # m; ground points closer to the camera plane are behind it


#: Fields of view (deg) a pinhole model of a navigation camera can have: narrower sees a few
#: metres of ground from altitude, wider is a fisheye the polynomial models fold over.
FIELD_OF_VIEW = (0.1, 160.0)
#: ... and a fisheye (equidistant) model: up to a lens that sees behind itself.
FISHEYE_FIELD_OF_VIEW = (0.1, 240.0)
LENS_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics and OpenCV distortion of one camera.

    Parameters
    ----------
    fx, fy, cx, cy : float
        Focal lengths and principal point (px).
    width, height : int
        Image size (px).
    dist : tuple of float
        OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); empty or all zero
        for an ideal pinhole. For ``model="equidistant"``: the fisheye's k1-k4.
    model : str
        ``sensor_msgs/CameraInfo.distortion_model``: one of :data:`LENS_MODELS`.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple = ()
    model: str = "plumb_bob"

    def __post_init__(self):
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))

    @classmethod
    def from_matrix(cls, K, width: int, height: int, dist=(),
                    model: str = "plumb_bob") -> CameraIntrinsics:
        """From a 3x3 camera matrix (e.g. ``CameraInfo.k`` reshaped)."""
        K = np.asarray(K, float).reshape(3, 3)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height), tuple(dist),
                   model)

    @property
    def fisheye(self) -> bool:
        return self.model == "equidistant"

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion coefficients padded to OpenCV's length (5 or 8)."""
        d = list(self.dist)
        n = 5 if len(d) <= 5 else 8
        return np.array(d + [0.0] * (n - len(d)), float)

    @property
    def distorted(self) -> bool:
        return self.fisheye or any(d != 0.0 for d in self.dist)

    def rays(self, u, v) -> np.ndarray:
        """Camera-optical directions (N, 3) through pixels ``u, v`` (distorted): ``(x, y, 1)``
        for the polynomial models; unit vectors for a fisheye, whose rays may reach past
        90 deg from the axis (``z <= 0``)."""
        pts = np.column_stack([np.ravel(u), np.ravel(v)]).astype(np.float64)
        if self.fisheye:
            return self._fisheye_rays(pts)
        if self.distorted:
            norm = cv2.undistortPoints(pts[:, None, :], self.matrix, self.dist_coeffs)[:, 0, :]
        else:
            norm = np.column_stack([(pts[:, 0] - self.cx) / self.fx,
                                    (pts[:, 1] - self.cy) / self.fy])
        return np.column_stack([norm, np.ones(len(norm))])

    def project(self, points) -> np.ndarray:
        """Pixels (N, 2) of camera-optical points (N, 3) in front of the camera (z > 0)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if self.fisheye:
            x, y, z = points.T
            radius = np.hypot(x, y)
            theta_d = self._distorted_angle(np.arctan2(radius, z))
            scale = np.where(radius > 0, theta_d / np.maximum(radius, 1e-300), 0.0)
            return np.column_stack([self.fx * x * scale + self.cx,
                                    self.fy * y * scale + self.cy])
        return cv2.projectPoints(points[:, None, :], np.zeros(3), np.zeros(3), self.matrix,
                                 self.dist_coeffs)[0][:, 0, :]

    def pinhole_pixels(self, u, v) -> np.ndarray:
        """Where pixels ``u, v`` of the lens would be in the ideal pinhole camera ``K``
        (N, 2); NaN for a fisheye's rays at 90 deg or more from the axis."""
        d = self.rays(u, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = np.where(d[:, 2] > 0, d[:, 0] / d[:, 2], np.nan), \
                np.where(d[:, 2] > 0, d[:, 1] / d[:, 2], np.nan)
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])

    def _distorted_angle(self, theta):
        k = (list(self.dist) + [0.0] * 4)[:4]
        t2 = theta * theta
        return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))

    def _fisheye_rays(self, pts: np.ndarray) -> np.ndarray:
        """Unit rays of a fisheye's pixels: theta from theta_d by Newton's method."""
        xd, yd = (pts[:, 0] - self.cx) / self.fx, (pts[:, 1] - self.cy) / self.fy
        theta_d = np.hypot(xd, yd)
        theta = theta_d.copy()
        k = (list(self.dist) + [0.0] * 4)[:4]
        for _ in range(20):
            t2 = theta * theta
            f = self._distorted_angle(theta) - theta_d
            df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
            theta = np.clip(theta - f / np.where(np.abs(df) > 1e-12, df, 1e-12), 0.0, np.pi)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(theta_d > 0, np.sin(theta) / np.maximum(theta_d, 1e-300), 1.0)
        return np.column_stack([xd * c, yd * c, np.cos(theta)])

    def problem(self) -> str:
        """Why these intrinsics cannot be used ("" when they can)."""
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals + self.dist):
            return "camera intrinsics are not finite"
        if self.fx <= 0 or self.fy <= 0:
            return "camera intrinsics are zero or negative (no CameraInfo calibration)"
        if self.width <= 0 or self.height <= 0:
            return "camera image size is zero"
        if self.model not in LENS_MODELS:
            return f"unsupported distortion model '{self.model}'"
        if len(self.dist) not in ((0, 4) if self.fisheye else (0, 4, 5, 8)):
            return f"unsupported distortion model with {len(self.dist)} coefficients"
        limits = FISHEYE_FIELD_OF_VIEW if self.fisheye else FIELD_OF_VIEW
        for axis, size, focal in (("across", self.width, self.fx), ("down", self.height,
                                                                       self.fy)):
            half = 0.5 * size / focal     # equidistant: the angle; pinhole: its tangent
            fov = 2.0 * np.degrees(half if self.fisheye else np.arctan(half))
            if not limits[0] <= fov <= limits[1]:
                return (f"camera field of view {fov:.3g} deg {axis}: a focal length of "
                        f"{focal:g} px for {size} px (in another unit, or another image "
                        f"size?); a {'fisheye' if self.fisheye else 'pinhole'} camera sees "
                        f"{limits[0]:g}-{limits[1]:g} deg")
        return ""


@dataclass(frozen=True)
class CameraPose:
    """Camera optical centre and orientation in local ENU.

    Parameters
    ----------
    position : (3,) array
        Optical centre (east, north, up) in metres.
    rotation : (3, 3) array
        Rotation from the camera optical frame (x right, y down, z forward) to ENU.
    """

    position: np.ndarray
    rotation: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "position", np.asarray(self.position, float).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, float).reshape(3, 3))

    def problem(self) -> str:
        """Why this pose cannot be used ("" when it can)."""
        if not (np.isfinite(self.position).all() and np.isfinite(self.rotation).all()):
            return "camera pose is not finite"
        R = self.rotation
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            return "camera attitude is not a rotation matrix"
        return ""


def look_at_rotation(forward, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-optical -> ENU rotation for an optical axis ``forward`` (ENU).

    The image's "up" (-y) is the projection of ``up`` on the image plane, so a nadir view
    with ``up=(0, 1, 0)`` has North at the top of the image and East to the right.
    """
    z = np.asarray(forward, float)
    z = z / np.linalg.norm(z)
    up = np.asarray(up, float)
    y = -(up - (up @ z) * z)
    n = np.linalg.norm(y)
    if n < 1e-9:
        raise ValueError("look_at_rotation: up is parallel to forward")
    y /= n
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


def nadir_rotation(heading_deg: float = 0.0) -> np.ndarray:
    """Straight-down camera whose image top points to ``heading_deg`` (clockwise from North)."""
    h = np.deg2rad(heading_deg)
    return look_at_rotation((0.0, 0.0, -1.0), (np.sin(h), np.cos(h), 0.0))


def _ground_rays(u, v, intr: CameraIntrinsics, pose: CameraPose):
    """ENU ray directions through (distorted) pixels."""
    return intr.rays(u, v) @ pose.rotation.T


def image_to_ground(u, v, intr: CameraIntrinsics, pose: CameraPose, plane_height: float):
    """Intersect the rays through pixels (u, v) with the plane ``z = plane_height``.

    Returns
    -------
    east, north : arrays
        NaN where the ray does not reach the plane (at or above the horizon).
    """
    d = _ground_rays(u, v, intr, pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane_height - pose.position[2]) / d[:, 2]
    ok = np.isfinite(t) & (t > 0)
    east = np.where(ok, pose.position[0] + t * d[:, 0], np.nan)
    north = np.where(ok, pose.position[1] + t * d[:, 1], np.nan)
    shape = np.shape(u)
    return east.reshape(shape), north.reshape(shape)


def ground_to_image(east, north, plane_height, intr: CameraIntrinsics, pose: CameraPose):
    """Project ENU points (on the plane, or with their own heights) to distorted pixels.

    Returns
    -------
    u, v : arrays
        Pixel coordinates; NaN for points behind the camera.
    """
    east, north = np.broadcast_arrays(np.asarray(east, float), np.asarray(north, float))
    up = np.broadcast_to(np.asarray(plane_height, float), east.shape)
    X = np.column_stack([east.ravel(), north.ravel(), up.ravel()]) - pose.position
    cam = X @ pose.rotation  # rows: R^T (X - C)
    front = cam[:, 2] > _MIN_DEPTH
    uv = intr.project(cam)
    uv[~front] = np.nan
    return uv[:, 0].reshape(east.shape), uv[:, 1].reshape(east.shape)


def ground_homography(intr: CameraIntrinsics, pose: CameraPose, plane_height: float,
                      georef: GeoReference) -> np.ndarray:
    """3x3 map from output raster pixels (col, row, 1) to undistorted image pixels."""
    C = pose.position
    Rt = pose.rotation.T
    plane = np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                             np.array([0.0, 0.0, plane_height]) - C])
    g = georef.gsd
    pix_to_enu = np.array([[g, 0.0, georef.origin_east + 0.5 * g],
                           [0.0, -g, georef.origin_north - 0.5 * g],
                           [0.0, 0.0, 1.0]])
    return intr.matrix @ Rt @ plane @ pix_to_enu


def check_view(intr: CameraIntrinsics, pose: CameraPose, plane_height: float) -> str:
    """Why this view cannot be projected on the ground plane ("" when it can)."""
    reason = intr.problem() or pose.problem()
    if reason:
        return reason
    if pose.position[2] <= plane_height:
        return (f"camera at {pose.position[2]:.1f} m is not above the ground plane at "
                f"{plane_height:.1f} m")
    # The view reaches the ground iff some image corner/edge ray points below the horizon.
    w, h = intr.width, intr.height
    u = np.r_[np.linspace(0, w - 1, 9), np.full(9, w - 1), np.linspace(0, w - 1, 9),
              np.zeros(9), (w - 1) / 2]
    v = np.r_[np.zeros(9), np.linspace(0, h - 1, 9), np.full(9, h - 1),
              np.linspace(0, h - 1, 9), (h - 1) / 2]
    if not (_ground_rays(u, v, intr, pose)[:, 2] < 0).any():
        return "camera is pointing at or above the horizon: no ground in view"
    return ""


def mean_height_near(heights: np.ndarray, georef: GeoReference, east: float, north: float,
                     radius: float) -> tuple[float | None, str]:
    """Mean DEM height within ``radius`` of (east, north): ``(height, "")``, or
    ``(None, why)`` when the tile does not reach there or holds only nodata there (an
    all-nodata DEM read "no DEM tile under the aircraft yet", issue 22)."""
    c0, r0 = georef.enu_to_pixel(east - radius, north + radius)
    c1, r1 = georef.enu_to_pixel(east + radius, north - radius)
    c0, r0 = max(int(c0), 0), max(int(r0), 0)
    c1, r1 = min(int(c1) + 1, georef.width), min(int(r1) + 1, georef.height)
    if c1 <= c0 or r1 <= r0:
        return None, "the DEM tile does not reach the aircraft yet"
    window = heights[r0:r1, c0:c1]
    if not np.isfinite(window).any():
        return None, NO_HEIGHTS_BELOW
    return float(np.nanmean(window)), ""


NO_HEIGHTS_BELOW = "the DEM has no heights under the aircraft (nodata or voids)"
# radius (m) around the nadir whose mean DEM height is the first guess of the ground plane
NADIR_RADIUS = 200.0


def projection_plane(heights: np.ndarray, georef: GeoReference, intr: CameraIntrinsics,
                     pose: CameraPose, gsd: float, max_range_factor: float
                     ) -> tuple[float | None, GeoReference | None, float, str]:
    """The terrain plane a frame is projected on, the raster of its footprint and the
    horizontal range cut, or ``(None, None, nan, why)``.

    The plane is the mean DEM height near the nadir, then over the footprint that plane
    implies (a view's ground lies above or below its nadir's). An aircraft past the DEM's
    edge, or above a void, may still see ground the DEM holds (on a coast, or flying along a
    mission DEM's edge): the footprint of a plane at the tile's median height is measured
    instead, and the frame is a no-fix only when that footprint holds no heights either.
    Ground is cut at ``max_range_factor`` times the height above the first plane.

    Parameters
    ----------
    heights : ndarray
        DEM tile heights (NaN = nodata) on ``georef``.
    intr, pose : CameraIntrinsics, CameraPose
    gsd : float
        Ground raster's GSD (m/px).
    max_range_factor : float
        Farthest ground projected, in heights above ground.
    """
    plane, why = mean_height_near(heights, georef, pose.position[0], pose.position[1],
                                  NADIR_RADIUS)
    below = plane is not None
    if not below:
        finite = heights[np.isfinite(heights)]
        plane = float(np.median(finite)) if finite.size else math.nan
        if why != NO_HEIGHTS_BELOW or not plane < pose.position[2]:
            return None, None, math.nan, why
    max_range = max_range_factor * max(pose.position[2] - plane, 1.0)
    footprint = footprint_georef(intr, pose, plane, gsd, max_range)
    if footprint is not None:
        half = 0.5 * max(footprint.width, footprint.height) * gsd
        seen, _ = mean_height_near(heights, georef, *footprint.centre, half)
        if seen is not None and seen < pose.position[2]:
            plane = seen
            footprint = footprint_georef(intr, pose, plane, gsd, max_range)
        elif not below:
            return None, None, math.nan, why   # nor anywhere in view
    if footprint is None:
        return None, None, math.nan, check_view(intr, pose, plane)
    return plane, footprint, max_range, ""


def footprint_georef(intr: CameraIntrinsics, pose: CameraPose, plane_height: float,
                     gsd: float, max_range: float | None = None) -> GeoReference | None:
    """North-up raster at ``gsd`` covering the ground seen by the camera.

    Rays above (or close to) the horizon are cut at ``max_range`` metres of horizontal
    distance (default: 20 times the height above the plane). None if nothing is in view.
    """
    if check_view(intr, pose, plane_height):
        return None
    height = pose.position[2] - plane_height
    max_range = 20.0 * height if max_range is None else float(max_range)
    w, h = intr.width, intr.height
    s = np.linspace(0.0, 1.0, 33)
    u = np.r_[s * (w - 1), np.full_like(s, w - 1), s * (w - 1), np.zeros_like(s)]
    v = np.r_[np.zeros_like(s), s * (h - 1), np.full_like(s, h - 1), s * (h - 1)]
    d = _ground_rays(u, v, intr, pose)
    horiz = np.hypot(d[:, 0], d[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[:, 2] < 0, -height / d[:, 2], np.inf)
    t = np.minimum(t, max_range / np.maximum(horiz, 1e-12))
    e = pose.position[0] + t * d[:, 0]
    n = pose.position[1] + t * d[:, 1]
    west, east = np.floor(e.min() / gsd) * gsd, np.ceil(e.max() / gsd) * gsd
    south, north = np.floor(n.min() / gsd) * gsd, np.ceil(n.max() / gsd) * gsd
    return GeoReference(west, north, gsd, int(round((east - west) / gsd)),
                        int(round((north - south) / gsd)))


@dataclass
class GroundImage:
    """A frame resampled onto a north-up ground raster.

    ``image`` is None and ``reason`` says why when the view could not be projected;
    ``valid`` is False where the output pixel is not seen by the camera. ``frame_pixels``,
    where known, is the raw frame pixel ``(u, v)`` each output pixel was sampled at (the
    projection's own maps: where in the lens it was seen).
    """

    image: np.ndarray | None
    valid: np.ndarray | None
    georef: GeoReference
    reason: str = ""
    frame_pixels: tuple[np.ndarray, np.ndarray] | None = None


def grey_frame(image, intr: CameraIntrinsics, bgr: bool) -> tuple[np.ndarray, str]:
    """The frame as one grey channel, its sensor's row and column stripes taken off
    (:func:`~.destripe.destripe`), and why it does not fit ``intr`` ("" when it does)."""
    img = destripe(_to_grey(image, bgr))
    if img.shape != (intr.height, intr.width):
        return img, (f"image size {img.shape[::-1]} differs from CameraInfo "
                     f"{intr.width}x{intr.height}")
    if img.dtype.kind == "f":
        bad = img.size - np.count_nonzero(np.isfinite(img))
        if bad > img.size // 2:
            return img, (f"{100 * bad / img.size:.0f} % of the frame's pixels are not "
                         "numbers (NaN or inf)")
    return img, ""


def _to_grey(image: np.ndarray, bgr: bool) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)  # what OpenCV's colour conversion and warps accept
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = (cv2.COLOR_BGR2GRAY, cv2.COLOR_BGRA2GRAY) if bgr else (cv2.COLOR_RGB2GRAY,
                                                                      cv2.COLOR_RGBA2GRAY)
        img = cv2.cvtColor(np.ascontiguousarray(img), code[img.shape[2] == 4])
    if img.ndim != 2:
        raise ValueError(f"expected a grey or colour image, got shape {img.shape}")
    return img


def project_to_ground(image, intr: CameraIntrinsics, pose: CameraPose, plane_height: float,
                      georef: GeoReference, interpolation: int = cv2.INTER_LINEAR,
                      bgr: bool = False, max_range: float | None = None) -> GroundImage:
    """Resample a camera frame onto the ground raster ``georef``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3/4) array
        Raw (distorted) frame; colour is converted to grey (``bgr`` selects the channel
        order). uint8/uint16 stay as they are, other types become float32.
    intr, pose : CameraIntrinsics, CameraPose
    plane_height : float
        Height (m, ENU up) of the mean terrain plane.
    georef : GeoReference
        Output raster (north-up, at the landmark GSD).
    interpolation : int
        OpenCV interpolation flag.
    max_range : float, optional
        Output pixels farther than this horizontal distance (m) from the camera are invalid
        (grazing rays have meaningless resolution).

    Returns
    -------
    GroundImage
    """
    img, reason = grey_frame(image, intr, bgr)
    reason = check_view(intr, pose, plane_height) or reason
    if reason:
        return GroundImage(None, None, georef, reason)
    H = ground_homography(intr, pose, plane_height, georef)
    rows, cols = georef.shape
    # Depth of each output pixel's ground point along the optical axis: affine in (col, row).
    r3 = pose.rotation[:, 2]  # optical axis in ENU
    east, north = georef.pixel_to_enu(np.arange(cols), np.arange(rows))
    depth = (r3[0] * (east[None, :] - pose.position[0])
             + r3[1] * (north[:, None] - pose.position[1])
             + r3[2] * (plane_height - pose.position[2]))
    valid = depth > _MIN_DEPTH
    if max_range is not None:
        valid &= np.hypot(east[None, :] - pose.position[0],
                          north[:, None] - pose.position[1]) <= max_range
    if not intr.distorted:
        out = cv2.warpPerspective(img, H, (cols, rows), flags=interpolation |
                                  cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT)
        cc, rr = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows,
                                                                         dtype=np.float64))
        den = H[2, 0] * cc + H[2, 1] * rr + H[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (H[0, 0] * cc + H[0, 1] * rr + H[0, 2]) / den
            v = (H[1, 0] * cc + H[1, 1] * rr + H[1, 2]) / den
    else:
        cc, rr = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows,
                                                                         dtype=np.float64))
        pts = np.stack([cc, rr, np.ones_like(cc)], axis=-1) @ H.T
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = (pts[..., 0] / pts[..., 2] - intr.cx) / intr.fx
            yn = (pts[..., 1] / pts[..., 2] - intr.cy) / intr.fy
        # The polynomial lens model folds back far outside the frame: only distort rays
        # within a margin of the undistorted field of view. (A fisheye's does not.)
        if not intr.fisheye:
            lim_x = 1.5 * max(intr.cx, intr.width - intr.cx) / intr.fx
            lim_y = 1.5 * max(intr.cy, intr.height - intr.cy) / intr.fy
            valid &= (np.abs(xn) <= lim_x) & (np.abs(yn) <= lim_y)
        valid &= np.isfinite(xn) & np.isfinite(yn)
        xn = np.where(valid, xn, 0.0)
        yn = np.where(valid, yn, 0.0)
        uv = intr.project(np.stack([xn.ravel(), yn.ravel(), np.ones(xn.size)], axis=-1))
        u = uv[:, 0].reshape(rows, cols)
        v = uv[:, 1].reshape(rows, cols)
        out = cv2.remap(img, u.astype(np.float32), v.astype(np.float32), interpolation,
                        borderMode=cv2.BORDER_CONSTANT)
    # Interpolated from frame pixels only (no constant border mixed in).
    valid &= (u >= 0) & (u <= intr.width - 1) & (v >= 0) & (v <= intr.height - 1)
    if out.dtype.kind == "f":
        valid &= np.isfinite(out)       # a float frame's NaN pixels
    if not valid.any():
        return GroundImage(None, None, georef, "camera view does not reach the output raster")
    out[~valid] = 0
    return GroundImage(out, valid, georef, frame_pixels=(u, v))
