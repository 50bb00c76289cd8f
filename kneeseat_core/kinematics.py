"""Secondary motions a table predicts at varus 0 against flexion (`kneeseat kinematics`).

What a settle finds besides the commanded flexion and varus: where the tibia and the
patella sit and how they turn. Each quantity follows the joint coordinate system of Grood
and Suntay (J Biomech Eng 1983): a flexion axis fixed in the femur (e1), a long axis fixed
in the moving bone (e3), and the floating axis e2 = e3 x e1 perpendicular to both. kneeseat's
attitude `R = Rot(flexion) Rot(varus) Rot(long, rotation)` is exactly that sequence, so the
angles are `KneeAxes.decompose` of the settled orientations.

Anatomical directions come from the table's axes, as every kneeseat config defines them:
anterior = the varus axis, superior = the long axis, lateral = varus x long for a right knee
(its opposite for a left one). Knee flexion is reported positive when flexed; kneeseat's
grids count flexion negative (the patent's 0 to -90), so it is minus the grid angle then.

Every quantity but patellar flexion is reported as its change from the first reported
angle (full extension by default); the rotations' own values there (relative to the meshes
as delivered) are kept in `KneeKinematics.at_first`.

Tibia (relative to the femur; translations of tibial landmarks in mm):
- `tibia_ap`: anterior(+)/posterior translation of the plateau centre along e2;
- `tibia_pd`: proximal(+)/distal translation along the tibial long axis e3 (+ = towards the
  femur, compression);
- `tibia_ml`: lateral(+)/medial translation along the femoral flexion axis e1;
- `tibia_ap_medial`, `tibia_ap_lateral`: `tibia_ap` of the medial and lateral plateau
  centres (a femoral condyle rolling back on its plateau is a negative value here);
- `tibia_ie` (deg): internal(+)/external rotation about e3.
  The plateau centre is measured from the femoral flexion axis (through the reference
  frame's origin), so that a pure flexion about that axis moves no translation.
Patella (relative to the femur, deg unless said):
- `patella_flexion`: rotation about e1, + = flexing with the knee;
- `patella_spin`: rotation about the floating (anterior) axis, + = distal pole lateral;
- `patella_tilt`: rotation about the patella's long axis, + = lateral tilt (the lateral
  border moves posteriorly, towards the femur);
- `patella_ml` (mm): lateral(+)/medial shift of the patellar landmark along e1, change from
  the first reported angle.
Landmarks (body frames): the plateau centre is the area centroid of the tibia's first
collision mesh (the tibial cartilage or insert); the medial and lateral centres are the
centroids of its parts on either side of that centre (the two cartilage sheets of a natural
knee); the patellar landmark is the centroid of the patella's first collision mesh.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
import csv
from dataclasses import dataclass
import io
import math
from pathlib import Path
from typing import Literal

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np
import trimesh

from .errors import ConfigError, MeshError, TableError
from .files import file_sha256, write_bytes
from .geometry import matrix_from_quat, TOL, unit
from .table import PoseTable
from .typed import Floats, Vec3

__all__ = ['QUANTITIES', 'DEFAULT_ANGLES_DEG', 'Landmarks', 'KneeKinematics', 'landmarks',
           'table_landmarks', 'knee_kinematics', 'kinematics_rows', 'kinematics_markdown',
           'write_kinematics_csv', 'write_text', 'read_reference', 'plot_kinematics']

Side = Literal['right', 'left']

# name -> (unit, label); the order is the order of tables and plots
QUANTITIES: dict[str, tuple[str, str]] = {
    'tibia_ap': ('mm', 'tibia anterior(+)/posterior'),
    'tibia_pd': ('mm', 'tibia proximal(+)/distal'),
    'tibia_ml': ('mm', 'tibia lateral(+)/medial'),
    'tibia_ie': ('deg', 'tibia internal(+)/external rotation'),
    'tibia_ap_medial': ('mm', 'medial plateau anterior(+)'),
    'tibia_ap_lateral': ('mm', 'lateral plateau anterior(+)'),
    'patella_flexion': ('deg', 'patellar flexion'),
    'patella_ml': ('mm', 'patella lateral(+)/medial shift'),
    'patella_tilt': ('deg', 'patellar lateral(+) tilt'),
    'patella_spin': ('deg', 'patellar spin, distal pole lateral(+)'),
}
DEFAULT_ANGLES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)


@dataclass(frozen=True, slots=True)
class Landmarks:
    """Landmark points (m) in their bodies' own frames; None where a body is absent."""

    tibia_centre: Vec3 | None = None
    tibia_medial: Vec3 | None = None
    tibia_lateral: Vec3 | None = None
    patella_centre: Vec3 | None = None


@dataclass(frozen=True, slots=True, eq=False)
class KneeKinematics:
    """Secondary motions at a list of knee flexion angles (one varus value)."""

    knee_flexion_deg: Floats             # (n,) positive = flexed
    varus_deg: float                     # the varus value used (grid value nearest 0)
    values: dict[str, Floats]            # quantity -> (n,), units as in QUANTITIES
    nonconverged: dict[str, Floats]      # 'tibia' / 'patella' -> (n,) bool
    at_first: dict[str, float]           # rotation -> its own value at the first angle (deg)


def _anatomy(table: PoseTable, side: Side) -> tuple[Vec3, Vec3, Vec3]:
    """(anterior, superior, lateral) unit vectors in the reference frame."""
    axes = table.axes
    anterior, superior = axes.varus, axes.long
    lateral = unit(np.cross(anterior, superior), 'lateral direction')
    if side not in ('right', 'left'):
        raise ConfigError(f"side={side!r} is not a knee side; use 'right' or 'left'")
    return anterior, superior, lateral if side == 'right' else -lateral


def landmarks(tibia_mesh: trimesh.Trimesh | None, patella_mesh: trimesh.Trimesh | None,
              lateral: Vec3) -> Landmarks:
    """Landmarks (module docstring) from the bodies' first collision meshes (m, own frame).

    Args:
        tibia_mesh: the tibia's first collision mesh, or None.
        patella_mesh: the patella's first collision mesh, or None.
        lateral: unit lateral direction in the tibia's frame at neutral.
    """
    out: dict[str, Vec3 | None] = {}
    if tibia_mesh is not None:
        centre = np.asarray(tibia_mesh.centroid, dtype=np.float64)
        side = (np.asarray(tibia_mesh.triangles_center) - centre) @ np.asarray(lateral)
        area = np.asarray(tibia_mesh.area_faces)
        parts = {}
        for name, mask in (('tibia_medial', side < 0.0), ('tibia_lateral', side >= 0.0)):
            if area[mask].sum() > 0.0:
                parts[name] = (np.asarray(tibia_mesh.triangles_center)[mask]
                               * area[mask, None]).sum(axis=0) / area[mask].sum()
        out.update(tibia_centre=centre, **parts)
    if patella_mesh is not None:
        out['patella_centre'] = np.asarray(patella_mesh.centroid, dtype=np.float64)
    return Landmarks(**out)


def table_landmarks(table: PoseTable, *, tibia: str | None = 'tibia',
                    patella: str | None = 'patella', side: Side = 'right',
                    tibia_point: Sequence[float] | None = None,
                    patella_point: Sequence[float] | None = None) -> Landmarks:
    """Landmarks from the first collision mesh the table records for each body.

    A point given explicitly (m, body frame) replaces that body's mesh landmarks.

    Raises:
        MeshError: a recorded mesh is missing or unreadable.
        TableError: a recorded mesh no longer has the SHA-256 the table was built with.
    """
    from .meshes import load_mesh
    from .table_format import mesh_entries
    entries = {b['name']: b for b in table.metadata['bodies']}
    units = (table.metadata.get('config') or {}).get('units', 'm')

    def first_mesh(name: str | None, given: Sequence[float] | None) -> trimesh.Trimesh | None:
        if given is not None or name not in entries:
            return None
        path, sha = mesh_entries(entries[name])[0]
        try:
            mesh = load_mesh(path, units, quiet=True)     # only its centroids are needed
        except MeshError as err:
            raise MeshError(f'{err} (the {name} landmark comes from it; or pass '
                            f'--{name}-point X,Y,Z)') from None
        if sha and file_sha256(Path(path)) != sha:
            raise TableError(f'{path} changed since the table was built (SHA-256 differs); '
                             f'pass --{name}-point X,Y,Z or rebuild the table')
        return mesh

    _, _, lateral = _anatomy(table, side)
    marks = landmarks(first_mesh(tibia, tibia_point), first_mesh(patella, patella_point),
                      lateral)
    if tibia_point is not None:
        marks = Landmarks(np.asarray(tibia_point, dtype=np.float64), None, None,
                          marks.patella_centre)
    if patella_point is not None:
        marks = Landmarks(marks.tibia_centre, marks.tibia_medial, marks.tibia_lateral,
                          np.asarray(patella_point, dtype=np.float64))
    return marks


def _flexed_sign(table: PoseTable) -> float:
    """-1 when the grid counts flexion negative (kneeseat's knees), else +1."""
    flexion = np.asarray(table.flexion_rad, dtype=np.float64)
    return -1.0 if abs(float(flexion.min())) >= abs(float(flexion.max())) else 1.0


def knee_kinematics(table: PoseTable, marks: Landmarks, *,
                    angles_deg: Sequence[float] | None = None, tibia: str | None = 'tibia',
                    patella: str | None = 'patella', side: Side = 'right') -> KneeKinematics:
    """The secondary motions of `table` at varus nearest 0 (module docstring).

    Args:
        table: a pose table.
        marks: landmarks in the bodies' own frames (see `landmarks`).
        angles_deg: knee flexion angles (deg, positive = flexed) inside the grid; default
            every grid value. Off-grid angles are interpolated (`PoseTable.interpolate`).
        tibia, patella: body names in the table; None (or absent from the table) skips it.
        side: 'right' or 'left' knee (sets which way is lateral).
    Returns:
        The quantities of the bodies present; translations are changes from the first angle.
    Raises:
        ConfigError: an angle outside the grid, an unknown side, or a landmark missing for a
            body that is present.
    """
    anterior, superior, lateral = _anatomy(table, side)
    axes = table.axes
    sign = _flexed_sign(table)
    grid_deg = np.degrees(np.asarray(table.flexion_rad, dtype=np.float64)) * sign
    if angles_deg is None:
        knee = np.sort(grid_deg)
    else:
        knee = np.asarray([float(a) for a in angles_deg], dtype=np.float64)
    lo, hi = float(grid_deg.min()), float(grid_deg.max())
    tol = TOL.grid_range_deg
    bad = knee[(knee < lo - tol) | (knee > hi + tol) | ~np.isfinite(knee)]
    if knee.size == 0 or bad.size:
        raise ConfigError(f'knee flexion angles {bad.tolist() or "[]"} deg are outside the '
                          f'table ({lo:g} to {hi:g} deg of flexion); pick angles inside it')
    varus = np.asarray(table.varus_rad, dtype=np.float64)
    v0 = float(varus[int(np.argmin(np.abs(varus)))])
    looks = [table.interpolate(math.radians(a * sign), v0) for a in knee.tolist()]
    names = list(table.bodies)
    values: dict[str, Floats] = {}
    flags: dict[str, Floats] = {}
    e1 = np.asarray(axes.flexion, dtype=np.float64)
    internal = -float(np.sign(np.cross(superior, anterior) @ lateral))
    if tibia is not None and tibia in names:
        b = names.index(tibia)
        if marks.tibia_centre is None:
            raise ConfigError(f'no landmark for {tibia!r}; give the tibia point')
        rot = matrix_from_quat(np.stack([lk.orientation_xyzw[b] for lk in looks]))
        pos = np.stack([lk.position_m[b] for lk in looks])
        e3 = rot @ superior                                               # (n, 3)
        e2 = np.cross(e3, e1)
        e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
        e2 *= float(np.sign(np.cross(superior, e1) @ anterior))

        def at(point: Vec3) -> Floats:
            return rot @ np.asarray(point) + pos                          # (n, 3)

        centre = at(marks.tibia_centre)
        values['tibia_ap'] = _change(np.sum(centre * e2, axis=1)) * 1e3
        values['tibia_pd'] = _change(np.sum(centre * e3, axis=1)) * 1e3
        values['tibia_ml'] = _change(centre @ lateral) * 1e3
        values['tibia_ie'] = np.degrees(axes.decompose(rot)[2]) * internal   # changed below
        for key, point in (('tibia_ap_medial', marks.tibia_medial),
                           ('tibia_ap_lateral', marks.tibia_lateral)):
            if point is not None:
                values[key] = _change(np.sum(at(point) * e2, axis=1)) * 1e3
        flags['tibia'] = np.array([bool(lk.nonconverged[b]) for lk in looks])
    if patella is not None and patella in names:
        b = names.index(patella)
        if marks.patella_centre is None:
            raise ConfigError(f'no landmark for {patella!r}; give the patella point')
        rot = matrix_from_quat(np.stack([lk.orientation_xyzw[b] for lk in looks]))
        pos = np.stack([lk.position_m[b] for lk in looks])
        flexion, spin, tilt = (np.degrees(a) for a in axes.decompose(rot))
        values['patella_flexion'] = flexion * sign
        values['patella_ml'] = _change((rot @ marks.patella_centre + pos) @ lateral) * 1e3
        values['patella_tilt'] = tilt * -internal                             # changed below
        values['patella_spin'] = -spin * float(np.sign(np.cross(anterior, superior) @ lateral))
        flags['patella'] = np.array([bool(lk.nonconverged[b]) for lk in looks])
    if not values:
        raise ConfigError(f'the table has neither {tibia!r} nor {patella!r} (bodies: '
                          f'{", ".join(names)}); name them with --tibia/--patella')
    rotations = [q for q in ('tibia_ie', 'patella_tilt', 'patella_spin') if q in values]
    first = {q: float(values[q][0]) for q in rotations}
    values.update({q: _change(values[q]) for q in rotations})
    return KneeKinematics(knee, math.degrees(v0), values, flags, first)


def _change(values: Floats) -> Floats:
    """`values` minus its first element."""
    return np.asarray(values, dtype=np.float64) - float(values[0])


def _body_of(quantity: str) -> str:
    return quantity.split('_', 1)[0]


def kinematics_rows(kin: KneeKinematics) -> list[dict[str, object]]:
    """One dict per angle: knee_flexion_deg, each quantity, and the non-converged bodies."""
    rows = []
    for i, angle in enumerate(kin.knee_flexion_deg.tolist()):
        row: dict[str, object] = {'knee_flexion_deg': angle}
        row.update({q: float(v[i]) for q, v in kin.values.items()})
        row['nonconverged'] = ' '.join(b for b, f in kin.nonconverged.items() if f[i])
        rows.append(row)
    return rows


def kinematics_markdown(kin: KneeKinematics, digits: int = 1) -> str:
    """A Markdown table, one row per angle; a value from a non-converged cell gets '*'."""
    quantities = [q for q in QUANTITIES if q in kin.values]
    head = ['knee flexion (deg)'] + [f'{QUANTITIES[q][1]} ({QUANTITIES[q][0]})'
                                     for q in quantities]
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for i, angle in enumerate(kin.knee_flexion_deg.tolist()):
        cells = [f'{angle:g}']
        for q in quantities:
            star = '*' if kin.nonconverged[_body_of(q)][i] else ''
            cells.append(f'{kin.values[q][i]:.{digits}f}{star}')
        lines.append('| ' + ' | '.join(cells) + ' |')
    notes = ['changes from the first angle (patellar flexion: its own value)']
    notes += [f'{QUANTITIES[q][1]} there: {v:.{digits}f} deg relative to the meshes as delivered'
              for q, v in kin.at_first.items()]
    if any(f.any() for f in kin.nonconverged.values()):
        notes.append('* from a non-converged cell')
    return '\n'.join(lines) + '\n\n' + '; '.join(notes) + '.\n'


def write_kinematics_csv(kin: KneeKinematics, out: Path) -> Path:
    """Write `kinematics_rows` as CSV, atomically."""
    rows = kinematics_rows(kin)
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator='\n')
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f'{v:.6g}' if isinstance(v, float) else v) for k, v in row.items()})
    return write_text(out, text.getvalue())


def write_text(out: Path, text: str) -> Path:
    """Write `text` to `out` atomically (temp file in the same directory, then rename).

    Raises:
        TableError: the file cannot be written (nothing is left behind).
    """
    try:
        write_bytes(Path(out), text.encode())
    except OSError as err:
        raise TableError(f'cannot write {out}: {err.strerror or err}; check that the '
                         'directory exists and is writable') from err
    return Path(out)


def read_reference(path: Path) -> list[dict[str, object]]:
    """Published values to draw beside a table's: CSV with columns source, quantity,
    knee_flexion_deg, value (quantity one of QUANTITIES); other columns are kept.

    Raises:
        ConfigError: unreadable file, missing column, unknown quantity or a bad number.
    """
    try:
        text = Path(path).read_text()
    except OSError as err:
        raise ConfigError(f'{path}: cannot read the reference CSV ({err.strerror}); '
                          'check the path') from None
    rows = list(csv.DictReader(line for line in text.splitlines()
                               if line.strip() and not line.startswith('#')))
    need = ('source', 'quantity', 'knee_flexion_deg', 'value')
    out = []
    for n, row in enumerate(rows, start=2):
        missing = [k for k in need if not row.get(k)]
        if missing:
            raise ConfigError(f'{path}: row {n} lacks {missing[0]!r}; give columns '
                              f'{", ".join(need)}')
        if row['quantity'] not in QUANTITIES:
            raise ConfigError(f'{path}: row {n}: unknown quantity {row["quantity"]!r}; use '
                              f'one of {", ".join(QUANTITIES)}')
        try:
            angle, value = float(row['knee_flexion_deg']), float(row['value'])
        except ValueError:
            raise ConfigError(f'{path}: row {n}: knee_flexion_deg and value must be '
                              'numbers') from None
        out.append({**row, 'knee_flexion_deg': angle, 'value': value})
    return out


_MARKERS = ('o', 's', '^', 'D', 'v', 'P', 'X', '<', '>', 'h')


def plot_kinematics(kin: KneeKinematics, out: Path, *, title: str,
                    reference: Sequence[Mapping[str, object]] = (),
                    others: Mapping[str, KneeKinematics] | None = None) -> Path:
    """One panel per quantity against knee flexion; published values as markers.

    Args:
        kin: the table's kinematics (a line; non-converged points as red crosses).
        out: PNG path.
        title: figure title and the table's legend label.
        reference: rows of `read_reference` (one marker style per source).
        others: more tables' kinematics to draw as dashed lines, by label (their
            non-converged cells are left out of the line).
    """
    from .plots import DPI, MARKER_RGB, write_png
    quantities = [q for q in QUANTITIES if q in kin.values]
    cols = 4
    rows = -(-len(quantities) // cols)
    fig = Figure(figsize=(4.0 * cols, 3.0 * rows + 1.2), dpi=DPI, layout='constrained')
    FigureCanvasAgg(fig)
    axs = fig.subplots(rows, cols, squeeze=False).ravel()
    sources = sorted({str(r['source']) for r in reference})
    style = {s: _MARKERS[i % len(_MARKERS)] for i, s in enumerate(sources)}
    for ax, q in zip(axs, quantities):
        unit_, label = QUANTITIES[q]
        ax.plot(kin.knee_flexion_deg, kin.values[q], color='tab:blue', lw=1.8, label=title)
        bad = kin.nonconverged[_body_of(q)]
        if bad.any():
            ax.plot(kin.knee_flexion_deg[bad], kin.values[q][bad], 'x', color=MARKER_RGB,
                    ms=7, mew=2, label='not converged')
        for k, (name, other) in enumerate((others or {}).items()):
            if q in other.values:       # converged cells only: a gap where it did not
                shown = np.where(other.nonconverged[_body_of(q)], np.nan, other.values[q])
                ax.plot(other.knee_flexion_deg, shown, '--', lw=1.2,
                        color=('tab:orange', 'tab:green', 'tab:purple')[k % 3],
                        label=f'{name} (converged cells)')
        for src in sources:
            pts = [(float(r['knee_flexion_deg']), float(r['value'])) for r in reference
                   if r['source'] == src and r['quantity'] == q]    # type: ignore[arg-type]
            if pts:
                x, y = zip(*pts)
                ax.plot(x, y, linestyle='none', marker=style[src], color='0.25', ms=5,
                        label=src)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel('knee flexion [deg]')
        ax.set_ylabel(f'[{unit_}]')
        ax.grid(True, lw=0.5, alpha=0.5)
        ax.legend(fontsize=6)
    for ax in axs[len(quantities):]:
        ax.set_visible(False)
    fig.suptitle(f'{title} (varus {kin.varus_deg:g} deg)')
    return write_png(fig, Path(out))
