"""ROS 2 message definitions as rosbag2 writes them into MCAP schemas.

Everything comes from the interface packages installed with the ROS wheels: the `.msg`
text from `<share>/<pkg>/msg/<Type>.msg` and the RIHS01 type hash from
`<share>/<pkg>/msg/<Type>.json`, where `<share>` is found through the ament index
(`AMENT_PREFIX_PATH`) or, when that is unset or lacks the package, beside the installed
Python package (`<prefix>/lib/pythonX.Y/site-packages/<pkg>` -> `<prefix>/share/<pkg>`).

Schema text (rosbag2 Jazzy, `ros2msg` encoding): the root type's `.msg` text, then for
each dependency, depth-first, sorted by name within one definition, each type once:
``'\\n' + '=' * 80 + '\\nMSG: pkg/Type\\n' + text``.

`serialize` writes a message as CDR (little endian, the encapsulation ROS 2 uses) with
zeroed alignment padding. rclpy's `serialize_message` (rmw_fastrtps, Jazzy) leaves the
padding bytes uninitialised and appends junk after messages with sequences (it reports the
estimated, not the written, length): rosbags rejects those bytes ("CDR message size
mismatch") and they differ from run to run. The bytes here are the same as rclpy's apart
from that, and `rclpy.serialization.deserialize_message` reads them back.
"""
from __future__ import annotations

import functools
import importlib
import importlib.util
import json
from pathlib import Path
import re
import struct
import sys
from typing import Any

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError
from rosidl_parser import definition as idl

from .errors import MessageTypeError

__all__ = ['MessageTypeError', 'split_type', 'message_class', 'message_definition',
           'type_hash', 'serialize']

# Field types that are not messages (rosidl primitive types and their ROS 1 aliases).
PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring', 'time', 'duration',
})
SEPARATOR = '=' * 80
_TYPE_RE = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)/(msg)/([A-Za-z][A-Za-z0-9_]*)$')


def split_type(msg_type: str) -> tuple[str, str]:
    """Split 'pkg/msg/Type' into ('pkg', 'Type').

    Raises:
        MessageTypeError: `msg_type` is not of the form 'pkg/msg/Type'.
    """
    match = _TYPE_RE.match(msg_type)
    if match is None:
        raise MessageTypeError(f'message type {msg_type!r} is not of the form pkg/msg/Type; '
                               "write it like 'geometry_msgs/msg/PoseStamped'")
    return match.group(1), match.group(3)


def _installed_share(package: str) -> Path | None:
    """`<prefix>/share/<package>` of an importable interface package, without the index.

    Wheels, colcon and apt all install `<prefix>/lib/pythonX.Y/site-packages/<package>/`
    beside `<prefix>/share/<package>/`; the Python interpreter's own prefix is tried too.
    """
    prefixes = []
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.origin:
        # <prefix>/lib/pythonX.Y/site-packages/<package>/__init__.py (or dist-packages)
        prefixes.append(Path(spec.origin).resolve().parents[4])
    prefixes.append(Path(sys.prefix))
    for prefix in prefixes:
        share = prefix / 'share' / package
        if (share / 'package.xml').is_file():
            return share
    return None


@functools.lru_cache(maxsize=None)
def _share_dir(package: str) -> Path | None:
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, LookupError, ValueError, OSError):
        return _installed_share(package)


def _msg_dir(package: str, msg_type: str) -> Path:
    share = _share_dir(package)
    if share is None:
        raise MessageTypeError(
            f'interface package {package!r} of {msg_type!r} not found (neither in the ament '
            'index nor beside its Python package); install its ROS wheel, or put its '
            'install prefix on AMENT_PREFIX_PATH') from None
    return share / 'msg'


def message_class(msg_type: str) -> Any:
    """The rclpy message class of 'pkg/msg/Type'.

    Raises:
        MessageTypeError: malformed name, or the Python package is not installed.
    """
    package, name = split_type(msg_type)
    try:
        return getattr(importlib.import_module(f'{package}.msg'), name)
    except (ImportError, AttributeError):
        raise MessageTypeError(f'message type {msg_type!r} is not importable in Python; '
                               f'install the ROS wheel that provides {package}') from None


@functools.lru_cache(maxsize=None)
def _msg_text(package: str, name: str) -> str:
    path = _msg_dir(package, f'{package}/msg/{name}') / f'{name}.msg'
    try:
        return path.read_text(encoding='utf-8')
    except OSError as err:
        raise MessageTypeError(f'cannot read the definition of {package}/msg/{name} at {path}: '
                               f'{err.strerror}; reinstall the {package} wheel') from None


def _dependencies(package: str, text: str) -> list[str]:
    """Message types ('pkg/Type') used by the fields of one `.msg` text, sorted, unique."""
    deps: set[str] = set()
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        field_type = line.split()[0]
        base = re.split(r'[\[<]', field_type, maxsplit=1)[0]
        if base in PRIMITIVES:
            continue
        if '/' not in base:
            base = f'{package}/{base}'
        deps.add(base.replace('/msg/', '/'))
    return sorted(deps)


@functools.lru_cache(maxsize=None)
def message_definition(msg_type: str) -> str:
    """Full `ros2msg` schema text of `msg_type`, with its dependencies, as rosbag2 writes it.

    Raises:
        MessageTypeError: the type or one of its dependencies cannot be found.
    """
    package, name = split_type(msg_type)
    seen: set[str] = set()

    def expand(pkg: str, type_name: str) -> str:
        text = _msg_text(pkg, type_name)
        out = text
        for dep in _dependencies(pkg, text):
            if dep in seen:
                continue
            seen.add(dep)
            dep_pkg, dep_name = dep.split('/')
            out += f'\n{SEPARATOR}\nMSG: {dep}\n' + expand(dep_pkg, dep_name)
        return out

    return expand(package, name)


@functools.lru_cache(maxsize=None)
def type_hash(msg_type: str) -> str:
    """The RIHS01 type description hash of `msg_type` ('RIHS01_<64 hex>').

    Raises:
        MessageTypeError: the type's `.json` description is missing or has no hash for it.
    """
    package, name = split_type(msg_type)
    path = _msg_dir(package, msg_type) / f'{name}.json'
    try:
        hashes = json.loads(path.read_text(encoding='utf-8'))['type_hashes']
        return next(str(h['hash_string']) for h in hashes if h['type_name'] == msg_type)
    except (OSError, ValueError, KeyError, TypeError, StopIteration):
        raise MessageTypeError(f'no RIHS01 type hash for {msg_type!r} in {path}; '
                               f'reinstall the {package} wheel') from None


# -- CDR ---------------------------------------------------------------------------------
CDR_HEADER = b'\x00\x01\x00\x00'      # CDR, little endian, no options
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
    return CDR_HEADER + bytes(out.buf)
