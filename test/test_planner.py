"""The compiled planner (`kneeseat_core.settle.planner`) against numpy written here and
finite differences (the order the model promises, the poses of the moves and the lift each
needs, the ligaments weighed at each, the objective's value and first-order terms, the
travel's model), and the compiled best move against scipy's linear programming."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

import settle_cases as sc
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.ligaments import fibre_energy, fibre_force, parse_ligaments, Tissue
from kneeseat_core.meshes import CollisionPair
from kneeseat_core.settle import _moves, _simplex, SettleParams
from kneeseat_core.meshes.sweep import Touch
from kneeseat_core.settle.model import best_move, Model, STEEPEST
from kneeseat_core.settle.objective import Objective
from kneeseat_core.settle.planner import Planner
from kneeseat_core.settle.search import Search

BODIES = ['femur', 'tibia', 'patella']
TRAVEL = Objective(False, 1.0, None, None)


def fibres(rng: np.random.Generator, paths: bool) -> Tissue:
    """40 one-segment fibres from femur to tibia, and 9 paths of two segments when asked."""
    def point() -> list[float]:
        return list(rng.normal(0, 0.02, 3))
    items = [{'name': f'f{i}', 'slack_length_m': 0.01 + 0.02 * rng.random(),
              'linear_stiffness_n': 1000.0,
              'points': [{'body': 'femur', 'position': point()},
                         {'body': 'tibia', 'position': point()}]} for i in range(40)]
    if paths:
        items += [{'name': f'p{i}', 'slack_length_m': 0.05, 'linear_stiffness_n': 1000.0,
                   'points': [{'body': b, 'position': point()}
                              for b in ('femur', 'tibia', 'tibia')]} for i in range(9)]
    tissue = parse_ligaments(items, 'test', BODIES).tissue('tibia', {'femur': np.eye(4)})
    assert tissue is not None
    assert (len(tissue.seg_fibre) > len(tissue.slack_m)) == paths   # several segments a fibre
    return tissue


def random_poses(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.array([pose_from(rotation_about(rng.normal(size=3) / 3.0, rng.normal(0, 0.2)),
                               rng.normal(0, 0.005, 3)) for _ in range(count)])


def search_of(load_toward: tuple[float, float, float] | None = None) -> Search:
    var = sc.variant('key_pocket', 'rotated')
    params = SettleParams(push=tuple(float(v) for v in var.push), load_n=250.0,
                          load_toward=load_toward)
    return Search(CollisionPair(var.fixed, var.moving), var.start, params, var.start)


def numpy_pushes(tissue: Tissue, pose: np.ndarray) -> tuple[float, np.ndarray]:
    """The energy and dE/dt at `pose`, written out with numpy: each segment's vector, each
    fibre's length and tension, the pulls summed over the segments' moving ends."""
    d = tissue.seg_local @ pose[:3, :3].T + tissue.seg_sign[:, None] * pose[:3, 3] \
        + tissue.seg_fixed
    seg = np.linalg.norm(d, axis=1)
    lengths = np.bincount(tissue.seg_fibre, seg, minlength=len(tissue.slack_m))
    strain = lengths / tissue.slack_m - 1.0
    tension = fibre_force(strain, tissue.stiffness_n, tissue.transition)[tissue.seg_fibre]
    energy = float(fibre_energy(strain, tissue.stiffness_n, tissue.transition,
                                tissue.slack_m).sum())
    return energy, tissue.seg_sign @ (d * (tension / seg)[:, None])


@pytest.mark.parametrize('paths', [False, True])
def test_the_ligaments_weigh_each_pose_as_numpy_and_finite_differences_do(paths: bool) -> None:
    rng = np.random.default_rng(20261202)
    tissue = fibres(rng, paths)
    search = search_of()
    planner = Planner(search, Objective(True, 250.0, None, tissue), 0.02, 0.0)
    poses = random_poses(rng, 64)
    for size in (0, 1, 4, 43):
        energies, forces = planner.pushes(poses[:size])
        assert energies.shape == (size,) and forces.shape == (size, 3)
        for pose, energy, force in zip(poses[:size], energies, forces):
            alone_energy, alone_force = numpy_pushes(tissue, pose)
            assert alone_energy > 0.0
            assert abs(energy - alone_energy) <= 1e-12 * alone_energy
            assert np.max(np.abs(force - alone_force)) <= 1e-12 * np.max(np.abs(alone_force))
    h = 1e-7
    for pose in poses[:4]:          # dE/dt is the energy's rate under a translation
        _, force = planner.pushes(pose[None])
        for axis in range(3):
            moved, back = pose.copy(), pose.copy()
            moved[axis, 3] += h
            back[axis, 3] -= h
            numeric = (tissue.energy(moved) - tissue.energy(back)) / (2 * h)
            assert float(force[0, axis]) == pytest.approx(numeric, rel=1e-5, abs=1e-9)


def numpy_worth(search: Search, work: Objective, pose: np.ndarray) -> tuple[float, float]:
    """What `pose` is worth (the load's work less the energy, per unit load) and the rate of
    that under a lift along the push, written out with numpy."""
    energy, force = numpy_pushes(work.tissue, pose) if work.tissue else (0.0, np.zeros(3))
    centre = search.centre(pose)
    if work.toward is None:
        value, line = float(centre @ search.push), search.push
    else:
        d = work.toward - centre
        value, line = -float(np.linalg.norm(d)), d / np.linalg.norm(d)
    slope = float(line @ search.push) - float(force @ search.push) / work.load_n
    return value - energy / work.load_n, slope


def numpy_lifts(search: Search, work: Objective, targets: np.ndarray, want: float) -> np.ndarray:
    """The lift each target needs, one Newton step from none."""
    out = []
    for pose in targets:
        value, slope = numpy_worth(search, work, pose)
        out.append((want - value) / slope if slope > 0 else math.inf)
    return np.array(out)


@pytest.mark.parametrize('toward', [None, (0.0, 0.3, 0.05)])
def test_the_first_order_terms_are_the_objective_s_rates_by_finite_differences(
        toward: tuple[float, float, float] | None) -> None:
    """press and drive against central differences of the objective written out with numpy
    (the load's work less `Tissue.energy` per unit load) under a lift along the push and
    each lateral move (slides, a spin about the axis through the centroid)."""
    rng = np.random.default_rng(20261208)
    search = search_of(toward)
    arm, tissue = 0.02, fibres(rng, True)
    objective = Objective(True, 250.0, None if toward is None else np.asarray(toward), tissue)
    planner = Planner(search, objective, arm, 0.0)

    def worth(pose: np.ndarray) -> float:
        centre = search.centre(pose)
        work = float(centre @ search.push) if toward is None \
            else -float(np.linalg.norm(np.asarray(toward) - centre))
        return work - tissue.energy(pose) / 250.0

    def moved(pose: np.ndarray, x: np.ndarray, lift: float) -> np.ndarray:
        turn = rotation_about(search.push, x[2] / arm)
        centre = search.centre(pose)
        out = pose.copy()
        out[:3, :3] = turn @ pose[:3, :3]
        out[:3, 3] = turn @ (pose[:3, 3] - centre) + centre + x[0] * search.e1 \
            + x[1] * search.e2 + lift * search.push
        return out
    for pose in random_poses(rng, 4):
        press, drive = planner.first_order(pose)
        h = 1e-7
        still = np.zeros(3)
        lifted = (worth(moved(pose, still, h)) - worth(moved(pose, still, -h))) / (2 * h)
        assert press == pytest.approx(lifted, rel=1e-5, abs=1e-7)
        for i in range(3):
            x = np.zeros(3)
            x[i] = h
            rate = (worth(moved(pose, x, 0.0)) - worth(moved(pose, -x, 0.0))) / (2 * h)
            assert drive[i] == pytest.approx(rate, rel=1e-5, abs=1e-7)
        pull, load = planner.pulls(pose)
        assert load - pull == pytest.approx(press, rel=1e-12, abs=1e-15)
    assert TRAVEL.gain == 'along the push' and TRAVEL.precision == 1.0
    travel = Planner(search, TRAVEL, arm, 0.0)
    press, drive = travel.first_order(search.start)
    assert press == 1.0 and not drive.any()


@pytest.mark.parametrize('locked', [None, (0.0, 0.0, 1.0)])
def test_a_model_keeps_the_features_within_reach_with_their_slopes(
        locked: tuple[float, float, float] | None) -> None:
    """The model's features and slopes against numpy: each slope is the rate of the
    feature's gap under a move, found here by moving the body's point (a slide, a spin
    about the axis through the centroid parallel to the push) and taking the change of the
    gap along the push onto the feature's plane; the features as measured and seen from a
    place further along the push (their gaps less, their points moved with the body)."""
    rng = np.random.default_rng(20261207)
    var = sc.variant('key_pocket', 'rotated')
    params = SettleParams(push=tuple(float(v) for v in var.push), locked_slide=locked)
    search = Search(CollisionPair(var.fixed, var.moving), var.start, params, var.start)
    arm = 0.02
    planner = Planner(search, TRAVEL, arm, 0.0)
    k = 60
    normals = search.push + rng.normal(0.0, 0.6, (k, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[normals @ search.push < 0] *= -1.0
    measured = Touch.of(0.0, False, rng.uniform(0.0, 5e-5, k), normals,
                        rng.normal(0.0, 0.02, (k, 3)), rng.uniform(0.0, 1e-4, k),
                        np.zeros(k, dtype=np.int64), rng.integers(0, 100, (k, 2)))
    centre = rng.normal(0.0, 0.01, 3)
    # as measured, and seen from a place 10 um further along the push (the climb's)
    for touch, (within, room) in itertools.product(
            (measured, measured.lifted(1e-5, search.push)),
            ((np.inf, 0.0), (2e-5, 3e-5), (2e-5, 1.0))):
        model = planner.model(touch, centre, within, room)
        near = touch.gaps <= within
        if (near & (touch.rooms >= room)).any():
            near &= touch.rooms >= room
        rates = []
        for j in range(k):         # the gap's rate under a unit of each move coordinate
            n, q = touch.normals[j], touch.points[j]
            moved = [search.e1, search.e2, np.cross(search.push, q - centre) / arm]
            rates.append([-(n @ dp) / (n @ search.push) * f for dp, f in zip(moved, search.free)])
        rates = np.array(rates)
        near &= np.max(np.abs(rates), axis=1) <= STEEPEST
        assert 0 < near.sum() < k
        assert np.array_equal(model.gaps, touch.gaps[near])
        assert np.array_equal(model.faces, touch.faces[near])
        assert np.allclose(model.slopes, rates[near], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize('toward', [None, (0.0, 0.3, 0.05)])
@pytest.mark.parametrize('tries', [None, 5])
def test_a_plan_orders_the_moves_by_their_promise_and_lifts_each_as_numpy_does(
        toward: tuple[float, float, float] | None, tries: int | None) -> None:
    rng = np.random.default_rng(20261206)
    search = search_of(toward)
    arm, standoff, gain = 0.02, 2e-6, 1e-6
    work = Objective(True, 250.0, None if toward is None else np.asarray(toward),
                     fibres(rng, True))
    planner = Planner(search, work, arm, standoff)
    base = search.start.copy()
    moves = rng.normal(0.0, 2e-4, (27, 3))
    moves[5] = moves[9]                    # a tie: kept in the order given
    near = Model(rng.uniform(0.0, 1e-5, 6), rng.normal(0.0, 0.5, (6, 3)),
                 np.zeros((6, 2), dtype=np.int64))
    press, drive = 0.8, rng.normal(0.0, 0.3, 3)
    want = planner.value(base) + gain
    order, targets, needed = planner.plan(base, moves, near, press, drive, tries, gain, want)
    promise = moves @ drive + press * (np.min(near.gaps + moves @ near.slopes.T, axis=1)
                                       - np.min(near.gaps))
    expected = np.argsort(-promise, kind='stable')[:tries]
    assert np.array_equal(order, expected)
    assert np.allclose(targets, planner.laterals(base, moves[order]), rtol=0, atol=1e-15)
    for pose in targets:
        assert planner.value(pose) == pytest.approx(numpy_worth(search, work, pose)[0],
                                                    rel=1e-12, abs=1e-15)
    lifts = numpy_lifts(search, work, targets, want) + standoff
    finite = np.isfinite(lifts)
    assert finite.any()
    assert np.array_equal(finite, np.isfinite(needed))
    assert np.allclose(needed[finite], lifts[finite], rtol=1e-9, atol=1e-12)
    # the travel alone: every move must reach the gain itself, in the order it promises
    travel = Planner(search, TRAVEL, arm, standoff)
    order, _, needed = travel.plan(base, moves, near, 1.0, np.zeros(3), tries, gain, want)
    plain = np.min(near.gaps + moves @ near.slopes.T, axis=1)
    assert np.array_equal(order, np.argsort(-plain, kind='stable')[:tries])
    assert np.all(needed == gain + standoff)
    assert travel.value(base) == pytest.approx(search.depth(base), rel=0, abs=1e-15)


def test_without_features_the_drive_alone_orders_the_moves() -> None:
    search = search_of()
    planner = Planner(search, TRAVEL, 0.02, 0.0)
    moves = np.array([[1e-4, 0.0, 0.0], [-1e-4, 0.0, 0.0], [0.0, 0.0, 2e-4]])
    empty = Model(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2), dtype=np.int64))
    order, targets, _ = planner.plan(search.start, moves, empty, 1.0,
                                     np.array([-1.0, 0.0, 0.5]), None, 1e-6, 0.0)
    assert order.tolist() == [1, 2, 0] and targets.shape == (3, 4, 4)


def test_the_compiled_planner_refuses_bad_arrays_without_crashing() -> None:
    """Wrong shapes, dtypes or a fibre index out of range are a Python error, never a crash."""
    e = np.eye(3)
    local, sign, fixed = np.zeros((2, 3)), np.ones(2), np.zeros((2, 3))
    laws = (np.ones(2), np.ones(2), np.ones(2))

    def planner(fibre_of: object, local: object = local) -> _moves.Planner:
        return _moves.Planner(e[2], e[0], e[1], np.ones(3), np.zeros(3), 1.0, 0.0, 3.0, True, 1.0,
                              None, (local, sign, fixed, fibre_of, *laws))
    good = planner(np.array([0, 1]))
    assert len(good.pushes(np.eye(4)[None])[0]) == 8
    with pytest.raises(ValueError):
        planner(np.array([0, 2]))
    with pytest.raises(ValueError):
        planner(np.array([0, 1]), local[:1])
    with pytest.raises(ValueError):
        planner(np.array([0.0, 1.0]))
    with pytest.raises(ValueError):
        good.pushes(np.eye(3))
    with pytest.raises(ValueError):
        good.laterals(np.eye(4), np.zeros((2, 2)))
    with pytest.raises(ValueError):
        good.plan(np.eye(4), np.zeros((2, 3)), np.zeros(2), np.zeros((3, 3)), 1.0, np.zeros(3),
                  -1, 0.0, 0.0)
    with pytest.raises(TypeError):
        good.pushes('x')
    with pytest.raises(ValueError):
        _moves.Planner(e[2], e[0], e[1], np.ones(3), np.zeros(3), 0.0, 0.0, 3.0, False, 1.0,
                       None, None)
    with pytest.raises(ValueError):      # not whole feature records
        good.model(bytes(100), 0.0, np.zeros(3), 1.0, 0.0)
    with pytest.raises(TypeError):
        good.model('x', 0.0, np.zeros(3), 1.0, 0.0)
    with pytest.raises(ValueError):
        good.model(bytes(88), 0.0, np.zeros(2), 1.0, 0.0)


@pytest.mark.parametrize('seed', range(6))
def test_the_best_move_is_the_linear_program_s_optimum_as_scipy_finds_it(seed: int) -> None:
    """The compiled program (`best_move`) against scipy's linprog on the same model: the
    objective it reaches is the optimum to rounding, inside the box, and what it promises
    is measured on the model."""
    from scipy.optimize import linprog
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 12))
    near = Model(rng.uniform(0.0, 2e-5, k), rng.normal(0.0, 0.6, (k, 3)),
                 np.zeros((k, 2), dtype=np.int64))
    press, drive = float(rng.uniform(0.2, 1.5)), rng.normal(0.0, 0.2, 3)
    radius = rng.uniform(1e-5, 1e-4, 3) * (rng.random(3) > 0.2)
    x, promised = best_move(near, press, drive, radius)
    assert np.all(np.abs(x) <= radius)
    modelled = float(np.min(near.gaps + near.slopes @ x))
    assert promised == pytest.approx(press * (modelled - np.min(near.gaps)) + drive @ x,
                                     abs=1e-15)
    # over (x, s): maximise press s + drive . x with s <= g_k + a_k . x, |x_i| <= r_i
    cost = -np.concatenate([drive, [press]])
    a = np.hstack([-near.slopes, np.ones((k, 1))])
    bounds = [(-r, r) for r in radius] + [(None, None)]
    ref = linprog(cost, A_ub=a, b_ub=near.gaps, bounds=bounds, method='highs')
    assert ref.status == 0
    best = -ref.fun - press * float(np.min(near.gaps))
    # each unit of a move's length costs a millionth of the rates: at most that is given up
    allowance = 1e-6 * max(press, float(np.max(np.abs(drive)))) * float(np.sum(radius)) * 2
    assert promised >= best - allowance - 1e-15
    assert promised <= best + 1e-15


def test_the_best_move_refuses_a_bad_model_without_crashing() -> None:
    with pytest.raises(ValueError):
        _simplex.best_move(np.zeros(0), np.zeros((0, 3)), 1.0, np.zeros(3), np.ones(3))
    with pytest.raises(ValueError):
        _simplex.best_move(np.zeros(2), np.zeros((3, 3)), 1.0, np.zeros(3), np.ones(3))
    with pytest.raises(ValueError):
        _simplex.best_move(np.array([np.nan]), np.zeros((1, 3)), 1.0, np.zeros(3), np.ones(3))
    with pytest.raises(ValueError):
        _simplex.best_move(np.zeros(1), np.zeros((1, 3)), 1.0, np.zeros(3), -np.ones(3))
