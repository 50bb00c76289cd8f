"""The `table_server` node: answers each tracked knee attitude with every bone's settled pose.

Run it as `ros2 run kneeseat_ros table_server --ros-args -p table:=knee.npz` (ament
layout) or as the `table_server` console script of the project's venv;
`table_server --help` prints the usage (`server_params.USAGE`). Its interface - topics
(relative names: they follow the namespace and remapping; `/diagnostics` and `/tf` are
absolute), the two input modes (attitude: `knee/pose`, `knee/joint_states`; tracker: two
marker clusters and a registration), parameters, QoS, `~/reload`, diagnostics and
recording - is described in docs/design.md ("The node").

QoS: inputs use `qos_profile_sensor_data` (best effort, volatile) with keep last 1000
instead of 5 (5 ms at 1 kHz is shorter than a scheduling hiccup), which matches both
reliable and best-effort publishers; outputs are reliable, keep last 1000 (a reliable
writer overwrites unacknowledged answers beyond its depth: 100 is 50 ms at 2 kHz). `/tf`
uses tf2_ros's broadcaster QoS (reliable, volatile, keep last 100). Every input and output
but `/tf` takes the standard `qos_overrides.*` parameters (history, depth, reliability):
a tracker that must not lose a sample asks for reliable inputs. Markers are published
at `marker_rate_hz` with the latest answer, not once per answer, so that a 1 kHz tracker
does not flood RViz/Foxglove.

The node is wired here; its parts are modules of their own: parameters
(`server_params`), the served table (`served`), the hot path (`responder`: CDR bytes in
and out, no rclpy message object per message), diagnostics (`diagnostics`), how it spins
(`spin`), session recording (`recorder`). Bad parameters stop the node with one line
`table_server: error: ...` on stderr and exit code 2.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import functools
from pathlib import Path
import sys
import time
from typing import Any, TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import (qos_profile_sensor_data, QoSDurabilityPolicy, QoSHistoryPolicy, QoSProfile,
                       QoSReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from kneeseat_core.errors import ConfigError, KneeseatError
from kneeseat_ros import topics
from kneeseat_ros.conversions import body_markers, DROP_REASONS, stamp_from_ns, stamp_ns
from kneeseat_ros.diagnostics import Counters, NodeState, status
from kneeseat_ros.responder import Responder, TrackerMode
from kneeseat_ros.served import Route, Served
from kneeseat_ros.server_params import declare_parameters, USAGE
from kneeseat_ros.spin import drain, Handler, InputsGroup, run_node, serve
from kneeseat_ros.topics import STATUS_NAME
from kneeseat_ros.tracker import load_registration, Pairer

if TYPE_CHECKING:
    from kneeseat_ros.bag.recorder import BagRecorder

__all__ = ['INPUT_QOS', 'OUTPUT_QOS', 'TF_QOS', 'STATUS_NAME', 'TableServer', 'main', 'USAGE']

# Sensor-data QoS (best effort, volatile, keep last) as the demos use, with a deeper queue:
# depth 5 is 5 ms at 1 kHz; 1000 is 0.5 s at 2 kHz, longer than the scheduler stalls seen
# on a loaded 2-core machine (up to ~0.3 s), so a node that keeps up on average drops none.
INPUT_QOS = QoSProfile(history=qos_profile_sensor_data.history, depth=1000,
                       reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability)
OUTPUT_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=QoSReliabilityPolicy.RELIABLE,
                        durability=QoSDurabilityPolicy.VOLATILE)
TF_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                    reliability=QoSReliabilityPolicy.RELIABLE,
                    durability=QoSDurabilityPolicy.VOLATILE)
_BODY_RGBA = ((0.85, 0.8, 0.7, 1.0), (0.7, 0.8, 0.9, 1.0), (0.8, 0.9, 0.7, 1.0))
_REFERENCE_RGBA = (0.95, 0.95, 0.9, 0.6)
_POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
# every input and output but /tf takes the standard `qos_overrides./<topic>.<entity>.*`
# parameters (history, depth, reliability)
_OVERRIDABLE = QoSOverridingOptions.with_default_policies


def _qos_words(qos: QoSProfile) -> str:
    """A profile as the startup line says it: reliability and depth."""
    return f'{qos.reliability.name.lower().replace("_", " ")}, depth {qos.depth}'


@dataclass(frozen=True, slots=True, eq=False)
class _Input:
    """One input: its subscription (raw CDR bytes), its handler, and the type recorded."""

    sub: Subscription
    handle: Handler
    msg_type: str


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
        self._ros_clock = self.get_clock()
        # the node clock in ns for the hot path: with use_sim_time off (read at start) ROS
        # time is the system clock, and time.time_ns is ~10x cheaper than Clock.now()
        self._now_ns: Callable[[], int] = (
            (lambda: self._ros_clock.now().nanoseconds)
            if self.get_parameter('use_sim_time').value else time.time_ns)
        self.params = declare_parameters(self)
        self._tracker: TrackerMode | None = None
        if self.params.tracker_registration:
            tolerance_s = self.params.tracker_pair_tolerance_s
            self._tracker = TrackerMode(
                load_registration(Path(self.params.tracker_registration).expanduser()),
                Pairer(int(round(tolerance_s * 1e9))), self.params.tracker_world_frame,
                tolerance_s)
        self._world = self._tracker.world_frame if self._tracker is not None else None
        served = Served.load(self.params.table, self._world)
        self._counters = Counters(DROP_REASONS, self._ros_clock.now().nanoseconds)
        self._recorder: BagRecorder | None = None
        self._recorder_error_logged = False
        self._pubs: dict[str, Publisher] = {}
        self._world_pubs: dict[str, Publisher] = {}
        self._inputs_group = InputsGroup()
        self._create_outputs(served)
        self._create_inputs()
        self._reload_srv = self.create_service(Trigger, '~/reload', self._on_reload)
        self.create_timer(self.params.diagnostics_period_s, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if self.params.record:
            self._start_recorder()
        self._log.info(self._startup_line())

    # ------------------------------------------------------------------ setup
    @property
    def _served(self) -> Served:
        return self._responder.route.served

    def _create_outputs(self, served: Served) -> None:
        """Pose publishers of every body, /diagnostics, /tf and knee/markers if wanted."""
        route = self._make_route(served)
        self._diag_pub = self.create_publisher(
            DiagnosticArray, topics.DIAGNOSTICS, OUTPUT_QOS,
            qos_overriding_options=_OVERRIDABLE())
        self._tf_pub = self._make_tf_publisher()
        self._responder = Responder(route, self._counters, self._log, self._now_ns,
                                    self.params.out_of_range,
                                    (self.params.flexion_joint, self.params.varus_joint),
                                    self._tracker, self._tf_pub)
        self._marker_pub = None
        if self.params.publish_markers:
            self._marker_pub = self.create_publisher(
                MarkerArray, topics.MARKERS, OUTPUT_QOS,
                qos_overriding_options=_OVERRIDABLE())
            self.create_timer(1.0 / self.params.marker_rate_hz, self._publish_markers)
            self._check_meshes()

    def _create_inputs(self) -> None:
        """knee/pose and knee/joint_states, or the two tracker topics (raw CDR bytes)."""
        responder = self._responder
        if self._tracker is None:
            wanted: list[tuple[type, str, Handler, str]] = [
                (PoseStamped, topics.POSE, responder.handle_pose, _POSE_TYPE),
                (JointState, topics.JOINT_STATES, responder.handle_joints,
                 'sensor_msgs/msg/JointState')]
        else:
            wanted = [(PoseStamped, topic, functools.partial(responder.handle_rigid, side),
                       _POSE_TYPE)
                      for side, topic in enumerate((self.params.tracker_femur_topic,
                                                    self.params.tracker_tibia_topic))]
        self._inputs: list[_Input] = []
        for msg_class, topic, handle, msg_type in wanted:
            sub = self.create_subscription(msg_class, topic,
                                           functools.partial(self._on_input, handle=handle),
                                           INPUT_QOS, raw=True,
                                           callback_group=self._inputs_group,
                                           qos_overriding_options=_OVERRIDABLE())
            self._inputs.append(_Input(sub, handle, msg_type))
        responder.set_input_topics([i.sub.topic_name for i in self._inputs])

    def _startup_line(self) -> str:
        s, route = self._served, self._responder.route
        bounds = s.bounds_deg
        mode = ('attitude' if self._tracker is None else
                f'tracker (registration {self._tracker.registration.path}, world frame '
                f'{self._tracker.world_frame!r})')
        return (
            f'serving {s.path} (sha256 {s.table.sha256[:12]}) bodies {list(s.bodies)} in '
            f'{s.frame!r}, flexion [{bounds.flexion_min_deg:.1f}, {bounds.flexion_max_deg:.1f}]'
            f' deg, varus [{bounds.varus_min_deg:.1f}, {bounds.varus_max_deg:.1f}] deg, '
            f'out_of_range={self.params.out_of_range}; {mode}; in '
            f'{[i.sub.topic_name for i in self._inputs]} '
            f'({_qos_words(self._inputs[0].sub.qos_profile)}); out '
            f'{[p.topic_name for p in route.body_pubs + route.body_world_pubs]} '
            f'({_qos_words(route.body_pubs[0].qos_profile)}), tf '
            f'{"on" if self._tf_pub is not None else "off"}; recording '
            f'{self._recorder.directory if self._recorder is not None else "off"}')

    def _make_route(self, served: Served) -> Route:
        """Publishers for `served` (created once per topic), bundled with it."""
        for body in served.bodies:
            if body not in self._pubs:
                self._pubs[body] = self._pose_publisher(topics.body_pose(body))
        world: tuple[Publisher, ...] = ()
        reference = None
        if self._tracker is not None:
            for body in (served.reference, *served.bodies):
                if body not in self._world_pubs:
                    self._world_pubs[body] = self._pose_publisher(topics.body_world_pose(body))
            reference = self._world_pubs[served.reference]
            world = tuple(self._world_pubs[b] for b in served.bodies)
        return Route(served, tuple(self._pubs[b] for b in served.bodies), world, reference)

    def _pose_publisher(self, topic: str) -> Publisher:
        pub = self.create_publisher(
            PoseStamped, topic, OUTPUT_QOS,
            qos_overriding_options=_OVERRIDABLE())
        if self._recorder is not None:
            self._recorder.add_topic(pub.topic_name, _POSE_TYPE, pub.qos_profile)
        return pub

    def _make_tf_publisher(self) -> Publisher | None:
        if not self.params.publish_tf:
            return None
        try:
            from tf2_msgs.msg import TFMessage
            return self.create_publisher(TFMessage, topics.TF, TF_QOS)
        except Exception as err:     # ImportError, or its typesupport library not loadable
            self._log.info(f'publish_tf: /tf is off: tf2_msgs is not usable here ({err}); '
                           'build it as the README says (no pip wheel exists) or set '
                           'publish_tf:=false to silence this line')
            return None

    def _check_meshes(self) -> None:
        for path in (p for paths in self._served.meshes for p in paths or [None]):
            if path is None or not Path(path).is_file():
                self._log.warning(f'display mesh {path} not found; its marker will not draw '
                                  '(set display_mesh in the knee config and rebuild)')

    def _recorded_topics(self) -> list[tuple[str, str, QoSProfile]]:
        recorded = [(i.sub.topic_name, i.msg_type, i.sub.qos_profile) for i in self._inputs]
        for pub in (*self._pubs.values(), *self._world_pubs.values()):
            recorded.append((pub.topic_name, _POSE_TYPE, pub.qos_profile))
        recorded.append((self._diag_pub.topic_name, 'diagnostic_msgs/msg/DiagnosticArray',
                         self._diag_pub.qos_profile))
        if self._tf_pub is not None:
            recorded.append((self._tf_pub.topic_name, 'tf2_msgs/msg/TFMessage', TF_QOS))
        if self._marker_pub is not None:
            recorded.append((self._marker_pub.topic_name,
                             'visualization_msgs/msg/MarkerArray',
                             self._marker_pub.qos_profile))
        return recorded

    def _start_recorder(self) -> None:
        try:
            from kneeseat_ros.bag.recorder import open_session
        except ImportError as err:
            raise ConfigError(f"parameter 'record' is set but the recorder is unavailable "
                              f"({err}); set record:='' or install kneeseat_ros fully") from None
        self._recorder = open_session(
            Path(self.params.record).expanduser().absolute(), self._ros_clock.now().nanoseconds,
            self._recorded_topics(), self._served.table.sha256, str(self._served.path),
            split_size_bytes=int(self.params.record_split_size_mb * 1024 * 1024),
            split_duration_s=self.params.record_split_duration_s)
        self._responder.start_recording(self._recorder)

    # ------------------------------------------------------------------ inputs
    def _on_input(self, msg: Any, handle: Handler) -> None:
        """Executor callback of an input: handle it, then what else is queued behind it."""
        with self._inputs_group.handling:
            handle(msg)
            for i in self._inputs:
                if i.handle is handle:
                    drain(i.sub, handle)

    def serve(self) -> None:
        """Spin until shutdown: the inputs in this thread, everything else in a second one
        (`kneeseat_ros.spin.serve`)."""
        serve(self, self._inputs_group, [(i.sub, i.handle) for i in self._inputs])

    def _record(self, topic: str, msg: Any, publish_time_ns: int) -> None:
        """Record a message object (the slow callbacks: markers, diagnostics)."""
        assert self._recorder is not None
        self._recorder.write(topic, msg, self._ros_clock.now().nanoseconds, publish_time_ns)

    # ------------------------------------------------------- slow callbacks
    def _publish_markers(self) -> None:
        served, last = self._served, self._responder.last
        stamp = (stamp_from_ns(last.sec * 1_000_000_000 + last.nanosec) if last is not None
                 else self._ros_clock.now().to_msg())
        markers = MarkerArray()
        markers.markers.extend(body_markers(0, served.meshes[0], served.frame, stamp,
                                            rgba=_REFERENCE_RGBA))
        if last is not None:
            lookup = last.lookup
            for i, meshes in enumerate(served.meshes[1:]):
                markers.markers.extend(body_markers(
                    i + 1, meshes, served.frame, stamp, lookup.position_m[i],
                    lookup.orientation_xyzw[i], rgba=_BODY_RGBA[i % len(_BODY_RGBA)]))
        assert self._marker_pub is not None
        self._marker_pub.publish(markers)
        if self._recorder is not None:
            self._record(self._marker_pub.topic_name, markers, stamp_ns(stamp))

    def diagnostics(self) -> DiagnosticArray:
        """The current DiagnosticArray; starts a new rate/latency window.

        The counters are read with the inputs' handling held (`InputsGroup.handling`): the
        input thread bumps them, and a read torn by it would say, say, every pair answered
        but not every drop counted.
        """
        state = NodeState(self.get_fully_qualified_name(), self.params.out_of_range,
                          self._tracker is not None, self._tf_pub is not None,
                          self.params.diagnostics_window_s, self._recorder_status(),
                          self._recorder is not None and bool(self._recorder.error))
        array = DiagnosticArray()
        with self._inputs_group.handling:
            now = self._ros_clock.now()
            dropped = dict(self._counters.dropped)
            if self._tracker is not None:
                dropped['unpaired'] += self._tracker.pairer.unpaired
                dropped['stale'] += self._tracker.pairer.stale
            array.status.append(status(self._counters, dropped, self._served, state,
                                       now.nanoseconds))
        array.header.stamp = now.to_msg()
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
        served = Served.load(path, self._world)
        self._responder.switch_route(self._make_route(served))
        if self._marker_pub is not None:
            self._check_meshes()
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


def main(args: list[str] | None = None) -> int:
    """Console entry point (`table_server`, `ros2 run kneeseat_ros table_server`).

    Returns:
        0 on a clean stop (SIGINT, SIGTERM, shutdown) or after --help, 2 on bad
        parameters, table or command-line arguments.
    """
    return run_node(TableServer, 'table_server', USAGE, args)


if __name__ == '__main__':
    sys.exit(main())
