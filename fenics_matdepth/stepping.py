"""Load stepping and time stepping: one engine, two front-ends.

:class:`StepEngine` runs the loop both share: a step is tried, a failed attempt (no
convergence, NaN, an inverted element raising, a rejection by the step controller) is retried
from the last converged state with a smaller step, each converged step is recorded, written,
reported (a progress bar or one line, :class:`~fenics_matdepth._progress.StepProgress`) and
saved, and the step grows back. What differs is the front-ends':

* :func:`solve_load_steps`: load factors from ``start`` to ``end``, an optional predictor,
  checkpoint and resume, stop requests from its callbacks, callbacks run collectively;
* :func:`solve_time_steps`: time steps of an integrator (:class:`~fenics_matdepth.Newmark`,
  :class:`~fenics_matdepth.BackwardEuler`), rejection by penetration or energy change, growth
  after ``grow_after`` steps without a cut, energies per step.
"""

from __future__ import annotations

import os
import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl

from fenics_matdepth import impacts
from fenics_matdepth._mpi import collective_error
from fenics_matdepth._progress import StepProgress
from fenics_matdepth.checkpoint import Checkpoint
from fenics_matdepth.kinematics import CellDeterminants
from fenics_matdepth.results import LoadStep, Solvable, SolveResult, StopRequested, TimeStep

if typing.TYPE_CHECKING:
    from fenics_matdepth.dynamics import BackwardEuler, Newmark

__all__ = [
    "StepEngine",
    "collective_call",
    "solve_load_steps",
    "solve_time_steps",
    "write_state",
]


def write_state(writer, u: dolfinx.fem.Function, value: float) -> None:
    """Write the converged state at ``value`` (load factor or time) with ``writer``: a
    ``dolfinx.io.XDMFFile``, a ``dolfinx.io.VTXWriter``, any callable ``writer(value)``, or
    None (nothing)."""
    if writer is None:
        return
    if hasattr(writer, "write_function"):  # dolfinx.io.XDMFFile (mesh written by the caller)
        writer.write_function(u, value)
    elif hasattr(writer, "write"):  # dolfinx.io.VTXWriter
        writer.write(value)
    else:
        writer(value)


def collective_call(comm: MPI.Comm, what: str, fix: str, function, *args) -> None:
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


class StepEngine:
    """The stepping loop shared by load steps and time steps (collective).

    :meth:`run` repeats, until :meth:`finished`: :meth:`begin_step`, then attempts
    (:meth:`prepare`, the problem's solve, :meth:`check` of a converged solve) until one
    converges on every rank, each failed one followed by :meth:`cut` (back to the last
    converged state, a smaller step, or RuntimeError where the step would fall below its
    smallest); then :meth:`accept` (the record), :meth:`write`, ``on_step``, the progress
    line (:meth:`line`), :meth:`grow` and :meth:`save`. A :class:`StopRequested` raised on
    the way ends the run through :meth:`stopped`. A front-end subclasses it and defines
    these.

    Args:
        problem: what is solved at each step.
        start, end: the range the progress report covers.
        label: what the progress counts (``"load"``, ``"t"``).
        progress: report each converged step on rank 0.
        on_step: called with each converged step's record, after :meth:`write`.
    """

    def __init__(
        self,
        problem: Solvable,
        start: float,
        end: float,
        label: str,
        progress: bool = True,
        on_step: typing.Callable | None = None,
    ):
        self.problem = problem
        self.u = problem.u
        self.comm = self.u.function_space.mesh.comm
        self.start, self.end, self.label = start, end, label
        self.progress = progress
        self.on_step = on_step
        #: the records of the converged steps
        self.records: list = []
        #: the result of the last solve that did not raise
        self.result: SolveResult | None = None
        self.reporter: StepProgress | None = None

    # -- what a front-end defines ---------------------------------------------------------------

    def finished(self) -> bool:
        """Whether the end is reached."""
        raise NotImplementedError

    def begin_step(self) -> None:
        """Before the first attempt of a step."""

    def prepare(self) -> None:
        """Set up an attempt: its step, the load or time, the state Newton starts from."""
        raise NotImplementedError

    def check(self, result: SolveResult) -> str | None:
        """Why a converged attempt is rejected anyway, or None."""
        return None

    def cut(self, failure: str | None) -> None:
        """After a failed attempt (``failure`` None where it failed on another rank): back to
        the last converged state and a smaller step, or raise RuntimeError."""
        raise NotImplementedError

    def accept(self, cuts: int, tic: float) -> typing.Any:
        """Make the converged attempt the last converged state; its record (``tic``: the
        step's start, ``time.perf_counter()``)."""
        raise NotImplementedError

    def write(self, record) -> None:
        """Write the converged state."""

    def reached(self) -> float:
        """The load factor or time of the last converged state."""
        raise NotImplementedError

    def line(self, record) -> str:
        """The progress line of a converged step."""
        raise NotImplementedError

    def grow(self, cuts: int) -> None:
        """After a converged step: the next step's size."""

    def save(self) -> None:
        """After a converged step: save it (checkpoint)."""

    def stopped(self, err: StopRequested) -> StopRequested | None:
        """The exception to raise for a stop request (None: ``err`` as it is)."""
        return None

    # -- the loop ---------------------------------------------------------------------------------

    def started(self) -> None:
        """Once the progress report exists, before the first step."""

    def attempt(self) -> str | None:
        """Solve from the prepared state: why the attempt failed on this rank, or None."""
        try:
            self.result = self.problem.solve(raise_on_failure=False)
            if not self.result.converged:
                return self.result.failure_message()
            return self.check(self.result)
        except (RuntimeError, FloatingPointError, PETSc.Error) as err:
            return str(err)

    def advance_friction(self) -> None:
        """Make the current state the reference of the contact's friction (the start, then each
        converged step, after its record, writer and ``on_step`` saw it): the next step's
        friction slips from here. A cut goes back to the last converged state, which stays the
        reference."""
        advance = getattr(getattr(self.problem, "contact", None), "advance", None)
        if advance is not None:
            advance()

    def run(self) -> list:
        """The steps to the end (collective). Returns the records."""
        self.reporter = StepProgress(
            self.comm, self.start, self.end, self.label, enabled=self.progress
        )
        try:
            self.started()
            self.advance_friction()
            while not self.finished():
                self.begin_step()
                cuts, tic = 0, time.perf_counter()
                while True:
                    self.prepare()
                    failure = self.attempt()
                    if not self.comm.allreduce(failure is not None, op=MPI.LOR):
                        break
                    cuts += 1
                    self.cut(failure)
                record = self.accept(cuts, tic)
                self.records.append(record)
                self.write(record)
                if self.on_step is not None:
                    self.on_step(record)
                self.reporter.step(self.reached(), self.line(record))
                self.advance_friction()
                self.grow(cuts)
                self.save()
        except StopRequested as err:
            replacement = self.stopped(err)
            if replacement is None:
                raise
            raise replacement from None
        finally:
            self.reporter.close()
        return self.records


# -- load steps ------------------------------------------------------------------------------------


class _LoadSteps(StepEngine):
    """:func:`solve_load_steps`'s stepping (see there)."""

    def __init__(self, problem, set_load, num_steps, start, end, min_step, writer, progress,
                 predictor, checkpoint, resume):  # fmt: skip
        super().__init__(problem, start, end, "load", progress)
        u = self.u
        self.set_load, self.writer, self.predictor = set_load, writer, predictor
        self.cells = CellDeterminants(u.function_space)
        self.nominal = nominal = (end - start) / num_steps
        self.min_step = abs(nominal) / 2**10 if min_step is None else float(min_step)
        self.t, self.dt = float(start), nominal
        self.previous, self.dt_previous, self.done = None, 0.0, 0
        self.run_keys = {"start": float(start), "end": float(end), "num_steps": int(num_steps)}
        if resume is not None:
            self._resume(resume)
        self.checkpoint = checkpoint
        self.saver = Checkpoint(checkpoint, u.function_space) if checkpoint is not None else None
        self.saved = u.x.array.copy()

    def _resume(self, resume) -> None:
        """Continue from the last step saved in the checkpoint file ``resume``."""
        u, run = self.u, self.run_keys
        arrays, meta = Checkpoint(resume, u.function_space).load()
        if {k: meta.get(k) for k in run} != run:
            raise ValueError(
                f"the checkpoint {resume} belongs to a run with start, end, num_steps = "
                f"{meta.get('start')}, {meta.get('end')}, {meta.get('num_steps')}; resume with "
                "the same values"
            )
        u.x.array[:] = arrays["u"]
        self.previous = arrays.get("u_previous")
        self.t, self.dt = meta["load"], meta["dt"]
        self.dt_previous, self.done = meta["dt_previous"], meta["steps"]
        t = self.t
        collective_call(
            self.comm, f"set_load({t:.6g})", "Fix the set_load callback.", self.set_load, t
        )

    def finished(self) -> bool:
        nominal = self.nominal
        return not (self.end - self.t) * np.sign(nominal) > 1e-12 * abs(nominal)

    def begin_step(self) -> None:
        self.t_next = self.t + self.dt
        if (self.end - self.t_next) * np.sign(self.nominal) < 0.0:
            self.t_next, self.dt = self.end, self.end - self.t

    def prepare(self) -> None:
        u, saved, t, t_next = self.u, self.saved, self.t, self.t_next
        u.x.array[:] = saved
        collective_call(
            self.comm, f"set_load({t_next:.6g})",
            f"Fix the set_load callback; u holds the converged state at load {t:.6g}.",
            self.set_load, t_next,
        )  # fmt: skip
        previous, dt_previous = self.previous, self.dt_previous
        if self.predictor == "extrapolate" and previous is not None and dt_previous != 0.0:
            guess = saved + (self.dt / dt_previous) * (saved - previous)
            if self.cells.min(guess) > 0.0:
                u.x.array[:] = guess

    def cut(self, failure: str | None) -> None:
        t, dt = self.t, self.dt
        self.u.x.array[:] = self.saved
        if abs(dt) / 2 < self.min_step:
            collective_call(self.comm, f"set_load({t:.6g})", "", self.set_load, t)
            raise RuntimeError(
                f"load stepping stopped at load factor {t:.6g}: the step to {self.t_next:.6g} "
                f"failed with an increment of {abs(dt):.3g} (min_step {self.min_step:.3g}). "
                f"Last failure: {failure}"
            )
        self.dt /= 2
        self.t_next = t + self.dt

    def accept(self, cuts: int, tic: float) -> LoadStep:
        u, result = self.u, self.result
        self.previous, self.dt_previous = self.saved, self.dt
        self.t = self.t_next
        self.saved = u.x.array.copy()
        diag = self.problem.contact.diagnostics()
        diag["min_det_F"] = self.cells.min(u)
        diag["rejected_states"] = result.rejected_states
        return LoadStep(
            self.t, result.iterations, result.residual_norms, cuts, diag,
            time.perf_counter() - tic, dict(getattr(self.problem, "timings", {})),
        )  # fmt: skip

    def write(self, record: LoadStep) -> None:
        t = self.t
        collective_call(
            self.comm, f"writer at load {t:.6g}",
            f"Check the writer (path writable, file open); u holds the converged state at load "
            f"{t:.6g}.", write_state, self.writer, self.u, t,
        )  # fmt: skip

    def reached(self) -> float:
        return self.t

    def line(self, step: LoadStep) -> str:
        diag = step.diagnostics
        return (
            f"step {self.done + len(self.records):3d}  load {step.load:.4g}  "
            f"newton {step.iterations:2d} it  "
            f"|r| {step.residual_norms[-1]:.2e}  cuts {step.cuts}  "
            f"active pairs {diag['active_pairs']}  "
            f"max penetration {diag['max_penetration']:.3e}  "
            f"min det F {diag['min_det_F']:.3f}  {step.seconds:.2f} s"
        )

    def grow(self, cuts: int) -> None:
        dt, nominal = self.dt, self.nominal
        if abs(dt) < abs(nominal):
            self.dt = min(abs(dt) * 2, abs(nominal)) * np.sign(nominal)

    def save(self) -> None:
        if self.saver is not None:
            self.saver.save(
                {"u": self.saved, "u_previous": self.previous}, load=self.t, dt=float(self.dt),
                dt_previous=float(self.dt_previous), steps=self.done + len(self.records),
                **self.run_keys,
            )  # fmt: skip

    def stopped(self, err: StopRequested) -> StopRequested:
        self.u.x.array[:] = self.saved
        t, checkpoint = self.t, self.checkpoint
        where = f"; it is saved in {checkpoint}" if checkpoint is not None else ""
        return StopRequested(
            f"stopped on request at load factor {t:.6g} ({err}): u holds the converged state "
            f"there{where}",
            load=t,
            steps=self.records,
        )


def solve_load_steps(
    problem: Solvable,
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
    through the first Newton step (see
    :class:`~fenics_matdepth.system_assembler.SystemAssembler`). Bodies held only by contact
    (a floating body, a hemisphere resting under its weight) need nothing here: the problems
    damp them while contact engages (``damp_free_bodies``, :mod:`fenics_matdepth.free_bodies`).

    Args:
        problem: a :class:`~fenics_matdepth.ContactProblem` or
            :class:`~fenics_matdepth.NonlinearContactProblem` (anything with
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
    return _LoadSteps(
        problem, set_load, num_steps, start, end, min_step, writer, progress, predictor,
        checkpoint, resume,
    ).run()  # fmt: skip


# -- time steps ------------------------------------------------------------------------------------


def _form_value(form, comm, missing: float = 0.0) -> float:
    if form is None:
        return missing
    return comm.allreduce(float(np.real(dolfinx.fem.assemble_scalar(form))))


class _TimeSteps(StepEngine):
    """:func:`solve_time_steps`'s stepping (see there); the caller has set up the initial
    state and its record."""

    def __init__(self, problem, integrator, t_end, dt, writer, on_step, min_dt, max_dt,
                 set_time, forms, max_penetration, max_energy_change, grow_after, predict,
                 progress):  # fmt: skip
        super().__init__(problem, integrator.t, t_end, "t", progress, on_step)
        self.integrator, self.writer, self.set_time = integrator, writer, set_time
        self.forms = forms
        self.min_dt, self.max_dt = min_dt, max_dt
        self.max_penetration, self.max_energy_change = max_penetration, max_energy_change
        self.grow_after, self.predict = grow_after, predict
        self.contact = getattr(problem, "contact", None)
        # continuous collision detection: the predictor and the converged step are cut at
        # their entry cap (truncate, resume_dt: the pending truncation and the step after it)
        self.collisions = getattr(problem, "collisions", None)
        self.truncations, self.truncate, self.resume_dt = 0, None, None
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

    def prepare(self) -> None:
        t, t_end, integrator = self.t, self.end, self.integrator
        this_dt = min(self.step_dt, t_end - t)
        if t_end - (t + this_dt) < self.tol:
            this_dt = t_end - t
        self.this_dt = integrator.dt = this_dt
        if self.set_time is not None:
            self.set_time(t + this_dt)
        if self.predict:
            integrator.predict()
        else:
            integrator.restore()
        self.truncate = None
        if self.predict and self.collisions is not None:
            # Newton starts on this side of any surface the prediction would jump through
            u_prev, u = integrator.u_prev.x.array, self.u.x.array
            fraction = self.collisions.step_fraction(u_prev, u)
            if fraction < 1.0:
                u[:] = u_prev + fraction * (u - u_prev)

    def check(self, result: SolveResult) -> str | None:
        """Why a converged step is rejected by the step controller, or None (at ``min_dt``
        the step is accepted anyway). A step whose trajectory takes a surface deeper than the
        entry tolerance into another it was apart from is truncated at that fraction."""
        if self.collisions is not None:
            fraction = self.collisions.step_fraction(self.integrator.u_prev.x.array, self.u.x.array)
            if fraction < 1.0 and self.this_dt > self.min_dt:
                self.truncate = fraction
                return f"truncated at {fraction:.3g} of the step (continuous collision detection)"
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
        if max_energy_change is not None:
            energy = (
                integrator.trial_kinetic_energy()
                + _form_value(forms["strain"], comm)
                + (contact.energy() if contact is not None else 0.0)
                - _form_value(forms["external"], comm)
            )
            change = energy - self.records[-1].total_energy
            if abs(change) > max_energy_change:
                return (
                    f"energy change {change:.3e} beyond max_energy_change {max_energy_change:.3e}"
                )
        return None

    def cut(self, failure: str | None) -> None:
        t, this_dt, min_dt = self.t, self.this_dt, self.min_dt
        self.successes = 0
        cause = ""
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
            raise RuntimeError(
                f"time stepping stopped at t = {t:.6g}: the step to {t + this_dt:.6g} "
                f"failed with dt = {this_dt:.3g} (min_dt {min_dt:.3g}). Last failure: "
                f"{failure} {cause}"
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
    grow_after: int = 2,
    predict: bool = True,
    progress: bool = True,
    contact_force: str | None = None,
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
            force). Default: ``"midpoint"`` where it applies, ``"endpoint"`` otherwise
            (backward Euler, other Newmark parameters, wrapped problems).

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
    if max_energy_change is not None and (strain_energy is None or integrator.rho is None):
        raise ValueError("max_energy_change needs strain_energy= and the integrator's rho")
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
        max_penetration, max_energy_change, grow_after, predict, progress,
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
    with impacts.contact_force_of_steps(problem, integrator, engine.contact_force) as midpoint:
        engine.step_contact = midpoint
        return engine.run()
