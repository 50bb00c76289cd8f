"""The range-of-motion sweep: settle every grid attitude, warm-started, in parallel chains.

The patent's warm start, made parallel: every cell is settled from its neighbour's rest,
along chains of three kinds:
1. the *centre* cell of each moving body (flexion and varus nearest 0) from its cold start;
2. a *spine* per body and side of the centre: the flexion values at the varus nearest 0,
   settled outward from the centre, each cell from its neighbour's equilibrium, run in
   segments of `SPINE_SEGMENT` cells (each segment from the rest the last one ended on);
3. a *rib* per (body, flexion value, side): the varus values settled outward from the spine
   cell, each from its neighbour's equilibrium and the change of rest the ribs beside it
   made over the same varus step. The ribs learn in rounds, so that the wait never grows
   with the grid: every 16th rib from the centre first (from its own last change of rest),
   then those halfway between them, learning from the two 8 steps away, then those
   halfway again (4 steps away), and so on to the ribs next to them (`ribs_beside`).
A chain runs as soon as the cells it starts from are settled (`sweep`): a rib as soon as
its spine cell and the ribs beside it, the next spine segment as soon as the last one, so
the ribs of the first flexion values keep every worker busy while the spine goes on, and no
phase waits for another. Of the chains ready, those listed first go first: a local pool is
given only as many as its workers can take (`submitted_ahead`), so a spine's next segment
goes before the ribs that wait already, and the spines are done long before the last ribs.
Chains run on any `concurrent.futures.Executor`
(`kneeseat_core.sweep.executors`); a chain is the same computation whenever and wherever
it runs, so the table does not depend on the order. A body whose attitude ignores varus
(`varus_fraction: 0`, e.g. a patella) is settled on its spine only and copied across
varus, unless its ligaments pull from a body that feels varus.

A body whose ligaments pull from another moving body (a patella's tendon from the tibia)
is settled at a cell after that body: a chain of it runs once the other body is settled at
each of its cells, its fibres attached to the other body as it was settled there. That
neglects the pull of those fibres on the body settled first (the tendon's on the tibia);
docs/design.md says what it changes.

Why ribs along varus rather than columns along flexion: where a body rests on one contact
only (a tibia tilted by a commanded varus bears on one condyle), its spin about the push
is free - no move gains depth - and a settle keeps the spin it starts with. Ribs carry the
spin that the spine's two-contact rests determine at each flexion out to every varus
value, so varus neighbours agree; independent flexion columns each kept their own spin
and disagreed by up to 2.6 deg (docs/tables.md).

The parent builds the scene before the sweep (`scene_bodies`: the meshes loaded and
validated, warnings such as an open cartilage sheet once per mesh, and the bodies'
hierarchies), so that workers forked from it (a local pool, `kneeseat_core.sweep.executors`)
start settling at once and others load quietly. With the centre chains it submits one
`prepare_worker`: a pool that starts its workers one by one (spawned, or Dask) starts its
next worker for it, which builds the scene while the first settles the centre cells that
every other chain waits for (on the total knee, with spawned workers, its first chain then
started 1.2 s sooner and took 0.06 s instead of 0.9 s).
"""
from __future__ import annotations

from concurrent.futures import Executor, FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
import heapq
import math
from pathlib import Path
import time
from typing import Callable, Sequence

import numpy as np

from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import quat_from_matrix, TOL
from kneeseat_core.knee import KneeConfig, neutral_pose
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .chains import (ChainJob, ChainResult, cold_start, mean_change, prepare_worker,
                     run_chain, SoftTissue)
from .executors import submitted_ahead
from .scene import scene_bodies, SceneSpec

__all__ = ['SweepResult', 'sweep', 'ribs_beside']


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
    travels: int = 0                # exact travels measured (of `collision_checks`)
    fcl_checks: int = 0             # python-fcl queries (of `collision_checks`)
    scene_s: float = 0.0            # of `wall_s`, the bodies and hierarchies built first
    chains_s: float = 0.0           # the chains' own times, summed over the workers

    @property
    def cells(self) -> int:
        """Number of (body, flexion, varus) cells."""
        return int(self.converged.size)


def _outward(n: int, centre: int) -> tuple[list[int], list[int]]:
    """Indices from `centre` going up and going down (centre excluded)."""
    return list(range(centre + 1, n)), list(range(centre - 1, -1, -1))


# A rib learns from ribs at most this many flexion steps away (a power of two): the change
# of rest along varus stays alike that far (on the total knee's ribs, the mean of the ribs
# 8 steps either side predicts the next rest with less than half the error of a rib's
# own last change, 0.29 against 0.76 mm at the 90th percentile), and a rib waits for at most
# log2(FARTHEST_BESIDE) + 1 rounds of ribs before it.
FARTHEST_BESIDE = 8


def ribs_beside(f: int, centre: int, count: int) -> list[int]:
    """The flexion indices of the ribs that the rib at `f` (of `count`, the centre at
    `centre`) waits for and learns from (module docstring): at a distance k from the
    centre, the two ribs s steps either side, s the largest power of two that divides k;
    none where s is beyond `FARTHEST_BESIDE` (the first round: the centre rib and every
    2 * FARTHEST_BESIDE-th one)."""
    k = abs(f - centre)
    step = k & -k           # the lowest bit set
    if k == 0 or step > FARTHEST_BESIDE:
        return []
    return [g for g in (f - step, f + step) if 0 <= g < count]


# Cells per segment of a spine: short, so that the ribs of the first flexion values run
# while the spine goes on; each segment starts from the rest the last one ended on.
SPINE_SEGMENT = 8

Cell = tuple[int, int, int]       # (body, flexion index, varus index)


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
    chains = run.chains()
    # each chain waits for the cells it starts from; a settled cell frees its waiters
    missing = [len(chain.after) for chain in chains]
    waiters: dict[Cell, list[int]] = {}
    for k, chain in enumerate(chains):
        for cell in chain.after:
            waiters.setdefault(cell, []).append(k)
    # the chains listed first go first: those ready wait here, least index first, while
    # the executor has as many as it can take (`submitted_ahead`)
    ready = [k for k, n in enumerate(missing) if n == 0]
    heapq.heapify(ready)
    ahead = submitted_ahead(executor)
    running: dict[Future[ChainResult], int] = {}
    preparing: Future[int] | None = None
    while ready or running:
        while ready and (ahead is None or len(running) < ahead):
            k = heapq.heappop(ready)
            running[executor.submit(run_chain, run.job_for(chains[k]))] = k
        if preparing is None:
            # the next worker of a pool gets ready while the first settles the centre
            # cells, which every other chain waits for (what it returns is not needed)
            preparing = executor.submit(prepare_worker, run.scene)
        finished, _ = wait(running, return_when=FIRST_COMPLETED)
        for future in finished:
            del running[future]
            for cell in run.take(future.result()):
                for k in waiters.pop(cell, ()):
                    missing[k] -= 1
                    if missing[k] == 0:
                        heapq.heappush(ready, k)
    assert not any(missing), 'a chain waited for a cell that no chain settles'
    return run.result(time.perf_counter() - started)


@dataclass(frozen=True, slots=True)
class _Chain:
    """A chain of the sweep before it runs: its kind, body and cells in order, and the
    cells that must be settled before it can start (what it is seeded from, and where the
    bodies its ligaments pull from rest at each of its cells)."""

    kind: str                          # 'centre', 'spine' or 'rib'
    body: int
    cells: tuple[tuple[int, int], ...]
    after: tuple[Cell, ...]


class _Sweep:
    """One sweep's cells in table layout, filled as its chains finish (module docstring)."""

    def __init__(self, config: KneeConfig, progress: Callable[[int], object] | None) -> None:
        self.config, self.progress = config, progress
        flex, var = config.flexion_rad, config.varus_rad
        nb, nf, nv = len(config.bodies), len(flex), len(var)
        groups = [tuple(str(m) for m in spec.meshes)
                  for spec in (config.reference, *config.bodies)]
        started = time.perf_counter()
        self.scene = SceneSpec(groups[0], tuple(groups[1:]), config.units,
                               tuple(file_sha256(Path(p)) for g in groups for p in g))
        scene_bodies(self.scene, quiet=False)     # validated here; workers forked now have it
        self.scene_s = time.perf_counter() - started
        self.chains_s = 0.0
        self.f0 = int(np.argmin(np.abs(flex)))
        self.v0 = int(np.argmin(np.abs(var)))
        self.poses = np.zeros((nb, nf, nv, 4, 4))
        self.converged = np.zeros((nb, nf, nv), dtype=bool)
        self.iterations = np.zeros((nb, nf, nv), dtype=np.int64)
        self.status = np.full((nb, nf, nv), Status.FAILED, dtype=np.int8)
        self.backed = np.zeros((nb, nf, nv))
        self.failures: list[str] = []
        self.checks = 0
        self.travels = 0
        self.fcl = 0
        self.attitudes = config.attitudes()       # (B, F, V, 3, 3): every cell's, asked often
        self.attitudes.flags.writeable = False
        self.centre_attitudes = [self.attitudes[b, self.f0, self.v0] for b in range(nb)]
        self.anchors = np.array([neutral_pose(a0) for a0 in self.centre_attitudes])
        self.depends = [config.depends_on(b) for b in config.bodies]
        # the fibres acting on each body, laid out once (the patent's method has none)
        ligaments = config.ligaments
        self.layouts = [None if ligaments is None or config.settle.method == 'patent' else
                        ligaments.layout(spec.name, config.placed_before(spec))
                        for spec in config.bodies]
        # settled once per flexion value and copied across varus: a body that ignores varus
        # and whose ligaments pull from no body that feels it
        self.varus_free: list[bool] = []
        for b, spec in enumerate(config.bodies):
            self.varus_free.append(abs(spec.varus_fraction) < TOL.fraction
                                   and all(self.varus_free[d] for d in self.depends[b]))

    def job(self, body: int, cells: Sequence[tuple[int, int]], start: Pose,
            start_attitude: Floats, beside: Floats | None = None,
            at_rest: bool = True) -> ChainJob:
        """The chain of `cells` of `body`, from `start` (settled at `start_attitude`; a
        rest unless `at_rest` is False), with the changes of rest the ribs `beside` it
        made (`changes_beside`)."""
        config, flex, var = self.config, self.config.flexion_rad, self.config.varus_rad
        spec = config.bodies[body]
        return ChainJob(self.scene, body, tuple(cells),
                        np.array([self.attitudes[body, f, v] for f, v in cells]),
                        tuple(config.params(spec, flex[f], var[v]) for f, v in cells),
                        start, start_attitude, self.anchors[body], self.centre_attitudes[body],
                        self.soft_tissue(body, cells), beside, at_rest)

    def soft_tissue(self, body: int, cells: Sequence[tuple[int, int]]) -> SoftTissue | None:
        """The ligaments acting on `body` along a chain, each cell's other bodies where they
        were settled there; None without ligaments (or with the patent's method, which has
        no soft tissue)."""
        layout = self.layouts[body]
        if layout is None:
            return None
        config, deps = self.config, self.depends[body]
        placed = np.array([[self.poses[d, f, v] for d in deps] for f, v in cells]) \
            if deps else np.zeros((len(cells), 0, 4, 4))
        return SoftTissue(layout, config.reference.name,
                          tuple(config.bodies[d].name for d in deps), placed)

    def chains(self) -> list[_Chain]:
        """Every chain of the sweep, in the order they should run when several can (module
        docstring): the centre cells, the spines' segments, the ribs by flexion."""
        nf, nv = len(self.config.flexion_rad), len(self.config.varus_rad)
        f0, v0 = self.f0, self.v0
        bodies = range(len(self.config.bodies))

        def pulled_from(b: int, cells: Sequence[tuple[int, int]]) -> list[Cell]:
            return [(d, f, v) for d in self.depends[b] for f, v in cells]

        out = [_Chain('centre', b, ((f0, v0),), tuple(pulled_from(b, [(f0, v0)])))
               for b in bodies]
        for b in bodies:
            for side in _outward(nf, f0):
                seed = f0
                for i in range(0, len(side), SPINE_SEGMENT):
                    cells = tuple((f, v0) for f in side[i:i + SPINE_SEGMENT])
                    out.append(_Chain('spine', b, cells,
                                      ((b, seed, v0), *pulled_from(b, cells))))
                    seed = cells[-1][0]
        for f in range(nf):
            for b in bodies:
                if self.varus_free[b]:
                    continue
                for side in _outward(nv, v0):
                    if side:
                        cells = tuple((f, v) for v in side)
                        beside = [(b, g, v) for g in ribs_beside(f, f0, nf) for v in side]
                        out.append(_Chain('rib', b, cells,
                                          ((b, f, v0), *beside, *pulled_from(b, cells))))
        return out

    def changes_beside(self, body: int, f: int, cells: Sequence[tuple[int, int]]
                       ) -> Floats | None:
        """(n, 4, 4) for each of the rib at `f`'s `cells`, the mean change of rest the ribs
        beside it made over the same varus step (from the spine for the first), at the
        cell's attitude (`mean_change`); NaN where no rib beside converged at both ends of
        the step. None: the rib learns from no rib beside it."""
        beside = ribs_beside(f, self.f0, len(self.config.flexion_rad))
        if not beside:
            return None
        out = np.full((len(cells), 4, 4), np.nan)
        before = self.v0
        poses, attitudes = self.poses[body], self.attitudes[body]
        for i, (_, v) in enumerate(cells):
            steps = [(poses[g, before], attitudes[g, before], poses[g, v], attitudes[g, v])
                     for g in beside
                     if self.converged[body, g, before] and self.converged[body, g, v]]
            if steps:
                out[i] = mean_change(steps, attitudes[f, v])
            before = v
        return out

    def job_for(self, chain: _Chain) -> ChainJob:
        """The job of `chain`, whose `after` cells are settled: a centre cell from its cold
        start, a spine segment from the last rest of the spine before it (the centre's
        pose when none converged), a rib from its spine cell."""
        config, b = self.config, chain.body
        spec, (f, v) = config.bodies[b], chain.cells[0]
        flex, var = config.flexion_rad, config.varus_rad
        if chain.kind == 'centre':
            a0 = self.centre_attitudes[b]
            return self.job(b, chain.cells, cold_start(a0, config.params(spec, flex[f],
                                                                         var[v])), a0,
                            at_rest=False)
        if chain.kind == 'spine':
            step = 1 if f > self.f0 else -1
            for g in range(f - step, self.f0, -step):       # nearest first
                if self.converged[b, g, self.v0]:
                    return self.job(b, chain.cells, self.poses[b, g, self.v0],
                                    self.attitudes[b, g, self.v0])
            return self.job(b, chain.cells, self.poses[b, self.f0, self.v0],
                            self.centre_attitudes[b],
                            at_rest=bool(self.converged[b, self.f0, self.v0]))
        return self.job(b, chain.cells, self.poses[b, f, self.v0],
                        self.attitudes[b, f, self.v0], self.changes_beside(b, f, chain.cells))

    def take(self, res: ChainResult) -> list[Cell]:
        """Put a finished chain's cells in place; return the cells now settled (with a
        body that ignores varus, its rows copied across varus)."""
        flex, var = self.config.flexion_rad, self.config.varus_rad
        b, nv = res.body, len(var)
        settled: list[Cell] = []
        for k, (f, v) in enumerate(res.cells):
            self.poses[b, f, v] = res.poses[k]
            self.converged[b, f, v] = res.converged[k]
            self.iterations[b, f, v] = res.iterations[k]
            self.status[b, f, v] = res.status[k]
            self.backed[b, f, v] = res.backed_out_m[k]
            if not res.converged[k] and len(self.failures) < 5:
                self.failures.append(
                    f'{self.config.bodies[b].name} flexion {math.degrees(flex[f]):g} '
                    f'varus {math.degrees(var[v]):g}: {res.reasons[k]}')
            if (f, v) == (self.f0, self.v0) and res.converged[k]:
                # every other cell's envelope is measured from the centre rest, carried
                self.anchors[b] = res.poses[k]
            if self.varus_free[b]:
                for cells in (self.poses, self.converged, self.iterations, self.status,
                              self.backed):
                    cells[b, f] = cells[b, f, v]
                settled.extend((b, f, w) for w in range(nv))
            else:
                settled.append((b, f, v))
        self.checks += res.collision_checks
        self.travels += res.travels
        self.fcl += res.fcl_checks
        self.chains_s += res.elapsed_s
        if self.progress:                 # a copy across varus is cells of the table too
            self.progress(len(settled))
        return settled

    def result(self, wall_s: float) -> SweepResult:
        """Everything in table layout."""
        return SweepResult(self.poses[..., :3, 3].copy(),
                           quat_from_matrix(self.poses[..., :3, :3]), self.converged,
                           self.iterations, self.status, self.checks, wall_s,
                           self.scene.mesh_sha256, self.anchors, (self.f0, self.v0),
                           self.backed, tuple(self.failures), self.travels, self.fcl,
                           self.scene_s, self.chains_s)
