"""`replay BAG`: publish a bag's input topics with the recorded timing.

Reads a rosbag2-style bag directory (metadata.yaml + .mcap files) or a single `.mcap` file
with the mcap reader and publishes the recorded CDR bytes unchanged (no decode/re-encode),
message i at `start + (log_time_i - log_time_0) / rate`. Publishers are reliable, depth
100, volatile, so reliable and best-effort subscribers both receive every message.

Exit codes: 0 done; 2 bad input (missing path, no bag, empty/non-MCAP/non-ros2 file,
no matching topic), one line on stderr, no traceback; 1 no subscriber appeared in time.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
import signal
import struct
import sys
import threading
import time
from typing import Any, TextIO

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.well_known import MessageEncoding, Profile
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
import yaml

from kneeseat_core.errors import KneeseatError
from kneeseat_ros import topics
from kneeseat_ros.errors import BagError
from .msgdefs import message_class

__all__ = ['BagError', 'BagMessage', 'PUBLISHER_QOS', 'DEFAULT_TOPICS', 'bag_files',
           'load_messages', 'main']

PUBLISHER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE)
DEFAULT_TOPICS = (topics.at_root(topics.POSE), topics.at_root(topics.JOINT_STATES))
PROGRESS_PERIOD_S = 0.5
WAIT_SLICE_S = 0.1          # longest uninterrupted wait, so Ctrl-C acts at once


@dataclass(frozen=True, slots=True)
class BagMessage:
    """One recorded message, still CDR-serialised."""

    topic: str
    msg_type: str          # 'pkg/msg/Type'
    data: bytes
    log_time_ns: int


def bag_files(path: Path) -> list[Path]:
    """The MCAP files of a bag directory (from metadata.yaml) or of a single `.mcap` path.

    Raises:
        BagError: the path is missing, or a directory without metadata.yaml or its files.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist; give a bag directory or an .mcap file')
    if path.is_file():
        return [path]
    meta = path / 'metadata.yaml'
    if not meta.is_file():
        hint = (f'run `python -m kneeseat_ros.bag.recovery {path}` to rebuild it'
                if any(path.glob('*.mcap')) else 'give a bag directory made by the recorder')
        raise BagError(f'{path} has no metadata.yaml; {hint}')
    try:
        info = yaml.safe_load(meta.read_text(encoding='utf-8'))['rosbag2_bagfile_information']
        names = [str(n) for n in info['relative_file_paths']]
        storage = info.get('storage_identifier', 'mcap')
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        raise BagError(f'{meta} is not a rosbag2 metadata file; re-record the bag or run '
                       '`python -m kneeseat_ros.bag.recovery` on it') from None
    if storage != 'mcap':
        raise BagError(f'bag {path} uses storage {storage!r}, not mcap; convert it with '
                       '`ros2 bag convert` or rosbags-convert')
    files = [path / Path(n).name for n in names]
    missing = [f.name for f in files if not f.is_file()]
    if not files or missing:
        raise BagError(f'bag {path} lists no .mcap file or misses {", ".join(missing)}; '
                       'restore the files or re-record')
    return files


def _read_file(path: Path, topics: set[str] | None) -> list[BagMessage]:
    if path.stat().st_size == 0:
        raise BagError(f'{path} is empty (0 bytes); record again or pick another file')
    try:
        with open(path, 'rb') as stream:
            reader = make_reader(stream)
            header = reader.get_header()
            if header.profile != Profile.ROS2:
                raise BagError(f'{path} has MCAP profile {header.profile!r}, not ros2; replay '
                               'only plays ROS 2 bags')
            if reader.get_summary() is None:
                raise BagError(f'{path} has no summary (its recording was interrupted); run '
                               '`python -m kneeseat_ros.bag.recovery` on the bag first')
            out = []
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if topics is not None and channel.topic not in topics:
                    continue
                if channel.message_encoding != MessageEncoding.CDR or schema is None:
                    raise BagError(f'{path}: topic {channel.topic} is encoded as '
                                   f'{channel.message_encoding!r} without a ros2 schema; only '
                                   'cdr messages can be replayed')
                out.append(BagMessage(channel.topic, schema.name, bytes(message.data),
                                      int(message.log_time)))
            return out
    except BagError:
        raise
    except OSError as err:
        raise BagError(f'cannot read {path}: {err.strerror}; check permissions') from None
    except (McapError, struct.error, ValueError, EOFError) as err:
        raise BagError(f'{path} is not a readable MCAP file ({err}); give a bag recorded '
                       'by kneeseat or ros2 bag') from None


def load_messages(path: Path, topics: Sequence[str] | None = DEFAULT_TOPICS
                  ) -> list[BagMessage]:
    """All recorded messages on `topics` (None = every topic), in log-time order.

    Raises:
        BagError: see `bag_files`; an empty, non-MCAP, truncated or non-ros2 file; or no
            message on any of `topics`.
    """
    wanted = set(topics) if topics is not None else None
    messages: list[BagMessage] = []
    seen: set[str] = set()
    for file in bag_files(path):
        part = _read_file(file, None)
        seen.update(m.topic for m in part)
        messages.extend(m for m in part if wanted is None or m.topic in wanted)
    if not messages:
        have = ', '.join(sorted(seen)) or 'no messages at all'
        raise BagError(f'bag {path} has no message on {", ".join(sorted(wanted or []))} '
                       f'(it has: {have}); choose topics with --topics')
    messages.sort(key=lambda m: m.log_time_ns)      # stable: file order breaks ties
    return messages


def build_parser() -> argparse.ArgumentParser:
    """The `replay` command line."""
    p = argparse.ArgumentParser(prog='replay', description='Publish the input topics of a '
                                'kneeseat/rosbag2 MCAP bag with the recorded timing.')
    p.add_argument('bag', type=Path, help='bag directory (with metadata.yaml) or .mcap file')
    p.add_argument('--topics', nargs='+', default=list(DEFAULT_TOPICS), metavar='TOPIC',
                   help='topics to publish (default: %(default)s)')
    p.add_argument('--rate', type=float, default=1.0, metavar='FACTOR',
                   help='speed factor: 2 plays twice as fast (default 1)')
    p.add_argument('--loop', type=int, nargs='?', const=0, default=1, metavar='N',
                   help='play N times in total; without N, until Ctrl-C (default: once)')
    p.add_argument('--delay-s', type=float, default=0.0,
                   help='wait this long after the publishers exist before playing')
    p.add_argument('--wait-for-subscribers', type=int, default=0, metavar='N',
                   help='before playing, wait until every published topic has N subscribers')
    p.add_argument('--wait-timeout-s', type=float, default=10.0,
                   help='give up waiting for subscribers after this long (default 10)')
    p.add_argument('--quiet', action='store_true', help='no progress line')
    return p


def _check_args(args: argparse.Namespace) -> None:
    def positive(name: str, value: float) -> None:
        if not (value > 0 and value < float('inf')):
            raise BagError(f'{name} {value} must be a positive finite number')
    positive('--rate', args.rate)
    if args.loop < 0:
        raise BagError(f'--loop {args.loop} is negative; give N >= 1, or no N for forever')
    if not args.delay_s >= 0 or args.wait_for_subscribers < 0:
        raise BagError('--delay-s and --wait-for-subscribers must not be negative')
    positive('--wait-timeout-s', args.wait_timeout_s)


class _Progress:
    """A throttled one-line progress display on a text stream."""

    def __init__(self, stream: TextIO | None, total: int, span_s: float) -> None:
        self._stream, self._total, self._span = stream, total, span_s
        self._last = -float('inf')

    def update(self, done: int, bag_s: float, loop: int, force: bool = False) -> None:
        now = time.monotonic()
        if self._stream is None or (not force and now - self._last < PROGRESS_PERIOD_S):
            return
        self._last = now
        self._stream.write(f'\rreplay: pass {loop}  {done}/{self._total} messages  '
                           f'{bag_s:7.2f}/{self._span:.2f} s bag time')
        self._stream.flush()


def _wait(stop: threading.Event, seconds: float, ok: Callable[[], bool]) -> bool:
    """Wait `seconds` unless stopped; False if the replay must end."""
    deadline = time.monotonic() + seconds
    while ok():
        left = deadline - time.monotonic()
        if left <= 0:
            return True
        if stop.wait(min(left, WAIT_SLICE_S)):
            return False
    return False


def _play(messages: list[BagMessage], publishers: dict[str, Any], rate: float, loops: int,
          ok: Callable[[], bool], stop: threading.Event, progress: _Progress) -> int:
    """Publish `messages` `loops` times (0 = until stopped); returns how many were sent."""
    t0 = messages[0].log_time_ns
    span_ns = messages[-1].log_time_ns - t0
    gap_ns = span_ns // (len(messages) - 1) if len(messages) > 1 else 0
    sent, loop = 0, 0
    while loops == 0 or loop < loops:
        loop += 1
        start = time.monotonic()
        for i, msg in enumerate(messages):
            due = start + (msg.log_time_ns - t0) / 1e9 / rate
            if not _wait(stop, due - time.monotonic(), ok):
                return sent
            publishers[msg.topic].publish(msg.data)
            sent += 1
            progress.update(i + 1, (msg.log_time_ns - t0) / 1e9, loop)
        progress.update(len(messages), span_ns / 1e9, loop, force=True)
        if (loops == 0 or loop < loops) and not _wait(stop, gap_ns / 1e9 / rate, ok):
            return sent
    return sent


def _stop_on_signals(stop: threading.Event) -> dict[int, Any]:
    """SIGINT/SIGTERM end the replay cleanly (main thread only); returns old handlers."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous: dict[int, Any] = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        previous[signum] = signal.signal(signum, lambda *_: stop.set())
    return previous


def _wait_for_subscribers(args: argparse.Namespace, pubs: dict[str, Any],
                          executor: SingleThreadedExecutor, ok: Callable[[], bool]) -> bool:
    """With --wait-for-subscribers N, spin until every topic has N subscribers; False when
    the replay must end first.

    Raises:
        TimeoutError: they did not come within --wait-timeout-s.
    """
    if not args.wait_for_subscribers:
        return True
    deadline = time.monotonic() + args.wait_timeout_s
    while min(p.get_subscription_count() for p in pubs.values()) < args.wait_for_subscribers:
        if not ok():
            return False
        if time.monotonic() > deadline:
            raise TimeoutError
        executor.spin_once(timeout_sec=WAIT_SLICE_S)
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `replay` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(remove_ros_args(['replay', *argv])[1:])
    try:
        _check_args(args)
        messages = load_messages(args.bag, args.topics)
        types = {m.topic: m.msg_type for m in messages}
        classes = {topic: message_class(t) for topic, t in types.items()}
    except KneeseatError as err:
        print(f'replay: error: {err}', file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = _stop_on_signals(stop)
    context = Context()
    rclpy.init(args=['replay', *argv], context=context,
               signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('kneeseat_replay', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def ok() -> bool:
        return context.ok() and not stop.is_set()

    status = 0
    try:
        pubs = {topic: node.create_publisher(cls, topic, PUBLISHER_QOS)
                for topic, cls in classes.items()}
        node.get_logger().info(f'replaying {len(messages)} messages on '
                               f'{", ".join(sorted(pubs))} from {args.bag} at x{args.rate:g}')
        if not _wait_for_subscribers(args, pubs, executor, ok):
            return 0
        if args.delay_s and not _wait(stop, args.delay_s, ok):
            return 0
        progress = _Progress(None if args.quiet else sys.stderr, len(messages),
                             (messages[-1].log_time_ns - messages[0].log_time_ns) / 1e9)
        started = time.monotonic()
        sent = _play(messages, pubs, args.rate, args.loop, ok, stop, progress)
        for pub in pubs.values():
            pub.wait_for_all_acked(Duration(seconds=5))
        if not args.quiet:
            print(f'\nreplay: published {sent} messages in {time.monotonic() - started:.2f} s',
                  file=sys.stderr)
    except TimeoutError:
        print(f'replay: error: fewer than {args.wait_for_subscribers} subscriber(s) on '
              f'{", ".join(sorted(classes))} after {args.wait_timeout_s:g} s; start the '
              'subscribers first or raise --wait-timeout-s', file=sys.stderr)
        status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return status


if __name__ == '__main__':
    sys.exit(main())
