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
The CSV, Markdown and figure of `kneeseat kinematics` are `kneeseat_core.report.kinematics_report`.

Landmarks (body frames): the plateau centre is the area centroid of the tibia's first
collision mesh (the tibial cartilage or insert); the medial and lateral centres are the
centroids of its parts on either side of that centre (the two cartilage sheets of a natural
knee); the patellar landmark is the centroid of the patella's first collision mesh.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from kneeseat_core.errors import ConfigError, MeshError, TableError
from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import matrix_from_quat, TOL, unit
from kneeseat_core.meshes import load_mesh
from kneeseat_core.table import Lookup, mesh_entries, PoseTable
from kneeseat_core.typed import Bools, Floats, Vec3

__all__ = ['QUANTITIES', 'DEFAULT_ANGLES_DEG', 'Side', 'Landmarks', 'KneeKinematics',
           'landmarks', 'table_landmarks', 'knee_kinematics']

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
    nonconverged: dict[str, Bools]       # 'tibia' / 'patella' -> (n,) bool
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
    sign = _flexed_sign(table)
    knee = _knee_angles(table, sign, angles_deg)
    varus = np.asarray(table.varus_rad, dtype=np.float64)
    v0 = float(varus[int(np.argmin(np.abs(varus)))])
    looks = [table.interpolate(_on_grid(table.flexion_rad, math.radians(a * sign)), v0)
             for a in knee.tolist()]
    names = list(table.bodies)
    values: dict[str, Floats] = {}
    flags: dict[str, Bools] = {}
    anatomy = (anterior, superior, lateral)
    if tibia is not None and tibia in names:
        if marks.tibia_centre is None:
            raise ConfigError(f'no landmark for {tibia!r}; give the tibia point')
        values.update(_tibia(table, _poses_of(looks, names.index(tibia)), marks, anatomy))
        flags['tibia'] = np.array([bool(lk.nonconverged[names.index(tibia)]) for lk in looks])
    if patella is not None and patella in names:
        if marks.patella_centre is None:
            raise ConfigError(f'no landmark for {patella!r}; give the patella point')
        values.update(_patella(table, _poses_of(looks, names.index(patella)),
                               marks.patella_centre, anatomy, sign))
        flags['patella'] = np.array([bool(lk.nonconverged[names.index(patella)])
                                     for lk in looks])
    if not values:
        raise ConfigError(f'the table has neither {tibia!r} nor {patella!r} (bodies: '
                          f'{", ".join(names)}); name them with --tibia/--patella')
    rotations = [q for q in ('tibia_ie', 'patella_tilt', 'patella_spin') if q in values]
    first: dict[str, float] = {q: float(values[q][0]) for q in rotations}
    values.update({q: _change(values[q]) for q in rotations})
    return KneeKinematics(knee, math.degrees(v0), values, flags, first)


def _knee_angles(table: PoseTable, sign: float, angles_deg: Sequence[float] | None) -> Floats:
    """The knee flexion angles (deg, positive = flexed) to report: every grid value, or the
    requested ones, which must lie inside the grid.

    Raises:
        ConfigError: an angle outside the grid or not finite, or no angle.
    """
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
    return knee


def _on_grid(grid_rad: Floats, angle_rad: float) -> float:
    """`angle_rad`, or the grid node it names (within `TOL.grid_match_deg`) exactly: an
    angle that went through degrees differs from its node in the last bits, and
    interpolation would then give the neighbour cell a weight (and its flags)."""
    grid = np.asarray(grid_rad, dtype=np.float64)
    node = int(np.argmin(np.abs(grid - angle_rad)))
    if abs(grid[node] - angle_rad) <= math.radians(TOL.grid_match_deg):
        return float(grid[node])
    return angle_rad


def _poses_of(looks: Sequence[Lookup], b: int) -> tuple[Floats, Floats]:
    """Body `b`'s rotations (n, 3, 3) and positions (n, 3) m over the lookups."""
    rot = matrix_from_quat(np.stack([lk.orientation_xyzw[b] for lk in looks]))
    return rot, np.stack([lk.position_m[b] for lk in looks])


def _tibia(table: PoseTable, poses: tuple[Floats, Floats], marks: Landmarks,
           anatomy: tuple[Vec3, Vec3, Vec3]) -> dict[str, Floats]:
    """The tibia's quantities (module docstring); its rotation still absolute."""
    rot, pos = poses
    anterior, superior, lateral = anatomy
    axes = table.axes
    e1 = np.asarray(axes.flexion, dtype=np.float64)
    internal = -float(np.sign(np.cross(superior, anterior) @ lateral))
    e3 = rot @ superior                                               # (n, 3)
    e2 = np.cross(e3, e1)
    e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
    e2 *= float(np.sign(np.cross(superior, e1) @ anterior))

    def at(point: Vec3) -> Floats:
        return rot @ np.asarray(point) + pos                          # (n, 3)

    assert marks.tibia_centre is not None
    centre = at(marks.tibia_centre)
    values = {'tibia_ap': _change(np.sum(centre * e2, axis=1)) * 1e3,
              'tibia_pd': _change(np.sum(centre * e3, axis=1)) * 1e3,
              'tibia_ml': _change(centre @ lateral) * 1e3,
              'tibia_ie': np.degrees(axes.decompose(rot)[2]) * internal}
    for key, point in (('tibia_ap_medial', marks.tibia_medial),
                       ('tibia_ap_lateral', marks.tibia_lateral)):
        if point is not None:
            values[key] = _change(np.sum(at(point) * e2, axis=1)) * 1e3
    return values


def _patella(table: PoseTable, poses: tuple[Floats, Floats], centre: Vec3,
             anatomy: tuple[Vec3, Vec3, Vec3], sign: float) -> dict[str, Floats]:
    """The patella's quantities (module docstring); its tilt and spin still absolute."""
    rot, pos = poses
    anterior, superior, lateral = anatomy
    internal = -float(np.sign(np.cross(superior, anterior) @ lateral))
    flexion, spin, tilt = (np.degrees(a) for a in table.axes.decompose(rot))
    return {'patella_flexion': flexion * sign,
            'patella_ml': _change((rot @ centre + pos) @ lateral) * 1e3,
            'patella_tilt': tilt * -internal,
            'patella_spin': -spin * float(np.sign(np.cross(anterior, superior) @ lateral))}


def _change(values: Floats) -> Floats:
    """`values` minus its first element."""
    return np.asarray(values, dtype=np.float64) - float(values[0])
