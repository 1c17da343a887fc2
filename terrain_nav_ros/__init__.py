"""terrain_nav: GPS-denied terrain-relative navigation by drainage-pattern minutiae.

``terrain_nav_ros.core`` holds the ROS-free algorithms, one subpackage per pipeline stage;
``terrain_nav_ros.nodes`` the thin rclpy adapters around them (one per node) and
``terrain_nav_ros.tools`` the ``terrain-nav`` command and what it runs. The README's Layout
section gives the stages' order.
"""
