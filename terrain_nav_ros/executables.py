"""The package's executables: ROS node name -> ``module:function``.

One list, read by ``setup.py`` (console-script entry points installed under
``lib/terrain_nav_ros`` so ``ros2 run terrain_nav_ros <name>`` works), by the graph runner
and by ``launch/terrain_nav.launch.py``'s test. This module must stay import-free so that
``setup.py`` can read it before anything is installed.
"""

NODES = {
    "bag_player": "terrain_nav_ros.nodes.bag_player_node:main",
    "bag_recorder": "terrain_nav_ros.nodes.bag_recorder_node:main",
    "camera_ingest": "terrain_nav_ros.nodes.camera_ingest_node:main",
    "feature_extractor": "terrain_nav_ros.nodes.feature_extractor_node:main",
    "metamap": "terrain_nav_ros.nodes.metamap_node:main",
    "landmark_renderer": "terrain_nav_ros.nodes.landmark_renderer_node:main",
    "matcher": "terrain_nav_ros.nodes.matcher_node:main",
    "ekf": "terrain_nav_ros.nodes.ekf_node:main",
    "autopilot_bridge": "terrain_nav_ros.nodes.autopilot_bridge_node:main",
}

# Command-line tools that are not nodes.
TOOLS = {
    "terrain-nav": "terrain_nav_ros.tools.cli:main",
}

#: Set by the graph runner to its pid: a node it started stops when the runner is gone
#: (killed with SIGKILL, or died in C code), not to go on publishing into the next run.
SUPERVISOR_VARIABLE = "TERRAIN_NAV_SUPERVISOR_PID"
