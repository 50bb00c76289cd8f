"""A slice of a knee's table built in this process, the options that choose it, and a
file's source at another revision: what the benchmarks that look inside the settles share
(`settle_costs.py`, `engine_ab.py`, `climb_ab.py`)."""
from __future__ import annotations

import argparse
from pathlib import Path
import subprocess
import sys

from bench_build import CONFIGS, DEFAULT_DATA, NATURAL_DATA, REPO
from kneeseat_core.cli import main as kneeseat


def add_slice_options(parser: argparse.ArgumentParser) -> None:
    """The knees, the slice's grid and where the meshes are."""
    parser.add_argument('--knees', default='tka,natural,default',
                        help='comma list: default, tka, natural, natural_no_menisci')
    parser.add_argument('--flexion-grid', default='-30,-50,-1', help='START,STOP,STEP degrees')
    parser.add_argument('--varus-grid', default='-10,10,1', help='START,STOP,STEP degrees')
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='directory of the total-knee meshes')
    parser.add_argument('--natural-data', type=Path, default=NATURAL_DATA,
                        help='directory of the natural-knee meshes')


def slice_knees(args: argparse.Namespace) -> list[str]:
    """The knees asked whose meshes are there (the others are named as skipped)."""
    data = {'data': args.data, 'natural_data': args.natural_data}
    knees = []
    for knee in (k for k in args.knees.split(',') if k):
        if knee in CONFIGS and not any(data[CONFIGS[knee][1]].glob('*.stl')):
            print(f'skipping {knee}: no meshes in {data[CONFIGS[knee][1]]}', file=sys.stderr)
        else:
            knees.append(knee)
    return knees


def build_slice(knee: str, args: argparse.Namespace, out: Path) -> None:
    """Build `knee`'s slice to `out` in this process (`kneeseat build --workers 1`)."""
    command = ['build', '--out', str(out), '--workers', '1', '--quiet',
               f'--flexion-grid={args.flexion_grid}', f'--varus-grid={args.varus_grid}']
    if knee in CONFIGS:
        config, where = CONFIGS[knee]
        data = args.data if where == 'data' else args.natural_data
        command[1:1] = [str(REPO / 'config' / config), '--mesh-dir', str(data)]
    if kneeseat(command) != 0:
        raise SystemExit(f'{knee}: the build failed')


def source_at(base: str, path: str) -> str:
    """The text of the repository's file `path` at git revision `base`, or of the file
    `base` itself."""
    if Path(base).is_file():
        return Path(base).read_text()
    found = subprocess.run(['git', '-C', str(REPO), 'show', f'{base}:{path}'],
                           capture_output=True, text=True)
    if found.returncode != 0:
        raise SystemExit(f'--base {base}: neither a file nor a git revision with {path}: '
                         f'{found.stderr.strip()}')
    return found.stdout
