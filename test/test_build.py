"""`kneeseat build` end to end, and a real built table refusing damage.

test_table.py covers every rejection on synthetic tables; here the same failures are made
on a table the CLI really built from the default knee (a coarse grid, seconds), and each
must be refused by `read_table` with a clear message and by `kneeseat info` with exit
code 2 and exactly one line on stderr (no traceback).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
import json
from pathlib import Path
import re
import shutil
import zipfile

import numpy as np
import pytest

from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.cli import main
from kneeseat_core.errors import ConfigError, TableError
from kneeseat_core.table import read_table

GRID = ('--flexion-grid', '0,-90,30', '--varus-grid', '-10,10,10')


@pytest.fixture(scope='module')
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """(table, mesh directory) of a coarse default-knee build through the CLI."""
    root = tmp_path_factory.mktemp('build')
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.setenv('XDG_CACHE_HOME', str(root / 'cache'))
        out = root / 'tables' / 'knee.npz'          # the directory is created by build
        assert main(['build', '--out', str(out), '--workers', '1', '--quiet', *GRID]) == 0
        yield out, materialise_default_knee().parent


def test_build_writes_a_verified_table(built: tuple[Path, Path],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    table_path, mesh_dir = built
    table = read_table(table_path, meshes={name: mesh_dir / f'{name}.stl'
                                           for name in ('femur', 'tibia', 'patella')})
    assert table.bodies == ('tibia', 'patella')
    assert table.position_m.shape == (2, 4, 3, 3)
    assert np.allclose(np.degrees(table.flexion_rad), [-90, -60, -30, 0])
    assert np.allclose(np.degrees(table.varus_rad), [-10, 0, 10])
    assert table.converged.all()
    meta = table.metadata
    assert meta['summary']['cells'] == 24 and meta['summary']['converged'] == 24
    # the bodies built before the chains, and the chains' own times: parts of the sweep
    summary = meta['summary']
    assert 0.0 < summary['scene_s'] < summary['wall_s']
    assert 0.0 < summary['chains_s'] <= summary['wall_s'] - summary['scene_s'] + 0.01
    assert meta['settle']['resolution_m'] == 1e-4 and meta['settle']['step_m'] == 1e-3
    assert meta['config']['resolved']['varus_deg'] == [-10.0, 0.0, 10.0]
    assert main(['info', str(table_path)]) == 0
    out = capsys.readouterr().out
    assert 'tibia: frame tibia' in out and 'converged 100.0% (12/12)' in out
    assert not list(table_path.parent.glob('.*.tmp'))       # atomic write left nothing


def flip_byte_in_member(path: Path, member: str) -> None:
    """Flip one bit of the last data byte of `member` inside the (stored) zip."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(member)
    data = bytearray(path.read_bytes())
    # local header: 30 bytes + name + extra, then the member's bytes
    name_len = int.from_bytes(data[info.header_offset + 26:info.header_offset + 28], 'little')
    extra_len = int.from_bytes(data[info.header_offset + 28:info.header_offset + 30], 'little')
    start = info.header_offset + 30 + name_len + extra_len
    data[start + info.compress_size - 1] ^= 0x01
    path.write_bytes(bytes(data))


def resave(path: Path, edit: Callable[[dict[str, np.ndarray]], None]) -> None:
    """Rewrite a table's .npz after `edit` changed its arrays (no new hash)."""
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: np.array(npz[name]) for name in npz.files}
    edit(arrays)
    with open(path, 'wb') as fh:
        np.savez(fh, allow_pickle=False, **arrays)


def _flipped(path: Path) -> None:
    flip_byte_in_member(path, 'position.npy')


def _truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])


def _edited(path: Path) -> None:
    def nudge(arrays: dict[str, np.ndarray]) -> None:
        arrays['position'][0, 1, 1, 2] += 1e-4             # 0.1 mm, one cell

    resave(path, nudge)


def _wrong_schema(path: Path) -> None:
    def schema(arrays: dict[str, np.ndarray]) -> None:
        meta = json.loads(str(arrays['metadata'][()]))
        meta['schema'] = 'kneeseat.table/99'
        arrays['metadata'] = np.array(json.dumps(meta))

    resave(path, schema)


@pytest.mark.parametrize('damage, message', [
    (_flipped, r'is corrupt|not a readable table'),
    (_truncated, r'not a readable table .*truncated, corrupt'),
    (_edited, r'do not match their SHA-256 .*corrupt or modified'),
    (_wrong_schema, r"unknown table schema 'kneeseat.table/99'"),
], ids=['flipped-byte', 'truncated', 'edited-array', 'wrong-schema'])
def test_damaged_real_table_is_refused(built: tuple[Path, Path], tmp_path: Path,
                                       damage: Callable[[Path], None], message: str,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / 'damaged.npz'
    shutil.copyfile(built[0], path)
    damage(path)
    with pytest.raises(TableError, match=message):
        read_table(path)
    capsys.readouterr()
    assert main(['info', str(path)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith('kneeseat info: error: table file ')
    assert 'rebuild' in lines[0] or 'kneeseat version' in lines[0]   # says how to fix it
    assert 'Traceback' not in captured.err and captured.out == ''


def test_real_table_refuses_other_meshes(built: tuple[Path, Path], tmp_path: Path) -> None:
    table_path, mesh_dir = built
    other = tmp_path / 'tibia.stl'                  # same name, one vertex moved
    data = bytearray((mesh_dir / 'tibia.stl').read_bytes())
    data[84 + 12] ^= 0x01                           # first triangle, first vertex, x
    other.write_bytes(bytes(data))
    with pytest.raises(TableError, match=r"built from other meshes: 'tibia' mesh .*rebuild"):
        read_table(table_path, meshes={'tibia': other})
    read_table(table_path, meshes={'tibia': mesh_dir / 'tibia.stl'})   # the right one


def test_verify_judges_only_the_cells_claimed_at_rest(built: tuple[Path, Path], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A cell that did not converge claims nothing: verify counts it and does not judge it."""
    from dataclasses import replace

    from kneeseat_core.status import Status
    from kneeseat_core.table import with_hash, write_table
    table = read_table(built[0])
    converged = np.array(table.converged, dtype=bool)
    codes = np.array(table.status)
    converged[0] = False                          # every tibial cell: left the envelope
    codes[0] = Status.ENVELOPE
    meta = dict(table.metadata, cells=dict(table.metadata['cells'], status=codes.tolist()))
    path = tmp_path / 'failed_tibia.npz'
    write_table(path, with_hash(replace(table, converged=converged, metadata=meta)))
    capsys.readouterr()
    assert main(['verify', str(path), '--sample', '6', '--workers', '1', '--quiet',
                 '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['not_converged'] == 12 and report['not_at_rest'] == 0
    assert report['cells'] and {c['body'] for c in report['cells']} == {'patella'}
    assert all(c['converged'] for c in report['cells'])


def test_verify_changed_from_judges_the_cells_that_moved(built: tuple[Path, Path],
                                                         tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """`--changed-from OLD` judges the cells whose pose differs from OLD's by more than the
    resolution: none against the table itself; exactly the one cell slid 3 mm across the
    push off its rest, which the referee finds gains (a pose lifted along the push would
    not: it drops back to the same rest); a table of another grid is refused in one
    line."""
    from dataclasses import replace

    from kneeseat_core.knee import config_from_metadata
    from kneeseat_core.table import with_hash, write_table
    table = read_table(built[0])
    assert main(['verify', str(built[0]), '--changed-from', str(built[0]), '--workers', '1',
                 '--quiet', '--no-extent', '--json']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['changed'] == 0 and report['cells'] == []
    b = 0
    i, j = (int(k) for k in np.argwhere(np.asarray(table.converged)[b])[0])
    config = config_from_metadata(table.metadata)
    push = np.asarray(config.params(config.bodies[b], float(table.flexion_rad[i]),
                                    float(table.varus_rad[j])).push, dtype=float)
    across = np.cross(push, [0.0, 0.0, 1.0])
    position = np.array(table.position_m)
    position[b, i, j] += 3e-3 * across / np.linalg.norm(across)
    slid = tmp_path / 'slid.npz'
    write_table(slid, with_hash(replace(table, position_m=position)))
    assert main(['verify', str(slid), '--changed-from', str(built[0]), '--workers', '1',
                 '--quiet', '--no-extent', '--json']) == 3
    report = json.loads(capsys.readouterr().out)
    assert report['changed'] == 1 and report['not_at_rest'] == 1
    (cell,) = report['cells']
    assert (cell['body'], cell['flexion_deg'], cell['varus_deg']) == (
        table.bodies[b], float(np.degrees(table.flexion_rad[i])),
        float(np.degrees(table.varus_rad[j])))
    assert cell['gain_m'] > 1.5e-3
    other = tmp_path / 'other_grid.npz'
    write_table(other, with_hash(replace(table, flexion_rad=np.array(table.flexion_rad) + 0.01)))
    assert main(['verify', str(slid), '--changed-from', str(other), '--quiet']) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and 'Traceback' not in captured.err, captured.err
    assert f'--changed-from {other}: ' in lines[0] and 'same config and grid' in lines[0]


def test_verify_says_where_the_meshes_went(built: tuple[Path, Path], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['verify', str(built[0]), '--mesh-dir', str(tmp_path), '--quiet']) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and 'Traceback' not in captured.err, captured.err
    assert "femur.stl: the table's mesh is not there; pass --mesh-dir DIR" in lines[0]


def test_one_grid_override_keeps_the_other_axis_of_the_config(tmp_path: Path) -> None:
    """`--flexion-grid` alone: the varus grid is the config's, bit for bit (it used to be
    rebuilt from degrees, one unit in the last place off), and the settle section stays."""
    from kneeseat_core.knee import load_config
    config = materialise_default_knee(tmp_path)
    base = load_config(config)
    only_flexion = load_config(config, overrides={'grid': {'flexion_deg': [0.0, -90.0, 30.0]}})
    assert np.array_equal(only_flexion.varus_rad, base.varus_rad)
    assert np.allclose(np.degrees(only_flexion.flexion_rad), [-90.0, -60.0, -30.0, 0.0])
    config.write_text(config.read_text().replace('max_iterations: 500', 'max_iterations: 321'))
    patent = load_config(config, overrides={'settle': {'method': 'patent'}})
    assert patent.settle.method == 'patent' and patent.settle.max_iterations == 321


@pytest.mark.parametrize('command', ['build', 'verify'])
@pytest.mark.parametrize('workers,needle', [
    ('0', 'give 1 to'), ('-2', 'give 1 to'), ('two', 'not a whole number'),
    ('100000', 'per core'),
])
def test_a_worker_count_that_cannot_be_is_refused_before_anything_starts(
        built: tuple[Path, Path], tmp_path: Path, command: str, workers: str, needle: str,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'out.npz'
    argv = (['build', '--out', str(out), '--quiet', *GRID] if command == 'build'
            else ['verify', str(built[0]), '--quiet'])
    assert main([*argv, '--workers', workers]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and 'Traceback' not in captured.err, captured.err
    assert 'argument --workers: ' in lines[0] and needle in lines[0], lines[0]
    assert captured.out == '' and not any(tmp_path.iterdir())     # nothing built or written


@pytest.mark.parametrize('options,needle', [
    (['--sample', '0'], '--sample 0: give a positive number of cells'),
    (['--sample', '5', '--seed', '-1'], '--seed -1: give a seed of 0 or more'),
    (['--changed-from', 'SELF', '--changed-deg', 'nan'], '--changed-deg nan: give an angle'),
])
def test_verify_refuses_bad_options_in_one_line(built: tuple[Path, Path], options: list[str],
                                                needle: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    options = [str(built[0]) if o == 'SELF' else o for o in options]
    assert main(['verify', str(built[0]), '--quiet', *options]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and 'Traceback' not in captured.err, captured.err
    assert needle in lines[0], lines[0]


@pytest.mark.parametrize('command', ['build', 'synth'])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(
        tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / 'a_file'
    blocker.write_text('not a directory')
    if command == 'build':
        argv = ['build', '--out', str(blocker / 'knee.npz'), '--quiet', *GRID]
        needle = f'--out {blocker / "knee.npz"}: cannot write a table there ({blocker} is not'
    else:
        argv = ['synth', '--out', str(blocker)]
        needle = f'--out {blocker}: cannot write the default knee there (it is a file)'
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and 'Traceback' not in captured.err, captured.err
    assert needle in lines[0], lines[0]
    assert captured.out == '' and blocker.read_text() == 'not a directory'
    assert [p.name for p in tmp_path.iterdir()] == ['a_file']


def test_build_refuses_a_directory_for_the_table_before_the_sweep(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['build', '--out', str(tmp_path), '--quiet', *GRID]) == 2
    err = capsys.readouterr().err
    assert f'--out {tmp_path}: cannot write a table there (it is a directory)' in err, err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize('setting,needle', [
    ('max_iterations: 12.5', 'settle.max_iterations must be a whole number, got 12.5'),
    ('max_iterations: 1e3x', "settle.max_iterations must be a whole number, got '1e3x'"),
    ('max_iterations: true', 'settle.max_iterations must be a whole number, got True'),
    ('max_iterations: [5]', 'settle.max_iterations must be a whole number, got [5]'),
    ('max_iterations: 40.0', None),
])
def test_a_settle_setting_that_is_not_a_number_is_named(tmp_path: Path, setting: str,
                                                        needle: str | None) -> None:
    from kneeseat_core.knee import load_config
    config = materialise_default_knee(tmp_path)
    config.write_text(config.read_text().replace('max_iterations: 500', setting))
    if needle is None:
        assert load_config(config).settle.max_iterations == 40
        return
    with pytest.raises(ConfigError, match=re.escape(needle)):
        load_config(config)
