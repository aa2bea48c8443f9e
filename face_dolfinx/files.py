"""Files and folders that appear whole or not at all.

A file is written under a temporary name beside it (``.NAME.tmp``), flushed to disk and renamed
over its target (``os.replace``, atomic on POSIX file systems): a killed process leaves the old
file or the new one, never half of one. A folder is built under a temporary name
(``.NAME.partial-XXXXXXXX``) and renamed into place when complete. The temporary names are
hidden, so what a kill leaves behind never looks like a result; the next write of the same file
replaces a file's leftover, a folder's leftover stays until removed by hand.

Under MPI, rank 0 of ``comm`` writes and renames; an error there is raised on every rank.
"""
import os
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path

from mpi4py import MPI

from face_dolfinx.parallel import on_rank_0


class AtomicFile:
    """A file written by name (h5py, ezc3d, ...) under a temporary name and renamed into place.

    ``with AtomicFile(path) as temporary:`` write ``temporary``; on success it becomes ``path``,
    on an exception it is removed. ``suffix`` ends the temporary name, for writers that choose
    the format by it. Unless ``overwrite``, an existing ``path`` is refused (FileExistsError)
    before and, without a race, when renaming. ``commit`` and ``discard`` end it by hand, for a
    file that stays open across calls.
    """

    def __init__(self, path, suffix: str = "", overwrite: bool = True):
        self.path = Path(path)
        self.overwrite = overwrite
        self.temporary = self.path.with_name(f".{self.path.name}.tmp{suffix}")
        if not overwrite and self.path.exists():
            raise FileExistsError(f"{self.path} already exists")

    def commit(self) -> Path:
        try:
            descriptor = os.open(self.temporary, os.O_RDONLY)
            try:
                os.fsync(descriptor)
            finally:
                os.close(descriptor)
            if self.overwrite:
                os.replace(self.temporary, self.path)
            else:  # a hard link is created only where no file is: no overwrite, even in a race
                os.link(self.temporary, self.path)
                self.temporary.unlink()
        except BaseException:
            self.discard()
            raise
        return self.path

    def discard(self) -> None:
        self.temporary.unlink(missing_ok=True)

    def __enter__(self) -> Path:
        return self.temporary

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.commit()
        else:
            self.discard()


def atomic_write(path, content, *, overwrite: bool = True, comm=MPI.COMM_SELF) -> Path:
    """Write ``content`` to ``path`` whole or not at all; returns ``path``.

    ``content`` is text (UTF-8), bytes, or a callable that writes to a binary file handle
    (e.g. ``lambda handle: numpy.save(handle, array)``). Collective over ``comm``: rank 0 writes.
    """
    def write():
        with AtomicFile(path, overwrite=overwrite) as temporary, open(temporary, "wb") as handle:
            if callable(content):
                content(handle)
            else:
                handle.write(content.encode() if isinstance(content, str) else content)
        return Path(path)

    return on_rank_0(write, comm)


@contextmanager
def atomic_directory(path, comm=MPI.COMM_SELF, overwrite: bool = False):
    """Yield a temporary folder beside ``path`` (the same on every rank of ``comm``) that
    becomes ``path`` when the block succeeds and is removed when it raises.

    Collective over ``comm``: rank 0 creates and renames. An existing ``path`` is refused
    (FileExistsError) unless ``overwrite``; then the old folder stays in place until the new one
    is complete, and is removed after the rename. The folder gets the permissions of a plain
    ``mkdir`` (the umask's), not the private ones of a temporary folder.
    """
    path = Path(path)

    def create() -> Path:
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass --overwrite to replace it")
        path.parent.mkdir(parents=True, exist_ok=True)
        return _fresh(path, "partial", make=True)

    staging = on_rank_0(create, comm)
    try:
        yield staging
    except BaseException:
        if comm.rank == 0:
            shutil.rmtree(staging, ignore_errors=True)
        raise
    comm.barrier()  # every rank has finished writing into the folder

    def move_into_place() -> None:
        try:
            if not path.exists():
                staging.rename(path)
            elif overwrite:
                old = _fresh(path, "old", make=False)
                path.rename(old)
                staging.rename(path)
                shutil.rmtree(old)
            else:  # appeared while the block ran
                raise FileExistsError(f"{path} already exists; pass --overwrite to replace it")
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    on_rank_0(move_into_place, comm)


def _fresh(path: Path, kind: str, make: bool) -> Path:
    """An unused hidden name beside ``path``; with ``make`` the folder is created."""
    while True:
        candidate = path.with_name(f".{path.name}.{kind}-{secrets.token_hex(4)}")
        if not make:
            if not candidate.exists():
                return candidate
            continue
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue
