"""The mission index (issue 24, item 1): ``terrain-nav prepare`` on a crop of a real DEM with
a local Dask cluster of one worker, read back with :class:`MissionIndex`; resuming, the
refusals, and the pieces (tile grid, suns over a window, DEM coverage)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from terrain_nav_ros.core.matching.mission_index import (
    MissionIndex,
    MissionIndexError,
    TileBuilder,
    TileGrid,
    build_tile,
    layer_name,
    load_tile,
    manifest_differences,
    save_tile,
)
from terrain_nav_ros.core.render.sun import parse_utc, sun_separation, suns_over_window
from terrain_nav_ros.core.terrain.dem_io import open_dem
from terrain_nav_ros.core.terrain.geodesy import EnuOrigin
from terrain_nav_ros.core.terrain.metamap import MetaMap
from terrain_nav_ros.tools import cli
from terrain_nav_ros.tools.prepare import graph_settings

AREA = "44.40,5.40,44.55,5.60"          # ~16 x 17 km of N44E005
SUNS = [(110.0, 35.0), (140.0, 50.0)]
TILE, OVERLAP = 128, 48                  # 2 x 2 tiles at 90 m


def _prepare(dem, out, *extra):
    suns = ",".join(f"{az:g}/{el:g}" for az, el in SUNS)
    return cli.main(["prepare", "--dem", str(dem), "--area", AREA, "--gsd", "90",
                     "--out", str(out), "--suns", suns, "--tile", str(TILE),
                     "--overlap", str(OVERLAP), "--workers", "1", *extra])


@pytest.fixture(scope="module")
def dem(shared_data):
    return shared_data / "dem" / "N44E005.hgt"


@pytest.fixture(scope="module")
def mission(dem, tmp_path_factory):
    """A 2 x 2 tile, 2 sun index built through the command."""
    out = tmp_path_factory.mktemp("mission") / "index"
    assert _prepare(dem, out) == 0
    return out


def _mtimes(out):
    return {p.name: p.stat().st_mtime_ns for p in (out / "tiles").glob("*.npz")}


def test_the_manifest_says_what_was_built(mission, dem):
    manifest = json.loads((mission / "manifest.json").read_text())
    assert manifest["version"] == 1 and manifest["gsd"] == 90.0
    assert manifest["suns"] == [list(s) for s in SUNS]
    assert manifest["grid"]["cols"] * manifest["grid"]["rows"] == 4
    assert manifest["grid"]["tile_px"] == TILE and manifest["grid"]["overlap_px"] == OVERLAP
    assert manifest["origin"]["lat"] == pytest.approx(44.475)
    assert manifest["origin"]["lon"] == pytest.approx(5.5)
    assert manifest["dems"][0]["path"] == str(dem.resolve())
    assert manifest["dems"][0]["size"] == dem.stat().st_size
    assert manifest["settings"]["minutia"]["max_minutiae"] == 100000
    assert MissionIndex(mission).settings == graph_settings()[0]   # the graph's, read back
    assert len(_mtimes(mission)) == 4 * len(SUNS)


def test_every_view_of_the_overlap_lies_inside_some_tile(mission):
    index = MissionIndex(mission)
    west, east, south, north = index.grid.extent
    aw, ae, as_, an = index.manifest["area"]["enu_extent"]
    assert west <= aw and east >= ae and south <= as_ and north >= an
    side = OVERLAP * index.gsd
    rng = np.random.default_rng(3)
    x0 = rng.uniform(west, east - side, 2000)
    y0 = rng.uniform(south, north - side, 2000)   # the view's south-west corner
    inside = np.zeros(len(x0), bool)
    for tile in index.tiles():
        w, e, s, n = tile.extent
        inside |= (x0 >= w) & (x0 + side <= e) & (y0 >= s) & (y0 + side <= n)
    assert inside.all()


@pytest.fixture(scope="module")
def built_here(mission):
    """The last tile of the mission built in this process with build_tile."""
    from terrain_nav_ros.core.render.renderer import create_headless_context

    index = MissionIndex(mission)
    s = index.settings
    metamap = MetaMap([open_dem(d["path"]) for d in index.manifest["dems"]], index.origin,
                      interpolation=s.interpolation, fill_voids=s.fill_voids)
    tile = index.tiles()[-1]
    builder = TileBuilder(create_headless_context(), s)
    built = build_tile(metamap, tile.georef, index.suns, builder)
    builder.release()
    return tile, built


def _assert_same_layer(a, b):
    for name in ("col", "row", "angle", "kind", "quality"):
        x, y = getattr(a.minutiae, name), getattr(b.minutiae, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.minutiae.extras.keys() == b.minutiae.extras.keys()
    for name, values in a.minutiae.extras.items():
        assert values.dtype == b.minutiae.extras[name].dtype, name
        assert np.array_equal(values, b.minutiae.extras[name]), name
    assert a.minutiae.georef == b.minutiae.georef == a.georef == b.georef
    assert a.minutiae.reason == b.minutiae.reason
    assert np.array_equal(a.creases, b.creases) and np.array_equal(a.ridges, b.ridges)
    assert a.sun == b.sun


def test_saved_layers_load_back_exactly(built_here, tmp_path):
    _, built = built_here
    for k, layer in enumerate(built):
        assert len(layer.minutiae) > 20
        save_tile(tmp_path / f"{k}.npz", layer)
        _assert_same_layer(layer, load_tile(tmp_path / f"{k}.npz"))


def test_the_command_wrote_what_build_tile_returns(mission, built_here):
    tile, built = built_here
    index = MissionIndex(mission)
    for k, layer in enumerate(built):
        loaded = index.load(tile.col, tile.row, k)
        assert loaded.sun == layer.sun == SUNS[k] and loaded.georef == tile.georef
        # the same up to the last bits of the extractor's fastmath kernels, which another
        # process may round differently (seen on a cold numba cache: angles within 1e-7)
        assert np.array_equal(loaded.minutiae.col, layer.minutiae.col)
        assert np.array_equal(loaded.minutiae.row, layer.minutiae.row)
        assert np.allclose(loaded.minutiae.angle, layer.minutiae.angle, atol=1e-5)
        assert np.array_equal(loaded.creases, layer.creases)
        assert np.array_equal(loaded.ridges, layer.ridges)


def test_index_is_smaller_than_its_renders(mission, dem, capsys):
    assert _prepare(dem, mission) == 0
    out = capsys.readouterr().out
    assert "index" in out and "renders" in out
    size = sum(p.stat().st_size for p in (mission / "tiles").glob("*.npz"))
    assert size < 4 * len(SUNS) * TILE * TILE


def test_a_rerun_skips_finished_tiles_and_rebuilds_only_a_missing_one(mission, dem, capsys):
    before = _mtimes(mission)
    assert _prepare(dem, mission) == 0
    assert "built 0 tiles" in capsys.readouterr().out
    assert _mtimes(mission) == before
    gone = layer_name(1, 0, 1).split("/")[-1]
    (mission / "tiles" / gone).unlink()
    assert _prepare(dem, mission) == 0
    assert "built 1 tiles (1 layers)" in capsys.readouterr().out
    after = _mtimes(mission)
    assert after.keys() == before.keys()
    assert {k for k in after if after[k] != before[k]} == {gone}


def test_an_area_outside_the_dems_is_refused_before_any_work(dem, tmp_path, capsys):
    out = tmp_path / "index"
    code = cli.main(["prepare", "--dem", str(dem), "--area", "44.8,5.8,45.3,6.3",
                     "--gsd", "90", "--out", str(out), "--suns", "120/40"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "do not cover the area" in err[0] and "span lat 43.99" in err[0]
    assert not out.exists()


def test_without_suns_the_command_says_which_option_to_give(dem, tmp_path, capsys):
    code = cli.main(["prepare", "--dem", str(dem), "--gsd", "90", "--out",
                     str(tmp_path / "i")])
    err = capsys.readouterr().err
    assert code == 2 and "--suns" in err and "--time" in err


def test_another_index_in_the_directory_is_refused(mission, dem, capsys):
    before = _mtimes(mission)
    code = cli.main(["prepare", "--dem", str(dem), "--area", AREA, "--gsd", "60",
                     "--out", str(mission), "--suns", "110/35,140/50", "--tile", str(TILE),
                     "--overlap", str(OVERLAP)])
    err = capsys.readouterr().err
    assert code == 2 and "holds another mission index" in err and "--overwrite" in err
    assert "gsd" in err and _mtimes(mission) == before


def test_overwrite_replaces_another_index(dem, tmp_path, capsys):
    out = tmp_path / "index"
    small = ["prepare", "--dem", str(dem), "--area", "44.40,5.40,44.43,5.44", "--gsd", "90",
             "--out", str(out), "--tile", "64", "--overlap", "0", "--workers", "1"]
    assert cli.main([*small, "--suns", "100/30,120/40"]) == 0
    assert cli.main([*small, "--suns", "150/50"]) == 2
    assert cli.main([*small, "--suns", "150/50", "--overwrite"]) == 0
    capsys.readouterr()
    assert MissionIndex(out).suns.tolist() == [[150.0, 50.0]]
    assert sorted(p.name for p in (out / "tiles").iterdir()) == ["r000_c000_s00.npz"]
    assert MissionIndex(out).load(0, 0, 0).sun == (150.0, 50.0)


def test_an_existing_cluster_is_used_with_scheduler(dem, tmp_path, capsys):
    from dask.distributed import LocalCluster

    out = tmp_path / "index"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        assert cli.main(["prepare", "--dem", str(dem), "--area", "44.40,5.40,44.43,5.44",
                         "--gsd", "90", "--out", str(out), "--tile", "64", "--overlap", "0",
                         "--suns", "120/40", "--scheduler", cluster.scheduler_address]) == 0
    assert "built 1 tiles (1 layers)" in capsys.readouterr().out
    assert len(MissionIndex(out).load(0, 0, 0).minutiae) > 0


def test_a_scheduler_address_where_no_dask_answers_is_refused_in_time(dem, tmp_path, capsys):
    """An HTTP server where the scheduler should be: the Dask client's own timeout covers
    the connection only, and it waited for ever on the handshake (11 min, then killed)."""
    import http.server
    import threading

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             http.server.SimpleHTTPRequestHandler)
    server.daemon_threads = True   # its handler waits for ever on the Dask handshake
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        code = cli.main(["prepare", "--dem", str(dem), "--area", "44.40,5.40,44.43,5.44",
                         "--gsd", "90", "--out", str(tmp_path / "index"), "--tile", "64",
                         "--overlap", "0", "--suns", "120/40", "--scheduler",
                         f"tcp://127.0.0.1:{server.server_port}"])
    finally:
        server.shutdown()
    assert code == 2
    assert "no Dask scheduler answered within 20 s" in capsys.readouterr().err


def test_the_nearest_sun_layer_is_picked(mission):
    index = MissionIndex(mission)
    assert index.nearest_sun((112.0, 36.0)) == 0
    assert index.nearest_sun((150.0, 55.0)) == 1
    assert index.load(0, 0, (139.0, 49.0)).sun == SUNS[1]
    with pytest.raises(IndexError):
        index.load(5, 0, 0)


def test_the_areas_terrain_heights_are_recorded_and_read_from_an_older_manifest(mission,
                                                                               tmp_path):
    """A cold start assumes the area's median terrain and searches the spread: the manifest
    records them; an index prepared before they were recorded samples its DEMs instead, and
    is the same request to a rerun."""
    manifest = json.loads((mission / "manifest.json").read_text())
    terrain = MissionIndex(mission).terrain()
    assert manifest["terrain"] == terrain.to_dict()
    # the Vercors foothills: a few hundred metres to about two kilometres
    assert 150.0 < terrain.low < terrain.median < terrain.high < 2500.0
    assert terrain.high - terrain.low > 500.0
    old = tmp_path / "old"
    old.mkdir()
    del manifest["terrain"]
    (old / "manifest.json").write_text(json.dumps(manifest))
    again = MissionIndex(old).terrain()
    assert again.to_dict() == pytest.approx(terrain.to_dict(), abs=1e-6)
    assert manifest_differences(manifest, json.loads(
        (mission / "manifest.json").read_text())) == []
    manifest["dems"][0]["path"] = str(tmp_path / "gone.hgt")
    (old / "manifest.json").write_text(json.dumps(manifest))
    assert MissionIndex(old).terrain() is None


def test_a_directory_without_an_index_is_no_mission_index(tmp_path):
    with pytest.raises(MissionIndexError, match="no mission index"):
        MissionIndex(tmp_path)


@pytest.mark.parametrize("span", [(0.0, 768.0 * 30), (0.0, 1000.0 * 30), (-5e3, 91e3)])
def test_tile_grid_covers_its_extent_with_views_of_the_overlap_inside_tiles(span):
    lo, hi = span
    grid = TileGrid.covering((lo, hi, lo - 7e3, hi + 3e3), 30.0, 256, 64)
    west, east, south, north = grid.extent
    assert west <= lo and east >= hi and south <= lo - 7e3 and north >= hi + 3e3
    assert grid.cols == max(1, math.ceil((hi - lo) / 30.0 / 192 - 64 / 192))
    step = grid.stride_px * grid.gsd
    x = np.linspace(west, east - 64 * grid.gsd, 997)
    col = np.minimum(((x - west) // step).astype(int), grid.cols - 1)
    assert (x + 64 * grid.gsd <= west + col * step + 256 * grid.gsd + 1e-6).all()


def test_suns_over_a_window_are_at_most_a_step_apart():
    start = parse_utc("2024-06-21T08:00:00Z")
    suns = suns_over_window(start, 2.0, 44.5, 5.5, 2.0)
    gaps = [sun_separation(a, b) for a, b in zip(suns[:-1], suns[1:], strict=True)]
    assert len(suns) > 5 and max(gaps) <= 2.0 and min(gaps) > 1.5
    first = suns_over_window(start, 0.0, 44.5, 5.5, 2.0)
    assert len(first) == 1 and np.allclose(first[0], suns[0])
    assert len(suns_over_window(parse_utc("2024-06-21T22:00:00Z"), 2.0, 44.5, 5.5, 2.0)) == 0


def test_metamap_covers_the_dem_footprint_not_beyond(dem):
    metamap = MetaMap([open_dem(dem)], EnuOrigin(44.5, 5.5))
    west, east, south, north = metamap.enu_bounds[0]
    e = np.array([0.0, 0.5 * west, west - 1e3, 0.0, 0.0])
    n = np.array([0.0, 0.0, 0.0, north + 1e3, 0.99 * south])
    assert metamap.covers(e, n).tolist() == [True, True, False, False, True]


def test_ctrl_c_exits_130_in_one_line_keeping_the_finished_tiles(dem, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "index"
    cmd = [sys.executable, "-m", "terrain_nav_ros.tools.cli", "prepare", "--dem", str(dem),
           "--area", "44.1,5.1,44.9,5.9", "--gsd", "90", "--out", str(out), "--suns",
           "110/35,120/40,130/45", "--tile", "96", "--overlap", "32", "--workers", "1"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                            start_new_session=True)   # its own group, as a terminal's job
    lines = []
    try:
        for line in proc.stderr:   # interrupted once some tiles are done
            lines.append(line)
            if "tile 3/" in line:
                os.killpg(proc.pid, signal.SIGINT)
                break
        rest = proc.stderr.read()
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert code == 130, (code, lines, rest)
    others = [line for line in rest.strip().splitlines() if " tile " not in line]
    assert len(others) == 1 and "Traceback" not in rest, rest   # one line, progress aside
    last = others[0]
    assert "interrupted" in last and "run the same command again" in last
    assert len(list((out / "tiles").glob("*.npz"))) >= 3 * 3


def test_a_replay_refuses_an_index_of_another_area_or_gsd_before_any_node(mission):
    """The matcher would search such an index in vain (and a cold start would project the
    frames with its area's terrain heights): the replay says so before it starts."""
    from terrain_nav_ros.tools.errors import InputError
    from terrain_nav_ros.tools.replay import _check_mission_index, _check_offsets

    index = MissionIndex(mission)
    here = [index.origin.lat, index.origin.lon, 0.0]
    _check_mission_index(mission, {"landmark_gsd": index.gsd, "origin": here})
    for bag_mission, words in (
            ({"landmark_gsd": index.gsd, "origin": [36.59, -84.25, 0.0]}, "another area"),
            ({"landmark_gsd": 2 * index.gsd, "origin": here}, "prepare it at --gsd"),
    ):
        with pytest.raises(InputError, match=words):
            _check_mission_index(mission, bag_mission)
    with pytest.raises(InputError, match="holds no mission index"):
        _check_mission_index(mission / "nope", {})
    for lost, kidnap, words in (((1e9, 0.0), None, "within 1000 km"),
                                ((math.nan, 0.0), None, "finite"),
                                (None, (-5.0, 0.0, 100.0), "must be >= 0 s")):
        with pytest.raises(InputError, match=words):
            _check_offsets(lost, kidnap)


def test_a_damaged_or_foreign_layer_is_found_before_flight_and_never_searched(mission,
                                                                             tmp_path):
    """A layer cut short, empty, or copied from another index (another tile's place or
    another sun) is named by the replay's check before any node starts; loaded anyway, it
    is a MissionIndexError, which the search skips (its area is lost, once), not a
    BadZipFile on every frame."""
    from terrain_nav_ros.core.matching.params import MatchParams
    from terrain_nav_ros.core.matching.relocaliser import MissionSearch
    from terrain_nav_ros.tools.errors import InputError
    from terrain_nav_ros.tools.replay import _check_mission_index

    copy = tmp_path / "index"
    shutil.copytree(mission, copy)
    index = MissionIndex(copy)
    assert index.damaged() == []
    cut = index.layer_path(0, 0, 0)
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    index.layer_path(1, 0, 0).write_bytes(b"")
    shutil.copy(index.layer_path(1, 1, 0), index.layer_path(0, 1, 0))   # another place
    shutil.copy(index.layer_path(1, 1, 1), index.layer_path(1, 1, 0))   # another sun
    problems = index.damaged()
    assert len(problems) == 4
    assert sum("is damaged" in p for p in problems) == 2
    assert sum("of another tile or index" in p for p in problems) == 1
    assert sum("is lit by the sun" in p for p in problems) == 1
    with pytest.raises(InputError, match="4 tile layer.s. damaged"):
        _check_mission_index(copy, {"landmark_gsd": index.gsd})
    for col, row in ((0, 0), (1, 0), (0, 1), (1, 1)):
        with pytest.raises(MissionIndexError):
            index.load(col, row, 0)
    search = MissionSearch(index, MatchParams())
    assert search.tiles_for(SUNS[0]) == [] and len(search.damaged) == 4


def test_an_area_across_the_antimeridian_is_one_box_not_the_whole_earth():
    """A DEM in UTM 60 around 180 deg E (pyproj gives its box west > east) and an --area
    whose corners lie either side of 180: both are the box across it, whose centre is the
    ENU origin (before, the origin fell at longitude 0 and the index held nothing)."""
    from affine import Affine
    from pyproj import Transformer

    from terrain_nav_ros.core.terrain.dem_io import Dem
    from terrain_nav_ros.tools.prepare import _area_box, _geodetic_bounds

    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32660", always_xy=True).transform(180.0,
                                                                                     40.0)
    dem = Dem.from_array(np.zeros((200, 200), np.float32),
                         Affine(100.0, 0.0, x - 10e3, 0.0, -100.0, y + 10e3), "EPSG:32660")
    south, west, north, east = _geodetic_bounds([dem])
    assert 179.8 < west < 180.0 < east < 180.2 and south < 40.0 < north
    assert _area_box((39.98, 179.95, 40.02, -179.95)) == pytest.approx(
        (39.98, 179.95, 40.02, 180.05))
