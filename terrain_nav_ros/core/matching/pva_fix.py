"""Aircraft position (and attitude) fixes from a minutiae registration (issue 6, PVA fix).

Two ways, matching the two kinds of camera minutiae the pipeline can produce:

* :func:`fix_from_ground_match`: the camera frame was projected onto a north-up ground raster
  with the prior pose (``camera_ingest``), its minutiae were localised in the landmark with
  :func:`~terrain_nav_ros.core.matching.matcher.localise`. The registration maps the ground point
  the prior put under the camera to where it really is, which moves the camera by the same
  amount; its rotation corrects the heading and, when a scale was measured, its scale
  corrects the height above ground. Covariance: the registration's (from the pairing
  residuals), the GSD quantisation and the landmark's own georeferencing error. Limitation:
  on a ground-plane projection a tilt error ``d`` at height ``H`` shifts the image by about
  ``H * d``, which this path reports as position; add the prior attitude uncertainty times
  ``H`` to the position covariance, or use the PnP path when the attitude prior is weak.
* :func:`fix_from_pnp`: the camera minutiae are also known in raw image pixels; the paired
  landmark minutiae become 3-D points with DEM heights and ``cv2.solvePnP`` (RANSAC, then
  Levenberg-Marquardt from the prior) gives the full camera pose. Covariance: Gauss-Newton
  ``sigma^2 (J^T J)^-1`` from the reprojection residuals, propagated to the camera centre
  and a world-frame attitude error. Attitude is reported only when it is well determined.

Conventions are those of :mod:`terrain_nav_ros.core.camera.ground_projection`: ENU metres; camera
pose = optical centre ``position`` and ``rotation`` from the camera optical frame (x right,
y down, z forward) to ENU. Status codes mirror ``terrain_nav_msgs/PvaFix``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from ..terrain.georef import GeoReference
from .matcher import Decision, MatchResult

STATUS_NO_FIX = 0
STATUS_POSITION = 1
STATUS_POSITION_ATTITUDE = 2


@dataclass
class PvaFixEstimate:
    """A fix, ready to be converted to ``terrain_nav_msgs/PvaFix``.

    Attributes
    ----------
    status : int
        :data:`STATUS_NO_FIX`, :data:`STATUS_POSITION` or :data:`STATUS_POSITION_ATTITUDE`.
    reason : str
        Why there is no fix, or notes on the fix.
    position : ndarray (3,)
        Camera optical centre, ENU metres.
    rotation : ndarray (3, 3)
        Camera optical -> ENU; the prior when the attitude was not estimated.
    covariance : ndarray (6, 6)
        (x, y, z, rot x, rot y, rot z) in ENU; rotation errors are small world-frame rotation
        vectors (rad). When the attitude was not estimated the rotation block's diagonal is -1
        (robot_localization's "not measured").
    yaw_correction, yaw_variance : float
        Heading change (rad, CCW about Up) found by a ground match, and its variance.
    similarity : float
    num_pairings, num_camera_minutiae, num_landmark_minutiae : int
    relocalisation : bool
        True when the fix was found by a search of the whole mission area (a global query),
        independent of the navigation estimate; False for a fix searched around the estimate.
        The filter resets onto relocalisations only when several agree.
    projection_height : float
        For a ground match: the camera's height (m) above the plane the prior projected the
        frame on. The fix is the ground point the prior attitude put below the camera, so a
        tilt error of that attitude moves it by about this height times the error; the
        covariance leaves that out for the filter, which knows its own attitude error, to
        model (``TerrainEkf.process_fix``). 0 when the tilt error is in the covariance
        (:func:`~.fix_stream.add_prior_tilt`) or does not apply (PnP).
    mosaic_lag : float
        For a fix from a track mosaic (:mod:`~..camera.track_mosaic`): the mean age (s) of
        its pixels. Its frames were moved into the newest frame's estimate by the filter's
        dead reckoning, so the fix measures the position less this times the estimate's
        velocity error, which the filter models (``TerrainEkf.process_fix``). 0 for a frame.
    """

    status: int
    reason: str = ""
    position: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    yaw_correction: float = 0.0
    yaw_variance: float = -1.0
    similarity: float = float("nan")
    num_pairings: int = 0
    num_camera_minutiae: int = 0
    num_landmark_minutiae: int = 0
    relocalisation: bool = False
    projection_height: float = 0.0
    mosaic_lag: float = 0.0

    @property
    def valid(self) -> bool:
        """True when the position is usable."""
        return self.status != STATUS_NO_FIX


def _no_fix(result: MatchResult | None, reason: str) -> PvaFixEstimate:
    fix = PvaFixEstimate(STATUS_NO_FIX, reason)
    if result is not None:
        fix.similarity = float(result.score)
        fix.num_pairings = int(result.n_pairings)
        fix.num_camera_minutiae = int(result.n_a)
        fix.num_landmark_minutiae = int(result.n_b)
    return fix


def _fill_match(fix: PvaFixEstimate, result: MatchResult) -> PvaFixEstimate:
    fix.similarity = float(result.score)
    fix.num_pairings = int(result.n_pairings)
    fix.num_camera_minutiae = int(result.n_a)
    fix.num_landmark_minutiae = int(result.n_b)
    return fix


def _pixel_cov_to_enu(cov_px: np.ndarray, gsd: float) -> np.ndarray:
    # east = +col * gsd, north = -row * gsd
    flip = np.diag([gsd, -gsd])
    return flip @ cov_px @ flip.T


def fix_from_ground_match(result: MatchResult, camera_georef: GeoReference,
                          landmark_georef: GeoReference, prior_position,
                          prior_rotation, ground_height: float,
                          landmark_sigma: float = 0.0,
                          height_sigma: float | None = None,
                          height_from_scale: bool = True) -> PvaFixEstimate:
    """Camera position from a localisation of a ground-projected camera set.

    Parameters
    ----------
    result : MatchResult
        :func:`~terrain_nav_ros.core.matching.matcher.localise` of the ground-image minutiae (A) in
        the landmark minutiae (B).
    camera_georef : GeoReference
        Where the prior put the ground image (its raster).
    landmark_georef : GeoReference
        The landmark raster.
    prior_position : array (3,)
        Prior camera centre (ENU) used for the ground projection.
    prior_rotation : array (3, 3)
        Prior camera optical -> ENU rotation (returned unchanged as the orientation).
    ground_height : float
        Height (m) of the plane the frame was projected on.
    landmark_sigma : float
        1-sigma horizontal georeferencing error of the landmark/DEM (m), added in quadrature.
    height_sigma : float, optional
        1-sigma of the height when the registration has no scale (default: 10% of the height
        above ground, i.e. "barely measured").
    height_from_scale : bool
        Take the height from the registration's measured scale. False: the prior's, with
        ``height_sigma`` (a relocalisation: the plane the frame was projected on lies under
        the estimate, not under the camera, and the scale measures the height above it).

    Returns
    -------
    PvaFixEstimate
        Status :data:`STATUS_POSITION`; the heading correction is in ``yaw_correction``, the
        height the prior's tilt error acts over in ``projection_height``.
    """
    if result.decision != Decision.MATCH:
        return _no_fix(result, f"no terrain match: {result.reason or result.decision.value}")
    prior_position = np.asarray(prior_position, float).reshape(3)
    agl = prior_position[2] - ground_height
    if not agl > 0:
        return _no_fix(result, f"camera {agl:.1f} m above the projection plane")
    # the ground point the prior placed under the camera, in ground-image pixels
    c0, r0 = camera_georef.enu_to_pixel(prior_position[0], prior_position[1])
    cl, rl = result.apply(c0, r0)
    east, north = landmark_georef.pixel_to_enu(cl, rl)
    cov = np.zeros((6, 6))
    cov[:2, :2] = _pixel_cov_to_enu(result.point_covariance(float(c0), float(r0)),
                                    landmark_georef.gsd)
    cov[:2, :2] += np.eye(2) * (landmark_georef.gsd ** 2 / 12.0 + landmark_sigma ** 2)
    # ground-image distances shrink by prior_agl / true_agl: the fitted scale restores them
    gsd_ratio = landmark_georef.gsd / camera_georef.gsd
    a, b = result.transform[0, 0], result.transform[0, 1]
    if height_from_scale and math.isfinite(result.scale_measured) and \
            math.isfinite(result.scale_variance):
        z = ground_height + result.scale_measured * gsd_ratio * agl
        var_z = result.scale_variance * (gsd_ratio * agl) ** 2
    elif height_from_scale and result.scale_estimated and np.isfinite(result.covariance).all():
        # d|c|/d(a, b) = (a, b) / |c|
        g = np.array([a, b]) / max(np.hypot(a, b), 1e-12)
        var_s = float(g @ result.covariance[:2, :2] @ g) * gsd_ratio ** 2
        z = ground_height + result.scale * gsd_ratio * agl
        var_z = var_s * agl ** 2
    else:
        z = prior_position[2]
        var_z = (0.1 * agl if height_sigma is None else height_sigma) ** 2
    cov[2, 2] = var_z
    cov[3:, 3:] = -np.eye(3)
    # heading: theta = atan2(b, a); var from the (a, b) block
    r2 = max(a * a + b * b, 1e-12)
    g = np.array([-b, a]) / r2
    yaw_var = float(g @ result.covariance[:2, :2] @ g) if np.isfinite(
        result.covariance).all() else -1.0
    fix = PvaFixEstimate(STATUS_POSITION, "", np.array([float(east), float(north), z]),
                         np.asarray(prior_rotation, float).reshape(3, 3), cov,
                         yaw_correction=float(result.rotation), yaw_variance=yaw_var,
                         projection_height=float(agl))
    return _fill_match(fix, result)


def dem_heights(dem: np.ndarray, dem_georef: GeoReference, east, north) -> np.ndarray:
    """Bilinear DEM heights at ENU points (NaN outside the DEM)."""
    col, row = dem_georef.enu_to_pixel(east, north)
    return ndimage.map_coordinates(np.asarray(dem, float), [np.ravel(row), np.ravel(col)],
                                   order=1, mode="constant", cval=np.nan).reshape(np.shape(east))


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel()


def _pose_from_params(p: np.ndarray):
    """(camera centre ENU, camera->ENU rotation) from OpenCV (rvec, tvec)."""
    r_cw = cv2.Rodrigues(np.ascontiguousarray(p[:3]))[0]
    return -r_cw.T @ p[3:], r_cw.T


def fix_from_pnp(result: MatchResult, camera_pixels, landmark_enu, landmark_heights,
                 camera_matrix, dist_coeffs=(), prior_position=None, prior_rotation=None,
                 reprojection_tol: float = 4.0, min_points: int = 6,
                 max_attitude_sigma: float = np.radians(3.0),
                 landmark_sigma: float = 0.0) -> PvaFixEstimate:
    """Camera pose by PnP over the paired minutiae's 3-D DEM points.

    Parameters
    ----------
    result : MatchResult
        Registration whose ``pairings`` index the camera minutiae (A) and landmark
        minutiae (B).
    camera_pixels : ndarray (n_a, 2)
        Raw (distorted) image pixel (u, v) of every camera minutia.
    landmark_enu : tuple of ndarray (n_b,)
        (east, north) of every landmark minutia (e.g. ``landmark_set.enu()``).
    landmark_heights : ndarray (n_b,)
        Terrain height (m) at each landmark minutia (e.g. :func:`dem_heights`).
    camera_matrix : array (3, 3)
    dist_coeffs : sequence of float
        OpenCV distortion coefficients.
    prior_position, prior_rotation : optional
        Prior camera centre and optical -> ENU rotation, used as the starting point (without
        them a RANSAC EPnP solution is used).
    reprojection_tol : float
        RANSAC inlier threshold (px).
    min_points : int
        Minimum inlier pairings for a fix.
    max_attitude_sigma : float
        The attitude is reported (status 2) only when its largest 1-sigma is below this.
    landmark_sigma : float
        Horizontal georeferencing error of the landmark (m), added to the position.

    Returns
    -------
    PvaFixEstimate
    """
    if result.decision != Decision.MATCH:
        return _no_fix(result, f"no terrain match: {result.reason or result.decision.value}")
    pairs = result.pairings
    east, north = (np.asarray(v, float) for v in landmark_enu)
    heights = np.asarray(landmark_heights, float)
    obj = np.column_stack([east[pairs[:, 1]], north[pairs[:, 1]], heights[pairs[:, 1]]])
    img = np.asarray(camera_pixels, float)[pairs[:, 0]]
    ok = np.isfinite(obj).all(axis=1) & np.isfinite(img).all(axis=1)
    obj, img = obj[ok], img[ok]
    if len(obj) < min_points:
        return _no_fix(result, f"only {len(obj)} pairings with DEM heights for PnP "
                               f"(need {min_points})")
    k = np.asarray(camera_matrix, float).reshape(3, 3)
    dist = np.asarray(dist_coeffs, float).ravel() if len(dist_coeffs) else np.zeros(0)
    # centre the object points: better conditioned for the solver
    origin = obj.mean(axis=0)
    objc = np.ascontiguousarray(obj - origin)
    imgc = np.ascontiguousarray(img.reshape(-1, 1, 2))
    guess = prior_position is not None and prior_rotation is not None
    if guess:
        r_cw = np.asarray(prior_rotation, float).reshape(3, 3).T
        rvec = _rotation_vector(r_cw).reshape(3, 1)
        tvec = (-r_cw @ (np.asarray(prior_position, float).reshape(3) - origin)).reshape(3, 1)
    else:
        rvec, tvec = np.zeros((3, 1)), np.zeros((3, 1))
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        objc, imgc, k, dist, rvec.copy(), tvec.copy(), useExtrinsicGuess=guess,
        iterationsCount=200, reprojectionError=reprojection_tol, confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP if not guess else cv2.SOLVEPNP_ITERATIVE)
    if not found or inliers is None or len(inliers) < min_points:
        return _no_fix(result, "PnP found no consistent pose")
    inl = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(objc[inl], imgc[inl], k, dist, rvec, tvec)
    proj, jac = cv2.projectPoints(objc[inl], rvec, tvec, k, dist)
    res = (proj - imgc[inl]).reshape(-1)
    n = len(inl)
    dof = max(2 * n - 6, 1)
    sigma2 = max(float(res @ res) / dof, 0.25 ** 2)   # floor: sub-pixel noise is not zero
    j = jac[:, :6]
    try:
        cov_p = sigma2 * np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return _no_fix(result, "PnP geometry is degenerate")
    params = np.concatenate([rvec.ravel(), tvec.ravel()])
    centre, r_ce = _pose_from_params(params)
    # numeric Jacobian of (centre, world-frame rotation error) w.r.t. (rvec, tvec)
    jn = np.zeros((6, 6))
    for i in range(6):
        h = 1e-6 * max(1.0, abs(params[i]))
        d = params.copy()
        d[i] += h
        c2, r2 = _pose_from_params(d)
        jn[:3, i] = (c2 - centre) / h
        dr = r2 @ r_ce.T   # = I + [w]x for the small world-frame rotation w
        jn[3:, i] = 0.5 * np.array([dr[2, 1] - dr[1, 2], dr[0, 2] - dr[2, 0],
                                    dr[1, 0] - dr[0, 1]]) / h
    cov = jn @ cov_p @ jn.T
    cov[:2, :2] += np.eye(2) * landmark_sigma ** 2
    position = centre + origin
    att_sigma = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0)))
    fix = PvaFixEstimate(STATUS_POSITION_ATTITUDE, "", position, r_ce, cov)
    if att_sigma > max_attitude_sigma:
        fix.status = STATUS_POSITION
        fix.reason = (f"attitude not determined (1-sigma {np.degrees(att_sigma):.1f} deg): "
                      "position only")
        if prior_rotation is not None:
            fix.rotation = np.asarray(prior_rotation, float).reshape(3, 3)
        fix.covariance[3:, :] = 0.0
        fix.covariance[:, 3:] = 0.0
        fix.covariance[3:, 3:] = -np.eye(3)
    note = f"PnP on {n} of {len(obj)} pairings, rms {np.sqrt(np.mean(res ** 2)):.2f} px"
    fix.reason = f"{fix.reason}; {note}" if fix.reason else note
    return _fill_match(fix, result)


def horizontal_disagreement(a: PvaFixEstimate, b: PvaFixEstimate,
                            extra_variance: float = 0.0) -> float:
    """Mahalanobis distance (sigma) between two fixes' horizontal positions under the sum of
    their covariances (plus ``extra_variance`` m^2 on each axis): two estimates of one camera
    position (e.g. PnP and the ground match) that should agree within their uncertainties;
    inf when either lacks a covariance."""
    d = np.asarray(a.position[:2], float) - np.asarray(b.position[:2], float)
    cov = np.asarray(a.covariance[:2, :2], float) + np.asarray(b.covariance[:2, :2], float) \
        + extra_variance * np.eye(2)
    if not (np.isfinite(d).all() and np.isfinite(cov).all()):
        return math.inf
    try:
        return float(math.sqrt(max(d @ np.linalg.solve(cov, d), 0.0)))
    except np.linalg.LinAlgError:
        return math.inf


def checked_pnp(pnp: PvaFixEstimate | None, ground: PvaFixEstimate,
                gate: float, tilt_sigma: float = 0.0) -> PvaFixEstimate:
    """The PnP fix when it agrees with the ground match within ``gate`` sigma
    (:func:`horizontal_disagreement`, the ground match's shift by a prior tilt error of
    ``tilt_sigma`` rad over its ``projection_height`` included), else the ground match with
    the reason.

    A PnP pose from a few nearly collinear pairings (minutiae along parallel ridges) seen
    from kilometres up trades tilt against translation: it can land a kilometre off with a
    covariance that claims a few hundred metres. The ground match of the same registration
    is biased by the prior's tilt (height x tilt) but never that far off; where the two
    disagree beyond their uncertainties the PnP solution is the one to drop.
    """
    if pnp is None or not pnp.valid:
        return ground
    if not ground.valid:
        return pnp
    sigma = horizontal_disagreement(pnp, ground, (ground.projection_height * tilt_sigma) ** 2)
    if sigma <= gate:
        return pnp
    note = (f"PnP pose {sigma:.1f} sigma from the ground match "
            f"({np.hypot(*(pnp.position[:2] - ground.position[:2])):.0f} m): ground match used")
    ground.reason = f"{ground.reason}; {note}" if ground.reason else note
    return ground


def reason_kind(reason: str) -> str:
    """A no-fix reason without its numbers, to count reasons by kind."""
    return re.sub(r"-?\d+(\.\d+)?", "#", reason)


def inflate_covariance(fix: PvaFixEstimate, scale: float) -> None:
    """Scale a fix's position variances, and its attitude and yaw ones where measured, in
    place: the PnP covariance treats the minutiae's errors as independent, and they are not
    (orthorectification and the prior's tilt move them together)."""
    if not (np.isfinite(scale) and scale >= 1.0):
        raise ValueError(f"covariance scale must be >= 1, got {scale!r}")
    measured = np.arange(3 if fix.status == STATUS_POSITION else 6)
    fix.covariance[np.ix_(measured, measured)] *= scale
    if fix.yaw_variance >= 0:
        fix.yaw_variance *= scale


def velocity_from_fixes(position_a, cov_a, time_a: float, position_b, cov_b,
                        time_b: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean velocity (m/s) between two independent fixes, and its 3x3 covariance."""
    dt = float(time_b - time_a)
    if not dt > 0:
        raise ValueError("velocity_from_fixes: the fixes must be in time order")
    v = (np.asarray(position_b, float) - np.asarray(position_a, float)) / dt
    cov = (np.asarray(cov_a, float)[:3, :3] + np.asarray(cov_b, float)[:3, :3]) / dt ** 2
    return v, cov
