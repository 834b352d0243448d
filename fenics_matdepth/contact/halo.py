"""Neighbour exchanges of per-vertex values between the ranks that hold a vertex.

A rank holds vertices it owns and vertices owned by other ranks (the ghosts of its own cells
and the vertices of halo tetrahedra). A :class:`VertexExchange` is built once per halo (set
up with a collective count exchange) and then moves, point to point between the ranks
concerned only, per-vertex values of any width from owners to holders
(:meth:`VertexExchange.pull`) or sums holders' contributions onto the owners
(:meth:`VertexExchange.push_add`).
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np

from fenics_matdepth._constants import INDEX

__all__ = ["VertexExchange", "alltoallv_rows", "owner_of"]


def owner_of(ranges: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Owning rank of global vertices, from the ranks' exclusive range ends ``ranges``."""
    return np.searchsorted(ranges, np.asarray(vertices, dtype=INDEX), side="right").astype(np.int32)


def alltoallv_rows(
    comm: MPI.Comm, rows: np.ndarray, dest: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Send row i of ``rows`` to rank ``dest[i]`` (collective; a count exchange, then the rows).

    Returns:
        (received rows in source-rank order, source rank of each received row).
    """
    rows = np.ascontiguousarray(rows)
    width = int(np.prod(rows.shape[1:], dtype=np.int64))
    order = np.argsort(dest, kind="stable")
    send_counts = np.bincount(dest, minlength=comm.size).astype(np.int64)
    recv_counts = np.empty(comm.size, dtype=np.int64)
    comm.Alltoall(send_counts, recv_counts)
    send = np.ascontiguousarray(rows[order]).reshape(-1)
    recv = np.empty(int(recv_counts.sum()) * width, dtype=rows.dtype)
    comm.Alltoallv([send, send_counts * width], [recv, recv_counts * width])
    source = np.repeat(np.arange(comm.size, dtype=np.int32), recv_counts)
    return recv.reshape((-1, *rows.shape[1:])), source


class VertexExchange:
    """Owner-to-holder transfer of per-vertex values (collective set-up).

    Args:
        comm: the communicator.
        ranges: (size,) exclusive end of each rank's owned global vertex range.
        held_global: (num_held,) global numbers of the held vertices; the first ``n_owned``
            are this rank's owned vertices in order (global ``offset + i``).
        n_owned: number of owned vertices.
    """

    def __init__(self, comm: MPI.Comm, ranges: np.ndarray, held_global: np.ndarray, n_owned: int):
        self.comm = comm
        self.n_owned = int(n_owned)
        offset = int(ranges[comm.rank - 1]) if comm.rank else 0
        remote = np.arange(n_owned, held_global.size, dtype=INDEX)
        owner = owner_of(ranges, held_global[remote])
        order = np.argsort(owner, kind="stable")
        self._recv_pos = remote[order]  # held positions, grouped by owner
        recv_counts = np.bincount(owner, minlength=comm.size).astype(np.int64)
        requests, source = alltoallv_rows(comm, held_global[remote], owner)
        self._send_idx = (requests - offset).astype(INDEX)  # owned positions, by requester
        send_counts = np.bincount(source, minlength=comm.size).astype(np.int64)
        self._send = [
            (int(r), int(a), int(b))
            for r, a, b in zip(
                np.flatnonzero(send_counts),
                np.cumsum(send_counts)[send_counts > 0] - send_counts[send_counts > 0],
                np.cumsum(send_counts)[send_counts > 0],
                strict=True,
            )
        ]
        self._recv = [
            (int(r), int(a), int(b))
            for r, a, b in zip(
                np.flatnonzero(recv_counts),
                np.cumsum(recv_counts)[recv_counts > 0] - recv_counts[recv_counts > 0],
                np.cumsum(recv_counts)[recv_counts > 0],
                strict=True,
            )
        ]

    @property
    def neighbours(self) -> int:
        """Number of ranks this rank sends to or receives from."""
        return len({r for r, _, _ in self._send} | {r for r, _, _ in self._recv})

    @property
    def sent_vertices(self) -> int:
        """Vertices whose values this rank sends per :meth:`pull`."""
        return int(self._send_idx.size)

    @property
    def received_vertices(self) -> int:
        """Vertices whose values this rank receives per :meth:`pull`."""
        return int(self._recv_pos.size)

    def _exchange(self, send_lists, recv_lists, send_buf, recv_buf, tag):
        reqs = [self.comm.Irecv(recv_buf[a:b], source=r, tag=tag) for r, a, b in recv_lists]
        reqs += [self.comm.Isend(send_buf[a:b], dest=r, tag=tag) for r, a, b in send_lists]
        MPI.Request.Waitall(reqs)

    def pull(self, owned: np.ndarray, held: np.ndarray) -> None:
        """Fill the non-owned rows of ``held`` (num_held, ...) from the owners' ``owned``
        (n_owned, ...) rows; the owned rows of ``held`` are set from ``owned`` too."""
        owned = np.ascontiguousarray(owned)
        held[: self.n_owned] = owned
        send = np.ascontiguousarray(owned[self._send_idx])
        recv = np.empty((self._recv_pos.size, *owned.shape[1:]), dtype=owned.dtype)
        self._exchange(self._send, self._recv, send, recv, tag=71)
        held[self._recv_pos] = recv

    def push_add(self, held: np.ndarray) -> np.ndarray:
        """Sum the ``held`` (num_held, ...) rows of every holder onto the owner: returns the
        (n_owned, ...) sums (the owned rows plus all contributions from other ranks)."""
        held = np.ascontiguousarray(held)
        out = held[: self.n_owned].copy()
        send = np.ascontiguousarray(held[self._recv_pos])
        recv = np.empty((self._send_idx.size, *held.shape[1:]), dtype=held.dtype)
        self._exchange(self._recv, self._send, send, recv, tag=72)
        np.add.at(out, self._send_idx, recv)
        return out
