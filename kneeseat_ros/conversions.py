"""Pure conversions between ROS messages and numpy/Python values (no node, no DDS).

Inputs are validated here so that the node's callbacks stay glue: every rejection raises
`BadInputError`, whose `reason` names the diagnostics counter it goes to. The hot path
(one tracker message -> one pose per body) avoids numpy where plain floats are faster.

Quaternion tolerance: trackers send float32-ish data (about 7 significant digits) and
often renormalise after filtering, so `|1 - |q||` up to `QUAT_NORM_TOL`
(`TOL.input_unit_norm`, 1e-3) is accepted and the quaternion is normalised; anything
further from unit length is corrupt data and rejected. A zero quaternion is rejected as
well (it has no rotation), which also covers an uninitialised `Pose` message.

Frame check: a PoseStamped must carry the table's reference frame in `header.frame_id`.
An empty frame_id is rejected too (reason 'frame_id'): a tracker that does not say which
frame it means cannot be trusted to mean the femur.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
import math
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseStamped
import numpy as np
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from kneeseat_core.geometry import KneeAxes, matrix_from_quat, quat_from_matrix, TOL
from kneeseat_core.table import display_paths
from kneeseat_core.typed import Floats, Pose as PoseArray
from .errors import BadInputError

__all__ = ['QUAT_NORM_TOL', 'JOINT_NAMES', 'DROP_REASONS', 'AttitudeDecoder', 'stamp_ns',
           'stamp_from_ns', 'quat_xyzw', 'angles_from_pose_stamped', 'angles_from_joint_state',
           'pose_stamped', 'pose_stamped_for_attitude', 'joint_state', 'pose_from_msg',
           'mesh_marker', 'MARKER_ID_STRIDE', 'display_mesh_paths', 'body_markers',
           'diagnostic_status', 'angles_from_orientation', 'angles_from_joints',
           'rigid_from_fields']

QUAT_NORM_TOL = TOL.input_unit_norm     # |1 - |q|| accepted from a tracker (float32 data)
JOINT_NAMES = ('knee_flexion', 'knee_varus')

# Diagnostics counter names (keys `dropped_<reason>`), in display order.
DROP_REASONS = ('nonfinite', 'quaternion', 'frame_id', 'joint_names', 'lengths',
                'out_of_range', 'unpaired', 'stale', 'malformed')


def stamp_ns(stamp: Time) -> int:
    """Nanoseconds since the epoch of a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_from_ns(ns: int) -> Time:
    """builtin_interfaces/Time from integer nanoseconds (>= 0)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def quat_xyzw(msg: Pose) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a geometry_msgs/Pose orientation, as floats."""
    o = msg.orientation
    return (o.x, o.y, o.z, o.w)


class AttitudeDecoder:
    """(flexion, varus) of a unit quaternion with a table's axes, in plain Python floats.

    Same result as `KneeAxes.decompose(matrix_from_quat(q))[:2]` (to rounding), written out
    for one message: only the third column of `B.T @ R @ B` is needed, where B is the
    right-handed basis [flexion, varus, +-long] of `KneeAxes`. Measured: 1.3 us, against
    55 us through `decompose(matrix_from_quat(q))` and 42 us through scipy's `Rotation`.
    """

    __slots__ = ('_b0', '_b1', '_b2')

    def __init__(self, axes: KneeAxes) -> None:
        f, v, long = (tuple(float(c) for c in a) for a in (axes.flexion, axes.varus, axes.long))
        cross = (f[1] * v[2] - f[2] * v[1], f[2] * v[0] - f[0] * v[2], f[0] * v[1] - f[1] * v[0])
        sign = 1.0 if sum(c * d for c, d in zip(cross, long)) > 0.0 else -1.0
        self._b0, self._b1 = f, v
        self._b2 = (sign * long[0], sign * long[1], sign * long[2])

    def angles(self, x: float, y: float, z: float, w: float) -> tuple[float, float]:
        """(flexion, varus) in rad of the unit quaternion (x, y, z, w)."""
        b0, b1, b2 = self._b0, self._b1, self._b2
        # R @ b2, with R the rotation matrix of the quaternion
        c0 = ((1 - 2 * (y * y + z * z)) * b2[0] + 2 * (x * y - z * w) * b2[1]
              + 2 * (x * z + y * w) * b2[2])
        c1 = (2 * (x * y + z * w) * b2[0] + (1 - 2 * (x * x + z * z)) * b2[1]
              + 2 * (y * z - x * w) * b2[2])
        c2 = (2 * (x * z - y * w) * b2[0] + 2 * (y * z + x * w) * b2[1]
              + (1 - 2 * (x * x + y * y)) * b2[2])
        r02 = b0[0] * c0 + b0[1] * c1 + b0[2] * c2
        r12 = b1[0] * c0 + b1[1] * c1 + b1[2] * c2
        r22 = b2[0] * c0 + b2[1] * c1 + b2[2] * c2
        return math.atan2(-r12, r22), math.asin(min(1.0, max(-1.0, r02)))


def angles_from_pose_stamped(msg: PoseStamped, axes: KneeAxes | AttitudeDecoder,
                             frame_id: str) -> tuple[float, float]:
    """(flexion, varus) in rad of a tracked tibia orientation in the femur frame.

    Position is ignored. The orientation is decomposed with the table's own axes
    (`KneeAxes.decompose`), so rotation about the long axis does not leak into the angles.

    Args:
        msg: the tracker message; `pose.orientation` (x, y, z, w) of the tibia in `frame_id`.
        axes: the table's attitude axes (pass an `AttitudeDecoder` on hot paths).
        frame_id: the table's reference frame; `msg.header.frame_id` must equal it.
    Raises:
        BadInputError: wrong or empty frame_id ('frame_id'), NaN/inf ('nonfinite'), a zero
            or non-unit quaternion ('quaternion').
    """
    return angles_from_orientation(msg.header.frame_id, quat_xyzw(msg.pose), axes, frame_id)


def angles_from_orientation(got_frame: str, quat: Sequence[float],
                            axes: KneeAxes | AttitudeDecoder,
                            frame_id: str) -> tuple[float, float]:
    """`angles_from_pose_stamped` on the fields: the message's frame_id and (x, y, z, w)."""
    if got_frame != frame_id:
        raise BadInputError('frame_id', f'PoseStamped frame_id {got_frame!r} is not the table '
                            f'reference frame {frame_id!r}; publish the tibia orientation '
                            f'in {frame_id!r}')
    x, y, z, w = quat
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(norm):
        raise BadInputError('nonfinite', 'PoseStamped orientation has NaN or inf '
                            f'({x}, {y}, {z}, {w}); fix the tracker output')
    if abs(1.0 - norm) > QUAT_NORM_TOL:
        raise BadInputError('quaternion', f'PoseStamped orientation |q| = {norm:.6g} is not '
                            f'a unit quaternion (tolerance {QUAT_NORM_TOL:g}); send '
                            'normalised (x, y, z, w)')
    decoder = axes if isinstance(axes, AttitudeDecoder) else AttitudeDecoder(axes)
    return decoder.angles(x / norm, y / norm, z / norm, w / norm)


def rigid_from_fields(got_frame: str, pose: Sequence[float], frame_id: str,
                      what: str) -> tuple[float, float, float, float, float, float, float]:
    """(px, py, pz, qx, qy, qz, qw) of a tracked rigid body's pose in `frame_id`, from a
    PoseStamped's frame_id and pose fields; the quaternion is normalised (within
    `QUAT_NORM_TOL` of unit length).

    Raises:
        BadInputError: wrong or empty frame_id ('frame_id'), NaN/inf ('nonfinite'), a zero
            or non-unit quaternion ('quaternion'). The message names `what`.
    """
    if got_frame != frame_id:
        raise BadInputError('frame_id', f'{what} frame_id {got_frame!r} is not the world frame '
                            f'{frame_id!r}; set tracker.world_frame or fix the tracker')
    px, py, pz, x, y, z, w = pose
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(norm) and math.isfinite(px + py + pz)):
        raise BadInputError('nonfinite', f'{what} pose has NaN or inf; fix the tracker output')
    if abs(1.0 - norm) > QUAT_NORM_TOL:
        raise BadInputError('quaternion', f'{what} orientation |q| = {norm:.6g} is not a unit '
                            f'quaternion (tolerance {QUAT_NORM_TOL:g}); send normalised '
                            '(x, y, z, w)')
    return (px, py, pz, x / norm, y / norm, z / norm, w / norm)


def angles_from_joint_state(msg: JointState,
                            names: Sequence[str] = JOINT_NAMES) -> tuple[float, float]:
    """(flexion, varus) in rad from a JointState carrying `names` (extra joints ignored).

    Raises:
        BadInputError: `position` (or a non-empty velocity/effort) length differs from
            `name` ('lengths'), a name is missing ('joint_names'), a value is NaN/inf
            ('nonfinite').
    """
    return angles_from_joints(msg.name, msg.position, len(msg.velocity), len(msg.effort),
                              names)


def angles_from_joints(joint_names: Sequence[str], position: Sequence[float],
                       n_velocity: int, n_effort: int,
                       names: Sequence[str] = JOINT_NAMES) -> tuple[float, float]:
    """`angles_from_joint_state` on the fields: names, positions, velocity/effort counts."""
    n = len(joint_names)
    if len(position) != n or n_velocity not in (0, n) or n_effort not in (0, n):
        raise BadInputError('lengths', f'JointState has {n} names but {len(position)} '
                            f'positions, {n_velocity} velocities, {n_effort} '
                            'efforts; send one position per name')
    try:
        index = [joint_names.index(name) for name in names]
    except ValueError:
        raise BadInputError('joint_names', f'JointState names {list(joint_names)} lack '
                            f'{list(names)}; publish both joints (radians)') from None
    flexion, varus = (float(position[i]) for i in index)
    if not (math.isfinite(flexion) and math.isfinite(varus)):
        raise BadInputError('nonfinite', f'JointState {names[0]}={flexion}, '
                            f'{names[1]}={varus} is not finite; fix the publisher')
    return flexion, varus


def pose_stamped(position_m: Sequence[float] | Floats, orientation_xyzw: Sequence[float] | Floats,
                 stamp: Time, frame_id: str) -> PoseStamped:
    """PoseStamped from a (3,) position in m and a (4,) quaternion (x, y, z, w)."""
    msg = PoseStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = float(position_m[0]), float(position_m[1]), float(position_m[2])
    o.x, o.y, o.z, o.w = (float(orientation_xyzw[0]), float(orientation_xyzw[1]),
                          float(orientation_xyzw[2]), float(orientation_xyzw[3]))
    return msg


def pose_stamped_for_attitude(axes: KneeAxes, flexion_rad: float, varus_rad: float,
                              stamp: Time, frame_id: str,
                              rotation_rad: float = 0.0) -> PoseStamped:
    """What a tracker would send for an attitude: orientation = `axes.orientation(...)`."""
    q = quat_from_matrix(axes.orientation(flexion_rad, varus_rad, rotation_rad))
    return pose_stamped((0.0, 0.0, 0.0), q, stamp, frame_id)


def joint_state(flexion_rad: float, varus_rad: float, stamp: Time,
                names: Sequence[str] = JOINT_NAMES) -> JointState:
    """JointState with the two knee joints (rad)."""
    msg = JointState()
    msg.header.stamp = stamp
    msg.name = list(names)
    msg.position = [float(flexion_rad), float(varus_rad)]
    return msg


def pose_from_msg(msg: Pose) -> PoseArray:
    """(4, 4) pose (m) of a geometry_msgs/Pose; the quaternion is normalised."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quat(np.array(quat_xyzw(msg)))
    p = msg.position
    out[:3, 3] = (p.x, p.y, p.z)
    return out


def mesh_marker(marker_id: int, mesh_path: str, frame_id: str, stamp: Time,
                position_m: Floats | Sequence[float] = (0.0, 0.0, 0.0),
                orientation_xyzw: Floats | Sequence[float] = (0.0, 0.0, 0.0, 1.0),
                rgba: Sequence[float] = (0.9, 0.9, 0.85, 1.0),
                namespace: str = 'kneeseat') -> Marker:
    """A MESH_RESOURCE marker drawing the mesh file at `mesh_path` (absolute) at a pose.

    Meshes are in metres (scale 1); the mesh's own colours are not used.
    """
    msg = Marker()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.ns = namespace
    msg.id = marker_id
    msg.type = Marker.MESH_RESOURCE
    msg.action = Marker.ADD
    msg.mesh_resource = 'file://' + mesh_path
    msg.mesh_use_embedded_materials = False
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = (float(v) for v in position_m)
    o.x, o.y, o.z, o.w = (float(v) for v in orientation_xyzw)
    msg.scale.x = msg.scale.y = msg.scale.z = 1.0
    msg.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                          a=float(rgba[3]))
    return msg


# Marker id of the k-th mesh of the body in slot s (reference 0, bodies 1..): s + STRIDE * k,
# so a body with one display mesh keeps id s as before multi-mesh bodies.
MARKER_ID_STRIDE = 1000


def display_mesh_paths(entry: Mapping[str, Any], table_dir: Path) -> tuple[str, ...]:
    """Absolute mesh files to draw for a table metadata body (or reference) entry.

    Its `display_meshes`, else its `display_mesh`, else its collision meshes (`meshes`,
    else `mesh`: tables written before multi-mesh bodies have only the singular keys).
    Relative paths are taken from `table_dir`.
    """
    out = []
    for name in display_paths(entry):
        path = Path(str(name)).expanduser()
        out.append(str(path if path.is_absolute() else (table_dir / path).resolve()))
    return tuple(out)


def body_markers(slot: int, mesh_paths: Sequence[str], frame_id: str, stamp: Time,
                 position_m: Floats | Sequence[float] = (0.0, 0.0, 0.0),
                 orientation_xyzw: Floats | Sequence[float] = (0.0, 0.0, 0.0, 1.0),
                 rgba: Sequence[float] = (0.9, 0.9, 0.85, 1.0)) -> list[Marker]:
    """One `mesh_marker` per mesh file of a body, all at the body's pose and colour.

    Ids are slot + MARKER_ID_STRIDE * k for the k-th file (slot 0 = the reference).
    """
    return [mesh_marker(slot + MARKER_ID_STRIDE * k, path, frame_id, stamp, position_m,
                        orientation_xyzw, rgba) for k, path in enumerate(mesh_paths)]


def diagnostic_status(name: str, level: bytes, message: str, hardware_id: str,
                      values: Sequence[tuple[str, object]]) -> DiagnosticStatus:
    """DiagnosticStatus with `values` as string key/value pairs (floats to 6 digits)."""
    def text(v: object) -> str:
        return f'{v:.6g}' if isinstance(v, float) else str(v)

    return DiagnosticStatus(level=level, name=name, message=message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=text(v)) for k, v in values])
