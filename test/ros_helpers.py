"""Helpers shared by the ROS tests: the table_server as a process, a probe node, checks.

Import them with `from ros_helpers import ServerProcess, Probe, assert_answer` (pytest puts
this directory on sys.path, as for conftest). Test modules import helpers from here or from
conftest, never from one another, so that a test module can change without breaking
another one.

- `ServerProcess`: the installed `table_server` console script (or another executable) in
  its own process, on the test's ROS_DOMAIN_ID, with its output in files.
- `Probe`: a node in the test's own Context that publishes `knee/pose` and
  `knee/joint_states` and collects the answers, `/diagnostics` and `knee/markers`.
- `expected`, `assert_answer`: what the core's interpolation says the node must answer.
- `rigid`: a 4 x 4 pose as the tracker's `(px, py, pz, qx, qy, qz, qw)`.
"""
from __future__ import annotations

import math
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any

from conftest import ros_env, spin_until, track_child
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from kneeseat_core.geometry import matrix_from_quat, quat_from_matrix
from kneeseat_core.table import Lookup, PoseTable
from kneeseat_ros.conversions import stamp_from_ns, stamp_ns
from kneeseat_ros.topics import STATUS_NAME

__all__ = ['TABLE_SERVER', 'RELIABLE', 'BODIES', 'ServerProcess', 'Probe', 'expected',
           'assert_answer', 'rigid']

TABLE_SERVER = Path(sys.prefix) / 'bin' / 'table_server'
RELIABLE = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
BODIES = ('tibia', 'patella')      # the moving bodies of conftest.synthetic_table


class ServerProcess:
    """The installed table_server in its own process; output goes to files."""

    def __init__(self, tmp_path: Path, domain_id: int, table: Path, *params: str,
                 executable: Path = TABLE_SERVER, env: dict[str, str] | None = None,
                 ros_args: list[str] | None = None, exact_env: bool = False) -> None:
        """Start the server (tracked: killed at the end of the test if still running).

        Args:
            tmp_path: folder of server.out and server.err (created).
            domain_id: the test's ROS_DOMAIN_ID.
            table: the `table` parameter.
            *params: more parameters, each `name:=value`.
            executable: the node's executable.
            env: the environment (ros_env's additions are made to it unless `exact_env`).
            ros_args: more `--ros-args` arguments, before the parameters.
            exact_env: use `env` as given.
        """
        tmp_path.mkdir(parents=True, exist_ok=True)
        self.out, self.err = tmp_path / 'server.out', tmp_path / 'server.err'
        args = [str(executable), '--ros-args', *(ros_args or []), '-p', f'table:={table}']
        for p in params:
            args += ['-p', p]
        with open(self.out, 'wb') as out, open(self.err, 'wb') as err:
            self.proc = track_child(subprocess.Popen(
                args, stdout=out, stderr=err,
                env=env if exact_env and env is not None else ros_env(domain_id, env)))

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int:
        """Send `sig` and wait; a node that does not exit is killed (and the test fails).

        Returns:
            The exit code.
        Raises:
            subprocess.TimeoutExpired: the node did not exit within `timeout_s`.
        """
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise

    def stderr(self) -> str:
        """What the server wrote on stderr so far."""
        return self.err.read_text()

    def stop_clean(self, sig: int = signal.SIGTERM) -> None:
        """Stop with `sig`; the node must exit 0 without a traceback."""
        rc = self.stop(sig)
        err = self.stderr()
        assert rc == 0 and 'Traceback' not in err, f'exit {rc}, stderr:\n{err}'


class Probe:
    """A test node: publishes pose and joint inputs, collects every output."""

    def __init__(self, context: Any, bodies: tuple[str, ...] = BODIES, ns: str = '',
                 node: str = 'table_server', name: str = 'probe') -> None:
        """Create the probe node in `context`.

        Args:
            context: the test's rclpy Context (conftest.context).
            bodies: the bodies whose `knee/<body>/pose` answers are collected.
            ns: the server's namespace ('' or '/name').
            node: the server's node name (its `~/reload` service).
            name: this node's name.
        """
        self.ns = ns
        self.node = rclpy.create_node(name, context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        # reliable tracker, best-effort joints: the node must accept both
        self.pose_pub = self.node.create_publisher(PoseStamped, f'{ns}/knee/pose', RELIABLE)
        self.joint_pub = self.node.create_publisher(JointState, f'{ns}/knee/joint_states',
                                                    qos_profile_sensor_data)
        self.answers: dict[tuple[str, int], PoseStamped] = {}
        self.arrivals: list[tuple[str, int]] = []
        for body in bodies:
            self.node.create_subscription(
                PoseStamped, f'{ns}/knee/{body}/pose',
                lambda msg, body=body: self._on_answer(body, msg), RELIABLE)
        self.status: dict[str, str] = {}
        self.level = b''
        self.hardware_id = ''
        self.levels: list[bytes] = []
        self.history: list[dict[str, str]] = []
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, RELIABLE)
        self.markers: list[MarkerArray] = []
        self.node.create_subscription(MarkerArray, f'{ns}/knee/markers', self.markers.append,
                                      RELIABLE)
        self.reload = self.node.create_client(Trigger, f'{ns}/{node}/reload')
        self._stamp = 1_000_000_000_000

    def _on_answer(self, body: str, msg: PoseStamped) -> None:
        key = (body, stamp_ns(msg.header.stamp))
        self.answers[key] = msg
        self.arrivals.append(key)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == STATUS_NAME and status.hardware_id.startswith(f'{self.ns}/'):
                self.status = {kv.key: kv.value for kv in status.values}
                self.level, self.hardware_id = status.level, status.hardware_id
                self.levels.append(status.level)
                self.history.append(dict(self.status))

    def next_stamp(self) -> Any:
        """A fresh stamp (builtin_interfaces/Time), later than every one before."""
        self._stamp += 1_000_003
        return stamp_from_ns(self._stamp)

    def wait_connected(self, bodies: tuple[str, ...] = BODIES) -> None:
        """Spin until the server subscribes to both inputs and publishes every answer."""
        topics = [f'{self.ns}/knee/{b}/pose' for b in bodies]
        spin_until(self.executor, lambda: (
            self.pose_pub.get_subscription_count() > 0
            and self.joint_pub.get_subscription_count() > 0
            and all(self.node.count_publishers(t) > 0 for t in topics)),
            timeout_s=20.0, what='discovery of table_server')

    def ask(self, msg: Any, bodies: tuple[str, ...] = BODIES) -> dict[str, PoseStamped]:
        """Publish `msg` until every body's answer with its stamp arrived (resend: 0.5 s).

        Returns:
            Each body's answer.
        """
        pub = self.pose_pub if isinstance(msg, PoseStamped) else self.joint_pub
        key = stamp_ns(msg.header.stamp)
        last = [-math.inf]

        def resend() -> None:
            if time.monotonic() - last[0] > 0.5:
                last[0] = time.monotonic()
                pub.publish(msg)

        spin_until(self.executor, lambda: all((b, key) in self.answers for b in bodies),
                   timeout_s=10.0, what=f'answer to stamp {key}', every=resend)
        return {b: self.answers[(b, key)] for b in bodies}

    def wait_status(self, want: dict[str, str], timeout_s: float = 10.0) -> dict[str, str]:
        """Spin until the server's diagnostics hold every value of `want`.

        Returns:
            The diagnostics values then.
        """
        spin_until(self.executor,
                   lambda: all(self.status.get(k) == v for k, v in want.items()),
                   timeout_s=timeout_s, what=f'diagnostics {want} (last: {self.status})')
        return self.status

    def destroy(self) -> None:
        """Shut the executor down and destroy the node."""
        self.executor.shutdown()
        self.node.destroy_node()


def expected(table: PoseTable, msg: Any, out_of_range: str = 'clamp') -> Lookup:
    """The core's answer for an input message: decompose (pose) or read (joints).

    Args:
        table: the served table.
        msg: a PoseStamped (tibia orientation) or a JointState (flexion, varus first).
        out_of_range: the server's `out_of_range`.
    Returns:
        `table.interpolate` at the message's attitude.
    """
    if isinstance(msg, PoseStamped):
        o = msg.pose.orientation
        flexion, varus, _ = table.axes.decompose(matrix_from_quat(np.array([o.x, o.y, o.z,
                                                                            o.w])))
    else:
        flexion, varus = msg.position[0], msg.position[1]
    return table.interpolate(float(flexion), float(varus), out_of_range)


def assert_answer(table: PoseTable, msg: Any, got: dict[str, PoseStamped]) -> None:
    """Every body's answer `got` to `msg` is the core's (1e-9), in 'femur', with its stamp."""
    want = expected(table, msg)
    for i, body in enumerate(table.bodies):
        out = got[body]
        assert out.header.frame_id == 'femur'
        assert stamp_ns(out.header.stamp) == stamp_ns(msg.header.stamp)
        p, o = out.pose.position, out.pose.orientation
        assert np.abs(np.array([p.x, p.y, p.z]) - want.position_m[i]).max() <= 1e-9
        assert np.abs(np.array([o.x, o.y, o.z, o.w]) - want.orientation_xyzw[i]).max() <= 1e-9


def rigid(m: np.ndarray) -> tuple[float, ...]:
    """The 4 x 4 pose `m` as a tracker rigid transform (px, py, pz, qx, qy, qz, qw)."""
    return (*m[:3, 3], *quat_from_matrix(m[:3, :3]))
