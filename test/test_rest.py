"""Rest you can prove: the default settle climbs to the true rest, and the referee agrees.

Scenes whose rest a probe of one fixed size cannot prove (test/settle_cases.py,
SHALLOW_SCENES): two joined spheres of unequal radii over two bowls with equal slack (the
pair determines the spin about the push), a rounded box wedged in a tapered pocket with the
push 10 degrees off its axis and starts 10-25 degrees off about the push, and a cylinder
in a 90-degree V groove with the push tilted 8.6 degrees across it. Each plain, tilted,
with the scene rotated, and at millimetre scale through the CLI. Thresholds: position
within 2 x resolution + 0.05 mm in the determined directions, spin within 1.5 x the 0.1
degree rotation resolution, and the referee (kneeseat_core.referee.judge, which shares no
search code with the settle) gains no more than the resolution from the reported pose.
"""
from __future__ import annotations

import ast
from dataclasses import replace
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import REPO
from kneeseat_core.cli import main
from kneeseat_core.meshes import CollisionPair, RigidBody, SweepPair
from kneeseat_core.geometry import matrix_from_quat, pose_from, quat_from_matrix, rotation_about
from kneeseat_core.referee import Envelope, Referee
import kneeseat_core.settle as settle_package
from kneeseat_core.settle import settle, SettleParams, SettleResult
from kneeseat_core.settle.climb import _Climb, _Place
from kneeseat_core.settle.search import Search
from kneeseat_core.settle.tuning import SettleTuning, TUNING
from kneeseat_core.status import Status
import settle_cases as sc
import shapes

RESOLUTION_M = 1e-4
POSITION_TOL_M = 2.0 * RESOLUTION_M + 0.05e-3
ROTATION_RES = math.radians(0.1)
SPIN_TOL = 1.5 * ROTATION_RES
CASES = list(itertools.product(sc.SHALLOW_SCENES, sc.VARIANTS))


def params(var: sc.Variant, **kwargs: object) -> SettleParams:
    return SettleParams(push=tuple(float(v) for v in var.push),
                        rotation_resolution_rad=ROTATION_RES, **kwargs)


def referee_gain(var: sc.Variant, pose: np.ndarray) -> float:
    return Referee([var.fixed_mesh], [var.moving_mesh], var.push, RESOLUTION_M).judge(pose).gain_m


def assert_at_the_answer(name: str, kind: str, result: SettleResult) -> None:
    assert result.converged, result.reason
    position_err, spin_err = sc.errors(name, kind, result.pose)
    assert position_err <= POSITION_TOL_M, f'{position_err * 1e3:.4f} mm from the answer'
    if spin_err is not None:
        assert spin_err <= SPIN_TOL, f'{math.degrees(spin_err):.4f} deg from the answer'


@pytest.mark.parametrize('name,kind', CASES)
def test_settle_reaches_the_analytic_rest_and_the_referee_agrees(name: str, kind: str) -> None:
    var = sc.variant(name, kind)
    result = settle(var.fixed, var.moving, var.start, params(var))
    assert_at_the_answer(name, kind, result)
    assert result.status == Status.REST and result.proof_checks > 0
    assert referee_gain(var, result.pose) <= RESOLUTION_M


def test_twenty_random_starts_on_the_two_sphere_scene() -> None:
    """3 mm lateral, 8 degrees of spin, 3-8 mm of lift, seeded: every end within tolerance."""
    name = 'spheres_equal_slack'
    var = sc.variant(name, 'plain')
    rest = sc.scene(name).rest_point - sc.scene(name).body_point
    rng = np.random.default_rng(20261201)
    up = np.array([0.0, 1.0, 0.0])
    for _ in range(20):
        dx, dz = rng.uniform(-3e-3, 3e-3, 2)
        lift = rng.uniform(3e-3, 8e-3)
        turn = rotation_about(up, math.radians(rng.uniform(-8.0, 8.0)))
        start = pose_from(turn, rest + np.array([dx, lift, dz]))
        assert_at_the_answer(name, 'plain', settle(var.fixed, var.moving, start, params(var)))


@pytest.mark.parametrize('kind', sc.VARIANTS)
@pytest.mark.parametrize('spin_deg', [10.0, 17.5, 25.0, -25.0])
def test_box_turns_into_its_pocket_from_10_to_25_degrees_off(kind: str, spin_deg: float) -> None:
    var = sc.variant('box_tapered_pocket', kind)
    start = var.start.copy()
    start[:3, :3] = rotation_about(var.push / np.linalg.norm(var.push),
                                   math.radians(spin_deg)) @ var.frame
    result = settle(var.fixed, var.moving, start, params(var))
    assert_at_the_answer('box_tapered_pocket', kind, result)
    assert referee_gain(var, result.pose) <= RESOLUTION_M


@pytest.mark.parametrize('name', sc.SHALLOW_SCENES)
def test_cli_settles_and_verifies_millimetre_meshes(
        name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    var = sc.variant(name, 'tilted')
    paths = tmp_path / 'fixed.stl', tmp_path / 'moving.stl'
    for mesh, path in zip((var.fixed_mesh, var.moving_mesh), paths):
        scaled = mesh.copy()
        scaled.apply_scale(1000.0)
        scaled.export(path)
    start = tmp_path / 'start.json'
    start.write_text(json.dumps({'position': var.start[:3, 3].tolist(),
                                 'orientation': quat_from_matrix(var.start[:3, :3]).tolist()}))
    push = ','.join(repr(float(v)) for v in var.push)
    common = ['--fixed', str(paths[0]), '--moving', str(paths[1]), '--units', 'mm',
              f'--push={push}']
    code = main(['settle', *common, '--start', str(start), '--rotation-resolution', '0.1',
                 '--json'])
    out, err = capsys.readouterr()
    assert code == 0, err
    result_path = tmp_path / 'result.json'
    result_path.write_text(out)
    data = json.loads(out)
    pose = pose_from(matrix_from_quat(np.array(data['pose']['orientation'])),
                     np.array(data['pose']['position']))
    position_err, spin_err = sc.errors(name, 'tilted', pose)
    assert position_err <= POSITION_TOL_M
    assert spin_err is None or spin_err <= SPIN_TOL
    code = main(['verify', *common, '--pose', str(result_path), '--json'])
    verdict = json.loads(capsys.readouterr().out)
    assert code == 0 and verdict['at_rest'] and verdict['gain_m'] <= RESOLUTION_M


def test_referee_catches_a_pose_that_is_not_at_rest() -> None:
    """Control: the sphere 1.5 mm off the bottom of its bowl, at contact, can still sink."""
    var = sc.variant('sphere_bowl', 'plain')
    referee = Referee([var.fixed_mesh], [var.moving_mesh], var.push, RESOLUTION_M)
    rest = sc.scene('sphere_bowl').rest_point
    pose = pose_from(np.eye(3), rest + np.array([1.5e-3, 0.0, 0.0]))
    pose[1, 3] -= referee.travel(pose)             # at contact
    verdict = referee.judge(pose)
    # sliding 1.5 mm back to the bottom of a 10 mm lever gains about 1.5^2 / 20 mm
    assert verdict.gain_m == pytest.approx(1.5e-3 ** 2 / 20e-3, abs=2e-5)
    assert verdict.slide_m == pytest.approx(1.5e-3, abs=0.1e-3)
    assert not verdict.at_rest(RESOLUTION_M / 2)


def test_referee_shares_no_code_with_the_settle() -> None:
    tree = ast.parse((REPO / 'kneeseat_core' / 'referee' / 'judge.py').read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                 for alias in node.names}
    # its own python-fcl objects and scipy's climb; of the project only the error it raises
    # and the array aliases (test_layers.py checks that nothing it loads is the settle's)
    assert imported <= {'__future__', 'dataclasses', 'math', 'typing', 'fcl', 'numpy',
                        'scipy.optimize', 'scipy.spatial.transform', 'trimesh',
                        'kneeseat_core.errors', 'kneeseat_core.typed'}


def sloped_block(slope: float) -> trimesh.Trimesh:
    """A block whose top rises along +X at `slope`: no rest anywhere along -Y."""
    return shapes.heightfield_solid(lambda x, z: slope * x, 0.05, 0.02, 60, bottom=-0.08)


def test_a_rest_beyond_the_envelope_is_not_converged() -> None:
    """A sphere on an incline slides downhill without end: the climb leaves the envelope."""
    fixed, ball = RigidBody.from_mesh(sloped_block(0.2)), RigidBody.from_mesh(shapes.sphere(5e-3))
    start = pose_from(np.eye(3), [0.0, 0.012, 0.0])
    result = settle(fixed, ball, start, SettleParams(push=(0.0, -1.0, 0.0), max_slide_m=0.01))
    assert not result.converged and result.status == Status.ENVELOPE
    assert 'envelope 10 mm' in result.reason


def test_an_envelope_that_holds_gives_a_constrained_rest_the_referee_accepts() -> None:
    """The same incline with the envelope holding: the sphere rests on its boundary, 8 mm
    downhill, and nothing inside the envelope gains."""
    block, sphere = sloped_block(0.2), shapes.sphere(5e-3)
    fixed, ball = RigidBody.from_mesh(block), RigidBody.from_mesh(sphere)
    start = pose_from(np.eye(3), [0.0, 0.012, 0.0])
    result = settle(fixed, ball, start, SettleParams(push=(0.0, -1.0, 0.0), max_slide_m=8e-3,
                                                     envelope_holds=True))
    assert result.converged and result.status == Status.CONSTRAINED, result.reason
    assert result.pose[0, 3] == pytest.approx(-8e-3, abs=0.2e-3)
    verdict = Referee([block], [sphere], np.array([0.0, -1.0, 0.0]), RESOLUTION_M).judge(
        result.pose, Envelope(start, 8e-3, math.radians(45.0)))
    assert verdict.gain_m <= RESOLUTION_M


def test_far_from_an_envelope_that_holds_every_move_keeps_its_length() -> None:
    """Far from an envelope that holds, the climb's moves are made whole at every scale,
    the least (a quarter of the finest move) included: none is dropped as having no room
    (it was, when a move's whole length equalled the share of the finest move below which
    one the envelope shortens is dropped)."""
    var = sc.variant('spheres_equal_slack', 'plain')
    held = params(var, max_slide_m=1.0, envelope_holds=True)
    search = Search(CollisionPair(var.fixed, var.moving), var.start, held, var.start)
    search.sweep = SweepPair(var.fixed, var.moving, search.push)
    climb = _Climb(search, search.sweep, TUNING, None)
    first = climb.arrive(var.start, 0.0, TUNING.pool_window_res)
    assert first is not None
    climb.settle_in(first)
    for scale in (TUNING.least_moves, TUNING.near_first_moves, 1.0, TUNING.far_moves):
        moves = scale * climb.finest * climb.directions
        assert np.array_equal(climb._inside(moves, scale * climb.finest), moves), scale


def test_only_a_scale_tried_in_every_direction_spares_the_proof() -> None:
    """At rest, a step at the longest scale tries only its most promising moves and finds
    nothing: the proof must still probe that scale in every direction (D5). A step at a
    scale it tries whole spares the proof that scale."""
    var = sc.variant('sphere_bowl', 'tilted')
    rest = settle(var.fixed, var.moving, var.start, params(var))
    assert rest.converged, rest.reason
    search = Search(CollisionPair(var.fixed, var.moving), rest.pose, params(var), var.start)
    search.sweep = SweepPair(var.fixed, var.moving, search.push)
    climb = _Climb(search, search.sweep, TUNING, None)
    first = climb.arrive(rest.pose, 0.0, TUNING.pool_window_res)
    assert isinstance(first, _Place)
    climb.settle_in(first)
    far, whole = TUNING.far_moves * climb.finest, TUNING.every_direction_moves * climb.finest
    assert far > whole
    climb.scale = far
    assert climb.step() is True and climb.scale < far     # nothing gained: it shrank
    assert far not in climb.failed
    climb.scale = whole
    assert climb.step() is True and climb.scale < whole
    assert whole in climb.failed


def ridge_groove(angle_deg: float, wall: float, fall: float) -> trimesh.Trimesh:
    """A V-groove whose floor falls at `fall` along its axis, which lies `angle_deg` from +X
    (e1 for a push along -Y) in the XZ plane; its walls rise at `wall` across it."""
    angle = math.radians(angle_deg)

    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        along = math.cos(angle) * x + math.sin(angle) * z
        across = -math.sin(angle) * x + math.cos(angle) * z
        out: np.ndarray = wall * np.abs(across) - fall * along
        return out
    return shapes.heightfield_solid(surface, 0.02, 0.02, 161, bottom=-0.06)


def climb_in_the_groove(tuning: SettleTuning) -> _Climb:
    """A sphere of 5 mm settled into the groove's floor, where its axis lies half-way
    between two probe directions (22.5 degrees from each): the climb at its first contact."""
    fixed = RigidBody.from_mesh(ridge_groove(22.5, 2.0, 0.6))
    ball = RigidBody.from_mesh(shapes.sphere(5e-3))
    start = pose_from(np.eye(3), [0.0, 0.02, 0.0])
    search = Search(CollisionPair(fixed, ball), start,
                    SettleParams(push=(0.0, -1.0, 0.0), max_slide_m=0.05), start)
    search.sweep = SweepPair(fixed, ball, search.push)
    climb = _Climb(search, search.sweep, tuning, None)
    first = climb.arrive(start, 0.0, tuning.pool_window_res)
    assert isinstance(first, _Place)
    climb.settle_in(first)
    return climb


def test_the_proof_follows_a_ridge_between_the_probe_directions() -> None:
    """Along the groove the travel grows by 0.6 of the move, across it it falls by 2: every
    probe direction, 22.5 degrees or more off the axis, loses, and probes alone would call
    the floor a rest. The near-active features' way up keeps both walls and follows the
    floor: the proof finds it gaining and the climb moves down the groove."""
    blind = climb_in_the_groove(replace(TUNING, uphill_probe_moves=()))
    assert blind.prove() is None            # the probe directions alone see no way up
    climb = climb_in_the_groove(TUNING)
    before = climb.here.state.copy()
    assert climb.prove() is True
    move = climb.here.state - before
    axis = np.array([math.cos(math.radians(22.5)), math.sin(math.radians(22.5))])
    along = float(move[:2] @ axis)
    assert along > 0.0
    assert abs(move[0] * axis[1] - move[1] * axis[0]) < 0.1 * along    # down the floor


def test_a_step_shorter_than_a_finest_move_tries_the_way_up_alone(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Below one finest move a step tries only the move the near-active features say climbs
    most; from one finest move on, every probe direction and that move."""
    climb = climb_in_the_groove(TUNING)
    tried: list[int] = []
    real_try = climb._try

    def counted(moves: np.ndarray, *rest: object) -> object:
        tried.append(len(moves))
        return real_try(moves, *rest)        # type: ignore[arg-type]
    monkeypatch.setattr(climb, '_try', counted)
    climb.scale = 0.5 * climb.finest
    climb.step()
    climb.scale = climb.finest
    climb.step()
    assert tried == [1, len(climb.directions) + 1]


def test_the_climbs_windows_must_hold_what_it_uses() -> None:
    """A place's window below the contact tolerance (plus its margin), or a pool narrower
    than a place's window, would drop features the climb uses: such a tuning is refused."""
    with pytest.raises(ValueError, match='window_res'):
        SettleTuning(window_res=TUNING.contact_tol_res)
    with pytest.raises(ValueError, match='pool_window_res'):
        SettleTuning(pool_window_res=0.5 * TUNING.window_res)
    with pytest.raises(ValueError, match='pool_cap'):
        SettleTuning(pool_cap=-1)
    assert TUNING.window_res > TUNING.contact_tol_res


@pytest.mark.parametrize('name', ['sphere_bowl', 'cylinder_groove', 'cylinder_v90'])
def test_a_wider_place_window_settles_the_same_bit_for_bit(
        name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A place's features beyond the contact tolerance are never used (a place that
    becomes the witnesses' pool is measured again with the pool's window), so the place's
    window moves the cost only: with it as wide as the pool's, every settle is the same.
    Without the pool's cap the same travels are measured too; with it (its features beyond
    a place's window capped, none beyond a window as wide as the pool's) the witnesses
    differ, which moves the travels measured and nothing else."""
    var = sc.variant(name, 'tilted')
    for cap in (0, TUNING.pool_cap):
        monkeypatch.setattr(settle_package, 'TUNING', replace(TUNING, pool_cap=cap))
        narrow = settle(var.fixed, var.moving, var.start, params(var))
        monkeypatch.setattr(settle_package, 'TUNING',
                            replace(TUNING, pool_cap=cap, window_res=TUNING.pool_window_res))
        wide = settle(var.fixed, var.moving, var.start, params(var))
        assert narrow.converged and wide.converged, (narrow.reason, wide.reason)
        assert np.array_equal(narrow.pose, wide.pose)
        assert narrow.iterations == wide.iterations
        assert narrow.travels == wide.travels or cap != 0


def test_a_dome_is_left_with_lost_contact() -> None:
    dome = shapes.heightfield_solid(lambda x, z: -30.0 * (x * x + z * z), 0.02, 0.02, 80,
                                    bottom=-0.05)
    fixed, ball = RigidBody.from_mesh(dome), RigidBody.from_mesh(shapes.sphere(4e-3))
    start = pose_from(np.eye(3), [1e-3, 0.01, 0.5e-3])
    result = settle(fixed, ball, start, SettleParams(push=(0.0, -1.0, 0.0), max_slide_m=0.05))
    assert not result.converged and result.status == Status.LOST
