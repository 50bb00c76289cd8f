"""Rigid bodies for python-fcl and the two collision queries the settle needs.

A `RigidBody` is built once per mesh: an fcl BVH plus, per triangle, the centre and the
outward normal taken as the normalised mean of its three vertex normals (the patent's
choice). A `CollisionPair` holds the fixed reference and the moving body and answers:
- `collides(pose)`: boolean, stops at the first overlapping triangle pair (dichotomy);
- `contacts(pose)`: every overlapping triangle of the reference (contact analysis);
- `contact_points(pose)`: the same triangles with the points where the two surfaces cross.
Poses are (4, 4) `fixed_from_moving`; the fixed body sits at identity.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import threading
import time
import weakref

import fcl
import numpy as np
import trimesh

from kneeseat_core.geometry import TOL
from kneeseat_core.typed import Floats, Ints, Pose

__all__ = ['RigidBody', 'CollisionPair']

# Contacts a single query may report; a settle's contact patch is far smaller.
_MAX_CONTACTS = 100_000


@dataclass(frozen=True, slots=True, eq=False, weakref_slot=True)
class RigidBody:
    """A triangle mesh ready for collision queries (metres, the body's own frame)."""

    mesh: trimesh.Trimesh
    bvh: fcl.BVHModel
    centres: Floats     # (n, 3) triangle centres, m
    normals: Floats     # (n, 3) unit outward normals at the centres (mean vertex normals)
    vertices: Floats    # (m, 3) vertices, m (a plain array: no trimesh cache checks)
    centroid: Floats    # (3,) m, centre of the surface
    bound_centre: Floats  # (3,) m, centre of a sphere enclosing every vertex
    bound_radius: float   # m
    reach: float          # m, farthest vertex from the centroid
    faces: Ints           # (n, 3) vertex indices
    vertex_normals: Floats  # (m, 3) unit
    adjacency: tuple[Ints, Ints]   # CSR (indptr, indices) of edge neighbours
    edges: Ints           # (e, 2) vertex indices of each distinct edge
    face_edges: Ints      # (n, 3) each triangle's edges, indices into `edges`

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh) -> RigidBody:
        """Build the BVH and the per-triangle centres and normals of `mesh`."""
        vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        bvh = _bvh(vertices, faces)
        normals = np.asarray(mesh.vertex_normals)[faces].mean(axis=1)
        lengths = np.linalg.norm(normals, axis=1, keepdims=True)
        # A triangle whose vertex normals cancel (a knife edge) keeps its face normal.
        flat = lengths[:, 0] < TOL.normal_length
        normals[flat] = np.asarray(mesh.face_normals)[flat]
        lengths[flat] = 1.0
        centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        radius = float(np.sqrt(np.max(np.sum((vertices - centre) ** 2, axis=1))))
        centroid = np.asarray(mesh.centroid, dtype=np.float64)
        reach = float(np.sqrt(np.max(np.sum((vertices - centroid) ** 2, axis=1))))
        pairs = np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2)
        both = np.concatenate([pairs, pairs[:, ::-1]])
        order = np.argsort(both[:, 0], kind='stable')
        indptr = np.searchsorted(both[order, 0], np.arange(len(faces) + 1))
        return cls(mesh, bvh, np.asarray(mesh.triangles_center), normals / lengths,
                   vertices, centroid, centre, radius, reach, faces,
                   np.asarray(mesh.vertex_normals, dtype=np.float64),
                   (indptr, np.ascontiguousarray(both[order, 1])),
                   np.asarray(mesh.edges_unique, dtype=np.int64),
                   np.asarray(mesh.faces_unique_edges, dtype=np.int64))

    def edge_ends(self, triangles: Ints) -> Floats:
        """The distinct edges of `triangles` (k,) (repeats allowed): their end points
        (e, 2, 3), the body's frame."""
        out: Floats = self.vertices[self.edges[np.unique(self.face_edges[triangles])]]
        return out


_IDENTITY = fcl.Transform()
_THREAD = threading.local()


def _collision_object(body: RigidBody) -> fcl.CollisionObject:
    """python-fcl's object for `body`, made once per body and thread and shared by the
    pairs made there (made afresh for each pair it cost about 0.1 ms, a tenth of what a
    settle's python-fcl queries take); a query sets its transform first."""
    kept: weakref.WeakKeyDictionary[RigidBody, fcl.CollisionObject] | None = \
        getattr(_THREAD, 'objects', None)
    if kept is None:
        kept = _THREAD.objects = weakref.WeakKeyDictionary()
    found = kept.get(body)
    if found is None:
        found = kept[body] = fcl.CollisionObject(body.bvh, fcl.Transform())
    return found


def _bvh(vertices: Floats, faces: Ints) -> fcl.BVHModel:
    bvh = fcl.BVHModel()
    bvh.beginModel(len(faces), len(vertices))   # (triangles, vertices)
    bvh.addSubModel(vertices, faces)
    bvh.endModel()
    return bvh


@dataclass(slots=True, eq=False)
class CollisionPair:
    """The fixed reference and the moving body, with query counters."""

    fixed: RigidBody
    moving: RigidBody
    checks: int = 0             # queries answered so far
    fcl_s: float = 0.0          # wall time spent inside python-fcl
    _fixed_obj: fcl.CollisionObject = field(init=False, repr=False)
    _moving_obj: fcl.CollisionObject = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._fixed_obj = _collision_object(self.fixed)
        self._moving_obj = _collision_object(self.moving) if self.moving is not self.fixed \
            else fcl.CollisionObject(self.moving.bvh, fcl.Transform())

    def _query(self, pose: Pose, request: fcl.CollisionRequest) -> fcl.CollisionResult:
        # the objects are shared by the pairs of this thread (`_collision_object`): each
        # query places both
        self._fixed_obj.setTransform(_IDENTITY)
        self._moving_obj.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
        result = fcl.CollisionResult()
        start = time.perf_counter()
        fcl.collide(self._moving_obj, self._fixed_obj, request, result)
        self.fcl_s += time.perf_counter() - start
        self.checks += 1
        return result

    def collides(self, pose: Pose) -> bool:
        """True if the moving body at `pose` overlaps the fixed body."""
        return bool(self._query(pose, fcl.CollisionRequest()).is_collision)

    def contacts(self, pose: Pose) -> Floats:
        """Indices (k,) of the reference triangles overlapping the moving body at `pose`.

        fcl reports each contact as (o1, b1, o2, b2); which side is the reference is
        decided by object identity, never by argument order.
        """
        return np.unique(self.contact_points(pose)[0])

    def contact_points(self, pose: Pose) -> tuple[Ints, Floats]:
        """Every overlapping pair of triangles at `pose`: the reference triangle (k,) and the
        point (k, 3) m, fixed frame, where the two triangles cross (python-fcl's contact).
        """
        ids, _, points = self.crossings(pose)
        return ids, points

    def crossings(self, pose: Pose) -> tuple[Ints, Ints, Floats]:
        """Every overlapping pair of triangles at `pose`: the reference triangle (k,), the
        moving body's triangle (k,) and the point (k, 3) m, fixed frame, where they cross.

        fcl reports each contact as (o1, b1, o2, b2); which side is the reference is
        decided by object identity, never by argument order.
        """
        request = fcl.CollisionRequest(num_max_contacts=_MAX_CONTACTS, enable_contact=True)
        result = self._query(pose, request)
        fixed_geom = self.fixed.bvh
        sides = np.array([(c.b1, c.b2) if c.o1 is fixed_geom else (c.b2, c.b1)
                          for c in result.contacts], dtype=np.int64).reshape(-1, 2)
        points = np.array([c.pos for c in result.contacts], dtype=np.float64).reshape(-1, 3)
        return sides[:, 0], sides[:, 1], points
