"""Shared pytest set-up (collective clean-up after each test, serial-only marker) and the
helpers several test files use: the neo-Hookean residual, meshes of several pieces, clamped
and moved boundaries, and the finite-difference checks of the pair kernels and the operator.

The helpers are plain functions, imported by the test files (``from conftest import ...``:
pytest puts this folder on ``sys.path``), so that module-level set-up code can call them too.
"""

from __future__ import annotations

import gc
import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path

from mpi4py import MPI

import dolfinx
import numpy as np
import pytest
import ufl
from hypothesis import settings

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh, interpolation_points
from fenics_matdepth.meshing import box_tetrahedra

# Property tests draw the same examples on every run and every rank (a CI run must not pass or
# fail by chance, and MPI ranks must agree); HYPOTHESIS_PROFILE=explore draws new ones.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))


@pytest.fixture(autouse=True)
def _collective_cleanup():
    """Collect garbage and wait for every rank: PETSc destructors are collective."""
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()


@pytest.fixture
def child_env() -> dict[str, str]:
    """The environment for a fresh serial child process: without the MPI launcher's
    variables (a child inheriting them would try to join this run and hang)."""
    launcher = ("OMPI_", "PMIX_", "PRTE_", "MPI_")
    return {k: v for k, v in os.environ.items() if not k.startswith(launcher)}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under MPI, a test that fails on some ranks only leaves the others waiting in a
    collective (and the failed rank in the barrier above): print the failure and abort the
    job instead of hanging until the timeout."""
    outcome = yield
    report = outcome.get_result()
    if report.failed and MPI.COMM_WORLD.size > 1:
        rank = MPI.COMM_WORLD.rank
        sys.stderr.write(f"\n[rank {rank}] {item.nodeid} failed:\n{report.longreprtext}\n")
        sys.stderr.write(f"[rank {rank}] aborting the MPI job (the other ranks may be stuck)\n")
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(1)


def pytest_collection_modifyitems(config, items):
    """Skip tests marked ``serial`` when running on more than one MPI process."""
    if MPI.COMM_WORLD.size == 1:
        return
    skip = pytest.mark.skip(reason="serial test (runs in the serial pass of `make test`)")
    for item in items:
        if "serial" in item.keywords:
            item.add_marker(skip)


# -- materials -------------------------------------------------------------------------------


def benchmark_module(name: str):
    """``benchmarks/<name>.py`` loaded as a module (registered in ``sys.modules``, where its
    dataclasses look their module up)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def neo_hookean(
    u: dolfinx.fem.Function, youngs: float = 1.0, poisson: float = 0.3
) -> tuple[ufl.core.expr.Expr, ufl.core.expr.Expr]:
    """The neo-Hookean strain-energy density of ``u`` and the deformation gradient it is a
    function of (a ``ufl.variable``, to differentiate by), from Young's modulus and Poisson's
    ratio."""
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(youngs, poisson)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    return fm.materials.neo_hookean(F_def, mu, kappa), F_def


def neo_hookean_residual(
    u: dolfinx.fem.Function,
    youngs: float = 1.0,
    poisson: float = 0.3,
    *,
    scale: ufl.core.expr.Expr | None = None,
    dx: ufl.Measure = ufl.dx,
) -> tuple[ufl.Form, ufl.core.expr.Expr]:
    """The residual ``inner(dpsi/dF, grad v) dx`` of the neo-Hookean energy and its density.

    Args:
        u: displacement, P1 vector Function.
        youngs: Young's modulus (pressure).
        poisson: Poisson's ratio.
        scale: a factor on the density (a DG0 stiffness field), or None.
        dx: the measure of the residual.

    Returns:
        ``(residual, psi)``; the strain energy is ``psi * dx``.
    """
    psi, F_def = neo_hookean(u, youngs, poisson)
    if scale is not None:
        psi = scale * psi
    v = ufl.TestFunction(u.function_space)
    return ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * dx, psi


def min_det_F(u: dolfinx.fem.Function) -> float:
    """Smallest det F over the cells, from UFL (independent of the library's evaluation;
    collective)."""
    mesh = u.function_space.mesh
    DG0 = dolfinx.fem.functionspace(mesh, ("DG", 0))
    det = dolfinx.fem.Function(DG0)
    det.interpolate(
        dolfinx.fem.Expression(ufl.det(ufl.Identity(3) + ufl.grad(u)), interpolation_points(DG0))
    )
    local = det.x.array.min() if det.x.array.size else np.inf
    return mesh.comm.allreduce(local, op=MPI.MIN)


# -- meshes and boundary conditions ----------------------------------------------------------


def merged_mesh(comm: MPI.Comm, *pieces: tuple[np.ndarray, np.ndarray]) -> dolfinx.mesh.Mesh:
    """One tetrahedral mesh of the pieces ``(X, cells)`` (vertices numbered piece after piece;
    pieces that meet are not glued: each is a body of its own)."""
    xs, cs, offset = [], [], 0
    for X, cells in pieces:
        xs.append(X)
        cs.append(cells + offset)
        offset += X.shape[0]
    return create_tetrahedral_mesh(comm, np.vstack(cs), np.vstack(xs))


def sunk_blocks(comm: MPI.Comm, everywhere: float = 0.0, tagged: bool = True):
    """A 1 x 1 x 0.5 block (cell tag 1) and a smaller one (tag 2) sunk 0.03 into it, each its
    own neo-Hookean (``tagged=False``: one neo-Hookean over every cell, ``psi * ufl.dx``),
    the upper one's top pushed on by a spring (an exterior-facet integral), with
    ``everywhere * |u|^2`` over every cell where ``everywhere`` is not 0; the displacement
    (zero) and the energy (:func:`sunk_blocks_state` gives a state)."""
    mesh = merged_mesh(
        comm,
        box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5)),
        box_tetrahedra(2, (0.25, 0.2, 0.51), (0.5, 0.55, 0.4)),
    )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    tdim = mesh.topology.dim
    cell_map = mesh.topology.index_map(tdim)
    n_cells = cell_map.size_local + cell_map.num_ghosts
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim, np.arange(n_cells, dtype=np.int32))
    tags = dolfinx.mesh.meshtags(
        mesh, tdim, np.arange(n_cells, dtype=np.int32), np.where(mid[:, 2] > 0.5, 2, 1)
    )
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.91))
    top_tags = dolfinx.mesh.meshtags(mesh, 2, top, np.full(top.size, 7, dtype=np.int32))
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=top_tags)
    stiff = fm.materials.neo_hookean(F, mu=1.0, kappa=10.0)
    if tagged:
        energy = stiff * dx(1) + fm.materials.neo_hookean(F, mu=0.5, kappa=4.0) * dx(2)
    else:
        energy = stiff * dx
    energy = energy + 0.5 * 3.0 * (u[2] + 0.05) ** 2 * ds(7)
    if everywhere:
        energy = energy + everywhere * ufl.inner(u, u) * dx
    return u, energy


def sunk_blocks_state(X: np.ndarray) -> np.ndarray:
    """Displacements (n, 3) of the vertices ``X`` of :func:`sunk_blocks`: a wave (a function of
    the position: the same state on one process and on several), the upper block sunk 0.03."""
    waves = np.array([[41.0, 17.0, 29.0], [23.0, 37.0, 13.0], [19.0, 31.0, 43.0]])
    values = 0.004 * np.sin(X @ waves)
    values[X[:, 2] > 0.505, 2] -= 0.03
    return values


def clamped_and_moved(
    V: dolfinx.fem.FunctionSpace,
    clamped: Callable[[np.ndarray], np.ndarray],
    moved: Callable[[np.ndarray], np.ndarray],
) -> tuple[list[dolfinx.fem.DirichletBC], dolfinx.fem.Function]:
    """Zero displacement on the boundary facets marked by ``clamped``, the displacement ``g``
    on those marked by ``moved``.

    Returns:
        ``(bcs, g)``: the two conditions, and ``g`` (zero; set it to move the boundary).
    """
    mesh = V.mesh
    fixed = dolfinx.mesh.locate_entities_boundary(mesh, 2, clamped)
    driven = dolfinx.mesh.locate_entities_boundary(mesh, 2, moved)
    g = dolfinx.fem.Function(V)
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, 2, fixed)
        ),
        dolfinx.fem.dirichletbc(g, dolfinx.fem.locate_dofs_topological(V, 2, driven)),
    ]
    return bcs, g


# -- finite-difference checks ----------------------------------------------------------------


def fd_derivatives(
    f: Callable[[np.ndarray], tuple], x0: np.ndarray, h: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """4th-order central differences of E (-> gradient) and of the gradient (-> Hessian)."""
    n = x0.size
    g = np.empty(n)
    hess = np.empty((n, n))
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        fm2, fm1, fp1, fp2 = f(x0 - 2 * e), f(x0 - e), f(x0 + e), f(x0 + 2 * e)
        g[k] = (fm2[0] - 8 * fm1[0] + 8 * fp1[0] - fp2[0]) / (12 * h)
        hess[:, k] = (fm2[1] - 8 * fm1[1] + 8 * fp1[1] - fp2[1]) / (12 * h)
    return g, hess


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    """Largest entry of ``|a - b|`` relative to the largest entry of ``|b|``."""
    return np.abs(a - b).max() / np.abs(b).max()


def assert_fd_derivatives(
    f: Callable[[np.ndarray], tuple],
    x0: np.ndarray,
    rtol: float,
    symmetric: bool = False,
    exact: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple:
    """Assert that the gradient and Hessian ``f`` returns at ``x0`` (``(E, grad, hess)``, or
    ``exact`` when given) match :func:`fd_derivatives` within ``rtol`` (:func:`rel_err`), and,
    if ``symmetric``, that the Hessian is symmetric to 1e-12 of its largest entry.

    Returns:
        ``f(x0)``.
    """
    value = f(x0)
    grad, hess = value[1:3] if exact is None else exact
    g_fd, h_fd = fd_derivatives(f, x0)
    assert rel_err(grad, g_fd) < rtol
    assert rel_err(hess, h_fd) < rtol
    if symmetric:
        assert np.abs(hess - hess.T).max() <= 1e-12 * np.abs(hess).max()
    return value


def aij_matrix(dense: np.ndarray, comm: MPI.Comm = MPI.COMM_WORLD):
    """``dense`` (square) as a PETSc AIJ matrix over ``comm``, its rows split between the
    ranks."""
    from petsc4py import PETSc

    n = dense.shape[0]
    A = PETSc.Mat().createAIJ([n, n], comm=comm)
    A.setPreallocationNNZ(n)
    A.setUp()
    start, end = A.getOwnershipRange()
    for i in range(start, end):
        A.setValues(i, np.arange(n, dtype=PETSc.IntType), dense[i])
    A.assemble()
    return A


def dense_matrix(A) -> np.ndarray:
    """An assembled PETSc matrix as a dense array, on every rank (collective; small models)."""
    indptr, indices, values = A.getValuesCSR()
    r0, r1 = A.getOwnershipRange()
    out = np.zeros(A.getSize())
    np.add.at(out, (np.repeat(np.arange(r0, r1), np.diff(indptr)), indices), values)
    return A.getComm().tompi4py().allreduce(out)


def operator_residual(op: fm.ContactOperator, V: dolfinx.fem.FunctionSpace):
    """A PETSc vector holding dE/du (a copy: a Function's petsc_vec dies with the Function)."""
    w = dolfinx.fem.Function(V)
    b = w.x.petsc_vec
    b.zeroEntries()
    op.add_residual(b)
    return b.copy()


def assert_operator_derivatives(
    op: fm.ContactOperator, u: dolfinx.fem.Function, h: float = 1e-6, rtol: float = 1e-6
) -> None:
    """Central differences (step ``h``) along a smooth direction v of the operator's energy
    and residual against ``residual . v`` and ``J v`` (relative tolerance ``rtol``), at the
    state ``u`` holds; the Jacobian must fit its pattern (no malloc). Collective."""
    V = u.function_space
    x = V.tabulate_dof_coordinates()
    v = dolfinx.fem.Function(V)
    v.x.array[:] = np.cos(np.array([1.3, 2.9, 0.7]) * x[:, [1, 2, 0]] + 0.2).ravel()
    u0 = u.x.array.copy()

    def at(t):
        u.x.array[:] = u0 + t * v.x.array
        op.update()

    at(h)
    e_plus, r_plus = op.energy(), operator_residual(op, V)
    at(-h)
    e_minus, r_minus = op.energy(), operator_residual(op, V)
    at(0.0)
    r0 = operator_residual(op, V)
    slope = r0.dot(v.x.petsc_vec)
    assert abs((e_plus - e_minus) / (2 * h) - slope) <= rtol * abs(slope)

    a = dolfinx.fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    A = op.create_matrix(a)
    A.zeroEntries()
    op.add_jacobian(A)
    assert A.getInfo()["mallocs"] == 0
    Hv = A.createVecLeft()
    A.mult(v.x.petsc_vec, Hv)
    fd = r_plus.copy()
    fd.axpy(-1.0, r_minus)
    fd.scale(1.0 / (2 * h))
    fd.axpy(-1.0, Hv)
    assert fd.norm() <= rtol * Hv.norm()
    A.destroy()
