"""The `table_server` node: answers each tracked knee attitude with every bone's settled pose.

Run it as `ros2 run kneeseat_ros table_server --ros-args -p table:=knee.npz` (ament
layout) or as the `table_server` console script of the project's venv.

Topics (DESIGN.md "ROS 2 node"; rename them by remapping, never by parameter):
- in  `/knee/pose` (geometry_msgs/PoseStamped: tibia orientation in the reference frame)
- in  `/knee/joint_states` (sensor_msgs/JointState: knee_flexion, knee_varus in rad)
- out `/knee/<body>/pose` per moving body (PoseStamped, frame = reference frame,
  stamp = the input's stamp)
- out `/knee/markers` (visualization_msgs/MarkerArray) when `publish_markers` is true:
  published at `marker_rate_hz` with the latest answer, not once per answer, so a 1 kHz
  tracker does not flood RViz/Foxglove; id 0 is the reference body, 1..B the moving ones,
  plus 1000 k for a body's k-th further display mesh (conversions.body_markers).
- out `/diagnostics` every `diagnostics_period_s` (DiagnosticArray, one status
  'kneeseat table_server'); rates and latency percentiles cover the last period,
  counters the whole run. Latency = node clock at publish - input stamp.
- service `~/reload` (std_srvs/Trigger): read the `table` parameter's file again (the
  parameter may be changed first with `ros2 param set`); on failure the old table stays.

QoS: inputs use `qos_profile_sensor_data` (best effort, volatile) with keep last 50 instead
of 5 (5 ms at 1 kHz is shorter than a scheduling hiccup), which matches both reliable and
best-effort publishers; outputs are reliable, keep last 100 (a reliable writer overwrites
unacknowledged answers beyond its depth: 10 would be 10 ms at 1 kHz), and their
policies can be overridden through the standard `qos_overrides.*` parameters.

Parameters are read once at start (all but `table` are read-only); bad values stop the
node with one line `table_server: error: ...` on stderr and exit code 2. Mesh paths in
the table metadata that are relative are taken relative to the table file's directory.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
import math
from pathlib import Path
import re
import sys
import time
from typing import Any, Literal

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
import rclpy
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import (qos_profile_sensor_data, QoSDurabilityPolicy, QoSHistoryPolicy,
                       QoSProfile, QoSReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from kneeseat_core.errors import ConfigError, KneeseatError, OutOfRangeError, TableError
from kneeseat_core.table import Lookup, PoseTable, read_table
from kneeseat_ros.conversions import (
    angles_from_joint_state, angles_from_pose_stamped, AttitudeDecoder, BadInputError,
    body_markers, diagnostic_status, display_mesh_paths, DROP_REASONS, pose_stamped, stamp_ns)

__all__ = ['INPUT_QOS', 'OUTPUT_QOS', 'STATUS_NAME', 'ServerParams', 'TableServer',
           'load_table', 'main']

RCLError = _rclpy.RCLError
# Sensor-data QoS (best effort, volatile, keep last) as the demos use, with a deeper queue:
# depth 5 is 5 ms at 1 kHz, shorter than one scheduler hiccup on a loaded 2-core machine.
INPUT_QOS = QoSProfile(history=qos_profile_sensor_data.history, depth=50,
                       reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability)
# Messages taken per executor wake-up (see TableServer._drain).
DRAIN_MAX = 100
# serve(): the executor (timers, services, parameters) runs at most this often while the
# inputs are waited on directly; it bounds the timer and service jitter (s).
HOUSEKEEPING_S = 0.005
OUTPUT_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                        reliability=QoSReliabilityPolicy.RELIABLE,
                        durability=QoSDurabilityPolicy.VOLATILE)
STATUS_NAME = 'kneeseat table_server'
POSE_TOPIC = '/knee/pose'
JOINT_TOPIC = '/knee/joint_states'
MARKER_TOPIC = '/knee/markers'
DIAGNOSTICS_TOPIC = '/diagnostics'
WARN_THROTTLE_S = 2.0
_BODY_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
_BODY_RGBA = ((0.85, 0.8, 0.7, 1.0), (0.7, 0.8, 0.9, 1.0), (0.8, 0.9, 0.7, 1.0))
_REFERENCE_RGBA = (0.95, 0.95, 0.9, 0.6)


@dataclass(frozen=True, slots=True)
class ServerParams:
    """The node's parameters after validation (SI units)."""

    table: Path
    out_of_range: Literal['clamp', 'drop']
    record: str
    record_split_size_mb: float
    record_split_duration_s: float
    publish_markers: bool
    marker_rate_hz: float
    diagnostics_period_s: float


_PARAMETERS: tuple[tuple[str, Any, int, str, bool], ...] = (
    ('table', '', ParameterType.PARAMETER_STRING,
     'Table file (.npz) written by `kneeseat build`; re-read by ~/reload.', False),
    ('out_of_range', 'clamp', ParameterType.PARAMETER_STRING,
     "Attitudes outside the grid: 'clamp' (nearest edge, counted) or 'drop'.", True),
    ('record', '', ParameterType.PARAMETER_STRING,
     'Directory for session bags (<record>/kneeseat_<YYYYmmdd_HHMMSS>/); empty = off.', True),
    ('record_split_size_mb', 0.0, ParameterType.PARAMETER_DOUBLE,
     'New .mcap file after this many MiB; 0 = no size split.', True),
    ('record_split_duration_s', 0.0, ParameterType.PARAMETER_DOUBLE,
     'New .mcap file after this many seconds; 0 = no duration split.', True),
    ('publish_markers', False, ParameterType.PARAMETER_BOOL,
     'Publish /knee/markers (mesh markers of every body) for RViz and Foxglove.', True),
    ('marker_rate_hz', 30.0, ParameterType.PARAMETER_DOUBLE,
     'Rate of /knee/markers (Hz, > 0), each with the latest answer.', True),
    ('diagnostics_period_s', 1.0, ParameterType.PARAMETER_DOUBLE,
     'Period of /diagnostics (s, > 0).', True),
)
_TYPE_NAMES = {ParameterType.PARAMETER_STRING: 'a string',
               ParameterType.PARAMETER_DOUBLE: 'a double (write 1.0, not 1)',
               ParameterType.PARAMETER_BOOL: 'a bool (true/false)'}


def load_table(path: Path) -> PoseTable:
    """Read and verify a table for serving: file checks plus ROS-usable names.

    Raises:
        TableError: the file is missing or corrupt (see `read_table`), or a body name
            cannot be used in a topic name.
    """
    table = read_table(path)
    for body in table.bodies:
        if not _BODY_NAME.match(body):
            raise TableError(f'{path}: body name {body!r} cannot be used in the topic '
                             '/knee/<body>/pose; rebuild the table with names made of '
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
    decoder: AttitudeDecoder
    bodies: tuple[str, ...]
    meshes: tuple[tuple[str, ...], ...]     # display mesh files: reference, then bodies
    bounds_deg: tuple[float, float, float, float]

    @classmethod
    def load(cls, path: Path) -> _Served:
        table = load_table(path)
        flexion, varus = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
        meta = table.metadata
        meshes = tuple(display_mesh_paths(e, path.parent)
                       for e in [meta['reference'], *meta['bodies']])
        return cls(table, path, table.reference_frame, AttitudeDecoder(table.axes),
                   table.bodies, meshes, (float(flexion[0]), float(flexion[-1]),
                                          float(varus[0]), float(varus[-1])))


class TableServer(Node):
    """Serves a pose table: tracked attitude in, settled pose of every moving body out."""

    def __init__(self, **kwargs: Any) -> None:
        """Declare and validate parameters, load the table, create the ROS interfaces.

        Args:
            **kwargs: forwarded to `rclpy.node.Node` (context=, parameter_overrides=, ...).
        Raises:
            ConfigError: a parameter is invalid.
            TableError: the table is missing or corrupt.
            KneeseatError: the session recorder cannot start (recorder.RecorderError).
        """
        super().__init__('table_server', **kwargs)
        self._log = self.get_logger()
        self._clock = self.get_clock()
        self.params = self._read_parameters()
        self._served = _Served.load(self.params.table)
        self._out_of_range = self.params.out_of_range
        self._received = 0
        self._answered = 0
        self._published = 0
        self._clamped = 0
        self._nonconverged = 0
        self._dropped = dict.fromkeys(DROP_REASONS, 0)
        self._window_received = 0
        self._window_start_ns = self._clock.now().nanoseconds
        self._latencies_ns: list[int] = []
        self._last: tuple[Lookup, Any] | None = None
        self._recorder: Any = None
        self._recorder_error_logged = False

        self._pubs: dict[str, Publisher] = {}
        self._body_pubs: list[Publisher] = []
        self._make_body_publishers()
        self._diag_pub = self.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, OUTPUT_QOS,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self._marker_pub = None
        if self.params.publish_markers:
            self._marker_pub = self.create_publisher(
                MarkerArray, MARKER_TOPIC, OUTPUT_QOS,
                qos_overriding_options=QoSOverridingOptions.with_default_policies())
            self.create_timer(1.0 / self.params.marker_rate_hz, self._publish_markers)
            self._check_meshes()
        self._pose_sub = self.create_subscription(PoseStamped, POSE_TOPIC, self._on_pose,
                                                  INPUT_QOS)
        self._joint_sub = self.create_subscription(JointState, JOINT_TOPIC, self._on_joints,
                                                   INPUT_QOS)
        self._reload_srv = self.create_service(Trigger, '~/reload', self._on_reload)
        self.create_timer(self.params.diagnostics_period_s, self._publish_diagnostics)
        if self.params.record:
            self._start_recorder()
        s = self._served
        self._log.info(
            f'serving {s.path} (sha256 {s.table.sha256[:12]}) bodies {list(s.bodies)} in '
            f'{s.frame!r}, flexion [{s.bounds_deg[0]:.1f}, {s.bounds_deg[1]:.1f}] deg, varus '
            f'[{s.bounds_deg[2]:.1f}, {s.bounds_deg[3]:.1f}] deg, out_of_range='
            f'{self._out_of_range}; in {self._pose_sub.topic_name}, '
            f'{self._joint_sub.topic_name} (sensor data QoS: best effort, depth '
            f'{INPUT_QOS.depth}); out '
            f'{[p.topic_name for p in self._body_pubs]} (reliable, depth 100); recording '
            f'{self._recorder_dir if self._recorder is not None else "off"}')

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
                              'table:=/path/to/table.npz (a file written by kneeseat build)')
        if values['out_of_range'] not in ('clamp', 'drop'):
            raise ConfigError(f"parameter 'out_of_range' is {values['out_of_range']!r}; use "
                              "'clamp' or 'drop'")
        for name in ('record_split_size_mb', 'record_split_duration_s'):
            if not (math.isfinite(values[name]) and values[name] >= 0.0):
                raise ConfigError(f'parameter {name!r} is {values[name]}; use a value >= 0 '
                                  '(0 = no split)')
        for name in ('marker_rate_hz', 'diagnostics_period_s'):
            if not (math.isfinite(values[name]) and values[name] > 0.0):
                raise ConfigError(f'parameter {name!r} is {values[name]}; use a value > 0')
        values['table'] = Path(values['table']).expanduser().absolute()
        return ServerParams(**values)

    def _make_body_publishers(self) -> None:
        for body in self._served.bodies:
            if body not in self._pubs:
                self._pubs[body] = self.create_publisher(
                    PoseStamped, f'/knee/{body}/pose', OUTPUT_QOS,
                    qos_overriding_options=QoSOverridingOptions.with_default_policies())
                if self._recorder is not None:
                    self._recorder.add_topic(self._pubs[body].topic_name,
                                             'geometry_msgs/msg/PoseStamped', OUTPUT_QOS)
        self._body_pubs = [self._pubs[b] for b in self._served.bodies]

    def _check_meshes(self) -> None:
        for path in (p for paths in self._served.meshes for p in paths or [None]):
            if path is None or not Path(path).is_file():
                self._log.warning(f'display mesh {path} not found; its marker will not draw '
                                  '(set display_mesh in the knee config and rebuild)')

    def _start_recorder(self) -> None:
        try:
            from kneeseat_ros.recorder import BagRecorder
        except ImportError as err:
            raise ConfigError(f"parameter 'record' is set but the recorder is unavailable "
                              f"({err}); set record:='' or install kneeseat_ros fully") from None
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
        self._recorder, self._recorder_dir = recorder, directory
        recorder.add_topic(self._pose_sub.topic_name, 'geometry_msgs/msg/PoseStamped', INPUT_QOS)
        recorder.add_topic(self._joint_sub.topic_name, 'sensor_msgs/msg/JointState', INPUT_QOS)
        for pub in self._pubs.values():
            recorder.add_topic(pub.topic_name, 'geometry_msgs/msg/PoseStamped', OUTPUT_QOS)
        recorder.add_topic(self._diag_pub.topic_name, 'diagnostic_msgs/msg/DiagnosticArray',
                           OUTPUT_QOS)
        if self._marker_pub is not None:
            recorder.add_topic(self._marker_pub.topic_name,
                               'visualization_msgs/msg/MarkerArray', OUTPUT_QOS)

    # -------------------------------------------------------------- hot path
    def _on_pose(self, msg: PoseStamped) -> None:
        self._handle_pose(msg)
        self._drain(self._pose_sub, self._handle_pose)

    def _on_joints(self, msg: JointState) -> None:
        self._handle_joints(msg)
        self._drain(self._joint_sub, self._handle_joints)

    def _drain(self, sub: Any, handle: Any) -> None:
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
        """Spin until shutdown: wait on the two inputs directly, the executor for the rest.

        rclpy's executor rebuilds its wait set over every entity (parameter services,
        timers, ...) for each message: about 0.15 ms idle on this machine, several times
        the answer itself, which at 1 kHz left no headroom (p99 2.6 ms). Here a wait set
        holding only /knee/pose and /knee/joint_states wakes for each input, and the
        executor runs once per `HOUSEKEEPING_S` for timers, services and parameters.
        Uses rclpy's WaitSet and take_message as rclpy.executors does (Jazzy).
        """
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(self)
        subs = (self._pose_sub, self._joint_sub)
        handlers = (self._handle_pose, self._handle_joints)
        wait_set = _rclpy.WaitSet(len(subs), 0, 0, 0, 0, 0, self.context.handle)
        due = 0.0
        while self.context.ok():
            now = time.monotonic()
            if now >= due:
                executor.spin_once(timeout_sec=0.0)
                due = now + HOUSEKEEPING_S
            with self.context.handle, self._pose_sub.handle, self._joint_sub.handle:
                wait_set.clear_entities()
                for sub in subs:
                    wait_set.add_subscription(sub.handle)
                wait_set.wait(int(max(due - time.monotonic(), 0.0) * 1e9))
            for sub, handle in zip(subs, handlers):
                self._drain(sub, handle)

    def _handle_pose(self, msg: PoseStamped) -> None:
        self._received += 1
        if self._recorder is not None:
            self._record(self._pose_sub.topic_name, msg, stamp_ns(msg.header.stamp))
        try:
            flexion, varus = angles_from_pose_stamped(msg, self._served.decoder,
                                                      self._served.frame)
        except BadInputError as err:
            self._drop(err.reason, err)
            return
        self._answer(flexion, varus, msg.header.stamp)

    def _handle_joints(self, msg: JointState) -> None:
        self._received += 1
        if self._recorder is not None:
            self._record(self._joint_sub.topic_name, msg, stamp_ns(msg.header.stamp))
        try:
            flexion, varus = angles_from_joint_state(msg)
        except BadInputError as err:
            self._drop(err.reason, err)
            return
        self._answer(flexion, varus, msg.header.stamp)

    def _answer(self, flexion: float, varus: float, stamp: Any) -> None:
        served = self._served
        try:
            lookup = served.table.interpolate(flexion, varus, self._out_of_range)
        except OutOfRangeError as err:
            self._drop('out_of_range', err)
            return
        except KneeseatError as err:       # non-finite angles are caught before; belt and braces
            self._drop('nonfinite', err)
            return
        position, orientation, frame = lookup.position_m, lookup.orientation_xyzw, served.frame
        for i, pub in enumerate(self._body_pubs):
            out = pose_stamped(position[i], orientation[i], stamp, frame)
            pub.publish(out)
            if self._recorder is not None:
                self._record(pub.topic_name, out, stamp_ns(stamp))
        self._published += len(self._body_pubs)
        self._answered += 1
        self._window_received += 1
        if lookup.clamped:
            self._clamped += 1
        if lookup.nonconverged.any():
            self._nonconverged += 1
        self._last = (lookup, stamp)
        self._latencies_ns.append(self._clock.now().nanoseconds - stamp_ns(stamp))

    def _drop(self, reason: str, err: Exception) -> None:
        self._dropped[reason] += 1
        self._log.warning(f'dropped input ({reason}): {err}',
                          throttle_duration_sec=WARN_THROTTLE_S)

    def _record(self, topic: str, msg: Any, publish_time_ns: int) -> None:
        self._recorder.write(topic, msg, self._clock.now().nanoseconds, publish_time_ns)

    # ------------------------------------------------------- slow callbacks
    def _publish_markers(self) -> None:
        served, last = self._served, self._last
        stamp = last[1] if last is not None else self._clock.now().to_msg()
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
        dropped = sum(self._dropped.values())
        level, message = DiagnosticStatus.OK, 'serving'
        if dropped:
            level, message = DiagnosticStatus.WARN, f'{dropped} inputs dropped'
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
            ('received', self._received),
            ('answered', self._answered),
            ('published', self._published),
            ('dropped', dropped),
            *((f'dropped_{reason}', n) for reason, n in self._dropped.items()),
            ('clamped', self._clamped),
            ('nonconverged_answers', self._nonconverged),
            ('rate_hz', rate_hz),
            ('latency_p50_ms', p50),
            ('latency_p99_ms', p99),
            ('latency_max_ms', worst),
            ('recorder', recorder),
        ]
        array = DiagnosticArray()
        array.header.stamp = now.to_msg()
        array.status.append(diagnostic_status(STATUS_NAME, level, message, served.frame,
                                              values))
        return array

    def _recorder_status(self) -> str:
        rec = self._recorder
        if rec is None:
            return 'off'
        if rec.error:
            if not self._recorder_error_logged:
                self._recorder_error_logged = True
                self._log.error(f'recording to {self._recorder_dir} stopped: {rec.error}; '
                                'still serving poses')
            return f'error: {rec.error}'
        return f'recording {self._recorder_dir} ({rec.message_count} messages)'

    def _publish_diagnostics(self) -> None:
        array = self.diagnostics()
        self._diag_pub.publish(array)
        if self._recorder is not None:
            self._record(self._diag_pub.topic_name, array, stamp_ns(array.header.stamp))

    def _on_reload(self, request: Trigger.Request,
                   response: Trigger.Response) -> Trigger.Response:
        path = Path(str(self.get_parameter('table').value)).expanduser().absolute()
        old = self._served
        try:
            served = _Served.load(path)
        except KneeseatError as err:
            response.success = False
            response.message = f'reload failed, still serving {old.path}: {err}'
            self._log.error(response.message)
            return response
        self._served = served
        self._make_body_publishers()
        if self._marker_pub is not None:
            self._check_meshes()
        self._last = None
        response.success = True
        response.message = (f'serving {path} (sha256 {served.table.sha256[:12]}), was '
                            f'{old.path} (sha256 {old.table.sha256[:12]})')
        self._log.info(response.message)
        return response

    def destroy_node(self) -> None:
        """Finalise the session bag (if recording), then destroy the node."""
        if self._recorder is not None:
            self._recorder.close()
            if self._recorder.error:
                self._log.error(f'recording to {self._recorder_dir} failed: '
                                f'{self._recorder.error}')
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point (`table_server`, `ros2 run kneeseat_ros table_server`).

    Returns:
        0 on a clean stop (SIGINT, SIGTERM, shutdown), 2 on bad parameters or table.
    """
    rclpy.init(args=args)
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
