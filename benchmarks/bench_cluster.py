"""The default knee swept on the process pool vs on a local Dask cluster, same worker count.

Run: `python benchmarks/bench_cluster.py [--runs 3] [--workers 2] [--flexion-grid 0,-90,2]
[--varus-grid -10,10,2]`.

Each run sweeps the embedded default knee (no table written):
- pool: a fresh process pool (what `kneeseat build --workers N` does), so the wall time
  includes starting the processes, importing kneeseat and building the scene in each;
- dask: a LocalCluster (N worker processes, 1 thread each, loopback) started once; before
  each run its workers are restarted (not timed), then a fresh client connects and ships the
  meshes (what `kneeseat build --scheduler` does against running workers), so the workers
  import kneeseat and build the scene inside the timed run, as the pool does.
Printed per executor (medians over runs): wall s, table cells/s, chains, mean chain compute
s (`ChainResult.elapsed_s`, scene build included), and the overhead per chain
`wall * workers / chains - mean chain compute`: what a chain costs beyond its own compute
(process start, shipping, serialisation, scheduling, and idle workers at the three phase
barriers of the sweep, which both executors share). Rows marked * are a second sweep on the
same pool / client right after the first: the steady state, where scenes are already built.
The two tables are compared too.
"""
from __future__ import annotations

import argparse
from concurrent.futures import Executor, Future
from pathlib import Path
import statistics
import sys
import tempfile
import time
from typing import Any, Callable

import numpy as np

from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.sweep.cluster import dask_executor
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.sweep import process_executor, sweep, SweepResult
from machine import describe_machine


class TimingExecutor(Executor):
    """Delegates to `inner` and records each finished chain's own compute time."""

    def __init__(self, inner: Executor) -> None:
        self.inner = inner
        self.chain_s: list[float] = []

    def submit(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Future:  # type: ignore
        future = self.inner.submit(fn, *args, **kwargs)
        future.add_done_callback(self._record)
        return future

    def _record(self, future: Future) -> None:
        if not future.cancelled() and future.exception() is None:
            self.chain_s.append(future.result().elapsed_s)


def machine() -> str:
    """The machine line plus the library versions this benchmark depends on."""
    import dask
    return f'{describe_machine()}, numpy {np.__version__}, dask {dask.__version__}'


def one_run(config: KneeConfig, executor: Executor,
            workers: int) -> tuple[dict[str, float], SweepResult]:
    """Sweep once on `executor`; the timings (module docstring) and the result."""
    timing = TimingExecutor(executor)
    started = time.perf_counter()
    result = sweep(config, timing)
    wall = time.perf_counter() - started
    chains = len(timing.chain_s)
    mean_chain = statistics.fmean(timing.chain_s)
    row = {'wall_s': wall, 'cells_per_s': result.cells / wall, 'chains': chains,
           'chain_s': mean_chain, 'overhead_s': wall * workers / chains - mean_chain}
    return row, result


def median_row(rows: list[dict[str, float]]) -> dict[str, float]:
    return {k: statistics.median(r[k] for r in rows) for k in rows[0]}


def show(name: str, rows: list[dict[str, float]]) -> None:
    m = median_row(rows)
    walls = ', '.join(f'{r["wall_s"]:.2f}' for r in rows)
    print(f'{name:5s} wall {m["wall_s"]:6.2f} s ({walls}), {m["cells_per_s"]:6.1f} cells/s, '
          f'{m["chains"]:.0f} chains, chain compute {1e3 * m["chain_s"]:7.1f} ms, '
          f'overhead {1e3 * m["overhead_s"]:6.1f} ms/chain')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--flexion-grid', default='0,-90,2')
    parser.add_argument('--varus-grid', default='-10,10,2')
    args = parser.parse_args()
    from distributed import Client, LocalCluster

    def grid(text: str) -> list[float]:
        return [float(x) for x in text.split(',')]

    print(machine())
    with tempfile.TemporaryDirectory(prefix='bench_cluster_') as tmp:
        config = load_config(materialise_default_knee(Path(tmp)), None, {'grid': {
            'flexion_deg': grid(args.flexion_grid), 'varus_deg': grid(args.varus_grid)}})
        cells = len(config.bodies) * config.flexion_rad.size * config.varus_rad.size
        print(f'default knee, flexion {args.flexion_grid} x varus {args.varus_grid} deg: '
              f'{cells} table cells; {args.workers} workers; {args.runs} runs, medians')
        names = ('pool', 'dask', 'pool*', 'dask*')
        rows: dict[str, list[dict[str, float]]] = {k: [] for k in names}
        results: dict[str, SweepResult] = {}
        started = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                          host='127.0.0.1', dashboard_address=None,
                          scheduler_kwargs={'dashboard_address': '127.0.0.1:0'}) as cluster:
            print(f'LocalCluster start: {time.perf_counter() - started:.2f} s (not in walls)')
            for _ in range(args.runs):
                pool = process_executor(args.workers)
                try:
                    row, results['pool'] = one_run(config, pool, args.workers)
                    rows['pool'].append(row)
                    rows['pool*'].append(one_run(config, pool, args.workers)[0])
                finally:
                    pool.shutdown(wait=True)
                with Client(cluster.scheduler_address, set_as_default=False) as admin:
                    admin.restart()
                executor, close = dask_executor(cluster.scheduler_address)
                try:
                    row, results['dask'] = one_run(config, executor, args.workers)
                    rows['dask'].append(row)
                    rows['dask*'].append(one_run(config, executor, args.workers)[0])
                finally:
                    close()
        for name, got in rows.items():
            show(name, got)
        print('*: a second sweep on the same executor (processes, imports and scenes warm)')
        pool_result, dask_result = results['pool'], results['dask']
        diff = max(float(np.max(np.abs(pool_result.position_m - dask_result.position_m))),
                   float(np.max(np.abs(pool_result.orientation_xyzw
                                       - dask_result.orientation_xyzw))))
        print(f'largest difference between the two tables: {diff:.3g} (positions m, '
              'quaternion components)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
