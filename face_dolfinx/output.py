"""Results on disk: XDMF (ParaView) of the deformed face, point evaluation, atomic folders.

A result folder is built under a temporary name and renamed into place only when complete, so an
interrupted run never leaves a folder that looks like a result.
"""
from contextlib import contextmanager
import pathlib
import shutil
import tempfile

from mpi4py import MPI
import numpy as np
from dolfinx import fem, io

from .points import PointEvaluator


@contextmanager
def atomic_directory(path, comm=MPI.COMM_WORLD, overwrite: bool = False):
    """Yield a temporary folder (same on every rank) that becomes ``path`` on success."""
    path = pathlib.Path(path)
    error = None
    if comm.rank == 0:
        if path.exists() and not overwrite:
            error = f"{path} already exists; pass --overwrite to replace it"
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            staging = pathlib.Path(tempfile.mkdtemp(prefix=f".{path.name}.partial-", dir=path.parent))
    error = comm.bcast(error, root=0)
    if error:
        raise FileExistsError(error)
    staging = comm.bcast(staging if comm.rank == 0 else None, root=0)
    try:
        yield staging
        comm.barrier()
        if comm.rank == 0:
            if path.exists():
                shutil.rmtree(path)
            staging.rename(path)
    except BaseException:
        if comm.rank == 0:
            shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        comm.barrier()


def displacement_at(u: fem.Function, points: np.ndarray) -> np.ndarray:
    """u at ``points`` (n, 3) of the reference configuration, the same array on every rank."""
    return PointEvaluator(u.function_space, points).values(u.x.array)


class FaceWriter:
    """XDMF time series of the face: displacement, each muscle's activation x fraction, fibers."""

    def __init__(self, problem, path):
        self.problem = problem
        mesh = problem.mesh
        self._file = io.XDMFFile(mesh.comm, str(path), "w")
        self._file.write_mesh(mesh)
        self._P1 = fem.VectorFunctionSpace(mesh, ("CG", 1))
        self._displacement = fem.Function(self._P1, name="displacement")
        DG0 = fem.FunctionSpace(mesh, ("DG", 0))
        self._muscle_fields = [fem.Function(DG0, name=f"activation_{m.name}") for m in problem.model.muscles]
        self._fiber = fem.Function(fem.VectorFunctionSpace(mesh, ("DG", 0)), name="fiber")
        # The fiber shown per cell is that of its strongest muscle (slot weights are fixed).
        slots = problem.slots
        weights = np.stack([w.x.array for w in slots.weight])
        strongest = np.argmax(weights, axis=0)
        fibers = np.stack([f.x.array.reshape(-1, 3) for f in slots.fiber])
        self._fiber.x.array[:] = fibers[strongest, np.arange(len(strongest))].reshape(-1)
        self._fiber.x.array.reshape(-1, 3)[weights.max(axis=0) == 0] = 0.0
        self._file.write_function(self._fiber, 0.0)

    def write(self, time: float) -> None:
        problem = self.problem
        self._displacement.interpolate(problem.u)
        self._file.write_function(self._displacement, time)
        slots = problem.slots
        for index, field in enumerate(self._muscle_fields):
            field.x.array[:] = 0.0
            for k in range(len(slots.weight)):
                in_slot = slots.muscle_of_slot[k] == index
                stress = slots.weight[k].x.array / max(problem.peak_stress(index), 1e-300)
                field.x.array[in_slot] = problem.controls.activations[index] * stress[in_slot]
            self._file.write_function(field, time)

    def close(self) -> None:
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
