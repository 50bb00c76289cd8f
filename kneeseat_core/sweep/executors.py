"""Where the chains of a sweep run: any `concurrent.futures.Executor`.

In-process for one worker (`InlineExecutor`), a process pool for more, or a Dask cluster
(`kneeseat_core.sweep.cluster`, imported only when a scheduler is given: Dask adds seconds
to the start-up of every build that does not use it).
"""
from __future__ import annotations

from concurrent.futures import Executor, Future, ProcessPoolExecutor
import multiprocessing
import multiprocessing.context
from typing import Callable, ParamSpec, TypeVar

__all__ = ['InlineExecutor', 'LocalPool', 'process_executor', 'executor_for', 'submitted_ahead']

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


class LocalPool(ProcessPoolExecutor):
    """The process pool of a local build, which says how many workers it has (`workers`):
    a sweep then keeps no more chains submitted than they can take (`submitted_ahead`)."""

    def __init__(self, workers: int, mp_context: multiprocessing.context.BaseContext) -> None:
        super().__init__(max_workers=workers, mp_context=mp_context)
        self.workers = workers


def submitted_ahead(executor: Executor) -> int | None:
    """How many chains a sweep keeps submitted to `executor` and not finished, the rest
    waiting in the sweep's own order (`kneeseat_core.sweep.phases`): for a local pool, its
    workers and one more, so that a worker finds its next chain queued when it finishes one
    and a chain that becomes ready (the next segment of a spine) waits behind at most one.
    A pool takes what is submitted in turn: given every ready chain at once, it ran the
    default knee's patella spine, each segment queued behind the tibia's ribs, last and
    alone (in one run, 0.36 s of one idle worker at the end of a 6.3 s sweep; docs/design.md
    gives the workers' idle time either way). None (every ready chain at once) for other
    executors: one that runs a chain as it is submitted, or a Dask cluster, whose workers
    may come and go."""
    return executor.workers + 1 if isinstance(executor, LocalPool) else None


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
    return LocalPool(workers, multiprocessing.get_context(method))


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
