"""`make_bag`: write an angle bag (tracked knee attitude on /knee/pose) for replay tests.

The angles come from a CSV file (header `time_s,flexion_deg,varus_deg`) or from a
generated trajectory: `sweep` (flexion 0 -> -90 -> 0 deg, varus 0, smooth turns) or `gait`
(a gait-like 1 Hz cycle, flexion between about -5 and -65 deg, small varus oscillation).
Each sample becomes a geometry_msgs/PoseStamped whose orientation is
`KneeAxes.orientation(flexion, varus, 0)` of the chosen knee axes, stamped
`--start-ns + t` (no wall clock: the same arguments give the same bytes).

Exit codes: 0 written; 2 bad input or an unwritable output (one line on stderr).
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
import csv
from dataclasses import dataclass
import math
from pathlib import Path
import sys

import numpy as np

from kneeseat_core.args import join_negative_values
from kneeseat_core.errors import KneeseatError
from kneeseat_core.geometry import KneeAxes, quat_from_matrix
from kneeseat_core.typed import Floats
from kneeseat_ros import topics
from kneeseat_ros.conversions import joint_state, pose_stamped, stamp_from_ns
from kneeseat_ros.errors import RecorderError, TrajectoryError
from .recorder import BagRecorder
from .replay import PUBLISHER_QOS

__all__ = ['TrajectoryError', 'AngleTrack', 'sweep', 'gait', 'read_csv', 'parse_axes',
           'write_angle_bag', 'main', 'DEFAULT_START_NS', 'DEFAULT_AXES']

DEFAULT_START_NS = 1_700_000_000 * 1_000_000_000   # fixed epoch: 2023-11-14T22:13:20Z
DEFAULT_AXES = '0,0,1/1,0,0/0,1,0'                  # flexion / varus / long (TKA frame)
CSV_COLUMNS = ('time_s', 'flexion_deg', 'varus_deg')
POSE_TOPIC = topics.at_root(topics.POSE)
JOINT_STATES_TOPIC = topics.at_root(topics.JOINT_STATES)
_VECTOR_OPTIONS = ('--axes',)     # values may start with a minus: -1,0,0/...


@dataclass(frozen=True, slots=True, eq=False)
class AngleTrack:
    """Knee angles over time."""

    time_s: Floats         # (n,) s from the start, strictly increasing, first = 0 or later
    flexion_rad: Floats    # (n,) rad
    varus_rad: Floats      # (n,) rad


def _times(duration_s: float, rate_hz: float) -> Floats:
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise TrajectoryError(f'--duration-s {duration_s} must be a positive number of seconds')
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= 10_000):
        raise TrajectoryError(f'--rate-hz {rate_hz} must be in (0, 10000] Hz')
    n = int(round(duration_s * rate_hz)) + 1
    return np.arange(n, dtype=np.float64) / rate_hz


def sweep(duration_s: float, rate_hz: float = 100.0) -> AngleTrack:
    """Slow flexion sweep 0 -> -90 -> 0 deg over `duration_s`, varus 0 (cosine ease)."""
    t = _times(duration_s, rate_hz)
    flexion = -0.5 * math.radians(90.0) * (1.0 - np.cos(2.0 * np.pi * t / duration_s))
    return AngleTrack(t, flexion, np.zeros_like(t))


def _bump(phase: Floats, centre: float, width: float) -> Floats:
    """Periodic Gaussian bump over the unit gait cycle."""
    d = (phase - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


def gait(duration_s: float, rate_hz: float = 100.0, cycle_hz: float = 1.0) -> AngleTrack:
    """Gait-like knee cycle at `cycle_hz`.

    Flexion (negative = flexed, deg): about -5 at heel strike, a loading-response peak of
    about -17 at 15 % of the cycle, back near -5 in mid stance, the swing peak of about -65
    at 72 %, extension again before the next heel strike. Varus oscillates by +-1.5 deg.
    """
    t = _times(duration_s, rate_hz)
    phase = (t * cycle_hz) % 1.0
    flexion_deg = -(4.0 + 12.0 * _bump(phase, 0.15, 0.06) + 61.0 * _bump(phase, 0.72, 0.095))
    varus_deg = 1.5 * np.sin(2.0 * np.pi * (phase - 0.1))
    return AngleTrack(t, np.radians(flexion_deg), np.radians(varus_deg))


def read_csv(path: Path) -> AngleTrack:
    """Read `time_s,flexion_deg,varus_deg` rows (header row required, extra columns ignored).

    Raises:
        TrajectoryError: unreadable file, missing header column, or a bad row (the message
            names the line): wrong field count, not a finite number, time not increasing.
    """
    try:
        text = Path(path).read_text(encoding='utf-8-sig')
    except (OSError, UnicodeDecodeError) as err:
        raise TrajectoryError(f'cannot read angle CSV {path}: '
                              f'{getattr(err, "strerror", None) or err}; check the path') from None
    rows = list(csv.reader(text.splitlines()))
    lines = [(i + 1, r) for i, r in enumerate(rows) if r and any(c.strip() for c in r)]
    if not lines:
        raise TrajectoryError(f'angle CSV {path} is empty; write a header '
                              f'{",".join(CSV_COLUMNS)} and one row per sample')
    header_line, header = lines[0]
    names = [c.strip() for c in header]
    missing = [c for c in CSV_COLUMNS if c not in names]
    if missing:
        raise TrajectoryError(f'{path}:{header_line}: header lacks column(s) '
                              f'{", ".join(missing)}; the first row must name '
                              f'{",".join(CSV_COLUMNS)}')
    cols = [names.index(c) for c in CSV_COLUMNS]
    values: list[tuple[float, float, float]] = []
    for line, row in lines[1:]:
        if len(row) != len(names):
            raise TrajectoryError(f'{path}:{line}: {len(row)} fields, the header has '
                                  f'{len(names)}; fix or remove this row')
        try:
            t, f, v = (float(row[c]) for c in cols)
        except ValueError:
            raise TrajectoryError(f'{path}:{line}: {",".join(row)!r} is not numeric; give '
                                  'seconds and degrees as plain numbers') from None
        if not all(math.isfinite(x) for x in (t, f, v)) or t < 0:
            raise TrajectoryError(f'{path}:{line}: values must be finite and time_s >= 0; '
                                  'fix this row')
        if values and t <= values[-1][0]:
            raise TrajectoryError(f'{path}:{line}: time_s {t} does not increase (previous '
                                  f'{values[-1][0]}); sort the rows by time')
        values.append((t, f, v))
    if not values:
        raise TrajectoryError(f'angle CSV {path} has a header but no rows; add samples')
    arr = np.asarray(values, dtype=np.float64)
    return AngleTrack(arr[:, 0], np.radians(arr[:, 1]), np.radians(arr[:, 2]))


def parse_axes(text: str) -> KneeAxes:
    """Parse 'FX,FY,FZ/VX,VY,VZ/LX,LY,LZ' (flexion / varus / long, reference frame).

    Raises:
        TrajectoryError: not three vectors of three numbers, or the axes are invalid.
    """
    try:
        vecs = [[float(x) for x in part.split(',')] for part in text.split('/')]
        if len(vecs) != 3 or any(len(v) != 3 for v in vecs):
            raise ValueError
    except ValueError:
        raise TrajectoryError(f'--axes {text!r} is not three vectors; write flexion/varus/long '
                              f'like {DEFAULT_AXES}') from None
    try:
        return KneeAxes.from_vectors(*vecs)
    except KneeseatError as err:
        raise TrajectoryError(f'--axes {text!r}: {err}') from None


def write_angle_bag(directory: Path, track: AngleTrack, axes: KneeAxes, *,
                    frame_id: str = 'femur', start_ns: int = DEFAULT_START_NS,
                    topic: str = POSE_TOPIC, joint_states: bool = False,
                    table_sha256: str = '', table_path: str = '') -> int:
    """Write `track` as PoseStamped messages (and optionally JointState) into a new bag.

    Args:
        directory: the new bag directory (must not exist or be empty).
        track: the angles; message i is stamped and logged at start_ns + time_s[i].
        axes: knee axes that turn (flexion, varus) into the tibia orientation.
        joint_states: also write sensor_msgs/JointState on /knee/joint_states.
    Returns:
        The number of messages written.
    Raises:
        RecorderError: the bag cannot be written.
    """
    quats = quat_from_matrix(axes.orientation(track.flexion_rad, track.varus_rad, 0.0))
    stamps = start_ns + np.round(track.time_s * 1e9).astype(np.int64)
    with BagRecorder(Path(directory), table_sha256=table_sha256,
                     table_path=table_path) as recorder:
        recorder.add_topic(topic, 'geometry_msgs/msg/PoseStamped', PUBLISHER_QOS)
        if joint_states:
            recorder.add_topic(JOINT_STATES_TOPIC, 'sensor_msgs/msg/JointState',
                               PUBLISHER_QOS)
        for i, ns in enumerate(int(s) for s in stamps):
            stamp = stamp_from_ns(ns)
            recorder.write(topic, pose_stamped((0.0, 0.0, 0.0), quats[i], stamp, frame_id),
                           ns, ns)
            if joint_states:
                recorder.write(JOINT_STATES_TOPIC,
                               joint_state(track.flexion_rad[i], track.varus_rad[i], stamp),
                               ns, ns)
    if recorder.error is not None:
        raise RecorderError(recorder.error)
    return recorder.message_count


def build_parser() -> argparse.ArgumentParser:
    """The `make_bag` command line."""
    p = argparse.ArgumentParser(
        prog='make_bag', description='Write an angle bag (PoseStamped on /knee/pose) from a '
        'CSV file or a generated trajectory.')
    p.add_argument('output', type=Path, help='new bag directory (must not exist or be empty)')
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument('--csv', type=Path, help='CSV with header time_s,flexion_deg,varus_deg')
    src.add_argument('--trajectory', choices=('sweep', 'gait'), help='generated trajectory')
    p.add_argument('--duration-s', type=float, default=10.0,
                   help='trajectory length in seconds (default 10)')
    p.add_argument('--rate-hz', type=float, default=100.0,
                   help='trajectory sample rate (default 100)')
    knee = p.add_mutually_exclusive_group()
    knee.add_argument('--axes', default=None,
                      help=f'flexion/varus/long axes in the reference frame '
                      f'(default {DEFAULT_AXES})')
    knee.add_argument('--table', type=Path, default=None,
                      help='take the axes and reference frame from this table file')
    p.add_argument('--frame', default=None, help="header frame_id (default 'femur' or the "
                   "table's reference frame)")
    p.add_argument('--start-ns', type=int, default=DEFAULT_START_NS,
                   help=f'stamp of t = 0 in ns since the epoch (default {DEFAULT_START_NS})')
    p.add_argument('--topic', default=POSE_TOPIC, help=f'pose topic (default {POSE_TOPIC})')
    p.add_argument('--joint-states', action='store_true',
                   help='also write sensor_msgs/JointState on /knee/joint_states')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `make_bag` console script; returns the exit code."""
    args = build_parser().parse_args(
        join_negative_values(sys.argv[1:] if argv is None else argv, _VECTOR_OPTIONS))
    try:
        if args.start_ns < 0:
            raise TrajectoryError(f'--start-ns {args.start_ns} is negative; give ns since the '
                                  'epoch')
        table_sha256 = table_path = ''
        frame = 'femur'
        if args.table is not None:
            from kneeseat_core.table import read_table
            table = read_table(args.table)
            axes, frame = table.axes, table.reference_frame
            table_sha256, table_path = table.sha256, str(args.table)
        else:
            axes = parse_axes(args.axes or DEFAULT_AXES)
        if args.csv is not None:
            track = read_csv(args.csv)
        elif args.trajectory == 'sweep':
            track = sweep(args.duration_s, args.rate_hz)
        else:
            track = gait(args.duration_s, args.rate_hz)
        count = write_angle_bag(args.output, track, axes, frame_id=args.frame or frame,
                                start_ns=args.start_ns, topic=args.topic,
                                joint_states=args.joint_states, table_sha256=table_sha256,
                                table_path=table_path)
    except KneeseatError as err:
        print(f'make_bag: error: {err}', file=sys.stderr)
        return 2
    print(f'make_bag: wrote {count} messages ({track.time_s[-1]:.2f} s) to {args.output}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
