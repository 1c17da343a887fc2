"""terrain_nav: GPS-denied terrain-relative navigation by drainage-pattern minutiae.

``terrain_nav_ros.core`` holds the ROS-free algorithms; the ``*_node`` modules are thin
rclpy adapters around them.
"""
