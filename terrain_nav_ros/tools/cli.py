"""``terrain-nav``: the command line of terrain_nav (graph runner, bag tools, jobs).

Run ``terrain-nav --help`` or ``terrain-nav <command> --help``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import traceback
from dataclasses import replace
from pathlib import Path

from .errors import InputError

REPO = Path(__file__).resolve().parents[2]
DEFAULT_GRAPH = REPO / "config" / "graph.yaml"
DEFAULT_BAG = REPO / "bags" / "jacksboro_demo"


def _cmd_graph(args) -> int:
    from .graph_runner import GraphError, load_graph, normalise_namespace, run_graph

    _check_positive(args, "duration")
    try:
        # a node named by --only runs even where the file disables it
        spec = load_graph(args.config, [*(args.enable or ()), *(args.only or ())])
    except GraphError as err:
        print(f"terrain-nav graph: {err}", file=sys.stderr)
        return 2
    if args.only:
        spec.nodes = [n for n in spec.nodes if n.name in args.only]
    if args.namespace is not None:
        try:
            spec.namespace = normalise_namespace(args.namespace, "--namespace")
        except GraphError as err:
            raise InputError(str(err)) from err
    if args.until_exit and args.until_exit not in [n.name for n in spec.nodes]:
        raise InputError(f"--until-exit {args.until_exit}: not a node this graph runs "
                         f"({', '.join(n.name for n in spec.nodes)})")
    extra = {"use_sim_time": True} if args.use_sim_time else {}
    return run_graph(spec, extra_parameters=extra, duration=args.duration,
                     until_exit=args.until_exit, log_dir=args.log_dir)


def _exec_node(executable: str, params: dict) -> int:
    from .graph_runner import NodeSpec, node_command

    cmd = node_command(NodeSpec(executable, executable, parameters=params))
    os.execv(cmd[0], cmd)
    return 1  # not reached


def _cmd_bag_info(args) -> int:
    from . import bags

    health = bags.verify(args.bag)
    print(bags.info(args.bag, health))
    return 1 if health.damaged else 0


def _cmd_bag_play(args) -> int:
    from . import bags

    _check_positive(args, "rate")
    health = bags.verify(args.bag)
    if health.damaged:
        if not health.readable:
            raise InputError(f"bag {args.bag} is damaged and holds nothing to play "
                             f"({health.problem})")
        print(f"terrain-nav bag play: bag {args.bag} is {health.describe()}: playing those; "
              "exit status 1 when done", file=sys.stderr)
    if not (math.isfinite(args.rate) and math.isfinite(args.delay) and args.delay >= 0):
        raise InputError(f"--rate {args.rate} and --delay {args.delay}: must be finite, the "
                         "delay >= 0")
    held = {t.topic for t in bags.topics(args.bag)}
    missing = sorted(set(args.topics or ()) - held)
    if missing:
        raise InputError(f"--topics {' '.join(missing)}: not in bag {args.bag} (it holds "
                         f"{', '.join(sorted(held))})")
    params = {"bag": str(Path(args.bag).resolve()), "rate": float(args.rate),
              "publish_clock": not args.no_clock, "start_delay": float(args.delay)}
    if args.topics:
        params["topics"] = args.topics
    if args.remap:
        params["remap"] = args.remap
    if args.wait_for:
        params["wait_for_topics"] = args.wait_for
    return _exec_node("bag_player", params)


def _cmd_bag_record(args) -> int:
    _check_new(args.output, "-o")
    params = {"output": str(Path(args.output).resolve()), "compress": not args.no_compress}
    if args.topics:
        params["topics"] = args.topics
    if args.exclude:
        params["exclude"] = args.exclude
    return _exec_node("bag_recorder", params)


def _cmd_replay(args) -> int:
    from .replay import run_replay

    bag = Path(args.bag) if args.bag else DEFAULT_BAG
    if not bag.exists():
        raise InputError(f"bag {bag} not found: give a bag directory with --bag")
    out = Path(args.out) if args.out else REPO / "out" / f"replay-{bag.name}-{_now()}"
    result = run_replay(bag, out, args.config, rate=args.rate, verbose=args.verbose,
                        enable=args.enable or (), mission_dir=args.mission,
                        lost_offset=args.lost, kidnap=args.kidnap,
                        cold_start=args.cold_start)
    if "stopped" in result["partial"]:
        return 130
    return 0 if result["graph_status"] == 0 and not result["died"] else 1


def _now() -> str:
    import time

    return time.strftime("%Y%m%d-%H%M%S")


# What one simulated flight may ask for: a day, a 16 M pixel camera, a 2 kHz IMU.
MAX_SIM_DURATION, MAX_SIM_PIXELS, MAX_IMU_RATE = 86400.0, 4096 * 4096, 2000.0


def _check_simulation_size(args):
    """InputError for a flight the simulator cannot hold in memory, or with no frame."""
    from .flight_sim import SimConfig

    cfg = SimConfig()
    duration = args.duration or cfg.duration
    rate = args.camera_rate or cfg.camera_rate
    if not (math.isfinite(rate) and math.isfinite(duration)
            and 2.0 / rate <= duration <= MAX_SIM_DURATION):
        raise InputError(f"--duration {duration:g}: must be {2.0 / rate:g} s (the first "
                         f"camera frame and after, at --camera-rate {rate:g}) to "
                         f"{MAX_SIM_DURATION:g} s")
    pixels = (args.camera_width or cfg.camera_width) * (args.camera_height or cfg.camera_height)
    if pixels > MAX_SIM_PIXELS:
        raise InputError(f"--camera-width x --camera-height: {pixels / 1e6:.3g} M pixels, at "
                         f"most {MAX_SIM_PIXELS / 1e6:.3g} M")
    if (args.imu_rate or cfg.imu_rate) > MAX_IMU_RATE:
        raise InputError(f"--imu-rate {args.imu_rate:g}: at most {MAX_IMU_RATE:g} Hz")
    if args.sun is not None:
        azimuth, elevation = args.sun
        if not (math.isfinite(azimuth) and 0 < elevation <= 90):
            raise InputError(f"--sun {azimuth:g} {elevation:g}: the elevation must be in "
                             "(0, 90] deg, the azimuth a number")


def _cmd_simulate(args) -> int:
    from dataclasses import fields

    from .flight_sim import SimConfig, SimInputError, simulate

    _check_positive(args, "duration", "speed", "agl", "camera_rate", "camera_width",
                    "camera_height", "camera_hfov", "imu_rate", "landmark_gsd")
    if args.camera_hfov is not None and args.camera_hfov >= 90:
        raise InputError(f"--camera-hfov {args.camera_hfov}: the simulated down-looking "
                         "camera takes below 90 deg")
    _check_simulation_size(args)
    if args.gnss_denied_after is not None and not args.gnss_denied_after >= 0:
        raise InputError(f"--gnss-denied-after {args.gnss_denied_after}: must be >= 0 s")
    _check_new(args.output, "-o")
    cfg = SimConfig()
    for f in fields(SimConfig):
        value = getattr(args, f.name, None)
        if value is not None:
            setattr(cfg, f.name, tuple(value) if isinstance(value, list) else value)
    if cfg.dem and not cfg.dem.startswith(("synthetic", "matplotlib:")):
        # a DEM file that cannot be read fails now, not after the set-up
        from ..core.terrain.dem_sources import open_dem_source

        with open_dem_source(cfg.dem) as dem:
            if dem.warning:
                print(f"terrain-nav simulate: warning: {dem.warning}", file=sys.stderr)
    try:
        summary = simulate(cfg, args.output)
    except SimInputError as err:   # --albedo, --start-time, --dem: the user's input
        raise InputError(str(err)) from err
    print(f"wrote {args.output}: {summary['duration_s']:.0f} s over {summary['dem']}, "
          f"{summary['camera_frames']} camera frames, GNSS denied after "
          f"{summary['gnss_denied_after_s']:.0f} s")
    return 0


def _cmd_evaluate(args) -> int:
    from ..core.matching.params import MatchParams
    from .evaluation import run_evaluation

    if args.image or args.scenes:
        return _cmd_evaluate_imagery(args)
    out = Path(args.out) if args.out else REPO / "out" / f"evaluate-{_now()}"
    params = MatchParams()
    if args.no_creases:
        params = MatchParams(crease_check=False, crease_descriptor=False)
    if args.no_ridges:
        params = replace(params, ridge_check=False)
    if args.heading_prior is not None:
        if not 0.0 < args.heading_prior <= 180.0:
            print("terrain-nav evaluate: --heading-prior must be in (0, 180] deg",
                  file=sys.stderr)
            return 2
        params = replace(params, max_rotation=math.radians(args.heading_prior))
    try:
        summary = run_evaluation(args.dem, args.gsd, args.blocks, out,
                                 block_size=args.block_size, sun_change=args.sun_change,
                                 false_match_rate=args.false_match_rate, seed=args.seed,
                                 quick=args.quick, baselines=not args.no_baselines,
                                 lighting=args.lighting, match_params=params,
                                 jobs=args.jobs)
    except (ValueError, OSError) as err:
        print(f"terrain-nav evaluate: {err}", file=sys.stderr)
        return 2
    print(summary["report"])
    print(f"wrote {out}")
    return 0


def _cmd_prepare(args) -> int:
    from .prepare import interrupted_message, request_from_args, run_prepare

    request = request_from_args(args)
    try:
        run_prepare(request)
    except KeyboardInterrupt:
        print(f"terrain-nav prepare: {interrupted_message(request.out)}", file=sys.stderr)
        return 130
    return 0


def _match_gsd(text: str):
    """``--match-gsd``: "native" -> None, "dem", or a positive GSD in metres."""
    if text in ("native", "dem"):
        return None if text == "native" else text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise ValueError(f"--match-gsd must be 'native', 'dem' or > 0 m, got {text}")
    return value


MAX_CASES = 10000   # views per scene, size and heading: a study of hours, not of days


def _cmd_evaluate_imagery(args) -> int:
    """``evaluate --image IMG --dem DEM`` / ``--scenes YAML``: the real-imagery study."""
    from ..core.matching.params import MatchParams
    from .real_imagery import load_scene, load_scenes, run_real_imagery_study

    out = Path(args.out) if args.out else REPO / "out" / f"evaluate-imagery-{_now()}"
    try:
        if args.scenes:
            scenes = load_scenes(args.scenes, args.data_dir)
        else:
            if not args.dem:
                raise ValueError("--image needs --dem (the DEM of the same place)")
            sun = _pair(args.sun, "--sun") if args.sun else None
            gsd = None if args.gsd in (None, "native") else float(args.gsd)
            scenes = [load_scene(args.image, args.dem, band=args.band, gsd=gsd, sun=sun,
                                 when=args.time)]
        for scene in scenes:
            for warning in (scene.image_warning, scene.dem_warning, scene.sun_warning,
                            scene.registration_warning):
                if warning:
                    print(f"terrain-nav evaluate: warning: {scene.name}: {warning}",
                          file=sys.stderr)
        try:
            sizes = tuple(int(x) for x in args.sizes.split(","))
        except ValueError:
            raise ValueError(f"--sizes {args.sizes}: give whole numbers of pixels, like "
                             "128,256") from None
        if min(sizes) < 16 or not 1 <= args.cases <= MAX_CASES or args.controls < 0:
            raise ValueError(f"--sizes must be >= 16 px, --cases 1-{MAX_CASES} and "
                             "--controls >= 0")
        if not 1.0 <= args.region_factor <= 10.0:
            raise ValueError(f"--region-factor {args.region_factor:g}: the region's side "
                             "must be 1-10 times the view's")
        headings = ("unknown", "known") if args.heading == "both" else (args.heading,)
        baselines = () if args.no_baselines else tuple(args.baselines.split(","))
        params = MatchParams(view_search=not args.no_view_search)
        summary = run_real_imagery_study(scenes, sizes=sizes, cases=args.cases,
                                         match_params=params,
                                         match_gsd=_match_gsd(args.match_gsd),
                                         out_dir=out, seed=args.seed, headings=headings,
                                         baselines=baselines,
                                         controls_per_case=args.controls,
                                         region_factor=args.region_factor,
                                         false_match_rate=args.false_match_rate,
                                         threshold=_graph_threshold() if args.threshold
                                         is None else args.threshold,
                                         shadows=bool(_graph_parameter("landmark_renderer",
                                                                       "shadows")))
    except (ValueError, OSError, KeyError) as err:
        print(f"terrain-nav evaluate: {err}", file=sys.stderr)
        return 2
    print(summary["report"])
    print(f"wrote {out}")
    return 0


def _graph_parameter(node: str, name: str):
    """A node's parameter ``name`` in the graph's parameters file."""
    import yaml

    doc = yaml.safe_load((REPO / "config" / "terrain_nav.yaml").read_text())
    return doc[node]["ros__parameters"][name]


def _graph_threshold() -> float:
    """The matcher's ``match.threshold`` in the graph's parameters file."""
    return float(_graph_parameter("matcher", "match.threshold"))


def _pair(text: str, option: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"{option} takes two numbers, e.g. 160.5,41.2; got {text!r}") from None
    return a, b


def _check_positive(args, *names):
    """InputError for an option given as zero, negative or NaN."""
    for name in names:
        value = getattr(args, name, None)
        if value is not None and not value > 0:
            raise InputError(f"--{name.replace('_', '-')} {value}: must be > 0")


def _check_new(path, option: str):
    """InputError when an output path exists already (nothing is overwritten)."""
    if Path(path).exists():
        raise InputError(f"{path} exists already: give a new path with {option}")


def _input_error_hint(err: BaseException) -> str | None:
    """What to do about an error that is the user's input, or None for any other error."""
    import yaml

    from .bags import BagError
    from .graph_runner import GraphError

    dem_io = sys.modules.get("terrain_nav_ros.core.terrain.dem_io")
    if isinstance(err, InputError):
        return ""
    if dem_io is not None and isinstance(err, dem_io.DemError):
        return "give a readable DEM (GeoTIFF, ESRI ASCII grid, SRTM .hgt)"
    if isinstance(err, BagError):
        return "give a rosbag2 MCAP bag (a directory with metadata.yaml and .mcap)"
    if isinstance(err, GraphError):
        return "fix the graph file (--config)"
    if isinstance(err, yaml.YAMLError):
        return "fix the YAML file"
    if isinstance(err, TimeoutError | ConnectionError):   # (both OSErrors)
        return "check the address, and that the service there runs"
    if isinstance(err, OSError):
        return "check the path and its permissions"
    return None


# the commands that start ROS nodes (evaluate, simulate and prepare need no DDS)
_ROS_COMMANDS = ("graph", "demo", "replay", "bag")
# Fast DDS maps a domain to UDP ports: 0-232 fit (beyond, the ports overflow)
_MAX_DOMAIN_ID = 232


def _check_ros_environment(env):
    """InputError for a ROS_DOMAIN_ID no node could join, or an RMW this install lacks:
    else every node dies at start-up with rcl's message, or the runner with a traceback."""
    domain = env.get("ROS_DOMAIN_ID", "").strip()
    if domain and not (domain.isdigit() and int(domain) <= _MAX_DOMAIN_ID):
        raise InputError(f"ROS_DOMAIN_ID={domain}: must be a whole number 0-{_MAX_DOMAIN_ID}")
    rmw = env.get("RMW_IMPLEMENTATION", "").strip()
    if rmw:   # rcl loads lib<rmw>.so from the install's lib folders
        folders = [Path(sys.prefix) / "lib"]
        folders += [Path(p) / "lib" for p in env.get("AMENT_PREFIX_PATH", "").split(":") if p]
        folders += [Path(p) for p in env.get("LD_LIBRARY_PATH", "").split(":") if p]
        if not any((folder / f"lib{rmw}.so").is_file() for folder in folders):
            raise InputError(f"RMW_IMPLEMENTATION={rmw}: not installed here (unset it for "
                             "the default, rmw_fastrtps_cpp)")


def _run(args) -> int:
    """Run a command; bad input is one line on stderr and exit status 2."""
    prog = " ".join(["terrain-nav", args.command] + ([args.bag_command]
                                                      if args.command == "bag" else []))
    try:
        if args.command in _ROS_COMMANDS:
            _check_ros_environment(os.environ)
        return args.func(args)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:   # `terrain-nav bag info BAG | head`: the reader has gone
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the interpreter's final flush
        return 1
    except Exception as err:
        hint = _input_error_hint(err)
        if hint is None:
            raise
        if getattr(args, "debug", False):
            traceback.print_exc()
        text = " ".join(str(err).split())   # one line whatever the message holds
        print(f"{prog}: {text}{'; ' + hint if hint else ''} (--debug shows the traceback)",
              file=sys.stderr)
        return 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="terrain-nav", description=__doc__.splitlines()[0])
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        help="show the traceback of an error, not only its line")
    sub = _Subparsers(parser.add_subparsers(dest="command", required=True), [common])

    graph = sub.add_parser("graph", help="run the node graph, one process per node")
    graph.add_argument("--config", default=DEFAULT_GRAPH, type=Path,
                       help="graph YAML (default: config/graph.yaml)")
    graph.add_argument("--only", nargs="+", help="run only these nodes")
    graph.add_argument("--enable", nargs="+", metavar="NODE",
                       help="also run these nodes the graph file disables (enabled: false)")
    graph.add_argument("--namespace", metavar="NS",
                       help="run every node and topic under this namespace (e.g. uav1; "
                            "default the graph file's, else the root)")
    graph.add_argument("--use-sim-time", action="store_true",
                       help="set use_sim_time on every node (when a bag publishes /clock)")
    graph.add_argument("--duration", type=float, help="stop after this many seconds")
    graph.add_argument("--until-exit", metavar="NODE",
                       help="stop the graph when this node exits (e.g. a bag player)")
    graph.add_argument("--log-dir", type=Path, help="also write each node's output here")
    graph.set_defaults(func=_cmd_graph)

    bag = sub.add_parser("bag", help="rosbag2 MCAP tools (info, play, record)")
    bag_sub = _Subparsers(bag.add_subparsers(dest="bag_command", required=True), [common])
    info = bag_sub.add_parser("info", help="summarise a bag")
    info.add_argument("bag")
    info.set_defaults(func=_cmd_bag_info)
    play = bag_sub.add_parser("play", help="publish a bag into the graph with its timing")
    play.add_argument("bag")
    play.add_argument("--rate", type=float, default=1.0, help="speed factor")
    play.add_argument("--topics", nargs="+", help="only these topics")
    play.add_argument("--remap", nargs="+", metavar="FROM:=TO", help="topic remappings")
    play.add_argument("--wait-for", nargs="+", metavar="TOPIC",
                      help="wait for subscribers on these topics before playing")
    play.add_argument("--delay", type=float, default=0.0, help="seconds before the first message")
    play.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    play.set_defaults(func=_cmd_bag_play)
    record = bag_sub.add_parser("record", help="record topics to a new MCAP bag")
    record.add_argument("-o", "--output", required=True, help="new bag directory")
    record.add_argument("--topics", nargs="+", help="only these topics (default: all)")
    record.add_argument("--exclude", nargs="+", help="never these topics")
    record.add_argument("--no-compress", action="store_true",
                        help="write the chunks uncompressed (default: zstd, as ros2 bag "
                             "record --compression-mode storage)")
    record.set_defaults(func=_cmd_bag_record)
    for name, text in (("demo", "the main job: replay the default bag through the graph and "
                                "report"), ("replay", "replay any bag through the graph and "
                                                      "report (same as demo with --bag)")):
        job = sub.add_parser(name, help=text)
        job.add_argument("--bag", help=f"bag to replay (default {DEFAULT_BAG.relative_to(REPO)})")
        job.add_argument("--out", help="output directory (default out/replay-<bag>-<time>)")
        job.add_argument("--rate", type=float, default=1.0, help="playback speed factor")
        job.add_argument("--config", type=Path, default=DEFAULT_GRAPH, help="graph YAML")
        job.add_argument("--verbose", action="store_true", help="show all node output")
        job.add_argument("--enable", nargs="+", metavar="NODE",
                         help="also run these disabled nodes (e.g. autopilot_bridge)")
        job.add_argument("--mission", type=Path, metavar="MISSION_DIR",
                         help="mission index (terrain-nav prepare) the matcher searches "
                              "when lost")
        job.add_argument("--lost", type=float, nargs=2, metavar=("E", "N"),
                         help="GNSS jammed from the start: the filter starts at the bag's "
                              "true initial state moved by E, N metres (a lost aircraft)")
        job.add_argument("--cold-start", action="store_true",
                         help="GNSS jammed from the start and no pose at all: camera_ingest "
                              "projects frames pose-free and the ekf starts from two "
                              "agreeing relocalisations in the --mission index")
        job.add_argument("--kidnap", type=float, nargs=3, metavar=("T", "E", "N"),
                         help="T s into the bag, set the filter's position to the truth "
                              "moved by E, N metres (/ekf/set_pose: a kidnapped aircraft)")
        job.set_defaults(func=_cmd_replay)

    sim = sub.add_parser("simulate", help="simulate a flight over a DEM into an MCAP bag")
    sim.add_argument("-o", "--output", required=True, help="new bag directory")
    sim.add_argument("--dem", help="DEM file or 'synthetic:seed=N,size=N,gsd=X' (default: "
                     "the embedded Jacksboro DEM)")
    sim.add_argument("--landmark-gsd", dest="landmark_gsd", type=float,
                     help="GSD the replay's metamap and camera_ingest use [m/px] (default 20)")
    sim.add_argument("--dem-ce90", dest="dem_ce90", type=float, metavar="M",
                     help="the DEM's stated horizontal accuracy, the circular error at 90 %% "
                          "[m] (SRTM: 20), written into mission.yaml: the replay's ekf "
                          "then doubts the map by as much (default: the ekf's 10 m per axis)")
    sim.add_argument("--duration", type=float, help="flight time [s] (default 120)")
    sim.add_argument("--pattern", choices=["survey", "turns", "straight"])
    sim.add_argument("--speed", type=float, help="airspeed [m/s] (default 30)")
    sim.add_argument("--agl", type=float, help="height above the highest terrain [m]")
    sim.add_argument("--heading", type=float, help="initial heading [deg from East, CCW]")
    sim.add_argument("--start-east", dest="start_east", type=float, help="start E [m]")
    sim.add_argument("--start-north", dest="start_north", type=float, help="start N [m]")
    sim.add_argument("--wind", type=float, nargs=2, metavar=("E", "N"), help="wind [m/s]")
    sim.add_argument("--camera-rate", dest="camera_rate", type=float, help="frames/s")
    sim.add_argument("--camera-width", dest="camera_width", type=int)
    sim.add_argument("--camera-height", dest="camera_height", type=int)
    sim.add_argument("--camera-hfov", dest="camera_hfov", type=float, help="[deg]")
    sim.add_argument("--image-format", dest="image_format", choices=["jpeg", "rgb8", "mono8"])
    sim.add_argument("--imu-rate", dest="imu_rate", type=float, help="[Hz] (default 200)")
    sim.add_argument("--sun", type=float, nargs=2, metavar=("AZ", "EL"),
                     help="camera sun azimuth/elevation [deg] (default: the solar "
                          "position at the flight's time and place)")
    sim.add_argument("--gnss-denied-after", dest="gnss_denied_after", type=float,
                     help="GNSS lost from this time [s]")
    sim.add_argument("--gnss-denial", dest="gnss_denial", choices=["stop", "nofix"])
    sim.add_argument("--seed", type=int)
    sim.add_argument("--albedo", help="a real georeferenced orthoimage of the DEM's place, "
                     "draped over the terrain for the camera frames (landmarks stay DEM "
                     "renders)")
    sim.add_argument("--albedo-band", dest="albedo_band",
                     help="its band (1-based) as grey (default: bands 1-3 as RGB)")
    sim.add_argument("--albedo-shift", dest="albedo_shift", metavar="measured|none|E,N",
                     help="where the image is draped: at its georeference (none, the "
                          "default), shifted back by the offset its shading shows from the "
                          "DEM's (measured), or shifted by E,N metres")
    sim.add_argument("--start-time", dest="start_time", metavar="ISO8601",
                     help="bag time of the start, UTC (with --albedo: the image's "
                          "acquisition, so the landmarks get its sun)")
    sim.add_argument("--cloud-cover", dest="cloud_cover", type=float, metavar="FRACTION",
                     help="broken cloud over this fraction of the sky, in [0, 1) (default 0)")
    sim.add_argument("--cloud-base", dest="cloud_base", type=float, metavar="M",
                     help="its height above the terrain under the flight [m] (default 1500)")
    sim.add_argument("--cloud-size", dest="cloud_size", type=float, metavar="M",
                     help="typical cloud diameter [m] (default 1500)")
    sim.set_defaults(func=_cmd_simulate)

    prep = sub.add_parser("prepare", help="the mission index: every tile of the area "
                          "rendered under the flight's suns and reduced to landmark features, "
                          "built before flight on Dask")
    prep.add_argument("--dem", nargs="+", required=True, metavar="FILE",
                      help="DEM files, folders or globs (GeoTIFF, ESRI ASCII grid, SRTM .hgt)")
    prep.add_argument("--area", metavar="LAT,LON,LAT,LON",
                      help="two opposite corners of the mission area [deg] (default: the "
                           "DEMs' extent); its centre is the ENU origin")
    prep.add_argument("--gsd", type=float, required=True, help="landmark GSD [m/px]")
    prep.add_argument("--out", required=True, metavar="MISSION_DIR",
                      help="the index's directory (new, or the same request's to resume)")
    prep.add_argument("--suns", metavar="AZ/EL,...",
                      help="the suns to index [deg], e.g. 120/35,135/40")
    prep.add_argument("--time", metavar="ISO8601",
                      help="start of the flight window (UTC): the suns over it at the area's "
                           "centre")
    prep.add_argument("--hours", type=float, default=2.0,
                      help="length of the flight window [h] (default 2)")
    prep.add_argument("--sun-step", dest="sun_step", type=float,
                      help="largest angle between indexed suns [deg] (default: the landmark "
                           "renderer's max_sun_change in config/terrain_nav.yaml, 2)")
    prep.add_argument("--tile", type=int, default=1024, help="tile side [px] (default 1024)")
    prep.add_argument("--overlap", type=int, default=256,
                      help="overlap of neighbouring tiles [px]: any view up to this side lies "
                           "wholly in some tile (default 256)")
    prep.add_argument("--scheduler", metavar="ADDRESS",
                      help="an existing Dask scheduler (e.g. tcp://host:8786); its workers "
                           "need this package and the DEM and --out paths")
    prep.add_argument("--workers", type=int,
                      help="worker processes of the local Dask cluster (default: one per "
                           "core)")
    prep.add_argument("--overwrite", action="store_true",
                      help="replace another index found in --out")
    prep.set_defaults(func=_cmd_prepare)

    ev = sub.add_parser("evaluate", help="PVA / non-PVA block study with baselines "
                                         "(dissertation chapter 5) on a DEM")
    ev.add_argument("--dem", help="DEM file (default: the embedded Jacksboro DEM)")
    ev.add_argument("--gsd", default="native",
                    help="block GSD: 'native', a refinement like 'x2', or metres")
    ev.add_argument("--blocks", type=int, default=9, help="number of blocks (9, 36, 144)")
    ev.add_argument("--block-size", dest="block_size", type=int, default=256,
                    help="largest block side [px] (smaller if the DEM cannot hold them)")
    ev.add_argument("--sun-change", dest="sun_change", type=float, default=180.0,
                    help="azimuth change [deg] of the hard-case camera sun (0: skip it)")
    ev.add_argument("--false-match-rate", dest="false_match_rate", type=float, default=1e-3,
                    help="false-match rate the threshold is calibrated for")
    ev.add_argument("--out", help="output directory (default out/evaluate-<time>)")
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--quick", action="store_true",
                    help="smoke run: no changed-sun case, no SIFT, 12 rotation steps")
    ev.add_argument("--no-baselines", dest="no_baselines", action="store_true",
                    help="minutiae only")
    ev.add_argument("--lighting", default="shading",
                    help="extractor input: 'shading' (the shaded image) or 'compensated' "
                         "(terrain curvature estimated from it with each image's sun)")
    ev.add_argument("--no-creases", dest="no_creases", action="store_true",
                    help="match on minutiae alone, as the dissertation (no crease check, no "
                         "crease descriptor)")
    ev.add_argument("--no-ridges", dest="no_ridges", action="store_true",
                    help="no ridge check: small blocks are scored on their valleys alone")
    ev.add_argument("--heading-prior", dest="heading_prior", type=float, metavar="DEG",
                    help="the matcher searches rotations within +-DEG only, as in flight "
                         "where frames are north-up within the heading error (default: any "
                         "rotation; the baselines are unchanged)")
    ev.add_argument("--jobs", type=int, default=1,
                    help="processes for the block comparisons (same results; the reported "
                         "compare times are per comparison either way)")
    im = ev.add_argument_group(
        "real imagery", "with --image (and --dem) or --scenes: views cut from a real image "
        "localised in the landmark render of its DEM, with non-PVA controls and baselines")
    im.add_argument("--image", help="a georeferenced real image of the DEM's place")
    im.add_argument("--band", help="its band (1-based; default: the near-infrared band "
                    "where the file's band descriptions name one, else the mean of bands 1-3)")
    im.add_argument("--sun", metavar="AZ,EL", help="the image's sun [deg]")
    im.add_argument("--time", metavar="ISO8601",
                    help="the image's acquisition time (UTC), for its sun")
    im.add_argument("--scenes", help="YAML list of scenes (e.g. benchmarks/real_scenes.yaml)")
    im.add_argument("--data-dir", dest="data_dir",
                    help="folder the --scenes file names are relative to")
    im.add_argument("--sizes", default="64,128,256,512", help="view sides [px]")
    im.add_argument("--cases", type=int, default=20,
                    help="views per scene, size and heading condition")
    im.add_argument("--heading", choices=["unknown", "known", "both"], default="both")
    im.add_argument("--controls", type=int, default=2,
                    help="non-PVA regions of other places per view, each once (fewer when "
                         "they run out), and one far part of its own scene where the scene "
                         "holds one")
    im.add_argument("--region-factor", dest="region_factor", type=float, default=3.0,
                    help="side of the landmark region each view is localised in, in view "
                         "sides (default 3: the prior's error as large as the view; a "
                         "tracking filter's is a fraction of it: 1.5)")
    im.add_argument("--baselines", default="ncc,orb", help="of ncc, orb, sift")
    im.add_argument("--match-gsd", dest="match_gsd", default="dem",
                    help="GSD [m] at which scenes finer than it are matched (views and "
                         "regions area averaged, as camera_ingest resamples a camera); "
                         "'dem' (default): each scene's DEM cell; 'native': the scene's own")
    im.add_argument("--no-view-search", dest="no_view_search", action="store_true",
                    help="without the matcher's crease search of large views")
    im.add_argument("--threshold", type=float,
                    help="acceptance threshold (default the graph's match.threshold)")
    ev.set_defaults(func=_cmd_evaluate)
    return parser


class _Subparsers:
    """add_parser with the common options (--debug) on every command."""

    def __init__(self, action, parents):
        self._action, self._parents = action, parents

    def add_parser(self, name, **kwargs):
        return self._action.add_parser(name, parents=self._parents, **kwargs)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return _run(args)


if __name__ == "__main__":
    raise SystemExit(main())
