"""The exact travel (`kneeseat_core.meshes.sweep`, compiled) against python-fcl.

The referee of every travel here is a dichotomy on python-fcl's boolean query written in
this file (nothing of the engine or of the settle): the engine's travel must be python-fcl's
first collision to the dichotomy's tolerance. Scenes: the analytic ones of
test/settle_cases.py (closed meshes), two prisms whose ridges meet edge across edge (no
vertex touches), and, when the shared data is there, the total knee (closed) and the natural
knee's open cartilage sheets. What the engine says refutes a move (a pair's or a vertex's gap
short of what the move needs) must be a collision python-fcl finds.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.meshes import CollisionPair, load_mesh, load_meshes, RigidBody, SweepPair
from kneeseat_core.meshes import _sweep
from kneeseat_core.meshes.sweep import facing, PLACE, SHORT, sweep_body, Touch
import settle_cases as sc

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'data'
TOL_M = 1e-8              # the referee's dichotomy stops this close


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
                    push: np.ndarray) -> None:
    """Each pose's exact travel, alone and with the others in one call, is the referee's."""
    pair = CollisionPair(fixed, moving)
    sweep = SweepPair(fixed, moving, push)
    free = [backed(pair, pose, push) for pose in poses]
    together, buried = sweep.travels(np.array(free))
    assert not buried.any()
    for pose, got in zip(free, together):
        want = fcl_travel(pair, pose, push)
        alone = sweep.touch(pose, 0.0, 1e-4).travel
        assert alone == got
        if math.isinf(want):
            assert math.isinf(got)
            continue
        assert abs(got - want) <= 2 * TOL_M, \
            f'exact travel {got * 1e3:.7f} mm, python-fcl {want * 1e3:.7f} mm'


def analytic_scene(name: str, seed: int, n: int
                   ) -> tuple[RigidBody, RigidBody, np.ndarray, list[np.ndarray]]:
    """The analytic scene `name` (rotated variant): its bodies, its unit push and `n`
    seeded poses about its start, slid up to 3 mm and spun up to 8 deg."""
    var = sc.variant(name, 'rotated')
    push = var.push / np.linalg.norm(var.push)
    centre = var.start[:3, :3] @ var.moving.centroid + var.start[:3, 3]
    poses = lateral_poses(var.start, push, centre, seed=seed, n=n, slide_m=3e-3,
                          spin_deg=8.0)
    return var.fixed, var.moving, push, poses


def total_knee(seed: int) -> tuple[RigidBody, RigidBody, np.ndarray, list[np.ndarray]]:
    """The femoral component, the insert, the push (+Y) and 6 seeded poses of the insert
    2 mm below its delivered pose, slid up to 2 mm and spun up to 4 deg."""
    fixed = RigidBody.from_mesh(load_mesh(SHARED / 'tka_dm' / 'femoral_component.stl', 'm'))
    moving = RigidBody.from_mesh(load_mesh(SHARED / 'tka_dm' / 'tibial_insert.stl', 'm'))
    push = np.array([0.0, 1.0, 0.0])
    start = pose_from(np.eye(3), np.array([0.0, -2e-3, 0.0]))
    poses = lateral_poses(start, push, moving.centroid, seed=seed, n=6, slide_m=2e-3,
                          spin_deg=4.0)
    return fixed, moving, push, poses


@pytest.mark.parametrize('name', sc.SCENES)
def test_travel_is_python_fcl_first_collision_on_the_analytic_scenes(name: str) -> None:
    fixed, moving, push, poses = analytic_scene(name, seed=3, n=8)
    check_agreement(fixed, moving, poses, push)


@pytest.mark.skipif(not (SHARED / 'tka_dm').is_dir(), reason='no shared total knee data')
def test_travel_is_python_fcl_first_collision_on_the_total_knee() -> None:
    fixed, moving, push, poses = total_knee(seed=5)
    check_agreement(fixed, moving, poses, push)


@pytest.mark.skipif(not (SHARED / 'natural_knee').is_dir(),
                    reason='no shared natural knee data')
def test_travel_is_python_fcl_first_collision_on_open_cartilage_sheets() -> None:
    """Open sheets take part with both faces: the travel is python-fcl's all the same."""
    data = SHARED / 'natural_knee'
    fixed = RigidBody.from_mesh(load_meshes([str(data / 'femur_cartilage.stl'),
                                             str(data / 'femur_bone.stl')], 'm', quiet=True))
    moving = RigidBody.from_mesh(load_meshes([str(data / 'tibia_cartilage.stl'),
                                              str(data / 'tibia_bone.stl')], 'm', quiet=True))
    assert 0 in facing(fixed.mesh) and 1 in facing(fixed.mesh)
    push = np.array([0.0, 1.0, 0.0])
    start = pose_from(np.eye(3), np.array([0.0, -1e-3, 0.0]))
    poses = lateral_poses(start, push, moving.centroid, seed=9, n=6, slide_m=1.5e-3,
                          spin_deg=3.0)
    check_agreement(fixed, moving, poses, push)


def test_a_pose_in_collision_has_a_negative_travel_or_is_buried() -> None:
    """From a pose 0.5 mm past contact, lowered by more than that, the travel is -0.5 mm;
    lowered by less, the lowered pose is itself in collision: buried."""
    var = sc.variant('sphere_bowl', 'plain')
    push = var.push / np.linalg.norm(var.push)
    pair = CollisionPair(var.fixed, var.moving)
    free = backed(pair, var.start, push)
    travel = fcl_travel(pair, free, push)
    deep = free.copy()
    deep[:3, 3] += (travel + 5e-4) * push
    assert pair.collides(deep)
    sweep = SweepPair(var.fixed, var.moving, push)
    got, buried = sweep.travels(deep[None], behind=1e-3)
    assert not buried[0] and abs(got[0] + 5e-4) <= 2 * TOL_M
    got, buried = sweep.travels(deep[None], behind=1e-4)
    assert buried[0] and got[0] == -math.inf


def crossed_ridges(offset_m: float) -> tuple[RigidBody, RigidBody, np.ndarray, np.ndarray]:
    """Two triangular prisms whose ridges cross at right angles, the moving one pointing
    down onto the fixed one 0.1 mm above their first touch and moved `offset_m` along the
    fixed ridge: the surfaces meet edge across edge, far from every vertex."""
    def prism(along: str, height: float) -> trimesh.Trimesh:
        points = [(s, a, z) if along == 'x' else (a, s, z) for s in (-0.03, 0.03)
                  for a, z in ((-0.01, 0.0), (0.01, 0.0), (0.0, height))]
        return trimesh.convex.convex_hull(np.array(points))
    fixed = RigidBody.from_mesh(prism('x', 0.01))       # its ridge at z = 10 mm
    moving = RigidBody.from_mesh(prism('y', -0.01))     # its ridge 10 mm below its origin
    push = np.array([0.0, 0.0, -1.0])
    return fixed, moving, push, pose_from(np.eye(3), np.array([offset_m, 0.0, 0.02 + 1e-4]))


@pytest.mark.parametrize('offset_mm', [0.0, 3.7])
def test_an_edge_across_an_edge_is_a_contact(offset_mm: float) -> None:
    """No vertex touches where the ridges cross: the travel is the edges' first meeting,
    0.1 mm, as python-fcl finds it, and the feature there is an edge across an edge."""
    fixed, moving, push, pose = crossed_ridges(offset_mm * 1e-3)
    touch = SweepPair(fixed, moving, push).touch(pose, 0.0, 1e-6)
    assert abs(touch.travel - 1e-4) <= 1e-12
    assert abs(fcl_travel(CollisionPair(fixed, moving), pose, push) - 1e-4) <= 2 * TOL_M
    assert set(touch.kinds[touch.gaps <= touch.travel + 1e-12].tolist()) == {2}


def test_which_faces_take_part() -> None:
    """A closed surface's faces face out (+1), or in where it is wound inside out (-1); an
    open surface's faces both ways (0), each surface of a combined mesh on its own."""
    box = trimesh.creation.box()
    inside_out = box.copy()
    inside_out.invert()
    sphere = trimesh.creation.icosphere()
    sheet = trimesh.Trimesh(sphere.vertices, sphere.faces[:-3])
    assert set(facing(box).tolist()) == {1}
    assert set(facing(inside_out).tolist()) == {-1}
    assert set(facing(sheet).tolist()) == {0}
    both = facing(trimesh.util.concatenate([box, sheet]))
    assert both[:len(box.faces)].tolist() == [1] * len(box.faces)
    assert set(both[len(box.faces):].tolist()) == {0}


def probing(fixed: RigidBody, moving: RigidBody, push: np.ndarray, start: np.ndarray,
            seed: int) -> tuple[CollisionPair, SweepPair, Touch, np.ndarray, np.ndarray]:
    """A pose 0.1 um short of contact (python-fcl's), its features within 0.3 mm, 24
    lateral probes about it and a lift each must reach."""
    pair = CollisionPair(fixed, moving)
    free = backed(pair, start, push)
    free[:3, 3] += (fcl_travel(pair, free, push) - 1e-7) * push
    sweep = SweepPair(fixed, moving, push)
    touch = sweep.touch(free, 0.0, 3e-4)
    assert len(touch.gaps), 'no contact to probe from'
    centre = free[:3, :3] @ moving.centroid + free[:3, 3]
    probes = np.array(lateral_poses(free, push, centre, seed, 24, 3e-4, 0.5))
    lifts = np.random.default_rng(seed).choice([2.5e-6, 2.5e-5, 1e-4], len(probes))
    return pair, sweep, touch, probes, lifts


def refutations(fixed: RigidBody, moving: RigidBody, push: np.ndarray, start: np.ndarray,
                seed: int) -> tuple[int, int]:
    """Probes about a contact pose, as the climb makes them: every pair of triangles within
    0.3 mm of touching there, and the vertices of its moving triangles, asked at each
    probe. Where a witness is short of the probe's lift, python-fcl must find the probe
    lifted by it in collision; the whole search must then find a travel short of the lift
    too, and where it does not, no witness may say so. A search told to stop short of the
    lift (`short_of`) must say short exactly where the whole search does, and otherwise
    give its answer. Returns (refuted probes, probes)."""
    pair, sweep, touch, probes, lifts = probing(fixed, moving, push, start, seed)
    # every pair a witness of every probe
    pool = (touch.gaps, np.zeros((len(touch.gaps), 3)), touch.faces)
    offsets = np.zeros((len(probes), 3))
    refuted = np.array([sweep.first_unrefuted(probes, lifts, pool, offsets, len(touch.gaps),
                                              0.0, 1e-3, i)[0] != i for i in range(len(probes))])
    for probe, lift, no in zip(probes, lifts, refuted):
        whole = sweep.touch(probe, 1e-3, 3e-4)
        short = sweep.touch(probe, 1e-3, 3e-4, short_of=lift)
        assert not whole.buried and (short.travel < lift) == (whole.travel < lift)
        if whole.travel >= lift:
            assert not no, 'a witness closed short of a travel the whole search finds'
            assert short.travel == whole.travel and np.array_equal(short.gaps, whole.gaps)
        if no:
            lifted = probe.copy()
            lifted[:3, 3] += lift * push
            assert pair.collides(lifted), f'refuted a probe python-fcl finds free ({lift})'
    return int(refuted.sum()), len(probes)


@pytest.mark.parametrize('name', sc.SCENES)
def test_a_refuted_probe_collides_for_python_fcl(name: str) -> None:
    var = sc.variant(name, 'rotated')
    push = var.push / np.linalg.norm(var.push)
    refuted, probes = refutations(var.fixed, var.moving, push, var.start, seed=7)
    assert 0 < refuted <= probes


@pytest.mark.parametrize('name', sc.SCENES)
def test_measuring_finds_the_first_probe_unrefuted_and_not_short(name: str) -> None:
    """`measure` (the climb's loop over its moves, compiled) against its parts asked in
    turn: the witnesses (`first_unrefuted`) and a search told to stop short of the lift
    (`touch`); the same probe, travel and features, and SHORT where every probe fails."""
    var = sc.variant(name, 'rotated')
    push = var.push / np.linalg.norm(var.push)
    _, sweep, touch, probes, lifts = probing(var.fixed, var.moving, push, var.start, seed=7)
    pool = (touch.gaps, np.zeros((len(touch.gaps), 3)), touch.faces)
    offsets = np.zeros((len(probes), 3))
    count, standoff, found = len(touch.gaps), 1e-7, 0
    i = 0
    while i <= len(probes):
        j, kind, got, _ = sweep.measure(probes, lifts, lifts, (3e-4, 3e-4), pool, offsets,
                                        np.zeros(3), math.inf, count, standoff, 1e-3, i)
        k, ref = i, None
        while k < len(probes):
            k, _ = sweep.first_unrefuted(probes, lifts, pool, offsets, count, standoff, 1e-3, k)
            if k >= len(probes):
                break
            ref = sweep.touch(probes[k], standoff, 3e-4, short_of=lifts[k])
            if ref.travel >= lifts[k]:
                break
            k += 1
        assert j == k
        if j == len(probes):
            assert kind == SHORT and got is None
            break
        assert kind == PLACE and got is not None and ref is not None
        assert got.travel == ref.travel and np.array_equal(got.gaps, ref.gaps)
        assert np.array_equal(got.faces, ref.faces)
        found += 1
        i = j + 1
    assert found > 0


def test_the_pairs_that_stopped_searches_short_spare_later_searches_and_change_no_answer(
        ) -> None:
    """A settle's pair keeps the pairs of triangles that stopped its searches short and asks
    them of its later moves before their witnesses: the moves about one place run into the
    same part of the fixed body, where a pool taken near the place may name none of it.
    Each probe about a contact, measured in turn with a pool that names only its farthest
    feature: the same answers as the same pair forgetting them before every call, and fewer
    searches over the scenes."""
    spared = 0
    for name in sc.SCENES:
        var = sc.variant(name, 'rotated')
        push = var.push / np.linalg.norm(var.push)
        _, _, touch, probes, lifts = probing(var.fixed, var.moving, push, var.start, seed=7)
        far = np.argsort(touch.gaps)[-1:]
        pool = (touch.gaps[far], np.zeros((1, 3)), touch.faces[far])
        answers, searches = [], []
        for remember in (True, False):
            sweep = SweepPair(var.fixed, var.moving, push)
            answered = []
            for probe, lift in zip(probes, lifts):
                if not remember:
                    sweep._stoppers.fill(-1)
                _, kind, got, _ = sweep.measure(probe[None], np.array([lift]),
                                                np.array([lift]), (3e-4, 3e-4), pool,
                                                np.zeros((1, 3)), np.zeros(3), math.inf, 1,
                                                1e-7, 1e-3)
                answered.append((kind, None if got is None else
                                 (got.travel, got.gaps.tobytes(), got.faces.tobytes())))
            assert any(kind == SHORT for kind, _ in answered)
            answers.append(answered)
            searches.append(sweep.queries)
        assert answers[0] == answers[1], name
        assert searches[0] <= searches[1], name
        spared += searches[1] - searches[0]
    assert spared > 0


@pytest.mark.parametrize('name', ['sphere_bowl', 'cylinder_groove', 'key_pocket'])
def test_a_capped_search_keeps_the_nearest_features_beyond_what_it_keeps_whole(
        name: str) -> None:
    """With a cap, the features within `keep` of the travel all stay and of the farther
    ones only the `cap` that close first (ties kept): the uncapped search's features so
    filtered, in the same order, at the same travel; a cap the window never reaches
    changes nothing."""
    var = sc.variant(name, 'rotated')
    sweep = SweepPair(var.fixed, var.moving, var.push / np.linalg.norm(var.push))
    none = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2), dtype=np.int64))

    def measured(cap: int, keep: float) -> Touch:
        _, kind, touch, _ = sweep.measure(var.start[None], np.array([-math.inf]),
                                          np.zeros(1), (1e-3, 1e-3), none, np.zeros((1, 3)),
                                          np.zeros(3), math.inf, 0, 1e-7, 0.0, cap=cap,
                                          keep=keep)
        assert kind == PLACE and touch is not None
        return touch

    whole = measured(0, 0.0)
    gaps = whole.gaps
    for cap, keep in ((10, 0.0), (10, 5e-5), (len(gaps) // 3, 1e-4), (len(gaps), 0.0)):
        got = measured(cap, keep)
        bound = max(np.sort(gaps)[min(cap, len(gaps)) - 1], whole.travel + keep)
        kept = gaps <= bound
        assert got.travel == whole.travel
        assert np.array_equal(got.gaps, gaps[kept]) and np.array_equal(got.faces,
                                                                       whole.faces[kept])
        assert len(got.gaps) >= min(cap, len(gaps))
    assert len(measured(10, 0.0).gaps) < len(gaps)       # the cap took some away


def test_measure_refuses_bad_input_without_crashing() -> None:
    var = sc.variant('key_pocket', 'rotated')
    sweep = SweepPair(var.fixed, var.moving, var.push / np.linalg.norm(var.push))
    none = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2), dtype=np.int64))
    one = var.start[None]

    def measure(expected: float = 0.0, windows: tuple[float, float] = (1.0, 1.0),
                reach: float = math.inf, standoff: float = 1e-7, **kwargs: Any) -> Any:
        return sweep.measure(one, np.zeros(1), np.array([expected]), windows, none,
                             np.zeros((1, 3)), np.zeros(3), reach, 0, standoff, 0.0, **kwargs)

    for standoff, expected in ((0.0, 0.0), (1e-7, math.inf)):      # a standoff, a depth
        with pytest.raises(ValueError):
            measure(expected, standoff=standoff)
    for windows, reach in (((-1.0, 1.0), math.inf), ((1.0, math.nan), math.inf),
                           ((1.0, 1.0), math.nan)):                 # the windows, the reach
        with pytest.raises(ValueError):
            measure(windows=windows, reach=reach)
    with pytest.raises(ValueError):
        measure(seeds=np.array([[0, 10 ** 9]]))
    with pytest.raises(ValueError):                                 # a move and its shift
        sweep.measure(one, np.zeros(1), np.zeros(1), (1.0, 1.0), none, np.zeros((2, 3)),
                      np.zeros(3), math.inf, 0, 1e-7, 0.0)
    with pytest.raises(ValueError):
        sweep.measure(one, np.zeros(1), np.zeros(1), (1.0, 1.0), none, np.zeros((1, 3)),
                      np.zeros(2), math.inf, 0, 1e-7, 0.0)
    for cap, keep in ((-1, 0.0), (1, -1e-4), (1, math.nan)):        # a cap, a keep
        with pytest.raises(ValueError):
            measure(cap=cap, keep=keep)
    # the pairs kept that stopped searches short: each must name faces the bodies have, and
    # the engine writes them
    sweep._stoppers[0] = (0, 10 ** 9)
    with pytest.raises(ValueError):
        measure()
    sweep._stoppers = np.full((4, 2), -1, dtype=np.int64)
    sweep._stoppers.flags.writeable = False
    with pytest.raises((ValueError, BufferError)):
        measure()
    sweep._stoppers = np.full((4, 2), -1, dtype=np.int64)
    index, kind, touch, wide = sweep.measure(one, np.array([-math.inf]), np.zeros(1),
                                             (1.0, 1.0), none, np.zeros((1, 3)), np.zeros(3),
                                             math.inf, 0, 1e-7, 0.0)
    assert (index, kind, wide) == (0, PLACE, False) and touch is not None
    assert len(touch.gaps) > 0


@pytest.mark.parametrize('name', ['sphere_bowl', 'key_pocket'])
def test_a_move_beyond_the_pools_reach_is_measured_with_the_wide_window(name: str) -> None:
    """A pose whose offset from where the pool was taken (its move plus the shift) exceeds
    the reach in a coordinate is measured with the second window and said to be wide; one
    within it with the first: each the features a search with that window finds."""
    var = sc.variant(name, 'rotated')
    push = var.push / np.linalg.norm(var.push)
    _, _, touch, probes, _ = probing(var.fixed, var.moving, push, var.start, seed=7)
    sweep = SweepPair(var.fixed, var.moving, push)
    pool = (touch.gaps, np.zeros((len(touch.gaps), 3)), touch.faces)
    near, far, reach, standoff = 1e-5, 3e-4, 1e-4, 1e-7
    # a probe that stands free (one in collision is measured from lower down)
    probes = probes[[sweep.touch(p, standoff).travel > 0.0 for p in probes]]
    move = np.array([[0.0, 6e-5, 0.0]])
    for shift, wide in ((np.array([-3e-5, 0.0, 0.0]), False),      # within the reach
                        (np.array([0.0, 5e-5, 0.0]), True),        # 1.1e-4 in e2
                        (np.array([0.0, 0.0, -1.2e-4]), True)):    # in the arc alone
        _, kind, got, said = sweep.measure(probes[:1], np.array([-math.inf]), np.zeros(1),
                                           (near, far), pool, move, shift, reach,
                                           len(touch.gaps), standoff, 1e-3)
        ref = sweep.touch(probes[0], standoff, far if wide else near)
        assert kind == PLACE and got is not None and said == wide
        assert np.array_equal(got.gaps, ref.gaps) and np.array_equal(got.faces, ref.faces)
    assert len(sweep.touch(probes[0], standoff, far).gaps) > \
        len(sweep.touch(probes[0], standoff, near).gaps)


@pytest.mark.skipif(not (SHARED / 'tka_dm').is_dir(), reason='no shared total knee data')
def test_a_refuted_probe_collides_for_python_fcl_on_the_total_knee() -> None:
    fixed, moving, push, _ = total_knee(seed=1)
    refuted, probes = refutations(fixed, moving, push, pose_from(np.eye(3),
                                                                 np.array([0.0, -2e-3, 0.0])),
                                  seed=13)
    assert refuted >= probes // 2


def test_a_moves_witnesses_are_the_pool_features_that_close_first_after_it() -> None:
    """The witnesses of a move are the `count` features of the pool whose first-order gap
    after the move's offset is least, first closing first (numpy ranks them here); a move
    whose needed travel is not finite is passed over, and one that no witness refutes
    comes back with them."""
    var = sc.variant(sc.SCENES[0], 'rotated')
    push = var.push / np.linalg.norm(var.push)
    sweep = SweepPair(var.fixed, var.moving, push)
    rng = np.random.default_rng(3)
    k = 200
    faces = np.column_stack([rng.integers(0, len(var.moving.faces), k),
                             rng.integers(0, len(var.fixed.faces), k)])
    gaps, slopes = rng.uniform(0.0, 1e-3, k), rng.uniform(-1.0, 1.0, (k, 3))
    offsets = rng.uniform(-1e-4, 1e-4, (3, 3))
    poses = np.repeat(np.asarray(var.start, dtype=np.float64)[None], 3, axis=0)
    poses[:, :3, 3] -= 0.5 * push      # far from the fixed body: nothing closes short
    needed = np.array([math.inf, -1.0, -1.0])
    for count in (1, 17, k, k + 5):
        index, witnesses = sweep.first_unrefuted(poses, needed, (gaps, slopes, faces), offsets,
                                                 count, 0.0, 1e-3)
        assert index == 1 and witnesses is not None
        ranked = np.argsort(gaps + slopes @ offsets[1], kind='stable')[:count]
        assert np.array_equal(witnesses, faces[ranked])
        index, _ = sweep.first_unrefuted(poses, needed, (gaps, slopes, faces), offsets, count,
                                         0.0, 1e-3, start=2)
        assert index == 2
    assert sweep.first_unrefuted(poses, needed, (gaps, slopes, faces), offsets, 5, 0.0, 1e-3,
                                 start=3) == (3, None)


@pytest.mark.skipif(not (SHARED / 'tka_dm').is_dir(), reason='no shared total knee data')
def test_seeds_change_how_fast_a_touch_comes_never_what_it_returns() -> None:
    """A touch seeded with pairs of triangles (those that close first, others that close
    later, pairs whose shadows never meet) returns bit for bit what the unseeded touch
    does, with fewer pairs evaluated when the seeds close first."""
    fixed, moving, push, poses = total_knee(seed=5)
    pair, sweep = CollisionPair(fixed, moving), SweepPair(fixed, moving, push)
    rng = np.random.default_rng(11)
    fewer = 0
    for pose in (backed(pair, p, push) for p in poses):
        plain = sweep.touch(pose, 1e-7, 3e-5)
        first = plain.faces[np.argsort(plain.gaps, kind='stable')[:16]]
        anywhere = np.column_stack([rng.integers(0, len(moving.faces), 16),
                                    rng.integers(0, len(fixed.faces), 16)])
        for seeds in (first, plain.faces[::-1], anywhere, np.zeros((0, 2), dtype=np.int64)):
            seeded = sweep.touch(pose, 1e-7, 3e-5, seeds=seeds)
            assert seeded.travel == plain.travel and seeded.buried == plain.buried
            for name in ('gaps', 'normals', 'points', 'rooms', 'kinds', 'faces'):
                assert np.array_equal(getattr(seeded, name), getattr(plain, name)), name
        before = sweep.pairs
        sweep.touch(pose, 1e-7, 3e-5)
        unseeded = sweep.pairs - before
        before = sweep.pairs
        sweep.touch(pose, 1e-7, 3e-5, seeds=first)
        fewer += sweep.pairs - before < unseeded
    assert fewer >= len(poses) // 2


def test_the_engine_refuses_bad_arrays_without_crashing() -> None:
    """Wrong dtypes, shapes, indices or directions are a Python error, never a crash."""
    box = trimesh.creation.box()
    v = np.ascontiguousarray(box.vertices, dtype=np.float64)
    f = np.ascontiguousarray(box.faces, dtype=np.int64)
    s = np.ones(len(f), dtype=np.int8)
    with pytest.raises(TypeError):
        _sweep.Body(v.astype(np.float32), f, s)
    with pytest.raises(ValueError):
        _sweep.Body(v, f + 100, s)
    with pytest.raises(ValueError):
        _sweep.Body(v, f, s[:-1])
    body = _sweep.Body(v, f, s)
    with pytest.raises(ValueError):
        _sweep.View(body, np.array([0.0, 0.0, 2.0]), -1)
    fixed = _sweep.View(body, np.array([0.0, 0.0, 1.0]), -1)
    moving = _sweep.View(body, np.array([0.0, 0.0, 1.0]), 1)
    with pytest.raises(ValueError):
        _sweep.travels(moving, fixed, np.eye(4)[None], 0.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        _sweep.travels(fixed, moving, np.eye(3), 0.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        _sweep.travels(fixed, moving, np.eye(4)[None], -1.0, 0.0, 1.0)
    pose, one = np.eye(4)[None], np.zeros(1)
    gaps, slopes, faces = np.zeros(1), np.zeros((1, 3)), np.array([[0, 0]])
    offsets = np.zeros((1, 3))

    def first(**named: object) -> tuple[int, bytes]:
        args = dict(poses=pose, needed=one, gaps=gaps, slopes=slopes, faces=faces,
                    offsets=offsets, count=1, behind=0.0, deepest=0.0, start=0)
        args.update(named)
        return _sweep.first_unrefuted(fixed, moving, *args.values())

    index, _ = first()
    assert index in (0, 1)
    with pytest.raises(ValueError):       # a face the body does not have
        first(faces=np.array([[0, 99]]))
    with pytest.raises(ValueError):       # a needed travel too many
        first(needed=np.zeros(2))
    with pytest.raises(ValueError):       # slopes of the wrong shape
        first(slopes=np.zeros((1, 2)))
    with pytest.raises(ValueError):       # an offset missing
        first(offsets=np.zeros((0, 3)))
    with pytest.raises(ValueError):       # a negative depth
        first(deepest=-1.0)
    with pytest.raises(TypeError):
        first(needed='x')
    with pytest.raises(TypeError):
        first(faces=np.zeros((1, 2)))
    with pytest.raises(ValueError):
        _sweep.contacts(fixed, moving, np.eye(4), 0.0, 0.0, 1.0, math.nan)
    with pytest.raises(ValueError):       # a seed face the body does not have
        _sweep.contacts(fixed, moving, np.eye(4), 0.0, 0.0, 1.0, 0.0, np.array([[0, 99]]))
    with pytest.raises(TypeError):
        _sweep.contacts(fixed, moving, np.eye(4), 0.0, 0.0, 1.0, 0.0, np.zeros((1, 2)))


def test_a_pose_measures_the_same_whatever_direction_was_asked_before() -> None:
    """A worker settles cell after cell, and a body's view is kept per direction rounded to
    1e-12: a view first built for another direction of the same rounding must measure a
    pose bit for bit as a view built for the pose itself would (else a table differs from
    run to run with the order in which chains reach the workers)."""
    var = sc.variant('sphere_bowl', 'rotated')
    push = var.push / np.linalg.norm(var.push)
    pose = backed(CollisionPair(var.fixed, var.moving), var.start, push)
    direction = pose[:3, :3].T @ push
    centre = np.round(direction / 1e-12) * 1e-12
    # the same rounding, on the other side of its centre (a different direction)
    other = centre - 0.4e-12 * np.where(direction >= centre, 1.0, -1.0)
    assert not np.array_equal(other, direction)

    def measured(first: np.ndarray) -> tuple[float, np.ndarray]:
        fixed, moving = (RigidBody.from_mesh(b.mesh.copy()) for b in (var.fixed, var.moving))
        sweep_body(moving).view(first, 1)
        touch = SweepPair(fixed, moving, push).touch(pose, 1e-3, 1e-3)
        return touch.travel, touch.gaps

    own, after_other = measured(direction), measured(other)
    assert own[0] == after_other[0] and np.array_equal(own[1], after_other[1])


def test_views_made_from_gone_views_arrays_answer_as_fresh_ones() -> None:
    """A moving view keeps its nodes' bounds placed for the query that placed them, marked
    with that query's number: views of one body taking turns, and views made from the
    arrays of views that are gone (never cleared), must answer every pose bit for bit as a
    body and views made for that pose alone do."""
    var = sc.variant('sphere_bowl', 'rotated')
    push = var.push / np.linalg.norm(var.push)
    start = backed(CollisionPair(var.fixed, var.moving), var.start, push)
    direction = start[:3, :3].T @ push
    rng = np.random.default_rng(20261206)
    poses = []
    for _ in range(8):          # slides across the push and spins about it: one direction
        turn = rotation_about(push, float(rng.uniform(-1.5, 1.5)))
        pose = pose_from(turn @ start[:3, :3], start[:3, 3] + rng.uniform(-3e-3, 3e-3, 3))
        pose[:3, 3] -= 2e-3 * push
        poses.append(pose)

    def native(body: RigidBody) -> _sweep.Body:
        return _sweep.Body(np.ascontiguousarray(body.vertices), np.ascontiguousarray(body.faces),
                           np.ascontiguousarray(facing(body.mesh)))

    def ask(fixed_view: _sweep.View, moving_view: _sweep.View,
            pose: np.ndarray) -> tuple[float, bytes]:
        travel, _, raw, _ = _sweep.contacts(fixed_view, moving_view, pose, 1e-3, 2e-4, 1e300)
        return travel, raw

    def alone(pose: np.ndarray) -> tuple[float, bytes]:
        fixed, moving = native(var.fixed), native(var.moving)
        return ask(_sweep.View(fixed, push, -1), _sweep.View(moving, direction, 1), pose)

    fixed, moving = native(var.fixed), native(var.moving)
    fixed_view = _sweep.View(fixed, push, -1)
    first = _sweep.View(moving, direction, 1)
    answers = [ask(fixed_view, first, pose) for pose in poses[:3]]
    del first                           # its arrays wait for the next view
    second = _sweep.View(moving, direction, 1)
    third = _sweep.View(moving, direction, 1)
    for k, pose in enumerate(poses[3:]):
        answers.append(ask(fixed_view, (second, third)[k % 2], pose))
    assert [alone(pose) for pose in poses] == answers
    assert len({raw for _, raw in answers}) > 1      # the poses meet the bowl differently
