"""Augmented Lagrangian contact (Hirota, Fisher & State 2003, section 8.3): Uzawa updates of
nodal contact pressures around a contact Newton solve.

The penalty method leaves an overlap of about ``p / eps`` (``p`` the contact pressure); making
it small takes a penalty so large that Newton's method struggles. The augmented Lagrangian
keeps a moderate penalty and carries the pressure in nodal values ``p_i`` on the boundary
vertices, interpolated linearly on every penetrating triangle. At fixed pressures the contact
energy is

    ``E = sum over (T, K) of int_{T cap K} (p g + (eps/2) g^2) dA``

(the force is ``(p + eps g) grad g``), with exact first and second derivatives, so each inner
Newton solve converges as the plain penalty one does. Between solves the pressures take the
Uzawa step

    ``p_i <- max(0, p_i + omega eps int mu_i g dA / int mu_i dA)``

(``mu_i`` the hat function of vertex i on its triangles, the integrals over the intersection
polygons; vertices whose triangles do not penetrate get 0), until the largest material depth
reached by any surface point is below the tolerance.

Why ``omega = 1/2`` by default: between two deformable bodies both surfaces penetrate the
other body, and both surfaces' pressures grow by ``omega eps g``, so the pressure they carry
together grows by ``2 omega eps g``, the whole penalty pressure when ``omega = 1``. The next
equilibrium would then need ``g = 0`` exactly, where the force ``p grad g`` of a surface point
drops to 0 as it leaves the other body: a kink of the energy on which Newton's method chatters
(measured on the patch test: the solve after the first update with ``omega = 1`` stalled at
30 % of its initial residual). With ``omega = 1/2`` the carried pressure approaches the
contact pressure from below, the overlap halves at each update and stays positive, and every
inner solve stays in the smooth region. Should an inner solve fail anyway, the update is
halved and the solve retried from the state before it.

The kink remains where pressures carried from an earlier solve (the last load step) hold a
face that now only touches: the equilibrium sits on it, and Newton's method cannot converge
however small the load step (measured on the knee, docs/demos.md). ``pressure_term =
"quadratic"`` removes it: the pressure term is ``p g^2 / (2 w)`` with ``w`` half the
tolerance and ``p`` the mean nodal pressure of the triangle, so the pressures act as a
stiffness, ``eps + p / w``, and the energy is C1 everywhere, like the plain penalty's. The
update then sets each nodal pressure to the contact pressure the solve produced at the deepest
point of the penetrating triangles around the vertex,

    ``p_i <- (1 - omega) p_i + omega max over those polygons of (eps + p_T / w) g``

(omega = 1 by default; ``ContactOperator.peak_pressure``), which lowers the pressures where a
contact relaxes. At a fixed point ``p = (eps + p / w) g_max``, so ``g_max = p / (eps + p / w)
< w``: the overlap ends below half the tolerance, whatever the pressure. (With the mean of
``g`` over the vertex's triangles instead of its maximum, the knee's fixed point kept its
deepest point at 1.36 times the tolerance.) The price is that the
stiffness grows with the pressure, ``p / w``, like a penalty sized for that overlap, reached
by updates from a moderate start.
"""

from __future__ import annotations

import dataclasses
import typing

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np

from fenics_matdepth.contact import diagnostics
from fenics_matdepth.depth import boundary_triangles
from fenics_matdepth.results import Solvable, SolveResult
from fenics_matdepth.tolerances import looser_tolerances

__all__ = ["AugmentedLagrangian", "RigidModeDamping", "UzawaUpdate", "damping_energy"]

#: A failed inner solve after a pressure update is retried with the update halved, at most
#: this many times.
MAX_UPDATE_HALVINGS = 4
#: The reason a solve ends with once its ``max_iterations`` are spent.
DIVERGED_MAX_IT = int(PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT)
#: A damped solve of RigidModeDamping that fails after k fell is retried from its anchor with
#: k falling by the square root of the factor, at most this many times.
MAX_DAMPED_RETRIES = 3


def _absolute_tolerance(
    problem, first_norm: float | None, inner_rtol: float, max_it: int | None = None
):
    """While solving again after a first solve (after a pressure update, or a damped solve),
    add an absolute Newton tolerance: ``inner_rtol`` times the first solve's initial residual
    (and stop after ``max_it`` iterations where that is fewer than the problem's limit).

    After an update the solve starts close to its solution, and a tolerance relative to
    that small initial residual falls below the residual's rounding floor (measured on the
    patch test with snes_rtol 1e-8: the solves after updates stalled between 1.2e-11 and
    3.9e-11 for relative targets of 4e-12 and below, while the first solve had started at
    2.2e-3)."""
    atol = None if first_norm is None else inner_rtol * first_norm
    return looser_tolerances(problem, None, atol, max_it)


@dataclasses.dataclass
class UzawaUpdate:
    """One inner solve of :class:`AugmentedLagrangian` and the pressure update after it.

    Attributes:
        newton_iterations: iterations of the inner Newton solve.
        overlap: largest material depth reached by the contact surface after it (L).
        overlap_h: ``overlap`` relative to the mesh size ``h`` of the driver.
        overlap_tol: ``overlap`` relative to the tolerance (<= 1: accepted).
        max_pressure: largest nodal pressure used in the solve (pressure units).
        pressure_change: largest change of a nodal pressure by the update that followed,
            relative to the largest updated pressure (0 when the solve was accepted).
    """

    newton_iterations: int
    overlap: float
    overlap_h: float
    overlap_tol: float
    max_pressure: float
    pressure_change: float


class AugmentedLagrangian:
    """Uzawa iterations on nodal contact pressures around a contact problem's Newton solve.

    Wraps a :class:`~fenics_matdepth.ContactProblem` or
    :class:`~fenics_matdepth.NonlinearContactProblem` whose operator uses area integration, and
    offers the same ``u``, ``contact`` and ``solve(raise_on_failure)``, so it goes where the
    problem went, e.g. ``fm.solve_load_steps(fm.AugmentedLagrangian(problem, tol_h=0.01),
    set_load)``. Pressures carry over from one solve (load step) to the next; a failed solve
    restores the pressures it started from, so load stepping can retry a smaller step.

    Args:
        problem: the contact problem (its operator gets the nodal pressures).
        tol: largest accepted overlap (L): the maximum material depth reached by any point of
            the contact surface (``ContactOperator.max_penetration``).
        tol_h: the same relative to the mesh size ``h``; with both, the smaller applies.
        max_updates: pressure updates before a solve counts as failed.
        max_iterations: the Newton iterations of one :meth:`solve`, its inner solves together
            (None: no limit but each inner solve's own). Each inner solve may take what is left
            of them; once they are spent the solve fails, and load stepping retries a smaller
            step. Without it the updates, and the halvings of an update whose solve failed
            (each solve up to the problem's iteration limit), can spend thousands of
            iterations on one load step (measured on the knee at 144 deg, docs/measurements.md).
        h: mesh size (L); default: the median edge length of the exterior boundary triangles
            (as :func:`~fenics_matdepth.propose_penalty`).
        relaxation: ``omega`` of the Uzawa step (see the module's docstring), in (0, 1];
            default 0.5 for the linear pressure term, 1 for the quadratic one.
        inner_rtol: the solves after a pressure update stop once the residual is below this
            fraction of the initial residual of the solve's first (pre-update) solve, or at the
            problem's own tolerances (see ``_absolute_tolerance``).
        pressure_term: ``"linear"`` (``int p g dA``, the pressures as Lagrange multipliers:
            the overlap can fall far below the tolerance at a moderate penalty) or
            ``"quadratic"`` (``int p g^2 / (2 w) dA`` with ``w = tol / 2``: no kink where a
            face lies flat on the other body, pressures that fall where a contact relaxes;
            for long load paths whose contacts slide and open, see the module's docstring).
        stall_rtol: a vertex whose pressure an update raised and whose overlap (the deepest
            point of the penetrating triangles round it) stayed above the tolerance and did
            not fall below ``1 - stall_rtol`` times its value before the update is *held* for
            the rest of the solve: its pressure goes back to its value before that update and
            no later update of the solve raises it (see "Stalled updates" below). 0 (the
            default): no vertex is held.
        stall_accept: a solve whose overlap is above the tolerance at held vertices only
            ends there (``stalled`` True): accepted where the overlap there is at most this
            many tolerances, failed above it.

    Stalled updates: an update multiplies the pressures round the deepest point by about
    ``g / w`` (quadratic term) or adds ``omega eps g`` (linear), on the assumption that a
    stiffer contact lowers ``g``. Where the overlap is held by what the solve cannot move, it
    does not: on one path of the knee demo a triangle of the femur (prescribed) stayed 1.72
    tolerances deep in a tetrahedron of the calf's tissue (all four vertices free, on the
    boundary) while eleven updates raised the pressures there 3.4-fold each, from 67 to 1.0e6
    MPa. A held vertex keeps its pressure from before the update that did not help (an update
    may still lower it), and the solve is judged by the overlap elsewhere. The next solve (load
    step) tries once more: its first update raises the vertex again, and holds it again where
    that does not help either, so the pressures there do not grow from step to step. (The state
    a stalled solve ends on was computed with the pressures before they were set back; the next
    solve starts from it with the pressures set back.)

    Attributes:
        tolerance: the overlap accepted (L).
        history: one :class:`UzawaUpdate` per inner solve of the last :meth:`solve`.
        total_updates: pressure updates summed over every :meth:`solve` so far.
        total_newton_iterations: Newton iterations summed over every :meth:`solve` so far.
        held: (num_vertices,) bool, the vertices the last :meth:`solve` held
            (``stall_rtol``).
        stalled: whether the last :meth:`solve` ended with its overlap above the tolerance
            at held vertices only.
        total_stalls: the solves so far that ended so, accepted or not.
    """

    def __init__(
        self,
        problem: Solvable,
        tol: float | None = None,
        tol_h: float | None = None,
        max_updates: int = 20,
        h: float | None = None,
        relaxation: float | None = None,
        inner_rtol: float = 1e-6,
        pressure_term: str = "linear",
        max_iterations: int | None = None,
        stall_rtol: float = 0.0,
        stall_accept: float = 2.0,
    ):
        contact = problem.contact
        if pressure_term not in ("linear", "quadratic"):
            raise ValueError(
                f"pressure_term must be 'linear' or 'quadratic', got {pressure_term!r}"
            )
        self.pressure_term = pressure_term
        if relaxation is None:
            relaxation = 0.5 if pressure_term == "linear" else 1.0
        if contact.integration != "area":
            raise ValueError(
                "the augmented Lagrangian needs a contact operator with area integration"
            )
        if tol is None and tol_h is None:
            raise ValueError("give a tolerance on the overlap: tol (length) or tol_h (times h)")
        if not 0.0 < relaxation <= 1.0:
            raise ValueError(f"relaxation must be in (0, 1], got {relaxation}")
        self.relaxation = float(relaxation)
        self.inner_rtol = float(inner_rtol)
        if max_updates < 0:
            raise ValueError(f"max_updates must be >= 0, got {max_updates}")
        if max_iterations is not None and max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1 or None, got {max_iterations}")
        self.max_iterations = max_iterations
        if not 0.0 <= stall_rtol < 1.0:
            raise ValueError(f"stall_rtol must be in [0, 1), got {stall_rtol}")
        if not stall_accept >= 1.0:
            raise ValueError(f"stall_accept must be >= 1 (tolerances), got {stall_accept}")
        self.stall_rtol = float(stall_rtol)
        self.stall_accept = float(stall_accept)
        if h is None:
            x = boundary_triangles(problem.u.function_space.mesh)
            h = float(np.median(np.linalg.norm(x[:, [1, 2, 0]] - x, axis=2)))
        self.h = float(h)
        bounds = [t for t in (tol, None if tol_h is None else tol_h * self.h) if t is not None]
        self.tolerance = float(min(bounds))
        if not (np.isfinite(self.tolerance) and self.tolerance > 0.0):
            raise ValueError(f"the overlap tolerance must be a positive length, got {bounds}")
        self.problem = problem
        self.u = problem.u
        self.contact = contact
        self.max_updates = int(max_updates)
        #: ``w`` of the quadratic pressure term (L), 0 for the linear one
        self.width = 0.5 * self.tolerance if pressure_term == "quadratic" else 0.0
        self.pressure = np.zeros(contact.num_vertices)
        self.history: list[UzawaUpdate] = []
        self.total_updates = 0
        self.total_newton_iterations = 0
        self.held = np.zeros(contact.num_vertices, dtype=bool)
        self.stalled = False
        self.total_stalls = 0
        self._before_update = self.pressure.copy()  # the pressures before the last update
        self._spent = False  # whether the last solve spent its max_iterations

    @property
    def pressure(self) -> np.ndarray:
        """The nodal pressures (global vertex numbering, the same on every rank); assigning
        them sets them on the operator too (e.g. to restore them from a checkpoint)."""
        return self._pressure

    @pressure.setter
    def pressure(self, value: np.ndarray) -> None:
        value = np.asarray(value, dtype=float)
        self.contact.set_pressure(value, self.width)
        self._pressure = self.contact.pressure

    def update_pressure(self) -> float:
        """One Uzawa step at the current state (collective).

        Returns:
            The largest change of a nodal pressure, relative to the largest new pressure.
        """
        if self.width > 0.0:  # towards the peak contact pressure round each vertex
            peak = self.contact.peak_pressure()
            touched = peak > 0.0
            step = peak[touched] - self.pressure[touched]
        else:  # by the penalty pressure of the mean overlap
            gmom, amom = self.contact.pressure_moments()
            touched = amom > 0.0
            step = self.contact.penalty * gmom[touched] / amom[touched]
        new = np.zeros_like(self.pressure)
        new[touched] = np.maximum(0.0, self.pressure[touched] + self.relaxation * step)
        new[self.held] = np.minimum(new[self.held], self.pressure[self.held])
        self._before_update = self.pressure.copy()
        scale = max(float(np.max(new, initial=0.0)), np.finfo(float).tiny)
        change = float(np.max(np.abs(new - self.pressure), initial=0.0)) / scale
        self.pressure = new
        return change

    def _absolute_tolerance(self, first_norm: float | None, max_it: int | None):
        """See :func:`_absolute_tolerance`."""
        return _absolute_tolerance(self.problem, first_norm, self.inner_rtol, max_it)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Newton solves and pressure updates until the overlap is within the tolerance.

        Args:
            raise_on_failure: raise ``RuntimeError`` if an inner solve fails or the overlap is
                still above the tolerance after ``max_updates`` updates; otherwise return the
                result with ``converged=False`` (the pressures are then restored).

        Returns:
            A :class:`~fenics_matdepth.SolveResult` whose ``iterations`` are the Newton
            iterations of all inner solves and ``residual_norms`` their histories joined.
        """
        start = self.pressure.copy()
        self.held = np.zeros_like(self.held)
        self.history = []
        before = None  # the vertices' overlaps after the last inner solve
        results: list[SolveResult] = []
        converged, reason = False, -1
        result = None
        previous = None  # (state, pressures) before the last update, to retry a failed solve
        halvings = 0
        k = 0
        first_norm = None
        self._spent = self.stalled = False
        while True:
            left = None
            if self.max_iterations is not None:
                left = self.max_iterations - sum(r.iterations for r in results)
                if left <= 0:  # (after a converged solve whose overlap is above the tolerance)
                    self._spent, reason = True, DIVERGED_MAX_IT
                    break
            with self._absolute_tolerance(first_norm, left):
                result = self.problem.solve(raise_on_failure=False)
            if first_norm is None and len(result.residual_norms):
                first_norm = float(result.residual_norms[0])
            results.append(result)
            if not result.converged:
                self._spent = left is not None and result.iterations >= left
                if previous is None or halvings >= MAX_UPDATE_HALVINGS or self._spent:
                    reason = result.reason
                    break
                # halve the last update and solve again from the state before it
                halvings += 1
                self.u.x.array[:] = previous[0]
                self.pressure = 0.5 * (previous[1] + self.pressure)
                continue
            overlap = self.contact.max_penetration()
            record = UzawaUpdate(
                result.iterations, overlap, overlap / self.h, overlap / self.tolerance,
                float(np.max(self.pressure, initial=0.0)), 0.0,
            )  # fmt: skip
            self.history.append(record)
            if overlap <= self.tolerance:
                converged, reason = True, result.reason
                break
            if self.stall_rtol > 0.0:
                before = self._hold_stalled(before)
                elsewhere = float(np.max(before[~self.held], initial=0.0))
                if self.held.any() and elsewhere <= self.tolerance:
                    self.stalled = True
                    self.total_stalls += 1
                    if overlap <= self.stall_accept * self.tolerance:
                        converged, reason = True, result.reason
                    else:
                        reason = 0
                    break
            if k == self.max_updates:
                reason = 0  # every inner solve converged, the overlap did not
                break
            previous = (self.u.x.array.copy(), self.pressure.copy())
            halvings = 0
            record.pressure_change = self.update_pressure()
            self.total_updates += 1
            k += 1
        out = SolveResult.merged(results, converged, reason)
        self.total_newton_iterations += out.iterations
        if not converged:
            self.pressure = start
            if raise_on_failure:
                raise RuntimeError(self.failure_message(out))
        return out

    def _vertex_overlaps(self) -> np.ndarray:
        """Per vertex, the deepest point reached by the penetrating boundary triangles round
        it (L; 0 elsewhere; global numbering, collective): ``peak_pressure`` at unit
        stiffness."""
        g, pair_a, _ = self.contact.pair_depths()
        return diagnostics.peak_pressure(self.contact.surface, g, pair_a, 1.0, None, 0.0)

    def _hold_stalled(self, before: np.ndarray | None) -> np.ndarray:
        """Hold the vertices the last update raised whose overlap stayed above the tolerance
        and fell by less than ``stall_rtol`` since ``before`` (the overlaps after the solve
        before that update), their pressures back to their values before it; returns the
        overlaps now."""
        now = self._vertex_overlaps()
        if before is not None:  # an update came between: the vertices it raised
            raised = self.pressure > self._before_update
            stuck = (now > self.tolerance) & (now >= (1.0 - self.stall_rtol) * before)
            newly = raised & stuck & ~self.held
            if newly.any():  # the update did not help there: undone
                pressure = self.pressure.copy()
                pressure[newly] = self._before_update[newly]
                self.pressure = pressure
                self.held |= newly
        return now

    def failure_message(self, result: SolveResult) -> str:
        """Why :meth:`solve` failed."""
        if self._spent:
            return (
                f"augmented Lagrangian: the {self.max_iterations} Newton iterations of a solve "
                f"(max_iterations) spent, the overlap not yet within {self.tolerance:.3e}; "
                "last residual norms: "
                + ", ".join(f"{r:.3e}" for r in result.residual_norms[-5:])
                + ". Reduce the load step (solve_load_steps cuts it automatically)"
            )
        if result.reason == 0 and self.stalled:
            return (
                f"augmented Lagrangian: the overlap {self.history[-1].overlap_tol:.3f} "
                f"tolerances at vertices whose pressure updates stalled (held: raising their "
                f"pressures did not lower it), above stall_accept = {self.stall_accept:g}: "
                "the pressures cannot move the deepest point (a surface prescribed into a "
                "body held there?); reduce the load step (solve_load_steps cuts it "
                "automatically)"
            )
        if result.reason == 0:
            last = self.history[-1]
            return (
                f"augmented Lagrangian: overlap {last.overlap:.3e} still above the tolerance "
                f"{self.tolerance:.3e} after {len(self.history) - 1} pressure updates; raise "
                "max_updates or the penalty"
            )
        return "augmented Lagrangian: " + result.failure_message()

    def diagnostics(self) -> dict[str, typing.Any]:
        """The last solve: ``updates`` (pressure updates), ``newton_iterations`` (all inner
        solves), ``overlap`` (L), ``overlap_h`` and ``overlap_tol`` (relative to h and to the
        tolerance), ``max_pressure``, the last ``pressure_change`` (relative), whether the
        solve ended ``stalled`` and how many vertices are held (``held_vertices``)."""
        if not self.history:
            return {}
        last = self.history[-1]
        return {
            "updates": len(self.history) - 1,
            "newton_iterations": sum(r.newton_iterations for r in self.history),
            "overlap": last.overlap,
            "overlap_h": last.overlap_h,
            "overlap_tol": last.overlap_tol,
            "max_pressure": float(np.max(self.pressure, initial=0.0)),
            "pressure_change": self.history[-2].pressure_change if len(self.history) > 1 else 0.0,
            "stalled": self.stalled,
            "held_vertices": int(np.count_nonzero(self.held)),
        }


def damping_energy(
    u: typing.Any, measure: typing.Any, stiffness: float
) -> tuple[typing.Any, typing.Any, typing.Any]:
    """The proximal term ``(k / 2) int |u - u_anchor|^2`` for :class:`RigidModeDamping`.

    Add the returned form to the energy (and its derivative to the residual) of a problem with
    a body held only by contact.

    Args:
        u: the displacement Function.
        measure: where to damp, e.g. ``dx(free_body_tag)`` (or ``ufl.dx``).
        stiffness: k (force / length^4: a body force per unit displacement); a body force
            ``f`` then moves a free body by about ``f / k`` per proximal step.

    Returns:
        ``(energy_term, k, anchor)``: the UFL form, the ``Constant`` k and the anchor Function,
        to pass to :class:`RigidModeDamping`.
    """
    from petsc4py import PETSc

    import dolfinx
    import ufl

    anchor = dolfinx.fem.Function(u.function_space, name="anchor")
    k = dolfinx.fem.Constant(u.function_space.mesh, PETSc.ScalarType(stiffness))
    return 0.5 * k * ufl.inner(u - anchor, u - anchor) * measure, k, anchor


class RigidModeDamping:
    """Proximal-point solves for bodies that are free until contact engages.

    A body held only by contact (a floating body under a body force, a body pushed by forces
    before it touches) has a rigid-body mode with no stiffness until the contact zone has
    grown: Newton's matrix is singular or nearly so, and the first solve of the first load step
    diverges. The problem's energy gets the term ``(k / 2) int |u - u_anchor|^2`` (from
    :func:`damping_energy`): with the anchor at the current state each solve is well posed and
    moves a free body by about ``f / k``; the anchor then moves to the solution and the solve
    repeats with ``k`` divided by ``1 / decrease`` (proximal point iteration with a falling
    stiffness: the first solve moves a free body little, the later ones let contact, which has
    engaged meanwhile, carry it) until a solve changes ``u`` by less than ``rtol`` times the
    whole change of this call or ``k`` has fallen below ``1e-6`` of its start (a damped solve
    that fails after ``k`` fell is retried from its anchor with ``k`` falling by the square
    root of the factor from then on, at most ``MAX_DAMPED_RETRIES`` times). Then ``k`` is set
    to 0 and a last solve, from that nearly balanced state, removes the remaining damping
    force: the result solves the undamped problem.

    After a call that converged, contact held the body at its end, and the next call (the next
    load step, or the next solve of an :class:`AugmentedLagrangian`) first solves the undamped
    problem from where it starts (``undamped_first``); only if that fails does it restore the
    start and run the damped solves. Measured on ``benchmarks/bench_hertz.py`` (the full model,
    res 1.0, penalty 10 E/h): with the damped solves in every step each load step took 4 or 5
    solves and 12 to 14 Newton iterations; now the steps after the first take one solve of 4 or
    5 iterations (docs/solvers.md).

    Args:
        problem: a contact problem whose energy and residual include the damping term.
        stiffness: the ``Constant`` k of :func:`damping_energy` (its value is the k used).
        anchor: the anchor Function of :func:`damping_energy`.
        rtol: stop the damped solves when the last one moved ``u`` by less than this fraction
            of the total change (max norm).
        max_solves: damped solves at most.
        decrease: factor on k from one damped solve to the next, in (0, 1].
        inner_rtol: the solves after the first stop at this fraction of the first solve's
            initial residual at the latest (see :class:`AugmentedLagrangian`).
        undamped_first: after a converged call, try the undamped solve first (see above).
        may_decrease: called after each damped solve that made progress with the ``k`` it
            used; ``k`` falls only where it returns True (default: always). A solver without
            a line search uses it to keep ``k`` until contact holds the body
            (:class:`~fenics_matdepth.free_bodies.FreeBodyDamping`).
    """

    def __init__(
        self,
        problem: Solvable,
        stiffness,
        anchor,
        rtol: float = 1e-2,
        max_solves: int = 20,
        decrease: float = 0.1,
        inner_rtol: float = 1e-6,
        undamped_first: bool = True,
        may_decrease: typing.Callable[[float], bool] | None = None,
    ):
        self.problem = problem
        self.u = problem.u
        self.contact = problem.contact
        self._k = stiffness
        self.stiffness = float(stiffness.value)
        self.anchor = anchor
        self.rtol = float(rtol)
        self.max_solves = int(max_solves)
        self.decrease = float(decrease)
        self.inner_rtol = float(inner_rtol)
        self.undamped_first = bool(undamped_first)
        self.may_decrease = may_decrease
        #: damped solves in the last :meth:`solve`
        self.damped_solves = 0
        #: whether the last :meth:`solve` converged (contact held the body at its end)
        self.held = False

    @property
    def snes(self):
        """The wrapped problem's SNES (if any)."""
        return getattr(self.problem, "snes", None)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Damped solves until ``u`` settles, then one undamped solve (collective); after a
        converged call the undamped solve first (``undamped_first``)."""
        comm = self.u.function_space.mesh.comm
        start = self.u.x.array.copy()
        results: list[SolveResult] = []
        self.damped_solves = 0
        first_norm = None

        def solve_once():
            with _absolute_tolerance(self.problem, first_norm, self.inner_rtol):
                results.append(self.problem.solve(raise_on_failure=False))
            return results[-1]

        try:
            result = None
            if self.undamped_first and self.held:
                self._k.value = 0.0
                result = solve_once()
                if not result.converged:
                    # contact no longer holds the body: damped solves from the start
                    self.u.x.array[:] = start
                    self.u.x.scatter_forward()
            k, decrease, retries = self.stiffness, self.decrease, 0
            damp = result is None or not result.converged
            while damp and self.damped_solves < self.max_solves:
                self._k.value = k
                self.anchor.x.array[:] = self.u.x.array
                result = solve_once()
                if first_norm is None and len(result.residual_norms):
                    first_norm = float(result.residual_norms[0])
                self.damped_solves += 1
                r = result.residual_norms
                if not result.converged:
                    # a damped solve only has to make progress: the undamped solve at the end
                    # decides (seen on DOLFINx 0.11: the energy line search stopped a damped
                    # solve at 7e-5 of its initial residual)
                    if not (len(r) and np.isfinite(r[-1]) and r[-1] <= 1e-3 * r[0]):
                        if k == self.stiffness or retries >= MAX_DAMPED_RETRIES:
                            break
                        # k fell too far for this solve (a body thrown deep into another;
                        # seen without a line search): from its anchor again, k falling by the
                        # square root of the factor from now on
                        self.u.x.array[:] = self.anchor.x.array
                        self.u.x.scatter_forward()
                        k /= decrease
                        decrease = np.sqrt(decrease)
                        k *= decrease
                        retries += 1
                        continue
                    result = dataclasses.replace(result, converged=True)
                local = self.u.x.array
                step = comm.allreduce(
                    float(np.max(np.abs(local - self.anchor.x.array))), op=MPI.MAX
                )
                total = comm.allreduce(float(np.max(np.abs(local - start))), op=MPI.MAX)
                if step <= self.rtol * total or k * decrease < 1e-6 * self.stiffness:
                    break
                if self.may_decrease is None or self.may_decrease(k):
                    k *= decrease
            if self.damped_solves and result.converged:
                self._k.value = 0.0
                result = solve_once()
        finally:
            self._k.value = 0.0
        out = SolveResult.merged(results, result.converged, result.reason)
        self.held = out.converged
        if raise_on_failure and not out.converged:
            raise RuntimeError(out.failure_message())
        return out
