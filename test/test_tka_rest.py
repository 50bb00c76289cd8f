"""The default settle ends at rest on a real total knee, as the independent referee sees it.

The tibial insert is pushed along +Y into the femoral component, from the benchmark's start
(5 mm below, 3 mm lateral, 5 degrees about Y) and from ten seeded starts around it. Each
end pose is judged by the referee (kneeseat_core.referee.judge: its own python-fcl objects,
boolean queries only, a Nelder-Mead climb of the travel from a two-resolution simplex):
at rest it gains no more than the resolution. A control checks that the referee does see
a pose that is not at rest (the first contact straight up from the start).
"""
from __future__ import annotations

import math

from conftest import fcl_collides, fcl_object, SHARED_DATA
import fcl
import numpy as np
import pytest
import trimesh

from kneeseat_core.meshes import load_mesh, RigidBody
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.referee import Referee
from kneeseat_core.settle import settle, SettleParams, SettleResult

TKA = SHARED_DATA / 'tka_dm'
RESOLUTION_M = 1e-4
PUSH = np.array([0.0, 1.0, 0.0])            # +Y: the insert rises into the femur

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (TKA / 'femoral_component.stl').is_file(),
                       reason=f'total-knee meshes not found at {TKA} (../shared/data/tka_dm '
                       'next to the repository); they are not shipped in the repo'),
]


def start_pose(insert: RigidBody, lateral_m: float = 3e-3, below_m: float = 5e-3,
               spin_deg: float = 5.0, anterior_m: float = 0.0) -> np.ndarray:
    """The insert as delivered, moved `below_m` down Y, `lateral_m` along Z, `anterior_m`
    along X and turned `spin_deg` about Y through its centroid (defaults: the benchmark's
    start, benchmarks/bench_settle.py)."""
    turn = rotation_about(PUSH, math.radians(spin_deg))
    centroid = insert.centroid
    return pose_from(turn, centroid - turn @ centroid
                     + np.array([anterior_m, -below_m, lateral_m]))


@pytest.fixture(scope='module')
def knee() -> tuple[trimesh.Trimesh, trimesh.Trimesh, RigidBody, RigidBody]:
    femoral = load_mesh(TKA / 'femoral_component.stl')
    insert = load_mesh(TKA / 'tibial_insert.stl')
    return femoral, insert, RigidBody.from_mesh(femoral), RigidBody.from_mesh(insert)


@pytest.fixture(scope='module')
def settled(knee: tuple) -> tuple[tuple[fcl.CollisionObject, fcl.CollisionObject],
                                  SettleResult]:
    """The insert (moving) and femoral component (fixed) as the tests' own python-fcl
    objects, and the default settle's result."""
    femoral_mesh, insert_mesh, femoral, insert = knee
    result = settle(femoral, insert, start_pose(insert), SettleParams(push=tuple(PUSH)))
    return (fcl_object(insert_mesh), fcl_object(femoral_mesh)), result


def test_default_settle_converges_on_the_knee(settled: tuple) -> None:
    _, result = settled
    assert result.converged, result.reason
    assert len(result.contacts.points) > 0


def test_end_pose_touches_without_penetrating(settled: tuple) -> None:
    (moving, fixed), result = settled
    assert not fcl_collides(moving, fixed, result.pose), 'the end pose is in collision'
    ahead = result.pose.copy()
    ahead[:3, 3] += RESOLUTION_M * PUSH
    assert fcl_collides(moving, fixed, ahead), (
        'the end pose can still rise a resolution along the push')


def test_ten_settles_from_different_starts_are_at_rest(knee: tuple) -> None:
    femoral_mesh, insert_mesh, femoral, insert = knee
    referee = Referee([femoral_mesh], [insert_mesh], PUSH, RESOLUTION_M)
    rng = np.random.default_rng(20261201)
    report = []
    for _ in range(10):
        start = start_pose(insert, lateral_m=rng.uniform(-3e-3, 3e-3),
                           below_m=rng.uniform(3e-3, 8e-3), spin_deg=rng.uniform(-8.0, 8.0),
                           anterior_m=rng.uniform(-3e-3, 3e-3))
        result = settle(femoral, insert, start, SettleParams(push=tuple(PUSH)))
        assert result.converged, result.reason
        verdict = referee.judge(result.pose)
        report.append(f'{verdict.gain_m * 1e3:.3f} mm ({result.collision_checks} checks)')
        assert verdict.gain_m <= RESOLUTION_M, \
            f'the referee gains {verdict.gain_m * 1e3:.3f} mm by sliding ' \
            f'{verdict.slide_m * 1e3:.2f} mm and turning {math.degrees(verdict.spin_rad):.2f} deg'
    print('referee gains from ten TKA settles: ' + ', '.join(report))


def test_the_referee_sees_a_pose_that_is_not_at_rest(knee: tuple) -> None:
    """Control: first contact straight up from the start is not at rest, and the referee
    says so; otherwise the test above proves nothing."""
    femoral_mesh, insert_mesh, _, insert = knee
    referee = Referee([femoral_mesh], [insert_mesh], PUSH, RESOLUTION_M)
    first = start_pose(insert)
    first[:3, 3] += referee.travel(first) * PUSH
    verdict = referee.judge(first)
    assert verdict.gain_m > 5.0 * RESOLUTION_M
