"""The rclpy node adapters, one module per node (``executables.NODES`` names them).

Each adapter declares its parameters and topics, converts messages to arrays
(:mod:`.conversions`, the only place where messages meet numpy) and calls into
:mod:`terrain_nav_ros.core`; :mod:`.ros_common` holds what several nodes share.
"""
