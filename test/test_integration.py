"""Whole-graph replays: the short CI bag through every node in its own process over DDS.

The nominal replay must produce terrain fixes and keep the fused error over the GPS-denied
segment within a few GSD and well below IMU-only dead reckoning. Damaged inputs (a truncated
bag, no camera_info, a flight over flat terrain) must degrade to "no fix" with reasons, and
never kill a node.
"""

import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from terrain_nav_ros.tools import bags, cli
from terrain_nav_ros.tools.flight_sim import SimConfig, simulate
from terrain_nav_ros.tools.replay import run_replay

REPO = Path(__file__).resolve().parents[1]
SHORT_BAG = REPO / "bags" / "jacksboro_short"
GRAPH = REPO / "config" / "graph.yaml"
GSD = 20.0  # the short bag's landmark GSD (mission.yaml)

pytestmark = pytest.mark.skipif(not SHORT_BAG.exists(), reason="bags/jacksboro_short missing")


def _nodes_survived(result):
    assert result["graph_status"] == 0 and result["died"] == [], result.get("died")
    # nor crashed and were respawned (config/graph.yaml respawns all nodes but the ekf)
    respawned = {n: u["respawns"] for n, u in result["usage"].items() if u.get("respawns")}
    assert not respawned, respawned


@pytest.fixture(scope="module")
def nominal(tmp_path_factory):
    # with the autopilot bridge (target px4), whose output is checked below: one more light
    # node in the same replay costs the suite almost nothing
    return run_replay(SHORT_BAG, tmp_path_factory.mktemp("nominal"), GRAPH,
                      enable=["autopilot_bridge"])


def test_replay_produces_fixes_and_bounds_the_error(nominal):
    _nodes_survived(nominal)
    fixes = nominal["fixes"]
    assert fixes["frames"] >= 30 and fixes["fixes"] >= 0.5 * fixes["frames"], fixes
    # every camera frame is answered, those before the first estimate with a no-fix (the
    # camera topic is best effort: one frame may be lost on a loaded machine)
    assert fixes["frames"] >= fixes["in_bag"] - 1, fixes
    fused, dr = nominal["fused_error"], nominal["dr_error"]
    # Bounded by a few landmark GSD, ending within one, and below dead reckoning (the
    # accelerometer levelling holds the dead reckoning's tilt: over the short bag's 45 s
    # without GNSS it drifts only ~17 m, the demo's 4 min take it hundreds of metres off).
    assert fused["rms"] <= 3 * GSD and fused["final"] <= GSD, fused
    assert fused["rms"] < dr["rms"], (fused, dr)
    assert nominal["fix_error"]["within_3_sigma"] >= 0.7
    # the baro holds the height (0.2 m RMS), and the ekf's sigmas cover the errors: the
    # height's too, since the offset learnt for the baro is a bias the filter estimates
    # (before, 7 % of the height errors were within 3 sigma)
    height = nominal["fused_height_error"]
    assert height["max"] <= GSD, height
    assert fused["within_3_sigma"] >= 0.9 and height["within_3_sigma"] >= 0.9, (fused, height)
    # the report says what the ekf did with the fixes: it fused most of them
    use = nominal["ekf_fix_use"]
    assert use["fused"] >= 0.7 * fixes["fixes"] and use["fused"] + use["gated"] <= \
        fixes["fixes"] + 1, (use, fixes)
    # and where it put the map: the camera sees the DEM itself, so in its place within its
    # doubt (horizontal sigma, no more than the prior's 10 m per axis: 14.1 m)
    east, north, sigma = use["map_bias"]
    assert math.hypot(east, north) <= 3.0 * sigma <= 3.0 * math.hypot(10.0, 10.0) + 1e-3, \
        use["map_bias"]


def test_recorded_outputs_are_readable_by_rosbags_and_mcap(nominal):
    from mcap.reader import make_reader

    out = Path(nominal["output_bag"])
    topics = {t.topic: t.count for t in bags.topics(out)}
    assert topics["/nav/odometry"] > 100 and topics["/nav/pva_fix"] >= 30
    # every node's health, once a second
    assert min(topics[f"/{node}/diagnostics"] for node in (
        "camera_ingest", "feature_extractor", "matcher")) >= 10, topics
    (mcap_file,) = out.glob("*.mcap")
    with open(mcap_file, "rb") as stream:
        names = {schema.name for schema, _, _ in make_reader(stream).iter_messages()}
    assert {"terrain_nav_msgs/msg/PvaFix", "nav_msgs/msg/Odometry"} <= names


def test_autopilot_bridge_output_in_the_replay(nominal):
    """The recorded PX4 odometry: 30 Hz of estimate time, NED/FRD of the ekf's odometry at
    the same stamp, its variances rotated, the reset counter what the bridge counted."""
    from terrain_nav_ros.core.estimation.autopilot_frames import (
        covariance_enu_to_ned,
        enu_to_ned,
        quaternion_enu_flu_to_ned_frd,
    )

    out = Path(nominal["output_bag"])
    odom = {}
    for m in bags.read(out, ["/nav/odometry"]):
        msg = bags.decode(m)
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        stamp_us = (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) // 1000
        odom[stamp_us] = (np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]),
                          np.asarray(msg.pose.covariance).reshape(6, 6))
    px4 = [bags.decode(m) for m in bags.read(out, ["/fmu/in/vehicle_visual_odometry"])]
    assert len(px4) > 100, f"{len(px4)} VehicleOdometry recorded"
    t = np.array([m.timestamp_sample for m in px4]) * 1e-6
    # 30 Hz from 50 Hz odometry (the recorder's subscription is best effort: a few may drop)
    rate = (len(t) - 1) / (t[-1] - t[0])
    assert 25.0 <= rate <= 30.5 and np.diff(t).min() >= 0.02 - 1e-6, rate
    matched = 0
    for m in px4[::10]:
        if m.timestamp_sample not in odom:
            continue
        matched += 1
        position, q, cov = odom[m.timestamp_sample]
        assert m.pose_frame == 1 and m.velocity_frame == 1            # NED
        assert np.allclose(m.position, enu_to_ned(position), atol=0.01)
        assert np.allclose(m.q, quaternion_enu_flu_to_ned_frd(q), atol=1e-6)
        expected = np.diag(covariance_enu_to_ned(cov))
        assert np.allclose(m.position_variance, expected[:3], rtol=1e-5)
        assert np.allclose(m.orientation_variance, expected[3:], rtol=1e-5, atol=1e-12)
        assert (np.asarray(m.velocity_variance) > 0).all()
    assert matched >= 0.9 * len(px4[::10])
    # the reset counter only moves on, and ends where the bridge's own count says
    counters = [m.reset_counter for m in px4]
    assert counters == sorted(counters)
    diag = [bags.decode(m) for m in bags.read(out, ["/autopilot_bridge/diagnostics"])]
    values = {kv.key: kv.value for kv in diag[-1].status[0].values}
    assert values["target"] == "px4" and values["sending"] == "True"
    assert counters[-1] == int(values["reset_counter"])


def _cut(until_s: float, drop_topics=()):
    """A :func:`~terrain_nav_ros.tools.bags.changed_copy` change: the bag without some
    topics, cut after ``until_s`` seconds."""
    return lambda topic, at, _decode: "drop" if topic in drop_topics or at > until_s else None


def _no_fix_reasons(result):
    return " | ".join(reason for reason, _ in result["fixes"]["reasons"])


@pytest.mark.parametrize("node", ["matcher", "ekf"])
def test_a_node_killed_mid_flight_is_respawned_and_the_fixes_resume(tmp_path, node):
    """The matcher comes back and fixes again; the ekf resumes from its checkpoint, where it
    was, and the fixes go on bounding its error."""
    import threading
    import time

    import psutil

    def kill():
        # 35 s after the start: the graph is up and the bag some 25 s in, GNSS denied
        time.sleep(35.0)
        for child in psutil.Process().children(recursive=True):
            if f"__node:={node}" in child.cmdline():
                child.kill()

    killer = threading.Thread(target=kill, daemon=True)
    killer.start()
    result = run_replay(SHORT_BAG, tmp_path / "out", GRAPH)
    killer.join()
    assert result["graph_status"] == 0 and result["died"] == [], result["died"]
    assert result["usage"][node]["respawns"] == 1
    if node == "ekf":
        ekf_log = (tmp_path / "out" / "logs" / "ekf.log").read_text()
        assert "resumed from the checkpoint" in ekf_log, ekf_log[-2000:]
    # the fixes before the kill (from 11 s to ~25 s into the bag) are not half the frames:
    # the fixes went on after the restart
    fixes, fused = result["fixes"], result["fused_error"]
    assert fixes["fixes"] >= 0.5 * fixes["in_bag"], fixes
    assert fused["rms"] <= 3 * GSD and fused["final"] <= GSD, fused
    text = (tmp_path / "out" / "report.txt").read_text()
    assert "died and respawned 1x" in text


def test_missing_camera_info_gives_no_fix_and_no_crash(tmp_path):
    bag = bags.changed_copy(SHORT_BAG, tmp_path / "no_info",
                            _cut(25.0, drop_topics={"/camera/camera_info"}))
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["fixes"] == 0
    log = (tmp_path / "out" / "logs" / "camera_ingest.log").read_text()
    assert "no CameraInfo" in log
    # and every frame is answered with that reason, not lost on the way
    assert fixes["no_fix"] >= 0.9 * fixes["in_bag"] > 0, fixes
    assert "no CameraInfo" in _no_fix_reasons(result)


def test_truncated_bag_replays_what_it_has(tmp_path):
    bag = bags.changed_copy(SHORT_BAG, tmp_path / "cut", _cut(30.0))
    (mcap_file,) = bag.glob("*.mcap")
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: int(len(data) * 0.6)])
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    log = (tmp_path / "out" / "logs" / "bag_player.log").read_text()
    assert "stopped after" in log or "damaged" in log or "finished" in log


def test_flight_over_flat_terrain_says_why_there_is_no_fix(tmp_path):
    dem = tmp_path / "lake.tif"
    with rasterio.open(dem, "w", driver="GTiff", width=400, height=400, count=1,
                       dtype="float32", crs="EPSG:32616",
                       # north-up 30 m pixels (rasterio's from_origin warns inside affine)
                       transform=Affine(30.0, 0.0, 600000.0, 0.0, -30.0, 4000000.0)) as dst:
        dst.write(np.full((1, 400, 400), 250.0, np.float32))
    bag = tmp_path / "flat"
    simulate(SimConfig(dem=str(dem), duration=32.0, gnss_denied_after=16.0, agl=1500.0,
                       camera_rate=1.0, seed=3), bag)
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    assert result["fixes"]["fixes"] == 0 and result["fixes"]["no_fix"] >= 5
    assert "no drainage" in _no_fix_reasons(result) or "minutiae" in _no_fix_reasons(result)


@pytest.mark.parametrize("cover", [0.9, 0.95])
def test_a_flight_under_overcast_says_so_and_coasts(tmp_path, cover):
    """90 and 95 % cloud cover between the camera and the ground (simulate --cloud-cover;
    83-89 and 93-96 % of each frame): every projected frame is answered with a "mostly
    cloud" no-fix (82-90 and 92-97 % found cloud), none with a fix, and the filter coasts
    on the IMU as it would with the camera off. (Before the ground was taken beyond the
    gaps' edges: 16-17 of 21 and 1 of 21.)"""
    bag = tmp_path / "overcast"
    simulate(SimConfig(duration=32.0, gnss_denied_after=16.0, cloud_cover=cover, seed=3),
             bag)
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["frames"] >= fixes["in_bag"] - 1 and fixes["fixes"] == 0, fixes
    clouded = sum(n for reason, n in fixes["reasons"] if "mostly cloud" in reason)
    projected = fixes["frames"] - sum(n for reason, n in fixes["reasons"]
                                      if "not projected" in reason)
    assert clouded >= projected - 1 > 0, fixes   # one frame's slack for its attitude
    assert result["fused_error"]["final"] <= result["dr_error"]["final"] + GSD


def test_a_flight_under_broken_cloud_keeps_fixing(tmp_path):
    """40 % cloud cover and its shadows: most frames still get a fix, none outside its
    covariance, and the fused error stays within a GSD."""
    bag = tmp_path / "broken"
    simulate(SimConfig(duration=40.0, gnss_denied_after=15.0, cloud_cover=0.4, seed=3), bag)
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["fixes"] >= 15, fixes                     # 21 of 30 projected frames
    assert result["fix_error"]["within_3_sigma"] >= 0.95, result["fix_error"]
    assert result["fused_error"]["rms"] <= GSD, result["fused_error"]   # 5.7 m


def test_raw_camera_images_are_answered_like_jpeg(tmp_path):
    """A bag of raw sensor_msgs/Image frames (rgb8, 590 KB each: what most camera drivers
    publish) reaches camera_ingest frame by frame, as JPEG bags do: before the graph's Fast
    DDS profile (config/fastdds.xml) 6 of 29 frames were answered."""
    bag = tmp_path / "raw"
    simulate(SimConfig(duration=30.0, gnss_denied_after=15.0, image_format="rgb8", seed=1),
             bag)
    result = run_replay(bag, tmp_path / "out", GRAPH)
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["in_bag"] == 29 and fixes["frames"] >= fixes["in_bag"] - 1, fixes
    assert fixes["fixes"] >= 10, fixes


def _replayed_real_image_flight(tmp_path, shared_data, agl: float, replays=("gnss",),
                                **changes) -> list[dict]:
    """150 s of survey over PA November's real image draped on its DEM (simulate --albedo),
    ``agl`` m above its highest terrain (``changes``: other simulator settings), replayed
    through the graph once per entry of ``replays``: "gnss" as flown (GNSS for the first
    15 s), "jammed" with GNSS jammed from take-off (``replay --lost 0 0``); every frame
    answered. Returns the replays' results in that order."""
    imagery = shared_data / "imagery"
    bag = tmp_path / "pa_real"
    flown = dict(dem=str(imagery / "pa_ridgevalley_dem30m_utm18.tif"),
                 albedo=str(imagery / "pa_ridgevalley_l7_20021125.tif"), albedo_band="4",
                 start_time="2002-11-25T15:35:00Z", duration=150.0, pattern="survey",
                 start_east=-900.0, start_north=-300.0, agl=agl, camera_hfov=70.0,
                 landmark_gsd=30.0, gnss_denied_after=15.0, seed=3)
    simulate(SimConfig(**(flown | changes)), bag)
    results = [run_replay(bag, tmp_path / mode, GRAPH,
                          lost_offset=(0.0, 0.0) if mode == "jammed" else None)
               for mode in replays]
    for result in results:
        _nodes_survived(result)
        assert result["fixes"]["frames"] >= result["fixes"]["in_bag"] - 1, result["fixes"]
    return results


def test_flight_over_a_real_image_bounds_the_error(tmp_path, shared_data):
    """150 s over the real Landsat 7 November image of Pennsylvania's ridges, draped on its
    DEM (simulate --albedo: fields, forest and roads the landmark renders do not have; the
    landmarks stay DEM renders lit by the image's sun): every frame is answered, most get a
    fix, the fixes are consistent with their covariances, and the fused error stays well
    below dead reckoning. The bag is made here from ../shared, never committed."""
    result, = _replayed_real_image_flight(tmp_path, shared_data, agl=3000.0)
    fixes = result["fixes"]
    assert fixes["fixes"] >= 0.7 * fixes["frames"], fixes
    assert result["fix_error"]["within_3_sigma"] >= 0.9, result["fix_error"]
    fused, dr = result["fused_error"], result["dr_error"]
    assert fused["rms"] <= 3 * 30.0, fused   # 56-57 m with the ridge skeletons
    assert fused["rms"] < 0.6 * dr["rms"] and fused["final"] < 0.5 * dr["final"], (fused, dr)


def test_a_map_off_its_place_by_its_stated_accuracy_is_learnt_without_gnss(tmp_path,
                                                                         shared_data):
    """The 3000 m flight with the image draped 60 m east and 40 m north of its place
    (simulate --albedo-shift -60,-40), so that the ground the camera sees lies ~95 m
    east-north-east of the DEM's (the pair's own +30 m east and the shift), and the DEM's
    stated accuracy, 200 m at 90 %, in mission.yaml (simulate --dem-ce90): every fix is
    ~90 m off, west. With GNSS jammed from take-off, the replay's ekf takes its doubt of
    the map from that accuracy (93 m per axis), and the take-off pose with the dead
    reckoning after it tells the map's offset from the aircraft's: fused RMS 9.8 and 14.3
    m in two replays, the map bias learnt as -77 to -85 m east, -35 to -39 m north. At the
    default prior (SRTM's 10 m per axis) the same replay ran 52 m RMS, 82 m final, within
    3 sigma half the time."""
    jammed, = _replayed_real_image_flight(tmp_path, shared_data, agl=3000.0,
                                          replays=("jammed",), albedo_shift="-60,-40",
                                          dem_ce90=200.0)
    assert jammed["fix_error"]["median"] > 60.0, jammed["fix_error"]   # the map is off
    fused = jammed["fused_error"]
    assert fused["rms"] < 30.0 and fused["final"] < 30.0, fused
    assert fused["within_3_sigma"] >= 0.9, fused
    east, north, sigma = jammed["ekf_fix_use"]["map_bias"]
    assert east < -40.0 and math.hypot(east + 90.0, north + 35.0) < 3.0 * sigma, \
        jammed["ekf_fix_use"]["map_bias"]


def test_a_low_flight_over_a_real_image_fixes_on_mosaics_of_its_track(tmp_path, shared_data):
    """The same real image flown 900 m above its highest terrain: a frame sees ~42 x 31 DEM
    cells, too few for its drainage to be told from chance (13 of 149 fixed alone, one 4.3 km
    off; fused RMS 50 m against dead reckoning's 95 m), so camera_ingest publishes mosaics of
    up to the last 60 s of the track (85 fixed, the worst 58 m off, fused 30 m). With GNSS
    jammed from take-off the baro's bias is never calibrated, and a mosaic's scale (its
    frames laid out by the dead reckoning) is no measure of the height: taken for one, the
    height ran 80 m off with a sigma of 20 m and the gate refused 16 fixes; the height is the
    baro's, with its doubt. The bag is made here from ../shared, never committed."""
    result, jammed = _replayed_real_image_flight(tmp_path, shared_data, agl=900.0,
                                                 replays=("gnss", "jammed"))
    dr = result["dr_error"]   # (with GNSS for its first 15 s: jammed, it drifts further)
    # Jammed, the first mosaic fixes (~50 s in, 40-110 m off: registrations a few landmark
    # pixels off, held to their creases' ~20 m) pull the estimate up to 115 m off the dead
    # reckoning's 12 m, and later fixes bring it back: its RMS spread over 30-52 m (0.32-0.54
    # of dead reckoning's) in replays of one bag while the fixes' covariances were their
    # pairings' (5-10 x their errors; the GNSS run's 26-32 m), 37 m with the creases' (GNSS
    # run 21 m). When the mosaics measured the heading too, jammed, their headings led the
    # estimate's 30 deg off and it ran 410 m off (RMS 114 m) in one CI replay; position only,
    # 42-53 m while consecutive mosaics gave a velocity, 31-36 m since (GNSS run 26 m), and
    # 62 m once (0.66 of dead reckoning's; the next replay of the same code passed):
    # consecutive mosaics share most of their frames, so their fixes' errors persist from
    # fix to fix (RESULTS, session 51), and where the first few put the estimate, it stays
    # a while.
    # The final error and the worst fix bound it whatever the early fixes did.
    for r, rms_share in ((result, 0.4), (jammed, 0.75)):
        fixes = r["fixes"]
        assert fixes["fixes"] >= 0.3 * fixes["frames"], fixes
        assert r["fix_error"]["max"] <= 150.0, r["fix_error"]
        fused = r["fused_error"]
        assert fused["rms"] < rms_share * dr["rms"] and fused["final"] < 0.4 * dr["final"], \
            (fused, dr)
        assert r["fused_height_error"]["within_3_sigma"] >= 0.9, r["fused_height_error"]


@pytest.fixture(scope="module")
def n44_flight(tmp_path_factory, shared_data):
    """A 90 s survey flight over N44E005 (GNSS denied after 15 s) and the mission index of a
    40 x 40 km area around it, prepared for the flight's hours: made once from ../shared for
    the lost, kidnapped and cold-start replays."""
    dem = shared_data / "dem" / "N44E005.hgt"
    tmp = tmp_path_factory.mktemp("n44")
    bag, index = tmp / "n44", tmp / "index"
    simulate(SimConfig(dem=str(dem), duration=90.0, pattern="survey", agl=3000.0,
                       camera_hfov=70.0, landmark_gsd=30.0, gnss_denied_after=15.0,
                       start_time="2024-06-21T09:00:00Z", seed=5), bag)
    assert cli.main(["prepare", "--dem", str(dem), "--area", "44.32,5.25,44.68,5.75",
                     "--gsd", "30", "--out", str(index), "--time", "2024-06-21T08:55:00Z",
                     "--hours", "0.2", "--workers", "1"]) == 0
    return bag, index


def test_a_lost_then_kidnapped_aircraft_finds_itself_in_the_mission_index(tmp_path,
                                                                         n44_flight):
    """GNSS jammed from take-off and the filter started 10 km east of the truth over
    N44E005, then, 40 s in, its position set 5 km north of the truth (/ekf/set_pose, a
    kidnap): each time the tile around the estimate cannot hold the camera view, so after a
    run of no-fixes the matcher searches the whole mission index (prepared before flight, 40
    x 40 km) and two agreeing relocalisations move the filter back onto the truth. The bag
    and the index are made from ../shared (n44_flight)."""
    bag, index = n44_flight
    result = run_replay(bag, tmp_path / "out", GRAPH, mission_dir=index,
                        lost_offset=(10_000.0, 0.0), kidnap=(40.0, 0.0, 5_000.0))
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["relocalisations"] >= 4, fixes
    assert fixes["fixes"] >= 0.6 * fixes["frames"], fixes
    jumps = [float(e.split("jumped ")[1].split(" m")[0]) for e in result["navigation_events"]]
    assert len(jumps) == 2 and 9_500 < jumps[0] < 10_500 and 4_500 < jumps[1] < 5_500, jumps
    t, err, _ = result["series"]["fused_error"]
    gsd = 30.0
    # tracking after each find is the graph's usual on this flight: its ground matches carry
    # the filter's tilt error x 3000 m, which the ekf models but cannot tell from position
    # before the turn at 60-65 s (about 1 deg here); over 8 runs the fused error peaked at
    # 41-49 m between 30 and 40 s and at 40-54 m from 65 s on (with PnP fixes and no tilt
    # model, 27-128 m: 2 runs of 6 over this bound)
    assert (err[(t >= 30.0) & (t < 40.0)] <= 3 * gsd).all()     # found after the start
    assert (err[t >= 65.0] <= 3 * gsd).all()                    # and after the kidnap
    assert result["fused_error"]["final"] <= 2 * gsd, result["fused_error"]


def test_a_cold_start_without_any_pose_finds_itself_in_the_mission_index(tmp_path,
                                                                         n44_flight):
    """The same flight with no pose at all: GNSS jammed from take-off, the ekf waiting for
    two agreeing relocalisations (init_mode fix), camera_ingest projecting the frames
    pose-free (the barometer's height over the mission area's median terrain, levelled from
    the accelerometers, heading unknown) and the matcher searching them in the whole index
    at a ladder of scales. The filter starts from the relocalisations, camera_ingest then
    projects with its odometry, and the fused error is below 2 GSD within 60 s (issue 24's
    target; over runs it was there 13-14 s after take-off, as the filter started), then
    tracks as the graph does on this flight (up to 2.2 GSD in the turn at 60-65 s)."""
    bag, index = n44_flight
    result = run_replay(bag, tmp_path / "out", GRAPH, mission_dir=index, cold_start=True)
    _nodes_survived(result)
    fixes = result["fixes"]
    assert fixes["relocalisations"] >= 2, fixes
    assert fixes["fixes"] >= 0.6 * fixes["frames"], fixes
    assert fixes["first_after"] <= 10.0, fixes
    assert any(e.startswith("started from agreeing relocalisations")
               for e in result["navigation_events"]), result["navigation_events"]
    gsd = 30.0
    fused = result["fused_error"]
    assert fused["first_below_2_gsd_after"] <= 60.0, fused
    t, err, _ = result["series"]["fused_error"]
    assert (err[t >= fused["first_below_2_gsd_after"] + 10.0] <= 3 * gsd).all(), fused
    assert fused["final"] <= 2 * gsd, fused
