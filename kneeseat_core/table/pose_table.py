"""The pose table: settled poses over a (flexion, varus) grid, and their interpolation.

A `PoseTable` holds, for every moving body and grid cell, the pose at which settling left
the body (its file format is `kneeseat_core.table.format`, reading and writing
`kneeseat_core.table.io`, reports `kneeseat_core.table.summary`).

Interpolation is bilinear in (flexion, varus) on the possibly non-uniform grid: positions
linearly, orientations by a normalised bilinear blend of the four corner quaternions after
aligning each to the first corner's hemisphere. A grid node returns its stored pose bit for
bit. Outside the grid a request is clamped to the nearest edge (and flagged) or refused;
an answer to which a non-converged cell contributed is flagged per body.

Why the lookup is plain Python: everything that does not depend on the query (node tuples,
hemisphere signs per cell, non-converged nodes) is precomputed once per table as plain
Python objects, and one query is plain Python + `math`: about 9 us median for a 91 x 21 x
2-body table on the 2-core dev machine, against about 20 us for the same query written with
numpy, whose per-call overhead outweighs arithmetic on a handful of numbers
(benchmarks/bench_interp.py). The node answers up to 2 kHz with it, so it stays one
function (see `PoseTable.interpolate`).
"""
from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass, field
import math
from typing import Any, Literal

import numpy as np

from kneeseat_core.errors import ConfigError, NonFiniteError, OutOfRangeError
from kneeseat_core.geometry import KneeAxes, TOL
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints
from .format import check_arrays, hash_arrays

__all__ = ['PoseTable', 'Lookup', 'arrays_sha256']

# A blend whose norm is this close to 1 is returned as is, so that a grid node returns its
# stored quaternion bit for bit (renormalising would change the last bit of a unit quaternion).
_UNIT_AS_IS = 4.0 * float(np.finfo(np.float64).eps)


@dataclass(frozen=True, slots=True, eq=False)
class Lookup:
    """One interpolated answer, one row per moving body (order of `PoseTable.bodies`)."""

    position_m: Floats          # (B, 3) m, reference frame
    orientation_xyzw: Floats    # (B, 4) unit, w >= 0
    clamped: bool               # the request lay outside the grid and was clamped
    nonconverged: Bools         # (B,): a non-converged cell contributed to that body


class _Grid:
    """Query-independent interpolation data of one table, as plain Python objects.

    Nodes are numbered k = i * V + j. For each cell (i, j) (i < max(F - 1, 1), same for j)
    the corners are k00 = k, k01 = k + dj, k10 = k + di, k11 = k + di + dj, where di = V and
    dj = 1 except along a grid axis of length 1 (then 0: the "cell" is a line or a point).
    """

    __slots__ = ('fx', 'vx', 'f_lo', 'f_hi', 'v_lo', 'v_hi', 'f_width', 'v_width', 'nf', 'nv',
                 'nvar', 'di', 'dj', 'nodes', 'signs', 'unconverged', 'nbodies')

    def __init__(self, table: PoseTable) -> None:
        nbodies = np.shape(table.position_m)[0] if np.ndim(table.position_m) else 0
        arrays = check_arrays(table.arrays(), nbodies, 'cannot interpolate pose table')
        fx, vx = arrays['flexion'], arrays['varus']
        pos, quat, conv = arrays['position'], arrays['orientation'], arrays['converged']
        nb, nfx, nvx = pos.shape[:3]
        self.fx, self.vx = fx.tolist(), vx.tolist()
        self.f_lo, self.f_hi = self.fx[0], self.fx[-1]
        self.v_lo, self.v_hi = self.vx[0], self.vx[-1]
        # width of each cell; a 1-long axis gets an infinite width so that u = 0 exactly
        self.f_width = np.diff(fx).tolist() or [math.inf]
        self.v_width = np.diff(vx).tolist() or [math.inf]
        self.nf, self.nv, self.nvar = max(nfx - 1, 1), max(nvx - 1, 1), nvx
        self.di, self.dj = (nvx if nfx > 1 else 0), (1 if nvx > 1 else 0)
        self.nbodies = nb
        node = np.concatenate([pos, quat], axis=-1).reshape(nb, nfx * nvx, 7)
        self.nodes = [[tuple(r) for r in body] for body in node.tolist()]
        # hemisphere signs of corners 01, 10, 11 relative to corner 00, per body and cell
        i0, j0 = np.arange(self.nf), np.arange(self.nv)
        i1, j1 = np.minimum(i0 + 1, nfx - 1), np.minimum(j0 + 1, nvx - 1)
        q00 = quat[:, i0][:, :, j0]
        corners = (quat[:, i0][:, :, j1], quat[:, i1][:, :, j0], quat[:, i1][:, :, j1])
        sign = np.stack([np.where(np.sum(q00 * qc, axis=-1) < 0.0, -1.0, 1.0)
                         for qc in corners], axis=-1).reshape(nb, self.nf * self.nv, 3)
        patterns: dict[tuple[float, ...], tuple[float, ...]] = {}
        self.signs = [[patterns.setdefault(t, t) for t in map(tuple, body)]
                      for body in sign.tolist()]
        self.unconverged = (None if bool(conv.all())
                            else [(~c).reshape(-1).tolist() for c in conv])


def _grid_of(table: PoseTable) -> _Grid:
    """The table's interpolation data, built (and the arrays checked) on first use.

    Raises:
        TableError: the arrays are not a valid table (shapes, NaN, grid, quaternions).
    """
    grid = table._grid
    if grid is None:
        grid = _Grid(table)
        object.__setattr__(table, '_grid', grid)
    return grid


@dataclass(frozen=True, slots=True, eq=False)
class PoseTable:
    """Settled poses of each moving body over the grid, plus provenance.

    The arrays must not be modified once the table is used: interpolation data derived from
    them is cached on the instance at the first `interpolate` call.
    """

    flexion_rad: Floats         # (F,) ascending
    varus_rad: Floats           # (V,) ascending
    position_m: Floats          # (B, F, V, 3)
    orientation_xyzw: Floats    # (B, F, V, 4)
    converged: Bools            # (B, F, V)
    iterations: Ints            # (B, F, V)
    metadata: dict[str, Any]
    _grid: _Grid | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def bodies(self) -> tuple[str, ...]:
        """Moving body names, in array order."""
        return tuple(b['name'] for b in self.metadata['bodies'])

    @property
    def body_frames(self) -> tuple[str, ...]:
        """ROS frame name of each moving body, in array order."""
        return tuple(b['frame'] for b in self.metadata['bodies'])

    @property
    def reference_frame(self) -> str:
        """ROS frame of the fixed reference body; every pose is expressed in it."""
        return str(self.metadata['reference']['frame'])

    @property
    def axes(self) -> KneeAxes:
        """The knee's attitude axes, used to turn a tracked orientation into angles."""
        a = self.metadata['axes']
        return KneeAxes.from_vectors(a['flexion'], a['varus'], a['long'])

    @property
    def sha256(self) -> str:
        """The arrays' SHA-256 (hex), as stored in the metadata."""
        return str(self.metadata['arrays_sha256'])

    def arrays(self) -> dict[str, Any]:
        """The six arrays by name (`table_format.ARRAY_NAMES`), as stored in the instance."""
        return {'flexion': self.flexion_rad, 'varus': self.varus_rad,
                'position': self.position_m, 'orientation': self.orientation_xyzw,
                'converged': self.converged, 'iterations': self.iterations}

    def prepare(self) -> None:
        """Check the arrays and build the interpolation data now, not at the first lookup.

        Raises:
            TableError: the arrays are not a valid table (shapes, NaN, grid, quaternions).
        """
        _grid_of(self)

    @property
    def status(self) -> Ints:
        """(B, F, V) int: how each cell's settle ended (`kneeseat_core.status.Status`).

        Read from the metadata; a table without codes (or with codes of another shape)
        gives REST for converged cells and UNKNOWN for the others.
        """
        conv = np.asarray(self.converged, dtype=bool)
        cells = self.metadata.get('cells')
        if isinstance(cells, dict):
            try:
                codes = np.asarray(cells.get('status'), dtype=np.int64)
            except (TypeError, ValueError):
                codes = None
            if codes is not None and codes.shape == conv.shape:
                return codes
        return np.where(conv, Status.REST, Status.UNKNOWN)

    def interpolate(self, flexion_rad: float, varus_rad: float,
                    out_of_range: Literal['clamp', 'drop'] = 'clamp') -> Lookup:
        """Bilinear pose of every body at (flexion, varus).

        Longer than 60 lines on purpose: this is the node's per-message lookup (up to 2 kHz),
        written as one function of plain Python because every helper call would add its
        overhead to a 9 us answer (module docstring; benchmarks/bench_interp.py).

        Positions are blended linearly; orientations by the normalised bilinear blend of the
        four corner quaternions, each first aligned to the hemisphere of the cell's first
        corner. A grid node returns that node's pose; a grid axis of length 1 accepts only its
        single value (anything else is out of range).

        Args:
            flexion_rad: flexion angle (rad), finite.
            varus_rad: varus angle (rad), finite.
            out_of_range: 'clamp' moves an outside request to the nearest grid edge and sets
                `Lookup.clamped`; 'drop' raises OutOfRangeError instead.
        Returns:
            The poses (B, 3) m and (B, 4) xyzw (w >= 0) in the reference frame, the clamped
            flag and, per body, whether a non-converged node had a non-zero weight.
        Raises:
            NonFiniteError: an angle is NaN or infinite.
            ConfigError: `out_of_range` is neither 'clamp' nor 'drop'.
            OutOfRangeError: outside the grid and `out_of_range` is 'drop'.
            TableError: (first call only) the arrays are not a valid table.
        """
        g = self._grid
        if g is None:
            g = _grid_of(self)
        f, v = float(flexion_rad), float(varus_rad)
        if not (math.isfinite(f) and math.isfinite(v)):
            raise NonFiniteError(f'pose table lookup at flexion={f} rad, varus={v} rad: angles '
                                 'must be finite; drop NaN/inf tracker samples before the lookup')
        if out_of_range != 'clamp' and out_of_range != 'drop':
            raise ConfigError(f'out_of_range={out_of_range!r} is not a policy; '
                              "use 'clamp' or 'drop'")
        clamped = False
        if f < g.f_lo or f > g.f_hi:
            if out_of_range == 'drop':
                raise OutOfRangeError('flexion', f, g.f_lo, g.f_hi)
            f, clamped = (g.f_lo if f < g.f_lo else g.f_hi), True
        if v < g.v_lo or v > g.v_hi:
            if out_of_range == 'drop':
                raise OutOfRangeError('varus', v, g.v_lo, g.v_hi)
            v, clamped = (g.v_lo if v < g.v_lo else g.v_hi), True
        i = bisect_right(g.fx, f) - 1
        if i >= g.nf:
            i = g.nf - 1
        j = bisect_right(g.vx, v) - 1
        if j >= g.nv:
            j = g.nv - 1
        u = (f - g.fx[i]) / g.f_width[i]
        t = (v - g.vx[j]) / g.v_width[j]
        a, b, c, d = (1.0 - u) * (1.0 - t), (1.0 - u) * t, u * (1.0 - t), u * t
        k00 = i * g.nvar + j
        k01, k10 = k00 + g.dj, k00 + g.di
        k11 = k10 + g.dj
        cell = i * g.nv + j
        positions, quats = [], []
        for nodes, signs in zip(g.nodes, g.signs):
            n00, n01, n10, n11 = nodes[k00], nodes[k01], nodes[k10], nodes[k11]
            positions.append([a * n00[0] + b * n01[0] + c * n10[0] + d * n11[0],
                              a * n00[1] + b * n01[1] + c * n10[1] + d * n11[1],
                              a * n00[2] + b * n01[2] + c * n10[2] + d * n11[2]])
            sb, sc, sd = signs[cell]
            qb, qc, qd = b * sb, c * sc, d * sd
            qx = a * n00[3] + qb * n01[3] + qc * n10[3] + qd * n11[3]
            qy = a * n00[4] + qb * n01[4] + qc * n10[4] + qd * n11[4]
            qz = a * n00[5] + qb * n01[5] + qc * n10[5] + qd * n11[5]
            qw = a * n00[6] + qb * n01[6] + qc * n10[6] + qd * n11[6]
            norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
            if norm < TOL.unit_norm:
                # corners nearly cancel (adjacent cells ~180 deg apart): take the heaviest one
                best = max(zip((a, b, c, d), (n00, n01, n10, n11)), key=lambda p: p[0])[1]
                qx, qy, qz, qw = best[3:]
                norm = 1.0
            s = 1.0 if abs(norm - 1.0) <= _UNIT_AS_IS else 1.0 / norm
            if qw < 0.0:
                s = -s
            quats.append([qx * s, qy * s, qz * s, qw * s])
        if g.unconverged is None:
            flags = [False] * g.nbodies
        else:
            flags = [(n[k00] and a != 0.0) or (n[k01] and b != 0.0) or (n[k10] and c != 0.0)
                     or (n[k11] and d != 0.0) for n in g.unconverged]
        return Lookup(np.array(positions), np.array(quats), clamped,
                      np.array(flags, dtype=bool))


def arrays_sha256(table: PoseTable) -> str:
    """SHA-256 (hex) of the table's six arrays, as defined in `kneeseat_core.table.format`."""
    return hash_arrays(table.arrays())
