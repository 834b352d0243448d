"""Active-set damping of Newton's method: a contact pair that left is kept in the Jacobian for
one iteration.

A (triangle, tetrahedron) pair contributes to the contact energy's Hessian only while their
intersection is not empty. Where a Newton step carries a triangle out of a tetrahedron (a
contact opening, a surface sliding on into the next tetrahedron, or overshooting after it was
pushed in without stiffness the step before), the next Jacobian has lost the pair's stiffness
at once, and the step after can push the triangle back in: the contact set flip-flops and the
full steps converge slowly. :class:`LaggedPairs` adds the Hessian each such pair had at the
last iterate to the Jacobian of the next one (a Jacobian, not a residual, change: the
solution is the same, and once the contact set settles the Jacobian is the exact one again,
so the final iterations stay quadratic).

:class:`~fenics_matdepth.ContactProblem` takes it with ``problem.assembler.keep_left_pairs()``
(``SystemAssembler.keep_left_pairs``); what it measured on
the knee is in docs/measurements.md.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from fenics_matdepth.contact import assembly
from fenics_matdepth.contact.operator import ContactOperator

__all__ = ["LaggedPairs"]


class LaggedPairs:
    """The Hessians of the pairs at the last Jacobian, added to the next Jacobian for the pairs
    that left in between (collective).

    Args:
        contact: the contact operator (area integration: its evaluated pairs are the
            intersecting ones).

    Attributes:
        added: pairs added to a Jacobian since the last :meth:`reset` (summed over the ranks).
        total_added: the same over the object's life.
    """

    def __init__(self, contact: ContactOperator):
        if contact.integration != "area":
            raise ValueError(
                "keeping the pairs that left in the Jacobian needs area integration (with "
                f"{contact.integration!r} every candidate pair is evaluated already)"
            )
        self.contact = contact
        self.total_added = 0
        self.reset()

    def reset(self) -> None:
        """Forget the last Jacobian's pairs (a solve starts: its first Jacobian is exact)."""
        self._last = None
        self.added = 0

    def add_jacobian(self, A: PETSc.Mat) -> None:
        """Add to ``A`` (assembled, with the contact's Hessian in it) the last Jacobian's
        Hessian of each pair that has left since, and remember the current pairs."""
        contact = self.contact
        surface = contact.surface
        verts, hess = contact.pair_hessians()
        # global vertices (a new halo numbers the held vertices anew): a pair is its 7
        # vertices, triangle's then tetrahedron's
        global_verts = surface.global_vertex[verts]
        keys = _row_keys(global_verts)
        last, self._last = self._last, (keys, global_verts, hess.copy())
        left = np.zeros(0, dtype=bool) if last is None else ~np.isin(last[0], keys)
        verts_left = np.empty((0, verts.shape[1]), dtype=verts.dtype)
        if last is not None:
            verts_left = surface.held_index(last[1][left]).astype(verts.dtype)
            # (a pair whose vertices the rank no longer holds reaches none of its rows)
            whole = np.all(verts_left >= 0, axis=1)
            left[np.flatnonzero(left)[~whole]] = False
            verts_left = verts_left[whole]
        count = contact.comm.allreduce(int(np.count_nonzero(left)), op=MPI.SUM)
        if count == 0:
            return
        held, transposed = contact.held_pattern()
        pos, _ = assembly.coupling_positions(surface, held, verts_left, transposed)
        assembly.add_jacobian_blocks(A, surface, held, pos, verts_left, last[2][left])
        A.assemble()
        self.added += count
        self.total_added += count


def _row_keys(rows: np.ndarray) -> np.ndarray:
    """Each row of an integer array as one comparable (sortable) value."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    return rows.view(np.dtype((np.void, 8 * rows.shape[1]))).ravel()
