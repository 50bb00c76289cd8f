"""Loading and validating triangle meshes (STL, PLY, OBJ, OFF, GLB) in metres."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from .errors import MeshError

__all__ = ['Units', 'UNIT_SCALE', 'load_mesh', 'check_mesh']

log = logging.getLogger(__name__)

Units = Literal['m', 'mm']
UNIT_SCALE: dict[str, float] = {'m': 1.0, 'mm': 1e-3}

# A bone or implant is millimetres to decimetres across; outside this the units are wrong.
_PLAUSIBLE_EXTENT_M = (1e-3, 1.0)


def load_mesh(path: Path | str, units: Units = 'm') -> trimesh.Trimesh:
    """Load one mesh file and return it validated, in metres.

    Degenerate and duplicate triangles are removed; a mesh that is not watertight is
    accepted with a warning (collision still works, inside/outside may not).

    Args:
        path: mesh file (STL, PLY, OBJ, OFF, GLB; a multi-part file is concatenated).
        units: units of the file's coordinates, 'm' or 'mm'. Never guessed.
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
        # hide a broken file; check_mesh validates first, then merges vertices
        loaded = trimesh.load(str(path), force='mesh', process=False)
    except Exception as err:  # trimesh raises many types for a bad file
        raise MeshError(f'{path}: not a readable mesh ({type(err).__name__}: {err}); '
                        'give an STL, PLY, OBJ, OFF or GLB file') from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f'{path}: holds no triangle mesh; give an STL, PLY, OBJ, OFF or GLB '
                        'file with triangles')
    mesh = loaded.copy()
    mesh.apply_scale(UNIT_SCALE[units])
    return check_mesh(mesh, str(path), units)


def check_mesh(mesh: trimesh.Trimesh, name: str, units: Units = 'm') -> trimesh.Trimesh:
    """Validate and clean a mesh already in metres (see `load_mesh`); `name` goes in errors.

    Raises:
        MeshError: no triangles, non-finite coordinates or an implausible size.
    """
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f'{name}: mesh is empty (no triangles); export the surface again')
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f'{name}: mesh has NaN or infinite vertex coordinates; '
                        'repair or re-export it')
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
        log.warning('%s: mesh is not watertight; settling works, but deep penetration '
                    'cannot be told from a hole', name)
    return mesh
