"""The hot path's CDR reader/writer against rclpy's serializer and kneeseat's msgdefs."""
from __future__ import annotations

import math

from geometry_msgs.msg import TransformStamped
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition as idl
from sensor_msgs.msg import JointState

from kneeseat_ros.cdr import (decode_joint_state, decode_pose_stamped, encode_joint_state,
                              encode_pose_stamped, PoseStampedWriter, serialize, TfWriter)
from kneeseat_ros.conversions import pose_stamped, stamp_from_ns
from kneeseat_ros.errors import CdrError


@pytest.mark.parametrize('frame', ['', 'f', 'femur', 'abc', 'world_frame_x', 'tibia01'])
def test_pose_stamped_round_trips(frame: str) -> None:
    rng = np.random.default_rng(len(frame))
    pose = tuple(float(v) for v in rng.normal(size=7))
    msg = pose_stamped(pose[:3], pose[3:], stamp_from_ns(1_234_567_890_123), frame)
    data = PoseStampedWriter(frame).encode(1234, 567_890_123, pose)
    assert data == serialize(msg) == encode_pose_stamped(1234, 567_890_123, frame, pose)
    assert deserialize_message(data, type(msg)) == msg
    # what rclpy/Fast DDS produce reads back field for field
    assert decode_pose_stamped(serialize_message(msg)) == (1234, 567_890_123, frame, pose)


@pytest.mark.parametrize('names, position, velocity, effort', [
    ([], [], [], []),
    (['knee_flexion', 'knee_varus'], [-0.5, 0.02], [], []),
    (['a', 'bb', 'ccc'], [1.0, math.nan, -2.5], [0.1, 0.2, 0.3], [5.0]),
    (['knee_flexion', 'hip'], [0.1], [], [1.0, 2.0, 3.0]),
])
def test_joint_state_round_trips(names: list[str], position: list[float],
                                 velocity: list[float], effort: list[float]) -> None:
    msg = JointState(name=names, position=position, velocity=velocity, effort=effort)
    msg.header.stamp = stamp_from_ns(7_000_000_001)
    msg.header.frame_id = 'base'
    data = encode_joint_state(7, 1, 'base', names, position, velocity, effort)
    assert data == serialize(msg)
    got = decode_joint_state(serialize_message(msg))
    assert got[:4] == (7, 1, 'base', names)
    for have, want in zip(got[4:], (position, velocity, effort)):
        np.testing.assert_array_equal(have, want)


class _TFMessage:
    """tf2_msgs/TFMessage's layout for cdr.serialize (tf2_msgs has no pip wheel)."""

    SLOT_TYPES = (idl.UnboundedSequence(idl.NamespacedType(['geometry_msgs', 'msg'],
                                                           'TransformStamped')),)

    def __init__(self, transforms: list[TransformStamped]) -> None:
        self.transforms = transforms

    def get_fields_and_field_types(self) -> dict[str, str]:
        return {'transforms': 'sequence<geometry_msgs/TransformStamped>'}


@pytest.mark.parametrize('pairs', [
    [('femur', 'tibia'), ('femur', 'patella')],
    [('world', 'femur'), ('femur', 'tibia'), ('femur', 'patella'), ('femur', 'abcdefg')],
    [('a', 'b')],
])
def test_tf_writer_equals_msgdefs(pairs: list[tuple[str, str]]) -> None:
    rng = np.random.default_rng(len(pairs))
    poses = [tuple(float(v) for v in rng.normal(size=7)) for _ in pairs]
    data = TfWriter(pairs).encode(5, 6, [(p, c, pose) for (p, c), pose in zip(pairs, poses)])
    transforms = []
    for (parent, child), pose in zip(pairs, poses):
        t = TransformStamped(child_frame_id=child)
        t.header.frame_id, t.header.stamp = parent, stamp_from_ns(5_000_000_006)
        tr, r = t.transform.translation, t.transform.rotation
        tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w = pose
        transforms.append(t)
    assert data == serialize(_TFMessage(transforms))


def test_bad_bytes_raise_cdr_error() -> None:
    good = PoseStampedWriter('femur').encode(1, 2, (0.0,) * 7)
    with pytest.raises(CdrError, match='too short'):
        decode_pose_stamped(good[:-8])
    with pytest.raises(CdrError, match='little-endian'):
        decode_pose_stamped(b'\x00\x00' + good[2:])
    with pytest.raises(CdrError):
        decode_joint_state(good[:12] + b'\xff\xff\xff\x7f')
