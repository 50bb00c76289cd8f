"""What settling the tibia before the patella neglects: the patellar tendon's pull on the tibia.

Run: `python benchmarks/tendon_iteration.py TABLE.npz CONFIG.yaml [--mesh-dir DIR]
[--flexion-deg 0,30,60,90] [--varus-deg 0] [--rounds 6]`.

A table settles the tibia with the fibres between it and the femur, then the patella with
its fibres to the femur and to the tibia as settled (`docs/design.md`, "Soft tissue"). At
each cell asked for, this script starts from the table's poses and alternates: the tibia
settled again with the patella's fibres to it attached to the patella where it rests, then
the patella again on that tibia, until neither moves by more than the resolution (or
`--rounds` rounds). It prints how far each body moved from the table's pose (frame origin,
mm; rotation, deg), the tendon's tension on the tibia at the table's poses, and the rounds
taken.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from kneeseat_core.errors import KneeseatError
from kneeseat_core.geometry import matrix_from_quat, pose_from, rotation_angle
from kneeseat_core.knee import load_config
from kneeseat_core.meshes import load_meshes, RigidBody
from kneeseat_core.settle import settle
from kneeseat_core.table import read_table
from kneeseat_core.typed import Pose


def _apart(a: Pose, b: Pose) -> tuple[float, float]:
    """Origin distance (mm) and rotation angle (deg) between two poses."""
    return (float(np.linalg.norm(a[:3, 3] - b[:3, 3])) * 1e3,
            math.degrees(rotation_angle(a[:3, :3], b[:3, :3])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('table', type=Path)
    parser.add_argument('config', type=Path)
    parser.add_argument('--mesh-dir', type=Path)
    parser.add_argument('--flexion-deg', default='0,30,60,90')
    parser.add_argument('--varus-deg', type=float, default=0.0)
    parser.add_argument('--rounds', type=int, default=6)
    args = parser.parse_args()
    try:
        config = load_config(args.config, args.mesh_dir)
        table = read_table(args.table)
    except KneeseatError as err:
        raise SystemExit(f'tendon_iteration: {err}') from None
    if config.ligaments is None:
        raise SystemExit(f'tendon_iteration: {args.config} has no ligaments')
    names = [b.name for b in config.bodies]
    tibia, patella = names.index('tibia'), names.index('patella')
    reference = config.reference.name
    bodies = {b.name: RigidBody.from_mesh(load_meshes(list(b.meshes), config.units, quiet=True))
              for b in (config.reference, *config.bodies)}
    between = [k for k, fib in enumerate(config.ligaments.fibres)
               if fib.ends == frozenset(('tibia', 'patella'))]
    j = int(np.argmin(np.abs(np.degrees(table.varus_rad) - args.varus_deg)))
    print(f'{args.table.name}, varus {np.degrees(table.varus_rad[j]):g} deg')
    print('flexion | tendon on tibia (N) | tibia moved (mm, deg) | patella moved (mm, deg)'
          ' | rounds | both at rest')
    for flex in (float(v) for v in args.flexion_deg.split(',')):
        i = int(np.argmin(np.abs(np.degrees(table.flexion_rad) + abs(flex))))
        f, v = table.flexion_rad[i], table.varus_rad[j]
        pose = {n: pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                             table.position_m[b, i, j])
                for b, n in enumerate(names)}
        start = dict(pose)
        tension = float(config.ligaments.forces({reference: np.eye(4), **pose})[between].sum())
        rounds, rested = 0, True
        for rounds in range(1, args.rounds + 1):
            moved = 0.0
            for b, other in ((tibia, patella), (patella, tibia)):
                spec = config.bodies[b]
                params = config.params(spec, f, v)
                tissue = config.ligaments.tissue(
                    spec.name, {reference: np.eye(4), names[other]: pose[names[other]]})
                back = pose[spec.name].copy()
                back[:3, 3] -= params.step_m * np.asarray(params.push)
                result = settle(bodies[reference], bodies[spec.name], back, params,
                                start[spec.name], tissue)
                rested = rested and result.converged
                moved = max(moved, _apart(pose[spec.name], result.pose)[0])
                pose[spec.name] = result.pose
            if moved <= config.settle.resolution_m * 1e3:
                break
        t_mm, t_deg = _apart(start['tibia'], pose['tibia'])
        p_mm, p_deg = _apart(start['patella'], pose['patella'])
        print(f'{-abs(flex):7g} | {tension:19.1f} | {t_mm:8.2f} mm {t_deg:5.2f} deg | '
              f'{p_mm:8.2f} mm {p_deg:5.2f} deg | {rounds:6d} | {rested}')


if __name__ == '__main__':
    main()
