"""ROS 2 message definitions as rosbag2 writes them into MCAP schemas.

Everything comes from the interface packages installed with the ROS wheels: the `.msg`
text from `<share>/<pkg>/msg/<Type>.msg` and the RIHS01 type hash from
`<share>/<pkg>/msg/<Type>.json`, where `<share>` is found through the ament index
(`AMENT_PREFIX_PATH` must include the virtual environment's prefix).

Schema text (rosbag2 Jazzy, `ros2msg` encoding): the root type's `.msg` text, then for
each dependency, depth-first, sorted by name within one definition, each type once:
``'\\n' + '=' * 80 + '\\nMSG: pkg/Type\\n' + text``.
"""
from __future__ import annotations

import functools
import importlib
import json
import re
from pathlib import Path
from typing import Any

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError

from kneeseat_core.errors import KneeseatError

__all__ = ['MessageTypeError', 'split_type', 'message_class', 'message_definition',
           'type_hash']

# Field types that are not messages (rosidl primitive types and their ROS 1 aliases).
PRIMITIVES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring', 'time', 'duration',
})
SEPARATOR = '=' * 80
_TYPE_RE = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)/(msg)/([A-Za-z][A-Za-z0-9_]*)$')


class MessageTypeError(KneeseatError):
    """A message type name is malformed or its interface package is not installed."""


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


def _msg_dir(package: str, msg_type: str) -> Path:
    try:
        return Path(get_package_share_directory(package)) / 'msg'
    except (PackageNotFoundError, LookupError, ValueError):
        raise MessageTypeError(
            f'interface package {package!r} of {msg_type!r} not found in the ament index; '
            'install its ROS wheel and put the venv prefix on AMENT_PREFIX_PATH '
            '(. scripts/env.sh)') from None


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
