"""Shared node helpers: failing callbacks are contained, settings become parameters."""

import rclpy
from rclpy.node import Node

from terrain_nav_ros.core.minutiae import MinutiaParams
from terrain_nav_ros.ros_common import contained, declare_settings, settings_from_parameters


class _Flaky(Node):
    def __init__(self, context):
        super().__init__("flaky", context=context)
        self.seen = []

    @contained
    def on_message(self, value):
        if value < 0:
            raise ValueError("negative")
        self.seen.append(value)
        return value


def test_a_failing_callback_is_logged_and_counted_and_the_node_goes_on():
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = _Flaky(context)
        assert node.on_message(1) == 1
        assert node.on_message(-1) is None
        assert node.on_message(-2) is None
        assert node.on_message(3) == 3
        assert node.seen == [1, 3] and node.failures == {"on_message": 2}
        declare_settings(node, "minutia", MinutiaParams())
        assert node.get_parameter("minutia.block_size").value == 16
        assert settings_from_parameters(node, "minutia", MinutiaParams()) == MinutiaParams()
        node.destroy_node()
    finally:
        context.try_shutdown()
