"""Cost of one settle of the tibial insert against the femoral component (total knee).

Run: `python benchmarks/bench_settle.py [--runs 11] [--method default|patent|both]
[--data ../shared/data/tka_dm]`.
The insert starts as delivered, moved -5 mm along Y (away from the femur), +3 mm along Z
(lateral) and turned 5 degrees about the Y axis through its centroid; it is pushed along
+Y. The rigid bodies (BVH, normals) are built once, outside the timing. For each method it
prints the median / min / max wall time per settle, iterations, collision checks (for the
default method: exact travels and python-fcl queries), the share of the time spent inside
python-fcl, and converged/reason; with both methods, how far apart their end poses are
(insert centroid distance in mm, rotation angle in deg). Target: default median <= 10 ms
per settle on this machine; the proof of rest's share is printed too. The first settle
of each method is run before the timing (it builds the bodies' hierarchies).
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
import statistics
import sys
import time

import numpy as np

from kneeseat_core.meshes import load_mesh, RigidBody
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.settle import settle, SettleParams, SettleResult
from machine import describe_machine

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / 'shared' / 'data' / 'tka_dm'
PUSH = (0.0, 1.0, 0.0)
TARGET_MS = 10.0


def start_pose(insert: RigidBody) -> np.ndarray:
    """(4, 4) femur_from_insert start: delivered pose, -5 mm Y, +3 mm Z, 5 deg about Y
    through the insert's centroid."""
    turn = rotation_about(np.array([0.0, 1.0, 0.0]), math.radians(5.0))
    centroid = insert.centroid
    return pose_from(turn, centroid - turn @ centroid + np.array([0.0, -5e-3, 3e-3]))


def run_method(fixed: RigidBody, moving: RigidBody, start: np.ndarray, method: str,
               runs: int, max_iterations: int) -> tuple[list[SettleResult], list[float]]:
    """`runs` settles; their results and the CPU time (ms) of this process for each."""
    params = SettleParams(push=PUSH, method=method,  # type: ignore[arg-type]
                          max_iterations=max_iterations)
    settle(fixed, moving, start, params)        # the hierarchies, outside the timing
    results, cpu_ms = [], []
    for _ in range(runs):
        cpu = time.process_time()
        results.append(settle(fixed, moving, start, params))
        cpu_ms.append((time.process_time() - cpu) * 1e3)
    return results, cpu_ms


def report(method: str, results: list[SettleResult], cpu_ms: list[float]) -> None:
    ms = [r.elapsed_s * 1e3 for r in results]
    share = [r.fcl_s / r.elapsed_s for r in results]
    last = results[-1]
    same = all(np.allclose(r.pose, last.pose, atol=1e-12) for r in results)
    checks = (f'{last.collision_checks} collision checks ({last.travels} exact travels, '
              f'{last.fcl_checks} python-fcl)' if last.travels
              else f'{last.collision_checks} collision checks')
    print(f'{method}: {len(results)} runs, median {statistics.median(ms):.1f} ms, '
          f'min {min(ms):.1f} ms, max {max(ms):.1f} ms wall per settle (CPU median '
          f'{statistics.median(cpu_ms):.1f} ms); {last.iterations} iterations, {checks}, '
          f'{statistics.median(share):.0%} of the time inside python-fcl; converged '
          f'{last.converged}: {last.reason}'
          + ('' if same else ' (WARNING: runs ended at different poses)'))
    if method == 'default':
        proof_ms = statistics.median(r.proof_s * 1e3 for r in results)
        print(f'  proof of rest (probes around the end pose): {last.proof_checks} exact '
              f'travels, median {proof_ms:.1f} ms ({proof_ms / statistics.median(ms):.0%} of '
              'the settle)')
    print(f'  end position {np.array2string(last.pose[:3, 3] * 1e3, precision=3)} mm'
          + (f'; backed out {last.backed_out_m * 1e3:.3f} mm' if last.backed_out_m else ''))


def pose_distance(a: np.ndarray, b: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """(distance in mm between `point` carried by both poses, rotation angle in deg)."""
    pa = a[:3, :3] @ point + a[:3, 3]
    pb = b[:3, :3] @ point + b[:3, 3]
    cos = (float(np.trace(a[:3, :3].T @ b[:3, :3])) - 1.0) / 2.0
    angle = math.acos(max(-1.0, min(1.0, cos)))
    return float(np.linalg.norm(pa - pb)) * 1e3, math.degrees(angle)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--runs', type=int, default=11, help='settles per method (11)')
    parser.add_argument('--method', choices=('default', 'patent', 'both'), default='both')
    parser.add_argument('--max-iterations', type=int, default=500)
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='folder with femoral_component.stl and tibial_insert.stl')
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be at least 1')
    if not (args.data / 'femoral_component.stl').is_file():
        print(f'bench_settle: no femoral_component.stl in {args.data}; pass --data pointing '
              'at the tka_dm folder', file=sys.stderr)
        return 2
    print(f'{describe_machine()}, numpy {np.__version__}')
    femoral = RigidBody.from_mesh(load_mesh(args.data / 'femoral_component.stl'))
    insert = RigidBody.from_mesh(load_mesh(args.data / 'tibial_insert.stl'))
    print(f'meshes: femoral component {len(femoral.mesh.faces)} triangles (fixed), tibial '
          f'insert {len(insert.mesh.faces)} triangles (moving); push +Y; start -5 mm Y, '
          '+3 mm Z, 5 deg about Y')
    start = start_pose(insert)
    methods = ('default', 'patent') if args.method == 'both' else (args.method,)
    ends = {}
    for method in methods:
        results, cpu_ms = run_method(femoral, insert, start, method, args.runs,
                                     args.max_iterations)
        report(method, results, cpu_ms)
        ends[method] = results[-1].pose
        if method == 'default':
            median = statistics.median(r.elapsed_s * 1e3 for r in results)
            verdict = 'met' if median <= TARGET_MS else 'NOT met'
            print(f'  target default median <= {TARGET_MS:.0f} ms: {verdict}')
    if len(ends) == 2:
        mm, deg = pose_distance(ends['default'], ends['patent'], insert.centroid)
        rise = (ends['default'][1, 3] - ends['patent'][1, 3]) * 1e3
        print(f'default vs patent end pose: insert centroid {mm:.3f} mm apart '
              f'(default {rise:+.3f} mm further along the push), rotation {deg:.3f} deg')
    return 0


if __name__ == '__main__':
    sys.exit(main())
