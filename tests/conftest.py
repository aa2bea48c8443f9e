"""Shared fixtures. The small built-in face is built once per session (and cached on disk under
meshes/cache/, so later sessions find it instantly); under ``mpirun -n 2 python -m pytest``
every rank gets the same folder."""
import pathlib

import pytest
from mpi4py import MPI

SMALL_FACE_TETS = 5000


@pytest.fixture(scope="session")
def builtin_model_path():
    from face_dolfinx.model.anatomy import build_builtin_face
    return build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_WORLD)


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
