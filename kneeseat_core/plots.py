"""Pictures of a pose table: curves against flexion, and renders of the settled bones.

Two public functions, both headless (a `matplotlib.figure.Figure` of their own drawn on an
Agg canvas; no pyplot, so no global state leaks between calls), both writing one PNG
atomically (`kneeseat_core.files.atomic_write`):

- `plot_table`: per moving body, the three translations (mm, reference frame) and the
  rotation about the long axis (deg) against flexion (deg), one curve per chosen varus
  column; non-converged cells marked with red crosses.
- `plot_convergence_map`: per moving body, the (flexion, varus) grid with every
  cell that did not end at a plain rest coloured by its status (`PoseTable.status`).
- `render_table`: the bones drawn at several flexion angles side by side (like FIG. 15 of
  US 6,708,142), as an orthographic projection of depth-sorted, Lambert-shaded triangles
  (painter's algorithm). Meshes above `RENDER_MAX_FACES` triangles are simplified first by
  vertex clustering (a uniform grid merges the vertices in each cell), which keeps the
  silhouette and costs milliseconds.

Each PNG carries tEXt chunks `kneeseat:nonconverged` (number of non-converged points marked,
or of bodies drawn from non-converged cells) and `kneeseat:table` (the table name), so
scripts and tests can read what was drawn without parsing pixels.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
import logging
import math
from pathlib import Path
import time
from typing import BinaryIO, Literal

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
import numpy as np
import trimesh

from .errors import ConfigError
from .files import atomic_write
from .geometry import matrix_from_quat, TOL, unit
from .status import Status, STATUS_NAMES
from .table import PoseTable
from .typed import Floats

__all__ = ['DPI', 'PLOT_PANEL_IN', 'PLOT_EXTRA_IN', 'RENDER_PANEL_IN', 'RENDER_EXTRA_IN',
           'RENDER_MAX_FACES', 'MARKER_RGB', 'PNG_KEY_NONCONVERGED', 'plot_table',
           'plot_convergence_map', 'render_table', 'write_png']

log = logging.getLogger(__name__)

DPI = 100                          # pixels per inch of every PNG written here
PLOT_PANEL_IN = (3.5, 2.75)        # (width, height) of one plot_table subplot, inches
PLOT_EXTRA_IN = 1.5                # plot_table: title + legend band, inches
RENDER_PANEL_IN = (3.25, 4.0)      # (width, height) of one render_table panel, inches
RENDER_EXTRA_IN = 1.25             # render_table: title + legend band, inches
RENDER_MAX_FACES = 15000           # triangles drawn per mesh at most (vertex clustering)
RENDER_MAX_PANELS = 12             # flexion angles per render at most
MARKER_RGB = (1.0, 0.0, 0.0)       # non-converged markers; no other element uses pure red
PNG_KEY_NONCONVERGED = 'kneeseat:nonconverged'
PNG_KEY_TABLE = 'kneeseat:table'

_DEFAULT_RENDER_PANELS = 5
# Curve colours: Tableau without its red, so that red means "not converged" only.
_CURVE_COLOURS = ('tab:blue', 'tab:orange', 'tab:green', 'tab:purple', 'tab:brown',
                  'tab:pink', 'tab:gray', 'tab:olive', 'tab:cyan')
# Body colours for renders: the reference in bone ivory, moving bodies in distinct hues.
_REFERENCE_RGB = (0.85, 0.82, 0.70)
_BODY_RGB = ((0.30, 0.55, 0.85), (0.35, 0.70, 0.40), (0.85, 0.60, 0.25),
             (0.60, 0.45, 0.80), (0.40, 0.75, 0.80), (0.75, 0.50, 0.60))
_AMBIENT, _DIFFUSE = 0.30, 0.70    # Lambert shading: intensity = ambient + diffuse * cos


def plot_table(table: PoseTable, out: Path, *, varus_deg: Sequence[float] | None = None,
               title: str | None = None) -> Path:
    """Plot each moving body's translations and long-axis rotation against flexion.

    One row of four subplots per moving body: x, y, z of the body's frame origin in the
    reference frame (mm) and its rotation about the knee's long axis (deg, the `rotation`
    of `KneeAxes.decompose`; the screw-home angle for a tibia), each against flexion
    (deg), one curve per chosen varus column. Non-converged cells on those curves are
    marked with red crosses (legend entry 'not converged (n)').

    Args:
        table: the pose table.
        out: PNG path (must end in .png); missing directories are created.
        varus_deg: varus values (deg) to draw. Default: the grid's minimum, the grid value
            nearest 0 and its maximum. A value between grid nodes draws the nearest
            column and the legend says so.
        title: figure title; default names the table and the short SHA-256 (8 hex) of
            every mesh.

    Returns:
        `out`, the PNG written, (4 * PLOT_PANEL_IN[0], B * PLOT_PANEL_IN[1] + PLOT_EXTRA_IN)
        inches at `DPI`.

    Raises:
        ConfigError: a varus value is outside the grid or not finite, the table has no
            moving body, `out` does not end in .png, or `out` cannot be written.
    """
    out = _checked_out(out)
    if not table.bodies:
        raise ConfigError('the table has no moving bodies, so there is nothing to plot; '
                          'build it with at least one moving body')
    flexion_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    grid_varus_deg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    columns = _varus_columns(grid_varus_deg, varus_deg)
    axes = table.axes
    frame = table.reference_frame
    n_bodies = len(table.bodies)
    converged = np.asarray(table.converged, dtype=bool)

    fig = Figure(figsize=(4 * PLOT_PANEL_IN[0], n_bodies * PLOT_PANEL_IN[1] + PLOT_EXTRA_IN),
                 dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    grid = fig.subplots(n_bodies, 4, squeeze=False, sharex=True)
    ylabels = (f'x ({frame}) [mm]', f'y ({frame}) [mm]', f'z ({frame}) [mm]',
               'rotation about long axis [deg]')
    names = ('x', 'y', 'z', 'rotation')
    marked_total = 0
    for b, (body, body_frame) in enumerate(zip(table.bodies, table.body_frames)):
        position_mm = np.asarray(table.position_m[b], dtype=np.float64) * 1e3    # (F, V, 3)
        rotation = matrix_from_quat(table.orientation_xyzw[b])                     # (F, V, 3, 3)
        spin_deg = np.degrees(np.unwrap(axes.decompose(rotation)[2], axis=0))       # (F, V)
        series = (position_mm[..., 0], position_mm[..., 1], position_mm[..., 2], spin_deg)
        bad = ~converged[b][:, [c for c, _ in columns]]                             # (F, k)
        marked = int(bad.sum())
        marked_total += marked
        for j, (values, ylabel, name) in enumerate(zip(series, ylabels, names)):
            ax = grid[b, j]
            for k, (c, _) in enumerate(columns):
                ax.plot(flexion_deg, values[:, c], color=_CURVE_COLOURS[k % len(_CURVE_COLOURS)],
                        linewidth=1.5, marker='.', markersize=3)
                rows = np.flatnonzero(bad[:, k])
                if rows.size:
                    ax.plot(flexion_deg[rows], values[rows, c], linestyle='none', marker='x',
                            markersize=7, markeredgewidth=2.0, color=MARKER_RGB, zorder=5)
            ax.set_ylabel(ylabel)
            label = body if body_frame == body else f'{body} ({body_frame})'
            label += f': {name}' + (f', {marked} not converged' if marked and j == 0 else '')
            ax.set_title(label, fontsize=10)
            ax.grid(True, linewidth=0.5, alpha=0.5)
            if b == n_bodies - 1:
                ax.set_xlabel('flexion [deg]')

    handles = [Line2D([], [], color=_CURVE_COLOURS[k % len(_CURVE_COLOURS)], linewidth=1.5,
                      label=label) for k, (_, label) in enumerate(columns)]
    handles.append(Line2D([], [], linestyle='none', marker='x', markersize=7,
                          markeredgewidth=2.0, color=MARKER_RGB,
                          label=f'not converged ({marked_total})'))
    fig.legend(handles=handles, loc='outside lower center', ncol=min(len(handles), 6))
    fig.suptitle(title if title is not None else _default_title(table))
    log.info('plot of %s: %d bodies, %d varus columns, %d non-converged points marked',
             _table_name(table), n_bodies, len(columns), marked_total)
    return write_png(fig, out, {PNG_KEY_NONCONVERGED: str(marked_total),
                                PNG_KEY_TABLE: _table_name(table)})


_REASON_COLOURS = ('tab:red', 'tab:orange', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:olive',
                   'tab:cyan', 'black')


def plot_convergence_map(table: PoseTable, out: Path) -> Path:
    """Map of every moving body's cells that did not end at a plain rest, coloured by how
    their settle ended (`PoseTable.status`).

    One panel per body: varus (deg) across, flexion (deg) down; cells at rest pale, every
    other cell coloured by its status (rests on the boundary of an envelope that holds,
    cells that left the search envelope, lost contact, ...; a table written without status
    codes shows its non-converged cells as 'not converged'). The legend gives the count
    per status; the panel title the converged share.

    Returns:
        `out`, the PNG written. Its `kneeseat:nonconverged` text is the number of cells drawn
        as not converged.

    Raises:
        ConfigError: `out` does not end in .png or cannot be written.
    """
    out = _checked_out(out)
    flexion_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    varus_deg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    converged = np.asarray(table.converged, dtype=bool)
    codes = table.status
    reasons: list[str] = []
    cells: list[dict[tuple[int, int], str]] = []
    for b in range(len(table.bodies)):
        by_cell = {(int(i), int(j)): STATUS_NAMES.get(int(codes[b, i, j]), 'not converged')
                   for i, j in zip(*np.nonzero(codes[b] != Status.REST))}
        cells.append(by_cell)
        reasons.extend(r for r in by_cell.values() if r not in reasons)
    colour = {r: _REASON_COLOURS[k % len(_REASON_COLOURS)] for k, r in enumerate(reasons)}
    n = len(table.bodies)
    fig = Figure(figsize=(4.5 * n, 6.5), dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    axs = fig.subplots(1, n, squeeze=False)[0]
    half_f = 0.5 * (np.diff(flexion_deg).min() if flexion_deg.size > 1 else 1.0)
    half_v = 0.5 * (np.diff(varus_deg).min() if varus_deg.size > 1 else 1.0)
    total = 0
    for b, (ax, body) in enumerate(zip(axs, table.bodies)):
        ax.add_patch(Rectangle((varus_deg[0] - half_v, flexion_deg[0] - half_f),
                               varus_deg[-1] - varus_deg[0] + 2 * half_v,
                               flexion_deg[-1] - flexion_deg[0] + 2 * half_f,
                               facecolor='0.93', edgecolor='0.6'))
        for (i, j), reason in cells[b].items():
            ax.add_patch(Rectangle((varus_deg[j] - half_v, flexion_deg[i] - half_f),
                                   2 * half_v, 2 * half_f, facecolor=colour[reason],
                                   edgecolor='none'))
        missed = int((~converged[b]).sum())
        total += missed
        share = 100.0 * converged[b].mean()
        ax.set_title(f'{body}: {share:.1f}% converged ({missed} not)', fontsize=10)
        ax.set_xlim(varus_deg[0] - half_v, varus_deg[-1] + half_v)
        ax.set_ylim(flexion_deg[0] - half_f, flexion_deg[-1] + half_f)
        ax.set_xlabel('varus [deg]')
        if b == 0:
            ax.set_ylabel('flexion [deg]')
    counts = {r: sum(1 for c in cells for v in c.values() if v == r) for r in reasons}
    handles = [Patch(facecolor='0.93', edgecolor='0.6', label='rest')]
    handles += [Patch(facecolor=colour[r], label=f'{r} ({counts[r]})') for r in reasons]
    fig.legend(handles=handles, loc='outside lower center', ncol=1, fontsize=8)
    fig.suptitle(f'{_table_name(table)}: cells that did not converge')
    return write_png(fig, out, {PNG_KEY_NONCONVERGED: str(total),
                                PNG_KEY_TABLE: _table_name(table)})


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
    out = _checked_out(out)
    if view not in ('lateral', 'anterior'):
        raise ConfigError(f"view={view!r} is not a view; use 'lateral' or 'anterior'")
    reference = str(table.metadata['reference']['name'])
    _check_meshes(meshes, reference, table.bodies)
    grid_flexion_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    grid_varus_deg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    v_col = int(np.argmin(np.abs(grid_varus_deg)))
    angles = _flexion_angles(grid_flexion_deg, flexion_deg)

    knee = table.axes
    toward = knee.flexion if view == 'lateral' else knee.varus     # points at the viewer
    up = unit(knee.long - (knee.long @ toward) * toward, 'long axis')
    right = np.cross(up, toward)
    light = unit(toward + 0.5 * up + 0.3 * right, 'light')
    screen = np.stack([right, up])                                  # (2, 3)

    names = (reference, *table.bodies)
    colours = (_REFERENCE_RGB, *(_BODY_RGB[i % len(_BODY_RGB)] for i in range(len(names) - 1)))
    simple = [_simplified(meshes[name], RENDER_MAX_FACES) for name in names]

    panels = []
    for angle_deg, node in angles:
        poses, stale = _poses_at(table, angle_deg, node, v_col, grid_varus_deg[v_col])
        polys, rgb = _project(simple, colours, poses, toward, screen, light)
        panels.append((angle_deg, polys, rgb, stale))
    corners = np.concatenate([p.reshape(-1, 2) for _, p, _, _ in panels])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = 0.05 * float((hi - lo).max())

    n = len(panels)
    fig = Figure(figsize=(n * RENDER_PANEL_IN[0], RENDER_PANEL_IN[1] + RENDER_EXTRA_IN),
                 dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    axs = fig.subplots(1, n, squeeze=False)[0]
    frame = table.reference_frame
    stale_total = 0
    for i, (ax, (angle_deg, polys, rgb, stale)) in enumerate(zip(axs, panels)):
        ax.add_collection(PolyCollection(polys, facecolors=rgb, edgecolors=rgb,
                                         linewidths=0.3))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect('equal', adjustable='box')
        label = f'flexion {angle_deg:.1f}°'
        if stale:
            label += '\nnot converged: ' + ', '.join(stale)
        stale_total += len(stale)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel(f'{_direction_name(right, frame)} [mm]')
        if i == 0:
            ax.set_ylabel(f'{_direction_name(up, frame)} [mm]')
        ax.tick_params(labelsize=8)
    handles = [Patch(facecolor=c, edgecolor='0.3',
                     label=f'{name} (reference)' if name == reference else name)
               for name, c in zip(names, colours)]
    fig.legend(handles=handles, loc='outside lower center', ncol=len(handles))
    fig.suptitle(f'{_table_name(table)}: {view} view, varus {grid_varus_deg[v_col]:.1f}°')
    path = write_png(fig, out, {PNG_KEY_NONCONVERGED: str(stale_total),
                                PNG_KEY_TABLE: _table_name(table)})
    log.info('render of %s: %d panels, %s view, %.2f s', _table_name(table), n, view,
             time.perf_counter() - started)
    return path


def _checked_out(out: Path) -> Path:
    """`out` as a Path; it must name a .png file."""
    path = Path(out)
    if path.suffix.lower() != '.png':
        raise ConfigError(f'out={str(path)!r} does not end in .png; the picture is a PNG, '
                          'give a path such as table.png')
    return path


def write_png(fig: Figure, out: Path, text: dict[str, str] | None = None) -> Path:
    """Save `fig` to `out` atomically (`kneeseat_core.files.atomic_write`).

    Raises:
        ConfigError: the directory cannot be created or the file cannot be written.
    """
    def save(stream: BinaryIO) -> None:
        fig.savefig(stream, format='png', dpi=DPI,
                    metadata={'Software': 'kneeseat', **(text or {})})

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out, save)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConfigError(f'cannot write picture {str(out)!r}: {reason}; '
                          'choose a writable path ending in .png') from None
    return out


def _finite_angles(values: Sequence[float], name: str) -> Floats:
    """`values` (n,) deg as float64; a non-empty sequence of finite numbers."""
    try:
        angles = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f'{name}={values!r} is not a list of numbers; '
                          'give angles in degrees such as -30,0,30') from None
    if angles.size == 0 or not np.all(np.isfinite(angles)):
        raise ConfigError(f'{name}={values!r} must hold at least one finite angle (deg); '
                          'give angles in degrees such as -30,0,30')
    return angles


def _outside(name: str, value: float, grid_deg: Floats) -> ConfigError:
    """The error for an angle outside the table grid."""
    return ConfigError(f'{name}={value:g} deg outside the table [{grid_deg[0]:g}, '
                       f'{grid_deg[-1]:g}] deg; pick angles inside the grid')


def _varus_columns(grid_deg: Floats, requested: Sequence[float] | None
                   ) -> list[tuple[int, str]]:
    """Varus columns to draw, each with its legend label, in request order, unique."""
    if requested is None:
        picks = sorted({0, int(np.argmin(np.abs(grid_deg))), len(grid_deg) - 1})
        return [(c, f'varus {grid_deg[c]:g}°') for c in picks]
    columns: list[tuple[int, str]] = []
    for value in _finite_angles(requested, 'varus_deg'):
        if not grid_deg[0] - TOL.grid_match_deg <= value <= grid_deg[-1] + TOL.grid_match_deg:
            raise _outside('varus_deg', float(value), grid_deg)
        c = int(np.argmin(np.abs(grid_deg - value)))
        if any(c == seen for seen, _ in columns):
            continue
        if abs(grid_deg[c] - value) <= TOL.grid_match_deg:
            columns.append((c, f'varus {grid_deg[c]:g}°'))
        else:
            columns.append((c, f'varus {value:g}° → {grid_deg[c]:g}° (nearest grid)'))
    return columns


def _flexion_angles(grid_deg: Floats, requested: Sequence[float] | None
                    ) -> list[tuple[float, int | None]]:
    """(angle deg, grid node or None when between nodes) for each panel, in order."""
    if requested is None:
        count = min(_DEFAULT_RENDER_PANELS, len(grid_deg))
        targets = np.linspace(grid_deg[0], grid_deg[-1], count)
        nodes = sorted({int(np.argmin(np.abs(grid_deg - t))) for t in targets})
        return [(float(grid_deg[f]), f) for f in nodes]
    angles = _finite_angles(requested, 'flexion_deg')
    if angles.size > RENDER_MAX_PANELS:
        raise ConfigError(f'flexion_deg has {angles.size} angles; draw at most '
                          f'{RENDER_MAX_PANELS} per picture')
    result: list[tuple[float, int | None]] = []
    for value in angles:
        if not grid_deg[0] - TOL.grid_match_deg <= value <= grid_deg[-1] + TOL.grid_match_deg:
            raise _outside('flexion_deg', float(value), grid_deg)
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
                              'load it with trimesh (kneeseat_core.meshes)')
    for name in meshes:
        if name not in wanted:
            raise ConfigError(f'meshes has {name!r}, which is not a body of the table; '
                              f'use the names {list(wanted)}')


def _simplified(mesh: trimesh.Trimesh, max_faces: int) -> tuple[Floats, np.ndarray, bool]:
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


def _poses_at(table: PoseTable, angle_deg: float, node: int | None, v_col: int,
              varus_deg: float) -> tuple[list[Floats], list[str]]:
    """(4, 4) reference_from_body for [reference, *bodies] and the non-converged bodies."""
    poses = [np.eye(4)]
    stale: list[str] = []
    converged = np.asarray(table.converged, dtype=bool)
    if node is not None:
        rotations = matrix_from_quat(np.asarray(table.orientation_xyzw)[:, node, v_col])
        positions = np.asarray(table.position_m, dtype=np.float64)[:, node, v_col]
        flags = ~converged[:, node, v_col]
    else:
        lookup = table.interpolate(math.radians(angle_deg), math.radians(varus_deg))
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


def _project(meshes: Sequence[tuple[Floats, np.ndarray, bool]],
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


def _table_name(table: PoseTable) -> str:
    """The table's file name if the metadata has it, else its name, else 'pose table'."""
    meta = table.metadata
    for key in ('file', 'path', 'table'):
        if isinstance(meta.get(key), str) and meta[key]:
            return Path(meta[key]).name
    config = meta.get('config')
    for source in (meta, config if isinstance(config, dict) else {}):
        if isinstance(source.get('name'), str) and source['name']:
            return str(source['name'])
    return 'pose table'


def _default_title(table: PoseTable) -> str:
    """Table name, then each mesh with the first 8 hex of its SHA-256."""
    meta = table.metadata
    entries = [meta.get('reference', {}), *meta.get('bodies', [])]
    hashes = ', '.join(f'{e.get("name", "?")} {str(e.get("mesh_sha256") or "?")[:8]}'
                       for e in entries)
    return f'{_table_name(table)}\nmeshes: {hashes}'
