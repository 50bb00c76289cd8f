"""What `kneeseat kinematics` writes of a table's secondary motions: CSV, Markdown, a figure.

The quantities and their definitions are `kneeseat_core.report.kinematics`; here they become one
CSV row and one Markdown row per knee flexion angle (a value from a non-converged cell is
starred), and a figure with one panel per quantity beside published values
(`read_reference`) and other tables' curves.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
import csv
import io
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np

from kneeseat_core.errors import ConfigError
from kneeseat_core.table import write_text
from .kinematics import KneeKinematics, QUANTITIES
from .plots import DPI, MARKER_RGB, write_png

__all__ = ['kinematics_rows', 'kinematics_markdown', 'write_kinematics_csv',
           'read_reference', 'plot_kinematics']


def _body_of(quantity: str) -> str:
    return quantity.split('_', 1)[0]


def kinematics_rows(kin: KneeKinematics) -> list[dict[str, object]]:
    """One dict per angle: knee_flexion_deg, each quantity, and the non-converged bodies."""
    rows = []
    for i, angle in enumerate(kin.knee_flexion_deg.tolist()):
        row: dict[str, object] = {'knee_flexion_deg': angle}
        row.update({q: float(v[i]) for q, v in kin.values.items()})
        row['nonconverged'] = ' '.join(b for b, f in kin.nonconverged.items() if f[i])
        rows.append(row)
    return rows


def kinematics_markdown(kin: KneeKinematics, digits: int = 1) -> str:
    """A Markdown table, one row per angle; a value from a non-converged cell gets '*'."""
    quantities = [q for q in QUANTITIES if q in kin.values]
    head = ['knee flexion (deg)'] + [f'{QUANTITIES[q][1]} ({QUANTITIES[q][0]})'
                                     for q in quantities]
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for i, angle in enumerate(kin.knee_flexion_deg.tolist()):
        cells = [f'{angle:g}']
        for q in quantities:
            star = '*' if kin.nonconverged[_body_of(q)][i] else ''
            cells.append(f'{kin.values[q][i]:.{digits}f}{star}')
        lines.append('| ' + ' | '.join(cells) + ' |')
    notes = ['changes from the first angle (patellar flexion: its own value)']
    notes += [f'{QUANTITIES[q][1]} there: {v:.{digits}f} deg relative to the meshes as delivered'
              for q, v in kin.at_first.items()]
    if any(f.any() for f in kin.nonconverged.values()):
        notes.append('* from a non-converged cell')
    return '\n'.join(lines) + '\n\n' + '; '.join(notes) + '.\n'


def write_kinematics_csv(kin: KneeKinematics, out: Path) -> Path:
    """Write `kinematics_rows` as CSV, atomically."""
    rows = kinematics_rows(kin)
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator='\n')
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f'{v:.6g}' if isinstance(v, float) else v) for k, v in row.items()})
    return write_text(out, text.getvalue())


def read_reference(path: Path) -> list[dict[str, str | float]]:
    """Published values to draw beside a table's: CSV with columns source, quantity,
    knee_flexion_deg, value (quantity one of QUANTITIES); other columns are kept.

    Raises:
        ConfigError: unreadable file, missing column, unknown quantity or a bad number.
    """
    try:
        text = Path(path).read_text()
    except OSError as err:
        raise ConfigError(f'{path}: cannot read the reference CSV ({err.strerror}); '
                          'check the path') from None
    rows = list(csv.DictReader(line for line in text.splitlines()
                               if line.strip() and not line.startswith('#')))
    need = ('source', 'quantity', 'knee_flexion_deg', 'value')
    out: list[dict[str, str | float]] = []
    for n, row in enumerate(rows, start=2):
        missing = [k for k in need if not row.get(k)]
        if missing:
            raise ConfigError(f'{path}: row {n} lacks {missing[0]!r}; give columns '
                              f'{", ".join(need)}')
        if row['quantity'] not in QUANTITIES:
            raise ConfigError(f'{path}: row {n}: unknown quantity {row["quantity"]!r}; use '
                              f'one of {", ".join(QUANTITIES)}')
        try:
            angle, value = float(row['knee_flexion_deg']), float(row['value'])
        except ValueError:
            raise ConfigError(f'{path}: row {n}: knee_flexion_deg and value must be '
                              'numbers') from None
        out.append({**row, 'knee_flexion_deg': angle, 'value': value})
    return out


_MARKERS = ('o', 's', '^', 'D', 'v', 'P', 'X', '<', '>', 'h')


def plot_kinematics(kin: KneeKinematics, out: Path, *, title: str,
                    reference: Sequence[Mapping[str, str | float]] = (),
                    others: Mapping[str, KneeKinematics] | None = None) -> Path:
    """One panel per quantity against knee flexion; published values as markers.

    Args:
        kin: the table's kinematics (a line; non-converged points as red crosses).
        out: PNG path.
        title: figure title and the table's legend label.
        reference: rows of `read_reference` (one marker style per source).
        others: more tables' kinematics to draw as dashed lines, by label (their
            non-converged cells are left out of the line).
    """
    quantities = [q for q in QUANTITIES if q in kin.values]
    cols = 4
    rows = -(-len(quantities) // cols)
    fig = Figure(figsize=(4.0 * cols, 3.0 * rows + 1.2), dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    axs = fig.subplots(rows, cols, squeeze=False).ravel()
    sources = sorted({str(r['source']) for r in reference})
    style = {s: _MARKERS[i % len(_MARKERS)] for i, s in enumerate(sources)}
    for ax, q in zip(axs, quantities):
        unit_, label = QUANTITIES[q]
        ax.plot(kin.knee_flexion_deg, kin.values[q], color='tab:blue', lw=1.8, label=title)
        bad = kin.nonconverged[_body_of(q)]
        if bad.any():
            ax.plot(kin.knee_flexion_deg[bad], kin.values[q][bad], 'x', color=MARKER_RGB,
                    ms=7, mew=2, label='not converged')
        for k, (name, other) in enumerate((others or {}).items()):
            if q in other.values:       # converged cells only: a gap where it did not
                shown = np.where(other.nonconverged[_body_of(q)], np.nan, other.values[q])
                ax.plot(other.knee_flexion_deg, shown, '--', lw=1.2,
                        color=('tab:orange', 'tab:green', 'tab:purple')[k % 3],
                        label=f'{name} (converged cells)')
        for src in sources:
            pts = [(float(r['knee_flexion_deg']), float(r['value'])) for r in reference
                   if r['source'] == src and r['quantity'] == q]
            if pts:
                x, y = zip(*pts)
                ax.plot(x, y, linestyle='none', marker=style[src], color='0.25', ms=5,
                        label=src)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel('knee flexion [deg]')
        ax.set_ylabel(f'[{unit_}]')
        ax.grid(True, lw=0.5, alpha=0.5)
        ax.legend(fontsize=6)
    for ax in axs[len(quantities):]:
        ax.set_visible(False)
    fig.suptitle(f'{title} (varus {kin.varus_deg:g} deg)')
    return write_png(fig, Path(out))
