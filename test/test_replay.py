"""replay: clear errors for bad bags; a real replay over Fast DDS with scaled timing."""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import time

from conftest import spin_until, track_child
from geometry_msgs.msg import PoseStamped
from mcap.writer import Writer
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy

from kneeseat_ros.bag.make_bag import main as make_bag
from kneeseat_ros.bag.recorder import BagRecorder
from kneeseat_ros.bag.replay import load_messages, main

# conftest.domain_id: own domain, loopback discovery and the venv prefix on the ament path,
# set in os.environ for every test (the replay subprocess inherits it)
pytestmark = pytest.mark.usefixtures('domain_id')


@pytest.fixture
def sweep_bag(tmp_path: Path) -> Path:
    """A 2 s flexion sweep at 10 Hz (21 messages) on /knee/pose."""
    bag = tmp_path / 'sweep'
    assert make_bag([str(bag), '--trajectory', 'sweep', '--duration-s', '2',
                     '--rate-hz', '10', '--start-ns', '5000000000']) == 0
    return bag


def run_main(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith('replay: error: ') and err.count('\n') == 1, err
    assert 'Traceback' not in err
    return err


def test_missing_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert 'does not exist' in run_main([str(tmp_path / 'nope')], capsys)


def test_directory_without_metadata(tmp_path: Path, sweep_bag: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert 'no metadata.yaml' in run_main([str(tmp_path)], capsys)
    (sweep_bag / 'metadata.yaml').unlink()
    assert 'recover' in run_main([str(sweep_bag)], capsys)


def test_metadata_listing_a_missing_file(sweep_bag: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    (sweep_bag / 'sweep_0.mcap').rename(sweep_bag / 'elsewhere.mcap')
    assert 'misses sweep_0.mcap' in run_main([str(sweep_bag)], capsys)


def test_empty_and_non_mcap_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / 'empty.mcap'
    empty.write_bytes(b'')
    assert 'is empty' in run_main([str(empty)], capsys)
    text = tmp_path / 'notes.mcap'
    text.write_text('hello, this is not an MCAP file at all\n')
    assert 'not a readable MCAP file' in run_main([str(text)], capsys)


def test_profile_not_ros2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / 'json.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='', library='test')
        schema = writer.register_schema('Pose', 'jsonschema', b'{}')
        channel = writer.register_channel('/knee/pose', 'json', schema)
        writer.add_message(channel, log_time=1, data=b'{}', publish_time=1)
        writer.finish()
    assert "profile '', not ros2" in run_main([str(path)], capsys)


def test_truncated_file(sweep_bag: Path, tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / 'cut.mcap'
    data = (sweep_bag / 'sweep_0.mcap').read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    err = run_main([str(cut)], capsys)
    assert 'recover' in err or 'not a readable MCAP file' in err


def test_no_matching_topics_and_bad_rate(sweep_bag: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    err = run_main([str(sweep_bag), '--topics', '/other'], capsys)
    assert 'no message on /other (it has: /knee/pose)' in err
    assert 'positive' in run_main([str(sweep_bag), '--rate', '0'], capsys)


def test_load_messages_from_directory_and_single_file(tmp_path: Path) -> None:
    bag = tmp_path / 'multi'
    with BagRecorder(bag, split_duration_s=0.5) as rec:
        rec.add_topic('/knee/pose', 'geometry_msgs/msg/PoseStamped')
        rec.add_topic('/knee/tibia/pose', 'geometry_msgs/msg/PoseStamped')
        for i in range(20):
            rec.write('/knee/pose', PoseStamped(), 10**9 + i * 10**8, 0)
            rec.write('/knee/tibia/pose', PoseStamped(), 10**9 + i * 10**8 + 1, 0)
    assert len(rec.paths) == 4
    inputs = load_messages(bag)
    assert [m.topic for m in inputs] == ['/knee/pose'] * 20        # outputs are not replayed
    assert [m.log_time_ns for m in inputs] == [10**9 + i * 10**8 for i in range(20)]
    single = load_messages(rec.paths[1], None)
    assert len(single) == 10 and {m.topic for m in single} == {'/knee/pose', '/knee/tibia/pose'}


def _replay(bag: Path, *extra: str) -> subprocess.Popen[str]:
    return track_child(subprocess.Popen(
        [sys.executable, '-m', 'kneeseat_ros.bag.replay', str(bag), '--wait-for-subscribers', '2',
         '--wait-timeout-s', '30', *extra],
        env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))


def _subscribe(context: Context) -> tuple[SingleThreadedExecutor, dict[str, list]]:
    node = rclpy.create_node('replay_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    got: dict[str, list] = {'reliable': [], 'best_effort': []}
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    for key, qos in (('reliable', reliable), ('best_effort', qos_profile_sensor_data)):
        node.create_subscription(
            PoseStamped, '/knee/pose',
            lambda msg, key=key: got[key].append((time.monotonic(), msg)), qos)
    return executor, got


def _stamps(items: list) -> list[int]:
    return [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in items]


@pytest.mark.ros
def test_replay_over_dds_in_order_with_scaled_timing(context: Context, sweep_bag: Path) -> None:
    executor, got = _subscribe(context)
    want = [5_000_000_000 + i * 100_000_000 for i in range(21)]
    proc = _replay(sweep_bag, '--rate', '10')
    try:
        spin_until(executor, lambda: len(got['reliable']) >= 21 and
                   len(got['best_effort']) >= 21 or proc.poll() not in (None, 0), 60.0)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert _stamps(got['reliable']) == want
    assert _stamps(got['best_effort']) == want
    span = got['reliable'][-1][0] - got['reliable'][0][0]
    print(f'replay of a 2 s bag at x10 took {span:.3f} s between first and last message')
    assert 0.1 < span < 1.0, span                 # 2 s of bag at x10 = 0.2 s
    assert 'published 21 messages' in stderr


@pytest.mark.ros
def test_replay_loops_a_bounded_number_of_times(context: Context, sweep_bag: Path) -> None:
    executor, got = _subscribe(context)
    want = [5_000_000_000 + i * 100_000_000 for i in range(21)]
    proc = _replay(sweep_bag, '--rate', '20', '--loop', '2', '--quiet')
    try:
        spin_until(executor, lambda: len(got['reliable']) >= 42
                   or proc.poll() not in (None, 0), 60.0)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert _stamps(got['reliable']) == want + want
    assert stderr.count('\n') <= 1                # --quiet: at most the startup log line
