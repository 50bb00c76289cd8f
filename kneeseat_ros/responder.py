"""The node's hot path: one input message in, every body's pose out, as CDR bytes.

A `Responder` takes an input's CDR bytes (`kneeseat_ros.cdr`; rclpy's deserialiser only for
another encapsulation), checks it (`kneeseat_ros.conversions`, each rejection counted by
reason), turns it into (flexion, varus), looks the table up (`PoseTable.interpolate`, plain
Python) and publishes the answer as CDR bytes, recording inputs and answers as the same
bytes. No rclpy message object is built per message (benchmarks/bench_hotpath.py).

Attitude mode answers each `knee/pose` (tibia orientation in the reference frame) and
`knee/joint_states` message. Tracker mode composes each marker cluster's world pose with
its registration, pairs femur and tibia by stamp (`tracker.Pairer`), decodes the tibia's
orientation relative to the femur, and also publishes every bone in the world frame.

The responder's state is named: `TrackerMode` (what tracker mode needs, fixed at start),
`Answer` (the latest answer, which the node's marker timer reads from the executor thread:
one immutable object assigned at once, so it never sees a lookup with another answer's
stamp) and `TrackedBone` (a sample waiting in the pairer). The node changes what the
responder serves or records only through its methods (`set_input_topics`,
`start_recording`, `switch_route`). `Answer` and `TrackedBone` are NamedTuples: one is
made per message, and a NamedTuple costs a third of a frozen dataclass (0.3 against 1.0 us
on the dev machine).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, TYPE_CHECKING

from geometry_msgs.msg import PoseStamped
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.publisher import Publisher
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from kneeseat_core.errors import NonFiniteError, OutOfRangeError
from kneeseat_core.table import Lookup
from .cdr import (decode_joint_state, decode_pose_stamped, encode_joint_state, encode_pose_stamped,
                  PoseStampedWriter)
from .conversions import angles_from_joints, angles_from_orientation, quat_xyzw, rigid_from_fields
from .diagnostics import Counters
from .errors import BadInputError, CdrError
from .served import Route
from .tracker import compose, Pairer, Registration, relative_rotation, Rigid

if TYPE_CHECKING:
    from .bag.recorder import BagRecorder

__all__ = ['Responder', 'TrackerMode', 'Answer', 'TrackedBone', 'WARN_THROTTLE_S']

WARN_THROTTLE_S = 2.0      # at most one warning per reason and this many seconds


class TrackedBone(NamedTuple):
    """A bone's world pose from one tracker input, with that input's stamp."""

    pose: Rigid
    sec: int
    nanosec: int


@dataclass(frozen=True, slots=True, eq=False)
class TrackerMode:
    """What tracker mode needs: fixed when the node starts."""

    registration: Registration      # each bone's frame in its marker cluster's frame
    pairer: Pairer[TrackedBone]     # femur and tibia samples paired by stamp
    world_frame: str                # the clusters' frame (world poses, /tf parent)
    pair_tolerance_s: float         # as given (the pairer holds it in ns)


class Answer(NamedTuple):
    """The latest answer: the table's lookup and the stamp of the input it answered."""

    lookup: Lookup
    sec: int
    nanosec: int


class Responder:
    """Answers the node's inputs; the node may switch the route or start recording at any
    time (`switch_route`, `start_recording`)."""

    def __init__(self, route: Route, counters: Counters, log: RcutilsLogger,
                 now_ns: Callable[[], int], out_of_range: Literal['clamp', 'drop'],
                 joint_names: tuple[str, str], tracker: TrackerMode | None = None,
                 tf_pub: Publisher | None = None) -> None:
        """Args:
            route: the served table and its output publishers.
            counters: the node's diagnostics counters.
            log: the node's logger (throttled warnings).
            now_ns: the node clock in ns (log times of recorded messages, latency).
            out_of_range: 'clamp' or 'drop'.
            joint_names: JointState names of the flexion and varus joints.
            tracker: tracker mode's state, or None in attitude mode.
            tf_pub: /tf, or None when it is off.
        """
        self._route = route
        self._recorder: BagRecorder | None = None
        self._input_topics: tuple[str, ...] = ()      # resolved names, in input order
        self._last: Answer | None = None
        self._counters = counters
        self._log = log
        self._now_ns = now_ns
        self._out_of_range = out_of_range
        self._joint_names = joint_names
        self._tracker = tracker
        self._world_writer = PoseStampedWriter(tracker.world_frame if tracker is not None
                                               else '')
        self._tf_pub = tf_pub

    # ---- what the node reads and changes ------------------------------------------
    @property
    def route(self) -> Route:
        """The served table and its output publishers."""
        return self._route

    @property
    def last(self) -> Answer | None:
        """The latest answer, None before the first one and after `switch_route`."""
        return self._last

    def set_input_topics(self, topics: Sequence[str]) -> None:
        """Name the topics the inputs are recorded under.

        Args:
            topics: the inputs' resolved names, in input order (attitude mode: pose,
                joints; tracker mode: femur, tibia).
        """
        self._input_topics = tuple(topics)

    def start_recording(self, recorder: BagRecorder) -> None:
        """Record every input and answer from the next message on.

        Args:
            recorder: the session's bag (its topics added; see `set_input_topics`).
        """
        self._recorder = recorder

    def switch_route(self, route: Route) -> None:
        """Serve another table from the next message on (a reload); the latest answer,
        which belongs to the previous table, is forgotten.

        Args:
            route: the table to serve with its output publishers.
        """
        self._route = route
        self._last = None

    # ---- inputs ---------------------------------------------------------------------
    def handle_pose(self, data: bytes) -> None:
        """Attitude mode: a PoseStamped of the tibia's orientation in the reference frame."""
        taken = self._take_pose(data, 0)
        if taken is None:
            return
        sec, nanosec, frame, pose, ns = taken
        served = self._route.served
        try:
            flexion, varus = angles_from_orientation(frame, pose[3:], served.decoder,
                                                     served.frame)
        except BadInputError as err:
            self.drop(err.reason, err)
            return
        self._answer(flexion, varus, sec, nanosec, ns)

    def handle_joints(self, data: bytes) -> None:
        """Attitude mode: a JointState with the flexion and varus joints (rad)."""
        try:
            sec, nanosec, frame, names, position, velocity, effort = decode_joint_state(data)
        except CdrError as err:
            msg = self._deserialize(data, JointState, err)
            if msg is None:
                return
            sec, nanosec, frame = (msg.header.stamp.sec, msg.header.stamp.nanosec,
                                   msg.header.frame_id)
            names, position = list(msg.name), tuple(msg.position)
            velocity, effort = tuple(msg.velocity), tuple(msg.effort)
        self._counters.received += 1
        ns = self._stamped(sec, nanosec)
        recorder = self._recorder
        if recorder is not None:
            recorder.write_raw(
                self._input_topics[1],
                encode_joint_state(sec, nanosec, frame, names, position, velocity, effort),
                self._now_ns(), ns)
        try:
            flexion, varus = angles_from_joints(names, position, len(velocity), len(effort),
                                                self._joint_names)
        except BadInputError as err:
            self.drop(err.reason, err)
            return
        self._answer(flexion, varus, sec, nanosec, ns)

    def handle_rigid(self, side: int, data: bytes) -> None:
        """Tracker mode: one rigid body's world pose (side 0 femur, 1 tibia); answers when
        it completes a pair."""
        taken = self._take_pose(data, side)
        if taken is None:
            return
        sec, nanosec, frame, pose, ns = taken
        tracker = self._tracker
        assert tracker is not None
        registration = tracker.registration
        try:
            cluster = rigid_from_fields(frame, pose, tracker.world_frame,
                                        ('femur', 'tibia')[side] + ' rigid body')
        except BadInputError as err:
            self.drop(err.reason, err)
            return
        bone = compose(cluster, registration.femur if side == 0 else registration.tibia)
        pairer = tracker.pairer
        unpaired, stale = pairer.unpaired, pairer.stale
        pair = pairer.add(side, ns, TrackedBone(bone, sec, nanosec))
        if pairer.unpaired != unpaired or pairer.stale != stale:
            self._log.warning(f'tracker inputs dropped: {pairer.unpaired} unpaired, '
                              f'{pairer.stale} stale so far (pair tolerance '
                              f'{tracker.pair_tolerance_s} s)',
                              throttle_duration_sec=WARN_THROTTLE_S)
        if pair is None:
            return
        femur, tibia, femur_ns = pair
        x, y, z, w = relative_rotation(femur.pose, tibia.pose)
        flexion, varus = self._route.served.decoder.angles(x, y, z, w)
        self._answer(flexion, varus, femur.sec, femur.nanosec, femur_ns, femur.pose)

    def drop(self, reason: str, err: Exception) -> None:
        """Count a dropped input under `reason` and warn (throttled)."""
        self._counters.dropped[reason] += 1
        self._log.warning(f'dropped input ({reason}): {err}',
                          throttle_duration_sec=WARN_THROTTLE_S)

    def _stamped(self, sec: int, nanosec: int) -> int:
        ns = sec * 1_000_000_000 + nanosec
        if ns == 0:
            self._counters.unstamped += 1
        return ns

    def _take_pose(self, data: bytes, index: int
                   ) -> tuple[int, int, str, tuple[float, ...], int] | None:
        """Stamp, frame and pose of the PoseStamped CDR of input `index` (rclpy for other
        encodings) and its stamp in ns; counted as received and recorded. None when it
        cannot be decoded (counted as malformed)."""
        try:
            sec, nanosec, frame, pose = decode_pose_stamped(data)
        except CdrError as err:
            msg = self._deserialize(data, PoseStamped, err)
            if msg is None:
                return None
            p = msg.pose.position
            sec, nanosec, frame = (msg.header.stamp.sec, msg.header.stamp.nanosec,
                                   msg.header.frame_id)
            pose = (p.x, p.y, p.z, *quat_xyzw(msg.pose))
        self._counters.received += 1
        ns = self._stamped(sec, nanosec)
        recorder = self._recorder
        if recorder is not None:
            recorder.write_raw(self._input_topics[index],
                               encode_pose_stamped(sec, nanosec, frame, pose),
                               self._now_ns(), ns)
        return sec, nanosec, frame, pose, ns

    def _deserialize(self, data: bytes, msg_type: type, err: CdrError) -> Any:
        """Bytes our CDR reader refused (another encapsulation), read by rclpy; None (counted
        as received and malformed) when rclpy cannot read them either."""
        try:
            return deserialize_message(data, msg_type)
        except Exception:             # the rmw's own error for undecodable bytes
            self._counters.received += 1
            self.drop('malformed', err)
            return None

    # ---- the answer -------------------------------------------------------------------
    def _answer(self, flexion: float, varus: float, sec: int, nanosec: int, ns: int,
                femur_world: Rigid | None = None) -> None:
        """Look the table up and publish the answer as CDR bytes (see kneeseat_ros.cdr)."""
        route = self._route
        served = route.served
        try:
            lookup = served.table.interpolate(flexion, varus, self._out_of_range)
        except OutOfRangeError as err:
            self.drop('out_of_range', err)
            return
        except NonFiniteError as err:      # non-finite angles are caught before; belt and braces
            self.drop('nonfinite', err)
            return
        positions, orientations = lookup.position_m.tolist(), lookup.orientation_xyzw.tolist()
        poses = [(*p, *q) for p, q in zip(positions, orientations)]
        recorder = self._recorder
        now_ns = self._now_ns() if recorder is not None else 0
        counters = self._counters
        encode = served.writer.encode
        for pub, pose in zip(route.body_pubs, poses):
            data = encode(sec, nanosec, pose)
            pub.publish(data)
            if recorder is not None:
                recorder.write_raw(pub.topic_name, data, now_ns, ns)
        counters.published += len(route.body_pubs)
        transforms: list[tuple[str, str, Sequence[float]]] = []
        if femur_world is not None:
            tracker = self._tracker
            assert tracker is not None
            encode = self._world_writer.encode
            outs: list[tuple[Publisher | None, Rigid]] = [(route.reference_world_pub,
                                                           femur_world)]
            outs += [(pub, compose(femur_world, pose))
                     for pub, pose in zip(route.body_world_pubs, poses)]
            for out, pose in outs:
                assert out is not None        # tracker mode has world publishers
                data = encode(sec, nanosec, pose)
                out.publish(data)
                if recorder is not None:
                    recorder.write_raw(out.topic_name, data, now_ns, ns)
            counters.published += len(outs)
            transforms.append((tracker.world_frame, served.frame, femur_world))
        if self._tf_pub is not None:
            transforms += [(served.frame, child, pose)
                           for child, pose in zip(served.body_frames, poses)]
            data = served.tf.encode(sec, nanosec, transforms)
            self._tf_pub.publish(data)
            if recorder is not None:
                recorder.write_raw(self._tf_pub.topic_name, data, now_ns, ns)
        counters.answered += 1
        counters.window_received += 1
        if lookup.clamped:
            counters.clamped += 1
        if True in lookup.nonconverged.tolist():    # 0.2 us; ndarray.any() 1.3 us
            counters.nonconverged += 1
        self._last = Answer(lookup, sec, nanosec)
        if ns != 0:
            counters.latencies_ns.append(self._now_ns() - ns)
