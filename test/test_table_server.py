"""The table_server node over real rclpy and Fast DDS.

Most tests run the node as the installed `table_server` console script in its own process,
on the test's own ROS_DOMAIN_ID, and talk to it from a probe node in a separate Context.
Nothing sleeps to synchronise: every wait spins until a condition holds or a deadline.
"""
from __future__ import annotations

from collections.abc import Iterator
import math
from pathlib import Path
import re
import signal
import subprocess
import sys
import time
from typing import Any

from conftest import ros_env, spin_until, synthetic_table, write_synthetic_table
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile, QoSReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray
import yaml

from kneeseat_core.geometry import matrix_from_quat
from kneeseat_core.table import PoseTable, read_table
from kneeseat_ros.conversions import (joint_state, pose_stamped, pose_stamped_for_attitude,
                                      stamp_from_ns, stamp_ns)
from kneeseat_ros.table_server import main, STATUS_NAME, TableServer

pytestmark = pytest.mark.ros

TABLE_SERVER = Path(sys.prefix) / 'bin' / 'table_server'
RELIABLE = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
BODIES = ('tibia', 'patella')


class ServerProcess:
    """The installed table_server in its own process; output goes to files."""

    def __init__(self, tmp_path: Path, domain_id: int, table: Path, *params: str,
                 executable: Path = TABLE_SERVER, env: dict[str, str] | None = None,
                 ros_args: list[str] | None = None) -> None:
        self.out, self.err = tmp_path / 'server.out', tmp_path / 'server.err'
        args = [str(executable), '--ros-args', *(ros_args or []), '-p', f'table:={table}']
        for p in params:
            args += ['-p', p]
        with open(self.out, 'wb') as out, open(self.err, 'wb') as err:
            self.proc = subprocess.Popen(args, stdout=out, stderr=err,
                                         env=ros_env(domain_id, env))

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(timeout=timeout_s)

    def stderr(self) -> str:
        return self.err.read_text()

    def stop_clean(self, sig: int = signal.SIGTERM) -> None:
        """Stop with `sig`; the node must exit 0 without a traceback."""
        rc = self.stop(sig)
        err = self.stderr()
        assert rc == 0 and 'Traceback' not in err, f'exit {rc}, stderr:\n{err}'


class Probe:
    """A test node: publishes tracker and joint inputs, collects every output."""

    def __init__(self, context: Any, bodies: tuple[str, ...] = BODIES) -> None:
        self.node = rclpy.create_node('probe', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        # reliable tracker, best-effort joints: the node must accept both
        self.pose_pub = self.node.create_publisher(PoseStamped, '/knee/pose', RELIABLE)
        self.joint_pub = self.node.create_publisher(JointState, '/knee/joint_states',
                                                    qos_profile_sensor_data)
        self.answers: dict[tuple[str, int], PoseStamped] = {}
        for body in bodies:
            self.node.create_subscription(
                PoseStamped, f'/knee/{body}/pose',
                lambda msg, body=body: self.answers.__setitem__(
                    (body, stamp_ns(msg.header.stamp)), msg), RELIABLE)
        self.status: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, RELIABLE)
        self.markers: list[MarkerArray] = []
        self.node.create_subscription(MarkerArray, '/knee/markers', self.markers.append,
                                      RELIABLE)
        self.reload = self.node.create_client(Trigger, '/table_server/reload')
        self._stamp = 1_000_000_000_000

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == STATUS_NAME:
                self.status = {kv.key: kv.value for kv in status.values}

    def next_stamp(self) -> Any:
        self._stamp += 1_000_003
        return stamp_from_ns(self._stamp)

    def wait_connected(self, bodies: tuple[str, ...] = BODIES) -> None:
        spin_until(self.executor, lambda: (
            self.pose_pub.get_subscription_count() > 0
            and self.joint_pub.get_subscription_count() > 0
            and all(self.node.count_publishers(f'/knee/{b}/pose') > 0 for b in bodies)),
            timeout_s=20.0, what='discovery of table_server')

    def ask(self, msg: Any, bodies: tuple[str, ...] = BODIES) -> dict[str, PoseStamped]:
        """Publish `msg` until every body's answer with its stamp arrived (resend: 0.5 s)."""
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
        spin_until(self.executor,
                   lambda: all(self.status.get(k) == v for k, v in want.items()),
                   timeout_s=timeout_s, what=f'diagnostics {want} (last: {self.status})')
        return self.status

    def destroy(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def probe(context: Any) -> Iterator[Probe]:
    p = Probe(context)
    yield p
    p.destroy()


@pytest.fixture
def table_path(tmp_path: Path) -> Path:
    return write_synthetic_table(tmp_path / 'knee.npz', seed=5)


@pytest.fixture
def server(tmp_path: Path, domain_id: int, table_path: Path) -> Iterator[ServerProcess]:
    srv = ServerProcess(tmp_path, domain_id, table_path, 'diagnostics_period_s:=0.2')
    yield srv
    srv.stop(signal.SIGKILL) if srv.proc.poll() is None else None


def expected(table: PoseTable, msg: Any, out_of_range: str = 'clamp') -> Any:
    """The core's answer for an input message: decompose (pose) or read (joints)."""
    if isinstance(msg, PoseStamped):
        o = msg.pose.orientation
        flexion, varus, _ = table.axes.decompose(matrix_from_quat(np.array([o.x, o.y, o.z,
                                                                            o.w])))
    else:
        flexion, varus = msg.position[0], msg.position[1]
    return table.interpolate(float(flexion), float(varus), out_of_range)


def assert_answer(table: PoseTable, msg: Any, got: dict[str, PoseStamped]) -> None:
    want = expected(table, msg)
    for i, body in enumerate(table.bodies):
        out = got[body]
        assert out.header.frame_id == 'femur'
        assert stamp_ns(out.header.stamp) == stamp_ns(msg.header.stamp)
        p, o = out.pose.position, out.pose.orientation
        assert np.abs(np.array([p.x, p.y, p.z]) - want.position_m[i]).max() <= 1e-9
        assert np.abs(np.array([o.x, o.y, o.z, o.w]) - want.orientation_xyzw[i]).max() <= 1e-9


def test_answers_equal_core_interpolation_and_markers(tmp_path: Path, domain_id: int,
                                                      context: Any) -> None:
    mesh_dir = tmp_path / 'meshes'
    mesh_dir.mkdir()
    for name in ('femur', *BODIES):
        (mesh_dir / f'{name}.stl').write_bytes(b'solid x\nendsolid x\n')
    path = tmp_path / 'knee.npz'
    from kneeseat_core.table import write_table
    write_table(path, synthetic_table(seed=2, mesh_dir=mesh_dir))
    table = read_table(path)
    srv = ServerProcess(tmp_path, domain_id, path, 'publish_markers:=true',
                        'marker_rate_hz:=20.0')
    probe = Probe(context)
    try:
        probe.wait_connected()
        rng = np.random.default_rng(21)
        attitudes = rng.uniform(np.radians([-95.0, -12.0, -20.0]), np.radians([5.0, 12.0, 20.0]),
                                (12, 3))
        for flexion, varus, rotation in attitudes:
            msg = pose_stamped_for_attitude(table.axes, flexion, varus, probe.next_stamp(),
                                            'femur', rotation)
            assert_answer(table, msg, probe.ask(msg))
            jmsg = joint_state(flexion, varus, probe.next_stamp())
            assert_answer(table, jmsg, probe.ask(jmsg))
        # a burst (no waiting in between) is answered completely and in order
        arrived: list[int] = []
        probe.node.create_subscription(PoseStamped, '/knee/tibia/pose',
                                       lambda m: arrived.append(stamp_ns(m.header.stamp)),
                                       RELIABLE)
        burst = [pose_stamped_for_attitude(table.axes, -0.01 * k, 0.0, probe.next_stamp(),
                                           'femur') for k in range(30)]
        for msg in burst:
            probe.pose_pub.publish(msg)
        keys = [stamp_ns(m.header.stamp) for m in burst]
        spin_until(probe.executor, lambda: all(('patella', k) in probe.answers for k in keys)
                   and set(keys) <= set(arrived), what='answers to a burst of 30')
        assert [k for k in arrived if k in set(keys)] == keys
        for msg in burst[::7]:
            assert_answer(table, msg, {b: probe.answers[(b, stamp_ns(msg.header.stamp))]
                                       for b in BODIES})
        # markers carry the last answer: reference (id 0) plus one mesh per moving body
        last_stamp = stamp_ns(burst[-1].header.stamp)
        spin_until(probe.executor, lambda: any(
            len(m.markers) == 3 and stamp_ns(m.markers[1].header.stamp) == last_stamp
            for m in probe.markers), what='markers of the last answer')
        markers = next(m for m in probe.markers if len(m.markers) == 3
                       and stamp_ns(m.markers[1].header.stamp) == last_stamp).markers
        assert [m.id for m in markers] == [0, 1, 2]
        assert all(m.type == Marker.MESH_RESOURCE and m.header.frame_id == 'femur'
                   for m in markers)
        assert [m.mesh_resource for m in markers] == [
            f'file://{mesh_dir / n}.stl' for n in ('femur', *BODIES)]
        want = expected(table, burst[-1])
        assert markers[1].pose.position.x == pytest.approx(want.position_m[0, 0], abs=1e-12)
    finally:
        probe.destroy()
        srv.stop_clean()


def test_bad_inputs_are_dropped_and_counted(server: ServerProcess, probe: Probe,
                                            table_path: Path) -> None:
    table = read_table(table_path)
    probe.wait_connected()
    good = 0

    def check_alive() -> None:
        nonlocal good
        flexion = -0.1 * (good % 10) - 0.05
        msg = pose_stamped_for_attitude(table.axes, flexion, 0.01, probe.next_stamp(), 'femur')
        assert_answer(table, msg, probe.ask(msg))
        good += 1

    check_alive()
    q = pose_stamped_for_attitude(table.axes, -0.5, 0.0, probe.next_stamp(), 'femur')
    o = q.pose.orientation
    quat = (o.x, o.y, o.z, o.w)
    bad: list[Any] = [
        pose_stamped((0.0, 0.0, 0.0), (math.nan, *quat[1:]), probe.next_stamp(), 'femur'),
        pose_stamped((0.0, 0.0, 0.0), (*quat[:3], math.inf), probe.next_stamp(), 'femur'),
        pose_stamped((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), probe.next_stamp(), 'femur'),
        pose_stamped((0.0, 0.0, 0.0), tuple(1.1 * c for c in quat), probe.next_stamp(),
                     'femur'),
        pose_stamped((0.0, 0.0, 0.0), quat, probe.next_stamp(), 'tibia'),
        pose_stamped((0.0, 0.0, 0.0), quat, probe.next_stamp(), ''),
        JointState(name=['knee_flexion', 'hip'], position=[0.1, 0.0]),
        JointState(name=['knee_flexion', 'knee_varus'], position=[0.1]),
        JointState(name=['knee_flexion', 'knee_varus'], position=[0.1, 0.0], effort=[1.0]),
        JointState(name=['knee_flexion', 'knee_varus'], position=[math.nan, 0.0]),
    ]
    for msg in bad:
        msg.header.stamp = probe.next_stamp()
        (probe.pose_pub if isinstance(msg, PoseStamped) else probe.joint_pub).publish(msg)
        check_alive()          # in-order delivery: the bad one was handled before this answer
    for msg in bad:            # none of them was answered
        assert not any(key[1] == stamp_ns(msg.header.stamp) for key in probe.answers)
    # out of range in clamp mode: answered at the edge, counted as clamped
    far = joint_state(-2.5, 0.0, probe.next_stamp())
    assert_answer(table, far, probe.ask(far))
    want = {'dropped_nonfinite': '3', 'dropped_quaternion': '2', 'dropped_frame_id': '2',
            'dropped_joint_names': '1', 'dropped_lengths': '2', 'dropped_out_of_range': '0',
            'dropped': '10', 'clamped': '1', 'answered': str(good + 1)}
    status = probe.wait_status(want)
    assert int(status['received']) >= len(bad) + good + 1
    assert status['table_sha256'] == table.sha256
    assert status['flexion_range_deg'] == '-90.000 0.000'
    assert float(status['latency_p99_ms']) >= 0.0 or status['latency_p99_ms'] == 'nan'
    assert server.proc.poll() is None
    server.stop_clean()
    err = server.stderr()
    assert 'dropped input' in err and 'Traceback' not in err


def test_drop_mode_drops_out_of_range(tmp_path: Path, domain_id: int, table_path: Path,
                                      probe: Probe) -> None:
    table = read_table(table_path)
    srv = ServerProcess(tmp_path, domain_id, table_path, 'out_of_range:=drop',
                        'diagnostics_period_s:=0.2')
    try:
        probe.wait_connected()
        assert_answer(table, (m := joint_state(-0.3, 0.0, probe.next_stamp())), probe.ask(m))
        far = joint_state(-0.3, math.radians(15.0), probe.next_stamp())
        probe.joint_pub.publish(far)
        assert_answer(table, (m := joint_state(-0.4, 0.0, probe.next_stamp())), probe.ask(m))
        probe.wait_status({'dropped_out_of_range': '1', 'clamped': '0', 'answered': '2',
                           'out_of_range': 'drop'})
        assert not any(key[1] == stamp_ns(far.header.stamp) for key in probe.answers)
    finally:
        srv.stop_clean()


def test_reload_swaps_tables_and_keeps_old_on_failure(server: ServerProcess, probe: Probe,
                                                      table_path: Path) -> None:
    old = read_table(table_path)
    probe.wait_connected()
    msg = joint_state(-0.6, 0.02, probe.next_stamp())
    assert_answer(old, msg, probe.ask(msg))

    def reload() -> Trigger.Response:
        spin_until(probe.executor, probe.reload.service_is_ready, what='~/reload service')
        future = probe.reload.call_async(Trigger.Request())
        spin_until(probe.executor, future.done, what='~/reload response')
        return future.result()

    write_synthetic_table(table_path, seed=9, offset_m=0.05)
    new = read_table(table_path)
    response = reload()
    assert response.success, response.message
    assert new.sha256[:12] in response.message
    msg = joint_state(-0.6, 0.02, probe.next_stamp())
    got = probe.ask(msg)
    assert_answer(new, msg, got)
    assert got['tibia'].pose.position.x > 0.04     # the new table's offset, not the old one
    probe.wait_status({'table_sha256': new.sha256})

    table_path.write_bytes(b'not a table')
    response = reload()
    assert not response.success
    assert 'still serving' in response.message and str(table_path) in response.message
    msg = joint_state(-0.7, 0.0, probe.next_stamp())
    assert_answer(new, msg, probe.ask(msg))
    server.stop_clean()


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT])
def test_signal_exits_0_and_finalises_recording(sig: int, tmp_path: Path, domain_id: int,
                                                table_path: Path, probe: Probe) -> None:
    pytest.importorskip('kneeseat_ros.recorder', reason='recorder not available')
    record = tmp_path / 'bags'
    srv = ServerProcess(tmp_path, domain_id, table_path, f'record:={record}',
                        'diagnostics_period_s:=0.1')
    probe.wait_connected()
    for flexion in (-0.2, -0.4):
        probe.ask(joint_state(flexion, 0.0, probe.next_stamp()))
    probe.wait_status({'answered': '2'})
    srv.stop_clean(sig)
    bags = list(record.glob('kneeseat_*'))
    assert len(bags) == 1, bags
    info = yaml.safe_load((bags[0] / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in info['topics_with_message_count']}
    assert counts['/knee/joint_states'] >= 2
    assert counts['/knee/tibia/pose'] == counts['/knee/patella/pose'] == 2
    assert counts['/diagnostics'] >= 1


def test_missing_table_exits_2_with_one_line(tmp_path: Path, domain_id: int) -> None:
    srv = ServerProcess(tmp_path, domain_id, tmp_path / 'missing.npz')
    assert srv.proc.wait(timeout=30) == 2
    lines = srv.stderr().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('table_server: error: table file')
    assert 'missing.npz' in lines[0] and 'not found' in lines[0]


@pytest.mark.parametrize('params, match', [
    (['-p', "table:=''"], r"parameter 'table' is empty"),
    (['-p', 'table:={bad}'], r'table_server: error: .*bad\.npz'),
    (['-p', 'table:={good}', '-p', 'out_of_range:=wrap'], r"'out_of_range' is 'wrap'"),
    (['-p', 'table:={good}', '-p', 'diagnostics_period_s:=0.0'], r'diagnostics_period_s'),
    (['-p', 'table:={good}', '-p', 'record_split_size_mb:=5'], r'must be a double'),
])
def test_bad_start_exits_2_without_traceback(params: list[str], match: str, tmp_path: Path,
                                             table_path: Path, domain_id: int,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'PK\x03\x04 truncated')
    args = ['table_server', '--ros-args',
            *(p.format(bad=bad, good=table_path) for p in params)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err


def test_in_process_node_answers_and_reports(context: Any, table_path: Path) -> None:
    table = read_table(table_path)
    server = TableServer(context=context, parameter_overrides=[
        Parameter('table', value=str(table_path)), Parameter('out_of_range', value='clamp')])
    probe = Probe(context)
    probe.executor.add_node(server)
    try:
        probe.wait_connected()
        msg = pose_stamped_for_attitude(table.axes, -0.3, -0.05, probe.next_stamp(), 'femur')
        assert_answer(table, msg, probe.ask(msg))
        status = server.diagnostics().status[0]
        values = {kv.key: kv.value for kv in status.values}
        assert values['answered'] == '1' and values['recorder'] == 'off'
        assert float(values['latency_p50_ms']) >= 0.0
        assert status.name == STATUS_NAME and status.hardware_id == 'femur'
    finally:
        probe.destroy()
        server.destroy_node()
