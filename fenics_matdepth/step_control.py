"""Automatic step control of :func:`~fenics_matdepth.solve_load_steps`: a target number of Newton
iterations per step, and attempts stopped as soon as their convergence rate says they will not
converge in time.

Without it, load stepping halves a step only after a failed attempt (its iteration limit, the
line search giving up) and doubles it back after each converged one: a hard step can run to
the iteration limit (100 on the knee) before it is cut, and the steps after it are as long as
the one that struggled. :class:`StepControl` does what FEBio's automatic time stepper and
Abaqus's time incrementation do:

- the next step is scaled from the last one's Newton iterations ``n`` towards the target
  ``n_opt``: by ``sqrt(n_opt / n)``, between ``1 / max_growth`` and ``max_growth``, never
  beyond the nominal step ``(end - start) / num_steps`` (the user's ``num_steps`` stays the
  largest step) nor below ``min_step``;
- an attempt is stopped as soon as, from the target on, its residual's rate over the last
  ``window`` iterations predicts that it needs more than ``stop_iterations`` iterations in all
  (:class:`~fenics_matdepth.step_control.SlowConvergence`, Abaqus's logarithmic
  rate-of-convergence check); the step is then retried from the last converged state with
  half the increment, as after any failure;
- the rate test stops at most ``stops_per_step`` attempts of one step (default 1): the retries
  after that run to the problem's own iteration limit. Where the retry at half the increment
  is slow too, the increment is not what makes the step hard: the load path has a limit point
  there (the equilibrium the steps follow ends, and the solution has to snap to another one:
  Newton's method meets an indefinite Jacobian and needs tens of iterations). Measured on the
  knee at 105.5 deg: with every attempt judged, the steps were cut to 0.01 deg and less and
  the run stalled at 105.7 deg; the step that snaps converges in 32 iterations when let run
  (docs/measurements.md).

The rate test needs a :class:`~fenics_matdepth.ContactProblem` (its SNES convergence test
consults it), as the problem or inside the wrappers
(:class:`~fenics_matdepth.AugmentedLagrangian`,
:class:`~fenics_matdepth.PenaltyContinuation`, :class:`~fenics_matdepth.RigidModeDamping`,
anything holding it as ``problem``); where there is none (the DOLFINx ``NewtonSolver`` of
:class:`~fenics_matdepth.NonlinearContactProblem`) only the step scaling applies. Each inner
solve of a wrapper is judged on its own.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["SlowConvergence", "StepControl", "find_contact_problem"]


class SlowConvergence:
    """The rate test of one Newton solve: whether to stop it because it will not converge in
    time (Abaqus's logarithmic rate-of-convergence check).

    Called by the problem's convergence test with each iterate's residual norm. From
    ``first_check`` iterations on it takes the rate ``rho`` of the residual per iteration: the
    mean over the last ``window`` iterations, ``(r_k / r_(k - window)) ** (1 / window)``, or
    the last iteration's ``r_k / r_(k - 1)`` where that is smaller (Newton's method entering
    its quadratic range); it predicts the iterations still needed to reach the target residual
    at that rate, ``log(target / r_k) / log(rho)`` (infinitely many where the residual did not
    fall: stagnation), and stops the solve when ``k`` plus that exceeds ``max_iterations``. A
    constant rate is pessimistic where Newton's method is about to converge quadratically,
    hence the test starts only at the step control's target.

    Args:
        first_check: the iteration from which the solve is judged.
        max_iterations: the iterations a solve may be predicted to need in all.
        window: the iterations over which the rate is measured.
        stops_per_step: the solves it stops between two calls of :meth:`new_step`; the solves
            after those are not judged (None: no limit).

    Attributes:
        message: why the last solve was stopped ("" if it was not).
        stops: solves stopped so far.
        step_stops: solves stopped since the last :meth:`new_step`.
    """

    def __init__(
        self, first_check: int, max_iterations: int, window: int, stops_per_step: int | None = None
    ):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if first_check < window:
            raise ValueError(
                f"the first check ({first_check}) comes before a window of {window} iterations "
                "exists: raise target_iterations or lower window"
            )
        if max_iterations < first_check:
            raise ValueError(
                f"stop_iterations ({max_iterations}) must be at least the target ({first_check})"
            )
        if stops_per_step is not None and stops_per_step < 1:
            raise ValueError(f"stops_per_step must be >= 1 or None, got {stops_per_step}")
        self.first_check, self.max_iterations, self.window = first_check, max_iterations, window
        self.stops_per_step = stops_per_step
        self.norms: list[float] = []
        self.message = ""
        self.stops = self.step_stops = 0

    def new_step(self) -> None:
        """A new step begins: its attempts are judged again."""
        self.step_stops = 0

    @property
    def judging(self) -> bool:
        """Whether the coming solves are judged (fewer than ``stops_per_step`` stopped in
        this step)."""
        return self.stops_per_step is None or self.step_stops < self.stops_per_step

    def __call__(self, iteration: int, norm: float, target: float) -> bool:
        """Record the residual norm ``norm`` of Newton iteration ``iteration`` (0: the solve's
        start, which resets the test) and say whether to stop the solve, whose target residual
        is ``target``."""
        del self.norms[iteration:]
        if iteration == 0:
            self.message = ""
        # (iterations this test did not see, if any, do not count in a rate)
        self.norms.extend([math.nan] * (iteration - len(self.norms)))
        self.norms.append(float(norm))
        if iteration < self.first_check or norm <= target or not self.judging:
            return False
        before, last = self.norms[iteration - self.window], self.norms[iteration - 1]
        rate = (norm / before) ** (1.0 / self.window) if before > 0.0 else math.inf
        if last > 0.0 and norm / last < rate:
            # the last iteration fell faster: Newton's method entering its quadratic range
            rate = norm / last
        if not rate < 1.0:  # (NaN: a gap in the window)
            needed = math.inf
        else:
            needed = math.log(target / norm) / math.log(rate)
        if iteration + needed <= self.max_iterations:
            return False
        self.stops += 1
        self.step_stops += 1
        more = f"{math.ceil(needed)} more" if math.isfinite(needed) else "no number of"
        self.message = (
            f"stopped after {iteration} Newton iterations by the step control's rate test: the "
            f"residual {norm:.3e} changed by a factor {rate:.3g} per iteration over the last "
            f"{self.window}; at that rate {more} iterations reach {target:.3e} (allowed: "
            f"{self.max_iterations} in all)"
        )
        return True


@dataclasses.dataclass(frozen=True)
class StepControl:
    """Automatic step control for :func:`~fenics_matdepth.solve_load_steps` (see the module).

    Args:
        target_iterations: the Newton iterations a step should take (FEBio's ``opt_iter``);
            the next step is scaled by ``sqrt(target_iterations / n)`` after a step of ``n``.
        stop_iterations: an attempt whose convergence rate predicts more Newton iterations
            than this in all is stopped and the step cut; default ``3 * target_iterations``.
            The problem's own iteration limit (``snes_max_it``) still applies.
        window: the iterations over which the rate test measures the convergence rate.
        max_growth: the next step is at most this factor longer, and at least its inverse
            shorter, than the last converged one (a cut halves it regardless).
        stops_per_step: the attempts of one step the rate test may stop; the later attempts of
            that step run to the problem's own iteration limit (see the module). None: every
            attempt is judged.
        min_scale: the smallest factor from a converged step to the next (default None:
            ``1 / max_growth``); 1 never shrinks the next step after a converged one, however
            many iterations it took (only a failed attempt cuts): for load paths whose hard
            steps are hard whatever their increment (a limit point, a snap), where shrinking
            after each only multiplies the steps.
    """

    target_iterations: int = 10
    stop_iterations: int | None = None
    window: int = 4
    max_growth: float = 2.0
    stops_per_step: int | None = 1
    min_scale: float | None = None

    def __post_init__(self):
        if self.target_iterations < 1:
            raise ValueError(f"target_iterations must be >= 1, got {self.target_iterations}")
        if not self.max_growth >= 1.0:
            raise ValueError(f"max_growth must be >= 1, got {self.max_growth}")
        if self.min_scale is not None and not 0.0 < self.min_scale <= 1.0:
            raise ValueError(f"min_scale must be in (0, 1] or None, got {self.min_scale}")
        self.rate_test()  # checks window and stop_iterations

    @property
    def max_iterations(self) -> int:
        """The iterations an attempt may be predicted to need."""
        if self.stop_iterations is None:
            return 3 * self.target_iterations
        return int(self.stop_iterations)

    def scale(self, iterations: int) -> float:
        """The factor from the last converged step to the next one, after ``iterations``."""
        factor = math.sqrt(self.target_iterations / max(int(iterations), 1))
        lowest = 1.0 / self.max_growth if self.min_scale is None else self.min_scale
        return min(max(factor, lowest), self.max_growth)

    def rate_test(self) -> SlowConvergence:
        """A new :class:`~fenics_matdepth.step_control.SlowConvergence` with this control's
        settings."""
        return SlowConvergence(
            self.target_iterations, self.max_iterations, self.window, self.stops_per_step
        )


def find_contact_problem(solver):
    """The :class:`~fenics_matdepth.ContactProblem` that ``solver`` is or wraps (following
    ``problem`` attributes), or None."""
    seen = set()
    while solver is not None and id(solver) not in seen:
        if hasattr(solver, "stop_test"):
            return solver
        seen.add(id(solver))
        solver = getattr(solver, "problem", None)
    return None
