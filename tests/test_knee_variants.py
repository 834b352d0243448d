"""``benchmarks/knee_variants.py``'s element Hessians made definite, checked against DOLFINx's
own assembly of the Hessian on a compressed, sheared neo-Hookean cube (each rank its own
mesh); the saddle escape's eigenpair; the local relaxation on a block with pushed vertices."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import pytest
import ufl
from conftest import aij_matrix, benchmark_module, merged_mesh

import fenics_matdepth as fm
from fenics_matdepth.meshing import box_tetrahedra


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


def _relaxation(variants, u, energy, bcs):
    """``--relax``'s LocalRelaxation on a plain DOLFINx problem: the residual, Jacobian and
    energy of ``energy`` at the state ``x`` (no boundary conditions: their dofs are held)."""
    V = u.function_space
    residual_form = dolfinx.fem.form(ufl.derivative(energy, u))
    jacobian_form = dolfinx.fem.form(ufl.derivative(ufl.derivative(energy, u), u))
    energy_form = dolfinx.fem.form(energy)

    def set_state(x):
        u.x.array[:] = x.getArray(readonly=True)

    def residual(x, b):
        set_state(x)
        b.setArray(dolfinx.fem.assemble_vector(residual_form).array)

    def jacobian(x):
        set_state(x)
        A = dolfinx.fem.petsc.assemble_matrix(jacobian_form)
        A.assemble()
        return A

    def value(x):
        set_state(x)
        e = dolfinx.fem.assemble_scalar(energy_form)
        return e if np.isfinite(e) else np.inf

    fixed = variants.dirichlet_mask(V, bcs)
    cells = np.asarray(V.dofmap.list).reshape(-1, 4)
    return variants.LocalRelaxation(residual, jacobian, value, cells, fixed), residual, value


def _block_at_rest(n: int = 5):
    """A neo-Hookean unit cube of n x n x n x 6 tetrahedra at rest, clamped at z = 0."""
    mesh = dolfinx.mesh.create_unit_cube(
        MPI.COMM_SELF, n, n, n, cell_type=dolfinx.mesh.CellType.tetrahedron
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    energy = fm.materials.neo_hookean(F, mu=1.0, kappa=10.0) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    return u, energy, [bc]


def test_local_relaxation_returns_a_pushed_vertex_and_leaves_the_rest(variants):
    """``--relax``: a block at rest with one interior vertex pushed 0.04 and another, far from
    it, 0.004: the residual is concentrated round the first (the second's cells hold 0.8 % of
    ``|F|^2``), so the patch is the first vertex's cells; relaxed, the first vertex is back
    at rest to a small fraction of its push, the energy fell, and no dof outside the patch
    moved (the second vertex keeps its push exactly)."""
    u, energy, bcs = _block_at_rest()
    X = u.function_space.tabulate_dof_coordinates()
    near, far = (int(np.argmin(np.linalg.norm(X - p, axis=1))) for p in ([0.2] * 3, [0.8] * 3))
    pushed = np.zeros_like(X)
    pushed[near] = (0.04, -0.03, 0.02)
    pushed[far] = (0.004, 0.0, -0.003)
    relaxation, residual, value = _relaxation(variants, u, energy, bcs)
    x = u.x.petsc_vec.copy()
    x.setArray(pushed.ravel())
    F = x.duplicate()
    residual(x, F)
    before = value(x)
    dofs, iterations, start, end = relaxation.relax(x, F)
    moved = x.getArray().reshape(-1, 3)
    patch = np.unique(dofs // 3)
    assert near in patch and far not in patch
    assert 1 <= iterations <= variants.RELAX_ITERATIONS and end < variants.RELAX_RTOL * start
    assert np.linalg.norm(moved[near]) < 0.05 * np.linalg.norm(pushed[near])
    assert value(x) < before
    outside = np.setdiff1d(np.arange(len(X)), patch)
    assert np.array_equal(moved[outside], pushed[outside])
    assert np.array_equal(moved[far], pushed[far])
    assert relaxation.uses == 1 and relaxation.local_iterations == iterations


def test_local_relaxation_leaves_a_spread_residual(variants):
    """Every interior vertex pushed alike: no dozen vertices hold 80 % of ``|F|^2``, so
    ``--relax`` does nothing; the clamped dofs are never in a patch."""
    u, energy, bcs = _block_at_rest()
    X = u.function_space.tabulate_dof_coordinates()
    interior = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
    relaxation, residual, _ = _relaxation(variants, u, energy, bcs)
    x = u.x.petsc_vec.copy()
    pushed = np.zeros_like(X)
    pushed[interior] = (0.01, 0.0, 0.0) * np.sin(7 * X[interior, :1])
    x.setArray(pushed.ravel())
    F = x.duplicate()
    residual(x, F)
    assert relaxation.patch(F) is None and relaxation.relax(x, F) is None
    assert np.array_equal(x.getArray(), pushed.ravel()) and relaxation.uses == 0
    # the vertex above a clamped one pushed: its patch holds no clamped dof
    bottom = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.0], axis=1)))
    above = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.2], axis=1)))
    pushed[:] = 0.0
    pushed[above] = (0.0, 0.0, 0.05)
    x.setArray(pushed.ravel())
    residual(x, F)
    dofs = relaxation.patch(F)
    clamped = bcs[0].dof_indices()[0]
    assert dofs.size > 0 and not np.isin(dofs, clamped).any()
    round_above = relaxation.cells[(relaxation.cells == above).any(axis=1)]
    assert bottom in round_above and np.isin(3 * bottom + 2, clamped)


def _sunk_blocks():
    """A 1 x 1 x 0.5 block (cell tag 1) and a smaller one (tag 2) sunk 0.03 into it, the
    lower one's bottom clamped and the upper one's top pushed on by a spring (an
    exterior-facet integral); a ContactProblem of the two, each its own neo-Hookean, at a
    state with the Dirichlet values reached."""
    mesh = merged_mesh(
        MPI.COMM_SELF,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5)),
        box_tetrahedra(2, (0.25, 0.2, 0.51), (0.5, 0.55, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    tdim = mesh.topology.dim
    n_cells = mesh.topology.index_map(tdim).size_local
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim, np.arange(n_cells, dtype=np.int32))
    tags = dolfinx.mesh.meshtags(
        mesh, tdim, np.arange(n_cells, dtype=np.int32), np.where(mid[:, 2] > 0.5, 2, 1)
    )
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.91))
    top_tags = dolfinx.mesh.meshtags(mesh, 2, top, np.full(top.size, 7, dtype=np.int32))
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=top_tags)
    energy = (
        fm.materials.neo_hookean(F, mu=1.0, kappa=10.0) * dx(1)
        + fm.materials.neo_hookean(F, mu=0.5, kappa=4.0) * dx(2)
        + 0.5 * 3.0 * (u[2] + 0.05) ** 2 * ds(7)
    )
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    clamped = dolfinx.fem.locate_dofs_topological(V, 2, bottom)
    bcs = [dolfinx.fem.dirichletbc(np.zeros(3), clamped, V)]
    X = V.tabulate_dof_coordinates()
    rng = np.random.default_rng(3)
    values = 0.004 * rng.standard_normal(X.shape)
    values[X[:, 2] > 0.505, 2] -= 0.03
    values[np.isclose(X[:, 2], 0.0)] = 0.0
    u.x.array[:] = values.ravel()
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=50.0)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    return problem, energy, X


def test_a_patch_assembled_over_itself_is_the_whole_problem_there(variants):
    """``--relax patch``: on two blocks sunk into each other (two cell tags, a spring on the
    upper one's top), the patch round a vertex of the upper block's bottom, in contact, has the
    whole problem's gradient (the residual's rows) and Hessian (the Jacobian's block) there, and
    its energy changes as the whole problem's when its dofs move; the spring's vertices are
    held on every patch."""
    patch_assembly = benchmark_module("patch_assembly")
    problem, energy, X = _sunk_blocks()
    cells = np.asarray(problem.u.function_space.dofmap.list).reshape(-1, 4)
    relaxation = variants.relaxation_of(problem, cells, energy)
    assembler = problem.assembler
    x = problem.u.x.petsc_vec.copy()
    assembler.set_state(x)
    assert assembler.contact.energy() > 0.0
    F = x.duplicate()
    assert assembler.residual(x, F)
    vertex = int(np.argmin(np.linalg.norm(X - [0.375, 0.35, 0.51], axis=1)))
    around = np.unique(cells[(cells == vertex).any(axis=1)])
    dofs = (3 * around[:, None] + np.arange(3)).ravel()
    dofs = dofs[~relaxation.fixed[dofs]].astype(np.int32)
    top = np.isclose(X[:, 2], 0.91)
    assert relaxation.fixed.reshape(-1, 3)[top].all() and dofs.size == 3 * around.size
    model = relaxation.restricted(dofs)
    assert isinstance(model, patch_assembly.PatchModel) and model.pair_a.size > 0
    gradient = model.gradient(x)
    assert np.abs(gradient).max() > 1e-3
    assert np.allclose(gradient, F.getValues(dofs), rtol=1e-10, atol=1e-12 * np.abs(gradient).max())
    whole = variants.WholeSystem(relaxation, dofs, F).hessian(x)
    hessian = model.hessian(x)
    assert np.allclose(hessian, whole, rtol=1e-10, atol=1e-12 * np.abs(whole).max())
    trial = x.copy()
    step = 0.003 * np.random.default_rng(4).standard_normal(dofs.size)
    trial.setValues(dofs, x.getValues(dofs) + step)
    trial.assemble()
    change = model.energy(trial) - model.energy(x)
    assembler.set_state(trial)
    after = assembler.total_energy()
    assembler.set_state(x)
    assert change == pytest.approx(after - assembler.total_energy(), rel=1e-9)
    assert abs(change) > 1e-6


def test_a_patch_no_contact_pair_reaches_is_the_bulk_alone(variants):
    """``--relax patch`` deep inside a body (a vertex two cells from the boundary of a clamped
    block, pushed): the patch has no contact pair, and its gradient is the residual's rows."""
    benchmark_module("patch_assembly")
    u, energy, bcs = _block_at_rest()
    V = u.function_space
    X = V.tabulate_dof_coordinates()
    vertex = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.4], axis=1)))
    u.x.array.reshape(-1, 3)[vertex] = (0.03, -0.02, 0.01)
    contact = fm.ContactOperator(u, fm.material_depth(V.mesh), penalty=50.0)
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    cells = np.asarray(V.dofmap.list).reshape(-1, 4)
    relaxation = variants.relaxation_of(problem, cells, energy)
    x = u.x.petsc_vec.copy()
    problem.assembler.set_state(x)
    F = x.duplicate()
    assert problem.assembler.residual(x, F)
    dofs = relaxation.patch(F)
    model = relaxation.restricted(dofs)
    assert model.pair_a.size == 0 and vertex in dofs // 3
    gradient = model.gradient(x)
    assert np.abs(gradient).max() > 1e-2
    assert np.allclose(gradient, F.getValues(dofs), rtol=1e-10, atol=1e-14)
    # --relax-det-floor: at a floor of 0.5 of the patch's lowest det F at the start (0.75, a
    # cell of the pushed vertex), a trial flattening a cell to 0.27 is refused; without a
    # floor it is not
    det_floor = variants.relaxation_of(problem, cells, energy, det_floor=0.5).restricted(dofs)
    assert np.isfinite(det_floor.energy(x)) and 0.3 < det_floor.floor < 0.5
    cell = cells[(cells == vertex).any(axis=1)][0]
    others = [v for v in cell if v != vertex]
    moved = x.copy()
    values = moved.getArray().reshape(-1, 3)
    plane = X[others].mean(axis=0) + values[others].mean(axis=0)  # the opposite face's centre
    here = X[vertex] + values[vertex]
    values[vertex] += 0.7 * (plane - here)  # towards the opposite face
    ratio = np.linalg.det((X + values)[others] - (X + values)[vertex]) / np.linalg.det(
        X[others] - X[vertex]
    )
    assert 0.0 < ratio < det_floor.floor
    assert det_floor.energy(moved) == np.inf and np.isfinite(model.energy(moved))
