"""ContactOperator: the material-depth contact energy of a P1 displacement, in PETSc terms.

The operator owns the contact geometry of one dolfinx mesh (all bodies in one mesh) and adds
the exact first and second derivatives of the contact energy into dolfinx-assembled PETSc
vectors and matrices. It is a thin class over these modules:

* :mod:`fenics_matdepth.contact.surface`: what a rank holds (vertices, tetrahedra, boundary
  triangles, depths, the AABB tree over its tetrahedra) and how it follows ``u``;
* :mod:`fenics_matdepth.contact.pairs`: candidate pairs (the :class:`PairSearch` kept from
  one update to the next) and the sparsity-pattern couplings;
* :mod:`fenics_matdepth.contact.evaluation`: the pair kernels over the evaluated pairs;
* :mod:`fenics_matdepth.contact.assembly`: sums per dof and insertion into PETSc;
* :mod:`fenics_matdepth.contact.diagnostics`: penetration, forces and pressures of the state;
* :mod:`fenics_matdepth.contact.checks`: the checks of a new operator's state.

Each rank handles the boundary triangles whose facets it owns, so every (triangle,
tetrahedron) pair is evaluated once across the ranks; contributions to dofs owned by other
ranks go through PETSc's off-process assembly (VecSetValues / MatSetValues stashes).

Numbering: the vertices of the operator are the *blocks* of the P1 vector space of ``u``,
in the global block numbering of its index map; the dof of component c of vertex v is
``3 v + c`` (PETSc global numbering of dolfinx vectors and matrices).
"""

from __future__ import annotations

import contextlib
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._jit import announces_compilation
from fenics_matdepth.contact import assembly, diagnostics, evaluation, pairs
from fenics_matdepth.contact.checks import check_contact_state
from fenics_matdepth.contact.friction import Coulomb, FrictionMixin
from fenics_matdepth.contact.surface import ContactSurface, DepthDeficiencyWarning
from fenics_matdepth.depth import DepthDeficiency
from fenics_matdepth.mesh_checks import check_contact_mesh

__all__ = ["ContactOperator", "DepthDeficiencyWarning", "propose_penalty"]

_INTEGRATIONS = ("area", "collocation")


class ContactOperator(FrictionMixin):
    """Material-depth penalty contact energy of the displacement ``u`` and its derivatives.

    Args:
        u: displacement, a Function on a P1 (Lagrange degree 1) vector space of dimension 3 on an
            affine tetrahedral mesh (length L).
        depth: material depth, a P1 scalar Function on the same mesh (from
            :func:`fenics_matdepth.material_depth`) (L).
        penalty: penalty parameter eps (pressure / length, F/L^3). Contact pressure is eps * g.
        integration: ``"area"`` (exact integration over triangle-tetrahedron intersection
            polygons, the paper's method) or ``"collocation"`` (boundary vertices only, the
            baseline that chatters).
        margin: inflation (L) of the triangle boxes used to find candidate pairs for the matrix
            sparsity pattern, so that the pattern survives motion of up to about ``margin``;
            default: one tenth of the mean boundary edge length.
        split_deficient: give every depth-deficient tetrahedron (all four vertices at depth 0,
            so depth 0 everywhere inside: layers one element thick, edges and corners of
            coarse meshes) an interior depth by evaluating it as four sub-tetrahedra around
            its centroid, which gets its exact distance to the boundary (default). The mesh
            and the function spaces are untouched; ``False`` keeps the plain P1 depth, through
            which a surface entering such a tetrahedron passes without force.
        allow_reference_overlap: accept bodies that overlap in the reference configuration
            (by default a ``ValueError``: their material depth is wrong).
        friction: ``fm.Coulomb(mu, slip_tol)`` for Coulomb friction over the intersection
            polygons (area integration; see :mod:`fenics_matdepth.contact.friction`), or None.
            Its reference state is ``u`` now; :meth:`advance` moves it on.

    Typical use in a Newton loop: ``update()`` at each iterate, then ``add_residual(b)`` and
    ``add_jacobian(A, bcs)`` after dolfinx has assembled the bulk terms into ``b`` and ``A``;
    ``A`` must come from :meth:`create_matrix`.
    """

    @announces_compilation("the contact operator (pair search, overlap check)")
    def __init__(
        self,
        u: dolfinx.fem.Function,
        depth: dolfinx.fem.Function,
        penalty: float,
        integration: typing.Literal["area", "collocation"] = "area",
        margin: float | None = None,
        split_deficient: bool = True,
        allow_reference_overlap: bool = False,
        friction: Coulomb | None = None,
    ):
        V = u.function_space
        mesh = V.mesh
        check_contact_mesh(mesh)
        if V.dofmap.index_map_bs != 3 or V.ufl_element().degree != 1:
            raise ValueError(
                "ContactOperator needs u on a P1 vector space of dimension 3, e.g. "
                'functionspace(mesh, ("Lagrange", 1, (3,)))'
            )
        if depth.function_space.mesh is not mesh or depth.function_space.dofmap.index_map_bs != 1:
            raise ValueError("depth must be a P1 scalar Function on the mesh of u")
        if integration not in _INTEGRATIONS:
            raise ValueError(f"integration must be one of {_INTEGRATIONS}, got {integration!r}")
        self._cache: dict[str, typing.Any] = {}
        self._penalty, self._penalty_revision = None, -1  # the setter makes this revision 0
        self.penalty = penalty
        self.u = u
        self.integration = integration
        self.comm: MPI.Comm = mesh.comm
        # the deficiency warning's stacklevel (4): the surface's set-up and __init__, this
        # __init__, the compile-notice wrapper
        self.surface = ContactSurface(u, depth, integration, margin, split_deficient, 4)
        s = self.surface
        self.num_vertices = s.num_vertices
        self.num_bodies, self.body_of_vertex = s.num_bodies, s.body_of_vertex
        self.split_deficient = s.split_deficient
        self.depth_deficiency: DepthDeficiency = s.depth_deficiency
        self.num_split_tets = s.num_split_tets
        self.margin = s.margin

        self._u_last: np.ndarray | None = None
        #: the candidate pairs and when to search them again (see :attr:`pair_skin`)
        self.pair_search = pairs.PairSearch(
            integration, pairs.PAIR_SKIN * s.mean_edge if integration == "area" else 0.0
        )
        self._pattern_keys: np.ndarray | None = None  # global couplings of the matrix pattern
        self._bulk: assembly.BulkPattern | None = None  # the bulk form's, for the rebuilds
        self._held_keys: np.ndarray | None = None  # the same in the held numbering
        self._held_transposed = np.empty(0, dtype=INDEX)  # where each has its transpose
        self._held_refreshes = -1  # the halo build they were made for
        self._pressure: np.ndarray | None = None  # augmented Lagrangian, see set_pressure
        self._pressure_width = 0.0
        # the fused passes (`_summed`), with output buffers reused from state to state
        self._summed_pass = evaluation.SummedPass()
        # the surface holds, until the first update, what its triangles meet at u = 0
        check_contact_state(s, allow_reference_overlap)
        self.update()
        self._init_friction(friction)

    @property
    def penalty(self) -> float:
        """The penalty parameter eps (pressure / length); assignable between solves (the next
        evaluation uses the new value). The operator is the one owner of the penalty: a solver
        that must know whether it changed reads :attr:`penalty_revision`, and a temporary
        value is set with :meth:`penalty_set_to`."""
        return self._penalty

    @penalty.setter
    def penalty(self, value: float) -> None:
        value = float(value)
        if not np.isfinite(value) or value <= 0.0:
            raise ValueError(f"penalty must be a positive number (pressure/length), got {value}")
        if value != self._penalty:
            self._penalty_revision += 1
        self._penalty = value
        self._cache.clear()  # energies, gradients and Hessians scale with eps

    @property
    def penalty_revision(self) -> int:
        """The number of times the penalty has changed value since the operator was built. Equal
        revisions mean the same penalty, and so the same contact stiffness at one state."""
        return self._penalty_revision

    @contextlib.contextmanager
    def penalty_set_to(self, value: float) -> typing.Iterator[ContactOperator]:
        """The penalty ``value`` inside a ``with`` block, the one before restored after it
        (penalty continuation solves its stages this way)."""
        before = self._penalty
        self.penalty = value
        try:
            yield self
        finally:
            self.penalty = before

    @property
    def pair_skin(self) -> float:
        """The skin of the candidate pairs (L; with area integration one tenth of the mean
        boundary edge length by default, with collocation 0). The pair search inflates the
        triangle boxes by it, and its pairs serve later updates until some held vertex has
        moved by more than about half of it (no pair can then have come into contact unseen).
        With 0 the operator searches at every update, as it always does with collocation,
        whose kernel evaluates every candidate. Assignable; the next update searches anew."""
        return self.pair_search.skin

    @pair_skin.setter
    def pair_skin(self, value: float) -> None:
        self.pair_search.skin = value

    @property
    def pair_searches(self) -> int:
        """The pair searches of the whole surface so far, on this process (the other updates
        reused the candidates or searched round the moved vertices: ``pair_search``)."""
        return self.pair_search.searches

    # -- geometry -------------------------------------------------------------------------

    @announces_compilation("the pair search")
    def update(self) -> None:
        """Refit the tree to the current ``u`` and find the candidate pairs (collective).

        Nothing is recomputed when ``u`` has not changed since the last update (a line search
        evaluating the energy and then the residual at the same point pays once).
        """
        u_owned = self.u.x.array[: self.surface.owned_dof_count()]
        bad = not np.all(np.isfinite(u_owned))
        if self.comm.allreduce(bad, op=MPI.LOR):
            raise FloatingPointError(
                "the displacement contains NaN or inf: the previous solve diverged; reduce "
                "the load step or the penalty"
            )
        same = self._u_last is not None and np.array_equal(u_owned, self._u_last)
        if self.comm.allreduce(same, op=MPI.LAND):
            return
        self._u_last = u_owned.copy()
        self.surface.update()
        self.pair_search.update(self.surface)
        if self.surface.refreshes != self._held_refreshes:
            self._held_keys = None  # a new halo numbers the held vertices anew
        self._cache.clear()

    # -- pair contributions ---------------------------------------------------------------

    @announces_compilation("the contact pair integrals")
    def _evaluate(self, want_grad: bool, want_hess: bool) -> dict[str, np.ndarray]:
        want_grad = want_grad or want_hess  # the kernels compute the Hessian with the gradient
        key = f"{want_grad}{want_hess}"
        # a pass that computed more serves a request for less
        for have in ("TrueTrue", "TrueFalse", "FalseFalse")[: 3 - want_grad - want_hess]:
            if have in self._cache:
                return self._cache[have]
        energy, grad, hess = self._kernel_pass(None, want_grad, want_hess)
        out = {"energy": energy, "grad": grad, "hess": hess, "verts": self._pair_verts()}
        if self.integration == "area":
            out["active"] = self._intersecting_pairs()
        self._cache[key] = out
        return out

    def _kernel_pass(
        self, select: np.ndarray | None, want_grad: bool, want_hess: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pair kernel's (energy, gradient, Hessian) arrays of the pairs `_pair_verts` lists
        (the intersecting area pairs, every collocation pair), or of its rows ``select``."""
        pa, pk = self._evaluated_pairs()
        if select is not None:
            pa, pk = pa[select], pk[select]
        return evaluation.pair_arrays(
            self.surface, self.integration, pa, pk, self.penalty, self._pressure,
            self._pressure_width, want_grad, want_hess,
        )  # fmt: skip

    def _pair_verts(self) -> np.ndarray:
        """The held vertices of the pairs the kernels evaluate ((n, 7) for the intersecting
        area pairs, (n, 5) for every collocation pair), kept until the next :meth:`update`."""
        if "verts" not in self._cache:
            pa, pk = self._evaluated_pairs()
            self._cache["verts"] = pairs.pair_vertices(self.surface, self.integration, pa, pk)
        return self._cache["verts"]

    def _evaluated_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """The (contact element, tetrahedron) pairs the kernels evaluate: the intersecting
        candidates with area integration, every candidate with collocation."""
        search = self.pair_search
        if self.integration == "area":
            active = self._intersecting_pairs()
            return search.pair_a[active], search.pair_k[active]
        return search.pair_a, search.pair_k

    def _sums_fused(self) -> bool:
        """Whether residual and Jacobian are summed as the pair kernel makes them (`_summed`;
        plain penalty, area integration), not from the per-pair arrays of `_evaluate`."""
        return self.integration == "area" and self._pressure is None

    @announces_compilation("the contact pair integrals")
    def _summed(self, want_hess: bool) -> dict[str, np.ndarray]:
        """The pairs' energies, their gradient summed per held dof and, with ``want_hess``,
        their Hessians summed into the pattern's 3 x 3 blocks (:class:`evaluation.SummedPass`),
        kept until the next :meth:`update` (a Hessian pass serves a gradient request). The
        returned arrays are the operator's buffers, valid until the next pass."""
        if "summed_hess" in self._cache:
            return self._cache["summed_hess"]
        if not want_hess and "summed_grad" in self._cache:
            return self._cache["summed_grad"]
        pa, pk = self._evaluated_pairs()
        pos = keys = None
        if want_hess:
            pos = self._coupling_positions()
            keys = self._pattern_in_held_numbering()
        out = self._summed_pass(self.surface, pa, pk, self.penalty, pos, keys)
        self._cache["summed_hess" if want_hess else "summed_grad"] = out
        return out

    def _intersecting_pairs(self) -> np.ndarray:
        """Indices of the candidate pairs whose intersection is not empty, kept until the next
        :meth:`update`: the energy, gradient and Hessian passes at one state share the test
        (24 ms of 188k candidates on the 40k-tetrahedron press)."""
        if "intersecting" not in self._cache:
            self._cache["intersecting"] = self.pair_search.intersecting(self.surface)
        return self._cache["intersecting"]

    def energy(self) -> float:
        """Contact energy plus friction potential at the last :meth:`update` (collective; F L)."""
        if self._sums_fused():
            # with the gradient: a line search asks for the energy at the state whose residual
            # comes next, which then costs nothing (the energy alone is about 2/3 of the cost)
            r = self._summed(want_hess=False)
        else:
            r = self._evaluate(self.integration == "area", False)  # the same, as above
        return self.comm.allreduce(float(np.sum(r["energy"])) + self._friction_energy())

    def gradient_array(self) -> tuple[np.ndarray, np.ndarray]:
        """This rank's gradient contributions: (global dofs, values), duplicates summed."""
        if self._sums_fused():
            r = self._summed(want_hess=False)
            return assembly.gradient_from_sums(self.surface, r["grad_sum"], r["reached"])
        r = self._evaluate(True, False)
        return assembly.gradient_array(self.surface, r["verts"], r["grad"])

    def add_residual(self, b: PETSc.Vec) -> None:
        """``b += dE/du`` for a dolfinx-assembled residual vector (collective).

        Call after ``assemble_vector`` and before ``apply_lifting``/``ghostUpdate``/``set_bc``
        (or anywhere before ``set_bc``): contributions to other ranks' dofs are sent with
        PETSc's off-process assembly here.
        """
        dofs, vals = self.gradient_array()
        b.setValues(dofs.astype(PETSc.IntType), vals, addv=PETSc.InsertMode.ADD_VALUES)
        self._add_friction_residual(b)
        b.assemblyBegin()
        b.assemblyEnd()

    def add_lifting(self, b: PETSc.Vec, offset: np.ndarray) -> None:
        """``b += H[:, D] offset[D]``: the contact part of DOLFINx's lifting (collective).

        ``apply_lifting(b, [a], [bcs], x0=[x], alpha=-1)`` adds ``A[:, D] (g - x)[D]`` to the
        residual, which makes the Newton step with the Dirichlet columns of the Jacobian zeroed
        the exact Newton step towards the prescribed values ``g``; this adds the contact
        Hessian's share of that term (the friction's too), from the pairs that have a Dirichlet
        dof whose value is not yet reached (a body moved by prescribed displacements into
        contact; only their Hessians are evaluated). Rows of Dirichlet dofs are left out
        (``set_bc`` writes them).

        Args:
            b: the residual vector (before ``set_bc``).
            offset: (3 n_owned,) ``g - x`` at the owned Dirichlet dofs of :meth:`set_bcs`,
                zero elsewhere.
        """
        assembly.add_lifting_pairs(
            self.surface, b, offset, self._pair_verts,
            lambda sel: self._kernel_pass(sel, True, True)[2],
        )  # fmt: skip
        self._add_friction_lifting(b, offset)

    def set_bcs(self, bcs: typing.Sequence[dolfinx.fem.DirichletBC]) -> None:
        """Remember the Dirichlet dofs, whose Jacobian rows and columns stay out (collective)."""
        mask_local = np.zeros(self.surface.owned_dof_count(), dtype=bool)
        mask_local[assembly.owned_dirichlet_dofs(bcs)] = True
        self.surface.set_bcs(mask_local)
        self._cache.pop("summed_hess", None)  # its blocks leave out the Dirichlet rows

    def hessian_coo(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This rank's Hessian contributions (rows, cols, values), duplicates summed, sorted.

        Entries in a Dirichlet row or column (see :meth:`set_bcs`) are left out. Independent of
        any matrix pattern (a sort of all pair entries); :meth:`add_jacobian` sums into the
        pattern of :meth:`create_matrix` instead.
        """
        r = self._evaluate(False, True)
        return assembly.hessian_coo(self.surface, r["verts"], r["hess"])

    def pair_hessians(self) -> tuple[np.ndarray, np.ndarray]:
        """The evaluated pairs at the current state (area integration: the intersecting ones):
        their held vertices (n, 7) and Hessians (n, 21, 21)."""
        r = self._evaluate(False, True)
        return r["verts"], r["hess"]

    def pair_energies(self) -> tuple[np.ndarray, np.ndarray]:
        """This rank's evaluated pairs now: global vertices (n, 7; collocation n, 5), energies."""
        r = self._evaluate(False, False)
        return self.surface.global_vertex[r["verts"]], r["energy"]

    def _pattern_in_held_numbering(self) -> np.ndarray:
        if self._held_keys is None:
            keys = self._pattern_keys if self._pattern_keys is not None else np.empty(0, INDEX)
            self._held_keys = assembly.held_keys(self.surface, keys)
            self._held_transposed = assembly.transposed_keys(self.surface, self._held_keys)
            self._held_refreshes = self.surface.refreshes
        return self._held_keys

    def _pattern_transposed(self) -> np.ndarray:
        """Where each key of :meth:`_pattern_in_held_numbering` has its transpose."""
        self._pattern_in_held_numbering()
        return self._held_transposed

    def held_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """The pattern's sorted held-numbered couplings, and where each has its transpose."""
        return self._pattern_in_held_numbering(), self._pattern_transposed()

    @announces_compilation("the contact Jacobian assembly")
    def add_jacobian(
        self, A: PETSc.Mat, bcs: typing.Sequence[dolfinx.fem.DirichletBC] | None = None
    ) -> None:
        """``A += d2E/du2`` for a dolfinx-assembled matrix from :meth:`create_matrix`.

        Rows and columns of Dirichlet dofs are left as dolfinx set them. Call after dolfinx's
        ``assemble_matrix`` and its ``A.assemble()``; this method assembles ``A`` again
        (collective).

        Raises:
            RuntimeError: if a contact coupling falls outside the sparsity pattern of ``A``
                (the bodies moved further than the pattern's margin since ``create_matrix``).
        """
        if bcs is not None:
            self.set_bcs(bcs)
        pos = self._coupling_positions()
        if self._cache["pattern_missing"]:
            raise RuntimeError(
                "contact couplings fall outside the matrix sparsity pattern: call "
                "create_matrix(a) again (ContactProblem does this automatically), or build the "
                "operator with a larger margin"
            )
        keys = self._pattern_in_held_numbering()
        if self._sums_fused():
            r = self._summed(want_hess=True)
            assembly.insert_blocks(A, self.surface, keys, r["blocks"], r["touched"])
        else:
            r = self._evaluate(False, True)
            assembly.add_jacobian_blocks(A, self.surface, keys, pos, r["verts"], r["hess"])
        self._add_friction_jacobian(A)
        A.assemble()

    # -- sparsity ---------------------------------------------------------------------------

    def pattern_needs_rebuild(self) -> bool:
        """Whether a current contact coupling lies outside the pattern (collective).

        The answer is kept until the next :meth:`update` or :meth:`create_matrix`: a solver
        that asks before assembling does not pay again inside :meth:`add_jacobian`.
        """
        self._coupling_positions()
        return self._cache["pattern_missing"] or self._friction_outside_pattern()

    def _coupling_positions(self) -> np.ndarray:
        """The pattern index of every vertex coupling of the current pairs (see
        :func:`assembly.coupling_positions`), kept with whether any rank has one outside the
        pattern until the next :meth:`update` or :meth:`create_matrix` (collective on first
        call at a state)."""
        if "positions" not in self._cache:
            verts = self._pair_verts()
            pos, missing = assembly.coupling_positions(
                self.surface, self._pattern_in_held_numbering(), verts, self._pattern_transposed()
            )
            self._cache["positions"] = pos
            self._cache["pattern_missing"] = bool(self.comm.allreduce(missing > 0, op=MPI.LOR))
        return self._cache["positions"]

    @announces_compilation("the contact sparsity pattern")
    def create_matrix(
        self,
        a: dolfinx.fem.Form,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] | None = None,
    ) -> PETSc.Mat:
        """A PETSc matrix holding the bulk form's pattern plus the contact couplings.

        The contact part comes from the candidate pairs of triangle boxes inflated by
        ``margin``, so the pattern survives moderate motion; :meth:`add_jacobian` tells when
        it no longer does. Insertion into the returned matrix never mallocs (collective).

        Args:
            a: the compiled bulk Jacobian form (``dolfinx.fem.form``).
            bcs: the Dirichlet conditions the matrix will be assembled with
                (``assemble_matrix(A, a, bcs)`` and :meth:`add_jacobian`), or None. Given,
                the rows and columns of their dofs hold only the diagonal: the zeros assembly
                leaves there are not stored, so a factorisation does not treat them as
                nonzeros (smaller factors; docs/operator.md). Assemble such a matrix with these
                conditions only: a nonzero in a Dirichlet row or column raises.
        """
        keys = pairs.pattern_keys(self.surface, self.integration, self.margin, self.pair_search)
        keys = self._pattern_keys = self._with_friction_keys(keys)
        self._held_keys = None
        for stale in ("pattern_missing", "positions", "summed_hess"):  # (the old pattern's)
            self._cache.pop(stale, None)
        self._bulk = assembly.BulkPattern.of(a, self.num_vertices, self._bulk)  # the mesh stays
        dirichlet = None
        if bcs is not None:
            dirichlet = assembly.global_dirichlet_dofs(self.comm, self.u.function_space, bcs)
        return assembly.create_matrix(self.comm, self._bulk, keys, self.num_vertices, dirichlet)

    # -- augmented Lagrangian (nodal contact pressures; driver: fenics_matdepth.augmented) ---

    @property
    def pressure(self) -> np.ndarray | None:
        """Nodal contact pressures (global vertex numbering, pressure units), or ``None``."""
        return self._pressure

    #: (read-only) ``w`` (L) of the quadratic pressure term, or 0 (:meth:`set_pressure`)
    pressure_width = property(lambda self: self._pressure_width)

    def set_pressure(self, pressure: np.ndarray | None, width: float = 0.0) -> None:
        """Set the augmented Lagrangian's nodal contact pressures (``None``: plain penalty).

        With ``width = 0`` the energy becomes ``sum over pairs of int_{T cap K} (p g +
        (eps/2) g^2) dA``, ``p`` interpolated linearly on each penetrating boundary triangle
        from its vertices' values; with ``width = w > 0`` it is ``sum over pairs of
        ((eps + p_T / w) / 2) int_{T cap K} g^2 dA``, ``p_T`` the mean of the triangle's nodal
        pressures: the pressures stiffen the penalty, and the energy has no kink where a face
        lies flat on the other body (see ``kernels.augmented.area_pairs_augmented``). The
        derivatives are exact at fixed pressures.

        Args:
            pressure: ``(num_vertices,)`` values >= 0, the same on every rank (only boundary
                vertices matter).
            width: 0, or ``w`` (L) of the quadratic pressure term.
        """
        width = float(width)
        if not (np.isfinite(width) and width >= 0.0):
            raise ValueError(f"width must be a length >= 0, got {width}")
        if pressure is not None:
            pressure = np.ascontiguousarray(pressure, dtype=FLOAT)
            if pressure.shape != (self.num_vertices,):
                raise ValueError(
                    f"pressure must have shape ({self.num_vertices},), got {pressure.shape}"
                )
            if self.integration != "area":
                raise ValueError("nodal contact pressures need integration='area'")
        self._pressure = pressure
        self._pressure_width = width
        self._cache.clear()

    def pressure_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Per vertex, ``int mu_i g dA`` (L^3) and ``int mu_i dA`` (L^2) over every intersection
        polygon of the boundary triangles around vertex i (``mu_i`` its hat function on the
        triangle), at the last update: the Uzawa update's data (collective; global vertex
        numbering, the same on every rank)."""
        active = self._evaluate(False, False)["active"]
        search = self.pair_search
        return diagnostics.pressure_moments(
            self.surface, search.pair_a[active], search.pair_k[active]
        )

    def peak_pressure(self) -> np.ndarray:
        """Per vertex, the largest contact pressure at the deepest point of a penetrating
        boundary triangle around it: the maximum over the triangle's intersection polygons of
        ``k g``, ``k`` the pair's stiffness (``eps``, or ``eps + p_T / w`` with the quadratic
        pressure term, see :meth:`set_pressure`), at the last update; 0 where no triangle
        penetrates (collective; global vertex numbering, the same on every rank). The update of
        the quadratic pressure term (area integration)."""
        g, pair_a, _ = self.pair_depths()
        return diagnostics.peak_pressure(
            self.surface, g, pair_a, self.penalty, self._pressure, self._pressure_width
        )

    # -- diagnostics ------------------------------------------------------------------------

    def max_penetration(self) -> float:
        """Largest material depth reached by the contact surface at the last update (L).

        Area integration: the maximum of ``g_K`` over every intersection polygon; collocation:
        the maximum of ``g_K(x_a)`` over the boundary vertices inside a tetrahedron
        (collective).
        """
        return diagnostics.max_penetration(self.surface, self.pair_depths()[0])

    def vertex_penetration(self) -> np.ndarray:
        """Material depth reached by each boundary vertex at the last update (collective).

        For a boundary vertex a: ``g_K(x_a)``, the material depth at its current position of
        the tetrahedron K (not one of its own) that contains it, i.e. how deep the vertex lies
        in the other body (or, in self-contact, in another part of its own); 0 for a vertex in
        no such tetrahedron and for every vertex off the boundary. Points on a face count as
        inside (see ``kernels.collocation.point_depths``).

        The contact pressure the model applies at a penetrating surface point y is
        ``eps g(y)``, plus the interpolated nodal pressure ``p(y)`` with the augmented
        Lagrangian (the force density ``(p + eps g) grad g`` of area integration), so at a
        boundary vertex with ``g_a > 0`` it is ``eps g_a + p_a``. Where two bodies meet, both
        surfaces enter the other: the pressure transmitted across the interface is the sum of
        the two surfaces' values at the same place.

        Returns:
            (num_vertices,) depths (L) in the global vertex numbering, the same on every rank.
        """
        return diagnostics.vertex_penetration(self.surface, self.integration)

    def pair_depths(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This rank's evaluated pairs with their deepest material depth at the last update:
        ``(g, pair_a, pair_k)`` (``contact.diagnostics.pair_depths``)."""
        energy = self._evaluate(False, False)["energy"]
        pair_a, pair_k = self._evaluated_pairs()
        g = diagnostics.pair_depths(
            self.surface, self.integration, self.penalty, pair_a, pair_k, energy
        )
        return g, pair_a, pair_k

    def deepest_contact(self) -> dict[str, typing.Any] | None:
        """Where the contact surface reaches deepest at the last update (collective; the same
        on every rank): ``None`` where nothing penetrates, else a dict with

        - ``depth``: the material depth reached, :meth:`max_penetration` (L);
        - ``surface_vertices``: the global vertex numbers (those of ``u``'s index map) of the
          penetrating boundary triangle (area integration; one vertex for collocation), and
          ``tetrahedron_vertices``, the four of the tetrahedron it enters; with
          the ``body_of_vertex`` array they tell which bodies meet there;
        - ``surface_reference`` and ``tetrahedron_reference``: their centroids in the
          reference configuration, and ``surface_position``, the surface's now (L);
        - ``local_h``: the mean reference edge length of the triangle, the local element size
          to judge the depth by (L; None for collocation).
        """
        g, pair_a, pair_k = self.pair_depths()
        return diagnostics.deepest_contact(self.surface, self.integration, g, pair_a, pair_k)

    def force_resultants(self) -> np.ndarray:
        """Net contact force on each body, ``(num_bodies, 3)`` (force units; collective).

        A body is a connected component of the mesh (``body_of_vertex``). The force on a
        vertex is ``-dE/dx``; contact between two bodies gives them opposite resultants, and
        self-contact contributes nothing to its body's resultant.
        """
        r = self._evaluate(True, False)
        return diagnostics.force_resultants(self.surface, r["verts"], r["grad"])

    def diagnostics(self) -> dict[str, typing.Any]:
        """Contact state at the last update (collective).

        Returns:
            ``candidate_pairs`` and ``active_pairs`` (global counts; active = non-zero
            energy), ``energy`` (F L), ``max_penetration`` (L, see :meth:`max_penetration`),
            ``force_resultant``, the net contact force on each body, ``(num_bodies, 3)``, the
            depth-deficient tetrahedra (all four vertices at depth 0): their number
            ``deficient_tets``, the number of tetrahedra touching the boundary
            ``boundary_adjacent_tets``, the ratio ``deficient_fraction`` and ``split_tets``,
            how many the operator splits around their centroid (see ``split_deficient``),
            and what this rank holds and sends (counts on this rank, see
            :meth:`fenics_matdepth.contact.surface.ContactSurface.sizes`): ``held_vertices``
            and ``held_tets`` (owned plus halo), ``halo_tets``, ``neighbours``,
            ``update_bytes_sent`` and ``halo_refreshes``.
        """
        r = self._evaluate(True, False)
        return {
            "deficient_tets": self.depth_deficiency.deficient,
            "boundary_adjacent_tets": self.depth_deficiency.boundary_adjacent,
            "deficient_fraction": self.depth_deficiency.fraction,
            "split_tets": self.num_split_tets,
            "candidate_pairs": self.comm.allreduce(int(self.pair_search.pair_a.size)),
            "active_pairs": self.comm.allreduce(int(np.count_nonzero(r["energy"] > 0.0))),
            "energy": self.energy(),
            "max_penetration": self.max_penetration(),
            "force_resultant": self.force_resultants(),
            **self.surface.sizes(),
            **self.friction_diagnostics(),
        }


def propose_penalty(
    mesh: dolfinx.mesh.Mesh, modulus: float, factor: float = 10.0, h: float | None = None
) -> float:
    """A penalty parameter eps (pressure / length) from the stiffest modulus and the mesh size.

    ``eps = factor * modulus / h``. Where one surface enters a body, a contact pressure p
    penetrates ``g = p / eps = (p / modulus) h / factor``: ``1 / factor`` of the compression that
    pressure causes across one element of size ``h``. Between two deformable bodies both
    surfaces enter the other body and both terms carry the load, so the overlap is about
    ``p / (2 eps)`` (the patch test in ``tests/test_validation.py`` checks this). At the edges
    and corners of the contact zone the other body's depth falls to 0 at its side faces, so
    only one surface pushes there and the overlap rises, within about one element of the
    edge, towards ``p / eps``: measured under a block on a larger block (soft penalty,
    ``tests/test_thin_layers.py``), 0.47 p/eps inside the footprint, 0.58-0.62 p/eps at its
    edge vertices and 0.60-0.65 p/eps at its corners (without the centroid split of
    depth-deficient tetrahedra, up to 1.17 p/eps on the sides where the mesh has them). A
    stiffer penalty adds the elastic stress concentration at the edges on top. The contact
    stiffness of a surface vertex (about ``eps h^2``) is ``factor`` times the stiffness of its
    element (about ``modulus h``). Larger factors reduce penetration but worsen conditioning;
    10 to 100 suits the Newton solver with a direct linear solver.

    Args:
        mesh: the tetrahedral mesh of the bodies.
        modulus: the stiffest small-strain modulus of the materials in contact (pressure), e.g.
            ``materials.small_strain_moduli(...).stiffest`` or Young's modulus.
        factor: the ratio above (dimensionless).
        h: mesh size (L); default: the median edge length of the exterior boundary triangles,
            the elements that meet in contact.

    Returns:
        The proposed penalty (collective).
    """
    from fenics_matdepth.boundary import boundary_triangles

    modulus, factor = float(modulus), float(factor)
    if not (np.isfinite(modulus) and modulus > 0.0 and np.isfinite(factor) and factor > 0.0):
        raise ValueError(
            f"modulus and factor must be positive numbers, got modulus={modulus}, factor={factor}"
        )
    if h is None:
        x = boundary_triangles(mesh)  # gathered on every rank
        if x.shape[0] == 0:
            raise ValueError("the mesh has no exterior boundary triangles")
        h = float(np.median(np.linalg.norm(x[:, [1, 2, 0]] - x, axis=2)))
    return factor * modulus / float(h)
