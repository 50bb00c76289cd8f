"""Triangle meshes in metres: loading and validating them, and the rigid bodies python-fcl
queries (`load`: files to checked trimesh meshes; `collision`: BVHs, per-triangle centres
and normals, boolean and contact queries; `sweep`: the travel along a push, exactly, by
the compiled swept-triangle search)."""
from .collision import CollisionPair, RigidBody
from .load import check_mesh, check_mesh_files, load_mesh, load_meshes, UNIT_SCALE, Units
from .sweep import sweep_body, SweepPair

__all__ = ['Units', 'UNIT_SCALE', 'load_mesh', 'load_meshes', 'check_mesh', 'check_mesh_files',
           'RigidBody', 'CollisionPair', 'SweepPair', 'sweep_body']
