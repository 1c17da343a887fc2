"""CPU share of the ekf node process at a 200 Hz IMU, per executor, against an empty node.

A simulated flight is published in real time (Imu at ``--rate`` Hz, baro at 10 Hz, a terrain
fix every 2 s) to the real ``ekf`` node, started exactly as ``config/graph.yaml`` starts it
(graph_runner.node_command: its executable, the graph's params files), with a known initial
pose and origin on top; psutil reads the node process's CPU time (all its threads). The
same stream into a node that only subscribes gives rclpy's own per-message cost (the floor),
for each executor. Rows are interleaved over ``--repeat`` rounds; median and range printed.

    .venv/bin/python benchmarks/bench_ekf_node.py [--seconds 15] [--rate 200] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
os.environ.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

from ros_helpers import SpinningNode, stop, wait_until  # noqa: E402

from terrain_nav_ros.core.estimation.baro import altitude_to_pressure  # noqa: E402
from terrain_nav_ros.core.estimation.ekf_params import EkfParams  # noqa: E402
from terrain_nav_ros.core.estimation.strapdown import quat_to_euler  # noqa: E402
from terrain_nav_ros.core.sim.imu_sim import ImuErrorModel, simulate_imu  # noqa: E402
from terrain_nav_ros.core.sim.trajectory_sim import (  # noqa: E402
    simulate_trajectory,
    turning_flight,
)
from terrain_nav_ros.nodes import conversions as cv  # noqa: E402
from terrain_nav_ros.tools.graph_runner import load_graph, node_command  # noqa: E402

GRAPH = REPO / "config" / "graph.yaml"

# The ekf's subscriptions (IMU, baro, GNSS, fix), spun by ros_common.spin with the executor
# named in argv[1].
EMPTY_NODE = """
import sys, rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure, Imu, NavSatFix
from terrain_nav_msgs.msg import PvaFix
from terrain_nav_ros.nodes.ros_common import spin
rclpy.init(args=sys.argv)
node = rclpy.create_node("ekf")
best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
node.create_subscription(Imu, "/imu/data", lambda m: None, best_effort)
node.create_subscription(FluidPressure, "/baro/pressure", lambda m: None, best_effort)
node.create_subscription(NavSatFix, "/gnss/fix", lambda m: None, best_effort)
node.create_subscription(PvaFix, "/nav/pva_fix", lambda m: None, 10)
try:
    spin(node, sys.argv[1])
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""


def start_graph_ekf(parameters: dict) -> subprocess.Popen:
    """The ekf node as the graph starts it, with ``parameters`` on top."""
    graph = load_graph(GRAPH)
    spec = next(n for n in graph.nodes if n.executable == "ekf")
    return subprocess.Popen(node_command(spec, graph.params_files, parameters),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def start_empty(executor: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", EMPTY_NODE, executor],
                            start_new_session=True)


def measure(proc, seconds: float, rate: float) -> tuple[float, int, int | None]:
    """Publish the flight to the node in ``proc`` in real time.

    Returns its CPU share (%), the IMU messages published and those the node reports as
    received in its diagnostics (None for a node without diagnostics).
    """
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import FluidPressure, Imu

    from terrain_nav_msgs.msg import PvaFix
    from terrain_nav_ros.nodes.ros_common import RELIABLE_QOS

    rng = np.random.default_rng(1)
    truth = simulate_trajectory(turning_flight(seconds + 2), rate_hz=rate)
    imu = simulate_imu(truth, ImuErrorModel.from_params(EkfParams()), rng)
    client = SpinningNode("bench_ekf_node")
    diagnostics = []
    client.node.create_subscription(DiagnosticArray, "/nav/ekf/diagnostics",
                                    diagnostics.append, RELIABLE_QOS)

    def received() -> int | None:
        if not diagnostics:
            return None
        return int(cv.diagnostic_values(diagnostics[-1].status[0])[1]["imu_received"])

    sent = int(seconds * rate)
    try:
        pub_imu = client.node.create_publisher(Imu, "/imu/data", 100)
        pub_fix = client.node.create_publisher(PvaFix, "/nav/pva_fix", 10)
        pub_baro = client.node.create_publisher(FluidPressure, "/baro/pressure", 10)
        if not wait_until(lambda: pub_imu.get_subscription_count() > 0, 30):
            raise RuntimeError("the node never subscribed to /imu/data")
        process = psutil.Process(proc.pid)
        time.sleep(1.0)
        cpu0, wall0 = process.cpu_times(), time.monotonic()
        for k in range(1, sent + 1):
            delay = wall0 + k / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            header = cv.make_header(cv.sec_to_stamp(truth.t[k]), "base_link")
            pub_imu.publish(cv.sample_to_imu(header, imu.gyro[k], imu.accel[k]))
            if k % int(rate / 10) == 0:
                pressure = float(altitude_to_pressure(truth.position[k, 2]))
                pub_baro.publish(FluidPressure(header=header, fluid_pressure=pressure))
            if k % int(2 * rate) == 0:
                pub_fix.publish(cv.arrays_to_pva_fix(
                    cv.make_header(cv.sec_to_stamp(truth.t[k]), "map"), 1,
                    truth.position[k] + rng.normal(0, 20, 3), [0, 0, 0, 1],
                    np.diag([400.0] * 3 + [-1] * 3)))
        cpu1, wall1 = process.cpu_times(), time.monotonic()
        if diagnostics:     # one more report (1 s period) covers the last samples
            wait_until(lambda: received() >= sent, 3.0)
    finally:
        client.close()
    used = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
    return 100.0 * used / (wall1 - wall0), sent, received()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--rate", type=float, default=200.0)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    truth = simulate_trajectory(turning_flight(2.0), rate_hz=args.rate)
    known_start = {
        "init_mode": "pose", "initial_position": list(map(float, truth.position[0])),
        "initial_velocity": list(map(float, truth.velocity[0])),
        "initial_rpy": list(map(float, quat_to_euler(truth.quaternion[0]))),
        "origin_latitude": 36.5, "origin_longitude": -84.3}
    low_rate = {"odometry_rate": 20.0, "navsatfix_rate": 1.0}
    rows = {
        "ekf, as configured (events executor)": lambda: start_graph_ekf(known_start),
        "ekf, single_threaded executor (before)":
            lambda: start_graph_ekf({**known_start, "executor": "single_threaded"}),
        "ekf, events, odometry 20 Hz, NavSatFix 1 Hz":
            lambda: start_graph_ekf({**known_start, **low_rate}),
        "ekf, single_threaded, odometry 20 Hz, NavSatFix 1 Hz":
            lambda: start_graph_ekf({**known_start, **low_rate, "executor": "single_threaded"}),
        "empty node, same subscriptions, events": lambda: start_empty("events"),
        "empty node, same subscriptions, single_threaded":
            lambda: start_empty("single_threaded"),
    }
    shares = {label: [] for label in rows}
    delivered = {label: [] for label in rows}
    load_before = os.getloadavg()
    for _ in range(args.repeat):
        for label, start in rows.items():
            proc = start()
            try:
                share, sent, received = measure(proc, args.seconds, args.rate)
                shares[label].append(share)
                if received is not None:
                    delivered[label].append(f"{received}/{sent}")
            finally:
                stop(proc)
    load_after = os.getloadavg()
    print(f"CPU share of one core, {args.rate:.0f} Hz IMU, {args.seconds:.0f} s real time, "
          f"{args.repeat} rounds: median (min-max); load average {load_before[0]:.1f} -> "
          f"{load_after[0]:.1f} on {os.cpu_count()} cores")
    for label, values in shares.items():
        got = f"  IMU received {', '.join(delivered[label])}" if delivered[label] else ""
        print(f"  {label:52s} {np.median(values):5.1f} % ({min(values):.1f}-{max(values):.1f})"
              f"{got}")


if __name__ == "__main__":
    main()
