"""load_mesh / check_mesh: formats, units, and every bad file a user can hand in."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from kneeseat_core.errors import MeshError
from kneeseat_core.meshes import check_mesh, load_mesh

FORMATS = ('stl', 'ply', 'obj', 'off', 'glb')
# a tetrahedron, 10 mm edges along the axes, outward winding (closed, watertight)
TETRA_VERTICES = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=float)
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
PLY_HEADER = ('ply\nformat ascii 1.0\nelement vertex {nv}\nproperty float x\n'
              'property float y\nproperty float z\nelement face {nf}\n'
              'property list uchar int vertex_indices\nend_header\n')


def box_m() -> trimesh.Trimesh:
    """A 40 x 20 x 10 mm box, in metres, off the origin."""
    box = trimesh.creation.box((0.04, 0.02, 0.01))
    box.apply_translation((0.01, -0.02, 0.005))
    return box


def write_tetra_text(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write an OBJ or ASCII PLY by hand (so NaN and degenerate data survive writing)."""
    if path.suffix == '.obj':
        lines = [f'v {x} {y} {z}' for x, y, z in vertices]
        lines += [f'f {a + 1} {b + 1} {c + 1}' for a, b, c in faces]
        path.write_text('\n'.join(lines) + '\n')
    else:
        body = [f'{x} {y} {z}' for x, y, z in vertices] + [f'3 {a} {b} {c}' for a, b, c in faces]
        path.write_text(PLY_HEADER.format(nv=len(vertices), nf=len(faces))
                        + '\n'.join(body) + '\n')
    return path


@pytest.mark.parametrize('fmt', FORMATS)
def test_loads_every_format_in_metres(fmt: str, tmp_path: Path) -> None:
    box = box_m()
    path = tmp_path / f'box.{fmt}'
    box.export(path)
    mesh = load_mesh(path)
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.faces) == 12 and mesh.is_watertight
    np.testing.assert_allclose(mesh.bounds, box.bounds, atol=1e-7)
    assert mesh.volume == pytest.approx(box.volume, rel=1e-5)


@pytest.mark.parametrize('fmt', FORMATS)
def test_millimetres_are_scaled_only_when_declared(fmt: str, tmp_path: Path) -> None:
    box = box_m()
    box.apply_scale(1000.0)
    path = tmp_path / f'box_mm.{fmt}'
    box.export(path)
    mesh = load_mesh(path, units='mm')
    np.testing.assert_allclose(mesh.extents, (0.04, 0.02, 0.01), rtol=1e-6)
    np.testing.assert_allclose(mesh.bounds, box.bounds * 1e-3, atol=1e-7)
    with pytest.raises(MeshError, match=r'not a plausible .* pass --units mm'):
        load_mesh(path)


def test_tiny_mesh_in_declared_mm_is_refused(tmp_path: Path) -> None:
    path = tmp_path / 'box.stl'
    box_m().export(path)           # metres, wrongly declared as millimetres: 40 um across
    with pytest.raises(MeshError, match='check the declared units'):
        load_mesh(path, units='mm')


def test_multi_part_glb_is_concatenated(tmp_path: Path) -> None:
    a, b = box_m(), box_m()
    b.apply_translation((0.05, 0.0, 0.0))
    path = tmp_path / 'two.glb'
    trimesh.Scene([a, b]).export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 24
    assert mesh.volume == pytest.approx(a.volume + b.volume, rel=1e-5)


def test_unknown_units(tmp_path: Path) -> None:
    path = tmp_path / 'box.stl'
    box_m().export(path)
    with pytest.raises(MeshError, match="unknown units 'cm'"):
        load_mesh(path, units='cm')  # type: ignore[arg-type]


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / 'absent.stl'
    with pytest.raises(MeshError, match='no such mesh file') as info:
        load_mesh(path)
    assert str(path) in str(info.value) and '\n' not in str(info.value)


def test_directory_is_not_a_mesh(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match='no such mesh file'):
        load_mesh(tmp_path)


@pytest.mark.parametrize('name,content', [
    ('notes.stl', b'these are not triangles\n' * 4),
    ('random.ply', bytes(range(256)) * 4),
    ('table.obj', b'\x00\x01\x02garbage'),
    ('picture.glb', b'glTF\x02\x00\x00\x00junk'),
])
def test_non_mesh_file(tmp_path: Path, name: str, content: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    message = str(info.value)
    assert str(path) in message and '\n' not in message


@pytest.mark.parametrize('name,content', [
    ('zero.stl', ''),
    ('ascii.stl', 'solid empty\nendsolid empty\n'),
    ('points.obj', 'v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\n'),
    ('none.ply', PLY_HEADER.format(nv=0, nf=0)),
    ('none.off', 'OFF\n0 0 0\n'),
])
def test_empty_mesh_file(tmp_path: Path, name: str, content: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    message = str(info.value)
    assert str(path) in message and '\n' not in message


def test_check_mesh_refuses_empty_and_non_finite() -> None:
    with pytest.raises(MeshError, match='empty'):
        check_mesh(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int)), 'empty')
    vertices = TETRA_VERTICES * 1e-3
    vertices[2, 1] = np.nan
    bad = trimesh.Trimesh(vertices, TETRA_FACES, process=False)
    with pytest.raises(MeshError, match='NaN or infinite'):
        check_mesh(bad, 'bad')


@pytest.mark.parametrize('suffix', ['.obj', '.ply'])
def test_nan_coordinates_in_a_file(tmp_path: Path, suffix: str) -> None:
    vertices = TETRA_VERTICES * 1e-3
    vertices[2, 1] = np.nan
    path = write_tetra_text(tmp_path / f'nan{suffix}', vertices, TETRA_FACES)
    with pytest.raises(MeshError, match='NaN or infinite'):
        load_mesh(path)


@pytest.mark.parametrize('suffix', ['.obj', '.ply'])
def test_hand_written_tetra_loads(tmp_path: Path, suffix: str) -> None:
    path = write_tetra_text(tmp_path / f'tetra{suffix}', TETRA_VERTICES * 1e-3, TETRA_FACES)
    mesh = load_mesh(path)
    assert mesh.is_watertight and len(mesh.faces) == 4
    assert mesh.volume == pytest.approx(1e-6 / 6.0, rel=1e-6)


def test_degenerate_and_duplicate_triangles_are_removed(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    vertices = np.vstack([TETRA_VERTICES, [[5.0, 0.0, 0.0]]]) * 1e-3
    faces = np.vstack([TETRA_FACES,
                       [[0, 1, 4],      # collinear: zero area
                        [1, 1, 2],      # repeated vertex
                        [0, 2, 1]]])    # duplicate of the first face
    path = write_tetra_text(tmp_path / 'dirty.ply', vertices, faces)
    with caplog.at_level(logging.INFO, logger='kneeseat_core.meshes.load'):
        mesh = load_mesh(path)
    assert len(mesh.faces) == 4 and len(mesh.vertices) == 4
    assert mesh.is_watertight
    assert np.all(mesh.area_faces > 0)
    assert any('removed' in r.getMessage() and 'degenerate' in r.getMessage()
               for r in caplog.records)


def test_only_degenerate_triangles_is_an_error() -> None:
    flat = trimesh.Trimesh(np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0]]),
                           np.array([[0, 1, 2]]), process=False)
    with pytest.raises(MeshError, match='degenerate'):
        check_mesh(flat, 'flat')


def test_not_watertight_is_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    box = box_m()
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)
    path = tmp_path / 'open.stl'
    open_box.export(path)
    with caplog.at_level(logging.WARNING, logger='kneeseat_core.meshes.load'):
        mesh = load_mesh(path)
    assert len(mesh.faces) == 11 and not mesh.is_watertight
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and 'not watertight' in warnings[0].getMessage()
    assert str(path) in warnings[0].getMessage()


def test_a_quiet_load_leaves_the_warning_to_the_check(tmp_path: Path,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    """A worker's quiet load (with one worker it runs before the sweep's check) does not
    use up the warning: the check still gives it, once."""
    box = box_m()
    path = tmp_path / 'open_first_quiet.stl'
    trimesh.Trimesh(box.vertices, box.faces[:-1], process=False).export(path)
    with caplog.at_level(logging.WARNING, logger='kneeseat_core.meshes.load'):
        load_mesh(path, quiet=True)
        assert not [r for r in caplog.records if r.levelno == logging.WARNING]
        load_mesh(path)
        load_mesh(path)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and str(path) in warnings[0].getMessage()


def test_watertight_mesh_gives_no_warning(tmp_path: Path,
                                          caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / 'box.stl'
    box_m().export(path)
    with caplog.at_level(logging.WARNING, logger='kneeseat_core.meshes.load'):
        load_mesh(path)
    assert not caplog.records


def test_implausibly_large_mesh_suggests_units_mm(tmp_path: Path) -> None:
    box = trimesh.creation.box((80.0, 40.0, 30.0))   # a 80 mm implant written in mm
    path = tmp_path / 'implant_mm.stl'
    box.export(path)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    message = str(info.value)
    assert '--units mm' in message and str(path) in message and '\n' not in message
    assert load_mesh(path, units='mm').extents.max() == pytest.approx(0.08)


def test_collision_pairs_sharing_bodies_each_answer_for_their_own_placing() -> None:
    """Pairs made in one thread share python-fcl's object per body: a body that is the
    moving one of a pair and the fixed one of another, queried in turn and from two
    threads at once, answers as a pair with its own objects does (an independent box
    overlap: the boxes are aligned)."""
    import threading

    from kneeseat_core.meshes.collision import CollisionPair, RigidBody

    a = RigidBody.from_mesh(trimesh.creation.box(extents=(0.02, 0.02, 0.02)))
    b = RigidBody.from_mesh(trimesh.creation.box(extents=(0.04, 0.01, 0.01)))
    shifts = np.linspace(-0.05, 0.05, 40)      # none where the boxes just touch

    def expected(shift: float) -> bool:       # |shift| below the half extents' sum
        return abs(shift) < 0.01 + 0.02 - 1e-9

    def pose(shift: float) -> np.ndarray:
        out = np.eye(4)
        out[0, 3] = shift
        return out

    def run(errors: list[str]) -> None:
        forward, backward = CollisionPair(a, b), CollisionPair(b, a)
        for shift in shifts:
            for pair in (forward, backward):
                if pair.collides(pose(shift)) != expected(shift):
                    errors.append(f'{shift:+.4f} m')
    errors: list[str] = []
    run(errors)
    threads = [threading.Thread(target=run, args=(errors,)) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not errors and not any(t.is_alive() for t in threads)
