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
import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth._compat import NewtonSolverProblemBase
from fenics_matdepth.contact.operator import ContactOperator

__all__ = [
    "ContactProblem",
    "LoadStep",
    "NonlinearContactProblem",
    "SolveResult",
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

#: The energy line search hands over to the residual norm once the residual has fallen by
#: this factor in a solve, or once an iteration changed it by less than STALL_RTOL (relative);
#: see ContactProblem._start_iteration.
MERIT_SWITCH_RTOL = 1e-5
STALL_RTOL = 1e-3

#: Names of the per-solve time split (seconds) kept in ``ContactProblem.timings``.
TIMING_KEYS = (
    "bulk_assembly",
    "contact_update",
    "contact_assembly",
    "linear_solve",
)


@dataclasses.dataclass
class SolveResult:
    """Outcome of a Newton solve.

    Attributes:
        converged: whether the solver reported convergence.
        reason: SNES converged reason (``PETSc.SNES.ConvergedReason``; > 0 converged); for
            :class:`NonlinearContactProblem` 1 if converged, -1 otherwise.
        iterations: Newton iterations taken.
        residual_norms: residual norm before each iteration and after the last one.
    """

    converged: bool
    reason: int
    iterations: int
    residual_norms: np.ndarray

    def failure_message(self) -> str:
        """Why the solve failed, with the residual history."""
        return (
            f"contact Newton solve did not converge (reason {self.reason}) after "
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


def _assemble_residual(b, L, a, bcs, x, contact, watch):
    """b = F(u) + dE/du with dolfinx's lifting and Dirichlet rows (DOLFINx's residual order)."""
    with watch("bulk_assembly"):
        with b.localForm() as b_local:
            b_local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(b, L)
    with watch("contact_assembly"):
        contact.add_residual(b)
    with watch("bulk_assembly"):
        dolfinx.fem.petsc.apply_lifting(b, [a], [bcs], x0=[x], alpha=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        dolfinx.fem.petsc.set_bc(b, bcs, x, -1.0)


def _assemble_jacobian(A, a, bcs, contact, watch):
    """A = dF/du + d2E/du2, Dirichlet rows and columns as dolfinx sets them."""
    with watch("bulk_assembly"):
        A.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(A, a, bcs)
        A.assemble()
    with watch("contact_assembly"):
        contact.add_jacobian(A)


class ContactProblem:
    """Nonlinear problem F(u) + dE_contact/du = 0 solved with PETSc SNES.

    Args:
        F: the user's residual form (any UFL physics), linear in the test function.
        u: the unknown displacement (P1 vector Function, the one the contact operator uses).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        J: Jacobian form; default ``ufl.derivative(F, u)``.
        energy: optional UFL energy functional whose derivative is ``F``; when given, the
            backtracking line search works on the total energy (bulk + contact) instead of the
            residual norm, until the energy's rounding noise stalls it near the solution (then
            on the residual norm; see ``_start_iteration``).
        petsc_options_prefix: prefix of this problem's PETSc options.
        petsc_options: options set under the prefix (defaults: newtonls, bt line search, LU with
            MUMPS, rtol 1e-10, atol 1e-12, at most 50 iterations).

    Attributes:
        timings: seconds spent in the last :meth:`solve`, split into ``bulk_assembly``,
            ``contact_update`` (gather, refit, pair search), ``contact_assembly`` (pair kernels
            and insertion) and ``linear_solve``.
        pattern_rebuilds: how many times the matrix was rebuilt because contact couplings left
            its sparsity pattern (over the problem's life).
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
    ):
        if contact.u is not u:
            raise ValueError("the contact operator must be built on the same Function u")
        self.u = u
        self.contact = contact
        self.bcs = list(bcs)
        self._F = dolfinx.fem.form(F)
        self._J = dolfinx.fem.form(J if J is not None else ufl.derivative(F, u))
        self._energy = dolfinx.fem.form(energy) if energy is not None else None
        contact.set_bcs(self.bcs)
        self.prefix = petsc_options_prefix
        self._watch = _Stopwatch()
        self.timings = dict(self._watch.totals)
        self.pattern_rebuilds = 0
        comm = u.function_space.mesh.comm

        self._A = contact.create_matrix(self._J)
        # Ghosted, as dolfinx's assembly and lifting read and write ghost entries.
        self._b = u.x.petsc_vec.duplicate()
        self._x = u.x.petsc_vec.duplicate()
        # the residual merit function's last evaluation: point and residual
        self._x_trial = u.x.petsc_vec.duplicate()
        self._b_trial = u.x.petsc_vec.duplicate()
        self._trial_valid = False
        self._residuals_reused = 0
        self.snes = PETSc.SNES().create(comm)
        self.snes.setOptionsPrefix(self.prefix)
        opts = PETSc.Options()
        opts.prefixPush(self.prefix)
        for key, value in {**_DEFAULT_OPTIONS, **(petsc_options or {})}.items():
            opts[key] = value
        opts.prefixPop()
        self.snes.setFunction(self._residual, self._b)
        self.snes.setJacobian(self._jacobian, self._A, self._A)
        self.snes.setUpdate(self._start_iteration)
        if self._energy is not None:
            self.snes.setObjective(self._objective)
            self.snes.setLineSearchPreCheck(self._check_direction)
        self.snes.setFromOptions()
        ksp = self.snes.getKSP()
        ksp.setFromOptions()
        ksp.setPreSolve(self._ksp_started)
        ksp.setPostSolve(self._ksp_finished)

    # -- callbacks ----------------------------------------------------------------------------

    def _set_state(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.u.x.petsc_vec)
        self.u.x.scatter_forward()
        with self._watch("contact_update"):
            self.contact.update()

    def _residual(self, snes: PETSc.SNES, x: PETSc.Vec, b: PETSc.Vec) -> None:
        self._set_state(x)
        if self._trial_valid and x.equal(self._x_trial):
            # SNES asks for the residual at the step the line search just accepted, which the
            # residual merit function (`_objective`) has assembled already
            self._b_trial.copy(b)
            self._residuals_reused += 1
            return
        _assemble_residual(b, self._F, self._J, self.bcs, x, self.contact, self._watch)

    def _jacobian(self, snes: PETSc.SNES, x: PETSc.Vec, A: PETSc.Mat, P: PETSc.Mat) -> None:
        # SNES evaluates the residual at x before the Jacobian, so the contact state is current.
        _assemble_jacobian(A, self._J, self.bcs, self.contact, self._watch)

    def _objective(self, snes: PETSc.SNES, x: PETSc.Vec) -> float:
        if not self._merit_is_energy:
            self._trial_valid = False
            self._residual(snes, x, self._b_trial)
            x.copy(self._x_trial)
            self._trial_valid = True
            return 0.5 * self._b_trial.norm() ** 2
        self._set_state(x)
        comm = self.u.function_space.mesh.comm
        with self._watch("bulk_assembly"):
            bulk = comm.allreduce(dolfinx.fem.assemble_scalar(self._energy))
        with self._watch("contact_assembly"):
            return bulk + self.contact.energy()

    def _check_direction(self, x: PETSc.Vec, y: PETSc.Vec) -> None:
        """Line-search pre-check: the energy judges this step only if the step goes downhill.

        SNES moves to ``x - lambda y`` with ``J y = F``; the energy's slope along that path is
        ``-F . y``, negative when J is positive definite. Where the contact Hessian makes J
        indefinite (deep, sharp overlaps), ``F . y`` can be negative: the Newton step climbs
        the energy and no step length decreases it. That step is judged by ``|F|^2 / 2``
        instead, which the Newton step always decreases for small enough steps.
        """
        self._merit_is_energy = self._energy_merit_allowed and y.dot(self._b) > 0.0

    def _start_iteration(self, snes: PETSc.SNES, iteration: int) -> None:
        """Before each Newton step's Jacobian: switch the line search's merit function if the
        energy stalled; rebuild the matrix if contact left its pattern.

        Near the solution a Newton step changes the energy by about ``r^2 / k`` (r the
        residual, k a stiffness), which falls below the energy's rounding error (relative to
        the stress scale, not to the energy, which may be near zero) while r is still well
        above the tolerance; the energy line search then cuts every step to almost nothing and
        Newton stalls. So once the residual has fallen by MERIT_SWITCH_RTOL, or an iteration
        stalled, the line search judges steps by ``|F|^2 / 2`` instead, which a Newton step in
        its quadratic range decreases. (Measured on the block presses of the tests and
        benchmark: the energy stops resolving steps at residuals of 1e-7 to 1e-8 of the
        initial one.)
        """
        norm = snes.getFunctionNorm()
        if iteration == 0:
            self._first_norm = norm
        elif (
            norm <= MERIT_SWITCH_RTOL * self._first_norm
            or abs(norm - self._last_norm) <= STALL_RTOL * self._last_norm
        ):
            self._energy_merit_allowed = False
        self._last_norm = norm
        self._set_state(snes.getSolution())
        with self._watch("contact_update"):
            rebuild = self.contact.pattern_needs_rebuild()
        if rebuild:
            with self._watch("contact_update"):
                A = self.contact.create_matrix(self._J)
            snes.setJacobian(self._jacobian, A, A)
            self._A.destroy()
            self._A = A
            self.pattern_rebuilds += 1

    def _ksp_started(self, ksp, b, x) -> None:
        self._ksp_start = time.perf_counter()

    def _ksp_finished(self, ksp, b, x) -> None:
        self._watch.totals["linear_solve"] += time.perf_counter() - self._ksp_start

    # -- solve ----------------------------------------------------------------------------------

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve from the current ``u``; ``u`` holds the last iterate afterwards (collective).

        Args:
            raise_on_failure: raise ``RuntimeError`` (with the residual history) when SNES does
                not converge; otherwise return the result with ``converged=False``.
        """
        self._watch.totals = dict.fromkeys(TIMING_KEYS, 0.0)
        self._merit_is_energy, self._last_norm = True, np.inf
        self._energy_merit_allowed = True
        self._trial_valid = False  # the load may have changed since
        self.u.x.petsc_vec.copy(self._x)
        dolfinx.fem.petsc.set_bc(self._x, self.bcs)
        self.snes.setConvergenceHistory(reset=True)
        self.snes.solve(None, self._x)
        self._set_state(self._x)
        self.timings = dict(self._watch.totals)
        history = np.asarray(self.snes.getConvergenceHistory()[0], dtype=float)
        reason = int(self.snes.getConvergedReason())
        result = SolveResult(reason > 0, reason, int(self.snes.getIterationNumber()), history)
        if raise_on_failure and not result.converged:
            raise RuntimeError(result.failure_message())
        return result

    def __del__(self):
        for obj in ("snes", "_A", "_b", "_x", "_x_trial", "_b_trial"):
            if getattr(self, obj, None) is not None:
                getattr(self, obj).destroy()


class NonlinearContactProblem(NewtonSolverProblemBase):
    """F(u) + dE_contact/du = 0 as a problem for ``dolfinx.nls.petsc.NewtonSolver``.

    The contact Jacobian needs a matrix with the contact couplings in its sparsity pattern,
    which the solver's own matrix (made from the bulk form alone) does not have; hand the
    solver this problem's matrix with :meth:`attach`, or let :meth:`newton_solver` build a
    configured solver::

        problem = fm.NonlinearContactProblem(F, u, contact, bcs)
        solver = dolfinx.nls.petsc.NewtonSolver(comm, problem)
        problem.attach(solver)          # or: solver = problem.newton_solver()
        n, converged = solver.solve(u)

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
        if contact.u is not u:
            raise ValueError("the contact operator must be built on the same Function u")
        super().__init__(
            F, u, bcs=list(bcs), J=J, form_compiler_options=form_compiler_options,
            jit_options=jit_options,
        )  # fmt: skip
        self.u = u
        self.contact = contact
        contact.set_bcs(self.bcs)
        self._matrix = contact.create_matrix(self.a)
        self._solver = None
        self._watch = _Stopwatch()
        self.pattern_rebuilds = 0
        #: residual norm at each residual evaluation of the current solve
        self.residual_norms: list[float] = []

    @property
    def matrix(self) -> PETSc.Mat:
        """The Jacobian matrix (bulk + contact pattern) the solver must use."""
        return self._matrix

    def attach(self, solver) -> None:
        """Make ``solver`` (a ``dolfinx.nls.petsc.NewtonSolver`` of this problem) assemble the
        Jacobian into :attr:`matrix`; also lets the problem swap in a rebuilt matrix when
        contact couplings leave the pattern."""
        solver.setJ(self.J, self._matrix)
        self._solver = solver

    def newton_solver(self, **settings) -> typing.Any:
        """A ``dolfinx.nls.petsc.NewtonSolver`` for this problem, attached, with settings.

        Defaults: residual convergence criterion, rtol 1e-10, atol 1e-12, at most 50
        iterations, no error on non-convergence (``solve`` reports it), LU with MUMPS.

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
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if x.handle != self.u.x.petsc_vec.handle:
            x.copy(self.u.x.petsc_vec)
            self.u.x.scatter_forward()
        with self._watch("contact_update"):
            self.contact.update()
            rebuild = self.contact.pattern_needs_rebuild()
        if rebuild:
            if self._solver is None:
                raise RuntimeError(
                    "contact couplings left the matrix pattern and no solver is attached: call "
                    "problem.attach(solver) after creating the NewtonSolver"
                )
            with self._watch("contact_update"):
                matrix = self.contact.create_matrix(self.a)
            self._solver.setJ(self.J, matrix)
            self._matrix.destroy()
            self._matrix = matrix
            self.pattern_rebuilds += 1

    def F(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """Assemble the residual F(u) + dE/du into ``b``."""
        _assemble_residual(b, self.L, self.a, self.bcs, x, self.contact, self._watch)
        self.residual_norms.append(b.norm())

    def J(self, x: PETSc.Vec, A: PETSc.Mat) -> None:
        """Assemble the Jacobian into ``A`` (which must be :attr:`matrix`)."""
        if A.handle != self._matrix.handle:
            raise RuntimeError(
                "the NewtonSolver assembles into its own matrix, which lacks the contact "
                "couplings: call problem.attach(solver) (or use problem.newton_solver())"
            )
        _assemble_jacobian(A, self.a, self.bcs, self.contact, self._watch)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve with the attached NewtonSolver (one from :meth:`newton_solver` if none).

        Args:
            raise_on_failure: raise ``RuntimeError`` with the residual history if Newton does
                not converge.
        """
        if self._solver is None:
            self.newton_solver()
        self.residual_norms = []
        iterations, converged = self._solver.solve(self.u)
        self.u.x.scatter_forward()
        with self._watch("contact_update"):
            self.contact.update()
        result = SolveResult(
            bool(converged), 1 if converged else -1, int(iterations),
            np.asarray(self.residual_norms, dtype=float),
        )  # fmt: skip
        if raise_on_failure and not converged:
            raise RuntimeError(result.failure_message())
        return result

    def __del__(self):
        if hasattr(self, "_matrix"):
            self._matrix.destroy()


# -- load stepping -----------------------------------------------------------------------------


@dataclasses.dataclass
class LoadStep:
    """One converged load step of :func:`solve_load_steps`.

    Attributes:
        load: the load factor reached (the argument of ``set_load``).
        iterations: Newton iterations of the converged solve.
        residual_norms: its residual history.
        cuts: failed attempts (step halvings) before this step converged.
        diagnostics: ``contact.diagnostics()`` after the step.
        seconds: wall time of the step, failed attempts included.
    """

    load: float
    iterations: int
    residual_norms: np.ndarray
    cuts: int
    diagnostics: dict
    seconds: float


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
) -> list[LoadStep]:
    """Solve ``problem`` for load factors from ``start`` to ``end`` with automatic step cutting.

    Each step calls ``set_load(t)`` (update a ``Constant``, a Dirichlet ``Function``, ...) and
    solves from the previous converged state. A step that fails (no convergence, NaN, an
    inverted element raising) is retried from that state with half the increment; after a
    success the increment grows back (doubles) up to the nominal ``(end - start) /
    num_steps``. The step never overshoots ``end``.

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
        progress: print one line per converged step on rank 0.

    Returns:
        The converged steps.

    Raises:
        RuntimeError: if the increment falls below ``min_step``; ``u`` then holds the last
            converged state, whose load factor the message gives, and everything already
            written stays written.
    """
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    u = problem.u
    comm = u.function_space.mesh.comm
    nominal = (end - start) / num_steps
    min_step = abs(nominal) / 2**10 if min_step is None else float(min_step)
    steps: list[LoadStep] = []
    t, dt = float(start), nominal
    saved = u.x.array.copy()
    while (end - t) * np.sign(nominal) > 1e-12 * abs(nominal):
        t_next = t + dt
        if (end - t_next) * np.sign(nominal) < 0.0:
            t_next, dt = end, end - t
        cuts, tic = 0, time.perf_counter()
        while True:
            set_load(t_next)
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
                set_load(t)
                raise RuntimeError(
                    f"load stepping stopped at load factor {t:.6g}: the step to {t_next:.6g} "
                    f"failed with an increment of {abs(dt):.3g} (min_step {min_step:.3g}). "
                    f"Last failure: {failure}"
                )
            dt /= 2
            t_next = t + dt
        t = t_next
        saved = u.x.array.copy()
        diag = problem.contact.diagnostics()
        step = LoadStep(
            t, result.iterations, result.residual_norms, cuts, diag, time.perf_counter() - tic
        )
        steps.append(step)
        _write(writer, u, t)
        if progress and comm.rank == 0:
            print(
                f"step {len(steps):3d}  load {t:.4g}  newton {result.iterations:2d} it  "
                f"|r| {result.residual_norms[-1]:.2e}  cuts {cuts}  "
                f"active pairs {diag['active_pairs']}  "
                f"max penetration {diag['max_penetration']:.3e}  {step.seconds:.2f} s",
                flush=True,
            )
        if abs(dt) < abs(nominal):
            dt = min(abs(dt) * 2, abs(nominal)) * np.sign(nominal)
    return steps
