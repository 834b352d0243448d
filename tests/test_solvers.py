"""ContactProblem: a block pressed onto another converges, quadratically near the solution."""

from __future__ import annotations

import itertools

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl
from test_operator import _box_tets

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.solvers import ContactProblem


def test_block_pressed_on_block_converges_quadratically():
    comm = MPI.COMM_WORLD
    xa, ca = _box_tets(4, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5))
    xb, cb = _box_tets(3, (0.25, 0.2, 0.5), (0.5, 0.55, 0.4))  # resting on the lower block
    mesh = create_tetrahedral_mesh(comm, np.vstack((ca, cb + xa.shape[0])), np.vstack((xa, xb)))
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    P = ufl.diff(psi, F_def)
    v = ufl.TestFunction(V)
    residual = ufl.inner(P, ufl.grad(v)) * ufl.dx
    energy = psi * ufl.dx

    fdim = 2
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], 0.0))
    top = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], 0.9))
    push = dolfinx.fem.Function(V)
    push.x.array.reshape(-1, 3)[:, 2] = -0.03
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, fdim, bottom)
        ),
        dolfinx.fem.dirichletbc(push, dolfinx.fem.locate_dofs_topological(V, fdim, top)),
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    result = problem.solve()
    assert result.converged
    r = result.residual_norms
    assert r[-1] <= 1e-10 * r[0]
    # Quadratic convergence: once the residual is small, each step squares it (up to C).
    tail = [(a, b) for a, b in itertools.pairwise(r) if a < 1e-3 * r[0] and b > 1e-14]
    assert tail, f"no iterations in the asymptotic range: {r}"
    assert all(b <= 1e3 * a**2 for a, b in tail), f"not quadratic: {r}"
    # The upper block is pushed into the lower one: contact is active, penetration small.
    diag = contact.diagnostics()
    assert diag["active_pairs"] > 0
