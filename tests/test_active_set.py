"""Active-set damping (`fenics_matdepth.contact.active_set.LaggedPairs`): a contact pair that
left keeps its last Hessian in the next Jacobian, for one iteration, and the solution is the
exact problem's."""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import clamped_and_moved, dense_matrix, merged_mesh, neo_hookean_residual

import fenics_matdepth as fm
from fenics_matdepth.meshing import box_tetrahedra
from fenics_matdepth.problems import ContactProblem

GAP = 0.01  # between the blocks in the reference configuration


def _blocks():
    """A 1 x 1 x 0.5 block and a smaller one GAP above it; the lower block's bottom clamped,
    the upper block's top pushed down by GAP + 0.02 (Dirichlet values). Returns the upper
    block's dofs (z) too."""
    comm = MPI.COMM_WORLD
    mesh = merged_mesh(
        comm,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5)),
        box_tetrahedra(2, (0.25, 0.2, 0.5 + GAP), (0.5, 0.55, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u, 1.0, 0.3)
    top = 0.9 + GAP
    bcs, g = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], top))
    g.x.array.reshape(-1, 3)[:, 2] = -GAP - 0.02
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=50.0, margin=0.3)
    n = V.dofmap.index_map.size_local
    upper = np.flatnonzero(V.tabulate_dof_coordinates()[:n, 2] > 0.5 + GAP / 2)
    return u, residual, psi * ufl.dx, bcs, contact, 3 * upper + 2


def _jacobian(problem, x) -> np.ndarray:
    assembler = problem.assembler
    assembler.set_state(x)
    assembler.jacobian(assembler.matrix)
    return dense_matrix(assembler.matrix)


def test_a_pair_that_left_keeps_its_last_hessian_for_one_jacobian():
    """The upper block sunk into the lower one (pairs intersecting), then lifted clear of it
    by a translation (every pair left; the bulk Jacobian unchanged, as a translation leaves F
    as it was): the next Jacobian is the sunk state's whole Jacobian, bulk and contact; the one
    after it, and any after a new solve starts, the lifted state's exact one."""
    u, residual, energy, bcs, contact, upper_z = _blocks()
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    problem.assembler.keep_left_pairs()
    lagged = problem.assembler.lagged_pairs
    u.x.array[upper_z] = -GAP - 0.05
    sunk = u.x.petsc_vec.copy()
    u.x.array[upper_z] = 0.2
    lifted = u.x.petsc_vec.copy()
    j_sunk = _jacobian(problem, sunk)
    assert MPI.COMM_WORLD.allreduce(contact.diagnostics()["active_pairs"]) > 0
    j_lagged = _jacobian(problem, lifted)
    assert contact.diagnostics()["active_pairs"] == 0
    assert lagged.added > 0
    j_lifted = _jacobian(problem, lifted)  # one iteration later: exact
    contact_part = np.abs(j_sunk - j_lifted).max()
    assert contact_part > 1.0  # the penalty's stiffness (50) times areas of order 0.01 - 0.1
    np.testing.assert_allclose(j_lagged, j_sunk, rtol=0, atol=1e-10 * contact_part)
    # a new solve forgets the last Jacobian's pairs
    _jacobian(problem, sunk)
    problem.assembler.start_solve()
    np.testing.assert_allclose(_jacobian(problem, lifted), j_lifted, rtol=0, atol=1e-12)
    # off again: the exact Jacobian
    _jacobian(problem, sunk)
    problem.assembler.keep_left_pairs(False)
    np.testing.assert_allclose(_jacobian(problem, lifted), j_lifted, rtol=0, atol=1e-12)
    for v in (sunk, lifted):
        v.destroy()
    problem.destroy()


def test_the_solution_is_the_exact_jacobians():
    """The upper block pressed onto the lower one: the same solution with and without the
    pairs that left in the Jacobian (the residual is the same; only the path differs), and
    the last iterations still converge fast (the contact set settled, the Jacobian exact)."""
    solutions, histories = [], []
    for keep in (False, True):
        u, residual, energy, bcs, contact, _ = _blocks()
        problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
        problem.assembler.keep_left_pairs(keep)
        result = problem.solve()
        assert result.converged
        # (two meshes, partitioned independently on several ranks: compared by global norms)
        solutions.append(
            [u.x.petsc_vec.norm(k) for k in (PETSc.NormType.NORM_2, PETSc.NormType.NORM_INFINITY)]
        )
        histories.append(result.residual_norms)
        problem.destroy()
    assert solutions[0][1] > 1e-2
    np.testing.assert_allclose(solutions[1], solutions[0], rtol=1e-8)
    r = histories[1]
    assert r[-1] <= 1e-10 * r[0] or r[-1] < 1e-12, r
    # the last step from the asymptotic range squares the residual (up to a constant)
    a, b = r[-2], r[-1]
    assert b <= max(1e3 * a**2, 1e-12), r


def test_collocation_is_refused():
    u = _blocks()[0]
    contact = fm.ContactOperator(
        u, fm.material_depth(u.function_space.mesh), penalty=50.0, integration="collocation"
    )
    from fenics_matdepth.contact.active_set import LaggedPairs

    with pytest.raises(ValueError, match="area integration"):
        LaggedPairs(contact)
