"""Files written whole or not at all, and files named by their content.

Every file kneeseat writes for others to read (tables, CSV, PNG, meshes, the default knee's
config, a bag's metadata.yaml) goes through `atomic_write`: the bytes go to a temporary
file in the destination's directory under a name no other writer uses (process id and a
random suffix), are flushed to disk, and the temporary file is renamed over the
destination. A reader sees the old file or the new one, never half of one; a crash or an
error leaves the destination as it was and removes the temporary file; two processes
writing the same destination at once each rename a complete file, the last one wins.
"""
from __future__ import annotations

from collections.abc import Callable
import contextlib
import hashlib
import os
from pathlib import Path
import secrets
import tempfile
from typing import BinaryIO

__all__ = ['atomic_write', 'write_bytes', 'file_sha256', 'unwritable', 'unwritable_directory']


def atomic_write(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Call `write` on a temporary file beside `path`, fsync it, then rename it to `path`.

    The file gets the usual permissions of a new file (0o666 less the umask). The rename
    itself is made durable by an fsync of the directory where the system allows it.

    Args:
        path: the destination; its directory must exist. Replaced if present.
        write: writes the whole content to the binary stream it is given.
    Raises:
        OSError: the directory is missing or not writable, or the disk is full; `path`
            is then unchanged and no temporary file is left.
    """
    path = Path(path)
    directory = path.parent
    tmp = directory / f'.{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp'
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)   # umask applies
    try:
        with os.fdopen(fd, 'wb') as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):          # make the rename itself durable
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` atomically (see `atomic_write`).

    Raises:
        OSError: as `atomic_write`.
    """
    def save(fh: BinaryIO) -> None:
        fh.write(data)

    atomic_write(path, save)


def file_sha256(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB chunks.

    Raises:
        OSError: the file cannot be read.
    """
    h = hashlib.sha256()
    with open(path, 'rb') as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


def unwritable(path: Path) -> str | None:
    """Why no file can be written at `path`, or None: it is a directory, its directory
    cannot be made (it is made here where missing, as a write would need it), or no file
    can be created there (tried with an empty temporary file, removed at once). Asked
    before long work whose end is that file."""
    path = Path(path)
    if path.is_dir():
        return 'it is a directory'
    for parent in path.parents:     # the nearest that exists must be a directory
        if parent.exists():
            if not parent.is_dir():
                return f'{parent} is not a directory'
            break
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.probe', dir=path.parent)
    except OSError as err:
        return err.strerror or str(err)
    os.close(fd)
    os.unlink(probe)
    return None


def unwritable_directory(path: Path) -> str | None:
    """Why no file can be written into the directory `path`, or None (`unwritable`: it is
    made here where missing)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        return 'it is a file'
    return unwritable(path / '.kneeseat')
