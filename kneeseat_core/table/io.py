"""Reading and writing table files (format: `kneeseat_core.table.format`).

`write_table` fills in the schema, version, build time and the arrays' SHA-256 and writes
the file atomically (`kneeseat_core.files.atomic_write`); `read_table` refuses anything
that is not exactly such a file - missing, truncated, a flipped byte (the hash), an unknown
schema, arrays of the wrong kind or shape, metadata a server cannot use - and, when given
the meshes, a table built from other meshes. Every refusal is a `TableError` whose message
names the file and says how to fix it.
"""
from __future__ import annotations

from dataclasses import replace
from datetime import datetime, timezone
import json
from pathlib import Path
from typing import Any, BinaryIO
import zipfile
import zlib

import numpy as np

from kneeseat_core import kneeseat_version
from kneeseat_core.errors import MeshError, TableError
from kneeseat_core.files import atomic_write, file_sha256
from .format import (ARRAY_NAMES, canonical, check_arrays, check_metadata, check_schema,
                     hash_arrays, mesh_entries, REBUILD, SCHEMA)
from .pose_table import PoseTable

__all__ = ['with_hash', 'write_table', 'read_table']


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
    check_metadata(meta, where)
    arrays = check_arrays(table.arrays(), len(meta['bodies']), where)
    meta.setdefault('kneeseat_version', kneeseat_version())
    meta.setdefault('built', datetime.now(timezone.utc).isoformat(timespec='seconds'))
    meta['arrays_sha256'] = hash_arrays(arrays)
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
    arrays = {name: canonical(name, a) for name, a in hashed.arrays().items()}
    arrays['metadata'] = np.array(text)

    def save(fh: BinaryIO) -> None:
        np.savez(fh, allow_pickle=False, **arrays)

    try:
        atomic_write(path, save)
    except OSError as err:
        raise TableError(f'cannot write table {path}: {err.strerror or err}; check that the '
                         'directory exists, is writable and has free space') from err


_CORRUPT = (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError)
_ZIP_MAGIC, _NPY_MAGIC = b'PK', b'\x93NUMPY'


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
    meta, loaded = _load(path, where)
    check_metadata(meta, where)
    stored = meta.get('arrays_sha256')
    if not isinstance(stored, str):
        raise TableError(f'{where}: metadata has no arrays_sha256; {REBUILD}')
    nbodies = len(meta['bodies'])
    for name in ('position', 'orientation', 'converged', 'iterations'):
        if loaded[name].ndim < 1 or loaded[name].shape[0] != nbodies:
            raise TableError(f'{where}: array {name!r} has shape {loaded[name].shape} but the '
                             f'metadata lists {nbodies} bodies; {REBUILD}')
    arrays = check_arrays(loaded, nbodies, where)
    actual = hash_arrays(arrays)
    if actual != stored:
        raise TableError(f'{where}: arrays do not match their SHA-256 (stored {stored[:12]}, '
                         f'computed {actual[:12]}): corrupt or modified; {REBUILD}')
    if meshes:
        _check_meshes(meta, meshes, where)
    for a in arrays.values():
        a.flags.writeable = False
    table = PoseTable(arrays['flexion'], arrays['varus'], arrays['position'],
                      arrays['orientation'], arrays['converged'], arrays['iterations'], meta)
    table.prepare()
    return table


def _load(path: Path, where: str) -> tuple[Any, dict[str, np.ndarray]]:
    """The metadata (parsed JSON, schema checked) and the six arrays of the file at `path`,
    as stored (their kinds, shapes and values are checked by the caller).

    Raises:
        TableError: missing, not a file, unreadable, not an .npz, no or bad metadata, an
            unknown schema, arrays missing or unexpected.
    """
    if not path.exists():
        raise TableError(f'{where} not found; check the path or build one with '
                         '`kneeseat build`')
    if not path.is_file():
        raise TableError(f'{where} is not a regular file; give the path of a .npz table')
    try:
        with open(path, 'rb') as fh:
            head = fh.read(len(_NPY_MAGIC))
        # numpy takes any file that is neither a zip nor an .npy for a pickle, which it
        # refuses with advice to unpickle it: the wrong advice for a text file
        problem = (None if head.startswith((_ZIP_MAGIC, _NPY_MAGIC))
                   else 'it is empty' if not head
                   else 'it does not start as a zip archive or an .npy array does')
        if problem is None:
            npz = np.load(path, allow_pickle=False)
    except PermissionError:
        raise TableError(f'{where} cannot be read (permission denied); check its '
                         'permissions') from None
    except _CORRUPT as err:
        problem = str(err)
    if problem is not None:
        raise TableError(f'{where} is not a readable table (.npz): {problem}; it is '
                         f'truncated, corrupt or another kind of file; {REBUILD}')
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise TableError(f'{where} holds a single array, not a table (.npz); {REBUILD}')
    with npz:
        names = set(npz.files)
        if 'metadata' not in names:
            raise TableError(f'{where} has no metadata array; it is not a kneeseat table; '
                             f'{REBUILD}')
        raw = _read_member(npz, 'metadata', where)
        if raw.dtype.kind != 'U' or raw.shape != ():
            raise TableError(f'{where}: metadata is a {raw.dtype} array of shape {raw.shape}, '
                             f'expected a JSON string; {REBUILD}')
        try:
            meta = json.loads(str(raw[()]))
        except ValueError as err:
            raise TableError(f'{where}: metadata is not valid JSON ({err}); the file is '
                             f'corrupt or modified; {REBUILD}') from None
        check_schema(meta, where)
        missing = [n for n in ARRAY_NAMES if n not in names]
        extra = sorted(names - set(ARRAY_NAMES) - {'metadata'})
        if missing or extra:
            what = '; '.join(([f'missing {", ".join(missing)}'] if missing else [])
                             + ([f'unexpected {", ".join(extra)}'] if extra else []))
            raise TableError(f'{where}: arrays {what}; not a {SCHEMA} table; {REBUILD}')
        return meta, {n: _read_member(npz, n, where) for n in ARRAY_NAMES}


def _read_member(npz: np.lib.npyio.NpzFile, name: str, where: str) -> np.ndarray:
    try:
        return np.asarray(npz[name])
    except _CORRUPT as err:
        raise TableError(f'{where} is corrupt (array {name!r}: {err}); {REBUILD}') from None


def _check_meshes(meta: dict[str, Any], meshes: dict[str, Any], where: str) -> None:
    """Each given mesh file must have the SHA-256 the table recorded for its body."""
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
                                 f'it cannot be checked; {REBUILD}')
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
