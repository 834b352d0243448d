"""The residual and Jacobian of bulk plus contact, shared by the contact problems.

:class:`SystemAssembler` assembles the user's UFL residual and Jacobian (DOLFINx) and adds the
contact operator's share, owns the Jacobian matrix with the bulk + contact pattern, rebuilds it
when a contact coupling leaves the pattern, and tells whether a state is admissible. Both
:class:`~fenics_matdepth.ContactProblem` and :class:`~fenics_matdepth.NonlinearContactProblem`
assemble through it.
"""

from __future__ import annotations

import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth._bulk import BulkMatrix, fixed_cells, without_cells
from fenics_matdepth.contact import assembly
from fenics_matdepth.contact.active_set import LaggedPairs
from fenics_matdepth.contact.operator import ContactOperator
from fenics_matdepth.kinematics import CellDeterminants

__all__ = ["TIMING_KEYS", "SystemAssembler"]

#: Names of the per-solve time split (seconds) kept in ``ContactProblem.timings``; ``ccd``
#: is the continuous collision detection of the Newton steps (0 with ``ccd=False``).
TIMING_KEYS = (
    "bulk_assembly",
    "contact_update",
    "contact_assembly",
    "linear_solve",
    "ccd",
)


class _Stopwatch:
    """Accumulates wall time per key: ``with watch("key"): ...``; ``totals`` per solve (the
    problem resets them), ``run_totals`` since it was made (never reset)."""

    def __init__(self):
        self.totals = dict.fromkeys(TIMING_KEYS, 0.0)
        self.run_totals = dict.fromkeys(TIMING_KEYS, 0.0)
        self._key = ""
        self._start = 0.0

    def __call__(self, key: str) -> _Stopwatch:
        self._key = key
        return self

    def __enter__(self):
        self._start = time.perf_counter()

    def __exit__(self, *exc):
        self.add(self._key, time.perf_counter() - self._start)

    def add(self, key: str, seconds: float) -> None:
        """Count ``seconds`` under ``key`` (timed elsewhere, as between two callbacks)."""
        self.totals[key] += seconds
        self.run_totals[key] += seconds


class SystemAssembler:
    """The residual ``F(u) + dE/du`` and Jacobian ``dF/du + d2E/du2`` of one problem.

    Both problems (:class:`~fenics_matdepth.ContactProblem` for SNES,
    :class:`~fenics_matdepth.NonlinearContactProblem` for the
    DOLFINx ``NewtonSolver``) assemble through this one object, so any change to the assembly
    reaches both. It owns the Jacobian matrix (bulk + contact pattern) and rebuilds it when a
    contact coupling leaves the pattern; it also tells whether a state is admissible (every
    element keeps ``det F > 0`` and the residual is finite).

    The residual follows DOLFINx's order (zero, ``assemble_vector``, contact, ``apply_lifting``
    at the current iterate ``x``, reverse ghost update, ``set_bc(b, bcs, x, -1)``): Dirichlet
    rows hold ``x - g``, so the Newton step moves the Dirichlet dofs onto their values and the
    interior follows the linearisation (the boundary values are never written into the
    iterate ahead of the step, which would invert the elements next to a boundary moved by
    more than their height).

    Args:
        L: compiled residual form.
        a: compiled Jacobian form.
        u: the unknown displacement (the Function the contact operator was built on).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        energy: optional compiled energy functional (bulk part of the total energy).
        forms: the UFL forms of ``L`` and ``a``, and the options they were compiled with
            (``form_compiler_options``, ``jit_options``): given them, the residual and the
            Jacobian are assembled over the cells that hold a free dof (``L_cells``,
            ``a_cells``), the same to the bit; otherwise over every cell.
    """

    def __init__(
        self,
        L: dolfinx.fem.Form,
        a: dolfinx.fem.Form,
        u: dolfinx.fem.Function,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        energy: dolfinx.fem.Form | None = None,
        forms: tuple[ufl.Form, ufl.Form, dict] | None = None,
    ):
        self.L, self.a, self.u, self.contact = L, a, u, contact
        self.bcs = list(bcs)
        # the forms the residual and the Jacobian are assembled with: ``L`` and ``a`` without
        # the cells whose every dof is prescribed (a cell of a bone moved as a whole adds only
        # to Dirichlet rows and columns, which the conditions overwrite; on the knee 17 % of
        # the cells), where ``forms`` are given; ``a`` gives the pattern
        self.L_cells, self.a_cells = L, a
        self.comm = u.function_space.mesh.comm
        left_out = None
        if forms is not None:
            left_out = fixed_cells(u.function_space, assembly.owned_dirichlet_dofs(self.bcs))
        if left_out is not None and self.comm.allreduce(bool(left_out.any()), op=MPI.LOR):
            F_ufl, J_ufl, options = forms
            try:
                self.L_cells, self.a_cells = (
                    without_cells(f, c, left_out, **options) for f, c in ((F_ufl, L), (J_ufl, a))
                )
            except NotImplementedError:  # interior-facet integrals: every cell
                pass
        self.energy_form = energy
        contact.set_bcs(self.bcs)
        self.watch = _Stopwatch()
        self.cells = CellDeterminants(u.function_space)
        self.matrix = contact.create_matrix(a, self.bcs)
        # the bulk Jacobian through DOLFINx's native CSR matrix (fenics_matdepth._bulk)
        self.bulk = BulkMatrix(
            a, self.bcs, assembly.global_dirichlet_dofs(self.comm, u.function_space, self.bcs),
            self.a_cells,
        )  # fmt: skip
        self.pattern_rebuilds = 0
        #: rigid-body modes set on every matrix (for an AMG preconditioner), or None
        self.near_nullspace: PETSc.NullSpace | None = None
        #: trial states found inadmissible (det F <= 0 or a non-finite residual or energy)
        self.rejected_states = 0
        self._scratch = u.x.petsc_vec.duplicate()
        #: the proximal term of bodies held only by contact
        #: (:class:`~fenics_matdepth.free_bodies.ProximalTerm`, active while its k > 0), or None
        self.proximal = None
        #: the pairs that left kept in the Jacobian for one iteration
        #: (:class:`~fenics_matdepth.contact.active_set.LaggedPairs`), or None
        self.lagged_pairs = None

    @property
    def run_timings(self) -> dict[str, float]:
        """Seconds per key of ``TIMING_KEYS`` over every solve since the problem was made:
        failed attempts, and the solves an augmented Lagrangian repeats, included (the
        problem's ``timings`` hold its last solve's)."""
        return dict(self.watch.run_totals)

    def keep_left_pairs(self, keep: bool = True) -> None:
        """Add to each Jacobian the last one's Hessian of every contact pair that has left
        since (:class:`~fenics_matdepth.contact.active_set.LaggedPairs`: active-set damping,
        for contact sets that flip-flop between Newton iterations; area integration), or
        (``keep=False``) assemble the exact Jacobian again (the default)."""
        self.lagged_pairs = LaggedPairs(self.contact) if keep else None

    def start_solve(self) -> None:
        """A Newton solve starts: its first Jacobian keeps no pair of an earlier one."""
        if self.lagged_pairs is not None:
            self.lagged_pairs.reset()

    def set_near_nullspace(self, modes: PETSc.NullSpace) -> None:
        """Set ``modes`` as the near-nullspace of the matrix, now and after every rebuild."""
        self.near_nullspace = modes
        self.matrix.setNearNullSpace(modes)

    def set_state(self, x: PETSc.Vec) -> None:
        """Make ``u`` (ghosts included) equal ``x`` and update the contact state there."""
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if x.handle != self.u.x.petsc_vec.handle:
            x.copy(self.u.x.petsc_vec)
            self.u.x.scatter_forward()
        with self.watch("contact_update"):
            self.contact.update()

    def min_det_F(self) -> float:
        """Smallest det F over the cells at the current ``u`` (collective)."""
        return self.cells.min(self.u)

    def residual(self, x: PETSc.Vec, b: PETSc.Vec) -> bool:
        """Assemble the residual at ``x`` (state already set) into ``b`` (collective).

        Returns:
            Whether the state is admissible. It is not when some element has det F <= 0 or
            the residual is not finite; ``b`` is then filled with NaN, which makes PETSc's
            backtracking line search shorten the step.
        """
        if self.min_det_F() <= 0.0:
            b.set(np.nan)
            self.rejected_states += 1
            return False
        with self.watch("bulk_assembly"):
            with b.localForm() as b_local:
                b_local.set(0.0)
            dolfinx.fem.petsc.assemble_vector(b, self.L_cells)
        with self.watch("contact_assembly"):
            self.contact.add_residual(b)
            increment = self._dirichlet_increment(x)
            if increment is not None:
                # the contact coupling to the prescribed values not yet reached, as
                # apply_lifting adds the bulk's: the Newton step is exact
                self.contact.add_lifting(b, increment)
        with self.watch("bulk_assembly"):
            if increment is not None:
                # where every Dirichlet dof holds its value the lifting adds A (g - x) = 0
                # (exactly: the same bits), at the cost of a matrix assembly over the cells
                # of the Dirichlet dofs (11 ms of the knee's 25 ms residual)
                dolfinx.fem.petsc.apply_lifting(b, [self.a_cells], [self.bcs], x0=[x], alpha=-1.0)
            b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            if self.proximal is not None:
                self.proximal.add_residual(x, b)
            dolfinx.fem.petsc.set_bc(b, self.bcs, x, -1.0)
        if not np.isfinite(b.norm()):
            b.set(np.nan)
            self.rejected_states += 1
            return False
        return True

    def jacobian(self, A: PETSc.Mat) -> None:
        """A = dF/du + d2E/du2 at the current state, Dirichlet rows and columns as DOLFINx sets
        them (collective)."""
        with self.watch("bulk_assembly"):
            A.zeroEntries()
            self.bulk.add_to(A)
            A.assemble()
        with self.watch("contact_assembly"):
            self.contact.add_jacobian(A)
            if self.lagged_pairs is not None:
                self.lagged_pairs.add_jacobian(A)
            if self.proximal is not None:
                self.proximal.add_jacobian(A)

    def total_energy(self) -> float:
        """Bulk plus contact energy at the current state; NaN where inadmissible (collective)."""
        if self.min_det_F() <= 0.0:
            self.rejected_states += 1
            return np.nan
        with self.watch("bulk_assembly"):
            bulk = self.comm.allreduce(dolfinx.fem.assemble_scalar(self.energy_form))
        with self.watch("contact_assembly"):
            value = bulk + self.contact.energy()
            if self.proximal is not None:
                value += self.proximal.energy(self.u.x.petsc_vec, self.comm)
        if not np.isfinite(value):
            self.rejected_states += 1
            return np.nan
        return value

    def rebuild_matrix_if_needed(self, register: typing.Callable[[PETSc.Mat], None]) -> bool:
        """If a contact coupling left the pattern: build a new matrix, hand it to the solver
        with ``register(new)``, then release the old one. Returns whether it rebuilt."""
        with self.watch("contact_update"):
            rebuild = self.contact.pattern_needs_rebuild()
        if not rebuild:
            return False
        with self.watch("contact_update"):
            matrix = self.contact.create_matrix(self.a, self.bcs)
        if self.near_nullspace is not None:
            matrix.setNearNullSpace(self.near_nullspace)
        register(matrix)
        self.matrix.destroy()
        self.matrix = matrix
        self.pattern_rebuilds += 1
        return True

    def _bc_gap(self, x: PETSc.Vec) -> PETSc.Vec:
        """``g - x`` at the Dirichlet dofs, zero elsewhere (a scratch vector; collective)."""
        x.copy(self._scratch)
        dolfinx.fem.petsc.set_bc(self._scratch, self.bcs)
        self._scratch.axpy(-1.0, x)
        return self._scratch

    def bc_offset(self, x: PETSc.Vec) -> float:
        """Largest distance of a Dirichlet dof of ``x`` from its prescribed value (collective)."""
        if not self.bcs:
            return 0.0
        return self._bc_gap(x).norm(PETSc.NormType.NORM_INFINITY)

    def _dirichlet_increment(self, x: PETSc.Vec) -> np.ndarray | None:
        """``g - x`` on the owned dofs (zero off the Dirichlet dofs), or None where every
        Dirichlet dof of ``x`` holds its value (collective)."""
        if not self.bcs:
            return None
        gap = self._bc_gap(x)
        if gap.norm(PETSc.NormType.NORM_INFINITY) == 0.0:
            return None
        return gap.getArray(readonly=True).copy()

    def destroy(self) -> None:
        """Release the PETSc objects (collective)."""
        for obj in (self.matrix, self._scratch, self.near_nullspace):
            if obj is not None:
                obj.destroy()
