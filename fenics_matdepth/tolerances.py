"""The Newton tolerances of a contact problem, loosened for a stage: for the wrappers that solve
a problem several times (:class:`~fenics_matdepth.AugmentedLagrangian`,
:class:`~fenics_matdepth.RigidModeDamping`, :class:`~fenics_matdepth.PenaltyContinuation`).
"""

from __future__ import annotations

import contextlib
import typing

__all__ = ["looser_tolerances", "own_rtol"]


def _newton_solvers(problem) -> tuple[typing.Any, typing.Any]:
    """The problem's SNES (``snes``) or DOLFINx NewtonSolver (``_solver``), either may be None."""
    return getattr(problem, "snes", None), getattr(problem, "_solver", None)


def own_rtol(problem) -> float | None:
    """The problem's relative Newton tolerance (None if it exposes no solver)."""
    snes, newton = _newton_solvers(problem)
    if snes is not None:
        return float(snes.getTolerances()[0])
    return None if newton is None else float(newton.rtol)


@contextlib.contextmanager
def looser_tolerances(problem, rtol: float | None, atol: float | None, max_it: int | None = None):
    """While solving a stage, stop Newton at ``rtol`` (relative to the stage's initial residual)
    or ``atol`` (absolute) where these are looser than the problem's own, and after ``max_it``
    iterations where that is fewer than the problem's own limit (None: unchanged)."""
    snes, newton = _newton_solvers(problem)
    if snes is not None:
        rtol0, atol0, stol, max_it0 = snes.getTolerances()
        snes.setTolerances(
            rtol=max(rtol0, rtol or 0.0),
            atol=max(atol0, atol or 0.0),
            max_it=max_it0 if max_it is None else min(max_it0, max_it),
        )
        try:
            yield
        finally:
            snes.setTolerances(rtol=rtol0, atol=atol0, stol=stol, max_it=max_it0)
    elif newton is not None:
        rtol0, atol0, max_it0 = newton.rtol, newton.atol, newton.max_it
        newton.rtol, newton.atol = max(rtol0, rtol or 0.0), max(atol0, atol or 0.0)
        if max_it is not None:
            newton.max_it = min(max_it0, max_it)
        try:
            yield
        finally:
            newton.rtol, newton.atol, newton.max_it = rtol0, atol0, max_it0
    else:
        yield
