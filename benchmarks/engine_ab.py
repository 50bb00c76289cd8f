"""Two builds of the exact travel's engine timed on the same searches, call by call.

Run: `python benchmarks/engine_ab.py --base REV [--knees tka,natural,default]
[--flexion-grid=-30,-50,-1] [--varus-grid=-10,10,1] [--runs 3] [--cold]`. Compiles the engine
(`kneeseat_core/meshes/_sweep.cpp`) of git revision REV (or a file) and of the working tree
as two modules under other names, with the flags the package builds it with; builds each
knee's slice in this process (`kneeseat build --workers 1`) and keeps every call the
settles make to `SweepPair.measure`; then asks each call of both engines, in turn, the two
orders alternating from call to call. A machine whose speed drifts within seconds (this
one is shared) then slows both alike, and their ratio holds where whole builds timed one
after the other differ by a tenth from run to run. Prints whether the two answered every
call the same, bit for bit (the pose found, its travel and features; the counts of searches
and pairs a call made may differ), the searches each made, and per run the seconds of each
and their ratio (new / base).
The first, untimed pass builds each engine's views and fills their bounds: the runs time
the searches themselves, not a view's first filling. With `--cold` each settle's calls
start from new views instead, as a build's do (a view per cell and body: the push turns
with the attitude), and a run times the views' making and filling with the searches. An
engine from before the pool's cap (its `measure` takes no `cap`) is asked without it: where
the cap keeps fewer features, the two answer differently.
"""
from __future__ import annotations

import argparse
import copy
import importlib
import inspect
from pathlib import Path
import sys
import tempfile
import time
from typing import Any

import numpy as np
from setuptools import Distribution, Extension

from bench_build import REPO
from kneeseat_core.meshes import sweep
from machine import describe_machine
from slices import add_slice_options, build_slice, slice_knees, source_at

ENGINE = 'kneeseat_core/meshes/_sweep.cpp'


def compile_engine(source: str, name: str, where: Path) -> Any:
    """`source` built as module `name` in `where` (the package's flags) and imported."""
    # the package's shared headers (`#include "../_buffers.h"` and the like) by their path
    text = source.replace('PyInit__sweep(', f'PyInit_{name}(').replace(
        '"_sweep",', f'"{name}",').replace('#include "../', f'#include "{REPO / "kneeseat_core"}/')
    (where / f'{name}.cpp').write_text(text)
    dist = Distribution({'ext_modules': [Extension(name, [str(where / f'{name}.cpp')],
                                                   extra_compile_args=['-O3', '-std=c++17'],
                                                   language='c++')]})
    command = dist.get_command_obj('build_ext')
    command.build_lib = str(where)
    command.build_temp = str(where / 'temp')
    command.ensure_finalized()
    command.run()
    sys.path.insert(0, str(where))
    return importlib.import_module(name)


def recorded_calls(knee: str, args: argparse.Namespace,
                   out: Path) -> list[tuple[Any, tuple[Any, ...]]]:
    """Every `SweepPair.measure` call of `knee`'s slice: the pair and its arguments."""
    calls: list[tuple[Any, tuple[Any, ...]]] = []
    original = sweep.SweepPair.measure
    signature = inspect.signature(original)

    def keep(pair: Any, *args: Any, **kwargs: Any) -> Any:
        # every argument in the signature's order, defaults filled in, however it was given
        bound = signature.bind(pair, *args, **kwargs)
        bound.apply_defaults()
        calls.append((pair, copy.deepcopy(tuple(bound.arguments.values())[1:])))
        return original(pair, *args, **kwargs)
    sweep.SweepPair.measure = keep      # type: ignore[method-assign]
    try:
        build_slice(knee, args, out)
    finally:
        sweep.SweepPair.measure = original   # type: ignore[method-assign]
    return calls


class Engine:
    """One build of the engine with its own bodies and views (as `SweepBody` keeps them)."""

    def __init__(self, module: Any) -> None:
        self.module = module
        self.bodies: dict[int, Any] = {}
        self.views: dict[tuple[int, int, int, int, int], Any] = {}
        # per settle (its `SweepPair`), for an engine that keeps the pairs that stopped its
        # searches short (`SweepPair._stoppers`)
        self.stoppers: dict[int, np.ndarray] = {}

    def start_settles(self) -> None:
        """Every settle's calls from its first again: no pair has stopped a search yet."""
        for kept in self.stoppers.values():
            kept.fill(-1)

    def view(self, body: Any, direction: Any, side: int) -> Any:
        x, y, z = (round(c / sweep._SAME_DIRECTION) for c in np.asarray(direction).tolist())
        key = (id(body), side, x, y, z)
        if key not in self.views:
            if id(body) not in self.bodies:
                self.bodies[id(body)] = self.module.Body(
                    np.ascontiguousarray(body.vertices, dtype=np.float64),
                    np.ascontiguousarray(body.faces, dtype=np.int64),
                    np.ascontiguousarray(sweep.sweep_body(body).facing))
            along = np.array([x, y, z], dtype=np.float64) * sweep._SAME_DIRECTION
            self.views[key] = self.module.View(self.bodies[id(body)],
                                               np.ascontiguousarray(along / np.linalg.norm(along)),
                                               side)
        return self.views[key]

    def call(self, pair: Any, args: tuple[Any, ...]) -> tuple[Any, ...]:
        """The engine's arguments for one recorded call (SweepPair.measure's conversions)."""
        poses, needed, expected, (near, far), (gaps, slopes, faces), moves, shift, reach, \
            count, standoff, deepest, start, seeds, cap, keep = args
        doc = self.module.measure.__doc__ or ''
        f64 = np.float64
        poses = np.ascontiguousarray(poses, dtype=f64)
        turn = poses[0][:3, :3].T @ pair.push
        head = (self.view(pair.fixed, pair.push, -1), self.view(pair.moving, turn, 1), poses,
                np.ascontiguousarray(needed, dtype=f64), np.ascontiguousarray(expected, dtype=f64))
        pool = (np.ascontiguousarray(gaps, dtype=f64), np.ascontiguousarray(slopes, dtype=f64),
                np.ascontiguousarray(faces, dtype=np.int64))
        if 'reach' in doc:          # the engine takes the moves and picks each one's window
            middle: tuple[Any, ...] = (float(near), float(far), float(reach), *pool,
                                       np.ascontiguousarray(moves, dtype=f64),
                                       np.ascontiguousarray(shift, dtype=f64))
        else:                       # one from before: each move's offset and window given
            offsets = np.asarray(moves, dtype=f64) + np.asarray(shift, dtype=f64)
            windows = np.where(np.abs(offsets).max(axis=-1) > reach, far, near)
            middle = (np.ascontiguousarray(windows, dtype=f64), *pool,
                      np.ascontiguousarray(offsets, dtype=f64))
        # the pool's cap and what it keeps whole, for an engine that takes them (one from
        # before them keeps every feature within the window)
        capped = (int(cap), float(keep)) if 'cap' in doc else ()
        stoppers = (self.stoppers.setdefault(id(pair), np.full_like(pair._stoppers, -1)),) \
            if 'stoppers' in doc else ()
        return (*head, *middle, int(count), float(standoff), float(deepest), pair._bounds,
                int(start), None if seeds is None else np.ascontiguousarray(seeds, dtype=np.int64),
                *capped, *stoppers)


def answer(measured: tuple[Any, ...]) -> tuple[Any, ...]:
    """What a `measure` call answers (index, kind, travel, features), without its counts of
    searches and pairs (a change that spares searches answers the same) or whether the pose
    found was wide (an engine from before does not say)."""
    return measured[:4]


def searches(measured: tuple[Any, ...]) -> int:
    """The searches a `measure` call made."""
    return int(measured[4])


def compare(calls: list[tuple[Any, tuple[Any, ...]]], engines: list[Engine],
            runs: int) -> tuple[int, list[int], list[list[float]]]:
    """How many calls the two engines answer differently, the searches each made, and per
    run the seconds of each."""
    asked = [[engine.call(pair, args) for engine in engines] for pair, args in calls]
    # the first pass also fills every view's bounds
    for engine in engines:
        engine.start_settles()
    measured = [[engine.module.measure(*one) for engine, one in zip(engines, both)]
                for both in asked]
    differ = sum(answer(a) != answer(b) for a, b in measured)
    made = [sum(searches(both[k]) for both in measured) for k in (0, 1)]
    seconds = [[0.0, 0.0] for _ in range(runs)]
    for run in range(runs):
        for engine in engines:
            engine.start_settles()
        for n, both in enumerate(asked):
            for k in ((0, 1) if (n + run) % 2 == 0 else (1, 0)):
                started = time.perf_counter()
                engines[k].module.measure(*both[k])
                seconds[run][k] += time.perf_counter() - started
    return differ, made, seconds


def compare_cold(calls: list[tuple[Any, tuple[Any, ...]]], engines: list[Engine],
                 runs: int) -> tuple[int, list[int], list[list[float]]]:
    """As `compare`, each settle's calls from new views (a settle is the calls of one
    `SweepPair`): the views' making and filling timed with the searches, each settle's
    calls made by one engine and then the other, which goes first alternating."""
    settles: list[list[tuple[Any, tuple[Any, ...]]]] = []
    for pair, args in calls:
        if not settles or settles[-1][0][0] is not pair:
            settles.append([])
        settles[-1].append((pair, args))
    differ = 0
    made = [0, 0]
    seconds = [[0.0, 0.0] for _ in range(runs)]
    for run in range(runs):
        for engine in engines:
            engine.start_settles()
        for n, settle in enumerate(settles):
            answers: list[list[Any]] = [[], []]
            for k in ((0, 1) if (n + run) % 2 == 0 else (1, 0)):
                engine = engines[k]
                engine.views.clear()      # gone views' arrays go to their body's spares
                started = time.perf_counter()
                for pair, args in settle:
                    answers[k].append(engine.module.measure(*engine.call(pair, args)))
                seconds[run][k] += time.perf_counter() - started
            if run == 0:
                differ += [answer(a) for a in answers[0]] != [answer(b) for b in answers[1]]
                for k in (0, 1):
                    made[k] += sum(searches(a) for a in answers[k])
    return differ, made, seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--base', required=True,
                        help='git revision (or file) of the engine to compare with')
    parser.add_argument('--runs', type=int, default=3, help='replays of every call')
    parser.add_argument('--cold', action='store_true',
                        help="each settle's calls from new views, their filling timed too")
    add_slice_options(parser)
    args = parser.parse_args()
    print(describe_machine())
    with tempfile.TemporaryDirectory(prefix='engine_ab.') as tmp:
        where = Path(tmp)
        modules = [compile_engine(source_at(args.base, ENGINE), 'engine_base', where),
                   compile_engine((REPO / ENGINE).read_text(), 'engine_new', where)]
        for knee in slice_knees(args):
            calls = recorded_calls(knee, args, where / f'{knee}.npz')
            differ, made, seconds = (compare_cold if args.cold else compare)(
                calls, [Engine(m) for m in modules], args.runs)
            same = 'the same answers bit for bit' if differ == 0 else \
                f'{differ} {"settles" if args.cold else "calls"} answered differently'
            print(f'{knee}: {len(calls)} calls, {same}; searches base / new: {made[0]} / '
                  f'{made[1]}; seconds base / new (ratio): ' +
                  ', '.join(f'{b:.3f} / {n:.3f} ({n / b:.3f})' for b, n in seconds))
    return 0


if __name__ == '__main__':
    sys.exit(main())
