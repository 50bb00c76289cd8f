"""Reading what a crash left of a bag, and rewriting it into a complete one.

A process killed mid-write leaves an MCAP file without its summary (and a bag without its
metadata.yaml). `read_readable` reads every record up to the first damage - only whole
chunks are readable, the chunk being written is lost - and `recover` writes every readable
message into a new, complete bag (`python -m kneeseat_ros.bag.recovery BAG`).
"""
from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
import re
import sys

from mcap.exceptions import McapError
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
import yaml

from kneeseat_core.errors import KneeseatError
from kneeseat_ros.errors import RecorderError
from .msgdefs import TopicSpec
from .recorder import BagRecorder, METADATA_NAME

__all__ = ['ReadableContent', 'read_readable', 'RecoveryReport', 'recover', 'main']

_SPLIT_RE = re.compile(r'_(\d+)\.mcap$')


@dataclass(slots=True)
class ReadableContent:
    """What could be read from one MCAP file, front to back."""

    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)
    complete: bool = False           # the footer was reached
    problem: str = ''                # why reading stopped early


def read_readable(path: Path) -> ReadableContent:
    """Read every record of an MCAP file up to the first damage (e.g. a crash's truncation).

    Only whole chunks are readable: the chunk being written when a process died is lost.
    """
    content = ReadableContent()
    try:
        with open(path, 'rb') as stream:
            for record in StreamReader(stream).records:
                if isinstance(record, Header):
                    content.header = record
                elif isinstance(record, Schema):
                    content.schemas[record.id] = record
                elif isinstance(record, Channel):
                    content.channels[record.id] = record
                elif isinstance(record, Message):
                    content.messages.append(record)
                elif isinstance(record, Metadata):
                    content.metadata.append(record)
        content.complete = True
    except (McapError, EOFError, ValueError, OSError, MemoryError) as err:
        content.problem = str(err) or type(err).__name__
    except Exception as err:  # noqa: B902 - zstd and struct errors have no common base
        content.problem = f'{type(err).__name__}: {err}'
    return content


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """What `recover` wrote."""

    output: Path
    messages: int
    files_read: int
    damaged: tuple[str, ...]     # names of input files that ended early


def _split_index(path: Path) -> tuple[int, str]:
    match = _SPLIT_RE.search(path.name)
    return (int(match.group(1)) if match else -1, path.name)


def _specs_from(content: ReadableContent) -> Iterator[TopicSpec]:
    for channel in content.channels.values():
        schema = content.schemas.get(channel.schema_id)
        if schema is None:
            continue
        try:
            qos = tuple(yaml.safe_load(channel.metadata.get('offered_qos_profiles', '')) or ())
        except yaml.YAMLError:
            qos = ()
        yield TopicSpec(channel.topic, schema.name, schema.data.decode('utf-8', 'replace'),
                        channel.metadata.get('topic_type_hash', ''), qos)


def recover(bag: Path, output: Path | None = None) -> RecoveryReport:
    """Rewrite every readable message of a (possibly crashed) bag into a new, complete bag.

    Args:
        bag: a bag directory (its `*.mcap` files are read in split order, with or without
            a metadata.yaml) or a single `.mcap` file.
        output: the new bag directory (default: `<bag>_recovered` next to it); one output
            file per input file that still holds messages.
    Raises:
        RecorderError: `bag` has no MCAP file, or `output` cannot be written.
    """
    bag = Path(bag)
    if bag.is_dir():
        inputs = sorted(bag.glob('*.mcap'), key=_split_index)
    elif bag.is_file():
        inputs = [bag]
    else:
        inputs = []
    if not inputs:
        raise RecorderError(f'no .mcap file found at {bag}; give a bag directory or an MCAP '
                            'file')
    stem = bag.name if bag.is_dir() else bag.stem
    output = Path(output) if output is not None else bag.with_name(f'{stem}_recovered')
    contents = [read_readable(p) for p in inputs]
    meta: dict[str, str] = {}
    for content in contents:
        for record in content.metadata:
            if record.name == METADATA_NAME and not meta:
                meta = dict(record.metadata)
    recorder = BagRecorder(output, table_sha256=meta.get('table_sha256', ''),
                           table_path=meta.get('table_path', ''))
    damaged: list[str] = []
    try:
        for path, content in zip(inputs, contents):
            if not content.complete:
                damaged.append(path.name)
            for spec in _specs_from(content):
                recorder.add_spec(spec)
            recorder.split()
            for msg in content.messages:
                channel = content.channels.get(msg.channel_id)
                if channel is None or not recorder.has_topic(channel.topic):
                    continue
                recorder.write_raw(channel.topic, msg.data, msg.log_time, msg.publish_time)
    finally:
        recorder.close()
    if recorder.error is not None:
        raise RecorderError(recorder.error)
    return RecoveryReport(output, recorder.message_count, len(inputs), tuple(damaged))


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m kneeseat_ros.bag.recovery BAG [--output DIR]`."""
    parser = argparse.ArgumentParser(prog='python -m kneeseat_ros.bag.recovery',
                                     description='Rewrite the readable part of a crashed '
                                     'kneeseat session bag into a new, complete bag.')
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('--output', type=Path, default=None,
                        help='new bag directory (default: <bag>_recovered)')
    args = parser.parse_args(argv)
    try:
        report = recover(args.bag, args.output)
    except KneeseatError as err:
        print(f'recover: error: {err}', file=sys.stderr)
        return 2
    print(f'recovered {report.messages} messages from {report.files_read} file(s) into '
          f'{report.output}' + (f' (damaged: {", ".join(report.damaged)})'
                                if report.damaged else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
