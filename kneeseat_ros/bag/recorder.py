"""Session logs: rosbag2-style bag directories of MCAP files (recovery: `recovery`).

A bag is a directory `<name>/` holding `<name>_0.mcap`, `<name>_1.mcap`, ... and a
`metadata.yaml` (rosbag2 version 9), so `ros2 bag`, rosbags, Foxglove and the `mcap` CLI
read it. Each MCAP file has profile `ros2`, one `ros2msg` schema per type (the full `.msg`
text with dependencies, see `kneeseat_ros.bag.msgdefs`), one `cdr` channel per topic with the
channel metadata `offered_qos_profiles` and `topic_type_hash`, zstd chunks with message
indexes, and a Metadata record named 'kneeseat' with the table's SHA-256 and path.

Nothing here reads a wall clock: the caller gives every time stamp, so the same input
gives the same bytes (the shipped demo bag relies on it).

Failure policy: a directory that cannot be created or written raises `RecorderError` at
construction. After that `write` never raises on an I/O error: it records the error in
`BagRecorder.error`, stops writing and returns, so a node keeps serving. A process killed
mid-write leaves a file without its summary; `kneeseat_ros.bag.recovery.recover` rewrites every
readable message into a new, complete bag (`python -m kneeseat_ros.bag.recovery BAG`).

The well-known MCAP names (profile, encodings) come from `mcap.well_known`. Messages are
CDR bytes: the node's own, or `cdr.serialize` for message objects (why not rclpy's or
mcap-ros2-support's serialiser: `kneeseat_ros.cdr`). What a bag stores about a topic
(definition, type hash, offered QoS) is `msgdefs.TopicSpec`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
import threading
from typing import Any, BinaryIO

from mcap.exceptions import McapError
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import __version__ as MCAP_VERSION, CompressionType, IndexType, Writer
from rclpy.qos import QoSProfile
import yaml

from kneeseat_core.errors import ConfigError
from kneeseat_core.files import write_bytes
from kneeseat_ros.cdr import serialize
from kneeseat_ros.errors import RecorderError
from .msgdefs import topic_spec, TopicSpec

__all__ = ['BagRecorder', 'session_directory', 'open_session', 'METADATA_NAME']

PROFILE = Profile.ROS2                      # 'ros2'
SCHEMA_ENCODING = SchemaEncoding.ROS2       # 'ros2msg'
MESSAGE_ENCODING = MessageEncoding.CDR      # 'cdr'
METADATA_NAME = 'kneeseat'
LIBRARY = f'kneeseat_ros.bag.recorder; mcap-python/{MCAP_VERSION}'
BAG_VERSION = 9
CHUNK_SIZE_BYTES = 768 * 1024      # rosbag2's default MCAP chunk size
MESSAGE_RECORD_OVERHEAD = 31       # opcode, length, channel, sequence, two stamps (bytes)


def _yaml(data: Any) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


@dataclass(slots=True)
class _FileStats:
    path: Path
    start_ns: int = -1
    end_ns: int = -1
    count: int = 0


@dataclass(slots=True)
class _OpenFile:
    stats: _FileStats
    stream: BinaryIO
    writer: Writer
    channels: dict[str, int] = field(default_factory=dict)    # topic -> channel id
    schemas: dict[str, int] = field(default_factory=dict)     # type -> schema id
    last_tell: int = 0
    pending_bytes: int = 0         # uncompressed bytes in the open chunk (estimate)
    last_flush_ns: int = -1


def session_directory(base: Path, now_ns: int) -> Path:
    """A new bag directory for one session under `base`: `kneeseat_<YYYYmmdd_HHMMSS>` at
    `now_ns` (UTC), with `_1`, `_2`, ... appended while that name exists."""
    now = datetime.fromtimestamp(now_ns / 1e9, tz=timezone.utc)
    directory = base / f'kneeseat_{now:%Y%m%d_%H%M%S}'
    n = 1
    while directory.exists():
        directory, n = base / f'kneeseat_{now:%Y%m%d_%H%M%S}_{n}', n + 1
    return directory


def open_session(base: Path, now_ns: int, topics: Sequence[tuple[str, str, QoSProfile]],
                 table_sha256: str, table_path: str, *, split_size_bytes: int = 0,
                 split_duration_s: float = 0.0) -> BagRecorder:
    """Start recording one node session into a new bag under `base` (`session_directory`).

    Every topic's definition is found first, so that a topic that cannot be recorded leaves
    no directory behind.

    Args:
        topics: (topic, 'pkg/msg/Type', offered QoS) of every topic to record.
    Raises:
        ConfigError: a topic's message type cannot be recorded (names the `record`
            parameter).
        RecorderError: the bag directory cannot be created.
    """
    try:
        specs = [topic_spec(*t) for t in topics]
    except RecorderError as err:
        raise ConfigError(f"parameter 'record': {err}") from None
    recorder = BagRecorder(session_directory(base, now_ns), split_size_bytes=split_size_bytes,
                           split_duration_s=split_duration_s, table_sha256=table_sha256,
                           table_path=table_path)
    for spec in specs:
        recorder.add_spec(spec)
    return recorder


class BagRecorder:
    """Writes one rosbag2-style bag directory (metadata.yaml + .mcap files).

    Thread-safe: `write` may be called from several executor threads. Do not call `close`
    from a signal handler that may interrupt `write`; let the handler stop the spin and
    close afterwards (rclpy's own SIGINT/SIGTERM handling does exactly that).
    """

    def __init__(self, directory: Path, *, split_size_bytes: int = 0,
                 split_duration_s: float = 0.0, table_sha256: str = '',
                 table_path: str = '', chunk_size_bytes: int = CHUNK_SIZE_BYTES,
                 flush_interval_s: float = 5.0) -> None:
        """Create the directory and its first MCAP file.

        Args:
            directory: the bag directory; must not exist yet or be empty. Files are named
                `<directory name>_<N>.mcap`.
            split_size_bytes: start a new file once a file reaches this size (0 = never).
            split_duration_s: start a new file once a file spans this much log time
                (0 = never).
            table_sha256: the served table's `arrays_sha256`, stored in every file.
            table_path: the served table's path, stored in every file.
            chunk_size_bytes: uncompressed size at which a chunk is closed and written.
            flush_interval_s: also close the open chunk once it spans this much log time,
                bounding what a crash can lose (0 = by size only).
        Raises:
            RecorderError: the directory is not empty, or cannot be created or written, or
                a size/duration is negative.
        """
        self._dir = Path(directory)
        for name, value in (('split_size_bytes', split_size_bytes),
                            ('split_duration_s', split_duration_s),
                            ('chunk_size_bytes', chunk_size_bytes),
                            ('flush_interval_s', flush_interval_s)):
            if not value >= 0:
                raise RecorderError(f'{name}={value} for bag {self._dir} is negative; '
                                    'give 0 (off) or a positive value')
        self._split_size = int(split_size_bytes)
        self._split_ns = int(round(split_duration_s * 1e9))
        self._chunk_size = int(chunk_size_bytes)
        self._flush_ns = int(round(flush_interval_s * 1e9))
        self._kneeseat_meta = {'table_sha256': str(table_sha256), 'table_path': str(table_path)}
        self._lock = threading.Lock()
        self._specs: dict[str, TopicSpec] = {}
        self._topic_counts: dict[str, int] = {}
        self._files: list[_FileStats] = []
        self._open: _OpenFile | None = None
        self._split_pending = False
        self._error: str | None = None
        self._closed = False
        self._count = 0
        try:
            if self._dir.exists() and (not self._dir.is_dir() or any(self._dir.iterdir())):
                raise RecorderError(f'bag directory {self._dir} already exists and is not '
                                    'empty; choose a new directory or remove the old bag')
            self._dir.mkdir(parents=True, exist_ok=True)
            self._open_file()
        except OSError as err:
            raise RecorderError(f'cannot create bag directory {self._dir}: '
                                f'{err.strerror or err}; choose a writable directory with '
                                'free space') from None

    # -- public API -----------------------------------------------------------------------
    @property
    def directory(self) -> Path:
        """The bag directory."""
        return self._dir

    @property
    def error(self) -> str | None:
        """Why recording stopped (one line), or None while it works."""
        return self._error

    @property
    def message_count(self) -> int:
        """Messages written so far, over all files."""
        return self._count

    @property
    def paths(self) -> list[Path]:
        """The MCAP files written so far, in order."""
        return [f.path for f in self._files]

    def add_topic(self, topic: str, msg_type: str, qos: QoSProfile | None = None) -> None:
        """Declare a topic before writing to it; idempotent per topic.

        Args:
            topic: the topic name, e.g. '/knee/pose'.
            msg_type: like 'geometry_msgs/msg/PoseStamped'.
            qos: the QoS offered by its publisher (rclpy's default profile if None).
        Raises:
            RecorderError: the type is unknown, or the topic was added with another type.
        """
        self.add_spec(topic_spec(topic, msg_type, qos))

    def has_topic(self, topic: str) -> bool:
        """Whether `topic` was added (`add_topic` or `add_spec`)."""
        with self._lock:
            return topic in self._specs

    def add_spec(self, spec: TopicSpec) -> None:
        """Declare a topic from a ready `TopicSpec` (used by `recover`); idempotent per topic.

        Raises:
            RecorderError: the topic was already added with another type.
        """
        with self._lock:
            old = self._specs.get(spec.topic)
            if old is not None:
                if old.msg_type != spec.msg_type:
                    raise RecorderError(f'topic {spec.topic} is already recorded as '
                                        f'{old.msg_type}, not {spec.msg_type}; use one type '
                                        'per topic')
                return
            self._specs[spec.topic] = spec
            self._topic_counts[spec.topic] = 0
            if self._open is not None and self._error is None:
                self._guard(self._register, self._open, spec)

    def write(self, topic: str, message: Any, log_time_ns: int, publish_time_ns: int) -> None:
        """Serialise an rclpy message (CDR, see `cdr.serialize`) and append it.

        Never raises on an I/O error: sets `error`, stops writing and returns.

        Args:
            topic: a topic declared with `add_topic`.
            message: an rclpy message instance of the topic's type.
            log_time_ns: receive time (ns, node clock).
            publish_time_ns: send time (ns), e.g. the header stamp.
        Raises:
            RecorderError: the topic was never added.
        """
        self.write_raw(topic, serialize(message), log_time_ns, publish_time_ns)

    def write_raw(self, topic: str, data: bytes, log_time_ns: int,
                  publish_time_ns: int) -> None:
        """Append already CDR-serialised bytes; same contract as `write`."""
        with self._lock:
            if topic not in self._specs:
                raise RecorderError(f'topic {topic} was not added to bag {self._dir}; call '
                                    'add_topic(topic, type) before writing')
            if self._closed or self._error is not None:
                return
            log_ns, pub_ns = int(log_time_ns), int(publish_time_ns)
            self._guard(self._write_locked, topic, data, log_ns, pub_ns)

    def split(self) -> None:
        """Start a new file before the next message (no-op if the current one is empty)."""
        with self._lock:
            if self._open is not None and self._open.stats.count:
                self._split_pending = True

    def close(self) -> None:
        """Finish the open MCAP file and write metadata.yaml; idempotent, never raises OSError.

        An I/O error here is recorded in `error`.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._open is not None and self._error is None:
                self._guard(self._finish_file)
            self._open = None
            self._guard(self._write_metadata)

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals (called with the lock held) ---------------------------------------------
    def _guard(self, func: Any, *args: Any) -> None:
        """Run an I/O step; on failure record the first error and stop writing."""
        try:
            func(*args)
        except (OSError, ValueError, McapError) as err:
            reason = getattr(err, 'strerror', None) or str(err)
            if self._error is None:
                self._error = (f'recording to {self._dir} stopped after {self._count} '
                               f'messages: {reason}; free disk space or choose another '
                               'record directory, then run `python -m kneeseat_ros.bag.recorder '
                               'recover` on this bag')
            if self._open is not None:
                try:
                    self._open.stream.close()
                except (OSError, ValueError):
                    pass
                self._open = None

    def _open_file(self) -> None:
        path = self._dir / f'{self._dir.name}_{len(self._files)}.mcap'
        stream: BinaryIO = open(path, 'xb')
        stats = _FileStats(path)
        self._files.append(stats)
        writer = Writer(stream, chunk_size=self._chunk_size, compression=CompressionType.ZSTD,
                        index_types=IndexType.ALL, repeat_channels=True, repeat_schemas=True,
                        use_chunking=True, use_statistics=True, use_summary_offsets=True)
        self._open = _OpenFile(stats, stream, writer)
        writer.start(profile=PROFILE, library=LIBRARY)
        writer.add_metadata(METADATA_NAME, dict(self._kneeseat_meta))
        for spec in self._specs.values():
            self._register(self._open, spec)
        stream.flush()
        self._open.last_tell = stream.tell()

    def _register(self, file: _OpenFile, spec: TopicSpec) -> None:
        if spec.msg_type not in file.schemas:
            file.schemas[spec.msg_type] = file.writer.register_schema(
                spec.msg_type, SCHEMA_ENCODING, spec.definition.encode('utf-8'))
        file.channels[spec.topic] = file.writer.register_channel(
            spec.topic, MESSAGE_ENCODING, file.schemas[spec.msg_type],
            {'offered_qos_profiles': _yaml(list(spec.qos)) if spec.qos else '',
             'topic_type_hash': spec.type_hash})

    def _finish_file(self) -> None:
        assert self._open is not None
        self._open.writer.finish()
        self._open.stream.close()
        self._open = None

    def _write_locked(self, topic: str, data: bytes, log_ns: int, pub_ns: int) -> None:
        file = self._open
        assert file is not None
        if file.stats.count and (
                self._split_pending
                or (self._split_ns and log_ns - file.stats.start_ns >= self._split_ns)):
            self._split_pending = False
            self._finish_file()
            self._open_file()
            file = self._open
            assert file is not None
        file.writer.add_message(file.channels[topic], log_time=log_ns, data=data,
                                publish_time=pub_ns, sequence=0)
        if file.last_flush_ns < 0:
            file.last_flush_ns = log_ns
        if self._flush_ns and log_ns - file.last_flush_ns >= self._flush_ns:
            file.writer.flush()          # closes the open chunk
            file.last_flush_ns = log_ns
        file.stream.flush()              # closed chunks reach the OS (survive SIGKILL)
        tell = file.stream.tell()
        if tell != file.last_tell:
            file.last_tell, file.pending_bytes = tell, 0
        else:
            file.pending_bytes += len(data) + MESSAGE_RECORD_OVERHEAD
        stats = file.stats
        stats.start_ns = log_ns if stats.count == 0 else min(stats.start_ns, log_ns)
        stats.end_ns = max(stats.end_ns, log_ns)
        stats.count += 1
        self._count += 1
        self._topic_counts[topic] += 1
        if self._split_size and tell + file.pending_bytes >= self._split_size:
            self._split_pending = True

    def _write_metadata(self) -> None:
        used = [f for f in self._files if f.count]
        start = min((f.start_ns for f in used), default=0)
        end = max((f.end_ns for f in used), default=0)
        info = {
            'version': BAG_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': end - start},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': self._count,
            'topics_with_message_count': [{
                'topic_metadata': {
                    'name': spec.topic,
                    'type': spec.msg_type,
                    'serialization_format': MESSAGE_ENCODING,
                    'offered_qos_profiles': [dict(q) for q in spec.qos],
                    'type_description_hash': spec.type_hash,
                },
                'message_count': self._topic_counts[spec.topic],
            } for spec in self._specs.values()],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [f.path.name for f in self._files],
            'files': [{
                'path': f.path.name,
                'starting_time': {'nanoseconds_since_epoch': f.start_ns if f.count else 0},
                'duration': {'nanoseconds': f.end_ns - f.start_ns if f.count else 0},
                'message_count': f.count,
            } for f in self._files],
            'custom_data': {f'kneeseat.{k}': v for k, v in self._kneeseat_meta.items()},
            'ros_distro': 'jazzy',
        }
        write_bytes(self._dir / 'metadata.yaml',
                    _yaml({'rosbag2_bagfile_information': info}).encode('utf-8'))
