"""ROS-free algorithm core: arrays in, arrays out.

Nothing under this package may import rclpy or any ROS message module; ``test_core_is_ros_free``
enforces that so the algorithms stay usable from notebooks, batch tools and other middlewares.
"""
