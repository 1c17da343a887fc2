"""Helpers for process-level ROS tests: an in-test node spinning in a thread, node processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

VENV_BIN = Path(sys.executable).parent


class SpinningNode:
    """An rclpy node in its own context, spun by a background thread."""

    def __init__(self, name: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - context shut down while spinning
                return

    def close(self):
        self.context.try_shutdown()
        self._thread.join(timeout=2)
        self.node.destroy_node()


def start_node(executable: str, params: dict | None = None, *extra: str) -> subprocess.Popen:
    """Start one of the package's executables as its own process with -p parameters."""
    args = [str(VENV_BIN / executable), "--ros-args"]
    for key, value in (params or {}).items():
        args += ["-p", f"{key}:={_param_text(value)}"]
    args += list(extra)
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=os.environ.copy(), start_new_session=True)


def _param_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ",".join(_param_text(v) for v in value) + "]"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"  # YAML single-quoted: ':' and '[' are safe
    return str(value)


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> str:
    """SIGINT a node process, wait for it, return its output."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out or ""


def call_service(client: SpinningNode, srv_type, name: str, request, timeout: float = 20.0,
                 resend_after: float = 5.0):
    """Call service ``name`` from ``client`` and return the response (asserts one comes).

    The request is sent again when no answer comes within ``resend_after`` seconds: a
    request sent just as the server appears can be lost (the client sees the server before
    the server has matched the client's endpoints, ros2/rclcpp#625), and these calls are
    idempotent.
    """
    cli = client.node.create_client(srv_type, name)
    deadline = time.monotonic() + timeout
    assert cli.wait_for_service(timeout_sec=timeout), f"{name} never appeared"
    while True:
        future = cli.call_async(request)
        left = deadline - time.monotonic()
        if wait_until(future.done, min(resend_after, max(left, 0.0))):
            return future.result()
        cli.remove_pending_request(future)
        assert left > resend_after, f"no response from {name} in {timeout:.0f} s"


def wait_until(predicate, timeout: float, period: float = 0.05) -> bool:
    """Poll ``predicate`` until true or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return predicate()
