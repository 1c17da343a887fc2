"""bag_player: publish a rosbag2 MCAP bag's messages into the graph with their original timing.

The PyPI ROS 2 wheels have no rosbag2_py, so this node plays bags with ``rosbags``:
raw CDR bytes are published unchanged, ``/clock`` is published for ``use_sim_time`` nodes,
and topics can be selected and remapped. With ``exit_when_done`` the process exits 0 after
the last message, which the graph runner treats as a normal end.
"""

from __future__ import annotations

import threading
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from ..tools import bags
from .conversions import ns_to_stamp
from .ros_common import check_parameters_known, declare, message_class, run


def parse_remaps(entries: list[str]) -> dict[str, str]:
    """['/a:=/b', ...] -> {'/a': '/b'}; raises ValueError on a malformed entry."""
    remaps = {}
    for entry in entries:
        source, sep, target = entry.partition(":=")
        if not sep or not source or not target:
            raise ValueError(f"remap entry '{entry}' is not of the form /from:=/to")
        remaps[source] = target
    return remaps


class BagPlayer(Node):
    """Publishes a bag's messages on their (remapped) topics, paced by their timestamps."""

    def __init__(self):
        super().__init__("bag_player")
        self.bag = declare(self, "bag", "", "rosbag2 bag directory (or .mcap file) to play")
        self.rate = declare(self, "rate", 1.0, "playback speed factor (2.0 = twice as fast)",
                            min_value=1e-3, max_value=1e3)
        topics = declare(self, "topics", [""], "topics to play; empty = all")
        remaps = declare(self, "remap", [""], "topic remappings, each '/from:=/to'")
        self.publish_clock = declare(self, "publish_clock", True,
                                     "publish /clock with the bag time for use_sim_time nodes")
        self.wait_for_topics = [t for t in declare(
            self, "wait_for_topics", [""],
            "topics that must have a subscriber before playback starts") if t]
        self.wait_for_nodes = [n for n in declare(
            self, "wait_for_nodes", [""],
            "nodes that must have subscribed to their inputs before playback starts (the "
            "graph's nodes subscribe once their kernels are loaded)") if n]
        self.wait_timeout = declare(self, "wait_timeout", 10.0,
                                    "longest wait for those subscribers and nodes [s]",
                                    min_value=0.0)
        self.start_delay = declare(self, "start_delay", 0.0,
                                   "pause before the first message [s]", min_value=0.0)
        self.exit_when_done = declare(self, "exit_when_done", True,
                                      "shut the process down after the last message")
        check_parameters_known(self)  # before anything is played
        if not self.bag:
            raise ValueError("parameter 'bag' is required")
        self.topics = [t for t in topics if t]
        self.remaps = parse_remaps([r for r in remaps if r])
        self.publishers_by_topic = {}
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.played = 0
        self.exit_code = 0       # 1 when the bag is damaged: what played is not all of it
        self.done = threading.Event()
        self._create_publishers()
        self._thread = threading.Thread(target=self._play, daemon=True)
        self._thread.start()

    def _create_publishers(self) -> None:
        if bags.is_damaged(self.bag):
            self.exit_code = 1
            self.get_logger().error(f"{self.bag} is damaged (cut short or no metadata.yaml): "
                                    "playing the messages that can be salvaged")
        for info in bags.topics(self.bag):
            if self.topics and info.topic not in self.topics:
                continue
            try:
                cls = message_class(info.msgtype)
            except LookupError as err:
                self.get_logger().warning(f"skipping {info.topic}: {err}")
                continue
            qos = QoSProfile(
                depth=100,
                reliability=ReliabilityPolicy.RELIABLE if info.reliable
                else ReliabilityPolicy.BEST_EFFORT,
                durability=DurabilityPolicy.TRANSIENT_LOCAL if info.transient_local
                else DurabilityPolicy.VOLATILE)
            name = self.remaps.get(info.topic, info.topic)
            self.publishers_by_topic[info.topic] = self.create_publisher(cls, name, qos)
        self.get_logger().info(
            f"playing {len(self.publishers_by_topic)} topics from {self.bag} at x{self.rate}")

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.wait_timeout
        for topic in self.wait_for_topics:
            pub = self.publishers_by_topic.get(topic)
            if pub is None:
                self.get_logger().warning(f"wait_for_topics: {topic} is not in the bag")
                continue
            self._wait(lambda pub=pub: pub.get_subscription_count() > 0, deadline,
                       f"no subscriber on {topic}")
        for name in self.wait_for_nodes:
            self._wait(lambda name=name: self._subscribed(name), deadline,
                       f"{name} has not subscribed to its inputs")

    def _wait(self, ready, deadline: float, missing: str) -> None:
        """Until ``ready()`` or the deadline; then, if still not ready, say ``missing``."""
        while not ready() and time.monotonic() < deadline:
            time.sleep(0.05)
        if not ready():
            self.get_logger().warning(f"{missing} after {self.wait_timeout} s; playing anyway")

    def _subscribed(self, name: str) -> bool:
        """Whether node ``name`` subscribes to a topic of its own (not the clock or the
        parameter events every node may have from its start)."""
        if name not in self.get_node_names():
            return False
        try:
            topics = self.get_subscriber_names_and_types_by_node(name, "/")
        except RuntimeError:   # rclpy's "nonexistent node": it left the graph meanwhile
            return False
        return any(t not in ("/clock", "/parameter_events") for t, _ in topics)

    def _play(self) -> None:
        try:
            self._wait_for_subscribers()
            time.sleep(self.start_delay)
            wall0 = bag0 = None
            for msg in bags.read(self.bag, self.publishers_by_topic):
                if not rclpy.ok():
                    return
                if wall0 is None:
                    wall0, bag0 = time.monotonic(), msg.timestamp_ns
                delay = wall0 + (msg.timestamp_ns - bag0) * 1e-9 / self.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if self.publish_clock:
                    self.clock_pub.publish(Clock(clock=ns_to_stamp(msg.timestamp_ns)))
                self.publishers_by_topic[msg.topic].publish(msg.rawdata)
                self.played += 1
            self.get_logger().info(f"finished: {self.played} messages played")
        except bags.BagError as err:
            self.exit_code = 1
            self.get_logger().error(f"stopped after {self.played} messages: {err}")
        except Exception:
            if self.context.ok():
                raise
            # Ctrl-C shut the context down while a message was on its way: nothing to say
        finally:
            self.done.set()
            if self.exit_when_done and rclpy.ok():
                time.sleep(0.5)  # let reliable subscribers fetch the last samples
                rclpy.try_shutdown()


def main(args=None):
    return run(BagPlayer, args)


if __name__ == "__main__":
    raise SystemExit(main())
