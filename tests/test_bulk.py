"""The bulk Jacobian through DOLFINx's CSR matrix (fenics_matdepth/_bulk.py) against
``dolfinx.fem.petsc.assemble_matrix`` of the same form and conditions; its reuse of the last
values while nothing the form reads has changed."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl
from conftest import clamped_and_moved, dense_matrix, neo_hookean, sunk_blocks, sunk_blocks_state

import fenics_matdepth as fm
from fenics_matdepth._bulk import BulkMatrix, csr_entries, fixed_cells
from fenics_matdepth._compat import create_tetrahedral_mesh, integral_domains
from fenics_matdepth.contact.assembly import global_dirichlet_dofs, owned_dirichlet_dofs
from fenics_matdepth.meshing import box_tetrahedra
from fenics_matdepth.system_assembler import SystemAssembler

pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

#: Sums in another order than DOLFINx's PETSc assembly: relative to the largest entry.
RTOL = 1e-13


def _setup():
    """A neo-Hookean Jacobian at a non-zero displacement, the bottom and the top held."""
    comm = MPI.COMM_WORLD
    X, cells = box_tetrahedra((5, 3, 2), (0.0, 0.0, 0.0), (1.0, 0.6, 0.4))
    mesh = create_tetrahedral_mesh(comm, cells, X)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    u.interpolate(lambda x: np.vstack((0.05 * x[2] ** 2, 0.02 * x[0] * x[1], -0.03 * x[0])))
    psi, _ = neo_hookean(u, 3.0, 0.3)
    a = dolfinx.fem.form(ufl.derivative(ufl.derivative(psi * ufl.dx, u), u))
    bcs, _ = clamped_and_moved(V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], 0.4))
    return u, a, bcs


def _reference(a, bcs) -> np.ndarray:
    A = dolfinx.fem.petsc.assemble_matrix(a, bcs)
    A.assemble()
    dense = dense_matrix(A)
    A.destroy()
    return dense


def _bulk_into_fresh(bulk: BulkMatrix, a, times: int = 1) -> np.ndarray:
    A = dolfinx.fem.petsc.create_matrix(a)
    A.zeroEntries()
    for _ in range(times):
        bulk.add_to(A)
    A.assemble()
    dense = dense_matrix(A)
    A.destroy()
    return dense


def test_matches_petsc_assembly():
    """Entries, Dirichlet rows and columns (1 on the diagonal, 0 elsewhere) as PETSc's
    assembly gives them."""
    u, a, bcs = _setup()
    dirichlet = global_dirichlet_dofs(u.function_space.mesh.comm, u.function_space, bcs)
    assert dirichlet.size > 0
    reference = _reference(a, bcs)
    bulk = BulkMatrix(a, bcs, dirichlet)
    ours = _bulk_into_fresh(bulk, a)
    assert np.abs(ours - reference).max() <= RTOL * np.abs(reference).max()
    assert np.array_equal(np.diag(ours)[dirichlet], np.ones(dirichlet.size))
    assert bulk.reused == 0


def test_reuses_values_until_an_input_changes():
    """A second addition with nothing changed reuses the values (the matrix doubles); after
    ``u`` changes, the form is assembled again, matching PETSc's assembly at the new ``u``."""
    u, a, bcs = _setup()
    dirichlet = global_dirichlet_dofs(u.function_space.mesh.comm, u.function_space, bcs)
    bulk = BulkMatrix(a, bcs, dirichlet)
    reference = _reference(a, bcs)
    twice = _bulk_into_fresh(bulk, a, times=2)
    assert bulk.reused == 1
    assert np.abs(twice - 2.0 * reference).max() <= 2.0 * RTOL * np.abs(reference).max()
    u.x.array[:] *= 1.5
    moved = _reference(a, bcs)
    assert np.abs(moved - reference).max() > 1e-6 * np.abs(reference).max()
    ours = _bulk_into_fresh(bulk, a)
    assert bulk.reused == 1
    assert np.abs(ours - moved).max() <= RTOL * np.abs(moved).max()


def test_csr_entries_are_the_owned_rows():
    """``csr_entries`` of an assembled DOLFINx matrix: (row, col) entries of the owned rows,
    sorted by row, whose values are the PETSc assembly's (no conditions)."""
    u, a, _ = _setup()
    csr = dolfinx.fem.assemble_matrix(a)
    csr.scatter_reverse()
    data_index, row, col = csr_entries(csr)
    assert np.all(np.diff(row) >= 0)
    bs = csr.block_size[0]
    r0 = bs * csr.index_map(0).local_range[0]
    n = 3 * u.function_space.dofmap.index_map.size_global
    local = np.zeros((n, n))
    np.add.at(local, (row + r0, col), csr.data[data_index])
    dense = u.function_space.mesh.comm.allreduce(local)
    reference = _reference(a, [])
    assert np.abs(dense - reference).max() <= RTOL * np.abs(reference).max()


#: the vertices of the lower block below this height are held (its two lowest layers)
HELD_BELOW = 0.2


def _sunk_blocks_lower_held(tagged: bool):
    """The two blocks of ``conftest.sunk_blocks`` with an integral over every cell (and their
    materials over cell tags, or one material over every cell), the lower block's vertices
    below HELD_BELOW held by Dirichlet conditions that turn them a little (off their values:
    at rest), the others displaced by the wave. Returns the displacement, the residual form,
    the conditions and the energy."""
    u, energy = sunk_blocks(MPI.COMM_WORLD, everywhere=0.01 if tagged else 0.0, tagged=tagged)
    V = u.function_space
    held = dolfinx.fem.locate_dofs_geometrical(V, lambda x: x[2] < HELD_BELOW)
    turned = dolfinx.fem.Function(V)
    turned.interpolate(lambda x: np.vstack((-0.02 * x[1], 0.02 * x[0], 0.01 + 0 * x[0])))
    bcs = [dolfinx.fem.dirichletbc(turned, held)]
    X = V.tabulate_dof_coordinates()
    values = sunk_blocks_state(X)
    values[X[:, 2] < HELD_BELOW] = 0.0
    u.x.array[:] = values.ravel()
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    return u, residual, bcs, energy


@pytest.mark.parametrize("tagged", [True, False])
def test_cells_whose_every_dof_is_prescribed_are_left_out_to_the_bit(tagged):
    """The problem assembles its residual and Jacobian over the cells that hold a free dof;
    they equal those over every cell to the bit, with the Dirichlet dofs off their values
    (the lifting at work) and at them, serially and on a distributed mesh: for integrals over
    cell tags and one over every cell, and for one over every cell alone."""
    u, residual, bcs, energy = _sunk_blocks_lower_held(tagged)
    V = u.function_space
    contact = fm.ContactOperator(u, fm.material_depth(V.mesh), penalty=50.0)
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    whole = SystemAssembler(problem._F, problem._J, u, contact, bcs)
    left_out = fixed_cells(V, owned_dirichlet_dofs(bcs))
    num_owned = V.mesh.topology.index_map(3).size_local
    # a cell is left out exactly where none of its vertices is free (the lowest layer of
    # cells; the layer above has held and free vertices)
    held = V.tabulate_dof_coordinates()[:, 2] < HELD_BELOW
    cell_held = held[np.asarray(V.dofmap.list)]
    assert np.array_equal(left_out, cell_held.all(axis=1))
    assert MPI.COMM_WORLD.allreduce(int((cell_held.any(axis=1) & ~left_out).sum())) > 0
    n_left = int(left_out[:num_owned].sum())
    assert MPI.COMM_WORLD.allreduce(n_left) > 0
    mine = problem.assembler
    assert mine.a_cells is not problem._J and mine.L_cells is not problem._F
    # each cell integral keeps the cells with a free vertex: the one over every cell is
    # compiled under id 0, below the tags 1 and 2
    cell = dolfinx.fem.IntegralType.cell
    ids = (0, 1, 2) if tagged else (0,)
    for form in (mine.a_cells, mine.L_cells):
        domains = integral_domains(form, cell)
        assert [ident for ident, _ in domains] == list(ids)
        kept = sum(entities.size for _, entities in domains)
        assert kept == (2 if tagged else 1) * (num_owned - n_left)  # the tags split the cells
    for reached in (False, True):
        x = u.x.petsc_vec.copy()
        if reached:
            dolfinx.fem.petsc.set_bc(x, bcs)
        vectors, matrices = [], []
        for assembler in (mine, whole):
            assembler.set_state(x)
            b = x.duplicate()
            assert assembler.residual(x, b)
            vectors.append(b.getArray().copy())
            A = assembler.matrix
            assembler.jacobian(A)
            matrices.append(A.getValuesCSR())
            b.destroy()
        assert MPI.COMM_WORLD.allreduce(np.abs(vectors[0]).max(initial=0.0), op=MPI.MAX) > 0
        assert np.array_equal(vectors[0], vectors[1])
        for mine_part, whole_part in zip(*matrices, strict=True):
            assert np.array_equal(mine_part, whole_part)
        x.destroy()
    whole.destroy()
    problem.destroy()
