"""Shared node helpers: failing callbacks are contained, settings become parameters, a node
is spun by the executor it asks for."""

import math
import threading

import pytest
import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from ros_helpers import start_node, wait_until

from terrain_nav_ros.core.features.creases import CreaseParams
from terrain_nav_ros.core.features.minutiae import MinutiaParams
from terrain_nav_ros.core.matching.params import MatchParams
from terrain_nav_ros.nodes.ros_common import (
    check_parameters_known,
    contained,
    declare_executor,
    declare_settings,
    node_executor,
    settings_from_parameters,
    spin,
)


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


class _Ticking(Node):
    """Records which executor runs its timer callbacks."""

    def __init__(self, context, executor=None):
        super().__init__("ticking", context=context)
        if executor is not None:
            declare_executor(self, executor)
        self.ran_by = []
        self.create_timer(0.01, lambda: self.ran_by.append(type(self.executor).__name__))


@pytest.mark.parametrize("asked, runner", [(None, "SingleThreadedExecutor"),
                                           ("single_threaded", "SingleThreadedExecutor"),
                                           ("events", "EventsExecutor")])
def test_a_node_is_spun_by_the_executor_it_asks_for_until_shutdown(asked, runner):
    context = rclpy.Context()
    rclpy.init(context=context)
    node = _Ticking(context, asked)
    kind = node_executor(node)
    ended = []

    def spin_until_shutdown():
        try:
            spin(node, kind)
        except ExternalShutdownException:   # what rclpy.spin raises too; run() expects it
            ended.append("shutdown")

    thread = threading.Thread(target=spin_until_shutdown, daemon=True)
    try:
        thread.start()
        assert wait_until(lambda: len(node.ran_by) >= 3, 5.0), "the timer never ran"
    finally:
        context.try_shutdown()
        thread.join(timeout=5.0)
    assert not thread.is_alive() and ended == ["shutdown"], "spin did not end at shutdown"
    assert kind == (asked or "single_threaded")
    assert set(node.ran_by) == {runner}
    node.destroy_node()


class _RacingExecutor(SingleThreadedExecutor):
    """Fails to build its wait set as rclpy does when Ctrl-C's handler shuts the context
    down from its own thread at that moment (``shut_down``), or with the context still
    valid (a real error)."""

    def __init__(self, context, shut_down: bool):
        super().__init__(context=context)
        self.shut_down = shut_down

    def spin_once(self, timeout_sec=None):
        if self.shut_down:
            self._context.try_shutdown()
        raise RCLError("failed to initialize wait set: the given context is not valid")


def test_a_wait_set_error_at_ctrl_c_ends_spin_as_a_shutdown():
    """The node then exits 0 like any Ctrl-C (an ekf once exited 1 with "fatal: RCLError"
    under load); the same error while the context is valid is not swallowed."""
    for shut_down, expected in [(True, ExternalShutdownException), (False, RCLError)]:
        context = rclpy.Context()
        rclpy.init(context=context)
        node = Node("racing", context=context)
        try:
            with pytest.raises(expected):
                spin(node, _RacingExecutor(context, shut_down))
        finally:
            node.destroy_node()
            context.try_shutdown()


def test_an_unknown_executor_is_refused():
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = Node("bad_executor", context=context,
                    parameter_overrides=[Parameter("executor", value="multi")])
        with pytest.raises(ValueError, match="executor must be one of"):
            declare_executor(node, "events")
        with pytest.raises(ValueError, match="executor must be one of"):
            spin(node, "multi")
        node.destroy_node()
    finally:
        context.try_shutdown()


def _settings_node(context, **given):
    return Node("settings", context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in given.items()])


def test_unknown_parameters_are_an_error_naming_them():
    """rclpy ignores a parameter no one declared: a misspelt match.thresold ran with the
    default threshold (issue 22)."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = _settings_node(context, **{"match.thresold": 4.0, "match.threshold": 4.0,
                                          "zzz": 1})
        declare_settings(node, "match", MatchParams(), MatchParams.FIX_RANGES)
        with pytest.raises(ValueError, match=r"settings: unknown parameter\(s\) "
                           r"match.thresold \(did you mean match.threshold\?\), zzz: fix"):
            check_parameters_known(node)
        node.destroy_node()
        node = _settings_node(context, **{"match.threshold": 4.0})
        declare_settings(node, "match", MatchParams(), MatchParams.FIX_RANGES)
        check_parameters_known(node)
        node.destroy_node()
    finally:
        context.try_shutdown()


def test_a_whole_number_for_a_float_parameter_is_that_float():
    """``threshold: 9`` in a params file is 9.0, not a node that dies at start-up; an int
    parameter given a float stays refused."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = _settings_node(context, **{"match.threshold": 9, "match.k_query": 4})
        declare_settings(node, "match", MatchParams(), MatchParams.FIX_RANGES)
        assert node.get_parameter("match.threshold").value == 9.0
        assert isinstance(node.get_parameter("match.threshold").value, float)
        node.destroy_node()
        node = _settings_node(context, **{"match.k_query": 4.5})
        with pytest.raises(rclpy.exceptions.InvalidParameterTypeException):
            declare_settings(node, "match", MatchParams(), MatchParams.FIX_RANGES)
        node.destroy_node()
    finally:
        context.try_shutdown()


@pytest.mark.parametrize("prefix,settings,name,value", [
    ("match", MatchParams(), "threshold", math.nan),
    ("match", MatchParams(), "threshold", -1.0),
    ("match", MatchParams(), "pos_tol", 0.0),
    ("match", MatchParams(), "k_query", 0),
    ("match", MatchParams(), "search_scale", 0.7),  # newer fields: ranges from the core
    ("match", MatchParams(), "crease_search_proposals", 0),
    ("crease", CreaseParams(), "sigma", math.inf),
])
def test_nan_and_out_of_range_settings_are_refused(prefix, settings, name, value):
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = _settings_node(context, **{f"{prefix}.{name}": value})
        ranges = MatchParams.FIX_RANGES if prefix == "match" else None
        with pytest.raises(InvalidParameterValueException, match=f"{prefix}.{name}"):
            declare_settings(node, prefix, settings, ranges)
        node.destroy_node()
    finally:
        context.try_shutdown()


def test_a_node_given_a_misspelt_parameter_stops_with_one_line(tmp_path):
    params = tmp_path / "ekf.yaml"
    params.write_text("ekf:\n  ros__parameters:\n    time_jump_reste: 2.0\n")
    proc = start_node("ekf", None, "--params-file", str(params))
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    assert ("fatal: ValueError: ekf: unknown parameter(s) time_jump_reste (did you mean "
            "time_jump_reset?)") in out
    assert "Traceback" not in out


@pytest.mark.parametrize("executable,params,misspelt,hint,untouched", [
    # the DEM named is never read: its absence is not what the node says
    ("metamap", {"dem_files": ["{tmp}/no_such_dem.tif"]}, "gdsd", "gsd", None),
    # the matcher is not built: its bad candidates setting is not what the node says
    ("matcher", {"match.candidates": "kd"}, "match.thresold", "match.threshold", None),
    # the bag is not created
    ("bag_recorder", {"output": "{tmp}/bag"}, "topcis", "topics", "bag"),
])
def test_unknown_parameters_are_refused_before_the_node_does_any_work(
        tmp_path, executable, params, misspelt, hint, untouched):
    given = {k: [v.format(tmp=tmp_path) for v in v] if isinstance(v, list)
             else v.format(tmp=tmp_path) for k, v in params.items()}
    given[misspelt] = 1.0
    proc = start_node(executable, given)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    assert (f"fatal: ValueError: {executable}: unknown parameter(s) {misspelt} (did you "
            f"mean {hint}?)") in out
    assert "no such DEM" not in out and "candidates" not in out and "Traceback" not in out
    assert untouched is None or not (tmp_path / untouched).exists()
