"""The node's topic names and diagnostics name, in one place.

The node's own names are relative, so they follow its namespace (`-r __ns:=/left` gives
`/left/knee/pose`) and remapping; `/diagnostics` and `/tf` are absolute, where every ROS
tool expects them. Tools that run beside a node at the root namespace (replay, the bag
maker, the demo's reader) use `at_root(name)`: `/knee/pose`, as recorded in a bag.
"""
from __future__ import annotations

__all__ = ['POSE', 'JOINT_STATES', 'MARKERS', 'DIAGNOSTICS', 'TF', 'TRACKER_FEMUR',
           'TRACKER_TIBIA', 'STATUS_NAME', 'body_pose', 'body_world_pose', 'at_root']

POSE = 'knee/pose'                       # in: tibia orientation in the reference frame
JOINT_STATES = 'knee/joint_states'       # in: flexion and varus joints (rad)
MARKERS = 'knee/markers'                 # out: mesh markers of every body
DIAGNOSTICS = '/diagnostics'
TF = '/tf'
TRACKER_FEMUR = 'tracker/femur/pose'     # in (tracker mode): thigh marker cluster, world
TRACKER_TIBIA = 'tracker/tibia/pose'     # in (tracker mode): shank marker cluster, world
STATUS_NAME = 'kneeseat table_server'    # the node's DiagnosticStatus name


def body_pose(body: str) -> str:
    """out: the pose of moving body `body` in the reference frame."""
    return f'knee/{body}/pose'


def body_world_pose(body: str) -> str:
    """out (tracker mode): the pose of `body` (or the reference) in the world frame."""
    return f'knee/{body}/world_pose'


def at_root(name: str) -> str:
    """`name` as a node at the root namespace resolves it ('knee/pose' -> '/knee/pose')."""
    return name if name.startswith('/') else '/' + name
