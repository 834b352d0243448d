"""The local relaxation (``fm.LocalRelaxation``) and its patch assembly (``fm.patches``): a
pushed vertex relaxed back, a spread residual left alone, a patch's gradient, Hessian and
energy against the whole problem's, the det F floor, a solve with the relaxation against one
without, and the errors. Each rank its own mesh (``MPI.COMM_SELF``), and under ``mpirun``
the same on a mesh distributed over the processes (``MPI.COMM_WORLD``) against one process's."""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import sunk_blocks, sunk_blocks_state

import fenics_matdepth as fm
from fenics_matdepth._compat import integral_domains
from fenics_matdepth._mpi import summed
from fenics_matdepth.patches import PatchModel

pytestmark = pytest.mark.filterwarnings("ignore::fenics_matdepth.DepthDeficiencyWarning")

#: one process's mesh, and under mpirun one distributed over the processes
COMMS = [
    MPI.COMM_SELF,
    pytest.param(
        MPI.COMM_WORLD,
        marks=pytest.mark.skipif(MPI.COMM_WORLD.size == 1, reason="a mesh over processes"),
    ),
]


def _block(n: int = 5, comm=MPI.COMM_SELF):
    """A neo-Hookean unit cube of n x n x n x 6 tetrahedra at rest, clamped at z = 0."""
    mesh = dolfinx.mesh.create_unit_cube(comm, n, n, n, cell_type=dolfinx.mesh.CellType.tetrahedron)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    energy = fm.materials.neo_hookean(F, mu=1.0, kappa=10.0) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bc = dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    return u, energy, [bc]


def _problem(u, energy, bcs, friction=None, **options):
    contact = fm.ContactOperator(
        u, fm.material_depth(u.function_space.mesh), penalty=50.0, friction=friction
    )
    residual = ufl.derivative(energy, u, ufl.TestFunction(u.function_space))
    return fm.ContactProblem(residual, u, contact, bcs=bcs, energy=energy, **options)


def _state(problem, values: np.ndarray):
    """The iterate ``values`` (n_vertices, 3), its residual, and the total energy there."""
    x = problem.u.x.petsc_vec.copy()
    x.setArray(values.ravel()[: x.getLocalSize()])  # the owned rows
    F = x.duplicate()
    problem.assembler.set_state(x)
    assert problem.assembler.residual(x, F)
    return x, F, problem.assembler.total_energy()


def test_a_pushed_vertex_is_relaxed_back_and_nothing_else_moves():
    """A block at rest with one interior vertex pushed 0.04 and another, far from it, 0.004:
    the residual is concentrated round the first (the second's cells hold 0.8 % of
    ``|F|^2``), so the patch is the first vertex's cells; relaxed, the first vertex is back at
    rest to a small fraction of its push, the energy fell, the residual is the whole problem's
    at the relaxed state, and no dof outside the patch moved."""
    u, energy, bcs = _block()
    X = u.function_space.tabulate_dof_coordinates()
    near, far = (int(np.argmin(np.linalg.norm(X - p, axis=1))) for p in ([0.2] * 3, [0.8] * 3))
    pushed = np.zeros_like(X)
    pushed[near] = (0.04, -0.03, 0.02)
    pushed[far] = (0.004, 0.0, -0.003)
    with _problem(u, energy, bcs) as problem:
        relaxation = fm.LocalRelaxation(energy, share=0.8, vertices=12, det_floor=0.0)
        problem.relaxation = relaxation
        x, F, before = _state(problem, pushed)
        dofs, iterations, start, end = relaxation.relax(x, F)
        moved = x.getArray().reshape(-1, 3)
        patch = np.unique(dofs // 3)
        assert near in patch and far not in patch
        assert 1 <= iterations <= relaxation.iterations and end < relaxation.rtol * start
        assert np.linalg.norm(moved[near]) < 0.05 * np.linalg.norm(pushed[near])
        _, F_after, after = _state(problem, moved)
        assert after < before
        assert np.allclose(F.getArray(), F_after.getArray(), rtol=0.0, atol=1e-12)
        outside = np.setdiff1d(np.arange(len(X)), patch)
        assert np.array_equal(moved[outside], pushed[outside])
        assert relaxation.uses == 1 and relaxation.local_iterations == iterations


def test_a_spread_residual_is_left_alone_and_clamped_dofs_are_never_in_a_patch():
    """Every interior vertex pushed alike: no dozen vertices hold 80 % of ``|F|^2``, so nothing
    is relaxed; a pushed vertex above a clamped one: its patch holds no clamped dof."""
    u, energy, bcs = _block()
    X = u.function_space.tabulate_dof_coordinates()
    interior = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
    pushed = np.zeros_like(X)
    pushed[interior] = (0.01, 0.0, 0.0) * np.sin(7 * X[interior, :1])
    with _problem(u, energy, bcs) as problem:
        relaxation = problem.relaxation = fm.LocalRelaxation(energy, share=0.8, vertices=12)
        x, F, _ = _state(problem, pushed)
        assert relaxation.patch(F) is None and relaxation.relax(x, F) is None
        assert np.array_equal(x.getArray(), pushed.ravel()) and relaxation.uses == 0
        bottom = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.0], axis=1)))
        above = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.2], axis=1)))
        pushed[:] = 0.0
        pushed[above] = (0.0, 0.0, 0.05)
        x, F, _ = _state(problem, pushed)
        dofs = relaxation.patch(F)
        clamped = bcs[0].dof_indices()[0]
        assert dofs.size > 0 and not np.isin(dofs, clamped).any()
        cells = np.asarray(u.function_space.dofmap.list)
        assert bottom in cells[(cells == above).any(axis=1)] and np.isin(3 * bottom + 2, clamped)


def _sunk_blocks(comm=MPI.COMM_SELF):
    """The two blocks of ``conftest.sunk_blocks``, the lower one's bottom clamped; the
    displacement, energy, conditions and reference coordinates, at a state with the Dirichlet
    values reached."""
    u, energy = sunk_blocks(comm)
    V = u.function_space
    bottom = dolfinx.mesh.locate_entities_boundary(V.mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, bottom), V)
    ]
    X = V.tabulate_dof_coordinates()
    values = sunk_blocks_state(X)
    values[np.isclose(X[:, 2], 0.0)] = 0.0
    u.x.array[:] = values.ravel()
    return u, energy, bcs, X


def _patch_near(relaxation, V, point) -> PatchModel:
    """The patch round the vertex nearest to ``point`` that has contact pairs and, on a
    distributed mesh, cells or pairs on more than one process (which ones do depends on the
    partitioner: the vertices are tried in order of distance). Collective."""
    imap = V.dofmap.index_map
    X = V.tabulate_dof_coordinates()[: imap.size_local]
    distance = np.linalg.norm(X - point, axis=1)
    global_vertex = imap.local_range[0] + np.arange(X.shape[0])
    distance = np.concatenate(V.mesh.comm.allgather(distance))
    global_vertex = np.concatenate(V.mesh.comm.allgather(global_vertex))
    comm, patches = V.mesh.comm, relaxation._patches
    for vertex in global_vertex[np.lexsort((global_vertex, distance))][:80]:
        around = patches.around([vertex])
        dofs = (3 * around[:, None] + np.arange(3)).ravel()
        model = patches.model(dofs[~np.isin(dofs, relaxation._fixed)])
        holds = int(model.cells.size > 0 or model.pair_a.size > 0)
        if comm.allreduce(model.pair_a.size) > 0 and comm.allreduce(holds) == comm.size:
            return model
    raise AssertionError("no patch near the contact with cells or pairs on every process")


def _whole_block(A, model: PatchModel) -> np.ndarray:
    """The block of the (distributed) matrix ``A`` on the patch's dofs, on every process."""
    K = np.zeros((model.dofs.size, model.dofs.size))
    if model._owned_global.size:
        cols = model.dofs.astype(np.int32)
        K[model._owned_at] = A.getValues(model._owned_global, cols).reshape(-1, cols.size)
    return summed(model.owner.comm, K)


@pytest.mark.parametrize("comm", COMMS)
def test_a_patch_is_the_whole_problem_on_its_dofs(comm):
    """On two blocks sunk into each other (two cell tags, a spring on the upper one's top), the
    patch round a vertex of the upper block's bottom, in contact, has the whole problem's
    gradient (the residual's rows) and Hessian (the Jacobian's block) there, and its energy
    changes as the whole problem's when its dofs move; the spring's vertices are held. On a
    distributed mesh, the patch round the nearest vertex whose cells and pairs lie on every
    process."""
    u, energy, bcs, X = _sunk_blocks(comm)
    V = u.function_space
    with _problem(u, energy, bcs) as problem:
        relaxation = problem.relaxation = fm.LocalRelaxation(energy)
        x, F, _ = _state(problem, u.x.array.reshape(-1, 3).copy())
        assert problem.assembler.contact.energy() > 0.0
        patches = relaxation._patches
        top = patches.global_vertex[np.isclose(X[:, 2], 0.91)]
        assert np.isin(3 * top[:, None] + np.arange(3), relaxation._fixed).all()
        model = _patch_near(relaxation, V, [0.375, 0.35, 0.51])
        dofs = model.dofs
        assert isinstance(model, PatchModel) and dofs.size > 0
        gradient = model.gradient(x)
        assert np.abs(gradient).max() > 1e-3
        scale = np.abs(gradient).max()
        assert np.allclose(gradient, model.values(F), rtol=1e-10, atol=1e-12 * scale)
        # the kernel ran on the pairs that meet only, and the patch holds others too
        meet = model._contact(False, False)[0].size
        mesh_comm = V.mesh.comm
        assert mesh_comm.allreduce(meet) > 0 and mesh_comm.allreduce(model.pair_a.size - meet) > 0
        problem.assembler.set_state(x)
        A = problem.assembler.matrix
        problem.assembler.jacobian(A)
        whole = _whole_block(A, model)
        hessian = model.hessian(x)
        assert np.allclose(hessian, whole, rtol=1e-10, atol=1e-12 * np.abs(whole).max())
        trial = x.copy()
        step = 0.003 * np.random.default_rng(4).standard_normal(dofs.size)
        model.put(trial, model.values(x) + step)
        change = model.energy(trial) - model.energy(x)
        _, _, after = _state(problem, trial.getArray())
        _, _, start = _state(problem, x.getArray())
        assert change == pytest.approx(after - start, rel=1e-9)
        assert abs(change) > 1e-6


def test_a_patch_no_contact_pair_reaches_is_the_bulk_alone_and_the_det_floor_holds():
    """Deep inside a clamped block (a vertex two cells from its boundary, pushed) the patch has
    no contact pair and its gradient is the residual's rows; at a floor of 0.5 of the patch's
    lowest det F at the start (0.75, a cell of the pushed vertex), a trial flattening a cell to
    0.27 is refused, and without a floor it is not."""
    u, energy, bcs = _block()
    V = u.function_space
    X = V.tabulate_dof_coordinates()
    vertex = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.4], axis=1)))
    values = np.zeros_like(X)
    values[vertex] = (0.03, -0.02, 0.01)
    cells = np.asarray(V.dofmap.list)
    with _problem(u, energy, bcs) as problem:
        models = []
        for det_floor in (0.0, 0.5):
            relaxation = problem.relaxation = fm.LocalRelaxation(energy, det_floor=det_floor)
            x, F, _ = _state(problem, values)
            dofs = relaxation.patch(F)
            models.append(relaxation._patches.model(dofs))
        model, floored = models
        assert model.pair_a.size == 0 and vertex in dofs // 3
        # the energy's integral over every cell is assembled over the patch's cells only
        cell_type = dolfinx.fem.IntegralType.cell
        for form in (model.energy_form, model.residual_form, model.jacobian_form):
            assert form.integral_types == {cell_type}
            ((_, held),) = integral_domains(form, cell_type)
            assert np.array_equal(held, model.cells) and 0 < model.cells.size < cells.shape[0] // 2
        gradient = model.gradient(x)
        assert np.abs(gradient).max() > 1e-2
        assert np.allclose(gradient, F.getValues(dofs), rtol=1e-10, atol=1e-14)
        assert np.isfinite(floored.energy(x)) and 0.3 < floored.floor < 0.5
        cell = cells[(cells == vertex).any(axis=1)][0]
        others = [v for v in cell if v != vertex]
        moved = values.copy()
        plane = X[others].mean(axis=0) + moved[others].mean(axis=0)  # the opposite face's centre
        moved[vertex] += 0.7 * (plane - (X[vertex] + moved[vertex]))  # towards it
        ratio = np.linalg.det((X + moved)[others] - (X + moved)[vertex]) / np.linalg.det(
            X[others] - X[vertex]
        )
        assert 0.0 < ratio < floored.floor
        trial = x.copy()
        trial.setArray(moved.ravel())
        assert floored.energy(trial) == np.inf and np.isfinite(model.energy(trial))


def test_nothing_is_relaxed_while_a_dirichlet_dof_is_off_its_value():
    """The problem's callback before a Newton step (``_start_iteration``, the second
    iteration of a solve), on a block with a pushed vertex: with the clamped face 1e-3 off its
    value it leaves the iterate alone (the residual's free rows then hold the lifting, which a
    patch's energy does not see); on its value it relaxes, and SNES's residual norm is the
    relaxed iterate's. A problem without an energy refuses the relaxation."""
    u, energy, bcs = _block()
    X = u.function_space.tabulate_dof_coordinates()
    vertex = int(np.argmin(np.linalg.norm(X - [0.4, 0.4, 0.4], axis=1)))
    with _problem(u, energy, bcs) as problem:
        problem.relaxation = fm.LocalRelaxation(energy)
        snes = problem.snes
        for offset, relaxed in ((1e-3, False), (0.0, True)):
            values = np.zeros_like(X)
            values[vertex] = (0.03, -0.02, 0.01)
            values[np.isclose(X[:, 2], 0.0)] = (0.0, 0.0, offset)
            x, F, _ = _state(problem, values)
            snes.setSolution(x)
            F.copy(snes.getFunction()[0])
            snes.setFunctionNorm(F.norm())
            problem._first_norm = problem._last_norm = np.inf  # as a solve's start sets them
            problem._start_iteration(snes, 1)
            moved = snes.getSolution().getArray().reshape(-1, 3)
            assert np.array_equal(moved, values) is not relaxed
            assert snes.getFunctionNorm() == pytest.approx(snes.getFunction()[0].norm())
        assert snes.getFunctionNorm() < 0.5 * F.norm()
    contact = fm.ContactOperator(u, fm.material_depth(u.function_space.mesh), penalty=50.0)
    residual = ufl.derivative(energy, u, ufl.TestFunction(u.function_space))
    with fm.ContactProblem(residual, u, contact, bcs=bcs) as problem:
        with pytest.raises(ValueError, match="energy="):
            problem.relaxation = fm.LocalRelaxation(energy)
        assert problem.relaxation is None


@pytest.mark.parametrize("comm", COMMS)
def test_a_solve_with_the_relaxation_reaches_the_same_equilibrium(comm):
    """The sunk blocks solved from their pushed state with and without the relaxation (a
    patch in the upper block's corner pushed further; its top held sideways, so that the
    equilibrium is unique): the same equilibrium to the Newton tolerance's scale, and the
    relaxation was used."""
    u, energy, bcs, X = _sunk_blocks(comm)
    V = u.function_space
    top = dolfinx.mesh.locate_entities_boundary(V.mesh, 2, lambda x: np.isclose(x[2], 0.91))
    for i in (0, 1):
        sub = V.sub(i)
        dofs = dolfinx.fem.locate_dofs_topological(sub, 2, top)
        bcs.append(dolfinx.fem.dirichletbc(0.0, dofs, sub))
    start = u.x.array.copy()
    corner = np.linalg.norm(X - [0.25, 0.2, 0.91], axis=1) < 0.2
    start.reshape(-1, 3)[corner] += (0.02, 0.01, -0.01)
    solutions, relaxations = [], []
    for relax in (False, True):
        u.x.array[:] = start
        options = {"snes_atol": 1e-9, "snes_rtol": 1e-14, "snes_max_it": 60}
        with _problem(u, energy, bcs, petsc_options=options) as problem:
            if relax:
                relaxations.append(fm.LocalRelaxation(energy, min_norm=1e-6))
                problem.relaxation = relaxations[-1]
            result = problem.solve()
            assert result.converged, result
            solutions.append(u.x.array.copy())
    assert relaxations[0].uses > 0 and relaxations[0].local_iterations > 0
    assert np.abs(solutions[1] - solutions[0]).max() < 1e-6


def test_bad_settings_and_unsupported_problems_are_refused():
    """The floor of the residual norm from each bound problem's tolerance; parameters out of
    range; friction; an interior-facet integral in the energy."""
    u, energy, bcs = _block(2)
    # the floor below which nothing is relaxed: ten times the bound problem's snes_atol
    relaxation = fm.LocalRelaxation(energy)
    for atol in (1e-3, 1e-6):
        with _problem(u, energy, bcs, petsc_options={"snes_atol": atol}) as problem:
            problem.relaxation = relaxation
            assert relaxation.wanted(11.0 * atol) and not relaxation.wanted(9.0 * atol)
            assert not relaxation.wanted(np.nan) and relaxation.min_norm is None
    for kwargs in ({"share": 0.0}, {"share": 1.5}, {"vertices": 0}, {"iterations": 0},
                   {"rtol": 1.0}, {"det_floor": 1.0}):  # fmt: skip
        with pytest.raises(ValueError, match=r"share|vertices|rtol"):
            fm.LocalRelaxation(energy, **kwargs)
    with _problem(u, energy, bcs, friction=fm.Coulomb(0.3)) as problem:
        with pytest.raises(NotImplementedError, match="friction"):
            problem.relaxation = fm.LocalRelaxation(energy)
        assert problem.relaxation is None
    jump = 0.5 * ufl.inner(ufl.jump(u), ufl.jump(u)) * ufl.dS
    with _problem(u, energy, bcs) as problem:
        with pytest.raises(NotImplementedError, match="interior_facet"):
            problem.relaxation = fm.LocalRelaxation(energy + jump)


def _by_position(V, values: np.ndarray) -> np.ndarray:
    """The owned rows of ``values`` (per vertex) of every process, ordered by their vertices'
    coordinates (collective): a field compared across meshes numbered differently."""
    n = V.dofmap.index_map.size_local
    X = V.tabulate_dof_coordinates()[:n]
    X = np.concatenate(V.mesh.comm.allgather(X))
    values = np.concatenate(V.mesh.comm.allgather(values.reshape(-1, 3)[:n]))
    return values[np.lexsort(np.round(X, 9).T)]


@pytest.mark.skipif(MPI.COMM_WORLD.size == 1, reason="a mesh distributed over processes")
def test_a_distributed_relaxation_is_the_serial_one():
    """A block's pushed vertex relaxed on the mesh distributed over the processes and on one
    process's copy: the same patch (its dofs by position), the same local iterations,
    the same relaxed state and residual norm to round-off."""
    results = []
    for comm in (MPI.COMM_SELF, MPI.COMM_WORLD):
        u, energy, bcs = _block(5, comm)
        V = u.function_space
        X = V.tabulate_dof_coordinates()
        pushed = np.zeros_like(X)
        pushed[np.linalg.norm(X - [0.4, 0.6, 0.4], axis=1) < 1e-9] = (0.04, -0.03, 0.02)
        with _problem(u, energy, bcs) as problem:
            relaxation = problem.relaxation = fm.LocalRelaxation(energy, det_floor=0.0)
            x, F, _ = _state(problem, pushed)
            dofs, iterations, start, end = relaxation.relax(x, F)
            in_patch = np.zeros(x.getLocalSize())  # the patch's owned dofs, marked
            first = 3 * V.dofmap.index_map.local_range[0]
            mine = dofs[(dofs >= first) & (dofs < first + in_patch.size)] - first
            in_patch[mine] = 1.0
            in_patch = _by_position(V, in_patch)
            moved = _by_position(V, x.getArray())
            pushed = _by_position(V, pushed)
            results.append((in_patch, iterations, start, end, F.norm(), moved, pushed))
    (c1, i1, s1, e1, n1, m1, p1), (c2, i2, s2, e2, n2, m2, _) = results
    assert c1.any() and np.array_equal(c1, c2) and i1 == i2 >= 1
    assert s2 == pytest.approx(s1, rel=1e-10) and e2 == pytest.approx(e1, rel=1e-8)
    assert n2 == pytest.approx(n1, rel=1e-8) and e1 < 0.05 * s1
    assert np.abs(m1 - p1).max() > 0.03 and np.allclose(m1, m2, rtol=0.0, atol=1e-12)
