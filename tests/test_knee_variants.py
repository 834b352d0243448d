"""``benchmarks/knee_variants.py``'s element Hessians made definite, checked against DOLFINx's
own assembly of the Hessian on a compressed, sheared neo-Hookean cube (each rank its own
mesh); the saddle escape's eigenpair. (The local relaxation is the library's:
tests/test_relaxation.py.)"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl
from conftest import aij_matrix, benchmark_module

import fenics_matdepth as fm


@pytest.fixture(scope="module")
def variants():
    """``benchmarks/knee_variants.py`` as a module."""
    return benchmark_module("knee_variants")


def _cube(deformed: bool):
    """A neo-Hookean unit cube (2 x 2 x 2 x 6 tetrahedra), clamped at z = 0; ``deformed``:
    compressed to about half its height and sheared (det F > 0 everywhere)."""
    mesh = dolfinx.mesh.create_unit_cube(
        MPI.COMM_SELF, 2, 2, 2, cell_type=dolfinx.mesh.CellType.tetrahedron
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    if deformed:
        u.interpolate(
            lambda x: np.stack(
                (0.6 * x[2] + 0.2 * x[1] ** 2, 0.3 * x[0] * x[2], -0.5 * x[2] ** 2 + 0.1 * x[0])
            )
        )
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    energy = fm.materials.neo_hookean(F, mu=1.0, kappa=10.0) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    dofs = dolfinx.fem.locate_dofs_topological(V, 2, facets)
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dofs, V)
    return u, energy, [bc]


def _hessian(u, energy):
    """The Hessian of ``energy`` assembled by DOLFINx (no boundary conditions), dense."""
    form = dolfinx.fem.form(ufl.derivative(ufl.derivative(energy, u), u))
    matrix = dolfinx.fem.assemble_matrix(form)
    return matrix.to_scipy().toarray()


def _scatter(blocks, dofs, size):
    """``sum_c P_c^T blocks[c] P_c`` (dense)."""
    total = np.zeros((size, size))
    for block, cell_dofs in zip(blocks, dofs, strict=True):
        total[np.ix_(cell_dofs, cell_dofs)] += block
    return total


def test_cell_matrices_sum_to_the_assembled_hessian(variants):
    u, energy, bcs = _cube(deformed=True)
    definite = variants.DefiniteHessians(u, bcs, energy)
    cells = definite.cell_matrices()
    assert cells.shape == (48, 12, 12)
    exact = _hessian(u, energy)
    assert np.allclose(
        _scatter(cells, definite.dofs, definite.size), exact, atol=1e-12 * abs(exact).max()
    )


def test_the_correction_makes_every_cell_definite_and_spares_dirichlet_dofs(variants):
    u, energy, bcs = _cube(deformed=True)
    definite = variants.DefiniteHessians(u, bcs, energy)
    cells = definite.cell_matrices()
    C, negative = variants.definite_correction(cells)
    # compressed and sheared, every cell has a negative eigenvalue
    assert negative.size == len(cells)
    lifted = np.linalg.eigvalsh(cells[negative] + C)
    assert lifted.min() >= -1e-9 * abs(lifted).max()
    # the correction assembled: zero in Dirichlet rows and columns; with the exact Hessian, a
    # sum of definite cell matrices on the free dofs
    correction = definite.correction().toarray()
    fixed = np.zeros(definite.size, dtype=bool)
    fixed[bcs[0].dof_indices()[0]] = True
    assert fixed.any() and not correction[fixed].any() and not correction[:, fixed].any()
    free = ~fixed
    corrected = (_hessian(u, energy) + correction)[np.ix_(free, free)]
    w = np.linalg.eigvalsh(corrected)
    assert w.min() >= -1e-9 * w.max()
    assert np.abs(correction).max() > 1e-3 * w.max()  # the correction acts
    assert definite.negative_cells == [negative.size]


def test_no_correction_at_rest(variants):
    """In the undeformed state every cell matrix is definite but for its rigid motions, whose
    zero eigenvalues round to either sign: no cell counts as negative."""
    u, energy, bcs = _cube(deformed=False)
    definite = variants.DefiniteHessians(u, bcs, energy)
    C, negative = variants.definite_correction(definite.cell_matrices())
    assert negative.size == 0 and C.shape == (0, 12, 12)


def test_unstable_mode_is_the_lowest_eigenpair(variants):
    """``--escape-saddles``' eigenpair: on a symmetric matrix of known eigenvectors with two
    negative eigenvalues among positive ones from 0.01 to 100, the shift found lies below the
    lowest eigenvalue within the bracket's 10 %, and the pair returned is the lowest one (its
    vector the known one)."""
    rng = np.random.default_rng(1)
    n = 60
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    values = rng.uniform(0.01, 100.0, n)
    values[5], values[9] = -0.37, -0.02
    dense = (Q * values) @ Q.T
    A = aij_matrix(0.5 * (dense + dense.T), MPI.COMM_SELF)
    shift = variants.lowest_eigenvalue_bracket(A)
    assert -0.37 / 0.9 <= shift < -0.37
    value, vector = variants.unstable_mode(A)
    w = vector.getArray()
    assert value == pytest.approx(-0.37, rel=1e-8)
    assert abs(w @ Q[:, 5]) / np.linalg.norm(w) == pytest.approx(1.0, abs=1e-8)
    A.destroy()
    vector.destroy()
