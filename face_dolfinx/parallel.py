"""MPI helpers shared by the drivers."""
from mpi4py import MPI


def root_first(action, comm: MPI.Comm = MPI.COMM_WORLD):
    """Run ``action`` on rank 0 and return its value on every rank; its exception is raised on
    every rank, so that all of them stop, not only rank 0."""
    value, error = None, None
    if comm.rank == 0:
        try:
            value = action()
        except Exception as exc:  # re-raised below on every rank
            error = exc
    error = comm.bcast(error, root=0)
    if error is not None:
        raise error
    return comm.bcast(value, root=0)
