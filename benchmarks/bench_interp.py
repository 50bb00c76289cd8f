"""Cost of one `PoseTable.interpolate` call on a 91 x 21 grid with 2 bodies.

Run: `python benchmarks/bench_interp.py [--runs 7] [--calls 20000] [--no-numpy]`.
Prints the machine, then median / p99 / max microseconds per call over all runs (each call
timed alone with perf_counter_ns, so about 0.1 us of timer cost is included) and the mean
from each run's total time. The same query written with numpy (the alternative that
kneeseat_core.table.pose_table does not use) is timed the same way for comparison.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from typing import Callable

import numpy as np

from kneeseat_core.geometry import KneeAxes, quat_from_matrix
from kneeseat_core.table import PoseTable
from machine import describe_machine


def knee_table(seed: int = 0) -> PoseTable:
    """Synthetic 2-body table on the patent's grid: flexion -90..0, varus -10..10, 1 deg."""
    rng = np.random.default_rng(seed)
    fx = np.radians(np.arange(-90.0, 0.5, 1.0))
    vx = np.radians(np.arange(-10.0, 10.5, 1.0))
    axes = KneeAxes.from_vectors([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    ff, vv = np.meshgrid(fx, vx, indexing='ij')
    quat = np.stack([quat_from_matrix(axes.orientation(
        ff.ravel(), vv.ravel(), 0.1 * np.sin(ff.ravel() + b)).reshape(*ff.shape, 3, 3))
        for b in range(2)])
    pos = rng.normal(scale=0.01, size=(2, *ff.shape, 3))
    conv = np.ones((2, *ff.shape), bool)
    conv[1, 40, 10] = False           # so the non-converged flag path runs too
    meta = {'reference': {'name': 'femur', 'frame': 'femur'},
            'bodies': [{'name': 'tibia', 'frame': 'tibia'},
                       {'name': 'patella', 'frame': 'patella'}],
            'axes': {'flexion': [0, 0, 1], 'varus': [1, 0, 0], 'long': [0, 1, 0]}}
    return PoseTable(fx, vx, pos, quat, conv, np.zeros((2, *ff.shape), np.int64), meta)


def numpy_query(table: PoseTable) -> Callable[[float, float], tuple[np.ndarray, ...]]:
    """The same bilinear query written with numpy on precomputed, hemisphere-aligned cells."""
    fx, vx = table.flexion_rad, table.varus_rad
    nf, nv = fx.size - 1, vx.size - 1
    i0, j0 = np.arange(nf), np.arange(nv)

    def corners(a: np.ndarray) -> np.ndarray:               # (B, nf, nv, 4, k)
        return np.stack([a[:, i0][:, :, j0], a[:, i0][:, :, j0 + 1], a[:, i0 + 1][:, :, j0],
                         a[:, i0 + 1][:, :, j0 + 1]], axis=3)

    pos = corners(table.position_m).transpose(1, 2, 0, 3, 4).copy()
    q = corners(table.orientation_xyzw)
    q = q * np.where(np.sum(q * q[:, :, :, :1], -1, keepdims=True) < 0.0, -1.0, 1.0)
    q = q.transpose(1, 2, 0, 3, 4).copy()
    unconv = ~corners(table.converged[..., None])[..., 0].transpose(1, 2, 0, 3)

    def query(f: float, v: float) -> tuple[np.ndarray, ...]:
        i = min(max(int(np.searchsorted(fx, f, 'right')) - 1, 0), nf - 1)
        j = min(max(int(np.searchsorted(vx, v, 'right')) - 1, 0), nv - 1)
        u = (f - fx[i]) / (fx[i + 1] - fx[i])
        t = (v - vx[j]) / (vx[j + 1] - vx[j])
        w = np.array([(1 - u) * (1 - t), (1 - u) * t, u * (1 - t), u * t])
        p = w @ pos[i, j]
        qq = w @ q[i, j]
        qq /= np.linalg.norm(qq, axis=-1, keepdims=True)
        qq *= np.where(qq[:, 3:] < 0.0, -1.0, 1.0)
        return p, qq, (unconv[i, j] & (w != 0.0)).any(axis=-1)

    return query


def time_calls(call: Callable[[float, float], object], queries: list[tuple[float, float]],
               runs: int) -> tuple[list[float], list[float]]:
    """Per-call times (us) over all runs, and each run's mean (us) from its total time."""
    per_call: list[float] = []
    means: list[float] = []
    clock = time.perf_counter_ns
    for _ in range(runs):
        start = clock()
        for f, v in queries:
            t0 = clock()
            call(f, v)
            per_call.append((clock() - t0) / 1e3)
        means.append((clock() - start) / 1e3 / len(queries))
    return per_call, means


def report(name: str, per_call: list[float], means: list[float]) -> None:
    ordered = sorted(per_call)
    p99 = ordered[min(len(ordered) - 1, math.ceil(0.99 * len(ordered)) - 1)]
    print(f'{name}: median {statistics.median(ordered):.2f} us, p99 {p99:.2f} us, '
          f'max {ordered[-1]:.1f} us over {len(ordered)} calls; run means '
          f'{", ".join(f"{m:.2f}" for m in means)} us')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=7)
    parser.add_argument('--calls', type=int, default=20000)
    parser.add_argument('--no-numpy', action='store_true', help='skip the numpy comparison')
    args = parser.parse_args(argv)
    print(f'{describe_machine()}, numpy {np.__version__}')
    table = knee_table()
    rng = np.random.default_rng(1)
    queries = list(zip(rng.uniform(table.flexion_rad[0], table.flexion_rad[-1],
                                   args.calls).tolist(),
                       rng.uniform(table.varus_rad[0], table.varus_rad[-1],
                                   args.calls).tolist()))
    print(f'table: {table.flexion_rad.size} x {table.varus_rad.size} x '
          f'{len(table.bodies)} bodies; {args.runs} runs x {args.calls} calls, random '
          'in-range queries')
    table.interpolate(*queries[0])            # build the per-table cache outside the timing
    per_call, means = time_calls(table.interpolate, queries, args.runs)
    report('PoseTable.interpolate (plain Python)', per_call, means)
    if not args.no_numpy:
        query = numpy_query(table)
        for f, v in queries[:200]:           # the two agree
            ref, alt = table.interpolate(f, v), query(f, v)
            assert np.allclose(ref.position_m, alt[0], atol=1e-12)
            assert np.allclose(ref.orientation_xyzw, alt[1], atol=1e-12)
            assert (ref.nonconverged == alt[2]).all()
        report('numpy variant (no Lookup object)', *time_calls(query, queries, args.runs))
    return 0


if __name__ == '__main__':
    sys.exit(main())
