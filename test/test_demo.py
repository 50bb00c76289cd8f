"""The full demo: build -> table_server recording -> replay -> stop -> summary and plot.

The end-to-end test is the round trip: generated bag -> replay -> node ->
recording; the recording is read back with an independent reader (rosbags) and every output
equals the interpolation of its input; metadata.yaml's counts and time ranges match the file.
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path
import re
import shutil
import struct
import subprocess
import sys

from conftest import next_domain_id, REPO, ros_env, SHARED_DATA
import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores
import yaml

from kneeseat_core.geometry import matrix_from_quat
from kneeseat_core.report.plots import SESSION_SIZE_PX
from kneeseat_core.table import PoseTable, read_table
from kneeseat_ros.demos.demo import main, PLOT_NAME
from kneeseat_ros.demos.demo_table import demo_bag, prepare_table
from kneeseat_ros.bag.replay import load_messages

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
SHIPPED = REPO / 'data' / 'angle_bags' / 'gait_demo'
STEP_DEG = 10.0          # 10 x 3 grid: seconds to build
DEMO_TIMEOUT_S = 300.0


def run_demo(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """`python -m kneeseat_ros.demos.demo` in its own ROS domain; fails the test on a hang."""
    env = ros_env(next_domain_id())
    return subprocess.run(
        [sys.executable, '-m', 'kneeseat_ros.demos.demo', '--out', str(out), '--grid-step-deg',
         f'{STEP_DEG:g}', '--quiet', *extra],
        env=env, capture_output=True, text=True, timeout=DEMO_TIMEOUT_S, cwd=REPO)


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    head = path.read_bytes()[:24]
    assert head[:8] == b'\x89PNG\r\n\x1a\n' and head[12:16] == b'IHDR'
    width, height = struct.unpack('>II', head[16:24])
    return width, height


def summary_value(stdout: str, pattern: str) -> str:
    match = re.search(pattern, stdout)
    assert match is not None, f'{pattern!r} not in the summary:\n{stdout}'
    return match.group(1)


def check_session(bag: Path, table: PoseTable, sent: int) -> dict[str, int]:
    """Read `bag` with rosbags; check outputs against the table and metadata.yaml."""
    inputs: dict[int, np.ndarray] = {}
    outputs: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {b: {} for b in table.bodies}
    counts: Counter[str] = Counter()
    times: list[int] = []
    with Reader(bag) as reader:
        for conn, t, raw in reader.messages():
            msg = TYPESTORE.deserialize_cdr(raw, conn.msgtype)
            counts[conn.topic] += 1
            times.append(t)
            if conn.topic == '/knee/pose':
                assert msg.header.frame_id == table.reference_frame
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                assert stamp not in inputs
                o = msg.pose.orientation
                inputs[stamp] = np.array([o.x, o.y, o.z, o.w])
            elif conn.topic.startswith('/knee/') and conn.topic.endswith('/pose'):
                body = conn.topic.split('/')[2]
                assert msg.header.frame_id == table.reference_frame
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                p, o = msg.pose.position, msg.pose.orientation
                outputs[body][stamp] = (np.array([p.x, p.y, p.z]),
                                        np.array([o.x, o.y, o.z, o.w]))
    # Every input answered once per body, and nothing else. The node's input is best effort
    # with a 50-deep queue: a stall longer than 50 samples (a loaded, shared machine) loses
    # the oldest ones. The demo reports that count; here it must stay small.
    assert 0.9 * sent <= len(inputs) <= sent, (len(inputs), sent)
    for body in table.bodies:
        assert set(outputs[body]) == set(inputs), body
    # every output equals the table's interpolation of its input (own decode of the angles)
    stamps = sorted(inputs)
    quats = np.stack([inputs[s] for s in stamps])
    flexion, varus, _ = table.axes.decompose(matrix_from_quat(quats))
    worst = 0.0
    for k, stamp in enumerate(stamps):
        look = table.interpolate(float(flexion[k]), float(varus[k]))
        for i, body in enumerate(table.bodies):
            pos, quat = outputs[body][stamp]
            worst = max(worst, float(np.abs(pos - look.position_m[i]).max()),
                        float(np.abs(quat - look.orientation_xyzw[i]).max()))
    assert worst <= 1e-9
    assert np.ptp(np.degrees(flexion)) > 50.0      # the gait cycle really was replayed
    # metadata.yaml agrees with what is in the file(s)
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    listed = {t['topic_metadata']['name']: t['message_count']
              for t in info['topics_with_message_count'] if t['message_count']}
    assert (info['message_count'], listed) == (sum(counts.values()), dict(counts)), bag
    assert info['starting_time']['nanoseconds_since_epoch'] == min(times)
    assert info['duration']['nanoseconds'] == max(times) - min(times)
    assert sorted(f['path'] for f in info['files']) == sorted(p.name for p in
                                                              bag.glob('*.mcap'))
    assert sum(f['message_count'] for f in info['files']) == sum(counts.values())
    if len(info['files']) == 1:
        only = info['files'][0]
        assert only['starting_time']['nanoseconds_since_epoch'] == min(times)
        assert only['duration']['nanoseconds'] == max(times) - min(times)
    assert counts['/diagnostics'] >= 1
    return {'in': len(inputs), 'out': sum(len(o) for o in outputs.values())}


@pytest.mark.slow
@pytest.mark.ros
def test_demo_round_trip_and_rerun(tmp_path: Path) -> None:
    out = tmp_path / 'demo'
    first = run_demo(out)
    assert first.returncode == 0, first.stderr[-3000:]
    assert 'Traceback' not in first.stderr
    table_path = out / f'default_knee_{STEP_DEG:g}deg.npz'
    table = read_table(table_path)
    assert (len(table.flexion_rad), len(table.varus_rad)) == (10, 3)
    sessions = sorted((out / 'sessions').iterdir())
    assert len(sessions) == 1
    assert str(sessions[0]) in first.stdout and str(out / PLOT_NAME) in first.stdout
    sent = len(load_messages(SHIPPED))
    counted = check_session(sessions[0], table, sent)
    # the demo's own summary agrees with the independent reader
    assert int(summary_value(first.stdout, r'messages +in (\d+) ')) == counted['in']
    assert int(summary_value(first.stdout, r', out (\d+) ')) == counted['out']
    assert int(summary_value(first.stdout, r'dropped (\d+)')) == 0
    p50 = float(summary_value(first.stdout, r'latency +p50 ([0-9.]+) ms'))
    p99 = float(summary_value(first.stdout, r'p99 ([0-9.]+) ms'))
    assert 0.0 < p50 <= p99 < 1000.0
    png = out / PLOT_NAME
    assert png_size(png) == SESSION_SIZE_PX

    # idempotent: the table is reused, a new session is recorded, the plot rewritten
    second = run_demo(out, '--rate', '2')
    assert second.returncode == 0, second.stderr[-3000:]
    assert 'reused' in second.stdout and 'building' not in second.stdout
    assert read_table(table_path).sha256 == table.sha256
    sessions = sorted((out / 'sessions').iterdir())
    assert len(sessions) == 2
    check_session(sessions[-1], table, sent)
    assert png_size(png) == SESSION_SIZE_PX


@pytest.mark.slow
def test_damaged_or_other_grid_table_is_rebuilt(tmp_path: Path) -> None:
    path = tmp_path / f'default_knee_{STEP_DEG:g}deg.npz'
    path.write_bytes(b'not a table')
    built_path, table, how = prepare_table(tmp_path, STEP_DEG, 2, show_progress=False)
    assert built_path == path and how == 'built'
    assert read_table(path).sha256 == table.sha256
    again = prepare_table(tmp_path, STEP_DEG, 2, show_progress=False)
    assert again[2].startswith('reused') and again[1].sha256 == table.sha256
    # a table of another grid under the expected name is not served
    other = tmp_path / 'other'
    other.mkdir()
    shutil.copytree(tmp_path / 'default_knee', other / 'default_knee')
    shutil.copy(path, other / 'default_knee_5deg.npz')
    _, rebuilt, how = prepare_table(other, 5.0, 2, show_progress=False)
    assert how == 'built' and len(rebuilt.flexion_rad) == 19


def test_regenerated_bag_equals_shipped(tmp_path: Path) -> None:
    from conftest import assert_same_poses, synthetic_table
    table = synthetic_table()
    bag = demo_bag(tmp_path, table, shipped=tmp_path / 'no_repo')
    assert bag == tmp_path / 'angle_bags' / 'gait_demo'
    assert_same_poses(bag, SHIPPED)
    assert demo_bag(tmp_path, table, shipped=tmp_path / 'no_repo') == bag    # reused
    assert demo_bag(tmp_path, table) == SHIPPED


@pytest.mark.parametrize('argv', [['--grid-step-deg', '3'], ['--grid-step-deg', 'x'],
                                  ['--full-grid', '--grid-step-deg', '2'],
                                  ['--rate', '0'], ['--workers', '0']])
def test_bad_arguments_exit_2(argv: list[str], tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    try:
        code = main(['--out', str(tmp_path), *argv])
    except SystemExit as exc:       # argparse refuses it
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert 'Traceback' not in err and err.strip()
    assert not any(tmp_path.iterdir())       # nothing built, nothing started


def test_bad_bag_fails_before_the_build(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['--out', str(tmp_path), '--bag', str(tmp_path / 'nope'), '--quiet']) == 1
    err = capsys.readouterr().err
    assert err.startswith('demo: error: bag ') and err.count('\n') == 1, err
    assert 'does not exist' in err
    assert not list(tmp_path.glob('*.npz')) and not (tmp_path / 'default_knee').exists()


def test_natural_knee_without_its_meshes_is_one_line_and_exit_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(['--out', str(tmp_path / 'out'), '--knee', 'natural', '--mesh-dir',
                 str(tmp_path / 'nowhere'), '--quiet'])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith('demo: error: --knee natural needs the natural knee meshes: ')
    assert err.count('\n') == 1 and 'nowhere' in err and 'Traceback' not in err
    assert not list((tmp_path / 'out').glob('*.npz'))


NATURAL_DATA = SHARED_DATA / 'natural_knee'


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.skipif(not (NATURAL_DATA / 'femur_cartilage.stl').is_file(),
                    reason=f'natural knee meshes not found at {NATURAL_DATA}')
def test_demo_on_the_natural_knee(tmp_path: Path) -> None:
    out = tmp_path / 'demo'
    run = run_demo(out, '--knee', 'natural')
    assert run.returncode == 0, run.stderr[-3000:]
    table = read_table(out / f'natural_knee_{STEP_DEG:g}deg.npz')
    assert table.bodies == ('tibia', 'patella')
    assert len(table.metadata['bodies'][0]['meshes']) == 3        # cartilage + two menisci
    sessions = sorted((out / 'sessions').iterdir())
    assert len(sessions) == 1
    check_session(sessions[0], table, len(load_messages(SHIPPED)))
    assert int(summary_value(run.stdout, r'dropped (\d+)')) == 0
