"""The flight simulator's real albedo (``simulate --albedo``) and start time."""

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine

from terrain_nav_ros.core.features.hillshade import hillshade
from terrain_nav_ros.core.terrain.georef import GeoReference
from terrain_nav_ros.core.terrain.synthetic_terrain import synthetic_dem
from terrain_nav_ros.tools import bags
from terrain_nav_ros.tools.flight_sim import (
    SimConfig,
    SimInputError,
    _epoch_ns,
    _open_metamap,
    albedo_registration,
    drape_photo,
    drape_registered,
    simulate,
)

# UTM 32N, north-up 30 m cells (rasterio's from_origin warns inside affine)
TRANSFORM = Affine(30.0, 0.0, 500000.0, 0.0, -30.0, 5000000.0)


def _write(path, data, transform=TRANSFORM, crs="EPSG:32632"):
    data = np.asarray(data, np.float32)
    data = data[None] if data.ndim == 2 else data
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1],
                       count=data.shape[0], dtype="float32", crs=crs,
                       transform=transform) as ds:
        ds.write(data)
    return str(path)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 256 px synthetic DEM and a photo of it: dark in the west half, bright in the east,
    with a band 2 that is the other way round."""
    tmp = tmp_path_factory.mktemp("scene")
    dem = _write(tmp / "dem.tif", synthetic_dem(256, gsd=30.0, seed=5) + 400.0)
    west_dark = np.where(np.arange(256)[None, :] < 128, 10.0, 200.0) * np.ones((256, 1))
    photo = _write(tmp / "photo.tif", np.stack([west_dark, 210.0 - west_dark, west_dark]))
    return dem, photo


def test_start_time_is_the_bags_time():
    assert _epoch_ns("2002-11-25T15:35:00Z") == 1038238500 * 10**9
    assert _epoch_ns("2002-11-25T16:35:00+01:00") == 1038238500 * 10**9
    with pytest.raises(ValueError, match="ISO 8601"):
        _epoch_ns("25/11/2002")


def test_a_photo_is_draped_on_the_render_grid(scene):
    dem, photo = scene
    metamap, _ = _open_metamap(SimConfig(dem=dem))
    # the DEM's centre is the ENU origin: west of it dark, east bright
    box = GeoReference.centred(0.0, 0.0, 15.0, 400, 300)
    rgb, _ = drape_photo(photo, "", metamap, box)
    assert rgb.shape == (300, 400, 3) and rgb.min() >= 0.0 and rgb.max() <= 1.0
    assert rgb[150, 100, 0] < 0.1 and rgb[150, 300, 0] > 0.9
    assert rgb[150, 100, 1] > 0.9                            # band 2 is the other way round
    one_band, _ = drape_photo(photo, "2", metamap, box)
    np.testing.assert_allclose(one_band[..., 0], one_band[..., 2])
    assert one_band[150, 100, 0] > 0.9
    # beyond the photo: its median grey, not black or NaN
    wide, _ = drape_photo(photo, "", metamap, GeoReference.centred(0.0, 0.0, 60.0, 400, 400))
    assert np.isfinite(wide).all() and 0.2 < wide[5, 5, 0] < 0.8
    with pytest.raises(ValueError, match="band 4 does not exist"):
        drape_photo(photo, "4", metamap, box)


def test_a_photo_elsewhere_is_a_clear_error(scene, tmp_path):
    dem, _ = scene
    far = _write(tmp_path / "far.tif", np.ones((50, 50)),
                 transform=Affine(30.0, 0.0, 700000.0, 0.0, -30.0, 4000000.0))
    metamap, _ = _open_metamap(SimConfig(dem=dem))
    with pytest.raises(ValueError, match="does not cover"):
        drape_photo(far, "", metamap, GeoReference.centred(0.0, 0.0, 30.0, 100, 100))


def test_camera_frames_see_the_draped_photo(scene, tmp_path):
    """Flying north along the photo's dark-bright edge: every frame shows the photo (one
    half dark, the other bright) instead of the rendered albedo, and the bag starts at the
    start time."""
    dem, photo = scene
    cfg = dict(dem=dem, duration=4.0, gnss_denied_after=100.0, agl=1500.0, camera_rate=1.0,
               pattern="straight", heading=90.0, start_north=-600.0, seed=2,
               image_format="mono8", start_time="2020-06-21T10:00:00Z")
    simulate(SimConfig(albedo=photo, **cfg), tmp_path / "photo")
    simulate(SimConfig(**cfg), tmp_path / "rendered")

    def frames(bag):
        out = []
        for msg in bags.read(bag):
            if msg.topic == "/camera/image_raw":
                m = bags.decode(msg)
                out.append(np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width))
        first = next(iter(bags.read(bag))).timestamp_ns
        return out, first

    draped, first = frames(tmp_path / "photo")
    rendered, _ = frames(tmp_path / "rendered")
    assert first >= _epoch_ns("2020-06-21T10:00:00Z")
    assert len(draped) == len(rendered) >= 3
    def split(frame):   # the contrast between the frame's halves across the track
        return abs(float(frame[:, frame.shape[1] // 2:].mean())
                   - frame[:, : frame.shape[1] // 2].mean())

    for d, r in zip(draped, rendered, strict=True):
        # haze and auto exposure compress the photo's contrast, but its split stays
        assert split(d) > 20.0 and split(d) > 3.0 * split(r)


def test_an_all_nodata_dem_is_said_as_such(tmp_path):
    """Not "the route leaves the DEM": the DEM is there, it holds no heights."""
    with rasterio.open(tmp_path / "void.tif", "w", driver="GTiff", width=200, height=200,
                       count=1, dtype="float32", crs="EPSG:32632", transform=TRANSFORM,
                       nodata=-9999.0) as ds:
        ds.write(np.full((1, 200, 200), -9999.0, np.float32))
    with pytest.raises(ValueError, match="no heights"):
        simulate(SimConfig(dem=str(tmp_path / "void.tif"), duration=5.0), tmp_path / "bag")


def test_a_flight_is_written_in_time_order_the_same_for_the_same_seed(tmp_path):
    """The streams are merged as they are made: every topic there, in stamp order, and the
    same seed gives the same bag byte for byte (the camera's noise is drawn last)."""
    cfg = dict(duration=4.0, gnss_denied_after=2.0, agl=1500.0, camera_rate=2.0, seed=4)
    simulate(SimConfig(**cfg), tmp_path / "a")
    simulate(SimConfig(**cfg), tmp_path / "b")
    a, b = list(bags.read(tmp_path / "a")), list(bags.read(tmp_path / "b"))
    stamps = [m.timestamp_ns for m in a]
    assert stamps == sorted(stamps)
    counts = {t.topic: t.count for t in bags.topics(tmp_path / "a")}
    assert counts["/imu/data"] == 400 and counts["/camera/camera_info"] == 7
    assert counts["/camera/image_raw/compressed"] == 7 and counts["/tf_static"] == 1
    assert counts["/gnss/fix"] == 10 and counts["/baro/pressure"] == 40
    assert [(m.topic, m.timestamp_ns, m.rawdata) for m in a] == \
        [(m.topic, m.timestamp_ns, m.rawdata) for m in b]


def test_a_flight_that_fails_part_way_leaves_no_bag(tmp_path):
    """The first frame fails (no such image format) after a second of IMU is written."""
    with pytest.raises(ValueError, match="unknown image_format"):
        simulate(SimConfig(duration=4.0, image_format="png"), tmp_path / "bag")
    assert not (tmp_path / "bag").exists()


def test_the_dem_s_stated_accuracy_goes_into_the_mission(tmp_path):
    """``dem_ce90`` is written into mission.yaml for the replay's ekf; a bad one is refused
    before anything is flown."""
    simulate(SimConfig(duration=4.0, camera_rate=1.0, dem_ce90=20.0), tmp_path / "bag")
    mission = yaml.safe_load((tmp_path / "bag" / "mission.yaml").read_text())
    assert mission["dem_horizontal_ce90"] == 20.0
    with pytest.raises(SimInputError, match="horizontal accuracy"):
        simulate(SimConfig(duration=4.0, dem_ce90=float("nan")), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()


def _shaded_photos(scene, tmp_path):
    """The scene's DEM, and its shading as a photo in register and one 2.5 cells (75 m)
    east of it."""
    dem, _ = scene
    with rasterio.open(dem) as src:
        heights = src.read(1)
    shade = hillshade(heights, 150.0, 40.0, gsd=30.0, ambient=0.2) * 200.0
    aligned = _write(tmp_path / "aligned.tif", shade)
    shifted = _write(tmp_path / "shifted.tif", shade,
                     transform=TRANSFORM @ Affine.translation(2.5, 0.0))
    return dem, aligned, shifted


def test_a_photo_off_its_dem_is_named_misregistered(scene, tmp_path, capsys):
    """A photo whose ground lies 75 m east of the DEM's, draped as it is (the default,
    --albedo-shift none): the camera would see it there and every fix would be off by as
    much, so simulate says so; one in register is not named."""
    dem, aligned, shifted = _shaded_photos(scene, tmp_path)
    metamap, _ = _open_metamap(SimConfig(dem=dem))
    box = GeoReference.centred(0.0, 0.0, 15.0, 360, 360)
    terrain = metamap.tile(box).elevation
    said = {}
    for name, photo in (("aligned", aligned), ("shifted", shifted)):
        rgb, covered = drape_photo(photo, "", metamap, box)
        said[name] = albedo_registration(rgb, covered, terrain, box, (150.0, 40.0),
                                         30.0).registration_warning()
    assert said["aligned"] is None
    assert "misregistered" in said["shifted"] and "+7" in said["shifted"]   # +75 m east
    cfg = SimConfig(dem=dem, albedo=shifted, duration=2.0, camera_rate=1.0, agl=1500.0,
                    pattern="straight", image_format="mono8", sun=(150.0, 40.0))
    summary = simulate(cfg, tmp_path / "bag")
    assert "misregistered" in capsys.readouterr().err
    assert summary["albedo_shift_m"] == [0.0, 0.0]


def test_a_photo_off_its_dem_is_draped_back_in_register(scene, tmp_path, capsys):
    """With --albedo-shift measured the photo 75 m east is draped shifted back by the
    offset its shading shows, so the camera sees the DEM's ground (its shading then agrees
    at no shift); the shift is said and recorded in mission.yaml. A given shift is applied
    as it is."""
    dem, _, shifted = _shaded_photos(scene, tmp_path)
    metamap, _ = _open_metamap(SimConfig(dem=dem))
    box = GeoReference.centred(0.0, 0.0, 15.0, 360, 360)
    terrain = metamap.tile(box).elevation
    cfg = SimConfig(dem=dem, albedo=shifted, albedo_shift="measured", sun=(150.0, 40.0))
    photo, (east, north) = drape_registered(cfg, metamap, box, terrain, cfg.sun)
    assert east == pytest.approx(75.0, abs=0.7 * 30.0) and abs(north) < 0.7 * 30.0
    assert "draped shifted back" in capsys.readouterr().err
    again = albedo_registration(photo, np.isfinite(photo).all(axis=-1), terrain, box,
                                cfg.sun, 30.0)
    assert np.hypot(again.offset_east, again.offset_north) < 0.7 * 30.0
    given = SimConfig(dem=dem, albedo=shifted, albedo_shift="75,0", sun=(150.0, 40.0))
    _, shift = drape_registered(given, metamap, box, terrain, given.sun)
    assert shift == (75.0, 0.0)
    summary = simulate(SimConfig(dem=dem, albedo=shifted, albedo_shift="measured",
                                 duration=2.0, camera_rate=1.0, agl=1500.0,
                                 pattern="straight", image_format="mono8",
                                 sun=(150.0, 40.0)), tmp_path / "bag")
    assert summary["albedo_shift_m"][0] == pytest.approx(75.0, abs=0.7 * 30.0)
    with pytest.raises(SimInputError, match="albedo shift"):
        simulate(SimConfig(dem=dem, albedo=shifted, albedo_shift="east"), tmp_path / "bad")
