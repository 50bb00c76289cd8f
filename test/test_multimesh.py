"""Bodies made of several meshes, moved as one rigid body.

A body's collision meshes are one rigid body: two separate sphere files of one body over
two bowls rest where the *pair* rests (analytic), which is where the same spheres in one
file rest and not where each sphere alone would. The table hashes every file, and tables
written before multi-mesh bodies (test/data/table_before_multimesh.npz, written by commit
d914088 from the default knee on a 45 x 10 degree grid) still load, describe and render.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from conftest import REPO
import shapes
from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.cli import main
from kneeseat_core.errors import ConfigError, TableError
from kneeseat_core.files import file_sha256
from kneeseat_core.geometry import matrix_from_quat, rotation_about
from kneeseat_core.knee import load_config
from kneeseat_core.sweep import build_table, InlineExecutor
from kneeseat_core.cli.table_commands import _table_meshes
from kneeseat_core.table import describe, PoseTable, read_table

MM = 1e-3
RADIUS, BOWL_R, DEPTH = 8 * MM, 16 * MM, 12 * MM
SPHERES_APART, BOWLS_APART = 40 * MM, 52 * MM      # each sphere 6 mm inside its bowl's axis
OLD_TABLE = REPO / 'test' / 'data' / 'table_before_multimesh.npz'
# The body as delivered: 6 mm above its rest, 0.7 / 0.4 mm off and turned 3 deg about Y.
OFFSET = np.array([0.7, 6.0, 0.4]) * MM
TURN = rotation_about(np.array([0.0, 1.0, 0.0]), math.radians(3.0))
CENTRES = [OFFSET + TURN @ np.array([s * SPHERES_APART / 2, 0.0, 0.0]) for s in (-1, 1)]


def rest_height(offset_from_axis: float) -> float:
    """Height of a sphere centre resting in a bowl, `offset_from_axis` off the bowl's axis.

    The centre lies on a sphere of radius BOWL_R - RADIUS about the bowl's centre of
    curvature, which is BOWL_R - DEPTH above the bowl frame's origin.
    """
    return (BOWL_R - DEPTH) - math.sqrt((BOWL_R - RADIUS) ** 2 - offset_from_axis ** 2)


def write_scene(root: Path, mesh: str) -> Path:
    """Bowls (reference), two sphere files and their union; a one-cell config; its path."""
    root.mkdir(parents=True, exist_ok=True)
    if not (root / 'bowls.stl').exists():
        shapes.two_bowls(BOWL_R, (DEPTH, DEPTH), BOWLS_APART, 44 * MM, 20 * MM).export(
            root / 'bowls.stl')
        spheres = []
        for name, centre in zip(('left', 'right'), CENTRES):
            sphere = shapes.sphere(RADIUS, 4)
            sphere.apply_translation(centre)
            sphere.export(root / f'{name}.stl')
            spheres.append(trimesh.load(root / f'{name}.stl'))
        trimesh.util.concatenate(spheres).export(root / 'both.stl')
        (root / 'open.stl').write_bytes(_open_sheet())
    config = root / f'{mesh.replace(",", "_").replace(" ", "")}.yaml'
    config.write_text(f"""name: balls
mesh_dir: .
reference: {{name: bowls, mesh: bowls.stl}}
axes: {{flexion: [0, 0, 1], varus: [1, 0, 0], long: [0, 1, 0]}}
bodies:
  - {{name: balls, mesh: {mesh}, display_mesh: [right.stl, left.stl], push: [0, -1, 0]}}
grid: {{flexion_deg: [0, 0, 1], varus_deg: [0, 0, 1]}}
""")
    return config


def _open_sheet() -> bytes:
    """An open disc (not watertight) 2 mm below the bowls' rim, binary STL bytes."""
    disc = trimesh.creation.annulus(r_min=1 * MM, r_max=4 * MM, height=1 * MM)
    sheet = trimesh.Trimesh(disc.vertices, disc.faces[disc.face_normals[:, 2] > 0.5])
    sheet.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, (1, 0, 0)))
    sheet.apply_translation((30 * MM, 0.0, 0.0))
    return trimesh.exchange.stl.export_stl(sheet)


@pytest.fixture(scope='module')
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Directory of the bowls scene (written once)."""
    root = tmp_path_factory.mktemp('bowls')
    write_scene(root, 'both.stl')
    return root


def settled_centres(config: Path, out: Path) -> tuple[PoseTable, list[np.ndarray]]:
    """Build the one-cell table of `config`; the settled sphere centres (bowls frame)."""
    table = build_table(load_config(config), out, InlineExecutor(), show_progress=False)
    rotation = matrix_from_quat(table.orientation_xyzw[0, 0, 0])
    return table, [rotation @ c + table.position_m[0, 0, 0] for c in CENTRES]


def test_two_meshes_of_one_body_rest_as_one_rigid_body(scene: Path, tmp_path: Path) -> None:
    table, (left, right) = settled_centres(write_scene(scene, '[left.stl, right.stl]'),
                                           tmp_path / 'pair.npz')
    assert table.converged.all()
    offset = (BOWLS_APART - SPHERES_APART) / 2
    want = rest_height(offset)                  # both spheres on their bowls' inner walls
    alone = rest_height(0.0)                    # where one sphere would go by itself
    assert want - alone > 2.5 * MM
    resolution = table.metadata['settle']['resolution_m']
    tolerance = 2 * resolution + 0.05 * MM      # the README's rule for determined directions
    for centre in (left, right):
        assert centre[1] == pytest.approx(want, abs=tolerance)
    # the pair sits midway between the bowls (a sideways slide would lift one sphere)
    assert 0.5 * (left[0] + right[0]) == pytest.approx(0.0, abs=tolerance)
    assert np.linalg.norm(right - left) == pytest.approx(SPHERES_APART, abs=1e-9)
    single, (left1, right1) = settled_centres(write_scene(scene, 'both.stl'),
                                              tmp_path / 'one.npz')
    assert single.converged.all()
    np.testing.assert_allclose(left, left1, atol=1e-6)   # the same body, one file or two
    np.testing.assert_allclose(right, right1, atol=1e-6)


def test_every_mesh_is_hashed_and_checked(scene: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'pair.npz'
    build_table(load_config(write_scene(scene, '[left.stl, right.stl]')), out,
                InlineExecutor(), show_progress=False)
    table = read_table(out, meshes={'balls': [scene / 'left.stl', scene / 'right.stl'],
                                    'bowls': scene / 'bowls.stl'})
    body = table.metadata['bodies'][0]
    assert [(Path(m['path']).name, m['sha256']) for m in body['meshes']] == [
        (n, file_sha256(scene / n)) for n in ('left.stl', 'right.stl')]
    assert Path(body['mesh']).name == 'left.stl'              # the first, as before
    assert body['mesh_sha256'] == file_sha256(scene / 'left.stl')
    assert [(Path(m['path']).name, m['sha256']) for m in body['display_meshes']] == [
        (n, file_sha256(scene / n)) for n in ('right.stl', 'left.stl')]
    with pytest.raises(TableError, match=r"'balls' mesh .*right\.stl has SHA-256 .*built from "
                                         r'.*left\.stl'):
        read_table(out, meshes={'balls': [scene / 'right.stl', scene / 'left.stl']})
    with pytest.raises(TableError, match=r"built from 2 mesh\(es\) for 'balls', 1 given"):
        read_table(out, meshes={'balls': scene / 'left.stl'})
    assert main(['info', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'meshes ' in text and 'left.stl (sha256 ' in text and 'right.stl (sha256 ' in text
    # render draws the display meshes of a body as one
    drawn = _table_meshes(table, display=True)
    assert len(drawn['balls'].faces) == 2 * len(shapes.sphere(RADIUS, 4).faces)


def test_table_written_before_multimesh_bodies_still_reads(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch,
                                                           capsys: pytest.CaptureFixture[str]
                                                           ) -> None:
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    knee = materialise_default_knee().parent        # the same bytes as when it was built
    meshes = {n: knee / f'{n}.stl' for n in ('femur', 'tibia', 'patella')}
    table = read_table(OLD_TABLE, meshes=meshes)
    assert 'meshes' not in table.metadata['bodies'][0]
    assert table.bodies == ('tibia', 'patella') and table.converged.all()
    assert 'tibia: frame tibia, mesh ' in describe(table)
    assert main(['info', str(OLD_TABLE)]) == 0
    assert 'sha256 4345725a3609' in capsys.readouterr().out
    meta = json.loads(json.dumps(table.metadata))   # its paths named a build directory
    for entry in (meta['reference'], *meta['bodies']):
        entry['mesh'] = str(knee / Path(entry['mesh']).name)
    moved = PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                      table.orientation_xyzw, table.converged, table.iterations, meta)
    drawn = _table_meshes(moved, display=True)
    assert sorted(drawn) == ['femur', 'patella', 'tibia']
    assert len(drawn['tibia'].faces) == len(trimesh.load(meshes['tibia']).faces)


@pytest.mark.parametrize('mesh, message', [
    ('[]', r'bodies\[0\]\.mesh must be a file name or a non-empty list'),
    ('[left.stl, left.stl]', r'bodies\[0\]\.mesh lists a mesh twice'),
    ('[left.stl, gone.stl]', r'bodies\[0\]\.mesh\[1\]: mesh file .*gone\.stl not found'),
    ('[left.stl, 3]', r'bodies\[0\]\.mesh\[1\] must be a file name, got 3'),
])
def test_bad_mesh_lists_are_refused(scene: Path, mesh: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(write_scene(scene, mesh))


def test_open_meshes_warn_once_per_mesh_with_two_workers(scene: Path, tmp_path: Path) -> None:
    # 'open.stl' (a sheet) rides with the spheres: 5 cells, 2 worker processes, and the
    # warning still comes once, from the parent that validated the meshes.
    config = write_scene(scene, '[left.stl, right.stl, open.stl]')
    proc = subprocess.run(
        [sys.executable, '-m', 'kneeseat_core', 'build', str(config), '--out',
         str(tmp_path / 't.npz'), '--workers', '2', '--quiet', '--flexion-grid', '0,-4,1'],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if 'not watertight' in ln]
    assert len(warnings) == 1 and 'open.stl' in warnings[0], proc.stderr


def test_a_start_in_collision_is_reported_once_per_body(scene: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    # The spheres as delivered sink 9 mm into the bowls' rim: every start backs out.
    root = tmp_path / 'sunk'
    shutil.copytree(scene, root)
    for name in ('left', 'right'):
        mesh = trimesh.load(root / f'{name}.stl')
        mesh.apply_translation((0.0, -15 * MM, 0.0))
        mesh.export(root / f'{name}.stl')
    config = write_scene(root, '[left.stl, right.stl]')
    out = tmp_path / 'sunk.npz'
    assert main(['build', str(config), '--out', str(out), '--workers', '1', '--quiet',
                 '--flexion-grid', '0,-2,1']) == 0
    lines = capsys.readouterr().out.splitlines()
    said = [ln for ln in lines if 'start was in collision' in ln]
    assert said == [said[0]] and said[0].startswith('  balls: the start was in collision at ')
    backed = read_table(out).metadata['backed_out']['balls']
    assert backed['cells'] >= 1 and backed['max_mm'] > 0.0
    assert f'backed out along the push) at {backed["cells"]} cells' in describe(read_table(out))


def test_push_flexion_fraction_turns_the_push_not_the_attitude(scene: Path) -> None:
    config = write_scene(scene, 'both.stl')
    text = config.read_text().replace('push: [0, -1, 0]}',
                                      'push: [0, -1, 0], flexion_fraction: 0.6, '
                                      'push_flexion_fraction: 0.4, locked_slide: [1, 0, 0]}')
    config.write_text(text)
    cfg = load_config(config)
    body = cfg.bodies[0]
    flexion = math.radians(-50.0)
    turn_z = (lambda a: rotation_about(np.array([0.0, 0.0, 1.0]), a))
    np.testing.assert_allclose(cfg.attitude(body, flexion, 0.0), turn_z(0.6 * flexion))
    params = cfg.params(body, flexion, 0.0)
    np.testing.assert_allclose(params.push, turn_z(0.4 * flexion) @ [0.0, -1.0, 0.0])
    np.testing.assert_allclose(params.locked_slide, turn_z(0.4 * flexion) @ [1.0, 0.0, 0.0])
    config.write_text(text.replace('push_flexion_fraction: 0.4', 'push_flexion_fraction: x'))
    with pytest.raises(ConfigError, match=r'push_flexion_fraction must be a number'):
        load_config(config)
