"""A sensor's row and column stripes are taken off its frame, and a frame without any is
left as it is."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from terrain_nav_ros.core.camera.destripe import destripe


def _terrain(shape=(300, 400), seed=0):
    """Shading-like relief: smooth random hills, 0-255 with sensor noise."""
    rng = np.random.default_rng(seed)
    hills = gaussian_filter(rng.normal(size=shape), 6.0)
    image = 128 + 60 * hills / hills.std() + rng.normal(0, 2, shape)
    return np.clip(image, 0, 255).astype(np.float32)


def _stripes(shape, seed=1):
    rows = 40 * np.sin(2 * np.pi * np.arange(shape[0]) / 16)[:, None]   # banding
    columns = np.random.default_rng(seed).normal(0, 25, shape[1])[None, :]   # column FPN
    return rows + columns


def test_banding_and_column_pattern_noise_are_taken_off():
    clean = _terrain()
    striped = clean + _stripes(clean.shape)
    out = destripe(striped)
    error = out - clean
    error -= error.mean()          # a constant offset is no stripe
    assert (striped - clean).std() > 30
    assert error.std() < 0.5 * (striped - clean).std(), error.std()


def test_a_frame_without_stripes_is_returned_as_it_is():
    for image in (_terrain(), np.clip(_terrain(seed=3), 0, 255).astype(np.uint8),
                  np.full((50, 60), 7, np.uint8)):
        assert destripe(image) is image


def test_an_integer_frame_stays_of_its_type_and_range():
    clean = _terrain()
    striped = np.clip(clean + _stripes(clean.shape), 0, 255).astype(np.uint8)
    out = destripe(striped)
    assert out.dtype == np.uint8
    error = out.astype(float) - clean
    assert (error - error.mean()).std() < 0.5 * (striped - clean.astype(float)).std()


@pytest.mark.parametrize("holes", ["nan", "mask"])
def test_pixels_not_seen_take_no_part(holes):
    """A frame's invalid corner (a rotated cut, NaN pixels) does not bend the stripes it
    estimates elsewhere; the corner stays invalid."""
    clean = _terrain()
    striped = clean + _stripes(clean.shape)
    unseen = np.zeros(clean.shape, bool)
    unseen[:120, :150] = True
    valid = None
    if holes == "nan":
        striped[unseen] = np.nan
    else:
        striped[unseen] = 255.0           # garbage where nothing was seen
        valid = ~unseen
    out = destripe(striped, valid)
    error = (out - clean)[~unseen]
    assert (error - error.mean()).std() < 0.5 * (striped - clean)[~unseen].std()
    if holes == "nan":
        assert np.isnan(out[unseen]).all()
