"""Two tables of one knee on one grid: where they differ, and whether the second is at rest there.

Run: `python benchmarks/travel_tables.py REFERENCE.npz JUDGED.npz [--workers 2]
[--limit N] [--mesh-dir DIR]` (say the same config built by an earlier release and by this
one; DIR: the folder that holds the tables' meshes when they are no longer where the tables
were built). Prints, per body, how many cells differ by more than the resolution (the frame
origin's displacement, or the turn times the body's reach), the largest difference, and
then the referee's verdicts (`kneeseat verify`'s judge: python-fcl and Nelder-Mead, nothing
of the settle) on those cells of the judged table: how many are at rest and the largest
gain. Also the build figures both tables recorded.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys

import numpy as np

from kneeseat_core.geometry import matrix_from_quat
from kneeseat_core.knee import config_from_metadata
from kneeseat_core.meshes import load_meshes
from kneeseat_core.errors import KneeseatError, MeshError
from kneeseat_core.referee import verify_table
from kneeseat_core.referee.cells import mesh_file
from kneeseat_core.sweep import executor_for, queries_per_cell
from kneeseat_core.table import PoseTable, read_table
from machine import describe_machine


def reach_m(table: PoseTable, body: int, mesh_dir: Path | None) -> float:
    """The body's farthest vertex from its centroid (m), from its meshes (in `mesh_dir`
    when given)."""
    config = config_from_metadata(table.metadata)
    spec = config.bodies[body]
    where = None if mesh_dir is None else str(mesh_dir)
    mesh = load_meshes([mesh_file(p, where) for p in spec.meshes], config.units, quiet=True)
    return float(np.max(np.linalg.norm(mesh.vertices - mesh.centroid, axis=1)))


def differing(a: PoseTable, b: PoseTable, body: int, resolution: float, reach: float) -> \
        tuple[list[tuple[int, int, int]], float, float]:
    """Cells of `body` converged in both and apart by more than `resolution` (as a
    displacement or an arc at the body's `reach`); the largest displacement and arc (m)."""
    cells, worst_d, worst_arc = [], 0.0, 0.0
    nf, nv = a.converged.shape[1:]
    for i in range(nf):
        for j in range(nv):
            if not (a.converged[body, i, j] and b.converged[body, i, j]):
                continue
            d = float(np.linalg.norm(a.position_m[body, i, j] - b.position_m[body, i, j]))
            ra = matrix_from_quat(a.orientation_xyzw[body, i, j])
            rb = matrix_from_quat(b.orientation_xyzw[body, i, j])
            cos = 0.5 * (float(np.trace(ra.T @ rb)) - 1.0)
            arc = float(np.arccos(np.clip(cos, -1.0, 1.0))) * reach
            worst_d, worst_arc = max(worst_d, d), max(worst_arc, arc)
            if d > resolution or arc > resolution:
                cells.append((body, i, j))
    return cells, worst_d, worst_arc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('reference', type=Path, help='the table compared against')
    parser.add_argument('judged', type=Path, help='the table whose differing cells are judged')
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--limit', type=int, default=None,
                        help='judge at most this many differing cells, evenly spread over '
                        'them (all by default)')
    parser.add_argument('--mesh-dir', type=Path, default=None,
                        help="the folder that holds the tables' meshes (default: where the "
                        'tables were built from)')
    args = parser.parse_args(argv)
    try:
        return compare(args)
    except MeshError as exc:
        print(f'travel_tables: {exc} (or pass --mesh-dir DIR, the folder the meshes are in '
              'now)', file=sys.stderr)
        return 2
    except KneeseatError as exc:
        print(f'travel_tables: {exc}', file=sys.stderr)
        return 2


def compare(args: argparse.Namespace) -> int:
    """Print where the two tables differ and the referee's verdicts there."""
    a, b = read_table(args.reference), read_table(args.judged)
    if a.position_m.shape != b.position_m.shape or a.bodies != b.bodies:
        print('travel_tables: the two tables have different grids or bodies', file=sys.stderr)
        return 2
    resolution = float(a.metadata['settle']['resolution_m'])
    print(describe_machine())
    for name, t in (('reference', a), ('judged', b)):
        s = t.metadata['summary']
        print(f'{name}: {s["converged"]}/{s["cells"]} converged, {s["wall_s"]:.1f} s wall, '
              f'{queries_per_cell(s)}')
    judge: list[tuple[int, int, int]] = []
    for body, name in enumerate(a.bodies):
        cells, worst_d, worst_arc = differing(a, b, body, resolution,
                                              reach_m(a, body, args.mesh_dir))
        print(f'{name}: {len(cells)} of {int(a.converged[body].sum())} cells differ by more '
              f'than the resolution ({resolution * 1e3:g} mm); largest {worst_d * 1e3:.3f} mm, '
              f'arc {worst_arc * 1e3:.3f} mm')
        judge += cells
    if args.limit is not None and len(judge) > args.limit:
        picks = np.linspace(0, len(judge) - 1, args.limit).round().astype(int)
        judge = [judge[k] for k in sorted(set(picks.tolist()))]
    if not judge:
        return 0
    executor, close = executor_for(args.workers, None)
    try:
        verdicts = list(verify_table(args.judged, judge, executor, mesh_dir=args.mesh_dir,
                                     extent=False))
    finally:
        close()
    gains = [v.gain_m for v in verdicts if v.converged]
    not_at_rest = [v for v in verdicts if v.converged and v.gain_m > resolution]
    print(f'referee on the {len(verdicts)} differing cells of the judged table: '
          f'{len(gains) - len(not_at_rest)} at rest, {len(not_at_rest)} not; largest gain '
          f'{max(gains) * 1e3:.3f} mm')
    for v in not_at_rest:
        print('  ' + v.line(resolution))
    return 0


if __name__ == '__main__':
    sys.exit(main())
