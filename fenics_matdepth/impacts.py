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

The midpoint rule is not exact where ``W`` is not smooth over the step: a contact that starts
late in a step is missed by the midpoint and then pays its whole energy at the next step's
midpoint force, a gain. :class:`DiscreteGradientContact` makes the average force the discrete
gradient of ``W`` (Gonzalez 1996), pair by pair: the midpoint gradient plus the correction
that makes its work over the step exactly ``W(u_{n+1}) - W(u_n)``.
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

from fenics_matdepth.contact import assembly
from fenics_matdepth.contact.discrete_gradient import StepPairs
from fenics_matdepth.contact.operator import ContactOperator

__all__ = [
    "CONTACT_FORCES",
    "DiscreteGradientContact",
    "MidpointContact",
    "CRUSHED_DET_F",
    "contact_force_of_steps",
    "crushed_cells_cause",
    "default_contact_force",
    "hand_incremental_potential",
    "impact_failure_cause",
]

#: The contact forces of a time step ``solve_time_steps(contact_force=...)`` offers.
CONTACT_FORCES = ("endpoint", "midpoint", "discrete_gradient")


def _is_trapezoidal(integrator) -> bool:
    """Whether the integrator is average-acceleration Newmark (the trapezoidal rule)."""
    beta, gamma = getattr(integrator, "beta", None), getattr(integrator, "gamma", None)
    return beta is not None and np.isclose(gamma, 0.5) and np.isclose(beta, 0.25)


def _takes_midpoint(problem) -> bool:
    """Whether the problem assembles through a SystemAssembler with a contact operator."""
    return getattr(problem, "contact", None) is not None and hasattr(problem, "assembler")


def default_contact_force(integrator, contact_force: str | None, problem=None) -> str:
    """The contact force a time step uses: ``contact_force`` checked, or by default the
    discrete gradient (``"discrete_gradient"``) with average-acceleration Newmark and a
    plain-penalty area contact (no augmented Lagrangian, no friction), else ``"endpoint"``.

    The discrete gradient's work over every step is the change of the contact energy, so
    contact creates no energy at impacts, where the end-of-step force gained 161 % (two cubes
    corner-on) and 22 % (blocks face-on); it keeps linear and angular momentum. Backward Euler
    keeps the end-of-step force, which only dissipates; the midpoint force is asked for, not
    the default (it gains where a contact starts late in a step).

    Raises:
        ValueError: for an unknown name, or ``"midpoint"`` with another integrator than
            average-acceleration Newmark or (given) a problem it cannot reach.
    """
    if contact_force is None:
        op = getattr(problem, "contact", None)
        if (
            _is_trapezoidal(integrator)
            and problem is not None
            and _takes_midpoint(problem)
            and op.integration == "area"
            and op.pressure is None
            and op.friction is None
        ):
            return "discrete_gradient"
        return "endpoint"
    if contact_force not in CONTACT_FORCES:
        raise ValueError(f"contact_force must be one of {CONTACT_FORCES}, got {contact_force!r}")
    if contact_force != "endpoint" and problem is not None and not _takes_midpoint(problem):
        raise ValueError(
            f'contact_force="{contact_force}" needs a ContactProblem or NonlinearContactProblem '
            '(a problem with an assembler and a contact operator); use contact_force="endpoint"'
        )
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
    :class:`MidpointContact` or :class:`DiscreteGradientContact` (yielded; None and nothing
    changed for ``"endpoint"``); afterwards the operator again, updated at ``u``
    (collective)."""
    if contact_force == "endpoint":
        yield None
        return
    operator = problem.contact
    kind = DiscreteGradientContact if contact_force == "discrete_gradient" else MidpointContact
    midpoint = kind(operator, integrator)
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


#: Where a time step fails at the smallest dt and the last accepted state has a cell with det F
#: below this, the failure is put down to crushed elements, not to the contact.
CRUSHED_DET_F = 0.05


def crushed_cells_cause(problem) -> str:
    """Whether the bodies are crushed at the problem's current state (the last accepted one),
    for the error message of a time step that failed at the smallest dt (collective).

    A cell near inversion makes every step from there fail, and no contact setting helps: the
    impact of ``tests/test_ccd_impact.py`` at 500 per second on a plate whose wave speed is 37
    per second crushes the plate's top elements to det F = 1e-3 with the contact holding.

    Args:
        problem: the time-stepped problem (its ``min_det_F()``), or anything without one.

    Returns:
        A sentence naming the smallest det F and what to change, or an empty string when it
        is not below :data:`CRUSHED_DET_F`.
    """
    min_det_F = getattr(problem, "min_det_F", None)
    if min_det_F is None:
        return ""
    lowest = float(min_det_F())
    if not lowest < CRUSHED_DET_F:
        return ""
    return (
        f"The bodies are crushed: the smallest det F at the last accepted state is {lowest:.3g} "
        "(cells about to invert), and no step goes on from there whatever the contact does. "
        "An impact faster than the material's wave speed (about sqrt(E / rho)) or a load it "
        "cannot carry does this: a stiffer material, a finer mesh where it is crushed or a "
        "slower impact is needed; neither the penalty nor the time step helps. "
    )


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
            'With contact_force="endpoint" average-acceleration Newmark creates energy where '
            'flat faces meet; contact_force="discrete_gradient" (the default where it applies) '
            "does not. "
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

    Raises:
        ValueError: for an operator with friction (its terms are not evaluated at the midpoint).
    """

    def __init__(self, operator: ContactOperator, integrator):
        if operator.friction is not None:
            raise ValueError(
                'contact_force="midpoint" does not carry friction (its dissipative terms are '
                'lagged per step, not evaluated at the midpoint); use contact_force="endpoint"'
            )
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


class DiscreteGradientContact(MidpointContact):
    """The contact term of a time step whose work over the step is the change of the contact
    energy, exactly: the discrete gradient of Gonzalez (1996), pair by pair.

    For each (triangle, tetrahedron) pair that intersects at the step's start ``u_n``, its
    midpoint or its end ``u`` (:class:`~fenics_matdepth.contact.discrete_gradient.StepPairs`),
    ``DG_p = dW_p/du (m) + c_p M dU_p`` with ``c_p`` such that ``DG_p . dU_p = W_p(u) -
    W_p(u_n)`` (`fenics_matdepth.contact.kernels.discrete_gradient`; ``M`` removes the pair's
    mean translation, so ``DG`` sums to zero over each pair and moves no momentum). Summed,
    ``DG . (u - u_n) = W(u) - W(u_n)``.

    With average-acceleration Newmark ``DG`` is the step's average contact force
    ``(f_n + f_{n+1}) / 2``: the residual gets ``2 DG - f_n`` (``f_{n+1} = 2 DG - f_n`` is
    carried to the next step, as :class:`MidpointContact` does), and the kinetic, strain and
    contact energies change by exactly the work of the other forces, up to the trapezoidal
    rule's error on the bulk's own nonlinearity. With backward Euler ``DG`` is the step's
    contact force itself: the residual gets ``DG``, and the contact gains no energy (the
    kinetic energy loses ``|v_{n+1} - v_n|^2_M / 2`` per step as before).

    The Jacobian is the exact derivative (non-symmetric: the rank-one parts of ``c_p``; the
    problem's factorisation becomes LU). The line search's merit is the potential of
    :class:`MidpointContact`, ``4 W(m) - f_n . u`` (backward Euler: ``2 W(m)``), whose gradient
    ``2 dW/du (m) - f_n`` is the residual's contact term but for the ``c_p`` corrections:
    where the step goes uphill on it, the problem's line search judges by the residual norm.

    Couplings of a pair that intersects only at the step's start or midpoint and that lie
    outside the matrix pattern (built around the end state) are left out of the Jacobian
    (:attr:`left_out` counts them); the residual is exact.

    Args:
        operator: the contact operator of ``integrator.u`` (area integration, plain penalty).
        integrator: :class:`~fenics_matdepth.Newmark` with ``beta = 1/4``, ``gamma = 1/2``, or
            :class:`~fenics_matdepth.BackwardEuler` (``u_prev`` is ``u_n``).

    Raises:
        ValueError: for collocation, an augmented Lagrangian's pressures, friction, or another
            integrator.
    """

    def __init__(self, operator: ContactOperator, integrator):
        if (
            operator.integration != "area"
            or operator.pressure is not None
            or operator.friction is not None
        ):
            raise ValueError(
                'contact_force="discrete_gradient" needs area integration with plain penalty '
                '(no augmented Lagrangian pressures, no friction); use contact_force="endpoint"'
            )
        self.trapezoidal = _is_trapezoidal(integrator)
        if not (self.trapezoidal or type(integrator).__name__ == "BackwardEuler"):
            raise ValueError(
                'contact_force="discrete_gradient" needs average-acceleration Newmark (beta = '
                "1/4, gamma = 1/2) or BackwardEuler, got "
                f'{type(integrator).__name__}; use contact_force="endpoint"'
            )
        self.pairs: StepPairs | None = None
        self._state: tuple | None = None
        #: Jacobian couplings left out at the last assembly (outside the pattern)
        self.left_out = 0
        super().__init__(operator, integrator)

    # -- the step's bookkeeping ---------------------------------------------------------------

    def accept(self) -> None:
        """Before the integrator advances to the converged ``u``: with Newmark, make this
        step's contact force ``2 DG - f_n`` the previous one (collective)."""
        self.update()
        if self.trapezoidal:
            gradient = self._gradient
            with gradient.localForm() as local:
                local.set(0.0)
            self._add_pairs(gradient, 1.0)
            self.force.aypx(-1.0, gradient)  # DG - f_n
            self.force.axpy(1.0, gradient)  # 2 DG - f_n

    def _add_pairs(self, b: PETSc.Vec, scale: float) -> None:
        """``b += scale DG`` (owned entries; collective)."""
        p = self.pairs
        dofs, vals = assembly.gradient_array(self.operator.surface, p.verts, scale * p.gradient)
        b.setValues(dofs.astype(PETSc.IntType), vals, addv=PETSc.InsertMode.ADD_VALUES)
        b.assemblyBegin()
        b.assemblyEnd()

    # -- what the assembler calls -------------------------------------------------------------

    def update(self) -> None:
        """Update the operator at ``u`` and the step's pairs between ``u_n`` and ``u``
        (collective; nothing is recomputed at the same state)."""
        operator = self.operator
        operator.update()
        s = operator.surface
        n = s.owned_dof_count()
        state = (
            self.u.x.array[:n].copy(), self.integrator.u_prev.x.array[:n].copy(), s.refreshes,
            operator.penalty_revision,
        )  # fmt: skip
        last = self._state
        same = last is not None and all(
            np.array_equal(a, b) for a, b in zip(state, last, strict=True)
        )
        if operator.comm.allreduce(same, op=MPI.LAND):
            return
        x0 = s.X + s.pull(state[1].reshape(-1, 3))
        self.pairs = StepPairs(s, x0, operator.penalty)
        self._state = state

    def add_residual(self, b: PETSc.Vec) -> None:
        """``b += 2 DG - f_n`` (Newmark) or ``DG`` (backward Euler) (collective)."""
        self._add_pairs(b, 2.0 if self.trapezoidal else 1.0)
        if self.trapezoidal:
            b.axpy(-1.0, self.force)

    def _scaled_jacobian(self) -> np.ndarray:
        return (2.0 if self.trapezoidal else 1.0) * self.pairs.jacobian()

    def add_lifting(self, b: PETSc.Vec, offset: np.ndarray) -> None:
        """``b += J[:, D] offset[D]`` with the discrete gradient's Jacobian, from the pairs
        with a Dirichlet dof not yet on its value (collective)."""
        assembly.add_lifting_pairs(
            self.operator.surface, b, offset, lambda: self.pairs.verts,
            lambda sel: self._scaled_jacobian()[sel],
        )  # fmt: skip

    def add_jacobian(
        self, A: PETSc.Mat, bcs: typing.Sequence[dolfinx.fem.DirichletBC] | None = None
    ) -> None:
        """``A +=`` the derivative of the residual's contact term (collective)."""
        operator = self.operator
        if bcs is not None:
            operator.set_bcs(bcs)
        s = operator.surface
        keys, transposed = operator.held_pattern()
        pos, missing = assembly.coupling_positions(s, keys, self.pairs.verts, transposed)
        self.left_out = operator.comm.allreduce(missing)
        assembly.add_jacobian_blocks(A, s, keys, pos, self.pairs.verts, self._scaled_jacobian())
        A.assemble()

    def energy(self) -> float:
        """The line search's merit: ``4 W(m) - f_n . u`` (Newmark) or ``2 W(m)`` (backward
        Euler) (collective)."""
        midpoint = self.operator.comm.allreduce(float(np.sum(self.pairs.energy_mid)))
        if not self.trapezoidal:
            return 2.0 * midpoint
        return 4.0 * midpoint - self.force.dot(self.u.x.petsc_vec)

    def pattern_needs_rebuild(self) -> bool:
        """Whether a coupling at ``u`` lies outside the pattern (collective)."""
        self.update()
        return self.operator.pattern_needs_rebuild()
