"""`kneeseat settle` through `main([...])`: its contract (docs/design.md) and its bad inputs.

Exit codes: 0 converged, 3 not converged (JSON still printed), 4 no contact along the
push, 2 bad input with exactly one line on stderr and no traceback.
"""
from __future__ import annotations

import json
from pathlib import Path
import re

import pytest
import trimesh

from kneeseat_core.cli import main

JSON_KEYS = {'converged', 'reason', 'pose', 'iterations', 'collision_checks', 'contacts',
             'elapsed_s'}


@pytest.fixture(scope='module')
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 40 mm slab (top at y = 0) and a 5 mm sphere 10 mm above it (metres, STL)."""
    folder = tmp_path_factory.mktemp('cli_scene')
    slab = trimesh.creation.box((0.04, 0.01, 0.04))
    slab.apply_translation((0.0, -0.005, 0.0))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.005)
    paths = {'fixed': folder / 'slab.stl', 'moving': folder / 'ball.stl'}
    slab.export(paths['fixed'])
    ball.export(paths['moving'])
    paths['start'] = folder / 'start.json'
    paths['start'].write_text(json.dumps({'position': [0.0, 0.01, 0.0],
                                          'orientation': [0.0, 0.0, 0.0, 1.0]}))
    return paths


def run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(['settle', *args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1, f'expected one line on stderr, got {err!r}'
    assert 'Traceback' not in err
    for needle in needles:
        assert needle in lines[0], f'{needle!r} not in {lines[0]!r}'


def base(scene: dict[str, Path]) -> list[str]:
    return ['--fixed', str(scene['fixed']), '--moving', str(scene['moving']),
            '--start', str(scene['start'])]


def test_settles_and_prints_exactly_the_documented_json(
        scene: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run([*base(scene), '--json'], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert set(data) == JSON_KEYS
    assert set(data['pose']) == {'position', 'orientation'}
    assert len(data['pose']['position']) == 3 and len(data['pose']['orientation']) == 4
    assert data['converged'] is True and isinstance(data['reason'], str)
    assert isinstance(data['iterations'], int) and isinstance(data['collision_checks'], int)
    assert isinstance(data['elapsed_s'], float)
    assert data['contacts'] and all(set(c) == {'point', 'normal'} for c in data['contacts'])
    # the ball rests on the slab: centre one radius above the top, within the resolution
    assert data['pose']['position'][1] == pytest.approx(0.005, abs=1e-4)
    assert err == ''


def test_human_output_without_json(scene: dict[str, Path],
                                   capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(base(scene), capsys)
    assert code == 0
    assert out.startswith('converged: ') and 'collision checks' in out
    with pytest.raises(json.JSONDecodeError):
        json.loads(out)


def test_push_with_a_leading_minus_as_two_words(scene: dict[str, Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    start = tmp_path / 'beside.json'    # the ball beside the slab, pushed towards -X
    start.write_text(json.dumps({'position': [0.04, -0.005, 0.0],
                                 'orientation': [0.0, 0.0, 0.0, 1.0]}))
    args = ['--fixed', str(scene['fixed']), '--moving', str(scene['moving']),
            '--start', str(start), '--json']
    poses = []
    for push in (['--push', '-1,0,0'], ['--push=-1,0,0'], ['--push', '-1 0 0']):
        code, out, err = run([*args, *push], capsys)
        assert code == 0, err
        poses.append(json.loads(out)['pose'])
    assert poses[0] == poses[1] == poses[2]
    # the ball rests against the slab's side wall at x = 20 mm: centre one radius out
    assert poses[0]['position'][0] == pytest.approx(0.025, abs=1e-4)


def test_not_converged_exits_3_and_still_prints_json(
        scene: dict[str, Path], capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    # start off-centre over a cone-like dish so one iteration cannot reach rest
    dish = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    dish.apply_translation((0.0, -0.03, 0.0))
    dish.export(tmp_path / 'dome.stl')
    start = tmp_path / 'start.json'
    start.write_text(json.dumps({'position': [0.004, 0.0, 0.0],
                                 'orientation': [0.0, 0.0, 0.0, 1.0]}))
    code, out, err = run(['--fixed', str(tmp_path / 'dome.stl'), '--moving',
                          str(scene['moving']), '--start', str(start),
                          '--max-iterations', '1', '--json'], capsys)
    assert code == 3, err
    data = json.loads(out)
    assert data['converged'] is False and 'iteration cap' in data['reason']


def test_missing_mesh_file(scene: dict[str, Path], tmp_path: Path,
                           capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / 'nope.stl'
    code, out, err = run(['--fixed', str(missing), '--moving', str(scene['moving'])], capsys)
    assert code == 2 and out == ''
    assert_one_line_error(err, str(missing), 'no such mesh file')


def test_non_mesh_file(scene: dict[str, Path], tmp_path: Path,
                       capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / 'notes.stl'
    junk.write_bytes(b'these are not triangles\n' * 3)
    code, _, err = run(['--fixed', str(scene['fixed']), '--moving', str(junk)], capsys)
    assert code == 2
    assert_one_line_error(err, str(junk))


@pytest.mark.parametrize('content', ['', 'solid empty\nendsolid empty\n'])
def test_empty_mesh(scene: dict[str, Path], tmp_path: Path, content: str,
                    capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / 'empty.stl'
    empty.write_text(content)
    code, _, err = run(['--fixed', str(empty), '--moving', str(scene['moving'])], capsys)
    assert code == 2
    assert_one_line_error(err, str(empty))


@pytest.mark.parametrize('push', ['0,1,0', '1,0,0'])
def test_bodies_that_never_touch_exit_4(scene: dict[str, Path], push: str,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run([*base(scene), f'--push={push}', '--json'], capsys)
    assert code == 4 and out == ''
    assert_one_line_error(err, 'no contact', '--push')


def test_start_in_collision_backs_out_and_settles(
        scene: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Backed out along -push until free, the ball then comes down on the flat top along
    its normal, as from above: one contact whose normal is the push, so no slide or spin
    gains travel and the settle proves a rest (exit 0). The settle is deterministic."""
    start = tmp_path / 'deep.json'     # the ball's centre 3 mm below the slab's top
    start.write_text(json.dumps({'position': [0.0, -0.003, 0.0],
                                 'orientation': [0.0, 0.0, 0.0, 1.0]}))
    code, out, err = run(['--fixed', str(scene['fixed']), '--moving', str(scene['moving']),
                          '--start', str(start), '--json'], capsys)
    assert code == 0, err
    assert_one_line_error(err, 'in collision', 'backed out')
    # free once the ball's bottom (5 mm below its centre) clears the top: 8 mm, to within
    # the resolution (0.1 mm) on the free side
    backed = re.search(r'backed out ([0-9.]+) mm', err)
    assert backed is not None and 8.0 <= float(backed.group(1)) <= 8.1, err
    data = json.loads(out)
    assert data['converged'] is True and data['reason'].startswith('rest')
    assert data['pose']['position'][1] == pytest.approx(0.005, abs=1e-4)


BAD_PUSH = [('1,2', 'three'), ('a,b,c', 'three'), ('1,0,nan', 'finite'), ('0,0,0', 'push')]
BAD_PARAMETERS = [['--resolution', '0.01'], ['--step', '-1'], ['--max-iterations', '0'],
                  ['--units', 'inch'], ['--method', 'magic']]


@pytest.mark.parametrize('push,needle', BAD_PUSH)
def test_bad_push(scene: dict[str, Path], push: str, needle: str,
                  capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run([*base(scene), f'--push={push}'], capsys)
    assert code == 2 and out == ''
    assert 'Traceback' not in err
    assert needle in err.strip().splitlines()[-1]


@pytest.mark.parametrize('args', BAD_PARAMETERS)
def test_bad_parameters(scene: dict[str, Path], args: list[str],
                        capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run([*base(scene), *args], capsys)
    assert code == 2 and out == ''
    assert 'Traceback' not in err
    assert err.strip().splitlines()[-1].startswith('kneeseat settle: error: ')


@pytest.mark.parametrize('args', [['--push=1,2'], ['--units', 'inch']])
def test_parse_time_errors_are_one_line(scene: dict[str, Path], args: list[str],
                                        capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run([*base(scene), *args], capsys)
    assert code == 2
    assert_one_line_error(err)


@pytest.mark.parametrize('text,needle', [
    ('{"position": [0, 0.01, 0]', 'not a start pose'),
    ('{"position": [0, 0.01, 0]}', 'not a start pose'),
    ('{"position": [0, 0.01], "orientation": [0, 0, 0, 1]}', 'not a start pose'),
    ('{"position": [0, 0.01, 0], "orientation": [0, 0, 0, 2]}', 'unit quaternion'),
    ('{"position": [0, NaN, 0], "orientation": [0, 0, 0, 1]}', 'non-finite'),
])
def test_bad_start_file(scene: dict[str, Path], tmp_path: Path, text: str, needle: str,
                        capsys: pytest.CaptureFixture[str]) -> None:
    start = tmp_path / 'start.json'
    start.write_text(text)
    code, out, err = run(['--fixed', str(scene['fixed']), '--moving', str(scene['moving']),
                          '--start', str(start)], capsys)
    assert code == 2 and out == ''
    assert_one_line_error(err, str(start), needle)


def test_missing_start_file(scene: dict[str, Path], tmp_path: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    start = tmp_path / 'absent.json'
    code, _, err = run(['--fixed', str(scene['fixed']), '--moving', str(scene['moving']),
                        '--start', str(start)], capsys)
    assert code == 2
    assert_one_line_error(err, str(start), 'no such start file')


def test_millimetre_mesh_without_units_suggests_mm(
        scene: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    big = trimesh.load(scene['fixed'], force='mesh')
    big.apply_scale(1000.0)
    big.export(tmp_path / 'slab_mm.stl')
    code, _, err = run(['--fixed', str(tmp_path / 'slab_mm.stl'), '--moving',
                        str(scene['moving'])], capsys)
    assert code == 2
    assert_one_line_error(err, '--units mm')


def test_sliding_off_the_edge_is_not_converged(scene: dict[str, Path],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A push tilted against a flat slab has no rest: the ball slides towards the edge.
    It did touch, so this is an honest not-converged end (exit 3), not 'no contact'."""
    code, out, err = run([*base(scene), '--push', '-0.3,-1,0', '--json'], capsys)
    assert code == 3, err
    data = json.loads(out)
    assert data['converged'] is False and data['reason']
    assert err == ''


def test_a_mesh_far_beyond_any_bone_is_named_as_such(scene: dict[str, Path], tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    far = tmp_path / 'far.stl'
    far.write_text('solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1e300 0 0\n'
                   'vertex 0 1e300 0\nendloop\nendfacet\nendsolid t\n')
    code, _, err = run(['--fixed', str(far), '--moving', str(scene['moving'])], capsys)
    assert code == 2
    assert_one_line_error(err, str(far), 'reaches 1e+300, far beyond any bone')
