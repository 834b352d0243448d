"""Bodies held only by contact (fenics_matdepth.free_bodies): found from the Dirichlet
conditions, damped while contact engages, the undamped problem solved at the end, and named
when contact can never hold them. Serial and on 2 ranks."""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import merged_mesh, neo_hookean

import fenics_matdepth as fm
from fenics_matdepth.free_bodies import find_free_bodies
from fenics_matdepth.meshing import box_tetrahedra

# the cube's eight cuboids have every vertex on its boundary (the operator splits them)
pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

PENALTY = 100.0
TRACTION = 0.02  # on the upper cube's top face (pressure; E = 1)
GAP = 0.05  # between the block and the cube (about a ninth of the mean boundary edge)


def _two_cubes(comm):
    """A block [0, 1]^3 (3^3 cuboids) and a cube [0, 1]^2 x [1 + GAP, 2 + GAP] (2^3 cuboids)
    above it."""
    return merged_mesh(comm, box_tetrahedra(3), box_tetrahedra(2, (0.0, 0.0, 1.0 + GAP)))


def _component_bc(V, where, component):
    facets = dolfinx.mesh.locate_entities_boundary(V.mesh, 2, where)
    dofs = dolfinx.fem.locate_dofs_topological(V.sub(component), 2, facets)
    return dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V.sub(component))


def _pushed_cube(comm, direction=-1.0, **problem_kwargs):
    """The cube pushed onto (``direction`` -1) or pulled away from (+1) the block by a traction on
    its top face; the block's bottom clamped, both bodies on rollers on x = 0 and y = 0 (the
    cube's vertical motion is held by nothing but contact). Returns (problem, u, top area)."""
    mesh = _two_cubes(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 2.0 + GAP))
    tags = dolfinx.mesh.meshtags(mesh, 2, top, np.full(top.size, 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    psi, _ = neo_hookean(u)
    energy = psi * ufl.dx - direction * TRACTION * u[2] * ds(1)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(
            np.zeros(3, dtype=PETSc.ScalarType), dolfinx.fem.locate_dofs_topological(V, 2, bottom), V
        ),
        _component_bc(V, lambda x: np.isclose(x[0], 0.0), 0),
        _component_bc(V, lambda x: np.isclose(x[1], 0.0), 1),
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=PENALTY)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy, petsc_options_prefix="free_body_",
        **problem_kwargs,
    )  # fmt: skip
    return problem, u, 1.0


def test_find_free_bodies():
    """The rank of the rigid modes at the Dirichlet dofs: a clamped face holds a body, a
    pinned vertex leaves its 3 rotations, rollers on x = 0 and y = 0 its vertical translation,
    no condition all 6."""
    comm = MPI.COMM_WORLD
    mesh = _two_cubes(comm)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=PENALTY)
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    clamp = dolfinx.fem.dirichletbc(
        np.zeros(3, dtype=PETSc.ScalarType), dolfinx.fem.locate_dofs_topological(V, 2, bottom), V
    )
    corner = dolfinx.fem.locate_dofs_geometrical(
        V, lambda x: np.isclose(x[0], 0.0) & np.isclose(x[1], 0.0) & np.isclose(x[2], 2.0 + GAP)
    )
    pin = dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), corner, V)
    rollers = [
        _component_bc(V, lambda x: np.isclose(x[0], 0.0), 0),
        _component_bc(V, lambda x: np.isclose(x[1], 0.0), 1),
    ]
    free = find_free_bodies(contact, [clamp])
    assert [(b.index, b.free_motions) for b in free] == [(1, 6)]
    assert free[0].vertices == 27
    assert np.allclose(free[0].centre, (0.5, 0.5, 1.5 + GAP))
    assert np.allclose(free[0].size, (1.0, 1.0, 1.0))
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [clamp, pin])] == [
        (1, 3)
    ]
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [clamp, *rollers])] == [
        (1, 1)
    ]
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [])] == [(0, 6), (1, 6)]


def test_floating_cube_pushed_by_traction():
    """Plain defaults: the cube starts a gap above the block, with no stiffness against its vertical motion;
    the problem damps it, and the converged result is the undamped problem's: the contact force
    on the cube balances the traction's resultant, the damping is off, and the state equals a
    solve without damping from that state (independent: no damping, the cube already held)."""
    comm = MPI.COMM_WORLD
    problem, u, area = _pushed_cube(comm)
    assert [b.index for b in problem.free_bodies.bodies] == [1]
    result = problem.solve()
    assert result.converged
    assert problem.free_bodies.damped
    assert problem.free_bodies.damped_solves >= 2
    assert problem.assembler.proximal.k == 0.0
    resultant = problem.contact.force_resultants()
    # traction TRACTION on the top face (area 1), downward: contact pushes the cube up by it,
    # to the Newton tolerance (the horizontal contact forces go into the rollers)
    assert resultant[1, 2] == pytest.approx(TRACTION * area, rel=1e-6)
    assert resultant[0] == pytest.approx(-resultant[1], abs=1e-12)
    solved = u.x.array.copy()
    # an undamped solve from the result stays there (the residual is the undamped one)
    plain, u_plain, _ = _pushed_cube(comm, damp_free_bodies=False)
    u_plain.x.array[:] = solved
    again = plain.solve()
    assert again.iterations <= 1
    scale = comm.allreduce(float(np.max(np.abs(solved))), op=MPI.MAX)
    change = comm.allreduce(float(np.max(np.abs(u_plain.x.array - solved))), op=MPI.MAX)
    # (the first solve stopped at its Newton tolerance, rtol 1e-10 of a residual of 1e-2)
    assert again.residual_norms[0] <= 1e-9
    assert change <= 1e-6 * scale
    # and the next solve (the cube held now) is a plain one
    problem.solve()
    assert not problem.free_bodies.damped
    for p in (problem, plain):
        p.destroy()


def test_damping_off_fails_as_before():
    """Without damping the cube's first solve fails (the singular Jacobian), with the
    message about the load step or the penalty."""
    problem, _, _ = _pushed_cube(MPI.COMM_WORLD, damp_free_bodies=False)
    assert problem.free_bodies.bodies == []
    result = problem.solve(raise_on_failure=False)
    assert not result.converged
    assert "Reduce the load step" in result.failure_message()
    problem.destroy()


def test_body_never_held_is_named():
    """A traction that pulls the cube off the block: contact can never hold it; the message
    names the body, where it is, and the fix."""
    problem, _, _ = _pushed_cube(MPI.COMM_WORLD, direction=1.0)
    with pytest.raises(RuntimeError) as err:
        problem.solve()
    message = str(err.value)
    assert "body 1 (27 vertices, centre (0.5, 0.5, 1.55), size 1 x 1 x 1" in message
    assert "1 of its 6 rigid motions free" in message
    assert "Dirichlet" in message and "Reduce the load step" not in message
    assert problem.assembler.proximal.k == 0.0
    problem.destroy()
