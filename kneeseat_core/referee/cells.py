"""`kneeseat verify`: the independent referee's verdict on settled poses.

One settle result (`--fixed/--moving/--push/--pose`, the pose as `kneeseat settle --json`
prints it or as a START.json), or the cells of a table (all, or `--sample N` spread over the
grid: every body's four corners, then a seeded shuffle of the rest). For each pose the
referee (`kneeseat_core.referee.judge`, which shares no search code with the settle) climbs the
travel and reports what it gains and the move that gains it. Exit 0 only when no converged
cell gains more than the resolution; 3 when one does; 2 on bad input.
"""
from __future__ import annotations

import argparse
from concurrent.futures import Executor
from dataclasses import dataclass
import json
import math
from pathlib import Path
import sys
from typing import Any, Iterator, Sequence, TYPE_CHECKING

import numpy as np
from tqdm import tqdm
import trimesh

from kneeseat_core.args import EXIT_NOT_CONVERGED, EXIT_OK, vector3
from kneeseat_core.errors import MeshError, TableError
from kneeseat_core.geometry import matrix_from_quat, pose_from, TOL
from kneeseat_core.knee.config import BodySpec, config_from_metadata, KneeConfig, neutral_pose
from kneeseat_core.meshes.load import check_mesh_files, load_mesh, Units
from kneeseat_core.params import SettleParams
from kneeseat_core.status import AT_REST, STATUS_NAMES
from kneeseat_core.sweep.chains import carried
from kneeseat_core.table.io import read_table
from kneeseat_core.table.pose_table import PoseTable
from kneeseat_core.typed import Pose
from .judge import Envelope, Referee, Verdict

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands

__all__ = ['CellVerdict', 'sample_cells', 'verify_table', 'register_command']

# the exit codes of `kneeseat settle`: at rest as converged, not at rest as not converged
EXIT_AT_REST, EXIT_NOT_AT_REST = EXIT_OK, EXIT_NOT_CONVERGED


@dataclass(frozen=True, slots=True)
class CellVerdict:
    """The referee's verdict on one cell of a table."""

    body: str
    flexion_deg: float
    varus_deg: float
    status: int
    gain_m: float
    slide_m: float
    spin_deg: float
    queries: int

    @property
    def converged(self) -> bool:
        """The table claims this cell is at rest."""
        return self.status in AT_REST

    def line(self, resolution_m: float) -> str:
        """One human line."""
        where = f'{self.body} flexion {self.flexion_deg:g} varus {self.varus_deg:g}'
        state = STATUS_NAMES.get(self.status, str(self.status))
        if math.isinf(self.gain_m):
            found = 'climbs off the fixed body'
        else:
            found = (f'gains {self.gain_m * 1e3:.3f} mm by sliding {self.slide_m * 1e3:.2f} mm '
                     f'and turning {self.spin_deg:.2f} deg')
        verdict = ('at rest' if self.gain_m <= resolution_m else 'NOT AT REST') \
            if self.converged else 'not claimed at rest'
        return f'{where} ({state}): {found}: {verdict}'

    def as_json(self) -> dict[str, Any]:
        """JSON-ready dict (gain_m null when the referee climbs off the fixed body)."""
        return {'body': self.body, 'flexion_deg': self.flexion_deg,
                'varus_deg': self.varus_deg, 'status': STATUS_NAMES.get(self.status),
                'converged': self.converged,
                'gain_m': None if math.isinf(self.gain_m) else self.gain_m,
                'slide_m': self.slide_m, 'spin_deg': self.spin_deg, 'queries': self.queries}


# ---- a table's cells ------------------------------------------------------------------
def _varus_free(meta: dict[str, Any], body: int) -> bool:
    specs = meta.get('config', {}).get('resolved', {}).get('bodies', [])
    return (body < len(specs)
            and abs(float(specs[body].get('varus_fraction', 1.0))) < TOL.fraction)


def sample_cells(table: PoseTable, count: int | None, seed: int = 20261201
                 ) -> list[tuple[int, int, int]]:
    """Cells (body, flexion index, varus index) to verify: the cells the table claims at
    rest (a cell that did not converge claims nothing; `kneeseat info` reports it).

    A body that ignores varus (copied across varus) is sampled on its centre column only.
    With `count`, every body's four corners come first (those at rest), then a seeded
    shuffle of its other cells at rest, taken in turn from each body, up to `count` cells.
    """
    nb, nf, nv = np.shape(table.converged)
    v0 = int(np.argmin(np.abs(table.varus_rad)))
    claimed = np.isin(table.status, AT_REST)
    per_body = []
    for b in range(nb):
        columns = [v0] if _varus_free(table.metadata, b) else list(range(nv))
        cells = [(b, i, j) for i in range(nf) for j in columns if claimed[b, i, j]]
        if count is None:
            per_body.append(cells)
            continue
        corners = [c for c in dict.fromkeys((b, i, j) for i in (0, nf - 1)
                                            for j in (columns[0], columns[-1]))
                   if claimed[c]]
        rest = [c for c in cells if c not in corners]
        rng = np.random.default_rng(seed + b)
        per_body.append(corners + [rest[k] for k in rng.permutation(len(rest))])
        # (up to four corners lead each body's list; the rest follow shuffled)
    if count is None:
        return [c for cells in per_body for c in cells]
    picked = [c for cells in per_body for c in cells[:min(4, len(cells))]][:count]
    queues = [cells[4:] for cells in per_body]
    while len(picked) < count and any(queues):
        for queue in queues:
            if queue and len(picked) < count:
                picked.append(queue.pop(0))
    return sorted(picked)


@dataclass(frozen=True, slots=True)
class _CellJob:
    table: str
    mesh_dir: str | None
    cells: tuple[tuple[int, int, int], ...]


_WORKER_STATE: dict[str, Any] = {}


def _mesh_file(path: Path, mesh_dir: str | None) -> str:
    return str(Path(mesh_dir) / path.name) if mesh_dir else str(path)


def _meshes(spec: BodySpec, units: Units, mesh_dir: str | None) -> list[trimesh.Trimesh]:
    """A body's collision meshes, loaded quietly (the parent validated them once)."""
    return [load_mesh(_mesh_file(p, mesh_dir), units, quiet=True) for p in spec.meshes]


def _cell_problem(config: KneeConfig, meta: dict[str, Any], body: int, flexion: float,
                  varus: float) -> tuple[SettleParams, Pose]:
    """The settle parameters (push, lock, envelope) and the envelope's anchor at a cell."""
    spec = config.bodies[body]
    attitude = config.attitude(spec, flexion, varus)
    anchor = neutral_pose(attitude)
    stored = meta['bodies'][body].get('envelope_anchor')
    if isinstance(stored, dict):          # the sweep's anchor: the centre rest, carried
        anchor = carried(pose_from(matrix_from_quat(np.asarray(stored['orientation'])),
                                   np.asarray(stored['position'])),
                         config.attitude(spec, math.radians(stored['flexion_deg']),
                                         math.radians(stored['varus_deg'])), attitude)
    return config.params(spec, flexion, varus), anchor


def _judge_cells(job: _CellJob) -> list[CellVerdict]:
    """Judge the cells of `job` (runs in a worker; tables and meshes cached per process)."""
    key = f'{job.table}|{job.mesh_dir}'
    if _WORKER_STATE.get('key') != key:
        loaded = read_table(Path(job.table))
        built = config_from_metadata(loaded.metadata)
        _WORKER_STATE.clear()
        _WORKER_STATE.update(
            key=key, table=loaded, config=built,
            fixed=_meshes(built.reference, built.units, job.mesh_dir),
            moving=[_meshes(b, built.units, job.mesh_dir) for b in built.bodies])
    table: PoseTable = _WORKER_STATE['table']
    config: KneeConfig = _WORKER_STATE['config']
    meta, codes = table.metadata, table.status
    out = []
    for b, i, j in job.cells:
        flexion, varus = float(table.flexion_rad[i]), float(table.varus_rad[j])
        params, anchor = _cell_problem(config, meta, b, flexion, varus)
        pose = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                         table.position_m[b, i, j])
        referee = Referee(_WORKER_STATE['fixed'], _WORKER_STATE['moving'][b],
                          np.asarray(params.push), params.resolution_m,
                          None if params.locked_slide is None else np.asarray(params.locked_slide))
        try:
            verdict = referee.judge(pose, Envelope(anchor, params.max_slide_m,
                                                   params.max_spin_rad))
            gain, slide, spin = verdict.gain_m, verdict.slide_m, math.degrees(verdict.spin_rad)
        except ValueError:              # the stored pose has no contact along the push
            gain, slide, spin = math.inf, 0.0, 0.0
        out.append(CellVerdict(table.bodies[b], math.degrees(flexion), math.degrees(varus),
                               int(codes[b, i, j]), gain, slide, spin, referee.queries))
    return out


def verify_table(path: Path, cells: Sequence[tuple[int, int, int]], executor: Executor,
                 mesh_dir: Path | None = None, progress: Any = None) -> Iterator[CellVerdict]:
    """Judge `cells` of the table at `path` on `executor`; yields verdicts as they finish."""
    from concurrent.futures import as_completed
    chunk = 2
    jobs = [_CellJob(str(path), None if mesh_dir is None else str(mesh_dir),
                     tuple(cells[k:k + chunk])) for k in range(0, len(cells), chunk)]
    futures = [executor.submit(_judge_cells, job) for job in jobs]
    for fut in as_completed(futures):
        for verdict in fut.result():
            if progress is not None:
                progress(1)
            yield verdict


def _cmd_verify(args: argparse.Namespace) -> int:
    if args.table is not None:
        return _verify_table_cmd(args)
    return _verify_one_cmd(args)


def _verify_table_cmd(args: argparse.Namespace) -> int:
    from kneeseat_core.sweep.build import executor_for
    if args.fixed or args.moving or args.pose:
        raise TableError('give either a TABLE or --fixed/--moving/--pose, not both')
    if args.sample is not None and args.sample < 1:
        raise TableError(f'--sample {args.sample}: give a positive number of cells')
    table = read_table(args.table)
    config = config_from_metadata(table.metadata)
    mesh_dir = None if args.mesh_dir is None else str(args.mesh_dir)
    paths = [_mesh_file(p, mesh_dir) for spec in (config.reference, *config.bodies)
             for p in spec.meshes]
    missing = [p for p in paths if not Path(p).is_file()]
    if missing:
        raise MeshError(f"{missing[0]}: the table's mesh is not there; pass --mesh-dir DIR, "
                        f"the folder that holds {Path(missing[0]).name} and the table's other "
                        f'meshes')
    check_mesh_files(paths, config.units)     # warnings once, here; workers load quietly
    cells = sample_cells(table, args.sample, args.seed)
    resolution = float(table.metadata.get('settle', {}).get('resolution_m', 1e-4))
    executor, close = executor_for(args.workers, None)
    verdicts: list[CellVerdict] = []
    try:
        with tqdm(total=len(cells), unit='cell', desc='verify', disable=args.quiet,
                  dynamic_ncols=True, file=sys.stderr) as bar:
            for verdict in verify_table(args.table, cells, executor, args.mesh_dir, bar.update):
                verdicts.append(verdict)
    finally:
        close()
    verdicts.sort(key=lambda v: (v.body, -v.flexion_deg, v.varus_deg))
    bad = [v for v in verdicts if v.converged and v.gain_m > resolution]
    unclaimed = int(np.size(table.status) - np.isin(table.status, AT_REST).sum())
    if args.json:
        print(json.dumps({'table': str(args.table), 'resolution_m': resolution,
                          'cells': [v.as_json() for v in verdicts],
                          'not_at_rest': len(bad), 'not_converged': unclaimed}))
    else:
        for v in verdicts:
            print(v.line(resolution))
        worst = max((v.gain_m for v in verdicts), default=0.0)
        unjudged = (f'; {unclaimed} cells of the table did not converge and claim no rest '
                    f'(kneeseat info lists them)' if unclaimed else '')
        print(f'{len(verdicts)} cells claimed at rest judged: {len(bad)} gain more than the '
              f'resolution ({resolution * 1e3:g} mm); largest gain {worst * 1e3:.3f} mm'
              f'{unjudged}')
    return EXIT_NOT_AT_REST if bad else EXIT_AT_REST


def _read_pose(path: Path) -> Pose:
    """A pose from `kneeseat settle --json` output or a START.json."""
    from kneeseat_core.cli.main import load_start_pose
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return load_start_pose(path)        # its one-line errors
    if isinstance(data, dict) and isinstance(data.get('pose'), dict):
        return load_start_pose(path, data['pose'])
    return load_start_pose(path)


def _verify_one_cmd(args: argparse.Namespace) -> int:
    from kneeseat_core.errors import ConfigError
    if not (args.fixed and args.moving and args.pose):
        raise ConfigError('give a TABLE, or --fixed, --moving and --pose for one settle result')
    pose = _read_pose(args.pose)
    push = np.asarray(args.push, dtype=float)
    referee = Referee([load_mesh(args.fixed, args.units)], [load_mesh(args.moving, args.units)],
                      push, args.resolution)
    try:
        verdict: Verdict = referee.judge(pose)
    except ValueError:
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
    from kneeseat_core.sweep.chains import default_workers
    p = sub.add_parser('verify', help='check settled poses with the independent referee')
    p.add_argument('table', nargs='?', type=Path, help='table file (.npz) to verify')
    p.add_argument('--sample', type=int, metavar='N',
                   help='verify N cells spread over the grid (default: all cells)')
    p.add_argument('--seed', type=int, default=20261201, help='seed of the sample')
    p.add_argument('--workers', type=int, default=default_workers(),
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
    p.add_argument('--json', action='store_true', help='print the verdicts as JSON')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(command=_cmd_verify)
