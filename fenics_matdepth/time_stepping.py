"""Time stepping: :func:`solve_time_steps`, the time-step front-end of
:class:`~fenics_matdepth.stepping.StepEngine` (an integrator's steps with step control:
rejection by penetration, energy change or a collision's entry cap, growth after ``grow_after``
steps without a cut, energies per step).
"""

from __future__ import annotations

import time
import typing

import dolfinx
import numpy as np
import ufl

from fenics_matdepth import impacts
from fenics_matdepth.contact.ccd import pass_through_message
from fenics_matdepth.penalty_raise import PenaltyRaise
from fenics_matdepth.results import Solvable, SolveResult, TimeStep
from fenics_matdepth.stepping import StepEngine, write_state

if typing.TYPE_CHECKING:
    from fenics_matdepth.dynamics import BackwardEuler, Newmark

__all__ = ["solve_time_steps"]

#: A converged step whose trajectory takes a pair past the entry tolerance is truncated
#: unless no pair went deeper than this many entry tolerances past its first contact.
ACCEPTED_ENTRY = 1.5


def _form_value(form, comm, missing: float = 0.0) -> float:
    if form is None:
        return missing
    return comm.allreduce(float(np.real(dolfinx.fem.assemble_scalar(form))))


class _TimeSteps(StepEngine):
    """:func:`solve_time_steps`'s stepping (see there); the caller has set up the initial
    state and its record."""

    def __init__(self, problem, integrator, t_end, dt, writer, on_step, min_dt, max_dt,
                 set_time, forms, max_penetration, max_energy_change, grow_after, predict,
                 progress, max_energy_gain=None):  # fmt: skip
        super().__init__(problem, integrator.t, t_end, "t", progress, on_step)
        self.integrator, self.writer, self.set_time = integrator, writer, set_time
        self.forms = forms
        self.min_dt, self.max_dt = min_dt, max_dt
        self.max_penetration, self.max_energy_change = max_penetration, max_energy_change
        self.max_energy_gain = max_energy_gain
        self.grow_after, self.predict = grow_after, predict
        self.contact = getattr(problem, "contact", None)
        # continuous collision detection: the predictor and the converged step are cut at
        # their entry cap (truncate, resume_dt: the pending truncation and the step after it)
        self.collisions = getattr(problem, "collisions", None)
        self.truncations, self.truncate, self.resume_dt = 0, None, None
        self.passing = False  # this try starts at min_dt from a prediction capped at an exit
        self.raiser: PenaltyRaise | None = None  # max_penalty's
        self.t = integrator.t
        self.tol = 1e-12 * max(abs(t_end), max_dt)
        self.step_dt, self.successes = min(float(dt), max_dt), 0
        #: the midpoint contact term standing in for the operator in the problem's assembler
        self.step_contact: impacts.MidpointContact | None = None
        self.contact_force = "endpoint"

    def record(self, step, t, dt, result, cuts, seconds) -> TimeStep:
        """The record of the state at ``t`` (step 0: the initial state)."""
        contact, integrator, forms, comm = self.contact, self.integrator, self.forms, self.comm
        diag = contact.diagnostics() if contact is not None else {}

        kinetic = integrator.kinetic_energy() if integrator.rho is not None else np.nan
        return TimeStep(
            step=step, t=t, dt=dt, iterations=result.iterations,
            residual_norms=result.residual_norms, cuts=cuts, diagnostics=diag,
            kinetic_energy=kinetic, strain_energy=_form_value(forms["strain"], comm, np.nan),
            contact_energy=diag.get("energy", 0.0),
            external_work=_form_value(forms["external"], comm), seconds=seconds,
            truncations=self.truncations if step else 0,
        )  # fmt: skip

    def started(self) -> None:
        self.reporter.message(self.line(self.records[-1]))

    def finished(self) -> bool:
        return not self.end - self.t > self.tol

    def _start(self, this_dt: float) -> None:
        """Begin the step of length ``this_dt`` from the last accepted state: the integrator's
        dt, the user's time, and the prediction (or the last state)."""
        self.this_dt = self.integrator.dt = this_dt
        if self.set_time is not None:
            self.set_time(self.t + this_dt)
        if self.predict:
            self.integrator.predict()
        else:
            self.integrator.restore()

    def prepare(self) -> None:
        t, t_end, integrator = self.t, self.end, self.integrator
        this_dt = min(self.step_dt, t_end - t)
        if t_end - (t + this_dt) < self.tol:
            this_dt = t_end - t
        self._start(this_dt)
        self.truncate, self.passing = None, False
        if self.predict and self.collisions is not None:
            u_prev, u = integrator.u_prev.x.array, self.u.x.array
            fraction = self.collisions.step_fraction(u_prev, u)
            if fraction < 1.0 and this_dt > self.min_dt:
                # the step ends where the prediction (u_prev + dt v_prev, linear in dt) makes
                # first contact: truncating at the converged state's cap instead chased caps
                # near 1, as the solver stops a body at the surface whatever the step (43
                # truncations of about 0.965 each on a plate falling edge-first)
                self.truncations += 1
                full, this_dt = this_dt, max(this_dt * fraction, self.min_dt)
                self.reporter.message(
                    f"      t {t:.5g}: dt {full:.3g} truncated to {this_dt:.3g} at the "
                    "predicted contact"
                )
                self._start(this_dt)
                fraction = self.collisions.step_fraction(u_prev, u)
            # at min_dt a vertex would leave a body through its far side: Newton tries the step
            # from the capped prediction (the penalty may yet hold the vertex, as on the stiff
            # plate of tests/test_ccd_impact.py); if it fails, the stop names the penalty needed
            self.passing = (
                fraction < 1.0 and this_dt <= self.min_dt and self.collisions.passing_through
            )
            if fraction < 1.0:
                # Newton starts on this side of any surface the prediction would jump through
                u[:] = u_prev + fraction * (u - u_prev)

    def _stop_passing_through(self, failure: str | None) -> None:
        """Give up: even the smallest step's prediction takes a vertex out of a body through
        its far side, and Newton failed from its capped prediction (the penalty is too weak for
        the layer); the last state is restored. With ``max_penalty`` the penalty is raised
        instead and the stepping goes back to the last state without contact."""
        t = self.t
        self.integrator.restore()
        if self.set_time is not None:
            self.set_time(t)
        if self.contact is not None:
            self.contact.update()
        kinetic = self.integrator.kinetic_energy() if self.integrator.rho is not None else np.nan
        back = self.raiser.attempt(t, kinetic) if self.raiser is not None else None
        if back is not None:
            step, self.t, self.step_dt = back
            del self.records[step + 1 :]
            self.resume_dt, self.successes, self.truncations = None, 0, 0
            if self.set_time is not None:
                self.set_time(self.t)
            self.reporter.message(
                f"      t {t:.5g}: penalty raised to {self.contact.penalty:.3g}, back to "
                f"t {self.t:.5g}"
            )
            return
        cause = pass_through_message(self.contact, kinetic) if self.contact is not None else ""
        raise RuntimeError(
            f"time stepping stopped at t = {t:.6g}, dt = {self.this_dt:.3g} (min_dt "
            f"{self.min_dt:.3g}). {cause} (The smallest step's Newton solve, started from "
            f"the prediction held inside, failed: {(failure or 'on another rank')[:120]})"
        )

    def check(self, result: SolveResult) -> str | None:
        """Why a converged step is rejected by the step controller, or None (at ``min_dt``
        the step is accepted anyway). A step whose trajectory takes a surface deeper than the
        entry tolerance into another it was apart from is truncated at that fraction."""
        if self.collisions is not None:
            u_prev, u = self.integrator.u_prev.x.array, self.u.x.array
            # where the solver holds a pair near the entry tolerance whatever the step, cutting
            # again gains nothing (seen: 24 truncations, each by less than 1 %): the step is
            # kept when no pair went more than ACCEPTED_ENTRY entry tolerances past contact.
            # The wider query first: the step's own cap is needed only where it caps, so a
            # step without contact costs one query, not two
            if (
                self.this_dt > self.min_dt
                and self.collisions.step_fraction(u_prev, u, ACCEPTED_ENTRY) < 1.0
                and (fraction := self.collisions.step_fraction(u_prev, u)) < 1.0
            ):
                self.truncate = fraction
                return f"truncated at {fraction:.3g} of the step (continuous collision detection)"
            if (
                self.this_dt <= self.min_dt
                and self.collisions.exits_active
                and self.collisions.step_fraction(u_prev, u) < 1.0
                and self.collisions.passing_through
            ):
                # a smallest step is accepted as it is, but not through a body's far side: a
                # vertex Newton brought ever closer to the exit level (each step capped at half
                # the way) crossed it by rounding and left (the cube at 500/s went through)
                self.passing = True
                return "a vertex would leave a body through its far side (collision detection)"
        if not self.this_dt / 2 >= self.min_dt:
            return None
        if self.step_contact is not None:
            self.contact.update()  # the operator was last evaluated at the step's midpoint
        contact, integrator, forms, comm = self.contact, self.integrator, self.forms, self.comm
        max_penetration, max_energy_change = self.max_penetration, self.max_energy_change
        if max_penetration is not None and contact is not None:
            depth = contact.max_penetration()
            if depth > max_penetration:
                return f"penetration {depth:.3e} > max_penetration {max_penetration:.3e}"
        if max_energy_change is not None or self.max_energy_gain is not None:
            energy = (
                integrator.trial_kinetic_energy()
                + _form_value(forms["strain"], comm)
                + (contact.energy() if contact is not None else 0.0)
                - _form_value(forms["external"], comm)
            )
            change = energy - self.records[-1].total_energy
            if max_energy_change is not None and abs(change) > max_energy_change:
                return (
                    f"energy change {change:.3e} beyond max_energy_change {max_energy_change:.3e}"
                )
            if self.max_energy_gain is not None and change > self.max_energy_gain:
                return f"energy gain {change:.3e} > max_energy_gain {self.max_energy_gain:.3e}"
        return None

    def cut(self, failure: str | None) -> None:
        t, this_dt, min_dt = self.t, self.this_dt, self.min_dt
        self.successes = 0
        cause = ""
        if this_dt / 2 < min_dt and self.passing and self.truncate is None:
            self._stop_passing_through(failure)  # returns where the penalty was raised
            return
        if this_dt / 2 < min_dt:  # giving up: say what the step met
            cause = impacts.impact_failure_cause(
                self.contact, self.integrator, self.contact_force, getattr(self, "result", None)
            )
        self.integrator.restore()
        if self.truncate is not None:
            # at the time of impact (the same on every rank), then on with the step before
            self.truncations += 1
            self.resume_dt = self.resume_dt or self.step_dt
            self.step_dt = max(this_dt * self.truncate, min_dt)
            self.reporter.message(
                f"      t {t:.5g}: dt {this_dt:.3g} truncated to {self.step_dt:.3g} (contact)"
            )
            return
        reason = (failure or "failed on another rank").split(";")[0]
        self.reporter.message(f"      t {t:.5g}: dt {this_dt:.3g} rejected ({reason[:90]})")
        if this_dt / 2 < min_dt:
            self.integrator.dt = max(this_dt, min_dt)
            if self.set_time is not None:
                self.set_time(t)
            # at the last accepted state: crushed cells are the cause, not the contact
            crushed = impacts.crushed_cells_cause(self.problem)
            raise RuntimeError(
                f"time stepping stopped at t = {t:.6g}: the step to {t + this_dt:.6g} "
                f"failed with dt = {this_dt:.3g} (min_dt {min_dt:.3g}). {crushed}Last "
                f"failure: {failure} {'' if crushed else cause}"
            )
        self.step_dt = this_dt / 2

    def accept(self, cuts: int, tic: float) -> TimeStep:
        if self.step_contact is not None:
            self.step_contact.accept()
        self.integrator.advance()
        self.t = self.integrator.t
        record = self.record(
            len(self.records), self.t, self.this_dt, self.result, cuts, time.perf_counter() - tic
        )
        self.truncations = 0
        if self.raiser is not None:
            self.raiser.keep(record.step, self.step_dt)
        return record

    def write(self, record: TimeStep) -> None:
        write_state(self.writer, self.u, self.t)

    def reached(self) -> float:
        return self.t

    def line(self, r: TimeStep) -> str:
        return (
            f"step {r.step:4d}  t {r.t:.5g}  dt {r.dt:.3g}  newton {r.iterations:2d}  "
            f"cuts {r.cuts}  pairs {r.active_pairs:5d}  max pen {r.max_penetration:.2e}  "
            f"E kin {r.kinetic_energy:.4e}  strain {r.strain_energy:.4e}  "
            f"contact {r.contact_energy:.3e}  total {r.total_energy:.6e}  {r.seconds:.2f} s"
        )

    def grow(self, cuts: int) -> None:
        if self.resume_dt is not None:  # a truncated step: the rest at the step before
            self.step_dt, self.resume_dt = self.resume_dt, None
            return
        if cuts == 0:
            self.successes += 1
            if self.successes >= self.grow_after and self.step_dt < self.max_dt:
                self.step_dt, self.successes = min(2.0 * self.step_dt, self.max_dt), 0


def solve_time_steps(
    problem: Solvable,
    integrator: Newmark | BackwardEuler,
    t_end: float,
    dt: float,
    writer=None,
    on_step: typing.Callable[[TimeStep], None] | None = None,
    min_dt: float | None = None,
    max_dt: float | None = None,
    *,
    set_time: typing.Callable[[float], None] | None = None,
    strain_energy: ufl.Form | None = None,
    external_work: ufl.Form | None = None,
    max_penetration: float | None = None,
    max_energy_change: float | None = None,
    max_energy_gain: float | None = None,
    grow_after: int = 2,
    predict: bool = True,
    progress: bool = True,
    contact_force: str | None = None,
    max_penalty: float | None = None,
) -> list[TimeStep]:
    """Integrate ``problem`` in time from the integrator's state to ``t_end`` with step control.

    Each step sets the integrator's dt (and calls ``set_time(t_next)`` for time-dependent
    loads), starts Newton from the integrator's prediction, and solves. A step that fails (no
    convergence, NaN, an inverted element raising) or, with ``max_penetration``, converges with a
    deeper penetration than that, is retried from the last converged state with half the step;
    after ``grow_after`` successive steps without a cut, the step doubles again, up to
    ``max_dt``. The last step is shortened to land on ``t_end``.

    With the problem's continuous collision detection (``ContactProblem(..., ccd=True)``,
    the default), the predictor is cut back where it would take a surface through another, and
    a converged step whose trajectory (straight, from the last state) takes a boundary vertex
    or edge deeper than the entry tolerance into a surface it was apart from is truncated at
    that fraction of the step and solved again (the paper's section 8.2); the step after it
    resumes the step size from before. ``TimeStep.truncations`` counts them.

    Where even ``min_dt`` cannot keep a boundary vertex from leaving a body through its far
    side (the penalty is too weak for the layer), the stepping stops with an error naming the
    penalty needed; with ``max_penalty`` it raises the contact's penalty instead (to twice the
    one needed, at most ``max_penalty``, with a ``RuntimeWarning``) and goes back to the last
    accepted state without contact, which drops the records after it (``on_step`` and
    ``writer`` have seen them, and see those times again).

    Args:
        problem: a :class:`~fenics_matdepth.ContactProblem` or
            :class:`~fenics_matdepth.NonlinearContactProblem` whose residual contains the
            integrator's inertia term (anything with ``u``, ``solve(raise_on_failure=...)`` and,
            optionally, ``contact``).
        integrator: the :class:`Newmark` or :class:`BackwardEuler` of ``problem.u``, holding the
            initial state (see ``initial``); its ``t`` is the start time.
        t_end: final time (T).
        dt: first (and nominal) time step (T).
        writer: called with each converged state: a ``dolfinx.io.XDMFFile``
            (``write_function(u, t)``), a ``dolfinx.io.VTXWriter`` (``write(t)``; give it ``u``,
            ``integrator.v_prev`` and the material depth), or any callable ``writer(t)``.
        on_step: called with each converged step's record, after ``integrator.advance()``.
        min_dt: smallest step tried before giving up; default ``dt / 2**10``.
        max_dt: largest step the controller grows to; default ``dt``.
        set_time: sets time-dependent data for a time t (collective).
        strain_energy: UFL form of the stored (strain) energy, reported per step (and, with
            ``external_work``, the incremental potential given to a problem without energy=).
        external_work: UFL form of the work of conservative loads (e.g. ``int rho g . u dx``),
            reported per step and subtracted in ``TimeStep.total_energy``.
        max_penetration: reject converged steps whose contact penetration exceeds this (L);
            at ``min_dt`` the step is accepted anyway.
        max_energy_change: reject converged steps that change the total energy (kinetic +
            strain + contact - external work) by more than this (F L); at ``min_dt`` the step
            is accepted anyway. An error control for energy-conserving schemes (average
            acceleration): where a step does not resolve an impact, it loses or gains energy.
            Needs the integrator's ``rho`` and ``strain_energy``.
        max_energy_gain: reject converged steps whose total energy rises above the last
            step's by more than this (F L); losses are accepted, and at ``min_dt`` the step is
            accepted anyway. The one-sided error control of an energy-conserving scheme
            through impacts: a step that does not resolve the bulk's nonlinearity gains or
            loses, and only the gains are retried: with it (1e-4 of the model's energy) the
            impacts of ``docs/dynamics.md`` ("Energy at impacts": corner-on cubes, face-on
            blocks, ten bounces) never rose above their start, with either contact force.
            Needs the integrator's ``rho`` and ``strain_energy``.
        grow_after: successful steps before dt doubles.
        predict: start each Newton solve from ``integrator.predict()`` (else from the last
            state).
        progress: report each converged step on rank 0: a progress bar in a terminal or a
            notebook, one printed line otherwise (``MATDEPTH_PROGRESS=lines`` forces lines).
        contact_force: the contact force in the step equation: ``"midpoint"``
            (:class:`~fenics_matdepth.impacts.MidpointContact`: the trapezoidal rule's average
            contact force is the one at the step's midpoint, so impacts pump no energy in; needs
            average-acceleration Newmark and a problem with an ``assembler``), or
            ``"endpoint"`` (the force at the end of the step, like every other internal
            force), or ``"discrete_gradient"``
            (:class:`~fenics_matdepth.impacts.DiscreteGradientContact`; average-acceleration
            Newmark or backward Euler, area integration, no friction): the contact force's work
            over each step is the change of the contact energy, exactly, with linear and
            angular momentum kept. Default: ``"discrete_gradient"`` with average-acceleration
            Newmark and a plain-penalty area contact (no augmented Lagrangian, no friction),
            ``"endpoint"`` otherwise; ``"midpoint"`` removes the energy flat faces meeting
            gain, but gains where a contact starts late in a step (``docs/dynamics.md``,
            "Energy at impacts").
        max_penalty: raise the contact's penalty, up to this (F/L^3), where a surface would
            pass through a body (above; :class:`~fenics_matdepth.penalty_raise.PenaltyRaise`):
            the raise goes back to a state where no pair overlaps, so it creates no energy.
            Needs the problem's collision detection and the integrator's ``rho``; not with
            friction. Default None: stop with an error instead.

    Returns:
        The initial state (step 0) and every converged step, in time order.

    Raises:
        RuntimeError: if dt falls below ``min_dt`` on failures; ``u`` and the integrator then
            hold the last converged state, whose time the message gives.
    """
    u = problem.u
    if integrator.u is not u:
        raise ValueError("the integrator must be built on the problem's unknown (problem.u)")
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive number, got {dt}")
    for name, bound in (("max_energy_change", max_energy_change), ("max_energy_gain",
                        max_energy_gain)):  # fmt: skip
        if bound is not None and (strain_energy is None or integrator.rho is None):
            raise ValueError(f"{name} needs strain_energy= and the integrator's rho")
    if max_penalty is not None and (
        getattr(problem, "collisions", None) is None or integrator.rho is None
    ):
        raise ValueError(
            "max_penalty needs the problem's collision detection (ccd=True) and the "
            "integrator's rho"
        )
    if grow_after < 1:
        raise ValueError(f"grow_after must be >= 1, got {grow_after}")
    max_dt = float(dt) if max_dt is None else float(max_dt)
    min_dt = float(dt) / 2**10 if min_dt is None else float(min_dt)
    if not 0.0 < min_dt <= max_dt:
        raise ValueError(f"need 0 < min_dt <= max_dt, got min_dt={min_dt}, max_dt={max_dt}")
    forms = {
        "strain": dolfinx.fem.form(strain_energy) if strain_energy is not None else None,
        "external": dolfinx.fem.form(external_work) if external_work is not None else None,
    }
    engine = _TimeSteps(
        problem, integrator, t_end, dt, writer, on_step, min_dt, max_dt, set_time, forms,
        max_penetration, max_energy_change, grow_after, predict, progress, max_energy_gain,
    )  # fmt: skip
    t = integrator.t
    u.x.array[:] = integrator.u_prev.x.array
    if engine.contact is not None:
        engine.contact.update()
    if set_time is not None:
        set_time(t)
    initial = SolveResult(True, 0, 0, np.zeros(0))
    engine.records.append(engine.record(0, t, 0.0, initial, 0, 0.0))
    impacts.hand_incremental_potential(problem, integrator, strain_energy, external_work)
    engine.contact_force = impacts.default_contact_force(integrator, contact_force, problem)
    collisions = engine.collisions
    if collisions is not None:  # the exit cap's default: on in time steps
        collisions.time_stepping = True
    try:
        with impacts.contact_force_of_steps(problem, integrator, engine.contact_force) as midpoint:
            engine.step_contact = midpoint
            if max_penalty is not None:
                engine.raiser = PenaltyRaise(engine.contact, integrator, max_penalty, midpoint)
                engine.raiser.keep(0, engine.step_dt)
            return engine.run()
    finally:
        if collisions is not None:
            collisions.time_stepping = False
