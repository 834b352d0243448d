"""The contact force of an implicit time step that does not pump energy into impacts.

Average-acceleration Newmark is the trapezoidal rule on ``(u, v)``: over a step,
``M (v_{n+1} - v_n) = -dt (f_n + f_{n+1}) / 2`` and ``u_{n+1} - u_n = dt (v_n + v_{n+1}) / 2``,
so the kinetic energy changes by ``-(f_n + f_{n+1}) / 2 . (u_{n+1} - u_n)``. With the contact
force evaluated at the end of the step (``f = dW/du (u_{n+1})``), that work is not the change
of the contact energy ``W``: a contact that closes within a step is paid for at its end-of-step
force, and the bodies leave faster than they came (two cubes meeting corner-on: 2.4 times the
initial energy).

:class:`MidpointContact` replaces the contact force of the step equation by

    ``f_{n+1} = 2 dW/du ((u_n + u_{n+1}) / 2) - f_n``,

carrying the previous step's ``f_n``: the average ``(f_n + f_{n+1}) / 2`` the trapezoidal rule
works with is the contact force at the step's midpoint, the energy-momentum (midpoint)
treatment of Simo & Tarnow (1992) applied to the contact term alone. Its work over the step is
``dW/du (m) . (u_{n+1} - u_n)``, the midpoint rule for ``W(u_{n+1}) - W(u_n)`` (exact for a
quadratic ``W``, second-order accurate otherwise, with no bias towards gaining). The force stays
the gradient of a potential of ``u_{n+1}``, ``4 W(m) - f_n . u_{n+1}``, whose Hessian is that of
``W`` at the midpoint: the Jacobian keeps its pattern and symmetry (LDL^T and the energy line
search work as before, on that potential), and the force sums to zero over each pair
(translation invariance of ``W``), so linear momentum stays exact. ``f_{n+1}`` alternates in
sign after the bodies separate; the alternation cancels in ``u`` and ``v`` (the trapezoidal
rule sees only the averages) and shows only in the integrator's stored acceleration.
"""

from __future__ import annotations

import contextlib
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth.contact.operator import ContactOperator

__all__ = [
    "CONTACT_FORCES",
    "MidpointContact",
    "contact_force_of_steps",
    "default_contact_force",
    "hand_incremental_potential",
    "impact_failure_cause",
]

#: The contact forces of a time step ``solve_time_steps(contact_force=...)`` offers.
CONTACT_FORCES = ("endpoint", "midpoint")


def _is_trapezoidal(integrator) -> bool:
    """Whether the integrator is average-acceleration Newmark (the trapezoidal rule)."""
    beta, gamma = getattr(integrator, "beta", None), getattr(integrator, "gamma", None)
    return beta is not None and np.isclose(gamma, 0.5) and np.isclose(beta, 0.25)


def _takes_midpoint(problem) -> bool:
    """Whether the problem assembles through a SystemAssembler with a contact operator."""
    return getattr(problem, "contact", None) is not None and hasattr(problem, "assembler")


def default_contact_force(integrator, contact_force: str | None, problem=None) -> str:
    """The contact force a time step uses: ``contact_force`` checked, or by default
    ``"endpoint"``. The midpoint force is asked for, not the default: it removes the energy
    that flat faces meeting gain with the end-of-step force (two cubes corner-on: 2.61 times the
    start with it, 1.015 with the midpoint force), but it gains where a contact starts late in a
    step, which the midpoint does not see: a step ended at the impact by the collision detection
    (a cube at 30 per second onto a plate, +15 % in that step) and a ball bouncing on a plate
    (+29 % of the drop's energy), where the end-of-step force gains nothing.

    Raises:
        ValueError: for an unknown name, or ``"midpoint"`` with another integrator than
            average-acceleration Newmark or (given) a problem it cannot reach.
    """
    if contact_force is None:
        return "endpoint"
    if contact_force == "midpoint" and problem is not None and not _takes_midpoint(problem):
        raise ValueError(
            'contact_force="midpoint" needs a ContactProblem or NonlinearContactProblem (a '
            'problem with an assembler and a contact operator); use contact_force="endpoint"'
        )
    if contact_force not in CONTACT_FORCES:
        raise ValueError(f"contact_force must be one of {CONTACT_FORCES}, got {contact_force!r}")
    if contact_force == "midpoint" and not _is_trapezoidal(integrator):
        raise ValueError(
            'contact_force="midpoint" needs average-acceleration Newmark (beta = 1/4, '
            f'gamma = 1/2), got {type(integrator).__name__}; use contact_force="endpoint"'
        )
    return contact_force


@contextlib.contextmanager
def contact_force_of_steps(
    problem, integrator, contact_force: str
) -> typing.Iterator[MidpointContact | None]:
    """Within the block, the problem's assembler takes the contact term of
    :class:`MidpointContact` (yielded; None and nothing changed for ``"endpoint"``); afterwards
    the operator again, updated at ``u`` (collective)."""
    if contact_force == "endpoint":
        yield None
        return
    operator = problem.contact
    midpoint = MidpointContact(operator, integrator)
    problem.assembler.contact = midpoint
    try:
        yield midpoint
    finally:
        problem.assembler.contact = operator
        operator.update()
        midpoint.destroy()


def hand_incremental_potential(problem, integrator, strain_energy, external_work) -> bool:
    """Give a problem built without ``energy=`` the integrator's incremental potential
    ``integrator.incremental_energy(strain_energy - external_work)``, which turns its energy
    line search on, if that potential's derivative is the problem's residual (collective).

    The check assembles both at the predicted state moved by a smooth perturbation: a residual
    with terms the potential does not know (damping, non-conservative loads) differs there, and
    the problem keeps its residual line search.

    Returns:
        Whether the problem got the potential.
    """
    assembler = getattr(problem, "assembler", None)
    if (
        assembler is None
        or not hasattr(problem, "set_energy")
        or assembler.energy_form is not None
        or strain_energy is None
        or integrator.rho is None
    ):
        return False
    u = integrator.u
    potential = strain_energy if external_work is None else strain_energy - external_work
    potential = integrator.incremental_energy(potential)
    derivative = dolfinx.fem.form(ufl.derivative(potential, u, ufl.TestFunction(u.function_space)))
    saved = u.x.array.copy()
    x = u.function_space.tabulate_dof_coordinates()
    # one length on every rank, so that owned and ghost values of the test state agree
    local = float(np.ptp(x, axis=0).max()) if x.size else 0.0
    size = u.function_space.mesh.comm.allreduce(local, op=MPI.MAX)
    shape = np.cos(np.array([1.3, 2.9, 0.7]) * x[:, [1, 2, 0]] / size + 0.2).ravel()
    u.x.array[:] = (
        integrator.u_prev.x.array + integrator.dt * integrator.v_prev.x.array + 1e-4 * size * shape
    )
    vectors = []
    for form in (assembler.L, derivative):
        b = dolfinx.fem.petsc.assemble_vector(form)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        vectors.append(b)
    u.x.array[:] = saved
    scale = vectors[0].norm()
    vectors[1].axpy(-1.0, vectors[0])
    same = vectors[1].norm() <= 1e-8 * scale
    for b in vectors:
        b.destroy()
    if same:
        problem.set_energy(potential)
    return same


def impact_failure_cause(
    contact: ContactOperator | None, integrator, contact_force: str, result=None
) -> str:
    """What a time step that failed at the smallest dt met, for its error message: a residual
    that stalled at its round-off floor, or the contact state at the last iterate ``u`` holds
    (collective; updates the operator there).

    Args:
        contact: the problem's contact operator, or None.
        integrator: the time integrator (its ``dt`` is the failed step's).
        contact_force: the contact force of the steps (``"midpoint"`` or ``"endpoint"``).
        result: the last attempt's :class:`~fenics_matdepth.SolveResult`, or None.

    Returns:
        A sentence, or an empty string when neither applies.
    """
    norms = np.asarray(result.residual_norms if result is not None else (), dtype=float)
    if norms.size >= 3 and np.all(np.abs(norms[-3:] - norms[-1]) <= 1e-2 * norms[-1]):
        return (
            f"The residual stalled at {norms[-1]:.3g}: at dt = {integrator.dt:.3g} the inertia "
            "term (which scales as 1/dt^2) puts its round-off above the absolute tolerance; "
            "raise snes_atol or min_dt."
        )
    if contact is None:
        return ""
    try:
        contact.update()
    except FloatingPointError:  # a diverged iterate: nothing to say about its contact
        return ""
    active = contact.diagnostics()["active_pairs"]
    if active == 0:
        return ""
    depth = contact.max_penetration()
    sentence = (
        f"The step is an impact: at the last iterate {active} contact pairs overlap, the "
        f"deepest penetration is {depth:.3g}. "
    )
    if contact_force == "endpoint" and _is_trapezoidal(integrator):
        sentence += (
            'With contact_force="endpoint" (the default) average-acceleration Newmark creates '
            'energy where flat faces meet; contact_force="midpoint" does not there. '
        )
    return sentence + (
        "A smaller penalty (propose_penalty's factor) softens the impact; a smaller min_dt "
        "lets the controller resolve it."
    )


class MidpointContact:
    """The contact term of an average-acceleration Newmark step, evaluated at the midpoint.

    Stands in for the :class:`~fenics_matdepth.ContactOperator` inside a problem's
    :class:`~fenics_matdepth.SystemAssembler` during
    :func:`~fenics_matdepth.solve_time_steps`: the residual gets ``2 dW/du (m) - f_n``, the
    Jacobian ``d2W/du2 (m)`` and the energy ``4 W(m) - f_n . u``, ``m = (u_n + u) / 2`` (see the
    module's docstring). Every evaluation moves the operator's state to the midpoint; call
    ``operator.update()`` to read it at ``u`` again.

    Args:
        operator: the contact operator of ``integrator.u``.
        integrator: the :class:`~fenics_matdepth.Newmark` integrator (``u_prev`` is ``u_n``).
    """

    def __init__(self, operator: ContactOperator, integrator):
        self.operator = operator
        self.integrator = integrator
        self.u = operator.u
        #: the contact force of the last converged step (owned entries; F)
        self.force = self.u.x.petsc_vec.copy()
        self._gradient = self.u.x.petsc_vec.duplicate()
        self.start()

    # -- the step's bookkeeping ---------------------------------------------------------------

    def _assemble_gradient(self, out: PETSc.Vec) -> PETSc.Vec:
        """``out = dW/du`` at the operator's current state (owned entries; collective)."""
        with out.localForm() as local:
            local.set(0.0)
        self.operator.add_residual(out)
        return out

    def start(self) -> None:
        """Take the contact force of the last converged state ``u_n``, ``dW/du (u_n)``, as the
        previous step's (collective): consistent with an initial acceleration computed from
        the equation of motion."""
        u = self.u
        saved = u.x.array.copy()
        u.x.array[:] = self.integrator.u_prev.x.array
        try:
            self.operator.update()
            self._assemble_gradient(self.force)
        finally:
            u.x.array[:] = saved
        self.operator.update()

    def accept(self) -> None:
        """Before the integrator advances to the converged ``u``: make this step's contact
        force ``2 dW/du (m) - f_n`` the previous one (collective)."""
        self.update()
        gradient = self._assemble_gradient(self._gradient)
        self.force.aypx(-1.0, gradient)  # g - f_n
        self.force.axpy(1.0, gradient)  # 2 g - f_n
        self.operator.update()

    # -- what the assembler calls -------------------------------------------------------------

    def update(self) -> None:
        """Update the operator at the midpoint of the last converged ``u_n`` and ``u``."""
        u = self.u
        saved = u.x.array.copy()
        u.x.array[:] = 0.5 * (self.integrator.u_prev.x.array + saved)
        try:
            self.operator.update()
        finally:
            u.x.array[:] = saved

    def add_residual(self, b: PETSc.Vec) -> None:
        """``b += 2 dW/du (m) - f_n`` (collective)."""
        dofs, vals = self.operator.gradient_array()
        b.setValues(dofs.astype(PETSc.IntType), 2.0 * vals, addv=PETSc.InsertMode.ADD_VALUES)
        b.assemblyBegin()
        b.assemblyEnd()
        b.axpy(-1.0, self.force)

    def add_lifting(self, b: PETSc.Vec, offset: np.ndarray) -> None:
        """The contact part of the lifting with the Jacobian ``d2W/du2 (m)`` (collective)."""
        self.operator.add_lifting(b, offset)

    def add_jacobian(
        self, A: PETSc.Mat, bcs: typing.Sequence[dolfinx.fem.DirichletBC] | None = None
    ) -> None:
        """``A += d/du (2 dW/du (m)) = d2W/du2 (m)`` (collective)."""
        self.operator.add_jacobian(A, bcs)

    def energy(self) -> float:
        """``4 W(m) - f_n . u``, whose gradient is the residual's contact term (collective)."""
        return 4.0 * self.operator.energy() - self.force.dot(self.u.x.petsc_vec)

    def set_bcs(self, bcs: typing.Sequence[dolfinx.fem.DirichletBC]) -> None:
        """As :meth:`~fenics_matdepth.ContactOperator.set_bcs`."""
        self.operator.set_bcs(bcs)

    def pattern_needs_rebuild(self) -> bool:
        """Whether a midpoint coupling lies outside the pattern (collective)."""
        return self.operator.pattern_needs_rebuild()

    def create_matrix(self, a, bcs=None) -> PETSc.Mat:
        """As :meth:`~fenics_matdepth.ContactOperator.create_matrix`, for the midpoint's
        couplings."""
        return self.operator.create_matrix(a, bcs)

    def destroy(self) -> None:
        """Release the PETSc vectors."""
        self.force.destroy()
        self._gradient.destroy()
