"""The embedded default knee: procedural femur, tibia and patella meshes made by our own code.

Frame (the same as the real TKA data): metres, right knee, X anterior, Y superior, Z lateral
(medial is -Z). The femur is the fixed reference. The origin is the centre of the medial
condyle's sagittal arc, i.e. on the flexion axis (+Z): rotating the tibia about +Z through
the origin by a negative flexion angle swings its distal end posteriorly, and it keeps
meeting the condyles from 0 to -90 deg.

Every mesh is a closed parametric surface built on a regular grid, so it is watertight and
consistently wound by construction, has no degenerate triangle and no randomness (the same
bytes every run):
- femur: a tube about the flexion axis. Each sagittal slice (fixed z) is star-shaped about
  the axis, its boundary radius `rho(phi, z)` the smooth maximum of a few parts: two
  condyles (tori about Z: medial sagittal radius 24 mm, lateral 21 mm, different widths),
  a core that forms the intercondylar notch, a trochlea (a larger arc anteriorly, with a
  groove) and a shaft stub up to y = 75 mm. The two ends are flat caps.
- tibia and patella: solids between two height fields over an elliptical footprint (polar
  grid), joined by a short rim wall. Tibia: a medial and a lateral dish, an intercondylar
  eminence (two spines) that sits in the notch, a metaphysis flaring to a shaft stub down
  to y = -95 mm. Patella: a domed anterior face and a posterior face that is the trochlea's
  anterior surface moved 1.5 mm forward (so a central vertical ridge fills the groove).

Secondary motion (why settling moves more than the push), and why every rest is sharp:
- The lateral condyle's sagittal arc is centred 2.25 mm posterior and 2.25 mm distal of
  the flexion axis (the medial one on it). Seen from the tibia, the lateral condyle's lowest
  point therefore moves 4.5 mm anteriorly relative to the medial one between 0 and -90 deg
  of flexion. Each dish is a "V" in the sagittal plane (flanks of slope 0.45 medially,
  0.35 laterally): a condyle bears on both flanks, so the dish holds it antero-posteriorly
  with a depth change linear in the offset, and with both condyles bearing the tibia must
  turn about its long axis to follow the lateral one (internal rotation grows with
  flexion: screw-home read the other way). The lateral dish sits under the lateral
  condyle at extension.
- Coronally each dish is a circle 1 mm wider in radius than its condyle, centred 0.6 mm
  towards the other compartment, so a condyle bears on its dish's outer wall. A
  medio-lateral shift then lowers one contact and raises the other: it takes up the
  height difference between the condyles (the lateral arc dips 0.9 mm at mid-flexion, a
  commanded varus tilts one side up by 0.42 mm per degree) and keeps both condyles
  bearing over a band of varus. Because the walls face outward, that shift opposes the
  0.44 mm per degree by which a varus tilt about the knee centre moves the dishes
  sideways (numbers in docs/tables.md). Outside the band one condyle
  bears alone, held by its V and its conforming circle, and its spin about the push is
  free (no move gains depth): the sweep carries the spin from varus 0 (sweep.py).
- The patella conforms to the trochlea in both planes, so it bears along the groove, its
  spin about its push is held, and it is free to slide along the groove (it seats where
  the conforming faces fit).

Dimensions below are millimetres (suffix `_MM`); the meshes are scaled to metres at the end.
"""
from __future__ import annotations

import functools
import hashlib
from importlib import resources
import json
import os
from pathlib import Path
import platform

import numpy as np
import trimesh

from kneeseat_core import _libm, libm
from kneeseat_core.files import file_sha256, write_bytes
from kneeseat_core.typed import Floats, Ints
from . import solids
from .solids import polar_solid, smooth_max, smoothstep, soft_cap, superellipse_scale

__all__ = ['DEFAULT_PUSH', 'PATELLA_FLEXION_FRACTION', 'default_knee', 'write_default_knee',
           'stl_bytes', 'NEUTRAL_GAP_MM', 'MEDIAL_CONDYLE_Z_MM', 'LATERAL_CONDYLE_Z_MM',
           'DEFAULT_CONFIG', 'GENERATED', 'generator_key', 'default_knee_dir',
           'materialise_default_knee']

DEFAULT_PUSH = {'tibia': (0.0, 1.0, 0.0), 'patella': (-1.0, 0.0, 0.0)}
"""Unit push direction of each moving body at neutral (femur frame): tibia up, patella back."""

PATELLA_FLEXION_FRACTION = 0.6
"""The patella's push direction (and start pose) turns about the flexion axis by this
fraction of the flexion angle (patellofemoral flexion is about 0.6-0.7 of knee flexion)."""

NEUTRAL_GAP_MM = (0.5, 3.0)
"""Designed range of the tibia-femur and patella-femur clearance at the identity pose."""

_M_PER_MM = 1e-3

# ---- femur (mm) ----------------------------------------------------------------------
MEDIAL_CONDYLE_Z_MM = -25.0        # centre of the medial condyle's coronal profile
LATERAL_CONDYLE_Z_MM = 23.0        # centre of the lateral condyle's coronal profile
_MED_SAG_R_MM = 24.0               # medial sagittal radius, arc centred on the origin
_LAT_SAG_R_MM = 21.0               # lateral sagittal radius
_LAT_SAG_CENTRE_MM = (-2.25, -2.25)  # lateral arc centre (x, y): posterior and distal
_MED_COR_R_MM = 18.0               # coronal radius of the medial condyle (its width: 36)
_LAT_COR_R_MM = 16.0               # coronal radius of the lateral condyle (width: 32)
_CORE_R_MM = 11.0                  # notch roof / end caps
_TROCH_CENTRE_MM = (6.0, 6.0)      # trochlear arc centre (x, y)
_TROCH_R_MM = 25.0
_TROCH_Z_MM = -1.0                 # centre of the trochlea's medio-lateral extent
_TROCH_HALF_WIDTH_MM = 32.0
_GROOVE_Z_MM = -1.0                # trochlear groove line (z)
_GROOVE_DEPTH_MM = 6.0
_GROOVE_WIDTH_MM = 6.0             # gaussian width of the groove
_LAT_FACET_RISE_MM = 1.5           # lateral trochlear facet stands higher than the medial
_SHAFT_TOP_MM = 75.0
_SHAFT_HALF_AP_MM = 14.0
_SHAFT_Z_MM = -1.0
_SHAFT_HALF_ML_MM = 17.0
_FEMUR_Z_RANGE_MM = (-42.0, 38.0)
_SMOOTH_MAX_K = 2.0                # 1/mm, sharpness of the blend between femur parts

# ---- tibia (mm) -----------------------------------------------------------------------
_MED_DISH_MM = (0.0, -24.4, -26.7)   # dish centre x, z and its bottom y
_LAT_DISH_MM = (-2.25, 22.4, -26.0)  # under the lateral condyle at extension
_MED_DISH_SHAPE = (0.45, 19.0)       # sagittal flank slope, coronal radius (mm)
_LAT_DISH_SHAPE = (0.35, 17.0)       # shallower flanks
_SAG_ROUND_MM = 2.0                  # rounding of the sagittal V's crease
_SAG_CAP_MM = 3.5                    # the V's flanks level off this high
_DISH_DEPTH_MM = 7.5                 # dishes level off this high (outer side)
_DISH_INNER_DEPTH_MM = 4.5           # and this high towards the eminence
_EMINENCE_SPINES_Z_MM = (-5.0, 3.0)
_EMINENCE_HEIGHT_MM = 8.5            # above the medial dish bottom
_EMINENCE_SIGMA_MM = (7.0, 2.6)      # (x, z) gaussian widths of each spine
_TIBIA_CENTRE_MM = (1.0, -2.0)       # footprint centre (x, z)
_TIBIA_SEMI_MM = (25.0, 46.0)        # footprint semi-axes (x, z)
_TIBIA_RIM_DROP_MM = 2.5             # rounding of the plateau rim
_TIBIA_RIM_WALL_MM = 7.0             # height of the plateau's side wall
_TIBIA_SHAFT_END_MM = -95.0
_TIBIA_SHAFT_FRACTION = 0.42         # shaft radius as a fraction of the footprint

# ---- patella (mm) ---------------------------------------------------------------------
_PATELLA_CENTRE_MM = (8.0, _GROOVE_Z_MM)   # footprint centre (y, z)
_PATELLA_SEMI_MM = (20.0, 22.0)            # footprint semi-axes (y, z)
_PATELLA_GAP_MM = 1.5                      # clearance to the trochlea along x at neutral
_PATELLA_RIDGE_RELIEF_MM = 0.6             # the ridge is this much shallower than the groove
_PATELLA_THICKNESS_MM = 20.0

# Grid resolution (chosen for 10k-40k triangles per mesh).
_FEMUR_N_Z, _FEMUR_N_PHI = 96, 176
_TIBIA_N_ANG, _TIBIA_N_TOP, _TIBIA_N_BOTTOM = 144, 44, 28
_PATELLA_N_ANG, _PATELLA_N_FRONT, _PATELLA_N_BACK = 128, 24, 40


def _ray_to_circle(phi: Floats, centre: tuple[float, float], radius: float) -> Floats:
    """Distance (mm) from the origin along direction `phi` to a circle enclosing the origin."""
    ux, uy = libm.cos(phi), libm.sin(phi)
    proj = ux * centre[0] + uy * centre[1]
    return proj + np.sqrt(proj * proj - (centre[0] ** 2 + centre[1] ** 2) + radius * radius)


def _coronal_drop(z: Floats, centre: float, radius: float) -> Floats:
    """How far (mm) a circular coronal profile falls below its crest; huge outside it."""
    dz = np.abs(z - centre)
    inside = np.sqrt(np.clip(radius * radius - dz * dz, 0.0, None))
    return np.where(dz < radius, radius - inside, 1e3)


def femur_radius_mm(phi: Floats, z: Floats) -> Floats:
    """Boundary radius (mm) of the femur's sagittal slice `z` (mm) in direction `phi` (rad).

    `phi` is measured about +Z from +X (anterior): -pi/2 is distal, +-pi posterior, +pi/2
    up the shaft. Each slice is star-shaped about the flexion axis. `phi` and `z` broadcast;
    what depends on one of them alone is computed on it alone.
    """
    phi, z = np.asarray(phi, dtype=np.float64), np.asarray(z, dtype=np.float64)
    medial = _MED_SAG_R_MM - _coronal_drop(z, MEDIAL_CONDYLE_Z_MM, _MED_COR_R_MM)
    lateral = (_ray_to_circle(phi, _LAT_SAG_CENTRE_MM, _LAT_SAG_R_MM)
               - _coronal_drop(z, LATERAL_CONDYLE_Z_MM, _LAT_COR_R_MM))
    core = np.full(np.broadcast_shapes(phi.shape, z.shape), _CORE_R_MM)
    # Trochlea: anterior only (fades out distally, before the notch), rounded at its ends.
    anterior = smoothstep((phi + np.radians(100.0)) / np.radians(25.0))
    anterior = anterior * (1.0 - smoothstep((phi - np.radians(110.0)) / np.radians(25.0)))
    width = superellipse_scale((z - _TROCH_Z_MM) / _TROCH_HALF_WIDTH_MM, 4.0)
    groove = _GROOVE_DEPTH_MM * libm.exp(-((z - _GROOVE_Z_MM) / _GROOVE_WIDTH_MM) ** 2)
    facet = _LAT_FACET_RISE_MM * smoothstep((z - _GROOVE_Z_MM) / 20.0)
    trochlea = (_ray_to_circle(phi, _TROCH_CENTRE_MM, _TROCH_R_MM) + facet - groove)
    trochlea = trochlea * anterior * width
    # Shaft: a box [-a, a] x [0, top] in the slice, scaled down towards its ML ends.
    s, c = libm.sin(phi), libm.cos(phi)
    with np.errstate(divide='ignore'):
        to_top = np.where(s > 1e-9, _SHAFT_TOP_MM / np.where(s > 1e-9, s, 1.0), 0.0)
        to_side = _SHAFT_HALF_AP_MM / np.maximum(np.abs(c), 1e-9)
    shaft = np.minimum(to_top, to_side) * superellipse_scale(
        (z - _SHAFT_Z_MM) / _SHAFT_HALF_ML_MM, 4.0)
    return smooth_max([medial, lateral, core, trochlea, shaft], _SMOOTH_MAX_K)


def _femur_mesh_mm() -> tuple[Floats, Ints]:
    """Vertices (n, 3) mm and faces (m, 3) of the femur tube with flat end caps."""
    z = np.linspace(*_FEMUR_Z_RANGE_MM, _FEMUR_N_Z)
    phi = np.linspace(-np.pi, np.pi, _FEMUR_N_PHI, endpoint=False)
    zz, pp = np.meshgrid(z, phi, indexing='ij')                     # (nz, nphi)
    rho = femur_radius_mm(pp, zz)
    ring = np.stack([rho * libm.cos(pp), rho * libm.sin(pp), zz], axis=-1).reshape(-1, 3)
    caps = np.array([[0.0, 0.0, z[0]], [0.0, 0.0, z[-1]]])
    vertices = np.vstack([ring, caps])
    nz, nphi = _FEMUR_N_Z, _FEMUR_N_PHI
    idx = np.arange(nz * nphi).reshape(nz, nphi)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)                  # slice i, phi j / j+1
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)                    # slice i+1
    side = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                           np.stack([a, d, c], -1).reshape(-1, 3)])
    first, last = nz * nphi, nz * nphi + 1
    j = np.arange(nphi)
    cap0 = np.stack([np.full(nphi, first), (j + 1) % nphi, j], -1)
    cap1 = np.stack([np.full(nphi, last), idx[-1, j], idx[-1, (j + 1) % nphi]], -1)
    return vertices, np.concatenate([side, cap0, cap1]).astype(np.int64)


def _circular_rise(u: Floats, radius: float) -> Floats:
    """Rise (mm) of a concave circular profile of `radius` at offset `u` from its bottom.

    Past 0.9 of the radius the profile continues as its tangent line, so it stays finite
    and increasing (the dish cap below keeps it from mattering).
    """
    limit = 0.9 * radius
    a = np.minimum(np.abs(u), limit)
    rise = radius - np.sqrt(radius * radius - a * a)
    slope = limit / np.sqrt(radius * radius - limit * limit)
    out: Floats = rise + slope * (np.abs(u) - a)
    return out


def _dish(x: Floats, z: Floats, centre: tuple[float, float, float],
          shape: tuple[float, float]) -> Floats:
    """Height (mm) of a concave dish at (x, z) mm: a rounded V sagittally (flank slope
    `shape[0]`), a circle of radius `shape[1]` coronally, the V capped softly at
    `_SAG_CAP_MM` and the whole at `_DISH_DEPTH_MM` above its bottom (`_DISH_INNER_DEPTH_MM`
    on the side facing the other dish, which stays clear of the femur's notch)."""
    dx = x - centre[0]
    sagittal = soft_cap(shape[0] * (np.sqrt(dx * dx + _SAG_ROUND_MM ** 2) - _SAG_ROUND_MM),
                        _SAG_CAP_MM, _SMOOTH_MAX_K)
    rise = sagittal + _circular_rise(z - centre[1], shape[1])
    inner = (z - centre[1]) * centre[1] < 0.0        # the side towards the other dish
    return centre[2] + soft_cap(rise, np.where(inner, _DISH_INNER_DEPTH_MM, _DISH_DEPTH_MM),
                                _SMOOTH_MAX_K)


def tibia_top_mm(x: Floats, z: Floats) -> Floats:
    """Height (mm) of the tibial plateau (before the rim rounding) at (x, z) mm."""
    lateral_share = 1.0 / (1.0 + libm.exp(-(z - 0.0) / 2.5))
    plateau = ((1.0 - lateral_share) * _dish(x, z, _MED_DISH_MM, _MED_DISH_SHAPE)
               + lateral_share * _dish(x, z, _LAT_DISH_MM, _LAT_DISH_SHAPE))
    sx, sz = _EMINENCE_SIGMA_MM
    spines = sum(libm.exp(-(z - zs) ** 2 / (2 * sz * sz)) for zs in _EMINENCE_SPINES_Z_MM)
    base = _MED_DISH_MM[2] + _EMINENCE_HEIGHT_MM
    eminence = base - (base - plateau) * (1.0 - np.minimum(
        spines * libm.exp(-x * x / (2 * sx * sx)), 1.0))
    out: Floats = np.maximum(plateau, eminence)
    return out


def _tibia_mesh_mm() -> tuple[Floats, Ints]:
    cx, cz = _TIBIA_CENTRE_MM
    ax, az = _TIBIA_SEMI_MM

    def top(r: Floats, ang: Floats) -> Floats:
        x, z = cx + ax * r * libm.cos(ang), cz + az * r * libm.sin(ang)
        return tibia_top_mm(x, z) - _TIBIA_RIM_DROP_MM * smoothstep((r - 0.8) / 0.2) ** 2

    def bottom(r: Floats, ang: Floats) -> Floats:
        x, z = cx + ax * libm.cos(ang), cz + az * libm.sin(ang)
        rim = tibia_top_mm(x, z) - _TIBIA_RIM_DROP_MM - _TIBIA_RIM_WALL_MM
        t = np.clip((r - _TIBIA_SHAFT_FRACTION) / (1.0 - _TIBIA_SHAFT_FRACTION), 0.0, 1.0)
        flare = 1.0 - libm.power(1.0 - t, 5.0)
        return _TIBIA_SHAFT_END_MM + (rim - _TIBIA_SHAFT_END_MM) * flare

    top_r = np.linspace(0.0, 1.0, _TIBIA_N_TOP + 1)[1:]
    # Bottom rings: a few on the shaft's flat end, most where the flare is steep.
    t = np.linspace(0.0, 1.0, _TIBIA_N_BOTTOM - 4 + 1)
    flare_r = _TIBIA_SHAFT_FRACTION + (1.0 - _TIBIA_SHAFT_FRACTION) * t ** 2.0
    bottom_r = np.concatenate([np.linspace(0.0, _TIBIA_SHAFT_FRACTION, 5)[1:-1],
                               [_TIBIA_SHAFT_FRACTION * 0.999], flare_r[1:]])
    uv, h, faces = polar_solid(top_r, bottom_r, _TIBIA_N_ANG, top, bottom)
    vertices = np.stack([cx + ax * uv[:, 0], h, cz + az * uv[:, 1]], axis=-1)
    return vertices, faces


@functools.cache
def _trochlea_front_mm() -> tuple[Floats, Floats, Floats]:
    """The femur's anterior surface over the patella's footprint, as x (mm) on a (z, y) grid.

    Returns:
        (nz,) z samples, (ny,) y samples (mm) and (nz, ny) x (mm): where each sagittal
        slice's boundary crosses height y in front of the flexion axis.
    """
    z = np.linspace(_PATELLA_CENTRE_MM[1] - _PATELLA_SEMI_MM[1] - 1.0,
                    _PATELLA_CENTRE_MM[1] + _PATELLA_SEMI_MM[1] + 1.0, 181)
    y = np.linspace(_PATELLA_CENTRE_MM[0] - _PATELLA_SEMI_MM[0],
                    _PATELLA_CENTRE_MM[0] + _PATELLA_SEMI_MM[0], 161)
    # Over these directions every slice's boundary rises monotonically through the
    # patella's height range, so x is a function of y there.
    phi = np.linspace(np.radians(-45.0), np.radians(75.0), 2001)
    rho = femur_radius_mm(phi[None, :], z[:, None])                # (nz, nphi)
    xs, ys = rho * libm.cos(phi), rho * libm.sin(phi)
    x = np.stack([np.interp(y, ys[k], xs[k]) for k in range(len(z))])
    return z, y, x


def patella_back_mm(y: Floats, z: Floats) -> Floats:
    """x (mm) of the patella's posterior face at (y, z) mm, before the rim rounding.

    It is the trochlea's anterior surface moved `_PATELLA_GAP_MM` forward: conforming in
    both planes, so its central vertical ridge fills the groove and the contact spreads
    along the groove, which holds the patella's spin about its push. The ridge is kept
    `_PATELLA_RIDGE_RELIEF_MM` shallower than the groove, so that the patella bears on
    both facets.
    """
    y, z = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(z, dtype=np.float64))
    z_s, y_s, x_s = _trochlea_front_mm()
    # bilinear interpolation in the (z, y) grid (clamped at its edges)
    fz = np.interp(z, z_s, np.arange(len(z_s)))
    fy = np.interp(y, y_s, np.arange(len(y_s)))
    iz = np.minimum(fz.astype(np.int64), len(z_s) - 2)
    iy = np.minimum(fy.astype(np.int64), len(y_s) - 2)
    tz, ty = fz - iz, fy - iy
    front = ((1 - tz) * ((1 - ty) * x_s[iz, iy] + ty * x_s[iz, iy + 1])
             + tz * ((1 - ty) * x_s[iz + 1, iy] + ty * x_s[iz + 1, iy + 1]))
    relief = _PATELLA_RIDGE_RELIEF_MM * libm.exp(
        -((z - _GROOVE_Z_MM) / (0.8 * _GROOVE_WIDTH_MM)) ** 2)
    out: Floats = front + _PATELLA_GAP_MM + relief
    return out


def _patella_mesh_mm() -> tuple[Floats, Ints]:
    cy, cz = _PATELLA_CENTRE_MM
    ay, az = _PATELLA_SEMI_MM

    def front(r: Floats, ang: Floats) -> Floats:
        y, z = cy + ay * r * libm.cos(ang), cz + az * r * libm.sin(ang)
        dome = np.sqrt(np.clip(1.0 - r * r, 0.0, None))
        rim = patella_back_mm(y, z) + 0.25 * _PATELLA_THICKNESS_MM
        return rim + 0.75 * _PATELLA_THICKNESS_MM * libm.power(dome, 0.7)

    def back(r: Floats, ang: Floats) -> Floats:
        y, z = cy + ay * r * libm.cos(ang), cz + az * r * libm.sin(ang)
        return patella_back_mm(y, z) + 1.5 * smoothstep((r - 0.75) / 0.25) ** 2

    front_r = np.linspace(0.0, 1.0, _PATELLA_N_FRONT + 1)[1:]
    back_r = np.linspace(0.0, 1.0, _PATELLA_N_BACK + 1)[1:]
    # The "top" height field is the anterior face (+x): the solid lies between the two.
    uv, h, faces = polar_solid(front_r, back_r, _PATELLA_N_ANG, front, back)
    vertices = np.stack([h, cy + ay * uv[:, 0], cz + az * uv[:, 1]], axis=-1)
    return vertices, faces


def _finish(vertices_mm: Floats, faces: Ints) -> trimesh.Trimesh:
    """Scale to metres and orient the faces outward (positive signed volume)."""
    mesh = trimesh.Trimesh(vertices_mm * _M_PER_MM, faces, process=False, validate=False)
    if mesh.volume < 0.0:
        mesh = trimesh.Trimesh(mesh.vertices, faces[:, ::-1], process=False, validate=False)
    return mesh


def default_knee() -> dict[str, trimesh.Trimesh]:
    """The embedded default knee: keys 'femur', 'tibia', 'patella'; metres; knee frame above.

    Deterministic (no randomness): two calls return identical arrays. The femur is the
    reference; at the identity pose the tibia sits just below it and the patella just in
    front of its trochlear groove, each with a small gap (`NEUTRAL_GAP_MM`).
    """
    return {'femur': _finish(*_femur_mesh_mm()),
            'tibia': _finish(*_tibia_mesh_mm()),
            'patella': _finish(*_patella_mesh_mm())}


def stl_bytes(mesh: trimesh.Trimesh) -> bytes:
    """Binary STL of `mesh` (float32, fixed header), byte-identical for identical meshes."""
    triangles = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(lengths > 0.0, lengths, 1.0)
    record = np.dtype([('normal', '<f4', (3,)), ('vertices', '<f4', (3, 3)), ('attr', '<u2')])
    data = np.zeros(len(triangles), dtype=record)
    data['normal'] = normals
    data['vertices'] = triangles
    header = b'kneeseat default knee (procedural), metres'.ljust(80, b' ')
    count: bytes = np.uint32(len(triangles)).astype('<u4').tobytes()
    return header + count + data.tobytes()


# Beside the meshes: what made them and the SHA-256 of each, so that a later call finds them
# current without making them again (0.5 s, a tenth of the default knee's table on two cores).
GENERATED = 'generated.json'


@functools.cache
def generator_key() -> str:
    """SHA-256 (hex) of everything the default knee's bytes follow from: the source of the
    code that makes them (this module, `solids`, `kneeseat_core.libm` and its compiled
    loop), the versions of numpy and trimesh, and the C library and CPU family whose
    functions `libm` calls."""
    h = hashlib.sha256()
    for module in (__file__, solids.__file__, libm.__file__, _libm.__file__):
        h.update(Path(module).read_bytes())
    h.update(repr((np.__version__, trimesh.__version__, platform.libc_ver(),
                   platform.machine())).encode())
    return h.hexdigest()


def write_default_knee(out_dir: Path) -> dict[str, Path]:
    """Write femur.stl, tibia.stl, patella.stl (binary STL, metres) into `out_dir`, and
    beside them `GENERATED` (what made them, and their SHA-256) where the directory takes
    it (meshes already current in one that does not are used as they are).

    Each file is written atomically (`kneeseat_core.files.atomic_write`), so a crash never
    leaves a half mesh; `out_dir` is created if missing. Idempotent: the same bytes
    every time (a file that already holds them is left untouched). The meshes are made
    only when a file is missing or differs from what `GENERATED` records, or when that
    record was made by other code (`generator_key`).

    Returns:
        Body name -> path of its STL file.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {name: out_dir / f'{name}.stl' for name in ('femur', 'tibia', 'patella')}
    record = out_dir / GENERATED
    on_disk = {path.name: _sha256_or_none(path) for path in paths.values()}
    if _recorded(record) == on_disk:
        return paths
    digests: dict[str, str] = {}
    for name, mesh in default_knee().items():
        path = paths[name]
        data = stl_bytes(mesh)
        digests[path.name] = hashlib.sha256(data).hexdigest()
        if on_disk[path.name] != digests[path.name]:
            write_bytes(path, data)
    try:
        write_bytes(record, json.dumps({'generator': generator_key(), 'sha256': digests},
                                       indent=1, sort_keys=True).encode())
    except OSError:
        pass    # the meshes are current (a cache one may only read): made again next time
    return paths


def _recorded(record: Path) -> dict[str, str] | None:
    """The meshes' SHA-256 by file name that `record` holds, None where it is missing,
    unreadable or made by other code."""
    try:
        data = json.loads(record.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get('generator') != generator_key():
        return None
    digests = data.get('sha256')
    return digests if isinstance(digests, dict) else None


def _sha256_or_none(path: Path) -> str | None:
    try:
        return file_sha256(path)
    except OSError:
        return None


DEFAULT_CONFIG = 'default_knee.yaml'


def default_knee_dir() -> Path:
    """Where the embedded default knee's meshes are written (a per-user cache)."""
    base = Path(os.environ.get('XDG_CACHE_HOME', Path.home() / '.cache'))
    return base / 'kneeseat' / 'default_knee'


def materialise_default_knee(out_dir: Path | None = None) -> Path:
    """Write the default knee's meshes and config into `out_dir`; return the config path.

    Generation is deterministic, so existing files are reused when their bytes match.
    """
    out_dir = default_knee_dir() if out_dir is None else Path(out_dir)
    write_default_knee(out_dir)
    config = out_dir / DEFAULT_CONFIG
    text = resources.files('kneeseat_core').joinpath('data', DEFAULT_CONFIG).read_text()
    if not config.is_file() or config.read_text() != text:
        write_bytes(config, text.encode())
    return config
