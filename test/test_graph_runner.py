"""Graph runner: real node processes exchange messages; a killed node is reported and the
graph shuts down without leaving processes behind. The launch file names the same nodes."""

import importlib.util
import io
import os
import re
import signal
import sys
import threading
import time
import types
from pathlib import Path

import psutil
import pytest
import yaml
from ros_helpers import wait_until

from terrain_nav_ros.core.estimation.checkpoint import RUN_DIR_VARIABLE
from terrain_nav_ros.tools import bags
from terrain_nav_ros.tools.graph_runner import (
    GraphError,
    GraphRunner,
    load_graph,
    namespaced_params_files,
    node_command,
    normalise_namespace,
)

REPO = Path(__file__).resolve().parents[1]


def _slow_bag(path, seconds=30.0, hz=10):
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    with bags.BagWriter(path) as writer:
        for i in range(int(seconds * hz)):
            writer.write_message("/chatter", int(i * 1e9 / hz), String(data=f"m{i}"),
                                 "std_msgs/msg/String")


def _graph_file(tmp_path, bag, out_bag):
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"recorder": {"ros__parameters": {
        "topics": ["/chatter_remapped"]}}}))
    graph = tmp_path / "graph.yaml"
    graph.write_text(yaml.safe_dump({"params_files": ["params.yaml"], "nodes": [
        {"name": "recorder", "executable": "bag_recorder",
         "parameters": {"output": str(out_bag)}},
        {"name": "player", "executable": "bag_player",
         "parameters": {"bag": str(bag), "wait_for_topics": ["/chatter"]},
         "remappings": {"/chatter": "/chatter_remapped"}},
    ]}))
    return graph


def test_runner_starts_nodes_reports_a_killed_node_and_stops_cleanly(tmp_path):
    bag, out_bag = tmp_path / "in", tmp_path / "out"
    _slow_bag(bag)
    spec = load_graph(_graph_file(tmp_path, bag, out_bag))
    log = io.StringIO()
    runner = GraphRunner(spec, out=log, grace=5.0)
    runner.start()
    try:
        runner.wait_until_up(timeout=30)
        pids = {name: p.pid for name, p in runner.procs.items()}
        # Messages flow from the player to the recorder through the remapping.
        assert wait_until(lambda: "subscribed to /chatter_remapped" in log.getvalue(), 20), \
            log.getvalue()
        time.sleep(1.5)
        os.kill(pids["player"], signal.SIGKILL)
        status = runner.spin(duration=20)
    finally:
        codes = runner.shutdown()
    text = log.getvalue()
    assert status == 1
    assert "NODE DIED: player (signal SIGKILL)" in text
    assert "graph stopped; non-zero exit codes: player signal SIGKILL" in text
    assert codes["recorder"] == 0, text
    for pid in pids.values():
        assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == "zombie"
    recorded = [bags.decode(m).data for m in bags.read(out_bag)]
    assert recorded and recorded == [f"m{i}" for i in range(len(recorded))]


def _respawning_graph(tmp_path):
    bag, out_bag = tmp_path / "in", tmp_path / "out"
    _slow_bag(bag, seconds=120)
    graph = _graph_file(tmp_path, bag, out_bag)
    doc = yaml.safe_load(graph.read_text())
    doc["nodes"][1]["respawn"] = True   # the player
    graph.write_text(yaml.safe_dump(doc))
    return load_graph(graph)


def _kill_when_up(runner, name, log):
    """SIGKILL ``name`` once its current process is up; return the killed pid."""
    pid = runner.procs[name].pid
    assert wait_until(lambda: log.getvalue().count(f"started {name}") and
                      psutil.pid_exists(pid), 20)
    time.sleep(1.0)
    os.kill(pid, signal.SIGKILL)
    return pid


def test_a_respawned_node_that_dies_is_started_again(tmp_path):
    spec = _respawning_graph(tmp_path)
    log = io.StringIO()
    runner = GraphRunner(spec, out=log, log_dir=tmp_path / "logs")
    runner.start()
    try:
        runner.wait_until_up(timeout=30)
        killed = _kill_when_up(runner, "player", log)
        status = runner.spin(duration=6)
        assert runner.procs["player"].pid != killed and runner.procs["player"].poll() is None
        runner.sample_usage()
    finally:
        runner.shutdown()
    text = log.getvalue()
    assert status == 0, text
    assert "NODE DIED: player (signal SIGKILL); respawning it in 0.1 s" in text
    assert text.count("started player") == 2 and runner.respawns == {"player": 1}
    assert runner.died == []
    # both lives write to one log
    assert (tmp_path / "logs" / "player.log").read_text().count("playing 1 topics") == 2


def test_a_node_that_keeps_dying_is_given_up_on(tmp_path, monkeypatch):
    from terrain_nav_ros.tools import graph_runner

    monkeypatch.setattr(graph_runner, "RESPAWN_LIMIT", 2)
    spec = _respawning_graph(tmp_path)
    log = io.StringIO()
    runner = GraphRunner(spec, out=log)
    runner.start()
    try:
        runner.wait_until_up(timeout=30)
        _kill_when_up(runner, "player", log)
        assert runner.spin(duration=4) == 0
        _kill_when_up(runner, "player", log)
        status = runner.spin(duration=10)
    finally:
        runner.shutdown()
    text = log.getvalue()
    assert status == 1 and runner.died == ["player"], text
    assert "player died 2 times within 60 s: not respawning it again" in text
    assert "stopping the graph: required node(s) ['player'] died" in text


def test_runner_forwards_stop_request_and_nodes_exit_cleanly(tmp_path):
    bag, out_bag = tmp_path / "in", tmp_path / "out"
    _slow_bag(bag, seconds=60)
    runner = GraphRunner(load_graph(_graph_file(tmp_path, bag, out_bag)), out=io.StringIO())
    runner.start()
    try:
        runner.wait_until_up(timeout=30)
        threading.Timer(1.0, runner.request_stop).start()
        assert runner.spin(duration=30) == 0
    finally:
        codes = runner.shutdown()
    assert codes == {"recorder": 0, "player": 0}


def test_disabled_nodes_start_only_when_enabled_by_name(tmp_path):
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  - {name: a, executable: bag_player}\n"
                     "  - {name: b, executable: bag_recorder, enabled: false}\n")
    assert [n.name for n in load_graph(graph).nodes] == ["a"]
    assert [n.name for n in load_graph(graph, ["b"]).nodes] == ["a", "b"]
    with pytest.raises(GraphError, match="cannot enable c"):
        load_graph(graph, ["c"])
    # the shipped graph has the autopilot bridge, off by default
    shipped = REPO / "config" / "graph.yaml"
    assert "autopilot_bridge" not in [n.name for n in load_graph(shipped).nodes]
    assert "autopilot_bridge" in [n.name for n in load_graph(shipped, ["autopilot_bridge"]).nodes]


def test_invalid_graph_files_are_rejected_with_the_reason(tmp_path):
    bad = tmp_path / "g.yaml"
    bad.write_text("nodes:\n  - {name: x, executable: no_such_node}\n")
    with pytest.raises(GraphError, match="unknown executable no_such_node"):
        load_graph(bad)
    bad.write_text("params_files: [missing.yaml]\nnodes: []\n")
    with pytest.raises(GraphError, match="does not exist"):
        load_graph(bad)


@pytest.mark.parametrize("text, words", [
    # quoted, "false" is a string, and a string is true: the node would start
    ('nodes:\n  - {name: ekf, enabled: "false"}\n', "enabled 'false' must be true or false"),
    ("nodes:\n  - {name: ekf, respawn: 'no'}\n", "respawn 'no' must be true or false"),
    ("nodes:\n  - {name: ekf}\nnodes:\n  - {name: matcher}\n", "key 'nodes' given twice"),
    ("nodes: {ekf: {}}\n", "nodes must be a list of node entries"),
    ("nodes:\n  - ekf\n", "node entry 'ekf' must be a mapping"),
    ("nodes:\n  - {executable: ekf}\n", "name must be a ROS node name"),
    ("nodes:\n  - {name: my-ekf, executable: ekf}\n", "name must be a ROS node name"),
    ("nodes:\n  - {name: ekf, parameters: [a, b]}\n", "parameters ['a', 'b'] must be a map"),
    ("- ekf\n", "the top level must be a mapping"),
    ("namespce: uav1\nnodes:\n  - {name: ekf}\n", "unknown keys ['namespce']"),
    ("namespace: uav-1\nnodes:\n  - {name: ekf}\n", "'uav-1' is no ROS namespace"),
    ("namespace: [uav1]\nnodes:\n  - {name: ekf}\n", "namespace must be a ROS namespace"),
    ("params_files: [p.yaml]\nnodes:\n  - {name: ekf}\n", "'ekf_typo', which names no node"),
    ("params_files: [q.yaml]\nnodes:\n  - {name: ekf}\n", "key 'gravity' given twice"),
])
def test_graph_and_params_file_mistakes_are_named_not_guessed(tmp_path, text, words):
    (tmp_path / "p.yaml").write_text("ekf_typo:\n  ros__parameters: {gravity: 9.8}\n")
    (tmp_path / "q.yaml").write_text("ekf:\n  ros__parameters:\n    gravity: 9.8\n"
                                     "    gravity: 9.7\n")
    graph = tmp_path / "g.yaml"
    graph.write_text(text)
    with pytest.raises(GraphError, match=re.escape(words)):
        load_graph(graph)


def test_parameters_nodes_must_share_are_refused_when_they_differ(tmp_path):
    """The geoid height set for the metamap (its DEM heights made ellipsoidal) and not for
    the autopilot bridge would have PX4 get altitude_msl_m N metres off; an ekf origin other
    than the metamap's would put its GNSS and /nav/fix in another frame than the fixes. No
    node can see either, so the graph is refused when loaded, naming the values."""
    params = tmp_path / "p.yaml"
    graph = tmp_path / "g.yaml"
    graph.write_text("params_files: [p.yaml]\nnodes:\n  - {name: metamap}\n  - {name: ekf}\n"
                     "  - {name: bridge, executable: autopilot_bridge, enabled: false}\n")
    params.write_text("metamap:\n  ros__parameters: {geoid_undulation: -31.0}\n")
    assert len(load_graph(graph).nodes) == 2   # no bridge: nothing converts back
    with pytest.raises(GraphError, match=r"geoid_undulation .* metamap -31; bridge 0"):
        load_graph(graph, ["bridge"])
    params.write_text("/**:\n  ros__parameters: {geoid_undulation: -31.0}\n"
                      "ekf:\n  ros__parameters: {origin_latitude: 36.5}\n")
    assert len(load_graph(graph, ["bridge"]).nodes) == 3   # one value; the ekf's origin
    # is half given (a NaN longitude: the metamap's)
    params.write_text("metamap:\n  ros__parameters: {origin_latitude: 36.5, "
                      "origin_longitude: -84.2, origin_altitude: 500.0}\n"
                      "ekf:\n  ros__parameters: {origin_latitude: 36.5, "
                      "origin_longitude: -84.2}\n")
    with pytest.raises(GraphError, match=r"origin_latitude.* metamap 36.5, -84.2, 500; "
                                         r"ekf 36.5, -84.2, 0"):
        load_graph(graph)
    graph.write_text(graph.read_text().replace(
        "{name: ekf}", "{name: ekf, parameters: {origin_altitude: 500.0}}"))
    assert len(load_graph(graph).nodes) == 2
    # the shipped files agree
    assert load_graph(REPO / "config" / "graph.yaml", ["autopilot_bridge"])


def _stub_launch_modules(monkeypatch):
    """launch/launch_ros are not installable from PyPI: record what the launch file builds."""

    class Action:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    for name, attrs in {
        "launch": {"LaunchDescription": Action},
        "launch.actions": {"DeclareLaunchArgument": Action, "OpaqueFunction": Action,
                           "SetEnvironmentVariable": Action, "RegisterEventHandler": Action},
        "launch.event_handlers": {"OnShutdown": Action},
        "launch.substitutions": {"LaunchConfiguration": Action},
        "launch_ros": {},
        "launch_ros.actions": {"Node": Action},
    }.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)


def _launch_file(monkeypatch):
    """launch/terrain_nav.launch.py loaded as a module, over the stubs."""
    _stub_launch_modules(monkeypatch)
    spec = importlib.util.spec_from_file_location(
        "terrain_nav_launch", REPO / "launch" / "terrain_nav.launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_launch_file_starts_the_same_nodes_as_the_runner(tmp_path, monkeypatch):
    launch_file = _launch_file(monkeypatch)
    graphs = [_graph_file(tmp_path, tmp_path / "a", tmp_path / "b")]
    if (REPO / "config" / "graph.yaml").exists():
        graphs.append(REPO / "config" / "graph.yaml")
    for graph in graphs:
        spec = load_graph(graph)
        actions = launch_file.graph_nodes(str(graph), use_sim_time=True)
        assert [a.kwargs["name"] for a in actions] == [n.name for n in spec.nodes]
        for action, node in zip(actions, spec.nodes, strict=True):
            assert action.kwargs["executable"] == node.executable
            files, overrides = action.kwargs["parameters"][:-1], action.kwargs["parameters"][-1]
            assert files == [str(p) for p in spec.params_files]
            assert overrides == {**node.parameters, "use_sim_time": True}
            assert dict(action.kwargs["remappings"]) == node.remappings
            # The runner passes the same overrides and remappings on the command line.
            cmd = " ".join(node_command(node, spec.params_files))
            assert all(f"{k}:=" in cmd for k in node.parameters)
            assert all(f"{s}:={t}" in cmd for s, t in node.remappings.items())


def test_the_graphs_dds_profile_reaches_every_node_unless_one_is_set(tmp_path, monkeypatch):
    """config/graph.yaml names a Fast DDS profile (a shared-memory segment that holds raw
    camera frames): the runner's and the launch file's nodes get it, unless the environment
    names a profile already; a missing profile file is an error."""
    from terrain_nav_ros.tools.graph_runner import DDS_PROFILE_VARIABLE

    spec = load_graph(REPO / "config" / "graph.yaml")
    assert spec.dds_profile == (REPO / "config" / "fastdds.xml").resolve()
    assert "<segment_size>16777216</segment_size>" in spec.dds_profile.read_text()
    assert spec.environment({})[DDS_PROFILE_VARIABLE] == str(spec.dds_profile)
    assert spec.environment({DDS_PROFILE_VARIABLE: "/mine.xml"})[DDS_PROFILE_VARIABLE] \
        == "/mine.xml"
    bad = tmp_path / "g.yaml"
    bad.write_text("dds_profile: none.xml\nnodes:\n  - {name: a, executable: bag_player}\n")
    with pytest.raises(GraphError, match="dds_profile"):
        load_graph(bad)
    monkeypatch.delenv(DDS_PROFILE_VARIABLE, raising=False)
    launch_file = _launch_file(monkeypatch)

    class Context:
        pass

    values = {"graph": str(REPO / "config" / "graph.yaml"), "use_sim_time": "true",
              "enable": "", "namespace": ""}
    monkeypatch.setattr(launch_file, "LaunchConfiguration",
                        lambda name: types.SimpleNamespace(perform=lambda ctx: values[name]))
    monkeypatch.delenv(RUN_DIR_VARIABLE, raising=False)
    actions = launch_file._from_arguments(Context())
    assert actions[0].args == (DDS_PROFILE_VARIABLE, str(spec.dds_profile))
    # and a fresh folder for the run (the ekf's checkpoint), as the runner makes, removed
    # when the launch shuts down
    run_dir = Path(actions[1].args[1])
    assert actions[1].args[0] == RUN_DIR_VARIABLE and run_dir.is_dir()
    (run_dir / "ekf.checkpoint").write_text("x")
    actions[2].args[0].kwargs["on_shutdown"](None, Context())
    assert not run_dir.exists()
    assert [a.kwargs["name"] for a in actions[3:]] == [n.name for n in spec.nodes]



def test_nodes_stop_when_the_runner_is_killed(tmp_path):
    """A runner killed with SIGKILL (or dead in C code) cannot stop its nodes: they see it
    gone and stop themselves, not to go on publishing into the next run."""
    import subprocess

    graph = tmp_path / "graph.yaml"
    graph.write_text("nodes:\n  - {name: ekf, executable: ekf}\n")
    runner = subprocess.Popen([sys.executable, "-m", "terrain_nav_ros.tools.cli", "graph",
                               "--config", str(graph)], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    node_pid = None
    try:
        for line in runner.stdout:
            if "started ekf (pid" in line:
                node_pid = int(line.split("(pid ")[1].split(")")[0])
            if "nodes up" in line:
                break
        assert node_pid is not None
        runner.kill()
        runner.wait(timeout=10)
        node = psutil.Process(node_pid)
        node.wait(timeout=15)       # gone within its one-second check and its shutdown
    finally:
        runner.kill()
        if node_pid is not None and psutil.pid_exists(node_pid):
            os.kill(node_pid, signal.SIGKILL)


def test_a_namespace_is_normalised_and_the_params_files_are_rewritten_for_it(tmp_path):
    """ROS matches a params file's block to the node's full name: ``ekf:`` would not reach
    ``/uav1/ekf``, which would start on its defaults without a word."""
    assert normalise_namespace("uav1") == normalise_namespace("/uav1/") == "/uav1"
    assert normalise_namespace("fleet/uav_2") == "/fleet/uav_2"
    assert normalise_namespace("") == normalise_namespace("/") == ""
    for bad in ("uav-1", "1uav", "uav 1", "a//b"):
        with pytest.raises(GraphError, match="no ROS namespace"):
            normalise_namespace(bad)
    params = tmp_path / "p.yaml"
    params.write_text("ekf:\n  ros__parameters: {gravity: 9.79}\n"
                      "/matcher:\n  ros__parameters: {x: 1}\n"
                      "/**:\n  ros__parameters: {use_sim_time: false}\n")
    assert namespaced_params_files([params], "", tmp_path) == [params]
    [rewritten] = namespaced_params_files([params], "/uav1", tmp_path / "run")
    assert rewritten.parent == tmp_path / "run"
    assert yaml.safe_load(rewritten.read_text()) == {
        "/uav1/ekf": {"ros__parameters": {"gravity": 9.79}},
        "/uav1/matcher": {"ros__parameters": {"x": 1}},
        "/**": {"ros__parameters": {"use_sim_time": False}}}


def test_the_launch_file_puts_nodes_params_and_tf_in_the_namespace(tmp_path, monkeypatch):
    launch_file = _launch_file(monkeypatch)
    graph = REPO / "config" / "graph.yaml"
    actions = launch_file.graph_nodes(str(graph), namespace="uav1", run_dir=tmp_path)
    assert actions and all(a.kwargs["namespace"] == "/uav1" for a in actions)
    for action in actions:
        *files, _ = action.kwargs["parameters"]
        blocks = {key for f in files for key in yaml.safe_load(Path(f).read_text())}
        assert f"/uav1/{action.kwargs['name']}" in blocks
        assert all(Path(f).parent == tmp_path for f in files)
        assert ("/tf", "tf") in action.kwargs["remappings"]
    # without one, the root, the files as they are and /tf as it is
    actions = launch_file.graph_nodes(str(graph))
    assert all(a.kwargs["namespace"] == "" for a in actions)
    assert all(("/tf", "tf") not in a.kwargs["remappings"] for a in actions)


def test_a_graph_in_a_namespace_takes_its_parameters_and_topics_there(tmp_path):
    """A second aircraft's graph (``--namespace uav1``): the real ekf node comes up as
    /uav1/ekf with its params file's values, publishing /uav1/nav/odometry and /uav1/tf,
    and nothing at the root."""
    from rcl_interfaces.srv import GetParameters
    from ros_helpers import SpinningNode, call_service

    (tmp_path / "p.yaml").write_text("ekf:\n  ros__parameters: {base_frame: uav1_base}\n")
    graph = tmp_path / "graph.yaml"
    graph.write_text("params_files: [p.yaml]\nnamespace: uav1\n"
                     "nodes:\n  - {name: ekf, executable: ekf}\n")
    log = io.StringIO()
    runner = GraphRunner(load_graph(graph), out=log, grace=5.0)
    probe = SpinningNode("namespace_probe")
    runner.start()
    try:
        runner.wait_until_up(timeout=30)
        answer = call_service(probe, GetParameters, "/uav1/ekf/get_parameters",
                              GetParameters.Request(names=["base_frame"]))
        assert [v.string_value for v in answer.values] == ["uav1_base"]

        def published():
            return {t for t, _ in probe.node.get_publisher_names_and_types_by_node(
                "ekf", "/uav1")}
        assert wait_until(lambda: {"/uav1/nav/odometry", "/uav1/tf",
                                   "/uav1/nav/ekf/diagnostics"} <= published(), 10), published()
        assert not {t for t in published() if not t.startswith("/uav1/")} - {"/rosout",
                                                                             "/parameter_events"}
    finally:
        probe.close()
        runner.shutdown()
