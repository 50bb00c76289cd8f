"""`kneeseat` command line: settle, info, lookup, export, plot, render, kinematics, build,
synth, verify.

Errors a user can fix print one line on stderr and exit non-zero (no traceback unless
--debug). `kneeseat settle` exit codes are part of its contract (docs/design.md): 0
converged, 3 not converged (JSON still printed), 4 no contact along the push, 2 bad input.
The table commands live in `kneeseat_core.cli.table_commands`, build and synth in
`kneeseat_core.sweep.build`, verify in `kneeseat_core.referee.cells`.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
import sys
from typing import Any, Callable, Sequence, TYPE_CHECKING

import numpy as np

from kneeseat_core.args import (EXIT_BAD_INPUT, EXIT_ERROR, EXIT_NO_CONTACT, EXIT_NOT_CONVERGED,
                                EXIT_OK, join_negative_values, OneLineParser, vector3)
from kneeseat_core.errors import KneeseatError, NoContactError, UsageError
from kneeseat_core.typed import Pose

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands
    from kneeseat_core.settle.search import SettleResult

__all__ = ['main', 'build_parser', 'load_start_pose']

log = logging.getLogger('kneeseat')

# Options whose value may start with a minus (`--push -1,0,0`), over every subcommand.
_VALUE_FLAGS = {'--push', '--flexion-deg', '--varus-deg', '--rotation-step',
                '--rotation-resolution', '--step', '--resolution', '--flexion-grid',
                '--varus-grid', '--tibia-point', '--patella-point', '--angles'}


# ---- settle --------------------------------------------------------------------------
def load_start_pose(path: Path | None, data: Any = None) -> Pose:
    """A (4, 4) pose from a START.json `{"position":[x,y,z],"orientation":[x,y,z,w]}` (or
    from `data`, that file's content already parsed); identity without a path.

    Raises:
        UsageError: the file is missing or is not such a pose (one-line message).
    """
    from kneeseat_core.geometry import matrix_from_quat, pose_from, TOL
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


def _settle_json(result: SettleResult) -> dict[str, Any]:
    from kneeseat_core.geometry import quat_from_matrix
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
    from kneeseat_core.meshes.collision import RigidBody
    from kneeseat_core.meshes.load import load_mesh
    from kneeseat_core.settle import SettleParams, settle

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
        from kneeseat_core.geometry import quat_from_matrix
        q = quat_from_matrix(result.pose[:3, :3])
        state = 'converged' if result.converged else 'NOT converged'
        print(f'{state}: {result.reason}')
        print(f'position (m)      {np.array2string(result.pose[:3, 3], precision=6)}')
        print(f'orientation xyzw  {np.array2string(q, precision=6)}')
        print(f'iterations {result.iterations}, collision checks {result.collision_checks}, '
              f'{len(result.contacts.points)} contacts, {result.elapsed_s * 1e3:.1f} ms '
              f'({result.fcl_s / max(result.elapsed_s, 1e-12):.0%} in python-fcl)')
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED


def _register_settle(sub: Subcommands) -> None:
    """Add `settle` to the `kneeseat` subcommand parser (defaults: `SettleParams`)."""
    from kneeseat_core.settle import SettleParams
    d = SettleParams()
    p = sub.add_parser('settle', help='settle one moving mesh against a fixed one')
    p.add_argument('--fixed', type=Path, required=True, help='reference mesh (fixed)')
    p.add_argument('--moving', type=Path, required=True, help='moving mesh')
    p.add_argument('--push', type=vector3, default=d.push,
                   help='push direction in the fixed frame (default '
                   f'{",".join(f"{c:g}" for c in d.push)})')
    p.add_argument('--start', type=Path, help='START.json with position and orientation '
                   '[x,y,z,w] of the moving frame in the fixed frame (default identity)')
    p.add_argument('--step', type=float, default=d.step_m,
                   help=f'translation step, m ({d.step_m:g})')
    p.add_argument('--resolution', type=float, default=d.resolution_m,
                   help=f'resolution T2, m ({d.resolution_m:g})')
    p.add_argument('--rotation-step', type=float, metavar='DEG',
                   help='rotation step, degrees (default: arc of one step at the '
                   'farthest vertex)')
    p.add_argument('--rotation-resolution', type=float, metavar='DEG',
                   help='rotation resolution, degrees (default: default method: arc of '
                   'one resolution at the farthest vertex; patent method: 1 degree)')
    p.add_argument('--max-iterations', type=int, default=d.max_iterations)
    p.add_argument('--units', choices=('m', 'mm'), default='m', help='units of both meshes')
    p.add_argument('--method', choices=('default', 'patent'), default=d.method)
    p.add_argument('--json', action='store_true', help='print the result as JSON')
    p.set_defaults(command=_cmd_settle)


# ---- parser -----------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `kneeseat` (subcommands register their handler as `command`)."""
    from kneeseat_core.sweep.build import register_commands as register_build
    from .table_commands import register_commands as register_tables
    from kneeseat_core.referee.cells import register_command as register_verify
    parser = OneLineParser(
        prog='kneeseat', description='Settle rigid bones by collision detection '
        '(US 6,708,142), build pose tables over a range of motion, inspect them.')
    parser.add_argument('--debug', action='store_true', help='show tracebacks')
    parser.add_argument('-v', '--verbose', action='count', default=0,
                        help='more log output (-v info, -vv debug)')
    sub = parser.add_subparsers(dest='name', required=True, metavar='COMMAND',
                                parser_class=OneLineParser)
    _register_settle(sub)
    register_tables(sub)
    register_build(sub)    # build and synth live with the knee model
    register_verify(sub)   # verify with the referee
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `kneeseat` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(join_negative_values(argv, _VALUE_FLAGS))
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
