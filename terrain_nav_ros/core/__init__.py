"""ROS-free algorithm core: arrays in, arrays out.

Nothing under this package may import rclpy or any ROS message module; ``test_core_is_ros_free``
enforces that so the algorithms stay usable from notebooks, batch tools and other middlewares.

One subpackage per stage, upstream first: ``terrain``, ``estimation``, ``camera``, ``render``,
``features``, ``matching``, ``sim``; a stage imports only those before it
(``test_import_direction`` holds the order the README's Layout section states).
"""
