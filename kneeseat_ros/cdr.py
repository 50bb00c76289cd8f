"""CDR bytes of ROS messages: the node's hot-path messages with `struct`, any other generically.

rclpy on Jazzy can take a subscription's messages as serialized bytes (`raw=True`) and
publish bytes (`Publisher.publish(bytes)`). Turning bytes into an rclpy message object and
back costs more than the table lookup itself (see benchmarks/bench_hotpath.py), so the
node reads the few fields it needs straight from the CDR and writes its answers the same
way. Layouts (XCDR1 / plain CDR, little endian, as rmw_fastrtps sends on every x86 and ARM
machine; 4-byte encapsulation header `00 01 00 00`; alignment relative to the byte after
the header; padding written as zeros, so the bytes equal `serialize`'s):

- std_msgs/Header: int32 sec, uint32 nanosec, string frame_id (uint32 length with the
  NUL, the bytes, NUL)
- geometry_msgs/PoseStamped: Header, align 8, 7 float64 (position xyz, orientation xyzw)
- sensor_msgs/JointState: Header, sequence<string> name, then position, velocity, effort
  as sequence<float64> (uint32 count, align 8, the values)
- tf2_msgs/TFMessage: sequence<TransformStamped>: Header, string child_frame_id, align 8,
  7 float64 (translation xyz, rotation xyzw)

A message in another encapsulation (big endian) raises `CdrError`; the node then falls
back to rclpy's deserializer. Truncated bytes raise `CdrError` too.

`serialize` writes any rclpy message object (the recorder's markers and diagnostics) from
its rosidl field types, with zeroed alignment padding; `rclpy.serialization` reads the
bytes back.

Why not a library's serialiser (measured on the dev machine, load 0.5, min of 7 x 3000):
rclpy's `serialize_message` (rmw_fastrtps, Jazzy) is fast (a PoseStamped object 5.4 us,
here 15.7 us) but leaves the padding bytes uninitialised and appends junk after messages
with sequences (it reports the estimated, not the written, length): rosbags rejects those
bytes ("CDR message size mismatch") and they differ from run to run. mcap-ros2-support's
dynamic encoder writes the same bytes as ours, but is slower on every path we use -
PoseStamped from its fields 8.8 us (ours 0.31 us, the hot path at 2 kHz), decoded 8.4 us
(ours 0.62 us); JointState 10.1 / 8.1 us (ours 2.6 / 2.1 us); a PoseStamped object 18.0
us (15.7 us), a MarkerArray of three markers 187 us (151 us) - and it cannot write a
DiagnosticArray at all (DiagnosticStatus.level is a `byte`, which rclpy holds as bytes and
its int() coercion rejects).
"""
from __future__ import annotations

from collections.abc import Sequence
import functools
import struct
from typing import Any

from rosidl_parser import definition as idl

from .errors import CdrError, MessageTypeError

__all__ = ['CDR_LE', 'decode_pose_stamped', 'decode_joint_state', 'PoseStampedWriter',
           'encode_pose_stamped', 'encode_joint_state', 'TfWriter', 'serialize']

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


def _string_bytes(text: str) -> bytes:
    """A CDR string (length, bytes, NUL); the caller places it 4-aligned."""
    raw = text.encode('utf-8') + b'\x00'
    return _U32.pack(len(raw)) + raw


def _pad(offset: int, align: int) -> bytes:
    return b'\x00' * (-offset % align)


class PoseStampedWriter:
    """CDR bytes of PoseStamped messages with one fixed frame_id."""

    __slots__ = ('_frame',)

    def __init__(self, frame_id: str) -> None:
        frame = _string_bytes(frame_id)
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
    out += _string_bytes(frame_id)
    out += _pad(len(out), 4) + _U32.pack(len(names))
    for name in names:
        out += _pad(len(out), 4)
        out += _string_bytes(name)
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
                body += _string_bytes(parent)
                body += _pad(start + len(body), 4)
                body += _string_bytes(child)
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
            offset += 8 + len(names) + 56     # 4-aligned: the name blocks are padded
        return CDR_LE + b''.join(out)


# -- any message object (recorder) ----------------------------------------------------
_BASIC = {                              # IDL basic type -> struct format (size = alignment)
    'boolean': '?', 'octet': 'B', 'char': 'B', 'uint8': 'B', 'int8': 'b',
    'int16': 'h', 'uint16': 'H', 'int32': 'i', 'uint32': 'I', 'int64': 'q', 'uint64': 'Q',
    'float': 'f', 'double': 'd',
}


class _CdrWriter:
    def __init__(self) -> None:
        self.buf = bytearray()

    def align(self, size: int) -> None:
        self.buf.extend(b'\x00' * (-len(self.buf) % size))

    def basic(self, fmt: str, value: Any) -> None:
        if isinstance(value, (bytes, bytearray)):
            value = value[0]
        elif fmt == 'B' and isinstance(value, str):
            value = ord(value)
        size = struct.calcsize(fmt)
        self.align(size)
        self.buf.extend(struct.pack('<' + fmt, value))

    def basics(self, fmt: str, values: Any) -> None:
        values = list(values)
        if not values:
            return
        if isinstance(values[0], (bytes, bytearray)):
            values = [v[0] for v in values]
        self.align(struct.calcsize(fmt))
        self.buf.extend(struct.pack(f'<{len(values)}{fmt}', *values))

    def string(self, value: str) -> None:
        data = value.encode('utf-8') + b'\x00'
        self.basic('I', len(data))
        self.buf.extend(data)


def _write_value(out: _CdrWriter, slot: Any, value: Any) -> None:
    if isinstance(slot, idl.BasicType):
        out.basic(_basic_format(slot), value)
    elif isinstance(slot, idl.AbstractString):
        out.string(value)
    elif isinstance(slot, idl.NamespacedType):
        _write_struct(out, value)
    elif isinstance(slot, (idl.Array, idl.AbstractSequence)):
        items = value
        if isinstance(slot, idl.AbstractSequence):
            out.basic('I', len(items))
        inner = slot.value_type
        if isinstance(inner, idl.BasicType):
            out.basics(_basic_format(inner), items)
        else:
            for item in items:
                _write_value(out, inner, item)
    else:
        raise MessageTypeError(f'cannot serialise field type {slot!r}; wide strings and long '
                               'double are not supported by the kneeseat recorder')


def _basic_format(slot: Any) -> str:
    try:
        return _BASIC[slot.typename]
    except KeyError:
        raise MessageTypeError(f'cannot serialise basic type {slot.typename!r}; it is not '
                               'used by the kneeseat topics') from None


def _write_struct(out: _CdrWriter, msg: Any) -> None:
    for name, slot in zip(msg.get_fields_and_field_types(), type(msg).SLOT_TYPES):
        _write_value(out, slot, getattr(msg, name))


def serialize(msg: Any) -> bytes:
    """CDR bytes (little endian, 4-byte encapsulation header) of an rclpy message.

    Raises:
        MessageTypeError: the message uses a field type the writer does not support.
    """
    out = _CdrWriter()
    _write_struct(out, msg)
    return CDR_LE + bytes(out.buf)
