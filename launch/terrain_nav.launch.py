"""Launch the terrain_nav node graph on a normal ROS 2 Jazzy install (ros2 launch).

The node list is not repeated here: it is read from config/graph.yaml, the same file the
``terrain-nav graph`` runner uses, so both start the same nodes with the same parameters.

    ros2 launch terrain_nav_ros terrain_nav.launch.py [graph:=/path/graph.yaml] [use_sim_time:=true]
        [enable:=autopilot_bridge]     # nodes the graph file disables, comma-separated
        [namespace:=uav1]              # every node and topic under /uav1 (default: the file's)
"""

import os
import shutil
import tempfile

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    OpaqueFunction,
    RegisterEventHandler,
    SetEnvironmentVariable,
)
from launch.event_handlers import OnShutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from terrain_nav_ros.core.estimation.checkpoint import RUN_DIR_VARIABLE
from terrain_nav_ros.tools.graph_runner import (
    DDS_PROFILE_VARIABLE,
    RESPAWN_DELAY,
    TF_REMAPPINGS,
    load_graph,
    namespaced_params_files,
    normalise_namespace,
)


def graph_nodes(graph_path, use_sim_time=False, enable=(), namespace=None, run_dir=None):
    """launch_ros Node actions for every enabled node of a graph file (plus ``enable``), in
    ``namespace`` (default the file's; its params files rewritten into ``run_dir``)."""
    spec = load_graph(graph_path, enable)
    if namespace is not None:
        spec.namespace = normalise_namespace(namespace, "namespace:=")
    if spec.namespace and not run_dir:
        run_dir = tempfile.mkdtemp(prefix="terrain_nav_params_")
    params_files = [str(p) for p in namespaced_params_files(spec.params_files, spec.namespace,
                                                            run_dir)]
    tf = list(TF_REMAPPINGS.items()) if spec.namespace else []
    return [
        Node(package="terrain_nav_ros", executable=node.executable, name=node.name,
             namespace=spec.namespace, output="screen", respawn=node.respawn,
             respawn_delay=RESPAWN_DELAY,
             parameters=params_files + [{**node.parameters, "use_sim_time": use_sim_time}],
             remappings=tf + list(node.remappings.items()))
        for node in spec.nodes
    ]


def _from_arguments(context):
    graph = LaunchConfiguration("graph").perform(context)
    sim = LaunchConfiguration("use_sim_time").perform(context).lower() in ("1", "true")
    enable = [n.strip() for n in LaunchConfiguration("enable").perform(context).split(",")]
    enable = [n for n in enable if n]
    # the graph's Fast DDS profile, unless the environment names one (as the runner does)
    env = load_graph(graph, enable).environment()
    actions = [SetEnvironmentVariable(DDS_PROFILE_VARIABLE, env[DDS_PROFILE_VARIABLE])] \
        if env.get(DDS_PROFILE_VARIABLE) else []
    # the run's folder (the ekf's checkpoint, for a respawned ekf), removed at the end as
    # the runner's is: a later launch must not resume from this run's checkpoint
    run_dir = os.environ.get(RUN_DIR_VARIABLE)
    if not run_dir:
        run_dir = tempfile.mkdtemp(prefix="terrain_nav_run_")
        actions += [SetEnvironmentVariable(RUN_DIR_VARIABLE, run_dir),
                    RegisterEventHandler(OnShutdown(on_shutdown=lambda event, context:
                                                    shutil.rmtree(run_dir, True)))]
    namespace = LaunchConfiguration("namespace").perform(context) or None
    return actions + graph_nodes(graph, sim, enable, namespace, run_dir)


def generate_launch_description():
    default_graph = os.path.join(get_package_share_directory("terrain_nav_ros"), "config",
                                 "graph.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("graph", default_value=default_graph,
                              description="graph YAML listing the nodes"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (when replaying a bag)"),
        DeclareLaunchArgument("enable", default_value="",
                              description="comma-separated nodes that the graph file "
                                          "disables (e.g. autopilot_bridge) to start too"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of every node and topic (e.g. uav1; "
                                          "default the graph file's, else the root)"),
        OpaqueFunction(function=_from_arguments),
    ])
