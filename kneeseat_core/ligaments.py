"""Ligaments and tendons: a set of fibres, their force law, and what they do to one body.

A knee config names its soft tissue (`ligaments:` in the config: a file in the shared format
or fibres listed inline). Each fibre is a path of points, each point fixed on one body (in
that body's mesh frame as delivered), joined by straight segments: wrapping around bone is
left out, so a path's length, and its strain, are lower bounds. The fibres of a set join two
bodies each (femur-tibia, femur-patella, patella-tibia).

Force law, Blankevoort 1991 (as in the OpenSim-JAM models the shared sets come from): with
strain e = L / L0 - 1 (L0 the slack length), stiffness k (N per unit strain) and transition
strain e_t,
    f = 0                      for e <= 0     (slack)
    f = k e^2 / (2 e_t)        for 0 < e < e_t (toe)
    f = k (e - e_t / 2)        for e >= e_t    (linear)
and the stored energy E = integral of f dL = L0 k e^3 / (6 e_t) in the toe region,
L0 k (e^2 / 2 - e_t e / 2 + e_t^2 / 6) above it; f and E are continuous and dE/dL = f.
Damping (the models' `damping_coefficient`) needs speeds: a quasi-static settle has none.

`Tissue` is the part of a set that acts on one moving body during one settle, with every
point not on that body already placed in the reference frame (the other bodies are where
they were settled): its energy as a function of the body's pose, and the force each
attachment feels. This module holds data and the force law only; it knows nothing of the
settle (which minimises nothing here: it reads energies and forces).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
import hashlib
import json
import math
from pathlib import Path
import re
from typing import Any

import numpy as np

from .errors import ConfigError
from .typed import Bools, Floats, Ints, Pose

__all__ = ['DEFAULT_TRANSITION_STRAIN', 'Fibre', 'LigamentSet', 'Tissue', 'TissueLayout',
           'fibre_force', 'fibre_energy', 'load_ligaments', 'parse_ligaments']

DEFAULT_TRANSITION_STRAIN = 0.06      # the OpenSim-JAM class default (Blankevoort 1991)

# Keys of the shared format: what a fibre, a point and the file may hold. The informational
# ones (sources, wrap objects, strains the file's authors measured) are accepted and kept
# out of the mechanics; anything else is a typo and refused with its name.
_FILE_KEYS = {'frame', 'units', 'source', 'provenance', 'fields', 'force_law', 'wrap_caveat',
              'wrap_objects', 'ligaments'}
_FIBRE_KEYS = {'name', 'bundle', 'points', 'slack_length_m', 'linear_stiffness_n',
               'transition_strain', 'wrap', 'wrap_method', 'applies_force',
               'damping_coefficient', 'strain_at_delivered_pose_straight',
               'strain_at_model_default_pose_straight'}
_FIBRE_REQUIRED = {'name', 'points', 'slack_length_m', 'linear_stiffness_n'}
_POINT_KEYS = {'body', 'position', 'source_frame', 'source_location', 'on_mesh'}
_UNITS = {'m': 1.0, 'mm': 1e-3}


def _law(strain: Floats, stiffness_n: Floats, transition: Floats) -> tuple[Floats, Floats]:
    """Tension (N) and energy per slack length (J/m) at `strain`, in one pass: with m the
    strain clipped to [0, e_t] and l what lies above e_t, f = k (m^2 / (2 e_t) + l) and
    E / L0 = k (m^3 / (6 e_t) + m l / 2 + l^2 / 2), the module docstring's pieces joined."""
    e = np.maximum(strain, 0.0)
    m = np.minimum(e, transition)
    over = e - m
    toe = m * m / (2.0 * transition)
    force: Floats = stiffness_n * (toe + over)
    energy: Floats = stiffness_n * (m * toe / 3.0 + over * (0.5 * m + 0.5 * over))
    return force, energy


def fibre_force(strain: Floats, stiffness_n: Floats, transition: Floats) -> Floats:
    """Tension (N) of fibres at `strain` (Blankevoort 1991, module docstring); arrays
    broadcast."""
    return _law(np.asarray(strain, dtype=np.float64), stiffness_n, transition)[0]


def fibre_energy(strain: Floats, stiffness_n: Floats, transition: Floats,
                 slack_m: Floats) -> Floats:
    """Elastic energy (J) stored in fibres at `strain`: the integral of `fibre_force` over
    the length from the slack length."""
    out: Floats = slack_m * _law(np.asarray(strain, dtype=np.float64), stiffness_n,
                                 transition)[1]
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Fibre:
    """One fibre: a path of points on two bodies and its mechanical constants."""

    name: str
    bundle: str
    bodies: tuple[str, ...]      # (n,) the body each point is fixed on
    points: Floats               # (n, 3) m, each in its body's mesh frame as delivered
    slack_m: float
    stiffness_n: float           # N per unit strain (the linear region's slope)
    transition: float            # transition strain e_t

    @property
    def ends(self) -> frozenset[str]:
        """The two bodies the fibre joins."""
        return frozenset(self.bodies)


@dataclass(frozen=True, slots=True, eq=False)
class LigamentSet:
    """The fibres of a knee config, where they came from, and their hash.

    `sha256` is the SHA-256 of the file's bytes, or of the inline list as canonical JSON.
    """

    fibres: tuple[Fibre, ...]
    source: str                  # the file, or 'inline'
    sha256: str

    @property
    def bundles(self) -> tuple[str, ...]:
        """Bundle names, in the order they first appear."""
        return tuple(dict.fromkeys(f.bundle for f in self.fibres))

    def acting_on(self, body: str, placed: Sequence[str]) -> tuple[Fibre, ...]:
        """The fibres that pull on `body` while the bodies `placed` are where they are: one
        end on `body`, the other on one of `placed` (the reference and the bodies settled
        before it)."""
        return tuple(f for f in self.fibres
                     if body in f.ends and (f.ends - {body}) <= set(placed))

    def lengths(self, poses: Mapping[str, Pose]) -> Floats:
        """(f,) path length (m) of every fibre, each point moved by its body's pose
        (a (4, 4) pose of the body's mesh frame in the reference frame)."""
        out = np.empty(len(self.fibres))
        for i, fibre in enumerate(self.fibres):
            world = np.array([poses[b][:3, :3] @ p + poses[b][:3, 3]
                              for b, p in zip(fibre.bodies, fibre.points)])
            out[i] = float(np.linalg.norm(np.diff(world, axis=0), axis=1).sum())
        return out

    def strains(self, poses: Mapping[str, Pose]) -> Floats:
        """(f,) straight-line strain of every fibre at `poses` (see `lengths`)."""
        slack = np.array([f.slack_m for f in self.fibres])
        out: Floats = self.lengths(poses) / slack - 1.0
        return out

    def forces(self, poses: Mapping[str, Pose]) -> Floats:
        """(f,) tension (N) of every fibre at `poses`."""
        return fibre_force(self.strains(poses), np.array([f.stiffness_n for f in self.fibres]),
                           np.array([f.transition for f in self.fibres]))

    def tissue(self, body: str, placed: Mapping[str, Pose]) -> Tissue | None:
        """The fibres acting on `body` (`acting_on` the bodies in `placed`), ready for one
        settle: their points on `body` kept in its frame, every other point placed once in
        the reference frame by `placed` (body name -> (4, 4) pose). None when no fibre acts."""
        layout = self.layout(body, tuple(placed))
        return None if layout is None else layout.place(placed)

    def layout(self, body: str, placed: Sequence[str]) -> TissueLayout | None:
        """The fibres acting on `body` while the bodies `placed` are where they are, laid
        out once for the settles of many cells (`TissueLayout.place`); None when no fibre
        acts."""
        fibres = self.acting_on(body, placed)
        if not fibres:
            return None
        owners: list[str] = []
        points: list[Floats] = []
        seg_a: list[int] = []
        seg_b: list[int] = []
        seg_fibre: list[int] = []
        for i, fibre in enumerate(fibres):
            start = len(points)
            owners.extend(fibre.bodies)
            points.extend(np.asarray(p, dtype=np.float64) if b == body else p
                          for b, p in zip(fibre.bodies, fibre.points))
            count = len(fibre.points)
            seg_a.extend(range(start, start + count - 1))
            seg_b.extend(range(start + 1, start + count))
            seg_fibre.extend([i] * (count - 1))
        return TissueLayout(body, tuple(f.name for f in fibres), tuple(f.bundle for f in fibres),
                            tuple(owners), np.array(points, dtype=np.float64).reshape(-1, 3),
                            np.array(seg_a), np.array(seg_b), np.array(seg_fibre),
                            np.array([f.slack_m for f in fibres]),
                            np.array([f.stiffness_n for f in fibres]),
                            np.array([f.transition for f in fibres]))


@dataclass(frozen=True, slots=True, eq=False)
class TissueLayout:
    """The fibres acting on one body, laid out once (`LigamentSet.layout`): each point's
    body and coordinates there, the segments as point indices and the fibre of each, and
    the fibres' names and constants. A sweep lays it out once per body and places it at
    every cell of a chain, where only the other bodies' poses change; its arrays make it
    small to send to a worker."""

    body: str
    names: tuple[str, ...]       # (f,)
    bundles: tuple[str, ...]     # (f,)
    owners: tuple[str, ...]      # (n,) the body each point is fixed on
    points: Floats               # (n, 3) m, each in its body's frame
    seg_a: Ints                  # (s,) first point of each straight segment
    seg_b: Ints                  # (s,) second point
    seg_fibre: Ints              # (s,) the fibre each segment belongs to
    slack_m: Floats              # (f,)
    stiffness_n: Floats          # (f,)
    transition: Floats           # (f,)
    # the tissue with the other bodies' points still in their own frames (what `place`
    # moves), and which of its fixed points each other body holds: the same at every cell
    _unplaced: Tissue = field(init=False, repr=False)
    _held: tuple[tuple[str, Ints], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        moving = np.array([b == self.body for b in self.owners], dtype=bool)
        unplaced = Tissue.of(self.names, self.bundles, self.points, moving, self.seg_a,
                             self.seg_b, self.seg_fibre, self.slack_m, self.stiffness_n,
                             self.transition)
        owners = [b for b in self.owners if b != self.body]    # in the tissue's order
        held = tuple((name, np.array([i for i, b in enumerate(owners) if b == name]))
                     for name in dict.fromkeys(owners))
        object.__setattr__(self, '_unplaced', unplaced)
        object.__setattr__(self, '_held', held)

    def place(self, placed: Mapping[str, Pose]) -> Tissue:
        """The tissue with every body other than the moving one at its pose in `placed`
        (body name -> (4, 4) pose in the reference frame)."""
        unplaced = self._unplaced
        world = unplaced.fixed_world.copy()
        for name, rows in self._held:
            # each point turned as a pose turns one point (`turn @ p`), all at once
            turn, shift = placed[name][:3, :3], placed[name][:3, 3]
            world[rows] = (np.broadcast_to(turn, (len(rows), 3, 3))
                           @ world[rows][:, :, None])[:, :, 0] + shift
        return unplaced.placed(world)


def _fixed_ends(points: Floats, k: int, seg_a: Ints, seg_b: Ints) -> Floats:
    """(s, 3) each segment's ends fixed in the reference frame, end less start (`points`:
    the k on the moving body first, then the fixed ones; a moving end counts none)."""
    out: Floats = np.where((seg_b >= k)[:, None], points[seg_b], 0.0) \
        - np.where((seg_a >= k)[:, None], points[seg_a], 0.0)
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Tissue:
    """The fibres acting on one moving body in one settle (`LigamentSet.tissue`).

    The points are ordered with the k on the moving body first (in its frame), then the
    ones fixed in the reference frame; a settle evaluates the energy hundreds of times, so
    the structure is prepared once: the segments as point indices, and which fibre each
    belongs to. A pose is the moving body's (4, 4) fixed_from_moving.
    """

    names: tuple[str, ...]       # (f,)
    bundles: tuple[str, ...]     # (f,)
    moving_local: Floats         # (k, 3) m, points on the moving body, its frame
    fixed_world: Floats          # (n - k, 3) m, the other points, reference frame
    seg_a: Ints                  # (s,) first point of each straight segment
    seg_b: Ints                  # (s,) second point
    seg_fibre: Ints              # (s,) the fibre each segment belongs to
    slack_m: Floats              # (f,)
    stiffness_n: Floats          # (f,)
    transition: Floats           # (f,)
    # each segment's vector b - a is seg_local turned by the pose, plus seg_sign times the
    # pose's translation, plus seg_fixed (the ends fixed in the reference frame)
    seg_local: Floats            # (s, 3) m, body frame
    seg_sign: Floats             # (s,) moving ends: +1 end, -1 start, 0 both or none
    seg_fixed: Floats            # (s, 3) m, reference frame

    @classmethod
    def of(cls, names: tuple[str, ...], bundles: tuple[str, ...], local: Floats,
           moving: Bools, seg_a: Ints, seg_b: Ints, seg_fibre: Ints, slack_m: Floats,
           stiffness_n: Floats, transition: Floats) -> Tissue:
        """From points flagged `moving` (in the body's frame) or not (reference frame)."""
        order = np.concatenate([np.flatnonzero(moving), np.flatnonzero(~moving)])
        where = np.empty(len(order), dtype=np.int64)
        where[order] = np.arange(len(order))
        a, b = where[seg_a], where[seg_b]
        k = int(moving.sum())
        # (k, s) +1 / -1 where a segment ends / starts on moving point j
        incidence = np.zeros((k, len(a)))
        incidence[b[b < k], np.flatnonzero(b < k)] += 1.0
        incidence[a[a < k], np.flatnonzero(a < k)] -= 1.0
        placed = local[order]
        return cls(names, bundles, placed[:k], placed[k:], a, b, seg_fibre,
                   slack_m, stiffness_n, transition, incidence.T @ placed[:k],
                   incidence.sum(axis=0), _fixed_ends(placed, k, a, b))

    def placed(self, fixed_world: Floats) -> Tissue:
        """The same fibres with the points fixed in the reference frame at `fixed_world`
        ((n - k, 3), in this tissue's order): where the bodies holding them rest now."""
        points = np.concatenate([self.moving_local, fixed_world])
        return replace(self, fixed_world=fixed_world,
                       seg_fixed=_fixed_ends(points, len(self.moving_local), self.seg_a,
                                             self.seg_b))

    def world(self, pose: Pose) -> Floats:
        """(n, 3) every point in the reference frame with the body at `pose` (the moving
        body's first)."""
        return np.concatenate([self.moving_local @ pose[:3, :3].T + pose[:3, 3],
                               self.fixed_world])

    def _segments(self, pose: Pose) -> tuple[Floats, Floats, Floats, Floats]:
        """Every point, each segment's vector and length, each fibre's strain at `pose`."""
        w = self.world(pose)
        d = w[self.seg_b] - w[self.seg_a]
        seg = np.sqrt(np.einsum('ij,ij->i', d, d))
        lengths = np.bincount(self.seg_fibre, seg, minlength=len(self.slack_m))
        strain: Floats = lengths / self.slack_m - 1.0
        return w, d, seg, strain

    def strains(self, pose: Pose) -> Floats:
        """(f,) strain of every fibre with the body at `pose`."""
        return self._segments(pose)[3]

    def energy(self, pose: Pose) -> float:
        """Elastic energy (J) of the fibres with the body at `pose`."""
        return float(fibre_energy(self.strains(pose), self.stiffness_n, self.transition,
                                  self.slack_m).sum())


# ---- reading a set --------------------------------------------------------------------
def load_ligaments(path: Path, bodies: Sequence[str]) -> LigamentSet:
    """Read a ligament file in the shared format (`ligaments.json` of the shared data).

    Args:
        path: the JSON file.
        bodies: the names of the config's bodies, the reference first; every point must
            lie on one of them.
    Raises:
        ConfigError: missing or unreadable file, unknown keys, bodies or units, bad numbers;
            the message names the file, the fibre and the key.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
        data = json.loads(raw)
    except FileNotFoundError:
        raise ConfigError(f'ligaments file {path} not found; fix the path (relative to '
                          'mesh_dir) or pass --mesh-dir DIR') from None
    except (OSError, ValueError) as err:
        raise ConfigError(f'ligaments file {path}: not readable JSON ({err})') from None
    where = f'ligaments file {path}'
    _check_keys(data, _FILE_KEYS, where, {'ligaments'})
    units = data.get('units', 'm')
    if units not in _UNITS:
        raise ConfigError(f"{where}: units must be 'm' or 'mm', got {units!r}")
    fibres = _fibres(data['ligaments'], where, bodies, _UNITS[units])
    return LigamentSet(fibres, str(path), hashlib.sha256(raw).hexdigest())


def parse_ligaments(items: Any, where: str, bodies: Sequence[str],
                    units: str = 'm') -> LigamentSet:
    """A ligament set listed inline in a config (a list of fibres in the shared format,
    positions in the config's `units`).

    Raises:
        ConfigError: as `load_ligaments`, naming the config key.
    """
    fibres = _fibres(items, where, bodies, _UNITS.get(units, 1.0))
    canonical = json.dumps(items, sort_keys=True, separators=(',', ':')).encode()
    return LigamentSet(fibres, 'inline', hashlib.sha256(canonical).hexdigest())


def _check_keys(data: Any, allowed: set[str], where: str, required: set[str]) -> None:
    if not isinstance(data, dict):
        raise ConfigError(f'{where} must be a mapping of keys, got {type(data).__name__}')
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ConfigError(f'{where}: unknown key {unknown[0]!r}; allowed: '
                          f'{", ".join(sorted(allowed))}')
    missing = sorted(required - set(data))
    if missing:
        raise ConfigError(f'{where}: missing key {missing[0]!r}')


def _positive(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0.0:
        raise ConfigError(f'{where} must be a positive number, got {value!r}')
    return float(value)


def _fibres(items: Any, where: str, bodies: Sequence[str], scale: float) -> tuple[Fibre, ...]:
    if not isinstance(items, list) or not items:
        raise ConfigError(f'{where}: ligaments must be a non-empty list of fibres')
    fibres, names = [], set()
    for i, item in enumerate(items):
        at = f'{where}: ligaments[{i}]'
        _check_keys(item, _FIBRE_KEYS, at, _FIBRE_REQUIRED)
        name = item['name']
        if not isinstance(name, str) or not name:
            raise ConfigError(f'{at}.name must be a non-empty string, got {name!r}')
        at = f'{where}: ligament {name!r}'
        if name in names:
            raise ConfigError(f'{at} is listed twice; give each fibre once')
        names.add(name)
        if item.get('applies_force', True) is not True:
            raise ConfigError(f'{at}: applies_force must be true (a fibre that applies no '
                              'force does not belong in the set); remove it')
        bundle = item.get('bundle', re.sub(r'\d+$', '', name))
        if not isinstance(bundle, str) or not bundle:
            raise ConfigError(f'{at}.bundle must be a non-empty string, got {bundle!r}')
        body_names, points = _points(item['points'], at, bodies, scale)
        fibres.append(Fibre(
            name, bundle, body_names, points,
            _positive(item['slack_length_m'], f'{at}.slack_length_m'),
            _positive(item['linear_stiffness_n'], f'{at}.linear_stiffness_n'),
            _positive(item.get('transition_strain', DEFAULT_TRANSITION_STRAIN),
                      f'{at}.transition_strain')))
    return tuple(fibres)


def _points(items: Any, at: str, bodies: Sequence[str],
            scale: float) -> tuple[tuple[str, ...], Floats]:
    if not isinstance(items, list) or len(items) < 2:
        raise ConfigError(f'{at}.points must be a list of at least two points')
    names, positions = [], []
    for j, point in enumerate(items):
        where = f'{at}.points[{j}]'
        _check_keys(point, _POINT_KEYS, where, {'body', 'position'})
        body = point['body']
        if body not in bodies:
            raise ConfigError(f'{where}.body {body!r} is not a body of the config '
                              f'({", ".join(bodies)}); name one of them')
        position = point['position']
        if not (isinstance(position, list) and len(position) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                        and math.isfinite(v) for v in position)):
            raise ConfigError(f'{where}.position must be three finite numbers, '
                              f'got {position!r}')
        names.append(body)
        positions.append([float(v) * scale for v in position])
    if len(set(names)) != 2:
        raise ConfigError(f'{at}: its points lie on {sorted(set(names))}; a fibre joins '
                          'exactly two bodies')
    return tuple(names), np.array(positions)
