"""The table_server node's parameters: declaration, validation and the usage text.

Every parameter is declared with a `ParameterDescriptor` (its description is what `ros2
param describe` shows; config/table_server.yaml documents each one too) and validated once
at start, so that a bad configuration never starts serving. All but `table` are
read-only; setting `table` loads that file (see `table_server`).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any, Literal

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node

from kneeseat_core.errors import ConfigError
from . import topics
from .conversions import JOINT_NAMES

__all__ = ['ServerParams', 'PARAMETERS', 'USAGE', 'declare_parameters']

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
PARAMETERS: tuple[tuple[str, Any, int, str, bool], ...] = (
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


def declare_parameters(node: Node) -> ServerParams:
    """Declare every parameter of the node (with its descriptor) and validate the values.

    Raises:
        ConfigError: a parameter has the wrong type or an invalid value; the message
            names it and the fix.
    """
    values: dict[str, Any] = {}
    for name, default, ptype, text, read_only in PARAMETERS:
        descriptor = ParameterDescriptor(name=name, type=ptype, description=text,
                                         read_only=read_only)
        try:
            values[name] = node.declare_parameter(name, default, descriptor).value
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
