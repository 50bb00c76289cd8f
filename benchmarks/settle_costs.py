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
from kneeseat_core.settle import _simplex
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


class Clock:
    """Seconds and calls per part, filled by the wrappers `timed` installs."""

    def __init__(self) -> None:
        self.seconds = {part: 0.0 for part in (*PARTS, 'settles')}
        self.calls = {part: 0 for part in self.seconds}

    def timed(self, part: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """`fn`, its time and calls added to `part`."""
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[part] += time.perf_counter() - started
                self.calls[part] += 1
        return wrapper


def measure(knee: str, args: argparse.Namespace, out: Path) -> Clock:
    """Build `knee`'s slice (`args`) in this process with every compiled part timed."""
    clock = Clock()
    timed = {**PARTS, 'settles': [(chains, 'settle')]}
    originals = [(owner, name, getattr(owner, name))
                 for calls in timed.values() for owner, name in calls]
    try:
        for part, calls in timed.items():
            for owner, name in calls:
                setattr(owner, name, clock.timed(part, getattr(owner, name)))
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
