"""Table file (write/read/verify), interpolation, describe, JSON and CSV export.

Synthetic tables are built directly from arrays with seeded rngs; files are real (`tmp_path`).
"""
from __future__ import annotations

import csv
import hashlib
import json
import math
from pathlib import Path
import struct
import subprocess
import sys
import textwrap
from typing import Any
import zipfile

import numpy as np
import pytest

from conftest import synthetic_table, TKA_AXES
from kneeseat_core.errors import (ConfigError, KneeseatError, MeshError, NonFiniteError,
                                  OutOfRangeError, TableError)
from kneeseat_core.geometry import KneeAxes, matrix_from_quat, quat_from_matrix, rotation_angle
from kneeseat_core.files import file_sha256
from kneeseat_core.status import converged_share
from kneeseat_core.table import (arrays_sha256, PoseTable, read_table, SCHEMA, with_hash,
                                 write_table)
from kneeseat_core.table.summary import CSV_COLUMNS, describe, export_csv, lookup_json

# the synthetic tables' axes (TKA knee frame): flexion about Z, varus about X, long Y
KNEE = KneeAxes.from_vectors(TKA_AXES['flexion'], TKA_AXES['varus'], TKA_AXES['long'])


def _rotation(body: int, f: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth long-axis rotation (rad) of `body` over the grid (screw-home-like)."""
    return 0.15 * np.sin(1.3 * f + body) + 0.4 * v * (body + 1)


def _position(body: int, f: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth position (m) of `body` over the grid, shape f.shape + (3,)."""
    return np.stack([0.01 * np.sin(f) + 0.002 * body, -0.02 * np.cos(f) + 0.01 * v,
                     0.004 * f * v - 0.001 * body], axis=-1)


BODIES = [{'name': n, 'frame': n + '_link', 'mesh': n + '.stl', 'mesh_sha256': f'{k + 1}' * 64}
          for k, n in enumerate(['tibial_insert', 'patellar_button', 'fibula', 'extra'])]
PROVENANCE = {
    'config': {'name': 'synthetic', 'grid_deg': [1.0, 1.0]},
    'settle': {'step_m': 1e-3, 'resolution_m': 1e-4, 'method': 'default'},
    'built': '2026-01-01T00:00:00+00:00',
    'summary': {'cells': 0, 'converged': 0, 'wall_s': 1.5, 'collision_checks': 1234},
}


def smooth_poses(f: np.ndarray, v: np.ndarray, nbodies: int) -> tuple[np.ndarray, np.ndarray]:
    """Body b at (f, v): KNEE.orientation(f, v, _rotation(b, f, v)), at _position(b, f, v)."""
    rot = np.stack([KNEE.orientation(f.ravel(), v.ravel(), _rotation(b, f, v).ravel())
                    for b in range(nbodies)]).reshape(nbodies, *f.shape, 3, 3)
    return rot, np.stack([_position(b, f, v) for b in range(nbodies)])


def make_table(flexion: np.ndarray, varus: np.ndarray, nbodies: int = 2, seed: int = 7,
               flip: bool = False) -> PoseTable:
    """A smooth synthetic table (conftest's builder), every cell converged; `flip` negates
    a seeded random half of the quaternions."""
    table = synthetic_table(
        seed, BODIES[:nbodies], flexion_rad=flexion, varus_rad=varus,
        poses=lambda f, v, rng: smooth_poses(f, v, nbodies), nonconverged=(),
        reference={'name': 'femoral_component', 'frame': 'femur', 'mesh': 'femur.stl',
                   'mesh_sha256': '0' * 64},
        meta={**PROVENANCE, 'summary': {**PROVENANCE['summary'],
                                        'cells': nbodies * flexion.size * varus.size,
                                        'converged': nbodies * flexion.size * varus.size}})
    if not flip:
        return table
    quat = table.orientation_xyzw
    mask = np.random.default_rng(seed + 1).random(quat.shape[:-1])[..., None] < 0.5
    return PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                     np.where(mask, -quat, quat), table.converged, table.iterations,
                     table.metadata)


def nonuniform(lo_deg: float, hi_deg: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Strictly ascending grid (rad) from lo to hi with random spacing."""
    steps = rng.uniform(0.5, 1.5, size=n - 1)
    deg = lo_deg + (hi_deg - lo_deg) * np.concatenate([[0.0], np.cumsum(steps)]) / steps.sum()
    return np.radians(deg)


@pytest.fixture
def table() -> PoseTable:
    rng = np.random.default_rng(11)
    return make_table(nonuniform(-90, 0, 19, rng), nonuniform(-10, 10, 7, rng), seed=11)


@pytest.fixture
def table_file(tmp_path: Path, table: PoseTable) -> Path:
    path = tmp_path / 'knee.npz'
    write_table(path, table)
    return path


def same_rotation(q1: np.ndarray, q2: np.ndarray) -> float:
    """Largest rotation angle (rad) between corresponding quaternions (..., 4)."""
    dots = np.abs(np.sum(np.asarray(q1) * np.asarray(q2), axis=-1))
    return float(np.max(2.0 * np.arccos(np.clip(dots, -1.0, 1.0))))


def repack(src: Path, dst: Path, **changes: Any) -> Path:
    """Rewrite an .npz (a valid zip) with arrays replaced (or dropped, with None)."""
    with np.load(src, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    np.savez(dst, **arrays)
    return dst


def stored_meta(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as npz:
        return json.loads(str(npz['metadata'][()]))


def flip_byte_in_member(path: Path, member: str, from_end: int = 3) -> None:
    """Flip one bit of a byte inside `member`'s stored payload (near its end)."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member)
    assert info.compress_type == zipfile.ZIP_STORED
    raw = bytearray(path.read_bytes())
    head = info.header_offset
    name_len, extra_len = struct.unpack('<HH', raw[head + 26:head + 30])
    start = info.header_offset + 30 + name_len + extra_len
    raw[start + info.compress_size - from_end] ^= 0x01
    path.write_bytes(bytes(raw))


def leftovers(directory: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name not in keep)


# ------------------------------------------------------------------------- round trip

def test_round_trip_is_exact(table: PoseTable, table_file: Path) -> None:
    loaded = read_table(table_file)
    pairs = [(table.flexion_rad, loaded.flexion_rad), (table.varus_rad, loaded.varus_rad),
             (table.position_m, loaded.position_m),
             (table.orientation_xyzw, loaded.orientation_xyzw),
             (table.converged, loaded.converged), (table.iterations, loaded.iterations)]
    for want, got in pairs:
        assert np.asarray(want).tobytes() == got.tobytes()
        assert np.asarray(want).shape == got.shape
    assert loaded.converged.dtype == np.bool_ and loaded.iterations.dtype == np.int64
    expected = json.loads(json.dumps(with_hash(table).metadata))
    assert loaded.metadata == expected
    assert loaded.metadata['schema'] == SCHEMA
    assert loaded.sha256 == arrays_sha256(loaded) == arrays_sha256(table)
    assert table.metadata.get('arrays_sha256') != loaded.sha256   # the caller's is untouched
    assert loaded.bodies == ('tibial_insert', 'patellar_button')
    assert loaded.body_frames == ('tibial_insert_link', 'patellar_button_link')
    assert loaded.reference_frame == 'femur'
    assert not loaded.position_m.flags.writeable


def test_hash_covers_every_array_and_value(table: PoseTable) -> None:
    base = arrays_sha256(table)
    pos = table.position_m.copy()
    pos[1, 3, 2, 0] = np.nextafter(pos[1, 3, 2, 0], 1.0)     # one ulp
    conv = table.converged.copy()
    conv[0, 0, 0] = False
    for changed in (PoseTable(table.flexion_rad, table.varus_rad, pos, table.orientation_xyzw,
                              table.converged, table.iterations, table.metadata),
                    PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                              table.orientation_xyzw, conv, table.iterations, table.metadata)):
        assert arrays_sha256(changed) != base
    # dtype width does not matter, values do: int32 iterations hash like int64
    same = PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                     table.orientation_xyzw, table.converged,
                     table.iterations.astype(np.int32), table.metadata)
    assert arrays_sha256(same) == base


def test_file_sha256_streams_whole_file(tmp_path: Path) -> None:
    data = np.random.default_rng(3).bytes(2 * (1 << 20) + 12345)
    path = tmp_path / 'blob.bin'
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()


def test_core_does_not_import_ros() -> None:
    code = 'import sys, kneeseat_core.table.pose_table; print("rclpy" in sys.modules)'
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == 'False'


# ---------------------------------------------------------------------- interpolation

def test_grid_nodes_interpolate_exactly(table: PoseTable) -> None:
    for i, f in enumerate(table.flexion_rad):
        for j, v in enumerate(table.varus_rad):
            got = table.interpolate(f, v)
            np.testing.assert_array_equal(got.position_m, table.position_m[:, i, j])
            want = table.orientation_xyzw[:, i, j] * np.where(
                table.orientation_xyzw[:, i, j, 3:] < 0, -1.0, 1.0)
            np.testing.assert_array_equal(got.orientation_xyzw, want)   # bit for bit
            assert not got.clamped and not got.nonconverged.any()


def test_between_nodes_rotations_are_proper(table: PoseTable) -> None:
    rng = np.random.default_rng(5)
    for f, v in zip(rng.uniform(-math.pi / 2, 0, 300), rng.uniform(-0.17, 0.17, 300)):
        got = table.interpolate(f, v)
        assert got.position_m.shape == (2, 3) and got.orientation_xyzw.shape == (2, 4)
        np.testing.assert_allclose(np.linalg.norm(got.orientation_xyzw, axis=1), 1.0,
                                   atol=1e-12)
        assert (got.orientation_xyzw[:, 3] >= 0).all()
        rot = matrix_from_quat(got.orientation_xyzw)
        np.testing.assert_allclose(rot.transpose(0, 2, 1) @ rot, np.broadcast_to(np.eye(3),
                                   (2, 3, 3)), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_positions_are_bilinear_on_a_nonuniform_grid() -> None:
    rng = np.random.default_rng(21)
    fx, vx = nonuniform(-90, 0, 13, rng), nonuniform(-10, 10, 5, rng)
    base = make_table(fx, vx, nbodies=1)
    coef = rng.normal(size=(4, 3))

    def exact(f: float, v: float) -> np.ndarray:   # bilinear reproduces f*v terms exactly
        return coef[0] + coef[1] * f + coef[2] * v + coef[3] * f * v

    ff, vv = np.meshgrid(fx, vx, indexing='ij')
    pos = exact(ff[..., None], vv[..., None])[None]
    tab = PoseTable(fx, vx, pos, base.orientation_xyzw, base.converged, base.iterations,
                    base.metadata)
    for f, v in zip(rng.uniform(fx[0], fx[-1], 200), rng.uniform(vx[0], vx[-1], 200)):
        np.testing.assert_allclose(tab.interpolate(f, v).position_m[0], exact(f, v),
                                   rtol=0, atol=1e-12)


def test_orientation_follows_the_rotation_between_nodes() -> None:
    """One axis, angle linear in flexion: the normalised blend stays within nlerp error."""
    fx = np.radians(np.arange(-90.0, 0.5, 1.0))
    base = make_table(fx, np.array([0.0]), nbodies=1)
    quat = quat_from_matrix(KNEE.orientation(fx, 0.0))[None, :, None, :]
    tab = PoseTable(fx, base.varus_rad, base.position_m, quat, base.converged,
                    base.iterations, base.metadata)
    for f in np.linspace(fx[0], fx[-1], 997):
        got = matrix_from_quat(tab.interpolate(f, 0.0).orientation_xyzw[0])
        assert rotation_angle(got, KNEE.orientation(f, 0.0)) < 2e-6   # 1 deg cells: ~3e-7


def test_q_and_minus_q_give_the_same_answer() -> None:
    rng = np.random.default_rng(9)
    fx, vx = nonuniform(-90, 0, 11, rng), nonuniform(-10, 10, 5, rng)
    plain, flipped = make_table(fx, vx), make_table(fx, vx, flip=True)
    assert (np.sign(plain.orientation_xyzw) != np.sign(flipped.orientation_xyzw)).any()
    for f, v in zip(rng.uniform(fx[0], fx[-1], 300), rng.uniform(vx[0], vx[-1], 300)):
        a, b = plain.interpolate(f, v), flipped.interpolate(f, v)
        np.testing.assert_allclose(a.orientation_xyzw, b.orientation_xyzw, atol=1e-12)
        np.testing.assert_array_equal(a.position_m, b.position_m)


def test_small_angle_steps_give_small_pose_steps(table: PoseTable) -> None:
    """Continuity, across cell edges and nodes too: steps bounded by the grid's own rates."""
    fx, vx = table.flexion_rad, table.varus_rad
    rot = matrix_from_quat(table.orientation_xyzw)
    rate_rot = max(rotation_angle(rot[b, i, j], rot[b, i + 1, j]) / (fx[i + 1] - fx[i])
                   for b in range(2) for i in range(fx.size - 1) for j in range(vx.size))
    rate_pos = float(np.max(np.linalg.norm(np.diff(table.position_m, axis=1), axis=-1)
                            / np.diff(fx)[None, :, None]))
    h = 1e-4
    fs = np.arange(fx[0], fx[-1], h)
    v = 0.5 * (vx[2] + vx[3])
    prev = table.interpolate(fs[0], v)
    for f in fs[1:]:
        cur = table.interpolate(f, v)
        step_rot = same_rotation(cur.orientation_xyzw, prev.orientation_xyzw)
        step_pos = float(np.max(np.linalg.norm(cur.position_m - prev.position_m, axis=1)))
        assert step_rot <= 1.5 * rate_rot * h + 1e-7
        assert step_pos <= 1.5 * rate_pos * h + 1e-12
        prev = cur


def test_clamp_flags_and_returns_the_edge(table: PoseTable) -> None:
    fx, vx = table.flexion_rad, table.varus_rad
    inside = table.interpolate(fx[-1], vx[0])                   # on the edge: not clamped
    assert not inside.clamped
    for f, v in ((fx[-1] + 0.3, vx[0]), (fx[-1], vx[0] - 0.05), (fx[-1] + 1.0, vx[0] - 1.0)):
        out = table.interpolate(f, v)
        assert out.clamped
        np.testing.assert_array_equal(out.position_m, inside.position_m)
        np.testing.assert_array_equal(out.orientation_xyzw, inside.orientation_xyzw)
    mid = table.interpolate(fx[0] - 2.0, 0.5 * (vx[1] + vx[2]))
    assert mid.clamped
    np.testing.assert_array_equal(mid.position_m,
                                  table.interpolate(fx[0], 0.5 * (vx[1] + vx[2])).position_m)


def test_drop_raises_out_of_range(table: PoseTable) -> None:
    fx, vx = table.flexion_rad, table.varus_rad
    with pytest.raises(OutOfRangeError, match=r'^flexion=0\.1000 rad outside table '
                                              r'\[-1\.5708, 0\.0000\] rad; re-run'):
        table.interpolate(0.1, 0.0, 'drop')
    with pytest.raises(OutOfRangeError, match=r'^varus=-0\.2000 rad outside table'):
        table.interpolate(-0.5, -0.2, out_of_range='drop')
    assert not table.interpolate(fx[0], vx[-1], 'drop').clamped     # edges are inside
    with pytest.raises(ConfigError, match="out_of_range='wrap'.*use 'clamp' or 'drop'"):
        table.interpolate(-0.5, 0.0, 'wrap')  # type: ignore[arg-type]


@pytest.mark.parametrize('mode', ['clamp', 'drop'])
@pytest.mark.parametrize('f, v', [(math.nan, 0.0), (-0.5, math.inf), (-math.inf, 0.0)])
def test_non_finite_angles_raise_their_own_error(table: PoseTable, mode: str, f: float,
                                                 v: float) -> None:
    with pytest.raises(NonFiniteError, match='must be finite') as info:
        table.interpolate(f, v, mode)  # type: ignore[arg-type]
    assert isinstance(info.value, KneeseatError)
    assert not isinstance(info.value, (OutOfRangeError, TableError, ConfigError))


def test_nonconverged_cells_are_flagged_only_where_they_weigh() -> None:
    fx, vx = np.radians([-30.0, -20.0, -10.0, 0.0]), np.radians([-5.0, 0.0, 5.0])
    base = make_table(fx, vx)
    conv = base.converged.copy()
    conv[0, 1, 1] = False                                     # body 0, node (-20, 0) deg
    tab = PoseTable(fx, vx, base.position_m, base.orientation_xyzw, conv, base.iterations,
                    base.metadata)
    d = math.radians

    def flags(f_deg: float, v_deg: float) -> list[bool]:
        return tab.interpolate(d(f_deg), d(v_deg)).nonconverged.tolist()

    assert flags(-20, 0) == [True, False]            # at the node itself
    assert flags(-25, -2.5) == [True, False]         # any of the four cells around it
    assert flags(-15, 2.5) == [True, False]
    assert flags(-20, 2.5) == [True, False]          # on an edge through it
    assert flags(-10, 0) == [False, False]           # next node: its weight is zero
    assert flags(-20, 5) == [False, False]
    assert flags(-15, 5) == [False, False]           # edge not touching it
    assert flags(-5, -2.5) == [False, False]         # far cell
    assert tab.interpolate(d(-20), d(0)).nonconverged.dtype == np.bool_


def test_single_row_single_column_and_single_point_tables() -> None:
    fx = np.radians(np.arange(-90.0, 1.0, 10.0))
    row = make_table(np.array([-0.3]), np.radians([-10.0, 0.0, 10.0]))
    col = make_table(fx, np.array([0.0]))
    point = make_table(np.array([-0.3]), np.array([0.0]))
    got = row.interpolate(-0.3, math.radians(5.0))
    assert not got.clamped
    np.testing.assert_allclose(got.position_m,
                               0.5 * (row.position_m[:, 0, 1] + row.position_m[:, 0, 2]))
    assert row.interpolate(-0.2, 0.0).clamped
    with pytest.raises(OutOfRangeError, match='flexion'):
        row.interpolate(-0.2, 0.0, 'drop')
    got = col.interpolate(math.radians(-45.0), 0.0)
    np.testing.assert_allclose(got.position_m,
                               0.5 * (col.position_m[:, 4, 0] + col.position_m[:, 5, 0]))
    assert not got.clamped
    np.testing.assert_array_equal(col.interpolate(fx[-1], 0.0).position_m,
                                  col.position_m[:, -1, 0])
    with pytest.raises(OutOfRangeError, match='varus'):
        col.interpolate(-0.5, 0.01, 'drop')
    exact = point.interpolate(-0.3, 0.0)
    assert not exact.clamped
    np.testing.assert_array_equal(exact.position_m, point.position_m[:, 0, 0])
    assert point.interpolate(1.0, -1.0).clamped


def test_output_quaternions_have_non_negative_w() -> None:
    fx, vx = np.radians([-90.0, 0.0]), np.radians([-10.0, 10.0])
    base = make_table(fx, vx, nbodies=1)
    tab = PoseTable(fx, vx, base.position_m, -base.orientation_xyzw, base.converged,
                    base.iterations, base.metadata)
    assert (tab.orientation_xyzw[..., 3] < 0).all()
    for f in np.linspace(fx[0], fx[1], 7):
        assert tab.interpolate(f, 0.0).orientation_xyzw[0, 3] >= 0.0


# ------------------------------------------------------------------ rejected table files

def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TableError, match=r'table file .*nope\.npz not found; check the path'):
        read_table(tmp_path / 'nope.npz')
    with pytest.raises(TableError, match='not a regular file'):
        read_table(tmp_path)


def test_flipped_byte_in_an_array_payload(table_file: Path) -> None:
    flip_byte_in_member(table_file, 'position.npy')
    with pytest.raises(TableError, match=r"knee\.npz is corrupt \(array 'position'.*CRC.*"
                                         r'rebuild it with `kneeseat build`'):
        read_table(table_file)


def test_flipped_byte_in_the_metadata(table_file: Path) -> None:
    flip_byte_in_member(table_file, 'metadata.npy', from_end=4)
    with pytest.raises(TableError, match=r"is corrupt \(array 'metadata'.*rebuild it"):
        read_table(table_file)


def test_modified_array_with_a_valid_zip_fails_the_hash(table_file: Path, tmp_path: Path) -> None:
    with np.load(table_file) as npz:
        pos = npz['position'].copy()
    pos[0, 4, 2, 1] += 1e-9
    bad = repack(table_file, tmp_path / 'edited.npz', position=pos)
    with pytest.raises(TableError, match=r'edited\.npz: arrays do not match their SHA-256 '
                                         r'.*corrupt or modified; rebuild it'):
        read_table(bad)


def test_truncated_and_foreign_files(table_file: Path, tmp_path: Path) -> None:
    raw = table_file.read_bytes()
    for name, data in (('half.npz', raw[:len(raw) // 2]), ('tail.npz', raw[:-10]),
                       ('empty.npz', b''), ('text.npz', b'flexion,varus\n0,0\n')):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(TableError, match=rf'{name} is not a readable table \(\.npz\).*'
                                             'truncated, corrupt') as err:
            read_table(tmp_path / name)
        # numpy's own words for a file it takes for a pickle advise unpickling it
        assert 'pickle' not in str(err.value), str(err.value)
    np.save(tmp_path / 'one.npy', np.zeros(3))
    with pytest.raises(TableError, match='holds a single array, not a table'):
        read_table(tmp_path / 'one.npy')


def test_metadata_not_json(table_file: Path, tmp_path: Path) -> None:
    bad = repack(table_file, tmp_path / 'bad.npz', metadata=np.array('{"schema": '))
    with pytest.raises(TableError, match=r'bad\.npz: metadata is not valid JSON'):
        read_table(bad)
    bad = repack(table_file, tmp_path / 'bad2.npz', metadata=np.arange(3))
    with pytest.raises(TableError, match='expected a JSON string'):
        read_table(bad)


def test_unknown_schema_version_names_the_supported_one(table_file: Path,
                                                        tmp_path: Path) -> None:
    meta = stored_meta(table_file)
    meta['schema'] = 'kneeseat.table/2'
    bad = repack(table_file, tmp_path / 'v2.npz', metadata=np.array(json.dumps(meta)))
    with pytest.raises(TableError, match=r"unknown table schema 'kneeseat\.table/2'; this "
                                         r'kneeseat reads kneeseat\.table/1; rebuild'):
        read_table(bad)
    del meta['schema']
    bad = repack(table_file, tmp_path / 'none.npz', metadata=np.array(json.dumps(meta)))
    with pytest.raises(TableError, match='unknown table schema None'):
        read_table(bad)


def test_missing_unexpected_and_misshapen_arrays(table_file: Path, tmp_path: Path) -> None:
    with pytest.raises(TableError, match='arrays missing iterations; not a kneeseat.table/1'):
        read_table(repack(table_file, tmp_path / 'a.npz', iterations=None))
    with pytest.raises(TableError, match='arrays unexpected extra'):
        read_table(repack(table_file, tmp_path / 'b.npz', extra=np.zeros(2)))
    with np.load(table_file) as npz:
        pos, vx = npz['position'], npz['varus']
    with pytest.raises(TableError, match=r"array 'position' has dtype float32, expected "
                                         'float64'):
        read_table(repack(table_file, tmp_path / 'c.npz', position=pos.astype(np.float32)))
    with pytest.raises(TableError, match=r"array 'position' has shape \(2, 19, 8, 3\), "
                                         r'expected \(2, 19, 7, 3\)'):
        read_table(repack(table_file, tmp_path / 'd.npz',
                          position=np.concatenate([pos, pos[:, :, :1]], axis=2)))
    with pytest.raises(TableError, match=r"array 'position' has shape \(2, 19, 7, 3\), "
                                         r'expected \(2, 19, 8, 3\)'):
        read_table(repack(table_file, tmp_path / 'e.npz', varus=np.append(vx, 1.0)))
    meta = stored_meta(table_file)
    meta['bodies'] = meta['bodies'][:1]
    with pytest.raises(TableError, match=r"array 'position' has shape \(2, .*metadata lists "
                                         '1 bodies'):
        read_table(repack(table_file, tmp_path / 'f.npz', metadata=np.array(json.dumps(meta))))


def _rehashed(table: PoseTable, **arrays: np.ndarray) -> PoseTable:
    """`table` with arrays replaced and a matching hash (as a buggy writer would produce)."""
    fields = {'flexion_rad': table.flexion_rad, 'varus_rad': table.varus_rad,
              'position_m': table.position_m, 'orientation_xyzw': table.orientation_xyzw,
              'converged': table.converged, 'iterations': table.iterations}
    fields.update(arrays)
    bad = PoseTable(metadata=dict(table.metadata), **fields)
    bad.metadata['arrays_sha256'] = arrays_sha256(bad)
    return bad


@pytest.mark.parametrize('change, message', [
    ({'varus_rad': 'reverse'}, r"grid 'varus' is not strictly ascending \(index 0"),
    ({'flexion_rad': 'repeat'}, "grid 'flexion' is not strictly ascending"),
    ({'position_m': 'nan'}, r"array 'position' holds 1 non-finite value\(s\) \(first at "
                            r'index \[1, 2, 3, 0\]\)'),
    ({'orientation_xyzw': 'scale'}, r'orientation of body 0 at flexion .* is not a unit '
                                    r'quaternion'),
])
def test_invalid_contents_rejected_on_write_and_on_read(table: PoseTable, tmp_path: Path,
                                                        change: dict[str, str],
                                                        message: str) -> None:
    (key, how), = change.items()
    value = np.array(getattr(table, key), dtype=float)
    if how == 'reverse':
        value = value[::-1].copy()
    elif how == 'repeat':
        value[3] = value[2]
    elif how == 'nan':
        value[1, 2, 3, 0] = np.nan
    else:
        value[0, 5, 1] *= 1.01
    bad = _rehashed(with_hash(table), **{key: value})
    with pytest.raises(TableError, match='cannot write table: ' + message):
        write_table(tmp_path / 'w.npz', bad)
    with pytest.raises(TableError, match='cannot interpolate pose table: ' + message):
        bad.interpolate(-0.5, 0.0)
    assert leftovers(tmp_path, set()) == []
    path = tmp_path / 'r.npz'
    arrays = {'flexion': bad.flexion_rad, 'varus': bad.varus_rad, 'position': bad.position_m,
              'orientation': bad.orientation_xyzw, 'converged': bad.converged,
              'iterations': bad.iterations, 'metadata': np.array(json.dumps(bad.metadata))}
    np.savez(path, **arrays)
    with pytest.raises(TableError, match=r'r\.npz: ' + message + '.*rebuild it'):
        read_table(path)


def test_bad_metadata_structure(table_file: Path, tmp_path: Path) -> None:
    meta = stored_meta(table_file)
    for edit, message in ((lambda m: m.pop('axes'), 'metadata lacks axes'),
                          (lambda m: m['bodies'][0].pop('frame'), 'must be a non-empty list'),
                          (lambda m: m['axes'].update(long=[0.0, 0.0, 1.0]),
                           'not orthogonal'),
                          (lambda m: m['bodies'][1].update(name='tibial_insert'),
                           'repeats a name')):
        m = json.loads(json.dumps(meta))
        edit(m)
        bad = repack(table_file, tmp_path / 'm.npz', metadata=np.array(json.dumps(m)))
        with pytest.raises(TableError, match=message):
            read_table(bad)


def test_mesh_hashes_are_checked(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    files = {}
    for name in ('femoral_component', 'tibial_insert', 'patellar_button', 'other'):
        files[name] = tmp_path / f'{name}.stl'
        files[name].write_bytes(b'solid ' + rng.bytes(300))
    table = make_table(np.radians([-10.0, 0.0]), np.radians([-5.0, 5.0]))
    meta = dict(table.metadata)
    meta['reference'] = dict(meta['reference'], mesh_sha256=file_sha256(
        files['femoral_component']))
    meta['bodies'] = [dict(b, mesh_sha256=file_sha256(files[b['name']]))
                      for b in meta['bodies']]
    path = tmp_path / 'meshes.npz'
    write_table(path, PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                                table.orientation_xyzw, table.converged, table.iterations,
                                meta))
    good = {n: files[n] for n in ('femoral_component', 'tibial_insert', 'patellar_button')}
    assert read_table(path, meshes=good).bodies == ('tibial_insert', 'patellar_button')
    with pytest.raises(TableError, match=r'meshes\.npz was built from other meshes: '
                                         r"'tibial_insert' mesh .*other\.stl has SHA-256 "
                                         r'[0-9a-f]{12}, the table expects [0-9a-f]{12}.*'
                                         'rebuild the table from these meshes'):
        read_table(path, meshes={'tibial_insert': files['other']})
    with pytest.raises(TableError, match="built from other meshes: 'femoral_component'"):
        read_table(path, meshes={'femoral_component': files['patellar_button']})
    with pytest.raises(TableError, match=r"has no body named 'fibula' \(bodies: "
                                         'tibial_insert, patellar_button, femoral_component'):
        read_table(path, meshes={'fibula': files['other']})
    with pytest.raises(MeshError, match=r'mesh file .*gone\.stl .*cannot be read'):
        read_table(path, meshes={'tibial_insert': tmp_path / 'gone.stl'})
    meta['bodies'][1]['mesh_sha256'] = ''
    write_table(path, PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                                table.orientation_xyzw, table.converged, table.iterations,
                                meta))
    with pytest.raises(TableError, match="records no SHA-256 for the mesh of 'patellar_button'"):
        read_table(path, meshes=good)


# ------------------------------------------------------------------------ atomic writes

def test_failed_rename_leaves_nothing_behind(table: PoseTable, tmp_path: Path) -> None:
    target = tmp_path / 'occupied.npz'
    target.mkdir()                                # os.replace onto a directory fails
    with pytest.raises(TableError, match=r'cannot write table .*occupied\.npz: .*check that'):
        write_table(target, table)
    assert leftovers(tmp_path, set()) == ['occupied.npz'] and target.is_dir()
    assert list(target.iterdir()) == []


def test_failed_write_mid_file_keeps_the_old_table(table: PoseTable, tmp_path: Path) -> None:
    """A real write error (file size limit, EFBIG) half way through the zip."""
    big = make_table(np.radians(np.arange(-90.0, 0.5, 0.5)), np.radians(np.arange(-10, 11.0)))
    write_table(tmp_path / 'big.npz', big)
    out = tmp_path / 'out'
    out.mkdir()
    target = out / 'knee.npz'
    write_table(target, table)
    before = target.read_bytes()
    limit = (tmp_path / 'big.npz').stat().st_size // 2
    assert limit > len(before)
    code = textwrap.dedent(f"""
        import resource, signal
        from pathlib import Path
        from kneeseat_core.errors import TableError
        from kneeseat_core.table.io import read_table, write_table
        big = read_table(Path({str(tmp_path / 'big.npz')!r}))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
        try:
            write_table(Path({str(target)!r}), big)
        except TableError as err:
            print('TableError:', err)
    """)
    run = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith('TableError: cannot write table'), run.stdout
    assert 'large' in run.stdout                   # 'File too large' (EFBIG)
    assert leftovers(out, set()) == ['knee.npz']
    assert target.read_bytes() == before
    read_table(target)


def test_unserialisable_metadata_and_missing_directory(table: PoseTable,
                                                       tmp_path: Path) -> None:
    meta = dict(table.metadata, config={'when': object()})
    with pytest.raises(TableError, match='metadata is not JSON .*store only str, numbers'):
        write_table(tmp_path / 'x.npz', PoseTable(
            table.flexion_rad, table.varus_rad, table.position_m, table.orientation_xyzw,
            table.converged, table.iterations, meta))
    with pytest.raises(TableError, match=r'cannot write table .*no_dir.*No such file'):
        write_table(tmp_path / 'no_dir' / 'x.npz', table)
    assert leftovers(tmp_path, set()) == []


def test_numpy_values_in_metadata_are_stored_as_json(table: PoseTable, tmp_path: Path) -> None:
    meta = dict(table.metadata, config={'grid': np.arange(3.0), 'n': np.int64(5),
                                        'mesh': Path('a/b.stl')})
    path = tmp_path / 'np.npz'
    write_table(path, PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                                table.orientation_xyzw, table.converged, table.iterations,
                                meta))
    assert read_table(path).metadata['config'] == {'grid': [0.0, 1.0, 2.0], 'n': 5,
                                                   'mesh': 'a/b.stl'}


# -------------------------------------------------------------------- describe / export

def test_describe_summarises_the_table(tmp_path: Path) -> None:
    fx, vx = np.radians(np.arange(-90.0, 0.5, 1.0)), np.radians(np.arange(-10.0, 10.5, 1.0))
    table = make_table(fx, vx)
    conv = table.converged.copy()
    conv[1, ::2] = False                                      # 46 of 91 rows
    its = np.zeros_like(table.iterations)
    its[0] = 10
    its[0, 0, 0] = 70
    path = tmp_path / 'd.npz'
    write_table(path, PoseTable(fx, vx, table.position_m, table.orientation_xyzw, conv, its,
                                table.metadata))
    text = describe(read_table(path))
    assert 'kneeseat.table/1' in text and '2026-01-01T00:00:00+00:00' in text
    assert 'flexion:    -90 to 0 deg, step 1, 91 values' in text
    assert 'varus:      -10 to 10 deg, step 1, 21 values' in text
    assert 'tibial_insert: frame tibial_insert_link' in text
    assert 'converged 100.0% (1911/1911), iterations median 10 max 70' in text
    assert 'converged 49.4% (945/1911)' in text              # 49.45 %, rounded down
    assert '111111111111' in text and '1111111111111' not in text      # short mesh hash
    assert 'step_m=0.001' in text and 'collision_checks=1234' in text
    assert 'reference:  femoral_component (frame femur' in text
    rng = np.random.default_rng(1)
    assert 'non-uniform steps' in describe(make_table(nonuniform(-90, 0, 9, rng),
                                                      np.array([0.0])))


def test_converged_share_says_100_percent_only_when_every_cell_converged() -> None:
    assert converged_share(3822, 3822) == '100.0%'
    assert converged_share(3821, 3822) == '99.9%'         # 99.97 %: not rounded up to 100.0
    assert converged_share(1, 3822) == '<0.1%' and converged_share(0, 3822) == '0.0%'
    assert converged_share(945, 1911) == '49.4%' and converged_share(0, 0) == '0.0%'


def test_lookup_json(table: PoseTable) -> None:
    hashed = with_hash(table)
    lookup = hashed.interpolate(-0.4, 0.3)
    doc = json.loads(json.dumps(lookup_json(hashed, lookup, -0.4, 0.3)))
    assert doc['reference_frame'] == 'femur' and doc['clamped'] is True
    assert doc['table_sha256'] == hashed.sha256
    assert doc['flexion_rad'] == -0.4 and doc['varus_rad'] == 0.3
    assert [b['name'] for b in doc['bodies']] == ['tibial_insert', 'patellar_button']
    assert doc['bodies'][1]['frame'] == 'patellar_button_link'
    np.testing.assert_array_equal([b['position'] for b in doc['bodies']], lookup.position_m)
    np.testing.assert_array_equal([b['orientation'] for b in doc['bodies']],
                                  lookup.orientation_xyzw)
    assert [b['nonconverged'] for b in doc['bodies']] == [False, False]
    assert 'flexion_rad' not in lookup_json(hashed, lookup)


def test_export_csv_rows_and_patent_fields(tmp_path: Path) -> None:
    fx, vx = np.radians(np.arange(-90.0, 0.5, 15.0)), np.radians([-10.0, 0.0, 10.0])
    table = make_table(fx, vx)
    conv = table.converged.copy()
    conv[1, 2, 0] = False
    table = PoseTable(fx, vx, table.position_m, table.orientation_xyzw, conv,
                      table.iterations, table.metadata)
    path = tmp_path / 'knee.csv'
    export_csv(table, path)
    assert leftovers(tmp_path, set()) == ['knee.csv']
    with open(path, newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS == (
        'body', 'flexion_deg', 'varus_deg', 'x_m', 'y_m', 'z_m', 'flexion_rot_deg',
        'varus_rot_deg', 'long_rot_deg', 'converged', 'iterations')
    assert len(rows) == 2 * fx.size * vx.size
    k = 0
    for b, body in enumerate(table.bodies):
        for i, f in enumerate(fx):
            for j, v in enumerate(vx):
                row = rows[k]
                k += 1
                assert row['body'] == body
                assert float(row['flexion_deg']) == pytest.approx(math.degrees(f), abs=1e-9)
                assert float(row['varus_deg']) == pytest.approx(math.degrees(v), abs=1e-9)
                np.testing.assert_allclose([float(row[c]) for c in ('x_m', 'y_m', 'z_m')],
                                           table.position_m[b, i, j], rtol=1e-11, atol=1e-15)
                # the synthetic orientation is KNEE.orientation(f, v, rotation(b, f, v))
                want = np.degrees([f, v, _rotation(b, np.array(f), np.array(v))])
                got = [float(row[c]) for c in ('flexion_rot_deg', 'varus_rot_deg',
                                               'long_rot_deg')]
                np.testing.assert_allclose(got, want, atol=1e-8)
                assert row['converged'] == ('false' if (b, i, j) == (1, 2, 0) else 'true')
                assert int(row['iterations']) == table.iterations[b, i, j]
    with pytest.raises(TableError, match=r'cannot write CSV .*missing.*No such file'):
        export_csv(table, tmp_path / 'missing' / 'x.csv')
