"""The main job: replay a bag through the whole node graph, record the outputs, report.

Every node of ``config/graph.yaml`` runs in its own process over DDS with ``use_sim_time``;
a ``bag_player`` publishes the bag (and ``/clock``) and a ``bag_recorder`` writes what the
graph produces to ``<out>/outputs``. When the player has finished and the graph has drained,
:mod:`.report` compares the outputs with the truth and writes ``report.txt``, ``report.yaml``
and PNG plots into ``<out>``. Simulated bags carry a ``mission.yaml`` (DEM, ENU origin) that
configures the metamap; bags recorded elsewhere use the parameter files as they are.
"""

from __future__ import annotations

import math
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from ..core.estimation.ekf_params import map_bias_sigma
from . import bags, report
from .errors import InputError
from .graph_runner import GraphError, GraphRunner, NodeSpec, load_graph

RECORDED_TOPICS = ["/nav/odometry", "/nav/pva_fix", "/nav/fix", "/nav/ekf/diagnostics",
                   "/camera/image_ground", "/camera/minutiae", "/landmark/minutiae",
                   "/camera_ingest/diagnostics", "/feature_extractor/diagnostics",
                   "/matcher/diagnostics",
                   # the autopilot bridge's, when it is enabled (--enable autopilot_bridge)
                   "/fmu/in/vehicle_visual_odometry", "/fmu/in/sensor_gps",
                   "/mavros/odometry/out", "/mavros/vision_pose/pose_cov",
                   "/autopilot_bridge/diagnostics"]


def _mission_parameters(topics: set[str], mission: dict) -> dict[str, dict]:
    """Per-node parameter overrides that make the graph match the bag (its topics, its
    mission.yaml)."""
    out: dict[str, dict] = {}
    if "/camera/image_raw/compressed" in topics and "/camera/image_raw" not in topics:
        out["camera_ingest"] = {"image_transport": "compressed"}
    dem = str(mission.get("dem", ""))
    metamap = {}
    if dem and not dem.startswith("matplotlib:"):
        metamap["dem_files"] = [dem]
    origin = mission.get("origin")
    if origin:
        metamap.update(origin_latitude=float(origin[0]), origin_longitude=float(origin[1]),
                       origin_altitude=float(origin[2]))
    gsd = mission.get("landmark_gsd")
    if gsd:
        metamap["gsd"] = float(gsd)
        out.setdefault("camera_ingest", {})["gsd"] = float(gsd)
    if mission.get("camera_footprint_radius"):
        metamap["camera_footprint_radius"] = float(mission["camera_footprint_radius"])
    if metamap:
        out["metamap"] = metamap
    ekf = {}
    if "/gnss/fix" in topics:
        ekf["init_mode"] = "gnss"  # GNSS is there before the denial: start from it
    if origin:
        ekf.update(origin_latitude=float(origin[0]), origin_longitude=float(origin[1]),
                   origin_altitude=float(origin[2]))
    if mission.get("dem_horizontal_ce90") is not None:   # the DEM's data sheet, not a guess
        ekf["init_map_bias_sigma"] = map_bias_sigma(mission["dem_horizontal_ce90"])
    if ekf:
        out["ekf"] = ekf
    return out


def _lost_parameters(bag: Path, offset) -> dict:
    """EKF parameters of a lost aircraft: GNSS jammed from the start (the replay leaves
    ``/gnss/fix`` out), the filter started at the bag's first true state with its position
    moved by ``offset`` (east, north metres) and the usual initial sigmas, which the offset
    far exceeds. The matcher must find the aircraft again (``--mission``)."""
    first = next(iter(bags.read(bag, ["/ground_truth/odometry"])), None)
    if first is None:
        raise InputError(f"bag {bag} has no /ground_truth/odometry to start a lost "
                         "aircraft from")
    from ..core.estimation.strapdown import quat_rotate, quat_to_euler

    truth = bags.decode(first)
    pose, twist = truth.pose.pose, truth.twist.twist
    q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                  pose.orientation.w])     # body -> ENU
    velocity = quat_rotate(q, np.array([twist.linear.x, twist.linear.y, twist.linear.z]))
    roll_pitch_yaw = quat_to_euler(q)
    position = (pose.position.x + float(offset[0]), pose.position.y + float(offset[1]),
                pose.position.z)
    return {"init_mode": "pose", "initial_position": [float(v) for v in position],
            "initial_velocity": [float(v) for v in velocity],
            "initial_rpy": [float(v) for v in roll_pitch_yaw]}


def _cold_start_parameters(mission_dir: Path, mission: dict) -> dict[str, dict]:
    """Parameters of a cold start: no pose at all (GNSS jammed from the start, the replay
    leaves ``/gnss/fix`` out), the ekf started from two agreeing relocalisations
    (``init_mode: fix``), the frames before them projected pose-free by camera_ingest
    (``cold_start``, the mission index's terrain heights). The barometer's pressure
    altitude is taken as the height above the geoid (as camera_ingest does): the ekf's
    ``baro_offset`` is minus the ENU origin's altitude, set rather than learnt (it is learnt
    only from a vertical sigma of 10 m, which fixes alone do not give)."""
    origin = mission.get("origin") or [0.0, 0.0, 0.0]
    return {"ekf": {"init_mode": "fix", "baro_offset": -float(origin[2])},
            "camera_ingest": {"cold_start": True, "mission_dir": str(mission_dir)}}


def _kidnapped(bag: Path, copy: Path, at: float, east: float, north: float) -> Path:
    """A copy of ``bag`` (and its mission.yaml) with one ``/ekf/set_pose`` ``at`` s after
    its first message: the true position then, moved by (``east``, ``north``) metres, with a
    10 m horizontal sigma; the height is left to the barometer (a 1 km sigma), so the kidnap
    moves the estimate sideways only. The filter believes it, as it would a wrong operator
    re-seed or a wrong fix accepted once, and the matcher must find the aircraft again
    (``--mission``)."""
    store = bags.typestore().types
    start, injected = None, False
    with bags.BagWriter(copy, compress=True) as writer:
        writer.add_topics_of(bag)
        for m in bags.read(bag):
            start = m.timestamp_ns if start is None else start
            if not injected and m.topic == "/ground_truth/odometry" and \
                    m.timestamp_ns - start >= at * 1e9:
                truth = bags.decode(m)
                p = truth.pose.pose.position
                pose = store["geometry_msgs/msg/Pose"](
                    position=store["geometry_msgs/msg/Point"](x=p.x + east, y=p.y + north,
                                                              z=p.z),
                    orientation=truth.pose.pose.orientation)
                covariance = np.diag([100.0, 100.0, 1e6] + [-1.0] * 3).ravel()
                msg = store["geometry_msgs/msg/PoseWithCovarianceStamped"](
                    header=truth.header, pose=store["geometry_msgs/msg/PoseWithCovariance"](
                        pose=pose, covariance=covariance))
                writer.write_message("/ekf/set_pose", m.timestamp_ns, msg,
                                     "geometry_msgs/msg/PoseWithCovarianceStamped")
                injected = True
            writer.write(m.topic, m.timestamp_ns, m.rawdata)
    if not injected:
        raise InputError(f"bag {bag} has no /ground_truth/odometry {at:g} s after its start "
                         "to kidnap the aircraft from")
    if (bag / "mission.yaml").exists():
        shutil.copy(bag / "mission.yaml", copy / "mission.yaml")
    return copy


def _echo(name: str, line: str) -> bool:
    """Show the player's progress and every warning or error; the rest goes to the logs."""
    return name == "bag_player" or "[WARN]" in line or "[ERROR]" in line or "fatal" in line


def _read_mission(bag: Path) -> dict:
    """The bag's mission.yaml, checked: InputError naming what is wrong with it."""
    path = bag / "mission.yaml"
    try:
        mission = report.read_mission(bag)
    except yaml.YAMLError as err:
        raise InputError(f"{path} is not valid YAML ({err}): fix it, or remove it to use "
                         "the parameter files as they are") from err
    if not isinstance(mission, dict):
        raise InputError(f"{path} must be a mapping (dem, origin, landmark_gsd, ...), not "
                         f"{type(mission).__name__}: fix or remove it")
    origin, gsd = mission.get("origin"), mission.get("landmark_gsd")
    try:
        if origin is not None and (len(origin) != 3 or not all(map(math.isfinite,
                                                                   map(float, origin)))):
            raise ValueError
        if gsd is not None and not float(gsd) > 0:
            raise ValueError
    except (TypeError, ValueError):
        raise InputError(f"{path}: origin must be [lat, lon, height] and landmark_gsd a "
                         f"positive number, got {origin!r} and {gsd!r}: fix or remove "
                         "it") from None
    if mission.get("dem_horizontal_ce90") is not None:
        try:
            map_bias_sigma(mission["dem_horizontal_ce90"])
        except (TypeError, ValueError) as err:
            raise InputError(f"{path}: dem_horizontal_ce90 (the DEM's stated horizontal "
                             f"accuracy, m at 90 %): {err}: fix or remove it") from None
    return mission


#: The message type the graph (and the report) takes on each input topic a bag may hold.
INPUT_TYPES = {
    "/imu/data": "sensor_msgs/msg/Imu",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/baro/pressure": "sensor_msgs/msg/FluidPressure",
    "/gnss/fix": "sensor_msgs/msg/NavSatFix",
    "/ground_truth/odometry": "nav_msgs/msg/Odometry",
}


def _wrong_types(topics) -> list[str]:
    """'topic is T, not U' for each input topic of another type than the graph takes (a
    subscription never matches it: the replay would wait for it, then play to no one)."""
    return [f"{t.topic} is {t.msgtype}, not {INPUT_TYPES[t.topic]}" for t in topics
            if t.topic in INPUT_TYPES and t.msgtype != INPUT_TYPES[t.topic]]


MAX_OFFSET = 1000e3   # m: a lost or kidnapped aircraft within a mission's reach


def _check_offsets(lost_offset, kidnap):
    """InputError for a --lost or --kidnap that is no place or time of the flight."""
    east_north = [*(lost_offset or ()), *(kidnap[1:] if kidnap else ())]
    if not all(math.isfinite(v) and abs(v) <= MAX_OFFSET for v in east_north):
        raise InputError(f"--lost / --kidnap offsets {east_north}: east and north must be "
                         f"finite and within {MAX_OFFSET / 1e3:g} km")
    if kidnap is not None and not (math.isfinite(kidnap[0]) and kidnap[0] >= 0):
        raise InputError(f"--kidnap at {kidnap[0]} s: must be >= 0 s into the bag")


def _check_mission_index(mission_dir: Path, mission: dict):
    """InputError for a mission index that is incomplete, of another area than the bag's
    mission, or at another landmark GSD: the matcher would search it in vain."""
    from ..core.matching.mission_index import MissionIndex, MissionIndexError

    try:
        index = MissionIndex(mission_dir)
    except (MissionIndexError, OSError) as err:
        raise InputError(f"--mission {mission_dir}: {err}") from None
    missing = index.missing()
    if missing:
        raise InputError(f"--mission {mission_dir}: {len(missing)} tile layers missing: run "
                         "terrain-nav prepare again to complete it")
    damaged = index.damaged()
    if damaged:
        raise InputError(f"--mission {mission_dir}: {len(damaged)} tile layer(s) damaged, "
                         f"the first: {damaged[0]}")
    gsd = mission.get("landmark_gsd")
    if gsd and abs(index.gsd - float(gsd)) > 1e-6 * float(gsd):
        raise InputError(f"--mission {mission_dir}: prepared at {index.gsd:g} m/px, the bag's "
                         f"landmarks at {float(gsd):g}: prepare it at --gsd {float(gsd):g}")
    origin = mission.get("origin")
    if origin:
        east, north, _ = index.origin.geodetic_to_enu(float(origin[0]), float(origin[1]), 0.0)
        west, east_edge, south, north_edge = index.grid.extent
        if not (west <= east <= east_edge and south <= north <= north_edge):
            raise InputError(f"--mission {mission_dir}: the bag's mission origin "
                             f"({float(origin[0]):.4f}, {float(origin[1]):.4f}) is outside "
                             "the index's area: an index of another area?")


def check_inputs(bag: Path, out_dir: Path, rate: float) -> tuple[dict, bags.BagHealth]:
    """Everything a replay needs, checked before any node starts: the options, the bag
    (read in full), its mission.yaml and the DEM it names. Returns (mission, bag health);
    raises InputError, BagError or DemError saying what is wrong."""
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"--rate {rate}: must be > 0 (1 = real time)")
    if (out_dir / "outputs").exists():
        raise InputError(f"{out_dir / 'outputs'} exists: choose another --out directory")
    health = bags.verify(bag)
    if not health.readable:
        raise InputError(f"bag {bag} holds no readable messages"
                         f"{' (' + health.problem + ')' if health.problem else ''}")
    if "/imu/data" not in {t.topic for t in bags.topics(bag)}:
        raise InputError(f"bag {bag} has no /imu/data: the EKF cannot navigate without it")
    mission = _read_mission(bag)
    dem = str(mission.get("dem", ""))
    if dem and not dem.startswith("matplotlib:"):
        from ..core.terrain.dem_sources import open_dem_source

        open_dem_source(dem).close()
    wrong = _wrong_types(bags.topics(bag))
    if wrong:
        raise InputError(f"bag {bag}: {'; '.join(wrong)}: the graph's subscriptions never "
                         "match a topic of another type; convert or remap it")
    return mission, health


def run_replay(bag: str | Path, out_dir: str | Path, graph_config: str | Path,
               rate: float = 1.0, drain: float = 5.0, startup_timeout: float = 60.0,
               verbose: bool = False, enable=(), mission_dir: str | Path | None = None,
               lost_offset=None, kidnap=None, cold_start: bool = False) -> dict:
    """Replay ``bag`` through the graph; return the report's metrics (see :mod:`.report`).

    The inputs are checked first (:func:`check_inputs`); a damaged bag is replayed as far
    as it can be read, and the report says so (``input_damaged``). ``enable`` names nodes
    the graph file disables to run too (e.g. ``autopilot_bridge``, whose outputs are then
    recorded). ``mission_dir`` is the mission index the matcher searches when lost;
    ``lost_offset`` (east, north metres) replays a lost aircraft (:func:`_lost_parameters`);
    ``kidnap`` (seconds, east, north metres) a kidnapped one (:func:`_kidnapped`);
    ``cold_start`` one with no pose at all, found from the mission index alone
    (:func:`_cold_start_parameters`).
    """
    if cold_start and mission_dir is None:
        raise InputError("--cold-start needs the mission index to search: give --mission "
                         "MISSION_DIR")
    if cold_start and lost_offset is not None:
        raise InputError("give either --cold-start (no pose at all) or --lost E N (a wrong "
                         "one), not both")
    _check_offsets(lost_offset, kidnap)
    gnss_jammed = lost_offset is not None or cold_start   # the replay leaves /gnss/fix out
    bag, out_dir = Path(bag).resolve(), Path(out_dir).resolve()
    mission, health = check_inputs(bag, out_dir, rate)
    if mission_dir is not None:
        _check_mission_index(Path(mission_dir), mission)
    spec = load_graph(graph_config, enable)
    out_dir.mkdir(parents=True, exist_ok=True)
    if kidnap is not None:
        bag = _kidnapped(bag, out_dir / "input", *kidnap)
    output_bag = out_dir / "outputs"
    input_topics = [t.topic for t in bags.topics(bag)]
    overrides = _mission_parameters(set(input_topics), mission)
    if mission_dir is not None:
        overrides.setdefault("matcher", {})["mission_dir"] = str(Path(mission_dir).resolve())
    if lost_offset is not None:
        overrides.setdefault("ekf", {}).update(_lost_parameters(bag, lost_offset))
    if cold_start:
        for node, values in _cold_start_parameters(Path(mission_dir).resolve(),
                                                   mission).items():
            overrides.setdefault(node, {}).update(values)
    if gnss_jammed:
        input_topics = [t for t in input_topics if t != "/gnss/fix"]
    for node in spec.nodes:
        node.parameters.update(overrides.get(node.name, {}))
    wait_for = [t for t in ("/imu/data", "/camera/image_raw", "/camera/image_raw/compressed")
                if t in input_topics]
    # and for the nodes downstream, which subscribe once their kernels are loaded (compiled
    # on a first run: tens of seconds in which the first frames would find no one)
    # and for the recorder, whose bag the report reads: the answers to the first frames too
    ready = [n.name for n in spec.nodes if n.name in ("feature_extractor", "matcher")]
    ready.append("bag_recorder")
    spec.nodes.append(NodeSpec("bag_recorder", "bag_recorder", required=True, parameters={
        "output": str(output_bag), "topics": RECORDED_TOPICS}))
    spec.nodes.append(NodeSpec("bag_player", "bag_player", required=False, parameters={
        "bag": str(bag), "rate": float(rate), "wait_for_topics": wait_for or [""],
        "wait_for_nodes": ready or [""],
        "wait_timeout": 120.0, "start_delay": 2.0,
        "topics": [t for t in input_topics if t != "/ground_truth/odometry"]}))
    runner = GraphRunner(spec, {"use_sim_time": True}, log_dir=out_dir / "logs",
                         echo=None if verbose else _echo)
    duration = _bag_duration(bag)
    runner.report(f"replaying {bag.name} ({duration:.0f} s at x{rate}) through "
                  f"{len(spec.nodes) - 2} nodes; logs in {out_dir / 'logs'}")
    if health.damaged:
        runner.report(f"the bag is {health.describe()}: replaying those")
    started = time.monotonic()
    status = 1
    stopped_by: list[str] = []

    def stop(signum, _frame):
        # Ctrl-C or SIGTERM: stop the graph, then write the report of what was replayed
        stopped_by.append(signal.Signals(signum).name)
        runner.request_stop()

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        runner.start()
        runner.wait_until_up(startup_timeout)
        status = runner.spin(duration=duration / rate + startup_timeout + 120.0,
                             until_exit="bag_player")
        if status == 0 and not stopped_by:
            runner.report(f"bag finished after {time.monotonic() - started:.0f} s; "
                          f"draining for {drain:.0f} s")
            status = runner.spin(duration=drain)
    except GraphError as err:
        runner.report(str(err))
    finally:
        runner.sample_usage()
        usage = {k: v for k, v in runner.usage.items()
                 if k not in ("bag_player", "bag_recorder")}
        for name, count in runner.respawns.items():   # restarts of nodes that died
            if name in usage:
                usage[name]["respawns"] = count
        codes = runner.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    died = [n for n, c in codes.items() if c not in (0, None) and n in runner.died
            and not (n == "bag_player" and health.damaged)]   # it says so: exit 1
    if not output_bag.exists():
        if stopped_by:   # stopped before the recorder wrote anything: no report to write
            raise KeyboardInterrupt
        raise RuntimeError(f"the recorder wrote no bag (graph status {status}, died: {died})")
    result = report.analyse(bag, output_bag, usage,
                            denied_after=0.0 if gnss_jammed else None)
    result["graph_status"], result["died"] = status, died
    result["input_damaged"] = health.problem
    result["partial"] = _cut_short(stopped_by, status, died)
    gsd = mission.get("landmark_gsd")
    text = report.format_report(result, gsd)
    if health.damaged:
        text = f"INPUT BAG {health.describe()}: this report covers those only\n\n{text}"
    if result["partial"]:
        text = f"PARTIAL REPORT: {result['partial']}\n\n{text}"
    (out_dir / "report.txt").write_text(text + "\n")
    (out_dir / "report.yaml").write_text(yaml.safe_dump(_summary(result), sort_keys=False))
    background = _hillshade_background(mission, result)
    result["plots"] = [str(p) for p in report.plot(result, out_dir, background)]
    print(text, flush=True)
    print(f"\nplots: {', '.join(result['plots'])}\nreport: {out_dir / 'report.txt'}",
          flush=True)
    return result


def _cut_short(stopped_by: list[str], status: int, died: list[str]) -> str:
    """Why the replay did not run to the end of the bag ("" when it did)."""
    if stopped_by:
        return f"the replay was stopped ({stopped_by[0]}) before the end of the bag"
    if died:
        return f"node(s) {', '.join(died)} died during the replay"
    if status != 0:
        return "the graph stopped before the end of the bag"
    return ""


def _bag_duration(bag: Path) -> float:
    first = last = None
    for m in bags.read(bag, ["/imu/data"]):
        first = m.timestamp_ns if first is None else first
        last = m.timestamp_ns
    return 0.0 if first is None else (last - first) * 1e-9


def _summary(result: dict) -> dict:
    """The scalar part of the metrics, for report.yaml."""
    keep = {}
    for key in ("fixes", "fix_error", "fused_error", "fused_height_error", "dr_error",
                "graph_status", "died", "denied_after", "input_damaged", "partial",
                "no_odometry", "odometry_stopped"):
        if key in result:
            keep[key] = result[key]
    keep["latency_ms"] = {k: {"p50": float(1e3 * np.median(v)),
                              "p95": float(1e3 * np.percentile(v, 95))}
                          for k, v in result["latency"].items()}
    keep["usage"] = {k: {"cpu_s": round(v["cpu_s"], 2), "peak_rss_mb": round(v["peak_rss_mb"]),
                         "respawns": v.get("respawns", 0)}
                     for k, v in result["usage"].items()}
    return report.plain(keep)


def _hillshade_background(mission: dict, result: dict):
    """Hillshade of the DEM under the flight, for the trajectory plot (None if unavailable)."""
    if result.get("truth") is None or not mission.get("origin"):
        return None
    try:
        from ..core.features.hillshade import hillshade
        from ..core.terrain.dem_sources import open_dem_source
        from ..core.terrain.geodesy import EnuOrigin
        from ..core.terrain.georef import GeoReference
        from ..core.terrain.metamap import MetaMap

        dem_name = str(mission.get("dem", ""))
        dem = open_dem_source(dem_name)
        metamap = MetaMap(dem, EnuOrigin(*mission["origin"]), heights="enu")
        p = result["truth"][1]
        pad = 0.15 * max(np.ptp(p[:, 0]), np.ptp(p[:, 1]), 500.0)
        west, east = p[:, 0].min() - pad, p[:, 0].max() + pad
        south, north = p[:, 1].min() - pad, p[:, 1].max() + pad
        gsd = max((east - west), (north - south)) / 800.0
        georef = GeoReference(west, north, gsd, int((east - west) / gsd),
                              int((north - south) / gsd))
        tile = metamap.tile(georef)
        shade = hillshade(np.nan_to_num(tile.elevation, nan=float(np.nanmean(tile.elevation))),
                          315.0, 45.0, gsd=gsd)
        return shade, (west, west + georef.width * gsd, north - georef.height * gsd, north)
    except Exception as err:  # noqa: BLE001 - the plot is still useful without the DEM
        print(f"[replay] no hillshade background: {err}", file=sys.stderr)
        return None
