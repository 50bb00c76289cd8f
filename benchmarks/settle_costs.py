"""Where a table's settles spend their time: in each compiled part, or in the Python around them.

Run: `python benchmarks/settle_costs.py [--knees tka,natural,default]
[--flexion-grid=-30,-50,-1] [--varus-grid=-10,10,1]` (with `=`: a grid starts with a
minus). Builds a slice of each knee's table in this process (`kneeseat build --workers
1`) and times every call into the compiled parts a settle uses: the moves measured
(`_sweep.measure`: the witnesses asked and the exact searches of the moves they do not
refute, in one call), python-fcl (`fcl.collide`), the moves' plans (`Planner.plan`: their
order, poses and lifts with the ligaments weighed, its thin wrapper included) and the
linear program (`_simplex.best_move`, built and solved). What is left of the settles' time
is Python and numpy around them. Prints, per knee, milliseconds a settle for each part, its
calls a settle and its share. Timing a call costs about a microsecond, so the Python share
is overstated by about that much per call (the calls a settle are printed).

Then the same settles' time by what the climb was doing (`kneeseat_core.settle.climb`,
compiled parts and Python together): finding the first contact (the search from the start,
with the pool's window), the steps that moved to a place that gains, the steps that found
nothing at their scale, the proof of rest, and the rest of the settle (setting it up,
python-fcl's judge of the end pose, the result).
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
import sys
import tempfile
import time
from typing import Any

import fcl

from kneeseat_core.meshes import _sweep
from kneeseat_core.settle import _simplex, climb
from kneeseat_core.settle.planner import Planner
from kneeseat_core.sweep import chains
from machine import describe_machine
from slices import add_slice_options, build_slice, slice_knees

# part -> the module attributes a settle calls it through
PARTS: dict[str, list[tuple[Any, str]]] = {
    'moves measured': [(_sweep, 'measure')],
    'python-fcl': [(fcl, 'collide')],
    'move plans': [(Planner, 'plan')],
    'linear program': [(_simplex, 'best_move')],
}


# what the climb does, each timed around its own method of `climb._Climb`
STAGES = ('first contact', 'steps that move', 'steps that find nothing', 'proof of rest')


class Clock:
    """Seconds and calls per part and per stage, filled by the wrappers `timed` and
    `staged` install."""

    def __init__(self) -> None:
        self.seconds = {part: 0.0 for part in (*PARTS, *STAGES, 'settles')}
        self.calls = {part: 0 for part in self.seconds}

    def add(self, part: str, started: float) -> None:
        """A call of `part` that started at `started` (perf_counter) has ended."""
        self.seconds[part] += time.perf_counter() - started
        self.calls[part] += 1

    def timed(self, part: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """`fn`, its time and calls added to `part`."""
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.add(part, started)
        return wrapper

    def staged(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """The climb's method `name` (`fn`), its time added to the stage it served: an
        `arrive` before the climb has a place is its first contact, a `step` moved where
        it left the climb at another place."""
        def wrapper(state: Any, *args: Any, **kwargs: Any) -> Any:
            before = state.here
            started = time.perf_counter()
            try:
                return fn(state, *args, **kwargs)
            finally:
                if name == 'step':
                    self.add('steps that move' if state.here is not before
                             else 'steps that find nothing', started)
                elif name == 'prove':
                    self.add('proof of rest', started)
                elif before is None:
                    self.add('first contact', started)
        return wrapper


def measure(knee: str, args: argparse.Namespace, out: Path) -> Clock:
    """Build `knee`'s slice (`args`) in this process with every compiled part and every
    stage of the climb timed."""
    clock = Clock()
    timed = {**PARTS, 'settles': [(chains, 'settle')]}
    stages = [(climb._Climb, name) for name in ('arrive', 'step', 'prove')]
    originals = [(owner, name, getattr(owner, name))
                 for calls in (*timed.values(), stages) for owner, name in calls]
    try:
        for part, calls in timed.items():
            for owner, name in calls:
                setattr(owner, name, clock.timed(part, getattr(owner, name)))
        for owner, name in stages:
            setattr(owner, name, clock.staged(name, getattr(owner, name)))
        build_slice(knee, args, out)
    finally:
        for owner, name, fn in originals:
            setattr(owner, name, fn)
    return clock


def report(knee: str, clock: Clock) -> None:
    """One line per part: ms a settle, calls a settle, share of the settles' time."""
    settles = max(clock.calls['settles'], 1)
    total = clock.seconds['settles']
    print(f'{knee}: {clock.calls["settles"]} settles, {1e3 * total / settles:.2f} ms a settle')
    rest = total
    for part in PARTS:
        spent = clock.seconds[part]
        rest -= spent
        print(f'  {part:15s} {1e3 * spent / settles:6.2f} ms  {clock.calls[part] / settles:6.1f} '
              f'calls  {100 * spent / total:5.1f} %')
    calls = sum(clock.calls[part] for part in PARTS) / settles
    print(f'  {"Python, numpy":15s} {1e3 * rest / settles:6.2f} ms  (around {calls:.1f} calls)'
          f'  {100 * rest / total:5.1f} %')
    print('  by what the climb was doing:')
    rest = total
    for stage in STAGES:
        spent = clock.seconds[stage]
        rest -= spent
        each = 1e3 * spent / max(clock.calls[stage], 1)
        print(f'    {stage:24s} {1e3 * spent / settles:6.2f} ms  '
              f'{clock.calls[stage] / settles:5.1f} a settle at {each:5.2f} ms  '
              f'{100 * spent / total:5.1f} %')
    print(f'    {"the rest of the settle":24s} {1e3 * rest / settles:6.2f} ms  (set-up, the end '
          f'pose judged, the result)  {100 * rest / total:5.1f} %')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_slice_options(parser)
    args = parser.parse_args()
    print(describe_machine())
    with tempfile.TemporaryDirectory(prefix='settle_costs.') as tmp:
        for knee in slice_knees(args):
            report(knee, measure(knee, args, Path(tmp) / f'{knee}.npz'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
