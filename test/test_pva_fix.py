"""PVA fixes from minutiae registrations: ground-match position and PnP pose."""

import cv2
import numpy as np
import pytest
from scipy import ndimage
from synthetic_minutiae import terrain_minutiae, transform_set

from terrain_nav_ros.core.features.minutia_set import MinutiaSet
from terrain_nav_ros.core.matching.matcher import Decision, MatchResult, localise
from terrain_nav_ros.core.matching.pva_fix import (
    STATUS_NO_FIX,
    STATUS_POSITION,
    STATUS_POSITION_ATTITUDE,
    PvaFixEstimate,
    dem_heights,
    fix_from_ground_match,
    fix_from_pnp,
    inflate_covariance,
    velocity_from_fixes,
)
from terrain_nav_ros.core.terrain.georef import GeoReference


def _look_at(forward, up):
    """Camera optical (x right, y down, z forward) -> ENU rotation."""
    z = np.asarray(forward, float) / np.linalg.norm(forward)
    y = -(np.asarray(up, float) - (np.dot(up, z)) * z)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _affine_from(fn):
    """2x3 affine pixel map from a function of (col, row) arrays (exact for affine fn)."""
    src = np.array([[0, 0], [100, 0], [0, 100]], np.float32)
    dst = np.column_stack(fn(src[:, 0].astype(float), src[:, 1].astype(float)))
    return cv2.getAffineTransform(src, dst.astype(np.float32)).astype(float)


def test_ground_match_fix_recovers_position_and_heading():
    land_geo = GeoReference(5000.0, 8000.0, 2.0, 512, 512)
    land, _ = terrain_minutiae((512, 512), seed=21)
    land = MinutiaSet(land.col, land.row, land.angle, land.kind, land.quality, georef=land_geo)
    true_c = np.array([5520.0, 7490.0, 900.0])
    prior_c = true_c + np.array([14.0, -9.0, 0.0])
    yaw_err = np.radians(4.0)
    cam_geo = GeoReference.centred(prior_c[0], prior_c[1], 2.0, 128, 128)

    def land_to_cam(col, row):
        e, n = land_geo.pixel_to_enu(col, row)
        d = _rot_z(-yaw_err)[:2, :2] @ np.vstack([e - true_c[0], n - true_c[1]])
        return cam_geo.enu_to_pixel(prior_c[0] + d[0], prior_c[1] + d[1])

    cam, _ = transform_set(land, _affine_from(land_to_cam), (128, 128), rng=4)
    result = localise(cam, land)
    assert result.decision == Decision.MATCH
    fix = fix_from_ground_match(result, cam_geo, land_geo, prior_c, np.eye(3), 0.0)
    assert fix.status == STATUS_POSITION
    assert np.hypot(*(fix.position[:2] - true_c[:2])) < 1.0
    assert abs(fix.yaw_correction - yaw_err) < np.radians(0.5)
    assert np.all(np.linalg.eigvalsh(fix.covariance[:2, :2]) > 0)
    assert np.all(np.diag(fix.covariance)[3:] == -1)
    assert fix.num_pairings == result.n_pairings > 10
    assert fix.projection_height == 900.0    # the prior's tilt acts over the camera's height


def test_a_ground_match_s_height_comes_from_its_measured_scale():
    """The view's scale on the creases measures the height above the projection plane: a
    camera 3 % lower than the prior sees the ground 3 % larger, the registration shrinks
    it back; without a measured scale the height is the prior's, at 10 % of the height."""
    geo = GeoReference.centred(0.0, 0.0, 2.0, 128, 128)
    transform = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    prior = np.array([0.0, 0.0, 1100.0])
    result = MatchResult(Decision.MATCH, score=20.0, transform=transform, rotation=0.0,
                         scale=1.0, covariance=np.eye(4) * 1e-6, scale_measured=0.97,
                         scale_variance=0.002 ** 2)
    fix = fix_from_ground_match(result, geo, geo, prior, np.eye(3), 100.0)
    assert fix.position[2] == pytest.approx(100.0 + 0.97 * 1000.0)
    assert np.sqrt(fix.covariance[2, 2]) == pytest.approx(0.002 * 1000.0)
    assert fix.projection_height == 1000.0
    # a relocalisation's plane lies under the estimate, not under the camera: its height
    # stays the prior's, as does that of a registration without a measured scale
    relocalised = fix_from_ground_match(result, geo, geo, prior, np.eye(3), 100.0,
                                        height_from_scale=False)
    result.scale_measured = result.scale_variance = np.nan
    fix = fix_from_ground_match(result, geo, geo, prior, np.eye(3), 100.0)
    for f in (relocalised, fix):
        assert f.position[2] == 1100.0 and np.sqrt(f.covariance[2, 2]) == pytest.approx(100.0)


@pytest.fixture(scope="module")
def pnp_scene():
    rng = np.random.default_rng(3)
    land_geo = GeoReference(0.0, 2000.0, 2.0, 1000, 1000)
    dem_geo = GeoReference(0.0, 2000.0, 10.0, 200, 200)
    dem = ndimage.gaussian_filter(rng.normal(size=(200, 200)), 12)
    dem = 1500.0 + 150.0 * dem / np.abs(dem).max()
    n = 400
    land = MinutiaSet(rng.uniform(0, 999, n), rng.uniform(0, 999, n), rng.uniform(0, 6, n),
                      np.ones(n, np.uint8), np.ones(n), georef=land_geo)
    east, north = land.enu()
    heights = dem_heights(dem, dem_geo, east, north)
    centre = np.array([1000.0, 1000.0, 3200.0])
    rot = _look_at([0.15, 0.1, -1.0], [np.sin(0.5), np.cos(0.5), 0.0])
    k = np.array([[900.0, 0, 320], [0, 900.0, 240], [0, 0, 1]])
    r_cw = rot.T
    pts = np.column_stack([east, north, heights])
    uv = cv2.projectPoints(pts, cv2.Rodrigues(r_cw)[0], -r_cw @ centre, k, None)[0][:, 0]
    seen = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    idx = np.flatnonzero(seen)
    cam_px = uv[idx] + rng.normal(0, 0.5, (len(idx), 2))
    pairs = np.column_stack([np.arange(len(idx)), idx])
    wrong = rng.random(len(idx)) < 0.1      # 10% wrong pairings: PnP must reject them
    pairs[wrong, 1] = rng.integers(0, n, wrong.sum())
    result = MatchResult(Decision.MATCH, score=50.0, n_pairings=len(pairs), pairings=pairs,
                         n_a=len(idx), n_b=n)
    return dict(result=result, cam_px=cam_px, enu=(east, north), heights=heights, k=k,
                centre=centre, rot=rot)


def test_pnp_fix_recovers_pose_with_consistent_covariance(pnp_scene):
    s = pnp_scene
    assert s["result"].n_pairings >= 30
    prior_c = s["centre"] + [40.0, -25.0, 30.0]
    prior_r = _rot_z(np.radians(2.0)) @ s["rot"]
    fix = fix_from_pnp(s["result"], s["cam_px"], s["enu"], s["heights"], s["k"],
                       prior_position=prior_c, prior_rotation=prior_r)
    assert fix.status == STATUS_POSITION_ATTITUDE, fix.reason
    err = fix.position - s["centre"]
    # 1700 m range, 0.5 px noise, 40 degree field of view: metres, not decimetres
    assert np.linalg.norm(err) < 8.0
    # the error is consistent with the reported covariance (chi-square, 3 dof, p = 0.001)
    assert err @ np.linalg.solve(fix.covariance[:3, :3], err) < 16.3
    d_rot = cv2.Rodrigues(fix.rotation @ s["rot"].T)[0].ravel()
    assert np.degrees(np.linalg.norm(d_rot)) < 0.3
    assert np.all(np.linalg.eigvalsh(fix.covariance) > 0)


def test_pnp_fix_without_prior_and_with_too_few_points(pnp_scene):
    s = pnp_scene
    fix = fix_from_pnp(s["result"], s["cam_px"], s["enu"], s["heights"], s["k"])
    assert fix.status == STATUS_POSITION_ATTITUDE
    assert np.linalg.norm(fix.position - s["centre"]) < 8.0
    r = s["result"]
    few = MatchResult(Decision.MATCH, pairings=r.pairings[:4], n_pairings=4)
    assert fix_from_pnp(few, s["cam_px"], s["enu"], s["heights"], s["k"]).status == \
        STATUS_NO_FIX


def test_no_match_gives_no_fix_with_reason():
    r = MatchResult(Decision.NO_DECISION, reason="too few minutiae (3, 200)")
    fix = fix_from_ground_match(r, GeoReference(0, 0, 1, 10, 10), GeoReference(0, 0, 1, 10, 10),
                                [0, 0, 100], np.eye(3), 0.0)
    assert fix.status == STATUS_NO_FIX and "too few" in fix.reason


def test_velocity_from_fixes():
    v, cov = velocity_from_fixes([0, 0, 100], np.eye(6), 1.0, [20, -10, 100], np.eye(6), 3.0)
    assert np.allclose(v, [10, -5, 0]) and np.allclose(cov, np.eye(3) * 0.5)


def test_inflate_covariance_scales_what_was_measured():
    cov = np.diag([4.0, 4.0, 9.0, 1e-4, 1e-4, 1e-4])
    full = PvaFixEstimate(STATUS_POSITION_ATTITUDE, "", np.zeros(3), np.eye(3), cov.copy())
    inflate_covariance(full, 3.0)
    assert np.allclose(full.covariance, 3.0 * cov)
    pos_only = np.diag([4.0, 4.0, 9.0, -1.0, -1.0, -1.0])     # attitude not measured: -1
    fix = PvaFixEstimate(STATUS_POSITION, "", np.zeros(3), np.eye(3), pos_only.copy(),
                         yaw_variance=0.01)
    inflate_covariance(fix, 2.0)
    assert np.allclose(np.diag(fix.covariance), [8, 8, 18, -1, -1, -1])
    assert fix.yaw_variance == pytest.approx(0.02)
    with pytest.raises(ValueError):
        inflate_covariance(fix, 0.5)


def _estimate(east, north, sigma):
    from terrain_nav_ros.core.matching.pva_fix import STATUS_POSITION, PvaFixEstimate

    cov = np.zeros((6, 6))
    cov[:2, :2] = np.eye(2) * sigma ** 2
    cov[2, 2] = 100.0
    return PvaFixEstimate(STATUS_POSITION, "", np.array([east, north, 3000.0]), np.eye(3), cov)


def test_a_pnp_pose_far_from_the_ground_match_is_dropped():
    """PnP and the ground match estimate one position: within their joint uncertainty the
    PnP pose stands; a kilometre off with a few hundred metres claimed, the ground match
    is used, and the reason says so."""
    from terrain_nav_ros.core.matching.pva_fix import checked_pnp, horizontal_disagreement

    ground = _estimate(0.0, 0.0, 30.0)
    near = _estimate(120.0, -90.0, 150.0)
    assert horizontal_disagreement(near, ground) == pytest.approx(150.0 / np.hypot(150, 30))
    assert checked_pnp(near, ground, gate=3.0) is near
    far = _estimate(1500.0, 600.0, 200.0)
    assert horizontal_disagreement(far, ground) > 7.0
    used = checked_pnp(far, ground, gate=3.0)
    assert used is ground and "ground match used" in used.reason and "1616 m" in used.reason
    # no PnP, or a PnP no-fix: the ground match; no ground match: the PnP
    from terrain_nav_ros.core.matching.pva_fix import STATUS_NO_FIX, PvaFixEstimate

    assert checked_pnp(None, ground, 3.0) is ground
    assert checked_pnp(PvaFixEstimate(STATUS_NO_FIX, "x"), ground, 3.0) is ground
    assert checked_pnp(near, PvaFixEstimate(STATUS_NO_FIX, "y"), 3.0) is near
    # a ground match carries the prior's tilt error over its height: the check allows for it
    tilted = _estimate(0.0, 0.0, 30.0)
    tilted.projection_height = 3000.0
    wide = _estimate(200.0, 0.0, 30.0)
    assert checked_pnp(wide, tilted, gate=3.0) is tilted
    assert checked_pnp(wide, tilted, gate=3.0, tilt_sigma=np.radians(1.0)) is wide
    nan_cov = _estimate(10.0, 0.0, 10.0)
    nan_cov.covariance[:2, :2] = np.nan
    assert horizontal_disagreement(nan_cov, ground) == float("inf")
