"""`kneeseat build` and `kneeseat synth`: from a knee config to a verified table file."""
from __future__ import annotations

import argparse
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import asdict
from datetime import datetime, timezone
from importlib import resources
import logging
import math
import os
from pathlib import Path
import sys
from typing import Any, Callable, Iterator, TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from kneeseat_core.errors import ConfigError
from kneeseat_core.files import file_sha256, write_bytes
from kneeseat_core.geometry import quat_from_matrix
from kneeseat_core.knee.config import BodySpec, grid_values, KneeConfig, load_config
from kneeseat_core.status import STATUS_NAMES
from kneeseat_core.table.io import write_table
from kneeseat_core.table.pose_table import PoseTable
from .chains import default_workers, process_executor, sweep, SweepResult
from .continuity import continuity

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands

__all__ = ['DEFAULT_CONFIG', 'default_knee_dir', 'materialise_default_knee', 'build_table',
           'make_table', 'register_commands', 'executor_for',
           'backed_out_lines']

log = logging.getLogger(__name__)

DEFAULT_CONFIG = 'default_knee.yaml'


def default_knee_dir() -> Path:
    """Where the embedded default knee's meshes are written (a per-user cache)."""
    base = Path(os.environ.get('XDG_CACHE_HOME', Path.home() / '.cache'))
    return base / 'kneeseat' / 'default_knee'


def materialise_default_knee(out_dir: Path | None = None) -> Path:
    """Write the default knee's meshes and config into `out_dir`; return the config path.

    Generation is deterministic, so existing files are reused when their bytes match.
    """
    from kneeseat_core.knee.synth import write_default_knee
    out_dir = default_knee_dir() if out_dir is None else Path(out_dir)
    write_default_knee(out_dir)
    config = out_dir / DEFAULT_CONFIG
    text = resources.files('kneeseat_core').joinpath('data', DEFAULT_CONFIG).read_text()
    if not config.is_file() or config.read_text() != text:
        write_bytes(config, text.encode())
    return config


def executor_for(workers: int, scheduler: str | None) -> tuple[Executor, Callable[[], None]]:
    """The executor a build runs on, and how to close it.

    Args:
        workers: process-pool size (ignored with a scheduler).
        scheduler: Dask scheduler address (tcp://HOST:PORT), or None for local processes.
    """
    if scheduler:
        from .cluster import dask_executor
        return dask_executor(scheduler)
    executor = process_executor(workers)
    return executor, lambda: executor.shutdown(wait=True, cancel_futures=True)


def make_table(config: KneeConfig, result: SweepResult) -> PoseTable:
    """Package a sweep result and its provenance as a `PoseTable`.

    Each body's metadata keeps `mesh`/`mesh_sha256` (its first collision mesh, as tables
    always had) and lists every mesh in `meshes` and `display_meshes` ([{path, sha256}]).
    """
    hashes = iter(result.mesh_sha256)   # taken by the sweep before it settled anything

    def body_meta(spec: BodySpec) -> dict[str, Any]:
        meshes = [{'path': str(m), 'sha256': next(hashes)} for m in spec.meshes]
        return {'name': spec.name, 'frame': spec.frame, 'mesh': meshes[0]['path'],
                'mesh_sha256': meshes[0]['sha256'], 'meshes': meshes,
                'display_mesh': None if spec.display_mesh is None else str(spec.display_mesh),
                'display_meshes': [{'path': str(m), 'sha256': file_sha256(m)}
                                   for m in spec.display_meshes]}

    f0, v0 = result.anchor_cell
    reference = body_meta(config.reference)      # hashes in order: reference, then bodies
    bodies = [body_meta(b) for b in config.bodies]
    for entry, anchor in zip(bodies, result.anchors):
        # where every cell's search envelope is measured from (kneeseat_core.sweep.chains)
        entry['envelope_anchor'] = {
            'flexion_deg': math.degrees(config.flexion_rad[f0]),
            'varus_deg': math.degrees(config.varus_rad[v0]),
            'position': anchor[:3, 3].tolist(),
            'orientation': quat_from_matrix(anchor[:3, :3]).tolist()}
    metadata = {
        'name': config.name,
        'reference': reference,
        'bodies': bodies,
        'axes': {'flexion': config.axes.flexion.tolist(), 'varus': config.axes.varus.tolist(),
                 'long': config.axes.long.tolist()},
        'config': config.metadata(),
        # push and locked slide are per body and per cell, not settle parameters
        'settle': {k: v for k, v in asdict(config.settle).items()
                   if k not in ('push', 'locked_slide')},
        'built': datetime.now(timezone.utc).isoformat(timespec='seconds'),
        'summary': {'cells': result.cells, 'converged': int(result.converged.sum()),
                    'wall_s': round(result.wall_s, 3),
                    'collision_checks': int(result.collision_checks)},
        'failures': list(result.failures),
        # how each cell's settle ended (codes: kneeseat_core.status.Status)
        'cells': {'status_names': {str(k): v for k, v in STATUS_NAMES.items()},
                  'status': np.asarray(result.status).tolist()},
        'continuity': continuity(result.position_m, result.orientation_xyzw, result.converged,
                                 config.flexion_rad, config.varus_rad,
                                 [b.name for b in config.bodies], config.attitudes()),
        'backed_out': _backed_out(config, result),
    }
    return PoseTable(config.flexion_rad, config.varus_rad, result.position_m,
                     result.orientation_xyzw, result.converged, result.iterations, metadata)


def _backed_out(config: KneeConfig, result: SweepResult) -> dict[str, Any]:
    """Per body: cells whose start was in collision and backed out along -push, and how far."""
    out: dict[str, Any] = {}
    for b, spec in enumerate(config.bodies):
        moved = result.backed_out_m[b][result.backed_out_m[b] > 0.0]
        out[spec.name] = {'cells': int(moved.size),
                          'max_mm': round(float(moved.max()) * 1e3, 3) if moved.size else 0.0}
    return out


def backed_out_lines(table: PoseTable) -> list[str]:
    """One line per body whose start was in collision at some cells (build summary)."""
    lines = []
    for name, entry in (table.metadata.get('backed_out') or {}).items():
        if entry.get('cells'):
            lines.append(f'  {name}: the start was in collision at {entry["cells"]} cells '
                         f'(up to {entry["max_mm"]:g} mm deep); each was backed out along '
                         'the push before settling')
    return lines


def build_table(config: KneeConfig, out: Path, executor: Executor,
                show_progress: bool = True) -> PoseTable:
    """Sweep `config` on `executor` and write the table to `out` (atomically).

    Ctrl-C stops the sweep and leaves no table file.
    """
    total = len(config.bodies) * len(config.flexion_rad) * len(config.varus_rad)
    with tqdm(total=total, unit='cell', desc=config.name, disable=not show_progress,
              dynamic_ncols=True, file=sys.stderr) as bar:
        result = sweep(config, executor, progress=bar.update)
    table = make_table(config, result)
    write_table(out, table)
    return table


def summary_line(table: PoseTable, out: Path) -> str:
    """One-paragraph summary of a finished build."""
    s = table.metadata['summary']
    conv = s['converged'] / max(s['cells'], 1)
    per_body = ', '.join(f'{name} {100 * table.converged[i].mean():.1f}%'
                         for i, name in enumerate(table.bodies))
    line = (f'{out}: {s["cells"]} cells, {100 * conv:.1f}% converged ({per_body}), '
            f'{s["wall_s"]:.1f} s wall, {s["cells"] / max(s["wall_s"], 1e-9):.1f} cells/s, '
            f'{s["collision_checks"] / max(s["cells"], 1):.0f} collision checks per cell')
    cont = table.metadata.get('continuity')
    if isinstance(cont, dict):
        over = sum(sum(b['pairs_over_bound'].values()) for b in cont['bodies'].values())
        line += (f'; {over} neighbour pairs over {cont["bound_mm"]:g} mm / '
                 f'{cont["bound_deg"]:g} deg, {len(cont["branch_changes"])} of them branch '
                 'changes between cells at rest')
    return line


@contextmanager
def _closing(close: Callable[[], None]) -> Iterator[None]:
    try:
        yield
    finally:
        close()


def _cmd_build(args: argparse.Namespace) -> int:
    configs = args.config or [None]
    outs: list[Path]
    if len(configs) == 1:
        outs = [args.out]
    else:
        if args.out.suffix:
            raise ConfigError(f'--out {args.out}: with several configs give a directory; '
                              'each table is named after its config')
        outs = [args.out / f'{Path(c).stem}.npz' for c in configs]
    loaded = []
    for path in configs:
        cfg_path = materialise_default_knee() if path is None else Path(path)
        mesh_dir = None if path is not None else cfg_path.parent
        if args.mesh_dir is not None:
            mesh_dir = args.mesh_dir
        overrides: dict[str, Any] = {}
        given = (('flexion_deg', args.flexion_grid), ('varus_deg', args.varus_grid))
        grid = {key: value for key, value in given if value is not None}
        if grid:
            overrides['grid'] = grid
        if args.method is not None:
            overrides['settle'] = {'method': args.method}
        loaded.append(load_config(cfg_path, mesh_dir, overrides or None))
    for out in outs:
        if not out.parent.is_dir():
            out.parent.mkdir(parents=True, exist_ok=True)
    executor, close = executor_for(args.workers, args.scheduler)
    totals = {'cells': 0, 'converged': 0, 'wall_s': 0.0}
    with _closing(close):
        for config, out in zip(loaded, outs):
            table = build_table(config, out, executor, show_progress=not args.quiet)
            print(summary_line(table, out))
            s = table.metadata['summary']
            totals['cells'] += s['cells']
            totals['converged'] += s['converged']
            totals['wall_s'] += s['wall_s']
            for line in backed_out_lines(table):
                print(line)
            for reason in table.metadata.get('failures', []):
                print(f'  not converged: {reason}')
    if len(loaded) > 1:
        print(f'all {len(loaded)} tables: {totals["cells"]} cells, '
              f'{100 * totals["converged"] / max(totals["cells"], 1):.1f}% converged, '
              f'{totals["wall_s"]:.1f} s wall')
    return 0


def _grid_arg(text: str) -> list[float]:
    parts = text.replace(',', ' ').split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not START,STOP,STEP in degrees") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"'{text}' is not START,STOP,STEP in degrees")
    try:
        grid_values(values, 'grid')
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return values


def _cmd_synth(args: argparse.Namespace) -> int:
    config = materialise_default_knee(args.out)
    print(f'wrote the default knee to {args.out} (meshes and {config.name})')
    return 0


def register_commands(sub: Subcommands) -> None:
    """Add `build` and `synth` to the `kneeseat` subcommand parser."""
    p = sub.add_parser('build', help='settle a knee over its range of motion into a table')
    p.add_argument('config', nargs='*', type=Path,
                   help='knee config YAML (none: the embedded default knee; several: a batch '
                   'sharing one executor)')
    p.add_argument('--out', type=Path, required=True,
                   help='table file (.npz), or a directory when several configs are given')
    p.add_argument('--workers', type=int, default=default_workers(),
                   help=f'worker processes (default: all cores, here {default_workers()})')
    p.add_argument('--scheduler', metavar='tcp://HOST:PORT',
                   help='run the sweep on a Dask distributed cluster instead')
    p.add_argument('--mesh-dir', type=Path, help='directory that holds the config meshes')
    p.add_argument('--flexion-grid', type=_grid_arg, metavar='START,STOP,STEP',
                   help='override the flexion grid (degrees)')
    p.add_argument('--varus-grid', type=_grid_arg, metavar='START,STOP,STEP',
                   help='override the varus grid (degrees)')
    p.add_argument('--method', choices=('default', 'patent'), help='override the settle method')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(command=_cmd_build)

    p = sub.add_parser('synth', help='write the embedded default knee (meshes + config)')
    p.add_argument('--out', type=Path, required=True, help='output directory')
    p.set_defaults(command=_cmd_synth)
