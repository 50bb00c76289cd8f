"""`kneeseat verify`: the independent referee's verdict on settled poses.

One settle result (`--fixed/--moving/--push/--pose`, the pose as `kneeseat settle --json`
prints it or as a START.json), or the cells of a table (`kneeseat_core.referee.cells`). For
each pose the referee climbs the travel and reports what it gains and the move that gains
it. Exit 0 only when no converged cell gains more than the resolution; 3 when one does; 2 on
bad input. The referee loads trimesh, python-fcl and scipy's optimiser (about 3 s): the
handlers import it, so that `kneeseat --help` and the other commands start without.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from kneeseat_core.args import (default_workers, EXIT_NOT_CONVERGED, EXIT_OK, vector3,
                                worker_count)
from kneeseat_core.errors import ConfigError, MeshError, NoContactError, TableError
from kneeseat_core.params import SettleParams
from kneeseat_core.status import AT_REST
from kneeseat_core.table import read_table
from kneeseat_core.typed import Pose
from .settle_command import load_start_pose

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands
    from kneeseat_core.referee import CellVerdict

__all__ = ['register_command']

# the exit codes of `kneeseat settle`: at rest as converged, not at rest as not converged
EXIT_AT_REST, EXIT_NOT_AT_REST = EXIT_OK, EXIT_NOT_CONVERGED


def _cmd_verify(args: argparse.Namespace) -> int:
    if args.table is not None:
        return _verify_table_cmd(args)
    return _verify_one_cmd(args)


def _verify_table_cmd(args: argparse.Namespace) -> int:
    from kneeseat_core.knee import config_from_metadata, ligaments_from_metadata  # trimesh
    from kneeseat_core.meshes import check_mesh_files
    from kneeseat_core.referee import (changed_cells, mesh_file, sample_cells,  # fcl, scipy
                                       verify_table)
    from kneeseat_core.sweep import executor_for
    if args.fixed or args.moving or args.pose:
        raise TableError('give either a TABLE or --fixed/--moving/--pose, not both')
    if args.sample is not None and args.sample < 1:
        raise TableError(f'--sample {args.sample}: give a positive number of cells')
    if args.seed < 0:
        raise TableError(f'--seed {args.seed}: give a seed of 0 or more')
    if args.sample is not None and args.changed_from is not None:
        raise TableError('give --sample or --changed-from, not both')
    if not (args.changed_deg >= 0.0):
        raise TableError(f'--changed-deg {args.changed_deg}: give an angle of 0 or more')
    table = read_table(args.table)
    config = config_from_metadata(table.metadata)
    mesh_dir = None if args.mesh_dir is None else str(args.mesh_dir)
    paths = [mesh_file(p, mesh_dir) for spec in (config.reference, *config.bodies)
             for p in spec.meshes]
    missing = [p for p in paths if not Path(p).is_file()]
    if missing:
        raise MeshError(f"{missing[0]}: the table's mesh is not there; pass --mesh-dir DIR, "
                        f"the folder that holds {Path(missing[0]).name} and the table's other "
                        f'meshes')
    check_mesh_files(paths, config.units)     # warnings once, here; workers load quietly
    ligaments_from_metadata(table.metadata, args.mesh_dir)    # there, and the table's
    resolution = float(table.metadata.get('settle', {}).get('resolution_m', 1e-4))
    changed = None
    if args.changed_from is None:
        cells = sample_cells(table, args.sample, args.seed)
    else:
        try:
            cells, changed = changed_cells(table, read_table(args.changed_from), resolution,
                                           args.changed_deg)
        except TableError as e:
            raise TableError(f'--changed-from {args.changed_from}: {e}') from None
    executor, close = executor_for(args.workers, None)
    verdicts: list[CellVerdict] = []
    try:
        with tqdm(total=len(cells), unit='cell', desc='verify', disable=args.quiet,
                  dynamic_ncols=True, file=sys.stderr) as bar:
            for verdict in verify_table(args.table, cells, executor, args.mesh_dir, bar.update,
                                        extent=not args.no_extent):
                verdicts.append(verdict)
    finally:
        close()
    verdicts.sort(key=lambda v: (v.body, -v.flexion_deg, v.varus_deg))
    bad = [v for v in verdicts if v.converged and v.gain_m > resolution]
    unclaimed = int(np.size(table.status) - np.isin(table.status, AT_REST).sum())
    differ = '' if changed is None else (
        f'{changed} cells differ from {args.changed_from} by more than the resolution '
        f'({resolution * 1e3:g} mm) or {args.changed_deg:g} deg; ')
    if args.json:
        report = {'table': str(args.table), 'resolution_m': resolution,
                  'cells': [v.as_json() for v in verdicts],
                  'not_at_rest': len(bad), 'not_converged': unclaimed}
        if changed is not None:
            report.update(changed_from=str(args.changed_from), changed_deg=args.changed_deg,
                          changed=changed)
        print(json.dumps(report))
    else:
        for v in verdicts:
            print(v.line(resolution))
        worst = max((v.gain_m for v in verdicts), default=0.0)
        unjudged = (f'; {unclaimed} cells of the table did not converge and claim no rest '
                    f'(kneeseat info lists them)' if unclaimed else '')
        extents = [v for v in verdicts if v.extent_m is not None]
        spread = '' if not extents else (
            f'; within a resolution of their best the rests move up to '
            f'{max(v.extent_m or 0.0 for v in extents) * 1e3:.2f} mm and '
            f'{max(v.extent_deg or 0.0 for v in extents):.2f} deg')
        print(f'{differ}{len(verdicts)} cells claimed at rest judged: {len(bad)} gain more '
              f'than the resolution ({resolution * 1e3:g} mm); largest gain {worst * 1e3:.3f} mm'
              f'{spread}{unjudged}')
    return EXIT_NOT_AT_REST if bad else EXIT_AT_REST


def _read_pose(path: Path) -> Pose:
    """A pose from `kneeseat settle --json` output or a START.json."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return load_start_pose(path)        # its one-line errors
    if isinstance(data, dict) and isinstance(data.get('pose'), dict):
        return load_start_pose(path, data['pose'])
    return load_start_pose(path)


def _verify_one_cmd(args: argparse.Namespace) -> int:
    from kneeseat_core.meshes import load_mesh                               # trimesh
    from kneeseat_core.referee import Referee                                # fcl, scipy
    if not (args.fixed and args.moving and args.pose):
        raise ConfigError('give a TABLE, or --fixed, --moving and --pose for one settle result')
    pose = _read_pose(args.pose)
    push = np.asarray(args.push, dtype=float)
    referee = Referee([load_mesh(args.fixed, args.units)], [load_mesh(args.moving, args.units)],
                      push, args.resolution)
    try:
        verdict = referee.judge(pose)
    except NoContactError:
        raise ConfigError(f'{args.pose}: the pose has no contact along the push '
                          f'{push.tolist()}; check --push and the pose') from None
    at_rest = verdict.at_rest(args.resolution)
    if args.json:
        print(json.dumps({'at_rest': at_rest,
                          'gain_m': None if math.isinf(verdict.gain_m) else verdict.gain_m,
                          'slide_m': verdict.slide_m, 'spin_deg': math.degrees(verdict.spin_rad),
                          'queries': verdict.queries}))
    else:
        gain = 'climbs off the fixed body' if math.isinf(verdict.gain_m) else \
            f'gains {verdict.gain_m * 1e3:.3f} mm'
        print(f'{gain} by sliding {verdict.slide_m * 1e3:.2f} mm and turning '
              f'{math.degrees(verdict.spin_rad):.2f} deg ({verdict.queries} collision queries): '
              f'{"at rest" if at_rest else "NOT AT REST"}')
    return EXIT_AT_REST if at_rest else EXIT_NOT_AT_REST


def register_command(sub: Subcommands) -> None:
    """Add `verify` to the `kneeseat` subcommand parser."""
    p = sub.add_parser('verify', help='check settled poses with the independent referee')
    p.add_argument('table', nargs='?', type=Path, help='table file (.npz) to verify')
    p.add_argument('--sample', type=int, metavar='N',
                   help='verify N cells spread over the grid (default: all cells)')
    p.add_argument('--seed', type=int, default=20261201, help='seed of the sample')
    p.add_argument('--changed-from', type=Path, metavar='OLD',
                   help='verify the cells whose pose differs from those of the table OLD '
                   '(same config and grid) by more than the resolution or --changed-deg')
    p.add_argument('--changed-deg', type=float, default=0.15, metavar='DEG',
                   help='with --changed-from: a cell turned by more than this differs too '
                   '(default 0.15, about the arc of a resolution at 40 mm)')
    p.add_argument('--workers', type=worker_count, default=default_workers(),
                   help=f'worker processes (default: all cores, here {default_workers()})')
    p.add_argument('--mesh-dir', type=Path, help="directory that holds the table's meshes")
    p.add_argument('--fixed', type=Path, help='one settle result: the fixed mesh')
    p.add_argument('--moving', type=Path, help='one settle result: the moving mesh')
    p.add_argument('--pose', type=Path, help='one settle result: its JSON (kneeseat settle '
                   '--json) or a START.json with the pose to judge')
    p.add_argument('--push', type=vector3, default=SettleParams().push,
                   help='one settle result: the push direction (default 0,-1,0)')
    p.add_argument('--resolution', type=float, default=SettleParams().resolution_m,
                   help='one settle result: the resolution, m (1e-4)')
    p.add_argument('--units', choices=('m', 'mm'), default='m', help='units of both meshes')
    p.add_argument('--no-extent', action='store_true',
                   help='skip measuring how far each rest can move within one resolution '
                   '(about half the time of the verdicts on a table)')
    p.add_argument('--json', action='store_true', help='print the verdicts as JSON')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(command=_cmd_verify)
