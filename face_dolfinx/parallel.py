"""MPI helpers shared by the drivers."""
from mpi4py import MPI


def on_rank_0(action, comm=MPI.COMM_SELF):
    """``action()`` on rank 0 of ``comm``; its value on every rank, and its exception raised on
    every rank (collective)."""
    value, error = None, None
    if comm.rank == 0:
        try:
            value = action()
        except Exception as exc:  # every rank must stop, not only rank 0
            error = exc
    if comm.size > 1:
        value, error = comm.bcast((value, error), root=0)
    if error is not None:
        raise error
    return value
