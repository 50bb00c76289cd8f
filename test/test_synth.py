"""The embedded default knee: closed, deterministic meshes that show real secondary motion.

Everything runs on the real meshes with python-fcl; nothing here needs the settle engine.
The screw-home test searches, by brute force with boolean collision queries, for the tibia
pose that goes furthest along its push at several flexion angles.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import hashlib
import json
import math
import os
from pathlib import Path
import subprocess
import sys
from typing import Any

import fcl
import numpy as np
import pytest
import trimesh

from conftest import fcl_collides, fcl_object
from kneeseat_core.knee import synth
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.typed import Floats, Pose

_, Y_AXIS, Z_AXIS = np.eye(3)
MM = 1e-3
BISECT_TOL_M = 1e-6          # lift resolution of the brute-force search
CONTACT_PROBE_M = 1e-4       # patent resolution T2: "in contact" = colliding this much further
NOTCH_HALF_WIDTH_M = 8e-3    # |z| below this is the intercondylar notch / eminence


@pytest.fixture(scope='module')
def knee() -> dict[str, trimesh.Trimesh]:
    return synth.default_knee()


class Pair:
    """The femur (fixed, identity) and one moving body, queried with python-fcl."""

    def __init__(self, femur: trimesh.Trimesh, moving: trimesh.Trimesh) -> None:
        self.femur = fcl_object(femur)
        self.moving = fcl_object(moving)
        self.queries = 0

    def _place(self, femur_from_moving: Pose) -> None:
        self.moving.setTransform(fcl.Transform(femur_from_moving[:3, :3],
                                               femur_from_moving[:3, 3]))

    def collides(self, femur_from_moving: Pose) -> bool:
        self.queries += 1
        return fcl_collides(self.moving, self.femur, femur_from_moving)

    def contacts(self, femur_from_moving: Pose) -> Floats:
        """(n, 3) contact points (m, femur frame) at this pose."""
        self._place(femur_from_moving)
        result = fcl.CollisionResult()
        fcl.collide(self.moving, self.femur,
                    fcl.CollisionRequest(num_max_contacts=100_000, enable_contact=True), result)
        return np.array([c.pos for c in result.contacts]).reshape(-1, 3)

    def distance(self, femur_from_moving: Pose) -> float:
        self._place(femur_from_moving)
        result = fcl.DistanceResult()
        return float(fcl.distance(self.moving, self.femur, fcl.DistanceRequest(), result))


def _travel_to_contact(pair: Pair, pose: Callable[[float], Pose], lo: float, hi: float) -> float:
    """Largest s in [lo, hi] (m) with pose(s) free, given pose(lo) free, pose(hi) colliding."""
    while hi - lo > BISECT_TOL_M:
        mid = 0.5 * (lo + hi)
        if pair.collides(pose(mid)):
            hi = mid
        else:
            lo = mid
    return lo


# ---- meshes ------------------------------------------------------------------------------
@pytest.mark.parametrize('name', ['femur', 'tibia', 'patella'])
def test_mesh_is_closed_outward_and_sized(knee: dict[str, trimesh.Trimesh], name: str) -> None:
    mesh = knee[name]
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0.0                                   # outward winding
    assert 10_000 <= len(mesh.faces) <= 40_000
    assert len(mesh.vertices) == len(np.unique(mesh.vertices, axis=0))  # no duplicates
    assert mesh.area_faces.min() > 1e-9                        # m^2: 0.001 mm^2
    assert mesh.nondegenerate_faces().all()
    assert mesh.euler_number == 2                              # one closed sphere-like shell
    assert np.isfinite(mesh.vertices).all()


def test_femur_reads_as_a_distal_femur(knee: dict[str, trimesh.Trimesh]) -> None:
    lo, hi = knee['femur'].bounds / MM
    assert 75.0 <= hi[2] - lo[2] <= 85.0                       # medio-lateral width
    assert 60.0 <= hi[1] <= 80.0                               # shaft stub up +Y
    assert lo[1] == pytest.approx(-24.0, abs=0.5)              # distal medial condyle
    t_lo, t_hi = knee['tibia'].bounds / MM
    assert t_lo[1] <= -60.0                                    # tibial shaft stub down -Y


def test_medial_and_lateral_sides_differ(knee: dict[str, trimesh.Trimesh]) -> None:
    femur = np.asarray(knee['femur'].vertices) / MM

    def sagittal_arc(z_crest: float) -> tuple[float, Floats]:
        """Circle fit (radius, centre) mm of the posterior-distal arc at a condyle's crest."""
        z_slice = femur[np.argmin(np.abs(femur[:, 2] - z_crest)), 2]
        ring = femur[(femur[:, 2] == z_slice) & (femur[:, 0] < -3.0) & (femur[:, 1] < -3.0)]
        x, y = ring[:, 0], ring[:, 1]
        design = np.stack([x, y, np.ones_like(x)], axis=1)     # x^2 + y^2 = 2ax + 2by + c
        (a2, b2, c), *_ = np.linalg.lstsq(design, x * x + y * y, rcond=None)
        centre = np.array([a2 / 2.0, b2 / 2.0])
        radius = float(np.sqrt(c + centre @ centre))
        assert np.abs(np.hypot(x - centre[0], y - centre[1]) - radius).max() < 0.05
        return radius, centre

    medial_r, medial_c = sagittal_arc(synth.MEDIAL_CONDYLE_Z_MM)
    lateral_r, lateral_c = sagittal_arc(synth.LATERAL_CONDYLE_Z_MM)
    assert medial_r == pytest.approx(24.0, abs=0.1)            # longer radius medially
    assert lateral_r == pytest.approx(21.0, abs=0.1)
    assert np.allclose(medial_c, 0.0, atol=0.05)               # on the flexion axis
    assert np.linalg.norm(lateral_c) > 2.0                     # offset: drives screw-home
    # Condyle widths differ: extent in z of the distal surface below y = -15 mm.
    distal = femur[femur[:, 1] < -15.0]
    medial_w = np.ptp(distal[distal[:, 2] < 0.0, 2])
    lateral_w = np.ptp(distal[distal[:, 2] > 0.0, 2])
    assert abs(medial_w - lateral_w) > 1.0

    # Plateau: the medial dish is deeper than the lateral one over the same +-10 mm (AP).
    tibia = knee['tibia']
    top = np.asarray(tibia.vertices)[np.asarray(tibia.vertex_normals)[:, 1] > 0.3] / MM

    def height(x: float, z: float) -> float:
        near = np.hypot(top[:, 0] - x, top[:, 2] - z) < 1.5
        return float(top[near, 1].max())

    def depth(z: float) -> float:
        return 0.5 * (height(-10.0, z) + height(10.0, z)) - height(0.0, z)

    assert depth(-28.0) > 1.2 * depth(26.0) > 0.0
    # The eminence rises between the compartments, into the notch (above the condyles' low
    # points, between their medio-lateral ranges).
    peak = top[np.argmax(top[:, 1])]
    assert abs(peak[2]) < 8.0 and peak[1] > -20.0


# ---- determinism and files ---------------------------------------------------------------
def test_two_calls_give_identical_arrays(knee: dict[str, trimesh.Trimesh]) -> None:
    again = synth.default_knee()
    for name, mesh in knee.items():
        assert np.array_equal(mesh.vertices, again[name].vertices)
        assert np.array_equal(mesh.faces, again[name].faces)
        assert synth.stl_bytes(mesh) == synth.stl_bytes(again[name])


def test_stl_hash_is_stable_across_processes() -> None:
    code = ('import hashlib, sys; from kneeseat_core.knee import synth; '
            'k = synth.default_knee(); '
            'print(" ".join(hashlib.sha256(synth.stl_bytes(k[n])).hexdigest() '
            'for n in ("femur", "tibia", "patella")))')
    env = dict(os.environ, PYTHONHASHSEED='12345')             # another process, other seed
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, env=env)
    here = synth.default_knee()
    assert out.stdout.strip() == ' '.join(hashlib.sha256(synth.stl_bytes(here[n])).hexdigest()
                                          for n in ('femur', 'tibia', 'patella'))


@pytest.mark.parametrize('name', ['sin', 'cos', 'exp', 'log', 'log1p', 'power'])
def test_libm_gives_math_bits(name: str) -> None:
    """The meshes' elementary functions (a compiled loop) are Python's `math` functions,
    element by element, bit for bit: on arguments across their ranges, and their edges."""
    rng = np.random.default_rng(20261207)
    x = np.concatenate([rng.normal(0.0, 10.0, 20000), rng.uniform(-700.0, 700.0, 20000),
                        [0.0, -0.0, 5e-324, 1e-300, 0.5, 1.0, -1.0, 709.0, -745.0]])
    reference: Callable[[float], float]
    if name in ('log', 'log1p', 'power'):
        x = np.abs(x)
        x = x[x > 0.0] if name == 'log' else x
    if name == 'power':
        for p in (0.25, 1.0 / 3.0, 4.0):
            grid = x[:len(x) // 7 * 7].reshape(-1, 7)       # any shape, kept
            got = synth.libm.power(grid, p)
            assert got.shape == grid.shape
            want = np.array([math.pow(v, p) for v in grid.ravel().tolist()])
            assert np.array_equal(got.ravel().view(np.int64), want.view(np.int64))
        return
    if name == 'exp':
        x = x[x < 709.5]
    reference = getattr(math, name)
    got = getattr(synth.libm, name)(x)
    want = np.array([reference(v) for v in x.tolist()])
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize('call', [lambda: synth.libm.log(np.array([1.0, 0.0])),
                                  lambda: synth.libm.exp(np.array([1000.0])),
                                  lambda: synth.libm.power(np.array([-2.0]), 0.5)])
def test_libm_refuses_what_math_refuses(call: Callable[[], object]) -> None:
    """Where `math` raises (no finite value for a finite argument), so do they."""
    with pytest.raises(ValueError, match='no finite value'):
        call()


def test_write_default_knee_is_atomic_and_idempotent(tmp_path: Path) -> None:
    out_dir = tmp_path / 'new' / 'knee'                        # created if missing
    paths = synth.write_default_knee(out_dir)
    assert set(paths) == {'femur', 'tibia', 'patella'}
    assert sorted(p.name for p in out_dir.iterdir()) == [
        'femur.stl', synth.GENERATED, 'patella.stl', 'tibia.stl']      # no temp files left
    knee = synth.default_knee()
    for name, path in paths.items():
        assert path == out_dir / f'{name}.stl'
        data = path.read_bytes()
        assert data == synth.stl_bytes(knee[name])
        assert len(data) == 84 + 50 * len(knee[name].faces)   # binary STL
        loaded = trimesh.load_mesh(path)                       # an independent reader
        assert loaded.is_watertight and len(loaded.faces) == len(knee[name].faces)
        assert np.allclose(loaded.bounds, knee[name].bounds, atol=1e-6)
    stamps = {name: path.stat().st_mtime_ns for name, path in paths.items()}
    assert synth.write_default_knee(out_dir) == paths
    assert {name: path.stat().st_mtime_ns for name, path in paths.items()} == stamps

    paths['tibia'].write_bytes(b'damaged')                     # a stale file is replaced
    synth.write_default_knee(out_dir)
    assert paths['tibia'].read_bytes() == synth.stl_bytes(knee['tibia'])


def _made(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the calls that make the default knee's meshes from now on."""
    calls: list[int] = []
    make = synth.default_knee

    def counted() -> dict[str, trimesh.Trimesh]:
        calls.append(1)
        return make()
    monkeypatch.setattr(synth, 'default_knee', counted)
    return calls


def test_current_meshes_are_not_made_again(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    paths = synth.write_default_knee(tmp_path)
    made = _made(monkeypatch)
    assert synth.write_default_knee(tmp_path) == paths and made == []
    record = json.loads((tmp_path / synth.GENERATED).read_text())
    assert record == {'generator': synth.generator_key(), 'sha256': {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths.values()}}


def test_current_meshes_need_no_record_where_it_cannot_be_written(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Meshes already current in a directory that takes no new file (a cache one may only
    read, filled by an older version): they are used as they are, without the record."""
    paths = synth.write_default_knee(tmp_path)
    (tmp_path / synth.GENERATED).unlink()
    stamps = {name: path.stat().st_mtime_ns for name, path in paths.items()}
    write = synth.write_bytes

    def refuse(path: Path, data: bytes) -> None:
        if path.name == synth.GENERATED:
            raise PermissionError(13, 'Permission denied', str(path))
        write(path, data)
    monkeypatch.setattr(synth, 'write_bytes', refuse)
    assert synth.write_default_knee(tmp_path) == paths
    assert {name: path.stat().st_mtime_ns for name, path in paths.items()} == stamps
    assert not (tmp_path / synth.GENERATED).exists()


@pytest.mark.parametrize('change', ['damaged mesh', 'missing mesh', 'other generator',
                                    'damaged record', 'missing record'])
def test_meshes_are_made_again_when_the_record_does_not_hold(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, change: str) -> None:
    paths = synth.write_default_knee(tmp_path)
    expected = {name: path.read_bytes() for name, path in paths.items()}
    record = tmp_path / synth.GENERATED
    if change == 'damaged mesh':
        paths['patella'].write_bytes(expected['patella'][:-1] + b'x')
    elif change == 'missing mesh':
        paths['femur'].unlink()
    elif change == 'other generator':
        monkeypatch.setattr(synth, 'generator_key', lambda: 'other code')
    elif change == 'damaged record':
        record.write_text('{"generator": ')
    else:
        record.unlink()
    made = _made(monkeypatch)
    assert synth.write_default_knee(tmp_path) == paths and made == [1]
    assert {name: path.read_bytes() for name, path in paths.items()} == expected
    assert json.loads(record.read_text())['generator'] == synth.generator_key()


# ---- neutral placement ---------------------------------------------------------------------
@pytest.mark.parametrize('name', ['tibia', 'patella'])
def test_neutral_gap_and_push_meets_femur(knee: dict[str, trimesh.Trimesh], name: str) -> None:
    pair = Pair(knee['femur'], knee[name])
    gap_mm = pair.distance(np.eye(4)) / MM
    lo, hi = synth.NEUTRAL_GAP_MM
    assert lo <= gap_mm <= hi
    push = np.array(synth.DEFAULT_PUSH[name])

    def along(s: float) -> Pose:
        return pose_from(np.eye(3), s * push)

    assert pair.collides(along(5e-3))                          # pushed 5 mm: it meets
    travel = _travel_to_contact(pair, along, 0.0, 5e-3)
    assert gap_mm * MM - 1e-5 <= travel <= 3e-3               # along >= shortest distance


@pytest.mark.parametrize('flexion_deg', [0.0, -30.0, -60.0, -90.0])
def test_patella_meets_femur_along_turned_push(knee: dict[str, trimesh.Trimesh],
                                               flexion_deg: float) -> None:
    pair = Pair(knee['femur'], knee['patella'])
    turn = rotation_about(Z_AXIS, synth.PATELLA_FLEXION_FRACTION * np.radians(flexion_deg))
    push = turn @ np.array(synth.DEFAULT_PUSH['patella'])

    def along(s: float) -> Pose:
        return pose_from(turn, s * push)

    assert not pair.collides(along(0.0))                       # turned start is free
    assert pair.collides(along(15e-3))
    travel = _travel_to_contact(pair, along, 0.0, 15e-3)
    points = pair.contacts(along(travel + CONTACT_PROBE_M))
    assert len(points) > 0
    print(f'patella flexion {flexion_deg:5.1f} deg: contact after {travel / MM:.2f} mm, '
          f'contact z {points[:, 2].min() / MM:.1f}..{points[:, 2].max() / MM:.1f} mm')


# ---- secondary motion ----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Rest:
    """Best tibia pose found at one flexion: offsets in the flexed tibia frame."""

    flexion_deg: float
    x_m: float          # antero-posterior translation (perpendicular to the push)
    z_m: float          # medio-lateral translation
    rotation_deg: float  # about the tibia's long axis (+ = internal for this right knee)
    lift_m: float       # how far along the push it went from the flexed neutral pose
    queries: int


def _tibia_pose(flexion_rad: float, x: float, z: float, rotation_rad: float,
                lift: float) -> Pose:
    """femur_from_tibia = Rot(Z, flexion) @ Trans(x, lift, z) @ Rot(Y, rotation)."""
    return (pose_from(rotation_about(Z_AXIS, flexion_rad), np.zeros(3))
            @ pose_from(rotation_about(Y_AXIS, rotation_rad), np.array([x, lift, z])))


def _furthest_along_push(pair: Pair, flexion_deg: float) -> Rest:
    """Brute force: the (x, z, rotation) grid pose that lets the tibia rise furthest.

    A coarse grid (rotation -8..8 deg by 2, x and z -4..4 mm by 2) and then 3x3x3 grids
    around the best, halving the steps whenever the best stays put, down to 0.03 mm and
    0.03 deg. A candidate is bisected only if it is still free at the best lift so far.
    """
    flexion = np.radians(flexion_deg)
    best: list[Any] = [-3e-3, (0.0, 0.0, 0.0)]          # the flexed neutral, lowered, is free
    assert not pair.collides(_tibia_pose(flexion, 0.0, 0.0, 0.0, best[0]))

    def consider(x: float, z: float, rot: float) -> None:
        lo = best[0] + BISECT_TOL_M
        if pair.collides(_tibia_pose(flexion, x, z, rot, lo)):
            return
        hi = 6e-3
        assert pair.collides(_tibia_pose(flexion, x, z, rot, hi))
        best[:] = [_travel_to_contact(
            pair, lambda s: _tibia_pose(flexion, x, z, rot, s), lo, hi), (x, z, rot)]

    for rot in np.radians(np.arange(-8.0, 8.1, 2.0)):
        for x in np.arange(-4e-3, 4.1e-3, 2e-3):
            for z in np.arange(-4e-3, 4.1e-3, 2e-3):
                consider(float(x), float(z), float(rot))
    step, rot_step = 1e-3, np.radians(1.0)
    while step > 3e-5:
        centre = best[1]
        bx, bz, brot = centre
        for rot in (brot - rot_step, brot, brot + rot_step):
            for x in (bx - step, bx, bx + step):
                for z in (bz - step, bz, bz + step):
                    consider(x, z, rot)
        if best[1] == centre:
            step, rot_step = step / 2.0, rot_step / 2.0
    x, z, rot = best[1]
    return Rest(flexion_deg, x, z, float(np.degrees(rot)), best[0], pair.queries)


def test_tibia_screw_home_and_roll_with_flexion(knee: dict[str, trimesh.Trimesh]) -> None:
    rests = {}
    pair = Pair(knee['femur'], knee['tibia'])
    for flexion_deg in (0.0, -30.0, -60.0, -90.0):
        pair.queries = 0
        rest = _furthest_along_push(pair, flexion_deg)
        rests[flexion_deg] = rest
        pose = _tibia_pose(np.radians(flexion_deg), rest.x_m, rest.z_m,
                           np.radians(rest.rotation_deg), rest.lift_m)
        assert not pair.collides(pose)
        # In contact: a little further along the push touches BOTH condyles.
        points = pair.contacts(_tibia_pose(np.radians(flexion_deg), rest.x_m, rest.z_m,
                                           np.radians(rest.rotation_deg),
                                           rest.lift_m + CONTACT_PROBE_M))
        medial = int((points[:, 2] <= -NOTCH_HALF_WIDTH_M).sum())
        lateral = int((points[:, 2] >= NOTCH_HALF_WIDTH_M).sum())
        notch = len(points) - medial - lateral
        print(f'tibia flexion {flexion_deg:5.1f} deg: rotation {rest.rotation_deg:+.2f} deg, '
              f'x {rest.x_m / MM:+.2f} mm, z {rest.z_m / MM:+.2f} mm, '
              f'lift {rest.lift_m / MM:.3f} mm; contacts medial {medial} lateral {lateral} '
              f'notch {notch}; {rest.queries} queries')
        assert medial > 0 and lateral > 0, 'rest pose must bear on both condyles'
    rotations = [rests[f].rotation_deg for f in (0.0, -30.0, -60.0, -90.0)]
    assert rotations[-1] - rotations[0] >= 2.0                 # screw-home, internal w/ flexion
    assert rotations == sorted(rotations)                      # monotonic over the range
    assert abs(rests[-90.0].x_m - rests[0.0].x_m) >= 1e-3      # antero-posterior shift
