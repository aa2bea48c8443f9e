"""Atomic files and folders (face_dolfinx.files): whole or not at all, also when killed, and
written by one rank under MPI."""
import os
import stat
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.files import AtomicFile, atomic_directory, atomic_write, on_rank_0

comm = MPI.COMM_WORLD


def hidden(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_text_bytes_and_callback(tmp_path):
    assert atomic_write(tmp_path / "a.txt", "héllo\n") == tmp_path / "a.txt"
    atomic_write(tmp_path / "b.bin", b"\x00\x01")
    atomic_write(tmp_path / "c.npy", lambda handle: np.save(handle, np.arange(5)))
    assert (tmp_path / "a.txt").read_text(encoding="utf-8") == "héllo\n"
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert np.array_equal(np.load(tmp_path / "c.npy"), np.arange(5))
    assert hidden(tmp_path) == []


def test_a_failed_write_leaves_the_old_file_or_nothing(tmp_path):
    def half_then_fail(handle):
        handle.write(b"half of the new")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(tmp_path / "new.txt", half_then_fail)
    assert list(tmp_path.iterdir()) == []
    atomic_write(tmp_path / "old.txt", "old")
    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(tmp_path / "old.txt", half_then_fail)
    assert (tmp_path / "old.txt").read_text() == "old"
    assert hidden(tmp_path) == []


@pytest.mark.skipif(comm.size > 1, reason="a child Python would join the MPI job")
def test_a_killed_write_leaves_the_old_file_and_the_next_write_succeeds(tmp_path):
    """The process dies (no exception handling, no cleanup) in the middle of writing."""
    target = tmp_path / "record.json"
    atomic_write(target, "old")
    script = textwrap.dedent(f"""
        import os
        from face_dolfinx.files import atomic_write
        def die(handle):
            handle.write(b"half")
            handle.flush()
            os._exit(3)
        atomic_write({str(target)!r}, die)
    """)
    killed = subprocess.run([sys.executable, "-c", script], cwd=os.getcwd(), env=dict(os.environ))
    assert killed.returncode == 3
    assert target.read_text() == "old"
    assert hidden(tmp_path) == [".record.json.tmp"]  # the kill's leftover, hidden
    atomic_write(target, "new")
    assert target.read_text() == "new" and hidden(tmp_path) == []


def test_overwrite_false_refuses_an_existing_file(tmp_path):
    atomic_write(tmp_path / "a.txt", "first", overwrite=False)
    with pytest.raises(FileExistsError, match="a.txt already exists"):
        atomic_write(tmp_path / "a.txt", "second", overwrite=False)
    assert (tmp_path / "a.txt").read_text() == "first"
    assert hidden(tmp_path) == []


def test_overwrite_false_loses_no_race(tmp_path):
    """A file that appears while the new one is written is kept, and the write fails."""
    target = tmp_path / "a.txt"
    with pytest.raises(FileExistsError):
        with AtomicFile(target, overwrite=False) as temporary:
            temporary.write_text("mine")
            target.write_text("theirs")
    assert target.read_text() == "theirs"
    assert hidden(tmp_path) == []


def test_atomic_file_by_name_with_a_suffix(tmp_path):
    target = tmp_path / "take.C3D"
    with AtomicFile(target, suffix=".c3d") as temporary:
        assert temporary.name.endswith(".c3d") and temporary.parent == tmp_path
        assert not target.exists()
        with h5py.File(temporary, "w") as h5:
            h5["x"] = np.arange(3)
    with h5py.File(target, "r") as h5:
        assert np.array_equal(h5["x"][:], np.arange(3))
    assert hidden(tmp_path) == []


def test_atomic_file_committed_by_hand(tmp_path):
    kept, dropped = AtomicFile(tmp_path / "kept"), AtomicFile(tmp_path / "dropped")
    kept.temporary.write_text("k")
    dropped.temporary.write_text("d")
    kept.commit()
    dropped.discard()
    assert [p.name for p in tmp_path.iterdir()] == ["kept"]


def test_a_directory_appears_whole(tmp_path):
    target = tmp_path / "deep" / "result"
    with atomic_directory(target) as staging:
        assert staging.parent == target.parent and staging.name.startswith(".result.partial-")
        (staging / "a.txt").write_text("a")
        assert not target.exists()
    assert [p.name for p in target.iterdir()] == ["a.txt"]
    assert hidden(target.parent) == []
    # The permissions of a plain mkdir, not the private ones of a temporary folder.
    (tmp_path / "plain").mkdir()
    assert stat.S_IMODE(target.stat().st_mode) == stat.S_IMODE((tmp_path / "plain").stat().st_mode)


def test_a_failed_directory_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="stop"):
        with atomic_directory(tmp_path / "result") as staging:
            (staging / "a.txt").write_text("a")
            raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []


def test_directory_overwrite_rules(tmp_path):
    target = tmp_path / "result"
    with atomic_directory(target) as staging:
        (staging / "old.txt").write_text("old")
    with pytest.raises(FileExistsError, match="--overwrite"):
        with atomic_directory(target):
            pytest.fail("the block must not run")
    with pytest.raises(RuntimeError):  # a failed overwrite keeps the old folder
        with atomic_directory(target, overwrite=True):
            raise RuntimeError("stop")
    assert [p.name for p in target.iterdir()] == ["old.txt"]
    with atomic_directory(target, overwrite=True) as staging:
        (staging / "new.txt").write_text("new")
        assert (target / "old.txt").is_file()  # the old one stays until the new one is whole
    assert [p.name for p in target.iterdir()] == ["new.txt"]
    assert hidden(tmp_path) == []


def test_a_directory_made_meanwhile_is_kept(tmp_path):
    target = tmp_path / "result"
    with pytest.raises(FileExistsError):
        with atomic_directory(target) as staging:
            (staging / "mine").write_text("mine")
            target.mkdir()
            (target / "theirs").write_text("theirs")
    assert [p.name for p in target.iterdir()] == ["theirs"]
    assert hidden(tmp_path) == []


# -- MPI: one rank writes, every rank learns the outcome -------------------------------------------
def test_one_rank_writes_a_file(shared_dir):
    calls = []

    def content(handle):
        calls.append(comm.rank)
        handle.write(b"from one rank")

    target = atomic_write(shared_dir / "one.txt", content, comm=comm)
    assert calls == ([0] if comm.rank == 0 else [])
    assert target.read_text() == "from one rank"  # visible on every rank on return


def test_an_error_on_rank_0_is_raised_on_every_rank(shared_dir):
    def fail(handle):
        raise RuntimeError("rank 0 failed")

    with pytest.raises(RuntimeError, match="rank 0 failed"):
        atomic_write(shared_dir / "failed.txt", fail, comm=comm)
    with pytest.raises(ZeroDivisionError):
        on_rank_0(lambda: 1 / 0, comm)
    assert on_rank_0(lambda: comm.rank + 41, comm) == 41
    assert not (shared_dir / "failed.txt").exists()


def test_every_rank_writes_into_one_directory(shared_dir):
    target = shared_dir / "together"
    with atomic_directory(target, comm) as staging:
        assert comm.allgather(str(staging)) == [str(staging)] * comm.size
        (staging / f"rank{comm.rank}.txt").write_text(str(comm.rank))
    assert sorted(p.name for p in target.iterdir()) == [f"rank{r}.txt" for r in range(comm.size)]
    with pytest.raises(FileExistsError):  # refused on every rank
        with atomic_directory(target, comm):
            pass
    comm.barrier()
    assert not [p for p in shared_dir.iterdir() if p.name.startswith(".together")]
