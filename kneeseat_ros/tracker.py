"""Tracker mode without ROS: rigid transforms, the registration file, pairing by stamp.

A motion capture system tracks two rigid bodies (marker clusters), one on the thigh and one
on the shank, and publishes each one's pose in its world frame. The registration gives,
for each cluster, the pose of its bone's frame (the table's femur frame and tibia frame)
in the cluster's frame. With them the node computes

    world_T_femur = world_T_femur_cluster * femur_cluster_T_femur
    world_T_tibia = world_T_tibia_cluster * tibia_cluster_T_tibia
    (flexion, varus) = KneeAxes.decompose(rotation of femur_T_tibia)   [as the PoseStamped input]
    world_T_body = world_T_femur * table(flexion, varus)[body]        for every moving body

Rigid transforms are tuples `(px, py, pz, qx, qy, qz, qw)` (metres, unit quaternion) in
plain Python floats, composed by hand: one message needs a handful of them, and library
call overhead is far larger than the arithmetic (measured on the dev machine: `compose`
1.0 us against 43 us with scipy's `Rotation`, `relative_rotation` 0.5 us against 40 us;
the node answers up to 2 kHz).

Registration file (YAML), one entry per role, each either a quaternion and a translation or
a 4 x 4 homogeneous matrix (rows), metres:

    femur:                       # the femur's frame in the thigh cluster's frame
      translation: [0.0, -0.18, 0.02]
      rotation: [0.0, 0.0, 0.0, 1.0]        # x, y, z, w
    tibia:                       # the tibia's frame in the shank cluster's frame
      matrix: [[1, 0, 0, 0], [0, 1, 0, 0.15], [0, 0, 1, 0], [0, 0, 0, 1]]

Anything that is not a rigid transform (scale, shear, reflection, a non-unit quaternion,
a bottom row other than 0 0 0 1) is refused with the key named.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import yaml

from kneeseat_core.errors import ConfigError
from kneeseat_core.geometry import quat_from_matrix, TOL

__all__ = ['Rigid', 'compose', 'inverse', 'relative_rotation', 'Registration',
           'load_registration', 'Pairer', 'RIGID_TOL', 'ROLES']

Rigid = tuple[float, float, float, float, float, float, float]
# Orthonormality and unit-norm tolerance of a registration (`Tolerances.registration`).
RIGID_TOL = TOL.registration
ROLES = ('femur', 'tibia')
_T = TypeVar('_T')


def _qmul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def _rotate(q: tuple[float, ...], v: tuple[float, ...]) -> tuple[float, float, float]:
    x, y, z, w = q
    vx, vy, vz = v
    # t = 2 u x v;  v' = v + w t + u x t
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx))


def compose(a: Rigid, b: Rigid) -> Rigid:
    """a * b: the pose b (given in a's frame) expressed in a's parent frame; w >= 0."""
    px, py, pz = _rotate(a[3:], b[:3])
    qx, qy, qz, qw = _qmul(a[3:], b[3:])
    if qw < 0.0:
        qx, qy, qz, qw = -qx, -qy, -qz, -qw
    return (a[0] + px, a[1] + py, a[2] + pz, qx, qy, qz, qw)


def inverse(a: Rigid) -> Rigid:
    """The inverse transform of `a`."""
    conj = (-a[3], -a[4], -a[5], a[6])
    px, py, pz = _rotate(conj, a[:3])
    return (-px, -py, -pz, *conj)


def relative_rotation(a: Rigid, b: Rigid) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of b's orientation in a's frame (a and b in one frame)."""
    return _qmul((-a[3], -a[4], -a[5], a[6]), b[3:])


@dataclass(frozen=True, slots=True)
class Registration:
    """Pose of each bone's frame in its marker cluster's frame (metres, unit quaternions)."""

    femur: Rigid
    tibia: Rigid
    path: Path


def _floats(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        array = np.empty(0)
    if array.shape != shape or not np.all(np.isfinite(array)):
        dims = ' x '.join(map(str, shape))
        raise ConfigError(f'{where} must be {dims} finite numbers, got {value!r}')
    return array


def _rigid(entry: Any, where: str) -> Rigid:
    if not isinstance(entry, dict):
        raise ConfigError(f'{where} must be a mapping with translation and rotation, or '
                          'matrix')
    keys = set(entry)
    if keys == {'matrix'}:
        m = _floats(entry['matrix'], (4, 4), f'{where}.matrix')
        rot = m[:3, :3]
        ortho = float(np.abs(rot.T @ rot - np.eye(3)).max())
        det = float(np.linalg.det(rot))
        if ortho > RIGID_TOL or det < 0.0 or np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 0.0:
            raise ConfigError(
                f'{where}.matrix is not a rigid transform (|R^T R - I| = {ortho:.3g}, '
                f'det R = {det:.6g}, bottom row {m[3].tolist()}); give a rotation (orthonormal, '
                'det +1) and a translation in metres, bottom row 0 0 0 1, no scale or shear')
        q = quat_from_matrix(rot)
        t = m[:3, 3]
    elif keys == {'translation', 'rotation'}:
        t = _floats(entry['translation'], (3,), f'{where}.translation')
        q = _floats(entry['rotation'], (4,), f'{where}.rotation')
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > RIGID_TOL:
            raise ConfigError(f'{where}.rotation {q.tolist()} has norm {norm:.9g}, not 1 '
                              f'(tolerance {RIGID_TOL:g}); give a unit quaternion x, y, z, w')
        q = q / norm
    else:
        raise ConfigError(f'{where} has keys {sorted(keys)}; give either translation and '
                          'rotation (x, y, z, w) or matrix (4 x 4 rows), in metres')
    qx, qy, qz, qw = (float(c) for c in (q if q[3] >= 0.0 else -q))
    return (float(t[0]), float(t[1]), float(t[2]), qx, qy, qz, qw)


def load_registration(path: Path) -> Registration:
    """Read and check a registration file (see the module docstring for its format).

    Raises:
        ConfigError: the file is missing or not YAML, a role is missing or unknown, or an
            entry is not a rigid transform; the message names the file and the key.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding='utf-8'))
    except OSError as err:
        raise ConfigError(f'registration file {path}: {err.strerror}; give the YAML file '
                          'with the femur and tibia cluster-to-bone transforms') from None
    except yaml.YAMLError as err:
        line = getattr(getattr(err, 'problem_mark', None), 'line', None)
        where = f' (line {line + 1})' if line is not None else ''
        raise ConfigError(f'registration file {path} is not valid YAML{where}; fix the '
                          'syntax') from None
    if not isinstance(data, dict) or set(data) != set(ROLES):
        got = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f'registration file {path} must have exactly the keys femur and '
                          f'tibia, got {got}')
    return Registration(_rigid(data['femur'], f'{path}: femur'),
                        _rigid(data['tibia'], f'{path}: tibia'), path)


class Pairer(Generic[_T]):
    """Pairs femur and tibia samples by stamp: nearest within a tolerance, in time order.

    `add` takes one sample of one side and returns the pair it completes, if any. A sample
    waits for its partner until a sample of the other side arrives more than `tolerance_ns`
    later; then it can no longer pair (stamps grow on each side) and is counted as
    unpaired. A sample stamped at or before the last pair of its side arrived too late
    (out of order) and is counted as stale. Each side keeps at most `depth` samples.
    """

    def __init__(self, tolerance_ns: int, depth: int = 64) -> None:
        """Args: tolerance_ns: largest stamp difference of a pair (ns); depth: per side."""
        self.tolerance_ns = int(tolerance_ns)
        self._waiting: tuple[deque[tuple[int, _T]], deque[tuple[int, _T]]] = (
            deque(), deque())
        self._depth = depth
        self._last = [-1, -1]
        self.unpaired = 0
        self.stale = 0

    def add(self, side: int, stamp_ns: int, item: _T) -> tuple[_T, _T, int] | None:
        """Add a sample of side 0 (femur) or 1 (tibia).

        Returns:
            (femur item, tibia item, femur stamp in ns) when this sample completes a pair,
            else None.
        """
        if stamp_ns <= self._last[side]:
            self.stale += 1
            return None
        other = self._waiting[1 - side]
        # the other side's samples too old to pair with this one or any later one
        while other and other[0][0] < stamp_ns - self.tolerance_ns:
            other.popleft()
            self.unpaired += 1
        best = None
        for k, (stamp, _) in enumerate(other):
            if stamp - stamp_ns > self.tolerance_ns:
                break
            if best is None or abs(stamp - stamp_ns) < abs(other[best][0] - stamp_ns):
                best = k
        if best is None:
            mine = self._waiting[side]
            if len(mine) >= self._depth:
                mine.popleft()
                self.unpaired += 1
            mine.append((stamp_ns, item))
            return None
        for _ in range(best):
            other.popleft()
            self.unpaired += 1
        partner_stamp, partner = other.popleft()
        # this side's waiting samples are older than this one: they lost their chance
        mine = self._waiting[side]
        self.unpaired += len(mine)
        mine.clear()
        self._last[side], self._last[1 - side] = stamp_ns, partner_stamp
        if side == 0:
            return item, partner, stamp_ns
        return partner, item, partner_stamp

    def pending(self) -> int:
        """Samples waiting for a partner (both sides)."""
        return len(self._waiting[0]) + len(self._waiting[1])
