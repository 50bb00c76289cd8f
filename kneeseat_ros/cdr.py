"""The node's hot-path messages as CDR bytes, read and written with `struct` (no rclpy).

rclpy on Jazzy can take a subscription's messages as serialized bytes (`raw=True`) and
publish bytes (`Publisher.publish(bytes)`). Turning bytes into an rclpy message object and
back costs more than the table lookup itself (see benchmarks/bench_hotpath.py), so the
node reads the few fields it needs straight from the CDR and writes its answers the same
way. Layouts (XCDR1 / plain CDR, little endian, as rmw_fastrtps sends on every x86 and ARM
machine; 4-byte encapsulation header `00 01 00 00`; alignment relative to the byte after
the header; padding written as zeros, so the bytes equal `msgdefs.serialize`):

- std_msgs/Header: int32 sec, uint32 nanosec, string frame_id (uint32 length with the
  NUL, the bytes, NUL)
- geometry_msgs/PoseStamped: Header, align 8, 7 float64 (position xyz, orientation xyzw)
- sensor_msgs/JointState: Header, sequence<string> name, then position, velocity, effort
  as sequence<float64> (uint32 count, align 8, the values)
- tf2_msgs/TFMessage: sequence<TransformStamped>: Header, string child_frame_id, align 8,
  7 float64 (translation xyz, rotation xyzw)

A message in another encapsulation (big endian) raises `CdrError`; the node then falls
back to rclpy's deserializer. Truncated bytes raise `CdrError` too.
"""
from __future__ import annotations

from collections.abc import Sequence
import functools
import struct

from .errors import CdrError

__all__ = ['CdrError', 'CDR_LE', 'decode_pose_stamped', 'decode_joint_state',
           'PoseStampedWriter', 'encode_pose_stamped', 'encode_joint_state', 'TfWriter']

CDR_LE = b'\x00\x01\x00\x00'
_STAMP = struct.Struct('<iI')
_U32 = struct.Struct('<I')
_POSE = struct.Struct('<7d')


def _string(data: bytes, o: int) -> tuple[str, int]:
    """A CDR string at payload offset `o` (already 4-aligned); returns it and the end."""
    (n,) = _U32.unpack_from(data, 4 + o)
    o += 4
    end = o + n
    if n == 0 or end + 4 > len(data):
        raise CdrError(f'string of {n} bytes at offset {o} runs past the message')
    return data[4 + o:4 + end - 1].decode('utf-8', 'replace'), end


def _header(data: bytes) -> tuple[int, int, str, int]:
    if data[:4] != CDR_LE:
        raise CdrError(f'encapsulation {data[:4].hex()} is not little-endian CDR (0001)')
    sec, nanosec = _STAMP.unpack_from(data, 4)
    frame, o = _string(data, 8)
    return sec, nanosec, frame, o


def decode_pose_stamped(data: bytes) -> tuple[int, int, str, tuple[float, ...]]:
    """(sec, nanosec, frame_id, (px, py, pz, qx, qy, qz, qw)) of a PoseStamped's CDR."""
    try:
        sec, nanosec, frame, o = _header(data)
        return sec, nanosec, frame, _POSE.unpack_from(data, 4 + ((o + 7) & ~7))
    except struct.error as err:
        raise CdrError(f'PoseStamped bytes too short ({len(data)} bytes): {err}') from None


def _doubles(data: bytes, o: int) -> tuple[tuple[float, ...], int]:
    o = (o + 3) & ~3
    (n,) = _U32.unpack_from(data, 4 + o)
    o += 4
    if n:
        o = (o + 7) & ~7
        values = struct.unpack_from(f'<{n}d', data, 4 + o)
        return values, o + 8 * n
    return (), o


JointStateFields = tuple[int, int, str, list[str], tuple[float, ...], tuple[float, ...],
                         tuple[float, ...]]


def decode_joint_state(data: bytes) -> JointStateFields:
    """(sec, nanosec, frame_id, names, positions, velocities, efforts) of a JointState."""
    try:
        sec, nanosec, frame, o = _header(data)
        o = (o + 3) & ~3
        (count,) = _U32.unpack_from(data, 4 + o)
        o += 4
        if count > len(data):
            raise CdrError(f'JointState claims {count} names in {len(data)} bytes')
        names = []
        for _ in range(count):
            o = (o + 3) & ~3
            name, o = _string(data, o)
            names.append(name)
        position, o = _doubles(data, o)
        velocity, o = _doubles(data, o)
        effort, o = _doubles(data, o)
        return sec, nanosec, frame, names, position, velocity, effort
    except struct.error as err:
        raise CdrError(f'JointState bytes too short ({len(data)} bytes): {err}') from None


def _string_bytes(text: str, offset: int) -> bytes:
    """A CDR string (length, bytes, NUL) starting 4-aligned at payload `offset`."""
    raw = text.encode('utf-8') + b'\x00'
    return _U32.pack(len(raw)) + raw


def _pad(offset: int, align: int) -> bytes:
    return b'\x00' * (-offset % align)


class PoseStampedWriter:
    """CDR bytes of PoseStamped messages with one fixed frame_id."""

    __slots__ = ('_frame',)

    def __init__(self, frame_id: str) -> None:
        frame = _string_bytes(frame_id, 8)
        self._frame = frame + _pad(8 + len(frame), 8)

    def encode(self, sec: int, nanosec: int, pose: Sequence[float]) -> bytes:
        """Bytes of PoseStamped{stamp, frame_id, pose = (px, py, pz, qx, qy, qz, qw)}."""
        return CDR_LE + _STAMP.pack(sec, nanosec) + self._frame + _POSE.pack(*pose)


@functools.lru_cache(maxsize=64)
def _writer(frame_id: str) -> PoseStampedWriter:
    return PoseStampedWriter(frame_id)


def encode_pose_stamped(sec: int, nanosec: int, frame_id: str,
                        pose: Sequence[float]) -> bytes:
    """CDR bytes of a PoseStamped (zero padding) with any frame_id."""
    return _writer(frame_id).encode(sec, nanosec, pose)


def encode_joint_state(sec: int, nanosec: int, frame_id: str, names: Sequence[str],
                       position: Sequence[float], velocity: Sequence[float],
                       effort: Sequence[float]) -> bytes:
    """CDR bytes of a JointState (zero padding): what the recorder stores for an input."""
    out = bytearray(_STAMP.pack(sec, nanosec))
    out += _string_bytes(frame_id, len(out))
    out += _pad(len(out), 4) + _U32.pack(len(names))
    for name in names:
        out += _pad(len(out), 4)
        out += _string_bytes(name, len(out))
    for values in (position, velocity, effort):
        out += _pad(len(out), 4) + _U32.pack(len(values))
        if values:
            out += _pad(len(out), 8) + struct.pack(f'<{len(values)}d', *values)
    return CDR_LE + bytes(out)


class TfWriter:
    """CDR bytes of TFMessages: one transform per (parent, child) pair, all one stamp."""

    __slots__ = ('_frames',)

    def __init__(self, pairs: Sequence[tuple[str, str]]) -> None:
        # each TransformStamped starts 4-aligned; its doubles 8-aligned relative to the
        # payload, which depends on where it starts: pre-render both cases (offset % 8)
        self._frames: dict[tuple[str, str], tuple[bytes, bytes]] = {}
        for parent, child in pairs:
            variants = []
            for start in (0, 4):
                body = bytearray(b'\x00' * 8)            # the stamp's place
                body += _string_bytes(parent, start + len(body))
                body += _pad(start + len(body), 4)
                body += _string_bytes(child, start + len(body))
                body += _pad(start + len(body), 8)
                variants.append(bytes(body[8:]))
            self._frames[(parent, child)] = (variants[0], variants[1])

    def encode(self, sec: int, nanosec: int,
               transforms: Sequence[tuple[str, str, Sequence[float]]]) -> bytes:
        """Bytes of TFMessage{transforms: [(parent, child, (px, py, pz, qx, qy, qz, qw))]}."""
        out = [_U32.pack(len(transforms))]
        offset = 4
        stamp = _STAMP.pack(sec, nanosec)
        for parent, child, pose in transforms:
            names = self._frames[(parent, child)][(offset % 8) // 4]
            out += (stamp, names, _POSE.pack(*pose))
            offset += 8 + len(names) + 56
            if offset % 4:
                raise AssertionError('TransformStamped ends 4-aligned')
        return CDR_LE + b''.join(out)
