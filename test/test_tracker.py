"""Tracker mode: rigid transforms, the registration file, pairing by stamp, and the node.

The end-to-end test runs the installed table_server in tracker mode in its own process and
moves the whole leg around the world with a synthetic tracker (two marker clusters): every
world pose the node answers must equal the composition, done here with 4 x 4 matrices, of
the inputs, the registration and the table within 1e-9.
"""
from __future__ import annotations

import math
from pathlib import Path
import subprocess
import time
from typing import Any

from conftest import ros_env, spin_until, write_synthetic_table
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from ros_helpers import RELIABLE, rigid, ServerProcess, TABLE_SERVER
import yaml

from kneeseat_core.errors import ConfigError
from kneeseat_core.geometry import quat_from_matrix
from kneeseat_core.table import read_table
from kneeseat_ros import topics
from kneeseat_ros.conversions import pose_stamped, stamp_from_ns, stamp_ns
from kneeseat_ros.tracker import compose, inverse, load_registration, Pairer, relative_rotation
from kneeseat_ros.demos.tracker_demo import (example_registration, expected_world, leg_motion,
                                             pose_matrix, registration_yaml)


def matrix(r: tuple[float, ...]) -> np.ndarray:
    return pose_matrix(r[:3], r[3:])


def test_compose_inverse_and_relative_match_matrices() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = (pose_matrix(rng.normal(size=3), q / np.linalg.norm(q))
                for q in rng.normal(size=(2, 4)))
        assert np.abs(matrix(compose(rigid(a), rigid(b))) - a @ b).max() < 1e-12
        assert np.abs(matrix(inverse(rigid(a))) - np.linalg.inv(a)).max() < 1e-12
        rel = matrix((0.0, 0.0, 0.0, *relative_rotation(rigid(a), rigid(b))))
        assert np.abs(rel[:3, :3] - a[:3, :3].T @ b[:3, :3]).max() < 1e-12


def test_registration_file_both_forms(tmp_path: Path) -> None:
    f, t = example_registration()
    path = tmp_path / 'reg.yaml'
    path.write_text(registration_yaml(f, t))
    reg = load_registration(path)
    assert np.abs(matrix(reg.femur) - f).max() < 1e-12
    path.write_text(yaml.safe_dump({'femur': {'matrix': f.tolist()},
                                    'tibia': {'matrix': t.tolist()}}))
    reg = load_registration(path)
    assert np.abs(matrix(reg.tibia) - t).max() < 1e-12


@pytest.mark.parametrize('femur, match', [
    ({'matrix': (np.diag([1.0, 1.0, 1.0, 1.0]) * [1.01, 1, 1, 1]).tolist()},
     r'femur\.matrix is not a rigid transform'),
    ({'matrix': np.diag([1.0, 1.0, -1.0, 1.0]).tolist()}, r'det R = -1'),
    ({'matrix': [[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     r'not a rigid transform'),
    ({'matrix': [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0, 0, 1]]}, r'bottom row'),
    ({'translation': [0, 0, 0], 'rotation': [0, 0, 0, 2]}, r'norm 2, not 1'),
    ({'translation': [0, 0], 'rotation': [0, 0, 0, 1]}, r'translation must be 3'),
    ({'rotation': [0, 0, 0, 1]}, r'give either translation and rotation'),
])
def test_registration_refuses_non_rigid(tmp_path: Path, femur: Any, match: str) -> None:
    path = tmp_path / 'reg.yaml'
    path.write_text(yaml.safe_dump({'femur': femur,
                                    'tibia': {'matrix': np.eye(4).tolist()}}))
    with pytest.raises(ConfigError, match=match):
        load_registration(path)


def test_registration_file_problems(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='No such file'):
        load_registration(tmp_path / 'missing.yaml')
    (tmp_path / 'r.yaml').write_text('femur: [1, 2\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_registration(tmp_path / 'r.yaml')
    (tmp_path / 'r.yaml').write_text('femur: {matrix: [[1]]}\n')
    with pytest.raises(ConfigError, match='exactly the keys femur and tibia'):
        load_registration(tmp_path / 'r.yaml')


def test_pairer_nearest_within_tolerance_in_order() -> None:
    p: Pairer[str] = Pairer(tolerance_ns=2)
    assert p.add(0, 100, 'f100') is None
    assert p.add(1, 101, 't101') == ('f100', 't101', 100)          # within 1
    assert p.add(1, 110, 't110') is None
    assert p.add(0, 105, 'f105') is None                           # 5 away: waits
    assert p.add(0, 111, 'f111') == ('f111', 't110', 111)
    assert p.unpaired == 1 and p.stale == 0                        # f105 lost its chance
    assert p.add(1, 109, 't109') is None and p.stale == 1          # before the last pair
    assert p.add(0, 120, 'f120') is None
    assert p.add(1, 130, 't130') is None                           # f120 is now hopeless
    assert p.unpaired == 2 and p.pending() == 1
    # nearest: of two waiting femur samples within the tolerance the closer one pairs
    assert p.add(0, 140, 'f140') is None and p.add(0, 141, 'f141') is None
    assert p.unpaired == 3                                         # t130 dropped at f140
    assert p.add(1, 141, 't141') == ('f141', 't141', 141)
    assert p.unpaired == 4                                         # f140 skipped


class TrackerProbe:
    """Publishes both marker clusters, collects every knee/<bone>/world_pose and pose."""

    def __init__(self, context: Any, names: tuple[str, ...]) -> None:
        self.node = rclpy.create_node('tracker_probe', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.pubs = [self.node.create_publisher(PoseStamped, f'tracker/{s}/pose', RELIABLE)
                     for s in ('femur', 'tibia')]
        self.names = names
        self.world: dict[tuple[str, int], PoseStamped] = {}
        self.local: dict[tuple[str, int], PoseStamped] = {}
        for name in names:
            self.node.create_subscription(
                PoseStamped, f'knee/{name}/world_pose',
                lambda m, n=name: self.world.__setitem__((n, stamp_ns(m.header.stamp)), m),
                RELIABLE)
            if name != names[0]:
                self.node.create_subscription(
                    PoseStamped, f'knee/{name}/pose',
                    lambda m, n=name: self.local.__setitem__((n, stamp_ns(m.header.stamp)),
                                                             m), RELIABLE)

    def publish(self, side: int, m: np.ndarray, stamp: int, frame: str = 'world') -> None:
        self.pubs[side].publish(pose_stamped(m[:3, 3], quat_from_matrix(m[:3, :3]),
                                             stamp_from_ns(stamp), frame))

    def answered(self, stamp: int) -> bool:
        return (all((n, stamp) in self.world for n in self.names)
                and all((n, stamp) in self.local for n in self.names[1:]))

    def destroy(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def pose_error(msg: PoseStamped, want: np.ndarray) -> float:
    p, o = msg.pose.position, msg.pose.orientation
    q, qw = np.array([o.x, o.y, o.z, o.w]), quat_from_matrix(want[:3, :3])
    return max(float(np.abs(np.array([p.x, p.y, p.z]) - want[:3, 3]).max()),
               float(min(np.abs(q - qw).max(), np.abs(q + qw).max())))


@pytest.mark.ros
def test_tracker_mode_world_poses_equal_the_composition(tmp_path: Path, domain_id: int,
                                                        context: Any) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=7)
    table = read_table(table_path)
    reg_f, reg_t = example_registration(seed=4)
    registration = tmp_path / 'registration.yaml'
    registration.write_text(registration_yaml(reg_f, reg_t))
    femur, tibia, truth = leg_motion(table.axes, 40, 2.0, (-1.5, 0.0), (-0.15, 0.15))
    femur_c, tibia_c = femur @ np.linalg.inv(reg_f), tibia @ np.linalg.inv(reg_t)
    # reliable inputs (a standard QoS override): the drops counted below must all arrive,
    # which best effort does not promise on a loaded machine
    reliable_inputs = [f'qos_overrides./{topic}.subscription.reliability:=reliable'
                       for topic in (topics.TRACKER_FEMUR, topics.TRACKER_TIBIA)]
    srv = ServerProcess(tmp_path, domain_id, table_path,
                        f'tracker.registration:={registration}', 'diagnostics_period_s:=0.1',
                        'tracker.pair_tolerance_s:=0.001', *reliable_inputs)
    names = ('femur', *table.bodies)
    probe = TrackerProbe(context, names)
    try:
        spin_until(probe.executor, lambda: all(p.get_subscription_count() for p in probe.pubs)
                   and all(probe.node.count_publishers(f'knee/{n}/world_pose') for n in names),
                   timeout_s=20.0, what='discovery of table_server in tracker mode')
        # warm-up pairs (fresh stamps) until one is answered: discovery may eat the first
        stamp = 10**15
        last = [-math.inf]

        def warm() -> None:
            nonlocal stamp
            if time.monotonic() - last[0] > 0.3:
                last[0] = time.monotonic()
                stamp += 10**6
                probe.publish(0, femur_c[0], stamp)
                probe.publish(1, tibia_c[0], stamp)

        spin_until(probe.executor, lambda: len(probe.world) > 0, what='a warm-up answer',
                   every=warm)
        # the session: tibia stamped 0.4 ms after the femur (within the 1 ms tolerance),
        # sometimes tibia first; the answer carries the femur's stamp
        stamps = []
        for k in range(len(femur)):
            s_f = 2 * 10**15 + k * 10**7
            stamps.append(s_f)
            order = (0, 1) if k % 3 else (1, 0)
            for side in order:
                probe.publish(side, (femur_c, tibia_c)[side][k], s_f + side * 400_000)
            spin_until(probe.executor, lambda s=s_f: probe.answered(s),
                       what=f'answer to pair {k}')
        worst = 0.0
        for k, s in enumerate(stamps):
            want_f, want_b = expected_world(table, femur_c[k], tibia_c[k], reg_f, reg_t)
            worst = max(worst, pose_error(probe.world[('femur', s)], want_f))
            for i, body in enumerate(table.bodies):
                worst = max(worst, pose_error(probe.world[(body, s)], want_b[i]))
                local = np.linalg.inv(want_f) @ want_b[i]
                worst = max(worst, pose_error(probe.local[(body, s)], local))
            assert probe.world[('femur', s)].header.frame_id == 'world'
            assert probe.local[('tibia', s)].header.frame_id == 'femur'
        assert worst <= 1e-9, worst
        # the truth of the motion is what was decoded (the table's grid covers it)
        f, v, _ = table.axes.decompose(np.linalg.inv(femur[5])[:3, :3] @ tibia[5][:3, :3])
        assert abs(f - truth[5, 0]) < 1e-9 and abs(v - truth[5, 1]) < 1e-9
        # unpaired (no partner within 1 ms) and stale (older than the last pair): counted
        s_last = stamps[-1]
        probe.publish(1, tibia_c[0], s_last + 10**7)            # tibia alone ...
        probe.publish(0, femur_c[0], s_last + 10**7 + 5_000_000)  # ... femur 5 ms later
        probe.publish(0, femur_c[0], s_last - 10**7)            # before the last pair
        s_ok = s_last + 10**8
        probe.publish(0, femur_c[1], s_ok)
        probe.publish(1, tibia_c[1], s_ok)
        spin_until(probe.executor, lambda: probe.answered(s_ok), what='answer after drops')
        status: dict[str, str] = {}

        def on_diag(msg: Any) -> None:
            for st in msg.status:
                status.update({kv.key: kv.value for kv in st.values})

        from diagnostic_msgs.msg import DiagnosticArray
        probe.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, RELIABLE)
        # every pair sent was answered, warm-ups included (all answers precede s_ok's)
        answers = len({s for _, s in probe.world})
        spin_until(probe.executor, lambda: status.get('answered') == str(answers),
                   what=f'diagnostics of {answers} answers (last: {status})')
        assert status['mode'] == 'tracker'
        assert status['dropped_stale'] == '1'
        assert int(status['dropped_unpaired']) >= 2   # the lone tibia and the late femur
    finally:
        probe.destroy()
        srv.stop_clean()
    startup = srv.stderr()
    assert "'/tracker/tibia/pose'] (reliable, depth 1000); out" in startup, startup


@pytest.mark.ros
def test_tracker_mode_refuses_non_rigid_registration(tmp_path: Path, domain_id: int) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=7)
    registration = tmp_path / 'registration.yaml'
    scaled = (np.eye(4) * [1.0, 1.0, 1.02, 1.0]).tolist()
    registration.write_text(yaml.safe_dump({'femur': {'matrix': np.eye(4).tolist()},
                                            'tibia': {'matrix': scaled}}))
    done = subprocess.run([str(TABLE_SERVER), '--ros-args', '-p', f'table:={table_path}',
                           '-p', f'tracker.registration:={registration}'],
                          capture_output=True, text=True, timeout=60, env=ros_env(domain_id))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith('table_server: error: ')
    assert 'tibia.matrix is not a rigid transform' in lines[0]


@pytest.mark.ros
def test_tracker_demo_writes_its_picture(tmp_path: Path, domain_id: int) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=7)
    import sys
    done = subprocess.run([sys.executable, '-m', 'kneeseat_ros.demos.tracker_demo', '--out',
                           str(tmp_path / 'out'), '--table', str(table_path), '--samples',
                           '30'], capture_output=True, text=True, timeout=120,
                          env=ros_env(domain_id))
    assert done.returncode == 0, done.stdout + done.stderr
    assert 'every answer arrived' in done.stdout
    png = tmp_path / 'out' / 'tracker_world.png'
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
