"""Pure message <-> numpy conversions of kneeseat_ros (no DDS, no node)."""
from __future__ import annotations

import math
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from kneeseat_core.errors import KneeseatError
from kneeseat_core.geometry import KneeAxes, quat_from_matrix
from kneeseat_ros.conversions import (angles_from_joint_state, angles_from_pose_stamped,
                                      AttitudeDecoder, body_markers, diagnostic_status,
                                      display_mesh_paths, joint_state, MARKER_ID_STRIDE,
                                      mesh_marker, pose_from_msg, pose_stamped,
                                      pose_stamped_for_attitude, QUAT_NORM_TOL, stamp_from_ns,
                                      stamp_ns)
from kneeseat_ros.errors import BadInputError

TKA_AXES = KneeAxes.from_vectors([0, 0, 1], [1, 0, 0], [0, 1, 0])
STAMP = stamp_from_ns(1_700_000_000_123_456_789)


def tracker_msg(quat: tuple[float, float, float, float], frame: str = 'femur') -> PoseStamped:
    return pose_stamped((0.1, 0.2, 0.3), quat, STAMP, frame)


def test_stamp_round_trip() -> None:
    for ns in (0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789):
        assert stamp_ns(stamp_from_ns(ns)) == ns


@pytest.mark.parametrize('axes', [
    TKA_AXES,
    KneeAxes.from_vectors([1, 0, 0], [0, 0, 1], [0, 1, 0]),       # patent axes, left-handed
    KneeAxes.from_vectors([0.6, 0.8, 0], [-0.8, 0.6, 0], [0, 0, 1]),
])
def test_pose_stamped_gives_the_attitude_back(axes: KneeAxes) -> None:
    rng = np.random.default_rng(7)
    for flexion, varus, rotation in rng.uniform([-1.6, -0.3, -0.5], [0.2, 0.3, 0.5], (50, 3)):
        msg = pose_stamped_for_attitude(axes, flexion, varus, STAMP, 'femur', rotation)
        got = angles_from_pose_stamped(msg, axes, 'femur')
        assert got == pytest.approx((flexion, varus), abs=1e-12)
        # the fast decoder agrees with the core decomposition
        core = axes.decompose(pose_from_msg(msg.pose)[:3, :3])
        assert got == pytest.approx((float(core[0]), float(core[1])), abs=1e-13)


def test_q_and_minus_q_give_the_same_angles() -> None:
    msg = pose_stamped_for_attitude(TKA_AXES, -0.7, 0.05, STAMP, 'femur', 0.1)
    o = msg.pose.orientation
    flipped = tracker_msg((-o.x, -o.y, -o.z, -o.w))
    assert (angles_from_pose_stamped(flipped, TKA_AXES, 'femur')
            == pytest.approx(angles_from_pose_stamped(msg, TKA_AXES, 'femur'), abs=1e-14))


def test_slightly_non_unit_quaternion_is_accepted_and_normalised() -> None:
    q = quat_from_matrix(TKA_AXES.orientation(-0.5, 0.1))
    scale = 1.0 + 0.5 * QUAT_NORM_TOL
    got = angles_from_pose_stamped(tracker_msg(tuple(q * scale)), TKA_AXES, 'femur')
    assert got == pytest.approx((-0.5, 0.1), abs=1e-12)


@pytest.mark.parametrize('quat, frame, reason, match', [
    ((0.0, 0.0, 0.0, 0.0), 'femur', 'quaternion', r'\|q\| = 0 is not a unit quaternion'),
    ((0.0, 0.0, 0.0, 1.01), 'femur', 'quaternion', r'not a unit quaternion'),
    ((math.nan, 0.0, 0.0, 1.0), 'femur', 'nonfinite', r'NaN or inf'),
    ((0.0, math.inf, 0.0, 1.0), 'femur', 'nonfinite', r'NaN or inf'),
    ((0.0, 0.0, 0.0, 1.0), 'tibia', 'frame_id', r"frame_id 'tibia' is not .* 'femur'"),
    ((0.0, 0.0, 0.0, 1.0), '', 'frame_id', r"frame_id '' is not"),
])
def test_bad_pose_stamped_is_rejected_with_reason(quat: tuple[float, float, float, float],
                                                  frame: str, reason: str, match: str) -> None:
    with pytest.raises(BadInputError, match=match) as info:
        angles_from_pose_stamped(tracker_msg(quat, frame), TKA_AXES, 'femur')
    assert info.value.reason == reason
    assert isinstance(info.value, KneeseatError)
    assert '\n' not in str(info.value)


def test_joint_state_round_trip_and_extra_joints() -> None:
    assert angles_from_joint_state(joint_state(-0.8, 0.04, STAMP)) == (-0.8, 0.04)
    msg = JointState(name=['hip', 'knee_varus', 'knee_flexion'], position=[1.0, 0.02, -0.3],
                     velocity=[0.0, 0.0, 0.0])
    assert angles_from_joint_state(msg) == (-0.3, 0.02)


@pytest.mark.parametrize('msg, reason', [
    (JointState(name=['knee_flexion'], position=[0.1]), 'joint_names'),
    (JointState(name=['knee_flexion', 'knee_varux'], position=[0.1, 0.0]), 'joint_names'),
    (JointState(name=['knee_flexion', 'knee_varus'], position=[0.1]), 'lengths'),
    (JointState(name=['knee_flexion', 'knee_varus'], position=[0.1, 0.0], velocity=[1.0]),
     'lengths'),
    (JointState(name=['knee_flexion', 'knee_varus'], position=[math.nan, 0.0]), 'nonfinite'),
    (JointState(name=['knee_flexion', 'knee_varus'], position=[0.0, -math.inf]), 'nonfinite'),
])
def test_bad_joint_state_is_rejected_with_reason(msg: JointState, reason: str) -> None:
    with pytest.raises(BadInputError) as info:
        angles_from_joint_state(msg)
    assert info.value.reason == reason
    assert '\n' not in str(info.value)


def test_pose_stamped_round_trip() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=4)
    q = q / np.linalg.norm(q)
    q = q if q[3] >= 0 else -q
    msg = pose_stamped([0.01, -0.02, 0.03], q, STAMP, 'femur')
    assert msg.header.frame_id == 'femur' and stamp_ns(msg.header.stamp) == stamp_ns(STAMP)
    pose = pose_from_msg(msg.pose)
    assert np.allclose(pose[:3, 3], [0.01, -0.02, 0.03], atol=0.0)
    assert np.allclose(quat_from_matrix(pose[:3, :3]), q, atol=1e-12)
    assert np.allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)


def test_attitude_decoder_matches_core_decompose() -> None:
    rng = np.random.default_rng(11)
    axes = KneeAxes.from_vectors([0.0, 0.1, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, -0.1])
    decoder = AttitudeDecoder(axes)
    for q in rng.normal(size=(200, 4)):
        q = q / np.linalg.norm(q)
        flexion, varus, _ = axes.decompose(pose_from_msg(tracker_msg(tuple(q)).pose)[:3, :3])
        assert decoder.angles(*q) == pytest.approx((float(flexion), float(varus)), abs=1e-12)


def test_mesh_marker_and_diagnostic_status() -> None:
    marker = mesh_marker(3, '/tmp/tibia.stl', 'femur', STAMP, (0.0, 0.01, 0.0),
                         (0.0, 0.0, 0.0, 1.0))
    assert marker.type == Marker.MESH_RESOURCE and marker.mesh_resource == 'file:///tmp/tibia.stl'
    assert marker.header.frame_id == 'femur' and marker.id == 3 and marker.scale.x == 1.0
    assert marker.pose.position.y == 0.01
    status = diagnostic_status('kneeseat table_server', DiagnosticStatus.WARN, 'msg', 'hw',
                               [('rate_hz', 999.98765), ('received', 12)])
    assert status.level == DiagnosticStatus.WARN
    values = {kv.key: kv.value for kv in status.values}
    assert values == {'rate_hz': '999.988', 'received': '12'}


def test_display_meshes_of_old_and_multi_mesh_entries() -> None:
    here = Path('/tables')
    old = {'name': 'tibia', 'mesh': 'insert.stl', 'mesh_sha256': 'ab', 'display_mesh': None}
    assert display_mesh_paths(old, here) == ('/tables/insert.stl',)
    assert display_mesh_paths(dict(old, display_mesh='/m/bone.stl'), here) == ('/m/bone.stl',)
    new = dict(old, meshes=[{'path': '/m/cart.stl', 'sha256': 'a'},
                            {'path': '/m/men.stl', 'sha256': 'b'}], display_meshes=[])
    assert display_mesh_paths(new, here) == ('/m/cart.stl', '/m/men.stl')
    new['display_meshes'] = [{'path': 'bone.stl', 'sha256': 'c'},
                             {'path': '/m/men.stl', 'sha256': 'b'}]
    assert display_mesh_paths(new, here) == ('/tables/bone.stl', '/m/men.stl')
    assert display_mesh_paths({'name': 'femur'}, here) == ()


def test_one_marker_per_mesh_of_a_body() -> None:
    markers = body_markers(2, ['/m/bone.stl', '/m/men.stl'], 'femur', STAMP, (0.0, 0.02, 0.0),
                           (0.0, 0.0, 0.0, 1.0), (0.1, 0.2, 0.3, 1.0))
    assert [m.id for m in markers] == [2, 2 + MARKER_ID_STRIDE]
    assert [m.mesh_resource for m in markers] == ['file:///m/bone.stl', 'file:///m/men.stl']
    assert all(m.pose.position.y == 0.02 and m.color.g == pytest.approx(0.2) for m in markers)
    assert body_markers(0, [], 'femur', STAMP) == []
