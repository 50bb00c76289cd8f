"""The pose table: settled poses over a (flexion, varus) grid and everything that reads them
without touching a mesh or the settle.

`pose_table` (`PoseTable`, the interpolation), `format` (what a file holds, its hash, what
makes it valid), `io` (atomic writing, reading that refuses anything else) and `summary`
(what `kneeseat info`, `lookup --json` and `export` show). The ROS node serves tables
through this package alone.
"""
from .format import display_paths, mesh_entries, SCHEMA
from .io import read_table, with_hash, write_table
from .pose_table import arrays_sha256, Lookup, PoseTable
from .summary import describe, export_csv, lookup_json, status_map, write_text

__all__ = ['PoseTable', 'Lookup', 'arrays_sha256', 'read_table', 'write_table', 'with_hash',
           'SCHEMA', 'mesh_entries', 'display_paths', 'describe', 'status_map', 'lookup_json',
           'export_csv', 'write_text']
