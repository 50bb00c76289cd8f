"""Loading and validating triangle meshes (STL, PLY, OBJ, OFF, GLB) in metres.

A mesh that is not watertight (an open cartilage sheet) is accepted with one warning per
mesh and process: loading it again, or loading it `quiet` (sweep workers, whose parent has
already validated every mesh with `check_mesh_files`), logs at debug level only.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import cast, Literal, Sequence

import numpy as np
import trimesh

from kneeseat_core.errors import MeshError

__all__ = ['Units', 'UNIT_SCALE', 'load_mesh', 'load_meshes', 'check_mesh', 'check_mesh_files']

log = logging.getLogger(__name__)

Units = Literal['m', 'mm']
UNIT_SCALE: dict[str, float] = {'m': 1.0, 'mm': 1e-3}

# A bone or implant is millimetres to decimetres across; outside this the units are wrong.
_PLAUSIBLE_EXTENT_M = (1e-3, 1.0)
# no coordinate of a mesh of any body, in metres or millimetres, comes near this; the
# squares and products a mesh's areas and normals take stay finite below it
_FARTHEST = 1e9
_WARNED_OPEN: set[str] = set()      # meshes already reported as not watertight


def load_mesh(path: Path | str, units: Units = 'm', quiet: bool = False) -> trimesh.Trimesh:
    """Load one mesh file and return it validated, in metres.

    Degenerate and duplicate triangles are removed; a mesh that is not watertight is
    accepted with a warning, once per file and process (collision still works,
    inside/outside may not).

    Args:
        path: mesh file (STL, PLY, OBJ, OFF, GLB; a multi-part file is concatenated).
        units: units of the file's coordinates, 'm' or 'mm'. Never guessed.
        quiet: log the not-watertight note at debug level (the caller validated it).
    Raises:
        MeshError: missing or unreadable file, no triangles, non-finite coordinates, or
            an implausible size for the declared units.
    """
    path = Path(path)
    if units not in UNIT_SCALE:
        raise MeshError(f"{path}: unknown units '{units}'; use 'm' or 'mm'")
    if not path.is_file():
        raise MeshError(f'{path}: no such mesh file; check the path')
    try:
        # process=False: trimesh's processing drops faces with NaN vertices, which would
        # hide a broken file; check_mesh validates first, then merges vertices (and says
        # what is wrong with coordinates whose normals the loader's arithmetic overflows)
        with np.errstate(over='ignore', invalid='ignore'):
            loaded = trimesh.load(str(path), force='mesh', process=False)
    except Exception as err:  # trimesh raises many types for a bad file
        raise MeshError(f'{path}: not a readable mesh ({type(err).__name__}: {err}); '
                        'give an STL, PLY, OBJ, OFF or GLB file') from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f'{path}: holds no triangle mesh; give an STL, PLY, OBJ, OFF or GLB '
                        'file with triangles')
    mesh = loaded.copy()
    mesh.apply_scale(UNIT_SCALE[units])
    return check_mesh(mesh, str(path), units, quiet)


def load_meshes(paths: Sequence[Path | str], units: Units = 'm',
                quiet: bool = False) -> trimesh.Trimesh:
    """Load several mesh files as one mesh (one rigid body), in metres.

    Each file is validated as by `load_mesh`; the results are concatenated without merging
    vertices across files, so every triangle keeps its own file's vertex normals.

    Raises:
        MeshError: as `load_mesh`, naming the file; or no path given.
    """
    if not paths:
        raise MeshError('no mesh file given; name at least one')
    meshes = [load_mesh(p, units, quiet) for p in paths]
    if len(meshes) == 1:
        return meshes[0]
    return cast(trimesh.Trimesh, trimesh.util.concatenate(meshes))   # meshes in, a mesh out


def check_mesh_files(paths: Sequence[Path | str], units: Units = 'm') -> None:
    """Load and validate every file once (warnings included), e.g. before a sweep.

    Raises:
        MeshError: a file is missing, unreadable or implausible (see `load_mesh`).
    """
    for path in dict.fromkeys(str(p) for p in paths):
        load_mesh(path, units)


def check_mesh(mesh: trimesh.Trimesh, name: str, units: Units = 'm',
               quiet: bool = False) -> trimesh.Trimesh:
    """Validate and clean a mesh already in metres (see `load_mesh`); `name` goes in errors.

    Raises:
        MeshError: no triangles, non-finite coordinates or an implausible size.
    """
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f'{name}: mesh is empty (no triangles); export the surface again')
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f'{name}: mesh has NaN or infinite vertex coordinates; '
                        'repair or re-export it')
    reach = float(np.abs(mesh.vertices).max())
    if reach > _FARTHEST:       # products of such coordinates overflow: nothing is measured
        raise MeshError(f'{name}: a vertex coordinate reaches {reach:.3g}, far beyond any bone '
                        'in metres or millimetres; repair or re-export it')
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)   # merge vertices
    keep = mesh.nondegenerate_faces() & mesh.unique_faces()
    dropped = int(len(keep) - keep.sum())
    if dropped:
        mesh.update_faces(keep)
        mesh.remove_unreferenced_vertices()
        log.info('%s: removed %d degenerate or duplicate triangles', name, dropped)
    if len(mesh.faces) == 0:
        raise MeshError(f'{name}: every triangle is degenerate; export the surface again')
    extent = float(np.max(mesh.extents))
    lo, hi = _PLAUSIBLE_EXTENT_M
    if not lo <= extent <= hi:
        hint = ('pass --units mm (units: mm in a config)' if units == 'm' and extent > hi
                else 'check the declared units')
        raise MeshError(f'{name}: {extent:.4g} m across is not a plausible bone or implant '
                        f'size with units={units}; {hint}')
    if not mesh.is_watertight:
        # a quiet load (a worker's) leaves the warning to the caller's own check
        warn = not quiet and name not in _WARNED_OPEN
        if warn:
            _WARNED_OPEN.add(name)
        log.log(logging.WARNING if warn else logging.DEBUG, '%s: mesh is not watertight (open '
                'sheet or holes); accepted: settling works, but deep penetration cannot be told '
                'from a hole', name)
    return mesh
