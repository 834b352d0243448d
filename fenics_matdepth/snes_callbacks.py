"""The Newton-iteration callbacks of :class:`~fenics_matdepth.ContactProblem`.

SNES calls them during a solve: the residual and Jacobian (through the problem's
:class:`~fenics_matdepth.SystemAssembler`), the merit function of the line search
(the total energy, or ``|F|^2 / 2``), the convergence test, the line-search pre-check that
replaces a step climbing the energy by the step of a shifted Jacobian (or reverses it), and
the start of each Newton iteration (the merit function's hand-over, the matrix's rebuild,
whether the coming Jacobian is factorised or solved on the kept factorisation). They form
:class:`SNESCallbacks`, a base class of ``ContactProblem``, whose ``__init__`` and ``solve``
set up the state they read.
"""

from __future__ import annotations

import time

from petsc4py import PETSc

import dolfinx.fem.petsc
import numpy as np

from fenics_matdepth import linear_solver
from fenics_matdepth._compat import set_lag_preconditioner

__all__ = [
    "MERIT_SWITCH_RTOL",
    "NAN_REASON",
    "NO_PROGRESS_ITERATIONS",
    "NO_PROGRESS_RTOL",
    "DIRICHLET_SNAP",
    "ROUNDING_FLOOR_RTOL",
    "LIMIT_SHIFT_BACK",
    "LIMIT_SHIFT_GROWTH",
    "LIMIT_SHIFT_START",
    "LIMIT_SHIFT_TRIES",
    "SHIFT_GROWTH",
    "SHIFT_START",
    "SHIFT_TRIES",
    "UPHILL_STEPS",
    "SLOW_CONVERGENCE_REASON",
    "STALL_RTOL",
    "SNESCallbacks",
]

#: The energy line search hands over to the residual norm once the residual has fallen by
#: this factor in a solve, or once an iteration changed it by less than STALL_RTOL (relative);
#: see SNESCallbacks._start_iteration.
MERIT_SWITCH_RTOL = 1e-5
STALL_RTOL = 1e-3

#: SNES's reason for a non-finite residual norm (renamed DIVERGED_FUNCTION_NANORINF in newer
#: PETSc; value -4 in both)
NAN_REASON = getattr(
    PETSc.SNES.ConvergedReason,
    "DIVERGED_FNORM_NAN",
    getattr(PETSc.SNES.ConvergedReason, "DIVERGED_FUNCTION_NANORINF", -4),
)

#: The reason a solve stopped by its ``stop_test`` (the step control's rate test) ends with.
SLOW_CONVERGENCE_REASON = PETSc.SNES.ConvergedReason.DIVERGED_DTOL

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
#: The search starts at the rung the last such step took and goes down while the rungs
#: qualify, or up until one does: a shift that qualifies keeps qualifying above it (no negative
#: pivot of J + mu I stays none for a larger mu), so the search ends on the rung a climb from
#: SHIFT_START would, in about two factorisations where the accepted rung repeats (on the knee
#: past 141 deg a climb took 2 to 8, 5 on average). With LU no pivot is counted, only the
#: downhill test remains, and the search may end on a higher rung than the climb.
SHIFT_START = 1e-6
SHIFT_GROWTH = 10.0
SHIFT_TRIES = 8

#: The values of ``SNESCallbacks.uphill_step``: how a Newton step that climbs the energy is
#: replaced ("shift": the step of J + mu I above; "reverse": the Newton step reversed, a
#: direction of negative curvature).
UPHILL_STEPS = ("shift", "reverse")

#: With a ``step_limit`` (SNESCallbacks.step_limit), a Newton step moving a degree of freedom
#: further is replaced by the step of ``J + mu I``, mu (relative to the mean absolute diagonal
#: of J, as above) starting at the last accepted one divided by LIMIT_SHIFT_BACK (at first
#: LIMIT_SHIFT_START) and growing LIMIT_SHIFT_GROWTH-fold until the step keeps within the
#: limit, has no negative pivot and goes downhill, at most LIMIT_SHIFT_TRIES factorisations.
#: On the knee past 144 deg the accepted mu ranged over 1e-4 to 4e2 (docs/measurements.md).
LIMIT_SHIFT_START = 1e-4
LIMIT_SHIFT_BACK = 4.0
LIMIT_SHIFT_GROWTH = 4.0
LIMIT_SHIFT_TRIES = 14

#: While the Dirichlet dofs move onto their values (through the Newton steps, see
#: SystemAssembler) only the residual norm can judge a step; once an iterate is within this
#: fraction of the solve's initial distance from them, it is set onto them (unless an element
#: would invert) and the energy judges the steps from there. Where the collision detection or
#: the line search shortened the first step, the rest came in by the same fraction of each
#: later step: on the knee at 93 deg (coarse leg) the first step went 0.98 of the way, and the
#: step to 96 deg failed after 98 iterations on the residual norm (cut to 94.5 deg); set onto
#: their values after the first step, it converged in 15.
DIRICHLET_SNAP = 0.25


class SNESCallbacks:
    """The SNES callbacks of :class:`~fenics_matdepth.ContactProblem` (its base class; the
    attributes they use are set up by ``ContactProblem.__init__`` and ``ContactProblem.solve``).

    Attributes:
        stop_test: None, or called by the convergence test with each iterate as ``(iteration,
            residual norm, target residual)``; once it returns True (and the solve has not
            converged) the solve stops with SLOW_CONVERGENCE_REASON. Load stepping with a
            :class:`~fenics_matdepth.StepControl` sets it to its
            :class:`~fenics_matdepth.step_control.SlowConvergence` for its run.
    """

    stop_test = None
    #: whether the collision detection shortened the last Newton step (ContactProblem._precheck)
    _step_capped = False
    #: the largest distance of a Dirichlet dof from its value at the solve's start
    _start_offset = 0.0
    #: iterates of the last solve whose Dirichlet dofs were set onto their values
    dirichlet_snaps = 0
    #: Newton steps taken with a Dirichlet dof off its value since the problem was made (the
    #: first step of each solve after a change of the Dirichlet values is one; the steps
    #: after it, judged by the residual norm, are the ones that cost)
    steps_off_dirichlet = 0
    _step_off_dirichlet = False  # whether the Newton step about to be taken is one
    #: None, or a :class:`~fenics_matdepth.PseudoTransient` shifting each Jacobian
    pseudo_transient = None
    _step_limit = None
    #: the shift (relative) of the last step kept within the step limit
    _limit_shift = 0.0
    #: the rung of SHIFT_START's ladder the last step that climbed the energy took
    _uphill_rung = 0
    #: factorisations of shifted matrices (the rungs tried by ``_shifted_direction``)
    shift_factorisations = 0
    _uphill_step = "shift"
    #: Newton steps reversed at a saddle (``uphill_step = "reverse"``), since the problem was made
    reversed_steps = 0
    #: (matrix, PC type, its shifted copy, the copy's KSP) of _shift_solver, or None
    _shift_kept = None

    _relaxation = None

    @property
    def relaxation(self):
        """None (the default), or a :class:`~fenics_matdepth.LocalRelaxation` that relaxes a
        concentrated residual before each Newton step after a solve's first. Setting
        it prepares the relaxation for this problem (compiles its patch forms).

        Raises:
            ValueError: on a problem made without ``energy`` (the relaxation runs where the
                energy judges the steps, once the Dirichlet dofs hold their values).
            NotImplementedError: with friction, or for an energy a patch cannot assemble
                (:meth:`~fenics_matdepth.LocalRelaxation.bind`).
        """
        return self._relaxation

    @relaxation.setter
    def relaxation(self, value) -> None:
        if value is not None:
            if self._energy is None:
                raise ValueError(
                    "the local relaxation needs the problem's energy: make the problem with "
                    "energy=... (the energy whose derivative is its residual form)"
                )
            value.bind(self)
        self._relaxation = value

    def _relax(self, snes: PETSc.SNES) -> bool:
        """The local relaxation before a Newton step, once the Dirichlet dofs hold their
        values (before, the residual's free rows hold the lifting ``A (g - x)`` too, which a
        patch's energy does not see): where it moved the iterate, SNES's residual and its norm
        are the relaxed iterate's, and the residual and energy kept for the last trial state
        are stale. Whether it moved the iterate."""
        if not (self._bcs_met and self._relaxation.wanted(snes.getFunctionNorm())):
            return False
        if self._relaxation.relax(snes.getSolution(), snes.getFunction()[0]) is None:
            return False
        self._trial_valid, self._energy_value = False, np.nan
        self._resumed_unchanged = False
        snes.setFunctionNorm(snes.getFunction()[0].norm())
        return True

    @property
    def step_limit(self) -> float | None:
        """None (the default), or the longest move of one degree of freedom in a Newton step
        the energy judges (a length, in the unit of the displacement).

        A longer Newton step (the Dirichlet dofs on their values, a direct MUMPS solver) is
        replaced by the Levenberg-Marquardt step ``(J + mu I)^-1 F`` with the smallest mu of
        a ladder (LIMIT_SHIFT_START) whose step keeps within the limit, has no negative pivot
        and goes downhill; where no mu does, the Newton step stays and the line search
        shortens it. A trust region of fixed radius: where the Jacobian is nearly singular,
        the step turns towards the energy's descent direction instead of only getting
        shorter. Each replaced step counts in ``shifted_steps`` and costs one factorisation
        per rung tried. Opt-in; the knee demo sets two median boundary edges: 873 to 1,103
        Newton iterations to 150 deg in five runs against 1,153 to 1,384 without
        (docs/measurements.md).

        Raises:
            ValueError: if set to anything but None or a positive finite number.
        """
        return self._step_limit

    @step_limit.setter
    def step_limit(self, value: float | None) -> None:
        if value is not None and not (np.isfinite(value) and value > 0.0):
            raise ValueError(f"step_limit is None or a positive finite length, got {value!r}")
        self._step_limit = None if value is None else float(value)

    @property
    def uphill_step(self) -> str:
        """How a Newton step ``y`` that climbs the energy (``F . y < 0``: the Jacobian is
        indefinite, the iterate near a saddle of the energy) is replaced once the Dirichlet
        dofs hold their values; the energy's line search then judges the new step.

        - ``"shift"`` (the default): the step of ``J + mu I``, mu the smallest of a ladder of
          shifts (SHIFT_START) whose factorisation has no negative pivot; a direct MUMPS
          solver only (otherwise the step stays). Counted in ``shifted_steps``.
        - ``"reverse"``: the Newton step reversed, ``-y``, scaled down to ``step_limit`` where
          it is longer. Along it the energy's slope ``-F . y`` and its curvature
          ``y . J y = F . y`` are both negative: the quadratic model falls without bound, so
          the step leaves the saddle (a direction of negative curvature, as trust-region
          methods take there), with no factorisation and any linear solver. Near a saddle the
          shifted step moves off it slowly: its mu exceeds the negative eigenvalue, and the
          component along that eigenvector grows by ``mu / (mu - |lambda|)`` an iteration
          (on the knee's 751-iteration path, four solves crept at ``|F|`` of 0.01 to 0.1 N
          for 18 to 31 iterations each; the one instrumented, on shifted steps of mu = the
          mean diagonal).
          Counted in ``reversed_steps``. Opt-in; the knee demo sets it: 554 to 640 Newton
          iterations to 150 deg on four paths against 525 to 751 (docs/measurements.md).

        Raises:
            ValueError: if set to anything but one of ``UPHILL_STEPS``.
        """
        return self._uphill_step

    @uphill_step.setter
    def uphill_step(self, value: str) -> None:
        if value not in UPHILL_STEPS:
            raise ValueError(f"uphill_step is one of {UPHILL_STEPS}, got {value!r}")
        self._uphill_step = value

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
            if self.pseudo_transient is not None:
                self._shift_pseudo_transient(snes, x, A)
        self._resumed_unchanged = False
        if self._choose_factorisation and self._factorise:
            with self._watch("linear_solve"):
                linear_solver.choose_factorisation(self.snes.getKSP().getPC(), A)

    def _shift_pseudo_transient(self, snes: PETSc.SNES, x: PETSc.Vec, A: PETSc.Mat) -> None:
        """The pseudo-transient continuation's shift of the Jacobian just assembled at ``x``
        (:mod:`fenics_matdepth.pseudo_transient`); a solve's first Jacobian resets it."""
        if snes.getIterationNumber() == 0 and not self._resuming:
            self.pseudo_transient.start_solve()
        scale = max(x.norm(PETSc.NormType.NORM_INFINITY), 1.0)
        bcs_met = self.assembler.bc_offset(x) <= 1e-12 * scale
        self.pseudo_transient.shift(A, self.assembler, snes.getFunctionNorm(), bcs_met)

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
        if iteration > 0:  # the step to this iterate was taken
            self.steps_off_dirichlet += int(self._step_off_dirichlet)
            self._step_off_dirichlet = False
        if not np.isfinite(fnorm):
            return NAN_REASON
        if iteration == 0 and not self._resuming:
            self._initial_norm, self._previous_norm, self._no_progress = fnorm, fnorm, 0
        slow = self.stop_test is not None and self.stop_test(
            iteration + self._iteration_offset, fnorm, max(atol, rtol * self._initial_norm)
        )
        if iteration == 0:
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
        if slow:  # the rate test says the solve will not converge in time
            return SLOW_CONVERGENCE_REASON
        return reasons.ITERATING

    def _check_direction(self, x: PETSc.Vec, y: PETSc.Vec) -> bool:
        """Line-search pre-check: the energy judges this step only if the step goes downhill
        and the Dirichlet dofs already sit on their values.

        SNES moves to ``x - lambda y`` with ``J y = F``; the energy's slope along that path is
        ``-F . y``, negative when J is positive definite. Where J is indefinite (deep, sharp
        overlaps; an iterate near a saddle of the energy), ``F . y`` can be negative: the
        Newton step climbs the energy and no step length decreases it. With the Dirichlet dofs
        on their values and a direct solver, that step is replaced by the step of ``J + mu I``
        (``_shifted_direction``), which goes downhill and is judged by the energy, or with
        ``uphill_step = "reverse"`` (any solver) by ``-y`` (``_uphill_direction``); otherwise it
        is judged by ``|F|^2 / 2``, which the Newton step always decreases for small enough
        steps. The same holds while the step still moves Dirichlet dofs onto their values:
        prescribing a displacement raises the energy, so only the residual norm can judge that
        step. Returns whether ``y`` was changed.
        """
        slope = y.dot(self._b)
        downhill = slope > 0.0
        if not downhill and self._bcs_met and self._uphill_direction(y, slope):
            self._merit_is_energy = True
            return True
        limit = self._step_limit
        if (
            limit is not None
            and downhill
            and self._bcs_met
            and self._energy_merit_allowed
            and y.norm(PETSc.NormType.NORM_INFINITY) > limit
            and self._shifted_direction(y, limit)
        ):
            self._merit_is_energy = True
            return True
        self._merit_is_energy = self._energy_merit_allowed and self._bcs_met and downhill
        return False

    def _uphill_direction(self, y: PETSc.Vec, slope: float) -> bool:
        """Replace the Newton step ``y`` that does not go downhill (``slope = F . y <= 0``) as
        ``uphill_step`` says: reversed where it climbs, else (and at a zero slope) shifted.
        Returns whether ``y`` was replaced (collective)."""
        if self._uphill_step == "reverse" and slope < 0.0:
            self._reverse_direction(y)
            return True
        return self._shifted_direction(y)

    def _reverse_direction(self, y: PETSc.Vec) -> None:
        """Reverse the climbing Newton step ``y`` (``uphill_step = "reverse"``), scaled down to
        the step limit where it moves a dof further (collective)."""
        y.scale(-1.0)
        limit = self._step_limit
        if limit is not None:
            size = y.norm(PETSc.NormType.NORM_INFINITY)
            if size > limit:
                y.scale(limit / size)
        self.reversed_steps += 1

    def _shifted_direction(self, y: PETSc.Vec, limit: float | None = None) -> bool:
        """Overwrite ``y`` with ``(J + mu I)^-1 F`` for the smallest mu of SHIFT_START *
        SHIFT_GROWTH^k (relative to the mean absolute diagonal of J) whose factorisation has no
        negative pivot (LDL^T; LU: none counted) and whose step goes downhill (collective),
        searched from the rung the last such step took; with a ``limit``, for the smallest of
        the ladder from LIMIT_SHIFT_START or the last accepted shift whose step also moves no
        entry further than ``limit``. Returns False, leaving ``y``, where the linear solver is
        not MUMPS or no mu up to the last try gives such a step."""
        solver_pc = self.snes.getKSP().getPC()
        if not linear_solver.is_mumps_direct(solver_pc):
            return False
        pc_type = solver_pc.getType()
        A = self._A
        diagonal = A.getDiagonal()
        # (not diagonal.norm(NORM_1), whose rounding depends on where the vector lies)
        scale = linear_solver.abs_sum(diagonal) / max(diagonal.getSize(), 1)
        diagonal.destroy()
        B, ksp = self._shift_solver(A, pc_type)
        if limit is None:
            start, growth, tries = SHIFT_START, SHIFT_GROWTH, SHIFT_TRIES
            first = min(self._uphill_rung, tries - 1)
        else:
            start = max(self._limit_shift / LIMIT_SHIFT_BACK, LIMIT_SHIFT_START)
            growth, tries, first = LIMIT_SHIFT_GROWTH, LIMIT_SHIFT_TRIES, 0
        shifts = [start * scale]
        for _ in range(tries - 1):
            shifts.append(shifts[-1] * growth)
        trial = y.duplicate()
        shifted_by = 0.0  # B holds J + shifted_by I

        def qualifies(k: int) -> bool:
            """Factorise J + mu_k I, solve for ``trial``: whether its step qualifies."""
            nonlocal shifted_by
            B.shift(shifts[k] - shifted_by)  # the matrix's new state: MUMPS factorises again
            shifted_by = shifts[k]
            with self._watch("linear_solve"):
                ksp.solve(self._b, trial)
            self.shift_factorisations += 1
            factor = ksp.getPC().getFactorMatrix()
            negative = factor.getMumpsInfog(12) if pc_type == "cholesky" else 0
            del factor  # (a borrowed wrapper: see _shift_solver)
            return (
                ksp.getConvergedReason() > 0
                and negative == 0
                and trial.dot(self._b) > 0.0
                and (limit is None or trial.norm(PETSc.NormType.NORM_INFINITY) <= limit)
            )

        try:
            if qualifies(first):  # down while the rungs qualify
                taken = first
                trial.copy(y)
                while taken > 0 and qualifies(taken - 1):
                    taken -= 1
                    trial.copy(y)
            else:  # up until one does
                taken = next((k for k in range(first + 1, tries) if qualifies(k)), None)
                if taken is None:
                    return False
                trial.copy(y)
            if limit is None:
                self._uphill_rung = taken
            else:
                self._limit_shift = shifts[taken] / scale
            self.shifted_steps += 1
            return True
        finally:
            trial.destroy()

    def _shift_solver(self, A: PETSc.Mat, pc_type: str) -> tuple[PETSc.Mat, PETSc.KSP]:
        """A copy of ``A`` and the MUMPS solver (``pc_type``) of the shifted steps, kept while
        ``A`` is the problem's matrix: MUMPS then analyses the pattern once per matrix, not
        once per shifted step (on the knee, 197 of a run's 320 analyses, 0.06 s each)."""
        if self._shift_kept is not None:
            matrix, kept_type, B, ksp = self._shift_kept
            if matrix is A and kept_type == pc_type:
                A.copy(B, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
                return B, ksp
        self.release_shift_solver()
        B = A.copy()
        ksp = PETSc.KSP().create(A.getComm())
        ksp.setType("preonly")
        ksp.setOperators(B)
        pc = ksp.getPC()
        pc.setType(pc_type)
        pc.setFactorSolverType("mumps")
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        factor.setMumpsIcntl(13, 1)  # negative pivots counted on the root node too
        factor.setMumpsIcntl(14, linear_solver.LDLT_WORKSPACE_PERCENT)
        # the borrowed PC and factor go now, before their KSP can: on more than one rank
        # petsc4py defers the destruction of an object whose last reference is a Python
        # wrapper to PETSc's garbage (freed only by PETSc.garbage_cleanup), and a PC kept by
        # its wrapper past ksp.destroy() held a MUMPS factorisation there per shifted step
        # (the knee on 2 ranks grew by GBs)
        del pc, factor
        self._shift_kept = (A, pc_type, B, ksp)
        return B, ksp

    def release_shift_solver(self) -> None:
        """Destroy the kept solver of the shifted steps and its matrix (collective)."""
        if self._shift_kept is not None:
            _, _, B, ksp = self._shift_kept
            self._shift_kept = None
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
            # only a step the energy judged, at the length the line search chose, tells that
            # the energy stalled: a step the collision detection shortened (to 1e-3 of the
            # Newton step and less where a surface would pass another) changes the residual
            # little because it is short, not because the energy no longer resolves it
            self._merit_is_energy
            and not self._step_capped
            and abs(norm - self._last_norm) <= STALL_RTOL * self._last_norm
        ):
            self._energy_merit_allowed = False
        self._last_norm = norm
        x = snes.getSolution()
        scale = max(x.norm(PETSc.NormType.NORM_INFINITY), 1.0)
        offset = self.assembler.bc_offset(x)
        if self._energy is not None:
            if iteration == 0:
                if not self._resuming:
                    self._start_offset = offset
            elif (
                1e-12 * scale < offset <= DIRICHLET_SNAP * self._start_offset
                and self._snap_dirichlet(snes, x)
            ):
                offset = 0.0
                self._last_norm = snes.getFunctionNorm()
            self._bcs_met = offset <= 1e-12 * scale
        self._step_off_dirichlet = offset > 1e-12 * scale
        if self._relaxation is not None and iteration > 0 and self._relax(snes):
            self._last_norm = snes.getFunctionNorm()
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
                growth = linear_solver.AMG_KEPT_GROWTH
                no_longer_pays = gmres_iterations > growth * self._fresh_iterations
            else:
                no_longer_pays = gmres_iterations > linear_solver.REFACTORISE_ITERATIONS
            self._factorise = (
                (iteration == 0 and (self._resuming or not self._carried))
                or rebuilt
                or not self._may_keep
                or no_longer_pays
                or self._stick_slip_moved()
            )
            set_lag_preconditioner(self.snes, -2 if self._factorise else -1)
            if self._factorise:
                self._factorisations += 1
                self._kept_since_factorisation = 0
                if hasattr(self.contact, "mark_stick_slip"):
                    self.contact.mark_stick_slip()
            else:
                self._kept_since_factorisation += 1

    def _snap_dirichlet(self, snes: PETSc.SNES, x: PETSc.Vec) -> bool:
        """Set the Dirichlet dofs of the iterate ``x`` onto their values, unless an element
        would invert; then the residual (SNES's function vector and norm) is that of the new
        iterate. Returns whether ``x`` was changed (collective)."""
        trial = x.copy()
        dolfinx.fem.petsc.set_bc(trial, self.assembler.bcs)
        try:
            self._set_state(trial)
            if not self.min_det_F() > 0.0:
                self._set_state(x)
                return False
            trial.copy(x)
        finally:
            trial.destroy()
        self._trial_valid, self._energy_value = False, np.nan
        f = snes.getFunction()[0]
        snes.computeFunction(x, f)
        snes.setFunctionNorm(f.norm())
        self.dirichlet_snaps += 1
        return True

    def _stick_slip_moved(self) -> bool:
        """Whether the friction's stick/slip set moved too far since the last factorisation for
        GMRES on it (``stick_slip_change`` above FRICTION_SWITCH_SHARE; collective; False
        without friction)."""
        change = getattr(self.contact, "stick_slip_change", None)
        return change is not None and change() > linear_solver.FRICTION_SWITCH_SHARE

    def _inspect_linear_solver(self, user: dict, keep_factorisation: bool) -> None:
        """What the linear solver the options made allows: the choice of LDL^T or LU, AMG,
        keeping a factorisation."""
        pc = self.snes.getKSP().getPC()
        # the default direct solver: LDL^T for the symmetric Jacobians (choose_factorisation)
        self._choose_factorisation = "pc_type" not in user and linear_solver.is_mumps_direct(pc)
        self._amg = self._amg and pc.getType() == "gamg"  # (PETSC_OPTIONS may differ)
        # the direct solver keeps its factorisation (KEPT_FACTORISATION_OPTIONS)
        self._keep_factorisation = keep_factorisation and (self._choose_factorisation or self._amg)
        #: GMRES on a kept factorisation stopped early by its rate (linear_solver.KeptRateTest)
        self.kept_rate_test = linear_solver.KeptRateTest()
        if self._keep_factorisation and not self._amg:
            self.snes.getKSP().addConvergenceTest(self.kept_rate_test)

    def _count_kept_failure(self) -> None:
        """Count a GMRES failure on a kept factorisation. Once the first GMRES on a new
        factorisation failed KEPT_TRIES times, the rest of the solve factorises every
        Jacobian."""
        self._kept_failed += 1
        if self._kept_since_factorisation == 1:
            self._failed_tries += 1
            self._may_keep = self._failed_tries < linear_solver.KEPT_TRIES

    def _ksp_started(self, ksp, b, x) -> None:
        self._ksp_start = time.perf_counter()

    def _ksp_finished(self, ksp, b, x) -> None:
        self._watch.add("linear_solve", time.perf_counter() - self._ksp_start)
