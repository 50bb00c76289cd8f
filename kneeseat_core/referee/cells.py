"""The referee's verdicts on the cells of a table (what `kneeseat verify TABLE` reports).

`sample_cells` picks the cells a table claims at rest (all, or N spread over the grid: every
body's four corners, then a seeded shuffle of the rest); `verify_table` judges them on an
executor: each worker rebuilds the cell's problem from the table's own record of its config
(push, locked slide, envelope and its anchor, the load and the ligaments placed by the
table's own poses of the other bodies) and climbs the objective from the stored pose with
the referee (`kneeseat_core.referee.judge`, which shares no code with the settle), then
measures how far the pose can move while the objective stays within one resolution of
the best it found (how well the rest is determined). A cell that did not converge claims
nothing and is not judged. The search envelope bounds the referee only where it holds
(a body's own `envelope`): a claimed rest from which an ascent leaves the envelope is not
at rest.
"""
from __future__ import annotations

from concurrent.futures import as_completed, Executor
from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import trimesh

from kneeseat_core.errors import NoContactError, TableError
from kneeseat_core.geometry import carried, matrix_from_quat, pose_from, quat_angles
from kneeseat_core.knee import (BodySpec, config_from_metadata, KneeConfig,
                                ligaments_from_metadata, neutral_pose)
from kneeseat_core.ligaments import LigamentSet
from kneeseat_core.meshes import load_mesh, Units
from kneeseat_core.params import SettleParams
from kneeseat_core.status import AT_REST, STATUS_NAMES
from kneeseat_core.table import PoseTable, read_table
from kneeseat_core.typed import Pose
from .judge import Envelope, Load, Referee

__all__ = ['CellVerdict', 'sample_cells', 'changed_cells', 'verify_table', 'mesh_file',
           'body_load']


@dataclass(frozen=True, slots=True)
class CellVerdict:
    """The referee's verdict on one cell of a table."""

    body: str
    flexion_deg: float
    varus_deg: float
    status: int
    gain_m: float
    slide_m: float
    spin_deg: float
    queries: int
    extent_m: float | None = None       # how far the rest can slide within one resolution
    extent_deg: float | None = None     # ... and spin (None: not measured)

    @property
    def converged(self) -> bool:
        """The table claims this cell is at rest."""
        return self.status in AT_REST

    def line(self, resolution_m: float) -> str:
        """One human line."""
        where = f'{self.body} flexion {self.flexion_deg:g} varus {self.varus_deg:g}'
        state = STATUS_NAMES.get(self.status, str(self.status))
        if math.isinf(self.gain_m):
            found = 'climbs off the fixed body'
        else:
            found = (f'gains {self.gain_m * 1e3:.3f} mm by sliding {self.slide_m * 1e3:.2f} mm '
                     f'and turning {self.spin_deg:.2f} deg')
        verdict = ('at rest' if self.gain_m <= resolution_m else 'NOT AT REST') \
            if self.converged else 'not claimed at rest'
        extent = '' if self.extent_m is None else \
            (f'; within a resolution of its best it moves {self.extent_m * 1e3:.2f} mm and '
             f'{self.extent_deg:.2f} deg')
        return f'{where} ({state}): {found}: {verdict}{extent}'

    def as_json(self) -> dict[str, Any]:
        """JSON-ready dict (gain_m null when the referee climbs off the fixed body)."""
        return {'body': self.body, 'flexion_deg': self.flexion_deg,
                'varus_deg': self.varus_deg, 'status': STATUS_NAMES.get(self.status),
                'converged': self.converged,
                'gain_m': None if math.isinf(self.gain_m) else self.gain_m,
                'slide_m': self.slide_m, 'spin_deg': self.spin_deg, 'queries': self.queries,
                'extent_m': self.extent_m, 'extent_deg': self.extent_deg}


# ---- a table's cells ------------------------------------------------------------------
def _copied_across_varus(table: PoseTable, body: int) -> bool:
    """The body's cells are the same at every varus value (the sweep settled it once per
    flexion value and copied it)."""
    v0 = int(np.argmin(np.abs(table.varus_rad)))
    centre = table.position_m[body, :, v0:v0 + 1]
    return bool(np.array_equal(np.broadcast_to(centre, table.position_m[body].shape),
                               table.position_m[body]))


def sample_cells(table: PoseTable, count: int | None, seed: int = 20261201
                 ) -> list[tuple[int, int, int]]:
    """Cells (body, flexion index, varus index) to verify: the cells the table claims at
    rest (a cell that did not converge claims nothing; `kneeseat info` reports it).

    A body that ignores varus (copied across varus) is sampled on its centre column only.
    With `count`, every body's four corners come first (those at rest), then a seeded
    shuffle of its other cells at rest, taken in turn from each body, up to `count` cells.
    """
    nb, nf, nv = np.shape(table.converged)
    v0 = int(np.argmin(np.abs(table.varus_rad)))
    claimed = np.isin(table.status, AT_REST)
    per_body = []
    for b in range(nb):
        columns = [v0] if _copied_across_varus(table, b) else list(range(nv))
        cells = [(b, i, j) for i in range(nf) for j in columns if claimed[b, i, j]]
        if count is None:
            per_body.append(cells)
            continue
        corners = [c for c in dict.fromkeys((b, i, j) for i in (0, nf - 1)
                                            for j in (columns[0], columns[-1]))
                   if claimed[c]]
        rest = [c for c in cells if c not in corners]
        rng = np.random.default_rng(seed + b)
        per_body.append(corners + [rest[k] for k in rng.permutation(len(rest))])
        # (up to four corners lead each body's list; the rest follow shuffled)
    if count is None:
        return [c for cells in per_body for c in cells]
    picked = [c for cells in per_body for c in cells[:min(4, len(cells))]][:count]
    queues = [cells[4:] for cells in per_body]
    while len(picked) < count and any(queues):
        for queue in queues:
            if queue and len(picked) < count:
                picked.append(queue.pop(0))
    return sorted(picked)


def changed_cells(table: PoseTable, before: PoseTable, moved_m: float, turned_deg: float
                  ) -> tuple[list[tuple[int, int, int]], int]:
    """The cells (body, flexion index, varus index) that `table` claims at rest and whose
    pose differs from `before`'s by more than `moved_m` in position or more than
    `turned_deg` in orientation (a body copied across varus: its centre column only), and
    how many cells differ that way, claimed at rest or not.

    Raises:
        TableError: `before` has other bodies or another grid.
    """
    if (tuple(before.bodies) != tuple(table.bodies)
            or not np.array_equal(before.flexion_rad, table.flexion_rad)
            or not np.array_equal(before.varus_rad, table.varus_rad)):
        raise TableError(
            f'the table to compare with holds {", ".join(before.bodies)} on '
            f'{len(before.flexion_rad)} x {len(before.varus_rad)} cells, this one '
            f'{", ".join(table.bodies)} on {len(table.flexion_rad)} x {len(table.varus_rad)}; '
            'compare two tables of the same config and grid')
    moved = np.linalg.norm(np.asarray(table.position_m) - np.asarray(before.position_m), axis=-1)
    turned = np.degrees(quat_angles(table.orientation_xyzw, before.orientation_xyzw))
    differs = (moved > moved_m) | (turned > turned_deg)
    nb, _, nv = differs.shape
    v0 = int(np.argmin(np.abs(table.varus_rad)))
    claimed = np.isin(table.status, AT_REST)
    cells, count = [], 0
    for b in range(nb):
        columns = [v0] if _copied_across_varus(table, b) else list(range(nv))
        count += int(differs[b][:, columns].sum())
        cells += [(b, int(i), columns[int(k)])
                  for i, k in np.argwhere((differs[b] & claimed[b])[:, columns])]
    return cells, count


@dataclass(frozen=True, slots=True)
class _CellJob:
    table: str
    mesh_dir: str | None
    cells: tuple[tuple[int, int, int], ...]
    extent: bool = True


_WORKER_STATE: dict[str, Any] = {}


def mesh_file(path: Path, mesh_dir: str | None) -> str:
    """`path`, or the file of the same name in `mesh_dir` when one is given."""
    return str(Path(mesh_dir) / path.name) if mesh_dir else str(path)


def _meshes(spec: BodySpec, units: Units, mesh_dir: str | None) -> list[trimesh.Trimesh]:
    """A body's collision meshes, loaded quietly (the parent validated them once)."""
    return [load_mesh(mesh_file(p, mesh_dir), units, quiet=True) for p in spec.meshes]


def body_load(config: KneeConfig, ligaments: LigamentSet | None, params: SettleParams,
              spec: BodySpec, placed: Mapping[str, Pose]) -> Load | None:
    """The load and the fibres pulling on `spec`'s body, every point on another moving body
    placed by that body's pose in `placed` (name -> pose; the reference's points stay as
    given); None without ligaments or a load."""
    if ligaments is None or params.load_n is None:
        return None
    fibres = ligaments.acting_on(spec.name, config.placed_before(spec))
    if not fibres:
        return None
    paths = []
    for fibre in fibres:
        points = np.array(fibre.points, dtype=np.float64)
        on_body = np.array([name == spec.name for name in fibre.bodies])
        for n, name in enumerate(fibre.bodies):
            if name != spec.name and name != config.reference.name:
                pose = placed[name]
                points[n] = pose[:3, :3] @ points[n] + pose[:3, 3]
        paths.append((points, on_body))
    toward = None if params.load_toward is None else np.asarray(params.load_toward, dtype=float)
    return Load(float(params.load_n), toward, tuple(paths),
                np.array([f.slack_m for f in fibres]), np.array([f.stiffness_n for f in fibres]),
                np.array([f.transition for f in fibres]))


def _cell_load(config: KneeConfig, ligaments: LigamentSet | None, table: PoseTable,
               params: SettleParams, cell: tuple[int, int, int]) -> Load | None:
    """`body_load` at a cell, the other bodies placed by the table's own poses there."""
    b, i, j = cell
    placed = {body.name: pose_from(matrix_from_quat(table.orientation_xyzw[k, i, j]),
                                   table.position_m[k, i, j])
              for k, body in enumerate(config.bodies[:b])}
    return body_load(config, ligaments, params, config.bodies[b], placed)


def _cell_problem(config: KneeConfig, meta: dict[str, Any], body: int, flexion: float,
                  varus: float) -> tuple[SettleParams, Pose]:
    """The settle parameters (push, lock, envelope) and the envelope's anchor at a cell."""
    spec = config.bodies[body]
    attitude = config.attitude(spec, flexion, varus)
    anchor = neutral_pose(attitude)
    stored = meta['bodies'][body].get('envelope_anchor')
    if isinstance(stored, dict):          # the sweep's anchor: the centre rest, carried
        anchor = carried(pose_from(matrix_from_quat(np.asarray(stored['orientation'])),
                                   np.asarray(stored['position'])),
                         config.attitude(spec, math.radians(stored['flexion_deg']),
                                         math.radians(stored['varus_deg'])), attitude)
    return config.params(spec, flexion, varus), anchor


def _judge_cells(job: _CellJob) -> list[CellVerdict]:
    """Judge the cells of `job` (runs in a worker; tables and meshes cached per process)."""
    key = f'{job.table}|{job.mesh_dir}'
    if _WORKER_STATE.get('key') != key:
        loaded = read_table(Path(job.table))
        built = config_from_metadata(loaded.metadata)
        _WORKER_STATE.clear()
        _WORKER_STATE.update(
            key=key, table=loaded, config=built,
            ligaments=ligaments_from_metadata(
                loaded.metadata, None if job.mesh_dir is None else Path(job.mesh_dir)),
            fixed=_meshes(built.reference, built.units, job.mesh_dir),
            moving=[_meshes(b, built.units, job.mesh_dir) for b in built.bodies])
    table: PoseTable = _WORKER_STATE['table']
    config: KneeConfig = _WORKER_STATE['config']
    meta, codes = table.metadata, table.status
    out = []
    for b, i, j in job.cells:
        flexion, varus = float(table.flexion_rad[i]), float(table.varus_rad[j])
        params, anchor = _cell_problem(config, meta, b, flexion, varus)
        pose = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                         table.position_m[b, i, j])
        referee = Referee(_WORKER_STATE['fixed'], _WORKER_STATE['moving'][b],
                          np.asarray(params.push), params.resolution_m,
                          None if params.locked_slide is None else np.asarray(params.locked_slide),
                          load=_cell_load(config, _WORKER_STATE['ligaments'], table, params,
                                          (b, i, j)))
        # a search envelope bounds the settle, never the referee; one that holds bounds both
        envelope = Envelope(anchor, params.max_slide_m, params.max_spin_rad) \
            if params.envelope_holds else None
        extent_m = extent_deg = None
        try:
            verdict = referee.judge(pose, envelope)
            gain, slide, spin = verdict.gain_m, verdict.slide_m, math.degrees(verdict.spin_rad)
            if job.extent and gain <= params.resolution_m:
                extent = referee.extent(pose, referee.measure(verdict.best_pose)[0], envelope)
                extent_m, extent_deg = extent.slide_m, math.degrees(extent.spin_rad)
        except NoContactError:          # the stored pose has no contact along the push
            gain, slide, spin = math.inf, 0.0, 0.0
        out.append(CellVerdict(table.bodies[b], math.degrees(flexion), math.degrees(varus),
                               int(codes[b, i, j]), gain, slide, spin, referee.queries,
                               extent_m, extent_deg))
    return out


def verify_table(path: Path, cells: Sequence[tuple[int, int, int]], executor: Executor,
                 mesh_dir: Path | None = None, progress: Any = None,
                 extent: bool = True) -> Iterator[CellVerdict]:
    """Judge `cells` of the table at `path` on `executor`; yields verdicts as they finish.
    With `extent`, a cell at rest also says how far it can move within one resolution."""
    chunk = 2
    jobs = [_CellJob(str(path), None if mesh_dir is None else str(mesh_dir),
                     tuple(cells[k:k + chunk]), extent) for k in range(0, len(cells), chunk)]
    futures = [executor.submit(_judge_cells, job) for job in jobs]
    for fut in as_completed(futures):
        for verdict in fut.result():
            if progress is not None:
                progress(1)
            yield verdict
