"""Load stepping and time stepping: one engine, two front-ends.

:class:`StepEngine` runs the loop both share: a step is tried, a failed attempt (no
convergence, NaN, an inverted element raising, a rejection by the step controller) is retried
from the last converged state with a smaller step, each converged step is recorded, written,
reported (a progress bar or one line, :class:`~fenics_matdepth._progress.StepProgress`) and
saved, and the step grows back. What differs is the front-ends':

* :func:`solve_load_steps`: load factors from ``start`` to ``end``, an optional predictor,
  checkpoint and resume, stop requests from its callbacks, callbacks run collectively;
* :func:`~fenics_matdepth.time_stepping.solve_time_steps` (in :mod:`fenics_matdepth.time_stepping`):
  time steps of an integrator (:class:`~fenics_matdepth.Newmark`,
  :class:`~fenics_matdepth.BackwardEuler`), rejection by penetration, energy change or a
  collision's entry cap, growth after ``grow_after`` steps without a cut, energies per step.
"""

from __future__ import annotations

import os
import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np

from fenics_matdepth._mpi import collective_error
from fenics_matdepth._progress import StepProgress
from fenics_matdepth.checkpoint import Checkpoint
from fenics_matdepth.kinematics import CellDeterminants
from fenics_matdepth.results import LoadStep, Solvable, SolveResult, StopRequested
from fenics_matdepth.step_control import StepControl, find_contact_problem

if typing.TYPE_CHECKING:
    pass

__all__ = [
    "StepEngine",
    "collective_call",
    "solve_load_steps",
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
                 predictor, checkpoint, resume, step_control=None):  # fmt: skip
        super().__init__(problem, start, end, "load", progress)
        self.control = step_control
        # the rate test goes into the contact problem's convergence test for the run
        self.rate_test = step_control.rate_test() if step_control is not None else None
        self.judged = find_contact_problem(problem) if step_control is not None else None
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

    def run(self) -> list:
        if self.judged is None:
            return super().run()
        self.judged.stop_test = self.rate_test
        try:
            return super().run()
        finally:
            self.judged.stop_test = None

    def attempt(self) -> str | None:
        failure = super().attempt()
        if failure is not None and self.rate_test is not None and self.rate_test.message:
            failure = f"{failure} ({self.rate_test.message})"
        return failure

    def finished(self) -> bool:
        nominal = self.nominal
        return not (self.end - self.t) * np.sign(nominal) > 1e-12 * abs(nominal)

    def begin_step(self) -> None:
        if self.rate_test is not None:
            self.rate_test.new_step()
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
        if self.control is not None:  # towards the target iterations, at most the nominal step
            size = abs(dt) * self.control.scale(self.records[-1].iterations)
            self.dt = min(max(size, self.min_step), abs(nominal)) * np.sign(nominal)
        elif abs(dt) < abs(nominal):
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
    step_control: StepControl | None = None,
) -> list[LoadStep]:
    """Solve ``problem`` for load factors from ``start`` to ``end`` with automatic step cutting.

    Each step calls ``set_load(t)`` (update a ``Constant``, a Dirichlet ``Function``, ...) and
    solves from the previous converged state, or from a prediction of the new one (below). A
    step that fails (no convergence, NaN, an inverted element raising, the line search unable
    to find an admissible state) is retried from that state with half the increment; after a
    success the increment grows back (doubles) up to the nominal ``(end - start) /
    num_steps``; with a ``step_control``, it is scaled towards a target number of Newton
    iterations instead, and an attempt whose convergence rate says it will not make it is
    stopped early. The step never overshoots ``end``.

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
        step_control: a :class:`~fenics_matdepth.StepControl`: each next step scaled from the
            last one's Newton iterations towards its target (never beyond the nominal step),
            and attempts stopped by its rate test as soon as their residual's rate predicts
            more iterations than it allows (:mod:`fenics_matdepth.step_control`). None
            (default): steps double back after a cut, attempts run to the problem's limit.

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
    if step_control is not None and not isinstance(step_control, StepControl):
        raise TypeError(f"step_control must be a StepControl or None, got {step_control!r}")
    return _LoadSteps(
        problem, set_load, num_steps, start, end, min_step, writer, progress, predictor,
        checkpoint, resume, step_control,
    ).run()  # fmt: skip


# -- time steps ------------------------------------------------------------------------------------
