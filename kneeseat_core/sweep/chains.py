"""The range-of-motion sweep: settle every grid attitude, warm-started, in parallel chains.

Order (the patent's warm start, made parallel):
1. the *centre* cell of each moving body (flexion and varus nearest 0) from its cold start;
2. a *spine* per body: the flexion values at the varus nearest 0, settled outward from the
   centre, each cell from its neighbour's equilibrium;
3. a *rib* per (body, flexion value, side): the varus values settled outward from the spine
   cell, each from its neighbour's equilibrium.
Each phase runs its chains in parallel (across bodies, then across flexion values and
sides) on any `concurrent.futures.Executor` (a process pool by default; Dask's executor
plugs in the same way). A body whose attitude ignores varus (`varus_fraction: 0`, e.g. a
patella) is settled on its spine only and copied across varus.

Why ribs along varus rather than columns along flexion: where a body rests on one contact
only (a tibia tilted by a commanded varus bears on one condyle), its spin about the push
is free - no move gains depth - and a settle keeps the spin it starts with. Ribs carry the
spin that the spine's two-contact rests determine at each flexion out to every varus
value, so varus neighbours agree; independent flexion columns each kept their own spin
and disagreed by up to 2.6 deg (docs/tables.md).

A warm start keeps the neighbour's spin about the push and its position relative to the
joint (both turned by the change of attitude), backed off one step along the push. Every
cell's search envelope is measured from the same place whatever the chain carried in: the
body's rest at the centre cell carried to the cell's attitude (`carried`), or, for the
centre cell itself and a body whose centre cell did not converge, the body as delivered
turned by the attitude (`knee.neutral_pose`). So a chain cannot drift farther from the
joint than the envelope. A cell whose warm-started settle does not converge is settled
once more from the cold start (the neutral pose backed off one step) and only a converged
result seeds the next cell.
Workers rebuild the rigid bodies once per process from a small picklable `SceneSpec`
(`kneeseat_core.sweep.scene`). The parent validates every mesh once before the sweep (warnings
such as an open cartilage sheet appear once per mesh), so workers load quietly.
"""
from __future__ import annotations

from concurrent.futures import as_completed, Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass, field
import logging
import math
import multiprocessing
import os
from pathlib import Path
import time
from typing import Callable, Iterable, ParamSpec, Sequence, TypeVar

import numpy as np

from kneeseat_core.errors import NoContactError, SettleError
from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import pose_from, quat_from_matrix, TOL
from kneeseat_core.knee.config import KneeConfig, neutral_pose
from kneeseat_core.meshes.load import check_mesh_files
from kneeseat_core.params import SettleParams
from kneeseat_core.settle import settle
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .scene import scene_bodies, SceneSpec

__all__ = ['ChainJob', 'ChainResult', 'SweepResult', 'InlineExecutor', 'run_chain', 'sweep',
           'default_workers', 'process_executor', 'carried', 'warm_start', 'cold_start']

log = logging.getLogger(__name__)

_P = ParamSpec('_P')
_T = TypeVar('_T')


@dataclass(frozen=True, slots=True, eq=False)
class ChainJob:
    """A chain of cells of one body, settled in order, each warm-started from the last."""

    scene: SceneSpec
    body: int
    cells: tuple[tuple[int, int], ...]      # (flexion index, varus index) in order
    attitudes: Floats                       # (n, 3, 3) attitude A of each cell
    params: tuple[SettleParams, ...]        # per cell (push differs)
    start: Pose                             # (4, 4) pose the first cell starts from
    start_attitude: Floats                  # (3, 3) attitude `start` was settled at
    anchor: Pose                            # (4, 4) envelope anchor, carried to each cell
    anchor_attitude: Floats                 # (3, 3) attitude the anchor belongs to


@dataclass(frozen=True, slots=True, eq=False)
class ChainResult:
    """Settled poses of a chain, in the job's cell order."""

    body: int
    cells: tuple[tuple[int, int], ...]
    poses: Floats             # (n, 4, 4)
    converged: Bools          # (n,)
    iterations: Ints          # (n,)
    status: Ints              # (n,) `Status` codes
    collision_checks: int
    reasons: tuple[str, ...]
    elapsed_s: float
    backed_out_m: Floats      # (n,) how far each kept settle backed its start out


def carried(pose: Pose, from_attitude: Floats, attitude: Floats) -> Pose:
    """`pose` (taken at `from_attitude`) turned by the change of attitude to `attitude`."""
    turn = attitude @ from_attitude.T
    return pose_from(turn @ pose[:3, :3], turn @ pose[:3, 3])


def warm_start(previous: Pose, previous_attitude: Floats, attitude: Floats,
               push: Floats, back_off_m: float) -> Pose:
    """Start pose at a new attitude from a neighbour's equilibrium (module docstring)."""
    start = carried(previous, previous_attitude, attitude)
    start[:3, 3] -= back_off_m * push
    return start


def cold_start(attitude: Floats, params: SettleParams) -> Pose:
    """The neutral pose backed off one step along the push."""
    return pose_from(attitude, -params.step_m * np.asarray(params.push))


def run_chain(job: ChainJob) -> ChainResult:
    """Settle the cells of `job` in order (runs in a worker process)."""
    started = time.perf_counter()
    fixed, bodies = scene_bodies(job.scene)
    moving = bodies[job.body]
    n = len(job.cells)
    poses = np.empty((n, 4, 4))
    converged = np.zeros(n, dtype=bool)
    iterations = np.zeros(n, dtype=np.int64)
    status = np.full(n, Status.FAILED, dtype=np.int8)
    backed = np.zeros(n)
    reasons: list[str] = []
    checks = 0
    previous, previous_attitude = job.start, job.start_attitude
    for i, (attitude, params) in enumerate(zip(job.attitudes, job.params)):
        start = warm_start(previous, previous_attitude, attitude, np.asarray(params.push),
                           params.step_m)
        anchor = carried(job.anchor, job.anchor_attitude, attitude)
        try:
            result = settle(fixed, moving, start, params, anchor)
            if not result.converged:       # the chain drifted: try the cold start once
                retry = settle(fixed, moving, cold_start(attitude, params), params, anchor)
                checks += result.collision_checks
                result = retry if retry.converged else result
        except (NoContactError, SettleError) as err:
            poses[i] = start
            reasons.append(f'failed: {err}')
            continue
        poses[i] = result.pose
        converged[i] = result.converged
        iterations[i] = result.iterations
        status[i] = result.status
        backed[i] = result.backed_out_m
        checks += result.collision_checks
        reasons.append(result.reason)
        if result.converged:   # a failed cell never seeds its neighbours
            previous, previous_attitude = result.pose, attitude
    return ChainResult(job.body, job.cells, poses, converged, iterations, status, checks,
                       tuple(reasons), time.perf_counter() - started, backed)


@dataclass(frozen=True, slots=True, eq=False)
class SweepResult:
    """Every cell of every body, in table layout."""

    position_m: Floats          # (B, F, V, 3)
    orientation_xyzw: Floats    # (B, F, V, 4)
    converged: Bools            # (B, F, V)
    iterations: Ints            # (B, F, V)
    status: Ints                # (B, F, V) int8, `Status` codes
    collision_checks: int
    wall_s: float
    mesh_sha256: tuple[str, ...]    # hex, of the mesh files swept (SceneSpec.paths order)
    anchors: Floats                 # (B, 4, 4) envelope anchor of each body (module docstring)
    anchor_cell: tuple[int, int]    # (flexion, varus) index the anchors belong to
    backed_out_m: Floats            # (B, F, V) how far each cell's start was backed out
    failures: tuple[str, ...] = field(default=())   # first few non-converged reasons

    @property
    def cells(self) -> int:
        """Number of (body, flexion, varus) cells."""
        return int(self.converged.size)


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


def default_workers() -> int:
    """All cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def process_executor(workers: int) -> Executor:
    """The default executor: in-process for one worker, else a process pool (spawn)."""
    if workers <= 1:
        return InlineExecutor()
    return ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context('spawn'))


def _outward(n: int, centre: int) -> tuple[list[int], list[int]]:
    """Indices from `centre` going up and going down (centre excluded)."""
    return list(range(centre + 1, n)), list(range(centre - 1, -1, -1))


def sweep(config: KneeConfig, executor: Executor,
          progress: Callable[[int], object] | None = None) -> SweepResult:
    """Settle every (body, flexion, varus) cell of `config` on `executor`.

    Args:
        progress: called with the number of cells just finished.
    Returns:
        All poses in table layout; non-converged cells are flagged, never hidden.
    """
    started = time.perf_counter()
    run = _Sweep(config, progress)
    run.collect([executor.submit(run_chain, j) for j in run.centre_jobs()])
    run.anchor_at_centres()
    run.collect([executor.submit(run_chain, j) for j in run.spine_jobs()])
    run.collect([executor.submit(run_chain, j) for j in run.rib_jobs()])
    run.copy_across_varus()
    return run.result(time.perf_counter() - started)


class _Sweep:
    """One sweep's cells in table layout, filled phase by phase (module docstring)."""

    def __init__(self, config: KneeConfig, progress: Callable[[int], object] | None) -> None:
        self.config, self.progress = config, progress
        flex, var = config.flexion_rad, config.varus_rad
        nb, nf, nv = len(config.bodies), len(flex), len(var)
        groups = [tuple(str(m) for m in spec.meshes)
                  for spec in (config.reference, *config.bodies)]
        self.scene = SceneSpec(groups[0], tuple(groups[1:]), config.units,
                               tuple(file_sha256(Path(p)) for g in groups for p in g))
        check_mesh_files(self.scene.paths(), config.units)   # once here; workers load quietly
        self.f0 = int(np.argmin(np.abs(flex)))
        self.v0 = int(np.argmin(np.abs(var)))
        self.poses = np.zeros((nb, nf, nv, 4, 4))
        self.converged = np.zeros((nb, nf, nv), dtype=bool)
        self.iterations = np.zeros((nb, nf, nv), dtype=np.int64)
        self.status = np.full((nb, nf, nv), Status.FAILED, dtype=np.int8)
        self.backed = np.zeros((nb, nf, nv))
        self.failures: list[str] = []
        self.checks = 0
        self.centre_attitudes = [config.attitude(spec, flex[self.f0], var[self.v0])
                                 for spec in config.bodies]
        self.anchors = np.array([neutral_pose(a0) for a0 in self.centre_attitudes])
        self.varus_free = [abs(b.varus_fraction) < TOL.fraction for b in config.bodies]

    def job(self, body: int, cells: Sequence[tuple[int, int]], start: Pose,
            start_attitude: Floats) -> ChainJob:
        """The chain of `cells` of `body`, from `start` (settled at `start_attitude`)."""
        config, flex, var = self.config, self.config.flexion_rad, self.config.varus_rad
        spec = config.bodies[body]
        return ChainJob(self.scene, body, tuple(cells),
                        np.array([config.attitude(spec, flex[f], var[v]) for f, v in cells]),
                        tuple(config.params(spec, flex[f], var[v]) for f, v in cells),
                        start, start_attitude, self.anchors[body], self.centre_attitudes[body])

    def collect(self, futures: Iterable[Future[ChainResult]]) -> None:
        """Put every finished chain's cells in place, as they finish."""
        flex, var = self.config.flexion_rad, self.config.varus_rad
        for fut in as_completed(list(futures)):
            res = fut.result()
            for k, (f, v) in enumerate(res.cells):
                self.poses[res.body, f, v] = res.poses[k]
                self.converged[res.body, f, v] = res.converged[k]
                self.iterations[res.body, f, v] = res.iterations[k]
                self.status[res.body, f, v] = res.status[k]
                self.backed[res.body, f, v] = res.backed_out_m[k]
                if not res.converged[k] and len(self.failures) < 5:
                    self.failures.append(
                        f'{self.config.bodies[res.body].name} flexion '
                        f'{math.degrees(flex[f]):g} varus {math.degrees(var[v]):g}: '
                        f'{res.reasons[k]}')
            self.checks += res.collision_checks
            if self.progress:
                self.progress(len(res.cells))

    def centre_jobs(self) -> list[ChainJob]:
        """1. Each body's centre cell, from its cold start."""
        config, f0, v0 = self.config, self.f0, self.v0
        jobs = []
        for b, spec in enumerate(config.bodies):
            a0 = self.centre_attitudes[b]
            params = config.params(spec, config.flexion_rad[f0], config.varus_rad[v0])
            jobs.append(self.job(b, [(f0, v0)], cold_start(a0, params), a0))
        return jobs

    def anchor_at_centres(self) -> None:
        """Every other cell's envelope is measured from the centre rest, carried."""
        for b in range(len(self.config.bodies)):
            if self.converged[b, self.f0, self.v0]:
                self.anchors[b] = self.poses[b, self.f0, self.v0]

    def spine_jobs(self) -> list[ChainJob]:
        """2. Spines: varus v0, flexion outward from f0, from the centre rest."""
        config, f0, v0 = self.config, self.f0, self.v0
        jobs = []
        for b in range(len(config.bodies)):
            for side in _outward(len(config.flexion_rad), f0):
                if side:
                    jobs.append(self.job(b, [(f, v0) for f in side], self.poses[b, f0, v0],
                                         self.centre_attitudes[b]))
        return jobs

    def rib_jobs(self) -> list[ChainJob]:
        """3. Ribs: every flexion value of a body that feels varus, varus outward from the
        spine cell."""
        config, v0 = self.config, self.v0
        jobs = []
        for b, spec in enumerate(config.bodies):
            if self.varus_free[b]:
                continue
            for f in range(len(config.flexion_rad)):
                for side in _outward(len(config.varus_rad), v0):
                    if side:
                        jobs.append(self.job(b, [(f, v) for v in side], self.poses[b, f, v0],
                                             config.attitude(spec, config.flexion_rad[f],
                                                             config.varus_rad[v0])))
        return jobs

    def copy_across_varus(self) -> None:
        """A body that ignores varus: its spine, copied to every varus value."""
        nf, nv, v0 = len(self.config.flexion_rad), len(self.config.varus_rad), self.v0
        for b in range(len(self.config.bodies)):
            if self.varus_free[b]:
                for cells in (self.poses, self.converged, self.iterations, self.status,
                              self.backed):
                    cells[b] = cells[b, :, v0:v0 + 1]
                if self.progress:           # the copies are cells of the table too
                    self.progress(nf * (nv - 1))

    def result(self, wall_s: float) -> SweepResult:
        """Everything in table layout."""
        return SweepResult(self.poses[..., :3, 3].copy(),
                           quat_from_matrix(self.poses[..., :3, :3]), self.converged,
                           self.iterations, self.status, self.checks, wall_s,
                           self.scene.mesh_sha256, self.anchors, (self.f0, self.v0),
                           self.backed, tuple(self.failures))
