"""What `kneeseat info`, `lookup --json` and `export` show of a table.

`describe` (and `status_map`) summarise a table for people; `lookup_json` is one lookup as
JSON; `export_csv` writes one row per (body, flexion, varus) with the patent's six fields.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np

from kneeseat_core.errors import TableError
from kneeseat_core.files import write_bytes
from kneeseat_core.geometry import matrix_from_quat, TOL
from kneeseat_core.status import converged_share, Status, STATUS_NAMES
from kneeseat_core.typed import Floats
from .format import mesh_entries
from .pose_table import Lookup, PoseTable

__all__ = ['describe', 'status_map', 'lookup_json', 'export_csv', 'write_text', 'CSV_COLUMNS']

CSV_COLUMNS = ('body', 'flexion_deg', 'varus_deg', 'x_m', 'y_m', 'z_m', 'flexion_rot_deg',
               'varus_rot_deg', 'long_rot_deg', 'converged', 'iterations')


def _grid_text(values_rad: Floats) -> str:
    deg = np.degrees(np.asarray(values_rad, dtype=np.float64))
    if deg.size == 1:
        return f'{deg[0]:g} deg (1 value)'
    steps = np.diff(deg)
    if np.allclose(steps, steps[0], rtol=TOL.grid_uniform, atol=TOL.grid_uniform):
        step = f'step {steps[0]:g}'
    else:
        step = f'non-uniform steps {steps.min():g} to {steps.max():g}'
    return f'{deg[0]:g} to {deg[-1]:g} deg, {step}, {deg.size} values'


def describe(table: PoseTable) -> str:
    """Human summary of a table for `kneeseat info` (several lines, no trailing newline)."""
    meta = table.metadata
    ref = meta.get('reference', {})
    lines = [f'schema:     {meta.get("schema", "?")} '
             f'(kneeseat {meta.get("kneeseat_version", "?")})',
             f'built:      {meta.get("built", "?")}',
             f'arrays:     sha256 {str(meta.get("arrays_sha256", "?"))[:12]}',
             f'reference:  {ref.get("name", "?")} (frame {ref.get("frame", "?")}, '
             f'{_meshes_text(ref)})',
             f'flexion:    {_grid_text(table.flexion_rad)}',
             f'varus:      {_grid_text(table.varus_rad)}']
    axes = meta.get('axes')
    if isinstance(axes, dict):
        lines.append('axes:       ' + ', '.join(
            f'{k} {np.round(np.asarray(axes[k], dtype=float), 4).tolist()}'
            for k in ('flexion', 'varus', 'long') if k in axes))
    lines.append(f'bodies:     {len(table.bodies)}')
    conv = np.asarray(table.converged, dtype=bool)
    iters = np.asarray(table.iterations)
    for b, body in enumerate(meta['bodies']):
        c = conv[b]
        lines.append(f'  {body["name"]}: frame {body["frame"]}, {_meshes_text(body)}')
        lines.append(f'    converged {converged_share(int(c.sum()), c.size)} '
                     f'({int(c.sum())}/{c.size}), '
                     f'iterations median {float(np.median(iters[b])):g} max {int(iters[b].max())}')
        backed = _mapping(_mapping(meta.get('backed_out')).get(body['name']))
        if backed.get('cells'):
            lines.append(f'    start in collision (backed out along the push) at '
                         f'{backed["cells"]} cells, up to {backed.get("max_mm", "?")} mm')
    settle = meta.get('settle')
    if isinstance(settle, dict) and settle:
        lines.append('settle:     ' + ', '.join(f'{k}={v}' for k, v in settle.items()))
    tissue = _mapping(meta.get('soft_tissue'))
    if tissue:
        lig = _mapping(tissue.get('ligaments'))
        lines.append(f'ligaments:  {lig.get("fibres", "?")} fibres in '
                     f'{len(lig.get("bundles", []))} bundles from {lig.get("source", "?")} '
                     f'(sha256 {str(lig.get("sha256", "?"))[:12]}); loads: ' + ', '.join(
                         f'{name} {_mapping(e).get("load_n")} N'
                         for name, e in _mapping(tissue.get('loads')).items()))
    summary = meta.get('summary')
    if isinstance(summary, dict) and summary:
        lines.append('summary:    ' + ', '.join(f'{k}={v}' for k, v in summary.items()))
    lines += _status_lines(table) + _continuity_lines(meta.get('continuity'))
    return '\n'.join(lines)


def _status_lines(table: PoseTable, listed: int = 5) -> list[str]:
    """Cells by how their settle ended; the first few cells that did not converge."""
    codes, conv = table.status, np.asarray(table.converged, dtype=bool)
    deg_f, deg_v = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
    lines = ['cells:']
    for b, name in enumerate(table.bodies):
        counts = np.bincount(codes[b].ravel(), minlength=len(STATUS_NAMES))
        lines.append(f'  {name}: ' + ', '.join(f'{int(n)} {STATUS_NAMES.get(k, str(k))}'
                                               for k, n in enumerate(counts) if n))
        bad = np.argwhere(~conv[b])
        for i, j in bad[:listed]:
            lines.append(f'    not converged at flexion {deg_f[i]:g} varus {deg_v[j]:g}: '
                         f'{STATUS_NAMES.get(int(codes[b, i, j]), "?")}')
        if len(bad) > listed:
            lines.append(f'    ... and {len(bad) - listed} more (kneeseat info --map)')
    return lines


def _continuity_lines(cont: Any, listed: int = 5) -> list[str]:
    """The continuity summary a build stored (kneeseat_core.sweep.continuity)."""
    if not isinstance(cont, dict) or not isinstance(cont.get('bodies'), dict):
        return []

    def between(pair: Any) -> str:
        if not pair:
            return ''
        (fa, va), (fb, vb) = pair
        return f' (flexion {fa:g} varus {va:g} -> flexion {fb:g} varus {vb:g})'

    lines = [f'continuity: neighbour steps, bound {cont.get("bound_mm", "?")} mm / '
             f'{cont.get("bound_deg", "?")} deg']
    for name, entry in cont['bodies'].items():
        pos, rot = entry.get('max_position_mm', {}), entry.get('max_rotation_deg', {})
        over = entry.get('pairs_over_bound', {})
        lines.append(f'  {name}: largest {pos.get("value", 0):.3f} mm{between(pos.get("between"))}'
                     f', {rot.get("value", 0):.3f} deg{between(rot.get("between"))}; pairs over '
                     f'the bound: flexion {over.get("flexion", 0)}, varus {over.get("varus", 0)}')
    changes = cont.get('branch_changes') or []
    lines.append(f'  branch changes (pairs over the bound, both cells at rest): {len(changes)}')
    for change in changes[:listed]:
        lines.append(f'    {change["body"]}{between(change["between"])}: '
                     f'{change["position_mm"]:.3f} mm, {change["rotation_deg"]:.3f} deg')
    if len(changes) > listed:
        lines.append(f'    ... and {len(changes) - listed} more (in the metadata)')
    return lines


def status_map(table: PoseTable) -> str:
    """A character map of every body's cells (rows flexion, columns varus) by status."""
    marks = {Status.REST: '.', Status.CONSTRAINED: 'c', Status.ENVELOPE: 'E', Status.LOST: 'L',
             Status.CAP: 'I', Status.WEDGED: 'W', Status.FAILED: 'F', Status.UNKNOWN: '?'}
    codes = table.status
    deg_f, deg_v = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
    legend = ', '.join(f'{m} {STATUS_NAMES[k]}' for k, m in marks.items())
    lines = [f'map: rows flexion, columns varus {deg_v[0]:g} to {deg_v[-1]:g} deg; {legend}']
    for b, name in enumerate(table.bodies):
        lines.append(f'{name}:')
        for i in range(codes.shape[1]):
            lines.append(f'{deg_f[i]:8g} ' + ''.join(marks.get(int(c), '?') for c in codes[b, i]))
    return '\n'.join(lines)


def _mapping(value: Any) -> dict[str, Any]:
    """`value` if it is a dict, else {} (optional metadata written by newer builds)."""
    return value if isinstance(value, dict) else {}


def _meshes_text(entry: dict[str, Any]) -> str:
    """'mesh PATH (sha256 HEX)' or 'meshes A (sha256 ..), B (..)' of a metadata entry."""
    files = mesh_entries(entry)
    text = ', '.join(f'{path} (sha256 {sha[:12] or "?"})' for path, sha in files)
    return f'mesh{"es" if len(files) > 1 else ""} {text}'


def lookup_json(table: PoseTable, lookup: Lookup, flexion_rad: float | None = None,
                varus_rad: float | None = None) -> dict[str, Any]:
    """JSON-ready dict of one lookup for `kneeseat lookup --json`.

    Shape: {"reference_frame", "table_sha256", "clamped", ["flexion_rad", "varus_rad"],
    "bodies": [{"name", "frame", "position" [3] m, "orientation" [x, y, z, w],
    "nonconverged"}]}. The request angles are included when given.
    """
    out: dict[str, Any] = {'reference_frame': table.reference_frame,
                           'table_sha256': table.metadata.get('arrays_sha256'),
                           'clamped': bool(lookup.clamped)}
    if flexion_rad is not None:
        out['flexion_rad'] = float(flexion_rad)
    if varus_rad is not None:
        out['varus_rad'] = float(varus_rad)
    out['bodies'] = [
        {'name': name, 'frame': frame, 'position': [float(x) for x in lookup.position_m[b]],
         'orientation': [float(x) for x in lookup.orientation_xyzw[b]],
         'nonconverged': bool(lookup.nonconverged[b])}
        for b, (name, frame) in enumerate(zip(table.bodies, table.body_frames))]
    return out


def export_csv(table: PoseTable, path: Path) -> None:
    """Write one CSV row per (body, flexion, varus), atomically.

    Columns `CSV_COLUMNS`: body, grid flexion and varus (deg), then the patent's six fields:
    the body's position x, y, z (m, reference frame) and its absolute orientation decomposed
    with the table's axes (`KneeAxes.decompose`) into angles about the flexion, varus and
    long axes (deg); then converged (true/false) and iterations.

    Raises:
        TableError: the file cannot be written (nothing is left behind).
    """
    path = Path(path)
    pos = np.asarray(table.position_m, dtype=np.float64)
    rot = matrix_from_quat(np.asarray(table.orientation_xyzw, dtype=np.float64))
    angles = np.degrees(np.stack(table.axes.decompose(rot), axis=-1))   # (B, F, V, 3)
    fdeg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64))
    vdeg = np.degrees(np.asarray(table.varus_rad, dtype=np.float64))
    conv = np.asarray(table.converged, dtype=bool)
    iters = np.asarray(table.iterations)
    text = io.StringIO()
    writer = csv.writer(text, lineterminator='\n')
    writer.writerow(CSV_COLUMNS)
    for b, name in enumerate(table.bodies):
        for i, fd in enumerate(fdeg.tolist()):
            for j, vd in enumerate(vdeg.tolist()):
                writer.writerow([name, f'{fd:.12g}', f'{vd:.12g}',
                                 *(f'{x:.12g}' for x in pos[b, i, j].tolist()),
                                 *(f'{x:.12g}' for x in angles[b, i, j].tolist()),
                                 'true' if conv[b, i, j] else 'false', int(iters[b, i, j])])
    write_text(path, text.getvalue(), 'CSV ')


def write_text(out: Path, text: str, what: str = '') -> Path:
    """Write a report's `text` to `out` atomically (`kneeseat_core.files.write_bytes`);
    `what` names the kind of file in the error ('CSV ').

    Raises:
        TableError: the file cannot be written (nothing is left behind).
    """
    try:
        write_bytes(Path(out), text.encode())
    except OSError as err:
        raise TableError(f'cannot write {what}{out}: {err.strerror or err}; check that the '
                         'directory exists, is writable and has free space') from err
    return Path(out)
