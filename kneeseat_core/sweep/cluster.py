"""Sweeps on a Dask distributed cluster, through the same Executor interface as the pool.

`kneeseat build --scheduler tcp://HOST:PORT` calls `dask_executor(address)`: it connects a
`distributed.Client`, checks that workers are there and run the same kneeseat, and returns
a `DaskExecutor`, a `concurrent.futures.Executor` that `sweep()` uses exactly like the
process pool (chains are submitted, their results come back as `concurrent.futures`
futures).

Meshes are shipped once per worker, not once per task. The first time a chain of a new
scene is submitted, the executor reads the scene's mesh files on the client, checks them
against the SHA-256 in the `SceneSpec`, and registers a `MeshShipment` worker plugin that
carries the bytes. The scheduler hands the plugin to every worker once (and to every worker
that joins later, e.g. a restarted one); each worker writes the bytes under its local
directory as `<sha256>.<ext>` and registers the copy with `scene.register_mesh_copy`, so
`scene_bodies` builds the rigid bodies from it even where the client's paths do not exist.
Tasks themselves carry only the small `ChainJob`.

Lost workers: when a worker dies, the scheduler re-runs the chains it held on another worker
(up to `distributed.scheduler.allowed-failures` deaths per chain, then the build fails with
a `KneeseatError`); a chain that raised is re-run up to `retries` times. A re-run chain
starts from the same pose as the first try, so the table does not depend on who ran what.
"""
from __future__ import annotations

from concurrent.futures import Executor, Future
from dataclasses import replace
import hashlib
import logging
import os
from pathlib import Path
import re
import threading
from typing import Any, Callable, TypeVar

from distributed import Client, KilledWorker
from distributed.diagnostics.plugin import WorkerPlugin

from kneeseat_core import kneeseat_version
from kneeseat_core.errors import ConfigError, KneeseatError, MeshError
from kneeseat_core.files import file_sha256, write_bytes
from .chains import ChainJob
from .scene import register_mesh_copy, scene_builds, SceneSpec

__all__ = ['DaskExecutor', 'MeshShipment', 'dask_executor', 'worker_stats',
           'CONNECT_TIMEOUT_S', 'WORKERS_TIMEOUT_S', 'RETRIES']

log = logging.getLogger(__name__)

_T = TypeVar('_T')

CONNECT_TIMEOUT_S = 10.0   # to reach the scheduler
WORKERS_TIMEOUT_S = 60.0   # for at least one worker to be connected to it
RETRIES = 2                # re-runs of a chain that raised (lost workers are always re-run)

_ADDRESS = re.compile(r'^(tcp|tls)://[^\s/]+:\d+$')
_MESH_DIR = 'kneeseat-meshes'

# Worker-side counters (read with `client.run(worker_stats)`).
_RECEIVED: dict[str, int] = {'meshes': 0, 'bytes': 0, 'written': 0}
_CHAIN_KEYS: set[str] = set()


def worker_stats() -> dict[str, int]:
    """This process's shipping counters (run on a worker with `client.run(worker_stats)`).

    Returns:
        meshes_received: mesh payloads handed to this worker by `MeshShipment` plugins;
        bytes_received: their total size; files_written: copies written to disk (a payload
        already on disk is not written again); scene_builds: scenes built from meshes
        (`scene.scene_bodies`); chains_run: `run_chain` tasks finished here; pid.
    """
    return {'meshes_received': _RECEIVED['meshes'], 'bytes_received': _RECEIVED['bytes'],
            'files_written': _RECEIVED['written'], 'scene_builds': scene_builds(),
            'chains_run': len(_CHAIN_KEYS), 'pid': os.getpid()}


class MeshShipment(WorkerPlugin):
    """Worker plugin carrying mesh bytes by SHA-256; installs them as local copies.

    Args:
        meshes: SHA-256 (hex) -> (file suffix such as '.stl', the file's bytes).
    """

    idempotent = True      # a name is one client's one set of meshes: nothing to redo

    def __init__(self, meshes: dict[str, tuple[str, bytes]]) -> None:
        self.meshes = meshes

    def setup(self, worker: Any) -> None:
        """Write each mesh under the worker's local directory and register the copy."""
        folder = Path(worker.local_directory) / _MESH_DIR
        folder.mkdir(parents=True, exist_ok=True)
        for sha, (suffix, data) in self.meshes.items():
            if hashlib.sha256(data).hexdigest() != sha:
                raise MeshError(f'mesh {sha[:12]}: bytes damaged on the way to worker '
                                f'{worker.address}; run the build again')
            _RECEIVED['meshes'] += 1
            _RECEIVED['bytes'] += len(data)
            path = folder / f'{sha}{suffix}'
            if not (path.is_file() and path.stat().st_size == len(data)):
                write_bytes(path, data)
                _RECEIVED['written'] += 1
            register_mesh_copy(sha, str(path))

    def transition(self, key: Any, start: str, finish: str, **kwargs: Any) -> None:
        """Count finished chains (for `worker_stats`)."""
        if finish == 'memory' and str(key).startswith('run_chain-'):
            _CHAIN_KEYS.add(str(key))


class DaskExecutor(Executor):
    """A `concurrent.futures.Executor` running tasks on a Dask cluster (module docstring).

    Args:
        client: a connected `distributed.Client`; closed by `close()`.
        retries: re-runs of a task that raised.
    """

    def __init__(self, client: Client, retries: int = RETRIES) -> None:
        self.client = client
        assert client.scheduler is not None          # a connected client has one
        self.address = str(client.scheduler.address)
        self._inner = client.get_executor(retries=retries, pure=False)
        self._plugins: dict[tuple[str, ...], str] = {}
        self._lock = threading.Lock()

    def submit(self, fn: Callable[..., _T], /, *args: Any,
               **kwargs: Any) -> Future[_T]:
        """Run `fn(*args, **kwargs)` on the cluster; ship the meshes of any `ChainJob` first."""
        args = tuple(self._with_meshes(a) if isinstance(a, ChainJob) else a for a in args)
        inner = self._inner.submit(fn, *args, **kwargs)
        outer: Future[_T] = Future()
        outer.add_done_callback(lambda done: done.cancelled() and inner.cancel())
        inner.add_done_callback(lambda done: _forward(done, outer, self.address))
        return outer

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop accepting tasks; cancel the queued ones if asked (the client stays open)."""
        self._inner.shutdown(wait=wait and not cancel_futures)

    def close(self) -> None:
        """Cancel what is left, remove this executor's mesh plugins, close the client."""
        self.shutdown(wait=False, cancel_futures=True)
        for name in self._plugins.values():
            try:
                self.client.unregister_worker_plugin(name)
            except (OSError, ValueError, KeyError) as err:   # scheduler gone or plugin gone
                log.debug('could not unregister %s: %s', name, err)
        self._plugins.clear()
        self.client.close()

    def ship(self, scene: SceneSpec) -> str:
        """Send the meshes of `scene` to every worker once; return the plugin's name.

        Raises:
            MeshError: a mesh cannot be read here, or its bytes no longer match the hash
                the sweep took (the file changed during the build).
        """
        with self._lock:
            if scene.mesh_sha256 in self._plugins:
                return self._plugins[scene.mesh_sha256]
            paths = scene.paths()
            meshes: dict[str, tuple[str, bytes]] = {}
            for path, sha in zip(paths, scene.mesh_sha256):
                try:
                    data = Path(path).read_bytes()
                except OSError as err:
                    raise MeshError(f'{path}: cannot read the mesh to ship it to the Dask '
                                    f'workers ({err.strerror}); check the path') from None
                if hashlib.sha256(data).hexdigest() != sha:
                    raise MeshError(f'{path}: changed during the build (SHA-256 differs); '
                                    'leave meshes alone while a build runs, then rebuild')
                meshes[sha] = (Path(path).suffix.lower(), data)
            digest = hashlib.sha256(''.join(scene.mesh_sha256).encode()).hexdigest()[:16]
            name = f'kneeseat-meshes-{digest}-{self.client.id}'
            self.client.register_plugin(MeshShipment(meshes), name=name)
            log.info('shipped %d meshes (%.1f MB) to the Dask workers as %s', len(meshes),
                     sum(len(d) for _, d in meshes.values()) / 1e6, name)
            self._plugins[scene.mesh_sha256] = name
            return name

    def _with_meshes(self, job: ChainJob) -> ChainJob:
        if len(job.scene.mesh_sha256) != len(job.scene.paths()):
            paths = job.scene.paths()
            try:
                hashes = tuple(file_sha256(Path(p)) for p in paths)
            except OSError as err:
                raise MeshError(f'{err.filename}: cannot read the mesh to ship it to the Dask '
                                f'workers ({err.strerror}); check the path') from None
            job = replace(job, scene=replace(job.scene, mesh_sha256=hashes))
        self.ship(job.scene)
        return job


def _forward(inner: Future[_T], outer: Future[_T], address: str) -> None:
    """Copy `inner`'s outcome to `outer`; a chain that kept killing workers -> KneeseatError."""
    if outer.done():              # cancelled by the caller
        return
    if inner.cancelled():
        outer.cancel()
        outer.set_running_or_notify_cancel()
        return
    err = inner.exception()
    if err is None:
        outer.set_result(inner.result())
    elif isinstance(err, KilledWorker):
        outer.set_exception(KneeseatError(
            f'a sweep chain was lost with every Dask worker that ran it ({address}): {err}; '
            "check the workers' logs (memory limit?) and rerun"))
    else:
        outer.set_exception(err)


def dask_executor(address: str, timeout_s: float = CONNECT_TIMEOUT_S,
                  workers_timeout_s: float = WORKERS_TIMEOUT_S,
                  retries: int = RETRIES) -> tuple[DaskExecutor, Callable[[], None]]:
    """Connect to the Dask scheduler at `address`; return the executor and its close().

    Args:
        address: scheduler address, tcp://HOST:PORT (as printed by `dask scheduler`).
        timeout_s: how long to try reaching the scheduler, s.
        workers_timeout_s: how long to wait for a first worker, s.
        retries: re-runs of a chain that raised.
    Raises:
        ConfigError: bad address, scheduler unreachable, no workers, or workers that do not
            run the same kneeseat.
    """
    if not _ADDRESS.match(address):
        raise ConfigError(f"--scheduler '{address}': not a Dask scheduler address; give "
                          'tcp://HOST:PORT as printed by `dask scheduler`')
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise ConfigError(f'cannot reach Dask scheduler {address} within {timeout_s:g} s '
                          f'({type(err).__name__}); start one with `dask scheduler` and '
                          'check host, port and firewall') from None
    try:
        _check_workers(client, address, workers_timeout_s)
    except BaseException:
        client.close()
        raise
    executor = DaskExecutor(client, retries)
    return executor, executor.close


def _check_workers(client: Client, address: str, timeout_s: float) -> None:
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except (OSError, TimeoutError):
        raise ConfigError(f'no Dask worker joined scheduler {address} within {timeout_s:g} s; '
                          f'start some with `dask worker {address} --nthreads 1`') from None
    mine = kneeseat_version()
    try:
        theirs = client.run(kneeseat_version)
    except ImportError as err:
        raise ConfigError(f'Dask workers of {address} cannot import kneeseat ({err}); install '
                          f"kneeseat {mine} in the workers' environment") from None
    wrong = sorted(w for w, v in theirs.items() if v != mine)
    if wrong:
        raise ConfigError(f'Dask workers {", ".join(wrong)} run kneeseat '
                          f'{theirs[wrong[0]]}, this client {mine}; install the same version '
                          'everywhere (tables must not depend on who ran what)')
