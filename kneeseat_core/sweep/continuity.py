"""How smoothly a table's poses change between neighbouring cells, and where they jump.

A step is the difference between the poses of two cells adjacent along flexion or along
varus: the distance between the body's frame origins (m) and the angle between the two
orientations (rad) once each cell's commanded attitude is taken out (what the settle
turned, not the commanded 1 degree step; without the attitudes, the whole angle). A pair
over the bound (1 mm or 2 degrees) whose two cells are both at rest is a *branch change* -
the rest the settle proved on one side is not the one on the other - and is recorded in
the table's metadata, never passed over silently; a pair with a cell that did not
converge is a jump at a failure, reported with the failures.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from kneeseat_core.geometry import matrix_from_quat, quat_angles, quat_from_matrix
from kneeseat_core.typed import Bools, Floats

__all__ = ['BOUND_M', 'BOUND_RAD', 'neighbour_steps', 'continuity']

BOUND_M = 1e-3
BOUND_RAD = math.radians(2.0)


def neighbour_steps(position_m: Floats, orientation_xyzw: Floats,
                    attitudes: Floats | None = None) -> dict[str, tuple[Floats, Floats]]:
    """Steps between adjacent cells, per axis.

    Args:
        position_m: (B, F, V, 3).
        orientation_xyzw: (B, F, V, 4) unit quaternions.
        attitudes: (B, F, V, 3, 3) each cell's commanded attitude, taken out of the
            rotation step (None: the whole angle between the orientations).
    Returns:
        {'flexion': (position (B, F-1, V) m, rotation (B, F-1, V) rad),
         'varus': (position (B, F, V-1), rotation (B, F, V-1))}.
    """
    p = np.asarray(position_m, dtype=np.float64)
    q = np.asarray(orientation_xyzw, dtype=np.float64)
    if attitudes is not None:        # the settled part: attitude^T @ orientation
        rot = np.swapaxes(np.asarray(attitudes), -1, -2) @ matrix_from_quat(q)
        q = quat_from_matrix(rot)
    out = {}
    for name, axis in (('flexion', 1), ('varus', 2)):
        dp = np.linalg.norm(np.diff(p, axis=axis), axis=-1)
        lo = np.take(q, range(q.shape[axis] - 1), axis=axis)
        hi = np.take(q, range(1, q.shape[axis]), axis=axis)
        out[name] = (dp, quat_angles(lo, hi))
    return out


def continuity(position_m: Floats, orientation_xyzw: Floats, converged: Bools,
               flexion_rad: Floats, varus_rad: Floats, bodies: Sequence[str],
               attitudes: Floats | None = None, bound_m: float = BOUND_M,
               bound_rad: float = BOUND_RAD) -> dict[str, Any]:
    """The continuity summary stored in a table's metadata (JSON-ready); `attitudes` as
    for `neighbour_steps`.

    Returns:
        {'bound_mm', 'bound_deg', 'bodies': {name: {'max_position_mm': {value, between},
        'max_rotation_deg': {...}, 'pairs_over_bound': {'flexion': n, 'varus': n}}},
        'branch_changes': [{'body', 'between': [[flexion_deg, varus_deg], [...]],
        'position_mm', 'rotation_deg'}]} where `between` names the two cells.
    """
    conv = np.asarray(converged, dtype=bool)
    deg_f, deg_v = np.degrees(flexion_rad), np.degrees(varus_rad)

    def cell(i: int, j: int) -> list[float]:
        return [round(float(deg_f[i]), 6), round(float(deg_v[j]), 6)]

    summary: dict[str, Any] = {'bound_mm': bound_m * 1e3, 'bound_deg': math.degrees(bound_rad),
                               'bodies': {}, 'branch_changes': []}
    steps = neighbour_steps(position_m, orientation_xyzw, attitudes)
    offsets = {'flexion': (1, 0), 'varus': (0, 1)}
    for b, name in enumerate(bodies):
        entry: dict[str, Any] = {'pairs_over_bound': {}}
        for key, unit_scale, label in (('position', 1e3, 'max_position_mm'),
                                       ('rotation', math.degrees(1.0), 'max_rotation_deg')):
            best: tuple[float, list[list[float]] | None] = (0.0, None)
            for axis, (dp, dr) in steps.items():
                values = (dp if key == 'position' else dr)[b]
                if values.size and float(values.max()) > best[0]:
                    i, j = np.unravel_index(int(np.argmax(values)), values.shape)
                    di, dj = offsets[axis]
                    best = (float(values.max()),
                            [cell(int(i), int(j)), cell(int(i) + di, int(j) + dj)])
            entry[label] = {'value': round(best[0] * unit_scale, 6), 'between': best[1]}
        for axis, (dp, dr) in steps.items():
            over = (dp[b] > bound_m) | (dr[b] > bound_rad)
            entry['pairs_over_bound'][axis] = int(over.sum())
            di, dj = offsets[axis]
            for i, j in np.argwhere(over):
                if conv[b, i, j] and conv[b, i + di, j + dj]:
                    summary['branch_changes'].append({
                        'body': name, 'between': [cell(i, j), cell(i + di, j + dj)],
                        'position_mm': round(float(dp[b, i, j]) * 1e3, 4),
                        'rotation_deg': round(math.degrees(float(dr[b, i, j])), 4)})
        summary['bodies'][name] = entry
    return summary
