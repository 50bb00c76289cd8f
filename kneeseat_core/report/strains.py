"""What the ligaments carry in a table: each bundle's strain and force against flexion.

For a table built with ligaments (`ligaments:` in its config), at one varus value (0 by
default), every bundle's straight-line strain (the largest of its fibres) and force (the
sum of its fibres' tensions) at each flexion value, with every body placed by the table's
own pose there: `kneeseat kinematics` writes them as `ligaments.csv` and draws the strains
as `ligaments.png`. Straight segments leave wrapping out, so the strains are lower bounds.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
import io
from pathlib import Path

import matplotlib
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np

from kneeseat_core.geometry import matrix_from_quat, pose_from
from kneeseat_core.ligaments import LigamentSet
from kneeseat_core.status import AT_REST
from kneeseat_core.table import PoseTable, write_text
from kneeseat_core.typed import Bools, Floats
from .plots import DPI, MARKER_RGB, write_png

__all__ = ['BundleLoads', 'bundle_loads', 'write_bundle_csv', 'plot_bundle_strains']


@dataclass(frozen=True, slots=True, eq=False)
class BundleLoads:
    """Per bundle and flexion value: strain and force, at one varus value."""

    flexion_deg: Floats        # (F,) as in the table (negative = flexed on shipped grids)
    varus_deg: float
    bundles: tuple[str, ...]   # (B,)
    strain: Floats             # (F, B) the largest fibre strain of each bundle
    force_n: Floats            # (F, B) the sum of its fibres' tensions
    converged: Bools           # (F,) every body of the table at rest there


def bundle_loads(table: PoseTable, ligaments: LigamentSet,
                 varus_deg: float = 0.0) -> BundleLoads:
    """Strain and force of every bundle at each flexion value of `table`, at the grid's
    varus value nearest `varus_deg`."""
    j = int(np.argmin(np.abs(np.degrees(table.varus_rad) - varus_deg)))
    meta = table.metadata
    reference = meta['reference']['name']
    bundles = ligaments.bundles
    member = np.array([[f.bundle == b for f in ligaments.fibres] for b in bundles])
    strain = np.empty((len(table.flexion_rad), len(bundles)))
    force = np.empty_like(strain)
    for i in range(len(table.flexion_rad)):
        poses = {reference: np.eye(4)}
        poses.update({name: pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                                      table.position_m[b, i, j])
                      for b, name in enumerate(table.bodies)})
        fibre_strain = ligaments.strains(poses)
        fibre_force = ligaments.forces(poses)
        strain[i] = [fibre_strain[m].max() for m in member]
        force[i] = [fibre_force[m].sum() for m in member]
    at_rest: Bools = np.asarray(np.isin(table.status[:, :, j], AT_REST).all(axis=0))
    return BundleLoads(np.degrees(table.flexion_rad), float(np.degrees(table.varus_rad[j])),
                       bundles, strain, force, at_rest)


def write_bundle_csv(loads: BundleLoads, out: Path) -> Path:
    """`flexion_deg, varus_deg, bundle, strain, force_n, converged`, one row per bundle and
    flexion value (atomic write)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator='\n')
    writer.writerow(['flexion_deg', 'varus_deg', 'bundle', 'strain', 'force_n', 'converged'])
    for i, flexion in enumerate(loads.flexion_deg.tolist()):
        for k, bundle in enumerate(loads.bundles):
            writer.writerow([f'{flexion:g}', f'{loads.varus_deg:g}', bundle,
                             f'{loads.strain[i, k]:.6f}', f'{loads.force_n[i, k]:.3f}',
                             int(loads.converged[i])])
    return write_text(Path(out), buf.getvalue())


def plot_bundle_strains(loads: BundleLoads, out: Path, *, title: str) -> Path:
    """Every bundle's strain (%) against flexion, one line each; cells not at rest marked."""
    fig = Figure(figsize=(9.0, 5.5), dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    x = loads.flexion_deg
    colours = matplotlib.colormaps['tab20']
    for k, bundle in enumerate(loads.bundles):
        ax.plot(x, 100.0 * loads.strain[:, k], lw=1.4, label=bundle,
                color=colours(k % 20), linestyle=('-', '--')[k // 20 % 2])
    bad = ~loads.converged
    if bad.any():
        ax.plot(x[bad], 100.0 * loads.strain[bad].max(axis=1), 'x', color=MARKER_RGB, ms=7,
                mew=2, label='a body not at rest')
    ax.axhline(0.0, color='0.4', lw=0.8)
    ax.set_xlabel('flexion [deg]')
    ax.set_ylabel('strain [%] (straight line, largest fibre)')
    ax.grid(True, lw=0.5, alpha=0.5)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(f'{title}: ligament strains at varus {loads.varus_deg:g} deg', fontsize=10)
    return write_png(fig, Path(out))
