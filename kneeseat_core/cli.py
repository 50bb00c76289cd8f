"""`kneeseat` command line: settle, build, verify, info, lookup, export, synth, plot, render.

Errors a user can fix print one line on stderr and exit non-zero (no traceback unless
--debug). `kneeseat settle` exit codes are fixed by DESIGN.md: 0 converged, 3 not
converged (JSON still printed), 4 no contact along the push, 2 bad input.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
import sys
from typing import Any, Callable, Sequence

import numpy as np

from .errors import KneeseatError, NoContactError, UsageError

__all__ = ['main', 'build_parser', 'load_start_pose']

log = logging.getLogger('kneeseat')

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT, EXIT_NOT_CONVERGED, EXIT_NO_CONTACT = 0, 1, 2, 3, 4


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (no usage block) and exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f'{self.prog}: error: {message}; see --help\n')


def _vector3(text: str) -> tuple[float, float, float]:
    """Parse 'x,y,z' (also 'x y z'); argparse reports failures as usage errors."""
    parts = text.replace(',', ' ').split()
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not three numbers like 0,-1,0") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"'{text}' is not three finite numbers like 0,-1,0")
    return values  # type: ignore[return-value]


def _angles(text: str) -> list[float]:
    """Parse '0,-30,-60' degrees."""
    try:
        values = [float(p) for p in text.replace(',', ' ').split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of numbers like 0,-45,-90") \
            from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of finite numbers")
    return values


def _fix_negative_values(argv: list[str], flags: set[str]) -> list[str]:
    """Join `--push -1,0,0` into `--push=-1,0,0` so a leading minus is not an option."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg in flags and i + 1 < len(argv) and argv[i + 1].startswith('-') \
                and len(argv[i + 1]) > 1 and (argv[i + 1][1].isdigit() or argv[i + 1][1] == '.'):
            out.append(f'{arg}={argv[i + 1]}')
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


_VALUE_FLAGS = {'--push', '--flexion-deg', '--varus-deg', '--rotation-step',
                '--rotation-resolution', '--step', '--resolution', '--flexion-grid',
                '--varus-grid', '--tibia-point', '--patella-point', '--angles'}


# ---- settle --------------------------------------------------------------------------
def load_start_pose(path: Path | None, data: Any = None) -> np.ndarray:
    """A (4, 4) pose from a START.json `{"position":[x,y,z],"orientation":[x,y,z,w]}` (or
    from `data`, that file's content already parsed); identity without a path.

    Raises:
        UsageError: the file is missing or is not such a pose (one-line message).
    """
    from .geometry import matrix_from_quat, pose_from, TOL
    if path is None:
        return np.eye(4)
    try:
        if data is None:
            data = json.loads(Path(path).read_text())
        position = np.asarray(data['position'], dtype=float).reshape(3)
        quat = np.asarray(data['orientation'], dtype=float).reshape(4)
    except FileNotFoundError:
        raise UsageError(f'{path}: no such start file') from None
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise UsageError(f'{path}: not a start pose ({type(err).__name__}); expected '
                         '{"position":[x,y,z],"orientation":[x,y,z,w]}') from None
    if not (np.all(np.isfinite(position)) and np.all(np.isfinite(quat))):
        raise UsageError(f'{path}: start pose has non-finite numbers')
    if abs(float(np.linalg.norm(quat)) - 1.0) > TOL.input_unit_norm:
        raise UsageError(f'{path}: orientation {quat.tolist()} is not a unit quaternion '
                         '[x,y,z,w]')
    return pose_from(matrix_from_quat(quat), position)


def _settle_json(result: Any) -> dict[str, Any]:
    from .geometry import quat_from_matrix
    return {
        'converged': bool(result.converged),
        'reason': result.reason,
        'pose': {'position': [float(v) for v in result.pose[:3, 3]],
                 'orientation': [float(v) for v in quat_from_matrix(result.pose[:3, :3])]},
        'iterations': int(result.iterations),
        'collision_checks': int(result.collision_checks),
        'contacts': [{'point': [float(v) for v in p], 'normal': [float(v) for v in n]}
                     for p, n in zip(result.contacts.points, result.contacts.normals)],
        'elapsed_s': float(result.elapsed_s),
    }


def _cmd_settle(args: argparse.Namespace) -> int:
    from .collision import RigidBody
    from .meshes import load_mesh
    from .settle import SettleParams, settle

    params = SettleParams(
        push=args.push, step_m=args.step, resolution_m=args.resolution,
        rotation_step_rad=None if args.rotation_step is None else math.radians(args.rotation_step),
        rotation_resolution_rad=(None if args.rotation_resolution is None
                                 else math.radians(args.rotation_resolution)),
        max_iterations=args.max_iterations, method=args.method)
    params.check()
    start = load_start_pose(args.start)
    fixed = RigidBody.from_mesh(load_mesh(args.fixed, args.units))
    moving = RigidBody.from_mesh(load_mesh(args.moving, args.units))
    try:
        result = settle(fixed, moving, start, params)
    except NoContactError as err:
        print(f'kneeseat settle: {err}', file=sys.stderr)
        return EXIT_NO_CONTACT
    if result.backed_out_m > 0:
        print(f'kneeseat settle: the start pose was in collision; backed out '
              f'{result.backed_out_m * 1e3:.3f} mm along -push first', file=sys.stderr)
    if args.json:
        print(json.dumps(_settle_json(result)))
    else:
        from .geometry import quat_from_matrix
        q = quat_from_matrix(result.pose[:3, :3])
        state = 'converged' if result.converged else 'NOT converged'
        print(f'{state}: {result.reason}')
        print(f'position (m)      {np.array2string(result.pose[:3, 3], precision=6)}')
        print(f'orientation xyzw  {np.array2string(q, precision=6)}')
        print(f'iterations {result.iterations}, collision checks {result.collision_checks}, '
              f'{len(result.contacts.points)} contacts, {result.elapsed_s * 1e3:.1f} ms '
              f'({result.fcl_s / max(result.elapsed_s, 1e-12):.0%} in python-fcl)')
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED


# ---- table commands -------------------------------------------------------------------
def _cmd_info(args: argparse.Namespace) -> int:
    from .table_io import read_table
    from .table_report import describe, status_map
    table = read_table(args.table)
    print(describe(table))
    if args.map:
        print(status_map(table))
    return EXIT_OK


def _cmd_lookup(args: argparse.Namespace) -> int:
    from .geometry import KneeAxes, matrix_from_quat
    from .table_io import read_table
    from .table_report import lookup_json
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
    from .table_io import read_table
    from .table_report import export_csv
    export_csv(read_table(args.table), args.csv)
    print(f'wrote {args.csv}')
    return EXIT_OK


def _display_paths(entry: dict[str, Any], display: bool) -> list[str]:
    """A metadata entry's display meshes when asked and recorded, else its collision meshes.

    Reads tables written before multi-mesh bodies (`mesh`/`display_mesh` only) too.
    """
    from .table_format import mesh_entries
    if display:
        listed = [m['path'] for m in entry.get('display_meshes') or [] if isinstance(m, dict)]
        if listed:
            return listed
        if entry.get('display_mesh'):
            return [entry['display_mesh']]
    return [path for path, _ in mesh_entries(entry)]


def _table_meshes(table: Any, display: bool) -> dict[str, Any]:
    """Meshes named in a table's metadata, one (combined) mesh per body.

    A body with several meshes (e.g. a tibia's bone and menisci) is drawn as their union.
    """
    from .meshes import load_meshes
    meta = table.metadata
    units = meta.get('config', {}).get('units', 'm')
    return {entry['name']: load_meshes(_display_paths(entry, display), units)
            for entry in (meta['reference'], *meta['bodies'])}


def _cmd_plot(args: argparse.Namespace) -> int:
    from .plots import plot_convergence_map, plot_table
    from .table_io import read_table
    if args.map:
        out = plot_convergence_map(read_table(args.table), args.out)
        print(f'wrote {out}')
        return EXIT_OK
    out = plot_table(read_table(args.table), args.out, varus_deg=args.varus_deg)
    print(f'wrote {out}')
    return EXIT_OK


def _cmd_render(args: argparse.Namespace) -> int:
    from .plots import render_table
    from .table_io import read_table
    table = read_table(args.table)
    out = render_table(table, _table_meshes(table, not args.implants), args.out,
                       flexion_deg=args.flexion_deg, view=args.view)
    print(f'wrote {out}')
    return EXIT_OK


def _cmd_kinematics(args: argparse.Namespace) -> int:
    from .kinematics import (DEFAULT_ANGLES_DEG, kinematics_markdown, knee_kinematics,
                             plot_kinematics, read_reference, table_landmarks,
                             write_kinematics_csv, write_text)
    from .table_io import read_table
    table = read_table(args.table)
    names = dict(tibia=args.tibia, patella=args.patella)
    marks = table_landmarks(table, side=args.side, tibia_point=args.tibia_point,
                            patella_point=args.patella_point, **names)
    angles = args.angles if args.angles is not None else list(DEFAULT_ANGLES_DEG)
    every = knee_kinematics(table, marks, side=args.side, **names)
    chosen = knee_kinematics(table, marks, angles_deg=angles, side=args.side, **names)
    reference = read_reference(args.reference) if args.reference else []
    args.out_dir.mkdir(parents=True, exist_ok=True)
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
    print(f'wrote {csv_path}, {md_path}, {png}')
    return EXIT_OK


# ---- parser -----------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `kneeseat` (subcommands register their handler as `command`)."""
    parser = _Parser(
        prog='kneeseat', description='Settle rigid bones by collision detection '
        '(US 6,708,142), build pose tables over a range of motion, inspect them.')
    parser.add_argument('--debug', action='store_true', help='show tracebacks')
    parser.add_argument('-v', '--verbose', action='count', default=0,
                        help='more log output (-v info, -vv debug)')
    sub = parser.add_subparsers(dest='name', required=True, metavar='COMMAND',
                                parser_class=_Parser)

    p = sub.add_parser('settle', help='settle one moving mesh against a fixed one')
    p.add_argument('--fixed', type=Path, required=True, help='reference mesh (fixed)')
    p.add_argument('--moving', type=Path, required=True, help='moving mesh')
    p.add_argument('--push', type=_vector3, default=(0.0, -1.0, 0.0),
                   help='push direction in the fixed frame, e.g. 0,-1,0 (default)')
    p.add_argument('--start', type=Path, help='START.json with position and orientation '
                   '[x,y,z,w] of the moving frame in the fixed frame (default identity)')
    p.add_argument('--step', type=float, default=1e-3, help='translation step, m (1e-3)')
    p.add_argument('--resolution', type=float, default=1e-4, help='resolution T2, m (1e-4)')
    p.add_argument('--rotation-step', type=float, metavar='DEG',
                   help='rotation step, degrees (default: arc of one step at the '
                   'farthest vertex)')
    p.add_argument('--rotation-resolution', type=float, metavar='DEG',
                   help='rotation resolution, degrees (default: default method: arc of '
                   'one resolution at the farthest vertex; patent method: 1 degree)')
    p.add_argument('--max-iterations', type=int, default=500)
    p.add_argument('--units', choices=('m', 'mm'), default='m', help='units of both meshes')
    p.add_argument('--method', choices=('default', 'patent'), default='default')
    p.add_argument('--json', action='store_true', help='print the result as JSON')
    p.set_defaults(command=_cmd_settle)

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
    p.add_argument('--varus-deg', type=_angles, help='varus values for the curves, e.g. -10,0,10')
    p.add_argument('--map', action='store_true',
                   help='draw the map of non-converged cells and their reasons instead')
    p.set_defaults(command=_cmd_plot)

    p = sub.add_parser('render', help='draw the bones at several flexion angles (PNG)')
    p.add_argument('table', type=Path)
    p.add_argument('--out', type=Path, required=True, help='output PNG')
    p.add_argument('--flexion-deg', type=_angles, help='flexion angles, e.g. 0,-30,-60,-90')
    p.add_argument('--view', choices=('lateral', 'anterior'), default='lateral')
    p.add_argument('--implants', action='store_true',
                   help='draw the collision meshes even where display meshes exist')
    p.set_defaults(command=_cmd_render)

    p = sub.add_parser('kinematics', help='secondary motions at varus 0 against flexion '
                       '(CSV, Markdown table, PNG)')
    p.add_argument('table', type=Path)
    p.add_argument('--out-dir', type=Path, required=True,
                   help='directory for kinematics.csv, kinematics.md and kinematics.png')
    p.add_argument('--angles', type=_angles, metavar='DEG,...',
                   help='knee flexion angles of the Markdown table, positive = flexed '
                   '(default 0,15,30,45,60,75,90)')
    p.add_argument('--side', choices=('right', 'left'), default='right', help='knee side')
    p.add_argument('--tibia', default='tibia', help='tibia body name (default tibia)')
    p.add_argument('--patella', default='patella', help='patella body name (default patella)')
    p.add_argument('--tibia-point', type=_vector3, metavar='X,Y,Z',
                   help='tibial landmark (m, tibia frame) instead of its mesh centroid')
    p.add_argument('--patella-point', type=_vector3, metavar='X,Y,Z',
                   help='patellar landmark (m, patella frame) instead of its mesh centroid')
    p.add_argument('--reference', type=Path, metavar='CSV',
                   help='published values to plot beside the table (source, quantity, '
                   'knee_flexion_deg, value)')
    p.add_argument('--compare', type=Path, action='append', metavar='TABLE',
                   help='another table to draw as a dashed line (repeatable)')
    p.set_defaults(command=_cmd_kinematics)

    _register_build_commands(sub)
    return parser


def _register_build_commands(sub: Any) -> None:
    """`build` and `synth` live with the knee model (kneeseat_core.build), `verify` with the
    referee (kneeseat_core.verify)."""
    from .build import register_commands
    from .verify import register_command
    register_commands(sub)
    register_command(sub, _vector3)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `kneeseat` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(_fix_negative_values(argv, _VALUE_FLAGS))
    except SystemExit as exit_:           # argparse already printed its one-line usage error
        return int(exit_.code or 0) and EXIT_BAD_INPUT
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format='kneeseat: %(levelname)s: %(message)s')
    logging.getLogger('trimesh').setLevel(max(level, logging.ERROR))
    command: Callable[[argparse.Namespace], int] = args.command
    try:
        return command(args)
    except KneeseatError as err:
        if args.debug:
            raise
        print(f'kneeseat {args.name}: error: {err}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as err:
        if args.debug:
            raise
        print(f'kneeseat {args.name}: error: {err}', file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f'kneeseat {args.name}: interrupted', file=sys.stderr)
        return 130
