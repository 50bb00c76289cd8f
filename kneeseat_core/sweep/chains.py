"""One chain of cells of one body, settled in order in a worker, each from its neighbour.

A warm start keeps the neighbour's spin about the push and its position relative to the
joint (both turned by the change of attitude) and adds the change the rest is expected to
make from the neighbour to the cell: where the neighbouring ribs (the same varus steps at
the flexion values beside) are settled, the change of rest they made over the same varus
step, the mean of the two where both are; else, where the rest before the neighbour in the
chain is known, the change from that one to the neighbour once more (rests move smoothly
along a chain: on the total knee's ribs its own last change puts the start 0.16 mm from
the rest, the ribs beside it 0.09-0.11 mm, medians). It is backed off one step along the
push. Every cell's search envelope is measured from the same place whatever the chain
carried in: the body's rest at the centre cell carried to the cell's attitude (`carried`),
or, for the centre cell itself and a body whose centre cell did not converge, the body as
delivered turned by the attitude (`kneeseat_core.knee.neutral_pose`). So a chain cannot
drift farther from the joint than the envelope. A cell whose warm-started settle does not
converge is settled once more from its own change where the ribs beside gave the start,
then from the cold start (the neutral pose backed off one step), and only a converged
result seeds the next cell. A settle started from a rest carried over climbs with short
first moves (`settle(..., near_rest=True)`: the rest is expected that close).

Workers forked from the sweep's parent (a local pool) start with its rigid bodies; others
rebuild them once per process from a small picklable `SceneSpec`
(`kneeseat_core.sweep.scene`), with their hierarchies for the exact travel: at their first
chain, or ahead of it (`prepare_worker`, which a sweep asks of a pool's next worker while
the first settles the centre cell). A process that runs chains keeps BLAS to one thread: a
settle's linear algebra is on 3-vectors and small matrices, which BLAS threads never speed
up, and between calls they spin on the cores the other workers need (on the default knee,
14 % more CPU for the same table).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property
import os
import time
from typing import Iterator, Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from kneeseat_core.errors import NoContactError, SettleError
from kneeseat_core.geometry import carried, pose_from
from kneeseat_core.ligaments import LigamentSet, Tissue, TissueLayout
from kneeseat_core.params import SettleParams
from kneeseat_core.settle import settle
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .scene import scene_bodies, SceneSpec

__all__ = ['ChainJob', 'SoftTissue', 'ChainResult', 'run_chain', 'prepare_worker', 'warm_start',
           'cold_start', 'rest_change', 'mean_change']


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
    soft_tissue: SoftTissue | None = None   # the ligaments acting on the body, if any
    # (n, 4, 4) per cell, the change of rest the ribs beside made from the cell before it
    # (the chain's start for the first) to it (`rest_change`); NaN where none is known
    beside: Floats | None = None
    start_at_rest: bool = True              # `start` is a rest (a centre cell's is not)

    def tissue(self, i: int) -> Tissue | None:
        """The ligaments acting on the body at the chain's i-th cell."""
        return None if self.soft_tissue is None else self.soft_tissue.at(i)

    def change_beside(self, i: int) -> Pose | None:
        """The change of rest the ribs beside made over the chain's i-th step, if known."""
        if self.beside is None or not np.isfinite(self.beside[i, 0, 0]):
            return None
        change: Pose = self.beside[i]
        return change


@dataclass(frozen=True, eq=False)
class SoftTissue:
    """What a chain needs to place the ligaments of its body at each of its cells: the
    fibres acting on it laid out (`LigamentSet.layout`; None: none acts), and where the
    bodies they pull from rest at each cell (the reference at identity, the other bodies as
    they were settled there)."""

    layout: TissueLayout | None
    reference: str
    placed: tuple[str, ...]                 # the settled bodies its fibres reach
    placed_poses: Floats                    # (n, len(placed), 4, 4) their poses per cell

    @classmethod
    def of(cls, ligaments: LigamentSet, body: str, reference: str, placed: tuple[str, ...],
           placed_poses: Floats) -> SoftTissue:
        """The fibres of `ligaments` acting on `body` with the reference and the bodies
        `placed` (at `placed_poses`, per cell) where they rest."""
        return cls(ligaments.layout(body, (reference, *placed)), reference, placed,
                   placed_poses)

    def at(self, i: int) -> Tissue | None:
        """The tissue at the chain's i-th cell."""
        if self.layout is None or not self.placed:
            return self._still
        poses = {self.reference: np.eye(4)}
        poses.update(zip(self.placed, self.placed_poses[i]))
        return self.layout.place(poses)

    @cached_property
    def _still(self) -> Tissue | None:
        """Where only the reference holds the fibres (`at` asks only then), the tissue
        itself: the same at every cell, built once."""
        return None if self.layout is None else self.layout.place({self.reference: np.eye(4)})


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
    travels: int = 0          # exact travels measured (of `collision_checks`)
    fcl_checks: int = 0       # python-fcl queries (of `collision_checks`)


def rest_change(older: Pose, newer: Pose) -> Pose:
    """The change from the pose `older` to `newer` (both (4, 4), at one attitude): the turn
    that takes one's orientation to the other's (left factor) and the shift of the origin.
    Stacks of poses ((..., 4, 4)) give the stack of each pair's, bit for bit."""
    out: Pose = np.zeros(np.shape(newer))
    out[..., :3, :3] = newer[..., :3, :3] @ np.swapaxes(older[..., :3, :3], -1, -2)
    out[..., :3, 3] = newer[..., :3, 3] - older[..., :3, 3]
    out[..., 3, 3] = 1.0
    return out


def mean_change(steps: Sequence[tuple[Pose, Floats, Pose, Floats]], attitude: Floats) -> Pose:
    """The mean of the changes of rest over `steps` (each: the older rest and its attitude,
    the newer rest and its attitude), each step's two rests carried to `attitude` first
    (`rest_change`; the mean turn is made a rotation where it is applied, `warm_start`)."""
    # the steps as stacks, at once: the same products as step by step, bit for bit
    older, older_attitudes, newer, newer_attitudes = (np.array(a) for a in zip(*steps))
    out: Pose = np.mean(rest_change(carried(older, older_attitudes, attitude),
                                    carried(newer, newer_attitudes, attitude)), axis=0)
    return out


def warm_start(previous: Pose, previous_attitude: Floats, attitude: Floats,
               push: Floats, back_off_m: float, before: tuple[Pose, Floats] | None = None,
               change: Pose | None = None) -> Pose:
    """Start pose at a new attitude from a neighbour's equilibrium (module docstring): the
    `change` expected from the neighbour to the cell (`rest_change`, at the cell's
    attitude) added; or, with the rest `before` it (pose, attitude) along the chain, the
    change from that one to the neighbour's carried on once more."""
    start = carried(previous, previous_attitude, attitude)
    if change is None and before is not None:
        change = rest_change(carried(before[0], before[1], attitude), start)
    if change is not None:
        start[:3, 3] += change[:3, 3]
        # the turn, made a rotation once more (a product or a mean drifts off one)
        u, _, vt = np.linalg.svd(change[:3, :3] @ start[:3, :3])
        start[:3, :3] = u @ vt
    start[:3, 3] -= back_off_m * push
    return start


def cold_start(attitude: Floats, params: SettleParams) -> Pose:
    """The neutral pose backed off one step along the push."""
    return pose_from(attitude, -params.step_m * np.asarray(params.push))


@cache
def _one_blas_thread() -> None:
    """Keep this process's BLAS to one thread (module docstring), once."""
    threadpool_limits(limits=1, user_api='blas')


def _retry_starts(previous: Pose, previous_attitude: Floats, attitude: Floats,
                  params: SettleParams, before: tuple[Pose, Floats] | None,
                  led_by_beside: bool, at_rest: bool) -> Iterator[tuple[Pose, bool]]:
    """The starts a cell whose warm-started settle did not converge is tried from next,
    each with whether it is a rest carried over (`previous` is one where `at_rest`), made
    only when asked: its own change where the ribs beside gave the start (they may lead it
    astray), then the cold start (the chain drifted)."""
    if led_by_beside:
        yield warm_start(previous, previous_attitude, attitude, np.asarray(params.push),
                         params.step_m, before), at_rest
    yield cold_start(attitude, params), False


def prepare_worker(scene: SceneSpec) -> int:
    """Make this process ready to settle `scene`'s chains (BLAS kept to one thread, the
    bodies built with their hierarchies for the exact travel) before its first chain comes;
    returns the process id. A pool that starts its workers one by one (spawned, or on a
    Dask cluster) starts its next one when the first chain is submitted, and the others
    wait for the centre cell anyway: the next worker does its part of the start meanwhile
    instead of at its first chain. A worker forked from the sweep's parent has it all
    already."""
    _one_blas_thread()
    scene_bodies(scene)
    return os.getpid()


def run_chain(job: ChainJob) -> ChainResult:
    """Settle the cells of `job` in order (runs in a worker process)."""
    _one_blas_thread()
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
    checks = travels = fcl = 0
    previous, previous_attitude = job.start, job.start_attitude
    at_rest = job.start_at_rest             # `previous` is a rest: its cell's are short
    before: tuple[Pose, Floats] | None = None
    # the triangles in contact at the rest just before: the next search starts from them
    seeds: Ints | None = None
    for i, (attitude, params) in enumerate(zip(job.attitudes, job.params)):
        # the ribs beside changed over this step from the rest just before: only while
        # `previous` is that rest
        beside = job.change_beside(i) if i == 0 or converged[i - 1] else None
        start = warm_start(previous, previous_attitude, attitude, np.asarray(params.push),
                           params.step_m, before, beside)
        anchor = carried(job.anchor, job.anchor_attitude, attitude)
        tissue = job.tissue(i)
        try:
            result = settle(fixed, moving, start, params, anchor, tissue, seeds,
                            near_rest=at_rest)
        except (NoContactError, SettleError) as err:
            poses[i] = start
            reasons.append(f'failed: {err}')
            continue
        tried = [result]
        retries = () if result.converged else _retry_starts(
            previous, previous_attitude, attitude, params, before, beside is not None,
            at_rest)
        for retry_start, near_rest in retries:
            try:
                retry = settle(fixed, moving, retry_start, params, anchor, tissue,
                               near_rest=near_rest)
            except (NoContactError, SettleError):
                continue            # a start that cannot settle is no better: the next
            tried.append(retry)
            if retry.converged:     # else the first start's failure is the one reported
                result = retry
                break
        checks += sum(t.collision_checks for t in tried)
        travels += sum(t.travels for t in tried)
        fcl += sum(t.fcl_checks for t in tried)
        poses[i] = result.pose
        converged[i] = result.converged
        iterations[i] = result.iterations
        status[i] = result.status
        backed[i] = result.backed_out_m
        reasons.append(result.reason)
        if result.converged:   # a failed cell never seeds its neighbours
            before = (previous, previous_attitude) if i > 0 and converged[i - 1] else None
            previous, previous_attitude = result.pose, attitude
            seeds = result.touching
            at_rest = True
        else:
            before = seeds = None
    return ChainResult(job.body, job.cells, poses, converged, iterations, status, checks,
                       tuple(reasons), time.perf_counter() - started, backed, travels, fcl)
