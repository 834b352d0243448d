"""Small helpers shared by the modules for data spread over the ranks: numpy rows over
mpi4py, sums the same to the bit on every rank, positions in a sorted (global) numbering."""

from __future__ import annotations

from mpi4py import MPI
from mpi4py.util.dtlib import from_numpy_dtype

import numpy as np

__all__ = ["allgather_rows", "collective_error", "positions", "summed"]


def allgather_rows(comm: MPI.Comm, local: np.ndarray) -> np.ndarray:
    """Concatenate the ranks' row blocks of ``local`` (rank order) on every rank (collective).

    Args:
        comm: the communicator.
        local: (n, ...) this rank's rows; the trailing shape and dtype agree on all ranks.

    Returns:
        (sum of n, ...) the rows of rank 0, then rank 1, and so on.
    """
    local = np.ascontiguousarray(local)
    width = int(np.prod(local.shape[1:], dtype=np.int64))
    counts = np.asarray(comm.allgather(local.shape[0] * width), dtype=np.int64)
    out = np.empty(int(counts.sum()), dtype=local.dtype)
    comm.Allgatherv(local.reshape(-1), [out, counts, from_numpy_dtype(local.dtype)])
    return out.reshape((-1, *local.shape[1:]))


def collective_error(comm: MPI.Comm, message: str | None, error: type = ValueError) -> None:
    """Raise ``error`` on every rank if any rank has a ``message`` (the first one found).

    Args:
        comm: communicator of the ranks that must agree.
        message: this rank's error message, or None if this rank found nothing wrong.
        error: exception class raised.
    """
    messages = comm.allgather(message)
    first = next((m for m in messages if m is not None), None)
    if first is not None:
        raise error(first)


def summed(comm: MPI.Comm, values) -> np.ndarray:
    """The sum over the processes of ``values`` (an array of floats), the same to the bit on
    every process: reduced on one and broadcast (collective)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if comm.size == 1:
        return values
    out = np.empty_like(values)
    comm.Reduce(values, out, op=MPI.SUM, root=0)
    comm.Bcast(out, root=0)
    return out


def positions(sorted_values: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The position of each of ``values`` in the sorted array ``sorted_values`` (-1 where it is
    not there); ``values``' shape."""
    values = np.asarray(values)
    if sorted_values.size == 0:
        return np.full(values.shape, -1, dtype=np.int64)
    at = np.minimum(np.searchsorted(sorted_values, values), sorted_values.size - 1)
    return np.where(sorted_values[at] == values, at, -1)
