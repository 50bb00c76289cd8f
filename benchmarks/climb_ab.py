"""Two revisions of the climb timed on the same settles, settle by settle.

Run: `python benchmarks/climb_ab.py --base REV [--tune NAME=VALUE ...]
[--knees tka,natural,default] [--flexion-grid=-30,-50,-1] [--varus-grid=-10,10,1]`. Loads
the climb (`kneeseat_core/settle/climb.py`) of git revision REV (or a file) as a second
module beside the working tree's, run with REV's own tuning (`tuning.py`; a file's: the
working tree's), the rest of the package shared; the working tree's climb runs with its
tuning, each `--tune` value replaced (`--base HEAD --tune pool_window_res=0.5`: one
constant tried against the code as it is). Builds each knee's slice in this
process (`kneeseat build --workers 1`) and settles every cell twice, once with each climb,
which goes first alternating from cell to cell, the table built from the working tree's
settles. A machine whose speed drifts within seconds (this one is shared) slows the two
settles of a cell alike: their ratio holds to about a percent where whole builds timed
one after the other differ by a tenth. Prints per knee the milliseconds a settle with
each (the whole settle: python-fcl's queries and the set-up are the same in both) and
their ratio (new / base), and how many cells the two settled differently (pose or
iterations, bit for bit). For a change to the engine, `engine_ab.py`; elsewhere in the
package, whole builds.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib.util
from pathlib import Path
import sys
import tempfile
import time
from types import ModuleType
from typing import Any

import kneeseat_core.settle as settle_package
from kneeseat_core.settle import climb as new_climb, tuning as settle_tuning
from kneeseat_core.sweep import chains
from machine import describe_machine
from slices import add_slice_options, build_slice, slice_knees, source_at

CLIMB = 'kneeseat_core/settle/climb.py'
TUNING = 'kneeseat_core/settle/tuning.py'


def load_base(source: str, where: Path, name: str) -> ModuleType:
    """`source` loaded as the module `name` of the settle package (its relative imports are
    the working tree's)."""
    path = where / f'{name}.py'
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f'kneeseat_core.settle.{name}', path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
    except ImportError as err:
        raise SystemExit(f'the base {name} does not load beside this tree: {err}') from None
    return module


def climb_with(climb: ModuleType, tuning: Any) -> Any:
    """`climb`'s `run_climb` run with `tuning`, whatever the settle passes."""
    def run(search: Any, start: Any, tissue: Any = None, _: Any = None, seeds: Any = None,
            near_rest: bool = False) -> Any:
        return climb.run_climb(search, start, tissue, tuning, seeds, near_rest)
    return run


def tuned(changes: list[str]) -> Any:
    """The working tree's tuning with `changes` (NAME=VALUE, each value a Python literal)."""
    values = {}
    names = {f.name for f in dataclasses.fields(settle_tuning.TUNING)}
    for change in changes:
        name, _, value = change.partition('=')
        if name not in names:
            raise SystemExit(f'--tune {change}: no tuning value {name!r}; the names are '
                             "`SettleTuning`'s (kneeseat_core/settle/tuning.py)")
        try:
            values[name] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            raise SystemExit(f'--tune {change}: give NAME=VALUE with a number or a tuple '
                             'as VALUE') from None
    try:
        return dataclasses.replace(settle_tuning.TUNING, **values)
    except (TypeError, ValueError) as err:
        raise SystemExit(f'--tune: {err}') from None


class Paired:
    """`chains.settle` replaced: every settle run with both climbs, timed."""

    def __init__(self, base: Any, new: Any) -> None:
        self.climbs = {'base': base, 'new': new}
        self.seconds = {'base': 0.0, 'new': 0.0}
        self.settles = 0
        self.differ = 0
        self.settle = getattr(chains, 'settle')      # what the chains call, replaced
        self.run_climb = getattr(settle_package, 'run_climb')    # what the settle calls

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        order = ('base', 'new') if self.settles % 2 == 0 else ('new', 'base')
        results: dict[str, Any] = {}
        try:
            for side in order:
                setattr(settle_package, 'run_climb', self.climbs[side])
                started = time.perf_counter()
                try:
                    results[side] = self.settle(*args, **kwargs)
                except Exception as err:          # the chain handles it; compared below
                    results[side] = err
                self.seconds[side] += time.perf_counter() - started
        finally:
            setattr(settle_package, 'run_climb', self.run_climb)
        self.settles += 1
        new, base = results['new'], results['base']
        if isinstance(new, Exception) or isinstance(base, Exception):
            self.differ += type(new) is not type(base)
        elif new.pose.tobytes() != base.pose.tobytes() or new.iterations != base.iterations:
            self.differ += 1
        if isinstance(new, Exception):
            raise new
        return new


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--base', required=True,
                        help='git revision (or file) of the climb to compare with')
    parser.add_argument('--tune', action='append', default=[], metavar='NAME=VALUE',
                        help="the working tree's climb with this `SettleTuning` value "
                             '(repeatable), e.g. --tune pool_window_res=0.5')
    add_slice_options(parser)
    args = parser.parse_args()
    new = climb_with(new_climb, tuned(args.tune))
    print(describe_machine())
    with tempfile.TemporaryDirectory(prefix='climb_ab.') as tmp:
        where = Path(tmp)
        # the base's own tuning (its constants steer it); a file's is the working tree's
        tuning = settle_tuning.TUNING if Path(args.base).is_file() else \
            load_base(source_at(args.base, TUNING), where, 'tuning_base').TUNING
        base = climb_with(load_base(source_at(args.base, CLIMB), where, 'climb_base'), tuning)
        for knee in slice_knees(args):
            paired = Paired(base, new)
            setattr(chains, 'settle', paired)
            try:
                build_slice(knee, args, where / f'{knee}.npz')
            finally:
                setattr(chains, 'settle', paired.settle)
            n = max(paired.settles, 1)
            b, w = (1e3 * paired.seconds[side] / n for side in ('base', 'new'))
            same = 'the same bit for bit' if paired.differ == 0 else \
                f'{paired.differ} settled differently'
            print(f'{knee}: {paired.settles} settles, {same}; ms a settle base / new: '
                  f'{b:.3f} / {w:.3f} (ratio {w / b:.4f})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
