"""`kneeseat build` and `kneeseat synth`: from knee configs to table files, and the
embedded default knee written out.

`build` loads each config (none: the embedded default knee), applies the grid and method
overrides, sweeps them on one executor and prints one summary per table
(`kneeseat_core.sweep.build`). Ctrl-C stops cleanly and leaves no table file. The knee
and the sweep load trimesh and python-fcl (about 2 s): the handlers import them, so that
`kneeseat --help` and the other commands start without.
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, TYPE_CHECKING

from kneeseat_core.args import default_workers, worker_count
from kneeseat_core.errors import ConfigError, TableError
from kneeseat_core.files import unwritable, unwritable_directory
from kneeseat_core.status import converged_share

if TYPE_CHECKING:
    from kneeseat_core.args import Subcommands

__all__ = ['register_commands']


@contextmanager
def _closing(close: Callable[[], None]) -> Iterator[None]:
    try:
        yield
    finally:
        close()


def _cmd_build(args: argparse.Namespace) -> int:
    from kneeseat_core.knee import load_config, materialise_default_knee     # trimesh
    from kneeseat_core.sweep import backed_out_lines, build_table, executor_for, summary_line
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
    for out in outs:        # before the sweep, not after it
        why = unwritable(out)
        if why is not None:
            raise TableError(f'--out {out}: cannot write a table there ({why}); give a file '
                             'path in a writable directory')
    executor, close = executor_for(args.workers, args.scheduler)
    cells = converged = 0
    wall_s = 0.0
    with _closing(close):
        for config, out in zip(loaded, outs):
            table = build_table(config, out, executor, show_progress=not args.quiet)
            print(summary_line(table, out))
            s = table.metadata['summary']
            cells += int(s['cells'])
            converged += int(s['converged'])
            wall_s += float(s['wall_s'])
            for line in backed_out_lines(table):
                print(line)
            for reason in table.metadata.get('failures', []):
                print(f'  not converged: {reason}')
    if len(loaded) > 1:
        print(f'all {len(loaded)} tables: {cells} cells, '
              f'{converged_share(converged, cells)} converged, {wall_s:.1f} s wall')
    return 0


def _grid_arg(text: str) -> list[float]:
    parts = text.replace(',', ' ').split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not START,STOP,STEP in degrees") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"'{text}' is not START,STOP,STEP in degrees")
    from kneeseat_core.knee import grid_values       # trimesh, only with this option
    try:
        grid_values(values, 'grid')
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return values


def _cmd_synth(args: argparse.Namespace) -> int:
    from kneeseat_core.knee import materialise_default_knee     # trimesh
    why = unwritable_directory(args.out)
    if why is not None:
        raise ConfigError(f'--out {args.out}: cannot write the default knee there ({why}); '
                          'give a directory that can be written or made')
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
    p.add_argument('--workers', type=worker_count, default=default_workers(),
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
