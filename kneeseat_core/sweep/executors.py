"""Where the chains of a sweep run: any `concurrent.futures.Executor`.

In-process for one worker (`InlineExecutor`), a process pool of spawned workers for more,
or a Dask cluster (`kneeseat_core.sweep.cluster`, imported only when a scheduler is given:
Dask adds seconds to the start-up of every build that does not use it).

The pool starts every worker at once, each importing the settle code as it starts, while
the parent reads the config and checks the meshes. Left to itself, a pool starts a worker
only when a task finds none idle; a sweep starts from one centre cell, so the second worker
was started only then and joined the total knee's build 2.5 s after the first.
"""
from __future__ import annotations

from concurrent.futures import Executor, Future, ProcessPoolExecutor
import importlib
import multiprocessing
import os
from typing import Callable, ParamSpec, TypeVar

__all__ = ['InlineExecutor', 'process_executor', 'executor_for']

_P = ParamSpec('_P')
_T = TypeVar('_T')


class InlineExecutor(Executor):
    """A `concurrent.futures.Executor` that runs each task at submit time, in-process."""

    def submit(self, fn: Callable[_P, _T], /, *args: _P.args,
               **kwargs: _P.kwargs) -> Future[_T]:
        """Run `fn(*args, **kwargs)` now; its result or exception is in the future."""
        future: Future[_T] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: B902 - handed to the caller via the future
            if isinstance(err, KeyboardInterrupt):
                raise
            future.set_exception(err)
        return future


def process_executor(workers: int) -> Executor:
    """The default executor: in-process for one worker, else a process pool of `workers`
    spawned processes, every one started now (module docstring)."""
    if workers <= 1:
        return InlineExecutor()
    pool = ProcessPoolExecutor(max_workers=workers, initializer=_import_settle_code,
                               mp_context=multiprocessing.get_context('spawn'))
    for _ in range(workers):
        # a task submitted while no worker is idle starts one more (up to `workers`)
        pool.submit(os.getpid)
    return pool


def _import_settle_code() -> None:
    """A worker's first act: import what a chain runs (numpy, trimesh, python-fcl, the
    settle), while the parent is still reading the config and hashing the meshes."""
    importlib.import_module('kneeseat_core.sweep.chains')


def executor_for(workers: int, scheduler: str | None) -> tuple[Executor, Callable[[], None]]:
    """The executor a build runs on, and how to close it.

    Args:
        workers: process-pool size (ignored with a scheduler).
        scheduler: Dask scheduler address (tcp://HOST:PORT), or None for local processes.
    """
    if scheduler:
        from .cluster import dask_executor     # Dask: seconds of start-up
        return dask_executor(scheduler)
    executor = process_executor(workers)
    return executor, lambda: executor.shutdown(wait=True, cancel_futures=True)
