"""Implicit dynamics: Newmark and backward Euler time integration (the time-step loop,
:func:`~fenics_matdepth.solve_time_steps`, is in :mod:`fenics_matdepth.stepping`).

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
That is the contact force of backward Euler's steps; with average-acceleration Newmark,
:func:`~fenics_matdepth.solve_time_steps` takes it at the step's midpoint instead
(:mod:`fenics_matdepth.impacts`: the end-of-step force creates energy at impacts), which keeps
this structure with ``4 E_contact((u_n + u) / 2) - f_n . u`` in place of ``E_contact(u)``.

Generalized-alpha is not offered: it evaluates the internal forces at an intermediate
configuration ``u_{n+1-alpha_f}``, and a consistent scheme would need the contact operator
there too (its residual and Jacobian at a blended displacement); the contact operator works on
``u`` itself. Numerical damping comes from Newmark with ``gamma > 1/2`` or backward Euler.
"""

from __future__ import annotations

import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

__all__ = ["BackwardEuler", "Newmark"]


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
        #: The density (mass / L^3), given as a number, a Constant, a DG0 Function or any UFL
        #: expression.
        self.rho = rho
        self.dx = dx if dx is not None else ufl.dx(domain=mesh)
        #: time of the last converged state (set by :func:`~fenics_matdepth.solve_time_steps`)
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
