"""The pose table: settled poses over a (flexion, varus) grid, its file, and interpolation.

File (DESIGN.md "Table file"): one `.npz` loaded with allow_pickle=False holding
`flexion` [F], `varus` [V] (rad, strictly ascending), `position` [B,F,V,3] (m, reference
frame), `orientation` [B,F,V,4] (x, y, z, w), `converged` [B,F,V] bool, `iterations`
[B,F,V] int, and `metadata`, a JSON string stored as a 0-d unicode array (see
`METADATA_KEYS`). Nothing else is in the file.

`arrays_sha256` (in the metadata) is the SHA-256 of, for each array in `ARRAY_NAMES` order,
the UTF-8 line `'<name> <dtype> <d0>x<d1>x...\\n'` followed by the array's C-order bytes,
where the array is first cast to its canonical dtype (`<f8` for the four float arrays, `|b1`
for `converged`, `<i8` for `iterations`). It covers the arrays only: the metadata itself is
protected against accidental damage by the zip's CRC-32, and a deliberate edit of it (say,
renaming a frame) keeps the table valid.

Interpolation (DESIGN.md "Interpolation") is bilinear in (flexion, varus) on the possibly
non-uniform grid: positions linearly, orientations by a normalised bilinear blend of the four
corner quaternions after aligning each to the first corner's hemisphere. Everything that does
not depend on the query (node tuples, hemisphere signs per cell, non-converged nodes) is
precomputed once per table as plain Python objects, and one query is plain Python + `math`:
about 9 us median for a 91 x 21 x 2-body table on the 2-core dev machine, against about 20 us
for the same query written with numpy (benchmarks/bench_interp.py).
"""
from __future__ import annotations

from bisect import bisect_right
import csv
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
import hashlib
import io
import json
import math
from pathlib import Path
from typing import Any, BinaryIO, Literal
import zipfile
import zlib

import numpy as np

from . import kneeseat_version
from .errors import ConfigError, KneeseatError, MeshError, OutOfRangeError, TableError
from .files import atomic_write, file_sha256
from .geometry import KneeAxes, matrix_from_quat, TOL
from .status import Status, STATUS_NAMES
from .typed import Floats

__all__ = ['SCHEMA', 'SUPPORTED_SCHEMAS', 'ARRAY_NAMES', 'METADATA_KEYS', 'PoseTable', 'Lookup',
           'write_table', 'read_table', 'with_hash', 'arrays_sha256',
           'describe', 'status_map', 'lookup_json', 'export_csv', 'CSV_COLUMNS', 'mesh_entries']

SCHEMA = 'kneeseat.table/1'
SUPPORTED_SCHEMAS = (SCHEMA,)

# metadata JSON (a dict):
#   schema: SCHEMA
#   kneeseat_version: str
#   reference: {"name": str, "frame": str, "mesh": str (path), "mesh_sha256": str}
#   bodies: [{"name": str, "frame": str, "mesh": str, "mesh_sha256": str,
#             "display_mesh": str | null}, ...]          (order = axis B of the arrays)
#   (since multi-mesh bodies, each reference/body entry also has "meshes" and
#    "display_meshes": [{"path": str, "sha256": str}, ...], every collision and display
#    mesh; "mesh"/"mesh_sha256" are then the first collision mesh. Older tables lack them.)
#   axes: {"flexion": [3], "varus": [3], "long": [3]}   (unit, reference frame)
#   config: the full knee config as a dict
#   settle: the settle parameters as a dict
#   arrays_sha256: hex SHA-256 over the arrays (checked on load)
#   built: ISO 8601 UTC build time
#   summary: {"cells": int, "converged": int, "wall_s": float, "collision_checks": int}
METADATA_KEYS = ('schema', 'kneeseat_version', 'reference', 'bodies', 'axes', 'config',
                 'settle', 'arrays_sha256', 'built', 'summary')
# Keys without which a table cannot be served; the others are provenance (shown if present).
_REQUIRED_KEYS = ('schema', 'reference', 'bodies', 'axes')

ARRAY_NAMES = ('flexion', 'varus', 'position', 'orientation', 'converged', 'iterations')
# canonical dtype of each array (file and hash)
_DTYPES = {'flexion': np.dtype('<f8'), 'varus': np.dtype('<f8'), 'position': np.dtype('<f8'),
           'orientation': np.dtype('<f8'), 'converged': np.dtype('|b1'),
           'iterations': np.dtype('<i8')}
_KINDS = {'flexion': 'f', 'varus': 'f', 'position': 'f', 'orientation': 'f', 'converged': 'b',
          'iterations': 'iu'}

CSV_COLUMNS = ('body', 'flexion_deg', 'varus_deg', 'x_m', 'y_m', 'z_m', 'flexion_rot_deg',
               'varus_rot_deg', 'long_rot_deg', 'converged', 'iterations')

_REBUILD = 'rebuild it with `kneeseat build`'
# A blend whose norm is this close to 1 is returned as is, so that a grid node returns its
# stored quaternion bit for bit (renormalising would change the last bit of a unit quaternion).
_UNIT_AS_IS = 4.0 * float(np.finfo(np.float64).eps)


@dataclass(frozen=True, slots=True, eq=False)
class Lookup:
    """One interpolated answer, one row per moving body (order of `PoseTable.bodies`)."""

    position_m: Floats          # (B, 3) m, reference frame
    orientation_xyzw: Floats    # (B, 4) unit, w >= 0
    clamped: bool               # the request lay outside the grid and was clamped
    nonconverged: Floats        # (B,) bool: a non-converged cell contributed to that body


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
        arrays = _check_arrays(_table_arrays(table), nbodies, 'cannot interpolate pose table')
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
    converged: Floats           # (B, F, V) bool
    iterations: Floats          # (B, F, V) int
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

    @property
    def status(self) -> np.ndarray:
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
            KneeseatError: an angle is NaN or infinite.
            ConfigError: `out_of_range` is neither 'clamp' nor 'drop'.
            OutOfRangeError: outside the grid and `out_of_range` is 'drop'.
            TableError: (first call only) the arrays are not a valid table.
        """
        g = self._grid
        if g is None:
            g = _grid_of(self)
        f, v = float(flexion_rad), float(varus_rad)
        if not (math.isfinite(f) and math.isfinite(v)):
            raise KneeseatError(f'pose table lookup at flexion={f} rad, varus={v} rad: angles '
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


# ----------------------------------------------------------------------------- hashing

def _canonical(name: str, value: Any) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(value).astype(_DTYPES[name], copy=False))


def arrays_sha256(table: PoseTable) -> str:
    """SHA-256 (hex) of the table's six arrays, as defined in this module's docstring."""
    return _hash_arrays(_table_arrays(table))


def _hash_arrays(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in ARRAY_NAMES:
        a = _canonical(name, arrays[name])
        h.update(f'{name} {a.dtype.str} {"x".join(map(str, a.shape))}\n'.encode())
        h.update(a.tobytes(order='C'))
    return h.hexdigest()


def _table_arrays(table: PoseTable) -> dict[str, Any]:
    return {'flexion': table.flexion_rad, 'varus': table.varus_rad,
            'position': table.position_m, 'orientation': table.orientation_xyzw,
            'converged': table.converged, 'iterations': table.iterations}


# -------------------------------------------------------------------------- validation

def _check_arrays(arrays: dict[str, Any], nbodies: int, where: str) -> dict[str, np.ndarray]:
    """Check kinds, shapes and values; return the arrays in their canonical dtypes."""
    out: dict[str, np.ndarray] = {}
    for name in ARRAY_NAMES:
        a = np.asarray(arrays[name])
        if a.dtype.kind not in _KINDS[name] or (_KINDS[name] == 'f' and a.dtype.itemsize != 8):
            want = {'f': 'float64', 'b': 'bool', 'iu': 'integer'}[_KINDS[name]]
            raise TableError(f'{where}: array {name!r} has dtype {a.dtype}, expected {want}; '
                             f'{_REBUILD}')
        out[name] = _canonical(name, a)
    fx, vx = out['flexion'], out['varus']
    for name, g in (('flexion', fx), ('varus', vx)):
        if g.ndim != 1 or g.size == 0:
            raise TableError(f'{where}: grid {name!r} has shape {g.shape}, expected a non-empty '
                             f'1-D array (rad); {_REBUILD}')
    grid = (nbodies, fx.size, vx.size)
    for name, tail in (('position', (3,)), ('orientation', (4,)), ('converged', ()),
                       ('iterations', ())):
        if out[name].shape != grid + tail:
            raise TableError(f'{where}: array {name!r} has shape {out[name].shape}, expected '
                             f'{grid + tail} (bodies, flexion, varus{", " if tail else ""}'
                             f'{tail[0] if tail else ""}); {_REBUILD}')
    for name in ('flexion', 'varus', 'position', 'orientation'):
        bad = ~np.isfinite(out[name])
        if bad.any():
            raise TableError(f'{where}: array {name!r} holds {int(bad.sum())} non-finite '
                             f'value(s) (first at index {np.argwhere(bad)[0].tolist()}); '
                             f'{_REBUILD}')
    for name, g in (('flexion', fx), ('varus', vx)):
        if g.size > 1 and not bool(np.all(np.diff(g) > 0.0)):
            k = int(np.argmax(np.diff(g) <= 0.0))
            raise TableError(f'{where}: grid {name!r} is not strictly ascending (index {k}: '
                             f'{g[k]:.6g} then {g[k + 1]:.6g} rad); {_REBUILD}')
    err = np.abs(np.linalg.norm(out['orientation'], axis=-1) - 1.0)
    if bool((err > TOL.unit_norm).any()):
        b, i, j = np.argwhere(err > TOL.unit_norm)[0].tolist()
        raise TableError(f'{where}: orientation of body {b} at flexion '
                         f'{math.degrees(fx[i]):.3f} deg, varus {math.degrees(vx[j]):.3f} deg '
                         f'is not a unit quaternion (|1 - |q|| = {err[b, i, j]:.2e}); '
                         f'{_REBUILD}')
    if bool((out['iterations'] < 0).any()):
        raise TableError(f'{where}: array "iterations" holds negative counts; {_REBUILD}')
    return out


def _check_metadata(meta: Any, where: str) -> None:
    """Check what serving needs: schema, bodies, reference and axes."""
    if not isinstance(meta, dict):
        raise TableError(f'{where}: metadata is a JSON {type(meta).__name__}, expected an '
                         f'object; {_REBUILD}')
    missing = [k for k in _REQUIRED_KEYS if k not in meta]
    if missing:
        raise TableError(f'{where}: metadata lacks {", ".join(missing)}; {_REBUILD}')
    bodies = meta['bodies']
    if (not isinstance(bodies, list) or not bodies
            or not all(isinstance(b, dict) and isinstance(b.get('name'), str) and b['name']
                       and isinstance(b.get('frame'), str) and b['frame'] for b in bodies)):
        raise TableError(f'{where}: metadata "bodies" must be a non-empty list of '
                         f'{{"name": str, "frame": str, ...}}; {_REBUILD}')
    names = [b['name'] for b in bodies]
    if len(set(names)) != len(names):
        raise TableError(f'{where}: metadata "bodies" repeats a name ({names}); give each '
                         f'moving body its own name and {_REBUILD}')
    ref = meta['reference']
    if not isinstance(ref, dict) or not isinstance(ref.get('frame'), str) or not ref['frame']:
        raise TableError(f'{where}: metadata "reference" must be {{"name": str, "frame": str, '
                         f'...}}; {_REBUILD}')
    axes = meta['axes']
    try:
        KneeAxes.from_vectors(axes['flexion'], axes['varus'], axes['long'])
    except (KeyError, TypeError, ValueError) as err:
        raise TableError(f'{where}: metadata "axes" must hold "flexion", "varus" and "long" '
                         f'3-vectors ({err!r}); {_REBUILD}') from None
    except ConfigError as err:
        raise TableError(f'{where}: metadata "axes": {err}') from None


def _check_schema(meta: Any, where: str) -> None:
    schema = meta.get('schema') if isinstance(meta, dict) else None
    if schema not in SUPPORTED_SCHEMAS:
        raise TableError(f'{where}: unknown table schema {schema!r}; this kneeseat reads '
                         f'{", ".join(SUPPORTED_SCHEMAS)}; rebuild the table with this '
                         'kneeseat or use the kneeseat version that wrote it')


# ------------------------------------------------------------------------------ writing

def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f'{type(value).__name__} is not JSON serialisable')


def with_hash(table: PoseTable) -> PoseTable:
    """A copy of `table` whose metadata is what `write_table` stores.

    The metadata gets `schema` = SCHEMA and `arrays_sha256`; `kneeseat_version` and `built`
    are filled in when absent. The arrays are shared, not copied.

    Raises:
        TableError: the arrays or metadata are not a valid table.
    """
    meta = dict(table.metadata)
    meta['schema'] = SCHEMA
    where = 'cannot write table'
    _check_metadata(meta, where)
    arrays = _check_arrays(_table_arrays(table), len(meta['bodies']), where)
    meta.setdefault('kneeseat_version', kneeseat_version())
    meta.setdefault('built', datetime.now(timezone.utc).isoformat(timespec='seconds'))
    meta['arrays_sha256'] = _hash_arrays(arrays)
    return replace(table, metadata=meta)


def write_table(path: Path, table: PoseTable) -> None:
    """Write `table` atomically (temp file + rename); fills in `arrays_sha256`.

    The file holds the metadata of `with_hash(table)`; the caller's `table` is unchanged.

    Args:
        path: destination `.npz` file; its directory must exist. Replaced if present.
        table: the table; arrays are stored in their canonical dtypes.
    Raises:
        TableError: the table is invalid (shapes, NaN, non-unit quaternions, metadata that
            is not JSON) or the file cannot be written (nothing is left behind).
    """
    path = Path(path)
    hashed = with_hash(table)
    try:
        text = json.dumps(hashed.metadata, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise TableError(f'cannot write table {path}: metadata is not JSON ({err}); store '
                         'only str, numbers, bools, None, lists and dicts in it') from None
    arrays = {name: _canonical(name, a) for name, a in _table_arrays(hashed).items()}
    arrays['metadata'] = np.array(text)

    def save(fh: BinaryIO) -> None:
        np.savez(fh, allow_pickle=False, **arrays)

    try:
        atomic_write(path, save)
    except OSError as err:
        raise TableError(f'cannot write table {path}: {err.strerror or err}; check that the '
                         'directory exists, is writable and has free space') from err


# ------------------------------------------------------------------------------ reading

_CORRUPT = (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError)


def read_table(path: Path, meshes: dict[str, Any] | None = None) -> PoseTable:
    """Load and verify a table file.

    Args:
        path: a `.npz` written by `write_table`.
        meshes: optional body name -> mesh path, or list of paths for a body made of
            several meshes (the reference body's name is accepted too); each file's SHA-256
            must match the one recorded in the metadata.
    Returns:
        The table, arrays read-only, interpolation data precomputed.
    Raises:
        TableError: missing, unreadable, truncated, tampered (hash), unknown schema,
            wrong array shapes, or built from other meshes.
        MeshError: a file given in `meshes` cannot be read.
    """
    path = Path(path)
    where = f'table file {path}'
    if not path.exists():
        raise TableError(f'{where} not found; check the path or build one with '
                         '`kneeseat build`')
    if not path.is_file():
        raise TableError(f'{where} is not a regular file; give the path of a .npz table')
    try:
        npz = np.load(path, allow_pickle=False)
    except PermissionError:
        raise TableError(f'{where} cannot be read (permission denied); check its '
                         'permissions') from None
    except _CORRUPT as err:
        raise TableError(f'{where} is not a readable table (.npz): {err}; it is truncated, '
                         f'corrupt or another kind of file; {_REBUILD}') from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise TableError(f'{where} holds a single array, not a table (.npz); {_REBUILD}')
    with npz:
        names = set(npz.files)
        if 'metadata' not in names:
            raise TableError(f'{where} has no metadata array; it is not a kneeseat table; '
                             f'{_REBUILD}')
        raw = _read_member(npz, 'metadata', where)
        if raw.dtype.kind != 'U' or raw.shape != ():
            raise TableError(f'{where}: metadata is a {raw.dtype} array of shape {raw.shape}, '
                             f'expected a JSON string; {_REBUILD}')
        try:
            meta = json.loads(str(raw[()]))
        except ValueError as err:
            raise TableError(f'{where}: metadata is not valid JSON ({err}); the file is '
                             f'corrupt or modified; {_REBUILD}') from None
        _check_schema(meta, where)
        missing = [n for n in ARRAY_NAMES if n not in names]
        extra = sorted(names - set(ARRAY_NAMES) - {'metadata'})
        if missing or extra:
            what = '; '.join(([f'missing {", ".join(missing)}'] if missing else [])
                             + ([f'unexpected {", ".join(extra)}'] if extra else []))
            raise TableError(f'{where}: arrays {what}; not a {SCHEMA} table; {_REBUILD}')
        loaded = {n: _read_member(npz, n, where) for n in ARRAY_NAMES}
    _check_metadata(meta, where)
    stored = meta.get('arrays_sha256')
    if not isinstance(stored, str):
        raise TableError(f'{where}: metadata has no arrays_sha256; {_REBUILD}')
    nbodies = len(meta['bodies'])
    for name in ('position', 'orientation', 'converged', 'iterations'):
        if loaded[name].ndim < 1 or loaded[name].shape[0] != nbodies:
            raise TableError(f'{where}: array {name!r} has shape {loaded[name].shape} but the '
                             f'metadata lists {nbodies} bodies; {_REBUILD}')
    arrays = _check_arrays(loaded, nbodies, where)
    actual = _hash_arrays(arrays)
    if actual != stored:
        raise TableError(f'{where}: arrays do not match their SHA-256 (stored {stored[:12]}, '
                         f'computed {actual[:12]}): corrupt or modified; {_REBUILD}')
    if meshes:
        _check_meshes(meta, meshes, where)
    for a in arrays.values():
        a.flags.writeable = False
    table = PoseTable(arrays['flexion'], arrays['varus'], arrays['position'],
                      arrays['orientation'], arrays['converged'], arrays['iterations'], meta)
    _grid_of(table)
    return table


def _read_member(npz: Any, name: str, where: str) -> np.ndarray:
    try:
        return np.asarray(npz[name])
    except _CORRUPT as err:
        raise TableError(f'{where} is corrupt (array {name!r}: {err}); {_REBUILD}') from None


def mesh_entries(entry: dict[str, Any]) -> list[tuple[str, str]]:
    """(path, sha256) of every collision mesh of a metadata body or reference entry.

    Tables written before multi-mesh bodies have only `mesh`/`mesh_sha256`.
    """
    listed = entry.get('meshes')
    if isinstance(listed, list) and listed:
        return [(str(m.get('path', '?')), str(m.get('sha256') or '')) for m in listed
                if isinstance(m, dict)]
    return [(str(entry.get('mesh', '?')), str(entry.get('mesh_sha256') or ''))]


def _check_meshes(meta: dict[str, Any], meshes: dict[str, Any], where: str) -> None:
    entries = {b['name']: b for b in meta['bodies']}
    ref = meta['reference']
    if isinstance(ref.get('name'), str):
        entries.setdefault(ref['name'], ref)
    for name, given in meshes.items():
        entry = entries.get(name)
        if entry is None:
            raise TableError(f'{where} has no body named {name!r} (bodies: '
                             f'{", ".join(entries)}); check the mesh names you pass')
        files = list(given) if isinstance(given, (list, tuple)) else [given]
        recorded = mesh_entries(entry)
        if len(files) != len(recorded):
            raise TableError(f'{where} was built from {len(recorded)} mesh(es) for {name!r}, '
                             f'{len(files)} given; pass the ones it was built from, in order')
        for mesh, (built_from, want) in zip(files, recorded):
            if not want:
                raise TableError(f'{where} records no SHA-256 for the mesh of {name!r}, so '
                                 f'it cannot be checked; {_REBUILD}')
            try:
                got = file_sha256(Path(mesh))
            except OSError as err:
                raise MeshError(f'mesh file {mesh} for {name!r} cannot be read '
                                f'({err.strerror or err}); check the path') from None
            if got != want:
                raise TableError(f'{where} was built from other meshes: {name!r} mesh {mesh} '
                                 f'has SHA-256 {got[:12]}, the table expects {want[:12]} '
                                 f'(built from {built_from}); rebuild the table from these '
                                 'meshes or pass the ones it was built from')


# ------------------------------------------------------------------- describe / export

def _grid_text(values_rad: Floats) -> str:
    deg = np.degrees(np.asarray(values_rad, dtype=np.float64))
    if deg.size == 1:
        return f'{deg[0]:g} deg (1 value)'
    steps = np.diff(deg)
    if np.allclose(steps, steps[0], rtol=1e-9, atol=1e-9):
        step = f'step {steps[0]:g}'
    else:
        step = f'non-uniform steps {steps.min():g} to {steps.max():g}'
    return f'{deg[0]:g} to {deg[-1]:g} deg, {step}, {deg.size} values'


def describe(table: PoseTable) -> str:
    """Human summary of a table for `kneeseat info` (several lines, no trailing newline)."""
    meta = table.metadata
    ref = meta.get('reference', {})
    lines = [f'schema:     {meta.get("schema", "?")} '
             f'(kneeseat {meta.get("kneeseat_version", "?")})',
             f'built:      {meta.get("built", "?")}',
             f'arrays:     sha256 {str(meta.get("arrays_sha256", "?"))[:12]}',
             f'reference:  {ref.get("name", "?")} (frame {ref.get("frame", "?")}, '
             f'{_meshes_text(ref)})',
             f'flexion:    {_grid_text(table.flexion_rad)}',
             f'varus:      {_grid_text(table.varus_rad)}']
    axes = meta.get('axes')
    if isinstance(axes, dict):
        lines.append('axes:       ' + ', '.join(
            f'{k} {np.round(np.asarray(axes[k], dtype=float), 4).tolist()}'
            for k in ('flexion', 'varus', 'long') if k in axes))
    lines.append(f'bodies:     {len(table.bodies)}')
    conv = np.asarray(table.converged, dtype=bool)
    iters = np.asarray(table.iterations)
    for b, body in enumerate(meta['bodies']):
        c = conv[b]
        lines.append(f'  {body["name"]}: frame {body["frame"]}, {_meshes_text(body)}')
        lines.append(f'    converged {100.0 * c.mean():.1f}% ({int(c.sum())}/{c.size}), '
                     f'iterations median {float(np.median(iters[b])):g} max {int(iters[b].max())}')
        backed = _mapping(_mapping(meta.get('backed_out')).get(body['name']))
        if backed.get('cells'):
            lines.append(f'    start in collision (backed out along the push) at '
                         f'{backed["cells"]} cells, up to {backed.get("max_mm", "?")} mm')
    settle = meta.get('settle')
    if isinstance(settle, dict) and settle:
        lines.append('settle:     ' + ', '.join(f'{k}={v}' for k, v in settle.items()))
    summary = meta.get('summary')
    if isinstance(summary, dict) and summary:
        lines.append('summary:    ' + ', '.join(f'{k}={v}' for k, v in summary.items()))
    lines += _status_lines(table) + _continuity_lines(meta.get('continuity'))
    return '\n'.join(lines)


def _status_lines(table: PoseTable, listed: int = 5) -> list[str]:
    """Cells by how their settle ended; the first few cells that did not converge."""
    codes, conv = table.status, np.asarray(table.converged, dtype=bool)
    deg_f, deg_v = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
    lines = ['cells:']
    for b, name in enumerate(table.bodies):
        counts = np.bincount(codes[b].ravel(), minlength=len(STATUS_NAMES))
        lines.append(f'  {name}: ' + ', '.join(f'{int(n)} {STATUS_NAMES.get(k, str(k))}'
                                               for k, n in enumerate(counts) if n))
        bad = np.argwhere(~conv[b])
        for i, j in bad[:listed]:
            lines.append(f'    not converged at flexion {deg_f[i]:g} varus {deg_v[j]:g}: '
                         f'{STATUS_NAMES.get(int(codes[b, i, j]), "?")}')
        if len(bad) > listed:
            lines.append(f'    ... and {len(bad) - listed} more (kneeseat info --map)')
    return lines


def _continuity_lines(cont: Any, listed: int = 5) -> list[str]:
    """The continuity summary a build stored (kneeseat_core.continuity)."""
    if not isinstance(cont, dict) or not isinstance(cont.get('bodies'), dict):
        return []

    def between(pair: Any) -> str:
        if not pair:
            return ''
        (fa, va), (fb, vb) = pair
        return f' (flexion {fa:g} varus {va:g} -> flexion {fb:g} varus {vb:g})'

    lines = [f'continuity: neighbour steps, bound {cont.get("bound_mm", "?")} mm / '
             f'{cont.get("bound_deg", "?")} deg']
    for name, entry in cont['bodies'].items():
        pos, rot = entry.get('max_position_mm', {}), entry.get('max_rotation_deg', {})
        over = entry.get('pairs_over_bound', {})
        lines.append(f'  {name}: largest {pos.get("value", 0):.3f} mm{between(pos.get("between"))}'
                     f', {rot.get("value", 0):.3f} deg{between(rot.get("between"))}; pairs over '
                     f'the bound: flexion {over.get("flexion", 0)}, varus {over.get("varus", 0)}')
    changes = cont.get('branch_changes') or []
    lines.append(f'  branch changes (pairs over the bound, both cells at rest): {len(changes)}')
    for change in changes[:listed]:
        lines.append(f'    {change["body"]}{between(change["between"])}: '
                     f'{change["position_mm"]:.3f} mm, {change["rotation_deg"]:.3f} deg')
    if len(changes) > listed:
        lines.append(f'    ... and {len(changes) - listed} more (in the metadata)')
    return lines


def status_map(table: PoseTable) -> str:
    """A character map of every body's cells (rows flexion, columns varus) by status."""
    marks = {Status.REST: '.', Status.CONSTRAINED: 'c', Status.ENVELOPE: 'E', Status.LOST: 'L',
             Status.CAP: 'I', Status.WEDGED: 'W', Status.FAILED: 'F', Status.UNKNOWN: '?'}
    codes = table.status
    deg_f, deg_v = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
    legend = ', '.join(f'{m} {STATUS_NAMES[k]}' for k, m in marks.items())
    lines = [f'map: rows flexion, columns varus {deg_v[0]:g} to {deg_v[-1]:g} deg; {legend}']
    for b, name in enumerate(table.bodies):
        lines.append(f'{name}:')
        for i in range(codes.shape[1]):
            lines.append(f'{deg_f[i]:8g} ' + ''.join(marks.get(int(c), '?') for c in codes[b, i]))
    return '\n'.join(lines)


def _mapping(value: Any) -> dict[str, Any]:
    """`value` if it is a dict, else {} (optional metadata written by newer builds)."""
    return value if isinstance(value, dict) else {}


def _meshes_text(entry: dict[str, Any]) -> str:
    """'mesh PATH (sha256 HEX)' or 'meshes A (sha256 ..), B (..)' of a metadata entry."""
    files = mesh_entries(entry)
    text = ', '.join(f'{path} (sha256 {sha[:12] or "?"})' for path, sha in files)
    return f'mesh{"es" if len(files) > 1 else ""} {text}'


def lookup_json(table: PoseTable, lookup: Lookup, flexion_rad: float | None = None,
                varus_rad: float | None = None) -> dict[str, Any]:
    """JSON-ready dict of one lookup for `kneeseat lookup --json`.

    Shape: {"reference_frame", "table_sha256", "clamped", ["flexion_rad", "varus_rad"],
    "bodies": [{"name", "frame", "position" [3] m, "orientation" [x, y, z, w],
    "nonconverged"}]}. The request angles are included when given.
    """
    out: dict[str, Any] = {'reference_frame': table.reference_frame,
                           'table_sha256': table.metadata.get('arrays_sha256'),
                           'clamped': bool(lookup.clamped)}
    if flexion_rad is not None:
        out['flexion_rad'] = float(flexion_rad)
    if varus_rad is not None:
        out['varus_rad'] = float(varus_rad)
    out['bodies'] = [
        {'name': name, 'frame': frame, 'position': [float(x) for x in lookup.position_m[b]],
         'orientation': [float(x) for x in lookup.orientation_xyzw[b]],
         'nonconverged': bool(lookup.nonconverged[b])}
        for b, (name, frame) in enumerate(zip(table.bodies, table.body_frames))]
    return out


def export_csv(table: PoseTable, path: Path) -> None:
    """Write one CSV row per (body, flexion, varus), atomically.

    Columns `CSV_COLUMNS`: body, grid flexion and varus (deg), then the patent's six fields:
    the body's position x, y, z (m, reference frame) and its absolute orientation decomposed
    with the table's axes (`KneeAxes.decompose`) into angles about the flexion, varus and
    long axes (deg); then converged (true/false) and iterations.

    Raises:
        TableError: the file cannot be written (nothing is left behind).
    """
    path = Path(path)
    pos = np.asarray(table.position_m, dtype=np.float64)
    rot = matrix_from_quat(np.asarray(table.orientation_xyzw, dtype=np.float64))
    angles = np.degrees(np.stack(table.axes.decompose(rot), axis=-1))   # (B, F, V, 3)
    fdeg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    vdeg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    conv = np.asarray(table.converged, dtype=bool)
    iters = np.asarray(table.iterations)
    text = io.StringIO()
    writer = csv.writer(text, lineterminator='\n')
    writer.writerow(CSV_COLUMNS)
    for b, name in enumerate(table.bodies):
        for i, fd in enumerate(fdeg.tolist()):
            for j, vd in enumerate(vdeg.tolist()):
                writer.writerow([name, f'{fd:.12g}', f'{vd:.12g}',
                                 *(f'{x:.12g}' for x in pos[b, i, j].tolist()),
                                 *(f'{x:.12g}' for x in angles[b, i, j].tolist()),
                                 'true' if conv[b, i, j] else 'false', int(iters[b, i, j])])
    data = text.getvalue().encode()

    def save(fh: BinaryIO) -> None:
        fh.write(data)

    try:
        atomic_write(path, save)
    except OSError as err:
        raise TableError(f'cannot write CSV {path}: {err.strerror or err}; check that the '
                         'directory exists, is writable and has free space') from err
