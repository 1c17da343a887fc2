"""bag_recorder: subscribe to topics and write them to a rosbag2 MCAP bag.

Topics are discovered continuously (a topic that appears later is recorded from then on);
each subscription matches the QoS of the topic's publishers, as ``ros2 bag record`` does, so a
topic is only subscribed to once it has a publisher (one that only a subscriber has made known
would be recorded best effort and volatile, and lose messages and latched ones).
The bag is closed cleanly on Ctrl-C, SIGTERM or shutdown, so it is always readable.
"""

from __future__ import annotations

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from ..tools import bags
from .ros_common import check_parameters_known, declare, message_class, run

HIDDEN_TOPICS = ("/rosout", "/parameter_events")


class BagRecorder(Node):
    """Writes every message of the selected topics, stamped with its receive time."""

    def __init__(self):
        super().__init__("bag_recorder")
        self.output = declare(self, "output", "", "new bag directory to write")
        self.topics = [t for t in declare(self, "topics", [""],
                                          "topics to record; empty = all") if t]
        self.exclude = [t for t in declare(self, "exclude", [""], "topics never recorded") if t]
        period = declare(self, "discovery_period", 0.25, "how often to look for new topics [s]",
                         min_value=0.01)
        flush = declare(self, "flush_period", 1.0, "how often what was recorded is written "
                        "to the file, for a recorder that is killed [s]", min_value=0.05)
        compress = declare(self, "compress", True,
                           "zstd-compress the bag's chunks (an uncompressed flight bag "
                           "takes ~17 MB a minute)")
        check_parameters_known(self)  # before the bag is created
        if not self.output:
            raise ValueError("parameter 'output' is required")
        self.writer = bags.BagWriter(self.output, compress=compress)
        self.writer.open()
        self.count = 0
        self.subs = {}
        # on the steady clock, as the flush: under use_sim_time a ROS timer waits for the
        # first /clock, which the player sends with the bag's first message, so the first
        # answers came before the recorder had subscribed to them and were lost
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(period, self._discover, clock=steady)
        self.create_timer(flush, self.writer.flush, clock=steady)
        self.get_logger().info(f"recording to {self.output}")

    def _wanted(self, topic: str) -> bool:
        if topic in self.exclude or topic in self.subs:
            return False
        return topic in self.topics if self.topics else topic not in HIDDEN_TOPICS

    def _qos_for(self, topic: str) -> tuple[QoSProfile, bool, bool] | None:
        """The subscription's QoS and whether it is reliable and latched; None while the
        topic has no publisher to match."""
        infos = self.get_publishers_info_by_topic(topic)
        if not infos:
            return None
        reliable = all(
            i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        latched = all(
            i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        qos = QoSProfile(
            depth=1000,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
            else DurabilityPolicy.VOLATILE)
        return qos, reliable, latched

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if not self._wanted(topic) or not types:
                continue
            matched = self._qos_for(topic)
            if matched is None:   # known from a subscriber only: wait for its publisher
                continue
            qos, reliable, latched = matched
            msgtype = types[0]
            try:
                cls = message_class(msgtype)
                self.writer.add_topic(topic, msgtype, bags.qos_profile(reliable, latched))
            except (LookupError, bags.BagError) as err:
                self.get_logger().warning(f"not recording {topic}: {err}")
                self.exclude.append(topic)
                continue
            self.subs[topic] = self.create_subscription(
                cls, topic, lambda raw, t=topic: self._write(t, raw), qos, raw=True)
            self.get_logger().info(f"subscribed to {topic} [{msgtype}]")

    def _write(self, topic: str, raw: bytes) -> None:
        self.writer.write(topic, self.get_clock().now().nanoseconds, raw)
        self.count += 1

    def close(self) -> None:
        """Flush and close the bag (called by ros_common.run on shutdown)."""
        self.writer.close()
        self.get_logger().info(f"closed {self.output}: {self.count} messages")


def main(args=None):
    return run(BagRecorder, args)


if __name__ == "__main__":
    raise SystemExit(main())
