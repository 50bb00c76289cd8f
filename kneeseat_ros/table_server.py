"""The `table_server` node: answers each tracked knee attitude with every bone's settled pose.

Run it as `ros2 run kneeseat_ros table_server --ros-args -p table:=knee.npz` (ament
layout) or as the `table_server` console script of the project's venv;
`table_server --help` prints the usage below.

Topic names are relative, so they follow the node's namespace (`-r __ns:=/left` gives
`/left/knee/pose`, ...) and remapping; `/diagnostics` and `/tf` are absolute, as every ROS
tool expects them there.

Attitude mode (default):
- in  `knee/pose` (geometry_msgs/PoseStamped: tibia orientation in the reference frame)
- in  `knee/joint_states` (sensor_msgs/JointState: the `flexion_joint` and `varus_joint`
  positions in rad)
Tracker mode (`tracker.registration` set, see kneeseat_ros/tracker.py):
- in  `tracker.femur_topic`, `tracker.tibia_topic` (PoseStamped of the thigh and shank
  marker clusters in `tracker.world_frame`), paired by stamp within
  `tracker.pair_tolerance_s`; the femur's stamp is the answer's stamp
- out `knee/<reference>/world_pose`, `knee/<body>/world_pose` (PoseStamped in the world
  frame: the femur from its cluster and the registration, each body = femur * table)
Both modes:
- out `knee/<body>/pose` per moving body (PoseStamped, frame = reference frame,
  stamp = the input's stamp)
- out `/tf` (tf2_msgs/TFMessage) when `publish_tf`: reference frame -> each body frame
  (tracker mode: also world -> reference frame), the input's stamp, one message per answer
- out `knee/markers` (visualization_msgs/MarkerArray) when `publish_markers` is true:
  published at `marker_rate_hz` with the latest answer, not once per answer, so a 1 kHz
  tracker does not flood RViz/Foxglove; id 0 is the reference body, 1..B the moving ones,
  plus 1000 k for a body's k-th further display mesh (conversions.body_markers).
- out `/diagnostics` every `diagnostics_period_s` (DiagnosticArray, one status
  'kneeseat table_server', hardware_id = the node's full name): counters over the whole
  run, rates and latency percentiles over the last period; the level is WARN while an
  input was dropped within the last `diagnostics_window_s`, then OK again. Latency = node
  clock at publish - input stamp; unstamped inputs (stamp 0) are answered and counted
  (`unstamped`) but left out of the latency.
- service `~/reload` (std_srvs/Trigger): read the `table` parameter's file again; setting
  the `table` parameter loads the new file at once (the set is refused, with the reason,
  if it cannot be served), so the parameter always names the table being served.

QoS: inputs use `qos_profile_sensor_data` (best effort, volatile) with keep last 1000
instead of 5 (5 ms at 1 kHz is shorter than a scheduling hiccup), which matches both
reliable and best-effort publishers; outputs are reliable, keep last 1000 (a reliable
writer overwrites unacknowledged answers beyond its depth: 100 is 50 ms at 2 kHz), and
their policies can be overridden through the standard `qos_overrides.*` parameters. `/tf`
uses tf2_ros's broadcaster QoS (reliable, volatile, keep last 100).

Hot path: inputs are taken as CDR bytes and answers published as CDR bytes
(kneeseat_ros.cdr); no rclpy message object is built per message.

Parameters are read once at start (all but `table` are read-only); bad values stop the
node with one line `table_server: error: ...` on stderr and exit code 2. Mesh paths in
the table metadata that are relative are taken relative to the table file's directory.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
import contextlib
from dataclasses import dataclass
from datetime import datetime, timezone
import gc
import math
import os
from pathlib import Path
import re
import sys
import tempfile
import threading
import time
from typing import Any, Literal, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle, InvalidParameterTypeException
from rclpy.executors import (ExternalShutdownException, ShutdownException,
                             SingleThreadedExecutor)
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import (qos_profile_sensor_data, QoSDurabilityPolicy, QoSHistoryPolicy,
                       QoSProfile, QoSReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from kneeseat_core.errors import (ConfigError, KneeseatError, NonFiniteError, OutOfRangeError,
                                  TableError)
from kneeseat_core.table import Lookup, PoseTable
from kneeseat_core.table_io import read_table
from kneeseat_ros import topics
from kneeseat_ros.cdr import (decode_joint_state, decode_pose_stamped, encode_joint_state,
                              encode_pose_stamped, PoseStampedWriter, TfWriter)
from kneeseat_ros.conversions import (
    angles_from_joints, angles_from_orientation, AttitudeDecoder, body_markers,
    diagnostic_status, display_mesh_paths, DROP_REASONS, JOINT_NAMES, quat_xyzw,
    rigid_from_fields, stamp_from_ns, stamp_ns)
from kneeseat_ros.errors import BadInputError, CdrError
from kneeseat_ros.topics import STATUS_NAME
from kneeseat_ros.tracker import (compose, load_registration, Pairer, Registration,
                                  relative_rotation, Rigid)

if TYPE_CHECKING:
    from kneeseat_ros.recorder import BagRecorder

__all__ = ['INPUT_QOS', 'OUTPUT_QOS', 'TF_QOS', 'STATUS_NAME', 'ServerParams', 'TableServer',
           'load_table', 'main', 'USAGE']

RCLError = _rclpy.RCLError
# Sensor-data QoS (best effort, volatile, keep last) as the demos use, with a deeper queue:
# depth 5 is 5 ms at 1 kHz; 1000 is 0.5 s at 2 kHz, longer than the scheduler stalls seen
# on a loaded 2-core machine (up to ~0.3 s), so a node that keeps up on average drops none.
INPUT_QOS = QoSProfile(history=qos_profile_sensor_data.history, depth=1000,
                       reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability)
# Messages taken per wake-up of one input (see TableServer._drain).
DRAIN_MAX = 100
OUTPUT_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=QoSReliabilityPolicy.RELIABLE,
                        durability=QoSDurabilityPolicy.VOLATILE)
TF_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                    reliability=QoSReliabilityPolicy.RELIABLE,
                    durability=QoSDurabilityPolicy.VOLATILE)
# serve(): the input wait also wakes this often to look at the context (a shutdown whose
# guard-condition trigger lands before the context is down would otherwise be missed).
SHUTDOWN_CHECK_NS = 1_000_000_000
WARN_THROTTLE_S = 2.0
_BODY_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
_BODY_RGBA = ((0.85, 0.8, 0.7, 1.0), (0.7, 0.8, 0.9, 1.0), (0.8, 0.9, 0.7, 1.0))
_REFERENCE_RGBA = (0.95, 0.95, 0.9, 0.6)

USAGE = """\
usage: table_server [-h] --ros-args -p table:=TABLE.npz [-p NAME:=VALUE ...]
                    [--params-file FILE] [-r __ns:=/NAMESPACE] [-r FROM:=TO]
                    [--log-level LEVEL]

Serve a kneeseat pose table to ROS 2: each tracked knee attitude is answered with the
settled pose of every moving body (see README.md, "The ROS 2 node").

topics (relative: they follow the node's namespace and remapping)
  in   knee/pose (geometry_msgs/PoseStamped)   tibia orientation in the reference frame
  in   knee/joint_states (sensor_msgs/JointState)   flexion and varus joints (rad)
  in   tracker.femur_topic, tracker.tibia_topic   tracker mode: rigid bodies in the world
  out  knee/<body>/pose, knee/<body>/world_pose (tracker mode), knee/markers,
       /tf, /diagnostics; service ~/reload (std_srvs/Trigger)

parameters (config/table_server.yaml documents each one)
  table (required), out_of_range clamp|drop, flexion_joint, varus_joint, publish_tf,
  publish_markers, marker_rate_hz, diagnostics_period_s, diagnostics_window_s, record,
  record_split_size_mb, record_split_duration_s, tracker.registration,
  tracker.femur_topic, tracker.tibia_topic, tracker.world_frame, tracker.pair_tolerance_s

examples
  ros2 run kneeseat_ros table_server --ros-args -p table:=knee.npz
  table_server --ros-args --params-file config/table_server.yaml -p table:=knee.npz \\
      -r __ns:=/left
exit codes: 0 stopped by SIGINT/SIGTERM, 2 bad parameters, table or arguments"""


@dataclass(frozen=True, slots=True)
class ServerParams:
    """The node's parameters after validation (SI units)."""

    table: Path
    out_of_range: Literal['clamp', 'drop']
    flexion_joint: str
    varus_joint: str
    record: str
    record_split_size_mb: float
    record_split_duration_s: float
    publish_tf: bool
    publish_markers: bool
    marker_rate_hz: float
    diagnostics_period_s: float
    diagnostics_window_s: float
    tracker_registration: str
    tracker_femur_topic: str
    tracker_tibia_topic: str
    tracker_world_frame: str
    tracker_pair_tolerance_s: float


_S, _D, _B = (ParameterType.PARAMETER_STRING, ParameterType.PARAMETER_DOUBLE,
              ParameterType.PARAMETER_BOOL)
_PARAMETERS: tuple[tuple[str, Any, int, str, bool], ...] = (
    ('table', '', _S, 'Table file (.npz) written by `kneeseat build`; setting it loads the '
     'file (refused if it cannot be served); ~/reload re-reads it.', False),
    ('out_of_range', 'clamp', _S,
     "Attitudes outside the grid: 'clamp' (nearest edge, counted) or 'drop'.", True),
    ('flexion_joint', JOINT_NAMES[0], _S, 'JointState name of the flexion joint (rad).', True),
    ('varus_joint', JOINT_NAMES[1], _S, 'JointState name of the varus joint (rad).', True),
    ('record', '', _S,
     'Directory for session bags (<record>/kneeseat_<YYYYmmdd_HHMMSS>/); empty = off.', True),
    ('record_split_size_mb', 0.0, _D,
     'New .mcap file after this many MiB; 0 = no size split.', True),
    ('record_split_duration_s', 0.0, _D,
     'New .mcap file after this many seconds; 0 = no duration split.', True),
    ('publish_tf', True, _B, 'Broadcast every answer on /tf (off, with one info line, when '
     'tf2_msgs is not installed).', True),
    ('publish_markers', False, _B,
     'Publish knee/markers (mesh markers of every body) for RViz and Foxglove.', True),
    ('marker_rate_hz', 30.0, _D,
     'Rate of knee/markers (Hz, > 0), each with the latest answer.', True),
    ('diagnostics_period_s', 1.0, _D, 'Period of /diagnostics (s, > 0).', True),
    ('diagnostics_window_s', 10.0, _D, 'Diagnostics stay WARN this long after a dropped '
     'input (s, >= diagnostics_period_s).', True),
    ('tracker.registration', '', _S, 'Tracker mode: registration YAML (marker cluster -> '
     'bone for femur and tibia); empty = attitude mode (knee/pose, knee/joint_states).', True),
    ('tracker.femur_topic', topics.TRACKER_FEMUR, _S,
     'Tracker mode: PoseStamped of the thigh marker cluster in the world frame.', True),
    ('tracker.tibia_topic', topics.TRACKER_TIBIA, _S,
     'Tracker mode: PoseStamped of the shank marker cluster in the world frame.', True),
    ('tracker.world_frame', 'world', _S, "Tracker mode: the tracker's frame (frame_id of "
     'its inputs and of the world_pose outputs).', True),
    ('tracker.pair_tolerance_s', 0.002, _D, 'Tracker mode: largest stamp difference of a '
     'femur/tibia pair (s, > 0).', True),
)
_TYPE_NAMES = {_S: 'a string', _D: 'a double (write 1.0, not 1)', _B: 'a bool (true/false)'}


def load_table(path: Path) -> PoseTable:
    """Read and verify a table for serving: file checks plus ROS-usable names.

    Raises:
        TableError: the file is missing or corrupt (see `read_table`), or a body name
            cannot be used in a topic name.
    """
    table = read_table(path)
    for body in (table.metadata['reference']['name'], *table.bodies):
        if not _BODY_NAME.match(str(body)):
            raise TableError(f'{path}: body name {body!r} cannot be used in the topic '
                             'knee/<body>/pose; rebuild the table with names made of '
                             'letters, digits and underscores')
    if not table.reference_frame:
        raise TableError(f'{path}: the table has an empty reference frame; rebuild it with '
                         'reference.frame set in the knee config')
    table.axes    # validates the axes (ConfigError) before the first message
    return table


@dataclass(frozen=True, slots=True, eq=False)
class _Served:
    """A loaded table and everything derived from it that the hot path needs."""

    table: PoseTable
    path: Path
    frame: str
    reference: str
    decoder: AttitudeDecoder
    bodies: tuple[str, ...]
    body_frames: tuple[str, ...]
    meshes: tuple[tuple[str, ...], ...]     # display mesh files: reference, then bodies
    bounds_deg: tuple[float, float, float, float]
    writer: PoseStampedWriter          # answers in the reference frame, as CDR bytes
    tf: TfWriter                       # reference -> bodies (and world -> reference)

    @classmethod
    def load(cls, path: Path, world_frame: str | None = None) -> _Served:
        table = load_table(path)
        flexion, varus = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
        meta = table.metadata
        meshes = tuple(display_mesh_paths(e, path.parent)
                       for e in [meta['reference'], *meta['bodies']])
        frame = table.reference_frame
        pairs = [(frame, child) for child in table.body_frames]
        if world_frame is not None:
            pairs.append((world_frame, frame))
        return cls(table, path, frame, str(meta['reference']['name']),
                   AttitudeDecoder(table.axes), table.bodies, table.body_frames, meshes,
                   (float(flexion[0]), float(flexion[-1]), float(varus[0]), float(varus[-1])),
                   PoseStampedWriter(frame), TfWriter(pairs))


@dataclass(frozen=True, slots=True, eq=False)
class _Route:
    """The served table with its output publishers, swapped as one by a reload."""

    served: _Served
    body_pubs: tuple[Publisher, ...]
    body_world_pubs: tuple[Publisher, ...]     # tracker mode only
    reference_world_pub: Publisher | None      # tracker mode only


class _InputsGroup(CallbackGroup):
    """The inputs' callback group: kept out of rclpy's executor while `serve()` runs.

    serve() waits on the inputs itself in the main thread and leaves every other entity
    (timers, services, parameter services) to an executor in a second thread; a node added
    to another executor (tests, composition) gets its inputs from it. The inputs' QoS event
    handlers stay out too: with rmw_fastrtps a subscription's event wakes the wait on every
    message of that subscription (the executor thread then spun at 60% of a core at 2 kHz);
    the inputs accept every publisher QoS by default, so these events practically never fire.
    """

    def __init__(self) -> None:
        super().__init__()
        self.direct = False

    def can_execute(self, entity: Any) -> bool:
        return not self.direct

    def beginning_execution(self, entity: Any) -> bool:
        return self.can_execute(entity)

    def ending_execution(self, entity: Any) -> None:
        pass


class TableServer(Node):
    """Serves a pose table: tracked attitude in, settled pose of every moving body out."""

    def __init__(self, **kwargs: Any) -> None:
        """Declare and validate parameters, load the table, create the ROS interfaces.

        Args:
            **kwargs: forwarded to `rclpy.node.Node` (context=, parameter_overrides=,
                namespace=, ...).
        Raises:
            ConfigError: a parameter or the registration file is invalid.
            TableError: the table is missing or corrupt.
            RecorderError: the session recorder cannot start.
        """
        super().__init__('table_server', **kwargs)
        self._log = self.get_logger()
        self._clock = self.get_clock()
        # the node clock in ns for the hot path: with use_sim_time off (read at start) ROS
        # time is the system clock, and time.time_ns is ~10x cheaper than Clock.now()
        self._now_ns: Callable[[], int] = (
            (lambda: self._clock.now().nanoseconds)
            if self.get_parameter('use_sim_time').value else time.time_ns)
        self.params = self._read_parameters()
        self._registration: Registration | None = None
        if self.params.tracker_registration:
            self._registration = load_registration(
                Path(self.params.tracker_registration).expanduser())
        self._world = (self.params.tracker_world_frame if self._registration is not None
                       else None)
        self._world_writer = PoseStampedWriter(self.params.tracker_world_frame)
        served = _Served.load(self.params.table, self._world)
        self._out_of_range = self.params.out_of_range
        self._joint_names = (self.params.flexion_joint, self.params.varus_joint)
        self._received = 0
        self._answered = 0
        self._published = 0
        self._clamped = 0
        self._nonconverged = 0
        self._unstamped = 0
        self._dropped = dict.fromkeys(DROP_REASONS, 0)
        self._drop_history: deque[tuple[int, int]] = deque()   # (node ns, total dropped)
        self._window_received = 0
        self._window_start_ns = self._clock.now().nanoseconds
        self._latencies_ns: list[int] = []
        self._last: tuple[Lookup, int, int] | None = None
        self._recorder: BagRecorder | None = None
        self._recorder_error_logged = False
        self._pairer: Pairer[Rigid] | None = None

        self._pubs: dict[str, Publisher] = {}
        self._world_pubs: dict[str, Publisher] = {}
        self._route = self._make_route(served)
        self._inputs_group = _InputsGroup()
        self._diag_pub = self.create_publisher(
            DiagnosticArray, topics.DIAGNOSTICS, OUTPUT_QOS,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self._tf_pub, self._tf_type = self._make_tf_publisher()
        self._marker_pub = None
        if self.params.publish_markers:
            self._marker_pub = self.create_publisher(
                MarkerArray, topics.MARKERS, OUTPUT_QOS,
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            self.create_timer(1.0 / self.params.marker_rate_hz, self._publish_markers)
            self._check_meshes()
        self._inputs: list[tuple[Any, Callable[[Any], None], str]] = []
        if self._registration is None:
            self._inputs += [
                (self.create_subscription(PoseStamped, topics.POSE, self._on_pose, INPUT_QOS,
                                          raw=True, callback_group=self._inputs_group),
                 self._handle_pose, 'geometry_msgs/msg/PoseStamped'),
                (self.create_subscription(JointState, topics.JOINT_STATES, self._on_joints,
                                          INPUT_QOS, raw=True,
                                          callback_group=self._inputs_group),
                 self._handle_joints, 'sensor_msgs/msg/JointState')]
        else:
            self._pairer = Pairer(int(round(self.params.tracker_pair_tolerance_s * 1e9)))
            for side, topic in enumerate((self.params.tracker_femur_topic,
                                          self.params.tracker_tibia_topic)):
                def handle(data: bytes, side: int = side) -> None:
                    self._handle_rigid(side, data)
                sub = self.create_subscription(PoseStamped, topic,
                                               lambda m, h=handle: self._on_input(m, h),
                                               INPUT_QOS, raw=True,
                                               callback_group=self._inputs_group)
                self._inputs.append((sub, handle, 'geometry_msgs/msg/PoseStamped'))
        self._reload_srv = self.create_service(Trigger, '~/reload', self._on_reload)
        self.create_timer(self.params.diagnostics_period_s, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if self.params.record:
            self._start_recorder()
        s = self._served
        mode = ('attitude' if self._registration is None else
                f'tracker (registration {self._registration.path}, world frame '
                f'{self.params.tracker_world_frame!r})')
        self._log.info(
            f'serving {s.path} (sha256 {s.table.sha256[:12]}) bodies {list(s.bodies)} in '
            f'{s.frame!r}, flexion [{s.bounds_deg[0]:.1f}, {s.bounds_deg[1]:.1f}] deg, varus '
            f'[{s.bounds_deg[2]:.1f}, {s.bounds_deg[3]:.1f}] deg, out_of_range='
            f'{self._out_of_range}; {mode}; in {[i[0].topic_name for i in self._inputs]} '
            f'(sensor data QoS: best effort, depth {INPUT_QOS.depth}); out '
            f'{[p.topic_name for p in self._route.body_pubs + self._route.body_world_pubs]} '
            f'(reliable, depth {OUTPUT_QOS.depth}), tf '
            f'{"on" if self._tf_pub is not None else "off"}; recording '
            f'{self._recorder.directory if self._recorder is not None else "off"}')

    # ------------------------------------------------------------------ setup
    def _read_parameters(self) -> ServerParams:
        values: dict[str, Any] = {}
        for name, default, ptype, text, read_only in _PARAMETERS:
            descriptor = ParameterDescriptor(name=name, type=ptype, description=text,
                                             read_only=read_only)
            try:
                values[name] = self.declare_parameter(name, default, descriptor).value
            except InvalidParameterTypeException:
                raise ConfigError(f'parameter {name!r} must be {_TYPE_NAMES[ptype]}; fix it in '
                                  'the params file or the -p option') from None
        if not values['table']:
            raise ConfigError("parameter 'table' is empty; pass --ros-args -p "
                              'table:=/path/to/table.npz (a file written by kneeseat build); '
                              'table_server --help shows the usage')
        if values['out_of_range'] not in ('clamp', 'drop'):
            raise ConfigError(f"parameter 'out_of_range' is {values['out_of_range']!r}; use "
                              "'clamp' or 'drop'")
        for name in ('record_split_size_mb', 'record_split_duration_s'):
            if not (math.isfinite(values[name]) and values[name] >= 0.0):
                raise ConfigError(f'parameter {name!r} is {values[name]}; use a value >= 0 '
                                  '(0 = no split)')
        for name in ('marker_rate_hz', 'diagnostics_period_s', 'diagnostics_window_s',
                     'tracker.pair_tolerance_s'):
            if not (math.isfinite(values[name]) and values[name] > 0.0):
                raise ConfigError(f'parameter {name!r} is {values[name]}; use a value > 0')
        for name in ('flexion_joint', 'varus_joint', 'tracker.femur_topic',
                     'tracker.tibia_topic', 'tracker.world_frame'):
            if not values[name]:
                raise ConfigError(f'parameter {name!r} is empty; give a name (the default '
                                  'is in config/table_server.yaml)')
        if values['flexion_joint'] == values['varus_joint']:
            raise ConfigError(f"parameters 'flexion_joint' and 'varus_joint' are both "
                              f"{values['flexion_joint']!r}; give two different joint names")
        values['table'] = Path(values['table']).expanduser().absolute()
        return ServerParams(**{k.replace('.', '_'): v for k, v in values.items()})

    @property
    def _served(self) -> _Served:
        return self._route.served

    def _make_route(self, served: _Served) -> _Route:
        """Publishers for `served` (created once per topic), bundled with it."""
        for body in served.bodies:
            if body not in self._pubs:
                self._pubs[body] = self._pose_publisher(topics.body_pose(body))
        world: tuple[Publisher, ...] = ()
        reference = None
        if self._registration is not None:
            for body in (served.reference, *served.bodies):
                if body not in self._world_pubs:
                    self._world_pubs[body] = self._pose_publisher(topics.body_world_pose(body))
            reference = self._world_pubs[served.reference]
            world = tuple(self._world_pubs[b] for b in served.bodies)
        return _Route(served, tuple(self._pubs[b] for b in served.bodies), world, reference)

    def _pose_publisher(self, topic: str) -> Publisher:
        pub = self.create_publisher(
            PoseStamped, topic, OUTPUT_QOS,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        if self._recorder is not None:
            self._recorder.add_topic(pub.topic_name, 'geometry_msgs/msg/PoseStamped',
                                     OUTPUT_QOS)
        return pub

    def _make_tf_publisher(self) -> tuple[Publisher | None, Any]:
        if not self.params.publish_tf:
            return None, None
        try:
            from tf2_msgs.msg import TFMessage
            return self.create_publisher(TFMessage, topics.TF, TF_QOS), TFMessage
        except Exception as err:     # ImportError, or its typesupport library not loadable
            self._log.info(f'publish_tf: /tf is off: tf2_msgs is not usable here ({err}); '
                           'build it as the README says (no pip wheel exists) or set '
                           'publish_tf:=false to silence this line')
            return None, None

    def _check_meshes(self) -> None:
        for path in (p for paths in self._served.meshes for p in paths or [None]):
            if path is None or not Path(path).is_file():
                self._log.warning(f'display mesh {path} not found; its marker will not draw '
                                  '(set display_mesh in the knee config and rebuild)')

    def _recorded_topics(self) -> list[tuple[str, str, QoSProfile]]:
        topics = [(sub.topic_name, msg_type, INPUT_QOS) for sub, _, msg_type in self._inputs]
        for pub in (*self._pubs.values(), *self._world_pubs.values()):
            topics.append((pub.topic_name, 'geometry_msgs/msg/PoseStamped', OUTPUT_QOS))
        topics.append((self._diag_pub.topic_name, 'diagnostic_msgs/msg/DiagnosticArray',
                       OUTPUT_QOS))
        if self._tf_pub is not None:
            topics.append((self._tf_pub.topic_name, 'tf2_msgs/msg/TFMessage', TF_QOS))
        if self._marker_pub is not None:
            topics.append((self._marker_pub.topic_name, 'visualization_msgs/msg/MarkerArray',
                           OUTPUT_QOS))
        return topics

    def _start_recorder(self) -> None:
        try:
            from kneeseat_ros.recorder import BagRecorder, RecorderError, topic_spec
        except ImportError as err:
            raise ConfigError(f"parameter 'record' is set but the recorder is unavailable "
                              f"({err}); set record:='' or install kneeseat_ros fully") from None
        # every topic's definition first: a failure leaves no directory behind
        try:
            specs = [topic_spec(*t) for t in self._recorded_topics()]
        except RecorderError as err:
            raise ConfigError(f"parameter 'record': {err}") from None
        now = datetime.fromtimestamp(self._clock.now().nanoseconds / 1e9, tz=timezone.utc)
        base = Path(self.params.record).expanduser().absolute()
        directory = base / f'kneeseat_{now:%Y%m%d_%H%M%S}'
        n = 1
        while directory.exists():
            directory, n = base / f'kneeseat_{now:%Y%m%d_%H%M%S}_{n}', n + 1
        recorder = BagRecorder(
            directory, split_size_bytes=int(self.params.record_split_size_mb * 1024 * 1024),
            split_duration_s=self.params.record_split_duration_s,
            table_sha256=self._served.table.sha256, table_path=str(self._served.path))
        for spec in specs:
            recorder.add_spec(spec)
        self._recorder = recorder

    # -------------------------------------------------------------- hot path
    def _on_pose(self, msg: PoseStamped) -> None:
        self._on_input(msg, self._handle_pose)

    def _on_joints(self, msg: JointState) -> None:
        self._on_input(msg, self._handle_joints)

    def _on_input(self, msg: Any, handle: Callable[[Any], None]) -> None:
        """Executor callback of an input: handle it, then what else is queued behind it."""
        handle(msg)
        for sub, h, _ in self._inputs:
            if h is handle:
                self._drain(sub, handle)

    def _drain(self, sub: Any, handle: Callable[[Any], None]) -> None:
        """Handle what else is queued on `sub` now, in order, without the executor.

        One pass of rclpy's Python executor (wait set rebuilt over every entity) costs
        several times the answer itself; after a scheduling hiccup the backlog is cleared
        at the cost of the answers alone. Uses the same `take_message` call as
        `rclpy.executors.Executor._take_subscription` (Jazzy).
        """
        for _ in range(DRAIN_MAX):
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            handle(taken[0])

    def serve(self) -> None:
        """Spin until shutdown: the inputs in this thread, everything else in a second one.

        This thread waits on a wait set holding only the inputs and one guard condition
        (stop) and drains every ready input: per message it pays one rcl_wait over 3
        entities. rcl_wait's cost grows with the entities in the set (each
        is attached to and detached from the wait), and a node's timers, parameter
        services and ~/reload are 12 more; rclpy's executor also rebuilds its wait set in
        Python on every call. So timers, services and parameters run in rclpy's executor in
        a second thread, which sleeps until one of them is ready (the inputs' callback
        group keeps them out of it). An idle node sleeps in both. The wait also times out
        every `SHUTDOWN_CHECK_NS` to look at the context, as a safety net for shutdown.
        Uses rclpy's WaitSet and take_message as rclpy.executors does (Jazzy).
        """
        executor = SingleThreadedExecutor(context=self.context)
        self._inputs_group.direct = True
        executor.add_node(self)
        failed: list[BaseException] = []

        def housekeeping() -> None:
            try:
                executor.spin()
            except (ExternalShutdownException, ShutdownException):
                pass
            except RCLError:
                if self.context.ok():
                    raise
            except BaseException as err:        # re-raised in the main thread
                failed.append(err)
                self.context.try_shutdown()
            finally:                            # wake the main thread: it stops too
                wake()

        # woken by the executor thread's end (SIGINT/SIGTERM reach it through rclpy's own
        # signal guard condition) and by a shutdown of the context from Python
        stop = GuardCondition(None, None, context=self.context)

        def wake() -> None:
            with contextlib.suppress(InvalidHandle):
                stop.trigger()

        self.context.on_shutdown(wake)
        subs = [sub for sub, _, _ in self._inputs]
        handlers = [handle for _, handle, _ in self._inputs]
        guards = [stop]
        wait_set = _rclpy.WaitSet(len(subs), len(guards), 0, 0, 0, 0, self.context.handle)
        thread = threading.Thread(target=housekeeping, name='table_server housekeeping',
                                  daemon=True)
        # everything alive now lives as long as the node: keep it out of the cyclic
        # collector's full passes, whose pauses grow with the heap (tables, imports)
        gc.collect()
        gc.freeze()
        thread.start()
        try:
            with contextlib.ExitStack() as held:
                for entity in (*subs, *guards):
                    held.enter_context(entity.handle)
                held.enter_context(self.context.handle)
                pairs = [(sub, sub.handle, handle) for sub, handle in zip(subs, handlers)]
                while self.context.ok():
                    wait_set.clear_entities()
                    for _, sub_handle, _ in pairs:
                        wait_set.add_subscription(sub_handle)
                    for guard in guards:
                        wait_set.add_guard_condition(guard.handle)
                    wait_set.wait(SHUTDOWN_CHECK_NS)
                    ready = wait_set.get_ready_entities('subscription')
                    for sub, sub_handle, handle in pairs:
                        if sub_handle.pointer in ready:
                            self._drain(sub, handle)
        finally:
            # After a signal the executor thread ends by itself (its context is down) and
            # nothing is destroyed here: rclpy's signal thread may still be triggering the
            # executor's signal guard condition, and executor.shutdown() would destroy it
            # under that thread (a segfault in rmw's trigger, seen once under load). Only a
            # stop with the context still up (an error here) shuts the executor down.
            if self.context.ok():
                executor.shutdown(timeout_sec=5.0)
            thread.join(timeout=10.0)
            if thread.is_alive():
                executor.shutdown(timeout_sec=5.0)
                thread.join(timeout=10.0)
            self._inputs_group.direct = False
            executor.remove_node(self)
        if failed:
            raise failed[0]

    def _stamped(self, sec: int, nanosec: int) -> int:
        ns = sec * 1_000_000_000 + nanosec
        if ns == 0:
            self._unstamped += 1
        return ns

    def _pose_fields(self, data: bytes) -> tuple[int, int, str, tuple[float, ...]] | None:
        """Stamp, frame and pose of a PoseStamped's CDR (rclpy for other encodings)."""
        try:
            return decode_pose_stamped(data)
        except CdrError as err:
            try:
                msg = deserialize_message(data, PoseStamped)
            except Exception:             # the rmw's own error for undecodable bytes
                self._received += 1
                self._drop('malformed', err)
                return None
            p = msg.pose.position
            return (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id,
                    (p.x, p.y, p.z, *quat_xyzw(msg.pose)))

    def _handle_pose(self, data: bytes) -> None:
        fields = self._pose_fields(data)
        if fields is None:
            return
        sec, nanosec, frame, pose = fields
        self._received += 1
        ns = self._stamped(sec, nanosec)
        if self._recorder is not None:
            self._recorder.write_raw(self._inputs[0][0].topic_name,
                                     encode_pose_stamped(sec, nanosec, frame, pose),
                                     self._now_ns(), ns)
        try:
            flexion, varus = angles_from_orientation(frame, pose[3:], self._served.decoder,
                                                     self._served.frame)
        except BadInputError as err:
            self._drop(err.reason, err)
            return
        self._answer(flexion, varus, sec, nanosec, ns)

    def _handle_joints(self, data: bytes) -> None:
        try:
            sec, nanosec, frame, names, position, velocity, effort = decode_joint_state(data)
        except CdrError as err:
            try:
                msg = deserialize_message(data, JointState)
            except Exception:             # the rmw's own error for undecodable bytes
                self._received += 1
                self._drop('malformed', err)
                return
            sec, nanosec, frame = (msg.header.stamp.sec, msg.header.stamp.nanosec,
                                   msg.header.frame_id)
            names, position = list(msg.name), tuple(msg.position)
            velocity, effort = tuple(msg.velocity), tuple(msg.effort)
        self._received += 1
        ns = self._stamped(sec, nanosec)
        if self._recorder is not None:
            self._recorder.write_raw(
                self._inputs[1][0].topic_name,
                encode_joint_state(sec, nanosec, frame, names, position, velocity, effort),
                self._now_ns(), ns)
        try:
            flexion, varus = angles_from_joints(names, position, len(velocity), len(effort),
                                                self._joint_names)
        except BadInputError as err:
            self._drop(err.reason, err)
            return
        self._answer(flexion, varus, sec, nanosec, ns)

    def _handle_rigid(self, side: int, data: bytes) -> None:
        """Tracker mode: one rigid body's world pose; answers when it completes a pair."""
        fields = self._pose_fields(data)
        if fields is None:
            return
        sec, nanosec, frame, pose = fields
        self._received += 1
        ns = self._stamped(sec, nanosec)
        if self._recorder is not None:
            self._recorder.write_raw(self._inputs[side][0].topic_name,
                                     encode_pose_stamped(sec, nanosec, frame, pose),
                                     self._now_ns(), ns)
        reg = self._registration
        assert reg is not None and self._pairer is not None
        try:
            cluster = rigid_from_fields(frame, pose, self.params.tracker_world_frame,
                                        ('femur', 'tibia')[side] + ' rigid body')
        except BadInputError as err:
            self._drop(err.reason, err)
            return
        bone = compose(cluster, reg.femur if side == 0 else reg.tibia)
        before = self._pairer.unpaired, self._pairer.stale
        pair = self._pairer.add(side, ns, (bone, sec, nanosec))
        if self._pairer.unpaired != before[0] or self._pairer.stale != before[1]:
            self._log.warning(f'tracker inputs dropped: {self._pairer.unpaired} unpaired, '
                              f'{self._pairer.stale} stale so far (pair tolerance '
                              f'{self.params.tracker_pair_tolerance_s} s)',
                              throttle_duration_sec=WARN_THROTTLE_S)
        if pair is None:
            return
        (femur, f_sec, f_nanosec), (tibia, _, _), femur_ns = pair
        x, y, z, w = relative_rotation(femur, tibia)
        flexion, varus = self._served.decoder.angles(x, y, z, w)
        self._answer(flexion, varus, f_sec, f_nanosec, femur_ns, femur)

    def _answer(self, flexion: float, varus: float, sec: int, nanosec: int, ns: int,
                femur_world: Rigid | None = None) -> None:
        """Look the table up and publish the answer as CDR bytes (see kneeseat_ros.cdr)."""
        route = self._route
        served = route.served
        try:
            lookup = served.table.interpolate(flexion, varus, self._out_of_range)
        except OutOfRangeError as err:
            self._drop('out_of_range', err)
            return
        except NonFiniteError as err:      # non-finite angles are caught before; belt and braces
            self._drop('nonfinite', err)
            return
        positions, orientations = lookup.position_m.tolist(), lookup.orientation_xyzw.tolist()
        poses = [(*p, *q) for p, q in zip(positions, orientations)]
        recorder = self._recorder
        now_ns = self._now_ns() if recorder is not None else 0
        encode = served.writer.encode
        for pub, pose in zip(route.body_pubs, poses):
            data = encode(sec, nanosec, pose)
            pub.publish(data)
            if recorder is not None:
                recorder.write_raw(pub.topic_name, data, now_ns, ns)
        self._published += len(route.body_pubs)
        transforms = []
        if femur_world is not None:
            world, encode = self.params.tracker_world_frame, self._world_writer.encode
            outs = [(route.reference_world_pub, femur_world)]
            outs += [(pub, compose(femur_world, pose))
                     for pub, pose in zip(route.body_world_pubs, poses)]
            for pub, pose in outs:
                data = encode(sec, nanosec, pose)
                pub.publish(data)
                if recorder is not None:
                    recorder.write_raw(pub.topic_name, data, now_ns, ns)
            self._published += len(outs)
            transforms.append((world, served.frame, femur_world))
        if self._tf_pub is not None:
            transforms += [(served.frame, child, pose)
                           for child, pose in zip(served.body_frames, poses)]
            data = served.tf.encode(sec, nanosec, transforms)
            self._tf_pub.publish(data)
            if recorder is not None:
                recorder.write_raw(self._tf_pub.topic_name, data, now_ns, ns)
        self._answered += 1
        self._window_received += 1
        if lookup.clamped:
            self._clamped += 1
        if lookup.nonconverged.any():
            self._nonconverged += 1
        self._last = (lookup, sec, nanosec)
        if ns != 0:
            self._latencies_ns.append(self._now_ns() - ns)

    def _drop(self, reason: str, err: Exception) -> None:
        self._dropped[reason] += 1
        self._log.warning(f'dropped input ({reason}): {err}',
                          throttle_duration_sec=WARN_THROTTLE_S)

    def _record(self, topic: str, msg: Any, publish_time_ns: int) -> None:
        """Record a message object (the slow callbacks: markers, diagnostics)."""
        self._recorder.write(topic, msg, self._clock.now().nanoseconds, publish_time_ns)

    # ------------------------------------------------------- slow callbacks
    def _publish_markers(self) -> None:
        served, last = self._served, self._last
        stamp = (stamp_from_ns(last[1] * 1_000_000_000 + last[2]) if last is not None
                 else self._clock.now().to_msg())
        markers = MarkerArray()
        markers.markers.extend(body_markers(0, served.meshes[0], served.frame, stamp,
                                            rgba=_REFERENCE_RGBA))
        if last is not None:
            lookup = last[0]
            for i, meshes in enumerate(served.meshes[1:]):
                markers.markers.extend(body_markers(
                    i + 1, meshes, served.frame, stamp, lookup.position_m[i],
                    lookup.orientation_xyzw[i], rgba=_BODY_RGBA[i % len(_BODY_RGBA)]))
        assert self._marker_pub is not None
        self._marker_pub.publish(markers)
        if self._recorder is not None:
            self._record(self._marker_pub.topic_name, markers, stamp_ns(stamp))

    def _dropped_counts(self) -> dict[str, int]:
        counts = dict(self._dropped)
        if self._pairer is not None:
            counts['unpaired'] += self._pairer.unpaired
            counts['stale'] += self._pairer.stale
        return counts

    def diagnostics(self) -> DiagnosticArray:
        """The current DiagnosticArray; starts a new rate/latency window."""
        now = self._clock.now()
        now_ns = now.nanoseconds
        window_s = max((now_ns - self._window_start_ns) * 1e-9, 1e-9)
        rate_hz = self._window_received / window_s
        lat = np.asarray(self._latencies_ns, dtype=np.float64) * 1e-6
        p50, p99, worst = ((float(np.percentile(lat, 50)), float(np.percentile(lat, 99)),
                            float(lat.max())) if lat.size else (math.nan,) * 3)
        self._window_received, self._window_start_ns, self._latencies_ns = 0, now_ns, []
        served = self._served
        recorder = self._recorder_status()
        counts = self._dropped_counts()
        dropped = sum(counts.values())
        # dropped within the sliding window: total now - total at the window's start
        history = self._drop_history
        horizon = now_ns - int(self.params.diagnostics_window_s * 1e9)
        history.append((now_ns, dropped))
        while len(history) > 1 and history[1][0] <= horizon:
            history.popleft()
        recent = dropped - (history[0][1] if history[0][0] <= horizon else 0)
        level, message = DiagnosticStatus.OK, 'serving'
        if recent:
            level = DiagnosticStatus.WARN
            message = (f'{recent} inputs dropped in the last '
                       f'{self.params.diagnostics_window_s:g} s')
        if self._recorder is not None and self._recorder.error:
            level, message = DiagnosticStatus.ERROR, 'recording failed; still serving'
        values: list[tuple[str, object]] = [
            ('table', str(served.path)),
            ('table_sha256', served.table.sha256),
            ('reference_frame', served.frame),
            ('bodies', ' '.join(served.bodies)),
            ('flexion_range_deg', f'{served.bounds_deg[0]:.3f} {served.bounds_deg[1]:.3f}'),
            ('varus_range_deg', f'{served.bounds_deg[2]:.3f} {served.bounds_deg[3]:.3f}'),
            ('out_of_range', self._out_of_range),
            ('mode', 'attitude' if self._registration is None else 'tracker'),
            ('tf', 'on' if self._tf_pub is not None else 'off'),
            ('received', self._received),
            ('answered', self._answered),
            ('published', self._published),
            ('dropped', dropped),
            ('dropped_recent', recent),
            *((f'dropped_{reason}', n) for reason, n in counts.items()),
            ('clamped', self._clamped),
            ('nonconverged_answers', self._nonconverged),
            ('unstamped', self._unstamped),
            ('rate_hz', rate_hz),
            ('latency_p50_ms', p50),
            ('latency_p99_ms', p99),
            ('latency_max_ms', worst),
            ('recorder', recorder),
        ]
        array = DiagnosticArray()
        array.header.stamp = now.to_msg()
        array.status.append(diagnostic_status(STATUS_NAME, level, message,
                                              self.get_fully_qualified_name(), values))
        return array

    def _recorder_status(self) -> str:
        rec = self._recorder
        if rec is None:
            return 'off'
        if rec.error:
            if not self._recorder_error_logged:
                self._recorder_error_logged = True
                self._log.error(f'recording to {rec.directory} stopped: {rec.error}; '
                                'still serving poses')
            return f'error: {rec.error}'
        return f'recording {rec.directory} ({rec.message_count} messages)'

    def _publish_diagnostics(self) -> None:
        array = self.diagnostics()
        self._diag_pub.publish(array)
        if self._recorder is not None:
            self._record(self._diag_pub.topic_name, array, stamp_ns(array.header.stamp))

    def _load(self, path: Path) -> str:
        """Serve the table at `path`; the old one stays on failure (KneeseatError)."""
        old = self._served
        served = _Served.load(path, self._world)
        self._route = self._make_route(served)
        if self._marker_pub is not None:
            self._check_meshes()
        self._last = None
        return (f'serving {path} (sha256 {served.table.sha256[:12]}), was '
                f'{old.path} (sha256 {old.table.sha256[:12]})')

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            if param.name != 'table':
                continue
            path = Path(str(param.value)).expanduser().absolute()
            try:
                message = self._load(path)
            except KneeseatError as err:
                reason = f'table not changed, still serving {self._served.path}: {err}'
                self._log.error(reason)
                return SetParametersResult(successful=False, reason=reason)
            self._log.info(message)
        return SetParametersResult(successful=True)

    def _on_reload(self, request: Trigger.Request,
                   response: Trigger.Response) -> Trigger.Response:
        path = self._served.path
        try:
            response.message = self._load(path)
        except KneeseatError as err:
            response.success = False
            response.message = f'reload failed, still serving {path} as loaded before: {err}'
            self._log.error(response.message)
            return response
        response.success = True
        self._log.info(response.message)
        return response

    def destroy_node(self) -> None:
        """Finalise the session bag (if recording), then destroy the node."""
        if self._recorder is not None:
            self._recorder.close()
            if self._recorder.error:
                self._log.error(f'recording to {self._recorder.directory} failed: '
                                f'{self._recorder.error}')
        super().destroy_node()


@contextlib.contextmanager
def _stderr_kept_on_success() -> Iterator[None]:
    """Hold what C code writes on stderr (fd 2) in the block; drop it if the block raises.

    rcl logs its own "[ERROR] [rcl]: Failed to parse global arguments" before rclpy.init
    raises on bad --ros-args; main() replaces both with one line.
    """
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        failed = True
        try:
            yield
            failed = False
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if not failed:
                held.seek(0)
                sys.stderr.buffer.write(held.read())
                sys.stderr.flush()


def _wants_help(args: list[str]) -> bool:
    return any(a in ('-h', '--help') for a in args)


def main(args: list[str] | None = None) -> int:
    """Console entry point (`table_server`, `ros2 run kneeseat_ros table_server`).

    Returns:
        0 on a clean stop (SIGINT, SIGTERM, shutdown) or after --help, 2 on bad
        parameters, table or command-line arguments.
    """
    argv = list(sys.argv if args is None else args)
    if _wants_help(argv[1:]):
        print(USAGE)
        return 0
    try:
        with _stderr_kept_on_success():
            rclpy.init(args=argv)
    except (RCLError, RuntimeError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f'table_server: error: bad command-line arguments ({first}); see '
              'table_server --help', file=sys.stderr)
        return 2
    node = None
    try:
        node = TableServer()
        node.serve()
    except KneeseatError as err:
        print(f'table_server: error: {err}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # rclpy's SIGINT/SIGTERM handler shuts the context down; if that lands between two
        # executor iterations, spin raises RCLError ('context is not valid') instead of
        # ExternalShutdownException. That is a clean stop too; anything else is a bug.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
