"""Rigid transforms, quaternions, the knee attitude decomposition and every tolerance.

Poses are (4, 4) float64 homogeneous matrices named `a_from_b` (they map points in b into
a). Quaternions are (x, y, z, w), ROS order, canonicalised to w >= 0; they exist only at
the ROS boundary, in table files and in interpolation. Everything is vectorised over a
leading axis where it says so.

Knee attitude (docs/design.md, "Conventions"): the orientation of the moving body in the
reference frame is
    R = Rot(flexion_axis, flexion) @ Rot(varus_axis, varus) @ Rot(long_axis, rotation)
with the three axes given in the reference frame at neutral.

Why `rotation_about`, `quat_from_matrix` and `matrix_from_quat` are our own and not
scipy's `Rotation` (which `rotation_angle` and the referee use): the settle, the sweep
and the bag maker run on them, and every table's and the shipped bag's bytes depend on
their exact arithmetic. scipy rounds differently in the last bit (measured on the 3,822
orientations of the default knee's full table): 20 % of the quaternions from matrices and
77 % of the matrices from quaternions differ in some component, by up to 2.2e-16 and
4.4e-16; of 1,000 rotations about one axis, 78 % of `from_rotvec`'s. That changes the
settles and so every table's hash. Speed decides nothing: one quaternion from a matrix
50 us here against scipy's 46 us, all 3,822 at once 0.88 ms against 1.05 ms, one
rotation about an axis 7.6 us against 11.2 us.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from .errors import ConfigError
from .typed import Floats, Pose, Vec3

__all__ = ['Tolerances', 'TOL', 'unit', 'rotation_about', 'pose_from', 'carried',
           'rotation_angle', 'quat_angles', 'quat_from_matrix', 'matrix_from_quat', 'KneeAxes']


@dataclass(frozen=True, slots=True)
class Tolerances:
    """Every numeric tolerance of the project, in one place (`TOL`).

    Geometry and arithmetic:
        zero_length: below this a vector (or a sum of weights) has no direction.
        unit_norm: |1 - |q|| accepted as a unit quaternion or axis in a table or a config.
        orthogonal: |cos| accepted between axes declared orthogonal.
        torque: |torque| (m) below this counts as zero (no sign), patent method.
        degenerate: |Gram determinant| (m^4) below this: a triangle has no area.
        normal_length: a sum of unit vertex normals shorter than this cancels (a knife
            edge), and the face normal stands in for it.
        fraction: a body's attitude fraction within this of 0 ignores that angle.
    Inputs from outside:
        input_unit_norm: |1 - |q|| accepted (then normalised) from a tracker or a START.json:
            float32 data, often renormalised after filtering.
        registration: |R^T R - I| and |1 - |q|| accepted in a tracker registration file
            (written with 6 to 9 digits; a scale error of 1e-6 is 0.2 um at 0.2 m).
    Grids (angles in degrees):
        grid_step: a grid's step must divide its range to within this many steps.
        demo_step: the demo's grid step must divide 10 deg to within this many steps.
        grid_match_deg: an angle this close to a grid node is that node.
        grid_range_deg: an angle this far outside a grid's range is still inside it.
        grid_uniform: relative and absolute difference of steps that count as equal.
        grid_same_rad: two grids whose values differ by less than this are the same grid.
    """

    zero_length: float = 1e-12
    unit_norm: float = 1e-6
    orthogonal: float = 1e-3
    torque: float = 1e-12
    degenerate: float = 1e-30
    normal_length: float = 1e-9
    fraction: float = 1e-12
    input_unit_norm: float = 1e-3
    registration: float = 1e-6
    grid_step: float = 1e-6
    demo_step: float = 1e-9
    grid_match_deg: float = 1e-6
    grid_range_deg: float = 1e-9
    grid_uniform: float = 1e-9
    grid_same_rad: float = 1e-12


TOL = Tolerances()


def unit(vector: ArrayLike, name: str = 'vector') -> Vec3:
    """Return `vector` (3,) scaled to unit length.

    Raises:
        ConfigError: the vector has (near) zero length or is not finite.
    """
    v = np.asarray(vector, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(v))
    if not np.isfinite(norm) or norm < TOL.zero_length:
        raise ConfigError(f'{name} {v.tolist()} has no direction (zero length or not finite); '
                          'give a non-zero vector such as 0,-1,0')
    return v / norm


def rotation_about(axis: Vec3, angle_rad: float | Floats) -> Floats:
    """Rotation matrices about a unit `axis` (3,) by `angle_rad` (scalar or (n,)).

    Returns:
        (3, 3) for a scalar angle, (n, 3, 3) for an array of angles (Rodrigues' formula).
    """
    kx, kx2 = _cross_matrices(*(float(c) for c in np.asarray(axis, dtype=np.float64)))
    a = np.asarray(angle_rad, dtype=np.float64)
    s, c = np.sin(a)[..., None, None], np.cos(a)[..., None, None]
    out: Floats = _EYE3 + s * kx + (1.0 - c) * kx2
    return out


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


@lru_cache(maxsize=64)
def _cross_matrices(x: float, y: float, z: float) -> tuple[Floats, Floats]:
    """The cross-product matrix K of the axis (x, y, z) and K @ K, read-only: a settle turns
    about one push many times."""
    kx = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    kx2 = kx @ kx
    kx.flags.writeable = kx2.flags.writeable = False
    return kx, kx2


def pose_from(rotation: Floats, translation: Floats) -> Pose:
    """(4, 4) pose from a (3, 3) rotation and a (3,) translation in metres; or a stack of
    them, (..., 4, 4) from (..., 3, 3) and (..., 3)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    pose = np.zeros(rotation.shape[:-2] + (4, 4))
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = translation
    pose[..., 3, 3] = 1.0
    return pose


def carried(pose: Pose, from_attitude: Floats, attitude: Floats) -> Pose:
    """`pose` (4, 4), taken at the attitude `from_attitude` (3, 3), turned by the change of
    attitude to `attitude` (3, 3): the same pose relative to the joint. Stacks of poses and
    attitudes ((..., 4, 4), (..., 3, 3)) give the stack of each one's, bit for bit."""
    turn = attitude @ np.swapaxes(from_attitude, -1, -2)
    return pose_from(turn @ pose[..., :3, :3], (turn @ pose[..., :3, 3, None])[..., 0])


def rotation_angle(a: Floats, b: Floats) -> float:
    """Angle (rad) of the rotation taking (3, 3) rotation `a` to `b` (scipy's Rotation:
    accurate near 0, where the arccos of the trace loses half the digits)."""
    # scipy.spatial costs about half a second of start-up, which the node and the table
    # commands (they never call this) do without
    from scipy.spatial.transform import Rotation
    return float(Rotation.from_matrix(np.asarray(a).T @ np.asarray(b)).magnitude())


def quat_angles(a: Floats, b: Floats) -> Floats:
    """Angles (rad) of the rotations between unit quaternions `a` and `b` (..., 4), each
    pair's (either sign of a quaternion is the same rotation)."""
    dot = np.clip(np.abs(np.sum(np.asarray(a) * np.asarray(b), axis=-1)), 0.0, 1.0)
    out: Floats = 2.0 * np.arccos(dot)
    return out


def quat_from_matrix(rotation: Floats) -> Floats:
    """Unit quaternions (x, y, z, w), w >= 0, of rotation matrices (..., 3, 3)."""
    r = np.asarray(rotation, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Each of the four candidates is well conditioned where its component is largest.
    cand = np.stack([
        np.stack([1 + m00 - m11 - m22, r[..., 1, 0] + r[..., 0, 1],
                  r[..., 0, 2] + r[..., 2, 0], r[..., 2, 1] - r[..., 1, 2]], -1),
        np.stack([r[..., 1, 0] + r[..., 0, 1], 1 - m00 + m11 - m22,
                  r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0]], -1),
        np.stack([r[..., 0, 2] + r[..., 2, 0], r[..., 2, 1] + r[..., 1, 2],
                  1 - m00 - m11 + m22, r[..., 1, 0] - r[..., 0, 1]], -1),
        np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                  r[..., 1, 0] - r[..., 0, 1], 1 + m00 + m11 + m22], -1),
    ], -2)                                                          # (..., 4, 4)
    pick = np.argmax(np.stack([m00, m11, m22, m00 + m11 + m22], -1), axis=-1)
    q = np.take_along_axis(cand, pick[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    out: Floats = np.where(q[..., 3:4] < 0.0, -q, q)
    return out


def matrix_from_quat(quat_xyzw: Floats) -> Floats:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in (x, y, z, w) order.

    The quaternion is normalised first; callers validate user input beforehand.
    """
    q = np.asarray(quat_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


@dataclass(frozen=True, slots=True, eq=False)
class KneeAxes:
    """The three attitude axes of a joint, unit vectors in the reference frame at neutral.

    Patent: X flexion, Z varus, Y long axis. The TKA knee frame (X anterior, Y superior,
    Z lateral) therefore uses flexion = Z, varus = X, long = Y.
    """

    flexion: Vec3
    varus: Vec3
    long: Vec3

    @classmethod
    def from_vectors(cls, flexion: ArrayLike, varus: ArrayLike, long: ArrayLike) -> KneeAxes:
        """Normalise and check three axes.

        Raises:
            ConfigError: an axis is zero, or two axes are not orthogonal.
        """
        f, v = unit(flexion, 'flexion axis'), unit(varus, 'varus axis')
        l_ = unit(long, 'long axis')
        for (na, a), (nb, b) in (((('flexion', f), ('varus', v))), (('flexion', f), ('long', l_)),
                                 (('varus', v), ('long', l_))):
            if abs(float(a @ b)) > TOL.orthogonal:
                raise ConfigError(f'{na} axis {a.round(4).tolist()} and {nb} axis '
                                  f'{b.round(4).tolist()} are not orthogonal '
                                  f'(cos = {float(a @ b):.3f}); give three perpendicular axes')
        return cls(f, v, l_)

    def _basis(self) -> tuple[Floats, float]:
        """Right-handed basis (3, 3) [flexion, varus, ±long] and the sign applied to long."""
        sign = 1.0 if float(np.cross(self.flexion, self.varus) @ self.long) > 0 else -1.0
        return np.stack([self.flexion, self.varus, sign * self.long], axis=1), sign

    def orientation(self, flexion_rad: float | Floats, varus_rad: float | Floats,
                    rotation_rad: float | Floats = 0.0) -> Floats:
        """R = Rot(flexion) @ Rot(varus) @ Rot(long, rotation): (3, 3) or (n, 3, 3)."""
        return (rotation_about(self.flexion, flexion_rad)
                @ rotation_about(self.varus, varus_rad)
                @ rotation_about(self.long, rotation_rad))

    def decompose(self, rotation: Floats) -> tuple[Floats, Floats, Floats]:
        """Inverse of `orientation`: (flexion, varus, rotation) in rad from (..., 3, 3).

        Varus is returned in [-pi/2, pi/2]; near varus = ±pi/2 flexion and rotation are
        not separable (gimbal lock), far outside any knee's range.
        """
        basis, sign = self._basis()
        r = basis.T @ np.asarray(rotation, dtype=np.float64) @ basis   # = Rx(a) Ry(b) Rz(c)
        flexion = np.arctan2(-r[..., 1, 2], r[..., 2, 2])
        varus = np.arcsin(np.clip(r[..., 0, 2], -1.0, 1.0))
        spin = np.arctan2(-r[..., 0, 1], r[..., 0, 0]) * sign
        return flexion, varus, spin
