"""The travel by rays (settle parameter `travel: rays`) against python-fcl.

The referee of every travel here is a dichotomy on python-fcl's boolean query written in
this file (nothing of the rays or of the settle's own search): a ray hit is a real contact,
so the rays can never report a longer travel than python-fcl's first collision, and they
may report a shorter one only by a gap an edge crossing an edge hides from vertex rays
(`hidden_gap_m`). Scenes: the analytic ones of test/settle_cases.py (closed meshes) and, when
the shared data is there, the total knee (closed) and the natural knee's open cartilage
sheets.
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from kneeseat_core.errors import SettleError
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.meshes import (CollisionPair, hidden_gap_m, load_mesh, load_meshes,
                                  RayPair, RigidBody)
from kneeseat_core.settle import settle, SettleParams
import settle_cases as sc

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'data'
RESOLUTION_M = 1e-4
TOL_M = 1e-7              # the referee's dichotomy stops this close


def fcl_travel(pair: CollisionPair, pose: np.ndarray, push: np.ndarray,
               limit: float = 0.05) -> float:
    """The travel along `push` from the free `pose` to python-fcl's first collision, by
    steps of 0.1 mm and a dichotomy to TOL_M (inf: none within `limit`)."""
    def hit(t: float) -> bool:
        moved = pose.copy()
        moved[:3, 3] += t * push
        return pair.collides(moved)
    assert not hit(0.0), 'the referee starts from a free pose'
    lo, step = 0.0, 1e-4
    while not hit(lo + step):
        lo += step
        if lo > limit:
            return math.inf
    hi = lo + step
    while hi - lo > TOL_M:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if hit(mid) else (mid, hi)
    return hi


def lateral_poses(base: np.ndarray, push: np.ndarray, centre: np.ndarray, seed: int,
                  n: int, slide_m: float, spin_deg: float) -> list[np.ndarray]:
    """`n` seeded poses: `base` slid across `push` and spun about it through `centre`."""
    rng = np.random.default_rng(seed)
    e1 = np.cross(push, [1.0, 0.0, 0.0] if abs(push[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(push, e1)
    out = []
    for _ in range(n):
        turn = rotation_about(push, math.radians(rng.uniform(-spin_deg, spin_deg)))
        pose = np.eye(4)
        pose[:3, :3] = turn @ base[:3, :3]
        pose[:3, 3] = turn @ (base[:3, 3] - centre) + centre \
            + rng.uniform(-slide_m, slide_m) * e1 + rng.uniform(-slide_m, slide_m) * e2
        out.append(pose)
    return out


def backed(pair: CollisionPair, pose: np.ndarray, push: np.ndarray) -> np.ndarray:
    """`pose` moved back along -push until python-fcl finds it free (by 0.5 mm steps)."""
    out = pose.copy()
    while pair.collides(out):
        out[:3, 3] -= 5e-4 * push
    return out


def check_agreement(fixed: RigidBody, moving: RigidBody, poses: list[np.ndarray],
                    push: np.ndarray, margin_m: float = 4e-3) -> RayPair:
    """Each pose's travel by rays against the referee's; returns the RayPair used."""
    pair = CollisionPair(fixed, moving)
    rays = RayPair(CollisionPair(fixed, moving), push, margin_m, 4 * RESOLUTION_M)
    hidden = hidden_gap_m(fixed, moving)[1]
    for pose in poses:
        pose = backed(pair, pose, push)
        want = fcl_travel(pair, pose, push)
        got = rays.travel_from(pose, 0.05)
        assert got is not None, 'a free pose was found in collision'
        if math.isinf(want):
            assert math.isinf(got)
            continue
        assert want - TOL_M - 1e-9 <= got <= want + hidden + 1e-6, \
            f'rays {got * 1e3:.5f} mm, python-fcl {want * 1e3:.5f} mm (hidden gap bound ' \
            f'{hidden * 1e3:.4f} mm)'
    return rays


@pytest.mark.parametrize('name', sc.SCENES)
def test_travel_matches_python_fcl_on_the_analytic_scenes(name: str) -> None:
    var = sc.variant(name, 'rotated')
    push = var.push / np.linalg.norm(var.push)
    centre = var.start[:3, :3] @ var.moving.centroid + var.start[:3, 3]
    poses = lateral_poses(var.start, push, centre, seed=3, n=8, slide_m=3e-3, spin_deg=8.0)
    check_agreement(var.fixed, var.moving, poses, push)


def test_the_near_set_is_drawn_again_when_the_body_has_moved() -> None:
    """Poses spread wider than the near set's margin: each answer still the referee's,
    and the set was drawn more than once (a narrow margin forces it)."""
    var = sc.variant('dumbbell_bowls', 'plain')
    push = var.push / np.linalg.norm(var.push)
    centre = var.start[:3, :3] @ var.moving.centroid + var.start[:3, 3]
    poses = lateral_poses(var.start, push, centre, seed=11, n=12, slide_m=6e-3,
                          spin_deg=10.0)
    rays = check_agreement(var.fixed, var.moving, poses, push, margin_m=1e-3)
    assert rays.draws > 2
    assert rays.casts >= len(poses)


def test_a_pose_in_collision_is_found_so() -> None:
    """Between closed meshes a vertex inside the other body is a collision without asking
    python-fcl; the referee agrees the pose is buried."""
    var = sc.variant('sphere_bowl', 'plain')
    push = var.push / np.linalg.norm(var.push)
    pair = CollisionPair(var.fixed, var.moving)
    free = backed(pair, var.start, push)
    travel = fcl_travel(pair, free, push)
    buried = free.copy()
    buried[:3, 3] += (travel + 5e-4) * push
    assert pair.collides(buried)
    rays = RayPair(CollisionPair(var.fixed, var.moving), push, 4e-3, 4 * RESOLUTION_M)
    assert rays.travel_from(buried, 0.05) is None
    assert rays.pair.checks == 0


def test_settle_by_rays_meets_the_analytic_rest() -> None:
    """Every analytic scene and variant, the same thresholds as test_settle.py's, and the
    end pose free for python-fcl and touching one resolution further."""
    for name, kind in itertools.product(sc.SCENES, sc.VARIANTS):
        var = sc.variant(name, kind)
        push = var.push / np.linalg.norm(var.push)
        result = settle(var.fixed, var.moving, var.start,
                        SettleParams(push=tuple(float(v) for v in push), travel='rays'))
        assert result.converged, f'{name} {kind}: {result.reason}'
        assert result.ray_casts > 0 and result.rays > 0
        position_err, _ = sc.errors(name, kind, result.pose)
        assert position_err <= 2.0 * RESOLUTION_M + 0.05e-3, \
            f'{name} {kind}: {position_err * 1e3:.4f} mm'
        pair = CollisionPair(var.fixed, var.moving)
        assert not pair.collides(result.pose)
        pushed = result.pose.copy()
        pushed[:3, 3] += RESOLUTION_M * push
        assert pair.collides(pushed), f'{name} {kind}: more than a resolution from contact'


def test_an_unknown_travel_is_refused() -> None:
    with pytest.raises(SettleError, match='travel'):
        SettleParams(travel='lasers').check()   # type: ignore[arg-type]


@pytest.mark.skipif(not (SHARED / 'tka_dm').is_dir(), reason='no shared total knee data')
def test_travel_matches_python_fcl_on_the_total_knee() -> None:
    fixed = RigidBody.from_mesh(load_mesh(SHARED / 'tka_dm' / 'femoral_component.stl', 'm'))
    moving = RigidBody.from_mesh(load_mesh(SHARED / 'tka_dm' / 'tibial_insert.stl', 'm'))
    push = np.array([0.0, 1.0, 0.0])
    start = pose_from(np.eye(3), np.array([0.0, -2e-3, 0.0]))
    poses = lateral_poses(start, push, moving.centroid, seed=5, n=6, slide_m=2e-3,
                          spin_deg=4.0)
    check_agreement(fixed, moving, poses, push)


@pytest.mark.skipif(not (SHARED / 'natural_knee').is_dir(),
                    reason='no shared natural knee data')
def test_travel_matches_python_fcl_on_open_cartilage_sheets() -> None:
    """Open sheets: the travel as python-fcl finds it, and a pose with rays inside the
    other body decided by one python-fcl query (a ray may meet a back face through a
    hole)."""
    data = SHARED / 'natural_knee'
    fixed = RigidBody.from_mesh(load_meshes([str(data / 'femur_cartilage.stl'),
                                             str(data / 'femur_bone.stl')], 'm', quiet=True))
    moving = RigidBody.from_mesh(load_meshes([str(data / 'tibia_cartilage.stl'),
                                              str(data / 'tibia_bone.stl')], 'm', quiet=True))
    assert not (fixed.mesh.is_watertight and moving.mesh.is_watertight)
    push = np.array([0.0, 1.0, 0.0])
    start = pose_from(np.eye(3), np.array([0.0, -1e-3, 0.0]))
    poses = lateral_poses(start, push, moving.centroid, seed=9, n=6, slide_m=1.5e-3,
                          spin_deg=3.0)
    check_agreement(fixed, moving, poses, push)
    pair = CollisionPair(fixed, moving)
    free = backed(pair, start, push)
    buried = free.copy()
    buried[:3, 3] += (fcl_travel(pair, free, push) + 5e-4) * push
    rays = RayPair(CollisionPair(fixed, moving), push, 4e-3, 4 * RESOLUTION_M)
    assert rays.travel_from(buried, 0.05) is None
    assert rays.pair.checks == 1


def test_a_config_chooses_the_travel_and_names_a_wrong_one() -> None:
    from kneeseat_core.errors import ConfigError
    from kneeseat_core.knee import load_config, materialise_default_knee
    path = materialise_default_knee()
    assert load_config(path, path.parent).settle.travel == 'fcl'
    rays = load_config(path, path.parent, {'settle': {'travel': 'rays'}})
    assert rays.settle.travel == 'rays'
    with pytest.raises(ConfigError, match="settle: travel 'lasers' is unknown"):
        load_config(path, path.parent, {'settle': {'travel': 'lasers'}})


def test_a_table_built_by_rays_is_at_rest_for_the_referee(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A coarse default-knee build with `--travel rays`: the casts are in the summary and
    the metadata, and `kneeseat verify` (python-fcl, nothing of the settle) finds every
    cell at rest."""
    from kneeseat_core.cli import main
    from kneeseat_core.table import read_table
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    out = tmp_path / 'knee.npz'
    assert main(['build', '--out', str(out), '--workers', '1', '--quiet', '--travel', 'rays',
                 '--flexion-grid', '0,-90,45', '--varus-grid', '-5,5,5']) == 0
    assert 'ray casts per cell' in capsys.readouterr().out
    meta = read_table(out).metadata
    assert meta['settle']['travel'] == 'rays'
    assert meta['summary']['ray_casts'] > meta['summary']['cells']
    assert meta['summary']['converged'] == meta['summary']['cells']
    assert main(['verify', str(out), '--workers', '1']) == 0, capsys.readouterr().out
