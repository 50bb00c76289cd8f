"""Ligaments: the force law, a set read from the shared format, the tissue acting on one body,
and the settle's rest with them (the load's work less their energy), each checked against an
answer computed here by other means (numerical integrals, finite differences, a 1-D
maximisation of the closed-form work)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize_scalar

import settle_cases as sc
import shapes
from conftest import SHARED_DATA
from kneeseat_core.errors import ConfigError, SettleError
from kneeseat_core.geometry import pose_from, rotation_about
from kneeseat_core.knee import ligaments_from_metadata, load_config, materialise_default_knee
from kneeseat_core.ligaments import (fibre_energy, fibre_force, LigamentSet, load_ligaments,
                                     parse_ligaments)
from kneeseat_core.meshes import RigidBody
from kneeseat_core.referee import Referee
from kneeseat_core.referee.judge import Load
from kneeseat_core.settle import settle, SettleParams
from kneeseat_core.status import Status
from kneeseat_core.sweep import build_table, InlineExecutor, SoftTissue, summary_line

BODIES = ['femur', 'tibia', 'patella']


def fibre(name: str, points: list[tuple[str, list[float]]], slack: float,
          k: float = 1000.0) -> dict[str, object]:
    return {'name': name, 'points': [{'body': b, 'position': p} for b, p in points],
            'slack_length_m': slack, 'linear_stiffness_n': k}


def test_force_is_continuous_and_the_energy_its_integral() -> None:
    k, et, slack = 500.0, 0.06, 0.03
    for e in (-0.01, 0.0, 0.01, 0.059999, 0.06, 0.0600001, 0.1, 0.3):
        integral, _ = quad(lambda x: float(fibre_force(np.array(x), k, et)) * slack,
                           0.0, max(e, 0.0), points=[et] if e > et else None)
        assert float(fibre_energy(np.array(e), k, et, slack)) == pytest.approx(
            integral, rel=1e-9, abs=1e-15)
    below = float(fibre_force(np.array(et - 1e-12), k, et))
    above = float(fibre_force(np.array(et + 1e-12), k, et))
    assert below == pytest.approx(above, rel=1e-9) == pytest.approx(k * et / 2)
    assert float(fibre_force(np.array(-0.2), k, et)) == 0.0


def test_tissue_gradient_is_the_energy_derivative() -> None:
    rng = np.random.default_rng(20261201)
    items = [fibre(f'f{i}', [('femur', list(rng.normal(0, 0.02, 3))),
                             ('tibia', list(rng.normal(0, 0.02, 3)))], 0.01 + 0.02 * rng.random())
             for i in range(12)]
    items.append(fibre('path', [('femur', [0.0, 0.05, 0.0]), ('tibia', [0.01, 0.0, 0.0]),
                                ('tibia', [0.02, -0.03, 0.0])], 0.05))
    ligaments = parse_ligaments(items, 'test', BODIES)
    tissue = ligaments.tissue('tibia', {'femur': np.eye(4)})
    assert tissue is not None and len(tissue.names) == 13
    pose = pose_from(rotation_about(np.array([0.0, 1.0, 0.0]), 0.1), [0.001, -0.002, 0.003])
    assert tissue.energy(pose) > 0.0
    # the lengths the set reports equal the tissue's
    strains = ligaments.strains({'femur': np.eye(4), 'tibia': pose})
    assert np.allclose(strains, tissue.strains(pose), rtol=0, atol=1e-12)


def three_fibres() -> LigamentSet:
    """An ACL (femur-tibia), a patellar tendon (patella-tibia) and an MPFL (femur-patella)."""
    return parse_ligaments([
        fibre('acl', [('femur', [0, 0, 0]), ('tibia', [0, -0.03, 0])], 0.03),
        fibre('pt', [('patella', [0.05, 0, 0]), ('tibia', [0.04, -0.05, 0])], 0.05),
        fibre('mpfl', [('femur', [0, 0, -0.04]), ('patella', [0.05, 0, -0.01])], 0.04)],
        'test', BODIES)


def test_a_fibre_acts_on_the_body_it_joins_to_bodies_already_placed() -> None:
    ligaments = three_fibres()
    assert [f.name for f in ligaments.acting_on('tibia', ['femur'])] == ['acl']
    assert [f.name for f in ligaments.acting_on('patella', ['femur', 'tibia'])] == ['pt', 'mpfl']
    assert [f.name for f in ligaments.acting_on('patella', ['femur'])] == ['mpfl']


def test_a_chain_places_the_fibres_where_the_bodies_they_reach_rest_at_each_cell() -> None:
    ligaments = three_fibres()
    tibia_rests = np.stack([pose_from(rotation_about(np.array([0.0, 0.0, 1.0]), 0.1 * i),
                                      np.array([0.002 * i, -0.001, 0.0])) for i in range(3)])
    patella = SoftTissue.of(ligaments, 'patella', 'femur', ('tibia',), tibia_rests[:, None])
    pose = pose_from(rotation_about(np.array([1.0, 0.0, 0.0]), 0.05), np.array([0.0, 0.01, 0.0]))
    for i, tibia in enumerate(tibia_rests):
        # each fibre's length from its definition: the points placed by hand
        pt = np.linalg.norm(pose[:3, :3] @ [0.05, 0, 0] + pose[:3, 3]
                            - (tibia[:3, :3] @ [0.04, -0.05, 0] + tibia[:3, 3]))
        mpfl = np.linalg.norm(pose[:3, :3] @ [0.05, 0, -0.01] + pose[:3, 3] - [0, 0, -0.04])
        tissue = patella.at(i)
        assert tissue is not None and tissue.names == ('pt', 'mpfl')
        assert tissue.strains(pose) == pytest.approx([pt / 0.05 - 1, mpfl / 0.04 - 1], abs=1e-12)
    # held by the reference alone, the tibia's fibres are the same at every cell
    tibia = SoftTissue.of(ligaments, 'tibia', 'femur', (), np.zeros((3, 0, 4, 4)))
    assert tibia.at(0) is tibia.at(2) is not None
    acl = np.linalg.norm(pose[:3, :3] @ [0, -0.03, 0] + pose[:3, 3])
    assert tibia.at(1).strains(pose) == pytest.approx([acl / 0.03 - 1], abs=1e-12)
    alone = SoftTissue.of(ligaments, 'femur', 'femur', (), np.zeros((3, 0, 4, 4)))
    assert alone.at(0) is None


@pytest.mark.parametrize('items, message', [
    ([{'name': 'a', 'points': [], 'slack_length_m': 0.01}], r"missing key 'linear_stiffness_n'"),
    ([fibre('a', [('femur', [0, 0, 0]), ('fibula', [0, 0, 0])], 0.01)],
     r"points\[1\]\.body 'fibula' is not a body of the config"),
    ([fibre('a', [('femur', [0, 0, 0]), ('femur', [0, 1, 0])], 0.01)],
     r'a fibre joins exactly two bodies'),
    ([fibre('a', [('femur', [0, 0, 0]), ('tibia', [0, 0, 0])], -0.01)],
     r"ligament 'a'\.slack_length_m must be a positive number"),
    ([fibre('a', [('femur', [0, 0, 0]), ('tibia', [0, 'x', 0])], 0.01)],
     r'position must be three finite numbers'),
    ([{**fibre('a', [('femur', [0, 0, 0]), ('tibia', [0, 0, 0])], 0.01), 'stifness': 1}],
     r"unknown key 'stifness'"),
    ([fibre('a', [('femur', [0, 0, 0]), ('tibia', [0, 0, 0])], 0.01)] * 2, r'listed twice'),
])
def test_bad_fibres_are_refused_with_the_key_named(items: list[object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_ligaments(items, 'config ligaments', BODIES)


@pytest.mark.parametrize('knee, fibres', [('natural_knee', 76), ('tka_dm', 149)])
def test_the_shared_sets_read_and_reproduce_their_recorded_strains(
        knee: str, fibres: int) -> None:
    path = SHARED_DATA / knee / 'ligaments.json'
    if not path.is_file():
        pytest.skip(f'{path} is not there (../shared/data is not beside the repository)')
    ligaments = load_ligaments(path, BODIES)
    assert len(ligaments.fibres) == fibres and len(ligaments.sha256) == 64
    raw = json.loads(path.read_text())['ligaments']
    recorded = [f.get('strain_at_delivered_pose_straight') for f in raw]
    if recorded[0] is not None:              # the natural set records its own strains
        got = ligaments.strains({b: np.eye(4) for b in BODIES})
        assert np.allclose(got, recorded, rtol=0, atol=1e-4)


def test_a_ligament_file_with_a_typo_names_the_file_and_the_key(tmp_path: Path) -> None:
    path = tmp_path / 'ligaments.json'
    path.write_text(json.dumps({'units': 'm', 'ligamnets': []}))
    with pytest.raises(ConfigError, match=r"ligaments\.json: unknown key 'ligamnets'"):
        load_ligaments(path, BODIES)
    with pytest.raises(ConfigError, match='not found'):
        load_ligaments(tmp_path / 'gone.json', BODIES)


# ---- the settle with a load and ligaments -------------------------------------------------
BOWL_R, BALL_R, DEPTH = 20 * sc.MM, 10 * sc.MM, 8 * sc.MM
ANCHOR_X = 0.5            # m: a far anchor, so the fibre pulls the ball almost along +X
LOAD_N = 100.0


def ball_in_bowl_with_a_side_fibre(slack_m: float, k: float = 1000.0
                                   ) -> tuple[RigidBody, RigidBody, LigamentSet]:
    bowl = RigidBody.from_mesh(shapes.bowl(BOWL_R, DEPTH, 30 * sc.MM))
    ball = RigidBody.from_mesh(shapes.sphere(BALL_R))
    centre_y = -DEPTH + BOWL_R - (BOWL_R - BALL_R)
    ligaments = parse_ligaments([fibre('side', [('femur', [ANCHOR_X, centre_y, 0.0]),
                                                ('tibia', [0.0, 0.0, 0.0])], slack_m, k)],
                                'test', BODIES)
    return bowl, ball, ligaments


def expected_angle(tissue_energy: object, lever: float, bottom: np.ndarray) -> float:
    """The ball's angle from the bowl's bottom that maximises the load's work less the
    fibre's energy, by a 1-D maximisation of the closed form (the ball's centre moves on a
    circle of radius `lever` about the bowl's centre)."""
    centre = bottom + np.array([0.0, lever, 0.0])

    def minus_work(theta: float) -> float:
        at = centre + lever * np.array([math.sin(theta), -math.cos(theta), 0.0])
        pose = pose_from(np.eye(3), at)
        return -(LOAD_N * lever * math.cos(theta) - tissue_energy(pose))  # type: ignore[operator]

    return float(minimize_scalar(minus_work, bounds=(-0.5, 1.2), method='bounded',
                                 options={'xatol': 1e-10}).x)


def test_a_side_fibre_moves_the_rest_up_the_bowl_where_its_pull_balances_the_load() -> None:
    bowl, ball, ligaments = ball_in_bowl_with_a_side_fibre(slack_m=ANCHOR_X - 0.02)
    tissue = ligaments.tissue('tibia', {'femur': np.eye(4)})
    assert tissue is not None
    params = SettleParams(push=(0.0, -1.0, 0.0), load_n=LOAD_N, max_iterations=800)
    result = settle(bowl, ball, pose_from(np.eye(3), [0.0, 0.012, 0.0]), params, tissue=tissue)
    assert result.converged and result.status == Status.REST, result.reason
    assert 'ligaments' in result.reason
    lever = BOWL_R - BALL_R
    bottom = np.array([0.0, -DEPTH + BALL_R, 0.0])
    theta = expected_angle(tissue.energy, lever, bottom)
    assert theta > 0.1                       # the fibre pulls it well up the side
    centre = bottom + np.array([0.0, lever, 0.0])
    want = centre + lever * np.array([math.sin(theta), -math.cos(theta), 0.0])
    # measured 0.011 mm from the closed form's maximum (the resolution is 0.1 mm)
    assert np.linalg.norm(result.pose[:3, 3] - want) < 0.05e-3, (result.pose[:3, 3], want)


def test_without_ligaments_the_load_changes_nothing() -> None:
    bowl, ball = (RigidBody.from_mesh(shapes.bowl(BOWL_R, DEPTH, 30 * sc.MM)),
                  RigidBody.from_mesh(shapes.sphere(BALL_R)))
    start = pose_from(np.eye(3), [0.003, 0.012, 0.0])
    plain = settle(bowl, ball, start, SettleParams(push=(0.0, -1.0, 0.0)))
    loaded = settle(bowl, ball, start, SettleParams(push=(0.0, -1.0, 0.0), load_n=300.0))
    assert np.array_equal(plain.pose, loaded.pose) and plain.reason == loaded.reason


def test_a_fibre_stronger_than_the_load_pulls_the_body_off() -> None:
    bowl, ball = (RigidBody.from_mesh(shapes.bowl(BOWL_R, DEPTH, 30 * sc.MM)),
                  RigidBody.from_mesh(shapes.sphere(BALL_R)))
    up = parse_ligaments([fibre('up', [('femur', [0.0, 0.2, 0.0]), ('tibia', [0.0, 0.0, 0.0])],
                                0.15, k=5000.0)], 'test', BODIES)   # strained 25%: 1 kN up
    tissue = up.tissue('tibia', {'femur': np.eye(4)})
    result = settle(bowl, ball, pose_from(np.eye(3), [0.0, 0.012, 0.0]),
                    SettleParams(push=(0.0, -1.0, 0.0), load_n=LOAD_N), tissue=tissue)
    assert not result.converged and result.status == Status.PULLED
    assert result.reason.startswith('pulled off') and 'N along the push' in result.reason


def test_a_tissue_without_a_load_is_refused() -> None:
    bowl, ball, ligaments = ball_in_bowl_with_a_side_fibre(slack_m=0.45)
    with pytest.raises(SettleError, match='no load is given'):
        settle(bowl, ball, pose_from(np.eye(3), [0.0, 0.012, 0.0]),
               SettleParams(push=(0.0, -1.0, 0.0)),
               tissue=ligaments.tissue('tibia', {'femur': np.eye(4)}))


# ---- the referee judges the same objective with its own energy ----------------------------
def referee_load(ligaments: LigamentSet, load_n: float) -> Load:
    fibres = ligaments.acting_on('tibia', ['femur'])
    paths = tuple((np.array(f.points), np.array([b == 'tibia' for b in f.bodies]))
                  for f in fibres)
    return Load(load_n, None, paths, np.array([f.slack_m for f in fibres]),
                np.array([f.stiffness_n for f in fibres]),
                np.array([f.transition for f in fibres]))


def test_the_referee_agrees_with_the_settle_and_refuses_the_rest_geometry_alone_finds() -> None:
    # a stiff fibre: the ball rests about 20 degrees up the side, 0.7 mm of work per unit
    # load above the bowl's bottom
    bowl, ball, ligaments = ball_in_bowl_with_a_side_fibre(slack_m=ANCHOR_X - 0.02, k=3000.0)
    tissue = ligaments.tissue('tibia', {'femur': np.eye(4)})
    params = SettleParams(push=(0.0, -1.0, 0.0), load_n=LOAD_N, max_iterations=800)
    result = settle(bowl, ball, pose_from(np.eye(3), [0.0, 0.012, 0.0]), params, tissue=tissue)
    referee = Referee([shapes.bowl(BOWL_R, DEPTH, 30 * sc.MM)], [shapes.sphere(BALL_R)],
                      np.array([0.0, -1.0, 0.0]), 1e-4, load=referee_load(ligaments, LOAD_N))
    verdict = referee.judge(result.pose)
    assert verdict.at_rest(1e-4), verdict
    extent = referee.extent(result.pose, referee.measure(verdict.best_pose)[0])
    # the fibre pins the ball up the side: within a resolution of its best the ball moves
    # a fraction of a millimetre across the push (the bowl alone would allow no less)
    assert 0.0 < extent.slide_m < 1.5e-3
    plain = settle(bowl, ball, pose_from(np.eye(3), [0.0, 0.012, 0.0]),
                   SettleParams(push=(0.0, -1.0, 0.0)))
    assert plain.converged and np.linalg.norm(plain.pose[:3, 3] - result.pose[:3, 3]) > 1e-3
    wrong = referee.judge(plain.pose)              # the bowl's bottom: the fibre pulls it up
    assert not wrong.at_rest(1e-4) and wrong.slide_m > 2e-3


# ---- knee configs with ligaments -------------------------------------------------------
@pytest.fixture
def knee_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    return materialise_default_knee().parent


def write_config(knee_dir: Path, text: str) -> Path:
    path = knee_dir / 'variant.yaml'
    path.write_text(text)
    return path


def test_the_default_knee_has_its_own_ligaments(knee_dir: Path) -> None:
    config = load_config(knee_dir / 'default_knee.yaml')
    assert config.ligaments is not None and config.ligaments.source == 'inline'
    assert [f.bundle for f in config.ligaments.fibres] == ['MCL', 'LCL', 'ACL', 'PCL']
    tibia, patella = config.bodies
    assert tibia.load_n == 100.0 and patella.load_n is None
    assert config.depends_on(patella) == ()          # no fibre reaches the patella


@pytest.mark.parametrize('change, message', [
    (('load_n: 100            # a relaxed knee moved by hand', ''),
     r"bodies\[0\]\.load_n: 4 ligament fibres act on 'tibia'; give the load"),
    (('load_n: 100            # a relaxed knee moved by hand', 'load_n: -5'),
     r'bodies\[0\]\.load_n=-5 must be a positive number of newtons'),
    (('load_n: 100            # a relaxed knee moved by hand', 'load_toward: [0, 1]'),
     r'bodies\[0\]\.load_toward must be three numbers'),
    (('{body: tibia, position: [0.0, -0.060, -0.030]}', '{body: fibula, position: [0, 0, 0]}'),
     r"ligaments: ligament 'MCL'\.points\[1\]\.body 'fibula' is not a body of the config"),
    (('slack_length_m: 0.0583', 'slack_lenght_m: 0.0583'), r"unknown key 'slack_lenght_m'"),
    (('linear_stiffness_n: 5000', 'linear_stiffness_n: .nan'),
     r"ligament 'MCL'\.linear_stiffness_n must be a positive number"),
])
def test_bad_ligament_keys_are_refused_with_the_key_named(knee_dir: Path,
                                                          change: tuple[str, str],
                                                          message: str) -> None:
    text = (knee_dir / 'default_knee.yaml').read_text()
    assert change[0] in text
    with pytest.raises(ConfigError, match=message):
        load_config(write_config(knee_dir, text.replace(change[0], change[1])))


def test_a_ligaments_file_is_found_beside_the_meshes(knee_dir: Path) -> None:
    text = (knee_dir / 'default_knee.yaml').read_text()
    start = text.index('ligaments:\n')
    end = text.index('bodies:\n')
    (knee_dir / 'set.json').write_text(json.dumps({'units': 'm', 'ligaments': [
        fibre('MCL', [('femur', [0.0, 0.0, -0.042]), ('tibia', [0.0, -0.06, -0.03])],
              0.0583)]}))
    config = load_config(write_config(knee_dir, text[:start] + 'ligaments: set.json\n'
                                      + text[end:]))
    assert config.ligaments is not None and config.ligaments.source == str(knee_dir / 'set.json')
    with pytest.raises(ConfigError, match=r'ligaments file .*gone\.json not found'):
        load_config(write_config(knee_dir, text[:start] + 'ligaments: gone.json\n' + text[end:]))


def test_a_tendon_to_the_tibia_settles_the_patella_after_it_at_every_varus(
        knee_dir: Path, tmp_path: Path) -> None:
    """A fibre from the patella to the tibia: the patella is swept after the tibia, its
    fibre attached to the tibia as it settled at each cell, so the patella (whose own
    attitude ignores varus) is settled in every varus column instead of copied."""
    text = (knee_dir / 'default_knee.yaml').read_text()
    tendon = ('  - {name: PT, points: [{body: patella, position: [0.026, -0.012, -0.001]},\n'
              '                        {body: tibia, position: [0.028, -0.045, -0.001]}],\n'
              '     slack_length_m: 0.034, linear_stiffness_n: 3000}\n')
    text = text.replace('bodies:\n', tendon + 'bodies:\n', 1)
    text = text.replace('    varus_fraction: 0.0    # and ignore varus\n',
                        '    varus_fraction: 0.0    # and ignore varus\n    load_n: 100\n')
    config = load_config(write_config(knee_dir, text),
                         overrides={'grid': {'flexion_deg': [0, -20, 20],
                                             'varus_deg': [-6, 6, 6]}})
    tibia, patella = config.bodies
    assert config.depends_on(patella) == (0,) and config.depends_on(tibia) == ()
    table = build_table(config, tmp_path / 'tendon.npz', InlineExecutor(), show_progress=False)
    loads = table.metadata['soft_tissue']['loads']
    assert loads['patella'] == {'load_n': 100.0, 'load_toward': None, 'fibres': 1}
    positions = table.position_m[1]
    assert not np.allclose(positions[:, 0], positions[:, 2], atol=1e-6)   # varus -6 vs +6
    assert 'ligaments: 5 fibres from inline' in summary_line(table, tmp_path / 'tendon.npz')
    # the tendon at each cell joins the patella to the tibia as the table holds them
    ligaments = ligaments_from_metadata(table.metadata)
    assert ligaments is not None and ligaments.sha256 == config.ligaments.sha256
