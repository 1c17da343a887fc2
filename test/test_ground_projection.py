"""Ground projection of camera frames (camera_ingest core): synthetic frames of known geometry."""

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.camera.ground_projection import (
    CameraIntrinsics,
    CameraPose,
    check_view,
    footprint_georef,
    ground_homography,
    ground_to_image,
    image_to_ground,
    look_at_rotation,
    mean_height_near,
    nadir_rotation,
    project_to_ground,
    projection_plane,
)
from terrain_nav_ros.core.terrain.georef import GeoReference

PLANE = 100.0          # mean terrain height (m)
ALT = 300.0            # camera height above the plane (m)
GSD = 0.5              # output raster (m/px)
SPOT_SIGMA = 1.5       # ground spot size (m)
PINHOLE = CameraIntrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
DISTORTED = CameraIntrinsics(500.0, 505.0, 322.0, 236.0, 640, 480,
                             (-0.08, 0.02, 0.0005, -0.0003, 0.0))
FISHEYE = CameraIntrinsics(400.0, 402.0, 321.0, 238.0, 640, 480,
                           (0.03, -0.012, 0.004, -0.0006), "equidistant")   # 92 x 69 deg


def tilted_rotation(tilt_deg, heading_deg=0.0):
    """Camera pitched ``tilt_deg`` from nadir towards ``heading_deg`` (clockwise from N)."""
    t, h = np.deg2rad(tilt_deg), np.deg2rad(heading_deg)
    fwd = np.array([np.sin(t) * np.sin(h), np.sin(t) * np.cos(h), -np.cos(t)])
    return look_at_rotation(fwd, (np.sin(h), np.cos(h), 0.0))


def render_frame(intr, pose, spots):
    """Camera frame of a flat ground with Gaussian bright spots at ENU (east, north)."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height,
                                                                        dtype=float))
    e, n = image_to_ground(u, v, intr, pose, PLANE)
    img = np.full(u.shape, 40.0)
    for se, sn in spots:
        img += 200.0 * np.exp(-((e - se) ** 2 + (n - sn) ** 2) / (2 * SPOT_SIGMA**2))
    return np.nan_to_num(img, nan=0.0).astype(np.float32)


def centroid(img, col, row, half=8):
    """Intensity-weighted centroid (col, row) of a spot near (col, row)."""
    c0, r0 = int(round(col)), int(round(row))
    win = img[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1].astype(float)
    win = np.clip(win - 40.0, 0, None)
    rr, cc = np.mgrid[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1]
    return (win * cc).sum() / win.sum(), (win * rr).sum() / win.sum()


CASES = {
    "nadir": (PINHOLE, nadir_rotation(0.0)),
    "nadir heading 35": (PINHOLE, nadir_rotation(35.0)),
    "tilt 20": (PINHOLE, tilted_rotation(20.0, 0.0)),
    "tilt 20 heading 120": (PINHOLE, tilted_rotation(20.0, 120.0)),
    "nadir distorted": (DISTORTED, nadir_rotation(10.0)),
    "tilt 20 distorted": (DISTORTED, tilted_rotation(20.0, 250.0)),
    "nadir fisheye": (FISHEYE, nadir_rotation(10.0)),
    "tilt 20 fisheye": (FISHEYE, tilted_rotation(20.0, 250.0)),
}


def test_the_fisheye_model_is_opencv_s():
    """Rays and projections of the equidistant model agree with cv2.fisheye's."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-1.0, 1.0, (50, 2)), rng.uniform(0.4, 2.0, 50)])
    K, D = FISHEYE.matrix, np.array(FISHEYE.dist)
    expect = cv2.fisheye.projectPoints(points[:, None, :], np.zeros(3), np.zeros(3), K,
                                       D)[0][:, 0, :]
    np.testing.assert_allclose(FISHEYE.project(points), expect, atol=1e-6)
    rays = FISHEYE.rays(*expect.T)
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], points[:, :2] / points[:, 2:],
                               atol=1e-6)
    pinhole = FISHEYE.pinhole_pixels(*expect.T)
    np.testing.assert_allclose(pinhole, points[:, :2] / points[:, 2:] * [400.0, 402.0]
                               + [321.0, 238.0], atol=1e-4)


@pytest.mark.parametrize("name", list(CASES))
def test_projected_points_land_within_half_a_pixel(name):
    intr, R = CASES[name]
    pose = CameraPose([500.0, 1000.0, PLANE + ALT], R)
    # Spots spread over the view: the ground points of a 3x3 grid of image positions.
    uu, vv = np.meshgrid([100.0, 320.0, 540.0], [80.0, 240.0, 400.0])
    se, sn = image_to_ground(uu.ravel(), vv.ravel(), intr, pose, PLANE)
    frame = render_frame(intr, pose, list(zip(se, sn, strict=True)))
    geo = footprint_georef(intr, pose, PLANE, GSD)
    ground = project_to_ground(frame, intr, pose, PLANE, geo)
    # (a fisheye's footprint bulges: more of its bounding raster is empty)
    assert ground.reason == "" and ground.valid.mean() > (0.35 if intr.fisheye else 0.5)
    cols, rows = geo.enu_to_pixel(se, sn)
    for c, r in zip(cols, rows, strict=True):
        cc, rr = centroid(ground.image, c, r)
        assert np.hypot(cc - c, rr - r) < 0.5, (name, c, r, cc, rr)


@pytest.mark.parametrize("name", list(CASES))
def test_image_ground_round_trip(name):
    intr, R = CASES[name]
    pose = CameraPose([0.0, 0.0, PLANE + ALT], R)
    u = np.array([0.0, 639.0, 320.5, 17.0, 600.0])
    v = np.array([0.0, 479.0, 240.2, 400.0, 30.0])
    e, n = image_to_ground(u, v, intr, pose, PLANE)
    u2, v2 = ground_to_image(e, n, PLANE, intr, pose)
    assert np.allclose(u2, u, atol=1e-3) and np.allclose(v2, v, atol=1e-3)


def test_homography_matches_the_pinhole_model():
    pose = CameraPose([10.0, -20.0, PLANE + ALT], tilted_rotation(20.0, 45.0))
    geo = footprint_georef(PINHOLE, pose, PLANE, 2.0)
    H = ground_homography(PINHOLE, pose, PLANE, geo)
    cols, rows = np.array([3.0, 50.0, 120.5]), np.array([7.0, 60.0, 99.0])
    p = H @ np.vstack([cols, rows, np.ones(3)])
    e, n = geo.pixel_to_enu(cols, rows)
    u, v = ground_to_image(e, n, PLANE, PINHOLE, pose)
    assert np.allclose(p[0] / p[2], u) and np.allclose(p[1] / p[2], v)


def test_nadir_output_is_north_up():
    pose = CameraPose([0.0, 0.0, PLANE + ALT], nadir_rotation(0.0))
    frame = render_frame(PINHOLE, pose, [(60.0, 0.0), (0.0, 40.0)])  # east, north spots
    geo = GeoReference.centred(0.0, 0.0, GSD, 400, 400)
    ground = project_to_ground(frame, PINHOLE, pose, PLANE, geo)
    east_spot = centroid(ground.image, *geo.enu_to_pixel(60.0, 0.0))
    north_spot = centroid(ground.image, *geo.enu_to_pixel(0.0, 40.0))
    assert east_spot[0] > 300 and abs(east_spot[1] - 199.5) < 0.5
    assert north_spot[1] < 150 and abs(north_spot[0] - 199.5) < 0.5
    # In the nadir frame with North up, the east spot is right of centre.
    assert frame[240, 420] > frame[240, 220]


def test_footprint_of_a_nadir_view():
    pose = CameraPose([100.0, 200.0, PLANE + ALT], nadir_rotation(0.0))
    geo = footprint_georef(PINHOLE, pose, PLANE, 1.0)
    w, e, s, n = geo.extent
    assert (e - w) == pytest.approx(640 * ALT / 500.0, abs=2.0)
    assert (n - s) == pytest.approx(480 * ALT / 500.0, abs=2.0)
    assert geo.centre == pytest.approx((100.0, 200.0), abs=1.0)


def test_view_partly_above_the_horizon_is_masked():
    # Optical axis 10 deg below the horizontal: the top of the frame shows sky.
    pose = CameraPose([0.0, 0.0, PLANE + ALT], tilted_rotation(80.0, 0.0))
    assert check_view(PINHOLE, pose, PLANE) == ""
    frame = np.full((480, 640), 77, np.uint8)
    geo = GeoReference.centred(0.0, 2000.0, 10.0, 400, 400)
    ground = project_to_ground(frame, PINHOLE, pose, PLANE, geo, max_range=3000.0)
    assert ground.reason == ""
    assert 0 < ground.valid.mean() < 1
    assert np.all(ground.image[ground.valid] == 77) and np.all(ground.image[~ground.valid] == 0)
    # Nothing south of the camera (behind it) is valid, nor beyond max_range.
    east, north = geo.pixel_to_enu(*np.meshgrid(np.arange(400), np.arange(400)))
    assert not ground.valid[north < 0].any()
    assert not ground.valid[np.hypot(east, north) > 3000.0].any()
    far = footprint_georef(PINHOLE, pose, PLANE, 10.0, max_range=5000.0)
    assert far.extent[3] <= 5000.0 + 10.0


@pytest.mark.parametrize("intr,R,height,expect", [
    (PINHOLE, look_at_rotation((0.0, 1.0, 0.5)), PLANE + ALT, "horizon"),
    (PINHOLE, look_at_rotation((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)), PLANE + ALT, "horizon"),
    (CameraIntrinsics(0.0, 0.0, 0.0, 0.0, 640, 480), nadir_rotation(), PLANE + ALT, "zero"),
    (CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 0, 0), nadir_rotation(), PLANE + ALT,
     "size"),
    (CameraIntrinsics(1e9, 1e9, 320.0, 240.0, 640, 480), nadir_rotation(), PLANE + ALT,
     "field of view 3.67e-05 deg across"),           # a focal length in nm, not px
    (CameraIntrinsics(1e-3, 1e-3, 320.0, 240.0, 640, 480), nadir_rotation(), PLANE + ALT,
     "field of view 180 deg across"),
    (PINHOLE, nadir_rotation(), PLANE - 5.0, "not above"),
    (PINHOLE, 2.0 * nadir_rotation(), PLANE + ALT, "rotation"),
    (PINHOLE, np.full((3, 3), np.nan), PLANE + ALT, "not finite"),
])
def test_unprojectable_views_give_a_reason(intr, R, height, expect):
    pose = CameraPose([0.0, 0.0, height], R)
    geo = GeoReference.centred(0.0, 0.0, 1.0, 64, 64)
    frame = np.zeros((max(intr.height, 1), max(intr.width, 1)), np.uint8)
    ground = project_to_ground(frame, intr, pose, PLANE, geo)
    assert ground.image is None and expect in ground.reason
    assert footprint_georef(intr, pose, PLANE, 1.0) is None


def test_wrong_frame_size_and_missed_raster():
    pose = CameraPose([0.0, 0.0, PLANE + ALT], nadir_rotation())
    geo = GeoReference.centred(0.0, 0.0, 1.0, 64, 64)
    bad = project_to_ground(np.zeros((10, 10), np.uint8), PINHOLE, pose, PLANE, geo)
    assert bad.image is None and "size" in bad.reason
    far = GeoReference.centred(1e5, 0.0, 1.0, 64, 64)
    miss = project_to_ground(np.zeros((480, 640), np.uint8), PINHOLE, pose, PLANE, far)
    assert miss.image is None and "does not reach" in miss.reason


def test_a_float_frame_s_nan_pixels_are_not_valid_ground():
    """32FC1 frames (thermal, depth-style drivers) with NaN pixels: the ground pixels they
    reach are invalid, never NaN marked valid; a frame mostly NaN says so."""
    pose = CameraPose([0.0, 0.0, PLANE + ALT], nadir_rotation())
    geo = GeoReference.centred(0.0, 0.0, 2.0, 200, 200)   # the whole 384 x 288 m view
    frame = np.full((480, 640), 50.0, np.float32)
    frame[:100] = np.nan                  # the top of the frame: 144 to 84 m north
    out = project_to_ground(frame, PINHOLE, pose, PLANE, geo)
    assert np.isfinite(out.image).all() and np.all(out.image[out.valid] == 50.0)
    assert out.valid[150, 20:180].all() and not out.valid[32:56].any()
    frame[:300] = np.nan
    mostly = project_to_ground(frame, PINHOLE, pose, PLANE, geo)
    assert mostly.image is None and "62 % of the frame's pixels are not numbers" in mostly.reason


def test_colour_frames_become_grey():
    pose = CameraPose([0.0, 0.0, PLANE + ALT], nadir_rotation())
    geo = GeoReference.centred(0.0, 0.0, 1.0, 64, 64)
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[..., 0] = 200
    out = project_to_ground(rgb, PINHOLE, pose, PLANE, geo)
    expect = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[0, 0]
    assert out.image.dtype == np.uint8 and np.all(out.image[out.valid] == expect)
    bgr = project_to_ground(rgb, PINHOLE, pose, PLANE, geo, bgr=True)
    assert np.all(bgr.image[bgr.valid] == cv2.cvtColor(rgb, cv2.COLOR_BGR2GRAY)[0, 0])


def test_mean_height_near_says_why_there_is_none():
    """An all-nodata DEM under the aircraft is said as such, not as a tile still to come
    (issue 22)."""
    georef = GeoReference(0.0, 1000.0, 10.0, 100, 100)     # 1 km square, NW corner (0, 1000)
    heights = np.full((100, 100), 250.0, np.float32)
    heights[:, 50:] = np.nan                                # eastern half: nodata
    assert mean_height_near(heights, georef, 200.0, 500.0, 100.0) == (250.0, "")
    assert mean_height_near(heights, georef, 800.0, 500.0, 100.0) == (
        None, "the DEM has no heights under the aircraft (nodata or voids)")
    assert mean_height_near(heights, georef, 5000.0, 500.0, 100.0) == (
        None, "the DEM tile does not reach the aircraft yet")


def test_a_view_from_beyond_the_dem_s_edge_is_projected_on_the_ground_the_dem_holds():
    """An aircraft past the DEM's edge (a coast, a mission DEM's border) still sees the
    ground the DEM holds: the frame is projected there, on that ground's height, and the
    pixels beyond the edge are not observed. Farther out, where its view holds no DEM
    either, it is a no-fix saying why."""
    from terrain_nav_ros.core.camera.orthorectify import heights_on, orthorectify

    tile = GeoReference.centred(0.0, 0.0, 20.0, 500, 500)     # 10 km square
    heights = np.full(tile.shape, 300.0, np.float32)
    heights[:, 250:] = np.nan                                   # nodata east of E = 0
    intr = CameraIntrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)   # 3.8 x 2.9 km at 3 km
    past = CameraPose([1000.0, 0.0, 3300.0], nadir_rotation())       # 1 km past the edge
    plane, footprint, max_range, why = projection_plane(heights, tile, intr, past, 20.0, 3.0)
    assert why == "" and plane == pytest.approx(300.0)
    assert max_range == pytest.approx(9000.0)
    west, _ = footprint.pixel_to_enu(0.0, 0.0)
    east, _ = footprint.pixel_to_enu(footprint.width - 1.0, 0.0)
    assert west == pytest.approx(1000.0 - 1920.0, abs=25.0) and east > 2800.0
    ground = orthorectify(np.full((480, 640), 90, np.uint8), intr, past,
                          heights_on(footprint, heights, tile), footprint)
    cols = footprint.pixel_to_enu(np.arange(footprint.width, dtype=float), 0.0)[0]
    assert ground.valid[:, cols < -20.0].all() and not ground.valid[:, cols > 20.0].any()
    far = CameraPose([3000.0, 0.0, 3300.0], nadir_rotation())        # the view ends 1 km east
    assert projection_plane(heights, tile, intr, far, 20.0, 3.0)[1:] == (
        None, pytest.approx(np.nan, nan_ok=True), "the DEM has no heights under the aircraft "
        "(nodata or voids)")
    over = CameraPose([-3000.0, 0.0, 3300.0], nadir_rotation())      # over the DEM: as before
    plane, footprint, _, _ = projection_plane(heights, tile, intr, over, 20.0, 3.0)
    assert plane == pytest.approx(300.0) and footprint.centre == pytest.approx((-3000.0, 0.0),
                                                                               abs=20.0)


def test_a_mount_is_chained_through_static_frames_and_read_back_as_angles():
    """``base_link -> camera_link -> camera_optical`` composes to the mount; a frame not
    under the base, or a loop, is no mount (the parameter is used instead)."""
    from terrain_nav_ros.core.camera.camera_mount import (
        R_BODY_OPTICAL_NADIR,
        chained_rotation,
        mount_angles,
        mount_rotation,
    )

    angles = (0.05, -0.2, 0.4)
    tilt = mount_rotation(*angles) @ R_BODY_OPTICAL_NADIR.T
    tree = {"camera_link": ("base_link", tilt), "camera_optical": ("camera_link",
                                                                   R_BODY_OPTICAL_NADIR)}
    chained = chained_rotation(tree, "base_link", "camera_optical")
    np.testing.assert_allclose(chained, mount_rotation(*angles), atol=1e-12)
    np.testing.assert_allclose(mount_angles(chained), angles, atol=1e-12)
    np.testing.assert_allclose(chained_rotation(tree, "base_link", "base_link"), np.eye(3))
    assert chained_rotation(tree, "base_link", "gimbal_optical") is None
    assert chained_rotation(tree, "body", "camera_optical") is None
    looped = {"a": ("b", np.eye(3)), "b": ("a", np.eye(3))}
    assert chained_rotation(looped, "base_link", "a") is None
