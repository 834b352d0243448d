"""Implicit dynamics: Newmark and backward Euler time integration, and a time-step loop.

The integrators hold the last converged state (displacement, velocity, acceleration) as
DOLFINx Functions and expose the new step's acceleration and velocity as UFL expressions of the
unknown ``u``, so the user writes the inertia term into their own residual::

    integrator = fm.Newmark(u, dt=1e-3, rho=rho)
    F = rho * ufl.inner(integrator.acceleration, v) * ufl.dx + ufl.inner(P, ufl.grad(v)) * ufl.dx
    Pi = integrator.incremental_energy(psi * ufl.dx - ufl.inner(rho * g, u) * ufl.dx)
    problem = fm.ContactProblem(F, u, contact, energy=Pi)
    history = fm.solve_time_steps(problem, integrator, t_end=1.0, dt=1e-3,
                                  strain_energy=psi * ufl.dx, external_work=...)

Each step solves ``F(u) + dE_contact/du = 0`` for ``u_{n+1}`` with the contact force evaluated
at ``u_{n+1}`` like every other internal force, which for Newmark is the stationarity condition
of the incremental potential

    Pi(u) = rho / (2 beta dt^2) |u - u_pred|^2_M + Psi(u) + E_contact(u),
    u_pred = u_n + dt v_n + dt^2 (1/2 - beta) a_n,

so the energy line search of :class:`~fenics_matdepth.ContactProblem` works in dynamics.

Generalized-alpha is not offered: it evaluates the internal forces at an intermediate
configuration ``u_{n+1-alpha_f}``, and a consistent scheme would need the contact operator
there too (its residual and Jacobian at a blended displacement); the contact operator works on
``u`` itself. Numerical damping comes from Newmark with ``gamma > 1/2`` or backward Euler.
"""

from __future__ import annotations

import dataclasses
import time
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth._progress import StepProgress
from fenics_matdepth.solvers import SolveResult, _write

__all__ = ["BackwardEuler", "Newmark", "TimeStep", "solve_time_steps"]


def _set_array(target: dolfinx.fem.Function, value) -> None:
    """Fill ``target`` from a Function, an array of its local size, a callable (interpolated) or
    a constant; None leaves it at zero."""
    if value is None:
        target.x.array[:] = 0.0
    elif isinstance(value, dolfinx.fem.Function):
        target.x.array[:] = value.x.array
    elif callable(value):
        target.interpolate(value)
    else:
        value = np.asarray(value, dtype=target.x.array.dtype)
        if value.size == target.x.array.size:
            target.x.array[:] = value.ravel()
        else:  # a constant vector, one value per component
            bs = target.function_space.dofmap.index_map_bs
            target.x.array.reshape(-1, bs)[:] = np.broadcast_to(value, (1, bs))
    target.x.scatter_forward()


class _Integrator:
    """The state and the bookkeeping shared by the one-step integrators.

    Subclasses define the acceleration of the new step as ``c (u - u_pred)`` with the predictor
    ``u_pred`` (depending on the last state and dt) and the coefficient ``c``, and the velocity
    of the new step; everything else (energies, momenta, initial conditions) is here.
    """

    def __init__(
        self,
        u: dolfinx.fem.Function,
        dt: float,
        rho: float | ufl.core.expr.Expr | None = None,
        dx: ufl.Measure | None = None,
    ):
        self.u = u
        V = u.function_space
        mesh = V.mesh
        self._comm: MPI.Comm = mesh.comm
        self.u_prev = dolfinx.fem.Function(V, name="displacement_previous")
        self.v_prev = dolfinx.fem.Function(V, name="velocity")
        self.a_prev = dolfinx.fem.Function(V, name="acceleration")
        self.u_prev.x.array[:] = u.x.array
        self._dt = dolfinx.fem.Constant(mesh, PETSc.ScalarType(1.0))
        self.dt = dt
        #: density (mass / L^3): a number, a Constant, a DG0 Function or any UFL expression
        self.rho = rho
        self.dx = dx if dx is not None else ufl.dx(domain=mesh)
        #: time of the last converged state (set by :func:`solve_time_steps`)
        self.t = 0.0
        self._forms: dict[str, dolfinx.fem.Form] = {}

    # -- time step ------------------------------------------------------------------------------

    @property
    def dt(self) -> float:
        """The time step (a ``dolfinx.fem.Constant`` inside the forms: changing it between steps
        needs no recompilation)."""
        return float(np.real(self._dt.value))

    @dt.setter
    def dt(self, value: float) -> None:
        value = float(value)
        if not (np.isfinite(value) and value > 0.0):
            raise ValueError(f"the time step must be a positive number, got {value}")
        self._dt.value = value

    @property
    def dt_constant(self) -> dolfinx.fem.Constant:
        """The Constant holding dt, for the user's own time-dependent forms."""
        return self._dt

    # -- what subclasses define -----------------------------------------------------------------

    def _coefficient(self, dt):
        """c in a = c (u - u_pred)."""
        raise NotImplementedError

    def _predictor(self, u_prev, v_prev, a_prev, dt):
        """u_pred in a = c (u - u_pred) (UFL or arrays alike)."""
        raise NotImplementedError

    def _velocity(self, v_prev, a_prev, a_new, u_new, u_prev, dt):
        """The new velocity from the new acceleration (UFL or arrays alike)."""
        raise NotImplementedError

    def _velocity_slope(self, dt):
        """d velocity / du (a number times the identity)."""
        raise NotImplementedError

    # -- UFL ------------------------------------------------------------------------------------

    @property
    def acceleration(self) -> ufl.core.expr.Expr:
        """The acceleration of the new step, a UFL expression of the unknown ``u`` (L / T^2)."""
        dt = self._dt
        return self._coefficient(dt) * (
            self.u - self._predictor(self.u_prev, self.v_prev, self.a_prev, dt)
        )

    @property
    def velocity(self) -> ufl.core.expr.Expr:
        """The velocity of the new step, a UFL expression of the unknown ``u`` (L / T)."""
        return self._velocity(
            self.v_prev, self.a_prev, self.acceleration, self.u, self.u_prev, self._dt
        )

    def _density(self, rho=None):
        rho = self.rho if rho is None else rho
        if rho is None:
            raise ValueError(
                "the density is unknown: pass rho= to the integrator (Newmark(u, dt, rho=...)) "
                "or to this method"
            )
        return rho

    def inertia(self, v: ufl.Argument, rho=None, damping=None) -> ufl.Form:
        """The inertia term ``rho * inner(acceleration, v) * dx`` of the residual.

        Args:
            v: the test function.
            rho: density; default the integrator's.
            damping: mass-proportional (Rayleigh) damping coefficient c (1/T): adds the
                viscous force ``c * rho * inner(velocity, v) * dx``.
        """
        rho = self._density(rho)
        form = rho * ufl.inner(self.acceleration, v) * self.dx
        if damping is not None:
            form += damping * rho * ufl.inner(self.velocity, v) * self.dx
        return form

    def incremental_energy(self, Psi: ufl.Form | None, rho=None, damping=None) -> ufl.Form:
        """The incremental potential of a step, whose derivative is the dynamic residual.

        ``Pi(u) = (c / 2) int rho |u - u_pred|^2 dx + Psi(u)``, where ``a = c (u - u_pred)`` is
        the step's acceleration (Newmark: ``c = 1 / (beta dt^2)``, ``u_pred = u_n + dt v_n +
        dt^2 (1/2 - beta) a_n``; backward Euler: ``c = 1 / dt^2``, ``u_pred = u_n + dt v_n``).
        Its derivative is ``rho * inner(acceleration, v) * dx + dPsi``; pass it as
        ``ContactProblem(..., energy=Pi)``, which adds the contact energy.

        Args:
            Psi: the static energy functional (strain energy minus the potential of conservative
                loads), a UFL form of ``u``; None for inertia alone.
            rho: density; default the integrator's.
            damping: the mass-proportional damping coefficient of ``inertia()``: adds
                ``int c rho |velocity|^2 / (2 s) dx``, ``s = d velocity / du`` (Newmark
                ``gamma / (beta dt)``, backward Euler ``1 / dt``), whose derivative is the
                viscous force.
        """
        rho = self._density(rho)
        dt = self._dt
        du = self.u - self._predictor(self.u_prev, self.v_prev, self.a_prev, dt)
        potential = 0.5 * self._coefficient(dt) * rho * ufl.inner(du, du) * self.dx
        if damping is not None:
            velocity = self.velocity
            slope = self._velocity_slope(dt)
            potential += 0.5 * damping * rho / slope * ufl.inner(velocity, velocity) * self.dx
        return potential if Psi is None else potential + Psi

    # -- state ----------------------------------------------------------------------------------

    def _new_acceleration(self, u_new: np.ndarray) -> np.ndarray:
        dt = self.dt
        pred = self._predictor(self.u_prev.x.array, self.v_prev.x.array, self.a_prev.x.array, dt)
        return self._coefficient(dt) * (u_new - pred)

    def predict(self) -> None:
        """Set ``u`` to the initial guess of the next step's Newton solve: the last state moved
        on with its velocity, ``u_n + dt v_n``.

        Extrapolating the acceleration too (``+ dt^2 a_n / 2``) would be exact in free fall, but
        after an impact the accelerations of the stiff, barely resolved contact modes are large
        and alternate in sign from step to step; on the colliding balls of the tests that guess
        took twice as many Newton iterations, and cuts.
        """
        self.u.x.array[:] = self.u_prev.x.array + self.dt * self.v_prev.x.array

    def restore(self) -> None:
        """Set ``u`` back to the last converged state (after a failed step)."""
        self.u.x.array[:] = self.u_prev.x.array

    def advance(self) -> None:
        """Accept ``u`` as the new step: compute its acceleration and velocity and make them,
        with ``u``, the last converged state (call after a converged solve)."""
        u_new = self.u.x.array
        a_new = self._new_acceleration(u_new)
        v_new = self._velocity(
            self.v_prev.x.array, self.a_prev.x.array, a_new, u_new, self.u_prev.x.array, self.dt
        )
        self.a_prev.x.array[:] = a_new
        self.v_prev.x.array[:] = v_new
        self.u_prev.x.array[:] = u_new
        self.t += self.dt

    def initial(
        self,
        u0=None,
        v0=None,
        a0=None,
        *,
        residual: ufl.Form | None = None,
        contact=None,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        t0: float = 0.0,
    ) -> None:
        """Set the initial state; ``u`` is set to ``u0`` too.

        Each of ``u0``, ``v0``, ``a0`` may be a Function on ``u``'s space, an array of its local
        size, a constant vector (one value per component), a callable (interpolated) or None
        (zero). The initial acceleration defaults to zero, which is consistent only if the body
        starts in equilibrium at rest; with ``residual=`` it is computed from the equation of
        motion instead: ``M a0 = -(f_int(u0) + f_contact(u0) - f_ext)``, solved with the
        consistent mass matrix of the integrator's ``rho`` (Dirichlet dofs keep ``a0 = 0``).
        Average-acceleration Newmark conserves energy only from a consistent ``a0``.

        Args:
            u0, v0, a0: initial displacement (L), velocity (L/T), acceleration (L/T^2).
            residual: the user's residual form, whose inertia term must be
                ``rho * inner(acceleration, v) * dx`` with the integrator's ``rho``.
            contact: the contact operator of ``u``, whose forces enter ``residual``'s problem.
            bcs: Dirichlet conditions of the problem.
            t0: initial time.
        """
        _set_array(self.u_prev, u0)
        _set_array(self.v_prev, v0)
        _set_array(self.a_prev, a0)
        self.u.x.array[:] = self.u_prev.x.array
        self.t = float(t0)
        if residual is not None:
            self.a_prev.x.array[:] = 0.0
            self.a_prev.x.array[:] = self._equilibrium_acceleration(residual, contact, bcs)
            self.a_prev.x.scatter_forward()

    def _equilibrium_acceleration(self, residual, contact, bcs) -> np.ndarray:
        """a0 = a(u0) - M^{-1} R(u0), R the dynamic residual at u = u0: R is affine in the
        acceleration term, R(u0) = M a(u0) + f(u0), so M a0 = -f(u0)."""
        V = self.u.function_space
        bcs = list(bcs)
        L = dolfinx.fem.form(residual)
        b = self.u.x.petsc_vec.duplicate()
        with b.localForm() as local:
            local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(b, L)
        if contact is not None:
            contact.update()
            contact.add_residual(b)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        for bc in bcs:
            dofs, n = bc.dof_indices()
            dofs = np.asarray(dofs[:n])
            b.array_w[dofs[dofs < n_owned]] = 0.0
        trial, test = ufl.TrialFunction(V), ufl.TestFunction(V)
        mass = dolfinx.fem.form(self._density() * ufl.inner(trial, test) * self.dx)
        M = dolfinx.fem.petsc.assemble_matrix(mass, bcs=bcs)
        M.assemble()
        ksp = PETSc.KSP().create(self._comm)
        ksp.setOperators(M)
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        x = b.duplicate()
        ksp.solve(b, x)
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with x.localForm() as x_local:
            correction = x_local.array_r.copy()
        a0 = self._new_acceleration(self.u.x.array) - correction
        for obj in (ksp, M, b, x):
            obj.destroy()
        return a0

    # -- bookkeeping ----------------------------------------------------------------------------

    def _scalar(self, key: str, make) -> float:
        if key not in self._forms:
            self._forms[key] = dolfinx.fem.form(make())
        return self._comm.allreduce(float(np.real(dolfinx.fem.assemble_scalar(self._forms[key]))))

    def kinetic_energy(self) -> float:
        """``int rho |v|^2 / 2 dx`` of the last converged state (collective; F L)."""
        return self._scalar(
            "kinetic", lambda: 0.5 * self._density() * ufl.inner(self.v_prev, self.v_prev) * self.dx
        )

    def trial_kinetic_energy(self) -> float:
        """``int rho |velocity(u)|^2 / 2 dx`` of the current ``u`` taken as the new step, before
        ``advance()`` (collective; F L)."""
        return self._scalar(
            "trial_kinetic",
            lambda: 0.5 * self._density() * ufl.inner(self.velocity, self.velocity) * self.dx,
        )

    def linear_momentum(self) -> np.ndarray:
        """``int rho v dx`` of the last converged state, (3,) (collective; mass L / T)."""
        rho = self._density()
        return np.array(
            [
                self._scalar(f"momentum{i}", lambda i=i: rho * self.v_prev[i] * self.dx)
                for i in range(3)
            ]
        )

    def angular_momentum(self, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
        """``int rho (x - origin) x v dx`` of the last converged state, x = X + u, (3,)
        (collective; mass L^2 / T)."""
        rho = self._density()
        x = ufl.SpatialCoordinate(self.u.function_space.mesh) + self.u_prev
        moment = ufl.cross(x, rho * self.v_prev)
        about = np.array(
            [self._scalar(f"angular{i}", lambda i=i: moment[i] * self.dx) for i in range(3)]
        )
        return about - np.cross(np.asarray(origin, dtype=float), self.linear_momentum())


class Newmark(_Integrator):
    """Newmark's method: ``u_{n+1} = u_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a_{n+1})``,
    ``v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1})``.

    Average acceleration (``beta = 1/4, gamma = 1/2``, the default) is second order and
    unconditionally stable and conserves the energy of a linear system; ``gamma > 1/2`` damps
    high frequencies (with ``beta = (gamma + 1/2)^2 / 4`` for the best dissipation), at first
    order.

    Args:
        u: the unknown displacement of the new step (any vector Function).
        dt: the time step (T).
        beta, gamma: Newmark's parameters (``beta > 0``: the method is implicit).
        rho: density (mass / L^3), needed for ``incremental_energy()``, ``inertia()``,
            the energies and momenta, and a consistent initial acceleration.
        dx: the integration measure of the inertia terms; default ``ufl.dx`` on u's mesh.

    Attributes:
        u_prev: the last converged displacement (Function); after ``advance()``, the new
            step's.
        v_prev: the last converged velocity (Function).
        a_prev: the last converged acceleration (Function).
    """

    def __init__(
        self,
        u: dolfinx.fem.Function,
        dt: float,
        beta: float = 0.25,
        gamma: float = 0.5,
        *,
        rho=None,
        dx: ufl.Measure | None = None,
    ):
        beta, gamma = float(beta), float(gamma)
        if not beta > 0.0:
            raise ValueError(f"Newmark needs beta > 0 (an implicit method), got beta={beta}")
        if gamma < 0.5:
            raise ValueError(
                f"Newmark with gamma={gamma} < 1/2 amplifies every mode (unstable); use gamma >= "
                "1/2"
            )
        self.beta, self.gamma = beta, gamma
        super().__init__(u, dt, rho=rho, dx=dx)

    def _coefficient(self, dt):
        return 1.0 / (self.beta * dt**2)

    def _predictor(self, u_prev, v_prev, a_prev, dt):
        return u_prev + dt * v_prev + (0.5 - self.beta) * dt**2 * a_prev

    def _velocity(self, v_prev, a_prev, a_new, u_new, u_prev, dt):
        return v_prev + dt * ((1.0 - self.gamma) * a_prev + self.gamma * a_new)

    def _velocity_slope(self, dt):
        return self.gamma / (self.beta * dt)


class BackwardEuler(_Integrator):
    """Backward (implicit) Euler on the first-order system: ``v_{n+1} = (u_{n+1} - u_n) / dt``,
    ``a_{n+1} = (v_{n+1} - v_n) / dt``.

    First order and strongly dissipative: it loses energy at every step (the more the larger
    ``omega dt``), which makes it robust for hard impacts and for bringing a scene to rest.

    Args:
        u: the unknown displacement of the new step (any vector Function).
        dt: the time step (T).
        rho: density (mass / L^3), see :class:`Newmark`.
        dx: the integration measure of the inertia terms; default ``ufl.dx`` on u's mesh.
    """

    def __init__(
        self,
        u: dolfinx.fem.Function,
        dt: float,
        *,
        rho=None,
        dx: ufl.Measure | None = None,
    ):
        super().__init__(u, dt, rho=rho, dx=dx)

    def _coefficient(self, dt):
        return 1.0 / dt**2

    def _predictor(self, u_prev, v_prev, a_prev, dt):
        return u_prev + dt * v_prev

    def _velocity(self, v_prev, a_prev, a_new, u_new, u_prev, dt):
        return (u_new - u_prev) / dt

    def _velocity_slope(self, dt):
        return 1.0 / dt


# -- the time-step loop ---------------------------------------------------------------------------


@dataclasses.dataclass
class TimeStep:
    """One converged time step of :func:`solve_time_steps` (or the initial state, step 0).

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


class _Solvable(typing.Protocol):
    u: dolfinx.fem.Function

    def solve(self, raise_on_failure: bool = True) -> SolveResult: ...


def _form_value(form, comm, missing: float = 0.0) -> float:
    if form is None:
        return missing
    return comm.allreduce(float(np.real(dolfinx.fem.assemble_scalar(form))))


def _record(step, t, dt, result, cuts, problem, integrator, forms, seconds, comm) -> TimeStep:
    contact = getattr(problem, "contact", None)
    diag = contact.diagnostics() if contact is not None else {}

    kinetic = integrator.kinetic_energy() if integrator.rho is not None else np.nan
    return TimeStep(
        step=step, t=t, dt=dt, iterations=result.iterations,
        residual_norms=result.residual_norms, cuts=cuts, diagnostics=diag,
        kinetic_energy=kinetic, strain_energy=_form_value(forms["strain"], comm, np.nan),
        contact_energy=diag.get("energy", 0.0), external_work=_form_value(forms["external"], comm),
        seconds=seconds,
    )  # fmt: skip


def solve_time_steps(
    problem: _Solvable,
    integrator: _Integrator,
    t_end: float,
    dt: float,
    writer=None,
    on_step: typing.Callable[[TimeStep], None] | None = None,
    min_dt: float | None = None,
    max_dt: float | None = None,
    *,
    set_time: typing.Callable[[float], None] | None = None,
    strain_energy: ufl.Form | None = None,
    external_work: ufl.Form | None = None,
    max_penetration: float | None = None,
    max_energy_change: float | None = None,
    grow_after: int = 2,
    predict: bool = True,
    progress: bool = True,
) -> list[TimeStep]:
    """Integrate ``problem`` in time from the integrator's state to ``t_end`` with step control.

    Each step sets the integrator's dt (and calls ``set_time(t_next)`` for time-dependent
    loads), starts Newton from the integrator's prediction, and solves. A step that fails (no
    convergence, NaN, an inverted element raising) or, with ``max_penetration``, converges with a
    deeper penetration than that, is retried from the last converged state with half the step;
    after ``grow_after`` successive steps without a cut, the step doubles again, up to
    ``max_dt``. The last step is shortened to land on ``t_end``.

    Args:
        problem: a :class:`~fenics_matdepth.ContactProblem` or
            :class:`~fenics_matdepth.NonlinearContactProblem` whose residual contains the
            integrator's inertia term (anything with ``u``, ``solve(raise_on_failure=...)`` and,
            optionally, ``contact``).
        integrator: the :class:`Newmark` or :class:`BackwardEuler` of ``problem.u``, holding the
            initial state (see ``initial``); its ``t`` is the start time.
        t_end: final time (T).
        dt: first (and nominal) time step (T).
        writer: called with each converged state: a ``dolfinx.io.XDMFFile``
            (``write_function(u, t)``), a ``dolfinx.io.VTXWriter`` (``write(t)``; give it ``u``,
            ``integrator.v_prev`` and the material depth), or any callable ``writer(t)``.
        on_step: called with each converged step's record, after ``integrator.advance()``.
        min_dt: smallest step tried before giving up; default ``dt / 2**10``.
        max_dt: largest step the controller grows to; default ``dt``.
        set_time: sets time-dependent data for a time t (collective).
        strain_energy: UFL form of the stored (strain) energy, reported per step.
        external_work: UFL form of the work of conservative loads (e.g. ``int rho g . u dx``),
            reported per step and subtracted in ``TimeStep.total_energy``.
        max_penetration: reject converged steps whose contact penetration exceeds this (L);
            at ``min_dt`` the step is accepted anyway.
        max_energy_change: reject converged steps that change the total energy (kinetic +
            strain + contact - external work) by more than this (F L); at ``min_dt`` the step
            is accepted anyway. An error control for energy-conserving schemes (average
            acceleration): where a step does not resolve an impact, it loses or gains energy.
            Needs the integrator's ``rho`` and ``strain_energy``.
        grow_after: successful steps before dt doubles.
        predict: start each Newton solve from ``integrator.predict()`` (else from the last
            state).
        progress: report each converged step on rank 0: a progress bar in a terminal or a
            notebook, one printed line otherwise (``MATDEPTH_PROGRESS=lines`` forces lines).

    Returns:
        The initial state (step 0) and every converged step, in time order.

    Raises:
        RuntimeError: if dt falls below ``min_dt`` on failures; ``u`` and the integrator then
            hold the last converged state, whose time the message gives.
    """
    u = problem.u
    if integrator.u is not u:
        raise ValueError("the integrator must be built on the problem's unknown (problem.u)")
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive number, got {dt}")
    if max_energy_change is not None and (strain_energy is None or integrator.rho is None):
        raise ValueError("max_energy_change needs strain_energy= and the integrator's rho")
    if grow_after < 1:
        raise ValueError(f"grow_after must be >= 1, got {grow_after}")
    comm = u.function_space.mesh.comm
    max_dt = float(dt) if max_dt is None else float(max_dt)
    min_dt = float(dt) / 2**10 if min_dt is None else float(min_dt)
    if not 0.0 < min_dt <= max_dt:
        raise ValueError(f"need 0 < min_dt <= max_dt, got min_dt={min_dt}, max_dt={max_dt}")
    forms = {
        "strain": dolfinx.fem.form(strain_energy) if strain_energy is not None else None,
        "external": dolfinx.fem.form(external_work) if external_work is not None else None,
    }
    t = integrator.t
    tol = 1e-12 * max(abs(t_end), max_dt)
    u.x.array[:] = integrator.u_prev.x.array
    contact = getattr(problem, "contact", None)
    if contact is not None:
        contact.update()
    if set_time is not None:
        set_time(t)
    initial = SolveResult(True, 0, 0, np.zeros(0))
    history = [_record(0, t, 0.0, initial, 0, problem, integrator, forms, 0.0, comm)]
    step_dt, successes = min(float(dt), max_dt), 0
    reporter = StepProgress(comm, t, t_end, "t", enabled=progress)
    reporter.message(_step_line(history[-1]))
    try:
        while t_end - t > tol:
            cuts, tic = 0, time.perf_counter()
            while True:
                this_dt = min(step_dt, t_end - t)
                if t_end - (t + this_dt) < tol:
                    this_dt = t_end - t
                integrator.dt = this_dt
                if set_time is not None:
                    set_time(t + this_dt)
                if predict:
                    integrator.predict()
                else:
                    integrator.restore()
                failure = None
                try:
                    result = problem.solve(raise_on_failure=False)
                    if not result.converged:
                        failure = result.failure_message()
                    elif this_dt / 2 >= min_dt:
                        failure = _rejection(
                            contact, integrator, forms, comm, history[-1], max_penetration,
                            max_energy_change,
                        )  # fmt: skip
                except (RuntimeError, FloatingPointError, PETSc.Error) as err:
                    failure = str(err)
                if not comm.allreduce(failure is not None, op=MPI.LOR):
                    break
                cuts += 1
                successes = 0
                integrator.restore()
                reason = (failure or "failed on another rank").split(";")[0]
                reporter.message(f"      t {t:.5g}: dt {this_dt:.3g} rejected ({reason[:90]})")
                if this_dt / 2 < min_dt:
                    integrator.dt = max(this_dt, min_dt)
                    if set_time is not None:
                        set_time(t)
                    raise RuntimeError(
                        f"time stepping stopped at t = {t:.6g}: the step to {t + this_dt:.6g} "
                        f"failed with dt = {this_dt:.3g} (min_dt {min_dt:.3g}). Last failure: "
                        f"{failure}"
                    )
                step_dt = this_dt / 2
            integrator.advance()
            t = integrator.t
            record = _record(
                len(history), t, this_dt, result, cuts, problem, integrator, forms,
                time.perf_counter() - tic, comm,
            )  # fmt: skip
            history.append(record)
            _write(writer, u, t)
            if on_step is not None:
                on_step(record)
            reporter.step(t, _step_line(record))
            if cuts == 0:
                successes += 1
                if successes >= grow_after and step_dt < max_dt:
                    step_dt, successes = min(2.0 * step_dt, max_dt), 0
    finally:
        reporter.close()
    return history


def _rejection(contact, integrator, forms, comm, last, max_penetration, max_energy_change):
    """Why a converged step is rejected by the step controller, or None."""
    if max_penetration is not None and contact is not None:
        depth = contact.max_penetration()
        if depth > max_penetration:
            return f"penetration {depth:.3e} > max_penetration {max_penetration:.3e}"
    if max_energy_change is not None:
        energy = (
            integrator.trial_kinetic_energy()
            + _form_value(forms["strain"], comm)
            + (contact.energy() if contact is not None else 0.0)
            - _form_value(forms["external"], comm)
        )
        change = energy - last.total_energy
        if abs(change) > max_energy_change:
            return f"energy change {change:.3e} beyond max_energy_change {max_energy_change:.3e}"
    return None


def _step_line(r: TimeStep) -> str:
    """The one-line report of a converged time step."""
    return (
        f"step {r.step:4d}  t {r.t:.5g}  dt {r.dt:.3g}  newton {r.iterations:2d}  cuts {r.cuts}  "
        f"pairs {r.active_pairs:5d}  max pen {r.max_penetration:.2e}  "
        f"E kin {r.kinetic_energy:.4e}  strain {r.strain_energy:.4e}  "
        f"contact {r.contact_energy:.3e}  total {r.total_energy:.6e}  {r.seconds:.2f} s"
    )
