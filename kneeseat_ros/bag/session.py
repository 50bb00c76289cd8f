"""Reading a session bag the node recorded: inputs matched to answers, last diagnostics.

`read_session` reads a bag written by table_server (mcap reader, mcap_ros2 decoder) and
pairs every `/knee/pose` input with the answers on `/knee/<body>/pose` that carry the same
header stamp. An answer's latency is the log time of the last body's output less the log
time of its input (both node clock, so it holds for a replay that re-publishes a bag's old
stamps, where the node's own stamp-based latency does not apply).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import numpy as np

from kneeseat_core.geometry import matrix_from_quat
from kneeseat_core.table import PoseTable
from kneeseat_core.typed import Floats
from kneeseat_ros import topics
from kneeseat_ros.conversions import stamp_ns

__all__ = ['SessionStats', 'read_session', 'table_deviation', 'POSE_TOPIC']

POSE_TOPIC = topics.at_root(topics.POSE)


@dataclass(frozen=True, slots=True, eq=False)
class SessionStats:
    """What one recorded session holds, matched input -> outputs by header stamp."""

    bag: Path
    bodies: tuple[str, ...]
    inputs: int                           # /knee/pose messages recorded (received)
    outputs: int                          # /knee/<body>/pose messages recorded
    answered: int                         # inputs with an output for every body
    diagnostics: int                      # /diagnostics messages recorded
    last_diagnostics: dict[str, str]      # key -> value of the last server status
    input_quat: Floats                    # (n, 4) xyzw of the answered inputs
    position_m: Floats                    # (n, B, 3) m, reference frame
    orientation_xyzw: Floats              # (n, B, 4)
    latency_ns: Floats                    # (n,) last output log_time - input log_time
    time_range_ns: tuple[int, int]        # first and last log_time in the bag

    def latency_ms(self, q: float) -> float:
        """Percentile `q` (0..100) of the answer latency in ms; NaN without answers."""
        if not self.latency_ns.size:
            return math.nan
        return float(np.percentile(self.latency_ns, q)) * 1e-6


def read_session(bag: Path, bodies: Sequence[str]) -> SessionStats:
    """Read a session bag written by table_server (mcap reader, mcap_ros2 decoder).

    Args:
        bag: the session directory (metadata.yaml + .mcap files).
        bodies: moving body names; outputs are read from /knee/<body>/pose.
    Raises:
        KneeseatError: the bag cannot be read (replay.BagError).
    """
    from .replay import bag_files
    out_topics = {topics.at_root(topics.body_pose(b)): i for i, b in enumerate(bodies)}
    inputs: dict[int, tuple[int, tuple[float, float, float, float]]] = {}
    outputs: dict[int, dict[int, tuple[int, list[float], list[float]]]] = {}
    n_out = n_diag = 0
    last: dict[str, str] = {}
    first_ns, last_ns = None, None
    for path in bag_files(bag):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
                t = int(message.log_time)
                first_ns = t if first_ns is None else min(first_ns, t)
                last_ns = t if last_ns is None else max(last_ns, t)
                topic = channel.topic
                if topic == POSE_TOPIC:
                    o = msg.pose.orientation
                    inputs[stamp_ns(msg.header.stamp)] = (t, (o.x, o.y, o.z, o.w))
                elif topic in out_topics:
                    n_out += 1
                    p, o = msg.pose.position, msg.pose.orientation
                    outputs.setdefault(stamp_ns(msg.header.stamp), {})[out_topics[topic]] = (
                        t, [p.x, p.y, p.z], [o.x, o.y, o.z, o.w])
                elif topic == topics.DIAGNOSTICS:
                    n_diag += 1
                    for status in msg.status:
                        if status.name == topics.STATUS_NAME:
                            last = {kv.key: kv.value for kv in status.values}
    quats, pos, ori, lat = [], [], [], []
    for stamp, (t_in, quat) in sorted(inputs.items()):
        answer = outputs.get(stamp, {})
        if len(answer) != len(bodies):
            continue
        quats.append(quat)
        pos.append([answer[i][1] for i in range(len(bodies))])
        ori.append([answer[i][2] for i in range(len(bodies))])
        lat.append(max(answer[i][0] for i in range(len(bodies))) - t_in)
    nb = len(bodies)
    return SessionStats(
        bag=bag, bodies=tuple(bodies), inputs=len(inputs), outputs=n_out, answered=len(quats),
        diagnostics=n_diag, last_diagnostics=last,
        input_quat=np.asarray(quats, dtype=np.float64).reshape(-1, 4),
        position_m=np.asarray(pos, dtype=np.float64).reshape(-1, nb, 3),
        orientation_xyzw=np.asarray(ori, dtype=np.float64).reshape(-1, nb, 4),
        latency_ns=np.asarray(lat, dtype=np.float64),
        time_range_ns=(first_ns or 0, last_ns or 0))


def table_deviation(session: SessionStats, table: PoseTable) -> tuple[float, float]:
    """Largest |output - table.interpolate(input)|: (position m, quaternion component)."""
    flexion, varus, _ = table.axes.decompose(matrix_from_quat(session.input_quat))
    dp = dq = 0.0
    for k, (f, v) in enumerate(zip(flexion.tolist(), varus.tolist())):
        look = table.interpolate(f, v)
        dp = max(dp, float(np.abs(session.position_m[k] - look.position_m).max()))
        dq = max(dq, float(np.abs(session.orientation_xyzw[k] - look.orientation_xyzw).max()))
    return dp, dq
