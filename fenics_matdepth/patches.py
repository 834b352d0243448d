"""The energy, gradient and Hessian of a contact problem on a patch of vertices, the others
held, assembled over the patch's cells and contact pairs only (for
:class:`~fenics_matdepth.relaxation.LocalRelaxation`), serially or on a distributed mesh.

:class:`PatchAssembly` compiles the bulk energy and its first two derivatives once; for each
patch it makes DOLFINx forms of the same compiled code whose cell integrals run over the owned
cells touching a patch vertex (``dolfinx.fem.create_form`` with those cells as the integrals'
subdomains), and the contact pairs that hold a patch vertex and lie within ``NEAR_EDGES`` mean
boundary edges (area integration: searched round the patch's vertices; collocation: of the
contact operator's candidate pairs). A patch's energy differs from
the whole problem's by the energy of what it does not touch, which the patch's vertices do not
change; its gradient and Hessian at the patch's dofs are the whole problem's. A trial state
that inverts a patch cell (or, with ``det_floor``, brings its det F that close to 0) has
infinite energy.

A patch is numbered by its global dofs, the same on every process. In parallel each process
assembles its owned cells and the contact pairs it evaluates (each cell and pair once over the
processes) into the patch's numbering, ghost rows included, and the sums are reduced on one
process and broadcast (``_mpi.summed``), so that every process holds the same patch gradient,
Hessian and energy to the bit and takes the same local steps. Every call of a
:class:`PatchModel` is collective.

Left out: friction; pairs that a local step brings into contact from further apart; and the
dofs of vertices on a facet of an exterior-facet integral (a spring or a dead load on a
boundary), which are held.
"""

from __future__ import annotations

import types

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl

from fenics_matdepth._bulk import everywhere_numbered
from fenics_matdepth._mpi import positions, summed
from fenics_matdepth.contact import evaluation, pairs
from fenics_matdepth.contact.kernels.drivers import intersecting
from fenics_matdepth.geometry.intersect import near_pairs

__all__ = ["PatchAssembly", "PatchModel"]

#: the contact pairs of a patch: the pairs holding a patch vertex whose triangle and
#: tetrahedron lie within this many mean boundary edges of each other
NEAR_EDGES = 0.1


def _subdomain_ids(ident) -> list[int] | None:
    """The integer ids of a UFL integral's subdomain (None: everywhere)."""
    if ident in ("everywhere", "otherwise"):
        return None
    return [int(i) for i in ident] if isinstance(ident, tuple) else [int(ident)]


class PatchAssembly:
    """Patch models (:meth:`model`) of a contact problem whose bulk energy is ``energy``.

    Args:
        energy: the bulk energy (UFL) of ``u``, in N mm (or the unit of the problem's
            residual times the displacement's); its integrals are cell integrals (over cell
            tags or everywhere) and exterior-facet integrals, whose vertices are held.
        u: the displacement (P1 on tetrahedra).
        contact: the contact operator of ``u`` (its state is the one at :meth:`model`).

    Raises:
        NotImplementedError: for another kind of integral (interior facets, vertices).
    """

    def __init__(self, energy: ufl.Form, u: dolfinx.fem.Function, contact):
        V = u.function_space
        mesh = V.mesh
        self.u, self.V, self.mesh, self.contact = u, V, mesh, contact
        self.comm = mesh.comm
        #: a patch's trial states whose lowest det F is at most this fraction of the patch's
        #: lowest at its start are refused (0: only inverted cells)
        self.det_floor = 0.0
        # an integral over every cell under an id of its own, one more than the largest: a
        # patch's forms are given the patch's cells (before, a patch of psi * ufl.dx assembled
        # the whole mesh)
        ids = [i for itg in energy.integrals() for i in _subdomain_ids(itg.subdomain_id()) or []]
        everywhere = max(ids, default=0) + 1
        energy = everywhere_numbered(energy, everywhere)
        residual = ufl.derivative(energy, u, ufl.TestFunction(V))
        jacobian = ufl.derivative(residual, u, ufl.TrialFunction(V))
        self._compiled = [
            (dolfinx.fem.compile_form(mesh.comm, form), form, spaces)
            for form, spaces in ((energy, []), (residual, [V]), (jacobian, [V, V]))
        ]
        imap = V.dofmap.index_map
        self.n_owned = imap.size_local
        #: the global vertex (dof block) of each of this process's, owned then ghosts
        self.global_vertex = imap.local_to_global(
            np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
        ).astype(np.int64)
        #: the global dof of each of this process's dofs (3 a vertex)
        self.global_dof = (3 * self.global_vertex[:, None] + np.arange(3)).ravel()
        #: the owned cells (this process's vertex numbering), each assembled by its owner
        self.cells = np.asarray(V.dofmap.list)[: mesh.topology.index_map(3).size_local]
        self._cells_global = self.global_vertex[self.cells]
        self.X = V.tabulate_dof_coordinates()
        p = self.X[self.cells]
        self._volumes = np.linalg.det(p[:, 1:] - p[:, :1])  # each cell's, at rest
        # the cells of each cell integral's subdomain id (everywhere: None)
        self._cell_sets: dict[int, np.ndarray | None] = {}
        held = [np.empty(0, np.int32)]
        for itg in energy.integrals():
            kind, data = itg.integral_type(), itg.subdomain_data()
            ids = _subdomain_ids(itg.subdomain_id())
            if kind == "cell":
                for ident in ids:
                    self._cell_sets[ident] = None if ident == everywhere else data.find(ident)
            elif kind == "exterior_facet":
                facets = (
                    dolfinx.mesh.exterior_facet_indices(mesh.topology)
                    if ids is None
                    else np.concatenate([data.find(i) for i in ids])
                )
                held.append(dolfinx.fem.locate_dofs_topological(V, mesh.topology.dim - 1, facets))
            else:
                raise NotImplementedError(
                    f"the energy has {kind} integrals, which a patch cannot assemble over its "
                    "cells: leave the local relaxation off for this problem"
                )
        blocks = self.global_vertex[np.concatenate(held)]
        blocks = np.unique(np.concatenate(self.comm.allgather(blocks)))
        #: global dofs held on every patch (on a facet of an exterior-facet integral)
        self.held = (3 * blocks[:, None] + np.arange(3)).ravel()

    def around(self, vertices: np.ndarray) -> np.ndarray:
        """The global vertices of the cells touching one of the global ``vertices``, sorted
        (collective)."""
        mine = np.unique(self._cells_global[self.touching(vertices)])
        if self.comm.size == 1:
            return mine
        return np.unique(np.concatenate(self.comm.allgather(mine)))

    def touching(self, vertices: np.ndarray) -> np.ndarray:
        """Whether each owned cell (``cells``) has one of the global ``vertices``: a mask of
        this process's vertices, gathered by cell (testing every cell's four global numbers,
        and every candidate pair's seven, against ``vertices`` took 2.7 s of the 18.8 s the
        knee's relaxation spent from 141 to 150 deg)."""
        return np.isin(self.global_vertex, vertices)[self.cells].any(axis=1)

    def model(self, dofs: np.ndarray) -> PatchModel:
        """The patch of the free global dofs ``dofs`` (sorted, whole vertices, the same on
        every process), with the contact pairs round it now (collective)."""
        return PatchModel(self, np.asarray(dofs, dtype=np.int64))

    def forms(self, cells: np.ndarray) -> list[dolfinx.fem.Form]:
        """The energy, residual and Jacobian forms over ``cells`` (sorted)."""
        subdomains = []
        for ident in sorted(self._cell_sets):
            members = self._cell_sets[ident]
            chosen = cells if members is None else np.intersect1d(members, cells)
            subdomains.append((ident, chosen.astype(np.int32)))
        out = []
        for compiled, form, spaces in self._compiled:
            out.append(
                dolfinx.fem.create_form(
                    compiled,
                    spaces,
                    self.mesh,
                    {dolfinx.fem.IntegralType.cell: subdomains},
                    {c: c for c in form.coefficients()},
                    {c: c for c in form.constants()},
                )
            )
        return out


class PatchModel:
    """One patch: energy, gradient and Hessian at its dofs' values of a full state ``x``, in
    the patch's numbering (its sorted global dofs), the same on every process. Collective."""

    def __init__(self, owner: PatchAssembly, dofs: np.ndarray):
        self.owner, self.dofs = owner, dofs
        self.floor: float | None = None  # the lowest det F a trial state may have (energy)
        vertices = np.unique(dofs // 3)
        self.cells = np.flatnonzero(owner.touching(vertices)).astype(np.int32)  # owned, local
        self.energy_form, self.residual_form, self.jacobian_form = owner.forms(self.cells)
        self.matrix = dolfinx.fem.create_matrix(self.jacobian_form)
        # this process's dofs in the patch (owned and ghosts) and their patch positions
        at = positions(dofs, owner.global_dof)
        self.rows = np.flatnonzero(at >= 0)
        self.rows_at = at[self.rows]
        owned = self.rows < 3 * owner.n_owned
        self._owned_rows = self.rows[owned].astype(PETSc.IntType)  # = the PETSc vector's
        self._owned_at = self.rows_at[owned]
        self._owned_global = dofs[self._owned_at].astype(PETSc.IntType)
        contact = owner.contact
        s = contact.surface
        held = np.isin(s.global_vertex, vertices)
        if contact.integration == "area":
            # the pairs within NEAR_EDGES mean boundary edges (wider ones cost most of a
            # patch's time: 0.3 s a patch at 0.5 edges on the knee; a local step that closes a
            # wider gap misses that pair), searched round the patch: the operator's candidates
            # may be those of coordinates a skin away (PairSearch)
            near = NEAR_EDGES * s.mean_edge
            pa, pk = pairs.pairs_touching(s, held, near)
            pa, pk = near_pairs(s.x, s.tri, s.tets, pa, pk, near)
        else:
            search = contact.pair_search
            chosen = pairs.pairs_holding(s, contact.integration, search.pair_a, search.pair_k, held)
            pa, pk = search.pair_a[chosen], search.pair_k[chosen]
        self.pair_a, self.pair_k = pa, pk
        # the pairs' dofs in the patch's numbering (-1: held)
        held = s.global_vertex[pairs.pair_vertices(s, contact.integration, pa, pk)]
        held_dofs = (3 * held[:, :, None] + np.arange(3)).reshape(pa.size, 3 * held.shape[1])
        self.pair_dofs = positions(dofs, held_dofs)

    def values(self, x: PETSc.Vec) -> np.ndarray:
        """The patch's dofs' values in ``x`` (a vector of the problem's layout)."""
        v = np.zeros(self.dofs.size)
        v[self._owned_at] = x.getArray(readonly=True)[self._owned_rows]
        return summed(self.owner.comm, v)

    def put(self, x: PETSc.Vec, values: np.ndarray) -> None:
        """Set the patch's dofs of ``x`` to ``values`` (the patch's numbering)."""
        x.setValues(self._owned_global, values[self._owned_at])
        x.assemble()

    def _set(self, x: PETSc.Vec) -> None:
        u = self.owner.u
        if x.handle == u.x.petsc_vec.handle:
            raise ValueError("a patch model evaluates states apart from u's own vector")
        u.x.array[: 3 * self.owner.n_owned] = x.getArray(readonly=True)
        u.x.scatter_forward()

    def _contact(self, want_grad: bool, want_hess: bool) -> tuple:
        """Which patch pairs meet at ``u`` (an index; with area integration those whose
        triangle meets the tetrahedron, the operator's own test, else all) and the pair
        kernel's (energies, gradients, Hessians) of those. The kernel gives the others no
        energy, and they are most of a patch's pairs (on the knee's last three steps two thirds
        to 85 %, of 579 to 4,054): the kernel on them took half of the patches' contact time."""
        contact = self.owner.contact
        s = contact.surface
        shift = s.pull(self.owner.u.x.array[: 3 * self.owner.n_owned].reshape(-1, 3))
        current = types.SimpleNamespace(
            x=s.X + shift, kernel_depth=s.kernel_depth, tri=s.tri, kernel_tets=s.kernel_tets,
            weight=s.weight, nodes=s.nodes, global_vertex=s.global_vertex,
        )  # fmt: skip
        hit = np.arange(self.pair_a.size)
        if contact.integration == "area":
            hit = intersecting(current.x, s.tri, s.kernel_tets, self.pair_a, self.pair_k)
        return (hit,) + evaluation.pair_arrays(
            current, contact.integration, self.pair_a[hit], self.pair_k[hit], contact.penalty,
            contact.pressure, contact.pressure_width, want_grad, want_hess,
        )  # fmt: skip

    def energy(self, x: PETSc.Vec) -> float:
        """The patch's energy at ``x``: ``inf`` where a patch cell is inverted, or its det F
        is at most ``det_floor`` times the patch's lowest at the first state asked for (the
        patch's start)."""
        self._set(x)
        owner = self.owner
        cells = owner.cells[self.cells]
        p = owner.X[cells] + owner.u.x.array.reshape(-1, 3)[cells]  # the patch cells' vertices
        volumes = np.linalg.det(p[:, 1:] - p[:, :1])
        lowest = (volumes / owner._volumes[self.cells]).min() if cells.size else np.inf
        lowest = owner.comm.allreduce(lowest, op=MPI.MIN)
        if self.floor is None:
            self.floor = owner.det_floor * max(lowest, 0.0)
        if not (lowest > 0.0 and lowest > self.floor):
            return np.inf
        value = dolfinx.fem.assemble_scalar(self.energy_form)
        hit, energies, _, _ = self._contact(False, False)
        every = np.zeros(self.pair_a.size)  # summed over every pair, as the kernel gave them
        every[hit] = energies
        value += float(np.sum(every))
        value = float(summed(owner.comm, [value])[0])
        return value if np.isfinite(value) else np.inf

    def gradient(self, x: PETSc.Vec) -> np.ndarray:
        """The energy's gradient at the patch's dofs, at ``x``."""
        self._set(x)
        g = np.zeros(self.dofs.size)
        g[self.rows_at] = dolfinx.fem.assemble_vector(self.residual_form).array[self.rows]
        hit, energy, grad, _ = self._contact(True, False)
        d, grad = self.pair_dofs[hit[energy > 0.0]], grad[energy > 0.0]  # the pairs in contact
        keep = d >= 0
        np.add.at(g, d[keep], grad[keep])
        return summed(self.owner.comm, g)

    def hessian(self, x: PETSc.Vec) -> np.ndarray:
        """The energy's Hessian on the patch's dofs (dense), at ``x``."""
        self._set(x)
        self.matrix.set_value(0.0)
        dolfinx.fem.assemble_matrix(self.matrix, self.jacobian_form)
        K = np.zeros((self.dofs.size, self.dofs.size))
        local = self.matrix.to_scipy(ghosted=True).tocsr()[self.rows][:, self.rows]
        K[np.ix_(self.rows_at, self.rows_at)] = local.toarray()
        hit, energy, _, hess = self._contact(True, True)
        d, hess = self.pair_dofs[hit[energy > 0.0]], hess[energy > 0.0]  # the pairs in contact
        keep = (d[:, :, None] >= 0) & (d[:, None, :] >= 0)
        rows = np.broadcast_to(d[:, :, None], hess.shape)[keep]
        cols = np.broadcast_to(d[:, None, :], hess.shape)[keep]
        np.add.at(K, (rows, cols), hess[keep])
        return summed(self.owner.comm, K)
