"""What the solvers return: the result of a Newton solve, the records of load steps and time
steps, the stop request, and the protocol of "something that solves".

:class:`Solvable` is what load stepping, time stepping and the wrappers
(:class:`~fenics_matdepth.AugmentedLagrangian`, :class:`~fenics_matdepth.RigidModeDamping`,
:class:`~fenics_matdepth.PenaltyContinuation`) take: a problem, or a wrapper of one, with
``u``, ``contact`` and ``solve(raise_on_failure)``.
"""

from __future__ import annotations

import dataclasses
import typing

from petsc4py import PETSc

import numpy as np

if typing.TYPE_CHECKING:
    import dolfinx

    from fenics_matdepth.contact.operator import ContactOperator

__all__ = ["LoadStep", "Solvable", "SolveResult", "StopRequested", "TimeStep"]


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
            :class:`~fenics_matdepth.NonlinearContactProblem` 1 if converged, -1 otherwise.
        iterations: Newton iterations taken.
        residual_norms: residual norm before each iteration and after the last one.
        rejected_states: trial states rejected because an element inverted (det F <= 0) or the
            residual or energy was not finite (the step was shortened instead).
        min_det_F: smallest det F over the cells at the returned state.
        shifted_steps: Newton steps taken with the shifted Jacobian ``J + mu I`` because the
            Newton step would have climbed the energy
            (:class:`~fenics_matdepth.ContactProblem` with an energy and a MUMPS solver; see
            ``snes_callbacks.SHIFT_START``).
        factorisations: Jacobians factorised by :class:`~fenics_matdepth.ContactProblem` with
            ``keep_factorisation=True``, which keeps a factorisation while GMRES on it
            converges fast (see ``linear_solver.REFACTORISE_ITERATIONS``), or with the default
            AMG preconditioner the hierarchies it built (``linear_solver.AMG_KEPT_GROWTH``); 0
            otherwise.
        advice: what to do about a failure, where the solver knows its cause (a body held only
            by contact: :mod:`fenics_matdepth.free_bodies`); empty otherwise.
    """

    converged: bool
    reason: int
    iterations: int
    residual_norms: np.ndarray
    rejected_states: int = 0
    min_det_F: float = np.nan
    shifted_steps: int = 0
    factorisations: int = 0
    advice: str = ""

    def failure_message(self) -> str:
        """Why the solve failed, with the residual history, and what to do: ``advice`` where
        the solver knows the cause (a body held only by contact), else to reduce the load step
        or the penalty."""
        return (
            "contact Newton solve did not converge "
            f"(reason {self.reason}{_reason_name(self.reason)}) after "
            f"{self.iterations} iterations; residual norms: "
            + ", ".join(f"{r:.3e}" for r in self.residual_norms)
            + ". "
            + (
                self.advice
                or "Reduce the load step (solve_load_steps cuts it automatically), or lower the "
                "penalty."
            )
        )

    @classmethod
    def merged(
        cls, results: typing.Sequence[SolveResult], converged: bool, reason: int
    ) -> SolveResult:
        """One result for several solves in a row (the inner solves of a wrapper).

        Args:
            results: the solves, in order.
            converged: whether the whole counts as converged.
            reason: the reason to report.

        Returns:
            A result whose counters (``iterations``, ``rejected_states``, ``shifted_steps``,
            ``factorisations``) are summed over ``results``, whose ``residual_norms`` are their
            histories joined, and whose ``min_det_F`` is the last solve's (NaN without solves).
        """
        return cls(
            converged, reason, sum(r.iterations for r in results),
            np.concatenate([np.asarray(r.residual_norms) for r in results])
            if results else np.empty(0),
            sum(r.rejected_states for r in results),
            results[-1].min_det_F if results else np.nan,
            sum(r.shifted_steps for r in results), sum(r.factorisations for r in results),
        )  # fmt: skip


class Solvable(typing.Protocol):
    """A contact problem or a wrapper of one: what load stepping, time stepping and the
    wrappers take (time stepping does without ``contact``)."""

    u: dolfinx.fem.Function
    contact: ContactOperator

    def solve(self, raise_on_failure: bool = True) -> SolveResult: ...


class StopRequested(Exception):
    """Raise it from a :func:`~fenics_matdepth.solve_load_steps` callback (``set_load`` or
    ``writer``) to end the run cleanly, e.g. when a stop file appears: ``solve_load_steps``
    then raises ``StopRequested`` on every rank, with ``u`` holding the last converged state
    (saved in the checkpoint, if any), ``load`` its load factor and ``steps`` the steps
    converged in this call.

    Args:
        message: why the run stops.
        load: set by ``solve_load_steps``: the last converged load factor.
        steps: set by ``solve_load_steps``: the converged steps of the call.
    """

    def __init__(self, message: str = "stop requested", load=None, steps=None):
        super().__init__(message)
        self.load = load
        self.steps = steps if steps is not None else []


@dataclasses.dataclass
class LoadStep:
    """One converged load step of :func:`~fenics_matdepth.solve_load_steps`.

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


@dataclasses.dataclass
class TimeStep:
    """One converged time step of :func:`~fenics_matdepth.solve_time_steps` (or the initial
    state, step 0).

    Energies are of the state at time ``t`` (F L). ``external_work`` is the value of the
    ``external_work`` form (the work of conservative loads, e.g. ``int rho g . u dx``), so the
    total energy ``kinetic + strain + contact - external_work`` is conserved by an exact
    integration of a conservative system.

    Attributes:
        step: number of the step (0: the initial state).
        t: time reached (T).
        dt: time step of this step (T).
        iterations: Newton iterations of the converged solve.
        residual_norms: its residual history.
        cuts: failed or rejected attempts (dt halvings) before this step converged.
        diagnostics: ``contact.diagnostics()`` after the step (empty without contact).
        kinetic_energy: kinetic energy (F L).
        strain_energy: strain energy (F L).
        contact_energy: contact energy (F L).
        external_work: work of the external loads (F L). Each energy is NaN when it cannot be
            computed (no density, no form given).
        seconds: wall time of the step, failed attempts included.
        truncations: attempts truncated at a time of impact by the continuous collision
            detection (counted among ``cuts`` too).
    """

    step: int
    t: float
    dt: float
    iterations: int
    residual_norms: np.ndarray
    cuts: int
    diagnostics: dict
    kinetic_energy: float
    strain_energy: float
    contact_energy: float
    external_work: float
    seconds: float
    truncations: int = 0

    @property
    def total_energy(self) -> float:
        """kinetic + strain + contact - external work (F L)."""
        return self.kinetic_energy + self.strain_energy + self.contact_energy - self.external_work

    @property
    def active_pairs(self) -> int:
        """Contact pairs with non-zero energy."""
        return int(self.diagnostics.get("active_pairs", 0))

    @property
    def max_penetration(self) -> float:
        """Largest material depth reached by the contact surface (L)."""
        return float(self.diagnostics.get("max_penetration", 0.0))
