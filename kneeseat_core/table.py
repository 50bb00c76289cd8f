"""The pose table: settled poses over a (flexion, varus) grid, its file, and interpolation.

STUB: signatures are the contract; bodies are being written (see issue 3).

File (DESIGN.md "Table file"): one `.npz` loaded with allow_pickle=False holding
`flexion` [F], `varus` [V] (rad, ascending), `position` [B,F,V,3] (m, reference frame),
`orientation` [B,F,V,4] (x, y, z, w), `converged` [B,F,V] bool, `iterations` [B,F,V] int,
and `metadata`, a JSON string (see `METADATA_KEYS`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .geometry import KneeAxes
from .typed import Floats

__all__ = ['SCHEMA', 'PoseTable', 'Lookup', 'write_table', 'read_table']

SCHEMA = 'kneeseat.table/1'

# metadata JSON (a dict):
#   schema: SCHEMA
#   kneeseat_version: str
#   reference: {"name": str, "frame": str, "mesh": str (path), "mesh_sha256": str}
#   bodies: [{"name": str, "frame": str, "mesh": str, "mesh_sha256": str,
#             "display_mesh": str | null}, ...]          (order = axis B of the arrays)
#   axes: {"flexion": [3], "varus": [3], "long": [3]}   (unit, reference frame)
#   config: the full knee config as a dict
#   settle: the settle parameters as a dict
#   arrays_sha256: hex SHA-256 over the arrays (checked on load)
#   built: ISO 8601 UTC build time
#   summary: {"cells": int, "converged": int, "wall_s": float, "collision_checks": int}


@dataclass(frozen=True, slots=True, eq=False)
class Lookup:
    """One interpolated answer, one row per moving body (order of `PoseTable.bodies`)."""

    position_m: Floats          # (B, 3) m, reference frame
    orientation_xyzw: Floats    # (B, 4) unit, w >= 0
    clamped: bool               # the request lay outside the grid and was clamped
    nonconverged: Floats        # (B,) bool: a non-converged cell contributed to that body


@dataclass(frozen=True, slots=True, eq=False)
class PoseTable:
    """Settled poses of each moving body over the grid, plus provenance."""

    flexion_rad: Floats         # (F,) ascending
    varus_rad: Floats           # (V,) ascending
    position_m: Floats          # (B, F, V, 3)
    orientation_xyzw: Floats    # (B, F, V, 4)
    converged: Floats           # (B, F, V) bool
    iterations: Floats          # (B, F, V) int
    metadata: dict[str, Any]

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

    def interpolate(self, flexion_rad: float, varus_rad: float,
                    out_of_range: Literal['clamp', 'drop'] = 'clamp') -> Lookup:
        """Bilinear pose of every body at (flexion, varus).

        Raises:
            OutOfRangeError: outside the grid and `out_of_range` is 'drop'.
        """
        raise NotImplementedError


def write_table(path: Path, table: PoseTable) -> None:
    """Write `table` atomically (temp file + rename); fills in `arrays_sha256`."""
    raise NotImplementedError


def read_table(path: Path, meshes: dict[str, Path] | None = None) -> PoseTable:
    """Load and verify a table file.

    Args:
        meshes: optional body name -> mesh path; their SHA-256 must match the metadata.
    Raises:
        TableError: missing, unreadable, truncated, tampered (hash), unknown schema,
            wrong array shapes, or built from other meshes.
    """
    raise NotImplementedError


_ = np
