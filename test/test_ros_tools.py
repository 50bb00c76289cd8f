"""The node with the real ROS tools PyPI lacks: /tf (tf2_msgs built with colcon) and `ros2`.

- tf2_msgs has no pip wheel; the shared build tool makes it from its message definition
  with colcon and the rosidl/ament_cmake wheels into a cached prefix (slow the first time,
  hence `slow`). Its typesupport libraries are found through LD_LIBRARY_PATH, which must be
  set before Python starts, so the node and the /tf subscriber run as subprocesses.
- The `ros2` command line (Jazzy ros2cli sources) is installed into a cached folder; the
  package is built with colcon (conftest.colcon_install), as a ROS user would, and driven
  with `ros2 run`, `ros2 topic pub/echo`, `ros2 param get` and `ros2 service call`.
Both skip with the reason when their tool (or a compiler) is missing.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys

from conftest import install_env, REPO, ros_env, track_child, write_synthetic_table
import numpy as np
import pytest
from ros_helpers import rigid, ServerProcess
import yaml

from kneeseat_core.table import read_table
from kneeseat_ros.demos.tracker_demo import (example_registration, expected_world, leg_motion,
                                             pose_matrix, registration_yaml)

pytestmark = pytest.mark.ros
TFMESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'


@pytest.mark.slow
def test_tf_carries_every_answer(tf2_msgs_env: dict[str, str], tmp_path: Path,
                                 domain_id: int) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=8)
    table = read_table(table_path)
    reg_f, reg_t = example_registration(seed=2)
    registration = tmp_path / 'registration.yaml'
    registration.write_text(registration_yaml(reg_f, reg_t))
    femur, tibia, _ = leg_motion(table.axes, 12, 1.0)
    femur_c, tibia_c = femur @ np.linalg.inv(reg_f), tibia @ np.linalg.inv(reg_t)
    stamps = [3 * 10**15 + k * 10**7 for k in range(len(femur))]
    spec = tmp_path / 'spec.json'
    spec.write_text(json.dumps({'pairs': [
        {'stamp': s, 'femur': list(rigid(f)), 'tibia': list(rigid(t))}
        for s, f, t in zip(stamps, femur_c, tibia_c)]}))
    env = ros_env(domain_id, tf2_msgs_env)
    srv = ServerProcess(tmp_path, domain_id, table_path,
                        f'tracker.registration:={registration}',
                        'tracker.pair_tolerance_s:=0.001', env=env, exact_env=True)
    try:
        done = subprocess.run([sys.executable, str(REPO / 'test' / 'tf_probe.py'), str(spec)],
                              capture_output=True, text=True, timeout=90, env=env)
        assert done.returncode == 0, done.stderr + srv.stderr()
    finally:
        srv.stop_clean()
    result = json.loads(done.stdout)
    assert result['types'] == ['tf2_msgs/msg/TFMessage']
    assert result['hash'] == [TFMESSAGE_HASH]
    worst = 0.0
    for k, stamp in enumerate(stamps):
        got = {(t[0], t[1]): np.array(t[2:]) for t in result['transforms'][str(stamp)]}
        want_f, want_b = expected_world(table, femur_c[k], tibia_c[k], reg_f, reg_t)
        want = {('world', 'femur'): want_f,
                **{('femur', frame): np.linalg.inv(want_f) @ b
                   for frame, b in zip(table.body_frames, want_b)}}
        assert set(got) == set(want)
        for key, m in want.items():
            g = pose_matrix(got[key][:3], got[key][3:])
            worst = max(worst, float(np.abs(g - m).max()))
    assert worst <= 1e-9, worst
    assert 'tf off' not in srv.stderr()


def _ros2(cli: Path, env: dict[str, str], *args: str, timeout_s: float = 60.0
          ) -> subprocess.CompletedProcess:
    return subprocess.run([str(cli / 'bin' / 'ros2'), *args], capture_output=True,
                          text=True, timeout=timeout_s, env=env)


def test_ros2_cli_drives_the_installed_node(ros2_cli: Path, colcon_install: Path,
                                            tmp_path: Path, domain_id: int) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=3)
    table = read_table(table_path)
    env = install_env(colcon_install, ros_env(domain_id))
    env['PYTHONPATH'] = os.pathsep.join([str(ros2_cli), env['PYTHONPATH']])
    params = colcon_install / 'share' / 'kneeseat_ros' / 'config' / 'table_server.yaml'
    log = tmp_path / 'run.log'
    with open(log, 'wb') as out:
        run = subprocess.Popen(
            [str(ros2_cli / 'bin' / 'ros2'), 'run', 'kneeseat_ros', 'table_server',
             '--ros-args', '--params-file', str(params), '-p', f'table:={table_path}'],
            stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    pub = None
    try:
        # echo first (it waits for one message), then publish until echo has its answer
        with open(tmp_path / 'echo.out', 'wb') as out:
            echo = track_child(subprocess.Popen(
                [str(ros2_cli / 'bin' / 'ros2'), 'topic', 'echo', '--once', '--no-daemon',
                 '/knee/tibia/pose', 'geometry_msgs/msg/PoseStamped'],
                stdout=out, stderr=subprocess.STDOUT, env=env))
        pub = track_child(subprocess.Popen(
            [str(ros2_cli / 'bin' / 'ros2'), 'topic', 'pub', '--rate', '5',
             '/knee/joint_states', 'sensor_msgs/msg/JointState',
             '{name: [knee_flexion, knee_varus], position: [-0.7, 0.05]}'],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env))
        assert echo.wait(timeout=60) == 0, (tmp_path / 'echo.out').read_text()
        answer = yaml.safe_load((tmp_path / 'echo.out').read_text().split('---')[0])
        want = table.interpolate(-0.7, 0.05)
        p, o = answer['pose']['position'], answer['pose']['orientation']
        assert answer['header']['frame_id'] == 'femur'
        assert answer['header']['stamp'] == {'sec': 0, 'nanosec': 0}   # pub's default
        assert np.abs(np.array([p['x'], p['y'], p['z']]) - want.position_m[0]).max() < 1e-9
        assert np.abs(np.array([o['x'], o['y'], o['z'], o['w']])
                      - want.orientation_xyzw[0]).max() < 1e-9
        got = _ros2(ros2_cli, env, 'param', 'get', '--no-daemon', '--timeout', '20',
                    '/table_server', 'table')
        assert got.returncode == 0 and got.stdout.strip() == f'String value is: {table_path}', (
            got.stdout + got.stderr)
        got = _ros2(ros2_cli, env, 'service', 'call', '/table_server/reload',
                    'std_srvs/srv/Trigger')
        assert got.returncode == 0 and 'success=True' in got.stdout, got.stdout + got.stderr
        assert 'serving' in got.stdout and table.sha256[:12] in got.stdout
    finally:
        try:
            if pub is not None:
                pub.send_signal(signal.SIGINT)
                pub.wait(timeout=15)
        finally:
            os.killpg(run.pid, signal.SIGINT)       # ros2 run and the node it started
            try:
                rc = run.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait()
                raise
    text = log.read_text()
    assert rc == 0 and 'Traceback' not in text, text
    assert 'serving' in text
    # --no-daemon where a verb has it: no ros2 daemon was spawned (it would outlive us)
    daemons = subprocess.run(['pgrep', '-f', f'_ros2_daemon.*--ros-domain-id {domain_id}'],
                             capture_output=True, text=True).stdout
    assert daemons.strip() == '', daemons
