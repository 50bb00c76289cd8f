"""`kneeseat settle`: one settle, for scripting and independent checks.

The contract (docs/design.md): exit 0 converged, 3 not converged (the JSON is still
printed), 4 no contact along the push, 2 bad input; `--json` prints the result's fields.
A START.json (`load_start_pose`) is the moving frame's pose in the fixed frame.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
from typing import Any, TYPE_CHECKING

import numpy as np

from kneeseat_core.args import EXIT_NO_CONTACT, EXIT_NOT_CONVERGED, EXIT_OK, vector3
from kneeseat_core.errors import NoContactError, UsageError
from kneeseat_core.geometry import matrix_from_quat, pose_from, quat_from_matrix, TOL
from kneeseat_core.params import SettleParams
from kneeseat_core.typed import Pose

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands
    from kneeseat_core.settle import SettleResult

__all__ = ['load_start_pose', 'register_command']


def load_start_pose(path: Path | None, data: Any = None) -> Pose:
    """A (4, 4) pose from a START.json `{"position":[x,y,z],"orientation":[x,y,z,w]}` (or
    from `data`, that file's content already parsed); identity without a path.

    Raises:
        UsageError: the file is missing or is not such a pose (one-line message).
    """
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
    # the settle loads trimesh and python-fcl (about 2 s), which the table commands and
    # --help do without
    from kneeseat_core.meshes import load_mesh, RigidBody
    from kneeseat_core.settle import settle

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
        q = quat_from_matrix(result.pose[:3, :3])
        state = 'converged' if result.converged else 'NOT converged'
        print(f'{state}: {result.reason}')
        print(f'position (m)      {np.array2string(result.pose[:3, 3], precision=6)}')
        print(f'orientation xyzw  {np.array2string(q, precision=6)}')
        print(f'iterations {result.iterations}, collision checks {result.collision_checks}'
              + (f' ({result.travels} exact travels, {result.fcl_checks} python-fcl)'
                 if result.travels else '')
              + f', {len(result.contacts.points)} contacts, {result.elapsed_s * 1e3:.1f} ms '
              f'({result.fcl_s / max(result.elapsed_s, 1e-12):.0%} in python-fcl)')
    return EXIT_OK if result.converged else EXIT_NOT_CONVERGED


def register_command(sub: Subcommands) -> None:
    """Add `settle` to the `kneeseat` subcommand parser (defaults: `SettleParams`)."""
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
