"""Track mosaics of a low camera's ground frames (core.camera.track_mosaic)."""

import numpy as np
import pytest
from scipy import ndimage

from terrain_nav_ros.core.camera.ground_projection import GroundImage
from terrain_nav_ros.core.camera.track_mosaic import FilterSteps, TrackMosaic
from terrain_nav_ros.core.terrain.georef import GeoReference

GSD = 30.0


@pytest.fixture(scope="module")
def terrain():
    """A smooth grey 'orthophoto' of 120 x 400 px at 30 m, north-west corner at (0, 0)."""
    rng = np.random.default_rng(4)
    image = ndimage.gaussian_filter(rng.normal(size=(120, 400)), 3.0)
    image = (image - image.min()) / np.ptp(image) * 200 + 20
    return image.astype(np.uint8), GeoReference(0.0, 0.0, GSD, 400, 120)


def _frame(terrain, col, row, placed_off=(0.0, 0.0), size=(40, 30)):
    """The ground frame of the photo's pixels [row:row+h, col:col+w], placed ``placed_off``
    (east, north m) from where it is (the estimate's error then)."""
    image, g = terrain
    w, h = size
    crop = image[row:row + h, col:col + w].copy()
    georef = GeoReference(g.origin_east + col * GSD + placed_off[0],
                          g.origin_north - row * GSD + placed_off[1], GSD, w, h)
    return GroundImage(crop, np.ones_like(crop, bool), georef)


def _photo_under(mosaic: GroundImage, terrain, placed_off=(0.0, 0.0)):
    """The photo's pixels where the mosaic's (observed) pixels would be, were it placed
    ``placed_off`` off."""
    image, g = terrain
    col0 = round((mosaic.georef.origin_east - placed_off[0] - g.origin_east) / GSD)
    row0 = round((g.origin_north - mosaic.georef.origin_north + placed_off[1]) / GSD)
    h, w = mosaic.georef.shape
    return image[row0:row0 + h, col0:col0 + w]


def test_filter_steps_keep_what_the_velocity_does_not_explain():
    steps = FilterSteps(horizon=60.0, max_gap=1.0)
    velocity = np.array([30.0, -4.0, 0.0])
    jump = np.array([12.0, -7.0, 0.0])
    for k in range(501):                       # 10 s at 50 Hz, a fix's step at 5 s
        t = 100.0 + 0.02 * k
        position = velocity * (t - 100.0) + (jump if t > 105.0 else 0.0)
        steps.add(t, position, velocity)
    np.testing.assert_allclose(steps.at(104.0) - steps.at(101.0), 0.0, atol=1e-9)
    np.testing.assert_allclose(steps.at(109.0) - steps.at(104.0), jump[:2], atol=1e-9)
    # a gap the velocity cannot be integrated across breaks the history
    epoch = steps.epoch
    steps.add(112.0, velocity * 12.0 + jump, velocity)
    assert steps.at(109.0) is None
    np.testing.assert_allclose(steps.at(112.0), 0.0)
    assert steps.epoch == epoch + 1      # the sums before and after do not compare
    assert steps.at(150.0) is None


def test_a_small_frame_is_published_with_the_frames_before_it(terrain):
    mosaic = TrackMosaic(min_pixels=3000, max_age=30.0)
    for k in range(40):                        # 3 px east per frame: a low camera's track
        out, n, _ = mosaic.compose(_frame(terrain, 10 + 3 * k, 40), 10.0 + k, np.zeros(2))
    # frames of 1200 px, each adding 90: 21 of them, not the 31 of the last 30 s
    assert n == 21 and out.georef.width == 40 + 3 * 20
    # the newest frame's raster is in it, and its pixels are the photo's
    assert out.georef.contains(*_frame(terrain, 10 + 3 * 39, 40).georef.centre)
    assert out.valid.sum() >= 3000
    photo = _photo_under(out, terrain)
    assert np.abs(out.image[out.valid].astype(int) - photo[out.valid]).max() <= 1


def test_past_frames_are_moved_by_the_steps_the_estimate_took_since(terrain):
    """The estimate jumps 90 m east and 60 m south at a fix: the frames before it were
    placed with the old error, those after with the new; the mosaic puts them all in the
    newest frame's, where the photo lies shifted by its error."""
    old, new = np.array([0.0, 0.0]), np.array([90.0, -60.0])
    steps = FilterSteps(horizon=60.0)
    velocity = np.array([90.0, 0.0, 0.0])     # 3 px a second east
    mosaic = TrackMosaic(min_pixels=6000, max_age=30.0)
    for k in range(30):
        t = 10.0 + k
        error = new if k >= 20 else old
        for s in np.arange(0.0, 1.0, 0.05):   # the estimate at 20 Hz
            steps.add(t + s, np.r_[velocity[:2] * (t + s) + (new if t + s >= 29.5 else old), 0],
                      velocity)
        out, n, _ = mosaic.compose(_frame(terrain, 10 + 3 * k, 40, placed_off=error), t,
                                steps.at(t))
    assert n > 12   # frames from before and after the step
    photo = _photo_under(out, terrain, placed_off=new)
    assert np.abs(out.image[out.valid].astype(int) - photo[out.valid]).max() <= 1
    # without the steps, the frames before it would be 3 px and 2 px off
    unmoved = TrackMosaic(min_pixels=6000, max_age=30.0)
    for k in range(30):
        out, n, _ = unmoved.compose(_frame(terrain, 10 + 3 * k, 40,
                                        placed_off=new if k >= 20 else old), 10.0 + k,
                                 np.zeros(2))
    photo = _photo_under(out, terrain, placed_off=new)
    assert np.abs(out.image[out.valid].astype(int) - photo[out.valid]).max() > 20


def test_large_frames_old_frames_and_unknown_steps_are_published_alone(terrain):
    mosaic = TrackMosaic(min_pixels=6000, max_age=5.0)
    for k in range(4):
        mosaic.compose(_frame(terrain, 10 + 3 * k, 40), 10.0 + k, np.zeros(2))
    # a frame seeing enough alone is published alone and forgets the track
    big = _frame(terrain, 100, 10, size=(100, 80))
    out, n, _ = mosaic.compose(big, 14.0, np.zeros(2))
    assert n == 1 and out is big and len(mosaic) == 0
    # frames older than max_age are left out
    for k in range(10):
        out, n, _ = mosaic.compose(_frame(terrain, 10 + 3 * k, 40), 20.0 + k, np.zeros(2))
    assert n == 6
    # frames of the odometry's history before a break are forgotten
    out, n, _ = mosaic.compose(_frame(terrain, 40, 40), 30.0, np.zeros(2), epoch=1)
    assert n == 1 and len(mosaic) == 1
    # with the estimate's steps unknown (a gap in the odometry) the frame goes alone
    frame = _frame(terrain, 50, 40)
    out, n, _ = mosaic.compose(frame, 31.0, None)
    assert out is frame and n == 1 and len(mosaic) == 0
    # off
    out, n, _ = TrackMosaic(0).compose(frame, 32.0, np.zeros(2))
    assert out is frame and n == 1


def test_a_fast_camera_s_mosaic_holds_the_frames_it_needs(terrain):
    """At 10 frames a second a frame moves a third of a pixel (here, a pixel every third
    frame): the frames that add under 2 % of their pixels are left out, so the mosaic of
    the 180 frames of 18 s holds 61, and it is the same strip of the photo."""
    fast = TrackMosaic(min_pixels=3000, max_age=30.0)
    for k in range(200):
        out, n, _ = fast.compose(_frame(terrain, 10 + k // 3, 40), 10.0 + 0.1 * k, np.zeros(2))
    # 1200 px a frame, 30 more per pixel moved: 60 pixels of track, one frame each
    assert n == 61 and out.georef.width == 40 + 60, (n, out.georef)
    photo = _photo_under(out, terrain)
    assert np.abs(out.image[out.valid].astype(int) - photo[out.valid]).max() <= 1


def test_a_mosaic_says_how_old_its_pixels_are(terrain):
    """A fix from a mosaic carries the estimate's velocity error over its frames' ages:
    the mosaic's lag is their mean age over its pixels, each pixel the newest frame's."""
    mosaic = TrackMosaic(min_pixels=3000, max_age=30.0)
    for k in range(40):
        out, n, lag = mosaic.compose(_frame(terrain, 10 + 3 * k, 40), 10.0 + k, np.zeros(2))
    first = 40 - n
    # each column of the mosaic as the newest of the n frames over it sees it
    cols = np.arange(10 + 3 * first, 50 + 3 * 39)
    newest_over = np.minimum((cols - 10) // 3, 39)
    expected = np.mean(39 - newest_over)
    # (a little older: each frame's feathered edge lets the older ones through)
    assert expected <= lag <= expected + 1.0
    # not the frames' mean age: most of the mosaic is its newest frames'
    assert lag < 0.75 * np.mean(np.arange(n))
    # a frame matched alone has none
    _, one, alone = mosaic.compose(_frame(terrain, 10, 10, size=(60, 60)), 60.0, np.zeros(2))
    assert one == 1 and alone == 0.0
