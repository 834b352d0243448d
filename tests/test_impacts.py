"""Impacts in implicit dynamics: the midpoint contact force of a Newmark step (its derivatives,
momentum, the energy it keeps where the end-of-step force creates energy) and backward Euler,
which never gains."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import assert_operator_derivatives, neo_hookean_residual, operator_residual

import fenics_matdepth as fm
from fenics_matdepth.impacts import MidpointContact, impact_failure_cause
from fenics_matdepth.results import SolveResult

E, NU, RHO = 100.0, 0.3, 1.0


def _two_cubes(comm, cells: int, gap: float = 0.1, offset: float = 0.0) -> dolfinx.mesh.Mesh:
    """Two unit cubes ``gap`` apart along x, the right one shifted by ``offset`` along y."""
    xa, ca = fm.meshing.box_tetrahedra(cells, origin=(-1.0 - gap / 2, 0.0, 0.0))
    xb, cb = fm.meshing.box_tetrahedra(cells, origin=(gap / 2, offset, 0.0))
    return fm.meshing.create_tetrahedral_mesh(
        comm, np.vstack([ca, cb + xa.shape[0]]), np.vstack([xa, xb])
    )


class _Cubes:
    """Two neo-Hookean cubes flying at each other at ``speed`` each, no gravity, no supports,
    set up as the docs show (the integrator's incremental potential as the energy)."""

    def __init__(self, cells, offset, speed, make_integrator, energy=True, damping=None):
        comm = MPI.COMM_WORLD
        mesh = _two_cubes(comm, cells, offset=offset)
        V = self.V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        u = self.u = dolfinx.fem.Function(V)
        v = ufl.TestFunction(V)
        elastic, psi = neo_hookean_residual(u, E, NU)
        self.strain_energy = psi * ufl.dx
        self.contact = fm.ContactOperator(
            u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E)
        )
        self.integrator = make_integrator(u)
        residual = self.integrator.inertia(v, damping=damping) + elastic
        v0 = dolfinx.fem.Function(V)
        v0.interpolate(lambda x: np.vstack((-speed * np.sign(x[0]), 0 * x[0], 0 * x[0])))
        self.integrator.initial(None, v0, residual=residual, contact=self.contact)
        self.problem = fm.ContactProblem(
            residual, u, self.contact,
            energy=self.integrator.incremental_energy(self.strain_energy) if energy else None,
            petsc_options_prefix="impacts_",
        )  # fmt: skip
        self.one_body = RHO * speed  # a unit cube's momentum

    def run(self, t_end, dt, **kwargs):
        p0 = self.integrator.linear_momentum()
        history = fm.solve_time_steps(
            self.problem, self.integrator, t_end, dt, strain_energy=self.strain_energy,
            progress=False, **kwargs,
        )  # fmt: skip
        drift = np.abs(self.integrator.linear_momentum() - p0).max() / self.one_body
        energy = np.array([r.total_energy for r in history])
        return history, energy / energy[0], drift


def test_midpoint_contact_derivatives_and_value():
    """The midpoint contact term's energy, residual and Jacobian agree by central differences,
    the residual is ``2 dW/du (m) - f_n`` (the operator's gradient at the midpoint, computed
    apart) and sums to zero over each component (linear momentum) when ``f_n`` does."""
    comm = MPI.COMM_WORLD
    # offset, and moved along z below: faces in general position (aligned grids make the
    # intersection polygons degenerate, where W has kinks a finite difference steps across)
    mesh = _two_cubes(comm, 2, offset=0.13)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    op = fm.ContactOperator(u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E))
    integrator = fm.Newmark(u, 0.01, rho=RHO)
    # the right cube moves left: by 0.05 at u_n, by 0.25 at u (midpoint 0.15: overlap 0.05)
    x = V.tabulate_dof_coordinates()
    right = (x[:, 0] > 0.0).astype(float)
    shape = np.cos(1.7 * x[:, 1] + 0.3 * x[:, 2])  # not a rigid motion
    prev, new = np.zeros((x.shape[0], 3)), np.zeros((x.shape[0], 3))
    prev[:, 0] = -0.05 * right
    new[:, 0] = -0.25 * right + 0.01 * shape
    new[:, 1] = 0.02 * shape * right
    prev[:, 2] = new[:, 2] = 0.07 * right
    integrator.initial(prev.ravel())
    mc = MidpointContact(op, integrator)
    # a carried force whose components sum to zero (an internal force)
    mc.force.setArray(np.tile([1.0, -2.0, 0.5], mc.force.getLocalSize() // 3) * 1e-2)
    rows = mc.force.getLocalSize() // 3
    sums = comm.allreduce(mc.force.getArray().reshape(rows, 3).sum(axis=0))
    start = mc.force.getArray().reshape(rows, 3)
    start[...] -= sums / comm.allreduce(rows)
    mc.force.setArray(start.ravel())
    u.x.array[:] = new.ravel()
    mc.update()
    assert op.energy() > 0.0  # the midpoint overlaps
    assert_operator_derivatives(mc, u, h=1e-6, rtol=1e-6)

    residual = operator_residual(mc, V)
    total = residual.getArray().reshape(-1, 3).sum(axis=0)
    scale = np.abs(residual.getArray()).max()
    assert np.abs(comm.allreduce(total)).max() <= 1e-12 * comm.allreduce(scale, op=MPI.MAX)
    u.x.array[:] = 0.5 * (prev.ravel() + new.ravel())
    op.update()
    expected = operator_residual(op, V)
    expected.scale(2.0)
    expected.axpy(-1.0, mc.force)
    expected.axpy(-1.0, residual)
    assert expected.norm() <= 1e-12 * residual.norm()
    mc.destroy()


def test_newmark_cubes_impact_keeps_energy_with_the_midpoint_force():
    """Two cubes meet corner-on (offset sideways by 0.1): with average-acceleration Newmark's
    midpoint contact force (``contact_force="midpoint"``) the total energy stays within 5 % of
    its start at every step (3.0 % measured on this coarse mesh, 1.5 % at 5^3 cuboids per
    cube; the end-of-step force fails the impact step here, and gains 2.4 times the energy at
    5^3) and ends within 1 %; linear momentum stays to round-off."""
    cubes = _Cubes(3, 0.1, 0.5, lambda u: fm.Newmark(u, 0.01, rho=RHO))
    history, energy, drift = cubes.run(0.4, 0.01, contact_force="midpoint")
    assert max(r.active_pairs for r in history) > 0  # they met
    assert history[-1].active_pairs == 0  # and separated
    assert drift <= 1e-12, drift
    assert energy.max() < 1.05, energy.max()
    assert abs(energy[-1] - 1.0) < 0.01, energy[-1]
    cubes.problem.destroy()


def test_newmark_face_on_impact_gains_no_energy():
    """Two cubes meet face-on, closing half an element per step: the end-of-step contact force
    gains more than 20 % of the energy, the midpoint force none (it loses a few per cent to
    the midpoint rule's error); linear momentum stays to round-off either way."""
    runs = {}
    for scheme in ("endpoint", "midpoint"):
        cubes = _Cubes(3, 0.0, 1.0, lambda u: fm.Newmark(u, 0.05, rho=RHO))
        history, energy, drift = cubes.run(0.6, 0.05, contact_force=scheme)
        assert max(r.active_pairs for r in history) > 0
        assert drift <= 1e-12, drift
        runs[scheme] = energy
        cubes.problem.destroy()
    assert runs["endpoint"].max() > 1.2, runs["endpoint"].max()
    assert runs["midpoint"].max() <= 1.0 + 1e-3, runs["midpoint"].max()
    assert runs["midpoint"][-1] > 0.9, runs["midpoint"][-1]


def test_backward_euler_impact_never_gains():
    """Backward Euler (end-of-step contact force, the default for it) through a face-on
    impact: the total energy never rises above the last step's, momentum to round-off."""
    cubes = _Cubes(3, 0.0, 1.0, lambda u: fm.BackwardEuler(u, 0.05, rho=RHO))
    history, energy, drift = cubes.run(0.6, 0.05)
    assert max(r.active_pairs for r in history) > 0
    assert drift <= 1e-12, drift
    assert np.all(np.diff(energy) <= 1e-12), np.diff(energy)
    assert energy[-1] < 0.9
    cubes.problem.destroy()


def test_midpoint_contact_force_needs_average_acceleration():
    """The midpoint force is offered for average-acceleration Newmark only, with a clear
    error otherwise."""
    cubes = _Cubes(1, 0.0, 1.0, lambda u: fm.BackwardEuler(u, 0.1, rho=RHO))
    with pytest.raises(ValueError, match="average-acceleration Newmark"):
        cubes.run(0.1, 0.1, contact_force="midpoint")
    with pytest.raises(ValueError, match="contact_force must be one of"):
        cubes.run(0.1, 0.1, contact_force="middle")
    cubes.problem.destroy()


def test_midpoint_contact_force_refuses_friction():
    """The midpoint force evaluates the penalty at the step's midpoint; friction's lagged
    terms are not part of it, so an operator with friction is refused by name, not dropped."""
    mesh = _two_cubes(MPI.COMM_WORLD, 1, offset=0.13)
    u = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,))))
    penalty = fm.propose_penalty(mesh, E)
    op = fm.ContactOperator(u, fm.material_depth(mesh), penalty=penalty, friction=fm.Coulomb(0.3))
    with pytest.raises(ValueError, match="does not carry friction"):
        MidpointContact(op, fm.Newmark(u, 0.01, rho=RHO))


def test_failed_step_names_a_stalled_residual():
    """A step given up on with a residual stuck at its round-off floor says so, with the
    remedy; a converging history without contact names nothing."""
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 1, 1, 1, dolfinx.mesh.CellType.tetrahedron)
    u = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,))))
    integrator = fm.Newmark(u, 1e-5, rho=RHO)
    stalled = SolveResult(False, -6, 3, np.array([1e-8, 7.5e-9, 7.5e-9, 7.5e-9]))
    cause = impact_failure_cause(None, integrator, "midpoint", stalled)
    assert "stalled at 7.5e-09" in cause and "snes_atol" in cause, cause
    converging = SolveResult(False, -6, 3, np.array([1.0, 1e-3, 1e-7]))
    assert impact_failure_cause(None, integrator, "midpoint", converging) == ""


def test_time_steps_hand_the_problem_its_incremental_potential():
    """A problem built without ``energy=`` gets the integrator's incremental potential (its
    energy line search on) when that potential's derivative is its residual, and keeps its
    residual line search when the residual has a term the potential lacks (damping); the
    run through the face-on impact (midpoint force) converges at every step either way."""
    for damping in (None, 0.5):
        cubes = _Cubes(2, 0.0, 1.0, lambda u: fm.Newmark(u, 0.05, rho=RHO), energy=False,
                       damping=damping)  # fmt: skip
        assert cubes.problem.assembler.energy_form is None
        history, _, drift = cubes.run(0.3, 0.05, contact_force="midpoint")
        assert (cubes.problem.assembler.energy_form is not None) == (damping is None)
        assert max(r.active_pairs for r in history) > 0 and sum(r.cuts for r in history) == 0
        assert drift <= 1e-12, drift
        cubes.problem.destroy()


def test_midpoint_contact_force_with_the_dolfinx_newton_solver():
    """The midpoint force reaches ``NonlinearContactProblem`` (DOLFINx's NewtonSolver) through
    its assembler alike: the face-on impact gains no energy, momentum to round-off."""
    cubes = _Cubes(2, 0.0, 1.0, lambda u: fm.Newmark(u, 0.05, rho=RHO))
    cubes.problem.destroy()
    v = ufl.TestFunction(cubes.V)
    elastic, _ = neo_hookean_residual(cubes.u, E, NU)
    cubes.problem = fm.NonlinearContactProblem(
        cubes.integrator.inertia(v) + elastic, cubes.u, cubes.contact
    )
    history, energy, drift = cubes.run(0.6, 0.05, contact_force="midpoint")
    assert max(r.active_pairs for r in history) > 0
    assert drift <= 1e-12, drift
    assert energy.max() <= 1.0 + 1e-3, energy.max()
    cubes.problem.destroy()
