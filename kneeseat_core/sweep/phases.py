"""The range-of-motion sweep: settle every grid attitude, warm-started, in parallel chains.

Order (the patent's warm start, made parallel):
1. the *centre* cell of each moving body (flexion and varus nearest 0) from its cold start;
2. a *spine* per body: the flexion values at the varus nearest 0, settled outward from the
   centre, each cell from its neighbour's equilibrium;
3. a *rib* per (body, flexion value, side): the varus values settled outward from the spine
   cell, each from its neighbour's equilibrium.
Each phase runs its chains (`kneeseat_core.sweep.chains`) in parallel (across bodies, then
across flexion values and sides) on any `concurrent.futures.Executor`
(`kneeseat_core.sweep.executors`). A body whose attitude ignores varus (`varus_fraction:
0`, e.g. a patella) is settled on its spine only and copied across varus, unless its
ligaments pull from a body that feels varus.

A body whose ligaments pull from another moving body (a patella's tendon from the tibia)
is swept after that body, in a later *wave*: at each cell its fibres are attached to the
other body as it was settled there. That neglects the pull of those fibres on the body
settled first (the tendon's on the tibia); docs/design.md says what it changes.

Why ribs along varus rather than columns along flexion: where a body rests on one contact
only (a tibia tilted by a commanded varus bears on one condyle), its spin about the push
is free - no move gains depth - and a settle keeps the spin it starts with. Ribs carry the
spin that the spine's two-contact rests determine at each flexion out to every varus
value, so varus neighbours agree; independent flexion columns each kept their own spin
and disagreed by up to 2.6 deg (docs/tables.md).

The parent validates every mesh once before the sweep (warnings such as an open cartilage
sheet appear once per mesh), so workers load quietly.
"""
from __future__ import annotations

from concurrent.futures import as_completed, Executor, Future
from dataclasses import dataclass, field
import math
from pathlib import Path
import time
from typing import Callable, Iterable, Sequence

import numpy as np

from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import quat_from_matrix, TOL
from kneeseat_core.knee import KneeConfig, neutral_pose
from kneeseat_core.meshes import check_mesh_files
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .chains import ChainJob, ChainResult, cold_start, run_chain, SoftTissue
from .scene import SceneSpec

__all__ = ['SweepResult', 'sweep']


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
    ray_casts: int = 0              # casts of the travel by rays (settle parameter `travel`)

    @property
    def cells(self) -> int:
        """Number of (body, flexion, varus) cells."""
        return int(self.converged.size)


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
    for wave in run.waves():
        run.collect([executor.submit(run_chain, j) for j in run.centre_jobs(wave)])
        run.anchor_at_centres(wave)
        run.collect([executor.submit(run_chain, j) for j in run.spine_jobs(wave)])
        run.collect([executor.submit(run_chain, j) for j in run.rib_jobs(wave)])
        run.copy_across_varus(wave)
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
        self.casts = 0
        self.centre_attitudes = [config.attitude(spec, flex[self.f0], var[self.v0])
                                 for spec in config.bodies]
        self.anchors = np.array([neutral_pose(a0) for a0 in self.centre_attitudes])
        self.depends = [config.depends_on(b) for b in config.bodies]
        # settled once per flexion value and copied across varus: a body that ignores varus
        # and whose ligaments pull from no body that feels it
        self.varus_free: list[bool] = []
        for b, spec in enumerate(config.bodies):
            self.varus_free.append(abs(spec.varus_fraction) < TOL.fraction
                                   and all(self.varus_free[d] for d in self.depends[b]))

    def waves(self) -> list[list[int]]:
        """The bodies in waves: each after the bodies its ligaments pull from (the config
        lists a body after those, `KneeConfig.placed_before`)."""
        wave_of: list[int] = []
        for deps in self.depends:
            wave_of.append(1 + max((wave_of[d] for d in deps), default=-1))
        return [[b for b, w in enumerate(wave_of) if w == k]
                for k in range(max(wave_of) + 1)]

    def job(self, body: int, cells: Sequence[tuple[int, int]], start: Pose,
            start_attitude: Floats) -> ChainJob:
        """The chain of `cells` of `body`, from `start` (settled at `start_attitude`)."""
        config, flex, var = self.config, self.config.flexion_rad, self.config.varus_rad
        spec = config.bodies[body]
        return ChainJob(self.scene, body, tuple(cells),
                        np.array([config.attitude(spec, flex[f], var[v]) for f, v in cells]),
                        tuple(config.params(spec, flex[f], var[v]) for f, v in cells),
                        start, start_attitude, self.anchors[body], self.centre_attitudes[body],
                        self.soft_tissue(body, cells))

    def soft_tissue(self, body: int, cells: Sequence[tuple[int, int]]) -> SoftTissue | None:
        """The ligaments acting on `body` along a chain, each cell's other bodies where they
        were settled there; None without ligaments (or with the patent's method, which has
        no soft tissue)."""
        config, spec = self.config, self.config.bodies[body]
        ligaments = config.ligaments
        if ligaments is None or config.settle.method == 'patent' or \
                not ligaments.acting_on(spec.name, config.placed_before(spec)):
            return None
        deps = self.depends[body]
        placed = np.array([[self.poses[d, f, v] for d in deps] for f, v in cells]) \
            if deps else np.zeros((len(cells), 0, 4, 4))
        return SoftTissue(ligaments, spec.name, config.reference.name,
                          tuple(config.bodies[d].name for d in deps), placed)

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
            self.casts += res.ray_casts
            if self.progress:
                self.progress(len(res.cells))

    def centre_jobs(self, wave: list[int]) -> list[ChainJob]:
        """1. Each body's centre cell, from its cold start."""
        config, f0, v0 = self.config, self.f0, self.v0
        jobs = []
        for b in wave:
            spec = config.bodies[b]
            a0 = self.centre_attitudes[b]
            params = config.params(spec, config.flexion_rad[f0], config.varus_rad[v0])
            jobs.append(self.job(b, [(f0, v0)], cold_start(a0, params), a0))
        return jobs

    def anchor_at_centres(self, wave: list[int]) -> None:
        """Every other cell's envelope is measured from the centre rest, carried."""
        for b in wave:
            if self.converged[b, self.f0, self.v0]:
                self.anchors[b] = self.poses[b, self.f0, self.v0]

    def spine_jobs(self, wave: list[int]) -> list[ChainJob]:
        """2. Spines: varus v0, flexion outward from f0, from the centre rest."""
        config, f0, v0 = self.config, self.f0, self.v0
        jobs = []
        for b in wave:
            for side in _outward(len(config.flexion_rad), f0):
                if side:
                    jobs.append(self.job(b, [(f, v0) for f in side], self.poses[b, f0, v0],
                                         self.centre_attitudes[b]))
        return jobs

    def rib_jobs(self, wave: list[int]) -> list[ChainJob]:
        """3. Ribs: every flexion value of a body that feels varus, varus outward from the
        spine cell."""
        config, v0 = self.config, self.v0
        jobs = []
        for b in wave:
            spec = config.bodies[b]
            if self.varus_free[b]:
                continue
            for f in range(len(config.flexion_rad)):
                for side in _outward(len(config.varus_rad), v0):
                    if side:
                        jobs.append(self.job(b, [(f, v) for v in side], self.poses[b, f, v0],
                                             config.attitude(spec, config.flexion_rad[f],
                                                             config.varus_rad[v0])))
        return jobs

    def copy_across_varus(self, wave: list[int]) -> None:
        """A body that ignores varus: its spine, copied to every varus value."""
        nf, nv, v0 = len(self.config.flexion_rad), len(self.config.varus_rad), self.v0
        for b in wave:
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
                           self.backed, tuple(self.failures), self.casts)
