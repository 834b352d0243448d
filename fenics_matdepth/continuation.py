"""Penalty continuation within one solve: a moderate penalty first, then geometrically larger
ones up to the one asked for, each solve warm-started from the last.

A large penalty makes the contact energy stiff against the bulk, and a Newton solve that starts
far from its solution can stall (measured: a soft block pressed by one element height in one
solve converges in 5 iterations at 10 E/h, and at 1000 E/h still has 2 % of its initial
residual after 50). At a moderate penalty the same solve is easy, and its solution is a good
start for a ten times larger penalty: the surfaces only have to move by the difference of the
two overlaps (the same press: 4 + 3 + 5 iterations through 10, 100 and 1000 E/h).
"""

from __future__ import annotations

import dataclasses
import typing

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from fenics_matdepth.augmented import RigidModeDamping
from fenics_matdepth.problems import looser_tolerances, own_rtol
from fenics_matdepth.results import Solvable, SolveResult

__all__ = ["ContinuationStage", "PenaltyContinuation"]


@dataclasses.dataclass
class ContinuationStage:
    """One solve of :class:`PenaltyContinuation` at one penalty.

    Attributes:
        penalty: the penalty of the solve (pressure / length).
        newton_iterations: its Newton iterations (all inner solves of a wrapped solver).
        converged: whether it converged; a failed stage is retried from the last converged
            stage with a smaller growth factor.
        overlap: largest material depth reached by the contact surface after it (L; NaN when
            the solve failed).
    """

    penalty: float
    newton_iterations: int
    converged: bool
    overlap: float


class PenaltyContinuation:
    """Solve at a moderate penalty, then raise it geometrically to the target, warm-started.

    Wraps a :class:`~fenics_matdepth.ContactProblem` (or a solver with the same ``u``,
    ``contact`` and ``solve(raise_on_failure)``, such as
    :class:`~fenics_matdepth.RigidModeDamping`) and offers the same, so it goes where the
    problem went: ``fm.solve_load_steps(fm.PenaltyContinuation(problem), set_load)``. Each
    :meth:`solve` runs the stages ``start, start * growth, start * growth**2, ...`` up to the
    target (the last stage is the target itself), each from the previous stage's solution. A
    stage that fails is retried from the last converged stage with the growth factor's square
    root (``10 -> 3.16 -> 1.78``, kept for the rest of the solve: a failed stage costs the
    problem's whole iteration limit), until the factor would fall below ``min_growth``. A first
    stage that fails is retried from the starting state one growth factor higher (at the
    latest at the target: the plain solve). If that fails too, or the retries run out, ``u`` is
    restored to where the solve started, so load stepping can cut the step. The operator holds
    the target from construction on; each stage sets its own penalty for its solve only
    (:meth:`~fenics_matdepth.ContactOperator.penalty_set_to`), so after every :meth:`solve`,
    converged or not, the penalty is the target again.

    To combine with the other drivers: ``PenaltyContinuation(RigidModeDamping(problem, ...))``
    for a body free until contact (the first stage runs the damped solves, the later ones the
    undamped problem, as contact holds the body by then; after a failed stage, the damped
    solves again), and
    ``AugmentedLagrangian(PenaltyContinuation(problem), ...)`` (each Uzawa solve runs the
    stages; the pressure updates use the target penalty).

    Args:
        problem: the contact problem or solver (its operator's ``penalty`` is changed).
        start: the first stage's penalty (pressure / length); default ``target / 100``.
        growth: factor between stages, > 1.
        target: the penalty to reach; default: the operator's penalty when this is built.
        min_growth: smallest growth factor a retry may use, > 1.
        stage_rtol: the stages below the target stop once their residual fell by this factor
            (or at the problem's own ``rtol`` if that is looser; ``None``: at the problem's
            own): they only have to start the next stage well. The target stage uses the
            problem's own ``rtol``. Every stage after the first also stops below the problem's
            ``rtol`` times the first stage's initial residual (see ``_stage``).

    Attributes:
        target: the penalty every solve ends with.
        history: one :class:`ContinuationStage` per stage solve (failed ones included) of the
            last :meth:`solve`.
        total_newton_iterations: Newton iterations summed over every :meth:`solve` so far.
        total_stages: stage solves (failed ones included) summed over every :meth:`solve` so
            far.
        total_retries: failed stages summed over every :meth:`solve` so far.
        timings: the wrapped problem's time split (``ContactProblem.timings``) summed over the
            stages of the last :meth:`solve` (empty if it keeps none).
    """

    def __init__(
        self,
        problem: Solvable,
        start: float | None = None,
        growth: float = 10.0,
        target: float | None = None,
        min_growth: float = 1.5,
        stage_rtol: float | None = 1e-6,
    ):
        contact = problem.contact
        self.target = float(contact.penalty if target is None else target)
        self.start = float(self.target / 100.0 if start is None else start)
        self.growth = float(growth)
        self.min_growth = float(min_growth)
        self.stage_rtol = None if stage_rtol is None else float(stage_rtol)
        if not (np.isfinite(self.target) and self.target > 0.0):
            raise ValueError(f"target must be a positive penalty, got {self.target}")
        if not (np.isfinite(self.start) and 0.0 < self.start <= self.target):
            raise ValueError(
                f"start must be a positive penalty at most the target {self.target:.4g}, got "
                f"{self.start}"
            )
        if not (np.isfinite(self.growth) and self.growth > 1.0):
            raise ValueError(f"growth must be a number > 1, got {growth}")
        if not (np.isfinite(self.min_growth) and 1.0 < self.min_growth <= self.growth):
            raise ValueError(f"min_growth must be in (1, growth], got {min_growth}")
        self.problem = problem
        self.u = problem.u
        self.contact = contact
        contact.penalty = self.target
        self.history: list[ContinuationStage] = []
        self.total_newton_iterations = 0
        self.total_stages = 0
        self.total_retries = 0
        self.timings: dict[str, float] = {}

    @property
    def snes(self):
        """The wrapped problem's SNES (if any)."""
        return getattr(self.problem, "snes", None)

    def _stage(
        self, penalty: float, first_norm: float | None, undamped: bool = False
    ) -> SolveResult | None:
        """One solve at ``penalty`` (collective); ``None`` if it raised on some rank.

        The stages after the first also stop once the residual is below the problem's
        relative tolerance times the first stage's initial residual: a stage starts from the
        last one's solution with a residual of the order of the contact forces (the penalty
        grew), and the problem's tolerance relative to that may lie below the residual's
        rounding floor, which grows with the penalty (measured on a soft block pressed by one
        element height at 10 E/h, continued to 100 E/h: the last stage stalled at 3.2e-12
        against 9.5e-13 asked, while 5.5e-11 is what the plain solve asks).

        ``undamped``: if the wrapped solver is a :class:`~fenics_matdepth.RigidModeDamping`,
        solve its undamped problem: after a converged stage contact holds the body, and the
        damped solves would only repeat (measured on the Hertz benchmark at res 1.0, 100 E/h:
        4 to 6 damped solves per stage)."""
        own = own_rtol(self.problem)
        rtol = self.stage_rtol if penalty < self.target else None
        atol = None if first_norm is None or own is None else own * first_norm
        try:
            with self.contact.penalty_set_to(penalty), looser_tolerances(self.problem, rtol, atol):
                solver = self.problem
                if undamped and isinstance(solver, RigidModeDamping):
                    solver = solver.problem
                result = solver.solve(raise_on_failure=False)
        except (RuntimeError, FloatingPointError, PETSc.Error):
            result = None
        comm = self.u.function_space.mesh.comm
        if comm.allreduce(result is None, op=MPI.LOR):
            return None
        return result

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """The stages from ``start`` to ``target`` (collective).

        Args:
            raise_on_failure: raise ``RuntimeError`` if the solve fails (``u`` restored);
                otherwise return the result with ``converged=False``.

        Returns:
            A :class:`~fenics_matdepth.SolveResult` whose ``iterations`` are the Newton
            iterations of all stages (failed ones included) and ``residual_norms`` their
            histories joined; its ``reason`` is the last stage's.
        """
        start_state = self.u.x.array.copy()
        self.history = []
        self.timings = {}
        results: list[SolveResult] = []
        converged = False
        last = None  # (state, penalty) of the last converged stage
        growth = self.growth
        penalty = min(self.start, self.target)
        first_norm, retry = None, False
        while True:
            # after a failed stage every stage solves the wrapped solver as given
            result = self._stage(penalty, first_norm, undamped=last is not None and not retry)
            if result is not None:
                if first_norm is None and len(result.residual_norms):
                    first_norm = float(result.residual_norms[0])
                results.append(result)
                for key, seconds in getattr(self.problem, "timings", {}).items():
                    self.timings[key] = self.timings.get(key, 0.0) + seconds
            ok = result is not None and result.converged
            self.history.append(
                ContinuationStage(
                    penalty,
                    0 if result is None else result.iterations,
                    ok,
                    self.contact.max_penetration() if ok else np.nan,
                )
            )
            if ok:
                if penalty >= self.target:
                    converged = True
                    break
                last = (self.u.x.array.copy(), penalty)
            else:
                self.total_retries += 1
                retry = True
                if last is None:
                    # the start is too soft for this state: start one growth factor higher
                    # (at the latest the target, the plain solve)
                    if penalty >= self.target:
                        break
                    self.u.x.array[:] = start_state
                    penalty, first_norm = min(penalty * self.growth, self.target), None
                    continue
                growth = np.sqrt(growth)
                if growth < self.min_growth:
                    break
                self.u.x.array[:] = last[0]
            penalty = min(last[1] * growth, self.target)
            if penalty > self.target * (1.0 - 1e-12):
                penalty = self.target
        # the reason is the last stage's that solved
        out = SolveResult.merged(results, converged, results[-1].reason if results else -1)
        self.total_newton_iterations += out.iterations
        self.total_stages += len(self.history)
        if not converged:
            self.u.x.array[:] = start_state
        if raise_on_failure and not converged:
            raise RuntimeError(self.failure_message(out))
        return out

    def failure_message(self, result: SolveResult) -> str:
        """Why :meth:`solve` failed, with the stages tried."""
        stages = ", ".join(
            f"{s.penalty:.3g} ({'ok' if s.converged else 'failed'}, {s.newton_iterations} it)"
            for s in self.history
        )
        return (
            f"penalty continuation to {self.target:.4g} failed; stages: {stages}. Lower start "
            "or growth, or cut the load step. Last: " + result.failure_message()
        )

    def diagnostics(self) -> dict[str, typing.Any]:
        """The last solve: ``stages`` (solves, failed ones included), ``retries`` (failed
        stages), ``penalties`` and ``newton_iterations`` per stage, ``overlap`` after the last
        stage (L)."""
        if not self.history:
            return {}
        return {
            "stages": len(self.history),
            "retries": sum(not s.converged for s in self.history),
            "penalties": [s.penalty for s in self.history],
            "newton_iterations": [s.newton_iterations for s in self.history],
            "overlap": self.history[-1].overlap,
        }
