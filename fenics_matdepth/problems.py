"""Newton problems with contact.

* :class:`ContactProblem`: PETSc SNES (``newtonls`` + line search) over a user's UFL residual
  plus the contact operator (its SNES callbacks in :mod:`fenics_matdepth.snes_callbacks`, its
  linear-solver policy in :mod:`fenics_matdepth.linear_solver`).
* :class:`NonlinearContactProblem`: the same residual and Jacobian as a problem for
  ``dolfinx.nls.petsc.NewtonSolver``.

Both assemble through one :class:`~fenics_matdepth.system_assembler.SystemAssembler`, which
keeps the Jacobian's sparsity pattern (bulk + contact couplings with a margin,
:meth:`ContactOperator.create_matrix`) across iterations and rebuilds it, at the start of a
Newton iteration, only when a contact coupling falls outside it. Load and time stepping are in
:mod:`fenics_matdepth.stepping`.
"""

from __future__ import annotations

import typing

from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl

from fenics_matdepth import linear_solver
from fenics_matdepth._compat import NewtonSolverProblemBase, bc_constrains_space
from fenics_matdepth.contact.ccd import ENTRY_FRACTION, ContinuousCollision
from fenics_matdepth.contact.friction import solve_with_updates
from fenics_matdepth.contact.operator import ContactOperator
from fenics_matdepth.free_bodies import FreeBodyDamping
from fenics_matdepth.linear_solver import rigid_body_modes
from fenics_matdepth.results import SolveResult
from fenics_matdepth.snes_callbacks import SNESCallbacks
from fenics_matdepth.system_assembler import TIMING_KEYS, SystemAssembler

# (kept importable from here, where they were first defined, as is rigid_body_modes)
from fenics_matdepth.tolerances import looser_tolerances, own_rtol

__all__ = [
    "ContactProblem",
    "NonlinearContactProblem",
    "looser_tolerances",
    "own_rtol",
    "rigid_body_modes",
]

#: NonlinearContactProblem halves a Newton step at most this many times while it would
#: invert an element.
MAX_STEP_HALVINGS = 30


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


class ContactProblem(SNESCallbacks, _Releasable):
    """Nonlinear problem F(u) + dE_contact/du = 0 solved with PETSc SNES.

    The Dirichlet values are imposed through the Newton step (see
    :class:`~fenics_matdepth.system_assembler.SystemAssembler`):
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
            energy) as LDL^T and any other as LU (``linear_solver.choose_factorisation``). From
            AMG_MIN_DOFS global dofs on, unless ``ksp_type`` or ``pc_type`` is given, the
            linear solver is GMRES with GAMG instead; with ``pc_type: gamg`` the rigid-body modes
            (:func:`~fenics_matdepth.rigid_body_modes`) are set as the matrix's near-nullspace.
        keep_factorisation: with the default direct solver, keep a factorisation across
            Newton iterations as the preconditioner of GMRES (exact Newton steps: to 1e-10 of
            the residual), factorising anew after a pattern rebuild and once GMRES needed more
            than REFACTORISE_ITERATIONS iterations; a solve starts on the factorisation the
            last one ended with when that one converged at the same contact penalty. A GMRES
            failure goes on from the iterate reached with a new factorisation; GMRES stops at
            its RATE_TEST_ITERATION-th iteration where its rate so far predicts more than
            RATE_TEST_LIMIT (``kept_rate_test`` counts those ``stops``). Where keeping
            does not pay (the first GMRES on a new factorisation does not converge in
            KEPT_MAX_ITERATIONS, twice in a solve), the solve factorises every Jacobian and
            the problem's next solves do not try (see ``linear_solver``). With the
            default AMG preconditioner (from AMG_MIN_DOFS dofs on), keep its hierarchy by the
            same rules, set up anew once GMRES needs more than AMG_KEPT_GROWTH times the
            iterations it took on a new one.
            ``False``: a factorisation per iteration.
        damp_free_bodies: find the bodies whose Dirichlet conditions leave a rigid motion free
            and, where their load would move them by more than an element (no contact yet) or
            a solve fails, damp them until contact holds them; the result is the undamped
            problem's (:mod:`fenics_matdepth.free_bodies`). ``False``: never.
        ccd: continuous collision detection in the line search: each Newton step is
            shortened (before the backtracking) so that no boundary vertex or edge apart from
            a triangle or edge at the iterate goes more than the entry tolerance past it
            (:class:`~fenics_matdepth.contact.ccd.ContinuousCollision`); a surface cannot jump
            through a thin layer in one Newton step. ``False``: steps are not capped.
        ccd_entry: the entry tolerance, as a fraction of the local boundary edge length.

    Attributes:
        free_bodies: the :class:`~fenics_matdepth.free_bodies.FreeBodyDamping` (its
            ``bodies``, and whether the last solve was ``damped``).
        timings: seconds spent in the last :meth:`solve`, split into ``bulk_assembly``,
            ``contact_update`` (gather, refit, pair search), ``contact_assembly`` (pair kernels
            and insertion) and ``linear_solve`` (factorisation or preconditioner set-up, and
            the solve), and ``ccd`` (continuous collision detection of the Newton steps; 0
            with ``ccd=False``): the keys of ``system_assembler.TIMING_KEYS``.
        collisions: the :class:`~fenics_matdepth.contact.ccd.ContinuousCollision` of the
            boundary (None with ``ccd=False``); ``solve_time_steps`` also truncates time steps
            with it.
        ccd_caps: Newton steps of the last solve that the collision detection shortened.
        assembler: the :class:`~fenics_matdepth.system_assembler.SystemAssembler` (residual,
            Jacobian, matrix).
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
        damp_free_bodies: bool = True,
        ccd: bool = True,
        ccd_entry: float = ENTRY_FRACTION,
    ):
        _check_problem_inputs(u, contact, bcs)
        self.u = u
        self.contact = contact
        self.collisions = ContinuousCollision(contact.surface, ccd_entry) if ccd else None
        self.ccd_caps = 0
        self.bcs = list(bcs)
        J = J if J is not None else ufl.derivative(F, u)
        self._F, self._J = dolfinx.fem.form(F), dolfinx.fem.form(J)
        self._energy = dolfinx.fem.form(energy) if energy is not None else None
        self.assembler = SystemAssembler(
            self._F, self._J, u, contact, self.bcs, self._energy, forms=(F, J, {})
        )
        self.free_bodies = FreeBodyDamping(contact, self.bcs, self.assembler, damp_free_bodies)
        self._watch = self.assembler.watch
        self.timings = dict(self._watch.totals)
        self.prefix = petsc_options_prefix
        self._create_vectors()
        user = petsc_options or {}
        self.snes = PETSc.SNES().create(u.function_space.mesh.comm)
        self.snes.setOptionsPrefix(self.prefix)
        dofmap = u.function_space.dofmap
        num_dofs = dofmap.index_map.size_global * dofmap.index_map_bs
        self._amg, keep_factorisation = linear_solver.set_solver_options(
            self.prefix, user, num_dofs, keep_factorisation
        )
        self._set_callbacks()
        self._inspect_linear_solver(user, keep_factorisation)
        self._reset_kept_factorisation()
        if self.snes.getKSP().getPC().getType() == "gamg":
            self.assembler.set_near_nullspace(rigid_body_modes(u.function_space))

    def _create_vectors(self) -> None:
        """The residual and iterate vectors, and the last residual and energy evaluated."""
        u = self.u
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

    def _set_callbacks(self) -> None:
        """Hand SNES the callbacks (:class:`~fenics_matdepth.snes_callbacks.SNESCallbacks`)
        and read the options."""
        self.snes.setFunction(self._residual, self._b)
        self.snes.setJacobian(self._jacobian, self._A, self._A)
        self.snes.setUpdate(self._start_iteration)
        self.snes.setConvergenceTest(self._converged)
        if self._energy is not None:
            self.snes.setObjective(self._objective)
        if self._energy is not None or self.collisions is not None:
            self.snes.setLineSearchPreCheck(self._precheck)
        self.snes.setFromOptions()
        ksp = self.snes.getKSP()
        ksp.setFromOptions()
        ksp.setPreSolve(self._ksp_started)
        ksp.setPostSolve(self._ksp_finished)

    def _reset_kept_factorisation(self) -> None:
        """The bookkeeping of the kept factorisation, as before a first solve."""
        # GMRES iterations of the last solve on a new AMG hierarchy
        self._fresh_iterations = 0
        self._factorise = True  # whether the coming Jacobian is factorised
        self._factorisations = self._kept_since_factorisation = 0
        self._may_keep = True  # whether this solve may keep a factorisation
        # this solve's GMRES solves on a kept factorisation that converged and that failed, and
        # its failures on the first GMRES after a factorisation (KEPT_TRIES)
        self._kept_converged = self._kept_failed = self._failed_tries = 0
        # solves that factorise every Jacobian after keeping did not pay
        self._keep_backoff = linear_solver.BackOff()
        # the operator's penalty revision at the end of the last solve if it converged (None
        # otherwise): the next solve at the same penalty may start on its factorisation;
        # whether this solve did; solves that factorise their first Jacobian after a start on
        # the last factorisation failed
        self._carried_revision = None
        self._carried = False
        self._carry_backoff = linear_solver.BackOff()
        # the solve goes on from the iterate reached (a kept factorisation's GMRES failed)
        self._resuming = False
        self._resumed_unchanged = False  # its residual and Jacobian are those of the failure
        self._iteration_offset = 0
        #: Newton steps of the last solve taken with the shifted Jacobian (_shifted_direction)
        self.shifted_steps = 0

    def _precheck(self, x: PETSc.Vec, y: PETSc.Vec) -> bool:
        """Line-search pre-check: the energy's direction check (``_check_direction``), then
        the step ``x -> x - y`` shortened to the collision detection's entry cap (collective).
        Returns whether ``y`` was changed."""
        changed = self._check_direction(x, y) if self._energy is not None else False
        if self.collisions is None:
            return changed
        x_array = x.getArray(readonly=True)
        with self._watch("ccd"):
            fraction = self.collisions.newton_fraction(x_array, x_array - y.getArray(True))
        self._step_capped = fraction < 1.0
        if fraction < 1.0:
            y.scale(fraction)
            self.ccd_caps += 1
            return True
        return changed

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

    # -- solve ----------------------------------------------------------------------------------

    def set_energy(self, energy: ufl.Form) -> None:
        """Turn the energy line search on after construction, as ``energy=`` does (the
        derivative of ``energy`` must be the residual ``F``)."""
        self._energy = dolfinx.fem.form(energy)
        self.assembler.energy_form = self._energy
        self.snes.setObjective(self._objective)
        # the pre-check that also caps the step by the collision detection (not the direction
        # check alone, which dropped it from every time step given strain_energy=)
        self.snes.setLineSearchPreCheck(self._precheck)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve from the current ``u``; ``u`` holds the last iterate afterwards (collective).

        The Dirichlet values are reached by the first Newton step, not written into ``u``
        beforehand. Bodies held only by contact are damped where needed (``damp_free_bodies``).

        Args:
            raise_on_failure: raise ``RuntimeError`` (with the residual history) when SNES does
                not converge; otherwise return the result with ``converged=False``.
        """
        return solve_with_updates(
            self.contact,
            lambda fail: self.free_bodies.solve(self, self._solve_undamped, fail),
            raise_on_failure,
        )

    def _solve_undamped(self, raise_on_failure: bool = True) -> SolveResult:
        """One SNES solve from the current ``u`` (see :meth:`solve`)."""
        start = self.u.x.petsc_vec.copy()
        # a solve keeps factorisations unless the last ones that tried found it did not pay
        self._may_keep = self._keep_backoff.take()
        self._kept_converged = self._kept_failed = self._failed_tries = 0
        # the first Newton step on the last solve's factorisation (its load changed little)
        may_carry = self._carry_backoff.take()
        self._carried = (
            self._keep_factorisation and self._may_keep and may_carry
            and self.contact.penalty_revision == self._carried_revision
        )  # fmt: skip
        self._carried_revision = None  # (until this solve converges)
        carried_failed = False
        history = []
        try:
            while True:
                if not self._resuming:
                    self._factorisations = self._iteration_offset = 0
                    self._watch.totals = dict.fromkeys(TIMING_KEYS, 0.0)
                    self._merit_is_energy, self._last_norm = True, np.inf
                    self.shifted_steps = self.ccd_caps = self.dirichlet_snaps = 0
                    self._energy_merit_allowed, self._bcs_met = True, False
                    self.assembler.rejected_states = 0
                    self.assembler.start_solve()
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
                failed = self.snes.getConvergedReason() == linear_solver.LINEAR_SOLVE_FAILED
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
            self._carried_revision = self.contact.penalty_revision
        result = SolveResult(
            reason > 0, reason, self._iteration_offset, np.asarray(history, dtype=float),
            self.assembler.rejected_states, self.min_det_F(), self.shifted_steps,
            self._factorisations,
        )  # fmt: skip
        if raise_on_failure and not result.converged:
            raise RuntimeError(result.failure_message())
        return result

    def destroy(self) -> None:
        """Release the problem's PETSc objects now: the SNES with its linear solvers and
        factorisations, the vectors and the matrix (collective: on every rank at one point).
        It cannot solve afterwards; ``u`` and the contact operator stay as they are.

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
        self.release_shift_solver()
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

    The residual and Jacobian come from the same
    :class:`~fenics_matdepth.system_assembler.SystemAssembler` as
    :class:`ContactProblem`'s. :meth:`attach` also installs the solution update: the Newton
    step (times the solver's relaxation parameter) is halved until no element is inverted
    (det F > 0 everywhere) and, with ``line_search``, until it lowers the residual norm (by
    ``1e-4`` times the step's fraction), at most ``MAX_STEP_HALVINGS`` times, after the
    continuous collision detection has capped it (``ccd``, as in :class:`ContactProblem`'s
    line search); where no fraction lowers it, the solve fails (the NewtonSolver has no line
    search of its own: a full step that reaches contact from a gap can throw a body deep into
    another).

    Args:
        F: the user's residual form, linear in the test function.
        u: the unknown displacement (the Function the contact operator was built on).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        J: Jacobian form; default ``ufl.derivative(F, u)``.
        form_compiler_options, jit_options: passed on to dolfinx's form compilation.
        damp_free_bodies: as for :class:`ContactProblem`.
        line_search: backtrack each Newton step on the residual norm (one more residual per
            Newton iteration); ``False``: take it whole unless it inverts an element.
        ccd: continuous collision detection of each Newton update, as for
            :class:`ContactProblem` (the update is shortened to the entry cap; time steps
            are truncated by ``solve_time_steps``); on by default.
        ccd_entry: the entry tolerance, as a fraction of the local boundary edge length.

    Attributes:
        collisions: the :class:`~fenics_matdepth.contact.ccd.ContinuousCollision` of the
            boundary (None with ``ccd=False``).
        ccd_caps: Newton updates of the last solve that the collision detection shortened.
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
        damp_free_bodies: bool = True,
        ccd: bool = True,
        ccd_entry: float = ENTRY_FRACTION,
        line_search: bool = True,
    ):
        _check_problem_inputs(u, contact, bcs)
        self.line_search = bool(line_search)
        super().__init__(
            F, u, bcs=list(bcs), J=J, form_compiler_options=form_compiler_options,
            jit_options=jit_options,
        )  # fmt: skip
        self.u = u
        self.contact = contact
        J = J if J is not None else ufl.derivative(F, u, ufl.TrialFunction(u.function_space))
        options = {"form_compiler_options": form_compiler_options, "jit_options": jit_options}
        self.assembler = SystemAssembler(
            self.L, self.a, u, contact, self.bcs, forms=(F, J, options)
        )
        # no line search: the damping falls only as far as a Newton step stays short
        self.free_bodies = FreeBodyDamping(
            contact, self.bcs, self.assembler, damp_free_bodies, line_search=False
        )
        self._watch = self.assembler.watch
        self._solver = None
        self._trial = u.x.petsc_vec.duplicate()
        self.collisions = ContinuousCollision(contact.surface, ccd_entry) if ccd else None
        self.ccd_caps = 0
        self._step_start = u.x.petsc_vec.duplicate()
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
        """x -= relaxation * dx, shortened to the collision detection's entry cap, then halved
        while it would invert an element or (with ``line_search``) while it does not lower the
        residual norm."""
        step = solver.relaxation_parameter
        if self.collisions is not None:
            x.copy(self._trial)
            self._trial.axpy(-step, dx)
            with self._watch("ccd"):
                x0, x1 = x.getArray(readonly=True), self._trial.getArray(readonly=True)
                fraction = self.collisions.newton_fraction(x0, x1)
            if fraction < 1.0:
                step *= fraction
                self.ccd_caps += 1
        start = self.residual_norms[-1] if self.line_search and self.residual_norms else None
        x.copy(self._step_start)  # (x is u's vector: setting a trial state overwrites it)
        lowered = start is None
        try:
            for _ in range(MAX_STEP_HALVINGS):
                self._step_start.copy(self._trial)
                self._trial.axpy(-step, dx)
                self._trial.ghostUpdate(
                    addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD
                )
                if start is None:
                    with self._trial.localForm() as local:
                        if self.assembler.cells.min(local.array_r) > 0.0:
                            break
                    self.assembler.rejected_states += 1
                else:
                    self.assembler.set_state(self._trial)
                    # (an inverted element gives a NaN residual: not lower)
                    self.assembler.residual(self._trial, self._step_start_residual())
                    if self._work.norm() < (1.0 - 1e-4 * step) * start:
                        lowered = True
                        break
                step /= 2.0
        finally:
            self._step_start.copy(x)
            self.assembler.set_state(x)
        if not lowered:
            raise RuntimeError(
                f"no fraction of the Newton step down to 2^-{MAX_STEP_HALVINGS} lowers the "
                f"residual norm {start:.3e}"
            )
        x.axpy(-step, dx)

    def _step_start_residual(self) -> PETSc.Vec:
        """A work vector for the trial residual of :meth:`_update`."""
        if getattr(self, "_work", None) is None:
            self._work = self._trial.duplicate()
        return self._work

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve with the attached NewtonSolver (one from :meth:`newton_solver` if none);
        bodies held only by contact are damped where needed (``damp_free_bodies``).

        Args:
            raise_on_failure: raise ``RuntimeError`` with the residual history if Newton does
                not converge.
        """
        return solve_with_updates(
            self.contact,
            lambda fail: self.free_bodies.solve(self, self._solve_undamped, fail),
            raise_on_failure,
        )

    def _solve_undamped(self, raise_on_failure: bool = True) -> SolveResult:
        """One Newton solve from the current ``u`` (see :meth:`solve`)."""
        if self._solver is None:
            self.newton_solver()
        self.residual_norms = []
        self.assembler.rejected_states = self.ccd_caps = 0
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
        for name in ("_trial", "_step_start", "_work"):
            if getattr(self, name, None) is not None:
                getattr(self, name).destroy()
        self._solver = None
