"""ROS 2 message definitions as rosbag2 writes them into MCAP schemas.

Everything comes from the interface packages installed with the ROS wheels: the `.msg`
text from `<share>/<pkg>/msg/<Type>.msg` and the RIHS01 type hash from
`<share>/<pkg>/msg/<Type>.json`, where `<share>` is found through the ament index
(`AMENT_PREFIX_PATH`) or, when that is unset or lacks the package, beside the installed
Python package (`<prefix>/lib/pythonX.Y/site-packages/<pkg>` -> `<prefix>/share/<pkg>`).

Schema text (rosbag2 Jazzy, `ros2msg` encoding): the root type's `.msg` text, then for
each dependency, depth-first, sorted by name within one definition, each type once:
``'\\n' + '=' * 80 + '\\nMSG: pkg/Type\\n' + text``.

A `TopicSpec` is everything a bag stores about one topic: its type, that schema text, the
type hash and the offered QoS as rosbag2 Jazzy (metadata v9) writes it (`qos_to_dicts`).
"""
from __future__ import annotations

from dataclasses import dataclass
import functools
import importlib
import importlib.util
import json
from pathlib import Path
import re
import sys
from typing import Any

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError
from rclpy.qos import QoSProfile

from kneeseat_ros.errors import MessageTypeError, RecorderError

__all__ = ['split_type', 'message_class', 'message_definition', 'type_hash', 'TopicSpec',
           'topic_spec', 'qos_to_dicts', 'DEFAULT_QOS']

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


# -- what a bag stores about a topic ------------------------------------------------------
DEFAULT_QOS = QoSProfile(depth=10)  # rclpy's default publisher QoS


def _duration_dict(ns: int) -> dict[str, int]:
    return {'sec': ns // 1_000_000_000, 'nsec': ns % 1_000_000_000}


def qos_to_dicts(qos: QoSProfile) -> list[dict[str, Any]]:
    """The offered QoS of one publisher as rosbag2 Jazzy (metadata v9) writes it.

    Returns:
        A one-element list (rosbag2 stores one entry per publisher) of a dict with string
        policy names (`keep_last`, `reliable`, `volatile`, `automatic`, ...) and durations
        as `{sec, nsec}`.
    """
    return [{
        'history': qos.history.name.lower(),
        'depth': int(qos.depth),
        'reliability': qos.reliability.name.lower(),
        'durability': qos.durability.name.lower(),
        'deadline': _duration_dict(qos.deadline.nanoseconds),
        'lifespan': _duration_dict(qos.lifespan.nanoseconds),
        'liveliness': qos.liveliness.name.lower(),
        'liveliness_lease_duration': _duration_dict(qos.liveliness_lease_duration.nanoseconds),
        'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions),
    }]


@dataclass(frozen=True, slots=True)
class TopicSpec:
    """Everything a bag stores about one topic."""

    topic: str
    msg_type: str                   # 'pkg/msg/Type'
    definition: str                 # ros2msg schema text, dependencies included
    type_hash: str                  # 'RIHS01_...', '' if unknown
    qos: tuple[dict[str, Any], ...]  # offered QoS profiles (v9 dicts)


def topic_spec(topic: str, msg_type: str, qos: QoSProfile | None = None) -> TopicSpec:
    """Everything a bag stores about one topic, from the installed message package.

    Args:
        topic: the topic name, e.g. '/knee/pose'.
        msg_type: like 'geometry_msgs/msg/PoseStamped'.
        qos: the QoS offered by its publisher (rclpy's default profile if None).
    Raises:
        RecorderError: the type's definition or hash cannot be found.
    """
    try:
        return TopicSpec(topic, msg_type, message_definition(msg_type), type_hash(msg_type),
                         tuple(qos_to_dicts(qos if qos is not None else DEFAULT_QOS)))
    except MessageTypeError as err:
        raise RecorderError(f'cannot record {topic}: {err}') from None
