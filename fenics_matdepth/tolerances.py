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
def looser_tolerances(problem, rtol: float | None, atol: float | None):
    """While solving a stage, stop Newton at ``rtol`` (relative to the stage's initial residual)
    or ``atol`` (absolute) where these are looser than the problem's own (None: unchanged)."""
    snes, newton = _newton_solvers(problem)
    if snes is not None:
        rtol0, atol0, stol, max_it = snes.getTolerances()
        snes.setTolerances(rtol=max(rtol0, rtol or 0.0), atol=max(atol0, atol or 0.0))
        try:
            yield
        finally:
            snes.setTolerances(rtol=rtol0, atol=atol0, stol=stol, max_it=max_it)
    elif newton is not None:
        rtol0, atol0 = newton.rtol, newton.atol
        newton.rtol, newton.atol = max(rtol0, rtol or 0.0), max(atol0, atol or 0.0)
        try:
            yield
        finally:
            newton.rtol, newton.atol = rtol0, atol0
    else:
        yield
