"""Triangle meshes in metres: loading and validating them, and the rigid bodies python-fcl
queries (`load`: files to checked trimesh meshes; `collision`: BVHs, per-triangle centres
and normals, boolean and contact queries; `rays`: the travel along a push by Embree
rays; `sweep`: the travel along a push, exactly, by the compiled swept-triangle search)."""
from .collision import CollisionPair, RigidBody
from .load import check_mesh, check_mesh_files, load_mesh, load_meshes, UNIT_SCALE, Units
from .rays import hidden_gap_m, RayPair
from .sweep import SweepPair

__all__ = ['Units', 'UNIT_SCALE', 'load_mesh', 'load_meshes', 'check_mesh', 'check_mesh_files',
           'RigidBody', 'CollisionPair', 'RayPair', 'SweepPair', 'hidden_gap_m']
