"""The natural knee: its configs, and a coarse table checked at rest.

The meshes live outside the repository (../shared/data/natural_knee); without them these
tests skip. The rest check uses python-fcl objects and a ligament energy of its own and
nothing of the settle but its answers: at every converged cell the body touches the femur
(one resolution further along the cell's push collides) without penetrating it, and no
admissible move - a slide across the push (not along a locked slide), a turn about the push
through the body's centroid, or both - lets it go one resolution further along the push
and be better off by a resolution: in the load's work less the ligaments' energy, per unit
load (the Blankevoort law integrated here), or, without ligaments, in the travel alone.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
import itertools
import json
import math
from pathlib import Path

import fcl
import numpy as np
import pytest
import trimesh
import yaml

from conftest import fcl_collides, fcl_object, REPO, SHARED_DATA
from kneeseat_core.cli import main
from kneeseat_core.geometry import matrix_from_quat, pose_from, rotation_about
from kneeseat_core.report.kinematics import knee_kinematics, table_landmarks
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.table import PoseTable, read_table

DATA = SHARED_DATA / 'natural_knee'
CONFIG = REPO / 'config' / 'natural_knee.yaml'
NO_MENISCI = REPO / 'config' / 'natural_knee_no_menisci.yaml'
GRID = ('--flexion-grid', '0,-90,30', '--varus-grid', '-10,10,10')
SLIDES_M = (0.2e-3, 0.5e-3)
TURNS_DEG = (0.2, 0.5)
N_DIRECTIONS = 8

pytestmark = pytest.mark.skipif(
    not (DATA / 'femur_cartilage.stl').is_file(),
    reason=f'natural knee meshes not found at {DATA} (../shared/data/natural_knee next to '
    'the repository); they are not shipped in the repo')


def test_configs_load_with_every_mesh() -> None:
    config = load_config(CONFIG)
    tibia, patella = config.bodies
    assert [p.name for p in tibia.meshes] == ['tibia_cartilage.stl', 'meniscus_medial.stl',
                                              'meniscus_lateral.stl']
    assert [p.name for p in tibia.display_meshes] == ['tibia_bone.stl', 'meniscus_medial.stl',
                                                      'meniscus_lateral.stl']
    assert config.reference.display_mesh is not None
    assert config.reference.display_mesh.name == 'femur_bone.stl'
    # its tendon and retinacula hold the patella along the groove: no locked slide
    assert patella.locked_slide is None and patella.varus_fraction == 0.0
    assert patella.load_n == 100.0 and patella.load_toward == (0.04, 0.25, 0.01)
    assert tibia.load_n == 100.0 and tibia.load_toward is None
    assert config.ligaments is not None and Path(config.ligaments.source).name == 'ligaments.json'
    assert len(config.ligaments.fibres) == 76 and len(config.ligaments.bundles) == 14
    assert patella.flexion_fraction == 0.65 and patella.push_flexion_fraction == 0.67
    above_posterior = math.degrees(math.atan2(patella.push[1], -patella.push[0]))
    assert above_posterior == pytest.approx(2.9, abs=0.05)
    assert len(config.flexion_rad) == 91 and len(config.varus_rad) == 21
    assert config.settle.resolution_m == 1e-4 and config.settle.step_m == 1e-3


def test_the_variant_differs_only_by_the_menisci() -> None:
    full, bare = (yaml.safe_load(p.read_text()) for p in (CONFIG, NO_MENISCI))
    assert bare['bodies'][0]['mesh'] == 'tibia_cartilage.stl'
    assert bare['bodies'][0]['display_mesh'] == 'tibia_bone.stl'
    for data in (full, bare):
        del data['name'], data['bodies'][0]['mesh'], data['bodies'][0]['display_mesh']
    assert full == bare
    assert load_config(NO_MENISCI).bodies[0].meshes[0].name == 'tibia_cartilage.stl'


class Probe:
    """python-fcl objects of our own: the femoral cartilage and one moving body."""

    def __init__(self, fixed: list[Path], moving: list[Path]) -> None:
        self.fixed, self.moving = self._object(fixed), self._object(moving)

    @staticmethod
    def _object(paths: list[Path]) -> fcl.CollisionObject:
        return fcl_object(trimesh.util.concatenate([trimesh.load_mesh(p, process=False)
                                                    for p in paths]))

    def collides(self, pose: np.ndarray) -> bool:
        return fcl_collides(self.moving, self.fixed, pose)


BUILT_FILE: dict[str, Path] = {}


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[KneeConfig, PoseTable,
                                                                      str]]:
    """(config, table, build stdout) of a coarse natural-knee build with 2 workers."""
    import contextlib
    import io
    out = tmp_path_factory.mktemp('natural') / 'natural.npz'
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        code = main(['build', str(CONFIG), '--out', str(out), '--workers', '2', '--quiet',
                     *GRID])
    assert code == 0
    BUILT_FILE['natural'] = out
    config = load_config(CONFIG, overrides={'grid': {'flexion_deg': [0, -90, 30],
                                                     'varus_deg': [-10, 10, 10]}})
    yield config, read_table(out, meshes={b.name: list(b.meshes) for b in
                                          (config.reference, *config.bodies)}), text.getvalue()


def probes(pose: np.ndarray, push: np.ndarray, lock: np.ndarray | None,
           centre: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Slides across the push (not along `lock`), turns about the push through `centre`,
    and every slide with every turn; each keeps the pose's depth along the push."""
    plane = np.linalg.svd(np.eye(3) - np.outer(push, push))[0][:, :2].T     # (2, 3)
    slides = []
    for k, size in itertools.product(range(N_DIRECTIONS), SLIDES_M):
        phi = 2.0 * math.pi * k / N_DIRECTIONS
        vector = size * (math.cos(phi) * plane[0] + math.sin(phi) * plane[1])
        if lock is not None:
            vector -= (vector @ lock) * lock
            if np.linalg.norm(vector) < 0.5 * size:
                continue
        slides.append((f'slide {vector * 1e3} mm', vector))
    turns = []
    for deg, sign in itertools.product(TURNS_DEG, (-1, 1)):
        rot = rotation_about(push, math.radians(sign * deg))
        turns.append((f'turn {sign * deg:+.1f} deg',
                      pose_from(rot @ pose[:3, :3], rot @ (pose[:3, 3] - centre) + centre)))
    out = [(label, pose_from(pose[:3, :3], pose[:3, 3] + v)) for label, v in slides]
    out += turns
    out += [(f'{s} + {t}', pose_from(q[:3, :3], q[:3, 3] + v))
            for (s, v), (t, q) in itertools.product(slides, turns)]
    return out


def strain_energy(strain: np.ndarray, slack_m: np.ndarray, stiffness_n: np.ndarray,
                  transition: np.ndarray) -> float:
    """Blankevoort's force, k e^2 / (2 e_t) up to the transition strain and k (e - e_t / 2)
    beyond, integrated from the slack length (J)."""
    e = np.maximum(strain, 0.0)
    toe = stiffness_n * e ** 3 / (6.0 * transition)
    beyond = stiffness_n * (e * e - transition * e + transition ** 2 / 3.0) / 2.0
    return float(np.sum(slack_m * np.where(e < transition, toe, beyond)))


def cell_objective(config: KneeConfig, table: PoseTable, b: int, i: int, j: int,
                   centroid: np.ndarray) -> Callable[[np.ndarray], float]:
    """What a rest of body `b` at cell (i, j) maximises, per unit load (m): the travel
    without ligaments; with them the load's work (its centroid's advance along the push, or
    minus its distance from the point the load pulls toward) less the energy of the fibres
    on it, every other point placed where the table put its body."""
    spec = config.bodies[b]
    params = config.params(spec, float(table.flexion_rad[i]), float(table.varus_rad[j]))
    push = np.asarray(params.push)
    placed = {config.reference.name: np.eye(4)}
    placed.update({other.name: pose_from(matrix_from_quat(table.orientation_xyzw[k, i, j]),
                                         table.position_m[k, i, j])
                   for k, other in enumerate(config.bodies[:b])})
    fibres = [] if config.ligaments is None else \
        [f for f in config.ligaments.fibres if spec.name in f.bodies
         and set(f.bodies) - {spec.name} <= set(placed)]
    toward = None if params.load_toward is None else np.asarray(params.load_toward)

    def value(pose: np.ndarray) -> float:
        centre = pose[:3, :3] @ centroid + pose[:3, 3]
        work = float(push @ centre) if toward is None else -float(np.linalg.norm(toward - centre))
        if not fibres:
            return work
        lengths = []
        for f in fibres:
            at = [pose if name == spec.name else placed[name] for name in f.bodies]
            points = np.array([q[:3, :3] @ p + q[:3, 3] for q, p in zip(at, f.points)])
            lengths.append(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
        slack = np.array([f.slack_m for f in fibres])
        energy = strain_energy(np.array(lengths) / slack - 1.0, slack,
                               np.array([f.stiffness_n for f in fibres]),
                               np.array([f.transition for f in fibres]))
        return work - energy / float(params.load_n)
    return value


def rest_failures(config: KneeConfig, table: PoseTable) -> tuple[int, list[str], list[str]]:
    """(converged cells checked, cells not touching at the resolution, cells a probe lifts
    one resolution further along the push, better off by a resolution)."""
    resolution = config.settle.resolution_m
    fixed = list(config.reference.meshes)
    checked, touching, lifted = 0, [], []
    for b, spec in enumerate(config.bodies):
        probe = Probe(fixed, list(spec.meshes))
        centroid = np.asarray(trimesh.util.concatenate(
            [trimesh.load_mesh(p) for p in spec.meshes]).centroid)
        for i, j in zip(*np.nonzero(table.converged[b])):
            params = config.params(spec, float(table.flexion_rad[i]), float(table.varus_rad[j]))
            push = np.asarray(params.push)
            lock = None if params.locked_slide is None else np.asarray(params.locked_slide)
            pose = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                             table.position_m[b, i, j])
            where = f'{spec.name} flexion {math.degrees(table.flexion_rad[i]):g} varus ' \
                    f'{math.degrees(table.varus_rad[j]):g}'
            checked += 1
            ahead = pose_from(pose[:3, :3], pose[:3, 3] + resolution * push)
            if probe.collides(pose) or not probe.collides(ahead):
                touching.append(where)
                continue
            value = cell_objective(config, table, b, int(i), int(j), centroid)
            # without ligaments a free probe gains exactly the resolution: the bar sits a
            # rounding below it
            bar = value(pose) + resolution * (1.0 - 1e-9)
            centre = pose[:3, :3] @ centroid + pose[:3, 3]
            for label, moved in probes(pose, push, lock, centre):
                further = pose_from(moved[:3, :3], moved[:3, 3] + resolution * push)
                if not probe.collides(further) and value(further) >= bar:
                    lifted.append(f'{where}: {label}')
                    break
    return checked, touching, lifted


@pytest.mark.slow
def test_coarse_table_converges_and_converged_cells_touch(
        built: tuple[KneeConfig, PoseTable, str]) -> None:
    config, table, output = built
    assert table.converged.mean() >= 0.9, output
    checked, touching, _ = rest_failures(config, table)
    assert checked == int(table.converged.sum())
    assert not touching, f'not touching at the resolution: {touching}'


@pytest.mark.slow
def test_every_converged_cell_passes_the_rest_probes(
        built: tuple[KneeConfig, PoseTable, str]) -> None:
    config, table, _ = built
    _, _, lifted = rest_failures(config, table)
    assert not lifted, '; '.join(lifted)


@pytest.mark.slow
def test_every_converged_cell_is_at_rest_for_the_referee(
        built: tuple[KneeConfig, PoseTable, str], capsys: pytest.CaptureFixture[str]) -> None:
    """`kneeseat verify` on every cell of the coarse table: no converged cell gains more
    than the resolution."""
    code = main(['verify', str(BUILT_FILE['natural']), '--workers', '2', '--quiet', '--json'])
    report = json.loads(capsys.readouterr().out)
    gains = [c['gain_m'] for c in report['cells'] if c['converged']]
    print(f'natural coarse table: {len(gains)} converged cells verified, largest gain '
          f'{max(gains) * 1e3:.3f} mm')
    assert code == 0 and report['not_at_rest'] == 0 and gains


@pytest.mark.slow
def test_coarse_build_reports_starts_in_collision_once_per_body(
        built: tuple[KneeConfig, PoseTable, str]) -> None:
    _, table, output = built
    lines = [ln for ln in output.splitlines() if 'start was in collision' in ln]
    for body in table.bodies:
        said = [ln for ln in lines if ln.startswith(f'  {body}: ')]
        cells = table.metadata['backed_out'][body]['cells']
        assert len(said) == (1 if cells else 0)
        if cells:
            assert f'in collision at {cells} cells' in said[0]


@pytest.mark.slow
def test_kinematics_of_the_coarse_table(built: tuple[KneeConfig, PoseTable, str]) -> None:
    _, table, _ = built
    kin = knee_kinematics(table, table_landmarks(table))
    np.testing.assert_allclose(kin.knee_flexion_deg, [0.0, 30.0, 60.0, 90.0])
    # the patella's attitude is prescribed (0.65 x flexion); the settle only turns it about
    # its push, which keeps the patellar flexion within a degree of it
    np.testing.assert_allclose(kin.values['patella_flexion'], 0.65 * kin.knee_flexion_deg,
                               atol=1.0)
    assert all(np.isfinite(v).all() for v in kin.values.values())
