"""Shared fixtures. The tests run on the small built-in face as committed in meshes/small_face/
(meshes/freeze_small_face.py); under ``mpirun -n 2 python -m pytest`` every rank reads the same
folder."""
import pathlib

import pytest
from mpi4py import MPI

from face_dolfinx.model.anatomy.builder import SMALL_FACE


@pytest.fixture(scope="session")
def builtin_model_path():
    """The small built-in face's model folder (built at SMALL_FACE_TETS, committed)."""
    return SMALL_FACE


@pytest.fixture(scope="module")
def model(builtin_model_path):
    """The small built-in face, distributed over all ranks (one per test module: tests solve on
    its mesh and may leave state in objects built on it)."""
    from face_dolfinx.model.folder import load_model
    return load_model(builtin_model_path, MPI.COMM_WORLD)


@pytest.fixture(scope="module")
def shared_dir(tmp_path_factory, request):
    """One temporary folder per test module for all ranks (each rank's tmp_path differs under
    mpirun)."""
    folder = tmp_path_factory.mktemp(request.module.__name__.rpartition(".")[2])
    return pathlib.Path(MPI.COMM_WORLD.bcast(str(folder), root=0))


@pytest.fixture(scope="module")
def template(builtin_model_path):
    """The small built-in face as plain arrays (``read_model_arrays``), for subject adaptation."""
    from face_dolfinx.model.folder import read_model_arrays
    return read_model_arrays(builtin_model_path)


def on_rank_0(action):
    """``action`` on rank 0, the other ranks waiting for it: a file every rank then reads."""
    if MPI.COMM_WORLD.rank == 0:
        action()
    MPI.COMM_WORLD.barrier()
