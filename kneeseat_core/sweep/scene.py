"""The rigid bodies a sweep worker settles, rebuilt once per process from a small spec.

A `SceneSpec` names each body's mesh files (one path, or several combined into one rigid
body) and units, and carries each file's SHA-256, so it is small, picklable and hashable:
a chain job carries only it. `scene_bodies` builds the bodies, with their hierarchies for
python-fcl and for the exact travel, once per process and keeps the last scene. The sweep's
parent builds it first, validating every mesh (warnings appear once); a local pool's
workers are forked from the parent and start with it, and other workers build it again,
quietly. A worker that cannot read the paths (a remote Dask worker) finds the bytes shipped
to it by content (`register_mesh_copy`, kneeseat_core/cluster.py), and a long-lived worker
never reuses bodies of a mesh file that has since changed (the hashes are part of the
spec).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
import threading

import trimesh

from kneeseat_core.meshes import load_meshes, RigidBody, sweep_body, Units

__all__ = ['SceneSpec', 'scene_bodies', 'register_mesh_copy', 'scene_builds']


@dataclass(frozen=True, slots=True)
class SceneSpec:
    """What a worker needs to rebuild the rigid bodies (small, picklable, hashable).

    A body's meshes are one path, or a tuple of paths combined into one rigid body.
    """

    reference_mesh: str | tuple[str, ...]
    body_meshes: tuple[str | tuple[str, ...], ...]
    units: Units
    mesh_sha256: tuple[str, ...] = ()   # hex, one per file of `paths()`; () = paths only

    def groups(self) -> tuple[tuple[str, ...], ...]:
        """The mesh files of each body: the reference first, then the moving bodies."""
        return tuple((g,) if isinstance(g, str) else tuple(g)
                     for g in (self.reference_mesh, *self.body_meshes))

    def paths(self) -> tuple[str, ...]:
        """Every mesh file, in body order (the order of `mesh_sha256`)."""
        return tuple(p for g in self.groups() for p in g)


_SCENES: dict[SceneSpec, tuple[RigidBody, tuple[RigidBody, ...]]] = {}
_SCENES_LOCK = threading.Lock()     # Dask workers may run several chains in threads
_MESH_COPIES: dict[str, str] = {}   # SHA-256 -> local file with those bytes
_SCENE_BUILDS = 0
_BUILDERS = 2                       # threads building the bodies' hierarchies


def register_mesh_copy(sha256: str, path: str) -> None:
    """Let `scene_bodies` load the mesh with content `sha256` from local file `path`.

    Used on Dask workers, where the SceneSpec's paths may not exist (kneeseat_core/cluster.py).
    A registered copy is preferred to the spec's path: it is the content the client hashed.
    """
    _MESH_COPIES[sha256] = path


def scene_builds() -> int:
    """How many scenes this process has built (meshes loaded, BVHs made) so far."""
    return _SCENE_BUILDS


def _body(mesh: trimesh.Trimesh) -> RigidBody:
    """`mesh` as a rigid body with its hierarchies: python-fcl's and the exact travel's."""
    body = RigidBody.from_mesh(mesh)
    sweep_body(body)
    return body


def _mesh_source(spec: SceneSpec, index: int, path: str) -> str:
    if index < len(spec.mesh_sha256):
        return _MESH_COPIES.get(spec.mesh_sha256[index], path)
    return path


def scene_bodies(spec: SceneSpec, quiet: bool = True) -> tuple[RigidBody, tuple[RigidBody, ...]]:
    """The rigid bodies of `spec` with their hierarchies for the exact travel
    (`sweep_body`), built once per process and cached.

    Args:
        quiet: load without the warnings a mesh may get (a worker's load: the sweep's
            parent has validated every mesh); False for the parent's own.
    Raises:
        MeshError: a mesh is missing, unreadable or implausible (`load_mesh`).
    """
    global _SCENE_BUILDS
    with _SCENES_LOCK:
        if spec not in _SCENES:
            # the meshes are loaded in turn here (their warnings in order) while a body
            # loaded already gets its hierarchies on another thread: the engine builds its
            # own without the GIL (python-fcl holds it), so the start-up, which would leave
            # the other core idle, uses it for part of the time
            with ThreadPoolExecutor(max_workers=_BUILDERS) as builders:
                building, index = [], 0
                for group in spec.groups():
                    sources = [_mesh_source(spec, index + k, p) for k, p in enumerate(group)]
                    index += len(group)
                    building.append(builders.submit(_body, load_meshes(sources, spec.units,
                                                                       quiet)))
                bodies = tuple(b.result() for b in building)
            _SCENES.clear()          # one scene per worker at a time keeps memory flat
            _SCENES[spec] = (bodies[0], bodies[1:])
            _SCENE_BUILDS += 1
        return _SCENES[spec]
