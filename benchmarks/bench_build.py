"""Cost of a full table build: the knees, 1 and 2 workers.

Run: `python benchmarks/bench_build.py [--knees default,tka,natural,natural_no_menisci]
[--workers 1,2] [--data ../shared/data/tka_dm] [--natural-data ../shared/data/natural_knee]
[--flexion-grid=0,-90,1 --varus-grid=-10,10,1] [--keep DIR]`.
Each build is `kneeseat build` (tibia and patella, the patent grid 91 x 21, step 1 mm,
resolution 0.1 mm unless overridden) run as its own subprocess into a temporary directory,
so that its peak memory can be read from the kernel: `os.wait4` returns the resource
usage of the build and of the worker processes it waited for, whose `ru_maxrss` is the
peak resident set of the largest of them (not a sum). For each build it prints wall time
(of the subprocess: start-up, meshes, sweep and the table write), the sweep's own wall time
from the table's metadata (of it the bodies and their hierarchies built before any chain
can start, and how busy the workers were after that: the chains' own times summed, over
the workers times the rest of the sweep), cells per second, collision checks per cell,
converged cells,
and the peak RSS; with the machine (CPU model, count) and the load average before and after
each build, because the 2 cores are shared with other engineers.
Targets (full grid, 2 workers, wall): the total knee's table and the natural knee's in
<= 10 s each, the default knee's in <= 5 s; each is printed as met or not (the README says
where they stand).
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

from kneeseat_core.status import converged_share
from kneeseat_core.table import read_table
from machine import describe_machine, load_average

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / 'shared' / 'data' / 'tka_dm'
NATURAL_DATA = REPO.parent / 'shared' / 'data' / 'natural_knee'
# knee -> (config, which data directory it reads); the default knee is embedded
CONFIGS = {'tka': ('tka_dm.yaml', 'data'), 'natural': ('natural_knee.yaml', 'natural_data'),
           'natural_no_menisci': ('natural_knee_no_menisci.yaml', 'natural_data')}
# full-grid wall with 2 workers (s), per knee
TARGETS_S = {'tka': 10.0, 'natural': 10.0, 'default': 5.0}


def build(knee: str, workers: int, data: Path, grid: list[str], work: Path) -> dict[str, Any]:
    """Run one `kneeseat build` subprocess; return its measurements."""
    out = work / f'{knee}_{workers}.npz'
    cmd = [sys.executable, '-m', 'kneeseat_core', 'build', '--out', str(out),
           '--workers', str(workers), '--quiet', *grid]
    if knee in CONFIGS:
        cmd[4:4] = [str(REPO / 'config' / CONFIGS[knee][0]), '--mesh-dir', str(data)]
    env = dict(os.environ, XDG_CACHE_HOME=str(work / 'cache'))
    before = load_average()
    started = time.perf_counter()
    log = work / f'{knee}_{workers}.log'
    with open(log, 'wb') as sink:       # a file, not a pipe: nothing can block the build
        proc = subprocess.Popen(cmd, env=env, stdout=sink, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - started
    output = log.read_text(errors='replace').strip()
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise SystemExit(f'build {knee} with {workers} workers failed (exit {code}): '
                         f'{output}')
    table = read_table(out)
    summary = table.metadata['summary']
    conv = np.asarray(table.converged)
    return {
        'knee': knee, 'workers': workers, 'wall_s': wall, 'sweep_s': summary['wall_s'],
        # tables from before these were recorded have neither
        'scene_s': summary.get('scene_s', math.nan),
        'busy': summary.get('chains_s', math.nan)
        / (workers * max(summary['wall_s'] - summary.get('scene_s', 0.0), 1e-9)),
        'cells': summary['cells'], 'cells_per_s': summary['cells'] / summary['wall_s'],
        'checks_per_cell': summary['collision_checks'] / summary['cells'],
        'converged': converged_share(int(conv.sum()), conv.size),
        'per_body': ', '.join(f'{n} {converged_share(int(conv[b].sum()), conv[b].size)}'
                              for b, n in enumerate(table.bodies)),
        'peak_rss_mb': usage.ru_maxrss / 1024.0,      # Linux: kilobytes
        'cpu_s': usage.ru_utime + usage.ru_stime,
        'load_before': before, 'load_after': load_average(),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--knees', default='default,tka',
                        help='comma list: default, tka, natural, natural_no_menisci')
    parser.add_argument('--workers', default='1,2', help='comma list of worker counts')
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='directory of the total-knee meshes')
    parser.add_argument('--natural-data', type=Path, default=NATURAL_DATA,
                        help='directory of the natural-knee meshes')
    parser.add_argument('--flexion-grid', help='override, START,STOP,STEP degrees')
    parser.add_argument('--varus-grid', help='override, START,STOP,STEP degrees')
    parser.add_argument('--keep', type=Path, metavar='DIR',
                        help='copy every table built into DIR (KNEE_WORKERS.npz)')
    args = parser.parse_args()
    grid = []
    if args.flexion_grid:
        grid += [f'--flexion-grid={args.flexion_grid}']
    if args.varus_grid:
        grid += [f'--varus-grid={args.varus_grid}']
    knees = [k for k in args.knees.split(',') if k]
    data = {'data': args.data, 'natural_data': args.natural_data}
    for knee in [k for k in knees if k in CONFIGS]:
        where = data[CONFIGS[knee][1]]
        if not any(where.glob('*.stl')):
            print(f'skipping {knee}: no meshes in {where}', file=sys.stderr)
            knees.remove(knee)
    print(describe_machine())
    rows = []
    with tempfile.TemporaryDirectory(prefix='bench_build.') as tmp:
        for knee in knees:
            for workers in (int(w) for w in args.workers.split(',')):
                where = data[CONFIGS[knee][1]] if knee in CONFIGS else args.data
                row = build(knee, workers, where, grid, Path(tmp))
                rows.append(row)
                if args.keep:
                    args.keep.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(Path(tmp) / f'{knee}_{workers}.npz', args.keep)
                print(f'{knee:18s} workers {workers}: wall {row["wall_s"]:6.1f} s (sweep '
                      f'{row["sweep_s"]:.1f} s: bodies {row["scene_s"]:.2f} s, then workers '
                      f'{row["busy"]:.0%} busy), {row["cells"]} cells, {row["cells_per_s"]:.1f}'
                      f' cells/s, {row["checks_per_cell"]:.0f} checks/cell, converged '
                      f'{row["converged"]} ({row["per_body"]}), peak RSS '
                      f'{row["peak_rss_mb"]:.0f} MB, CPU {row["cpu_s"]:.0f} s; load '
                      f'{row["load_before"]} -> {row["load_after"]}', flush=True)
    for row in rows:
        target = TARGETS_S.get(row['knee'])
        if target is not None and row['workers'] == 2 and not grid:
            verdict = 'met' if row['wall_s'] <= target else 'NOT met'
            print(f'target ({row["knee"]}, 2 workers, <= {target:.0f} s wall): {verdict} '
                  f'({row["wall_s"]:.1f} s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
