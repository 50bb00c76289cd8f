"""How the node runs: started from the command line, its inputs spun in the main thread and
everything else in rclpy's executor, stopped cleanly on a signal.

`run_node` is the console entry: --help prints the usage; rclpy.init's own complaint about
bad --ros-args is replaced by one line; a `KneeseatError` while the node starts (bad
parameter, missing table) is one line and exit code 2; SIGINT/SIGTERM end the spin and the
node is destroyed (its recording finalised) before rclpy shuts down, exit code 0.

`serve` waits on a wait set holding only the inputs and one guard condition (stop) and
drains every ready input: per message it pays one rcl_wait over 3 entities. rcl_wait's cost
grows with the entities in the set (each is attached to and detached from the wait), and a
node's timers, parameter services and ~/reload are 12 more; rclpy's executor also rebuilds
its wait set in Python on every call. So timers, services and parameters run in rclpy's
executor in a second thread, which sleeps until one of them is ready (the inputs' callback
group, `InputsGroup`, keeps the inputs out of it). An idle node sleeps in both. The wait
also times out every `SHUTDOWN_CHECK_NS` to look at the context, as a safety net for
shutdown.

This speed costs a dependence on rclpy below its public API: its C extension's WaitSet,
take_message and entity pointers, the Python entities' handles, and how its executor asks
a callback group, used as rclpy.executors uses them (Jazzy). `RCLPY_INTERNALS` lists each
one with the signature used here, in one place; test_table_server checks every entry
against the installed rclpy, and when one fails this module must be adapted to the new
rclpy before the node can be trusted on it.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
from dataclasses import dataclass
import gc
import os
import sys
import tempfile
import threading
from typing import Any, Literal, Protocol

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException, ShutdownException, SingleThreadedExecutor
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.subscription import Subscription

from kneeseat_core.errors import KneeseatError

__all__ = ['InputsGroup', 'Handler', 'drain', 'serve', 'run_node', 'DRAIN_MAX',
           'SHUTDOWN_CHECK_NS', 'RCLError', 'RclpyInternal', 'RCLPY_INTERNALS']

RCLError = _rclpy.RCLError
# Messages taken per wake-up of one input (see `drain`).
DRAIN_MAX = 100
# The input wait also wakes this often to look at the context (a shutdown whose
# guard-condition trigger lands before the context is down would otherwise be missed).
SHUTDOWN_CHECK_NS = 1_000_000_000

Handler = Callable[[Any], None]


@dataclass(frozen=True, slots=True)
class RclpyInternal:
    """One piece of rclpy below its public API that this module relies on.

    `owner` is the dotted path of the class (or module) that has it, `name` the attribute.
    `kind` says what it must be: 'class' (an exception or base class: `returns` is the
    class it must derive from), 'method' (`params` are the parameters after self: for the
    C extension the types its pybind11 signature declares, for Python code their names;
    `returns` is the type the C extension declares, '' for Python), 'property' (a property
    of the class), or 'attribute' (of live instances; `returns` is its type's dotted path).
    """

    owner: str
    name: str
    kind: Literal['class', 'method', 'property', 'attribute']
    params: tuple[str, ...] = ()
    returns: str = ''
    use: str = ''


_C = 'rclpy.impl.implementation_singleton.rclpy_implementation'    # `_rclpy` here
_SUB, _GUARD = 'rclpy.subscription.Subscription', 'rclpy.guard_condition.GuardCondition'
_GROUP = 'rclpy.callback_groups.CallbackGroup'
# Every internal `serve`, `drain`, `InputsGroup` and `RCLError` use (rclpy 7, Jazzy).
RCLPY_INTERNALS: tuple[RclpyInternal, ...] = (
    RclpyInternal(_C, 'RCLError', 'class', returns='builtins.Exception',
                  use='what rcl_wait and rclpy.init raise (caught on shutdown, bad args)'),
    RclpyInternal(f'{_C}.WaitSet', '__init__', 'method', ('int',) * 6 + ('Context',), 'None',
                  use='_wait_loop: a wait set of (subscriptions, guards, timers, clients, '
                      'services, events) on the context handle'),
    RclpyInternal(f'{_C}.WaitSet', 'clear_entities', 'method', (), 'None',
                  use='_wait_loop: empty the set before each wait'),
    RclpyInternal(f'{_C}.WaitSet', 'add_subscription', 'method', ('Subscription',), 'int',
                  use='_wait_loop: wait on an input'),
    RclpyInternal(f'{_C}.WaitSet', 'add_guard_condition', 'method', ('GuardCondition',),
                  'int', use='_wait_loop: wait on the stop guard'),
    RclpyInternal(f'{_C}.WaitSet', 'wait', 'method', ('int',), 'None',
                  use='_wait_loop: rcl_wait with a timeout in ns'),
    RclpyInternal(f'{_C}.WaitSet', 'get_ready_entities', 'method', ('str',), 'list',
                  use="_wait_loop: the ready subscriptions' pointers ('subscription')"),
    RclpyInternal(f'{_C}.Subscription', 'take_message', 'method', ('object', 'bool'),
                  'object', use='drain: (message, info) or None; bytes when raw'),
    RclpyInternal(f'{_C}.Subscription', 'pointer', 'property',
                  use='_wait_loop: matched against get_ready_entities'),
    RclpyInternal(f'{_C}.Subscription', '__enter__', 'method', (), 'None',
                  use='drain, _wait_loop: hold the handle while it is used'),
    RclpyInternal(f'{_C}.Subscription', '__exit__', 'method', ('object',) * 3, 'None',
                  use='drain, _wait_loop: release it'),
    RclpyInternal(f'{_C}.GuardCondition', '__enter__', 'method', (), 'None',
                  use='_wait_loop: hold the stop guard while waiting on it'),
    RclpyInternal(f'{_C}.GuardCondition', '__exit__', 'method', ('object',) * 3, 'None',
                  use='_wait_loop: release it'),
    RclpyInternal(f'{_C}.Context', '__enter__', 'method', (), 'None',
                  use='_wait_loop: hold the context while waiting in it'),
    RclpyInternal(f'{_C}.Context', '__exit__', 'method', ('object',) * 3, 'None',
                  use='_wait_loop: release it'),
    RclpyInternal(_SUB, 'handle', 'attribute', returns=f'{_C}.Subscription',
                  use='drain, _wait_loop: the C subscription'),
    RclpyInternal(_SUB, 'msg_type', 'attribute', returns='builtins.type',
                  use='drain: take_message argument'),
    RclpyInternal(_SUB, 'raw', 'attribute', returns='builtins.bool',
                  use='drain: take_message argument'),
    RclpyInternal(_GUARD, '__init__', 'method', ('callback', 'callback_group', 'context'),
                  use='serve: the stop guard, GuardCondition(None, None, context=)'),
    RclpyInternal(_GUARD, 'handle', 'attribute', returns=f'{_C}.GuardCondition',
                  use='_wait_loop: the C guard condition'),
    RclpyInternal('rclpy.context.Context', 'handle', 'attribute', returns=f'{_C}.Context',
                  use='_wait_loop: the C context of the wait set'),
    RclpyInternal(_GROUP, '__init__', 'method', (),
                  use='InputsGroup: a callback group of its own, built without arguments'),
    RclpyInternal(_GROUP, 'can_execute', 'method', ('entity',),
                  use='InputsGroup: the executor leaves out what it refuses'),
    RclpyInternal(_GROUP, 'beginning_execution', 'method', ('entity',),
                  use='InputsGroup: asked before a callback runs'),
    RclpyInternal(_GROUP, 'ending_execution', 'method', ('entity',),
                  use='InputsGroup: told after a callback ran'),
)


class InputsGroup(CallbackGroup):
    """The inputs' callback group: kept out of rclpy's executor while `serve()` runs.

    serve() waits on the inputs itself in the main thread and leaves every other entity
    (timers, services, parameter services) to an executor in a second thread; a node added
    to another executor (tests, composition) gets its inputs from it. The inputs' QoS event
    handlers stay out too: with rmw_fastrtps a subscription's event wakes the wait on every
    message of that subscription (the executor thread then spun at 60% of a core at 2 kHz);
    the inputs accept every publisher QoS by default, so these events practically never fire.

    `handling` is held while inputs are handled (a wake-up's batch at a time): whatever reads
    the counters that handling bumps from another thread (diagnostics) holds it too, so that
    its numbers belong to one moment (answered and dropped counted from the same inputs).
    """

    def __init__(self) -> None:
        super().__init__()
        self.direct = False
        self.handling = threading.Lock()

    def can_execute(self, entity: Any) -> bool:
        """Whether an executor may run `entity` now: not while `serve()` takes the inputs."""
        return not self.direct

    def beginning_execution(self, entity: Any) -> bool:
        """rclpy's hook before a callback runs: the same answer as `can_execute`."""
        return self.can_execute(entity)

    def ending_execution(self, entity: Any) -> None:
        """rclpy's hook after a callback ran: nothing to release."""


def drain(sub: Subscription, handle: Handler) -> None:
    """Handle what else is queued on `sub` now, in order, without the executor.

    One pass of rclpy's Python executor (wait set rebuilt over every entity) costs several
    times the answer itself; after a scheduling hiccup the backlog is cleared at the cost of
    the answers alone. Uses the same `take_message` call as
    `rclpy.executors.Executor._take_subscription` (Jazzy).
    """
    for _ in range(DRAIN_MAX):
        with sub.handle:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
        if taken is None:
            return
        handle(taken[0])


def serve(node: Node, group: InputsGroup,
          inputs: Sequence[tuple[Subscription, Handler]]) -> None:
    """Spin `node` until shutdown: `inputs` in this thread, everything else in a second one.

    Raises:
        BaseException: whatever the executor thread raised (re-raised here).
    """
    executor = SingleThreadedExecutor(context=node.context)
    group.direct = True
    executor.add_node(node)
    failed: list[BaseException] = []
    # woken by the executor thread's end (SIGINT/SIGTERM reach it through rclpy's own
    # signal guard condition) and by a shutdown of the context from Python
    stop = GuardCondition(None, None, context=node.context)

    def wake() -> None:
        with contextlib.suppress(InvalidHandle):
            stop.trigger()

    node.context.on_shutdown(wake)
    thread = threading.Thread(target=_housekeeping, args=(node, executor, failed, wake),
                              name='table_server housekeeping', daemon=True)
    # everything alive now lives as long as the node: keep it out of the cyclic
    # collector's full passes, whose pauses grow with the heap (tables, imports)
    gc.collect()
    gc.freeze()
    thread.start()
    try:
        _wait_loop(node, inputs, stop, group.handling)
    finally:
        # After a signal the executor thread ends by itself (its context is down) and
        # nothing is destroyed here: rclpy's signal thread may still be triggering the
        # executor's signal guard condition, and executor.shutdown() would destroy it
        # under that thread (a segfault in rmw's trigger, seen once under load). Only a
        # stop with the context still up (an error here) shuts the executor down.
        if node.context.ok():
            executor.shutdown(timeout_sec=5.0)
        thread.join(timeout=10.0)
        if thread.is_alive():
            executor.shutdown(timeout_sec=5.0)
            thread.join(timeout=10.0)
        group.direct = False
        executor.remove_node(node)
    if failed:
        raise failed[0]


def _housekeeping(node: Node, executor: SingleThreadedExecutor, failed: list[BaseException],
                  wake: Callable[[], None]) -> None:
    """The second thread: rclpy's executor for timers, services and parameters."""
    try:
        executor.spin()
    except (ExternalShutdownException, ShutdownException):
        pass
    except BaseException as err:        # re-raised in the main thread
        if isinstance(err, RCLError) and not node.context.ok():
            return                      # the context went down under the executor
        failed.append(err)
        node.context.try_shutdown()
    finally:                            # wake the main thread: it stops too
        wake()


def _wait_loop(node: Node, inputs: Sequence[tuple[Subscription, Handler]],
               stop: GuardCondition, handling: threading.Lock) -> None:
    """Wait on the inputs and `stop`; drain every ready input, holding `handling`; return
    once the context is down."""
    guards = [stop]
    wait_set = _rclpy.WaitSet(len(inputs), len(guards), 0, 0, 0, 0, node.context.handle)
    context_handle = node.context.handle
    assert context_handle is not None           # the node's context is initialised
    with contextlib.ExitStack() as held:
        for sub, _ in inputs:
            held.enter_context(sub.handle)
        for guard in guards:
            held.enter_context(guard.handle)
        held.enter_context(context_handle)
        pairs = [(sub, sub.handle, handle) for sub, handle in inputs]
        while node.context.ok():
            wait_set.clear_entities()
            for _, sub_handle, _ in pairs:
                wait_set.add_subscription(sub_handle)
            for guard in guards:
                wait_set.add_guard_condition(guard.handle)
            wait_set.wait(SHUTDOWN_CHECK_NS)
            ready = wait_set.get_ready_entities('subscription')
            for sub, sub_handle, handle in pairs:
                if sub_handle.pointer in ready:
                    with handling:
                        drain(sub, handle)


@contextlib.contextmanager
def _stderr_kept_on_success() -> Iterator[None]:
    """Hold what C code writes on stderr (fd 2) in the block; drop it if the block raises.

    rcl logs its own "[ERROR] [rcl]: Failed to parse global arguments" before rclpy.init
    raises on bad --ros-args; main() replaces both with one line.
    """
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        failed = True
        try:
            yield
            failed = False
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            if not failed:
                held.seek(0)
                sys.stderr.buffer.write(held.read())
                sys.stderr.flush()


def _wants_help(args: list[str]) -> bool:
    return any(a in ('-h', '--help') for a in args)


class ServingNode(Protocol):
    """A node `run_node` can run: it spins itself until shutdown."""

    def serve(self) -> None:
        """Spin until the context shuts down."""

    def destroy_node(self) -> None:
        """Release the node's resources (and finalise what it records)."""


def run_node(make: Callable[[], ServingNode], prog: str, usage: str,
             args: list[str] | None = None) -> int:
    """Run the node `make()` builds until SIGINT/SIGTERM (module docstring).

    Args:
        make: builds the node (after rclpy.init); may raise KneeseatError.
        prog: the program's name in error lines.
        usage: printed for -h/--help.
        args: the command line, program name first (default sys.argv).
    Returns:
        0 on a clean stop (SIGINT, SIGTERM, shutdown) or after --help, 2 on bad
        parameters, table or command-line arguments.
    """
    argv = list(sys.argv if args is None else args)
    if _wants_help(argv[1:]):
        print(usage)
        return 0
    try:
        with _stderr_kept_on_success():
            rclpy.init(args=argv)
    except (RCLError, RuntimeError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f'{prog}: error: bad command-line arguments ({first}); see '
              f'{prog} --help', file=sys.stderr)
        return 2
    node = None
    try:
        node = make()
        node.serve()
    except KneeseatError as err:
        print(f'{prog}: error: {err}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # rclpy's SIGINT/SIGTERM handler shuts the context down; if that lands between two
        # executor iterations, spin raises RCLError ('context is not valid') instead of
        # ExternalShutdownException. That is a clean stop too; anything else is a bug.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
