"""Renders of the settled bones: several flexion angles side by side (US 6,708,142, FIG. 15).

An orthographic projection of depth-sorted, Lambert-shaded triangles (painter's
algorithm), headless like `kneeseat_core.report.plots` and written the same way (one PNG with
the `kneeseat:nonconverged` and `kneeseat:table` text chunks). Meshes above
`RENDER_MAX_FACES` triangles are simplified first by vertex clustering (a uniform grid
merges the vertices in each cell), which keeps the silhouette and costs milliseconds.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
import logging
import math
from pathlib import Path
import time
from typing import cast, Literal

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch
import numpy as np
import trimesh

from kneeseat_core.errors import ConfigError
from kneeseat_core.geometry import matrix_from_quat, TOL, unit
from kneeseat_core.table import PoseTable
from kneeseat_core.typed import Floats, Ints
from .plots import (checked_png_path, DPI, finite_angles, outside_grid, PNG_KEY_NONCONVERGED,
                    PNG_KEY_TABLE, table_name, write_png)

__all__ = ['RENDER_PANEL_IN', 'RENDER_EXTRA_IN', 'RENDER_MAX_FACES', 'RENDER_MAX_PANELS',
           'render_table']

log = logging.getLogger(__name__)

RENDER_PANEL_IN = (3.25, 4.0)      # (width, height) of one render_table panel, inches
RENDER_EXTRA_IN = 1.25             # render_table: title + legend band, inches
RENDER_MAX_FACES = 15000           # triangles drawn per mesh at most (vertex clustering)
RENDER_MAX_PANELS = 12             # flexion angles per render at most
_DEFAULT_RENDER_PANELS = 5
# Body colours for renders: the reference in bone ivory, moving bodies in distinct hues.
_REFERENCE_RGB = (0.85, 0.82, 0.70)
_BODY_RGB = ((0.30, 0.55, 0.85), (0.35, 0.70, 0.40), (0.85, 0.60, 0.25),
             (0.60, 0.45, 0.80), (0.40, 0.75, 0.80), (0.75, 0.50, 0.60))
_AMBIENT, _DIFFUSE = 0.30, 0.70    # Lambert shading: intensity = ambient + diffuse * cos


def render_table(table: PoseTable, meshes: Mapping[str, trimesh.Trimesh], out: Path, *,
                 flexion_deg: Sequence[float] | None = None,
                 view: Literal['lateral', 'anterior'] = 'lateral') -> Path:
    """Draw the bones at several flexion angles side by side (US 6,708,142, FIG. 15).

    The reference body is drawn at identity, each moving body at its settled pose at
    (flexion, varus nearest 0): the grid node when the angle is a node, else
    `table.interpolate`. The projection is orthographic; every panel has the same axis
    limits (mm, reference frame), so sizes and displacements compare across panels.
    'lateral' looks along the knee's flexion axis, 'anterior' along its varus axis, from
    the side that axis points to; screen up is the long axis. Panels whose pose comes
    from a non-converged cell say so in their title.

    Args:
        table: the pose table.
        meshes: body name -> mesh in that body's own frame (m), for the reference and every
            moving body of the table (display meshes where the caller has them).
        out: PNG path (must end in .png); missing directories are created.
        flexion_deg: flexion angles (deg) to draw, inside the table's range. Default:
            five angles evenly over the range, each snapped to the nearest grid node.
        view: 'lateral' or 'anterior'.

    Returns:
        `out`, the PNG written, (n * RENDER_PANEL_IN[0], RENDER_PANEL_IN[1] +
        RENDER_EXTRA_IN) inches at `DPI` for n angles.

    Raises:
        ConfigError: unknown view, a mesh missing or unknown or empty, a flexion angle
            outside the table or not finite, `out` does not end in .png, or `out`
            cannot be written.
    """
    started = time.perf_counter()
    out = checked_png_path(out)
    if view not in ('lateral', 'anterior'):
        raise ConfigError(f"view={view!r} is not a view; use 'lateral' or 'anterior'")
    reference = str(table.metadata['reference']['name'])
    _check_meshes(meshes, reference, table.bodies)
    grid_flexion_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    grid_varus_deg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    v_col = int(np.argmin(np.abs(grid_varus_deg)))
    angles = _flexion_angles(grid_flexion_deg, flexion_deg)

    toward, up, right, light = _view(table, view)
    screen = np.stack([right, up])                                  # (2, 3)
    names = (reference, *table.bodies)
    colours = (_REFERENCE_RGB, *(_BODY_RGB[i % len(_BODY_RGB)] for i in range(len(names) - 1)))
    simple = [_simplified(meshes[name], RENDER_MAX_FACES) for name in names]
    panels = []
    for angle_deg, node in angles:
        poses, stale = _poses_at(table, angle_deg, node, v_col)
        polys, rgb = _project(simple, colours, poses, toward, screen, light)
        panels.append((angle_deg, polys, rgb, stale))
    n = len(panels)
    fig = Figure(figsize=(n * RENDER_PANEL_IN[0], RENDER_PANEL_IN[1] + RENDER_EXTRA_IN),
                 dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    stale_total = _draw_panels(fig.subplots(1, n, squeeze=False)[0], panels,
                               (_direction_name(right, table.reference_frame),
                                _direction_name(up, table.reference_frame)))
    handles = [Patch(facecolor=c, edgecolor='0.3',
                     label=f'{name} (reference)' if name == reference else name)
               for name, c in zip(names, colours)]
    fig.legend(handles=handles, loc='outside lower center', ncol=len(handles))
    fig.suptitle(f'{table_name(table)}: {view} view, varus {grid_varus_deg[v_col]:.1f}°')
    path = write_png(fig, out, {PNG_KEY_NONCONVERGED: str(stale_total),
                                PNG_KEY_TABLE: table_name(table)})
    log.info('render of %s: %d panels, %s view, %.2f s', table_name(table), n, view,
             time.perf_counter() - started)
    return path


def _view(table: PoseTable, view: str) -> tuple[Floats, Floats, Floats, Floats]:
    """(toward the viewer, screen up, screen right, light) unit vectors, reference frame:
    'lateral' looks along the flexion axis, 'anterior' along the varus axis; up is the
    long axis."""
    knee = table.axes
    toward = knee.flexion if view == 'lateral' else knee.varus     # points at the viewer
    up = unit(knee.long - (knee.long @ toward) * toward, 'long axis')
    right = np.cross(up, toward)
    light = unit(toward + 0.5 * up + 0.3 * right, 'light')
    return toward, up, right, light


def _draw_panels(axs: Sequence[Axes], panels: list[tuple[float, Floats, Floats, list[str]]],
                 labels: tuple[str, str]) -> int:
    """Draw each (angle, polygons, colours, non-converged bodies) panel with common limits;
    returns how many bodies were drawn from non-converged cells."""
    corners = np.concatenate([p.reshape(-1, 2) for _, p, _, _ in panels])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = 0.05 * float((hi - lo).max())
    stale_total = 0
    for i, (ax, (angle_deg, polys, rgb, stale)) in enumerate(zip(axs, panels)):
        # an (n, 3, 2) array is matplotlib's fast path for n triangles (its stub wants a list)
        ax.add_collection(PolyCollection(cast(Sequence[Floats], polys), facecolors=rgb,
                                         edgecolors=rgb, linewidths=0.3))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect('equal', adjustable='box')
        label = f'flexion {angle_deg:.1f}°'
        if stale:
            label += '\nnot converged: ' + ', '.join(stale)
        stale_total += len(stale)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel(f'{labels[0]} [mm]')
        if i == 0:
            ax.set_ylabel(f'{labels[1]} [mm]')
        ax.tick_params(labelsize=8)
    return stale_total


def _flexion_angles(grid_deg: Floats, requested: Sequence[float] | None
                    ) -> list[tuple[float, int | None]]:
    """(angle deg, grid node or None when between nodes) for each panel, in order."""
    if requested is None:
        count = min(_DEFAULT_RENDER_PANELS, len(grid_deg))
        targets = np.linspace(grid_deg[0], grid_deg[-1], count)
        nodes = sorted({int(np.argmin(np.abs(grid_deg - t))) for t in targets})
        return [(float(grid_deg[f]), f) for f in nodes]
    angles = finite_angles(requested, 'flexion_deg')
    if angles.size > RENDER_MAX_PANELS:
        raise ConfigError(f'flexion_deg has {angles.size} angles; draw at most '
                          f'{RENDER_MAX_PANELS} per picture')
    result: list[tuple[float, int | None]] = []
    for value in angles:
        if not grid_deg[0] - TOL.grid_match_deg <= value <= grid_deg[-1] + TOL.grid_match_deg:
            raise outside_grid('flexion_deg', float(value), grid_deg)
        f = int(np.argmin(np.abs(grid_deg - value)))
        on_node = abs(grid_deg[f] - value) <= TOL.grid_match_deg
        result.append((float(grid_deg[f]) if on_node else float(value),
                       f if on_node else None))
    return result


def _check_meshes(meshes: Mapping[str, trimesh.Trimesh], reference: str,
                  bodies: Sequence[str]) -> None:
    """Every body of the table (and the reference) has a non-empty mesh; no strangers."""
    wanted = (reference, *bodies)
    for name in wanted:
        if name not in meshes:
            raise ConfigError(f'meshes has no mesh for {name!r} (has {sorted(meshes)}); '
                              f'give one for each of {list(wanted)}')
        mesh = meshes[name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ConfigError(f'meshes[{name!r}] is not a non-empty triangle mesh; '
                              'load it with trimesh (kneeseat_core.meshes.load)')
    for name in meshes:
        if name not in wanted:
            raise ConfigError(f'meshes has {name!r}, which is not a body of the table; '
                              f'use the names {list(wanted)}')


def _simplified(mesh: trimesh.Trimesh, max_faces: int) -> tuple[Floats, Ints, bool]:
    """(vertices (n, 3) m, faces (m, 3) int, cull back faces) with at most `max_faces`.

    Vertex clustering: vertices in one cube of a uniform grid merge into their mean;
    faces that collapse are dropped, duplicates kept once. The cube starts at the size that
    would give `max_faces` on a mesh of this area and shrinks the count until it fits.
    Back faces are culled only for closed, consistently wound meshes.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    closed = bool(mesh.is_watertight and mesh.is_winding_consistent)
    if len(faces) <= max_faces:
        return vertices, faces, closed
    lo = vertices.min(axis=0)
    cell = math.sqrt(2.0 * float(mesh.area) / max_faces)
    for _ in range(20):
        key = np.floor((vertices - lo) / cell).astype(np.int64)                   # (n, 3)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        merged = np.zeros((len(counts), 3))
        np.add.at(merged, inverse, vertices)
        merged /= counts[:, None]
        new = inverse[faces]                                                        # (m, 3)
        keep = (new[:, 0] != new[:, 1]) & (new[:, 1] != new[:, 2]) & (new[:, 0] != new[:, 2])
        new = new[keep]
        _, first = np.unique(np.sort(new, axis=1), axis=0, return_index=True)
        new = new[np.sort(first)]
        if len(new) <= max_faces:
            log.debug('simplified %d -> %d faces (cell %.2f mm)', len(faces), len(new),
                      cell * 1e3)
            return merged, new, closed
        cell *= 1.05 * math.sqrt(len(new) / max_faces)
    return merged, new, closed                  # pragma: no cover - converges in 2-3 rounds


def _poses_at(table: PoseTable, angle_deg: float, node: int | None, v_col: int
              ) -> tuple[list[Floats], list[str]]:
    """(4, 4) reference_from_body for [reference, *bodies] and the non-converged bodies."""
    poses = [np.eye(4)]
    stale: list[str] = []
    converged = np.asarray(table.converged, dtype=bool)
    if node is not None:
        rotations = matrix_from_quat(np.asarray(table.orientation_xyzw)[:, node, v_col])
        positions = np.asarray(table.position_m, dtype=np.float64)[:, node, v_col]
        flags = ~converged[:, node, v_col]
    else:
        lookup = table.interpolate(math.radians(angle_deg), float(table.varus_rad[v_col]))
        rotations = matrix_from_quat(lookup.orientation_xyzw)
        positions = np.asarray(lookup.position_m, dtype=np.float64)
        flags = np.asarray(lookup.nonconverged, dtype=bool)
    for b, body in enumerate(table.bodies):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotations[b], positions[b]
        poses.append(pose)
        if flags[b]:
            stale.append(body)
    return poses, stale


def _project(meshes: Sequence[tuple[Floats, Ints, bool]],
             colours: Sequence[tuple[float, float, float]], poses: Sequence[Floats],
             toward: Floats, screen: Floats, light: Floats) -> tuple[Floats, Floats]:
    """Screen triangles (n, 3, 2) mm, far to near, and their shaded colours (n, 3)."""
    polys, rgb, depth = [], [], []
    for (vertices, faces, closed), colour, pose in zip(meshes, colours, poses):
        world = vertices @ pose[:3, :3].T + pose[:3, 3]                     # (n, 3) m
        tri = world[faces]                                                  # (m, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), TOL.zero_length)
        facing = normal @ toward
        if closed:
            tri, normal = tri[facing > 0.0], normal[facing > 0.0]
        cos = np.abs(normal @ light)
        polys.append(tri @ screen.T * 1e3)
        rgb.append(np.clip(np.outer(_AMBIENT + _DIFFUSE * cos, colour), 0.0, 1.0))
        depth.append(tri.mean(axis=1) @ toward)
    order = np.argsort(np.concatenate(depth), kind='stable')
    return np.concatenate(polys)[order], np.concatenate(rgb)[order]


def _direction_name(direction: Floats, frame: str) -> str:
    """'+x (femur)' for a frame axis, else the vector rounded, e.g. '[0.71, 0, 0.71] (femur)'."""
    for i, axis in enumerate('xyz'):
        if abs(abs(direction[i]) - 1.0) < TOL.unit_norm:
            return f'{"+" if direction[i] > 0 else "-"}{axis} ({frame})'
    return f'{np.round(direction, 2).tolist()} ({frame})'
