"""``terrain-nav``: the command line of terrain_nav (graph runner, bag tools, jobs).

Run ``terrain-nav --help`` or ``terrain-nav <command> --help``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_GRAPH = REPO / "config" / "graph.yaml"


def _cmd_graph(args) -> int:
    from .graph_runner import GraphError, load_graph, run_graph

    try:
        spec = load_graph(args.config)
    except GraphError as err:
        print(f"terrain-nav graph: {err}", file=sys.stderr)
        return 2
    if args.only:
        spec.nodes = [n for n in spec.nodes if n.name in args.only]
    extra = {"use_sim_time": True} if args.use_sim_time else {}
    return run_graph(spec, extra_parameters=extra, duration=args.duration,
                     until_exit=args.until_exit, log_dir=args.log_dir)


def _exec_node(executable: str, params: dict) -> int:
    from .graph_runner import NodeSpec, node_command

    cmd = node_command(NodeSpec(executable, executable, parameters=params), None)
    os.execv(cmd[0], cmd)
    return 1  # not reached


def _cmd_bag_info(args) -> int:
    from . import bags

    try:
        print(bags.info(args.bag))
    except bags.BagError as err:
        print(f"terrain-nav bag info: {err}", file=sys.stderr)
        return 1
    return 0


def _cmd_bag_play(args) -> int:
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
    params = {"output": str(Path(args.output).resolve())}
    if args.topics:
        params["topics"] = args.topics
    if args.exclude:
        params["exclude"] = args.exclude
    return _exec_node("bag_recorder", params)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="terrain-nav", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    graph = sub.add_parser("graph", help="run the node graph, one process per node")
    graph.add_argument("--config", default=DEFAULT_GRAPH, type=Path,
                       help="graph YAML (default: config/graph.yaml)")
    graph.add_argument("--only", nargs="+", help="run only these nodes")
    graph.add_argument("--use-sim-time", action="store_true",
                       help="set use_sim_time on every node (when a bag publishes /clock)")
    graph.add_argument("--duration", type=float, help="stop after this many seconds")
    graph.add_argument("--until-exit", metavar="NODE",
                       help="stop the graph when this node exits (e.g. a bag player)")
    graph.add_argument("--log-dir", type=Path, help="also write each node's output here")
    graph.set_defaults(func=_cmd_graph)

    bag = sub.add_parser("bag", help="rosbag2 MCAP tools (info, play, record)")
    bag_sub = bag.add_subparsers(dest="bag_command", required=True)
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
    record.set_defaults(func=_cmd_bag_record)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
