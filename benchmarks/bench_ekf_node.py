"""CPU share of the ekf node process at a 200 Hz IMU, against an empty rclpy node's floor.

A simulated flight is published in real time (Imu at ``--rate`` Hz, baro at 10 Hz, a terrain
fix every 2 s) to the real ``ekf`` node in its own process; psutil reads the node's CPU time.
The same stream into a node that only subscribes gives rclpy's own per-message cost.

    .venv/bin/python benchmarks/bench_ekf_node.py [--seconds 20] [--rate 200]
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

from ros_helpers import SpinningNode, start_node, stop, wait_until  # noqa: E402

from terrain_nav_ros import conversions as cv  # noqa: E402
from terrain_nav_ros.core.baro import altitude_to_pressure  # noqa: E402
from terrain_nav_ros.core.ekf_params import EkfParams  # noqa: E402
from terrain_nav_ros.core.imu_sim import ImuErrorModel, simulate_imu  # noqa: E402
from terrain_nav_ros.core.strapdown import quat_to_euler  # noqa: E402
from terrain_nav_ros.core.trajectory_sim import simulate_trajectory, turning_flight  # noqa: E402

EMPTY_NODE = """
import sys, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu
from terrain_nav_msgs.msg import PvaFix
rclpy.init(args=sys.argv)
node = rclpy.create_node("ekf")
node.create_subscription(Imu, "/imu/data", lambda m: None,
                         QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
node.create_subscription(PvaFix, "/nav/pva_fix", lambda m: None, 10)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def measure(proc, seconds: float, rate: float) -> float:
    """Publish the flight to the node in ``proc`` in real time; return its CPU share (%)."""
    from sensor_msgs.msg import FluidPressure, Imu

    from terrain_nav_msgs.msg import PvaFix

    rng = np.random.default_rng(1)
    truth = simulate_trajectory(turning_flight(seconds + 2), rate_hz=rate)
    imu = simulate_imu(truth, ImuErrorModel.from_params(EkfParams()), rng)
    client = SpinningNode("bench_ekf_node")
    try:
        pub_imu = client.node.create_publisher(Imu, "/imu/data", 100)
        pub_fix = client.node.create_publisher(PvaFix, "/nav/pva_fix", 10)
        pub_baro = client.node.create_publisher(FluidPressure, "/baro/pressure", 10)
        if not wait_until(lambda: pub_imu.get_subscription_count() > 0, 30):
            raise RuntimeError("the node never subscribed to /imu/data")
        process = psutil.Process(proc.pid)
        time.sleep(1.0)
        cpu0, wall0 = process.cpu_times(), time.monotonic()
        for k in range(1, int(seconds * rate) + 1):
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
    finally:
        client.close()
    used = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
    return 100.0 * used / (wall1 - wall0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rate", type=float, default=200.0)
    args = parser.parse_args()
    truth = simulate_trajectory(turning_flight(2.0), rate_hz=args.rate)
    rpy = quat_to_euler(truth.quaternion[0])
    rows = []
    for label, params in (("ekf node, odometry 50 Hz", {}),
                          ("ekf node, odometry 20 Hz, NavSatFix 1 Hz",
                           {"odometry_rate": 20.0, "navsatfix_rate": 1.0})):
        proc = start_node("ekf", {
            "init_mode": "pose", "initial_position": list(map(float, truth.position[0])),
            "initial_velocity": list(map(float, truth.velocity[0])),
            "initial_rpy": list(map(float, rpy)), "origin_latitude": 36.5,
            "origin_longitude": -84.3, **params})
        try:
            rows.append((label, measure(proc, args.seconds, args.rate)))
        finally:
            stop(proc)
    empty = subprocess.Popen([sys.executable, "-c", EMPTY_NODE], start_new_session=True)
    try:
        rows.append(("empty rclpy node, same subscriptions", measure(empty, args.seconds,
                                                                     args.rate)))
    finally:
        stop(empty)
    print(f"CPU share of one core, {args.rate:.0f} Hz IMU, {args.seconds:.0f} s real time:")
    for label, share in rows:
        print(f"  {label:42s} {share:5.1f} %")


if __name__ == "__main__":
    main()
