"""The real total knee's full table (issue 3, "Show" list): converged cells, no penetration.

The table is built once per module with `kneeseat build config/tka_dm.yaml` (the patent
grid: flexion 0 to -90, varus -10 to +10, 1 degree; 2 workers). Penetration is then
checked with python-fcl objects made here from the STL files, using nothing of the settle
or of `CollisionPair`: at every cell the moving body, moved back by the resolution along
its push, must not touch the femoral component, and at every converged cell, moved one
resolution further, it must (it rests in contact). Skipped when ../shared/data/tka_dm is
absent.
"""
from __future__ import annotations

from collections.abc import Iterator
import math
from pathlib import Path

import fcl
import numpy as np
import pytest
import trimesh

from kneeseat_core.cli import main
from kneeseat_core.geometry import matrix_from_quat, pose_from
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.table import PoseTable, read_table
from kneeseat_core.typed import Floats, Pose

REPO = Path(__file__).resolve().parents[1]
TKA = REPO.parent / 'shared' / 'data' / 'tka_dm'
CONFIG = REPO / 'config' / 'tka_dm.yaml'
RESOLUTION_M = 1e-4
BISECT_TOL_M = 2e-6         # resolution of the penetration estimate

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (TKA / 'femoral_component.stl').is_file(),
                       reason=f'total-knee meshes not found at {TKA} (../shared/data/tka_dm '
                       'next to the repository); they are not shipped in the repo'),
]


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[KneeConfig, PoseTable]]:
    """The config and the full TKA table, built once through the CLI (2 workers)."""
    out = tmp_path_factory.mktemp('tka') / 'tka_dm.npz'
    assert main(['build', str(CONFIG), '--out', str(out), '--workers', '2', '--quiet']) == 0
    config = load_config(CONFIG)
    meshes = {config.reference.name: config.reference.mesh}
    meshes.update({b.name: b.mesh for b in config.bodies})
    yield config, read_table(out, meshes=meshes)      # also checks the recorded mesh hashes


class Probe:
    """python-fcl objects of our own: the fixed reference and one moving body."""

    def __init__(self, fixed: Path, moving: Path) -> None:
        self.fixed = self._object(fixed)
        self.moving = self._object(moving)

    @staticmethod
    def _object(path: Path) -> fcl.CollisionObject:
        mesh = trimesh.load_mesh(path, process=False)
        bvh = fcl.BVHModel()
        bvh.beginModel(len(mesh.vertices), len(mesh.faces))
        bvh.addSubModel(np.asarray(mesh.vertices, dtype=np.float64),
                        np.asarray(mesh.faces, dtype=np.int64))
        bvh.endModel()
        return fcl.CollisionObject(bvh, fcl.Transform())

    def collides(self, fixed_from_moving: Pose) -> bool:
        self.moving.setTransform(fcl.Transform(fixed_from_moving[:3, :3],
                                               fixed_from_moving[:3, 3]))
        return fcl.collide(self.moving, self.fixed, fcl.CollisionRequest(),
                           fcl.CollisionResult()) > 0

    def penetration(self, pose: Pose, push: Floats, limit_m: float) -> float:
        """How far (m) `pose` must move back along -push to be free; 0 if free already.

        Returns `math.inf` when it is still colliding after backing out `limit_m`.
        """
        def back(s: float) -> Pose:
            out = pose.copy()
            out[:3, 3] -= s * push
            return out

        if not self.collides(pose):
            return 0.0
        if self.collides(back(limit_m)):
            return math.inf
        lo, hi = 0.0, limit_m            # colliding at lo, free at hi
        while hi - lo > BISECT_TOL_M:
            mid = 0.5 * (lo + hi)
            if self.collides(back(mid)):
                lo = mid
            else:
                hi = mid
        return hi


def test_tka_table_converges_on_99_percent(built: tuple[KneeConfig, PoseTable]) -> None:
    config, table = built
    assert table.position_m.shape == (2, 91, 21, 3)
    per_body = {name: float(table.converged[b].mean()) for b, name in enumerate(table.bodies)}
    overall = float(table.converged.mean())
    print(f'TKA converged: {100 * overall:.2f}% overall, '
          + ', '.join(f'{n} {100 * c:.2f}%' for n, c in per_body.items()))
    for b, name in enumerate(table.bodies):
        bad = np.argwhere(~table.converged[b])
        if len(bad):
            cells = [(round(math.degrees(table.flexion_rad[i])),
                      round(math.degrees(table.varus_rad[j]))) for i, j in bad]
            print(f'  {name} not converged at (flexion, varus) deg: {cells}')
    assert overall >= 0.99
    assert per_body['patella'] == 1.0
    # Honest failures sit at the grid's corner (extreme varus, deep flexion), not inside.
    tibia_bad = np.argwhere(~table.converged[0])
    assert all(abs(math.degrees(table.varus_rad[j])) >= 8.0 for _, j in tibia_bad)


def test_tka_no_penetration_beyond_resolution(built: tuple[KneeConfig, PoseTable]) -> None:
    config, table = built
    worst: dict[str, tuple[float, tuple[float, float]]] = {}
    for b, spec in enumerate(config.bodies):
        probe = Probe(config.reference.mesh, spec.mesh)
        # a varus-free body holds the same pose in every varus column: check it once
        columns = [len(table.varus_rad) // 2] if spec.varus_fraction == 0.0 else \
            range(len(table.varus_rad))
        depth = np.zeros((len(table.flexion_rad), len(table.varus_rad)))
        free_back = np.ones_like(depth, dtype=bool)
        touches = np.ones_like(depth, dtype=bool)   # converged: one T2 further collides
        for i, flexion in enumerate(table.flexion_rad):
            for j in columns:
                push = config.push(spec, flexion, table.varus_rad[j])
                pose = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                                 table.position_m[b, i, j])
                depth[i, j] = probe.penetration(pose, push, 10 * RESOLUTION_M)
                back = pose.copy()
                back[:3, 3] -= RESOLUTION_M * push
                free_back[i, j] = not probe.collides(back)
                if table.converged[b, i, j]:
                    ahead = pose.copy()
                    ahead[:3, 3] += RESOLUTION_M * push
                    touches[i, j] = probe.collides(ahead)
        i, j = np.unravel_index(np.argmax(depth), depth.shape)
        worst[spec.name] = (float(depth[i, j]), (math.degrees(table.flexion_rad[i]),
                                                 math.degrees(table.varus_rad[j])))
        touching = int((depth[:, list(columns)] > 0.0).sum())
        print(f'{spec.name}: max penetration estimate {depth.max() * 1e3:.4f} mm at '
              f'(flexion, varus) {worst[spec.name][1]} deg; {touching} of '
              f'{depth[:, list(columns)].size} cells collide at the exact pose '
              '(within the resolution band)')
        assert free_back.all(), f'{spec.name}: a cell still collides after backing off T2'
        assert depth.max() <= RESOLUTION_M
        assert touches.all(), f'{spec.name}: a converged cell floats more than T2 above'
