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


def _two_cubes(comm, gap=GAP, width=1.0):
    """A block [0, 1]^3 (3^3 cuboids) and a cube of edge ``width`` (2^3 cuboids) centred above
    it, its bottom at 1 + gap."""
    corner = (0.5 - width / 2, 0.5 - width / 2, 1.0 + gap)
    return merged_mesh(comm, box_tetrahedra(3), box_tetrahedra(2, corner, (width,) * 3))


def _component_bc(V, where, component):
    facets = dolfinx.mesh.locate_entities_boundary(V.mesh, 2, where)
    dofs = dolfinx.fem.locate_dofs_topological(V.sub(component), 2, facets)
    return dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V.sub(component))


def _clamp(V, facets):
    dofs = dolfinx.fem.locate_dofs_topological(V, 2, facets)
    return dolfinx.fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), dofs, V)


def _pushed_cube(comm, direction=-1.0, newton_solver=False, gap=GAP, **problem_kwargs):
    """The cube pushed onto (``direction`` -1) or pulled away from (+1) the block by a traction on
    its top face; the block's bottom clamped, both bodies on rollers on x = 0 and y = 0 (the
    cube's vertical motion is held by nothing but contact). A ContactProblem, or with
    ``newton_solver`` a NonlinearContactProblem. Returns (problem, u, top area); a
    ContactProblem also keeps its forms as ``problem.forms`` (residual, energy)."""
    mesh = _two_cubes(comm, gap)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 2.0 + gap))
    tags = dolfinx.mesh.meshtags(mesh, 2, top, np.full(top.size, 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    psi, _ = neo_hookean(u)
    energy = psi * ufl.dx - direction * TRACTION * u[2] * ds(1)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        _clamp(V, bottom),
        _component_bc(V, lambda x: np.isclose(x[0], 0.0), 0),
        _component_bc(V, lambda x: np.isclose(x[1], 0.0), 1),
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=PENALTY)
    if newton_solver:
        return fm.NonlinearContactProblem(residual, u, contact, bcs, **problem_kwargs), u, 1.0
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy, petsc_options_prefix="free_body_",
        **problem_kwargs,
    )  # fmt: skip
    problem.forms = (residual, energy)
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
    clamp = _clamp(V, bottom)
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
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [clamp, pin])] == [(1, 3)]
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [clamp, *rollers])] == [
        (1, 1)
    ]
    assert [(b.index, b.free_motions) for b in find_free_bodies(contact, [])] == [(0, 6), (1, 6)]


def test_floating_cube_pushed_by_traction():
    """Plain defaults: the cube starts a gap above the block, with no stiffness against its
    vertical motion; the problem damps it, and the converged result is the undamped problem's:
    the contact force on the cube balances the traction's resultant, the damping is off, and
    the state equals a solve without damping from that state (independent: no damping, the
    cube already held)."""
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
    residual, energy = problem.forms
    plain = fm.ContactProblem(
        residual, u, problem.contact, bcs=problem.bcs, energy=energy, damp_free_bodies=False,
        petsc_options_prefix="free_body_plain_",
    )  # fmt: skip
    again = plain.solve()
    scale = comm.allreduce(float(np.max(np.abs(solved))), op=MPI.MAX)
    change = comm.allreduce(float(np.max(np.abs(u.x.array - solved))), op=MPI.MAX)
    # the damped solves' tolerance: 1e-6 of the first one's initial residual (RigidModeDamping)
    assert again.residual_norms[0] <= 1e-6 * result.residual_norms[0]
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
    # the motion contact does not hold: the vertical translation (the rollers hold the rest)
    assert problem.free_bodies.unheld == [["translation along z"]]
    assert "did not hold these rigid motions (body 1: translation along z)" in message
    assert problem.assembler.proximal.k == 0.0
    problem.destroy()


def test_body_free_in_six_motions_is_named():
    """A cube free in all six rigid motions (no rollers), pressed onto the block by a traction
    on its top, under frictionless contact: contact holds its vertical translation and its
    tilts, never its sliding and turning on the block's face. The damped solves end there, and
    the message names the motions not held and the fixes; the library does not hold them with
    a term of its own (that would bias the answer)."""
    comm = MPI.COMM_WORLD
    mesh = _two_cubes(comm, width=0.5)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 1.5 + GAP))
    tags = dolfinx.mesh.meshtags(mesh, 2, top, np.full(top.size, 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    psi, _ = neo_hookean(u)
    energy = psi * ufl.dx + TRACTION * u[2] * ds(1)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=PENALTY)
    with fm.ContactProblem(
        residual, u, contact, bcs=[_clamp(V, bottom)], energy=energy,
        petsc_options_prefix="free_body_six_",
    ) as problem:  # fmt: skip
        assert [(b.index, b.free_motions) for b in problem.free_bodies.bodies] == [(1, 6)]
        with pytest.raises(RuntimeError) as err:
            problem.solve()
        unheld = ["translation along x", "translation along y", "rotation about z"]
        assert problem.free_bodies.unheld == [unheld]
        message = str(err.value)
        assert f"(body 1: {', '.join(unheld)})" in message
        assert "fm.Coulomb" in message and "Dirichlet" in message
        assert problem.assembler.proximal.k == 0.0


def test_nonlinear_contact_problem_damps_the_cube():
    """The same through dolfinx's NewtonSolver, with its defaults, from the gap h / 9: damped,
    then the undamped equilibrium (force balance). The NewtonSolver has no line search of its
    own: without the problem's backtracking on the residual norm and the damping's limit on a
    free body's motion per solve, a Newton step threw the cube from the gap deep into the
    block, and the damped solve that first reached contact diverged at every k tried."""
    problem, _, area = _pushed_cube(MPI.COMM_WORLD, newton_solver=True)
    result = problem.solve()
    assert result.converged and problem.free_bodies.damped
    assert problem.assembler.proximal.k == 0.0
    assert problem.contact.force_resultants()[1, 2] == pytest.approx(TRACTION * area, rel=1e-6)
    problem.destroy()


def test_hertz_floating_hemisphere_plain_load_steps():
    """The quarter Hertz model (meshes/hertz.py, coarse), its hemisphere held only by contact
    under a body force, penalty 1000 E/h, plain solve_load_steps: every step converges without
    a cut, and the contact force on the hemisphere balances the body force on it."""
    pytest.importorskip("gmsh")
    from test_validation import _mesh_script

    hertz = _mesh_script("hertz")
    comm = MPI.COMM_WORLD
    mesh, cell_tags, facet_tags = hertz.hertz_mesh(
        comm, radius=1.0, block_width=1.0, block_depth=1.0, contact_size=0.1, far_size=0.3
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    youngs, poisson, density = 1.0, 0.3, 0.02
    mu, lmbda = youngs / (2 * (1 + poisson)), youngs * poisson / ((1 + poisson) * (1 - 2 * poisson))
    strain = ufl.sym(ufl.grad(u))
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=cell_tags)
    scale = dolfinx.fem.Constant(mesh, PETSc.ScalarType(0.0))
    energy = (mu * ufl.inner(strain, strain) + 0.5 * lmbda * ufl.tr(strain) ** 2) * dx
    energy = energy + scale * density * u[2] * dx(hertz.SPHERE)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    bcs = [_clamp(V, facet_tags.find(hertz.BLOCK_BOTTOM))]
    for tag, component in ((hertz.SYMMETRY_X, 0), (hertz.SYMMETRY_Y, 1)):
        dofs = dolfinx.fem.locate_dofs_topological(V.sub(component), 2, facet_tags.find(tag))
        bcs.append(dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V.sub(component)))
    penalty = fm.propose_penalty(mesh, youngs, factor=1000)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=penalty)
    with fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy) as problem:
        assert [b.free_motions for b in problem.free_bodies.bodies] == [1]
        steps = fm.solve_load_steps(
            problem, lambda t: setattr(scale, "value", t), num_steps=2, progress=False
        )
        assert [s.cuts for s in steps] == [0, 0]
        weight = comm.allreduce(
            dolfinx.fem.assemble_scalar(dolfinx.fem.form(density * dx(hertz.SPHERE))), op=MPI.SUM
        )
        # the free body is the hemisphere: contact holds it up against its weight
        resultant = contact.force_resultants()[problem.free_bodies.bodies[0].index]
        assert resultant[2] == pytest.approx(weight, rel=1e-6)
        assert problem.assembler.proximal.k == 0.0
