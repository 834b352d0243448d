"""The discrete gradient of the contact energy over a time step
(``solve_time_steps(contact_force="discrete_gradient")``): per pair and assembled, its work
equals the change of the contact energy to round-off, it moves no momentum, its Jacobian
matches finite differences; through impacts the total energy does not rise."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import assert_fd_derivatives, operator_residual
from test_impacts import _Cubes, _two_cubes

import fenics_matdepth as fm
from fenics_matdepth.contact.kernels import pair_energy
from fenics_matdepth.contact.kernels.discrete_gradient import (
    discrete_gradient_jacobians,
    discrete_gradients,
)
from fenics_matdepth.impacts import DiscreteGradientContact

pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

E, NU, RHO = 100.0, 0.3, 1.0
EPS = 50.0

# a tetrahedron with depths, and a triangle in general position across it
X_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
D_TET = np.array([0.05, 0.3, 0.2, 0.4])
X_TRI = np.array([[-0.2, -0.1, 0.2], [0.9, 0.05, 0.23], [0.1, 0.8, 0.18]])
# a non-rigid step of the pair (triangle first, then the tetrahedron)
STEP = 0.04 * np.cos(np.arange(21) * np.array([1.3]) + 0.4).reshape(7, 3)


def _pair(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    x = x.reshape(7, 3)
    return pair_energy(x[:3], x[3:], D_TET, EPS)


def _discrete_gradient(x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(DG (21,), its Jacobian (21, 21) with respect to x1) of the pair over a step."""
    e0, _, _ = _pair(x0)
    e1, g1, _ = _pair(x1)
    _, gm, hm = _pair(0.5 * (x0 + x1))
    verts = np.arange(7).reshape(1, 7)
    dg, coef, jac = np.empty((1, 21)), np.empty(1), np.empty((1, 21, 21))
    x0, x1 = x0.reshape(7, 3), x1.reshape(7, 3)
    discrete_gradients(x0, x1, verts, np.array([e0]), np.array([e1]), gm[None], dg, coef)
    discrete_gradient_jacobians(x0, x1, verts, gm[None], g1[None], hm[None], coef, jac)
    return dg[0], jac[0]


@pytest.mark.parametrize("start", ["in contact", "apart"])
def test_pair_discrete_gradient_work_momentum_and_jacobian(start):
    """One pair over a step: ``DG . dU = W(x1) - W(x0)`` to round-off, ``DG`` sums to zero
    per component (no momentum) and has no moment about the midpoint configuration (no
    angular momentum), and its Jacobian with respect to ``x1`` matches 4th-order
    finite differences (rtol 1e-5), for a pair in contact at both ends and for one apart at
    the start (``W(x0) = 0``: the contact begins within the step)."""
    x1 = np.vstack((X_TRI, X_TET)).ravel() + STEP.ravel()
    x0 = np.vstack((X_TRI, X_TET)).ravel()
    if start == "apart":  # the triangle above the tetrahedron at the start
        x0[:9] += np.tile([0.0, 0.0, 0.9], 3)
    e0, e1 = _pair(x0)[0], _pair(x1)[0]
    assert e1 > 0.0 and (e0 == 0.0) == (start == "apart")
    dg, jac = _discrete_gradient(x0, x1)
    assert abs(dg @ (x1 - x0) - (e1 - e0)) <= 1e-13 * abs(e1 - e0) + 1e-16
    assert np.abs(dg.reshape(7, 3).sum(axis=0)).max() <= 1e-13 * np.abs(dg).max()
    # no moment about the midpoint configuration (angular momentum under the trapezoidal
    # rule), though the step turns the pair: the step less its mean has a moment of the
    # order of the step itself, so a correction along it would turn the pair
    m = 0.5 * (x0 + x1).reshape(7, 3)
    r = m - m.mean(axis=0)
    du = (x1 - x0).reshape(7, 3)
    assert np.linalg.norm(np.cross(r, du - du.mean(axis=0)).sum(axis=0)) > 1e-3
    torque = np.cross(m, dg.reshape(7, 3)).sum(axis=0)
    assert np.abs(torque).max() <= 1e-12 * np.abs(dg).max(), torque
    # the midpoint gradient alone does not have the exact work here
    gm = _pair(0.5 * (x0 + x1))[1]
    assert abs(gm @ (x1 - x0) - (e1 - e0)) > 1e-6 * abs(e1 - e0)

    def at(x):
        e, _, _ = _pair(x)
        return e, _discrete_gradient(x0, x)[0]

    assert_fd_derivatives(at, x1, rtol=1e-5, exact=(_pair(x1)[1], jac))


def _moved_cubes(comm=MPI.COMM_WORLD):
    """Two cubes, the right one moved left by 0.05 at u_n and by 0.25 (with a non-rigid
    part) at u: the contact starts within the step (as in test_impacts)."""
    mesh = _two_cubes(comm, 2, offset=0.13)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    op = fm.ContactOperator(u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E))
    x = V.tabulate_dof_coordinates()
    right = (x[:, 0] > 0.0).astype(float)
    shape = np.cos(1.7 * x[:, 1] + 0.3 * x[:, 2])
    prev, new = np.zeros((x.shape[0], 3)), np.zeros((x.shape[0], 3))
    prev[:, 0] = -0.05 * right
    new[:, 0] = -0.25 * right + 0.01 * shape
    new[:, 1] = 0.02 * shape * right
    prev[:, 2] = new[:, 2] = 0.07 * right
    return V, u, op, prev.ravel(), new.ravel()


def _step_term(method: str, comm=MPI.COMM_WORLD):
    """The contact term of the step of `_moved_cubes` with ``f_n = 0``; returns (V, u, the
    term, u_n, u, W(u_n), W(u), its residual scale: 2 Newmark, 1 backward Euler)."""
    V, u, op, prev, new = _moved_cubes(comm)
    if method == "newmark":
        integrator, scale = fm.Newmark(u, 0.01, rho=RHO), 2.0
    else:
        integrator, scale = fm.BackwardEuler(u, 0.01, rho=RHO), 1.0
    integrator.initial(prev)
    term = DiscreteGradientContact(op, integrator)
    term.force.zeroEntries()
    u.x.array[:] = prev
    op.update()
    w0 = op.energy()
    u.x.array[:] = new
    op.update()
    w1 = op.energy()
    term.update()
    return V, u, term, prev, new, w0, w1, scale


@pytest.mark.parametrize("method", ["newmark", "backward_euler"])
def test_discrete_gradient_contact_assembled(method):
    """The assembled contact term of a step (serial or distributed): with ``f_n = 0`` its
    residual is ``2 DG`` (Newmark) or ``DG`` (backward Euler); ``DG . (u - u_n)`` equals the
    operator's ``W(u) - W(u_n)`` to 1e-12, it sums to zero per component, and the Jacobian
    times a smooth direction matches central differences of the residual (rtol 1e-6). On
    2 ranks, the residual's norm, its work and the merit equal those of a serial copy on
    each rank (1e-12)."""
    comm = MPI.COMM_WORLD
    V, u, dg, prev, new, w0, w1, scale = _step_term(method)
    assert w0 == 0.0 and w1 > 0.0  # the contact starts within the step
    residual = operator_residual(dg, V)
    step = dolfinx.fem.Function(V)
    step.x.array[:] = new - prev
    work = residual.dot(step.x.petsc_vec) / scale
    assert abs(work - (w1 - w0)) <= 1e-12 * w1, (work, w1 - w0)
    rows = residual.getLocalSize() // 3
    total = comm.allreduce(residual.getArray().reshape(rows, 3).sum(axis=0))
    biggest = comm.allreduce(np.abs(residual.getArray()).max(initial=0.0), op=MPI.MAX)
    assert np.abs(total).max() <= 1e-12 * biggest
    if comm.size > 1:
        Vs, _, serial, prev_s, new_s, _, _, _ = _step_term(method, MPI.COMM_SELF)
        rs = operator_residual(serial, Vs)
        step_s = dolfinx.fem.Function(Vs)
        step_s.x.array[:] = new_s - prev_s
        assert abs(rs.norm() - residual.norm()) <= 1e-12 * rs.norm()
        assert abs(rs.dot(step_s.x.petsc_vec) / scale - work) <= 1e-12 * w1
        assert abs(serial.energy() - dg.energy()) <= 1e-12 * abs(serial.energy())
        serial.destroy()

    # Jacobian against central differences of the residual along a smooth direction
    x = V.tabulate_dof_coordinates()
    v = dolfinx.fem.Function(V)
    v.x.array[:] = 1e-2 * np.cos(np.array([1.3, 2.9, 0.7]) * x[:, [1, 2, 0]] + 0.2).ravel()
    h = 1e-5
    sides = []
    for t in (h, -h):
        u.x.array[:] = new + t * v.x.array
        dg.update()
        sides.append(operator_residual(dg, V))
    u.x.array[:] = new
    dg.update()
    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = dg.create_matrix(a)
    A.zeroEntries()
    dg.add_jacobian(A)
    assert dg.left_out == 0
    Jv = A.createVecLeft()
    A.mult(v.x.petsc_vec, Jv)
    fd = sides[0].copy()
    fd.axpy(-1.0, sides[1])
    fd.scale(1.0 / (2 * h))
    fd.axpy(-1.0, Jv)
    assert fd.norm() <= 1e-6 * Jv.norm(), fd.norm() / Jv.norm()
    A.destroy()
    dg.destroy()


@pytest.mark.parametrize("model", ["cubes"])
def test_newmark_impacts_gain_no_energy_with_the_discrete_gradient(model):
    """The corner-on impact of the issue on coarse cubes (3^3 cuboids, offset 0.1, 0.5 each,
    dt = 0.01): with the discrete gradient the total energy never exceeds its start by more
    than 0.1 % (the midpoint force: 3 %), and linear momentum stays to round-off.

    (The face-on blocks, 1 each, dt = 0.05, are not here: their steps in contact take 48 to
    60 Newton iterations, on 2 ranks the path of cuts differs from run to run, and on some
    paths the bulk's trapezoidal error raises the total energy by 1.4e-2 after the blocks
    separate — measured 1.0136 of the start — with no contact pair active. The contact's own
    part is exact there too; ``test_max_energy_gain_retries_only_the_steps_that_gain`` runs
    the blocks with the bound that removes the bulk's gain.)"""
    offset, speed, dt, t_end = {"cubes": (0.1, 0.5, 0.01, 0.4)}[model]
    cubes = _Cubes(3, offset, speed, lambda u: fm.Newmark(u, dt, rho=RHO))
    history, energy, drift = cubes.run(t_end, dt, contact_force="discrete_gradient")
    assert max(r.active_pairs for r in history) > 0  # they met
    assert drift <= 1e-12, drift
    assert energy.max() <= 1.001, energy.max()
    cubes.problem.destroy()


def test_max_energy_gain_retries_only_the_steps_that_gain():
    """The coarse blocks face-on with the discrete gradient (1 each, dt = 0.05): without a
    bound the bulk's trapezoidal error raises the total energy by 1.4e-2 of the start in a
    step after they separate (t = 0.525) and loses 1.75e-2 in the first contact step. With
    ``max_energy_gain`` at 1e-3 of the start no accepted step above ``min_dt`` rises by more
    than that (5.7e-4 measured, 8 cuts), while a loss larger than the bound stays (a
    one-sided bound: ``max_energy_change`` would retry it too)."""
    dt, bound = 0.05, 1e-3
    cubes = _Cubes(3, 0.0, 1.0, lambda u: fm.Newmark(u, dt, rho=RHO))
    history, energy, drift = cubes.run(
        0.6, dt, contact_force="discrete_gradient",
        max_energy_gain=bound * cubes.integrator.kinetic_energy(),
    )  # fmt: skip
    assert max(r.active_pairs for r in history) > 0
    # momentum to round-off and the Newton tolerance (a step's residual is converged to 1e-10
    # of its first, not to zero): 1e-15 of a body's momentum on most paths, 4.95e-12 on one
    # 2-rank path (the retries make the path, which on 2 ranks differs between runs), where a
    # bound of 1e-12 failed; a force that moved momentum would leave an error of the order of
    # the momentum the blocks exchange
    assert drift <= 1e-10, drift
    above_min = np.array([r.dt > dt / 2**10 for r in history[1:]])
    change = np.diff(energy)
    assert change[above_min].max() <= bound, change.max()
    # a loss larger than the bound was accepted, not retried (one-sided); how large depends on
    # the path of cuts, which on 2 ranks differs between runs (-1.75e-2 serially, -6.9e-3 seen)
    assert change.min() < -bound, change.min()
    assert sum(r.cuts for r in history) > 0
    cubes.problem.destroy()


def test_backward_euler_discrete_gradient_never_gains():
    """Backward Euler with the discrete gradient through the face-on impact: the total energy
    never rises from one step to the next (to 1e-12 of the start)."""
    cubes = _Cubes(3, 0.0, 1.0, lambda u: fm.BackwardEuler(u, 0.05, rho=RHO))
    history, energy, drift = cubes.run(0.6, 0.05, contact_force="discrete_gradient")
    assert max(r.active_pairs for r in history) > 0
    assert drift <= 1e-12, drift
    assert np.all(np.diff(energy) <= 1e-12), np.diff(energy).max()
    cubes.problem.destroy()
