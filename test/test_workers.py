"""A sweep's workers get ready for their chains: the default pool's are forked from the sweep
with its scene built, and the next worker of a pool that starts them one by one builds the
scene while the first settles the centre cells (`prepare_worker`)."""
from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor
import json
import multiprocessing
import os
from pathlib import Path
import subprocess
import sys
import threading
from typing import Any, Callable

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from kneeseat_core.cli.main import one_blas_thread
from kneeseat_core.knee import load_config, materialise_default_knee
from kneeseat_core.meshes import sweep_body
from kneeseat_core.sweep import (InlineExecutor, prepare_worker, process_executor,
                                 scene_bodies, SceneSpec, sweep)
from kneeseat_core.sweep.chains import run_chain
from kneeseat_core.sweep.executors import LocalPool, submitted_ahead
from kneeseat_core.sweep.scene import scene_builds

GRID = {'flexion_deg': [0, -20, 10], 'varus_deg': [-5, 5, 5]}


class Recording(ProcessPoolExecutor):
    """A process pool (spawned workers) that notes what is submitted to it, in order."""

    def __init__(self) -> None:
        super().__init__(max_workers=2, mp_context=multiprocessing.get_context('spawn'))
        self.names: list[str] = []
        self.prepared: list[Future[Any]] = []

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        self.names.append(fn.__name__)
        future = super().submit(fn, *args, **kwargs)
        if fn is prepare_worker:
            self.prepared.append(future)
        return future


def test_a_sweep_readies_the_next_worker_while_the_centre_cells_settle(tmp_path: Path) -> None:
    config = load_config(materialise_default_knee(tmp_path), None, {'grid': GRID})
    with Recording() as pool:
        result = sweep(config, pool)
        pid = pool.prepared[0].result(timeout=120)
    # once, right after the chains that start from nothing (the centre cells), before any
    # chain that waits for them
    assert pool.names.count('prepare_worker') == 1
    first = pool.names.index('prepare_worker')
    assert first >= 1 and set(pool.names[:first]) == {'run_chain'}
    assert len(pool.names) > first + 1
    assert pid != os.getpid()
    assert result.converged.all()
    # the same table as in-process, where preparing finds everything built already
    inline = sweep(config, InlineExecutor())
    assert np.array_equal(result.position_m, inline.position_m)
    assert np.array_equal(result.orientation_xyzw, inline.orientation_xyzw)


def test_the_default_pool_starts_its_workers_with_the_scene_the_sweep_built(
        tmp_path: Path) -> None:
    """The sweep builds its scene before it submits anything, and the default pool's
    workers are forked then: none of them builds it again."""
    config = load_config(materialise_default_knee(tmp_path), None, {'grid': GRID})
    pool = process_executor(2)
    try:
        result = sweep(config, pool)
        built_here = scene_builds()
        workers = {pool.submit(os.getpid).result(timeout=60) for _ in range(8)}
        builds = {pool.submit(scene_builds).result(timeout=60) for _ in range(8)}
    finally:
        pool.shutdown(wait=True)
    assert result.converged.all()
    assert os.getpid() not in workers
    assert builds == {built_here}       # what each worker inherited, and nothing since


class Counting(LocalPool):
    """The default pool, counting the chains submitted and not yet finished, in the order
    they were submitted."""

    def __init__(self) -> None:
        super().__init__(2, multiprocessing.get_context('fork'))
        self.outstanding = self.most = 0
        self.chains: list[tuple[tuple[int, int], ...]] = []
        self._lock = threading.Lock()

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        future = super().submit(fn, *args, **kwargs)
        if fn is run_chain:
            with self._lock:
                self.outstanding += 1
                self.most = max(self.most, self.outstanding)
                self.chains.append(args[0].cells)
            future.add_done_callback(self._finished)
        return future

    def _finished(self, _: Future[Any]) -> None:
        with self._lock:
            self.outstanding -= 1


@pytest.mark.skipif('fork' not in multiprocessing.get_all_start_methods(),
                    reason='the default pool forks its workers where the platform forks')
def test_a_sweep_keeps_no_more_chains_submitted_than_the_pool_can_take(
        tmp_path: Path) -> None:
    """The default pool of two workers is given at most three chains at a time, the others
    waiting in the sweep's order; the table is the one settled in-process."""
    config = load_config(materialise_default_knee(tmp_path), None,
                         {'grid': {'flexion_deg': [0, -30, 5], 'varus_deg': [-3, 3, 1]}})
    assert submitted_ahead(process_executor(1)) is None           # in-process: as submitted
    with Counting() as pool:
        assert submitted_ahead(pool) == 3
        result = sweep(config, pool)
    assert pool.most == 3
    assert len(pool.chains) > 3 * pool.most
    inline = sweep(config, InlineExecutor())
    assert np.array_equal(result.position_m, inline.position_m)
    assert np.array_equal(result.orientation_xyzw, inline.orientation_xyzw)


def test_preparing_builds_the_scene_once_per_process(tmp_path: Path) -> None:
    config = load_config(materialise_default_knee(tmp_path), None, {'grid': GRID})
    groups = [tuple(str(m) for m in spec.meshes) for spec in (config.reference, *config.bodies)]
    spec = SceneSpec(groups[0], tuple(groups[1:]), config.units)
    built = scene_builds()
    assert prepare_worker(spec) == os.getpid()
    assert scene_builds() == built + 1
    fixed, bodies = scene_bodies(spec)
    kept = [sweep_body(body) for body in (fixed, *bodies)]
    assert prepare_worker(spec) == os.getpid()
    assert scene_builds() == built + 1                      # nothing built again
    assert all(sweep_body(b) is k for b, k in zip((fixed, *bodies), kept))


def test_a_command_keeps_openblas_to_one_thread_while_it_runs(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """While a command runs, this process's OpenBLAS uses one thread and a worker spawned
    then starts with one; afterwards the variable that told it is gone, and a value the
    user set is left as it was."""
    monkeypatch.delenv('OPENBLAS_NUM_THREADS', raising=False)
    with one_blas_thread():
        assert os.environ['OPENBLAS_NUM_THREADS'] == '1'
        assert blas_threads(threadpool_info()) == {1}
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) as pool:
            pool.submit(exec, 'import numpy').result(timeout=60)
            assert blas_threads(pool.submit(threadpool_info).result(timeout=60)) == {1}
    assert 'OPENBLAS_NUM_THREADS' not in os.environ
    monkeypatch.setenv('OPENBLAS_NUM_THREADS', '2')
    with one_blas_thread():
        assert os.environ['OPENBLAS_NUM_THREADS'] == '2'


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason='OpenBLAS starts no thread on one core')
def test_the_kneeseat_program_loads_openblas_with_one_thread(tmp_path: Path) -> None:
    """Run as a program (`kneeseat_core.console.run`), the command line sets the variable
    before numpy loads OpenBLAS, so that OpenBLAS never makes a second thread (one the
    command's scope set after loading left behind, for this process and a forked worker
    to start again); its exit code still comes through."""
    probe = tmp_path / 'probe.py'
    probe.write_text(
        'import atexit, json, os, sys\n'
        'from threadpoolctl import threadpool_info\n'
        'def report():\n'
        '    counts = sorted({lib["num_threads"] for lib in threadpool_info()\n'
        '                     if lib["user_api"] == "blas"})\n'
        '    print(json.dumps([counts, os.environ.get("OPENBLAS_NUM_THREADS")]))\n'
        'atexit.register(report)\n'
        'sys.argv = ["kneeseat", "info", sys.argv[1]]\n'
        'from kneeseat_core.console import run\n'
        'run()\n')
    env = {k: v for k, v in os.environ.items() if k != 'OPENBLAS_NUM_THREADS'}
    done = subprocess.run([sys.executable, str(probe), str(tmp_path / 'missing.npz')],
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr          # the table is missing: bad input
    assert 'missing.npz' in done.stderr and 'Traceback' not in done.stderr
    counts, variable = json.loads(done.stdout.strip().splitlines()[-1])
    assert counts == [1] and variable == '1'


def blas_threads(info: list[dict[str, Any]]) -> set[int]:
    """The thread counts of the BLAS libraries in a `threadpool_info()`."""
    return {lib['num_threads'] for lib in info if lib['user_api'] == 'blas'}
