"""Atomic writes: whole or not at all, and writers of one file do not trip over each other."""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import BinaryIO

import pytest

from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.files import (atomic_write, file_sha256, unwritable, unwritable_directory,
                                 write_bytes)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / 'table.npz'
    path.write_bytes(b'old')

    def half(fh: BinaryIO) -> None:
        fh.write(b'new but ')
        raise OSError(28, 'No space left on device')

    with pytest.raises(OSError, match='No space'):
        atomic_write(path, half)
    assert path.read_bytes() == b'old'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['table.npz']


def test_two_writers_of_one_file_each_rename_a_whole_file(tmp_path: Path) -> None:
    path = tmp_path / 'default_knee.yaml'

    def outer(fh: BinaryIO) -> None:
        fh.write(b'first ')
        write_bytes(path, b'second, complete')       # another writer finishes meanwhile
        assert path.read_bytes() == b'second, complete'
        fh.write(b'complete')

    atomic_write(path, outer)
    assert path.read_bytes() == b'first complete'     # the last rename wins, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ['default_knee.yaml']


def test_missing_directory_is_an_os_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        write_bytes(tmp_path / 'no' / 'such' / 'x.csv', b'x')


def test_file_sha256_is_the_sha256_of_the_bytes(tmp_path: Path) -> None:
    data = bytes(range(256)) * 9000          # more than one 1 MiB chunk
    path = tmp_path / 'mesh.stl'
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()


def test_default_knee_written_twice_into_one_directory(tmp_path: Path) -> None:
    first = materialise_default_knee(tmp_path)
    text = first.read_text()
    mtime = first.stat().st_mtime_ns
    again = materialise_default_knee(tmp_path)
    assert again == first and again.read_text() == text
    assert again.stat().st_mtime_ns == mtime               # same bytes: left untouched
    assert not [p for p in tmp_path.iterdir() if p.name.endswith('.tmp')]


def test_unwritable_says_why_and_leaves_only_the_directories_a_write_needs(
        tmp_path: Path) -> None:
    (tmp_path / 'a_file').write_text('x')
    assert unwritable(tmp_path) == 'it is a directory'
    assert unwritable(tmp_path / 'a_file' / 'deeper' / 't.npz') == \
        f'{tmp_path / "a_file"} is not a directory'
    assert unwritable(tmp_path / 'a_file') is None            # a file there is replaced
    assert unwritable(tmp_path / 'new' / 'dir' / 't.npz') is None
    assert sorted(p.name for p in tmp_path.rglob('*')) == ['a_file', 'dir', 'new']
    assert unwritable_directory(tmp_path / 'a_file') == 'it is a file'
    made = tmp_path / 'new' / 'made'
    assert unwritable_directory(made) is None
    assert made.is_dir() and not any(made.iterdir())
