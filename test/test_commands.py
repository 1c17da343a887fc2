"""The terrain-nav command on bad input (issue 22): one line saying what is wrong and what
to do, exit status 2, no traceback, nothing started; damaged bags called damaged, with a
non-zero exit. Every case runs the real command in a subprocess. Last, the CI subset of
``scripts/fault_cases.py`` (which shares its fault makers with these tests)."""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest


def _load_fault_cases():
    path = Path(__file__).resolve().parents[1] / "scripts" / "fault_cases.py"
    spec = importlib.util.spec_from_file_location("fault_cases", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


faults = _load_fault_cases()


def terrain_nav(*args, timeout=60) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in faults.terrain_nav(*args)], text=True,
                          capture_output=True, timeout=timeout)


def _one_line_error(proc, *words):
    """Exit 2 and a single stderr line holding ``words``."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def bag_dir(tmp_path_factory):
    """Holds ``whole``, a small zstd bag on /imu/data (several chunks), and its variants."""
    root = tmp_path_factory.mktemp("bags")
    faults.make_bag(root / "whole")
    return root


def _variant(bag_dir, name, change):
    bag = bag_dir / name
    return bag if bag.exists() else faults.damaged_copy(bag_dir / "whole", bag, change)


def _mission(bag_dir, name, text):
    bag = bag_dir / f"mission_{name}"
    return bag if bag.exists() else faults.with_mission(bag_dir / "whole", bag, text)


DAMAGE = {"cut": faults.cut_half, "corrupt": faults.corrupt_chunk, "no_metadata": None}


@pytest.mark.parametrize("name", ["cut", "corrupt", "no_metadata"])
def test_bag_info_calls_a_damaged_bag_damaged(bag_dir, name):
    proc = terrain_nav("bag", "info", _variant(bag_dir, name, DAMAGE[name]))
    assert proc.returncode == 1, proc.stdout + proc.stderr
    health = next(line for line in proc.stdout.splitlines() if line.startswith("Health:"))
    assert "DAMAGED" in health and {"cut": "cut short", "corrupt": "corrupt data",
                                    "no_metadata": "metadata.yaml"}[name] in health


def test_bag_info_of_a_whole_bag_and_of_no_bag(bag_dir, tmp_path):
    proc = terrain_nav("bag", "info", bag_dir / "whole")
    assert proc.returncode == 0 and "Health:     whole: 3000 messages" in proc.stdout
    _one_line_error(terrain_nav("bag", "info", tmp_path), "no .mcap file", "rosbag2")


def test_bag_play_of_a_corrupt_bag_plays_what_it_can_and_fails(bag_dir):
    proc = terrain_nav("bag", "play", _variant(bag_dir, "corrupt", faults.corrupt_chunk),
                       "--rate", 100)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "is DAMAGED: corrupt data" in proc.stderr and "stopped after" in proc.stderr


@pytest.mark.parametrize("case", ["empty_folder", "broken_mission", "missing_dem", "rate_0",
                                  "existing_out", "cold_start_without_mission",
                                  "cold_start_and_lost", "bad_dem_accuracy"])
def test_replay_checks_its_inputs_before_starting_the_graph(bag_dir, tmp_path, case):
    out = tmp_path / "out"
    bag, extra, words = {
        "empty_folder": (tmp_path, [], ["no .mcap file"]),
        "broken_mission": (_mission(bag_dir, "broken", "dem: [unclosed\n"), [],
                           ["mission.yaml is not valid YAML", "fix it"]),
        "missing_dem": (_mission(bag_dir, "dem", "dem: /no/such/dem.tif\n"), [],
                        ["/no/such/dem.tif: no such DEM file", "give a readable DEM"]),
        "bad_dem_accuracy": (_mission(bag_dir, "ce90", "dem_horizontal_ce90: -5\n"), [],
                             ["dem_horizontal_ce90", "got -5", "fix or remove it"]),
        "rate_0": (bag_dir / "whole", ["--rate", 0], ["--rate 0.0: must be > 0"]),
        "existing_out": (bag_dir / "whole", [], ["exists: choose another --out"]),
        "cold_start_without_mission": (bag_dir / "whole", ["--cold-start"],
                                       ["--cold-start needs the mission index",
                                        "--mission"]),
        "cold_start_and_lost": (bag_dir / "whole", ["--cold-start", "--mission", tmp_path,
                                                    "--lost", 0, 0],
                                ["either --cold-start", "not both"]),
    }[case]
    if case == "existing_out":
        (out / "outputs").mkdir(parents=True)
    _one_line_error(terrain_nav("replay", "--bag", bag, "--out", out, *extra), *words)
    assert not (out / "logs").exists(), "the graph was started"


def test_a_mission_s_dem_accuracy_sets_the_ekf_s_doubt_of_the_map():
    """mission.yaml's ``dem_horizontal_ce90`` (the DEM's data sheet, m at 90 %) becomes the
    replay's ekf ``init_map_bias_sigma`` per axis; without it the ekf keeps its default."""
    from terrain_nav_ros.tools.replay import _mission_parameters

    topics = {"/imu/data", "/gnss/fix"}
    given = _mission_parameters(topics, {"dem_horizontal_ce90": 20.0})["ekf"]
    assert given["init_map_bias_sigma"] == pytest.approx(20.0 / 2.146, rel=1e-3)
    assert "init_map_bias_sigma" not in _mission_parameters(topics, {})["ekf"]


def test_simulate_refuses_bad_options_and_a_truncated_dem(tmp_path):
    _one_line_error(terrain_nav("simulate", "-o", tmp_path / "a", "--duration", -5),
                    "--duration -5.0: must be > 0")
    dem = tmp_path / "cut.asc"
    dem.write_text(faults.ASC_HEADER.format(c=100, r=100) + "1 2 3 4\n")
    _one_line_error(terrain_nav("simulate", "-o", tmp_path / "b", "--dem", dem, timeout=30),
                    "truncated ESRI ASCII grid")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_simulate_says_what_the_dem_or_the_time_lacks_in_one_line(tmp_path):
    import numpy as np
    import rasterio
    from affine import Affine

    void = tmp_path / "void.tif"
    with rasterio.open(void, "w", driver="GTiff", width=64, height=64, count=1, dtype="int16",
                       crs="EPSG:32611", transform=Affine(30, 0, 4e5, 0, -30, 3.8e6),
                       nodata=-9999) as ds:
        ds.write(np.full((1, 64, 64), -9999, np.int16))
    _one_line_error(terrain_nav("simulate", "-o", tmp_path / "a", "--dem", void,
                                "--duration", 5), "no heights under the route")
    _one_line_error(terrain_nav("simulate", "-o", tmp_path / "b", "--duration", 5,
                                "--start-time", "2024-06-21T06:00:00Z"),
                    "night; give a daytime --start-time")
    garbage = tmp_path / "garbage.tif"
    with rasterio.open(garbage, "w", driver="GTiff", width=64, height=64, count=1,
                       dtype="float32", crs="EPSG:32611",
                       transform=Affine(30, 0, 4e5, 0, -30, 3.8e6)) as ds:
        ds.write(np.full((1, 64, 64), -1e30, np.float32))
    _one_line_error(terrain_nav("simulate", "-o", tmp_path / "c", "--dem", garbage,
                                "--duration", 5), "4096 of 4096 heights (100 %) are impossible")


def test_debug_shows_the_traceback(tmp_path):
    proc = terrain_nav("replay", "--bag", tmp_path, "--debug")
    assert proc.returncode == 2 and "Traceback" in proc.stderr


def _level_imu_bag(path: Path, seconds: float = 30.0) -> Path:
    """A bag of /imu/data at 100 Hz: level and still."""
    import numpy as np

    from terrain_nav_ros.tools import bags

    types = bags.typestore().types
    vector, no_covariance = types["geometry_msgs/msg/Vector3"], np.zeros(9)
    with bags.BagWriter(path) as writer:
        for k in range(int(seconds * 100)):
            ns = 10**18 + k * 10**7
            header = types["std_msgs/msg/Header"](
                stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                frame_id="base_link")
            imu = types["sensor_msgs/msg/Imu"](
                header=header, orientation=types["geometry_msgs/msg/Quaternion"](0, 0, 0, 1),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=vector(0.0, 0.0, 0.0),
                angular_velocity_covariance=no_covariance,
                linear_acceleration=vector(0.0, 0.0, 9.80665),
                linear_acceleration_covariance=no_covariance)
            writer.write_message("/imu/data", ns, imu, "sensor_msgs/msg/Imu")
    return path


def test_an_interrupted_replay_writes_its_report_marked_partial(bag_dir, tmp_path):
    """Ctrl-C during a replay: the graph stops, the report of what was replayed is written
    and says it is partial, no traceback (a graph of the ekf alone, which waits for a fix
    to start from: no odometry)."""
    graph = tmp_path / "graph.yaml"
    graph.write_text("nodes:\n  - name: ekf\n    executable: ekf\n")
    out = tmp_path / "out"
    proc = subprocess.Popen([str(a) for a in faults.terrain_nav(
        "replay", "--bag", _level_imu_bag(tmp_path / "imu"), "--out", out, "--config",
        graph)],
        text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if "nodes up" in line or "NODE DIED" in line:
            break
    proc.send_signal(signal.SIGINT)
    rest, _ = proc.communicate(timeout=60)
    text = "".join(seen) + rest
    assert proc.returncode == 130, text
    assert "Traceback" not in text
    report = (out / "report.txt").read_text()
    assert report.startswith(
        "PARTIAL REPORT: the replay was stopped (SIGINT) before the end of the bag")
    assert "NO ODOMETRY: the EKF published none; its last diagnostics: " in report


@pytest.mark.parametrize("case", [c for c in faults.cases() if c.ci], ids=lambda c: c.name)
def test_fault_cases_ci_subset_are_answered_well(case, tmp_path):
    verdict, detail = case.run(tmp_path)
    assert verdict == faults.GOOD, f"{case.fault}: {case.name}: {verdict}: {detail}"


@pytest.mark.parametrize("env, words", [
    ({"ROS_DOMAIN_ID": "300"}, "ROS_DOMAIN_ID=300: must be a whole number 0-232"),
    ({"ROS_DOMAIN_ID": "abc"}, "ROS_DOMAIN_ID=abc"),
    ({"ROS_DOMAIN_ID": "-1"}, "ROS_DOMAIN_ID=-1"),
    ({"RMW_IMPLEMENTATION": "rmw_nonexistent"}, "RMW_IMPLEMENTATION=rmw_nonexistent: not "
                                                "installed here"),
])
def test_a_ros_environment_no_node_could_start_in_is_one_line(env, words):
    """Else every node dies at start-up with rcl's message, or the runner with a
    traceback; the ROS-free commands do not care."""
    from terrain_nav_ros.tools.cli import _check_ros_environment
    from terrain_nav_ros.tools.errors import InputError

    with pytest.raises(InputError, match=re.escape(words)):
        _check_ros_environment(env)
    _check_ros_environment({"ROS_DOMAIN_ID": "42", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"})
    proc = subprocess.run([str(a) for a in faults.terrain_nav("graph", "--duration", 1)],
                          env={**os.environ, **env}, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and words in proc.stderr
