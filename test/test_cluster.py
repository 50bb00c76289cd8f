"""Sweeps on Dask distributed (kneeseat_core/cluster.py) against the process pool.

Real LocalClusters (worker processes, loopback only, no dashboard), the embedded default knee
on a small grid (flexion 0..-90 by 10, varus -10..10 by 5: 100 cells, 24 chains). The slow
tests build the knee on the process pool once (a batch of two configs) and compare.
"""
from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor
import dataclasses
import multiprocessing
import os
from pathlib import Path
import shutil
import signal
import socket
import threading
import time
from types import SimpleNamespace
from typing import Any, Iterator

from distributed import Client, KilledWorker, LocalCluster
import numpy as np
import pytest
from threadpoolctl import threadpool_info

from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.cli import main
from kneeseat_core.sweep.cluster import _forward, dask_executor, worker_stats
from kneeseat_core.errors import ConfigError, KneeseatError, MeshError
from kneeseat_core.geometry import pose_from
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.sweep import chains as chain_module
from kneeseat_core.sweep import ChainJob, make_table, run_chain, SceneSpec, sweep
from kneeseat_core.files import file_sha256
from kneeseat_core.table import PoseTable, read_table

FLEXION = '0,-90,10'
VARUS = '-10,10,5'
GRID = {'flexion_deg': [0, -90, 10], 'varus_deg': [-10, 10, 5]}
UNDER_WAY = 22                # cells reported (of 100) when a worker is killed mid-sweep
# 2 centres + 2 flexion spines in segments of 8 + 1 cells + 10 x 2 tibia varus ribs
CHAINS = 2 + 2 * 2 + 20
MESHES = 3                    # femur, tibia, patella
DEADLINE_S = 120.0


def local_cluster(n_workers: int = 2) -> LocalCluster:
    """Worker processes with one thread each, bound to loopback, no dashboard.

    The scheduler still serves /health and /metrics over HTTP; it gets a free loopback port
    (by default it would try 8787, which another cluster on this machine may hold).
    """
    return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                        host='127.0.0.1', dashboard_address=None,
                        scheduler_kwargs={'dashboard_address': '127.0.0.1:0'})


@pytest.fixture(scope='module')
def knees(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two configs of a 'cohort': the default knee, and a copy of it in another folder."""
    first = materialise_default_knee(tmp_path_factory.mktemp('knee_a'))
    other = tmp_path_factory.mktemp('knee_b')
    for item in first.parent.iterdir():
        shutil.copy(item, other / item.name)
    second = other / 'subject_b.yaml'
    (other / first.name).rename(second)
    return first, second


@pytest.fixture(scope='module')
def small_config(knees: tuple[Path, Path]) -> KneeConfig:
    return load_config(knees[0], None, {'grid': GRID})


@pytest.fixture(scope='module')
def cluster() -> Iterator[LocalCluster]:
    with local_cluster() as running:
        yield running


@pytest.fixture(scope='module')
def pool_tables(knees: tuple[Path, Path],
                tmp_path_factory: pytest.TempPathFactory) -> tuple[PoseTable, PoseTable]:
    """The cohort built on the process pool (2 workers), through the CLI."""
    out = tmp_path_factory.mktemp('pool')
    code = main(['build', str(knees[0]), str(knees[1]), '--out', str(out), '--workers', '2',
                 f'--flexion-grid={FLEXION}', f'--varus-grid={VARUS}', '--quiet'])
    assert code == 0
    return read_table(out / f'{knees[0].stem}.npz'), read_table(out / f'{knees[1].stem}.npz')


def assert_same_table(got: PoseTable, want: PoseTable) -> None:
    np.testing.assert_array_equal(got.flexion_rad, want.flexion_rad)
    np.testing.assert_array_equal(got.varus_rad, want.varus_rad)
    assert got.position_m.shape == want.position_m.shape
    # bit for bit: what a cell settles to does not depend on which process settled the
    # cells before it
    np.testing.assert_array_equal(got.position_m, want.position_m)
    np.testing.assert_array_equal(got.orientation_xyzw, want.orientation_xyzw)
    np.testing.assert_array_equal(got.converged, want.converged)
    np.testing.assert_array_equal(got.iterations, want.iterations)


def stats(address: str) -> dict[str, dict[str, int]]:
    with Client(address, set_as_default=False, timeout=10) as client:
        return client.run(worker_stats)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(('127.0.0.1', 0))
        return int(sock.getsockname()[1])


# --- bad input: one-line ConfigErrors, fast ----------------------------------------------

@pytest.mark.parametrize('address', ['localhost', 'tcp://127.0.0.1', 'http://host:8786',
                                     'tcp://host:port'])
def test_bad_address_is_refused(address: str) -> None:
    with pytest.raises(ConfigError, match=r'not a Dask scheduler address; give tcp://HOST'):
        dask_executor(address)


def test_unreachable_scheduler_is_one_clear_line() -> None:
    address = f'tcp://127.0.0.1:{free_port()}'
    started = time.monotonic()
    with pytest.raises(ConfigError, match=r'cannot reach Dask scheduler tcp://127\.0\.0\.1:\d+ '
                       r'within 1 s .*start one with `dask scheduler`') as err:
        dask_executor(address, timeout_s=1.0)
    assert '\n' not in str(err.value)
    assert time.monotonic() - started < 15.0


def test_scheduler_without_workers_is_one_clear_line() -> None:
    with local_cluster(n_workers=0) as empty:
        with pytest.raises(ConfigError, match=r'no Dask worker joined scheduler tcp://.* within '
                           r'0\.5 s; start some with `dask worker tcp://'):
            dask_executor(empty.scheduler_address, workers_timeout_s=0.5)


def test_cli_bad_scheduler_exits_with_one_line(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str],
                                               knees: tuple[Path, Path]) -> None:
    code = main(['build', str(knees[0]), '--out', str(tmp_path / 't.npz'),
                 '--scheduler', 'scheduler-host', '--quiet'])
    err = capsys.readouterr().err
    assert code == 2                                   # bad input (docs/design.md)
    assert err.count('\n') == 1 and 'Traceback' not in err
    assert "--scheduler 'scheduler-host': not a Dask scheduler address" in err
    assert not (tmp_path / 't.npz').exists()


def test_a_chain_that_keeps_killing_workers_becomes_a_kneeseat_error() -> None:
    inner: Future = Future()
    outer: Future = Future()
    last = SimpleNamespace(address='tcp://127.0.0.1:1')   # stands for a WorkerState
    inner.set_exception(KilledWorker('run_chain-1', last, 3))
    _forward(inner, outer, 'tcp://127.0.0.1:8786')
    err = outer.exception()
    assert isinstance(err, KneeseatError)
    assert 'lost with every Dask worker that ran it (tcp://127.0.0.1:8786)' in str(err)
    ok: Future = Future()
    ok.set_result(42)
    copied: Future = Future()
    _forward(ok, copied, 'tcp://127.0.0.1:8786')
    assert copied.result() == 42


# --- meshes: shipped once per worker, resolved by content -------------------------------

def tibia_scene(config: KneeConfig) -> SceneSpec:
    """The scene of `config`'s reference and first body, as the sweep ships it."""
    return SceneSpec(str(config.reference.mesh), (str(config.bodies[0].mesh),), config.units,
                     (file_sha256(config.reference.mesh), file_sha256(config.bodies[0].mesh)))


def spine_job(config: KneeConfig, scene: SceneSpec) -> ChainJob:
    """The tibia's centre cell and two flexion steps, as `sweep` would chain them."""
    body = config.bodies[0]
    flexion = np.radians([0.0, -10.0, -20.0])
    attitudes = np.array([config.attitude(body, f, 0.0) for f in flexion])
    params = tuple(config.params(body, f, 0.0) for f in flexion)
    start = pose_from(np.eye(3), -np.asarray(params[0].push) * config.settle.step_m)
    return ChainJob(scene, 0, ((0, 0), (1, 0), (2, 0)), attitudes, params, start, np.eye(3),
                    np.eye(4), np.eye(3))


def test_a_chain_starts_its_climbs_with_short_moves_only_from_a_rest(
        small_config: KneeConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    # a chain whose start is not a rest (a centre cell's) climbs its first cell with the
    # ordinary first moves, and the cells after it, each started from the rest before it,
    # with short ones; a chain that starts from a rest starts short at once
    asked: list[bool] = []
    real = chain_module.settle

    def recording(*args: Any, **kwargs: Any) -> Any:
        asked.append(bool(kwargs['near_rest'] if 'near_rest' in kwargs
                          else len(args) > 7 and args[7]))
        return real(*args, **kwargs)
    monkeypatch.setattr(chain_module, 'settle', recording)
    job = spine_job(small_config, tibia_scene(small_config))
    cold = run_chain(dataclasses.replace(job, start_at_rest=False))
    assert cold.converged.all() and asked == [False, True, True]
    asked.clear()
    warm = run_chain(job)
    assert warm.converged.all() and asked == [True, True, True]


def test_a_cell_the_ribs_beside_lead_astray_settles_from_its_own_change(
        small_config: KneeConfig) -> None:
    # a change of rest "from the ribs beside" that throws the middle cell's start 25 mm
    # across the push, beyond the 20 mm envelope: that settle fails, and the cell settles
    # from the start it would have had without the ribs beside, to the same pose bit for bit
    job = spine_job(small_config, tibia_scene(small_config))
    plain = run_chain(job)
    astray = np.full((3, 4, 4), np.nan)
    astray[1] = np.eye(4)
    astray[1, 0, 3] = 0.025
    led = run_chain(dataclasses.replace(job, beside=astray))
    assert plain.converged.all() and led.converged.all()
    np.testing.assert_array_equal(led.poses, plain.poses)
    assert led.collision_checks > plain.collision_checks    # the failed settle is counted


def blas_threads(info: list[dict[str, Any]]) -> set[int]:
    """The thread counts of the BLAS libraries in a `threadpool_info()`."""
    return {lib['num_threads'] for lib in info if lib['user_api'] == 'blas'}


def test_a_worker_that_runs_a_chain_keeps_blas_to_one_thread(small_config: KneeConfig) -> None:
    # OpenBLAS threads spin between a settle's small products on the cores the other
    # workers need: a process that has run a chain uses one
    scene = tibia_scene(small_config)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) as pool:
        pool.submit(exec, 'import numpy').result(timeout=DEADLINE_S)
        before = blas_threads(pool.submit(threadpool_info).result(timeout=DEADLINE_S))
        pool.submit(run_chain, spine_job(small_config, scene)).result(timeout=DEADLINE_S)
        after = blas_threads(pool.submit(threadpool_info).result(timeout=DEADLINE_S))
    assert after == {1}
    if (os.cpu_count() or 1) > 1:
        assert max(before) > 1          # a fresh worker had more: the limit is the chain's


def test_workers_without_the_files_settle_from_shipped_bytes(
        cluster: LocalCluster, small_config: KneeConfig, tmp_path: Path) -> None:
    # The meshes only exist on the 'client' (this process) while they are shipped; the
    # workers then get jobs whose paths exist nowhere. PLY copies: content the workers
    # have never seen, so nothing can come from an earlier build.
    import trimesh
    paths = []
    for spec in (small_config.reference, small_config.bodies[0]):     # femur, tibia
        path = tmp_path / 'client_only' / f'{spec.name}.ply'
        path.parent.mkdir(exist_ok=True)
        trimesh.load(str(spec.mesh), force='mesh').export(str(path))
        paths.append(path)
    scene = SceneSpec(str(paths[0]), tuple(str(p) for p in paths[1:]), small_config.units,
                      tuple(file_sha256(p) for p in paths))
    job = spine_job(small_config, scene)
    want = run_chain(job)                   # in this process, from the files
    before = stats(cluster.scheduler_address)
    executor, close = dask_executor(cluster.scheduler_address)
    try:
        executor.ship(scene)
        shutil.rmtree(paths[0].parent)
        assert not any(p.exists() for p in paths)
        got = executor.submit(run_chain, job).result(timeout=DEADLINE_S)
    finally:
        close()
    after = stats(cluster.scheduler_address)
    np.testing.assert_array_equal(got.poses, want.poses)
    np.testing.assert_array_equal(got.converged, want.converged)
    for worker, row in after.items():
        assert row['meshes_received'] - before[worker]['meshes_received'] == 2
        assert row['files_written'] - before[worker]['files_written'] == 2


def test_shipping_refuses_a_mesh_changed_during_the_build(
        cluster: LocalCluster, small_config: KneeConfig, tmp_path: Path) -> None:
    path = tmp_path / 'femur.stl'
    shutil.copy(small_config.reference.mesh, path)
    scene = SceneSpec(str(path), (str(small_config.bodies[0].mesh),), small_config.units,
                      (file_sha256(path), file_sha256(small_config.bodies[0].mesh)))
    path.write_bytes(path.read_bytes()[:-50])
    executor, close = dask_executor(cluster.scheduler_address)
    try:
        with pytest.raises(MeshError, match=r'femur\.stl: changed during the build'):
            executor.submit(run_chain, spine_job(small_config, scene))
    finally:
        close()


@pytest.mark.slow
def test_batch_on_local_cluster_equals_process_pool_and_ships_once_per_worker(
        cluster: LocalCluster, knees: tuple[Path, Path], pool_tables: tuple[PoseTable, ...],
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = stats(cluster.scheduler_address)
    code = main(['build', str(knees[0]), str(knees[1]), '--out', str(tmp_path),
                 '--scheduler', cluster.scheduler_address, f'--flexion-grid={FLEXION}',
                 f'--varus-grid={VARUS}', '--quiet'])
    out = capsys.readouterr().out
    assert code == 0
    after = stats(cluster.scheduler_address)
    # one table per config, a summary line each and a combined one
    for knee, want in zip(knees, pool_tables):
        table = tmp_path / f'{knee.stem}.npz'
        assert f'{table}: 100 cells' in out
        assert_same_table(read_table(table), want)
    assert 'all 2 tables: 200 cells' in out
    # meshes went to each worker once per build client, not once per task
    delta = {w: {k: after[w][k] - before[w][k] for k in after[w]} for w in after}
    chains = [d['chains_run'] for d in delta.values()]
    assert sum(chains) == 2 * CHAINS and max(chains) >= 2
    for row in delta.values():
        assert row['meshes_received'] == MESHES     # same bytes in both configs: one plugin
        assert row['scene_builds'] <= 2             # one per config it worked on
        assert row['files_written'] in (0, MESHES)  # 0: on disk from an earlier build


@pytest.mark.slow
def test_build_survives_a_killed_worker(small_config: KneeConfig,
                                        pool_tables: tuple[PoseTable, ...]) -> None:
    cells = 0
    enough = threading.Event()
    outcome: dict[str, Any] = {}

    def progress(n: int) -> None:
        nonlocal cells
        cells += n
        if cells >= UNDER_WAY:
            enough.set()

    with local_cluster() as running:
        executor, close = dask_executor(running.scheduler_address)
        try:
            def build() -> None:
                try:
                    outcome['result'] = sweep(small_config, executor, progress)
                except BaseException as err:  # noqa: B902 - reported by the test thread
                    outcome['error'] = err
                    enough.set()

            worker = threading.Thread(target=build, daemon=True)
            worker.start()
            assert enough.wait(DEADLINE_S), 'sweep made no progress'
            assert 'error' not in outcome, outcome.get('error')
            busy = [w for w, keys in executor.client.processing().items() if keys]
            assert busy, 'no worker held a chain when one was to be killed'
            pid = executor.client.run(os.getpid, workers=[busy[0]])[busy[0]]
            os.kill(pid, signal.SIGKILL)
            worker.join(DEADLINE_S)
            assert not worker.is_alive(), 'sweep did not finish after a worker was killed'
            assert busy[0] not in executor.client.scheduler_info()['workers']   # it is gone
        finally:
            close()
    assert 'error' not in outcome, outcome.get('error')
    result = outcome['result']
    assert cells == result.cells   # every cell reported once, the patella's copies too
    table = make_table(small_config, result)
    assert_same_table(table, pool_tables[0])
