"""From a knee config to a table: sweep it, package the result with its provenance, write it.

`make_table` turns a `SweepResult` into a `PoseTable` whose metadata records where every
number came from (meshes and their SHA-256, the config as read and as resolved, the settle
parameters, each cell's status, the continuity summary, each body's envelope anchor);
`build_table` sweeps and writes it atomically; `summary_line` and `backed_out_lines` are
what `kneeseat build` prints of it.
"""
from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import asdict
from datetime import datetime, timezone
import logging
import math
from pathlib import Path
import sys
from typing import Any

import numpy as np
from tqdm import tqdm

from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import quat_from_matrix
from kneeseat_core.knee import BodySpec, KneeConfig
from kneeseat_core.status import converged_share, Status, STATUS_NAMES
from kneeseat_core.table import PoseTable, write_table
from .continuity import continuity
from .phases import sweep, SweepResult

__all__ = ['make_table', 'build_table', 'summary_line', 'queries_per_cell', 'backed_out_lines']

log = logging.getLogger(__name__)


def make_table(config: KneeConfig, result: SweepResult) -> PoseTable:
    """Package a sweep result and its provenance as a `PoseTable`.

    Each body's metadata keeps `mesh`/`mesh_sha256` (its first collision mesh, as tables
    always had) and lists every mesh in `meshes` and `display_meshes` ([{path, sha256}]).
    """
    hashes = iter(result.mesh_sha256)   # taken by the sweep before it settled anything

    def body_meta(spec: BodySpec) -> dict[str, Any]:
        meshes = [{'path': str(m), 'sha256': next(hashes)} for m in spec.meshes]
        return {'name': spec.name, 'frame': spec.frame, 'mesh': meshes[0]['path'],
                'mesh_sha256': meshes[0]['sha256'], 'meshes': meshes,
                'display_mesh': None if spec.display_mesh is None else str(spec.display_mesh),
                'display_meshes': [{'path': str(m), 'sha256': file_sha256(m)}
                                   for m in spec.display_meshes]}

    f0, v0 = result.anchor_cell
    reference = body_meta(config.reference)      # hashes in order: reference, then bodies
    bodies = [body_meta(b) for b in config.bodies]
    for entry, anchor in zip(bodies, result.anchors):
        # where every cell's search envelope is measured from (kneeseat_core.sweep.chains)
        entry['envelope_anchor'] = {
            'flexion_deg': math.degrees(config.flexion_rad[f0]),
            'varus_deg': math.degrees(config.varus_rad[v0]),
            'position': anchor[:3, 3].tolist(),
            'orientation': quat_from_matrix(anchor[:3, :3]).tolist()}
    metadata = {
        'name': config.name,
        'reference': reference,
        'bodies': bodies,
        'axes': {'flexion': config.axes.flexion.tolist(), 'varus': config.axes.varus.tolist(),
                 'long': config.axes.long.tolist()},
        'config': config.metadata(),
        # push and locked slide are per body and per cell, not settle parameters
        'settle': {k: v for k, v in asdict(config.settle).items()
                   if k not in ('push', 'locked_slide')},
        'built': datetime.now(timezone.utc).isoformat(timespec='seconds'),
        # the sweep's wall time, of it the bodies built first (`scene_s`), and the chains'
        # own times summed over the workers (`chains_s`: how busy they were)
        'summary': {'cells': result.cells, 'converged': int(result.converged.sum()),
                    'wall_s': round(result.wall_s, 3), 'scene_s': round(result.scene_s, 3),
                    'chains_s': round(result.chains_s, 3),
                    'collision_checks': int(result.collision_checks),
                    'travels': int(result.travels), 'fcl_queries': int(result.fcl_checks)},
        'failures': list(result.failures),
        # how each cell's settle ended (codes: kneeseat_core.status.Status)
        'cells': {'status_names': {str(k): v for k, v in STATUS_NAMES.items()},
                  'status': np.asarray(result.status).tolist()},
        'continuity': continuity(result.position_m, result.orientation_xyzw, result.converged,
                                 config.flexion_rad, config.varus_rad,
                                 [b.name for b in config.bodies], config.attitudes()),
        'backed_out': _backed_out(config, result),
        'soft_tissue': _soft_tissue(config),
    }
    return PoseTable(config.flexion_rad, config.varus_rad, result.position_m,
                     result.orientation_xyzw, result.converged, result.iterations, metadata)


def _soft_tissue(config: KneeConfig) -> dict[str, Any] | None:
    """The ligament set (its file and SHA-256) and each body's load: what the rest of each
    cell was a maximum of (None: geometry alone, the travel)."""
    ligaments = config.ligaments
    if ligaments is None:
        return None
    return {'ligaments': {'source': ligaments.source, 'sha256': ligaments.sha256,
                          'fibres': len(ligaments.fibres), 'bundles': list(ligaments.bundles)},
            'loads': {b.name: {'load_n': b.load_n, 'load_toward': b.load_toward,
                               'fibres': len(ligaments.acting_on(b.name,
                                                                 config.placed_before(b)))}
                      for b in config.bodies},
            'method': config.settle.method}


def _backed_out(config: KneeConfig, result: SweepResult) -> dict[str, Any]:
    """Per body: cells whose start was in collision and backed out along -push, and how far."""
    out: dict[str, Any] = {}
    for b, spec in enumerate(config.bodies):
        moved = result.backed_out_m[b][result.backed_out_m[b] > 0.0]
        out[spec.name] = {'cells': int(moved.size),
                          'max_mm': round(float(moved.max()) * 1e3, 3) if moved.size else 0.0}
    return out


def backed_out_lines(table: PoseTable) -> list[str]:
    """One line per body whose start was in collision at some cells (build summary)."""
    lines = []
    for name, entry in (table.metadata.get('backed_out') or {}).items():
        if entry.get('cells'):
            lines.append(f'  {name}: the start was in collision at {entry["cells"]} cells '
                         f'(up to {entry["max_mm"]:g} mm deep); each was backed out along '
                         'the push before settling')
    return lines


def build_table(config: KneeConfig, out: Path, executor: Executor,
                show_progress: bool = True) -> PoseTable:
    """Sweep `config` on `executor` and write the table to `out` (atomically).

    Ctrl-C stops the sweep and leaves no table file.
    """
    total = len(config.bodies) * len(config.flexion_rad) * len(config.varus_rad)
    with tqdm(total=total, unit='cell', desc=config.name, disable=not show_progress,
              dynamic_ncols=True, file=sys.stderr) as bar:
        result = sweep(config, executor, progress=bar.update)
    table = make_table(config, result)
    write_table(out, table)
    return table


def queries_per_cell(s: dict[str, Any]) -> str:
    """The summary's queries per cell: exact travels and python-fcl queries (tables built
    before the exact travel: collision checks, and ray casts where there were any)."""
    cells = max(s['cells'], 1)
    if 'travels' in s:
        return (f'{s["travels"] / cells:.1f} exact travels and '
                f'{s["fcl_queries"] / cells:.1f} python-fcl queries per cell')
    return (f'{s["collision_checks"] / cells:.0f} collision checks per cell'
            + (f', {s["ray_casts"] / cells:.0f} ray casts per cell' if s.get('ray_casts') else ''))


def summary_line(table: PoseTable, out: Path) -> str:
    """One-paragraph summary of a finished build."""
    s = table.metadata['summary']
    per_body = ', '.join(
        f'{name} {converged_share(int(table.converged[i].sum()), table.converged[i].size)}'
        for i, name in enumerate(table.bodies))
    line = (f'{out}: {s["cells"]} cells, {converged_share(s["converged"], s["cells"])} '
            f'converged ({per_body}), {s["wall_s"]:.1f} s wall, '
            f'{s["cells"] / max(s["wall_s"], 1e-9):.1f} cells/s, ' + queries_per_cell(s))
    cont = table.metadata.get('continuity')
    if isinstance(cont, dict):
        over = sum(sum(b['pairs_over_bound'].values()) for b in cont['bodies'].values())
        line += (f'; {over} neighbour pairs over {cont["bound_mm"]:g} mm / '
                 f'{cont["bound_deg"]:g} deg, {len(cont["branch_changes"])} of them branch '
                 'changes between cells at rest')
    tissue = table.metadata.get('soft_tissue')
    if isinstance(tissue, dict):
        lig = tissue['ligaments']
        loads = ', '.join(f'{name} {entry["load_n"]:g} N ({entry["fibres"]} fibres)'
                          for name, entry in tissue['loads'].items()
                          if entry.get('load_n') is not None)
        pulled = int(np.sum(np.asarray(table.metadata['cells']['status']) == Status.PULLED))
        line += (f'; ligaments: {lig["fibres"]} fibres from {Path(lig["source"]).name} '
                 f'(sha256 {lig["sha256"][:12]}), loads {loads}'
                 + (f', {pulled} cells pulled off by them' if pulled else '')
                 + ('; the patent method ignores them' if tissue.get('method') == 'patent'
                    else ''))
    return line
