"""`kneeseat info | lookup | export | plot | render | kinematics`: commands that read a table.

Each handler takes the parsed arguments and returns the exit code; errors are
`KneeseatError`s, which `kneeseat_core.cli.main` turns into one line on stderr. The table
commands need only numpy and the table package; the pictures import matplotlib and the
meshes trimesh inside their handlers (about 1 and 2 s of start-up that info, lookup and
export do without).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kneeseat_core.args import angles, EXIT_OK, vector3
from kneeseat_core.errors import ConfigError
from kneeseat_core.files import unwritable_directory
from kneeseat_core.geometry import KneeAxes, matrix_from_quat
from kneeseat_core.table import (describe, display_paths, export_csv, lookup_json, mesh_entries,
                                 PoseTable, read_table, status_map, write_text)

if TYPE_CHECKING:
    import trimesh

    from kneeseat_core.args import Subcommands

__all__ = ['register_commands']


def _cmd_info(args: argparse.Namespace) -> int:
    table = read_table(args.table)
    print(describe(table))
    if args.map:
        print(status_map(table))
    return EXIT_OK


def _cmd_lookup(args: argparse.Namespace) -> int:
    table = read_table(args.table)
    flexion, varus = math.radians(args.flexion_deg), math.radians(args.varus_deg)
    result = table.interpolate(flexion, varus, args.out_of_range)
    if args.json:
        print(json.dumps(lookup_json(table, result, flexion, varus)))
        return EXIT_OK
    axes: KneeAxes = table.axes
    print(f'flexion {args.flexion_deg:g} deg, varus {args.varus_deg:g} deg'
          + (' (clamped to the grid)' if result.clamped else ''))
    for i, (name, frame) in enumerate(zip(table.bodies, table.body_frames)):
        _, _, spin = axes.decompose(matrix_from_quat(result.orientation_xyzw[i]))
        flag = '  (uses a non-converged cell)' if result.nonconverged[i] else ''
        pos_mm = np.array2string(result.position_m[i] * 1e3, precision=3)
        print(f'{name} ({frame} in {table.reference_frame}): position {pos_mm} mm, '
              f'rotation about long axis {math.degrees(float(spin)):.3f} deg, '
              f'xyzw {np.array2string(result.orientation_xyzw[i], precision=6)}{flag}')
    return EXIT_OK


def _cmd_export(args: argparse.Namespace) -> int:
    export_csv(read_table(args.table), args.csv)
    print(f'wrote {args.csv}')
    return EXIT_OK


def _table_meshes(table: PoseTable, display: bool) -> dict[str, trimesh.Trimesh]:
    """Meshes named in a table's metadata, one (combined) mesh per body.

    A body with several meshes (e.g. a tibia's bone and menisci) is drawn as their union.
    """
    from kneeseat_core.meshes import load_meshes         # trimesh: start-up
    meta = table.metadata
    units = meta.get('config', {}).get('units', 'm')
    return {entry['name']: load_meshes(display_paths(entry) if display
                                       else [path for path, _ in mesh_entries(entry)], units)
            for entry in (meta['reference'], *meta['bodies'])}


def _cmd_plot(args: argparse.Namespace) -> int:
    from kneeseat_core.report import plot_convergence_map, plot_table     # matplotlib
    if args.map:
        out = plot_convergence_map(read_table(args.table), args.out)
        print(f'wrote {out}')
        return EXIT_OK
    out = plot_table(read_table(args.table), args.out, varus_deg=args.varus_deg)
    print(f'wrote {out}')
    return EXIT_OK


def _cmd_render(args: argparse.Namespace) -> int:
    from kneeseat_core.report import render_table                         # matplotlib
    table = read_table(args.table)
    out = render_table(table, _table_meshes(table, not args.implants), args.out,
                       flexion_deg=args.flexion_deg, view=args.view)
    print(f'wrote {out}')
    return EXIT_OK


def _cmd_kinematics(args: argparse.Namespace) -> int:
    from kneeseat_core.report import (DEFAULT_ANGLES_DEG, kinematics_markdown,  # matplotlib
                                      knee_kinematics, plot_kinematics, read_reference,
                                      table_landmarks, write_kinematics_csv)
    why = unwritable_directory(args.out_dir)
    if why is not None:
        raise ConfigError(f'--out-dir {args.out_dir}: cannot write the kinematics there '
                          f'({why}); give a directory that can be written or made')
    table = read_table(args.table)
    names = dict(tibia=args.tibia, patella=args.patella)
    marks = table_landmarks(table, side=args.side, tibia_point=args.tibia_point,
                            patella_point=args.patella_point, **names)
    angles = args.angles if args.angles is not None else list(DEFAULT_ANGLES_DEG)
    every = knee_kinematics(table, marks, side=args.side, **names)
    chosen = knee_kinematics(table, marks, angles_deg=angles, side=args.side, **names)
    reference = read_reference(args.reference) if args.reference else []
    csv_path = write_kinematics_csv(every, args.out_dir / 'kinematics.csv')
    md_path = write_text(args.out_dir / 'kinematics.md', kinematics_markdown(chosen))
    name = str(table.metadata.get('name') or args.table.stem)
    others = {}
    for path in args.compare or []:
        other = read_table(path)
        other_marks = table_landmarks(other, side=args.side, tibia_point=args.tibia_point,
                                      patella_point=args.patella_point, **names)
        label = str(other.metadata.get('name') or path.stem)
        others[label] = knee_kinematics(other, other_marks, side=args.side, **names)
    png = plot_kinematics(every, args.out_dir / 'kinematics.png', title=name,
                          reference=reference, others=others)
    print(kinematics_markdown(chosen), end='')
    written = [csv_path, md_path, png] + _ligament_report(table, args.out_dir, name,
                                                          args.mesh_dir)
    print(f'wrote {", ".join(str(w) for w in written)}')
    return EXIT_OK


def _ligament_report(table: PoseTable, out_dir: Path, name: str,
                     mesh_dir: Path | None) -> list[Path]:
    """ligaments.csv and ligaments.png for a table built with ligaments (none otherwise)."""
    from kneeseat_core.knee import ligaments_from_metadata           # trimesh
    from kneeseat_core.report import bundle_loads, plot_bundle_strains, write_bundle_csv
    ligaments = ligaments_from_metadata(table.metadata, mesh_dir)
    if ligaments is None:
        return []
    loads = bundle_loads(table, ligaments)
    return [write_bundle_csv(loads, out_dir / 'ligaments.csv'),
            plot_bundle_strains(loads, out_dir / 'ligaments.png', title=name)]


def register_commands(sub: Subcommands) -> None:
    """Add info, lookup, export, plot, render and kinematics to the `kneeseat` parser."""
    p = sub.add_parser('info', help='describe a table file: cells, continuity, failures')
    p.add_argument('table', type=Path)
    p.add_argument('--map', action='store_true',
                   help='also print a map of every cell by how its settle ended')
    p.set_defaults(command=_cmd_info)

    p = sub.add_parser('lookup', help='interpolate a table at one attitude')
    p.add_argument('table', type=Path)
    p.add_argument('--flexion-deg', type=float, required=True)
    p.add_argument('--varus-deg', type=float, default=0.0)
    p.add_argument('--out-of-range', choices=('clamp', 'drop'), default='clamp')
    p.add_argument('--json', action='store_true')
    p.set_defaults(command=_cmd_lookup)

    p = sub.add_parser('export', help='export a table as CSV')
    p.add_argument('table', type=Path)
    p.add_argument('--csv', type=Path, required=True, help='output CSV file')
    p.set_defaults(command=_cmd_export)

    p = sub.add_parser('plot', help='plot translations and rotation against flexion (PNG)')
    p.add_argument('table', type=Path)
    p.add_argument('--out', type=Path, required=True, help='output PNG')
    p.add_argument('--varus-deg', type=angles, help='varus values for the curves, e.g. -10,0,10')
    p.add_argument('--map', action='store_true',
                   help='draw the map of non-converged cells and their reasons instead')
    p.set_defaults(command=_cmd_plot)

    p = sub.add_parser('render', help='draw the bones at several flexion angles (PNG)')
    p.add_argument('table', type=Path)
    p.add_argument('--out', type=Path, required=True, help='output PNG')
    p.add_argument('--flexion-deg', type=angles, help='flexion angles, e.g. 0,-30,-60,-90')
    p.add_argument('--view', choices=('lateral', 'anterior'), default='lateral')
    p.add_argument('--implants', action='store_true',
                   help='draw the collision meshes even where display meshes exist')
    p.set_defaults(command=_cmd_render)

    p = sub.add_parser('kinematics', help='secondary motions at varus 0 against flexion '
                       '(CSV, Markdown table, PNG)')
    p.add_argument('table', type=Path)
    p.add_argument('--out-dir', type=Path, required=True,
                   help='directory for kinematics.csv, kinematics.md and kinematics.png')
    p.add_argument('--angles', type=angles, metavar='DEG,...',
                   help='knee flexion angles of the Markdown table, positive = flexed '
                   '(default 0,15,30,45,60,75,90)')
    p.add_argument('--side', choices=('right', 'left'), default='right', help='knee side')
    p.add_argument('--tibia', default='tibia', help='tibia body name (default tibia)')
    p.add_argument('--patella', default='patella', help='patella body name (default patella)')
    p.add_argument('--tibia-point', type=vector3, metavar='X,Y,Z',
                   help='tibial landmark (m, tibia frame) instead of its mesh centroid')
    p.add_argument('--patella-point', type=vector3, metavar='X,Y,Z',
                   help='patellar landmark (m, patella frame) instead of its mesh centroid')
    p.add_argument('--reference', type=Path, metavar='CSV',
                   help='published values to plot beside the table (source, quantity, '
                   'knee_flexion_deg, value)')
    p.add_argument('--compare', type=Path, action='append', metavar='TABLE',
                   help='another table to draw as a dashed line (repeatable)')
    p.add_argument('--mesh-dir', type=Path,
                   help="directory that holds the table's ligament file (a table built with "
                   'ligaments also gets ligaments.csv and ligaments.png)')
    p.set_defaults(command=_cmd_kinematics)
