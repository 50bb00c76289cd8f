"""The table a node serves, with everything derived from it that the hot path needs.

`Served.load` reads and checks a table for serving (`load_table`: the file's own checks
plus body names usable in topic names and a reference frame) and prepares the attitude
decoder and the CDR writers; a `Route` bundles it with its output publishers, so that a
reload swaps both in one assignment.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
import re
from typing import NamedTuple

import numpy as np
from rclpy.publisher import Publisher

from kneeseat_core.errors import TableError
from kneeseat_core.table import PoseTable, read_table
from .cdr import PoseStampedWriter, TfWriter
from .conversions import AttitudeDecoder, display_mesh_paths

__all__ = ['load_table', 'GridBounds', 'Served', 'Route']

_BODY_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')


def load_table(path: Path) -> PoseTable:
    """Read and verify a table for serving: file checks plus ROS-usable names.

    Raises:
        TableError: the file is missing or corrupt (see `read_table`), or a body name
            cannot be used in a topic name.
    """
    table = read_table(path)
    for body in (table.metadata['reference']['name'], *table.bodies):
        if not _BODY_NAME.match(str(body)):
            raise TableError(f'{path}: body name {body!r} cannot be used in the topic '
                             'knee/<body>/pose; rebuild the table with names made of '
                             'letters, digits and underscores')
    if not table.reference_frame:
        raise TableError(f'{path}: the table has an empty reference frame; rebuild it with '
                         'reference.frame set in the knee config')
    table.axes    # validates the axes (ConfigError) before the first message
    return table


class GridBounds(NamedTuple):
    """The table grid's first and last flexion and varus, in degrees."""

    flexion_min_deg: float
    flexion_max_deg: float
    varus_min_deg: float
    varus_max_deg: float


@dataclass(frozen=True, slots=True, eq=False)
class Served:
    """A loaded table and everything derived from it that the hot path needs."""

    table: PoseTable
    path: Path
    frame: str
    reference: str
    decoder: AttitudeDecoder
    bodies: tuple[str, ...]
    body_frames: tuple[str, ...]
    meshes: tuple[tuple[str, ...], ...]     # display mesh files: reference, then bodies
    bounds_deg: GridBounds
    writer: PoseStampedWriter          # answers in the reference frame, as CDR bytes
    tf: TfWriter                       # reference -> bodies (and world -> reference)

    @classmethod
    def load(cls, path: Path, world_frame: str | None = None) -> Served:
        """Load the table at `path` for serving; `world_frame`: tracker mode's world frame.

        Raises:
            KneeseatError: the table cannot be served (`load_table`).
        """
        table = load_table(path)
        flexion, varus = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
        meta = table.metadata
        meshes = tuple(display_mesh_paths(e, path.parent)
                       for e in [meta['reference'], *meta['bodies']])
        frame = table.reference_frame
        pairs = [(frame, child) for child in table.body_frames]
        if world_frame is not None:
            pairs.append((world_frame, frame))
        return cls(table, path, frame, str(meta['reference']['name']),
                   AttitudeDecoder(table.axes), table.bodies, table.body_frames, meshes,
                   GridBounds(float(flexion[0]), float(flexion[-1]), float(varus[0]),
                              float(varus[-1])),
                   PoseStampedWriter(frame), TfWriter(pairs))


@dataclass(frozen=True, slots=True, eq=False)
class Route:
    """The served table with its output publishers, swapped as one by a reload."""

    served: Served
    body_pubs: tuple[Publisher, ...]
    body_world_pubs: tuple[Publisher, ...]     # tracker mode only
    reference_world_pub: Publisher | None      # tracker mode only
