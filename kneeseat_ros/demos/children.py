"""The demos' child processes: their ROS environment, stopping them, and listening to a
server's /diagnostics from the demo's own rclpy context.

SIGTERM to a demo raises `Stop` in its main thread (`sigterm_unwinds`), so that the
`finally` blocks stop every child before the demo exits.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any

from kneeseat_ros import topics

__all__ = ['Stop', 'child_env', 'last_line', 'stop_child', 'DiagnosticsMonitor',
           'sigterm_unwinds', 'SPIN_SLICE_S']

SPIN_SLICE_S = 0.05


class Stop(Exception):
    """SIGTERM reached the demo: unwind (children are stopped in `finally`)."""


def child_env() -> dict[str, str]:
    """Environment of the ROS children (and of the demo's own rclpy): the venv on the ament
    prefix path, discovery on this machine, a domain of its own unless one is set."""
    env = dict(os.environ)
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if sys.prefix not in prefixes:
        prefixes.insert(0, sys.prefix)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(prefixes)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 1))
    env['PYTHONUNBUFFERED'] = '1'
    return env


def last_line(log: Path) -> str:
    """The last non-empty line of a child's log ('' when there is none)."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors='replace').splitlines() if ln.strip()]
    except OSError:
        return ''
    return lines[-1] if lines else ''


def stop_child(proc: subprocess.Popen[Any] | None, timeout_s: float) -> int | None:
    """SIGINT, then SIGTERM, then SIGKILL; returns the exit code of the first clean exit."""
    if proc is None:
        return None
    if proc.poll() is not None:
        return proc.returncode
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc.send_signal(sig)
        try:
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            continue
    proc.kill()
    proc.wait()
    return None


class DiagnosticsMonitor:
    """An rclpy node of the demo's own listening to /diagnostics of its server."""

    def __init__(self, table_path: Path) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        self._rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('kneeseat_demo', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.values: dict[str, str] = {}
        self.count = 0
        self._table = str(table_path)
        qos = QoSProfile(depth=10, reliability=QoSReliabilityPolicy.RELIABLE,
                         durability=QoSDurabilityPolicy.VOLATILE)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos)

    def _on_diag(self, msg: Any) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            # another server on this ROS domain serves another table: not ours
            if status.name == topics.STATUS_NAME and values.get('table') == self._table:
                self.values = values
                self.count += 1

    def spin_until(self, done: Callable[[], bool], timeout_s: float,
                   alive: Callable[[], None]) -> bool:
        """Spin until `done()`; False at the deadline. `alive()` raises if a child died."""
        deadline = time.monotonic() + timeout_s
        while not done():
            alive()
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=SPIN_SLICE_S)
        return True

    def close(self) -> None:
        """Destroy the listening node and its context."""
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


@contextmanager
def sigterm_unwinds() -> Iterator[None]:
    """SIGTERM raises `Stop` in the main thread, so `finally` blocks stop the children."""
    def raise_stop(*_: Any) -> None:
        raise Stop
    previous = signal.signal(signal.SIGTERM, raise_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
