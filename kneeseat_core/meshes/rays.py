"""The travel along the push measured directly, by rays (Embree through `embreex`).

How far a moving body can go along a direction Δ before it touches a fixed body is the
shortest of two sets of ray hits: from each vertex of the moving body along +Δ onto the
fixed body, and from each vertex of the fixed body along -Δ onto the moving body. One
cast of a few hundred rays answers what python-fcl answers by ten boolean queries in a
dichotomy. Rays from vertices do not see an edge crossing an edge: the gap that can hide
there is about the sagitta of the surface's turn across an edge (`hidden_gap_m`), and
python-fcl stays the judge where that matters (a start in collision, the settle's final
pose, the referee).

`RayBody` is one mesh's Embree scene, built once per body and process, and for the near
set the samples of its surface in a k-d tree and two grids of distance bounds, a coarse
one asked first and a fine one where it leaves a point near, filled as they are asked
(built when first needed). `RayPair` answers for one settle. `blocked`: whether
probes, each lifted along Δ, are in collision as given vertices see them (the proof of
rest asks it before python-fcl; a ray entering the other body short of the lift is a real
contact, so a probe it blocks is blocked; one it does not is left to python-fcl).
`crossed`: the same for edges, each a segment at the lifted probe (an edge that crosses a
face of the other body is a contact; these see an edge across an edge). `gaps`:
the gap field, every near ray's gap with the normal of the face it enters (the climb's
leap models the travel over a small lateral move from it).
`travel_from` (the travel by rays, `travel: rays`) casts only from the vertices near the
other body (the near set) and proves the set still holds before every answer, from how
far the body has moved since the set was drawn (`_moved`) and how far the vertices left
out were from the other body then: a vertex at distance d from the other surface cannot
touch it before some point of the body has moved by d. A ray whose first hit leaves the
other body may start inside it, and python-fcl decides: a closed mesh can fold over itself
(the total knee's insert does, by a fraction of a millimetre), so a back face met first
does not prove a vertex inside, and a vertex through an open sheet sees no back face at
all (where a mesh is open, a pose not known free is asked of python-fcl first).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
import math
import weakref

import numpy as np
from numpy.typing import NDArray
import trimesh

from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .collision import CollisionPair, RigidBody

__all__ = ['RayBody', 'RayPair', 'ray_body', 'hidden_gap_m']


# The surface is sampled for the near set's distances by its vertices and, on triangles
# with a longer edge than the sample spacing, a grid of points across them; the spacing is
# the median of the mesh's edges, at least this (every point of the surface is
# then within one spacing of a sample).
_SAMPLE_EDGE_M = 5e-4
# The distances are kept on a grid of cubes at least this wide about the body (wider for a
# body so large that the grid would hold more cubes than `_MAX_CELLS`), filled as points
# fall in them, out to this far from its bounding box (beyond: not near).
_CELL_M = 5e-4
_MAX_CELLS = 8_000_000
_PAD_M = 8e-3
# The coarse grid's cubes are this many fine cubes wide (`_DistanceGrid`).
_COARSE = 4
# A hit distance is trusted to this (m): the scenes are float32 about each body's centre,
# whose rounding at a knee's size is a few nanometres.
_RAY_NOISE_M = 1e-7


class RayBody:
    """One body's triangles as an Embree scene (float32, about the body's bound centre, so
    a nanometre is still resolved); for the near set, built when first asked, a k-d tree
    of points sampling its surface and its grids of distance bounds (`near`)."""

    def __init__(self, body: RigidBody) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        self.body = weakref.proxy(body)
        self.origin = body.bound_centre.copy()
        self.scene = rtcore_scene.EmbreeScene()
        local = (body.vertices - self.origin).astype(np.float32)
        TriangleMesh(scene=self.scene, vertices=local,
                     indices=body.faces.astype(np.int32))
        self.face_normals = np.asarray(body.mesh.face_normals, dtype=np.float64)
        self.closed = bool(body.mesh.is_watertight)
        self._grid: _DistanceGrid | None = None

    def first_hits(self, origins: Floats, direction: Floats,
                   reach: Floats | None = None) -> tuple[Floats, Ints]:
        """The first hit of a ray from each of `origins` (k, 3), body frame, along the unit
        `direction` (3,) or directions (k, 3): distances (k,) m (inf: no hit) and triangle
        indices (k,) (-1). With `reach` (k,) m each ray ends there (at least): a hit
        beyond may be missed, and a short ray costs Embree a few BVH nodes."""
        if len(origins) == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        o = (origins - self.origin).astype(np.float32)
        d = np.ascontiguousarray(np.broadcast_to(direction.astype(np.float32), o.shape))
        if reach is None:
            out = self.scene.run(o, d, output=1)
        else:               # rounded up to float32: a ray never ends short of its reach
            far = np.nextafter(reach.astype(np.float32), np.float32(np.inf))
            out = self.scene.run(o, d, dists=far, output=1)
        dist = out['tfar'].astype(np.float64)
        prim = out['primID'].astype(np.int64)
        dist[prim < 0] = math.inf      # a miss (Embree leaves its far distance there)
        return dist, prim

    def near(self, points: Floats, within: float) -> tuple[Ints, Floats]:
        """The indices of `points` (k, 3), body frame, that may lie within `within` m of
        the surface, and a lower bound on each one's distance from it (m)
        (`_DistanceGrid.near`)."""
        if self._grid is None:
            self._grid = _DistanceGrid(self.body)
        return self._grid.near(points, within)


class _DistanceGrid:
    """Lower bounds on the distance to one body's surface, on grids of cubes about it
    filled as points fall in them, from a k-d tree of points sampling the surface: a
    coarse grid first, whose cubes are `_COARSE` fine cubes wide, and the fine grid only
    for the points the coarse bound leaves near (most of a body is far from the other, and
    a fine cube costs a k-d tree query as a coarse one does)."""

    def __init__(self, body: RigidBody) -> None:
        from scipy.spatial import cKDTree
        edges = np.linalg.norm(body.vertices[body.faces]
                               - body.vertices[np.roll(body.faces, 1, axis=1)], axis=2)
        self.spacing_m = max(_SAMPLE_EDGE_M, float(np.percentile(edges, 50.0)))
        self.tree = cKDTree(_surface_samples(body.vertices, body.faces, edges.max(axis=1),
                                             self.spacing_m))
        self.pad_m = _PAD_M + self.spacing_m
        self.low = body.vertices.min(axis=0) - self.pad_m
        extent = body.vertices.max(axis=0) + self.pad_m - self.low
        cell_m = max(_CELL_M, float(np.prod(extent) / _MAX_CELLS) ** (1.0 / 3.0))
        self.fine = _Cubes(cell_m, self.low, extent, self.fill)
        self.coarse = _Cubes(_COARSE * cell_m, self.low, extent, self.fill)

    def near(self, points: Floats, within: float) -> tuple[Ints, Floats]:
        """The indices of `points` (k, 3), body frame, that may lie within `within` m of
        the surface, and a lower bound on each one's distance from it (m): from the cube
        it lies in, the distance of the cube's centre to the nearest sample less the
        samples' spacing and the cube's half diagonal; the larger of the coarse and the
        fine cube's bound where the coarse one is under `within` (the answer does not
        depend on which cubes earlier calls filled)."""
        if within > self.pad_m - self.spacing_m - self.fine.reach_m:
            raise ValueError(f'a near set {within} m wide is wider than the distance grid')
        ijk = np.floor((points - self.low) / self.fine.cell_m).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < self.fine.shape), axis=1)
        idx = np.flatnonzero(inside)
        coarse = self.coarse.bounds(ijk[idx] // _COARSE)
        keep = coarse < within
        idx, coarse = idx[keep], coarse[keep]
        bound = np.maximum(self.fine.bounds(ijk[idx]), coarse)
        near = bound < within
        return idx[near], bound[near].astype(np.float64)

    def fill(self, centres: Floats, reach_m: float) -> Floats:
        """Lower bounds (m) on the distance to the surface from any point within `reach_m`
        of each of `centres` (k, 3): the nearest sample's distance less the samples'
        spacing and the reach (at least 0); infinite where that is beyond the padding less
        the spacing, wider than any near set."""
        dist, _ = self.tree.query(centres, k=1, distance_upper_bound=self.pad_m + reach_m)
        return np.maximum(dist - self.spacing_m - reach_m, 0.0)


class _Cubes:
    """One grid of cubes over the box from `low` (m, 3) `extent` wide, each with its bound
    (NaN: not known yet) as `fill` gives it from the cube's centre and half diagonal."""

    def __init__(self, cell_m: float, low: Floats, extent: Floats,
                 fill: Callable[[Floats, float], Floats]) -> None:
        self.cell_m = cell_m
        self.low = low
        self.fill = fill
        self.reach_m = 0.5 * math.sqrt(3.0) * cell_m       # a point from the cube's centre
        self.shape = tuple(int(n) for n in np.ceil(extent / cell_m))
        self.cells = np.full(int(np.prod(self.shape)), np.nan, dtype=np.float32)

    def bounds(self, ijk: Ints) -> NDArray[np.float32]:
        """The bounds of the cubes `ijk` (k, 3) (float32, as kept), the unknown ones filled
        first."""
        flat: Ints = np.asarray(np.ravel_multi_index(tuple(ijk.T), self.shape))
        bound: NDArray[np.float32] = self.cells[flat]
        unknown = np.isnan(bound)
        if unknown.any():
            cells = np.unique(flat[unknown])
            centres = (np.stack(np.unravel_index(cells, self.shape), axis=1) + 0.5) \
                * self.cell_m + self.low
            self.cells[cells] = self.fill(centres, self.reach_m)
            bound = self.cells[flat]
        return bound


def _surface_samples(vertices: Floats, faces: Ints, longest: Floats,
                     spacing: float) -> Floats:
    """The vertices, and on each triangle whose longest edge exceeds `spacing` the corners
    of its division into n x n similar triangles with edges no longer than `spacing`."""
    out = [vertices]
    parts = np.ceil(longest / spacing).astype(np.int64)
    for n in np.unique(parts[parts > 1]):
        tri = vertices[faces[parts == n]]                   # (k, 3, 3)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing='ij')
        keep = (i + j) <= n
        a, b = (i[keep] / n)[:, None], (j[keep] / n)[:, None]   # (m, 1)
        pts = tri[:, None, 0] + a[None] * (tri[:, None, 1] - tri[:, None, 0]) \
            + b[None] * (tri[:, None, 2] - tri[:, None, 0])
        out.append(pts.reshape(-1, 3))
    return np.concatenate(out)


_RAY_BODIES: weakref.WeakKeyDictionary[RigidBody, RayBody] = weakref.WeakKeyDictionary()


def ray_body(body: RigidBody) -> RayBody:
    """The body's `RayBody`, built on first use and kept while the body lives."""
    found = _RAY_BODIES.get(body)
    if found is None:
        found = _RAY_BODIES[body] = RayBody(body)
    return found


def hidden_gap_m(*meshes: trimesh.Trimesh) -> tuple[float, float]:
    """How wide a gap vertex rays can miss between the `meshes` (m): the median and the
    99th percentile over the edges of all of them.

    Where an edge of one mesh first touches an edge of the other, no vertex touches yet;
    the nearest vertices stand off by about a quarter of an edge times the angle the
    surface turns across it (the sagitta of that turn). On a knee's articular surfaces the
    median is a few micrometres; rims and creases, where the surfaces do not meet, make
    the upper tail.
    """
    bounds = []
    for mesh in meshes:
        edges = mesh.face_adjacency_edges
        length = np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]],
                                axis=1)
        bounds.append(0.25 * length * np.asarray(mesh.face_adjacency_angles))
    every = np.concatenate(bounds) if bounds else np.zeros(0)
    if len(every) == 0:
        return 0.0, 0.0
    return float(np.median(every)), float(np.percentile(every, 99.0))


@dataclass(slots=True, eq=False)
class _NearSet:
    """The vertices of each body near the other where the set was drawn (`ref`), each with
    a lower bound on its distance from the other body then (m)."""

    ref: Pose
    moving: Floats           # (k, 3) moving frame
    moving_bound: Floats     # (k,)
    fixed: Floats            # (j, 3) fixed frame
    fixed_bound: Floats      # (j,)


# The last near set of each pair of bodies, kept while both live: the settles of a table's
# neighbouring cells start where the last one ended.
_PairSets = weakref.WeakKeyDictionary[RigidBody, weakref.WeakKeyDictionary[RigidBody, _NearSet]]
_NEAR_SETS: _PairSets = weakref.WeakKeyDictionary()
# The same for the gap field's vertices (`RayPair.gaps`).
_GAP_SETS: _PairSets = weakref.WeakKeyDictionary()


@dataclass(slots=True, eq=False)
class RayPair:
    """The travel along Δ of one settle's moving body onto its fixed body, by rays from the
    near set (module docstring).

    The near set holds the vertices of each body within `margin_m` of the other where it
    was drawn, each with a lower bound on that distance. A cast at a pose the body reached
    since, by moving each of its points at most δ (`_moved`), uses only the vertices whose
    bound less δ is inside a window μ: no other vertex can touch before the body travels μ
    along Δ, so a first hit within μ is the travel; beyond it, the window doubles. Where a
    ray's first hit leaves the other body, python-fcl decides whether the pose is in
    collision (module docstring). The set is drawn again where the body has moved by half the
    margin since, and kept for the next settle of the same pair.
    """

    pair: CollisionPair
    push: Floats                 # (3,) unit Δ, fixed frame
    margin_m: float              # the near set: vertices nearer than this to the other body
    window_m: float              # the first cast's window μ (m of travel)
    casts: int = 0               # casts made
    rays: int = 0                # rays cast
    draws: int = 0               # near sets drawn
    _fixed: RayBody = field(init=False, repr=False)
    _moving: RayBody = field(init=False, repr=False)
    _closed: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._fixed = ray_body(self.pair.fixed)
        self._moving = ray_body(self.pair.moving)
        self._closed = self._fixed.closed and self._moving.closed

    # ---- the near set -------------------------------------------------------------------
    @property
    def _near(self) -> _NearSet | None:
        return self._kept(_NEAR_SETS)

    def _kept(self, sets: _PairSets) -> _NearSet | None:
        """The set `sets` keeps for this pair of bodies, if any."""
        found = sets.get(self.pair.moving)
        return None if found is None else found.get(self.pair.fixed)

    def _keep(self, sets: _PairSets, found: _NearSet) -> _NearSet:
        """Keep `found` in `sets` for this pair of bodies (for the next settles)."""
        sets.setdefault(self.pair.moving, weakref.WeakKeyDictionary())[self.pair.fixed] = found
        return found

    def _draw(self, pose: Pose) -> _NearSet:
        """Draw the near set at `pose` (the vertices left out are at least the margin from
        the other body)."""
        rot, t = pose[:3, :3], pose[:3, 3]
        moving = self.pair.moving.vertices
        keep_m, bound_m = self._fixed.near(moving @ rot.T + t, self.margin_m)
        fixed = self.pair.fixed.vertices
        keep_f, bound_f = self._moving.near((fixed - t) @ rot, self.margin_m)
        self.draws += 1
        return self._keep(_NEAR_SETS, _NearSet(pose.copy(), moving[keep_m], bound_m,
                                               fixed[keep_f], bound_f))

    def _moved(self, near: _NearSet | None, pose: Pose) -> float:
        """How far any point of the moving body may have moved since `near` was drawn (its
        centroid's displacement plus the turn times the body's reach; inf: none drawn)."""
        if near is None:
            return math.inf
        ref, moving = near.ref, self.pair.moving
        rel = pose[:3, :3] @ ref[:3, :3].T
        cos = max(-1.0, min(1.0, 0.5 * (float(np.trace(rel)) - 1.0)))
        a = (pose[:3, :3] - ref[:3, :3]) @ moving.centroid + pose[:3, 3] - ref[:3, 3]
        return math.sqrt(float(a @ a)) + math.acos(cos) * moving.reach

    # ---- casting --------------------------------------------------------------------------
    def _cast(self, near: _NearSet, pose: Pose, window: float,
              moved: float) -> tuple[float, bool]:
        """One cast at `pose` from the vertices of `near` that may be within `window` of
        the other body (their bound less `moved`): the travel to the first hit that enters
        the other body, and whether some ray's first hit leaves it instead."""
        rot, t = pose[:3, :3], pose[:3, 3]
        up = near.moving[near.moving_bound < window + moved] @ rot.T + t
        d1, p1 = self._fixed.first_hits(up, self.push)
        down_dir = -(rot.T @ self.push)
        down = (near.fixed[near.fixed_bound < window + moved] - t) @ rot
        d2, p2 = self._moving.first_hits(down, down_dir)
        leaves1 = (p1 >= 0) & (self._fixed.face_normals[np.maximum(p1, 0)] @ self.push > 0.0)
        leaves2 = (p2 >= 0) & (self._moving.face_normals[np.maximum(p2, 0)] @ down_dir > 0.0)
        travel = min(float(np.min(d1[~leaves1], initial=math.inf)),
                     float(np.min(d2[~leaves2], initial=math.inf)))
        self.casts += 1
        self.rays += len(up) + len(down)
        return travel, bool(leaves1.any() or leaves2.any())

    def blocked(self, moving: Floats, fixed: Floats, poses: Floats, lifts: Floats) -> Bools:
        """For each pose of `poses` (m, 4, 4): True when a ray from one of the vertices
        `moving` (k, 3, moving frame) along +Δ, or from one of `fixed` (j, 3, fixed frame)
        along -Δ, enters the other body short of the pose's lift (`lifts` (m,), by more than
        the rays' rounding `_RAY_NOISE_M`): the surfaces meet before the lift, so the body
        there, lifted, is in collision. False proves nothing (the vertices left out, an edge
        crossing an edge, a ray that starts inside; a back face met first is not taken for
        inside: a ray from outside meets one where a closed mesh folds over itself, as the
        total knee's insert does). One cast of every vertex at every pose with a lift
        beyond the rounding, each ray ending at its pose's lift."""
        out = np.zeros(len(poses), dtype=bool)
        reach = lifts - _RAY_NOISE_M
        asked = np.flatnonzero(reach > 0.0)
        if len(asked) == 0:
            return out
        rot, t = poses[asked, :3, :3], poses[asked, :3, 3]
        up = (moving[None] @ rot.transpose(0, 2, 1) + t[:, None]).reshape(-1, 3)
        down = ((fixed[None] - t[:, None]) @ rot).reshape(-1, 3)
        down_dirs = np.repeat(-(self.push @ rot), len(fixed), axis=0)
        for body, origins, dirs, of in ((self._fixed, up, self.push,
                                         np.repeat(asked, len(moving))),
                                        (self._moving, down, down_dirs,
                                         np.repeat(asked, len(fixed)))):
            if len(origins) == 0:
                continue
            ray_reach = reach[of]
            dist, prim = body.first_hits(origins, dirs, ray_reach)
            hit = np.flatnonzero((prim >= 0) & (dist < ray_reach))
            facing = np.einsum('ij,ij->i', body.face_normals[prim[hit]],
                               np.broadcast_to(dirs, origins.shape)[hit])
            out[of[hit[facing < 0.0]]] = True
            self.rays += len(origins)
        self.casts += 1
        return out

    def crossed(self, moving_edges: Floats, fixed_edges: Floats, poses: Floats) -> Bools:
        """For each pose of `poses` (m, 4, 4): True when one of the segments `moving_edges`
        (k, 2, 3, moving frame) crosses a face of the fixed body there, or one of
        `fixed_edges` (j, 2, 3, fixed frame) a face of the moving body, by more than the
        rays' rounding `_RAY_NOISE_M` (`_crossing`, checked in double precision): the
        surfaces cross, so the body at that pose is in collision. Where two surfaces
        cross, an edge of one crosses a face of the other, so these see the contacts of an
        edge across an edge that vertex rays miss. False proves nothing (the edges left
        out, a first face met that fails the check). One cast of every segment at every
        pose."""
        out = np.zeros(len(poses), dtype=bool)
        if len(poses) == 0 or not (len(moving_edges) or len(fixed_edges)):
            return out
        rot, t = poses[:, :3, :3], poses[:, :3, 3]
        into_fixed = moving_edges.reshape(-1, 3)[None] @ rot.transpose(0, 2, 1) + t[:, None]
        into_moving = (fixed_edges.reshape(-1, 3)[None] - t[:, None]) @ rot
        for body, ends, count in ((self._fixed, into_fixed, len(moving_edges)),
                                  (self._moving, into_moving, len(fixed_edges))):
            if count == 0:
                continue
            ends = ends.reshape(-1, 2, 3)                   # (m * count, 2, 3)
            start, span = ends[:, 0], ends[:, 1] - ends[:, 0]
            length = np.sqrt(np.einsum('ij,ij->i', span, span))
            cast = np.flatnonzero(length > 0.0)             # a degenerate edge has no ray
            _, prim = body.first_hits(start[cast], span[cast] / length[cast, None],
                                      length[cast])
            hit = cast[prim >= 0]
            prim = prim[prim >= 0]
            real = _crossing(body.body.vertices, body.body.faces, prim, start[hit],
                             ends[hit, 1])
            out[hit[real] // count] = True
            self.rays += len(start)
        self.casts += 1
        return out

    def gaps(self, pose: Pose, within_m: float) -> tuple[Floats, Floats, Floats]:
        """The gap field at `pose`: every ray (+Δ from the moving body's vertices, -Δ from
        the fixed body's) that enters the other body within `within_m`. Returns the gaps
        (k,) m, the unit normal (k, 3, fixed frame) of the face each ray enters and the
        point on the moving body's surface where the ray starts or ends (k, 3, fixed
        frame). The rays are cast from the vertices whose gap was under the margin where
        they were last drawn (`_gap_draw`: one cast from every vertex, drawn again where
        the body has moved by half the margin since); a vertex left out may have come
        nearer on a steep slope, and python-fcl judges every pose the field proposes."""
        found = self._kept(_GAP_SETS)
        if found is None or self._moved(found, pose) > 0.5 * self.margin_m:
            found = self._gap_draw(pose)
        (up, d1, p1), (down_dir, d2, p2) = self._cast_both(pose, found.moving, found.fixed,
                                                           within_m)
        n1 = self._fixed.face_normals[np.maximum(p1, 0)]
        in1 = (p1 >= 0) & (d1 < within_m) & (n1 @ self.push < 0.0)
        n2 = self._moving.face_normals[np.maximum(p2, 0)]
        in2 = (p2 >= 0) & (d2 < within_m) & (n2 @ down_dir < 0.0)
        return (np.concatenate([d1[in1], d2[in2]]),
                np.concatenate([n1[in1], n2[in2] @ pose[:3, :3].T]),
                np.concatenate([up[in1], found.fixed[in2] - d2[in2, None] * self.push]))

    def _gap_draw(self, pose: Pose) -> _NearSet:
        """The vertices of both bodies whose rays along ±Δ enter the other body within the
        margin at `pose` (bounds: their gaps then), kept for the next settles of the pair."""
        moving, fixed = self.pair.moving.vertices, self.pair.fixed.vertices
        (_, d1, _), (_, d2, _) = self._cast_both(pose, moving, fixed, self.margin_m)
        near1, near2 = d1 < self.margin_m, d2 < self.margin_m
        return self._keep(_GAP_SETS, _NearSet(pose.copy(), moving[near1], d1[near1],
                                              fixed[near2], d2[near2]))

    def _cast_both(self, pose: Pose, moving: Floats, fixed: Floats, reach_m: float
                   ) -> tuple[tuple[Floats, Floats, Ints], tuple[Floats, Floats, Ints]]:
        """One cast at `pose`, no ray longer than `reach_m`: along +Δ from the points
        `moving` (the moving body's frame) onto the fixed body, and along -Δ from the points
        `fixed` onto the moving body (in its frame). Returns (the rays' origins, fixed
        frame; distances; primitives hit, -1 for none) for the first, and (the ray
        direction in the moving frame; distances; primitives) for the second."""
        rot, t = pose[:3, :3], pose[:3, 3]
        up = moving @ rot.T + t
        d1, p1 = self._fixed.first_hits(up, self.push, np.full(len(up), reach_m))
        down_dir = -(rot.T @ self.push)
        d2, p2 = self._moving.first_hits((fixed - t) @ rot, down_dir,
                                         np.full(len(fixed), reach_m))
        self.casts += 1
        self.rays += len(up) + len(fixed)
        return (up, d1, p1), (down_dir, d2, p2)

    def travel_from(self, pose: Pose, limit_m: float, known_free: bool = False) -> float | None:
        """The travel along Δ from `pose` to the first contact (inf: none within
        `limit_m`), or None when `pose` is itself in collision. Where either mesh is open
        and `pose` is not `known_free`, python-fcl is asked first: a vertex that has
        passed through an open sheet sees no back face."""
        if not (known_free or self._closed) and self.pair.collides(pose):
            return None
        asked = not self._closed and not known_free
        base, done, window = pose, 0.0, self.window_m
        near = self._near
        while True:
            moved = self._moved(near, base)
            if near is None or moved > 0.5 * self.margin_m:   # loose: draw it here
                near = self._draw(base)
                moved = 0.0
            room = self.margin_m - moved       # no vertex left out touches within it
            window = min(window, room)
            travel, inside = self._cast(near, base, window, moved)
            if inside and not asked:
                asked = True
                if done == 0.0 and self.pair.collides(base):
                    return None
            if travel <= window:
                return done + travel
            if window < room:                  # nothing within the window: widen it
                window *= 2.0
                continue
            if done + room > limit_m:
                return math.inf
            # nothing touches within the room: go on from there
            base = base.copy()
            base[:3, 3] += room * self.push
            done += room
            window = self.window_m


def _crossing(vertices: Floats, faces: Ints, triangles: Ints, a: Floats, b: Floats) -> Bools:
    """(k,) True where the segment from a[i] to b[i] (k, 3) crosses triangle
    `triangles[i]` of the mesh (`vertices`, `faces`) with a margin of `_RAY_NOISE_M`, in
    double precision: its ends that far on either side of the triangle's plane, and the
    point where it crosses that far inside each of the triangle's edges."""
    tri = vertices[faces[triangles]]
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = np.cross(v1 - v0, v2 - v0)
    with np.errstate(divide='ignore', invalid='ignore'):
        unit = normal / np.sqrt(np.einsum('ij,ij->i', normal, normal))[:, None]
        da = np.einsum('ij,ij->i', unit, a - v0)
        db = np.einsum('ij,ij->i', unit, b - v0)
        out: Bools = ((da > _RAY_NOISE_M) & (db < -_RAY_NOISE_M)) \
            | ((da < -_RAY_NOISE_M) & (db > _RAY_NOISE_M))
        point = a + (da / (da - db))[:, None] * (b - a)
        for p, q in ((v0, v1), (v1, v2), (v2, v0)):
            edge = q - p
            inward = np.cross(unit, edge) / np.sqrt(np.einsum('ij,ij->i', edge, edge))[:, None]
            out &= np.einsum('ij,ij->i', inward, point - p) > _RAY_NOISE_M
    return out
