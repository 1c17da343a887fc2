"""What every terrain_nav node shares: QoS profiles, parameter declaration, the main() pattern.

Executor: :func:`run` spins a node with rclpy's default executor unless the node declared an
``executor`` parameter (:func:`declare_executor`) that asks for ``events``, rclpy's
experimental ``EventsExecutor``. The default executor rebuilds its wait set in Python for
every message, which at a 200 Hz IMU costs more CPU than the node's own work; the events
executor dispatches from C++ callbacks. It does not support guard conditions (no node here
uses one).
"""

from __future__ import annotations

import dataclasses
import difflib
import faulthandler
import functools
import importlib
import math
import os
import re
import sys
from collections.abc import Callable

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from tf2_msgs.msg import TFMessage

from ..core.camera.camera_mount import chained_rotation, mount_angles, mount_rotation
from ..executables import SUPERVISOR_VARIABLE
from . import conversions as cv

# Camera, IMU and other streams: best effort, newest wins (REP 2003).
SENSOR_QOS = qos_profile_sensor_data
# Data products every consumer must get (minutiae, fixes, odometry).
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
# Latched data (DEM tiles): a late joiner still receives the last message.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)


# /tf_static as tf2's static broadcasters publish it: every transform stays for late joiners.
TF_STATIC_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL,
                           history=HistoryPolicy.KEEP_LAST)

# diagnostic_msgs/DiagnosticStatus levels
DIAG_OK, DIAG_WARN, DIAG_ERROR = 0, 1, 2


def publish_diagnostics(node: Node, topic: str, period: float,
                        report: Callable[[], list[DiagnosticStatus]]):
    """Publish ``report()`` as a ``diagnostic_msgs/DiagnosticArray`` on ``topic`` every
    ``period`` s of wall time (a steady clock: reports also flow when sim time stands still,
    e.g. a paused bag). Returns the function that publishes one at once (an event that must
    not wait for the period)."""
    quiet = PublisherEventCallbacks(use_default_callbacks=False)
    pub = node.create_publisher(DiagnosticArray, topic, RELIABLE_QOS, event_callbacks=quiet)

    def tick():
        msg = DiagnosticArray(status=report())
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)

    node.create_timer(period, tick, clock=Clock(clock_type=ClockType.STEADY_TIME))
    return tick


def declare(node: Node, name: str, default, description: str, *, min_value=None,
            max_value=None, read_only: bool = False):
    """Declare a parameter with a description and an optional range; return its value.

    A whole number given for a float parameter (``rate: 30`` in a params file) is taken as
    that float: rclpy would refuse it, and the node would die, over a missing ``.0``."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    overrides = getattr(node, "_parameter_overrides", {})
    given = overrides.get(name)
    if isinstance(default, float) and given is not None and \
            given.type_ == Parameter.Type.INTEGER:
        overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))
    if min_value is not None or max_value is not None:
        lo = min_value if min_value is not None else -sys.float_info.max
        hi = max_value if max_value is not None else sys.float_info.max
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(
                from_value=int(max(lo, -2**63)), to_value=int(min(hi, 2**63 - 1)), step=0)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(lo), to_value=float(hi), step=0.0)]
    return node.declare_parameter(name, default, descriptor).value


def field_docs(cls) -> dict[str, str]:
    """First description line of each field in a numpydoc ``Parameters`` section."""
    docs, names = {}, []
    lines = (cls.__doc__ or "").splitlines()
    for i, line in enumerate(lines):
        match = re.match(r"^\s{4}([a-z_][a-z0-9_, ]*) : (.+)$", line)
        if match:
            names = [n.strip() for n in match.group(1).split(",")]
            text = lines[i + 1].strip() if i + 1 < len(lines) else ""
            for name in names:
                docs[name] = f"{text} ({match.group(2).strip()})"
    return docs


def declare_settings(node: Node, prefix: str, settings, ranges=None) -> None:
    """Declare one parameter per field of a settings dataclass, as ``prefix.field``.

    Float fields are declared finite (a NaN ``match.threshold`` silently gave no fixes,
    issue 22) and ``ranges`` maps a field to its ``(min, max)`` (None: open); rclpy refuses
    a value outside, from a params file at start-up or from a later change.
    """
    docs = field_docs(type(settings))
    ranges = ranges or {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if isinstance(value, bool | int | float | str):
            lo, hi = ranges.get(f.name, (None, None))
            if isinstance(value, float) and lo is None:
                lo = -sys.float_info.max
            declare(node, f"{prefix}.{f.name}", value, docs.get(f.name, f.name),
                    min_value=lo, max_value=hi)


def check_parameters_known(node: Node) -> None:
    """Raise ValueError naming every parameter given to ``node`` (params file, ``-p``) that
    it never declared: rclpy ignores those, so a misspelt ``match.thresold`` ran with the
    default threshold (issue 22). A node calls it as soon as it has declared its
    parameters, before any work (reading DEMs, loading kernels, creating a bag); :func:`run`
    calls it again once the node is built, for nodes that do not."""
    # rclpy keeps what it was given only here (no public accessor)
    given = getattr(node, "_parameter_overrides", {})
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if not unknown:
        return
    known = list(node.get_parameters_by_prefix(""))
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(name, known, n=1)
        hints.append(f"{name} (did you mean {close[0]}?)" if close else name)
    raise ValueError(f"{node.get_name()}: unknown parameter(s) {', '.join(hints)}: fix or "
                     "remove them in the params file")


def settings_from_parameters(node: Node, prefix: str, settings, overrides=None):
    """A settings dataclass rebuilt from the node's ``prefix.*`` parameters (+ overrides).

    Raises ValueError (from the dataclass's own validation) on an invalid combination.
    """
    values = {f.name: node.get_parameter(f"{prefix}.{f.name}").value
              for f in dataclasses.fields(settings)
              if node.has_parameter(f"{prefix}.{f.name}")}
    for param in overrides or []:
        if param.name.startswith(prefix + "."):
            values[param.name[len(prefix) + 1:]] = param.value
    return dataclasses.replace(settings, **values)


def contained(callback):
    """Decorator for a node's message callbacks: an unexpected exception on one message is
    logged (with its type and text, at most every 5 s) and counted in ``self.failures``; the
    node keeps serving the next messages instead of dying mid-flight."""

    @functools.wraps(callback)
    def wrapper(self, *args, **kwargs):
        try:
            return callback(self, *args, **kwargs)
        except Exception as err:  # noqa: BLE001 - the point is to survive anything
            failures = self.__dict__.setdefault("failures", {})
            failures[callback.__name__] = failures.get(callback.__name__, 0) + 1
            self.get_logger().error(
                f"{callback.__name__} failed on a message ({failures[callback.__name__]} so "
                f"far): {type(err).__name__}: {err}", throttle_duration_sec=5.0)
            return None

    return wrapper


def new_failures(node: Node) -> tuple[int, int]:
    """Callback failures counted by :func:`contained`: in all, and since the last call (for
    a diagnostics report)."""
    total = sum(node.__dict__.get("failures", {}).values())
    new = total - node.__dict__.get("_failures_reported", 0)
    node._failures_reported = total
    return total, new


# The executors a node can ask for with its ``executor`` parameter (see :func:`run`).
SINGLE_THREADED_EXECUTOR, EVENTS_EXECUTOR = "single_threaded", "events"
EXECUTORS = (SINGLE_THREADED_EXECUTOR, EVENTS_EXECUTOR)
# The EventsExecutor is spun in bounded steps: in rclpy 7.1 (Jazzy) an unbounded spin() or
# spin_once() busy-waits (a whole core while idle, measured); a bounded wait blocks properly.
_EVENTS_SPIN_STEP_S = 0.5


def declare_executor(node: Node, default: str = SINGLE_THREADED_EXECUTOR) -> str:
    """Declare the read-only ``executor`` parameter that :func:`run` honours; return it.

    Raises ValueError for a name not in :data:`EXECUTORS`.
    """
    kind = declare(node, "executor", default,
                   "single_threaded (rclpy's default executor) | events (rclpy.experimental."
                   "EventsExecutor: far less CPU per message)", read_only=True)
    if kind not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, not {kind!r}")
    return kind


def node_executor(node: Node) -> str:
    """The executor a node asked for (its ``executor`` parameter), else single_threaded."""
    if node.has_parameter("executor"):
        return node.get_parameter("executor").value
    return SINGLE_THREADED_EXECUTOR


def make_executor(node: Node, executor: str = SINGLE_THREADED_EXECUTOR):
    """A new executor of the named kind (:data:`EXECUTORS`) in ``node``'s context."""
    if executor == EVENTS_EXECUTOR:
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=node.context)
    if executor == SINGLE_THREADED_EXECUTOR:
        return SingleThreadedExecutor(context=node.context)
    raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, not {executor!r}")


def spin(node: Node, executor=SINGLE_THREADED_EXECUTOR) -> None:
    """Spin ``node`` until its context shuts down, with an executor or a kind of one
    (:data:`EXECUTORS`, made by :func:`make_executor`).

    Like ``rclpy.spin``, a shutdown from elsewhere (not Ctrl-C) ends it with
    ``ExternalShutdownException``. Pass the executor in, and keep it until the node is
    destroyed and rclpy shut down, as ``rclpy.spin``'s global executor lives: its SIGINT
    guard condition must not be freed while rclpy's signal thread may still trigger it.
    """
    runner = make_executor(node, executor) if isinstance(executor, str) else executor
    events = type(runner).__name__ == "EventsExecutor"
    step = _EVENTS_SPIN_STEP_S if events else None
    runner.add_node(node)
    try:
        while node.context.ok():
            try:
                runner.spin_once(timeout_sec=step)
            except RuntimeError:   # rclpy's RCLError
                if node.context.ok():
                    raise
                # Ctrl-C: rclpy's signal handler shuts the context down from its own
                # thread, and the executor building its wait set just then fails with
                # "the given context is not valid" (ros2/rclpy#402, ros2/ros2cli#854)
                raise ExternalShutdownException() from None
    finally:
        if events:
            # Before the node's entities are destroyed: the events executor unregisters the
            # middleware callbacks it set on them.
            runner.shutdown()
        else:
            # As rclpy.spin does (the executor itself goes with rclpy.shutdown). With
            # runner.shutdown() here a bag_recorder once died with SIGSEGV while stopping, in
            # a fresh-clone CI run; the cause is not pinned down, rclpy.spin's order never did.
            runner.remove_node(node)


def reject_all_changes(_params) -> SetParametersResult:
    """on_set_parameters callback for nodes whose parameters only apply at start-up."""
    return SetParametersResult(successful=False,
                               reason="parameters of this node apply at start-up only")


def message_class(msgtype: str):
    """The rclpy message class for ``pkg/msg/Name`` (as bags and graph queries name types)."""
    try:
        package, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ValueError, ImportError, AttributeError) as err:
        raise LookupError(f"message type {msgtype} is not available here: {err}") from err


def _stop_with_supervisor(node: Node) -> None:
    """Shut rclpy down once the process that started this node, by its
    :data:`SUPERVISOR_VARIABLE`, is no longer its parent (checked every second)."""
    supervisor = os.environ.get(SUPERVISOR_VARIABLE, "")
    if not supervisor.isdigit():
        return

    def check():
        if os.getppid() != int(supervisor):
            node.get_logger().error(f"the graph runner (pid {supervisor}) is gone: stopping")
            rclpy.try_shutdown(context=node.context)

    node.create_timer(1.0, check, clock=Clock(clock_type=ClockType.STEADY_TIME))


def run(node_factory: Callable[[], Node], args=None) -> int:
    """The Jazzy main() pattern: init, spin, clean shutdown on Ctrl-C or external shutdown.

    The node is spun by the executor its ``executor`` parameter names, if it declared one
    (:func:`declare_executor`), else by rclpy's default single-threaded executor. A node
    that ends on bad input it could only partly serve (a damaged bag) sets ``exit_code``.
    """
    # A crash in a C extension (rclpy, DDS) prints every thread's Python stack to stderr,
    # which the graph runner shows with the node's name.
    faulthandler.enable()
    node = executor = None
    code = 0
    try:
        rclpy.init(args=args)     # a bad node name or remapping fails here
    except Exception as err:
        print(f"fatal: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}",
              file=sys.stderr)
        return 1
    try:
        node = node_factory()
        check_parameters_known(node)
        _stop_with_supervisor(node)
        # held until rclpy is shut down (see spin): a metamap node once died with SIGSEGV
        # in destroy_node after Ctrl-C when the executor had already been freed
        executor = make_executor(node, node_executor(node))
        spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:  # report why a node dies: the graph runner shows the exit code
        print(f"fatal: {type(err).__name__}: {err}", file=sys.stderr)
        code = 1
    finally:
        if node is not None:
            code = code or getattr(node, "exit_code", 0)
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
        del executor
    return code


class CameraMount:
    """The camera's mount, body -> optical rotation: from ``/tf_static`` when it links
    ``base_frame`` to the camera's frame (the frame_id of its images and CameraInfo, through
    any static frames between, e.g. ``base_link -> camera_link -> camera_optical``), else
    the node's ``mount_rpy`` parameter.

    A robot description (robot_state_publisher, a static_transform_publisher) is where an
    integrator declares a camera's mount; the parameter is for a graph without one. A
    ``/tf_static`` mount that differs from a non-zero ``mount_rpy`` by more than
    :data:`MISMATCH_DEG` is logged once: the transform is used.
    """

    MISMATCH_DEG = 0.5

    def __init__(self, node: Node, base_frame: str, mount_rpy_deg):
        self.node, self.base_frame = node, base_frame
        self.mount_rpy = [float(v) for v in mount_rpy_deg]
        self.parameter = mount_rotation(*(math.radians(v) for v in self.mount_rpy))
        self.rotations: dict = {}
        self.used = ("mount_rpy", self.parameter)   # source, rotation of the last frame
        self._warned: set = set()
        node.create_subscription(TFMessage, "/tf_static", self.on_tf_static, TF_STATIC_QOS)

    def on_tf_static(self, msg) -> None:
        rotations, refused = cv.static_rotations(msg)
        self.rotations.update(rotations)
        for why in refused:
            self.node.get_logger().warning(f"/tf_static: {why}; left out")

    def rotation(self, camera_frame: str):
        """Body -> optical rotation for frames of ``camera_frame``."""
        found = chained_rotation(self.rotations, self.base_frame, camera_frame) \
            if camera_frame else None
        if found is None:
            self.used = ("mount_rpy", self.parameter)
            return self.parameter
        self.used = (f"/tf_static {self.base_frame} -> {camera_frame}", found)
        self._check_parameter(camera_frame, found)
        return found

    def _check_parameter(self, camera_frame: str, found) -> None:
        angle = np.degrees(np.arccos(np.clip((np.trace(found.T @ self.parameter) - 1) / 2,
                                             -1.0, 1.0)))
        if any(self.mount_rpy) and angle > self.MISMATCH_DEG and camera_frame not in \
                self._warned:
            self._warned.add(camera_frame)
            self.node.get_logger().warning(
                f"mount_rpy {self.mount_rpy} deg differs by {angle:.1f} deg from /tf_static's "
                f"{self.base_frame} -> {camera_frame}: using /tf_static's")

    def describe(self) -> str:
        """The last frame's mount and where it came from, for the diagnostics."""
        source, rotation = self.used
        roll, pitch, yaw = (math.degrees(a) for a in mount_angles(rotation))
        return f"{source}: roll {roll:.1f}, pitch {pitch:.1f}, yaw {yaw:.1f} deg"
