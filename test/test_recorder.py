"""BagRecorder: rosbag2-style MCAP bags read back by rosbags and by mcap's own reader."""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap

from conftest import REPO, track_child
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import pytest
from rclpy.qos import qos_profile_sensor_data, QoSProfile
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import JointState
import yaml

from kneeseat_ros.errors import RecorderError
from kneeseat_ros.cdr import serialize
from kneeseat_ros.bag.msgdefs import message_definition, qos_to_dicts, SEPARATOR, type_hash
from kneeseat_ros.bag.recorder import BagRecorder
from kneeseat_ros.bag.recovery import read_readable, recover

T0 = 1_700_000_000_000_000_000
SHA = 'ab' * 32
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
pytestmark = pytest.mark.usefixtures('ament_prefix')     # conftest: venv on the ament path


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        filter(None, [sys.prefix, os.environ.get('AMENT_PREFIX_PATH', '')]))
    env['PYTHONPATH'] = os.pathsep.join(
        filter(None, [str(REPO), os.environ.get('PYTHONPATH')]))
    return env


def pose(i: int) -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, i * 1000
    msg.header.frame_id = 'femur'
    msg.pose.position.x = float(i)
    msg.pose.orientation.z, msg.pose.orientation.w = 0.6, 0.8
    return msg


def joints(i: int) -> JointState:
    return JointState(name=['knee_flexion', 'knee_varus'], position=[-0.01 * i, 0.001 * i])


def diagnostics(i: int) -> DiagnosticArray:
    status = DiagnosticStatus(level=DiagnosticStatus.WARN, name='kneeseat', message=f'tick {i}',
                              values=[KeyValue(key='clamped', value=str(i))])
    return DiagnosticArray(status=[status])


def test_round_trip_three_types(tmp_path: Path) -> None:
    bag = tmp_path / 'session'
    written: list[tuple[str, object, int]] = []
    with BagRecorder(bag, table_sha256=SHA, table_path='/tables/knee.npz') as rec:
        rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped', qos_profile_sensor_data)
        rec.add_topic('/knee/joint_states', 'sensor_msgs/msg/JointState')
        rec.add_topic('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', QoSProfile(depth=1))
        rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')      # idempotent
        for i in range(30):
            t = T0 + i * 10_000_000
            for topic, msg in (('/knee/pose', pose(i)), ('/knee/joint_states', joints(i))):
                rec.write(topic, msg, t, t - 1000)
                written.append((topic, msg, t))
            if i % 10 == 0:
                rec.write('/diagnostics', diagnostics(i), t + 5, t + 5)
                written.append(('/diagnostics', diagnostics(i), t + 5))
    assert rec.error is None and rec.message_count == len(written) == 63
    assert rec.paths == [bag / 'session_0.mcap']

    # rosbags: the independent reader (it refuses files whose profile is not ros2)
    with Reader(bag) as reader:
        assert reader.message_count == 63
        got = [(c.topic, TYPESTORE.deserialize_cdr(raw, c.msgtype), t)
               for c, t, raw in reader.messages()]
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in reader.connections}
        hashes = {c.topic: c.digest for c in reader.connections}
    assert [(topic, t) for topic, _, t in got] == [(topic, t) for topic, _, t in written]
    for (topic, theirs, _), (_, ours, _) in zip(got, written):
        if topic == '/knee/pose':
            assert theirs.header.frame_id == ours.header.frame_id
            assert theirs.pose.position.x == ours.pose.position.x
            assert theirs.header.stamp.nanosec == ours.header.stamp.nanosec
        elif topic == '/knee/joint_states':
            assert list(theirs.name) == ours.name
            assert list(theirs.position) == list(ours.position)
        else:
            assert theirs.status[0].message == ours.status[0].message
            assert theirs.status[0].values[0].value == ours.status[0].values[0].value
    assert qos['/knee/pose'].reliability.name == 'BEST_EFFORT'
    assert qos['/knee/pose'].depth == 5
    assert qos['/diagnostics'].reliability.name == 'RELIABLE'
    assert hashes['/knee/pose'] == type_hash('geometry_msgs/msg/PoseStamped')

    # mcap's own reader: profile, schemas, channel metadata, decoded content, table hash
    with open(bag / 'session_0.mcap', 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 63
        assert len(summary.chunk_indexes) >= 1
        for schema in summary.schemas.values():
            assert schema.encoding == 'ros2msg'
            assert schema.data.decode() == message_definition(schema.name)
        for channel in summary.channels.values():
            assert channel.message_encoding == 'cdr'
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            offered = yaml.safe_load(channel.metadata['offered_qos_profiles'])
            assert offered[0]['history'] == 'keep_last'
            assert set(offered[0]) >= {'deadline', 'lifespan', 'liveliness_lease_duration',
                                       'avoid_ros_namespace_conventions', 'durability'}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta['kneeseat'] == {'table_sha256': SHA, 'table_path': '/tables/knee.npz'}
        decoded = [(c.topic, m.log_time, m.publish_time, d)
                   for _, c, m, d in reader.iter_decoded_messages()]
    assert [(c, t) for c, t, _, _ in decoded] == [(topic, t) for topic, _, t in written]
    assert decoded[0][2] == decoded[0][1] - 1000            # publish_time kept apart
    diag = [d for c, _, _, d in decoded if c == '/diagnostics']
    assert [d.status[0].message for d in diag] == ['tick 0', 'tick 10', 'tick 20']
    assert diag[1].status[0].level == DiagnosticStatus.WARN[0]

    # metadata.yaml agrees with the file
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == ['session_0.mcap']
    assert info['message_count'] == 63
    assert info['starting_time']['nanoseconds_since_epoch'] == T0
    assert info['duration']['nanoseconds'] == 29 * 10_000_000
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in info['topics_with_message_count']}
    assert counts == {'/knee/pose': 30, '/knee/joint_states': 30, '/diagnostics': 3}
    assert info['files'] == [{'path': 'session_0.mcap',
                              'starting_time': {'nanoseconds_since_epoch': T0},
                              'duration': {'nanoseconds': 29 * 10_000_000},
                              'message_count': 63}]
    assert info['custom_data']['kneeseat.table_sha256'] == SHA


def test_schema_text_lists_dependencies_once_depth_first() -> None:
    text = message_definition('geometry_msgs/msg/PoseStamped')
    names = [part.split('\n', 1)[0] for part in text.split(f'\n{SEPARATOR}\nMSG: ')[1:]]
    assert names == ['geometry_msgs/Pose', 'geometry_msgs/Point', 'geometry_msgs/Quaternion',
                     'std_msgs/Header', 'builtin_interfaces/Time']
    assert text.startswith('# A Pose with reference coordinate frame and timestamp')
    diag = message_definition('diagnostic_msgs/msg/DiagnosticArray')
    assert diag.count('MSG: diagnostic_msgs/KeyValue') == 1


@pytest.mark.parametrize('msg', [pose(7), joints(7), diagnostics(7)],
                         ids=['PoseStamped', 'JointState', 'DiagnosticArray'])
def test_cdr_bytes_are_canonical(msg: object) -> None:
    data = serialize(msg)
    assert deserialize_message(data, type(msg)) == msg
    name = f'{type(msg).__module__.split(".")[0]}/msg/{type(msg).__name__}'
    assert bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(data, name), name)) == data


def test_qos_dicts_use_v9_strings() -> None:
    (best,) = qos_to_dicts(qos_profile_sensor_data)
    assert best['history'] == 'keep_last' and best['depth'] == 5
    assert best['reliability'] == 'best_effort' and best['durability'] == 'volatile'
    assert best['deadline'] == {'sec': 0, 'nsec': 0}
    assert best['avoid_ros_namespace_conventions'] is False


def test_split_by_size_lists_every_file(tmp_path: Path) -> None:
    bag = tmp_path / 'sized'
    with BagRecorder(bag, split_size_bytes=6000, chunk_size_bytes=1500) as rec:
        rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')
        for i in range(400):
            rec.write('/knee/pose', pose(i), T0 + i * 1_000_000, T0 + i * 1_000_000)
    assert len(rec.paths) >= 3
    assert [p.name for p in rec.paths] == [f'sized_{i}.mcap' for i in range(len(rec.paths))]
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['relative_file_paths'] == [p.name for p in rec.paths]
    assert sum(f['message_count'] for f in info['files']) == 400
    for path in rec.paths[:-1]:            # each finished file stopped near the limit
        assert 6000 <= path.stat().st_size < 6000 + 3 * 1500
    with Reader(bag) as reader:
        xs = [TYPESTORE.deserialize_cdr(raw, c.msgtype).pose.position.x
              for c, _, raw in reader.messages()]
    assert xs == [float(i) for i in range(400)]


def test_split_by_duration(tmp_path: Path) -> None:
    bag = tmp_path / 'timed'
    with BagRecorder(bag, split_duration_s=1.0) as rec:
        rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')
        for i in range(35):                 # 3.4 s at 10 Hz -> files of 1 s each
            rec.write('/knee/pose', pose(i), T0 + i * 100_000_000, T0)
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert [f['message_count'] for f in info['files']] == [10, 10, 10, 5]
    assert all(f['duration']['nanoseconds'] < 1_000_000_000 for f in info['files'])
    assert info['files'][1]['starting_time']['nanoseconds_since_epoch'] == T0 + 10**9
    with Reader(bag) as reader:
        assert reader.message_count == 35
        assert len(list(reader.messages())) == 35


def test_unwritable_or_used_directory_raises(tmp_path: Path) -> None:
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    with pytest.raises(RecorderError, match=r'cannot create bag directory .*a_file/bag'):
        BagRecorder(blocker / 'bag')
    used = tmp_path / 'used'
    used.mkdir()
    (used / 'other.txt').write_text('x')
    with pytest.raises(RecorderError, match='already exists and is not empty'):
        BagRecorder(used)


def test_unknown_type_and_topic_raise(tmp_path: Path) -> None:
    with BagRecorder(tmp_path / 'bag') as rec:
        with pytest.raises(RecorderError, match='not of the form pkg/msg/Type'):
            rec.add_topic('/x', 'PoseStamped')
        with pytest.raises(RecorderError, match="'nosuch_msgs' .* not found"):
            rec.add_topic('/x', 'nosuch_msgs/msg/Thing')
        with pytest.raises(RecorderError, match='was not added'):
            rec.write('/knee/pose', pose(0), T0, T0)


DISK_FULL = textwrap.dedent("""
    import json, resource, signal, sys
    from pathlib import Path
    from geometry_msgs.msg import PoseStamped
    from kneeseat_ros.bag.recorder import BagRecorder
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)      # a failing write, not a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
    rec = BagRecorder(Path(sys.argv[1]), chunk_size_bytes=2000)
    rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')
    counts = []
    for i in range(2000):
        msg = PoseStamped()
        msg.header.frame_id = 'femur' * 10
        rec.write('/knee/pose', msg, 1000 + i, 1000 + i)
        counts.append(rec.message_count)
    rec.close()
    rec.close()
    print(json.dumps({'error': rec.error, 'count': rec.message_count, 'last': counts[-50:]}))
""")


def test_disk_full_sets_error_and_stops(tmp_path: Path) -> None:
    script = tmp_path / 'disk_full.py'
    script.write_text(DISK_FULL)
    out = subprocess.run([sys.executable, str(script), str(tmp_path / 'bag')], env=_env(),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert 'File too large' in result['error'] and 'stopped after' in result['error']
    assert 0 < result['count'] < 2000
    assert set(result['last']) == {result['count']}          # writing stopped, no raise
    assert '\n' not in result['error']


WRITER = textwrap.dedent("""
    import signal, sys, threading
    from pathlib import Path
    from geometry_msgs.msg import PoseStamped
    from kneeseat_ros.bag.recorder import BagRecorder
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    rec = BagRecorder(Path(sys.argv[1]), chunk_size_bytes=2000, table_sha256='cafe')
    rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')
    i = 0
    while not stop.is_set() and i < 2_000_000:
        msg = PoseStamped()
        msg.pose.position.x = float(i)
        rec.write('/knee/pose', msg, 10**18 + i * 10**6, 10**18 + i * 10**6)
        i += 1
        if i == 500:
            print('ready', flush=True)
    rec.close()
    print(rec.message_count, flush=True)
""")


def _start_writer(tmp_path: Path, bag: Path) -> subprocess.Popen[str]:
    script = tmp_path / 'writer.py'
    script.write_text(WRITER)
    proc = track_child(subprocess.Popen([sys.executable, str(script), str(bag)], env=_env(),
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        text=True))
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == 'ready', proc.stderr.read() if proc.stderr else ''
    return proc


def test_sigkill_leaves_readable_chunks_and_recover_completes(tmp_path: Path) -> None:
    bag = tmp_path / 'crashed'
    proc = _start_writer(tmp_path, bag)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert not (bag / 'metadata.yaml').exists()
    content = read_readable(bag / 'crashed_0.mcap')
    assert not content.complete and content.problem
    xs = [TYPESTORE.deserialize_cdr(m.data, 'geometry_msgs/msg/PoseStamped').pose.position.x
          for m in content.messages]
    assert len(xs) >= 480                      # at most one 2 kB chunk (~18 msgs) lost
    assert xs == [float(i) for i in range(len(xs))]

    report = recover(bag)
    assert report.output == tmp_path / 'crashed_recovered'
    assert report.messages == len(xs) and report.damaged == ('crashed_0.mcap',)
    with Reader(report.output) as reader:
        got = [TYPESTORE.deserialize_cdr(raw, c.msgtype).pose.position.x
               for c, _, raw in reader.messages()]
        assert reader.connections[0].digest == type_hash('geometry_msgs/msg/PoseStamped')
    assert got == xs
    with open(report.output / 'crashed_recovered_0.mcap', 'rb') as stream:
        meta = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert meta['kneeseat']['table_sha256'] == 'cafe'


def test_sigterm_leaves_a_complete_bag(tmp_path: Path) -> None:
    bag = tmp_path / 'stopped'
    proc = _start_writer(tmp_path, bag)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    count = int(stdout.split()[-1])
    assert count >= 500
    assert read_readable(bag / 'stopped_0.mcap').complete
    with Reader(bag) as reader:
        assert reader.message_count == count
        assert sum(1 for _ in reader.messages()) == count


def test_recover_cli_reports_missing_bag(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    from kneeseat_ros.bag.recovery import main
    assert main([str(tmp_path / 'nothing')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('recover: error: no .mcap file found') and err.count('\n') == 1
