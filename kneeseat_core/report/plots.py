"""Pictures of a pose table: its curves against flexion, its convergence map, a session.

The public functions are headless (a `matplotlib.figure.Figure` of their own drawn on an
Agg canvas; no pyplot, so no global state leaks between calls), each writing one PNG
atomically (`kneeseat_core.files.atomic_write`):

- `plot_table`: per moving body, the three translations (mm, reference frame) and the
  rotation about the long axis (deg) against flexion (deg), one curve per chosen varus
  column; non-converged cells marked with red crosses.
- `plot_convergence_map`: per moving body, the (flexion, varus) grid with every
  cell that did not end at a plain rest coloured by its status (`PoseTable.status`).
- `plot_session`: recorded answers of a node (translations and spin against the input's
  flexion) over the table's own curve at varus 0 (the demo's picture).
The bones themselves are drawn by `kneeseat_core.report.render`.

The table's pictures (`plot_table`, `plot_convergence_map` and the renders) carry tEXt
chunks `kneeseat:nonconverged` (number of non-converged points marked, or of bodies drawn
from non-converged cells) and `kneeseat:table` (the table name), so scripts and tests can
read what was drawn without parsing pixels.
"""
from __future__ import annotations

from collections.abc import Sequence
import logging
import math
from pathlib import Path
from typing import BinaryIO

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
import numpy as np

from kneeseat_core.errors import ConfigError
from kneeseat_core.files import atomic_write, unwritable
from kneeseat_core.geometry import matrix_from_quat, TOL
from kneeseat_core.status import converged_share, Status, STATUS_NAMES
from kneeseat_core.table import mesh_entries, PoseTable
from kneeseat_core.typed import Bools, Floats

__all__ = ['DPI', 'PLOT_PANEL_IN', 'PLOT_EXTRA_IN', 'SESSION_SIZE_PX', 'MARKER_RGB',
           'PNG_KEY_NONCONVERGED', 'PNG_KEY_TABLE', 'plot_table', 'plot_convergence_map',
           'plot_session', 'write_png', 'checked_png_path', 'finite_angles', 'outside_grid',
           'table_name']

log = logging.getLogger(__name__)

DPI = 100                          # pixels per inch of every PNG written here
PLOT_PANEL_IN = (3.5, 2.75)        # (width, height) of one plot_table subplot, inches
PLOT_EXTRA_IN = 1.5                # plot_table: title + legend band, inches
MARKER_RGB = (1.0, 0.0, 0.0)       # non-converged markers; no other element uses pure red
PNG_KEY_NONCONVERGED = 'kneeseat:nonconverged'
PNG_KEY_TABLE = 'kneeseat:table'
SESSION_SIZE_PX = (1400, 900)      # (width, height) of a plot_session PNG, pixels
MIN_SPIN_SPAN_DEG = 1.0            # plot_session: spin axes show at least this range

# Curve colours: Tableau without its red, so that red means "not converged" only.
_CURVE_COLOURS = ('tab:blue', 'tab:orange', 'tab:green', 'tab:purple', 'tab:brown',
                  'tab:pink', 'tab:gray', 'tab:olive', 'tab:cyan')


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
    out = checked_png_path(out)
    if not table.bodies:
        raise ConfigError('the table has no moving bodies, so there is nothing to plot; '
                          'build it with at least one moving body')
    flexion_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    grid_varus_deg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    columns = _varus_columns(grid_varus_deg, varus_deg)
    axes = table.axes
    n_bodies = len(table.bodies)
    converged = np.asarray(table.converged, dtype=bool)

    fig = Figure(figsize=(4 * PLOT_PANEL_IN[0], n_bodies * PLOT_PANEL_IN[1] + PLOT_EXTRA_IN),
                 dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    grid = fig.subplots(n_bodies, 4, squeeze=False, sharex=True)
    marked_total = 0
    for b in range(n_bodies):
        position_mm = np.asarray(table.position_m[b], dtype=np.float64) * 1e3    # (F, V, 3)
        rotation = matrix_from_quat(table.orientation_xyzw[b])                     # (F, V, 3, 3)
        spin_deg = np.degrees(np.unwrap(axes.decompose(rotation)[2], axis=0))       # (F, V)
        series = (position_mm[..., 0], position_mm[..., 1], position_mm[..., 2], spin_deg)
        bad = ~converged[b][:, [c for c, _ in columns]]                             # (F, k)
        marked_total += int(bad.sum())
        _body_row(grid[b], table, b, flexion_deg, series, columns, bad,
                  last=b == n_bodies - 1)

    handles = [Line2D([], [], color=_CURVE_COLOURS[k % len(_CURVE_COLOURS)], linewidth=1.5,
                      label=label) for k, (_, label) in enumerate(columns)]
    handles.append(Line2D([], [], linestyle='none', marker='x', markersize=7,
                          markeredgewidth=2.0, color=MARKER_RGB,
                          label=f'not converged ({marked_total})'))
    fig.legend(handles=handles, loc='outside lower center', ncol=min(len(handles), 6))
    fig.suptitle(title if title is not None else _default_title(table))
    log.info('plot of %s: %d bodies, %d varus columns, %d non-converged points marked',
             table_name(table), n_bodies, len(columns), marked_total)
    return write_png(fig, out, {PNG_KEY_NONCONVERGED: str(marked_total),
                                PNG_KEY_TABLE: table_name(table)})


def _body_row(row: Sequence[Axes], table: PoseTable, b: int, flexion_deg: Floats,
              series: Sequence[Floats], columns: list[tuple[int, str]], bad: Bools, *,
              last: bool) -> None:
    """plot_table's four panels of body `b`: x, y, z, rotation against flexion, one curve
    per varus column, non-converged cells as red crosses."""
    frame = table.reference_frame
    body, body_frame = table.bodies[b], table.body_frames[b]
    ylabels = (f'x ({frame}) [mm]', f'y ({frame}) [mm]', f'z ({frame}) [mm]',
               'rotation about long axis [deg]')
    marked = int(bad.sum())
    for j, (values, ylabel, name) in enumerate(zip(series, ylabels, ('x', 'y', 'z', 'rotation'))):
        ax = row[j]
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
        if last:
            ax.set_xlabel('flexion [deg]')


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
    out = checked_png_path(out)
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
    total = 0
    for b, (ax, body) in enumerate(zip(axs, table.bodies)):
        _map_panel(ax, flexion_deg, varus_deg, cells[b], colour)
        missed = int((~converged[b]).sum())
        total += missed
        share = converged_share(int(converged[b].sum()), converged[b].size)
        ax.set_title(f'{body}: {share} converged ({missed} not)', fontsize=10)
        if b == 0:
            ax.set_ylabel('flexion [deg]')
    counts = {r: sum(1 for c in cells for v in c.values() if v == r) for r in reasons}
    handles = [Patch(facecolor='0.93', edgecolor='0.6', label='rest')]
    handles += [Patch(facecolor=colour[r], label=f'{r} ({counts[r]})') for r in reasons]
    fig.legend(handles=handles, loc='outside lower center', ncol=1, fontsize=8)
    fig.suptitle(f'{table_name(table)}: cells that did not converge')
    return write_png(fig, out, {PNG_KEY_NONCONVERGED: str(total),
                                PNG_KEY_TABLE: table_name(table)})


def checked_png_path(out: Path) -> Path:
    """`out` as a Path; it must name a .png file."""
    path = Path(out)
    if path.suffix.lower() != '.png':
        raise ConfigError(f'out={str(path)!r} does not end in .png; the picture is a PNG, '
                          'give a path such as table.png')
    return path


def _map_panel(ax: Axes, flexion_deg: Floats, varus_deg: Floats,
               cells: dict[tuple[int, int], str], colour: dict[str, str]) -> None:
    """One body's convergence map: the grid pale, each listed cell in its status's colour."""
    half_f = 0.5 * (np.diff(flexion_deg).min() if flexion_deg.size > 1 else 1.0)
    half_v = 0.5 * (np.diff(varus_deg).min() if varus_deg.size > 1 else 1.0)
    ax.add_patch(Rectangle((varus_deg[0] - half_v, flexion_deg[0] - half_f),
                           varus_deg[-1] - varus_deg[0] + 2 * half_v,
                           flexion_deg[-1] - flexion_deg[0] + 2 * half_f,
                           facecolor='0.93', edgecolor='0.6'))
    for (i, j), reason in cells.items():
        ax.add_patch(Rectangle((varus_deg[j] - half_v, flexion_deg[i] - half_f),
                               2 * half_v, 2 * half_f, facecolor=colour[reason],
                               edgecolor='none'))
    ax.set_xlim(varus_deg[0] - half_v, varus_deg[-1] + half_v)
    ax.set_ylim(flexion_deg[0] - half_f, flexion_deg[-1] + half_f)
    ax.set_xlabel('varus [deg]')


_XYZ_COLOURS = ('tab:blue', 'tab:orange', 'tab:green')


def plot_session(table: PoseTable, input_xyzw: Floats, position_m: Floats,
                 orientation_xyzw: Floats, out: Path, *, name: str) -> Path:
    """Recorded answers against the input's flexion, over the table at varus 0, as a PNG.

    Per moving body (rows): translations x, y, z (mm, reference frame) and the spin about
    the long axis (deg) of each answer against the flexion of its input (deg, decoded with
    the table's axes) as dots, and `table.interpolate(flexion, 0)` as lines.
    `SESSION_SIZE_PX` pixels.

    Args:
        table: the served table.
        input_xyzw: (n, 4) the answered inputs' orientations (x, y, z, w).
        position_m: (n, B, 3) and orientation_xyzw: (n, B, 4), the answers.
        out: PNG path.
        name: the session's name, for the title.
    Raises:
        ConfigError: no answer to draw, or the file cannot be written.
    """
    if len(input_xyzw) == 0:
        raise ConfigError(f'{name} has no answered input to plot')
    axes = table.axes
    flex_in, varus_in, _ = axes.decompose(matrix_from_quat(input_xyzw))
    flex_in_deg = np.degrees(flex_in)
    spin_out = np.degrees(axes.decompose(matrix_from_quat(orientation_xyzw))[2])
    lo, hi = float(table.flexion_rad[0]), float(table.flexion_rad[-1])
    curve_rad = np.linspace(lo, hi, 181)
    varus0 = min(max(0.0, float(table.varus_rad[0])), float(table.varus_rad[-1]))
    looks = [table.interpolate(f, varus0) for f in curve_rad.tolist()]
    curve_pos = np.stack([lk.position_m for lk in looks]) * 1e3                # (m, B, 3)
    curve_spin = np.degrees(axes.decompose(matrix_from_quat(
        np.stack([lk.orientation_xyzw for lk in looks])))[2])                  # (m, B)
    curve_deg = np.degrees(curve_rad)
    fig = Figure(figsize=(SESSION_SIZE_PX[0] / DPI, SESSION_SIZE_PX[1] / DPI), dpi=DPI,
                 layout='constrained')
    FigureCanvasAgg(fig)
    grid = fig.subplots(len(table.bodies), 2, squeeze=False)
    for b, body in enumerate(table.bodies):
        ax_t, ax_s = grid[b]
        for c, (axis, colour) in enumerate(zip('xyz', _XYZ_COLOURS)):
            ax_t.plot(curve_deg, curve_pos[:, b, c], color=colour, lw=1.5,
                      label=f'{axis} table (varus {math.degrees(varus0):g} deg)')
            ax_t.scatter(flex_in_deg, position_m[:, b, c] * 1e3, s=4, color=colour,
                         alpha=0.5, edgecolors='none', label=f'{axis} recorded')
        ax_s.plot(curve_deg, curve_spin[:, b], color='tab:purple', lw=1.5,
                  label=f'table (varus {math.degrees(varus0):g} deg)')
        ax_s.scatter(flex_in_deg, spin_out[:, b], s=4, color='tab:purple', alpha=0.5,
                     edgecolors='none', label='recorded')
        _session_axes(ax_t, ax_s, body, table.reference_frame, (lo, hi))
        _min_span(ax_s, np.concatenate([curve_spin[:, b], spin_out[:, b]]), MIN_SPIN_SPAN_DEG)
    fig.suptitle(f'{name}: {len(input_xyzw)} answers (input varus '
                 f'{np.degrees(varus_in).min():.1f}..{np.degrees(varus_in).max():.1f} deg), '
                 f'table {table.metadata.get("name", "")} {len(table.flexion_rad)} x '
                 f'{len(table.varus_rad)}')
    return write_png(fig, Path(out))


def _session_axes(ax_t: Axes, ax_s: Axes, body: str, frame: str,
                  flexion_rad: tuple[float, float]) -> None:
    """Titles, labels, limits, grids and legends of one body's two session panels."""
    ax_t.set_title(f'{body}: translation in {frame!r}')
    ax_s.set_title(f'{body}: spin about the long axis')
    ax_t.set_ylabel('mm')
    ax_s.set_ylabel('deg')
    for ax in (ax_t, ax_s):
        ax.set_xlabel('flexion (deg, negative = flexed)')
        ax.set_xlim(math.degrees(flexion_rad[0]), math.degrees(flexion_rad[1]))
        ax.grid(True, alpha=0.3)
    ax_t.legend(fontsize=7, ncol=3, loc='best', markerscale=3)
    ax_s.legend(fontsize=7, loc='best', markerscale=3)


def _min_span(ax: Axes, values: Floats, span: float) -> None:
    """Show at least `span` on the y axis, so that round-off does not look like motion."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - 0.5 * span, mid + 0.5 * span)


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
        reason = unwritable(out) or err.strerror or type(err).__name__
        raise ConfigError(f'cannot write picture {str(out)!r}: {reason}; '
                          'choose a writable path ending in .png') from None
    return out


def finite_angles(values: Sequence[float], name: str) -> Floats:
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


def outside_grid(name: str, value: float, grid_deg: Floats) -> ConfigError:
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
    for value in finite_angles(requested, 'varus_deg'):
        if not grid_deg[0] - TOL.grid_match_deg <= value <= grid_deg[-1] + TOL.grid_match_deg:
            raise outside_grid('varus_deg', float(value), grid_deg)
        c = int(np.argmin(np.abs(grid_deg - value)))
        if any(c == seen for seen, _ in columns):
            continue
        if abs(grid_deg[c] - value) <= TOL.grid_match_deg:
            columns.append((c, f'varus {grid_deg[c]:g}°'))
        else:
            columns.append((c, f'varus {value:g}° → {grid_deg[c]:g}° (nearest grid)'))
    return columns


def table_name(table: PoseTable) -> str:
    """The table's name (its metadata's, else its config's), else 'pose table'."""
    meta = table.metadata
    config = meta.get('config')
    for source in (meta, config if isinstance(config, dict) else {}):
        if isinstance(source.get('name'), str) and source['name']:
            return str(source['name'])
    return 'pose table'


def _default_title(table: PoseTable) -> str:
    """Table name, then each body with the first 8 hex of each of its meshes' SHA-256."""
    meta = table.metadata
    entries = [meta.get('reference', {}), *meta.get('bodies', [])]
    hashes = ', '.join(f'{e.get("name", "?")} '
                       + '+'.join((sha or '?')[:8] for _, sha in mesh_entries(e))
                       for e in entries)
    return f'{table_name(table)}\nmeshes: {hashes}'
