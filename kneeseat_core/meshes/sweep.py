"""The travel along the push measured exactly, and the contact features where it ends.

How far a moving body can go along a direction Δ before it first touches a fixed body is
the least gap along Δ over every pair of triangles whose shadows (seen along Δ) overlap; two
flat triangles first meet at a vertex of one on the face of the other or at an edge across
an edge, so every candidate is one of those fifteen features a pair has, and each is
computed exactly (`_sweep.cpp`, compiled with the package: a bounding volume hierarchy per
body, bounded seen along Δ by planes, so conforming surfaces prune to the few pairs near
contact). The same query returns every feature that closes within a window beyond the
first contact: its gap, the normal it closes along and the point of the moving body
there, from which the travel after a small lateral move follows to first order (the
settle's model of the travel, `kneeseat_core.settle.climb`).

The travel is measured from a pose lowered along -Δ by `behind`: a pose that a lateral move
left in collision by less than that has a negative travel (the first contact from below);
one that collides even lowered that far is reported `buried` and the caller lowers
further. Only triangles facing the other body take part where a surface is closed (a ray
from outside enters through a front face); an open surface (a cartilage sheet) takes part
with both faces.

python-fcl stays the judge where it matters (a start in collision, the end of a settle, the
referee): its booleans and this travel agree to the nanometre on the knees
(test/test_sweep.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
import weakref

import numpy as np
import trimesh

from kneeseat_core.typed import Floats, Ints, Pose
from . import _sweep
from .collision import RigidBody

__all__ = ['SweepBody', 'SweepPair', 'Touch', 'FEATURE', 'sweep_body', 'facing', 'PLACE', 'SHORT',
           'LOST']

# A view of a body is kept per direction, the direction rounded to this (rad): the moving
# body's direction in its own frame stays put while it spins about Δ, up to rounding. The
# view looks along the rounded direction itself, so that what a pose measures does not
# depend on which direction of the same rounding happened to be asked first in the process
# (a worker's history: the tables would differ from run to run in the last bits, and a
# climb can turn on those).
_SAME_DIRECTION = 1e-12
_VIEWS_KEPT = 8
# How many of the pairs of triangles that stopped a settle's searches short its later moves
# are asked first (`SweepPair.measure`).
STOPPERS = 8

# What `SweepPair.measure` found: a pose that reached its travel, every pose short (or
# refuted), or a pose with no contact along the push.
PLACE, SHORT, LOST = 0, 1, 2

# The layout of one feature from `_sweep.contacts` (the C struct of _feature.h: gap, normal,
# point, room, kind, moving face, fixed face).
FEATURE = np.dtype([('gap', '<f8'), ('normal', '<f8', 3), ('point', '<f8', 3),
                    ('room', '<f8'), ('kind', '<i8'), ('moving_face', '<i8'),
                    ('fixed_face', '<i8')])


def facing(mesh: trimesh.Trimesh) -> np.ndarray:
    """(m,) int8 per face: +1 where its winding's normal points out of a closed surface, -1
    where it points in (a surface wound inside out), 0 where the face's surface is not
    closed (both its sides can be met). A surface is a set of faces joined along edges; it
    is closed when each of its edges is one face's and, reversed, exactly one other's."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int8)
    n = int(faces.max()) + 1
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    key = directed[:, 0] * n + directed[:, 1]
    reverse = directed[:, 1] * n + directed[:, 0]
    order = np.argsort(key, kind='stable')
    sorted_keys = key[order]
    once = np.ones(len(key), dtype=bool)          # this directed edge occurs once only
    repeated = sorted_keys[1:] == sorted_keys[:-1]
    once[order[1:][repeated]] = False
    once[order[:-1][repeated]] = False
    at = np.searchsorted(sorted_keys, reverse)
    matched = (at < len(sorted_keys)) & (sorted_keys[np.minimum(at, len(key) - 1)] == reverse)
    good = (once & matched).reshape(-1, 3).all(axis=1)
    labels = _surfaces(faces, len(faces))
    closed = np.ones(int(labels.max()) + 1, dtype=bool)
    np.logical_and.at(closed, labels, good)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    signed = np.einsum('ij,ij->i', v[faces[:, 0]], np.cross(v[faces[:, 1]], v[faces[:, 2]]))
    volume = np.zeros(len(closed))
    np.add.at(volume, labels, signed)
    out = np.where(closed[labels], np.where(volume[labels] >= 0.0, 1, -1), 0)
    return out.astype(np.int8)


def _surfaces(faces: Ints, count: int) -> Ints:
    """(m,) label of the surface (faces joined along shared edges) of each face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    ends = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    key = ends[:, 0] * (int(faces.max()) + 1) + ends[:, 1]
    owner = np.repeat(np.arange(count), 3)
    order = np.argsort(key, kind='stable')
    same = key[order][1:] == key[order][:-1]
    a, b = owner[order][:-1][same], owner[order][1:][same]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    return np.asarray(labels, dtype=np.int64)


class SweepBody:
    """One body's hierarchy for the exact travel (built once per body and process) and its
    views, one per direction asked (kept for the last few directions)."""

    def __init__(self, body: RigidBody) -> None:
        self.faces = body.faces
        self.facing = facing(body.mesh)
        self.native = _sweep.Body(np.ascontiguousarray(body.vertices, dtype=np.float64),
                                  np.ascontiguousarray(body.faces, dtype=np.int64),
                                  np.ascontiguousarray(self.facing))
        self._views: dict[tuple[int, int, int, int], _sweep.View] = {}

    def view(self, direction: Floats, side: int) -> _sweep.View:
        """The body seen along the unit `direction` (its own frame): `side` +1 for the
        moving body (its faces facing +direction take part), -1 for the fixed body."""
        x, y, z = (c / _SAME_DIRECTION for c in np.asarray(direction, dtype=np.float64).tolist())
        key = (side, round(x), round(y), round(z))     # to the nearest, ties to even
        found = self._views.get(key)
        if found is None:
            if len(self._views) >= _VIEWS_KEPT:
                del self._views[next(iter(self._views))]
            along = np.array(key[1:], dtype=np.float64) * _SAME_DIRECTION
            unit = np.ascontiguousarray(along / np.linalg.norm(along), dtype=np.float64)
            found = self._views[key] = _sweep.View(self.native, unit, side)
        return found


_SWEEP_BODIES: weakref.WeakKeyDictionary[RigidBody, SweepBody] = weakref.WeakKeyDictionary()


def sweep_body(body: RigidBody) -> SweepBody:
    """The body's `SweepBody`, built on first use and kept while the body lives."""
    found = _SWEEP_BODIES.get(body)
    if found is None:
        found = _SWEEP_BODIES[body] = SweepBody(body)
    return found


@dataclass(frozen=True, slots=True, eq=False)
class Touch:
    """The travel from one pose and the features that close within a window beyond it: the
    engine's records (`FEATURE`), read as arrays only where asked (the climb hands them to
    the planner whole), and seen from the pose `rise` further along Δ (`push`) than the one
    they were measured from (`lifted`: a place stands there, short of touching)."""

    travel: float           # m along Δ from the pose measured (inf: no contact; -inf: buried)
    buried: bool            # the pose lowered by `behind` is in collision: lower further
    features: np.ndarray    # (k,) `FEATURE` records, as the engine found them
    rise: float = 0.0       # m along Δ from the pose measured to the pose seen from
    push: Floats | None = None   # (3,) Δ, where rise is not 0

    @classmethod
    def of(cls, travel: float, buried: bool, gaps: Floats, normals: Floats, points: Floats,
           rooms: Floats, kinds: Ints, faces: Ints) -> Touch:
        """A touch from its features' arrays (k,), (k, 3), (k, 3), (k,), (k,), (k, 2)."""
        features = np.zeros(len(gaps), dtype=FEATURE)
        features['gap'], features['normal'], features['point'] = gaps, normals, points
        features['room'], features['kind'] = rooms, kinds
        features['moving_face'], features['fixed_face'] = faces[:, 0], faces[:, 1]
        return cls(travel, buried, features)

    def lifted(self, rise: float, push: Floats) -> Touch:
        """The same features seen from the pose measured moved `rise` along `push` (Δ)."""
        return Touch(self.travel, self.buried, self.features, rise, push)

    def __len__(self) -> int:
        return len(self.features)

    @property
    def gaps(self) -> Floats:
        """(k,) m along Δ from the pose seen from, each feature's."""
        out: Floats = self.features['gap'] - self.rise
        return out

    @property
    def normals(self) -> Floats:
        """(k, 3) unit, n . Δ >= 0: a gap changes by -n . dp / n . Δ."""
        return np.ascontiguousarray(self.features['normal'])

    @property
    def points(self) -> Floats:
        """(k, 3) the moving body's point at each feature, fixed frame (at the pose seen
        from)."""
        points = self.features['point']
        out: Floats = points.copy() if self.push is None else points + self.rise * self.push
        return out

    @property
    def rooms(self) -> Floats:
        """(k,) m: how far a slide keeps each feature one (its domain)."""
        return np.ascontiguousarray(self.features['room'])

    @property
    def kinds(self) -> Ints:
        """(k,) 0: moving vertex on fixed face, 1: the reverse, 2: edges."""
        return np.ascontiguousarray(self.features['kind'])

    @property
    def faces(self) -> Ints:
        """(k, 2) the triangles (moving, fixed) of each feature."""
        return np.column_stack([self.features['moving_face'], self.features['fixed_face']])


@dataclass(slots=True, eq=False)
class SweepPair:
    """The exact travel along Δ (fixed frame) of one settle's moving body onto its fixed
    body, with counters."""

    fixed: RigidBody
    moving: RigidBody
    push: Floats                      # (3,) unit Δ, fixed frame
    queries: int = 0                  # poses asked
    pairs: int = 0                    # triangle pairs evaluated
    _fixed: SweepBody = field(init=False, repr=False)
    _moving: SweepBody = field(init=False, repr=False)
    _fixed_view: _sweep.View = field(init=False, repr=False)
    _bounds: Floats = field(init=False, repr=False)
    # (STOPPERS, 2) the pairs (moving face, fixed face) that stopped `measure`'s searches
    # short, newest first, -1 past the last: the engine asks them first and keeps them
    _stoppers: Ints = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._fixed = sweep_body(self.fixed)
        self._moving = sweep_body(self.moving)
        self._fixed_view = self._fixed.view(self.push, -1)
        # how far a pose can travel before no contact can happen (the engine's
        # `travel_limit`): the moving body's bounding centre in its frame, the fixed
        # body's, the sum of their radii
        self._bounds = np.concatenate([self.moving.bound_centre, self.fixed.bound_centre,
                                       [self.fixed.bound_radius + self.moving.bound_radius]])
        self._stoppers = np.full((STOPPERS, 2), -1, dtype=np.int64)

    def _moving_view(self, pose: Pose) -> _sweep.View:
        return self._moving.view(pose[:3, :3].T @ self.push, 1)

    def travels(self, poses: Floats, behind: float = 0.0,
                limit: float = math.inf) -> tuple[Floats, np.ndarray]:
        """The travel along Δ from each of `poses` (k, 4, 4) (inf: none within `limit`),
        measured from each lowered by `behind` along -Δ; and (k,) True where that lowered
        pose is itself in collision (travel -inf: lower further). The poses share one
        orientation about Δ up to spins about it."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        if len(poses) == 0:
            return np.zeros(0), np.zeros(0, dtype=bool)
        out, buried, pairs = _sweep.travels(self._fixed_view, self._moving_view(poses[0]),
                                            poses, float(behind), 0.0, _finite(limit))
        self.queries += len(poses)
        self.pairs += pairs
        return np.frombuffer(out, dtype=np.float64).copy(), \
            np.frombuffer(buried, dtype=np.int8).astype(bool)

    def touch(self, pose: Pose, behind: float = 0.0, window: float = 0.0,
              limit: float = math.inf, short_of: float = -math.inf,
              seeds: Ints | None = None) -> Touch:
        """The travel from `pose` (as `travels`) and the features closing within `window`
        beyond it; the search stops as soon as the travel is known to be below `short_of`
        (the travel returned is then a gap below it, the travel at most that, and the
        features are partial). `seeds` (k, 2): pairs of triangles (moving face, fixed face)
        likely to close first, asked before the search so that it prunes from the start;
        they change how fast the answer comes, never the answer."""
        pose = np.ascontiguousarray(pose, dtype=np.float64)
        travel, buried, raw, pairs = _sweep.contacts(
            self._fixed_view, self._moving_view(pose), pose, float(behind), float(window),
            _finite(limit), float(short_of),
            None if seeds is None else np.ascontiguousarray(seeds, dtype=np.int64))
        self.queries += 1
        self.pairs += pairs
        return _touch(travel, bool(buried), raw)

    def measure(self, poses: Floats, needed: Floats, expected: Floats,
                windows: tuple[float, float], pool: tuple[Floats, Floats, Ints], moves: Floats,
                shift: Floats, reach: float, count: int, standoff: float, deepest: float,
                start: int = 0, seeds: Ints | None = None, cap: int = 0,
                keep: float = 0.0) -> tuple[int, int, Touch | None, bool]:
        """From `start` on, the first of `poses` (m, 4, 4) that none of its witnesses
        refutes (`first_unrefuted`, with `count` witnesses, each pose at the lateral offset
        `moves` (m, 3) + `shift` (3,) from where the pool was taken, and `standoff` the depth
        below a pose a pair is not counted at; none asked with `count` 0; before them, the
        pairs that stopped this pair's earlier searches short, the latest `STOPPERS`: the
        moves about a place run into the same part of the fixed body, of which the pool,
        taken near it, may name nothing) and whose search does not find it short of `needed`
        (m,): its index, `PLACE` and the travel from it with the features within its window
        beyond (the pose lowered first by twice the travel `expected` (m,) where that is
        negative, plus the standoff, and four times further while the lowered pose is
        buried); or its index and `LOST` where no contact lies along Δ from it; or (m,
        SHORT, None) where every pose is refuted or short; and whether the pose found is
        wide: its offset exceeds `reach` in a coordinate (the pool is too far to name what
        closes first there), its window then the second of `windows` (near, wide), the first
        elsewhere. A needed travel of +inf is passed over; -inf stops no search. A search
        starts from the pose's witnesses, or from `seeds` where none are asked. `cap` (0:
        none): of the features more than `keep` beyond the travel only the `cap` that close
        first are kept (ties kept), and the search prunes by them as by the window."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        gaps, slopes, faces = pool
        index, kind, travel, raw, queries, pairs, wide = _sweep.measure(
            self._fixed_view, self._moving_view(poses[0]), poses,
            np.ascontiguousarray(needed, dtype=np.float64),
            np.ascontiguousarray(expected, dtype=np.float64),
            float(windows[0]), float(windows[1]), float(reach),
            np.ascontiguousarray(gaps, dtype=np.float64),
            np.ascontiguousarray(slopes, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int64),
            np.ascontiguousarray(moves, dtype=np.float64),
            np.ascontiguousarray(shift, dtype=np.float64), int(count), float(standoff),
            float(deepest), self._bounds, int(start),
            None if seeds is None else np.ascontiguousarray(seeds, dtype=np.int64),
            int(cap), float(keep), self._stoppers)
        self.queries += queries
        self.pairs += pairs
        if kind != PLACE:
            return index, kind, None, wide
        return index, kind, _touch(travel, False, raw), wide

    def first_unrefuted(self, poses: Floats, needed: Floats, pool: tuple[Floats, Floats, Ints],
                        offsets: Floats, count: int, behind: float, deepest: float,
                        start: int = 0) -> tuple[int, Ints | None]:
        """The index of the first of `poses` (m, 4, 4), from `start` on, that none of its
        witnesses refutes, and those witnesses (c, 2) to seed its search; (m, None) when
        every pose is refuted. A pose whose
        travel `needed` (m,) is not finite is passed over (it cannot gain); one is refuted
        where a contact closes short of the travel it needs: the travel from it is no longer
        than any contact's gap, so it cannot go that far.

        The witnesses of a pose: the `count` features of the `pool` (gaps (k,), slopes (k, 3)
        over the lateral state, pairs of triangles (k, 2) as (moving face, fixed face)) that
        the pool's first-order model says close first after the pose's lateral `offsets`
        (m, 3) from where the pool was taken, first closing first (the least gap over the
        overlap of their shadows, a pair lying wholly more than `behind` below the pose not
        counting); then the vertices of their moving triangles, each onto whatever face of
        the fixed body lies under it (a face more than `deepest` above a vertex not
        counting), asked in turn until one closes short."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        if start >= len(poses):
            return len(poses), None
        gaps, slopes, faces = pool
        index, raw = _sweep.first_unrefuted(
            self._fixed_view, self._moving_view(poses[0]), poses,
            np.ascontiguousarray(needed, dtype=np.float64),
            np.ascontiguousarray(gaps, dtype=np.float64),
            np.ascontiguousarray(slopes, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int64),
            np.ascontiguousarray(offsets, dtype=np.float64), int(count), float(behind),
            float(deepest), int(start))
        # the engine sends no witnesses when every pose is refuted
        return index, (np.frombuffer(raw, dtype=np.int64).reshape(-1, 2) if raw else None)


def _touch(travel: float, buried: bool, raw: bytes) -> Touch:
    """The travel and the engine's features (bytes of its `Feature` structs) as a `Touch`."""
    return Touch(travel, buried, np.frombuffer(raw, dtype=FEATURE))


def _finite(limit: float) -> float:
    """The engine's limit: a large finite number stands for none."""
    return limit if math.isfinite(limit) else 1e300
