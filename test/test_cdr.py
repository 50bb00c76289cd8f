"""The hot path's CDR reader/writer against rclpy's serializer, kneeseat's generic writer
and rosbags (an independent CDR implementation, with its own Jazzy message definitions)."""
from __future__ import annotations

from collections.abc import Sequence
import math

from geometry_msgs.msg import TransformStamped
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import get_typestore, Stores
from rosidl_parser import definition as idl
from sensor_msgs.msg import JointState

from kneeseat_core.errors import KneeseatError
from kneeseat_ros.cdr import (decode_joint_state, decode_pose_stamped, encode_joint_state,
                              encode_pose_stamped, PoseStampedWriter, serialize, TfWriter)
from kneeseat_ros.conversions import pose_stamped, stamp_from_ns
from kneeseat_ros.errors import CdrError

ROSBAGS = get_typestore(Stores.ROS2_JAZZY)


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
    with pytest.raises(KneeseatError):          # in the error tree ...
        decode_pose_stamped(good[:-8])
    with pytest.raises(ValueError):             # ... and still a ValueError
        decode_pose_stamped(good[:-8])


# ---- read back by rosbags ------------------------------------------------------------
def _same_floats(got: object, want: Sequence[float]) -> None:
    """Equal value for value, bit for bit (NaN included), in order."""
    np.testing.assert_array_equal(np.asarray(got, dtype=np.float64).view(np.uint64),
                                  np.asarray(want, dtype=np.float64).view(np.uint64))


@pytest.mark.parametrize('sec, nanosec, frame, names, position, velocity, effort', [
    (0, 0, '', [], [], [], []),
    (7, 1, 'base', ['knee_flexion', 'knee_varus'], [-0.5, 0.02], [], []),
    (1_700_000_000, 999_999_999, 'b', ['a', 'bb', 'ccc'], [1.0, math.nan, -2.5],
     [0.1, 0.2, 0.3], [5.0]),
    (-3, 5, 'abc', ['knee_flexion', 'hip'], [0.1], [], [1.0, 2.0, 3.0]),
    (2**31 - 1, 2**32 - 1, 'genou_gauche', ['flexion_é', 'varus_ü'], [math.inf, -0.0],
     [-math.inf], [1e-300, 1e300]),
])
def test_joint_state_bytes_read_by_rosbags(sec: int, nanosec: int, frame: str, names: list[str],
                                           position: list[float], velocity: list[float],
                                           effort: list[float]) -> None:
    data = encode_joint_state(sec, nanosec, frame, names, position, velocity, effort)
    msg = ROSBAGS.deserialize_cdr(data, 'sensor_msgs/msg/JointState')
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (sec, nanosec)
    assert msg.header.frame_id == frame
    assert msg.name == names
    for got, want in ((msg.position, position), (msg.velocity, velocity),
                      (msg.effort, effort)):
        _same_floats(got, want)
    # and rosbags writes the very same bytes (padding included) for that message
    assert bytes(ROSBAGS.serialize_cdr(msg, 'sensor_msgs/msg/JointState',
                                       little_endian=True)) == data


@pytest.mark.parametrize('pairs', [
    [('femur', 'tibia'), ('femur', 'patella')],
    [('world', 'femur'), ('femur', 'tibia'), ('femur', 'patella'), ('femur', 'abcdefg')],
    [('a', 'b')],
    [('femur', 'tibia_cartilage_1'), ('world_frame', 'femur'), ('ab', 'cdef'), ('x', 'yz')],
    [],
])
def test_tf_bytes_read_by_rosbags(pairs: list[tuple[str, str]]) -> None:
    """Frame names of assorted lengths: transforms start at offsets 4 and 0 mod 8 (the
    writer's two pre-rendered variants); none at all is an empty sequence."""
    rng = np.random.default_rng(len(pairs) + 11)
    poses = [tuple(float(v) for v in rng.normal(size=7)) for _ in pairs]
    transforms = [(p, c, pose) for (p, c), pose in zip(pairs, poses)]
    data = TfWriter(pairs).encode(1_700_000_123, 456_789, transforms)
    msg = ROSBAGS.deserialize_cdr(data, 'tf2_msgs/msg/TFMessage')
    assert len(msg.transforms) == len(pairs)
    for got, (parent, child, pose) in zip(msg.transforms, transforms):
        assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_123, 456_789)
        assert (got.header.frame_id, got.child_frame_id) == (parent, child)
        t, r = got.transform.translation, got.transform.rotation
        _same_floats([t.x, t.y, t.z, r.x, r.y, r.z, r.w], pose)
    assert bytes(ROSBAGS.serialize_cdr(msg, 'tf2_msgs/msg/TFMessage',
                                       little_endian=True)) == data


@pytest.mark.parametrize('frame', ['', 'f', 'femur', 'abc', 'world_frame_x'])
def test_pose_stamped_bytes_read_by_rosbags(frame: str) -> None:
    rng = np.random.default_rng(len(frame) + 3)
    pose = tuple(float(v) for v in rng.normal(size=7))
    data = PoseStampedWriter(frame).encode(12, 34, pose)
    msg = ROSBAGS.deserialize_cdr(data, 'geometry_msgs/msg/PoseStamped')
    header = msg.header
    assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (12, 34, frame)
    p, o = msg.pose.position, msg.pose.orientation
    _same_floats([p.x, p.y, p.z, o.x, o.y, o.z, o.w], pose)
    assert bytes(ROSBAGS.serialize_cdr(msg, 'geometry_msgs/msg/PoseStamped',
                                       little_endian=True)) == data
