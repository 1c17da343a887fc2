"""The real-imagery study (terrain_nav_ros.tools.real_imagery, ``evaluate --image/--scenes``)."""

import json
import math

import numpy as np
import pytest

from terrain_nav_ros.core.terrain.ortho_io import nir_band, rasterio_quiet
from terrain_nav_ros.tools.cli import main
from terrain_nav_ros.tools.real_imagery import (
    _control_regions,
    load_scene,
    load_scenes,
    run_real_imagery_study,
)

SCENES_YAML = "benchmarks/real_scenes.yaml"


def _write_pair(tmp_path, *, geographic: bool, nodata_hole: bool = False):
    """A synthetic image + DEM pair in one CRS: the image is the DEM's hillshade plus a
    stripe of "albedo", so the pair is co-registered by construction."""
    import rasterio
    from affine import Affine

    from terrain_nav_ros.core.features.hillshade import hillshade
    from terrain_nav_ros.core.terrain.synthetic_terrain import synthetic_dem

    z = synthetic_dem(160, gsd=30.0, seed=3).astype(np.float32)
    image = (hillshade(z, 160.0, 40.0, gsd=30.0) * 200.0 + 20.0).astype(np.float32)
    image[:, 100:110] += 40.0
    if nodata_hole:
        image[:20, :20] = -9999.0
    if geographic:
        crs, transform = "EPSG:4326", Affine(0.0003, 0.0, 6.0, 0.0, -0.0003, 45.0)
    else:
        crs, transform = "EPSG:32632", Affine(30.0, 0.0, 500000.0, 0.0, -30.0, 5000000.0)
    paths = []
    for name, data, nodata in (("image.tif", image, -9999.0), ("dem.tif", z, None)):
        path = tmp_path / name
        with rasterio.open(path, "w", driver="GTiff", height=160, width=160, count=1,
                           dtype="float32", crs=crs, transform=transform,
                           nodata=nodata) as ds:
            ds.write(data, 1)
        paths.append(path)
    return paths


def _warped(path, crs, out):
    """``path`` reprojected to ``crs`` (its own resolution there) as ``out``."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(path) as src, rasterio_quiet():
        transform, w, h = calculate_default_transform(src.crs, crs, src.width, src.height,
                                                      *src.bounds)
        profile = src.profile | {"crs": crs, "transform": transform, "width": w, "height": h}
        with rasterio.open(out, "w", **profile) as dst:
            reproject(rasterio.band(src, 1), rasterio.band(dst, 1),
                      resampling=Resampling.bilinear)
    return out


def test_a_pair_in_degrees_is_put_on_a_utm_grid(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=True, nodata_hole=True)
    scene = load_scene(image, dem, when="2021-06-21T10:00:00Z")
    # 0.0003 x 0.0003 deg at 45 N: 33 m by 24 m, the side of its area 28 m
    assert 27.0 < scene.gsd < 30.0
    assert 27.0 < scene.dem_cell < 30.0
    assert scene.image.dtype == np.uint8 and scene.image.shape == scene.elevation.shape
    h, w = scene.valid.shape
    assert not scene.valid[:10, :10].any() and scene.valid[h // 3:-h // 3, w // 3:-w // 3].all()
    assert np.isfinite(scene.elevation).all()
    # the sun of a June morning in the Alps: in the south-east, well up
    az, el = scene.sun
    assert 90.0 < az < 180.0 and 40.0 < el < 70.0


@pytest.mark.parametrize("crs", ["EPSG:3857", "+proj=utm +zone=32 +datum=WGS84 +units=us-ft"])
def test_a_grid_whose_units_are_not_ground_metres_is_put_on_utm(tmp_path, crs):
    """Web Mercator's metres are 1/cos(latitude) too short on the ground (1.41 at 45 N);
    a US state plane grid is in feet. Either pair, read at face value, would be matched at
    the wrong GSD and its render's slopes scaled wrong."""
    (tmp_path / "utm").mkdir()
    image, dem = _write_pair(tmp_path, geographic=False)     # 30 m, UTM 32N, at 45 N
    image = _warped(image, crs, tmp_path / "image_warped.tif")
    dem = _warped(dem, crs, tmp_path / "dem_warped.tif")
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert scene.gsd == pytest.approx(30.0, rel=0.03)
    assert scene.dem_cell == pytest.approx(30.0, rel=0.03)
    h, w = scene.valid.shape
    assert scene.valid[h // 4:-h // 4, w // 4:-w // 4].all()
    assert abs(h - 160) < 12 and abs(w - 160) < 12          # the same ground, not 1.4x
    utm = load_scene(*_write_pair(tmp_path / "utm", geographic=False), sun=(150.0, 40.0))
    # the same relief: the DEM is not stretched by the grid's units
    assert np.ptp(scene.elevation) == pytest.approx(np.ptp(utm.elevation), rel=0.05)


def test_a_dem_s_undeclared_voids_are_voids_not_pits(tmp_path):
    """SRTM's -32768 in a GeoTIFF that declares no nodata: read as the graph reads it, as
    voids; a small void is filled, a large one is never observed and renders no cliff."""
    import rasterio

    image, dem = _write_pair(tmp_path, geographic=False)
    with rasterio.open(dem) as ds:
        profile, z = ds.profile, ds.read(1)
    z[60:100, 60:100] = -32768.0     # 1600 cells: large
    z[20:24, 120:124] = -32768.0     # 16 cells: small
    with rasterio.open(dem, "w", **profile) as ds:
        ds.write(z, 1)
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert "impossible on Earth" in scene.dem_warning
    assert not scene.valid[62:98, 62:98].any()
    assert scene.valid[18:26, 118:126].all()
    intact = z[z > -1000]
    assert intact.min() - 1.0 < scene.elevation.min() and scene.elevation.max() < intact.max() + 1.0
    summary = run_real_imagery_study([scene], sizes=(64,), cases=2, headings=("unknown",),
                                     baselines=(), controls_per_case=0,
                                     out_dir=tmp_path / "study", log=lambda *a: None)
    assert "impossible on Earth" in summary["setup"]["scenes"][0]["dem_warning"]
    assert "Input warnings" in (tmp_path / "study" / "report.md").read_text()


def test_an_image_s_undeclared_fill_is_no_data_not_the_stretch_s_low_end(tmp_path):
    """Reflectances with -9999 outside the footprint and no nodata declared: read as they
    were, the fill took the stretch's 1st percentile and squeezed the terrain into a few
    grey levels (every view of PA November "too little drainage"), and its edge was a
    line of full contrast."""
    import rasterio

    image, dem = _write_pair(tmp_path, geographic=False)
    clean = load_scene(image, dem, sun=(150.0, 40.0))
    with rasterio.open(image) as ds:
        profile, grey = ds.profile, ds.read(1)
    reflectance = (grey * 40.0).astype(np.int16)
    reflectance[:40] = -9999
    profile.update(dtype="int16", nodata=None)
    with rasterio.open(image, "w", **profile) as ds:
        ds.write(reflectance, 1)
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert "hold -9999" in scene.image_warning and "read as no data" in scene.image_warning
    assert not scene.valid[:40].any() and scene.valid[40:].all()
    # the terrain keeps its grey levels, as in the image without the fill
    assert scene.image[40:].std() > 0.9 * clean.image[40:].std()
    summary = run_real_imagery_study([scene], sizes=(64,), cases=2, headings=("unknown",),
                                     baselines=(), controls_per_case=0,
                                     out_dir=tmp_path / "study", log=lambda *a: None)
    assert "hold -9999" in summary["setup"]["scenes"][0]["image_warning"]
    assert "hold -9999" in (tmp_path / "study" / "report.md").read_text()


def test_a_study_no_view_fits_in_is_a_clear_error(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=False)
    scene = load_scene(image, dem, sun=(150.0, 40.0))    # 160 x 160 px
    with pytest.raises(ValueError, match=r"no view of 256 px fits in image \(160x160 px\)"):
        run_real_imagery_study([scene], sizes=(256,), cases=2, headings=("unknown",),
                               baselines=(), out_dir=tmp_path / "study", log=lambda *a: None)
    summary = run_real_imagery_study([scene], sizes=(64, 256), cases=2, headings=("unknown",),
                                     baselines=(), controls_per_case=0,
                                     out_dir=tmp_path / "study", log=lambda *a: None)
    assert summary["skipped"] == [{"scene": "image", "size": 256, "heading": "unknown"}]
    assert "Not studied" in summary["report"] and "image 256 px" in summary["report"]


def test_an_image_s_undeclared_zeros_are_fill(tmp_path):
    """Landsat 7's SLC-off gaps and a footprint's edge are DN 0 in products that often
    declare no nodata; a gap's edge would be read as a valley. Zeros of an image without a
    nodata value, mask or alpha are nodata (a GDAL warp's float border too); a declared
    nodata value keeps them."""
    import rasterio

    image, dem = _write_pair(tmp_path, geographic=False)
    with rasterio.open(image) as ds:
        profile, grey = ds.profile, ds.read(1)
    dn = np.clip(grey, 1, 255).astype(np.uint8)
    gaps = np.zeros(dn.shape, bool)
    for r in range(10, 160, 33):
        gaps[r:r + 6] = True
    gaps[:, :12] = True              # outside the footprint
    dn[gaps] = 0
    profile.update(dtype="uint8", nodata=None)
    with rasterio.open(image, "w", **profile) as ds:
        ds.write(dn, 1)
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert not scene.valid[gaps].any() and scene.valid[~gaps].mean() > 0.99
    with rasterio.open(image, "r+") as ds:
        ds.nodata = 255               # declared: its zeros are data
    assert load_scene(image, dem, sun=(150.0, 40.0)).valid[gaps].all()
    warped = np.where(gaps, 0.0, grey).astype(np.float32)
    profile.update(dtype="float32", nodata=None)
    with rasterio.open(image, "w", **profile) as ds:
        ds.write(warped, 1)
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert not scene.valid[gaps].any() and scene.valid[~gaps].mean() > 0.99


def test_a_study_gsd_resamples_both(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=False)
    native = load_scene(image, dem, sun=(150.0, 40.0))
    half = load_scene(image, dem, sun=(150.0, 40.0), gsd=15.0)
    assert native.gsd == 30.0 and native.image.shape == (160, 160)
    assert half.gsd == 15.0 and half.image.shape == (320, 320)
    # the DEM's own cell is kept: the study matches a finer scene at it
    assert native.dem_cell == half.dem_cell == 30.0


@pytest.mark.parametrize("descriptions, band", [
    (("B02 blue", "B03 green", "B04 red", "B05 nir"), 4),
    (("TM B1 reflectance", "TM B2", "TM B3", "TM B4 reflectance x1e4"), 4),
    (("ETM+ B1 DN", "ETM+ B4 DN"), 2),
    (("coastal", "OLI B5"), 2),
    (("MSI B4", "MSI B8A"), 2),
    (("red", "Near-Infrared"), 2),
    (("blue", "green", "red", "nir08", "swir16"), 4),     # STAC's asset keys (Landsat C2)
    (("B02", "B03", "B04", "B8A", "B11"), 4),             # Sentinel-2's narrow NIR band
    (("B1", "B2", "B3", "B8"), None),                     # Landsat's B8 is panchromatic
    ((None, None, None), None),
    (("B1", "B2", "B4"), None),       # no sensor named: B4 may be anything
    (("red", "green", "blue"), None),
])
def test_the_near_infrared_band_is_found_by_its_description(descriptions, band):
    assert nir_band(descriptions) == band


def test_a_scene_without_a_band_takes_the_near_infrared(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=False)
    import rasterio
    with rasterio.open(image) as ds:
        profile, grey = ds.profile, ds.read(1)
    profile.update(count=2)
    with rasterio.open(image, "w", **profile) as ds:   # band 1 "red" flat, band 2 "nir"
        ds.write(np.full_like(grey, 50.0), 1)
        ds.write(grey, 2)
        ds.set_band_description(1, "B04 red")
        ds.set_band_description(2, "B05 nir")
    scene = load_scene(image, dem, sun=(150.0, 40.0))
    assert scene.image.std() > 20.0   # the shaded band, not the flat one
    with pytest.raises(ValueError, match="every valid pixel holds 50"):   # the flat one
        load_scene(image, dem, sun=(150.0, 40.0), band=1)


@pytest.mark.parametrize("kwargs, message", [
    ({"band": 4}, "band 4 does not exist"),
    ({}, "the scene's sun is needed"),
    ({"sun": (150.0, -5.0)}, "sun elevation"),
    ({"sun": (math.nan, 45.0)}, "sun azimuth must be a finite number"),
    ({"sun": (150.0, 40.0), "gsd": -5.0}, "GSD must be a number of metres > 0"),
    ({"sun": (150.0, 40.0), "gsd": math.nan}, "GSD must be a number of metres > 0"),
    ({"sun": (150.0, 40.0), "gsd": 1e-3}, "M pixels .*nearer its own cell"),
])
def test_bad_scene_options_are_clear_errors(tmp_path, kwargs, message):
    image, dem = _write_pair(tmp_path, geographic=False)
    with pytest.raises(ValueError, match=message):
        load_scene(image, dem, **kwargs)


def test_a_scene_without_a_sun_is_told_the_azimuth_its_shading_follows(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=False)   # shaded from azimuth 160
    with pytest.raises(ValueError, match=r"sun is needed.*from azimuth 1(5[5-9]|6[0-5]) deg"):
        load_scene(image, dem)


def test_a_doubtful_sun_is_warned_of_and_reported(tmp_path, capsys):
    image, dem = _write_pair(tmp_path, geographic=False)   # shaded from azimuth 160
    assert load_scene(image, dem, sun=(160.0, 40.0)).sun_warning is None
    out = tmp_path / "study"
    code = main(["evaluate", "--image", str(image), "--dem", str(dem), "--sun", "300,40",
                 "--sizes", "64", "--cases", "1", "--controls", "0", "--no-baselines",
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0 and "warning: image: its shading agrees better with a sun from " \
        "azimuth 1" in err and "check the sun" in err
    saved = json.loads((out / "results.json").read_text())["setup"]["scenes"][0]
    assert "check the sun" in saved["sun_warning"]
    assert abs(saved["shading"]["best_azimuth_deg"] - 160.0) <= 5.0
    assert saved["shading"]["r_at_sun"] < 0.8 * saved["shading"]["r_best"]
    assert "check the sun" in (out / "report.md").read_text()


def test_the_dev_scenes_shading_follows_their_stated_sun(shared_data):
    """Landsat and HLS scenes whose sun is known: the azimuth their shading follows is within
    a few degrees of it; July's canopy and cloud show little of the terrain."""
    scenes = {s.name: s for s in load_scenes(SCENES_YAML, shared_data / "imagery")
              if not s.name.startswith(("swellendam", "rmnp"))}   # their dates are not known
    for name, scene in scenes.items():
        if name == "pa_july_clouds":
            assert "little of its terrain's shading" in scene.sun_warning
            continue
        off = abs((scene.shading.best_azimuth - scene.sun[0] + 180.0) % 360.0 - 180.0)
        assert off <= 10.0 and scene.sun_warning is None, (name, scene.shading)


def test_a_corrupt_image_is_a_clear_error(tmp_path):
    image, dem = _write_pair(tmp_path, geographic=False)
    image.write_bytes(b"II*\x00" + b"\x00" * 40)
    with pytest.raises(ValueError, match="cannot read the image"):
        load_scene(image, dem, sun=(150.0, 40.0))


def test_cli_answers_bad_input_with_one_line(tmp_path, capsys):
    code = main(["evaluate", "--image", str(tmp_path / "missing.tif"), "--dem",
                 str(tmp_path / "missing_dem.tif"), "--sun", "150,40"])
    err = capsys.readouterr().err
    assert code == 2 and "no such file" in err and "Traceback" not in err
    image, dem = _write_pair(tmp_path, geographic=False)
    code = main(["evaluate", "--image", str(image), "--dem", str(dem), "--sun", "150"])
    assert code == 2 and "--sun takes two numbers" in capsys.readouterr().err
    code = main(["evaluate", "--image", str(image), "--dem", str(dem), "--sun", "150,40",
                 "--region-factor", "0.5"])
    assert code == 2 and "--region-factor 0.5: the region's side must be 1-10 times" in \
        capsys.readouterr().err


def test_the_region_s_size_is_the_study_s_to_choose(tmp_path, capsys):
    """``--region-factor 1.5``: each view is localised in a region 1.5 times its side (a
    tracking filter's prior), and the outputs say so."""
    image, dem = _write_pair(tmp_path, geographic=False)
    out = tmp_path / "study"
    assert main(["evaluate", "--image", str(image), "--dem", str(dem), "--sun", "150,40",
                 "--sizes", "64", "--cases", "2", "--controls", "0", "--no-baselines",
                 "--heading", "known", "--region-factor", "1.5", "--out", str(out)]) == 0
    saved = json.loads((out / "results.json").read_text())
    assert saved["setup"]["region_factor"] == 1.5
    assert "localised in a region 1.5x their side" in capsys.readouterr().out


def test_study_on_real_scenes(tmp_path, shared_data):
    """Two real places (Athabasca, Pennsylvania): views are localised at their place,
    views of one place are never accepted in the other's regions, and the outputs say so."""
    scenes = [s for s in load_scenes(SCENES_YAML, shared_data / "imagery")
              if s.name in ("athabasca_l30", "pa_november@30m")]
    assert len(scenes) == 2
    out = tmp_path / "study"
    summary = run_real_imagery_study(scenes, sizes=(128,), cases=4, out_dir=out,
                                     headings=("known",), baselines=("ncc",),
                                     log=lambda *_: None)
    rows = summary["rows"]
    assert {r["scene"] for r in rows} == {"athabasca_l30", "pa_november@30m"}
    for r in rows:
        assert r["minutiae"]["cases"] == 4 and len(r["cases"]) == 4
        assert "ncc" in r
    localised = sum(r["minutiae"]["success"] for r in rows)
    wrong = sum(r["minutiae"]["wrong"] for r in rows)
    assert localised >= 4 and wrong == 0
    non = summary["non_pva"]
    # each view meets up to two of the other place's distinct regions (its cases' regions,
    # clipped to a scene smaller than a 3x region, repeat): at least one, never one twice
    # (test_a_view_s_controls_are_distinct_regions_of_other_places); neither scene has room
    # for a far part of its own
    assert 8 <= non["comparisons"] <= 2 * 8 and non["accepted"] == 0
    assert {"report.md", "results.json", "scores.png"} <= {p.name for p in out.iterdir()}
    saved = json.loads((out / "results.json").read_text())
    assert saved["non_pva"]["comparisons"] == non["comparisons"]
    # each case says what its score is made of: valleys, and ridges given the valleys
    for case in (c for r in saved["rows"] for c in r["cases"]):
        if case["err_px"] <= 3.0:
            assert case["valleys_score"] > 0 and case["ridges_score"] >= 0
            assert 0 <= case["ridges_dependence"] < 1
            # the offset east and north of which the error is the length
            assert math.hypot(*case["offset_m"]) == pytest.approx(case["err_m"])
    for r in saved["rows"]:   # their mean, the pair's registration as the matcher sees it
        mean = r["minutiae"]["mean_offset_m"]
        assert (mean is None) == (r["minutiae"]["success"] == 0)
        assert mean is None or math.hypot(*mean) <= 3.0 * 30.0
    assert "minus the localised views' mean offset" in (out / "report.md").read_text()
    assert "Controls (non-PVA)" in (out / "report.md").read_text()
    # the landmarks are rendered as the graph's landmark_renderer does: with cast shadows
    assert saved["setup"]["shadows"] is True
    assert "with cast shadows" in (out / "report.md").read_text()


def test_a_scene_finer_than_its_dem_is_matched_at_the_dem_cell(tmp_path, shared_data):
    """PA November resampled to 15 m over its 30 m DEM: matched at 30 m (views and regions
    area averaged), its 256 px views are localised, their places given in 15 m pixels."""
    scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                       shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                       band=4, sun=(159.5, 26.2), gsd=15.0)
    summary = run_real_imagery_study([scene], sizes=(256,), cases=3, out_dir=tmp_path,
                                     headings=("known",), baselines=(), controls_per_case=0,
                                     match_gsd="dem", log=lambda *_: None)
    assert summary["setup"]["match_gsd_m"][scene.name] == pytest.approx(30.0, rel=0.01)
    (row,) = summary["rows"]
    assert row["minutiae"]["success"] >= 2 and row["minutiae"]["wrong"] == 0
    assert "| 15 | 30 | 30 |" in summary["report"]
    # 256 px of 15 m are 128 cells of the 30 m it is matched at
    (group,) = summary["by_cells"]
    assert group["cells"] == 128 and group["cases"] == 3 and not group["faint_shading"]
    assert group["success"] == row["minutiae"]["success"]
    assert "| known | seen | 128 | 3 |" in summary["report"]


def test_a_scene_that_shows_no_terrain_is_counted_apart(tmp_path, shared_data):
    """PA July's canopy and clouds follow its DEM's shading at no sun azimuth: its views are
    counted apart from those of scenes that show their terrain."""
    (july,) = [s for s in load_scenes(SCENES_YAML, shared_data / "imagery")
               if s.name == "pa_july_clouds"]
    summary = run_real_imagery_study([july], sizes=(128,), cases=2, out_dir=tmp_path,
                                     headings=("known",), baselines=(), controls_per_case=0,
                                     log=lambda *_: None)
    (group,) = summary["by_cells"]
    assert group["faint_shading"] and group["cells"] == 128 and group["cases"] == 2
    assert "| known | faint | 128 | 2 |" in summary["report"]


def test_scenes_file_lists_every_dev_pair(shared_data):
    """benchmarks/real_scenes.yaml names files that exist in the shared imagery folder."""
    import yaml

    doc = yaml.safe_load(open(SCENES_YAML))
    for entry in doc["scenes"]:
        for key in ("image", "dem"):
            assert (shared_data / "imagery" / entry[key]).is_file(), entry[key]


@pytest.mark.parametrize("text, message", [
    ("scenes: 5", "expected 'scenes:' and a list of scenes"),
    ("scenes: []", "expected 'scenes:' and a list of scenes"),
    ("- image.tif", "expected 'scenes:' and a list of scenes"),
    ("scenes: [image.tif]", "scene 1: expected a mapping"),
    ("scenes: [{name: a, image: image.tif}]", r"scene 1 \(a\): 'dem' \(a file name\) is missing"),
    ("scenes: [{image: image.tif, dem: dem.tif, sun: [150, 40], bnad: 4}]",
     "unknown key bnad"),
    ("scenes: [{image: image.tif, dem: dem.tif, sun: [150, 40], band: red}]",
     "band must be a band number"),
    ("scenes: [{image: image.tif, dem: dem.tif, sun: [150, 40], gsd: [30, thirty]}]",
     "gsd must be a number of metres"),
    ("scenes: [{image: image.tif, dem: dem.tif, sun: [150]}]",
     r"scene 1 \(image\): the sun must be two numbers"),
])
def test_a_scenes_file_s_mistakes_are_named(tmp_path, text, message):
    _write_pair(tmp_path, geographic=False)
    (tmp_path / "scenes.yaml").write_text(text)
    with pytest.raises(ValueError, match=message):
        load_scenes(tmp_path / "scenes.yaml")


def test_a_scene_without_a_name_is_named_after_its_image(tmp_path):
    _write_pair(tmp_path, geographic=False)
    (tmp_path / "scenes.yaml").write_text(
        "scenes: [{image: image.tif, dem: dem.tif, sun: [150, 40], gsd: [30, 60]}]")
    assert [s.name for s in load_scenes(tmp_path / "scenes.yaml")] == ["image@30m", "image@60m"]


def test_a_views_nodata_makes_no_creases(tmp_path):
    """A view with a patch of nodata (a cloud mask, the scene's edge) is extracted with its
    mask, as camera_ingest's GeoImage tells the graph's extractor: the patch's edge, a step
    from the terrain to 0, gives no creases; unmasked it does."""
    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools.real_imagery import _Extractor

    scene = load_scene(*_write_pair(tmp_path, geographic=False), sun=(160.0, 40.0))
    view = scene.image[10:138, 10:138].copy()
    valid = np.ones(view.shape, bool)
    valid[40:80, 40:80] = False
    view[~valid] = 0
    ring = np.zeros(view.shape, bool)
    ring[36:84, 36:84] = True
    ring[44:76, 44:76] = False                   # 4 px either side of the patch's edge
    extractor, matcher = _Extractor(MatchParams()), Matcher()
    masked, _ = extractor.index(matcher, view, scene, valid=valid)
    unmasked, _ = extractor.index(matcher, view, scene)
    masked_creases, unmasked_creases = (ix.crease_image.astype(bool)
                                        for ix in (masked, unmasked))
    assert not masked_creases[~valid].any()
    assert (masked_creases & ring).sum() < 0.6 * (unmasked_creases & ring).sum()
    assert masked.n > 0


def _localise_view(scene, m, size: int, region_scene=None, box=None, seen=None) -> dict:
    """The study's localisation (graph's settings, matched at the DEM's cell) of the
    ``size`` px view of ``scene`` that ``m`` (view px -> scene px) cuts, in the whole scene
    or in the landmark region ``box`` (x0, y0, x1, y1) of ``region_scene``; ``seen`` maps
    the view to what the camera saw of it."""
    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools import real_imagery as ri

    region_scene = region_scene or scene
    ri.render_landmark([region_scene])
    view, valid = ri.view_at(scene, m, size)
    if seen is not None:
        view = seen(view)
    centre = m[:, :2] @ np.full(2, 0.5 * (size - 1)) + m[:, 2]
    h, w = region_scene.image.shape
    case = ri._Case(view, box or (0, 0, w, h), centre, valid, m)
    params = MatchParams()
    matcher = Matcher(params, threshold=-1e9)
    extractor = ri._Extractor(params, "dem")
    region_index = extractor.region_index(matcher, region_scene, case.region)
    return ri._localise(matcher, extractor, scene, case, region_index) | {
        "region_index": region_index[0]}


def test_a_small_view_with_a_large_view_s_minutiae_is_found_behind_chance_peaks(shared_data):
    """A 128 px view of Costa Rica's volcano with 65 minutiae goes through the view search
    (a large view's path), whose coarse crease peak at the view's place trails chance peaks:
    when the ICP's best is not clear, the fine level ranks the coarse candidates again, and
    the view is localised (it scored -0.5, 25 px off, without)."""
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "costarica_barva_l5_20010114.tif",
                       shared_data / "imagery" / "costarica_barva_astergdem_4326.tif",
                       band=4, when="2001-01-14T15:30:00Z")
    # view px -> scene px: turned by 170 deg, 3 % smaller (the study's case, seed 1)
    m = np.array([[-0.95424341, 0.17135961, 182.01848094],
                  [-0.17135961, -0.95424341, 143.40288659]])
    result = _localise_view(scene, m, 128)
    assert result["view_index"].n >= MatchParams().crease_search_below
    # within 3 px: the DEM is ~2 px off the image (the imagery README)
    assert result["score"] >= _graph_threshold() and result["err"] <= 3.0


def test_a_view_whose_rotation_ranks_low_at_half_resolution_is_found(shared_data):
    """A 512 px view of PA November at 15 m (256 px at the DEM's 30 m): its true rotation
    has twice any other's crease hits in full but ranks 49th of 228 at half the
    resolution, where the view search shortlists its rotations; 16 per proposal keep it
    (8 did not: the view scored 1.0, 54 px off)."""
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                       shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                       band=4, sun=(159.5, 26.2), gsd=15.0)
    # view px -> scene px: turned by 5 deg, 9 % smaller (the study's case, seed 3)
    m = np.array([[0.90278673, -0.07841006, 124.35610959],
                  [0.07841006, 0.90278673, 56.71157536]])
    result = _localise_view(scene, m, 512)
    # 3 px at the matching GSD (30 m) are 6 of the scene's 15 m pixels
    assert result["score"] >= _graph_threshold() and result["err"] <= 6.0


def test_parallel_ridges_aligned_where_the_valleys_are_do_not_count_twice(shared_data):
    """A 128 px view of PA November's parallel ridges at 15 m (64 px at the DEM's cell, 6
    minutiae) against an Athabasca region, a control: at the best transform a third of its
    valleys and a third of its ridges land on the region's (chance: a tenth each), and
    summed as independent they passed the threshold at 11.0. Ridges lie between valleys,
    and the shifted transforms show the two agreements rise and fall together: the ridges
    count given the valleys, and the pair is no match."""
    from terrain_nav_ros.core.matching.crease_check import conditioned_on, crease_evidence
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools.cli import _graph_threshold

    view_scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                            shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                            band=4, sun=(159.5, 26.2), gsd=15.0)
    region_scene = load_scene(shared_data / "imagery" / "athabasca_hls_l30_20200816.tif",
                              shared_data / "imagery" / "athabasca_dem30m_utm11.tif",
                              band=4, when="2020-08-16T18:50:00Z")
    # view px -> scene px: turned by -10 deg, 9 % larger (the study's case, seed 4)
    m = np.array([[1.07715138, 0.19368372, 361.987693],
                  [-0.19368372, 1.07715138, 309.266114]])
    result = _localise_view(view_scene, m, 128, region_scene, (0, 0, 215, 205))
    assert result["score"] < _graph_threshold()
    # The transform the search accepted at 11.0 (matching px; the region's DEM void was then
    # filled with its median height, now inpainted, and the search ends elsewhere). Both
    # channels agree there at ~3.7 times chance, and the ridges add little given the valleys.
    view, region = result["view_index"], result["region_index"]
    c, t = complex(-0.65438996, -0.65147304), complex(211.49851162, -52.98177501)
    tolerances = MatchParams().crease_tolerances
    valleys = crease_evidence(view.crease_samples, region.crease_field, c, t, **tolerances)
    ridges = crease_evidence(view.ridge_samples, region.ridge_field, c, t, **tolerances)
    assert valleys.fraction > 3 * valleys.chance and ridges.fraction > 3 * ridges.chance
    given = conditioned_on(ridges, valleys)
    assert given.dependence > 0.2 and given.score < 0.5 * ridges.score


def test_a_view_scored_at_its_true_place_shows_the_evidence_it_holds(shared_data):
    """``Matcher.score_at`` scores the view's true transform as the search would have: for
    a view the search localises, about its answer; a quarter turn off, nothing."""
    import math

    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools import real_imagery as ri

    scene = load_scene(shared_data / "imagery" / "athabasca_hls_l30_20200816.tif",
                       shared_data / "imagery" / "athabasca_dem30m_utm11.tif",
                       band=4, when="2020-08-16T18:50:00Z")
    ri.render_landmark([scene])
    rng = np.random.default_rng(3)
    case = ri._cut_cases(scene, 128, 1, False, 3.0, rng)[0]
    params = MatchParams()
    matcher, extractor = Matcher(params, threshold=-1e9), ri._Extractor(params, "dem")
    view, f_view = extractor.index(matcher, case.view, scene, valid=case.valid)
    region, f_region = extractor.region_index(matcher, scene, case.region)
    truth = case.true_transform(f_view, f_region)
    centre = 0.5 * (np.array(case.view.shape[::-1]) - 1.0)
    assert np.allclose(truth @ [*centre, 1.0], case.truth)
    found = matcher.localise(view, region)
    assert ri.view_error(found, case, f_view, f_region) < 3.0
    at_truth = matcher.score_at(view, region, truth)
    assert np.allclose(at_truth.apply(*centre), case.truth, atol=3.0)
    assert abs(at_truth.score - found.score) < 3.0
    quarter = np.array([[0.0, 1.0], [-1.0, 0.0]])     # a quarter turn about the centre
    turned = np.column_stack([truth[:, :2] @ quarter,
                              truth @ [*centre, 1.0] - truth[:, :2] @ quarter @ centre])
    assert matcher.score_at(view, region, turned).score < found.score - 10.0
    assert math.isfinite(at_truth.score)


def test_a_view_is_ambiguous_only_for_a_place_that_scores_as_well_weighed_as_it_was(
        shared_data):
    """A 128 px view of RMNP under haze, found 1 px off at 19.3 once moved onto the
    render's creases: the places the search scored it at before that (-0.8 there, -1.3 at
    58 px) are weighed the same way before one of them can make it ambiguous. Compared as
    scored, the chance registration at 58 px vetoed the fix ("scores -1.3, within 1 of the
    best (-0.8)")."""
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "rmnp_rgb_4326.tif",
                       shared_data / "imagery" / "rmnp_dem_4326.tif",
                       when="2010-07-15T17:00:00Z")
    # view px -> scene px (the degraded-view probe's case: seed 7, turned by -105 deg)
    m = np.array([[-0.2782348, 1.02770012, 125.07526334],
                  [-1.02770012, -0.2782348, 269.38374223]])
    def hazy(view):
        return np.clip(np.rint(0.4 * view + 0.6 * 230.0), 0, 255).astype(np.uint8)
    result = _localise_view(scene, m, 128, box=(0, 0, 364, 378), seen=hazy)
    assert not result["vetoed"], result["reason"]
    assert result["score"] > _graph_threshold() and result["err"] <= 3.0


def test_a_large_view_between_two_of_the_coarser_level_s_scales_is_found(shared_data):
    """A 256 px view of PA November at 30 m, 3.5 % smaller than the view search's nearest
    scale at its coarser level (8 % apart): from there the coarse-to-fine ICP drifted along
    the parallel creases to a scale 5 % off (8.5, 2.8 px off); placed at the coarse level
    first, the proposal reaches its truth (77)."""
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                       shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                       band=4, sun=(159.5, 26.2))
    # view px -> scene px (the view-search bench's case, seed 0)
    m = np.array([[0.0222, -0.965, 272.4367], [0.965, 0.0222, 6.8043]])
    result = _localise_view(scene, m, 256)
    assert result["err"] < 1.0 and result["score"] > _graph_threshold() + 30.0


@pytest.mark.parametrize("reach, agree", [(None, True), (1, False)])
def test_a_large_scene_s_landmark_is_rendered_in_blocks_as_in_one_piece(monkeypatch, reach,
                                                                        agree):
    """Blocks bound the renderer's memory (~100 bytes per pixel); each carries the terrain
    that can shade it, so the landmark is the one-piece render (up to a few pixels where
    the ray march's steps differ). Without that margin the shadows cast from a block's
    neighbours are missing."""
    from terrain_nav_ros.core.terrain.synthetic_terrain import synthetic_dem
    from terrain_nav_ros.tools import real_imagery as ri

    z = synthetic_dem(256, gsd=30.0, seed=4).astype(np.float32)[:200, :240] * 3.0
    scene = ri.Scene("blocks", np.zeros(z.shape, np.uint8), np.ones(z.shape, bool), z, 30.0,
                     (135.0, 20.0), (45.0, 7.0))
    ri.render_landmark([scene])
    whole = scene.landmark.astype(int)
    monkeypatch.setattr(ri, "RENDER_BLOCK", 64)
    if reach is not None:
        monkeypatch.setattr(ri, "_shadow_reach", lambda s: reach)
    ri.render_landmark([scene])
    differ = np.mean(scene.landmark.astype(int) != whole)
    assert (differ < 0.002) == agree, differ


def test_a_scene_reads_only_the_dem_under_its_image(tmp_path, monkeypatch):
    """A scene of a large mosaic reads a scene's worth of it, with the same heights as
    from the DEM cut to the image."""
    import rasterio
    from affine import Affine

    from terrain_nav_ros.core.terrain import dem_io

    image, dem = _write_pair(tmp_path, geographic=False)
    with rasterio.open(dem) as ds:
        profile, z = ds.profile, ds.read(1)
    big = np.pad(z, 420, mode="reflect")            # 1000 x 1000 cells around the image
    profile.update(width=1000, height=1000,
                   transform=profile["transform"] @ Affine.translation(-420, -420))
    with rasterio.open(tmp_path / "big.tif", "w", **profile) as ds:
        ds.write(big, 1)
    read = []
    original = dem_io.Dem.read
    monkeypatch.setattr(dem_io.Dem, "read",
                        lambda self, window=None: read.append(out := original(self, window))
                        or out)
    scene = load_scene(image, tmp_path / "big.tif", sun=(150.0, 40.0))
    assert read and read[-1].size < 1.2 * (160 + 8) ** 2
    np.testing.assert_allclose(scene.elevation, load_scene(image, dem, sun=(150.0, 40.0))
                               .elevation, atol=1e-3)


def test_a_dem_finer_than_the_image_is_not_aliased_onto_its_grid(tmp_path):
    """A 10 m DEM under a 30 m image: point samples would alias relief finer than the grid
    (a ripple 35 m long becomes a 210 m one of full height, creases no camera sees). The
    warp's cubic kernel, stretched over the coarser cell when it shrinks (GDAL), keeps
    under 1 % of it (0.13 m of 14 m rms; a box average of the cells would keep 2.6 m)."""
    import rasterio
    from affine import Affine

    x = (np.arange(480) + 0.5) * 10.0                 # cell centres (m)
    broad = 1000.0 + 200.0 * np.sin(x / 1500.0)
    fine = (broad + 20.0 * np.sin(2.0 * np.pi * x / 35.0))[None, :].repeat(480, 0)
    origin = (500000.0, 5000000.0)
    with rasterio.open(tmp_path / "dem.tif", "w", driver="GTiff", width=480, height=480,
                       count=1, dtype="float32", crs="EPSG:32632",
                       transform=Affine(10.0, 0, origin[0], 0, -10.0, origin[1])) as ds:
        ds.write(fine.astype(np.float32), 1)
    grey = np.random.default_rng(0).integers(10, 250, (160, 160)).astype(np.uint8)
    with rasterio.open(tmp_path / "image.tif", "w", driver="GTiff", width=160, height=160,
                       count=1, dtype="uint8", crs="EPSG:32632", nodata=0,
                       transform=Affine(30.0, 0, origin[0], 0, -30.0, origin[1])) as ds:
        ds.write(grey, 1)
    scene = load_scene(tmp_path / "image.tif", tmp_path / "dem.tif", sun=(150.0, 40.0))
    assert scene.dem_cell == 10.0
    centres = (np.arange(160) + 0.5) * 30.0
    ripple = scene.elevation[2:-2, 2:-2] - (1000.0 + 200.0 * np.sin(centres / 1500.0))[2:-2]
    assert ripple.std() < 0.05 * 20.0 / np.sqrt(2.0), ripple.std()


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_an_image_with_control_points_in_degrees_is_studied_like_its_georeferenced_twin(
        tmp_path):
    """A scanned or level-1 image carries only control points (here in lon/lat): it is
    warped onto their grid, then onto UTM like any image in degrees."""
    import rasterio
    from rasterio.control import GroundControlPoint

    image, dem = _write_pair(tmp_path, geographic=True)
    with rasterio.open(image) as ds:
        profile, grey, transform = ds.profile, ds.read(1), ds.transform
    profile.update(crs=None, transform=rasterio.Affine.identity())
    gcp_image = tmp_path / "gcps.tif"
    with rasterio.open(gcp_image, "w", **profile) as ds:
        ds.write(grey, 1)
        ds.gcps = ([GroundControlPoint(r, c, *(transform @ (c, r)))
                    for r in (0, 80, 160) for c in (0, 80, 160)], "EPSG:4326")
    twin = load_scene(image, dem, sun=(150.0, 40.0))
    scene = load_scene(gcp_image, dem, sun=(150.0, 40.0))
    assert scene.gsd == pytest.approx(twin.gsd, rel=0.02)
    h, w = (min(a, b) - 4 for a, b in zip(scene.image.shape, twin.image.shape, strict=True))
    seen = scene.valid[2:h, 2:w] & twin.valid[2:h, 2:w]
    a, b = scene.image[2:h, 2:w][seen], twin.image[2:h, 2:w][seen]
    assert seen.mean() > 0.9 and np.corrcoef(a, b)[0, 1] > 0.95


def test_a_sensor_s_banding_is_no_fix_kilometres_off(shared_data):
    """Views of PA November's ridges with a sensor's banding (+-40 grey levels every 16
    rows), and of flat grey with that banding alone: the banding is taken off the view
    (it played the camera's frame), so the terrain is still localised where it is, and the
    flat grey is no drainage. Before, the stripes were matched to ridges parallel to them:
    banded views accepted 1-5 km off, and flat grey at scores up to 19.5."""
    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools import real_imagery as ri
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                       shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                       band=4, sun=(159.5, 26.2))
    ri.render_landmark([scene])
    params, threshold = MatchParams(), _graph_threshold()
    matcher, extractor = Matcher(params, threshold=-1e9), ri._Extractor(params, "dem")
    cases = ri._cut_cases(scene, 128, 6, False, 3.0, np.random.default_rng(11))
    banding = 40.0 * np.sin(2 * np.pi * np.arange(128) / 16)[:, None]
    flat = np.random.default_rng(0).normal(128.0, 2.0, (128, 128))
    found = 0
    for case in cases:
        region = extractor.region_index(matcher, scene, case.region)
        for view, terrain in ((case.view + banding, True), (flat + banding, False)):
            banded = ri._Case(np.clip(view, 0, 255).astype(np.uint8), case.region,
                              case.truth, case.valid, case.cut)
            result = ri._localise(matcher, extractor, scene, banded, region)
            if result["score"] < threshold:
                continue
            assert terrain and result["err"] <= 3.0, (terrain, result["score"], result["err"])
            found += 1
    assert found >= 4, found


def test_a_mirrored_view_is_found_once_mirrored_back(shared_data):
    """A 256 px view of PA November as a camera flipped left to right sees it: no turn of
    it lies on the terrain, so it is not localised; mirrored back across its columns
    (:func:`mirrored_view`, the matcher's diagnosis of a flipped camera) it is, where the
    view itself is."""
    from terrain_nav_ros.core.features.minutia_set import MinutiaSet
    from terrain_nav_ros.core.matching.global_search import mirrored_view
    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.terrain.georef import GeoReference
    from terrain_nav_ros.tools.cli import _graph_threshold

    scene = load_scene(shared_data / "imagery" / "pa_ridgevalley_l7_20021125.tif",
                       shared_data / "imagery" / "pa_ridgevalley_dem30m_utm18.tif",
                       band=4, sun=(159.5, 26.2))
    m = np.array([[0.98, -0.17, 20.0], [0.17, 0.98, 10.0]])   # turned 10 deg, at its NW
    seen = _localise_view(scene, m, 256)
    assert seen["score"] >= _graph_threshold() and seen["err"] <= 3.0
    flipped = _localise_view(scene, m, 256, seen=lambda view: view[:, ::-1].copy())
    assert flipped["score"] < _graph_threshold()
    ix = flipped["view_index"]
    h, w = ix.crease_image.shape
    g = GeoReference(0.0, 0.0, 30.0, w, h)
    s = ix.set
    back = mirrored_view(MinutiaSet(s.col, s.row, s.angle, s.kind, s.quality, georef=g),
                         ix.crease_image, ix.ridge_image, g.centre, math.pi / 2)
    # across the raster's middle column: the same raster
    assert back[0].georef.shape == g.shape
    assert np.allclose((back[0].georef.origin_east, back[0].georef.origin_north), 0.0, atol=1e-6)
    matcher = Matcher(MatchParams(), threshold=-1e9)
    found = matcher.localise(matcher.index(*back), flipped["region_index"])
    unflipped = matcher.localise(seen["view_index"], flipped["region_index"])
    assert found.score >= _graph_threshold()
    centre = (0.5 * (w - 1), 0.5 * (h - 1))
    assert np.hypot(*(np.subtract(found.apply(*centre), unflipped.apply(*centre)))) <= 2.0


def test_costa_rica_s_dem_is_found_two_cells_off_its_images_and_athabasca_s_is_not(shared_data):
    """The data's README: Costa Rica's ASTER DEM is ~2 px (60 m S, 30 m E) off the images.
    The image's shading places it there, and the warning says so; Athabasca's pair, in
    register, gets none."""
    imagery = shared_data / "imagery"
    costa = load_scene(imagery / "costarica_barva_l5_19860206.tif",
                       imagery / "costarica_barva_astergdem_4326.tif", band=4,
                       when="1986-02-06T15:30:00Z")
    s = costa.shading
    assert 20.0 < s.offset_east < 45.0 and -70.0 < s.offset_north < -35.0, s
    assert "misregistered" in costa.registration_warning
    athabasca = load_scene(imagery / "athabasca_hls_s30_20200909.tif",
                           imagery / "athabasca_dem30m_utm11.tif", band=4, sun=(164.8, 41.1))
    assert math.hypot(athabasca.shading.offset_east, athabasca.shading.offset_north) < 20.0
    assert athabasca.registration_warning is None


@pytest.mark.parametrize("size, level", [(384, "SIXTEENTH"), (768, "THIRTY_SECOND")])
def test_a_view_too_large_for_the_coarser_level_is_searched_at_a_coarser_one(shared_data, size,
                                                                            level):
    """A 384 px view (seed 0: 8 % larger than the prior's scale, turned 113 deg) of a DEM's
    camera render in its 3x region holds more work than the work bound allows at an eighth
    of the resolution, a 768 px one more than at a sixteenth. Without a level for them, the
    minutiae's rigid votes placed the 384 px view 7 px off at 13 (its scale fitted nowhere)
    and lost 4 of 6 768 px views; searched at the level that fits, then placed at each finer
    level, they are found where they are, at their true scale."""
    import math

    from terrain_nav_ros.core.matching import crease_search
    from terrain_nav_ros.core.matching.crease_proposals import _view_search_level
    from terrain_nav_ros.core.matching.matcher import Matcher
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.tools import real_imagery as ri

    scene = ri.dem_camera_scene(shared_data / "dem" / "N44E005.hgt")
    ri.render_landmark([scene])
    case = ri._cut_cases(scene, size, 1, False, 3.0, np.random.default_rng(0))[0]
    params = MatchParams()
    matcher = Matcher(params, threshold=-1e9, max_rotation=math.pi)
    extractor = ri._Extractor(params, "dem")
    view, f_view = extractor.index(matcher, case.view, scene, valid=case.valid)
    region, f_region = extractor.region_index(matcher, scene, case.region)
    assert _view_search_level(view, region, params) == getattr(crease_search, level)
    truth = case.true_transform(f_view, f_region)
    found = matcher.localise(view, region)
    assert ri.view_error(found, case, f_view, f_region) < 1.0
    assert abs(found.scale - math.hypot(*truth[0, :2])) < 0.005
    assert found.score > 100.0


def test_a_scenes_file_names_its_dem_s_camera_render_as_an_image(tmp_path, shared_data):
    """``image: render`` studies a DEM through its camera render (the views of 384 px and
    more that no real pair holds); what does not apply to a render, or a sun it lacks, is
    refused by name."""
    from terrain_nav_ros.tools import real_imagery as ri

    dem = shared_data / "dem" / "N44E005.hgt"
    path = tmp_path / "scenes.yaml"
    path.write_text(f"scenes:\n  - name: alps\n    image: render\n    dem: {dem}\n"
                    "    sun: [315, 45]\n")
    scene, = ri.load_scenes(path)
    assert scene.name == "alps" and scene.image.dtype == np.uint8
    assert scene.image.shape == scene.elevation.shape and scene.image.shape[0] > 1000
    assert scene.sun == (315, 45) and scene.dem_cell == scene.gsd
    assert scene.image.std() > 5           # a shaded relief, not a flat grey
    for extra, message in (("", "needs its sun"), ("    sun: [315, 45]\n    gsd: 30\n",
                                                   "gsd do not apply")):
        path.write_text(f"scenes:\n  - image: render\n    dem: {dem}\n{extra}")
        with pytest.raises(ValueError, match=message):
            ri.load_scenes(path)


def test_a_view_s_controls_are_distinct_regions_of_other_places():
    """A view asks for controls from the other places' cases, one scene after another:
    it gets each distinct region once (a scene smaller than a region gives every case the
    whole scene), never its own place's, and fewer than asked when they run out; views
    start at different regions."""
    from types import SimpleNamespace as S

    scenes = [S(name="pa30", place="pa"), S(name="pa15", place="pa"),
              S(name="small", place="ab"), S(name="big", place="cr")]
    whole = (0, 0, 200, 200)
    per_scene = {"pa30": [S(region=(0, 0, 9, 9))], "pa15": [S(region=(1, 1, 9, 9))],
                 "small": [S(region=whole)] * 4,
                 "big": [S(region=(x, 0, x + 90, 90)) for x in (0, 30, 60)]}
    got = _control_regions(scenes, scenes[0], per_scene, 0, 10)
    pairs = [(sc.name, box) for sc, box in got]
    assert len(pairs) == len(set(pairs)) == 4          # 1 + 3 distinct, not 10
    assert {name for name, _ in pairs} == {"small", "big"}
    assert pairs.count(("small", whole)) == 1
    assert [sc.name for sc, _ in _control_regions(scenes, scenes[0], per_scene, 0, 2)] == \
        ["small", "big"]                                # one scene after another
    assert _control_regions(scenes, scenes[0], per_scene, 1, 1) != \
        _control_regions(scenes, scenes[0], per_scene, 0, 1)
    assert _control_regions(scenes, scenes[2], {**per_scene, "pa30": [], "pa15": [],
                                                "big": []}, 0, 5) == []
