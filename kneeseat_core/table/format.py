"""The table file format: what a `.npz` table holds, its hash, and what makes it valid.

One `.npz`, loaded with allow_pickle=False, holding exactly these arrays (`ARRAY_NAMES`):
`flexion` [F] and `varus` [V] (rad, strictly ascending), `position` [B,F,V,3] (m, the
reference frame), `orientation` [B,F,V,4] (x, y, z, w), `converged` [B,F,V] bool,
`iterations` [B,F,V] int, and `metadata`, a JSON object stored as a 0-d unicode array.

Metadata keys. Needed to serve a table (`REQUIRED_KEYS`, checked by `check_metadata`):
  schema: SCHEMA ('kneeseat.table/1'; a reader refuses a schema it does not know)
  reference: {"name", "frame", "mesh", "mesh_sha256", "meshes", "display_mesh",
              "display_meshes"} of the fixed body
  bodies: [{"name", "frame", "mesh", "mesh_sha256", "meshes", "display_mesh",
            "display_meshes", "envelope_anchor"}, ...]   (order = axis B of the arrays)
  axes: {"flexion": [3], "varus": [3], "long": [3]}  (unit, orthogonal, reference frame)
`mesh`/`mesh_sha256` are the first collision mesh; `meshes` and `display_meshes` list every
collision and display mesh as [{"path", "sha256"}] (tables written before bodies of several
meshes lack them and still load: `mesh_entries`). `envelope_anchor` ({"flexion_deg",
"varus_deg", "position", "orientation"}) is the centre rest every cell's search envelope
was measured from. Provenance, shown when present:
  kneeseat_version, built (ISO 8601 UTC), arrays_sha256 (checked on load), name,
  config (the knee config as read, with a "resolved" part: absolute mesh paths, settle
  parameters, grid in degrees), settle (the settle parameters), summary ({"cells",
  "converged", "wall_s", "collision_checks"}, the queries of all settles, and "travels"
  and "fcl_queries": how many of them were exact travels and python-fcl queries; tables
  built before the exact travel have "ray_casts" instead; "scene_s", of "wall_s" the
  bodies and their hierarchies built before any chain, and "chains_s", the chains' own
  times summed over the workers, in tables built since they were recorded), failures (the first
  non-converged reasons),
  cells ({"status_names", "status"}: each cell's `kneeseat_core.status.Status` code),
  continuity (`kneeseat_core.sweep.continuity`), backed_out (per body: starts in collision).

`arrays_sha256` is the SHA-256 of, for each array in `ARRAY_NAMES` order, the UTF-8 line
`'<name> <dtype> <d0>x<d1>x...\\n'` followed by the array's C-order bytes, where the array is
first cast to its canonical dtype (`<f8` for the four float arrays, `|b1` for `converged`,
`<i8` for `iterations`). It covers the arrays only: the metadata itself is protected against
accidental damage by the zip's CRC-32, and a deliberate edit of it (say, renaming a frame)
keeps the table valid.
"""
from __future__ import annotations

from collections.abc import Mapping
import hashlib
import math
from typing import Any

import numpy as np

from kneeseat_core.errors import ConfigError, TableError
from kneeseat_core.geometry import KneeAxes, TOL

__all__ = ['SCHEMA', 'SUPPORTED_SCHEMAS', 'ARRAY_NAMES', 'REQUIRED_KEYS', 'REBUILD',
           'canonical', 'hash_arrays', 'check_arrays', 'check_metadata', 'check_schema',
           'mesh_entries', 'display_paths']

SCHEMA = 'kneeseat.table/1'
SUPPORTED_SCHEMAS = (SCHEMA,)
# Keys without which a table cannot be served; the others are provenance (shown if present).
REQUIRED_KEYS = ('schema', 'reference', 'bodies', 'axes')

ARRAY_NAMES = ('flexion', 'varus', 'position', 'orientation', 'converged', 'iterations')
# canonical dtype of each array (file and hash)
_DTYPES = {'flexion': np.dtype('<f8'), 'varus': np.dtype('<f8'), 'position': np.dtype('<f8'),
           'orientation': np.dtype('<f8'), 'converged': np.dtype('|b1'),
           'iterations': np.dtype('<i8')}
_KINDS = {'flexion': 'f', 'varus': 'f', 'position': 'f', 'orientation': 'f', 'converged': 'b',
          'iterations': 'iu'}

REBUILD = 'rebuild it with `kneeseat build`'


def canonical(name: str, value: Any) -> np.ndarray:
    """`value` as a C-contiguous array of the canonical dtype of array `name`."""
    return np.ascontiguousarray(np.asarray(value).astype(_DTYPES[name], copy=False))


def hash_arrays(arrays: dict[str, Any]) -> str:
    """`arrays_sha256` of the six arrays by name (module docstring)."""
    h = hashlib.sha256()
    for name in ARRAY_NAMES:
        a = canonical(name, arrays[name])
        h.update(f'{name} {a.dtype.str} {"x".join(map(str, a.shape))}\n'.encode())
        h.update(a.tobytes(order='C'))
    return h.hexdigest()


def check_arrays(arrays: dict[str, Any], nbodies: int, where: str) -> dict[str, np.ndarray]:
    """Check kinds, shapes and values; return the arrays in their canonical dtypes."""
    out: dict[str, np.ndarray] = {}
    for name in ARRAY_NAMES:
        a = np.asarray(arrays[name])
        if a.dtype.kind not in _KINDS[name] or (_KINDS[name] == 'f' and a.dtype.itemsize != 8):
            want = {'f': 'float64', 'b': 'bool', 'iu': 'integer'}[_KINDS[name]]
            raise TableError(f'{where}: array {name!r} has dtype {a.dtype}, expected {want}; '
                             f'{REBUILD}')
        out[name] = canonical(name, a)
    fx, vx = out['flexion'], out['varus']
    for name, g in (('flexion', fx), ('varus', vx)):
        if g.ndim != 1 or g.size == 0:
            raise TableError(f'{where}: grid {name!r} has shape {g.shape}, expected a non-empty '
                             f'1-D array (rad); {REBUILD}')
    grid = (nbodies, fx.size, vx.size)
    for name, tail in (('position', (3,)), ('orientation', (4,)), ('converged', ()),
                       ('iterations', ())):
        if out[name].shape != grid + tail:
            raise TableError(f'{where}: array {name!r} has shape {out[name].shape}, expected '
                             f'{grid + tail} (bodies, flexion, varus{", " if tail else ""}'
                             f'{tail[0] if tail else ""}); {REBUILD}')
    for name in ('flexion', 'varus', 'position', 'orientation'):
        bad = ~np.isfinite(out[name])
        if bad.any():
            raise TableError(f'{where}: array {name!r} holds {int(bad.sum())} non-finite '
                             f'value(s) (first at index {np.argwhere(bad)[0].tolist()}); '
                             f'{REBUILD}')
    for name, g in (('flexion', fx), ('varus', vx)):
        if g.size > 1 and not bool(np.all(np.diff(g) > 0.0)):
            k = int(np.argmax(np.diff(g) <= 0.0))
            raise TableError(f'{where}: grid {name!r} is not strictly ascending (index {k}: '
                             f'{g[k]:.6g} then {g[k + 1]:.6g} rad); {REBUILD}')
    err = np.abs(np.linalg.norm(out['orientation'], axis=-1) - 1.0)
    if bool((err > TOL.unit_norm).any()):
        b, i, j = np.argwhere(err > TOL.unit_norm)[0].tolist()
        raise TableError(f'{where}: orientation of body {b} at flexion '
                         f'{math.degrees(fx[i]):.3f} deg, varus {math.degrees(vx[j]):.3f} deg '
                         f'is not a unit quaternion (|1 - |q|| = {err[b, i, j]:.2e}); '
                         f'{REBUILD}')
    if bool((out['iterations'] < 0).any()):
        raise TableError(f'{where}: array "iterations" holds negative counts; {REBUILD}')
    return out


def check_metadata(meta: Any, where: str) -> None:
    """Check what serving needs: schema, bodies, reference and axes."""
    if not isinstance(meta, dict):
        raise TableError(f'{where}: metadata is a JSON {type(meta).__name__}, expected an '
                         f'object; {REBUILD}')
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise TableError(f'{where}: metadata lacks {", ".join(missing)}; {REBUILD}')
    bodies = meta['bodies']
    if (not isinstance(bodies, list) or not bodies
            or not all(isinstance(b, dict) and isinstance(b.get('name'), str) and b['name']
                       and isinstance(b.get('frame'), str) and b['frame'] for b in bodies)):
        raise TableError(f'{where}: metadata "bodies" must be a non-empty list of '
                         f'{{"name": str, "frame": str, ...}}; {REBUILD}')
    names = [b['name'] for b in bodies]
    if len(set(names)) != len(names):
        raise TableError(f'{where}: metadata "bodies" repeats a name ({names}); give each '
                         f'moving body its own name and {REBUILD}')
    ref = meta['reference']
    if not isinstance(ref, dict) or not isinstance(ref.get('frame'), str) or not ref['frame']:
        raise TableError(f'{where}: metadata "reference" must be {{"name": str, "frame": str, '
                         f'...}}; {REBUILD}')
    axes = meta['axes']
    try:
        KneeAxes.from_vectors(axes['flexion'], axes['varus'], axes['long'])
    except (KeyError, TypeError, ValueError) as err:
        raise TableError(f'{where}: metadata "axes" must hold "flexion", "varus" and "long" '
                         f'3-vectors ({err!r}); {REBUILD}') from None
    except ConfigError as err:
        raise TableError(f'{where}: metadata "axes": {err}') from None


def check_schema(meta: Any, where: str) -> None:
    """Refuse a schema this kneeseat does not read (`SUPPORTED_SCHEMAS`)."""
    schema = meta.get('schema') if isinstance(meta, dict) else None
    if schema not in SUPPORTED_SCHEMAS:
        raise TableError(f'{where}: unknown table schema {schema!r}; this kneeseat reads '
                         f'{", ".join(SUPPORTED_SCHEMAS)}; rebuild the table with this '
                         'kneeseat or use the kneeseat version that wrote it')


def mesh_entries(entry: Mapping[str, Any]) -> list[tuple[str, str]]:
    """(path, sha256) of every collision mesh of a metadata body or reference entry.

    Tables written before multi-mesh bodies have only `mesh`/`mesh_sha256`.
    """
    listed = entry.get('meshes')
    if isinstance(listed, list) and listed:
        return [(str(m.get('path', '?')), str(m.get('sha256') or '')) for m in listed
                if isinstance(m, dict)]
    return [(str(entry.get('mesh', '?')), str(entry.get('mesh_sha256') or ''))]


def display_paths(entry: Mapping[str, Any]) -> list[str]:
    """The mesh files to draw for a metadata body or reference entry, as recorded: its
    display meshes, else its collision meshes; [] when the entry names none.

    Reads tables written before multi-mesh bodies (`display_mesh`/`mesh` only) too.
    """
    listed = [str(m['path']) for m in entry.get('display_meshes') or []
              if isinstance(m, Mapping) and m.get('path')]
    if listed:
        return listed
    if entry.get('display_mesh'):
        return [str(entry['display_mesh'])]
    return [path for path, _ in mesh_entries(entry) if path != '?']
