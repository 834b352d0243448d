"""Continuous collision detection of the boundary between two states: how far a step may go.

:class:`ContinuousCollision` answers, for a step from displacement ``u0`` to ``u1`` (every
vertex on a straight line), the fraction of the step after which some boundary vertex could
be more than the *entry tolerance* past a boundary triangle it was apart from at the start, or
some boundary edge past an edge (the entry cap of `fenics_matdepth.geometry.ccd`). Pairs that
start in contact (closer than the entry tolerance, or a vertex behind the plane of the
triangle: inside the body or leaving it) move freely: the material depth handles them, and our
surfaces intersect by design.

Distributed: the boundary surface (triangles, edges, vertex positions) is small against the
volume, so every rank holds all of it (one allgather of the boundary vertices' displacements
per query); each rank tests the primitive pairs of the triangles it owns, against all, and the
smallest cap is reduced over the ranks: the answer does not depend on the partition.

Broad phase: an AABB tree (`fenics_matdepth.geometry.bvh`) over the swept boxes of the
boundary triangles (the box of a triangle's six positions at the step's start and end),
refitted at each query and rebuilt when refits have degraded it; each owned triangle's swept
box is queried against it, or, without the exit cap, only the boxes of the triangles that move
far enough to enter anything (``geometry.ccd.STILL_REACH``), each pair with a still triangle
taken both ways round.
"""

from __future__ import annotations

import time

from mpi4py import MPI

import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._mpi import allgather_rows, positions
from fenics_matdepth.contact.surface import ContactSurface
from fenics_matdepth.geometry.boxes import element_boxes
from fenics_matdepth.geometry.bvh import AABBTree
from fenics_matdepth.geometry.ccd import (
    PASS_THROUGH,
    STILL_REACH,
    sweep_caps,
    sweep_topology,
    triangle_bodies,
    triangle_travel,
)

__all__ = [
    "ENTRY_FRACTION",
    "NEWTON_TRAVEL_EDGES",
    "ContinuousCollision",
    "pass_through_message",
    "penalty_needed",
]

#: Default entry tolerance, as a fraction of the local boundary edge length (the smaller of
#: the two triangles' mean reference edge lengths): how far a separated pair may go past its
#: first contact within one step. Below the thickness of a layer one element thick, and large
#: enough that a Newton step reaching a new contact is not cut to nothing.
ENTRY_FRACTION = 0.25

#: A Newton step is shortened, before it is swept, so that no boundary vertex moves more than
#: this many median boundary edges (:meth:`ContinuousCollision.newton_fraction`). Near a limit
#: point of the load path a Newton step can move a few vertices hundreds of metres (6.2e5 mm
#: measured on the knee's coarse leg at 96 deg, median edge 4.3 mm, residual 100 to 340 N), which
#: the line search then cuts to a tenth or less; the swept boxes of such a step overlap
#: nearly every triangle, and one query took 40 s and more (the knee's 6.8k boundary
#: triangles, against 0.1 s for a step of element size).
NEWTON_TRAVEL_EDGES = 10.0


class ContinuousCollision:
    """The entry cap of a step of the boundary between two displacements (collective).

    Args:
        surface: the contact operator's :class:`~fenics_matdepth.contact.surface.ContactSurface`
            (its owned boundary triangles, outward oriented, and vertex numbering).
        entry_fraction: entry tolerance per pair, as a fraction of the local boundary edge
            length (reference configuration), > 0.
        exits: also cap a vertex inside a body from leaving through the body's far side
            (`fenics_matdepth.geometry.ccd`, "pass-through"); False: vertices inside a body
            are free to leave through any face; None (default): on while
            ``solve_time_steps`` runs (``time_stepping``), off otherwise (in load steps
            the entry caps hold a fold, and the exit cap stalled Newton on the knee's skin
            fold, docs/dynamics.md).

    Attributes:
        entry: (num boundary triangles,) entry tolerance of each triangle's pairs (L).
        max_travel: the longest a boundary vertex may move in a Newton step
            (:meth:`newton_fraction`; L): NEWTON_TRAVEL_EDGES times the median of the
            triangles' mean reference edge lengths (settable).
        queries: number of :meth:`step_fraction` calls so far.
        seconds: wall time spent in them (s).
        capped: pairs capped below 1 by the last query (over all ranks).
        exits: the ``exits`` argument (settable); :attr:`exits_active` says whether it applies.
        time_stepping: True while ``solve_time_steps`` runs (the exit cap's default).
        last_pair: ``(kind, i, j)`` of the pair that set the last cap below 1: kind 0 a
            vertex and a triangle, 1 two edges, 2 a vertex leaving through the far side of a
            body (a vertex and a triangle), in the boundary numbering; None otherwise.
    """

    def __init__(
        self,
        surface: ContactSurface,
        entry_fraction: float = ENTRY_FRACTION,
        exits: bool | None = None,
    ):
        if not entry_fraction > 0.0:
            raise ValueError(
                f"entry_fraction must be > 0 (a fraction of the boundary edge length), got "
                f"{entry_fraction}"
            )
        comm = self.comm = surface.comm
        self.entry_fraction = float(entry_fraction)
        self.exits = exits
        self.time_stepping = False  # set by solve_time_steps while it runs
        n_owned = surface.owned_dof_count() // 3
        self._n_owned_dofs = 3 * n_owned
        own_tri = surface.global_vertex[surface.tri]
        tri_global = allgather_rows(comm, own_tri.astype(INDEX))
        counts = np.asarray(comm.allgather(int(own_tri.shape[0])), dtype=INDEX)
        first = int(counts[: comm.rank].sum())
        self._owned_tri = np.arange(first, first + own_tri.shape[0], dtype=INDEX)
        # boundary vertices (global numbers, sorted) and the triangles over them
        self.vertices = np.unique(tri_global)
        self.tri = np.searchsorted(self.vertices, tri_global).astype(INDEX)
        nb = self.vertices.size
        # the owned boundary vertices: their local rows and boundary numbers, in gather order
        owned_global = surface.global_vertex[:n_owned]
        pos = positions(self.vertices, owned_global)
        mine = pos >= 0
        self._owned_rows = np.flatnonzero(mine)
        self._gather_order = allgather_rows(comm, pos[mine].astype(INDEX))
        self.X = np.empty((nb, 3), dtype=FLOAT)
        self.X[self._gather_order] = allgather_rows(comm, surface.X[self._owned_rows])
        self._edges_and_owners()
        # the triangles of each body, for the exit cap's contact test
        body = surface.body_of_vertex[self.vertices[self.tri[:, 0]]] if nb else np.empty(0)
        self._bodies = triangle_bodies(self.tri, body)
        edge_length = np.linalg.norm(
            self.X[self.tri[:, [1, 2, 0]]] - self.X[self.tri], axis=2
        ).mean(axis=1)
        self.entry = np.ascontiguousarray(self.entry_fraction * edge_length, dtype=FLOAT)
        median_edge = float(np.median(edge_length)) if edge_length.size else 0.0
        self.max_travel = NEWTON_TRAVEL_EDGES * median_edge
        # the swept-box tree: a "cell" of six points, the triangle at the start and the end
        self._swept_cells = np.ascontiguousarray(np.hstack((self.tri, self.tri + nb)))
        self._tree: AABBTree | None = None
        self.queries = 0
        self.seconds = 0.0
        self.capped = 0
        self.last_pair: tuple[int, int, int] | None = None

    def _edges_and_owners(self) -> None:
        """Boundary edges, each triangle's edges, and the owner triangle of each edge and
        vertex (:func:`~fenics_matdepth.geometry.ccd.sweep_topology`)."""
        self.tri_edge, self.edges, self.vertex_owner, self.edge_owner = sweep_topology(
            self.tri, self.vertices.size
        )

    @property
    def exits_active(self) -> bool:
        """Whether queries apply the exit cap now (``exits``, or by default while time
        stepping)."""
        return self.time_stepping if self.exits is None else bool(self.exits)

    @property
    def passing_through(self) -> bool:
        """Whether the last query's cap (below 1) was set by a vertex leaving a body through
        its far side (the exit cap), not by an entry."""
        return self.last_pair is not None and self.last_pair[0] == PASS_THROUGH

    @property
    def num_triangles(self) -> int:
        """Number of boundary triangles (all ranks)."""
        return int(self.tri.shape[0])

    def positions(self, u_owned: np.ndarray) -> np.ndarray:
        """Current positions (nb, 3) of all boundary vertices, from this rank's owned dof
        values of the displacement (3 per owned vertex; collective)."""
        x = np.empty_like(self.X)
        x[self._gather_order] = allgather_rows(self.comm, self._owned_boundary(u_owned))
        x += self.X
        return x

    def _owned_boundary(self, u_owned: np.ndarray) -> np.ndarray:
        """The displacements (n, 3) of this rank's owned boundary vertices, in gather order."""
        u = np.asarray(u_owned)[: self._n_owned_dofs].reshape(-1, 3)
        return u[self._owned_rows].astype(FLOAT)

    def travel(self, u0_owned: np.ndarray, u1_owned: np.ndarray) -> float:
        """The longest distance a boundary vertex moves on the step from ``u0`` to ``u1``
        (owned dof values, as :meth:`step_fraction`; collective)."""
        d = self._owned_boundary(u1_owned) - self._owned_boundary(u0_owned)
        local = float(np.sqrt((d**2).sum(axis=1)).max()) if d.size else 0.0
        return self.comm.allreduce(local, op=MPI.MAX)

    def newton_fraction(self, u0_owned: np.ndarray, u1_owned: np.ndarray) -> float:
        """The fraction of a Newton step from ``u0`` to ``u1`` (owned dof values) to take:
        the step first shortened so that no boundary vertex moves more than
        ``max_travel``, then that step's :meth:`step_fraction` (collective)."""
        travel = self.travel(u0_owned, u1_owned)
        if not travel > self.max_travel:
            return self.step_fraction(u0_owned, u1_owned)
        bound = self.max_travel / travel
        u0 = np.asarray(u0_owned)
        return bound * self.step_fraction(u0, u0 + bound * (np.asarray(u1_owned) - u0))

    def _swept_pairs(
        self, points: np.ndarray, travel: np.ndarray, entry: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ordered triangle pairs ``(a, b)``, ``a`` owned, whose swept boxes overlap and
        which the sweep has to test. With the exit cap, all of them. Without it, those where
        one of the two triangles has a vertex moving more than half ``STILL_REACH`` times the
        smallest entry tolerance (for any other pair ``sweep_caps`` finds every entry cap 1):
        the moving triangles' boxes are queried, and each pair with a still triangle is taken
        both ways round. Where more triangles move than the rank owns, the owned ones are
        queried instead. ``travel``: :func:`triangle_travel` of the step."""
        owned = self._owned_tri
        if not self.exits_active:
            reach = 0.5 * STILL_REACH * float(entry.min())
            still = travel <= reach  # (NaN: moving)
            moving = np.flatnonzero(~still)
            if moving.size < owned.size:
                lo, hi = element_boxes(points, self._swept_cells[moving])
                qm, qb = self._tree.query_boxes(lo, hi)
                qm = moving[qm]
                back = still[qb]
                a = np.concatenate((qm, qb[back]))
                b = np.concatenate((qb, qm[back]))
                mine = (a >= owned[0]) & (a <= owned[-1])
                return a[mine], b[mine]
        lo, hi = element_boxes(points, self._swept_cells[owned])
        qa, qb = self._tree.query_boxes(lo, hi)
        return owned[qa], qb

    def step_fraction(
        self, u0_owned: np.ndarray, u1_owned: np.ndarray, entry_scale: float = 1.0
    ) -> float:
        """The fraction of the step from ``u0`` to ``u1`` (owned dof values) that keeps every
        pair apart at ``u0`` from going deeper than its entry tolerance past first contact
        (1: the whole step; collective, the same on every rank).

        Args:
            u0_owned: displacement at the step's start, this rank's owned dofs (or more:
                ghosts after them are ignored).
            u1_owned: displacement at the step's end, the same layout.
            entry_scale: the entry tolerances times this (> 0) for this query: a pair counts
                as apart at ``u0`` beyond the scaled tolerance, and may go that deep.
        """
        if not entry_scale > 0.0:
            raise ValueError(f"entry_scale must be > 0, got {entry_scale}")
        tic = time.perf_counter()
        x0 = self.positions(u0_owned)
        x1 = self.positions(u1_owned)
        nb = x0.shape[0]
        best, capped, which = 1.0, 0, (-1, -1, -1)
        if self._owned_tri.size and nb:
            points = np.ascontiguousarray(np.vstack((x0, x1)))
            if self._tree is None:
                self._tree = AABBTree(points, self._swept_cells)
            else:
                self._tree.refit(points)
                if self._tree.needs_rebuild():
                    self._tree.rebuild(points)
            entry = self.entry if entry_scale == 1.0 else entry_scale * self.entry
            travel = triangle_travel(x0, x1, self.tri)
            pair_a, pair_b = self._swept_pairs(points, travel, entry)
            best, capped, kind, i, j = sweep_caps(
                x0, x1, self.tri, self.tri_edge, self.edges, self.vertex_owner,
                self.edge_owner, entry, pair_a, pair_b, self.exits_active, self._bodies,
                travel=travel,
            )  # fmt: skip
            which = (int(kind), int(i), int(j))
        best_all, rank = self.comm.allreduce((float(best), self.comm.rank), op=MPI.MINLOC)
        self.capped = self.comm.allreduce(int(capped))
        pair = self.comm.bcast(which, root=rank)
        self.last_pair = pair if best_all < 1.0 else None
        self.queries += 1
        self.seconds += time.perf_counter() - tic
        return float(best_all)


def penalty_needed(contact, kinetic_energy: float) -> float | None:
    """The penalty that would store the kinetic energy ``K`` at the overlap the contact holds
    now (energy ``E_c``; it scales with the penalty): ``eps (K + E_c) / E_c``, or None where
    nothing overlaps (collective).

    Args:
        contact: the problem's :class:`~fenics_matdepth.ContactOperator`, updated at the state
            reached.
        kinetic_energy: the kinetic energy there (F L).
    """
    stored = contact.energy()
    if not (stored > 0.0 and np.isfinite(kinetic_energy)):
        return None
    return contact.penalty * (kinetic_energy + stored) / stored


def pass_through_message(contact, kinetic_energy: float) -> str:
    """Why a surface held against a body's far side cannot go on, and the penalty that would
    stop it: the contact stores ``E_c`` at the overlap reached (it is largest about there: a
    layer's depth peaks at its middle), against the kinetic energy ``K``; the energy stored at
    a given overlap scales with the penalty, so a penalty about ``(K + E_c) / E_c`` times
    higher would store all of it (collective).

    Args:
        contact: the problem's :class:`~fenics_matdepth.ContactOperator`, updated at the state
            reached.
        kinetic_energy: the kinetic energy there (F L).
    """
    stored = contact.energy()
    sentence = (
        "A surface would pass through a body: a boundary vertex inside it would leave through "
        "the body's far side within the smallest step, and the collision detection holds it "
        f"there. The penalty cannot stop the motion within the layer: at this overlap the "
        f"contact stores {stored:.3g} against a kinetic energy of {kinetic_energy:.3g}"
    )
    needed = penalty_needed(contact, kinetic_energy)
    if needed is not None:
        sentence += (
            f"; a penalty of about {needed:.3g} (now {contact.penalty:.3g}; about 2 K / (A t^2) "
            "for kinetic energy K, contact area A and layer thickness t) would, or a thicker "
            "layer, or a slower impact"
        )
    return sentence + "."
