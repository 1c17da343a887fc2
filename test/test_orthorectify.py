"""True-ortho projection: a point on a mountain top lands on its ground position; the
mean-plane homography would misplace it by height x distance / flying height."""

import cv2
import numpy as np
import pytest

from terrain_nav_ros.core.camera.ground_projection import (
    CameraIntrinsics,
    CameraPose,
    footprint_georef,
    look_at_rotation,
    project_to_ground,
)
from terrain_nav_ros.core.camera.orthorectify import heights_on, orthorectify
from terrain_nav_ros.core.terrain.georef import GeoReference

INTR = CameraIntrinsics(400.0, 400.0, 319.5, 239.5, 640, 480)
POSE = CameraPose([0.0, 0.0, 3000.0], look_at_rotation([0.15, 0.0, -1.0]))  # tilted ~8.5 deg
PEAK = np.array([800.0, 300.0, 600.0])   # a summit 600 m above the terrain at 0 m


def _frame():
    """A frame with one bright 3x3 blob where the summit is seen (pinhole, by hand)."""
    p = POSE.rotation.T @ (PEAK - POSE.position)
    u = INTR.fx * p[0] / p[2] + INTR.cx
    v = INTR.fy * p[1] / p[2] + INTR.cy
    image = np.full((INTR.height, INTR.width), 30, np.uint8)
    image[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2] = 250
    return image


def _heights(georef):
    east, north = georef.pixel_to_enu(np.arange(georef.width)[None, :],
                                      np.arange(georef.height)[:, None])
    return PEAK[2] * np.exp(-((east - PEAK[0]) ** 2 + (north - PEAK[1]) ** 2) / 300.0**2)


def _blob(ground):
    img = ground.image.astype(float)
    rows, cols = np.nonzero(img > 0.5 * img.max())
    w = img[rows, cols]
    return ground.georef.pixel_to_enu(np.average(cols, weights=w), np.average(rows, weights=w))


def test_summit_lands_on_its_ground_position_only_with_the_dem():
    georef = GeoReference.centred(500.0, 0.0, 5.0, 600, 500)
    dem_georef = GeoReference.centred(500.0, 0.0, 10.0, 400, 400)
    heights = heights_on(georef, _heights(dem_georef), dem_georef)
    ortho = orthorectify(_frame(), INTR, POSE, heights, georef)
    assert ortho.reason == "" and ortho.valid.mean() > 0.5
    np.testing.assert_allclose(_blob(ortho), PEAK[:2], atol=5.0)   # within one ground pixel
    plane = project_to_ground(_frame(), INTR, POSE, 0.0, georef)
    assert np.hypot(*(np.array(_blob(plane)) - PEAK[:2])) > 100.0  # relief displacement


def test_heights_outside_the_dem_are_invalid():
    georef = GeoReference.centred(0.0, 0.0, 5.0, 100, 100)
    dem_georef = GeoReference(0.0, 250.0, 5.0, 50, 100)             # covers the east half
    heights = heights_on(georef, np.zeros((100, 50)), dem_georef)
    assert np.isnan(heights[:, :40]).all() and np.isfinite(heights[:, 60:]).all()
    ortho = orthorectify(np.full((480, 640), 100, np.uint8), INTR, POSE, heights, georef)
    assert not ortho.valid[:, :40].any()


@pytest.mark.parametrize("sigma", [6.0, 20.0, 60.0])
def test_a_wide_blur_is_the_gaussian_it_stands_for(sigma):
    """A large frame low over the ground needs a wide low-pass: the cheap one keeps the
    Gaussian's response (a step's edge spread and the noise left) and the frame's grid."""
    from terrain_nav_ros.core.camera.orthorectify import wide_blur

    rng = np.random.default_rng(1)
    frame = rng.normal(100.0, 20.0, (600, 800)).astype(np.float32)
    frame[:, 400:] += 100.0                               # a step across the frame
    exact = cv2.GaussianBlur(frame, (0, 0), sigma)
    cheap = wide_blur(frame, sigma)
    assert cheap.shape == frame.shape
    row = slice(200, 400)
    np.testing.assert_allclose(cheap[row].mean(axis=0)[100:-100],
                               exact[row].mean(axis=0)[100:-100], atol=2.5)
    assert cheap[row, 100:300].std() == pytest.approx(exact[row, 100:300].std(), rel=0.35)


def _textured_relief(n=420, gsd=20.0):
    """Rolling relief with valleys every few hundred metres, on a north-up grid."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    h = (600 + 60 * np.sin(x / 2.3) * np.cos(y / 3.1) + 40 * np.sin((x + 2 * y) / 4.7)
         + 30 * np.cos((3 * x - y) / 6.1) + 80 * np.sin(x / 11.0 + y / 17.0))
    return h.astype(np.float32), GeoReference(-n * gsd / 2, n * gsd / 2, gsd, n, n)


def _shift_px(a, b, valid):
    """Sub-pixel shift of ``a`` against ``b`` over ``valid`` (away from its edge): the
    translation ECC finds between the band-passed images."""
    def band(img):
        img = img.astype(np.float32)
        return cv2.GaussianBlur(img, (0, 0), 1.0) - cv2.GaussianBlur(img, (0, 0), 5.0)
    inner = cv2.erode(valid.astype(np.uint8), np.ones((21, 21), np.uint8))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    _, warp = cv2.findTransformECC(band(b), band(a), np.eye(2, 3, dtype=np.float32),
                                   cv2.MOTION_TRANSLATION, criteria, inner, 1)
    return warp[:, 2]


def test_a_rendered_frame_projected_with_its_pose_lies_on_the_landmark():
    """A camera frame rendered in perspective from a pose (tilted, turned), projected back
    onto the ground with that pose, lies on the nadir landmark render of the ground to a
    tenth of a ground pixel: the perspective render, the nadir render and the projection
    keep one pixel-centre convention. A principal point one pixel off (20 m on the ground
    here) is seen, so half a pixel of disagreement anywhere in the chain would be too: at the
    demo's 20 m GSD it would be a 10 m bias in every fix."""
    from terrain_nav_ros.core.render.renderer import (
        EGLUnavailableError,
        LandmarkRenderer,
        PinholeCamera,
        create_headless_context,
    )
    try:
        ctx = create_headless_context()
    except EGLUnavailableError as exc:
        pytest.skip(f"no headless EGL OpenGL context on this machine: {exc}")
    heights, tile = _textured_relief()
    intr = CameraIntrinsics(110.0, 110.0, 79.5, 59.5, 160, 120)
    pose = CameraPose([150.0, -90.0, 2600.0],
                      look_at_rotation([0.04, -0.03, -1.0], up=(np.sin(0.5), np.cos(0.5), 0.0)))
    georef = footprint_georef(intr, pose, 600.0, 20.0)
    sun = (135.0, 40.0)
    renderer = LandmarkRenderer(ctx, shadows=False)
    try:
        renderer.set_terrain(heights, tile)
        frame = renderer.render_perspective(PinholeCamera(110.0, 110.0, 79.5, 59.5, 160, 120),
                                            pose.position, pose.rotation, sun=sun).grey_u8
        landmark = renderer.render_nadir(georef, sun=sun).grey_u8
    finally:
        renderer.release()
        ctx.release()
    on_ground = heights_on(georef, heights, tile)
    ground = orthorectify(frame, intr, pose, on_ground, georef)
    assert ground.valid.mean() > 0.5
    shift = _shift_px(ground.image, landmark, ground.valid)
    assert np.abs(shift).max() < 0.1, shift
    off = CameraIntrinsics(110.0, 110.0, 80.5, 59.5, 160, 120)
    ground = orthorectify(frame, off, pose, on_ground, georef)
    shift = _shift_px(ground.image, landmark, ground.valid)
    assert np.hypot(*shift) > 0.5, shift
