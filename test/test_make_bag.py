"""make_bag: angle bags from CSV files and generated trajectories; the shipped demo bag."""
from __future__ import annotations

import os
from pathlib import Path
import re
import subprocess
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores

from conftest import assert_same_poses, REPO
from kneeseat_core.geometry import KneeAxes, matrix_from_quat, rotation_angle
from kneeseat_ros.bag.make_bag import DEFAULT_START_NS, gait, main, sweep

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
TKA_AXES = KneeAxes.from_vectors([0, 0, 1], [1, 0, 0], [0, 1, 0])
pytestmark = pytest.mark.usefixtures('ament_prefix')     # conftest: venv on the ament path


def read_poses(bag: Path) -> list[tuple[str, int, object]]:
    with Reader(bag) as reader:
        return [(c.topic, t, TYPESTORE.deserialize_cdr(raw, c.msgtype))
                for c, t, raw in reader.messages()]


def angles(msg: object, axes: KneeAxes = TKA_AXES) -> tuple[float, float]:
    q = msg.pose.orientation  # type: ignore[attr-defined]
    flexion, varus, rotation = axes.decompose(matrix_from_quat([q.x, q.y, q.z, q.w]))
    assert abs(float(rotation)) < 1e-9
    return float(np.degrees(flexion)), float(np.degrees(varus))


def test_csv_to_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / 'angles.csv'
    csv.write_text('time_s,flexion_deg,varus_deg\n0.0,0,0\n0.5,-30,2.5\n1.25,-60.5,-1\n')
    assert main([str(tmp_path / 'bag'), '--csv', str(csv), '--start-ns', '1000']) == 0
    assert 'wrote 3 messages' in capsys.readouterr().out
    got = read_poses(tmp_path / 'bag')
    assert [(topic, t) for topic, t, _ in got] == [
        ('/knee/pose', 1000), ('/knee/pose', 1000 + 500_000_000),
        ('/knee/pose', 1000 + 1_250_000_000)]
    assert [tuple(round(a, 9) for a in angles(m)) for _, _, m in got] == [
        (0.0, 0.0), (-30.0, 2.5), (-60.5, -1.0)]
    stamp = got[1][2].header.stamp
    assert (stamp.sec, stamp.nanosec) == (0, 500_001_000)
    assert got[0][2].header.frame_id == 'femur'


@pytest.mark.parametrize('body, fragment', [
    ('flexion_deg,varus_deg\n0,0\n', r'header lacks column\(s\) time_s'),
    ('time_s,flexion_deg,varus_deg\n0,0,0\n0.1,abc,0\n', r'angles.csv:3: .* is not numeric'),
    ('time_s,flexion_deg,varus_deg\n0,0,0\n0.1,0\n', r'angles.csv:3: 2 fields'),
    ('time_s,flexion_deg,varus_deg\n0,0,0\n0,1,0\n', r'angles.csv:3: time_s 0.0 does not'),
    ('time_s,flexion_deg,varus_deg\n0,nan,0\n', r'angles.csv:2: values must be finite'),
    ('time_s,flexion_deg,varus_deg\n', 'has a header but no rows'),
    ('', 'is empty'),
])
def test_bad_csv_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                    body: str, fragment: str) -> None:
    csv = tmp_path / 'angles.csv'
    csv.write_text(body)
    assert main([str(tmp_path / 'bag'), '--csv', str(csv)]) == 2
    err = capsys.readouterr().err
    assert err.startswith('make_bag: error: ') and err.count('\n') == 1
    assert 'Traceback' not in err
    assert re.search(fragment, err), err
    assert not (tmp_path / 'bag').exists()


def test_bad_axes_and_used_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / 'a'), '--trajectory', 'sweep', '--axes', '1,0,0/1,0,0/0,1,0']
                ) == 2
    assert 'not orthogonal' in capsys.readouterr().err
    (tmp_path / 'used').mkdir()
    (tmp_path / 'used' / 'x').write_text('x')
    assert main([str(tmp_path / 'used'), '--trajectory', 'sweep']) == 2
    assert 'already exists and is not empty' in capsys.readouterr().err


def test_sweep_trajectory_with_leading_minus_axes(tmp_path: Path) -> None:
    axes = KneeAxes.from_vectors([-1, 0, 0], [0, 0, 1], [0, 1, 0])
    assert main([str(tmp_path / 'bag'), '--trajectory', 'sweep', '--duration-s', '4',
                 '--rate-hz', '10', '--axes', '-1,0,0/0,0,1/0,1,0', '--frame', 'f2']) == 0
    got = read_poses(tmp_path / 'bag')
    assert len(got) == 41
    flexion = np.array([angles(m, axes)[0] for _, _, m in got])
    assert flexion[0] == pytest.approx(0.0, abs=1e-9)
    assert flexion[20] == pytest.approx(-90.0, abs=1e-6)          # turn at mid-time
    assert flexion[-1] == pytest.approx(0.0, abs=1e-6)
    assert np.all(np.diff(flexion[:21]) < 0) and np.all(np.diff(flexion[20:]) > 0)
    assert got[0][2].header.frame_id == 'f2'
    assert got[-1][1] - got[0][1] == 4_000_000_000


def test_gait_trajectory_shape() -> None:
    track = gait(3.0, 100.0)
    flexion, varus = np.degrees(track.flexion_rad), np.degrees(track.varus_rad)
    assert len(flexion) == 301
    assert -66.0 < flexion.min() < -60.0 and -8.0 < flexion.max() < -3.0
    assert np.allclose(flexion[:100], flexion[100:200])
    assert np.allclose(flexion[:100], flexion[200:300])
    peak = np.argmin(flexion[:100])
    assert 65 <= peak <= 78                               # swing peak late in the cycle
    loading = np.argmin(flexion[:40])
    assert 10 <= loading <= 20 and flexion[loading] < flexion[0] - 5   # loading response
    assert 0.5 < np.abs(varus).max() <= 2.0
    step = np.abs(np.diff(flexion)).max()
    assert step < 4.0                                     # smooth at 100 Hz
    assert len(sweep(1.0, 10.0).time_s) == 11


def test_gait_bag_with_joint_states(tmp_path: Path) -> None:
    assert main([str(tmp_path / 'bag'), '--trajectory', 'gait', '--duration-s', '1',
                 '--joint-states']) == 0
    got = read_poses(tmp_path / 'bag')
    assert len(got) == 2 * 101
    poses = [m for topic, _, m in got if topic == '/knee/pose']
    joints = [m for topic, _, m in got if topic == '/knee/joint_states']
    for p, j in zip(poses, joints):
        assert list(j.name) == ['knee_flexion', 'knee_varus']
        flexion, varus = angles(p)
        assert np.degrees(j.position) == pytest.approx([flexion, varus], abs=1e-9)
    assert got[0][1] == DEFAULT_START_NS


def test_table_axes(tmp_path: Path) -> None:
    from kneeseat_core.table import PoseTable
    from kneeseat_core.table import SCHEMA
    from kneeseat_core.table import write_table
    axes = {'flexion': [1.0, 0.0, 0.0], 'varus': [0.0, 0.0, 1.0], 'long': [0.0, 1.0, 0.0]}
    meta = {'schema': SCHEMA, 'kneeseat_version': '0', 'axes': axes,
            'reference': {'name': 'femur', 'frame': 'femur_ref', 'mesh': 'f.stl',
                          'mesh_sha256': ''},
            'bodies': [{'name': 'tibia', 'frame': 'tibia', 'mesh': 't.stl', 'mesh_sha256': '',
                        'display_mesh': None}],
            'config': {}, 'settle': {}, 'arrays_sha256': '', 'built': '', 'summary': {}}
    f, v = np.radians([-10.0, 0.0]), np.radians([-5.0, 5.0])
    table = PoseTable(f, v, np.zeros((1, 2, 2, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (1, 2, 2, 1)),
                      np.ones((1, 2, 2), bool), np.ones((1, 2, 2), np.int64), meta)
    path = tmp_path / 'knee.npz'
    write_table(path, table)
    csv = tmp_path / 'a.csv'
    csv.write_text('time_s,flexion_deg,varus_deg\n0,-20,3\n')
    assert main([str(tmp_path / 'bag'), '--csv', str(csv), '--table', str(path)]) == 0
    (_, _, msg), = read_poses(tmp_path / 'bag')
    assert msg.header.frame_id == 'femur_ref'
    q = msg.pose.orientation
    want = KneeAxes.from_vectors(**axes).orientation(np.radians(-20.0), np.radians(3.0))
    assert rotation_angle(matrix_from_quat([q.x, q.y, q.z, q.w]), want) < 1e-9


def test_demo_bag_regenerates(tmp_path: Path) -> None:
    shipped = REPO / 'data' / 'angle_bags' / 'gait_demo'
    out = tmp_path / 'gait_demo'
    env = dict(os.environ, AMENT_PREFIX_PATH=os.pathsep.join(
        filter(None, [sys.prefix, os.environ.get('AMENT_PREFIX_PATH', '')])))
    done = subprocess.run([str(REPO / 'scripts' / 'make_demo_bag'), str(out)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    names = sorted(p.name for p in shipped.iterdir())
    assert names == ['gait_demo_0.mcap', 'metadata.yaml']
    assert sorted(p.name for p in out.iterdir()) == names
    assert (out / 'metadata.yaml').read_bytes() == (shipped / 'metadata.yaml').read_bytes()
    assert_same_poses(out, shipped)
    assert sum(p.stat().st_size for p in shipped.iterdir()) < 1_000_000
    got = read_poses(shipped)
    assert len(got) == 1001 and got[-1][1] - got[0][1] == 10_000_000_000
