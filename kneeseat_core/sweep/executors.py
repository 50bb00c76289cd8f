"""Where the chains of a sweep run: any `concurrent.futures.Executor`.

In-process for one worker (`InlineExecutor`), a process pool for more, or a Dask cluster
(`kneeseat_core.sweep.cluster`, imported only when a scheduler is given: Dask adds seconds
to the start-up of every build that does not use it).
"""
from __future__ import annotations

from concurrent.futures import Executor, Future, ProcessPoolExecutor
import multiprocessing
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
    """The default executor: in-process for one worker, else a process pool.

    The pool's workers are forked from this process where the platform forks (all of
    them at the first submit: `concurrent.futures` forks before its own thread starts), so
    they start with its imports and the scene a sweep builds before it submits anything
    (`kneeseat_core.sweep.scene`); spawned, each took about 1.4 s on the total knee to
    import and build its own (docs/design.md). Elsewhere they are spawned.
    """
    if workers <= 1:
        return InlineExecutor()
    method = 'fork' if 'fork' in multiprocessing.get_all_start_methods() else 'spawn'
    return ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context(method))


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
