"""The settle engine against analytic rest poses.

Scenes (test/settle_cases.py): a sphere in a spherical bowl, a sphere in a cone, a cylinder
in a V groove (FIG. 13: across the groove determined, along it free), an elongated key
started 20 degrees off about the push that must turn into its pocket, and two rigidly
joined spheres over two bowls of different depth. Each plain, with a tilted push and with
the whole scene rotated; each plain scene once more at millimetre scale through the CLI.

Thresholds, never loosened (docs/design.md, "The settle"): with the default method the
position error in the determined directions is within 2 x resolution + 0.05 mm, and the
rotation about the push (where determined) within 1.5 x the rotation resolution, that is
resolution / (farthest-vertex radius about the push axis) unless a test sets
`rotation_resolution_rad` (the 0.1 degree runs).
"""
from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from kneeseat_core.cli import main
from kneeseat_core.meshes import CollisionPair
from kneeseat_core.geometry import pose_from, quat_from_matrix, rotation_about
from kneeseat_core.settle import settle, SettleParams, SettleResult
from kneeseat_core.settle.objective import objective_for
from kneeseat_core.settle.planner import Planner
from kneeseat_core.settle.search import Search
from kneeseat_core.settle.tuning import TUNING
import settle_cases as sc

RESOLUTION_M = 1e-4                          # the default SettleParams().resolution_m
POSITION_TOL_M = 2.0 * RESOLUTION_M + 0.05e-3
CASES = list(itertools.product(sc.SCENES, sc.VARIANTS))
JSON_KEYS = {'converged', 'reason', 'pose', 'iterations', 'collision_checks', 'contacts',
             'elapsed_s'}


def farthest_radius(var: sc.Variant, pose: np.ndarray) -> float:
    """Distance (m) of the moving body's farthest vertex from the axis through its
    centroid parallel to the push, with the body at `pose` (our own computation)."""
    push = var.push / np.linalg.norm(var.push)
    world = var.moving_mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    centre = pose[:3, :3] @ var.moving_mesh.centroid + pose[:3, 3]
    rel = world - centre
    rel -= np.outer(rel @ push, push)
    return float(np.max(np.linalg.norm(rel, axis=1)))


def default_rotation_tol(var: sc.Variant) -> float:
    """1.5 x the default rotation resolution (rad): resolution / farthest-vertex radius."""
    return 1.5 * RESOLUTION_M / farthest_radius(var, var.start)


def run(name: str, kind: str, **kwargs: object) -> SettleResult:
    var = sc.variant(name, kind)
    return settle(var.fixed, var.moving, var.start,
                  SettleParams(push=tuple(float(v) for v in var.push), **kwargs))


def assert_at_contact(var: sc.Variant, pose: np.ndarray) -> None:
    """Not in collision, and in collision once pushed one resolution further."""
    pair = CollisionPair(var.fixed, var.moving)
    push = var.push / np.linalg.norm(var.push)
    assert not pair.collides(pose), 'the end pose penetrates the fixed body'
    pushed = pose.copy()
    pushed[:3, 3] += RESOLUTION_M * push
    assert pair.collides(pushed), 'the end pose is more than one resolution from contact'


def test_farthest_radius_of_the_key_matches_the_issue() -> None:
    # the issue quotes "about 0.28 deg for the 40 mm key"
    var = sc.variant('key_pocket', 'plain')
    assert math.degrees(RESOLUTION_M / farthest_radius(var, var.start)) == \
        pytest.approx(0.28, abs=0.01)


@pytest.mark.parametrize('name,kind', CASES)
def test_default_settle_meets_analytic_rest(name: str, kind: str) -> None:
    result = run(name, kind)
    assert result.converged, result.reason
    position_err, rotation_err = sc.errors(name, kind, result.pose)
    assert position_err <= POSITION_TOL_M, \
        f'position error {position_err * 1e3:.4f} mm > {POSITION_TOL_M * 1e3:.3f} mm'
    if rotation_err is not None:
        tol = default_rotation_tol(sc.variant(name, kind))
        assert rotation_err <= tol, \
            f'rotation error {math.degrees(rotation_err):.4f} deg > {math.degrees(tol):.4f} deg'
    assert_at_contact(sc.variant(name, kind), result.pose)
    assert result.collision_checks > 0 and result.iterations > 0
    assert 0.0 < result.fcl_s <= result.elapsed_s


@pytest.mark.parametrize('name,kind', list(itertools.product(
    ('key_pocket', 'cylinder_groove'), sc.VARIANTS)))
def test_default_settle_at_a_tenth_of_a_degree(name: str, kind: str) -> None:
    rotation_res = math.radians(0.1)
    result = run(name, kind, rotation_resolution_rad=rotation_res)
    assert result.converged, result.reason
    position_err, rotation_err = sc.errors(name, kind, result.pose)
    assert position_err <= POSITION_TOL_M
    assert rotation_err is not None
    assert rotation_err <= 1.5 * rotation_res, \
        f'rotation error {math.degrees(rotation_err):.4f} deg > 0.15 deg'


def test_key_really_turns_into_its_pocket() -> None:
    """The key starts 20 degrees off; the rest is reachable only by turning about the push."""
    var = sc.variant('key_pocket', 'plain')
    _, start_err = sc.errors('key_pocket', 'plain', var.start)
    assert start_err == pytest.approx(math.radians(20.0), abs=1e-9)
    _, end_err = sc.errors('key_pocket', 'plain', run('key_pocket', 'plain').pose)
    assert end_err is not None and end_err < math.radians(0.5)


def test_cylinder_is_free_along_the_groove() -> None:
    """Across the groove the rest is determined; along it (Z) the cylinder does not move
    further than the step: nothing pushes it that way."""
    var = sc.variant('cylinder_groove', 'plain')
    result = run('cylinder_groove', 'plain')
    along = result.pose[2, 3] - var.start[2, 3]
    assert abs(along) <= 1e-3, f'moved {along * 1e3:.3f} mm along the free direction'


@pytest.mark.parametrize('name,kind', CASES)
def test_patent_method_ends_honestly(name: str, kind: str) -> None:
    """The literal method may stop short (recorded in docs/settle_cases.md), but its end
    pose is never in collision and a stop is always explained."""
    result = run(name, kind, method='patent')
    var = sc.variant(name, kind)
    assert not CollisionPair(var.fixed, var.moving).collides(result.pose)
    if result.converged:
        assert result.reason.startswith('stable')
    else:
        assert result.reason.startswith(('wedged', 'iteration cap', 'no usable contact',
                                         'lost contact'))
    assert 1 <= result.iterations <= 500


def test_settling_again_does_not_move() -> None:
    var = sc.variant('key_pocket', 'rotated')
    first = run('key_pocket', 'rotated')
    again = settle(var.fixed, var.moving, first.pose,
                   SettleParams(push=tuple(float(v) for v in var.push)))
    assert again.converged
    assert np.linalg.norm(again.pose[:3, 3] - first.pose[:3, 3]) <= 2.0 * RESOLUTION_M
    cos = (np.trace(first.pose[:3, :3].T @ again.pose[:3, :3]) - 1.0) / 2.0
    arc = math.acos(min(1.0, cos)) * farthest_radius(var, first.pose)
    assert arc <= 2.0 * RESOLUTION_M


def test_python_fcl_judges_a_start_that_touches_or_nearly() -> None:
    """D7: a start the exact travel finds farther than the standoff from touching is free
    without python-fcl (its one query is the end pose's); one nearer, or in collision, is
    asked of python-fcl, which backs the colliding one out, and all three settle to the
    same rest."""
    var = sc.variant('sphere_bowl', 'plain')
    params = SettleParams(push=tuple(float(v) for v in var.push))
    push = var.push / np.linalg.norm(var.push)
    standoff = TUNING.standoff_res * params.resolution_m
    far = settle(var.fixed, var.moving, var.start, params)
    assert far.converged and far.fcl_checks == 1 and far.backed_out_m == 0.0
    near_start = far.pose.copy()         # a rest stands the standoff short of touching
    near_start[:3, 3] += 0.5 * standoff * push
    pair = CollisionPair(var.fixed, var.moving)
    assert not pair.collides(near_start)
    near = settle(var.fixed, var.moving, near_start, params)
    assert near.fcl_checks == 2 and near.backed_out_m == 0.0
    deep_start = far.pose.copy()
    deep_start[:3, 3] += 2e-3 * push
    assert pair.collides(deep_start)
    deep = settle(var.fixed, var.moving, deep_start, params)
    assert deep.fcl_checks > 2 and deep.backed_out_m >= 2e-3 - params.resolution_m
    for result in (near, deep):
        assert result.converged and not pair.collides(result.pose)
        assert np.linalg.norm(result.pose[:3, 3] - far.pose[:3, 3]) <= POSITION_TOL_M


def test_the_pairs_touching_at_rest_seed_a_settle_without_changing_its_answer() -> None:
    """A settle reports the pairs of triangles in contact at its rest; a settle seeded with
    them (a chain's next cell) ends at the same pose, bit for bit, as one without."""
    var = sc.variant('key_pocket', 'rotated')
    params = SettleParams(push=tuple(float(v) for v in var.push))
    first = settle(var.fixed, var.moving, var.start, params)
    assert first.converged and len(first.touching) > 0
    assert first.touching.shape[1] == 2 and first.touching.dtype == np.int64
    assert np.all(first.touching[:, 0] < len(var.moving.faces))
    assert np.all(first.touching[:, 1] < len(var.fixed.faces))
    start = var.start.copy()
    start[:3, 3] += 1e-3 * np.array([1.0, 0.0, 0.5])
    plain = settle(var.fixed, var.moving, start, params)
    seeded = settle(var.fixed, var.moving, start, params, seeds=first.touching)
    assert np.array_equal(plain.pose, seeded.pose)
    assert (plain.iterations, plain.travels) == (seeded.iterations, seeded.travels)
    assert np.array_equal(plain.touching, seeded.touching)


@pytest.mark.parametrize('locked', [None, (0.0, 0.0, 1.0)])
def test_lateral_moves_slide_across_the_push_and_spin_about_it(
        locked: tuple[float, float, float] | None) -> None:
    """Every move the climb makes is rigid: the centroid slides across the push by the
    move's slides (none along a locked direction) and the body turns about the push by
    the move's arc over the arm, whatever the pose it starts from."""
    var = sc.variant('key_pocket', 'rotated')
    rng = np.random.default_rng(20261202)
    params = SettleParams(push=tuple(float(v) for v in var.push), locked_slide=locked)
    search = Search(CollisionPair(var.fixed, var.moving), var.start, params, var.start)
    arm = 0.02
    planner = Planner(search, objective_for(params, None), arm, 0.0)
    for _ in range(20):
        axis = rng.normal(size=3)
        base = pose_from(rotation_about(axis / np.linalg.norm(axis), rng.normal()),
                         rng.normal(0.0, 0.01, 3))
        moves = rng.normal(0.0, 1e-3, (26, 3))
        for move, pose in zip(moves, planner.laterals(base, moves)):
            turn = pose[:3, :3] @ base[:3, :3].T
            assert np.allclose(turn @ turn.T, np.eye(3), atol=1e-12)
            assert np.allclose(turn @ search.push, search.push, atol=1e-12)
            slide = search.centre(pose) - search.centre(base)
            free = search.free * move
            assert np.allclose(slide, free[0] * search.e1 + free[1] * search.e2, atol=1e-15)
            angle = math.atan2(float(np.cross(search.e1, turn @ search.e1) @ search.push),
                               float(search.e1 @ turn @ search.e1))
            assert math.isclose(angle, move[2] / arm, abs_tol=1e-12)
        if locked is not None:        # e1 is the locked direction, across the push
            lock = np.asarray(locked) - (np.asarray(locked) @ search.push) * search.push
            assert np.allclose(search.e1, lock / np.linalg.norm(lock))


@pytest.mark.parametrize('name', ['sphere_cone', 'key_pocket'])
def test_end_pose_independent_of_start(name: str) -> None:
    """The patent's claim: 10 seeded random starts in one basin end within 2 x resolution
    of each other (positions; orientations as an arc at the farthest vertex).

    For the key, a start is in the pocket's basin only if the key's footprint lies inside
    the pocket's opening (30 x 15 mm half-sizes at the top): turned 30 degrees and 3 mm
    off, a corner lands on the flat top beside the pocket, and a key resting on one corner
    on a flat top is at rest too (a flat top offers no ascent). Such starts are drawn again.
    """
    var = sc.variant(name, 'plain')
    rng = np.random.default_rng(7)
    up = np.array([0.0, 1.0, 0.0])
    corners = np.array([[x, 0.0, z] for x in (-20e-3, 20e-3) for z in (-5e-3, 5e-3)])
    poses = []
    while len(poses) < 10:
        dx, dz = rng.uniform(-3e-3, 3e-3, 2)
        turn = rotation_about(up, math.radians(rng.uniform(-10.0, 10.0)))
        start = pose_from(turn @ var.start[:3, :3], var.start[:3, 3] + [dx, 0.0, dz])
        footprint = corners @ start[:3, :3].T + start[:3, 3]
        if name == 'key_pocket' and (np.abs(footprint[:, 0]).max() > 30e-3
                                     or np.abs(footprint[:, 2]).max() > 15e-3):
            continue
        result = settle(var.fixed, var.moving, start, SettleParams(push=tuple(var.push)))
        assert result.converged, result.reason
        poses.append(result.pose)
    radius = farthest_radius(var, poses[0])
    worst_position = worst_arc = 0.0
    for a, b in itertools.combinations(poses, 2):
        worst_position = max(worst_position, float(np.linalg.norm(a[:3, 3] - b[:3, 3])))
        cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
        worst_arc = max(worst_arc, math.acos(min(1.0, cos)) * radius)
    assert worst_position <= 2.0 * RESOLUTION_M, f'{worst_position * 1e3:.4f} mm apart'
    if name == 'key_pocket':    # a sphere's spin about its centre is not determined
        assert worst_arc <= 2.0 * RESOLUTION_M, f'arc {worst_arc * 1e3:.4f} mm apart'


def write_mm_scene(var: sc.Variant, folder: Path) -> tuple[Path, Path, Path]:
    """Both meshes scaled x1000 to STL, and the start as START.json (metres)."""
    paths = folder / 'fixed.stl', folder / 'moving.stl', folder / 'start.json'
    for mesh, path in zip((var.fixed_mesh, var.moving_mesh), paths):
        scaled = mesh.copy()
        scaled.apply_scale(1000.0)
        scaled.export(path)
    paths[2].write_text(json.dumps({
        'position': [float(v) for v in var.start[:3, 3]],
        'orientation': [float(v) for v in quat_from_matrix(var.start[:3, :3])]}))
    return paths


@pytest.mark.parametrize('name', sc.SCENES)
def test_cli_settles_millimetre_meshes(name: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    from kneeseat_core.geometry import matrix_from_quat
    var = sc.variant(name, 'plain')
    fixed, moving, start = write_mm_scene(var, tmp_path)
    push = ','.join(repr(float(v)) for v in var.push)
    code = main(['settle', '--fixed', str(fixed), '--moving', str(moving), '--units', 'mm',
                 '--start', str(start), f'--push={push}', '--json'])
    out, err = capsys.readouterr()
    assert code == 0, err
    data = json.loads(out)
    assert set(data) == JSON_KEYS and data['converged'] is True
    pose = pose_from(matrix_from_quat(np.array(data['pose']['orientation'])),
                     np.array(data['pose']['position']))
    position_err, rotation_err = sc.errors(name, 'plain', pose)
    assert position_err <= POSITION_TOL_M, f'{position_err * 1e3:.4f} mm'
    if rotation_err is not None:
        assert rotation_err <= default_rotation_tol(var), \
            f'{math.degrees(rotation_err):.4f} deg'
