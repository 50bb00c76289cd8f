"""The table_server node over real rclpy and Fast DDS.

Most tests run the node as the installed `table_server` console script in its own process,
on the test's own ROS_DOMAIN_ID, and talk to it from a probe node in a separate Context.
Nothing sleeps to synchronise: every wait spins until a condition holds or a deadline.
"""
from __future__ import annotations

from collections.abc import Iterator
import importlib
import inspect
import math
from pathlib import Path
import re
import signal
import subprocess
import threading
import time
from typing import Any

from conftest import (next_domain_id, REPO, ros_env, spin_until, synthetic_table,
                      write_synthetic_table)
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.guard_condition import GuardCondition
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from rosbags.typesys import get_typestore, Stores
from ros_helpers import (assert_answer, BODIES, expected, Probe, RELIABLE, ServerProcess,
                         TABLE_SERVER)
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker
import yaml

from kneeseat_core.errors import ConfigError
from kneeseat_core.table import read_table
from kneeseat_ros import spin
from kneeseat_ros.cdr import (decode_joint_state, decode_pose_stamped, encode_joint_state,
                              encode_pose_stamped)
from kneeseat_ros.conversions import (DROP_REASONS, joint_state, pose_stamped,
                                      pose_stamped_for_attitude, stamp_from_ns, stamp_ns)
from kneeseat_ros.diagnostics import Counters
from kneeseat_ros.errors import CdrError
from kneeseat_ros.responder import Responder, TrackerMode
from kneeseat_ros.served import Route, Served
from kneeseat_ros.table_server import main, STATUS_NAME, TableServer
from kneeseat_ros.tracker import Pairer, Registration

pytestmark = pytest.mark.ros


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
    pytest.importorskip('kneeseat_ros.bag.recorder', reason='recorder not available')
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


class _FakePublisher:
    """Stands for an rclpy Publisher of CDR bytes."""

    def __init__(self, topic_name: str) -> None:
        self.topic_name = topic_name
        self.sent: list[bytes] = []

    def publish(self, data: bytes) -> None:
        self.sent.append(data)


class _FakeLog:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warning(self, message: str, throttle_duration_sec: float = 0.0) -> None:
        self.warnings.append(message)


class _FakeRecorder:
    def __init__(self) -> None:
        self.written: list[tuple[str, bytes, int]] = []

    def write_raw(self, topic: str, data: bytes, log_time_ns: int,
                  publish_time_ns: int) -> None:
        self.written.append((topic, data, publish_time_ns))


def _route(served: Served, tracker: bool = False) -> Route:
    world = (tuple(_FakePublisher(f'/knee/{b}/world_pose') for b in served.bodies)
             if tracker else ())
    return Route(served, tuple(_FakePublisher(f'/knee/{b}/pose') for b in served.bodies),
                 world, _FakePublisher('/knee/femur/world_pose') if tracker else None)


def _close(got: Any, want: Any) -> bool:
    return float(np.abs(np.asarray(got) - np.asarray(want)).max()) <= 1e-9


def test_responder_state_and_cdr_fallback(tmp_path: Path, table_path: Path) -> None:
    """The hot path without DDS: big-endian inputs (CdrError) are read by rclpy and answered
    like little-endian ones, undecodable bytes are counted as malformed; the latest answer
    and what the node switches (route, recording) go through the responder's own API."""
    table = read_table(table_path)
    log, recorder = _FakeLog(), _FakeRecorder()
    counters = Counters(DROP_REASONS, 0)
    responder = Responder(_route(Served.load(table_path)), counters, log, time.time_ns,
                          'clamp', ('knee_flexion', 'knee_varus'))
    responder.set_input_topics(['/knee/pose', '/knee/joint_states'])
    responder.start_recording(recorder)
    assert responder.last is None
    msg = pose_stamped_for_attitude(table.axes, -0.4, 0.05, stamp_from_ns(3_000_000_004),
                                    'femur')
    o = msg.pose.orientation
    pose_le = encode_pose_stamped(3, 4, 'femur', (0.0, 0.0, 0.0, o.x, o.y, o.z, o.w))
    joints = joint_state(-0.6, 0.02, stamp_from_ns(5_000_000_006))
    joints_le = encode_joint_state(5, 6, '', list(joints.name), list(joints.position), [], [])
    rosbags = get_typestore(Stores.ROS2_JAZZY)
    for name, data, decode, handle, sent, stamp in (
            ('geometry_msgs/msg/PoseStamped', pose_le, decode_pose_stamped,
             responder.handle_pose, msg, (3, 4)),
            ('sensor_msgs/msg/JointState', joints_le, decode_joint_state,
             responder.handle_joints, joints, (5, 6))):
        as_be = bytes(rosbags.serialize_cdr(rosbags.deserialize_cdr(data, name), name,
                                            little_endian=False))
        with pytest.raises(CdrError, match='little-endian'):
            decode(as_be)
        for raw in (data, as_be):
            before = [len(pub.sent) for pub in responder.route.body_pubs]
            handle(raw)
            assert [len(pub.sent) for pub in responder.route.body_pubs] == [
                n + 1 for n in before], f'{name} {raw[:4].hex()} not answered'
        # the same answer, bit for bit, whichever reader took the input
        assert all(pub.sent[-1] == pub.sent[-2] for pub in responder.route.body_pubs)
        last = responder.last
        assert last is not None and (last.sec, last.nanosec) == stamp
        assert _close(last.lookup.position_m, expected(table, sent).position_m)
    assert counters.received == counters.answered == 4
    # inputs are recorded little endian (as our writer puts them) under their topics
    inputs = [(t, d) for t, d, _ in recorder.written if t in ('/knee/pose', '/knee/joint_states')]
    assert inputs == [('/knee/pose', pose_le)] * 2 + [('/knee/joint_states', joints_le)] * 2
    assert [t for t, _, _ in recorder.written].count('/knee/tibia/pose') == 4
    # undecodable by both readers: counted as received and malformed, not answered
    responder.handle_pose(b'\x00\x00\x00\x00\x01')
    responder.handle_joints(b'\x00\x01\x00\x00\x01\x02')
    assert counters.dropped['malformed'] == 2 and counters.received == 6
    assert counters.answered == 4 and len(log.warnings) == 2
    # a new route: the old answer is forgotten, answers go to the new publishers
    new_route = _route(Served.load(write_synthetic_table(tmp_path / 'new.npz', seed=9,
                                                         offset_m=0.05)))
    responder.switch_route(new_route)
    assert responder.route is new_route and responder.last is None
    responder.handle_joints(joints_le)
    assert [len(pub.sent) for pub in new_route.body_pubs] == [1, 1]
    assert responder.last is not None and responder.last.lookup.position_m[0, 0] > 0.04
    with pytest.raises(AttributeError):
        responder.last = None       # read-only: the node calls switch_route
    # tracker mode: a pair is answered with the femur's stamp, in the world frame too
    identity = (0.0,) * 6 + (1.0,)
    tracker = TrackerMode(Registration(identity, identity, tmp_path / 'reg.yaml'),
                          Pairer(1_000_000), 'world', 0.001)
    tracked = Responder(_route(Served.load(table_path, 'world'), tracker=True),
                        Counters(DROP_REASONS, 0), _FakeLog(), time.time_ns, 'clamp',
                        ('knee_flexion', 'knee_varus'), tracker)
    tracked.handle_rigid(0, encode_pose_stamped(9, 100, 'world', identity))
    assert tracked.last is None
    tracked.handle_rigid(1, encode_pose_stamped(9, 200, 'world',
                                                (0.0, 0.0, 0.0, o.x, o.y, o.z, o.w)))
    assert tracked.last is not None and (tracked.last.sec, tracked.last.nanosec) == (9, 100)
    assert _close(tracked.last.lookup.position_m, expected(table, msg).position_m)
    world = tracked.route.reference_world_pub
    assert isinstance(world, _FakePublisher) and len(world.sent) == 1


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
        assert status.name == STATUS_NAME and status.hardware_id == '/table_server'
    finally:
        probe.destroy()
        server.destroy_node()


def test_diagnostics_wait_for_the_inputs_in_hand(context: Any, table_path: Path) -> None:
    """Diagnostics read the counters only between inputs, never halfway through one.

    The input thread bumps answered, dropped and the pairer's counts while handling; a read
    in the middle once reported every tracker pair answered but a drop not yet counted.
    """
    server = TableServer(context=context, parameter_overrides=[
        Parameter('table', value=str(table_path))])
    read: list[Any] = []
    done = threading.Event()

    def read_diagnostics() -> None:
        read.append(server.diagnostics())
        done.set()

    try:
        reader = threading.Thread(target=read_diagnostics, daemon=True)
        with server._inputs_group.handling:      # an input halfway through its handling
            reader.start()
            assert not done.wait(0.5), 'diagnostics read the counters during an input'
        assert done.wait(10.0), 'diagnostics never read once the input was handled'
        reader.join(timeout=10.0)
        assert read and read[0].status[0].name == STATUS_NAME
    finally:
        server.destroy_node()


def _params_file(path: Path, **overrides: Any) -> Path:
    """The shipped params file (keyed /**) with some values changed."""
    data = yaml.safe_load((REPO / 'config' / 'table_server.yaml').read_text())
    assert list(data) == ['/**']
    data['/**']['ros__parameters'].update(overrides)
    path.write_text(yaml.safe_dump(data))
    return path


def test_namespaces_keep_two_servers_apart(tmp_path: Path, domain_id: int,
                                           context: Any) -> None:
    """/left and /right on one graph: one input each, one answer each, params file applied."""
    tables = {'left': write_synthetic_table(tmp_path / 'left.npz', seed=5),
              'right': write_synthetic_table(tmp_path / 'right.npz', seed=6, offset_m=0.05)}
    params = _params_file(tmp_path / 'params.yaml', out_of_range='drop',
                          diagnostics_period_s=0.2)
    servers, probes = {}, {}
    try:
        for side, node in (('left', 'table_server'), ('right', 'right_knee')):
            servers[side] = ServerProcess(
                tmp_path / side, domain_id, tables[side],
                ros_args=['--params-file', str(params), '-r', f'__ns:=/{side}',
                          '-r', f'__node:={node}'])
            probes[side] = Probe(context, ns=f'/{side}', node=node, name=f'probe_{side}')
        for probe in probes.values():
            probe.wait_connected()
        stamps = {}
        for side, probe in probes.items():
            table = read_table(tables[side])
            msg = joint_state(-0.5, 0.02, probe.next_stamp())
            stamps[side] = stamp_ns(msg.header.stamp)
            assert_answer(table, msg, probe.ask(msg))
        for side, probe in probes.items():
            status = probe.wait_status({'answered': '1', 'out_of_range': 'drop'})
            assert status['received'] == '1'
            assert probe.hardware_id == ('/left/table_server' if side == 'left'
                                         else '/right/right_knee')
        # each probe saw its own server's answers only, once per body
        assert sorted(probes['left'].arrivals) == sorted((b, stamps['left']) for b in BODIES)
        assert sorted(probes['right'].arrivals) == sorted((b, stamps['right']) for b in BODIES)
        assert probes['right'].answers[('tibia', stamps['right'])].pose.position.x > 0.04
        assert probes['left'].answers[('tibia', stamps['left'])].pose.position.x < 0.04
    finally:
        for probe in probes.values():
            probe.destroy()
        for srv in servers.values():
            srv.stop_clean()


def test_diagnostics_window_unstamped_and_joint_names(tmp_path: Path, domain_id: int,
                                                      table_path: Path, probe: Probe) -> None:
    table = read_table(table_path)
    names = ('hip_flexion', 'hip_varus')
    srv = ServerProcess(tmp_path, domain_id, table_path, 'diagnostics_period_s:=0.1',
                        'diagnostics_window_s:=0.5', f'flexion_joint:={names[0]}',
                        f'varus_joint:={names[1]}')
    try:
        probe.wait_connected()
        # stamped with the clock (not the probe's made-up stamps): a real latency
        msg = joint_state(-0.3, 0.0, stamp_from_ns(time.time_ns()), names=names)
        assert_answer(table, msg, probe.ask(msg))
        spin_until(probe.executor, lambda: probe.level == DiagnosticStatus.OK
                   and probe.status.get('answered') == '1', what='OK after one answer')
        # the default names are unknown now: dropped, WARN for a while, then OK again
        probe.joint_pub.publish(joint_state(-0.3, 0.0, probe.next_stamp()))
        probe.wait_status({'dropped_joint_names': '1', 'dropped_recent': '1'})
        assert probe.level == DiagnosticStatus.WARN
        status = probe.wait_status({'dropped_recent': '0'})
        assert probe.level == DiagnosticStatus.OK and status['dropped'] == '1'
        # unstamped (stamp 0, as `ros2 topic pub` sends): answered, counted, no latency
        unstamped = joint_state(-0.4, 0.01, stamp_from_ns(0), names=names)
        assert_answer(table, unstamped, probe.ask(unstamped))
        probe.wait_status({'unstamped': '1', 'answered': '2'})
        latencies = [float(h['latency_max_ms']) for h in probe.history]
        assert all(math.isnan(v) or 0.0 <= v < 60_000.0 for v in latencies), latencies
    finally:
        srv.stop_clean()


def test_table_parameter_names_the_served_table(server: ServerProcess, probe: Probe,
                                                table_path: Path, tmp_path: Path) -> None:
    from rclpy.parameter_client import AsyncParameterClient
    probe.wait_connected()
    client = AsyncParameterClient(probe.node, '/table_server')
    spin_until(probe.executor, client.services_are_ready, what='parameter services')

    def call(future: Any) -> Any:
        spin_until(probe.executor, future.done, what='parameter service answer')
        return future.result()

    def table_param() -> str:
        return call(client.get_parameters(['table'])).values[0].string_value

    assert table_param() == str(table_path)
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'not a table')
    result = call(client.set_parameters([Parameter('table', value=str(bad))])).results[0]
    assert not result.successful and 'still serving' in result.reason
    assert str(bad) in result.reason
    assert table_param() == str(table_path)
    msg = joint_state(-0.6, 0.02, probe.next_stamp())
    assert_answer(read_table(table_path), msg, probe.ask(msg))
    new = write_synthetic_table(tmp_path / 'new.npz', seed=9, offset_m=0.05)
    result = call(client.set_parameters([Parameter('table', value=str(new))])).results[0]
    assert result.successful, result.reason
    assert table_param() == str(new)
    msg = joint_state(-0.6, 0.02, probe.next_stamp())
    assert_answer(read_table(new), msg, probe.ask(msg))
    probe.wait_status({'table': str(new)})
    server.stop_clean()


def test_help_prints_usage(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['table_server', '--help']) == 0
    assert capsys.readouterr().out.startswith('usage: table_server')
    for args in (['--ros-args', '--help'], ['-h']):
        done = subprocess.run([str(TABLE_SERVER), *args], capture_output=True, text=True,
                              timeout=60, env=ros_env(next_domain_id()))
        assert done.returncode == 0 and 'Traceback' not in done.stderr, done.stderr
        assert done.stdout.startswith('usage: table_server')
    done = subprocess.run([str(TABLE_SERVER), '--ros-args', '-r', 'nonsense'],
                          capture_output=True, text=True, timeout=60,
                          env=ros_env(next_domain_id()))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and 'bad command-line arguments' in lines[0], done.stderr


def test_records_without_ament_prefix_path(tmp_path: Path, domain_id: int, table_path: Path,
                                           probe: Probe) -> None:
    """Started straight from the venv (no scripts/env.sh): message definitions still found."""
    env = ros_env(domain_id)
    env.pop('AMENT_PREFIX_PATH')
    record = tmp_path / 'bags'
    srv = ServerProcess(tmp_path, domain_id, table_path, f'record:={record}',
                        'diagnostics_period_s:=0.1', env=env, exact_env=True)
    try:
        probe.wait_connected()
        probe.ask(joint_state(-0.2, 0.0, probe.next_stamp()))
        probe.wait_status({'answered': '1'})
    finally:
        srv.stop_clean()
    bags = list(record.glob('kneeseat_*'))
    assert len(bags) == 1, bags
    info = yaml.safe_load((bags[0] / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in info['topics_with_message_count']}
    assert counts['/knee/tibia/pose'] == counts['/knee/joint_states'] == 1


def test_record_refused_at_start_leaves_nothing(tmp_path: Path, table_path: Path,
                                                context: Any,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """A message definition that cannot be found: ConfigError naming it, no bag directory."""
    from kneeseat_ros.bag import msgdefs
    monkeypatch.setattr(msgdefs, '_share_dir', lambda package: None)
    msgdefs.message_definition.cache_clear()
    msgdefs.type_hash.cache_clear()
    msgdefs._msg_text.cache_clear()
    record = tmp_path / 'bags'
    try:
        with pytest.raises(ConfigError, match=r"parameter 'record': cannot record .*not found"):
            TableServer(context=context, parameter_overrides=[
                Parameter('table', value=str(table_path)),
                Parameter('record', value=str(record))])
    finally:
        msgdefs.message_definition.cache_clear()
        msgdefs.type_hash.cache_clear()
        msgdefs._msg_text.cache_clear()
    assert not record.exists()


def test_debug_logging_does_not_flood_when_idle(tmp_path: Path, domain_id: int,
                                                table_path: Path, probe: Probe) -> None:
    srv = ServerProcess(tmp_path, domain_id, table_path, 'diagnostics_period_s:=0.25',
                        ros_args=['--log-level', 'debug'])
    try:
        probe.wait_connected()
        probe.wait_status({'answered': '0'})
        start, t0 = len(srv.stderr().splitlines()), time.monotonic()
        seen = len(probe.history)
        spin_until(probe.executor, lambda: len(probe.history) >= seen + 8,
                   what='8 diagnostics periods')
        rate = (len(srv.stderr().splitlines()) - start) / (time.monotonic() - t0)
        assert rate < 100.0, f'{rate:.0f} debug lines/s while idle'
    finally:
        srv.stop_clean()


# ---- the rclpy internals kneeseat_ros.spin relies on ---------------------------------
_PYBIND11_SIGNATURE = re.compile(r'^\w+\((?P<params>.*)\) -> (?P<returns>.+)$')
_SUPPORTS = {'SupportsInt': 'int', 'SupportsIndex': 'int', 'SupportsFloat': 'float'}


def _resolve(path: str) -> Any:
    """The object at a dotted path: its longest importable module, then attributes."""
    parts = path.split('.')
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module('.'.join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(f'no module of {path} can be imported')


def _type_name(declared: str) -> str:
    """A pybind11 type as RclpyInternal names it: 'typing.SupportsInt' -> 'int'."""
    name = declared.split('=')[0].strip().rsplit('.', 1)[-1]
    return _SUPPORTS.get(name, name)


def _split_params(text: str) -> list[str]:
    """The comma-separated parameters of a signature (commas inside brackets kept)."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch in '[(') - (ch in '])')
        if ch == ',' and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    return [p.strip() for p in [*parts, text[start:]] if p.strip()]


def _internal_problem(internal: spin.RclpyInternal, live: dict[str, Any]) -> str | None:
    """What differs between `internal` and the installed rclpy (None: nothing)."""
    try:
        owner = _resolve(internal.owner)
        if internal.kind == 'attribute':
            if internal.owner not in live:
                return 'the test has no live instance of its owner: add one to `live`'
            instance = live[internal.owner]
            assert isinstance(instance, owner), f'{instance!r} is not a {owner}'
            value = getattr(instance, internal.name)
        else:
            value = getattr(owner, internal.name)
    except (ImportError, AttributeError) as err:
        return f'missing ({err})'
    want = internal.returns
    if internal.kind == 'class':
        if not (isinstance(value, type) and issubclass(value, _resolve(want))):
            return f'{value!r} is no longer a class derived from {want}'
    elif internal.kind == 'property':
        if not isinstance(inspect.getattr_static(owner, internal.name), property):
            return f'no longer a property ({type(value).__name__})'
    elif internal.kind == 'attribute':
        if not isinstance(value, _resolve(want)):
            return f'is a {type(value).__name__}, not a {want}'
    elif inspect.isfunction(value):           # Python: the parameters' names
        got = tuple(inspect.signature(value).parameters)[1:]
        if got != internal.params:
            return f'parameters are now {got}, spin.py passes {internal.params}'
    else:                                     # the C extension: pybind11's signature
        first = (value.__doc__ or '').strip().splitlines()[:1]
        match = _PYBIND11_SIGNATURE.match(first[0] if first else '')
        if match is None:
            return f'no pybind11 signature to check in its docstring ({first})'
        got = tuple(_type_name(p.split(':', 1)[-1])
                    for p in _split_params(match['params'])[1:])
        returns = _type_name(match['returns'])
        if got != internal.params or returns != want:
            return (f'signature is now ({", ".join(got)}) -> {returns}, spin.py calls it as '
                    f'({", ".join(internal.params)}) -> {want}')
    return None


def test_spin_rclpy_internals_are_still_there(context: Any) -> None:
    """Every rclpy internal spin.py declares (spin.RCLPY_INTERNALS) has the shape spin.py
    uses, the declaration lists every one spin.py's source touches, and spin's calls work
    on a live subscription: wait on it, find it ready by pointer, drain its raw bytes."""
    adapt = ('kneeseat_ros/spin.py relies on rclpy internals that changed in the installed '
             'rclpy: adapt spin.py (and its RCLPY_INTERNALS) to it')
    source = inspect.getsource(spin)
    used = {*re.findall(r'_rclpy\.(\w+)', source), *re.findall(r'wait_set\.(\w+)', source),
            *re.findall(r'handle\.(\w+)', source)}
    declared = {name for i in spin.RCLPY_INTERNALS
                for name in (i.name, i.owner.rsplit('.', 1)[-1])}
    assert used <= declared, (f'spin.py uses {sorted(used - declared)} without declaring '
                              'them in RCLPY_INTERNALS')
    node = rclpy.create_node('rclpy_internals', context=context)
    try:
        sub = node.create_subscription(PoseStamped, 'internals', lambda msg: None, RELIABLE,
                                       raw=True)
        pub = node.create_publisher(PoseStamped, 'internals', RELIABLE)
        guard = GuardCondition(None, None, context=context)
        live = {'rclpy.subscription.Subscription': sub,
                'rclpy.guard_condition.GuardCondition': guard,
                'rclpy.context.Context': context}
        # the checker itself tells a changed signature and a missing name
        wait = next(i for i in spin.RCLPY_INTERNALS if i.name == 'wait')
        assert _internal_problem(spin.RclpyInternal(wait.owner, 'wait', 'method', ('str',),
                                                    'None'), live)
        assert _internal_problem(spin.RclpyInternal(wait.owner, 'wait_for_ever', 'method'),
                                 live)
        problems = [f'{i.owner}.{i.name} (used in {i.use}): {problem}'
                    for i in spin.RCLPY_INTERNALS
                    if (problem := _internal_problem(i, live)) is not None]
        assert not problems, adapt + ':\n' + '\n'.join(problems)
        # spin.py's calls, as _wait_loop and drain make them
        wait_set = _resolve(wait.owner)(1, 1, 0, 0, 0, 0, context.handle)
        msg = pose_stamped((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), stamp_from_ns(7), 'femur')
        deadline = time.monotonic() + 20.0
        with sub.handle, guard.handle, context.handle:
            ready: list[Any] = []
            while sub.handle.pointer not in ready:      # published again until matched
                assert time.monotonic() < deadline, (
                    f'{adapt}: published messages never made the wait set report the '
                    f'subscription ready (get_ready_entities gave {ready!r})')
                pub.publish(msg)
                wait_set.clear_entities()
                wait_set.add_subscription(sub.handle)
                wait_set.add_guard_condition(guard.handle)
                wait_set.wait(200_000_000)
                ready = wait_set.get_ready_entities('subscription')
            taken: list[Any] = []
            spin.drain(sub, taken.append)      # until take_message gives None
            assert taken and all(isinstance(t, bytes) for t in taken), (
                f'{adapt}: take_message(msg_type, raw=True) gave {taken!r}, not (bytes, '
                'info) tuples, then None')
            assert deserialize_message(taken[0], PoseStamped) == msg
            guard.trigger()
            wait_set.clear_entities()
            wait_set.add_subscription(sub.handle)
            wait_set.add_guard_condition(guard.handle)
            wait_set.wait(10_000_000_000)
            assert guard.handle.pointer in wait_set.get_ready_entities('guard_condition'), (
                f'{adapt}: a triggered guard condition did not end the wait')
    finally:
        node.destroy_node()
