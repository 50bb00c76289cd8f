"""The real total knee's full table: which cells converge and why not, rest verified by the
referee, no penetration.

The table is built once per module with `kneeseat build config/tka_dm.yaml` (the patent
grid: flexion 0 to -90, varus -10 to +10, 1 degree; 2 workers). `kneeseat verify --sample
60` then judges cells spread over the grid with the independent referee. Penetration is
checked with python-fcl objects made here from the STL files, using nothing of the settle
or of `CollisionPair`: at every cell the moving body, moved back by the resolution along
its push, must not touch the femoral component, and at every converged cell, moved one
resolution further, it must (it rests in contact). Skipped when ../shared/data/tka_dm is
absent.
"""
from __future__ import annotations

from collections.abc import Iterator
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import fcl_collides, fcl_object, REPO, SHARED_DATA
from kneeseat_core.cli import main
from kneeseat_core.sweep import continuity
from kneeseat_core.geometry import matrix_from_quat, pose_from
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.status import AT_REST, Status
from kneeseat_core.table import PoseTable, read_table, status_map
from kneeseat_core.typed import Floats, Pose

TKA = SHARED_DATA / 'tka_dm'
CONFIG = REPO / 'config' / 'tka_dm.yaml'
RESOLUTION_M = 1e-4
BISECT_TOL_M = 2e-6         # resolution of the penetration estimate

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (TKA / 'femoral_component.stl').is_file(),
                       reason=f'total-knee meshes not found at {TKA} (../shared/data/tka_dm '
                       'next to the repository); they are not shipped in the repo'),
]


TABLE_FILE: dict[str, Path] = {}


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[KneeConfig, PoseTable]]:
    """The config and the full TKA table, built once through the CLI (2 workers)."""
    out = tmp_path_factory.mktemp('tka') / 'tka_dm.npz'
    assert main(['build', str(CONFIG), '--out', str(out), '--workers', '2', '--quiet']) == 0
    TABLE_FILE['tka'] = out
    config = load_config(CONFIG)
    meshes = {config.reference.name: config.reference.mesh}
    meshes.update({b.name: b.mesh for b in config.bodies})
    yield config, read_table(out, meshes=meshes)      # also checks the recorded mesh hashes


class Probe:
    """python-fcl objects of our own: the fixed reference and one moving body."""

    def __init__(self, fixed: Path, moving: Path) -> None:
        self.fixed = fcl_object(trimesh.load_mesh(fixed, process=False))
        self.moving = fcl_object(trimesh.load_mesh(moving, process=False))

    def collides(self, fixed_from_moving: Pose) -> bool:
        return fcl_collides(self.moving, self.fixed, fixed_from_moving)

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


def test_tka_cells_converge_or_say_why(built: tuple[KneeConfig, PoseTable]) -> None:
    config, table = built
    assert table.position_m.shape == (2, 91, 21, 3)
    per_body = {name: float(table.converged[b].mean()) for b, name in enumerate(table.bodies)}
    overall = float(table.converged.mean())
    print(f'TKA converged: {100 * overall:.2f}% overall, '
          + ', '.join(f'{n} {100 * c:.2f}%' for n, c in per_body.items()))
    print(status_map(table))
    assert per_body['patella'] == 1.0
    assert overall >= 0.95
    # every cell that did not converge left the search envelope: the insert escapes over a
    # condyle at extreme varus, where geometry alone has no rest near the attitude
    codes = table.status
    assert set(codes[~np.asarray(table.converged)].tolist()) <= {Status.ENVELOPE}
    tibia_bad = np.argwhere(~table.converged[0])
    assert all(math.degrees(table.varus_rad[j]) <= -2.0 or math.degrees(table.varus_rad[j])
               >= 8.0 for _, j in tibia_bad)


def test_tka_sampled_cells_are_at_rest(built: tuple[KneeConfig, PoseTable],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """`kneeseat verify --sample 60`: no converged cell gains more than the resolution."""
    code = main(['verify', str(TABLE_FILE['tka']), '--sample', '60', '--workers', '2',
                 '--quiet', '--json'])
    report = json.loads(capsys.readouterr().out)
    gains = [c['gain_m'] for c in report['cells'] if c['converged']]
    print(f'verify --sample 60: {len(gains)} converged cells judged, largest gain '
          f'{max(gains) * 1e3:.3f} mm; {report["not_at_rest"]} not at rest')
    config, table = built
    judged = {(c['flexion_deg'], c['varus_deg']) for c in report['cells']
              if c['body'] == 'tibia'}
    nf, nv = len(table.flexion_rad), len(table.varus_rad)
    corners_at_rest = {(round(math.degrees(table.flexion_rad[i]), 6),
                        round(math.degrees(table.varus_rad[j]), 6))
                       for i in (0, nf - 1) for j in (0, nv - 1)
                       if table.status[0, i, j] in AT_REST}
    # the tibia's corners claimed at rest lead the sample; one that left the envelope
    # (extension at varus -10) claims nothing and is not judged
    assert corners_at_rest and corners_at_rest <= {(round(f, 6), round(v, 6)) for f, v in judged}
    assert report['not_converged'] == int(np.size(table.status)
                                          - np.isin(table.status, AT_REST).sum())
    assert code == 0 and report['not_at_rest'] == 0
    assert all(g is not None and g <= RESOLUTION_M for g in gains)


def test_tka_branch_changes_are_recorded(built: tuple[KneeConfig, PoseTable]) -> None:
    """Every neighbour pair over 1 mm / 2 deg between two converged cells is in the
    metadata's branch changes (nothing passed over silently)."""
    config, table = built
    summary = continuity(table.position_m, table.orientation_xyzw, table.converged,
                         table.flexion_rad, table.varus_rad, table.bodies, config.attitudes())
    recorded = table.metadata['continuity']
    assert recorded['branch_changes'] == summary['branch_changes']
    print(f'TKA continuity: {recorded["bodies"]}; {len(recorded["branch_changes"])} branch '
          'changes')


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
