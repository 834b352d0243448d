"""Newton solvers with contact, and load stepping.

* :class:`ContactProblem`: PETSc SNES (``newtonls`` + line search) over a user's UFL residual
  plus the contact operator.
* :class:`NonlinearContactProblem`: the same residual and Jacobian as a problem for
  ``dolfinx.nls.petsc.NewtonSolver``.
* :func:`solve_load_steps`: a loop over load increments with automatic step cutting, a
  one-line progress report per step and a writer hook, for either problem.

Both problems keep the Jacobian's sparsity pattern (bulk + contact couplings with a margin,
:meth:`ContactOperator.create_matrix`) across iterations and rebuild it, at the start of a
Newton iteration, only when a contact coupling falls outside it.
"""

from __future__ import annotations

import dataclasses
import os
import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth._bulk import BulkMatrix
from fenics_matdepth._compat import (
    NewtonSolverProblemBase,
    bc_constrains_space,
    set_lag_preconditioner,
)
from fenics_matdepth._mpi import collective_error
from fenics_matdepth._progress import StepProgress
from fenics_matdepth.checkpoint import Checkpoint
from fenics_matdepth.contact import assembly
from fenics_matdepth.contact.operator import ContactOperator
from fenics_matdepth.kinematics import CellDeterminants

__all__ = [
    "ContactAssembler",
    "ContactProblem",
    "LoadStep",
    "NonlinearContactProblem",
    "SolveResult",
    "rigid_body_modes",
    "solve_load_steps",
]

_DEFAULT_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "bt",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-12,
    "snes_stol": 0.0,
    "snes_max_it": 50,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}

#: With ``keep_factorisation=True`` (the default), ContactProblem's direct solver keeps a
#: factorisation across the Newton iterations of a solve: each Jacobian is solved by flexible
#: GMRES (right-preconditioned, to 1e-10 of the residual: an exact Newton step) preconditioned
#: by the last factorisation. A Jacobian is factorised anew after the matrix's pattern was
#: rebuilt and once GMRES needed more than REFACTORISE_ITERATIONS iterations; a solve starts on
#: the last solve's factorisation if that solve converged (a load step, a time step or a
#: pressure update later the Jacobian changed little) and the contact penalty is the same,
#: otherwise it factorises its first Jacobian. GMRES stops after KEPT_MAX_ITERATIONS, where a kept
#: factorisation no longer pays (one factorisation costs about 30 GMRES iterations on
#: benchmarks/bench_factor.py's press, 25k dofs: LDL^T analysis and factorisation 0.84 s, one
#: substitution 27 ms; about 11 on the knee's coarse leg: 0.18 s against 16 ms), and the solve
#: goes on from the iterate it had reached, whose Jacobian is factorised. When that happened
#: KEPT_TRIES times in a solve on the first GMRES after a factorisation, the Jacobian changes
#: too much from one iteration to the next: the solve factorises every Jacobian from then on,
#: and the problem's next 1, 2, 4, ... solves do not try (until a kept factorisation pays
#: again). (Once is common: a load step's first Newton step changes the contact set.) When
#: GMRES fails on the factorisation a solve started on, the next 1, 2, 4, ... solves factorise
#: their first Jacobian. Measured:
#: the press's GMRES took 3 to 11 iterations; the knee's first GMRES on a new factorisation 18
#: to 61. Giving ``ksp_type`` or ``pc_type`` turns it off.
REFACTORISE_ITERATIONS = 10
KEPT_MAX_ITERATIONS = 20
KEPT_TRIES = 2
_KEPT_FACTORISATION_OPTIONS = {
    # flexible GMRES keeps the preconditioned vectors: no substitution more to form the
    # solution, which right-preconditioned GMRES spends on every solve (measured on the knee:
    # a factorised solve 0.18 to 0.19 s with preonly, 0.21 to 0.23 s with GMRES)
    "ksp_type": "fgmres",
    "ksp_pc_side": "right",
    "ksp_norm_type": "unpreconditioned",
    "ksp_rtol": 1e-10,
    "ksp_atol": 0.0,
    "ksp_max_it": KEPT_MAX_ITERATIONS,
    "ksp_gmres_restart": KEPT_MAX_ITERATIONS,
}

#: From this many global dofs on, ContactProblem's default linear solver is GMRES preconditioned
#: by GAMG with the rigid-body near-nullspace (_AMG_OPTIONS) instead of MUMPS LU. Measured with
#: benchmarks/bench_linear.py on the press's contact Jacobian (CPU seconds of set-up + solve):
#: 24.7k dofs LU 1.24, GAMG 1.19; 92.3k dofs LU 12.2, GAMG 4.5; 282k dofs GAMG 16.9.
AMG_MIN_DOFS = 50_000
#: With ``keep_factorisation=True`` (the default), ContactProblem's default AMG preconditioner
#: keeps its hierarchy across Newton iterations, as the direct solver keeps its factorisation
#: (same rules: a new one at a solve's start unless it starts on the last solve's, on a new
#: pattern, after a GMRES failure): GAMG's set-up is redone once GMRES on the kept hierarchy
#: needs more than AMG_KEPT_GROWTH times the iterations it needed on a new one. A GAMG set-up
#: costs about 30 GMRES iterations (the Hertz benchmark, 96k dofs: 1.3 s against 0.04 s, the
#: Galerkin products PtAP most of it).
AMG_KEPT_GROWTH = 2.0
_AMG_OPTIONS = {
    "ksp_type": "gmres",
    "ksp_gmres_restart": 200,
    "ksp_rtol": 1e-9,
    "ksp_max_it": 1000,
    "pc_type": "gamg",
    "pc_gamg_threshold": 0.01,
}

#: PETSc's options key that makes the multiple dot products of a vector (the orthogonalisation
#: of GMRES) one BLAS gemv, PETSc's default since 3.21. OpenBLAS's gemv sums in an order that
#: depends on where the vectors lie in memory, which varies from run to run: with it, two runs
#: of one script (benchmarks/bench_newton.py) parted in the last bits at the first GMRES on a
#: kept factorisation and ended with 10 124 or 10 126 active pairs. PETSc's own kernel sums in
#: a fixed order, at the same speed (measured: 0.56 s for 80 products of 5 to 60 vectors of
#: 300k entries either way). A vector takes the setting in force when it is created, and
#: copies of it keep it, so the package sets it off when imported (`_fix_summation_order`),
#: unless it is given (PETSC_OPTIONS, the command line, or PETSc.Options() beforehand).
MDOT_GEMV_OPTION = "vec_mdot_use_gemv"


def _fix_summation_order() -> None:
    """Make the multiple dot products of the vectors created from now on sum in a fixed order
    (MDOT_GEMV_OPTION off), unless the option was given: a run then repeats to the bit."""
    options = PETSc.Options()
    if not options.hasName(MDOT_GEMV_OPTION):
        options.setValue(MDOT_GEMV_OPTION, "0")
    # read once, so that PETSc does not report it as unused at exit in a run without vectors
    options.getBool(MDOT_GEMV_OPTION)


_fix_summation_order()


#: An assembled Jacobian counts as symmetric when no entry differs from its transpose's by more
#: than this fraction of the matrix's infinity norm (rounding leaves about 1e-16); the
#: problems' default direct solver then factorises it as LDL^T (MUMPS, ``pc_type cholesky``,
#: symmetric indefinite) instead of LU: 0.64 s against 0.84 s for the press of
#: benchmarks/bench_factor.py (25k dofs, CPU seconds; docs/solvers.md).
SYMMETRY_RTOL = 1e-10


def choose_factorisation(pc: PETSc.PC, A: PETSc.Mat) -> bool:
    """Factorise the symmetric ``A`` as LDL^T, any other as LU (MUMPS both; collective).

    Checks ``A`` for symmetry (to SYMMETRY_RTOL), flags it, and sets ``pc``'s type to
    ``cholesky`` or ``lu`` accordingly (a change of type redoes the symbolic factorisation).
    Returns whether ``A`` is symmetric.
    """
    symmetric = bool(A.isSymmetric(SYMMETRY_RTOL * A.norm(PETSc.NormType.INFINITY)))
    A.setOption(PETSc.Mat.Option.SYMMETRIC, symmetric)
    wanted = "cholesky" if symmetric else "lu"
    if pc.getType() != wanted:
        pc.setType(wanted)
        pc.setFactorSolverType("mumps")
    return symmetric


#: SNES's reason when a linear solve (or the factorisation) failed
LINEAR_SOLVE_FAILED = PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE

#: MUMPS's working space for LDL^T: this percentage above its analysis' estimate (ICNTL(14),
#: MUMPS's default 20): with pivoting near a singular Jacobian (a body held only by contact)
#: the 20 % ran out (INFOG(1) = -9) on 2 ranks in several runs of the floating cube of
#: test_augmented.py, 100 % in none of 12. A failed LDL^T factorisation is retried with LU.
LDLT_WORKSPACE_PERCENT = 100


def _is_mumps_direct(pc: PETSc.PC) -> bool:
    """Whether ``pc`` is a MUMPS factorisation (LU or Cholesky)."""
    return pc.getType() in ("lu", "cholesky") and pc.getFactorSolverType() == "mumps"


#: The energy line search hands over to the residual norm once the residual has fallen by
#: this factor in a solve, or once an iteration changed it by less than STALL_RTOL (relative);
#: see ContactProblem._start_iteration.
MERIT_SWITCH_RTOL = 1e-5
STALL_RTOL = 1e-3

#: SNES's reason for a non-finite residual norm (renamed DIVERGED_FUNCTION_NANORINF in newer
#: PETSc; value -4 in both)
NAN_REASON = getattr(
    PETSc.SNES.ConvergedReason,
    "DIVERGED_FNORM_NAN",
    getattr(PETSc.SNES.ConvergedReason, "DIVERGED_FUNCTION_NANORINF", -4),
)

#: ContactProblem stops with DIVERGED_LINE_SEARCH after this many consecutive iterations
#: that changed the residual norm by less than NO_PROGRESS_RTOL (relative): the line search
#: is taking steps of no length (measured: a patch-test solve sat at the same residual for 45
#: iterations until the iteration limit), so a caller (load stepping, the augmented
#: Lagrangian's update halving) can react at once.
NO_PROGRESS_ITERATIONS = 3
NO_PROGRESS_RTOL = 1e-10

#: ... unless the residual had fallen below this fraction of the solve's initial residual
#: first: then the solve has reached the residual's rounding floor and counts as converged
#: (CONVERGED_SNORM_RELATIVE: the line search takes steps of no length). Measured on the knee
#: (coarse leg) from 121 deg on: steps converged quadratically to 2e-9 ... 7e-8 N (forces of
#: order 100 N in the leg) and stayed there, 1e-10 ... 3e-7 of their initial residuals, and were
#: cut until the load stepping gave up.
ROUNDING_FLOOR_RTOL = 1e-6

#: When a Newton step would climb the energy (the Jacobian is indefinite: the iterate is near
#: a saddle of the energy, an unstable equilibrium), ContactProblem takes the step of
#: ``J + mu I`` instead (a Hessian modification), mu starting at SHIFT_START times the mean
#: absolute diagonal of J and growing SHIFT_GROWTH-fold until the factorisation has no
#: negative pivot and the step goes downhill, at most SHIFT_TRIES factorisations. Measured on
#: the knee at 90.6 deg (coarse leg): Newton sat at |F| = 3e-2 with one negative pivot and
#: its step 470 mm long; 1e-6 removed the negative pivot and the energy fell by 0.012 N mm
#: along the shifted step.
SHIFT_START = 1e-6
SHIFT_GROWTH = 10.0
SHIFT_TRIES = 8

#: NonlinearContactProblem halves a Newton step at most this many times while it would
#: invert an element.
MAX_STEP_HALVINGS = 30

#: Names of the per-solve time split (seconds) kept in ``ContactProblem.timings``.
TIMING_KEYS = (
    "bulk_assembly",
    "contact_update",
    "contact_assembly",
    "linear_solve",
)


def _reason_name(reason: int) -> str:
    """``", NAME"`` of a SNES converged reason, or ``""`` if PETSc has no name for it."""
    for name, value in vars(PETSc.SNES.ConvergedReason).items():
        if value == reason and not name.startswith("_") and name.isupper():
            return f", {name}"
    return ""


@dataclasses.dataclass
class SolveResult:
    """Outcome of a Newton solve.

    Attributes:
        converged: whether the solver reported convergence.
        reason: SNES converged reason (``PETSc.SNES.ConvergedReason``; > 0 converged); for
            :class:`NonlinearContactProblem` 1 if converged, -1 otherwise.
        iterations: Newton iterations taken.
        residual_norms: residual norm before each iteration and after the last one.
        rejected_states: trial states rejected because an element inverted (det F <= 0) or the
            residual or energy was not finite (the step was shortened instead).
        min_det_F: smallest det F over the cells at the returned state.
        shifted_steps: Newton steps taken with the shifted Jacobian ``J + mu I`` because the
            Newton step would have climbed the energy (:class:`ContactProblem` with an energy
            and a MUMPS solver; see SHIFT_START).
        factorisations: Jacobians factorised by :class:`ContactProblem` with
            ``keep_factorisation=True``, which keeps a factorisation while GMRES on it
            converges fast (see REFACTORISE_ITERATIONS), or with the default AMG
            preconditioner the hierarchies it built (see AMG_KEPT_GROWTH); 0 otherwise.
    """

    converged: bool
    reason: int
    iterations: int
    residual_norms: np.ndarray
    rejected_states: int = 0
    min_det_F: float = np.nan
    shifted_steps: int = 0
    factorisations: int = 0

    def failure_message(self) -> str:
        """Why the solve failed, with the residual history."""
        return (
            "contact Newton solve did not converge "
            f"(reason {self.reason}{_reason_name(self.reason)}) after "
            f"{self.iterations} iterations; residual norms: "
            + ", ".join(f"{r:.3e}" for r in self.residual_norms)
            + ". Reduce the load step (solve_load_steps cuts it automatically), or lower the "
            "penalty."
        )


class _Stopwatch:
    """Accumulates wall time per key: ``with watch("key"): ...``."""

    def __init__(self):
        self.totals = dict.fromkeys(TIMING_KEYS, 0.0)
        self._key = ""
        self._start = 0.0

    def __call__(self, key: str) -> _Stopwatch:
        self._key = key
        return self

    def __enter__(self):
        self._start = time.perf_counter()

    def __exit__(self, *exc):
        self.totals[self._key] += time.perf_counter() - self._start


class ContactAssembler:
    """The residual ``F(u) + dE/du`` and Jacobian ``dF/du + d2E/du2`` of one problem.

    Both problems (:class:`ContactProblem` for SNES, :class:`NonlinearContactProblem` for the
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
    """

    def __init__(
        self,
        L: dolfinx.fem.Form,
        a: dolfinx.fem.Form,
        u: dolfinx.fem.Function,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        energy: dolfinx.fem.Form | None = None,
    ):
        self.L, self.a, self.u, self.contact = L, a, u, contact
        self.bcs = list(bcs)
        self.energy_form = energy
        self.comm = u.function_space.mesh.comm
        contact.set_bcs(self.bcs)
        self.watch = _Stopwatch()
        self.cells = CellDeterminants(u.function_space)
        self.matrix = contact.create_matrix(a, self.bcs)
        # the bulk Jacobian through DOLFINx's native CSR matrix (fenics_matdepth._bulk)
        self.bulk = BulkMatrix(
            a, self.bcs, assembly.global_dirichlet_dofs(self.comm, u.function_space, self.bcs)
        )
        self.pattern_rebuilds = 0
        #: rigid-body modes set on every matrix (for an AMG preconditioner), or None
        self.near_nullspace: PETSc.NullSpace | None = None
        #: trial states found inadmissible (det F <= 0 or a non-finite residual or energy)
        self.rejected_states = 0
        self._scratch = u.x.petsc_vec.duplicate()

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
            dolfinx.fem.petsc.assemble_vector(b, self.L)
        with self.watch("contact_assembly"):
            self.contact.add_residual(b)
            increment = self._dirichlet_increment(x)
            if increment is not None:
                # the contact coupling to the prescribed values not yet reached, as
                # apply_lifting adds the bulk's: the Newton step is exact
                self.contact.add_lifting(b, increment)
        with self.watch("bulk_assembly"):
            dolfinx.fem.petsc.apply_lifting(b, [self.a], [self.bcs], x0=[x], alpha=-1.0)
            b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
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

    def total_energy(self) -> float:
        """Bulk plus contact energy at the current state; NaN where inadmissible (collective)."""
        if self.min_det_F() <= 0.0:
            self.rejected_states += 1
            return np.nan
        with self.watch("bulk_assembly"):
            bulk = self.comm.allreduce(dolfinx.fem.assemble_scalar(self.energy_form))
        with self.watch("contact_assembly"):
            value = bulk + self.contact.energy()
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


def rigid_body_modes(V: dolfinx.fem.FunctionSpace) -> PETSc.NullSpace:
    """The six rigid-body modes of a P1 displacement space (orthonormal, owned dofs) as a
    PETSc null space: the near-nullspace an AMG preconditioner (GAMG) needs for elasticity
    (collective)."""
    comm = V.mesh.comm
    n = V.dofmap.index_map.size_local
    x = V.tabulate_dof_coordinates()[:n]
    count = comm.allreduce(n)
    x = x - comm.allreduce(x.sum(axis=0)) / max(count, 1)
    modes = np.zeros((6, n, 3))
    for i in range(3):
        modes[i, :, i] = 1.0
    modes[3, :, 0], modes[3, :, 1] = -x[:, 1], x[:, 0]
    modes[4, :, 1], modes[4, :, 2] = -x[:, 2], x[:, 1]
    modes[5, :, 2], modes[5, :, 0] = -x[:, 0], x[:, 2]
    vecs = []
    for k in range(6):
        vec = PETSc.Vec().createMPI((3 * n, PETSc.DECIDE), bsize=3, comm=comm)
        vec.setArray(modes[k].ravel())
        vecs.append(vec)
    # Gram-Schmidt across ranks
    for k, vec in enumerate(vecs):
        for other in vecs[:k]:
            vec.axpy(-vec.dot(other), other)
        vec.normalize()
    return PETSc.NullSpace().create(vectors=vecs, comm=comm)


def _check_problem_inputs(u, contact, bcs) -> None:
    """The problem's ``u``, operator and boundary conditions must belong together."""
    if not isinstance(contact, ContactOperator):
        raise TypeError(
            f"contact must be a fenics_matdepth.ContactOperator, got {type(contact).__name__}"
        )
    if contact.u is not u:
        raise ValueError(
            "the contact operator must be built on the same Function u: create it with "
            "ContactOperator(u, depth, penalty) for the u you pass here"
        )
    for i, bc in enumerate(bcs):
        if not isinstance(bc, dolfinx.fem.DirichletBC):
            raise TypeError(
                f"bcs[{i}] is a {type(bc).__name__}, not a dolfinx.fem.DirichletBC: build it "
                "with dolfinx.fem.dirichletbc"
            )
        if not bc_constrains_space(bc, u.function_space):
            raise ValueError(
                f"bcs[{i}] constrains a different function space than u's: build it on "
                "u.function_space (or one of its subspaces, u.function_space.sub(i))"
            )


class _BackOff:
    """After a failure, the next 1, 2, 4, ... chances are skipped (doubling with each failure
    in a row), until a success."""

    def __init__(self):
        self._skip = self._length = 0

    def take(self) -> bool:
        """Whether this chance may be taken (one chance used either way)."""
        allowed = self._skip == 0
        self._skip = max(self._skip - 1, 0)
        return allowed

    def record(self, failed: bool, succeeded: bool) -> None:
        """The outcome of a chance taken: a failure lengthens the skip, a success ends it."""
        if failed:
            self._length = max(1, 2 * self._length)
            self._skip = self._length
        elif succeeded:
            self._length = 0


class _Releasable:
    """``destroy()`` at the end of a ``with`` block, and when Python frees the object. A
    problem is freed only once ``destroy()`` has broken its solver's reference cycle (or if its
    construction failed before), so the call from ``__del__`` has, as a rule, nothing left to
    release: no collective call runs at a moment that differs between the ranks."""

    def destroy(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.destroy()

    def __del__(self):
        self.destroy()


class ContactProblem(_Releasable):
    """Nonlinear problem F(u) + dE_contact/du = 0 solved with PETSc SNES.

    The Dirichlet values are imposed through the Newton step (see :class:`ContactAssembler`):
    ``solve`` starts from ``u`` as it is, and the first step moves the Dirichlet dofs onto
    their values while the interior follows the linearisation. Trial states of the line search
    that invert an element (det F <= 0) or give a non-finite residual or energy are rejected:
    the backtracking line search shortens the step.

    Args:
        F: the user's residual form (any UFL physics), linear in the test function.
        u: the unknown displacement (P1 vector Function, the one the contact operator uses).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        J: Jacobian form; default ``ufl.derivative(F, u)``.
        energy: optional UFL energy functional whose derivative is ``F``; when given, the
            backtracking line search works on the total energy (bulk + contact) instead of the
            residual norm, until the energy's rounding noise stalls it near the solution (then
            on the residual norm; see ``_start_iteration``), and only once the Dirichlet dofs
            sit on their values (the energy is not a merit function while they move).
        petsc_options_prefix: prefix of this problem's PETSc options.
        petsc_options: options set under the prefix (defaults: newtonls, bt line search, MUMPS
            direct solve, rtol 1e-10, atol 1e-12, at most 50 iterations). Unless ``pc_type``
            is given, MUMPS factorises each Jacobian that is symmetric (every problem with an
            energy) as LDL^T and any other as LU (``solvers.choose_factorisation``). From
            AMG_MIN_DOFS global dofs on, unless ``ksp_type`` or ``pc_type`` is given, the
            linear solver is GMRES with GAMG instead; with ``pc_type: gamg`` the rigid-body modes
            (:func:`~fenics_matdepth.rigid_body_modes`) are set as the matrix's near-nullspace.
        keep_factorisation: with the default direct solver, keep a factorisation across
            Newton iterations as the preconditioner of GMRES (exact Newton steps: to 1e-10 of
            the residual), factorising anew after a pattern rebuild and once GMRES needed more
            than REFACTORISE_ITERATIONS iterations; a solve starts on the factorisation the
            last one ended with when that one converged at the same contact penalty. A GMRES
            failure goes on from the iterate reached with a new factorisation. Where keeping
            does not pay (the first GMRES on a new factorisation does not converge in
            KEPT_MAX_ITERATIONS, twice in a solve), the solve factorises every Jacobian and
            the problem's next solves do not try (see _KEPT_FACTORISATION_OPTIONS). With the
            default AMG preconditioner (from AMG_MIN_DOFS dofs on), keep its hierarchy by the
            same rules, set up anew once GMRES needs more than AMG_KEPT_GROWTH times the
            iterations it took on a new one.
            ``False``: a factorisation per iteration.

    Attributes:
        timings: seconds spent in the last :meth:`solve`, split into ``bulk_assembly``,
            ``contact_update`` (gather, refit, pair search), ``contact_assembly`` (pair kernels
            and insertion) and ``linear_solve`` (factorisation or preconditioner set-up, and
            the solve).
        assembler: the :class:`ContactAssembler` (residual, Jacobian, matrix).
    """

    def __init__(
        self,
        F: ufl.Form,
        u: dolfinx.fem.Function,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        J: ufl.Form | None = None,
        energy: ufl.Form | None = None,
        petsc_options_prefix: str = "matdepth_",
        petsc_options: dict | None = None,
        keep_factorisation: bool = True,
    ):
        _check_problem_inputs(u, contact, bcs)
        self.u = u
        self.contact = contact
        self.bcs = list(bcs)
        self._F = dolfinx.fem.form(F)
        self._J = dolfinx.fem.form(J if J is not None else ufl.derivative(F, u))
        self._energy = dolfinx.fem.form(energy) if energy is not None else None
        self.assembler = ContactAssembler(self._F, self._J, u, contact, self.bcs, self._energy)
        self._watch = self.assembler.watch
        self.timings = dict(self._watch.totals)
        self.prefix = petsc_options_prefix
        comm = u.function_space.mesh.comm

        # Ghosted, as dolfinx's assembly and lifting read and write ghost entries.
        self._b = u.x.petsc_vec.duplicate()
        self._x = u.x.petsc_vec.duplicate()
        # the last residual assembled (point and residual) and the last energy evaluated
        # (point and value), valid within a solve: the line search asks its merit function at
        # the step's start, where it was evaluated as the last step's trial point
        self._x_trial = u.x.petsc_vec.duplicate()
        self._b_trial = u.x.petsc_vec.duplicate()
        self._trial_valid = False
        self._residuals_reused = 0
        self._x_energy = u.x.petsc_vec.duplicate()
        self._energy_value = np.nan
        self._energies_reused = 0
        self.snes = PETSc.SNES().create(comm)
        self.snes.setOptionsPrefix(self.prefix)
        options = dict(_DEFAULT_OPTIONS)
        user = petsc_options or {}
        # a user's linear solver or preconditioner lag comes first
        keep_factorisation = keep_factorisation and not {
            "ksp_type", "pc_type", "snes_lag_preconditioner", "snes_lag_jacobian"
        } & set(user)  # fmt: skip
        dofmap = u.function_space.dofmap
        num_dofs = dofmap.index_map.size_global * dofmap.index_map_bs
        # the default AMG preconditioner (_AMG_OPTIONS), which keeps its hierarchy like the
        # direct solver its factorisation (AMG_KEPT_GROWTH)
        self._amg = num_dofs >= AMG_MIN_DOFS and not {"ksp_type", "pc_type"} & set(user)
        if self._amg:
            options.update(_AMG_OPTIONS)
            del options["pc_factor_mat_solver_type"]
        elif "pc_type" not in user:  # LDL^T or LU, chosen per Jacobian (choose_factorisation)
            options["mat_mumps_icntl_14"] = LDLT_WORKSPACE_PERCENT
            if keep_factorisation:
                options.update(_KEPT_FACTORISATION_OPTIONS)
        opts = PETSc.Options()
        opts.prefixPush(self.prefix)
        for key, value in {**options, **user}.items():
            opts[key] = value
        opts.prefixPop()
        if "mat_mumps_icntl_14" not in user and "mat_mumps_icntl_14" in options:
            # read once now: MUMPS reads it at the first factorisation, and a problem that
            # never factorises would otherwise leave it for PETSc to report as unused at exit
            opts.getInt(self.prefix + "mat_mumps_icntl_14")
        self.snes.setFunction(self._residual, self._b)
        self.snes.setJacobian(self._jacobian, self._A, self._A)
        self.snes.setUpdate(self._start_iteration)
        self.snes.setConvergenceTest(self._converged)
        if self._energy is not None:
            self.snes.setObjective(self._objective)
            self.snes.setLineSearchPreCheck(self._check_direction)
        self.snes.setFromOptions()
        ksp = self.snes.getKSP()
        ksp.setFromOptions()
        # the default direct solver: LDL^T for the symmetric Jacobians (choose_factorisation)
        self._choose_factorisation = "pc_type" not in user and _is_mumps_direct(ksp.getPC())
        self._amg = self._amg and ksp.getPC().getType() == "gamg"  # (PETSC_OPTIONS may differ)
        # the direct solver keeps its factorisation (_KEPT_FACTORISATION_OPTIONS)
        self._keep_factorisation = keep_factorisation and (self._choose_factorisation or self._amg)
        # GMRES iterations of the last solve on a new AMG hierarchy
        self._fresh_iterations = 0
        self._factorise = True  # whether the coming Jacobian is factorised
        self._factorisations = self._kept_since_factorisation = 0
        self._may_keep = True  # whether this solve may keep a factorisation
        # this solve's GMRES solves on a kept factorisation that converged and that failed, and
        # its failures on the first GMRES after a factorisation (KEPT_TRIES)
        self._kept_converged = self._kept_failed = self._failed_tries = 0
        # solves that factorise every Jacobian after keeping did not pay
        self._keep_backoff = _BackOff()
        # the contact penalty of the last solve if it converged (None otherwise): the next
        # solve may start on its factorisation; whether this solve did; solves that factorise
        # their first Jacobian after a start on the last factorisation failed
        self._carried_penalty = None
        self._carried = False
        self._carry_backoff = _BackOff()
        # the solve goes on from the iterate reached (a kept factorisation's GMRES failed)
        self._resuming = False
        self._resumed_unchanged = False  # its residual and Jacobian are those of the failure
        self._iteration_offset = 0
        #: Newton steps of the last solve taken with the shifted Jacobian (_shifted_direction)
        self.shifted_steps = 0
        if ksp.getPC().getType() == "gamg":
            self.assembler.set_near_nullspace(rigid_body_modes(u.function_space))
        ksp.setPreSolve(self._ksp_started)
        ksp.setPostSolve(self._ksp_finished)

    @property
    def _A(self) -> PETSc.Mat:
        """The Jacobian matrix with the full (bulk + contact margin) pattern."""
        return self.assembler.matrix

    @property
    def pattern_rebuilds(self) -> int:
        """How many times the matrix was rebuilt because contact couplings left its sparsity
        pattern (over the problem's life)."""
        return self.assembler.pattern_rebuilds

    def min_det_F(self) -> float:
        """Smallest det F over the cells at the current ``u`` (collective)."""
        return self.assembler.min_det_F()

    # -- callbacks ----------------------------------------------------------------------------

    def _set_state(self, x: PETSc.Vec) -> None:
        self.assembler.set_state(x)

    def _residual(self, snes: PETSc.SNES, x: PETSc.Vec, b: PETSc.Vec) -> None:
        if self._resumed_unchanged:
            # the solve goes on from the iterate where GMRES failed: b (the SNES's residual
            # vector), the contact state and the matrix still hold its residual and Jacobian
            return
        self._set_state(x)
        if self._trial_valid and x.equal(self._x_trial):
            # SNES asks for the residual at the step the line search just accepted, which the
            # residual merit function (`_objective`) has assembled already
            self._b_trial.copy(b)
            self._residuals_reused += 1
            return
        if not self.assembler.residual(x, b):
            # An inadmissible trial state: b holds NaN, which the backtracking line search
            # answers by shortening the step (and SNES stops if the start is inadmissible).
            self._trial_valid = False
            domain_error = getattr(snes, "setFunctionDomainError", None)
            if domain_error is not None:
                domain_error()
            return
        # kept for the residual merit function, which the line search asks at the step's
        # start (this point) as well as at its trial points
        if b.handle != self._b_trial.handle:
            b.copy(self._b_trial)
        x.copy(self._x_trial)
        self._trial_valid = True

    def _jacobian(self, snes: PETSc.SNES, x: PETSc.Vec, A: PETSc.Mat, P: PETSc.Mat) -> None:
        # SNES evaluates the residual at x before the Jacobian, so the contact state is current.
        if not self._resumed_unchanged:
            self.assembler.jacobian(A)
        self._resumed_unchanged = False
        if self._choose_factorisation and self._factorise:
            with self._watch("linear_solve"):
                choose_factorisation(self.snes.getKSP().getPC(), A)

    def _objective(self, snes: PETSc.SNES, x: PETSc.Vec) -> float:
        if not self._merit_is_energy:
            if self._trial_valid and x.equal(self._x_trial):
                self._residuals_reused += 1
            else:
                self._trial_valid = False
                self._residual(snes, x, self._b_trial)
            return 0.5 * self._b_trial.norm() ** 2
        if np.isfinite(self._energy_value) and x.equal(self._x_energy):
            self._energies_reused += 1
            return self._energy_value
        self._set_state(x)
        self._energy_value = self.assembler.total_energy()
        x.copy(self._x_energy)
        return self._energy_value

    def _converged(self, snes: PETSc.SNES, iteration: int, norms: tuple) -> int:
        """PETSc's default convergence test (absolute, relative and step tolerances, the
        iteration limit, divergence and NaN), plus a stop when the line search makes no
        progress for NO_PROGRESS_ITERATIONS iterations: DIVERGED_LINE_SEARCH, or
        CONVERGED_SNORM_RELATIVE where the residual had fallen below ROUNDING_FLOOR_RTOL of the
        initial one (its rounding floor)."""
        reasons = PETSc.SNES.ConvergedReason
        xnorm, step_norm, fnorm = norms
        rtol, atol, stol, max_it = snes.getTolerances()
        if not np.isfinite(fnorm):
            return NAN_REASON
        if iteration == 0:
            if not self._resuming:
                self._initial_norm, self._previous_norm, self._no_progress = fnorm, fnorm, 0
            return reasons.CONVERGED_FNORM_ABS if fnorm < atol else reasons.ITERATING
        if fnorm < atol:
            return reasons.CONVERGED_FNORM_ABS
        if fnorm <= rtol * self._initial_norm:
            return reasons.CONVERGED_FNORM_RELATIVE
        if step_norm < stol * xnorm:
            return reasons.CONVERGED_SNORM_RELATIVE
        divergence = snes.getDivergenceTolerance()
        if divergence > 0.0 and fnorm > divergence * self._initial_norm:
            return reasons.DIVERGED_DTOL
        stalled = abs(fnorm - self._previous_norm) <= NO_PROGRESS_RTOL * self._previous_norm
        self._no_progress = self._no_progress + 1 if stalled else 0
        self._previous_norm = fnorm
        if self._no_progress >= NO_PROGRESS_ITERATIONS:
            if fnorm <= ROUNDING_FLOOR_RTOL * self._initial_norm:
                return reasons.CONVERGED_SNORM_RELATIVE
            return reasons.DIVERGED_LINE_SEARCH
        if iteration + self._iteration_offset >= max_it:
            return reasons.DIVERGED_MAX_IT
        return reasons.ITERATING

    def _check_direction(self, x: PETSc.Vec, y: PETSc.Vec) -> bool:
        """Line-search pre-check: the energy judges this step only if the step goes downhill
        and the Dirichlet dofs already sit on their values.

        SNES moves to ``x - lambda y`` with ``J y = F``; the energy's slope along that path is
        ``-F . y``, negative when J is positive definite. Where J is indefinite (deep, sharp
        overlaps; an iterate near a saddle of the energy), ``F . y`` can be negative: the
        Newton step climbs the energy and no step length decreases it. With the Dirichlet dofs
        on their values and a direct solver, that step is replaced by the step of ``J + mu I``
        (``_shifted_direction``), which goes downhill and is judged by the energy; otherwise it
        is judged by ``|F|^2 / 2``, which the Newton step always decreases for small enough
        steps. The same holds while the step still moves Dirichlet dofs onto their values:
        prescribing a displacement raises the energy, so only the residual norm can judge that
        step. Returns whether ``y`` was changed.
        """
        downhill = y.dot(self._b) > 0.0
        if not downhill and self._bcs_met and self._shifted_direction(y):
            self._merit_is_energy = True
            return True
        self._merit_is_energy = self._energy_merit_allowed and self._bcs_met and downhill
        return False

    def _shifted_direction(self, y: PETSc.Vec) -> bool:
        """Overwrite ``y`` with ``(J + mu I)^-1 F`` for the smallest mu of SHIFT_START *
        SHIFT_GROWTH^k (relative to the mean absolute diagonal of J) whose factorisation has no
        negative pivot (LDL^T; LU: none counted) and whose step goes downhill (collective).
        Returns False, leaving ``y``, where the linear solver is not MUMPS or no mu up to the
        last try gives such a step."""
        solver_pc = self.snes.getKSP().getPC()
        if not _is_mumps_direct(solver_pc):
            return False
        pc_type = solver_pc.getType()
        A = self._A
        diagonal = A.getDiagonal()
        scale = diagonal.norm(PETSc.NormType.NORM_1) / max(diagonal.getSize(), 1)
        diagonal.destroy()
        B = A.copy()
        ksp = PETSc.KSP().create(A.getComm())
        trial = y.duplicate()
        pc = factor = None
        try:
            ksp.setType("preonly")
            ksp.setOperators(B)
            pc = ksp.getPC()
            pc.setType(pc_type)
            pc.setFactorSolverType("mumps")
            pc.setFactorSetUpSolverType()
            factor = pc.getFactorMatrix()
            factor.setMumpsIcntl(13, 1)  # negative pivots counted on the root node too
            factor.setMumpsIcntl(14, LDLT_WORKSPACE_PERCENT)
            mu, added = SHIFT_START * scale, 0.0
            for _ in range(SHIFT_TRIES):
                B.shift(mu - added)  # the matrix's new state makes the PC factorise again
                added = mu
                with self._watch("linear_solve"):
                    ksp.solve(self._b, trial)
                negative = factor.getMumpsInfog(12) if pc_type == "cholesky" else 0
                if ksp.getConvergedReason() > 0 and negative == 0 and trial.dot(self._b) > 0.0:
                    trial.copy(y)
                    self.shifted_steps += 1
                    return True
                mu *= SHIFT_GROWTH
            return False
        finally:
            # the borrowed PC and factor go before their KSP: on more than one rank petsc4py
            # defers the destruction of an object whose last reference is a Python wrapper to
            # PETSc's garbage (freed only by PETSc.garbage_cleanup), and a PC kept by its
            # wrapper past ksp.destroy() held a MUMPS factorisation there per shifted step
            # (the knee on 2 ranks grew by GBs)
            del pc, factor
            trial.destroy()
            ksp.destroy()
            B.destroy()

    def _start_iteration(self, snes: PETSc.SNES, iteration: int) -> None:
        """Before each Newton step's Jacobian: switch the line search's merit function if the
        energy stalled; rebuild the matrix if contact left its pattern.

        Near the solution a Newton step changes the energy by about ``r^2 / k`` (r the
        residual, k a stiffness), which falls below the energy's rounding error (relative to
        the stress scale, not to the energy, which may be near zero) while r is still well
        above the tolerance; the energy line search then cuts every step to almost nothing and
        Newton stalls. So once the residual has fallen by MERIT_SWITCH_RTOL, or an iteration
        whose step the energy judged stalled, the line search judges steps by ``|F|^2 / 2``
        instead, which a Newton step in its quadratic range decreases. (Measured on the block
        presses of the tests and benchmark: the energy stops resolving steps at residuals of
        1e-7 to 1e-8 of the initial one.) A slow step judged by ``|F|^2 / 2``, say while the
        Dirichlet dofs move onto their values, says nothing about the energy's rounding and
        keeps the energy for the steps after.
        """
        norm = snes.getFunctionNorm()
        if iteration == 0:
            if not self._resuming:
                self._first_norm = norm
        elif norm <= MERIT_SWITCH_RTOL * self._first_norm or (
            # only a step the energy judged tells that the energy stalled
            self._merit_is_energy and abs(norm - self._last_norm) <= STALL_RTOL * self._last_norm
        ):
            self._energy_merit_allowed = False
        self._last_norm = norm
        x = snes.getSolution()
        if self._energy is not None:
            scale = max(x.norm(PETSc.NormType.NORM_INFINITY), 1.0)
            self._bcs_met = self.assembler.bc_offset(x) <= 1e-12 * scale
        self._set_state(x)

        def register(A: PETSc.Mat) -> None:
            snes.setJacobian(self._jacobian, A, A)

        rebuilt = self.assembler.rebuild_matrix_if_needed(register)
        self._resumed_unchanged = self._resumed_unchanged and not rebuilt
        if self._keep_factorisation:
            # factorise at a solve's start (unless it starts on the last solve's
            # factorisation), on a new pattern, and once the kept factorisation no longer
            # pays (GMRES iterations are counted on every rank alike)
            gmres_iterations = self.snes.getKSP().getIterationNumber()
            if iteration > 0 and not self._factorise:
                self._kept_converged += 1  # (SNES stops where GMRES failed: solve())
            if iteration > 0 and self._factorise:
                self._fresh_iterations = gmres_iterations
            if self._amg:
                no_longer_pays = gmres_iterations > AMG_KEPT_GROWTH * self._fresh_iterations
            else:
                no_longer_pays = gmres_iterations > REFACTORISE_ITERATIONS
            self._factorise = (
                (iteration == 0 and (self._resuming or not self._carried))
                or rebuilt
                or not self._may_keep
                or no_longer_pays
            )
            set_lag_preconditioner(self.snes, -2 if self._factorise else -1)
            if self._factorise:
                self._factorisations += 1
                self._kept_since_factorisation = 0
            else:
                self._kept_since_factorisation += 1

    def _count_kept_failure(self) -> None:
        """Count a GMRES failure on a kept factorisation. Once the first GMRES on a new
        factorisation failed KEPT_TRIES times, the rest of the solve factorises every
        Jacobian."""
        self._kept_failed += 1
        if self._kept_since_factorisation == 1:
            self._failed_tries += 1
            self._may_keep = self._failed_tries < KEPT_TRIES

    def _ksp_started(self, ksp, b, x) -> None:
        self._ksp_start = time.perf_counter()

    def _ksp_finished(self, ksp, b, x) -> None:
        self._watch.totals["linear_solve"] += time.perf_counter() - self._ksp_start

    # -- solve ----------------------------------------------------------------------------------

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve from the current ``u``; ``u`` holds the last iterate afterwards (collective).

        The Dirichlet values are reached by the first Newton step, not written into ``u``
        beforehand.

        Args:
            raise_on_failure: raise ``RuntimeError`` (with the residual history) when SNES does
                not converge; otherwise return the result with ``converged=False``.
        """
        start = self.u.x.petsc_vec.copy()
        # a solve keeps factorisations unless the last ones that tried found it did not pay
        self._may_keep = self._keep_backoff.take()
        self._kept_converged = self._kept_failed = self._failed_tries = 0
        # the first Newton step on the last solve's factorisation (its load changed little)
        may_carry = self._carry_backoff.take()
        self._carried = (
            self._keep_factorisation and self._may_keep and may_carry
            and self.contact.penalty == self._carried_penalty
        )  # fmt: skip
        self._carried_penalty = None  # (until this solve converges)
        carried_failed = False
        history = []
        try:
            while True:
                if not self._resuming:
                    self._factorisations = self._iteration_offset = 0
                    self._watch.totals = dict.fromkeys(TIMING_KEYS, 0.0)
                    self._merit_is_energy, self._last_norm = True, np.inf
                    self.shifted_steps = 0
                    self._energy_merit_allowed, self._bcs_met = True, False
                    self.assembler.rejected_states = 0
                    # the load may have changed since
                    self._trial_valid, self._energy_value = False, np.nan
                    start.copy(self._x)
                    history = []
                self.snes.setConvergenceHistory(reset=True)
                self.snes.solve(None, self._x)
                norms = list(self.snes.getConvergenceHistory()[0])
                history += norms[1:] if self._resuming else norms
                self._iteration_offset += int(self.snes.getIterationNumber())
                self._resuming = False
                pc = self.snes.getKSP().getPC()
                failed = self.snes.getConvergedReason() == LINEAR_SOLVE_FAILED
                if failed and self._keep_factorisation and not self._factorise:
                    # GMRES did not converge on a kept factorisation: on from the iterate
                    # reached (SNES leaves it in _x), whose Jacobian is factorised
                    if self._carried and self._iteration_offset == 0:
                        # on the last solve's factorisation: later solves factorise their
                        # first Jacobian for a while (1, 2, 4, ... solves)
                        carried_failed = True
                    self._count_kept_failure()
                    self._resuming = self._resumed_unchanged = True
                    continue
                if not (failed and self._choose_factorisation and pc.getType() == "cholesky"):
                    break
                # MUMPS could not complete the LDL^T factorisation (seen: its workspace
                # estimate too small, INFOG(1) = -9, for a Jacobian near singular): LU from now
                # on, and the solve again from its start
                self._choose_factorisation = self._carried = False
                pc.setType("lu")
                pc.setFactorSolverType("mumps")
        finally:
            start.destroy()
            self._resuming = self._resumed_unchanged = False
        self._keep_backoff.record(
            failed=self._kept_failed > 0 and not self._kept_converged,
            succeeded=self._kept_converged > 0,
        )
        self._carry_backoff.record(failed=carried_failed, succeeded=self._carried)
        self._set_state(self._x)
        self.timings = dict(self._watch.totals)
        reason = int(self.snes.getConvergedReason())
        if reason > 0:
            self._carried_penalty = self.contact.penalty
        result = SolveResult(
            reason > 0, reason, self._iteration_offset, np.asarray(history, dtype=float),
            self.assembler.rejected_states, self.min_det_F(), self.shifted_steps,
            self._factorisations,
        )  # fmt: skip
        if raise_on_failure and not result.converged:
            raise RuntimeError(result.failure_message())
        return result

    def destroy(self) -> None:
        """Release the problem's PETSc objects now: the SNES with its linear solver and
        factorisation, the vectors and the matrix (collective: call it on every rank at the
        same point). The problem cannot solve afterwards; ``u`` and the contact operator are
        the caller's and stay as they are.

        Needed wherever problems are made again and again (a notebook cell run twice, a loop
        over cases): the SNES holds the problem's own methods as its callbacks, a reference
        cycle through PETSc's C objects that Python's garbage collector cannot see, so a
        problem nobody refers to is never freed, with its MUMPS factorisation, until it is
        destroyed. Destroying the SNES drops the callbacks, and the problem is freed as usual.
        ``with ContactProblem(...) as problem:`` calls it at the end of the block.
        """
        for obj in ("snes", "_b", "_x", "_x_trial", "_b_trial", "_x_energy"):
            if getattr(self, obj, None) is not None:
                getattr(self, obj).destroy()
        if getattr(self, "assembler", None) is not None:
            self.assembler.destroy()


class NonlinearContactProblem(NewtonSolverProblemBase, _Releasable):
    """F(u) + dE_contact/du = 0 as a problem for ``dolfinx.nls.petsc.NewtonSolver``.

    The contact Jacobian needs a matrix with the contact couplings in its sparsity pattern,
    which the solver's own matrix (made from the bulk form alone) does not have; hand the
    solver this problem's matrix with :meth:`attach`, or let :meth:`newton_solver` build a
    configured solver::

        problem = fm.NonlinearContactProblem(F, u, contact, bcs)
        solver = dolfinx.nls.petsc.NewtonSolver(comm, problem)
        problem.attach(solver)          # or: solver = problem.newton_solver()
        n, converged = solver.solve(u)

    The residual and Jacobian come from the same :class:`ContactAssembler` as
    :class:`ContactProblem`'s. :meth:`attach` also installs the solution update: the Newton
    step (times the solver's relaxation parameter) is halved until no element is inverted
    (det F > 0 everywhere), at most ``MAX_STEP_HALVINGS`` times.

    Args:
        F: the user's residual form, linear in the test function.
        u: the unknown displacement (the Function the contact operator was built on).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        J: Jacobian form; default ``ufl.derivative(F, u)``.
        form_compiler_options, jit_options: passed on to dolfinx's form compilation.
    """

    def __init__(
        self,
        F: ufl.Form,
        u: dolfinx.fem.Function,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        J: ufl.Form | None = None,
        form_compiler_options: dict | None = None,
        jit_options: dict | None = None,
    ):
        _check_problem_inputs(u, contact, bcs)
        super().__init__(
            F, u, bcs=list(bcs), J=J, form_compiler_options=form_compiler_options,
            jit_options=jit_options,
        )  # fmt: skip
        self.u = u
        self.contact = contact
        self.assembler = ContactAssembler(self.L, self.a, u, contact, self.bcs)
        self._watch = self.assembler.watch
        self._solver = None
        self._trial = u.x.petsc_vec.duplicate()
        #: residual norm at each residual evaluation of the current solve
        self.residual_norms: list[float] = []

    @property
    def matrix(self) -> PETSc.Mat:
        """The Jacobian matrix (bulk + contact pattern) the solver must use."""
        return self.assembler.matrix

    @property
    def pattern_rebuilds(self) -> int:
        """How many times the matrix was rebuilt because contact couplings left its pattern."""
        return self.assembler.pattern_rebuilds

    def min_det_F(self) -> float:
        """Smallest det F over the cells at the current ``u`` (collective)."""
        return self.assembler.min_det_F()

    def attach(self, solver) -> None:
        """Make ``solver`` (a ``dolfinx.nls.petsc.NewtonSolver`` of this problem) assemble the
        Jacobian into :attr:`matrix` and use the inversion-avoiding update; also lets the
        problem swap in a rebuilt matrix when contact couplings leave the pattern."""
        solver.setJ(self.J, self.matrix)
        solver.set_update(self._update)
        self._solver = solver

    def newton_solver(self, **settings) -> typing.Any:
        """A ``dolfinx.nls.petsc.NewtonSolver`` for this problem, attached, with settings.

        Defaults: residual convergence criterion, rtol 1e-10, atol 1e-12, at most 50
        iterations, no error on non-convergence (``solve`` reports it), LU with MUMPS (not the
        LDL^T that :class:`ContactProblem` picks for symmetric Jacobians: the NewtonSolver
        cannot retry a solve whose LDL^T factorisation failed).

        Args:
            settings: NewtonSolver attributes to override (``rtol=``, ``max_it=``, ...).
        """
        import dolfinx.nls.petsc

        solver = dolfinx.nls.petsc.NewtonSolver(self.u.function_space.mesh.comm, self)
        defaults = {
            "convergence_criterion": "residual",
            "rtol": 1e-10,
            "atol": 1e-12,
            "max_it": 50,
            "error_on_nonconvergence": False,
        }
        for key, value in {**defaults, **settings}.items():
            setattr(solver, key, value)
        ksp = solver.krylov_solver
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        self.attach(solver)
        return solver

    # -- NewtonSolver callbacks -------------------------------------------------------------------

    def form(self, x: PETSc.Vec) -> None:
        """Before F and J at a new iterate: ghost values, contact update, pattern check."""
        self.assembler.set_state(x)
        if self._solver is None:
            if self.contact.pattern_needs_rebuild():
                raise RuntimeError(
                    "contact couplings left the matrix pattern and no solver is attached: call "
                    "problem.attach(solver) after creating the NewtonSolver"
                )
            return
        self.assembler.rebuild_matrix_if_needed(lambda A: self._solver.setJ(self.J, A))

    def F(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """Assemble the residual F(u) + dE/du into ``b`` (NaN where the state is inadmissible)."""
        self.assembler.residual(x, b)
        self.residual_norms.append(b.norm())

    def J(self, x: PETSc.Vec, A: PETSc.Mat) -> None:
        """Assemble the Jacobian into ``A`` (which must be :attr:`matrix`)."""
        if A.handle != self.matrix.handle:
            raise RuntimeError(
                "the NewtonSolver assembles into its own matrix, which lacks the contact "
                "couplings: call problem.attach(solver) (or use problem.newton_solver())"
            )
        self.assembler.jacobian(A)

    def _update(self, solver, dx: PETSc.Vec, x: PETSc.Vec) -> None:
        """x -= relaxation * dx, the step halved while it would invert an element."""
        step = solver.relaxation_parameter
        for _ in range(MAX_STEP_HALVINGS):
            x.copy(self._trial)
            self._trial.axpy(-step, dx)
            self._trial.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            with self._trial.localForm() as local:
                if self.assembler.cells.min(local.array_r) > 0.0:
                    break
            self.assembler.rejected_states += 1
            step /= 2.0
        x.axpy(-step, dx)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve with the attached NewtonSolver (one from :meth:`newton_solver` if none).

        Args:
            raise_on_failure: raise ``RuntimeError`` with the residual history if Newton does
                not converge.
        """
        if self._solver is None:
            self.newton_solver()
        self.residual_norms = []
        self.assembler.rejected_states = 0
        try:
            iterations, converged = self._solver.solve(self.u)
        except RuntimeError:
            if raise_on_failure:
                raise
            iterations, converged = len(self.residual_norms), False
        self.u.x.scatter_forward()
        with self._watch("contact_update"):
            self.contact.update()
        result = SolveResult(
            bool(converged), 1 if converged else -1, int(iterations),
            np.asarray(self.residual_norms, dtype=float), self.assembler.rejected_states,
            self.min_det_F(),
        )  # fmt: skip
        if raise_on_failure and not converged:
            raise RuntimeError(result.failure_message())
        return result

    def destroy(self) -> None:
        """Release the problem's PETSc objects (matrix, vectors) and its reference to the
        attached solver (collective). As for :meth:`ContactProblem.destroy`: the solver holds
        the problem's methods and the problem its solver, a cycle Python cannot free, so a
        problem made again and again must be destroyed (or used in a ``with`` block); then
        it is freed once neither it nor its solver is referred to. The solver cannot solve
        this problem afterwards."""
        if getattr(self, "assembler", None) is not None:
            self.assembler.destroy()
        if getattr(self, "_trial", None) is not None:
            self._trial.destroy()
        self._solver = None


# -- load stepping -----------------------------------------------------------------------------


@dataclasses.dataclass
class LoadStep:
    """One converged load step of :func:`solve_load_steps`.

    Attributes:
        load: the load factor reached (the argument of ``set_load``).
        iterations: Newton iterations of the converged solve.
        residual_norms: its residual history.
        cuts: failed attempts (step halvings) before this step converged.
        diagnostics: ``contact.diagnostics()`` after the step, plus ``min_det_F`` (smallest
            det F over the cells) and ``rejected_states`` (inadmissible trial states the solve
            rejected).
        seconds: wall time of the step, failed attempts included.
        timings: the converged solve's time split (``problem.timings``: ``bulk_assembly``,
            ``contact_update``, ``contact_assembly``, ``linear_solve``; seconds), empty for a
            problem that keeps none.
    """

    load: float
    iterations: int
    residual_norms: np.ndarray
    cuts: int
    diagnostics: dict
    seconds: float
    timings: dict = dataclasses.field(default_factory=dict)


class _Solvable(typing.Protocol):
    u: dolfinx.fem.Function
    contact: ContactOperator

    def solve(self, raise_on_failure: bool = True) -> SolveResult: ...


def _write(writer, u: dolfinx.fem.Function, load: float) -> None:
    if writer is None:
        return
    if hasattr(writer, "write_function"):  # dolfinx.io.XDMFFile (mesh written by the caller)
        writer.write_function(u, load)
    elif hasattr(writer, "write"):  # dolfinx.io.VTXWriter
        writer.write(load)
    else:
        writer(load)


class StopRequested(Exception):
    """Raise it from a :func:`solve_load_steps` callback (``set_load`` or ``writer``) to end the
    run cleanly, e.g. when a stop file appears: ``solve_load_steps`` then raises
    ``StopRequested`` on every rank, with ``u`` holding the last converged state (saved in the
    checkpoint, if any), ``load`` its load factor and ``steps`` the steps converged in this
    call.

    Args:
        message: why the run stops.
        load: set by ``solve_load_steps``: the last converged load factor.
        steps: set by ``solve_load_steps``: the converged steps of the call.
    """

    def __init__(self, message: str = "stop requested", load=None, steps=None):
        super().__init__(message)
        self.load = load
        self.steps = steps if steps is not None else []


def _collective_call(comm: MPI.Comm, what: str, fix: str, function, *args) -> None:
    """Call ``function(*args)`` on every rank; if it raises on any rank, raise RuntimeError on
    every rank, naming ``what`` failed and the ``fix``; a :class:`StopRequested` on any rank is
    raised as such on every rank."""
    stop = None
    try:
        function(*args)
        message = None
    except StopRequested as err:
        message, stop = None, str(err)
    except Exception as err:  # any error of user code is reported
        message = f"{what} raised {type(err).__name__}: {err}. {fix}"
    stops = [m for m in comm.allgather(stop) if m is not None]
    if stops:
        raise StopRequested(stops[0])
    collective_error(comm, message, RuntimeError)


def solve_load_steps(
    problem: _Solvable,
    set_load: typing.Callable[[float], None],
    num_steps: int = 10,
    *,
    start: float = 0.0,
    end: float = 1.0,
    min_step: float | None = None,
    writer=None,
    progress: bool = True,
    predictor: typing.Literal["extrapolate", "none"] = "none",
    checkpoint: str | os.PathLike | None = None,
    resume: str | os.PathLike | None = None,
) -> list[LoadStep]:
    """Solve ``problem`` for load factors from ``start`` to ``end`` with automatic step cutting.

    Each step calls ``set_load(t)`` (update a ``Constant``, a Dirichlet ``Function``, ...) and
    solves from the previous converged state, or from a prediction of the new one (below). A
    step that fails (no convergence, NaN, an inverted element raising, the line search unable
    to find an admissible state) is retried from that state with half the increment; after a
    success the increment grows back (doubles) up to the nominal ``(end - start) /
    num_steps``. The step never overshoots ``end``.

    The Dirichlet values are not written into the starting state: the problems impose them
    through the first Newton step (see :class:`ContactAssembler`).

    Args:
        problem: a :class:`ContactProblem` or :class:`NonlinearContactProblem` (anything with
            ``u``, ``contact`` and ``solve(raise_on_failure=...)``).
        set_load: sets the load for a load factor t (collective).
        num_steps: nominal number of increments.
        start, end: first and last load factor.
        min_step: smallest increment tried before giving up; default nominal / 2**10.
        writer: called with each converged state: a ``dolfinx.io.XDMFFile`` (``write_function(u,
            t)``; write the mesh first), a ``dolfinx.io.VTXWriter`` on ``u`` (``write(t)``), or
            any callable ``writer(t)``.
        progress: report each converged step on rank 0: a progress bar in a terminal or a
            notebook, one printed line otherwise (``MATDEPTH_PROGRESS=lines`` forces lines).
        predictor: ``"extrapolate"``: start each step from the last converged displacement plus
            the last converged increment scaled to the new load increment (linear
            extrapolation, as FEBio and Abaqus do), unless that would invert an element;
            ``"none"`` (default): start from the last converged displacement.
        checkpoint: save each converged step to this file (the format of
            :class:`~fenics_matdepth.checkpoint.Checkpoint`; ``.npz``), replacing the previous one.
        resume: continue from the last step saved in this checkpoint file (written by a run
            with the same ``start``, ``end``, ``num_steps`` and mesh); the returned list holds
            the steps of this call only.

    Returns:
        The converged steps. Each ``LoadStep.diagnostics`` is ``contact.diagnostics()`` plus
        ``min_det_F`` (the smallest det F over the cells) and ``rejected_states``.

    Raises:
        RuntimeError: if the increment falls below ``min_step``; ``u`` then holds the last
            converged state, whose load factor the message gives, and everything already
            written stays written. Also (on every rank) if ``set_load`` or ``writer`` raises,
            with ``u`` holding the last converged state.
        StopRequested: (on every rank) if ``set_load`` or ``writer`` raised it: a stop on
            request, not a failure; ``u`` holds the last converged state (the checkpoint holds
            it too), the exception's ``load`` and ``steps`` say where the run stopped. The load
            last set may be the next step's: call ``set_load(err.load)`` to restore it.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    if predictor not in ("extrapolate", "none"):
        raise ValueError(f'predictor must be "extrapolate" or "none", got {predictor!r}')
    if not (np.isfinite(start) and np.isfinite(end)) or start == end:
        raise ValueError(f"start and end must be distinct finite numbers, got {start}, {end}")
    u = problem.u
    comm = u.function_space.mesh.comm
    cells = CellDeterminants(u.function_space)
    nominal = (end - start) / num_steps
    min_step = abs(nominal) / 2**10 if min_step is None else float(min_step)
    steps: list[LoadStep] = []
    t, dt = float(start), nominal
    previous, dt_previous, done = None, 0.0, 0
    run = {"start": float(start), "end": float(end), "num_steps": int(num_steps)}
    if resume is not None:
        arrays, meta = Checkpoint(resume, u.function_space).load()
        if {k: meta.get(k) for k in run} != run:
            raise ValueError(
                f"the checkpoint {resume} belongs to a run with start, end, num_steps = "
                f"{meta.get('start')}, {meta.get('end')}, {meta.get('num_steps')}; resume with "
                "the same values"
            )
        u.x.array[:] = arrays["u"]
        previous = arrays.get("u_previous")
        t, dt, dt_previous, done = meta["load"], meta["dt"], meta["dt_previous"], meta["steps"]
        _collective_call(comm, f"set_load({t:.6g})", "Fix the set_load callback.", set_load, t)
    saver = Checkpoint(checkpoint, u.function_space) if checkpoint is not None else None
    saved = u.x.array.copy()
    reporter = StepProgress(comm, start, end, "load", enabled=progress)
    try:
        while (end - t) * np.sign(nominal) > 1e-12 * abs(nominal):
            t_next = t + dt
            if (end - t_next) * np.sign(nominal) < 0.0:
                t_next, dt = end, end - t
            cuts, tic = 0, time.perf_counter()
            while True:
                u.x.array[:] = saved
                _collective_call(
                    comm, f"set_load({t_next:.6g})",
                    f"Fix the set_load callback; u holds the converged state at load {t:.6g}.",
                    set_load, t_next,
                )  # fmt: skip
                if predictor == "extrapolate" and previous is not None and dt_previous != 0.0:
                    guess = saved + (dt / dt_previous) * (saved - previous)
                    if cells.min(guess) > 0.0:
                        u.x.array[:] = guess
                try:
                    result = problem.solve(raise_on_failure=False)
                    failure = None if result.converged else result.failure_message()
                except (RuntimeError, FloatingPointError, PETSc.Error) as err:
                    failure = str(err)
                failed = comm.allreduce(failure is not None, op=MPI.LOR)
                if not failed:
                    break
                cuts += 1
                u.x.array[:] = saved
                if abs(dt) / 2 < min_step:
                    _collective_call(comm, f"set_load({t:.6g})", "", set_load, t)
                    raise RuntimeError(
                        f"load stepping stopped at load factor {t:.6g}: the step to {t_next:.6g} "
                        f"failed with an increment of {abs(dt):.3g} (min_step {min_step:.3g}). "
                        f"Last failure: {failure}"
                    )
                dt /= 2
                t_next = t + dt
            previous, dt_previous = saved, dt
            t = t_next
            saved = u.x.array.copy()
            diag = problem.contact.diagnostics()
            diag["min_det_F"] = cells.min(u)
            diag["rejected_states"] = result.rejected_states
            step = LoadStep(
                t, result.iterations, result.residual_norms, cuts, diag,
                time.perf_counter() - tic, dict(getattr(problem, "timings", {})),
            )  # fmt: skip
            steps.append(step)
            _collective_call(
                comm, f"writer at load {t:.6g}",
                f"Check the writer (path writable, file open); u holds the converged state at load "
                f"{t:.6g}.", _write, writer, u, t,
            )  # fmt: skip
            reporter.step(
                t,
                f"step {done + len(steps):3d}  load {t:.4g}  newton {result.iterations:2d} it  "
                f"|r| {result.residual_norms[-1]:.2e}  cuts {cuts}  "
                f"active pairs {diag['active_pairs']}  "
                f"max penetration {diag['max_penetration']:.3e}  "
                f"min det F {diag['min_det_F']:.3f}  {step.seconds:.2f} s",
            )
            if abs(dt) < abs(nominal):
                dt = min(abs(dt) * 2, abs(nominal)) * np.sign(nominal)
            if saver is not None:
                saver.save(
                    {"u": saved, "u_previous": previous}, load=t, dt=float(dt),
                    dt_previous=float(dt_previous), steps=done + len(steps), **run,
                )  # fmt: skip
    except StopRequested as err:
        u.x.array[:] = saved
        where = f"; it is saved in {checkpoint}" if checkpoint is not None else ""
        raise StopRequested(
            f"stopped on request at load factor {t:.6g} ({err}): u holds the converged state "
            f"there{where}",
            load=t,
            steps=steps,
        ) from None
    finally:
        reporter.close()
    return steps
