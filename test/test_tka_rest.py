"""The default settle ends at rest on a real total knee (issue 2, "Show" list).

The tibial insert is pushed along +Y into the femoral component from the benchmark's
start (5 mm below, 3 mm lateral, 5 degrees about Y). The end pose is then checked with
this file's own probes, using nothing of the settle but its answer: only
`CollisionPair.collides`. At rest no admissible move - a slide in the plane normal to
the push, a rotation about an axis parallel to the push, or both together - may let the
insert go further than the resolution along the push without collision.
"""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from kneeseat_core.collision import CollisionPair, RigidBody
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.meshes import load_mesh
from kneeseat_core.settle import Contacts, settle, SettleParams, SettleResult

TKA = Path(__file__).resolve().parents[1].parent / 'shared' / 'data' / 'tka_dm'
RESOLUTION_M = 1e-4
PUSH = np.array([0.0, 1.0, 0.0])            # +Y: the insert rises into the femur
IN_PLANE = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
SLIDES_M = (0.1e-3, 0.2e-3, 0.5e-3)
TURNS_DEG = (0.1, 0.2, 0.5)
N_DIRECTIONS = 16
Settled = tuple[CollisionPair, SettleResult]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (TKA / 'femoral_component.stl').is_file(),
                       reason=f'total-knee meshes not found at {TKA} (../shared/data/tka_dm '
                       'next to the repository); they are not shipped in the repo'),
]


def benchmark_start(insert: RigidBody) -> np.ndarray:
    """The insert as delivered, -5 mm along Y, +3 mm along Z, 5 deg about Y through its
    centroid (the same start as benchmarks/bench_settle.py)."""
    turn = rotation_about(np.array([0.0, 1.0, 0.0]), math.radians(5.0))
    centroid = insert.centroid
    return pose_from(turn, centroid - turn @ centroid + np.array([0.0, -5e-3, 3e-3]))


@pytest.fixture(scope='module')
def settled() -> tuple[CollisionPair, SettleResult]:
    """The femoral component and insert as a pair, and the default settle's result."""
    femoral = RigidBody.from_mesh(load_mesh(TKA / 'femoral_component.stl'))
    insert = RigidBody.from_mesh(load_mesh(TKA / 'tibial_insert.stl'))
    result = settle(femoral, insert, benchmark_start(insert),
                    SettleParams(push=tuple(PUSH), method='default'))
    return CollisionPair(femoral, insert), result


def pushed(pose: np.ndarray, distance_m: float) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += distance_m * PUSH
    return out


def slid(pose: np.ndarray, vector_m: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += vector_m
    return out


def turned(pose: np.ndarray, centre: np.ndarray, angle_rad: float) -> np.ndarray:
    """The whole body turned about the axis through `centre` (fixed frame) parallel to Δ."""
    rot = rotation_about(PUSH, angle_rad)
    return pose_from(rot @ pose[:3, :3], rot @ (pose[:3, 3] - centre) + centre)


def contact_regions(points: np.ndarray) -> list[np.ndarray]:
    """Split contact points in two at the largest gap along their widest in-plane spread
    (the two condyles); one region if no gap wider than 5 mm."""
    if len(points) < 2:
        return []
    axis = max(IN_PLANE, key=lambda a: float(np.ptp(points @ a)))
    order = np.argsort(points @ axis)
    coords = (points @ axis)[order]
    gaps = np.diff(coords)
    cut = int(np.argmax(gaps))
    if gaps[cut] < 5e-3:
        return []
    return [points[order[:cut + 1]].mean(axis=0), points[order[cut + 1:]].mean(axis=0)]


def probe_poses(pair: CollisionPair, result: SettleResult) -> list[tuple[str, np.ndarray]]:
    """Slides, turns about axes parallel to Δ through several centres, and each slide
    combined with each turn; every probe keeps the end pose's depth along Δ."""
    end = result.pose
    centres = {'insert centroid': end[:3, :3] @ pair.moving.centroid + end[:3, 3],
               'contact centroid': result.contacts.points.mean(axis=0)}
    for i, centre in enumerate(contact_regions(result.contacts.points)):
        centres[f'contact region {i}'] = centre
    slides = []
    for k, size in itertools.product(range(N_DIRECTIONS), SLIDES_M):
        phi = 2.0 * math.pi * k / N_DIRECTIONS
        vector = size * (math.cos(phi) * IN_PLANE[0] + math.sin(phi) * IN_PLANE[1])
        slides.append((f'slide {size * 1e3:.1f} mm at {math.degrees(phi):.1f} deg', vector))
    turns = []
    for (name, centre), deg, sign in itertools.product(centres.items(), TURNS_DEG, (-1, 1)):
        turns.append((f'turn {sign * deg:+.1f} deg about {name}', centre,
                      math.radians(sign * deg)))
    probes = [(label, slid(end, vector)) for label, vector in slides]
    probes += [(label, turned(end, centre, angle)) for label, centre, angle in turns]
    for (s_label, vector), (t_label, centre, angle) in itertools.product(slides, turns):
        probes.append((f'{s_label} + {t_label}', slid(turned(end, centre, angle), vector)))
    return probes


def test_default_settle_converges_on_the_knee(settled: Settled) -> None:
    _, result = settled
    assert result.converged, result.reason
    assert len(result.contacts.points) > 0


def test_end_pose_touches_without_penetrating(settled: Settled) -> None:
    pair, result = settled
    assert not pair.collides(result.pose), 'the end pose is in collision'
    assert pair.collides(pushed(result.pose, RESOLUTION_M)), \
        'the end pose can still rise a resolution along the push'


def test_no_probe_gains_more_than_the_resolution(settled: Settled) -> None:
    pair, result = settled
    probes = probe_poses(pair, result)
    # 48 slides, 6 turns per centre (at least the two centroids), every slide x every turn
    assert len(probes) >= 48 + 12 + 48 * 12
    depth = float(result.pose[:3, 3] @ PUSH)
    winners = []
    for label, pose in probes:
        assert float(pose[:3, 3] @ PUSH) == pytest.approx(depth, abs=1e-12), label
        if not pair.collides(pushed(pose, RESOLUTION_M)):
            # how far does it go? (for the report; coarse steps of a resolution)
            gain = RESOLUTION_M
            while gain < 5e-3 and not pair.collides(pushed(pose, gain + RESOLUTION_M)):
                gain += RESOLUTION_M
            winners.append(f'{label}: rises >= {gain * 1e3:.1f} mm')
    assert not winners, f'{len(winners)} of {len(probes)} probes gain: ' + '; '.join(winners[:10])


def test_the_probes_see_a_pose_that_is_not_at_rest(settled: Settled) -> None:
    """Control: first contact straight up from the start (found here by bisection) is not
    a rest pose, and the same probes must say so; otherwise the test above proves nothing.
    """
    pair, result = settled
    start = benchmark_start(pair.moving)
    free, hit = 0.0, 0.02
    assert not pair.collides(start) and pair.collides(pushed(start, hit))
    while hit - free > RESOLUTION_M / 4.0:
        mid = 0.5 * (free + hit)
        free, hit = (free, mid) if pair.collides(pushed(start, mid)) else (mid, hit)
    ids = pair.contacts(pushed(start, hit))
    first = SettleResult(pushed(start, free), False, 'first contact', 0, 0,
                         Contacts(pair.fixed.centres[ids], pair.fixed.normals[ids]), 0.0, 0.0)
    winners = [label for label, pose in probe_poses(pair, first)
               if not pair.collides(pushed(pose, RESOLUTION_M))]
    assert len(winners) >= 10, winners
    assert float(result.pose[:3, 3] @ PUSH) > float(first.pose[:3, 3] @ PUSH) + 1e-3
