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
  half the increment, as after any failure.

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

    Attributes:
        message: why the last solve was stopped ("" if it was not).
        stops: solves stopped so far.
    """

    def __init__(self, first_check: int, max_iterations: int, window: int):
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
        self.first_check, self.max_iterations, self.window = first_check, max_iterations, window
        self.norms: list[float] = []
        self.message = ""
        self.stops = 0

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
        if iteration < self.first_check or norm <= target:
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
    """

    target_iterations: int = 10
    stop_iterations: int | None = None
    window: int = 4
    max_growth: float = 2.0

    def __post_init__(self):
        if self.target_iterations < 1:
            raise ValueError(f"target_iterations must be >= 1, got {self.target_iterations}")
        if not self.max_growth >= 1.0:
            raise ValueError(f"max_growth must be >= 1, got {self.max_growth}")
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
        return min(max(factor, 1.0 / self.max_growth), self.max_growth)

    def rate_test(self) -> SlowConvergence:
        """A new :class:`~fenics_matdepth.step_control.SlowConvergence` with this control's
        settings."""
        return SlowConvergence(self.target_iterations, self.max_iterations, self.window)


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
