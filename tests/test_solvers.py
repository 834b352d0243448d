"""Newton solvers with contact: quadratic convergence, the sparsity pattern rebuilt when bodies
close a gap, the NewtonSolver problem, load stepping, and contact added to a user's own form."""

from __future__ import annotations

import contextlib
import gc
import itertools
import math
import re
import subprocess
import sys
import warnings
import weakref
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import pytest
import ufl
from conftest import (
    aij_matrix,
    clamped_and_moved,
    merged_mesh,
    neo_hookean,
    neo_hookean_residual,
)

import fenics_matdepth as fm
from fenics_matdepth import linear_solver, snes_callbacks, system_assembler
from fenics_matdepth._bulk import BulkMatrix
from fenics_matdepth._compat import create_tetrahedral_mesh
from fenics_matdepth.contact import assembly
from fenics_matdepth.meshing import box_tetrahedra
from fenics_matdepth.problems import ContactProblem, NonlinearContactProblem
from fenics_matdepth.results import SolveResult

E, NU = 1.0, 0.3


def _stacked_blocks(comm, gap: float = 0.0, sink: float = 0.0, mesh=None):
    """A 1 x 1 x 0.5 block and a smaller block above it (bottom at z = 0.5 + gap - sink);
    a new mesh unless ``mesh`` (made by this function) is given."""
    if mesh is None:
        mesh = merged_mesh(
            comm,
            box_tetrahedra(4, (0.0, 0.0, 0.0), (1.0, 1.0, 0.5)),
            box_tetrahedra(3, (0.25, 0.2, 0.5 + gap - sink), (0.5, 0.55, 0.4)),
        )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    residual, psi = neo_hookean_residual(u, E, NU)
    return mesh, V, u, residual, psi * ufl.dx


def _press_bcs(mesh, V, top_z: float, push: float):
    """Lower block's bottom clamped; the upper block's top face moved by ``push`` along z."""
    bcs, g = clamped_and_moved(
        V, lambda x: np.isclose(x[2], 0.0), lambda x: np.isclose(x[2], top_z)
    )
    g.x.array.reshape(-1, 3)[:, 2] = push
    return bcs, g


def _relative_difference(u, reference) -> float:
    """|u - reference| / |reference| of two Functions on one space (collective). Tests keep
    the Functions, not PETSc copies of ``u.x.petsc_vec``, which need ``u``'s space alive
    (docs/solvers.md)."""
    difference = u.x.petsc_vec.copy()
    difference.axpy(-1.0, reference.x.petsc_vec)
    value = difference.norm() / reference.x.petsc_vec.norm()
    difference.destroy()
    return value


def _assert_quadratic(r: np.ndarray) -> None:
    assert r[-1] <= 1e-10 * r[0], f"not converged to 1e-10: {r}"
    # pairs in the asymptotic range whose result is above round-off (1e-12 of the start)
    tail = [(a, b) for a, b in itertools.pairwise(r) if a < 1e-3 * r[0] and b > 1e-12 * r[0]]
    assert tail, f"no iterations in the asymptotic range: {r}"
    # once the residual is small, each step squares it (up to a constant)
    assert all(b <= 1e3 * a**2 for a, b in tail), f"not quadratic: {r}"


def test_block_pressed_on_block_converges_quadratically():
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    result = problem.solve()
    assert result.converged
    _assert_quadratic(result.residual_norms)
    diag = contact.diagnostics()
    assert diag["active_pairs"] > 0
    # every second of the solve is attributed, and each part was exercised
    assert all(problem.timings[k] > 0.0 for k in problem.timings), problem.timings


def _record_factorisations(problem, record: list) -> None:
    """A KSP monitor appending, at each linear solve's start, whether its preconditioner was
    factorised anew for it (the PETSc state of MUMPS's factor matrix changed): counted apart
    from the problem's own counters."""
    pc = problem.snes.getKSP().getPC()
    last = [None]

    def monitor(ksp, its, rnorm):
        if its == 0:
            state = pc.getFactorMatrix().stateGet()
            record.append(state != last[0])
            last[0] = state

    problem.snes.getKSP().setMonitor(monitor)


def test_a_kept_factorisation():
    """With ``keep_factorisation=True`` the direct solver factorises fewer Jacobians than it
    takes Newton iterations (GMRES preconditioned by the kept factorisation), converges as fast
    and to the solution of a factorisation per iteration (``keep_factorisation=False``). A
    solve after a converged one starts on that one's last factorisation, unless the contact
    penalty changed in between. Where GMRES cannot converge on a kept factorisation (here: one
    GMRES iteration allowed), the solve goes on from the iterate reached, factorising every
    Jacobian, and converges as fast; the problem's next solve then does not try to keep a
    factorisation (one linear solve per iteration), the one after tries again, first on the
    factorisation it was handed."""
    comm = MPI.COMM_WORLD
    runs, mesh = {}, None
    for name, options, keep in (
        ("kept", None, True),
        ("every", None, False),
        ("one_gmres_iteration", {"ksp_max_it": 1}, True),
    ):
        mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
        bcs, push = _press_bcs(mesh, V, 0.9, -0.02)
        contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
        results = []
        with ContactProblem(
            residual, u, contact, bcs=bcs, energy=energy, petsc_options=options,
            keep_factorisation=keep,
        ) as problem:  # fmt: skip
            factorised = []
            _record_factorisations(problem, factorised)
            # the last solve at the third one's load, with a stiffer penalty
            for depth, penalty in ((-0.02, 200.0), (-0.03, 200.0), (-0.04, 200.0), (-0.04, 250.0)):
                push.x.array.reshape(-1, 3)[:, 2] = depth
                contact.penalty = penalty
                del factorised[:]
                result = problem.solve()
                assert result.converged
                assert len(result.residual_norms) == result.iterations + 1
                if penalty == 200.0:  # (the last starts near its solution, at round-off)
                    _assert_quadratic(result.residual_norms)
                # (the problem counts its factorisations only when it may keep one)
                assert sum(factorised) == (result.factorisations if keep else result.iterations)
                results.append((result.iterations, result.factorisations, list(factorised)))
        runs[name] = (results, u)
    kept, every = runs["kept"][0], runs["every"][0]
    for (iterations, factorisations, _), (every_iterations, none, _) in zip(
        kept, every, strict=True
    ):
        assert factorisations < iterations
        assert abs(every_iterations - iterations) <= 1 and none == 0
    # the first solve and the one after the penalty changed factorise their first Jacobian,
    # the others start on the factorisation the solve before ended with
    assert [first for _, _, (first, *_) in kept] == [True, False, False, True]
    assert _relative_difference(runs["every"][1], runs["kept"][1]) <= 1e-8
    failing = runs["one_gmres_iteration"][0]
    for (iterations, factorisations, _), (every_iterations, _, _) in zip(
        failing, every, strict=True
    ):
        assert factorisations == iterations
        assert abs(every_iterations - iterations) <= 1
    # the first and third solves tried to keep a factorisation KEPT_TRIES times (as many linear
    # solves more than iterations), the third first on the second's last factorisation; the
    # second and fourth did not try (backing off after the first and third)
    tries = linear_solver.KEPT_TRIES
    linear_solves = [len(record) - iterations for iterations, _, record in failing]
    assert linear_solves == [tries, 0, tries, 0]
    assert [record[0] for _, _, record in failing] == [True, True, False, True]


def test_the_kept_factorisation_has_the_rate_test():
    """With a kept factorisation the problem's GMRES runs ``linear_solver.KeptRateTest`` after
    PETSc's own test: at the 5th iteration a residual at 0.9 of the first (a prediction of
    1,093 iterations to 1e-10) stops it as diverged, at the 3rd nothing does, and the test
    counts the stop; with a factorisation per iteration (``preonly``) nothing stops."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.02)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    diverged = int(PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT)
    for keep, expected, stops in ((True, [0, 0, diverged], 1), (False, [0, 0, 0], 0)):
        with ContactProblem(
            residual, u, contact, bcs=bcs, energy=energy, keep_factorisation=keep
        ) as problem:
            assert problem.solve().converged
            ksp = problem.snes.getKSP()
            calls = ((0, 1.0), (3, 0.5), (5, 0.9))  # (iteration, residual norm)
            assert [int(ksp.callConvergenceTest(i, r)) for i, r in calls] == expected
            assert problem.kept_rate_test.stops == stops


def test_a_carried_factorisation_that_fails_backs_off():
    """Where GMRES does not converge on the factorisation a solve was handed by the one before
    (here: the bulk made 20 times stiffer in between), the solve goes on with a factorisation
    of its first Jacobian and converges, and the problem's next solve factorises its first
    Jacobian rather than trying again; the one after starts on the factorisation it is
    handed."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    stiffness = dolfinx.fem.Constant(mesh, 1.0)
    bcs, push = _press_bcs(mesh, V, 0.9, -0.02)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    records = []
    with ContactProblem(
        stiffness * residual, u, contact, bcs=bcs, energy=stiffness * energy
    ) as problem:
        factorised = []
        _record_factorisations(problem, factorised)
        steps = ((-0.02, 1.0), (-0.03, 1.0), (-0.04, 20.0), (-0.05, 20.0), (-0.06, 20.0))
        for depth, scale in steps:
            push.x.array.reshape(-1, 3)[:, 2] = depth
            stiffness.value = scale
            del factorised[:]
            result = problem.solve()
            assert result.converged
            _assert_quadratic(result.residual_norms)
            assert sum(factorised) == result.factorisations
            records.append(list(factorised))
    assert [record[0] for record in records] == [True, False, False, True, False]
    assert records[2][1], "the failed carried start is followed by a factorisation"


def test_symmetric_jacobians_are_factorised_as_ldlt():
    """The Jacobian of an energy is symmetric: the default direct solver factorises it as
    LDL^T (MUMPS Cholesky, symmetric indefinite) and reaches LU's solution in as many
    iterations; a user's ``pc_type`` is kept. A residual that is no energy's derivative (here
    with a convection-like term) has an unsymmetric Jacobian and is factorised as LU."""
    comm = MPI.COMM_WORLD
    runs, mesh = {}, None
    for name, options in (("default", None), ("lu", {"pc_type": "lu"}), ("convected", None)):
        mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
        if name == "convected":
            drift = ufl.as_vector((0.05, 0.0, 0.0))
            residual += ufl.inner(ufl.dot(ufl.grad(u), drift), ufl.TestFunction(V)) * ufl.dx
            energy = None
        bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
        contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
        problem = ContactProblem(
            residual, u, contact, bcs=bcs, energy=energy, petsc_options=options
        )
        result = problem.solve()
        assert result.converged
        _assert_quadratic(result.residual_norms)
        pc = problem.snes.getKSP().getPC()
        runs[name] = (pc.getType(), result.iterations, u)
        symmetric = problem._A.isSymmetric(1e-10 * problem._A.norm(PETSc.NormType.INFINITY))
        assert symmetric == (name != "convected")
    assert [runs[name][0] for name in runs] == ["cholesky", "lu", "lu"]
    assert runs["default"][1] == runs["lu"][1]
    assert _relative_difference(runs["default"][2], runs["lu"][2]) <= 1e-9


def test_failed_ldlt_factorisation_is_retried_with_lu():
    """When MUMPS cannot complete the LDL^T factorisation (here: its working memory capped at
    1 MB, ICNTL(23)), the solve is repeated once from its start with LU, which the problem
    keeps from then on (here LU fails as well, so the result is the linear solver's failure)."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(
        residual,
        u,
        contact,
        bcs=bcs,
        energy=energy,
        petsc_options_prefix="ldlt_fallback_",  # PETSc keeps options: not the default prefix
        petsc_options={"mat_mumps_icntl_23": 1},
    )
    start = u.x.array.copy()
    solved_with = []

    class CountingSNES:
        def __init__(self, snes):
            self._snes = snes

        def __getattr__(self, name):
            return getattr(self._snes, name)

        def solve(self, *args):
            self._snes.solve(*args)
            solved_with.append(self._snes.getKSP().getPC().getType())

    problem.snes = CountingSNES(problem.snes)
    result = problem.solve(raise_on_failure=False)
    assert solved_with == ["cholesky", "lu"]
    assert not result.converged and result.reason == linear_solver.LINEAR_SOLVE_FAILED
    assert np.array_equal(u.x.array, start)  # no Newton step was taken
    problem.solve(raise_on_failure=False)
    assert solved_with == ["cholesky", "lu", "lu"]  # LU from then on


_NEVER_SOLVED = """
from mpi4py import MPI
import dolfinx, ufl
import fenics_matdepth as fm

mesh = dolfinx.mesh.create_box(
    MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [2, 2, 2], dolfinx.mesh.CellType.tetrahedron
)
V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
u = dolfinx.fem.Function(V)
F = ufl.inner(ufl.grad(u), ufl.grad(ufl.TestFunction(V))) * ufl.dx
contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=1.0)
fm.ContactProblem(F, u, contact, petsc_options_prefix="never_solved_")
"""


def test_a_problem_never_solved_leaves_no_unused_petsc_option(child_env):
    """The working-space option the problem sets for MUMPS is not reported by PETSc as unused
    at exit when the problem never factorises (a created-but-unsolved problem, e.g. a run
    resumed and stopped before its first solve, printed that warning)."""
    if MPI.COMM_WORLD.rank != 0:
        return
    # a fresh serial process (not a rank of this run), PETSc listing unused options at exit
    env = dict(child_env, PETSC_OPTIONS="-options_left", MATDEPTH_QUIET_JIT="1")
    out = subprocess.run(
        [sys.executable, "-c", _NEVER_SOLVED], env=env, capture_output=True, text=True,
        check=True, timeout=600,
    )  # fmt: skip
    printed = out.stdout + out.stderr
    assert "Option left: name:-never_solved_mat_mumps_icntl_14" not in printed, printed
    assert "There are no unused options." in printed, printed


_PLACED_VECTORS = """
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
import fenics_matdepth  # noqa: F401

n = 27_783
values = np.random.default_rng(1).standard_normal((9, n))
x = PETSc.Vec().createWithArray(values[0].copy(), comm=MPI.COMM_SELF)
products = set()
for gap in range(9):
    # the eight vectors y one after the other in one block, as GMRES's work vectors lie, but
    # for a gap before y[gap]: with gemv, each equally spaced run of vectors is one gemv
    block = np.zeros(8 * n + 8)
    ys = []
    for i, v in enumerate(values[1:]):
        start = i * n + (8 if i >= gap else 0)
        block[start : start + n] = v
        ys.append(PETSc.Vec().createWithArray(block[start : start + n], comm=MPI.COMM_SELF))
    products.add(np.asarray(x.mDot(ys)).tobytes())
print(len(products))
"""


def test_multiple_dot_products_do_not_depend_on_where_the_vectors_lie(child_env):
    """GMRES's orthogonalisation (VecMDot) gives the same bits however its vectors lie in
    memory once the package is imported (linear_solver.MDOT_GEMV_OPTION), so a run repeats to
    the bit. With PETSc's gemv kernel (the option given) each equally spaced run of vectors is
    summed by one gemv, so the same products laid out with a gap at nine places differ: the
    test sees the difference it guards against. (The vectors are laid out by hand: where the
    heap puts vectors of their own depends on what the process allocated before.)"""
    if MPI.COMM_WORLD.rank != 0:
        return

    def distinct_results(**extra) -> int:
        env = dict(child_env, MATDEPTH_QUIET_JIT="1", **extra)
        out = subprocess.run(
            [sys.executable, "-c", _PLACED_VECTORS], env=env, capture_output=True, text=True,
            check=True, timeout=600,
        )  # fmt: skip
        return int(out.stdout.split()[-1])

    assert distinct_results() == 1
    # the option given: left as it is, and the layout decides the summation order
    assert distinct_results(PETSC_OPTIONS=f"-{linear_solver.MDOT_GEMV_OPTION} 1") > 1


def test_inertia_counts_negative_and_null_eigenvalues():
    """``linear_solver.inertia`` against numpy's eigenvalues: a random symmetric indefinite
    matrix (its negative eigenvalues counted), the same with two eigenvalues set to zero (the
    null pivots), a definite one (no negative); a matrix that is not symmetric is refused."""
    rng = np.random.default_rng(7)
    n = 40
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    eigenvalues = rng.uniform(0.5, 2.0, n) * np.where(np.arange(n) % 5 == 0, -1.0, 1.0)
    cases = {"indefinite": eigenvalues, "singular": np.where(np.arange(n) < 2, 0.0, eigenvalues)}
    cases["definite"] = np.abs(eigenvalues)
    for name, values in cases.items():
        dense = (Q * values) @ Q.T
        dense = 0.5 * (dense + dense.T)
        computed = np.linalg.eigvalsh(dense)
        expected = (int(np.sum(computed < -1e-8)), int(np.sum(np.abs(computed) <= 1e-8)))
        A = aij_matrix(dense)
        assert linear_solver.inertia(A) == expected, name
        A.destroy()
    assert expected == (0, 0) and cases["indefinite"].min() < 0
    skew = aij_matrix(np.triu(rng.standard_normal((n, n))) + np.eye(n))
    with pytest.raises(ValueError, match="not"):
        linear_solver.inertia(skew)
    skew.destroy()


def test_sum_of_magnitudes_does_not_depend_on_where_the_vector_lies():
    """``linear_solver.abs_sum``, the 1-norm behind the shifted Jacobian's scale
    (``SNESCallbacks._shifted_direction``), gives the same bits wherever the vector lies: the
    correctly rounded sum. PETSc's ``norm(NORM_1)`` (OpenBLAS's asum) sums in an order that
    depends on the address modulo 32 bytes: for these values, placed at the four offsets of 8
    bytes, it gave three results (OpenBLAS 0.3.29 on an AVX-512 machine), and two runs of
    tests/test_ccd_fold.py without the collision detection parted at the first shifted step."""
    values = np.random.default_rng(3).standard_normal(1001)
    expected = math.fsum(np.abs(values))
    block = np.zeros(values.size + 8)
    sums = set()
    for offset in range(4):
        block[offset : offset + values.size] = values
        v = PETSc.Vec().createWithArray(block[offset : offset + values.size], comm=MPI.COMM_SELF)
        sums.add(linear_solver.abs_sum(v))
        v.destroy()
    assert sums == {expected}


def test_convergence_test_stops_a_line_search_without_progress():
    """ContactProblem's convergence test: PETSc's tolerances as SNES holds them, and a stop
    (DIVERGED_LINE_SEARCH) once NO_PROGRESS_ITERATIONS iterations in a row left the residual
    norm unchanged, instead of running on to the iteration limit; a convergence
    (CONVERGED_SNORM_RELATIVE) if that happens below ROUNDING_FLOOR_RTOL of the start."""

    from fenics_matdepth.snes_callbacks import NO_PROGRESS_ITERATIONS

    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    reasons = PETSc.SNES.ConvergedReason
    rtol, atol, _, max_it = problem.snes.getTolerances()

    def run(norms):
        return [problem._converged(problem.snes, i, (1.0, 1.0, f)) for i, f in enumerate(norms)]

    stuck = run([1.0, 0.5] + [0.5] * NO_PROGRESS_ITERATIONS)
    assert stuck[:-1] == [reasons.ITERATING] * (len(stuck) - 1)
    assert stuck[-1] == reasons.DIVERGED_LINE_SEARCH
    # stuck at the rounding floor, far below the start: converged
    floor = 0.1 * snes_callbacks.ROUNDING_FLOOR_RTOL
    at_floor = run([1.0, 1e-3, floor] + [floor] * NO_PROGRESS_ITERATIONS)
    assert at_floor[:-1] == [reasons.ITERATING] * (len(at_floor) - 1)
    assert at_floor[-1] == reasons.CONVERGED_SNORM_RELATIVE
    above = 10.0 * snes_callbacks.ROUNDING_FLOOR_RTOL
    assert run([1.0, above] + [above] * NO_PROGRESS_ITERATIONS)[-1] == reasons.DIVERGED_LINE_SEARCH
    # slow progress is not a stall
    assert set(run([1.0] + [0.5 * (1.0 - 1e-6 * k) for k in range(10)])) == {reasons.ITERATING}
    assert run([1.0, 0.1 * rtol])[-1] == reasons.CONVERGED_FNORM_RELATIVE
    assert run([1.0, 0.1 * atol])[-1] == reasons.CONVERGED_FNORM_ABS
    assert run([1.0, np.nan])[-1] == snes_callbacks.NAN_REASON
    assert run([1.0] + [0.9**k for k in range(1, max_it + 1)])[-1] == reasons.DIVERGED_MAX_IT
    # and a real solve still converges through it
    assert problem.solve().converged


def test_only_a_stalled_energy_step_hands_the_line_search_to_the_residual():
    """The energy line search hands over to |F|^2 / 2 for the rest of a solve when an
    iteration judged by the energy changed |F| by less than STALL_RTOL (the energy's rounding);
    a slow step that |F|^2 / 2 judged (the Dirichlet dofs still moving) does not count. On the
    knee, a start with the femur 0.5 mm off its fixed place lost the energy after three such
    steps and crawled for 50 iterations. Nor does an energy step the collision detection
    shortened: it is short, and says nothing of the energy's rounding (on the knee at 117 deg
    a step cut to 1e-2 by the collision detection handed over at |F| = 67 N, and the step
    took 40 iterations on |F|^2 / 2, 27 with the energy kept)."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)

    class Snes:
        norm = 1.0

        def getFunctionNorm(self):
            return self.norm

        def getSolution(self):
            return u.x.petsc_vec

        def setJacobian(self, *args):
            pass

    snes = Snes()
    problem._energy_merit_allowed, problem._last_norm = True, np.inf
    problem._start_iteration(snes, 0)
    slow = 1.0 - 0.1 * snes_callbacks.STALL_RTOL
    for k, by_energy in enumerate((False, False, False), start=1):
        problem._merit_is_energy = by_energy
        snes.norm *= slow
        problem._start_iteration(snes, k)
    assert problem._energy_merit_allowed
    problem._merit_is_energy, problem._step_capped = True, True
    snes.norm *= slow
    problem._start_iteration(snes, 4)
    assert problem._energy_merit_allowed
    problem._step_capped = False
    snes.norm *= slow
    problem._start_iteration(snes, 5)
    assert not problem._energy_merit_allowed


@pytest.mark.parametrize("case", ["near", "far", "inverting"])
def test_dirichlet_dofs_near_their_values_are_set_onto_them(case):
    """An iterate whose Dirichlet dofs are within DIRICHLET_SNAP of the solve's initial
    distance from their values is set onto them at the next iteration's start, if no element
    inverts: SNES's residual and its norm are then those of the new iterate (an independent
    assembly), and the energy may judge the steps ("near": a fifth of the press left). Not
    with half of it left ("far"), nor where an element would invert ("inverting": the upper
    block lifted 1.0 at the start and 0.2 at the iterate, its top to be pressed 0.03 down:
    0.22 of the start's distance left, but the top layer of cells, 0.13 high, would be pushed
    0.23 down through the block)."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    upper = V.tabulate_dof_coordinates()[: V.dofmap.index_map.size_local, 2] > 0.5 + 1e-9
    x = problem._x
    f = x.duplicate()

    def lift(height):
        x.set(0.0)
        x.getArray()[: 3 * upper.size].reshape(-1, 3)[upper, 2] = height

    class Snes:
        norm = 1.0

        def getFunctionNorm(self):
            return self.norm

        def setFunctionNorm(self, norm):
            self.norm = norm

        def getSolution(self):
            return x

        def getFunction(self):
            return f, None

        def computeFunction(self, state, b):
            problem._residual(self, state, b)

        def setJacobian(self, *args):
            pass

    snes = Snes()
    problem._energy_merit_allowed, problem._last_norm, problem.dirichlet_snaps = True, np.inf, 0
    problem._merit_is_energy = False
    lift(1.0 if case == "inverting" else 0.0)
    problem._start_iteration(snes, 0)
    start = problem.assembler.bc_offset(x)
    assert start == pytest.approx(1.03 if case == "inverting" else 0.03, rel=1e-12)
    if case == "inverting":
        lift(0.2)
    else:
        gap = problem.assembler._bc_gap(x).copy()
        x.axpy(0.8 if case == "near" else 0.5, gap)
        gap.destroy()
    before = x.copy()
    problem._start_iteration(snes, 1)
    if case == "near":
        assert problem.dirichlet_snaps == 1
        assert problem.assembler.bc_offset(x) <= 1e-14
        assert problem._bcs_met
        reference = x.duplicate()
        problem.assembler.set_state(x)
        assert problem.assembler.residual(x, reference)
        assert snes.norm == pytest.approx(reference.norm(), rel=1e-12)
        assert np.allclose(f.getArray(), reference.getArray(), rtol=0.0, atol=1e-12 * snes.norm)
        reference.destroy()
    else:
        assert problem.dirichlet_snaps == 0 and not problem._bcs_met
        assert x.equal(before)
        assert problem.assembler.bc_offset(x) == pytest.approx(
            0.23 if case == "inverting" else 0.015, rel=1e-9
        )
    for vec in (f, before):
        vec.destroy()
    problem.destroy()


@pytest.mark.parametrize("with_energy", [True, False])
def test_the_newton_steps_taken_off_the_dirichlet_values_are_counted(with_energy):
    """The upper block, 0.05 above the lower one, pressed 0.15 down in one solve: the
    collision detection shortens the first Newton steps, so several steps begin with the
    pressed face off its values. The problem's count of such steps equals the count of the
    iterates a monitor found off the values that a step was taken from (none was set onto
    them here), and grows by the second solve's count over a second solve from the same start
    (on the first one's factorisation: another path); with the energy line search and
    without."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm, gap=0.05)
    bcs, _ = _press_bcs(mesh, V, 0.95, -0.15)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    energy = energy if with_energy else None
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    offsets = []

    def monitor(snes, iteration, norm):
        x = snes.getSolution()
        scale = max(x.norm(PETSc.NormType.NORM_INFINITY), 1.0)
        offsets.append((iteration, problem.assembler.bc_offset(x) > 1e-12 * scale))

    problem.snes.setMonitor(monitor)
    expected = 0
    for _ in range(2):
        u.x.array[:] = 0.0
        offsets.clear()
        result = problem.solve()
        assert result.converged and problem.ccd_caps > 0 and problem.dirichlet_snaps == 0
        # the iterates a step was taken from (a solve goes on after GMRES failed on a kept
        # factorisation from the iterate reached, which the monitor sees again)
        taken = [a for a, b in itertools.pairwise(offsets) if b[0] == a[0] + 1]
        assert len(taken) == result.iterations
        off = sum(is_off for _, is_off in taken)
        assert off > 1  # the first step, and steps after it the collision detection shortened
        expected += off
        assert problem.steps_off_dirichlet == expected
    problem.destroy()


def petsc_garbage_entries(comm: MPI.Comm, capfd) -> int:
    """How many PETSc objects wait in PETSc's garbage on ``comm`` (all ranks; collective;
    a mesh's communicator is its own, not MPI.COMM_WORLD).

    On more than one rank petsc4py does not destroy an object whose last reference was a
    Python wrapper: it queues it until ``PETSc.garbage_cleanup``, so an object the library
    drops without ``destroy()`` lingers there (serially it is destroyed at once)."""
    capfd.readouterr()
    PETSc.garbage_view(comm)
    printed = capfd.readouterr().out  # rank 0 prints every rank's table
    count = sum(int(n) for n in re.findall(r"Total entries: (\d+)", printed))
    return comm.bcast(count, root=0)


def _double_well_block(comm, a: float):
    """A soft unit block (no contact, no Dirichlet condition) in the double well
    ``c (u_x^2 - a^2)^2 + k (u_y^2 + u_z^2)``: its minima are u = (+-a, 0, 0)."""
    x, c = box_tetrahedra(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    mesh = create_tetrahedral_mesh(comm, c, x)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    psi, _ = neo_hookean(u, E, NU)
    psi += 1000.0 * (u[0] ** 2 - a**2) ** 2 + 10.0 * (u[1] ** 2 + u[2] ** 2)
    energy = psi * ufl.dx
    residual = ufl.derivative(energy, u, ufl.TestFunction(V))
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=1.0)
    return u, ContactProblem(residual, u, contact, energy=energy)


def test_newton_steps_that_climb_the_energy_are_shifted_downhill(capfd):
    """Near a saddle of the energy (an unstable equilibrium) the Newton step climbs the energy;
    ContactProblem then steps with J + mu I (SHIFT_START) and reaches the minimum. Energy: a
    soft block (no contact) in the double well c (u_x^2 - a^2)^2 + k (u_y^2 + u_z^2), started
    at u_x = a / 10 next to the saddle u = 0; the minimum is u = (a, 0, 0). Plain Newton goes
    to the saddle (checked: its first step has F . y < 0), so the test fails without the
    shift. The shifted steps' solver objects (a KSP, its PC and the MUMPS factorisation) are
    released: on 2 ranks nothing is left in PETSc's garbage (a PC left there per shifted step
    held its factorisation, and the knee's memory grew by GBs)."""
    comm = MPI.COMM_WORLD
    a = 0.1
    u, problem = _double_well_block(comm, a)
    mesh = u.function_space.mesh
    start = np.zeros_like(u.x.array)
    start[0::3] = 0.1 * a
    u.x.array[:] = start
    # the plain Newton step from the start climbs the energy
    x0 = u.x.petsc_vec.copy()
    b = x0.duplicate()
    problem.assembler.set_state(x0)
    problem.assembler.residual(x0, b)
    A = problem.assembler.matrix
    problem.assembler.jacobian(A)
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    y = x0.duplicate()
    ksp.solve(b, y)
    assert b.dot(y) < 0.0
    for obj in (ksp, y, b, x0):
        obj.destroy()

    PETSc.garbage_cleanup(mesh.comm)
    result = problem.solve()
    assert result.converged
    assert np.allclose(u.x.array[0::3], a, rtol=1e-8)
    assert np.allclose(u.x.array[1::3], 0.0, atol=1e-10)
    assert np.allclose(u.x.array[2::3], 0.0, atol=1e-10)
    assert result.shifted_steps >= 1
    assert petsc_garbage_entries(mesh.comm, capfd) == 0


def _solve_recording_moves(problem):
    """Solve ``problem``; returns its result and the largest move of a dof in each Newton
    step."""
    moves = []
    last = problem.u.x.petsc_vec.copy()

    def monitor(snes, k, fnorm):
        x = snes.getSolution()
        if k > 0:
            last.axpy(-1.0, x)
            moves.append(last.norm(PETSc.NormType.NORM_INFINITY))
        x.copy(last)

    problem.snes.setMonitor(monitor)
    result = problem.solve()
    problem.snes.cancelMonitor()
    last.destroy()
    return result, moves


@pytest.mark.parametrize("limit", [None, 0.004])
def test_newton_steps_that_climb_the_energy_can_be_reversed(limit):
    """With ``uphill_step = "reverse"`` a Newton step that climbs the energy is reversed (a
    direction of negative curvature) instead of shifted: the double well from u_x = a / 10
    next to its saddle, where plain Newton goes to the saddle (the test above), reaches the
    minimum u = (a, 0, 0) with reversed steps, no shifted one and no factorisation of a
    shifted matrix, and in fewer Newton iterations than with the shifted steps (17), whose
    component along the negative eigenvector grows by ``mu / (mu - |lambda|)`` an iteration.
    With a step limit the reversed steps are scaled into it (a shifted step that replaces a
    climbing one is not held to the limit: from this start one moves 0.096)."""
    a = 0.1
    counts = {}
    for mode in ("shift", "reverse"):
        u, problem = _double_well_block(MPI.COMM_WORLD, a)
        assert problem.uphill_step == "shift"  # the default
        problem.uphill_step = mode
        problem.step_limit = limit
        u.x.array[0::3] = 0.1 * a
        factorisations = problem.shift_factorisations
        result, moves = _solve_recording_moves(problem)
        assert result.converged
        assert np.allclose(u.x.array[0::3], a, rtol=1e-8)
        assert np.allclose(u.x.array.reshape(-1, 3)[:, 1:], 0.0, atol=1e-9)
        if mode == "shift":
            assert problem.reversed_steps == 0 and result.shifted_steps >= 1
        elif limit is None:
            assert problem.reversed_steps >= 1 and result.shifted_steps == 0
            assert problem.shift_factorisations == factorisations
        else:  # (the downhill steps longer than the limit are shifted into it)
            assert max(moves) <= limit * (1.0 + 1e-12), moves
            assert problem.reversed_steps >= 2
        counts[mode] = result.iterations, problem.reversed_steps
        problem.destroy()
    if limit is None:
        assert counts["reverse"][0] < counts["shift"][0], counts


def test_uphill_step_is_shift_or_reverse():
    _, problem = _double_well_block(MPI.COMM_WORLD, 0.1)
    with pytest.raises(ValueError, match="uphill_step"):
        problem.uphill_step = "flip"
    assert problem.uphill_step == "shift"
    problem.destroy()


@pytest.mark.parametrize("start", [0.1, 0.57])
def test_the_shift_search_ends_on_the_rung_a_climb_from_the_start_takes(start):
    """Where the Newton step climbs the energy, ``_shifted_direction`` searches the ladder of
    shifts from the rung the last such step took: down while the rungs qualify, up until one
    does. From every starting rung it takes the rung a climb from SHIFT_START takes (the double
    well next to its saddle, where that is the last rung, and near its inflection, where it is
    one between), the same step, in one factorisation per rung tried: from the rung of the
    last step, two."""
    a = 0.1
    u, problem = _double_well_block(MPI.COMM_WORLD, a)
    u.x.array[0::3] = start * a
    x = u.x.petsc_vec.copy()
    problem.snes.computeFunction(x, problem._b)
    problem.snes.computeJacobian(x, problem._A)
    y = x.duplicate()
    found = []
    for first in range(snes_callbacks.SHIFT_TRIES):
        problem._uphill_rung = first
        before = problem.shift_factorisations
        assert problem._shifted_direction(y)
        found.append((problem._uphill_rung, problem.shift_factorisations - before, y.copy()))
    climbed, climb_count, climb_step = found[0]
    assert climbed >= 1 and climb_count == climbed + 1  # a climb tries every rung below
    for first, (rung, count, step) in enumerate(found):
        assert rung == climbed
        tried = first - climbed + 1 + (climbed > 0) if first >= climbed else climbed - first + 1
        assert count == tried
        assert np.allclose(step.array, climb_step.array, rtol=1e-8, atol=0.0)
        assert step.dot(problem._b) > 0.0  # downhill
    assert found[climbed][1] == 2
    for v in [x, y] + [step for _, _, step in found]:
        v.destroy()
    problem.destroy()


@pytest.mark.parametrize("limit", [None, 0.02])
def test_a_step_limit_keeps_each_newton_step_within_it(limit):
    """With ``step_limit`` no Newton step moves a dof further than the limit, and the solve
    reaches the same minimum. The double well from u_x = 3a: the first Newton step of the
    quartic alone is 0.092 for a = 0.1, longer than the limit, so without the limit the check
    of the step lengths fails (the case None asserts that it would)."""
    a = 0.1
    u, problem = _double_well_block(MPI.COMM_WORLD, a)
    problem.step_limit = limit
    u.x.array[0::3] = 3.0 * a
    result, moves = _solve_recording_moves(problem)
    assert result.converged
    assert np.allclose(u.x.array[0::3], a, rtol=1e-8)
    assert np.allclose(u.x.array.reshape(-1, 3)[:, 1:], 0.0, atol=1e-9)
    if limit is None:
        assert max(moves) > 0.02 and result.shifted_steps == 0
    else:
        assert max(moves) <= limit * (1.0 + 1e-12), moves
        assert result.shifted_steps >= 1
    problem.destroy()


def _factorisation_analyses() -> int:
    """MUMPS analyses (symbolic factorisations, LU or LDL^T) logged so far in this process."""
    return sum(
        PETSc.Log.Event(name).getPerfInfo()["count"]
        for name in ("MatLUFactorSym", "MatCholFctrSym")
    )


def test_the_shifted_steps_analyse_the_pattern_once(capfd):
    """The step limit's shifted steps factorise ``J + mu I`` anew in every rung, on one kept
    solver whose MUMPS analysis serves every step while the matrix is the problem's: the
    double well from u_x = 3a with the limit 0.02 takes several shifted steps, and the solve
    analyses the pattern twice (the Newton steps' solver and the shifted steps'), not once
    per shifted step (as when each step made its own solver). The steps still keep within
    the limit and reach the minimum; ``destroy`` releases the kept solver (on 2 ranks nothing
    is left in PETSc's garbage)."""
    a = 0.1
    u, problem = _double_well_block(MPI.COMM_WORLD, a)
    mesh = u.function_space.mesh
    problem.step_limit = 0.02
    u.x.array[0::3] = 3.0 * a
    PETSc.Log.begin()
    before = _factorisation_analyses()
    result = problem.solve()
    assert result.converged
    assert np.allclose(u.x.array[0::3], a, rtol=1e-8)
    assert result.shifted_steps >= 3
    assert _factorisation_analyses() - before == 2
    assert problem._shift_kept is not None and problem._shift_kept[0] is problem._A
    problem.destroy()
    assert problem._shift_kept is None
    PETSc.garbage_cleanup(mesh.comm)
    assert petsc_garbage_entries(mesh.comm, capfd) == 0


@pytest.mark.parametrize("value", [0.0, -1.0, np.nan, np.inf])
def test_a_step_limit_must_be_a_positive_length(value):
    _, problem = _double_well_block(MPI.COMM_WORLD, 0.1)
    with pytest.raises(ValueError, match="step_limit"):
        problem.step_limit = value
    assert problem.step_limit is None
    problem.destroy()


@pytest.mark.parametrize("how", ["destroy", "with"])
@pytest.mark.parametrize("kind", ["snes", "newton"])
def test_a_destroyed_problem_is_freed(capfd, how, kind):
    """A problem released with destroy() (or a with block) is freed once nothing refers to
    it, with its solver objects: its callbacks kept it alive before (a reference cycle
    through PETSc's or DOLFINx's C++ objects that Python's garbage collector cannot see), so
    a notebook cell run again kept every earlier problem and its factorisation. On 2 ranks
    nothing is left in PETSc's garbage."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    PETSc.garbage_cleanup(mesh.comm)
    if kind == "snes":
        problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
        solver = None
    else:
        problem = NonlinearContactProblem(residual, u, contact, bcs=bcs)
        solver = problem.newton_solver()
    with problem if how == "with" else contextlib.nullcontext():
        if solver is None:
            assert problem.solve().converged
        else:
            assert solver.solve(u)[1]
    if how == "destroy":
        problem.destroy()
    alive = weakref.ref(problem)
    del problem, solver
    gc.collect()
    assert alive() is None
    assert petsc_garbage_entries(mesh.comm, capfd) == 0


def test_amg_default_above_the_size_threshold(monkeypatch):
    """Above AMG_MIN_DOFS the default linear solver is GMRES + GAMG with the rigid-body
    near-nullspace on the matrix; the contact solve reaches the LU solution. A user's own
    ``pc_type`` keeps its choice."""

    comm = MPI.COMM_WORLD
    solutions = {}
    mesh = None  # one mesh, so that both solutions have one partition
    for name in ("lu", "amg"):
        monkeypatch.setattr(linear_solver, "AMG_MIN_DOFS", 10**12 if name == "lu" else 0)
        mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
        bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
        contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
        problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
        pc = problem.snes.getKSP().getPC()
        assert pc.getType() == ("lu" if name == "lu" else "gamg")
        if name == "amg":
            modes = problem.assembler.matrix.getNearNullSpace()
            assert modes is not None and len(modes.getVecs()) == 6
            # the modes are rigid motions: the bulk stiffness (no Dirichlet rows) maps them to 0
            bulk = dolfinx.fem.petsc.assemble_matrix(problem._J)
            bulk.assemble()
            image = modes.getVecs()[5].duplicate()
            bulk.mult(modes.getVecs()[5], image)
            assert image.norm() <= 1e-10 * bulk.norm()
        result = problem.solve()
        assert result.converged
        solutions[name] = u
    assert _relative_difference(solutions["amg"], solutions["lu"]) <= 1e-7
    mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, petsc_options={"pc_type": "jacobi"})
    assert problem.snes.getKSP().getPC().getType() == "jacobi"


def _record_amg_setups(problem, record: list) -> None:
    """A KSP monitor appending, at each linear solve's start, whether GAMG built its
    hierarchy anew for it (the coarsest operator, a Galerkin product, changed): counted apart
    from the problem's own counters."""
    pc = problem.snes.getKSP().getPC()
    last = [None]

    def monitor(ksp, its, rnorm):
        if its == 0:
            coarse = pc.getMGCoarseSolve().getOperators()[0]
            state = (coarse.handle, coarse.stateGet())
            record.append(state != last[0])
            last[0] = state

    problem.snes.getKSP().setMonitor(monitor)


def test_amg_keeps_its_hierarchy_while_gmres_stays_fast(monkeypatch):
    """The default AMG preconditioner keeps its hierarchy across Newton iterations as the
    direct solver keeps its factorisation: fewer GAMG set-ups than iterations (none in a solve
    that starts on the last solve's hierarchy), the solution of a set-up per iteration. With
    AMG_KEPT_GROWTH 0 every GMRES needs more iterations than the rule allows, and every
    Jacobian gets a new hierarchy."""
    comm = MPI.COMM_WORLD
    monkeypatch.setattr(linear_solver, "AMG_MIN_DOFS", 0)
    runs, mesh = {}, None
    for name, keep, growth in (("kept", True, 2.0), ("every", False, 2.0), ("zero", True, 0.0)):
        monkeypatch.setattr(linear_solver, "AMG_KEPT_GROWTH", growth)
        mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
        bcs, push = _press_bcs(mesh, V, 0.9, -0.02)
        contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
        results = []
        with ContactProblem(
            residual, u, contact, bcs=bcs, energy=energy, keep_factorisation=keep
        ) as problem:
            assert problem.snes.getKSP().getPC().getType() == "gamg"
            setups = []
            _record_amg_setups(problem, setups)
            for depth in (-0.02, -0.03):
                push.x.array.reshape(-1, 3)[:, 2] = depth
                del setups[:]
                result = problem.solve()
                assert result.converged
                results.append((result.iterations, result.factorisations, sum(setups)))
        runs[name] = (results, u)
    for iterations, counted, setups in runs["kept"][0]:
        assert counted == setups < iterations
    # the first solve builds a hierarchy; the second starts on the one the first ended with
    assert runs["kept"][0][0][2] > 0
    for iterations, counted, setups in runs["every"][0]:
        assert counted == 0 and setups == iterations
    for iterations, counted, setups in runs["zero"][0]:
        assert counted == setups == iterations
    assert _relative_difference(runs["kept"][1], runs["every"][1]) <= 1e-7


def test_linear_solve_time_includes_the_factorisation():
    """The reported linear-solve time covers the factorisation (PETSc's PCSetUp event, which
    its KSPSolve event leaves out) as well as the solve."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    PETSc.Log.begin()
    events = [PETSc.Log.Event(name) for name in ("PCSetUp", "KSPSolve")]
    before = sum(event.getPerfInfo()["time"] for event in events)
    problem.solve()
    logged = sum(event.getPerfInfo()["time"] for event in events) - before
    assert logged > 0.0
    assert problem.timings["linear_solve"] >= logged, (problem.timings, logged)


def test_residual_of_the_accepted_step_is_reused_and_exact():
    """Once the line search judges steps by |F|^2 / 2, SNES's residual at an accepted step is
    the one the line search assembled (not assembled again), and it is the residual there: the
    final residual SNES holds equals a fresh assembly at the solution."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    problem.solve()
    assert problem._residuals_reused > 0
    held = problem.snes.getFunction()[0].copy()
    fresh = held.duplicate()
    x = problem.snes.getSolution().copy()
    problem._trial_valid = False  # assemble, whatever the line search held
    problem._residual(problem.snes, x, fresh)
    diff = fresh.copy()
    diff.axpy(-1.0, held)
    # a residual from another point of the line search would differ by about |F| itself
    assert held.norm() > 0.0 and diff.norm() <= 1e-10 * held.norm()
    for vec in (held, fresh, x, diff):
        vec.destroy()


def test_owned_dirichlet_dofs_are_owned_once():
    """`assembly.owned_dirichlet_dofs` returns each rank's owned Dirichlet dofs only: every dof
    of the conditions is owned by exactly one rank, and together they are
    `global_dirichlet_dofs` (ghosts included), on any number of ranks; for conditions on the
    blocked space (one on every dof, so that on 2 ranks the ghosts are Dirichlet dofs
    whatever the partition) and on a subspace."""
    comm = MPI.COMM_WORLD
    mesh, V, _, _, _ = _stacked_blocks(comm)
    press, _ = _press_bcs(mesh, V, 0.9, -0.03)
    side = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], 0.0))
    V1, _ = V.sub(1).collapse()
    dofs = dolfinx.fem.locate_dofs_topological((V.sub(1), V1), 2, side)
    sub = dolfinx.fem.dirichletbc(dolfinx.fem.Function(V1), dofs, V.sub(1))
    every_dof = dolfinx.fem.locate_dofs_geometrical(V, lambda x: np.full(x.shape[1], True))
    everything = dolfinx.fem.dirichletbc(dolfinx.fem.Function(V), every_dof)
    imap = V.dofmap.index_map
    for bcs in (press + [sub], [everything]):
        owned = assembly.owned_dirichlet_dofs(bcs)
        assert np.all(owned < 3 * imap.size_local)
        glob = 3 * imap.local_to_global(owned // 3).astype(np.int64) + owned % 3
        listed = np.concatenate(comm.allgather(glob))
        assert listed.size == np.unique(listed).size  # no dof listed by two ranks
        assert np.array_equal(np.sort(listed), assembly.global_dirichlet_dofs(comm, V, bcs))
    assert listed.size == 3 * imap.size_global


def test_bulk_jacobian_through_dolfinx_csr_equals_dolfinx_petsc_assembly():
    """The problems assemble the bulk Jacobian into DOLFINx's native CSR matrix and add it to
    the contact-pattern matrix (fenics_matdepth._bulk): equal to dolfinx.fem.petsc's assembly
    into the same matrix at a deformed state with Dirichlet rows and columns, on any number
    of ranks (ghost rows summed into their owners)."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, _ = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    u.interpolate(lambda p: np.vstack((0.05 * p[1] * p[2], -0.03 * p[0] ** 2, 0.04 * p[0] * p[1])))
    a = dolfinx.fem.form(ufl.derivative(residual, u, ufl.TrialFunction(V)))
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=1.0)
    bulk = BulkMatrix(a, bcs, assembly.global_dirichlet_dofs(comm, V, bcs))
    mine, theirs = contact.create_matrix(a, bcs), contact.create_matrix(a, bcs)
    for _ in range(2):  # the second assembly starts from the first's values
        mine.zeroEntries()
        bulk.add_to(mine)
        mine.assemble()
    theirs.zeroEntries()
    dolfinx.fem.petsc.assemble_matrix(theirs, a, bcs)
    theirs.assemble()
    # the Dirichlet rows hold 1 on the diagonal only
    owned = assembly.owned_dirichlet_dofs(bcs)
    assert comm.allreduce(owned.size) > 0
    r0, r1 = mine.getOwnershipRange()
    assert np.all(owned < r1 - r0)
    for row in owned:
        cols, vals = mine.getRow(r0 + int(row))
        assert np.array_equal(vals[vals != 0.0], [1.0]) and cols[vals != 0.0][0] == r0 + row
    reference = theirs.norm(PETSc.NormType.FROBENIUS)
    assert reference > 0.0
    mine.axpy(-1.0, theirs)
    assert mine.norm(PETSc.NormType.FROBENIUS) <= 1e-13 * reference
    for mat in (mine, theirs):
        mat.destroy()


def test_bulk_jacobian_reused_while_nothing_it_reads_changes():
    """BulkMatrix adds the last assembly's values again, without assembling, while the form's
    constants, coefficients and mesh coordinates are unchanged (a Jacobian independent of the
    displacement), and assembles again when any of them changes: the matrix equals
    dolfinx.fem.petsc's assembly after every change, on any number of ranks."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, _ = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    stiffness = dolfinx.fem.Constant(mesh, 2.0)
    field = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("DG", 0)))
    field.x.array[:] = 1.0
    du, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    sym = ufl.sym
    linear = dolfinx.fem.form(
        stiffness * field * ufl.inner(sym(ufl.grad(du)), sym(ufl.grad(v))) * ufl.dx
    )
    nonlinear = dolfinx.fem.form(ufl.derivative(residual, u, du))
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=1.0)
    dirichlet = assembly.global_dirichlet_dofs(comm, V, bcs)

    def check(bulk, a, reused):
        mine, theirs = contact.create_matrix(a, bcs), contact.create_matrix(a, bcs)
        bulk.add_to(mine)
        mine.assemble()
        dolfinx.fem.petsc.assemble_matrix(theirs, a, bcs)
        theirs.assemble()
        reference = theirs.norm(PETSc.NormType.FROBENIUS)
        mine.axpy(-1.0, theirs)
        assert mine.norm(PETSc.NormType.FROBENIUS) <= 1e-13 * reference
        assert bulk.reused == reused
        for mat in (mine, theirs):
            mat.destroy()

    bulk = BulkMatrix(linear, bcs, dirichlet)
    check(bulk, linear, 0)
    u.x.array[:] = 0.01  # the linear form does not read u
    check(bulk, linear, 1)
    check(bulk, linear, 2)
    stiffness.value = 3.0  # a constant
    check(bulk, linear, 2)
    check(bulk, linear, 3)
    field.x.array[: field.x.array.size // 2] = 0.5  # a coefficient (on some rank)
    check(bulk, linear, 3)
    mesh.geometry.x[:, 2] *= 1.1  # the mesh
    check(bulk, linear, 3)
    check(bulk, linear, 4)
    mesh.geometry.x[:, 2] /= 1.1
    bulk = BulkMatrix(nonlinear, bcs, dirichlet)
    for step in range(3):  # reads u, which changes
        u.x.array[:] = 0.01 * step
        check(bulk, nonlinear, 0)


def test_line_search_start_merit_is_not_evaluated_again():
    """The line search asks its merit function (the energy, then |F|^2 / 2 near the solution)
    at the step's start, where the last step's trial evaluated it already, and at its trial
    points: within a solve no point's residual is assembled twice, nor its energy evaluated
    twice; with full steps the residual is assembled once per iteration plus once at the
    start."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, _ = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    points = {"residual": [], "total_energy": []}
    for name, seen in points.items():
        original = getattr(problem.assembler, name)

        def counted(*args, _original=original, _seen=seen):
            _seen.append(u.x.array.copy())  # the state it is evaluated at
            return _original(*args)

        setattr(problem.assembler, name, counted)
    result = problem.solve()
    assert result.converged and result.iterations >= 3
    assert not problem._merit_is_energy  # (the last steps were judged by |F|^2 / 2)
    for name, seen in points.items():
        assert len(seen) > 1, name
        twice = [
            (i, j) for i in range(len(seen)) for j in range(i) if np.array_equal(seen[i], seen[j])
        ]
        assert not twice, (name, twice)
    # (this press takes full steps)
    assert len(points["residual"]) == result.iterations + 1


@pytest.mark.parametrize("offset", [0.0, 1e-13])
def test_the_residual_is_dolfinx_lifted_residual(offset):
    """The residual is DOLFINx's (the form, apply_lifting, set_bc) plus the contact's, to the
    bit. Where every Dirichlet dof holds its value (offset 0) the assembler leaves out
    apply_lifting, whose A (g - x) is then zero; a Dirichlet dof off its value by 1e-13
    (below any tolerance) brings the lifting back, which the bits tell (checked: with the
    lifting left out there, they differ). At a pressed state with contact, the free dofs moved
    off it so that the residual is not small."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    bcs, g = _press_bcs(mesh, V, 0.9, -0.03)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    assert problem.solve().converged
    assert contact.diagnostics()["active_pairs"] > 0
    assembler = problem.assembler
    x = u.x.petsc_vec.copy()
    owned = x.getLocalSize()
    held = assembly.owned_dirichlet_dofs(bcs)
    free = ~np.isin(np.arange(owned), held)
    rng = np.random.default_rng(comm.rank)
    x.getArray()[free] += 1e-3 * rng.standard_normal(int(free.sum()))
    moved = held[np.abs(g.x.array[held]) > 0.0]
    x.getArray()[moved[:1]] += offset
    x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    b, reference = x.duplicate(), x.duplicate()
    assembler.set_state(x)
    assert assembler.residual(x, b)
    with reference.localForm() as local:
        local.set(0.0)
    dolfinx.fem.petsc.assemble_vector(reference, assembler.L)
    contact.add_residual(reference)
    increment = assembler._dirichlet_increment(x)
    assert (increment is None) == (comm.allreduce(moved[:1].size) == 0 or offset == 0.0)
    if increment is not None:
        contact.add_lifting(reference, increment)
    dolfinx.fem.petsc.apply_lifting(reference, [assembler.a], [bcs], x0=[x], alpha=-1.0)
    reference.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    dolfinx.fem.petsc.set_bc(reference, bcs, x, -1.0)
    assert b.norm() > 1e-3
    assert np.array_equal(b.getArray(), reference.getArray())
    for vec in (x, b, reference):
        vec.destroy()
    problem.destroy()


@pytest.mark.parametrize("friction", [False, True], ids=["frictionless", "friction"])
def test_residual_lifts_the_contact_coupling_to_prescribed_values(friction):
    """With Dirichlet values not yet reached, the residual holds the contact Hessian's share of
    the lifting, as apply_lifting adds the bulk's: at x with the indenter's prescribed
    displacement raised by eps d, its free rows equal, to O(eps^2), the residual at x with the
    indenter moved there (no lifting needed), so the Newton step with the Dirichlet columns
    zeroed is exact. Without the contact share the difference is O(eps). With friction the
    indenter is also moved sideways from the friction's reference (the pressed state), and the
    friction Hessian's share is checked to be needed for the second order."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, energy = _stacked_blocks(comm)
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, tdim)
    upper = dolfinx.mesh.locate_entities(mesh, tdim, lambda x: x[2] >= 0.5 - 1e-9)
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    # the upper block is a rigid indenter: every one of its dofs prescribed
    g = dolfinx.fem.Function(V)
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, 2, bottom)
        ),
        dolfinx.fem.dirichletbc(g, dolfinx.fem.locate_dofs_topological(V, tdim, upper)),
    ]
    law = fm.Coulomb(0.5) if friction else None
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0, friction=law)
    problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    g.x.array.reshape(-1, 3)[:, 2] = -0.01
    assert problem.solve().converged
    assert contact.diagnostics()["active_pairs"] > 0
    contact.advance()  # the friction's reference: the pressed state (nothing without friction)
    # with friction the indenter moves only sideways (its slip a fifth of the slip tolerance at
    # eps = 1e-2), so that the friction's share is most of the lifting
    side = 0.2 * contact.slip_tol if friction else 0.0
    down = 0.0 if friction else 0.01
    assembler = problem.assembler
    x = u.x.petsc_vec.copy()
    free = ~np.isin(np.arange(x.getLocalSize()), assembly.owned_dirichlet_dofs(bcs))
    lifted, moved = x.duplicate(), x.duplicate()

    def differences(eps: float) -> tuple[float, float, float]:
        g.x.array.reshape(-1, 3)[:, 2] = -0.01 - down * eps
        g.x.array.reshape(-1, 3)[:, 0] = side * eps * 100.0
        # at x, the indenter not yet moved: lifted residual, and its contact share
        assembler.set_state(x)
        assert assembler.residual(x, lifted)
        increment = assembler._dirichlet_increment(x)
        share, friction_share = x.duplicate(), x.duplicate()
        share.zeroEntries()
        contact.add_lifting(share, increment)
        friction_share.zeroEntries()
        contact._add_friction_lifting(friction_share, increment)
        friction_share.assemble()
        # the indenter moved onto its values
        y = x.copy()
        dolfinx.fem.petsc.set_bc(y, bcs)
        assembler.set_state(y)
        assert assembler.residual(y, moved)
        out = tuple(
            np.sqrt(comm.allreduce(float(a[free] @ a[free])))
            for a in (lifted.getArray() - moved.getArray(), share.getArray(),
                      friction_share.getArray())
        )  # fmt: skip
        for vec in (share, friction_share, y):
            vec.destroy()
        return out

    coarse, _, _ = differences(1e-2)
    fine, share_fine, friction_fine = differences(1e-3)
    assert share_fine > 0.0
    # second order: ten times smaller a step, about a hundred times smaller a difference;
    # without the contact share the difference would be of the share's size (first order)
    assert fine <= 0.03 * coarse, (coarse, fine)
    assert fine <= 0.05 * share_fine, (fine, share_fine)
    if friction:
        # without the friction's share the difference would be of its size
        assert fine <= 0.05 * friction_fine, (coarse, fine, share_fine, friction_fine)
    else:
        assert friction_fine == 0.0
    for vec in (x, lifted, moved):
        vec.destroy()


def _gap_closing(comm, solver: str, mesh=None):
    """The upper block starts 0.05 above the lower one (more than the pattern margin) and its
    top is pushed down 0.08 in two load steps: contact appears outside the first pattern."""
    mesh, V, u, residual, energy = _stacked_blocks(comm, gap=0.05, mesh=mesh)
    bcs, g = _press_bcs(mesh, V, 0.95, 0.0)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    assert contact.margin < 0.05
    if solver == "snes":
        problem = ContactProblem(residual, u, contact, bcs=bcs, energy=energy)
    else:
        with warnings.catch_warnings():  # DOLFINx >= 0.10 deprecates the NewtonSolver
            warnings.simplefilter("ignore", DeprecationWarning)
            problem = NonlinearContactProblem(residual, u, contact, bcs=bcs)
            problem.newton_solver()

    def set_load(t):
        g.x.array.reshape(-1, 3)[:, 2] = -0.08 * t

    return problem, set_load


@pytest.mark.parametrize("solver", ["snes", "newton"])
def test_pattern_rebuilt_when_contact_appears(solver):
    problem, set_load = _gap_closing(MPI.COMM_WORLD, solver)
    assert problem.contact.energy() == 0.0
    steps = fm.solve_load_steps(problem, set_load, num_steps=2)
    assert np.isclose(steps[-1].load, 1.0)
    assert problem.pattern_rebuilds >= 1
    assert steps[-1].diagnostics["active_pairs"] > 0
    A = problem._A if solver == "snes" else problem.matrix
    assert A.getInfo()["mallocs"] == 0
    _assert_quadratic(steps[-1].residual_norms)
    # each step keeps its own solve's time split (problem.timings holds the last one only)
    if solver == "snes":
        assert steps[-1].timings == problem.timings
        for step in steps:
            # the split's parts, the collision detection's time among them
            assert set(step.timings) == set(system_assembler.TIMING_KEYS)
            assert 0.0 < sum(step.timings.values()) <= step.seconds, step
        # the whole run's split: the steps' solves summed (no step was cut here), then a
        # failed solve's added to it
        run = problem.assembler.run_timings
        assert all(step.cuts == 0 for step in steps)
        for key in system_assembler.TIMING_KEYS:
            assert np.isclose(run[key], sum(step.timings[key] for step in steps)), key
        problem.snes.setTolerances(max_it=1)
        set_load(2.0)
        assert not problem.solve(raise_on_failure=False).converged
        after = problem.assembler.run_timings
        for key in system_assembler.TIMING_KEYS:
            assert np.isclose(after[key], run[key] + problem.timings[key]), key
        assert sum(after.values()) > sum(run.values())
    else:
        assert all(step.timings == {} for step in steps)


def test_newton_solver_problem_matches_snes():
    """NonlinearContactProblem (dolfinx NewtonSolver, full steps) reaches the SNES solution."""
    comm = MPI.COMM_WORLD
    snes, set_snes = _gap_closing(comm, "snes")
    newton, set_newton = _gap_closing(comm, "newton", snes.u.function_space.mesh)
    fm.solve_load_steps(snes, set_snes, num_steps=2, progress=False)
    fm.solve_load_steps(newton, set_newton, num_steps=2, progress=False)
    a, b = snes.u.x.array, newton.u.x.array
    assert np.abs(a - b).max() <= 1e-8 * np.abs(a).max()
    assert snes.snes.getKSP().getPC().getType() == "cholesky"  # symmetric: LDL^T


def test_newton_solver_needs_the_contact_matrix():
    import dolfinx.nls.petsc

    comm = MPI.COMM_WORLD
    mesh, V, u, residual, _ = _stacked_blocks(comm, sink=0.01)
    bcs, _ = _press_bcs(mesh, V, 0.89, 0.0)
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=200.0, allow_reference_overlap=True
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        problem = NonlinearContactProblem(residual, u, contact, bcs=bcs)
        solver = dolfinx.nls.petsc.NewtonSolver(comm, problem)
    with pytest.raises(RuntimeError, match="attach"):
        solver.solve(u)


class _FailsOnLargeSteps:
    """Wraps a problem; a solve whose load increment exceeds ``limit``, or whose load exceeds
    ``max_load``, fails (and leaves NaN in u, as a diverged solve would); a successful one
    adds 1 to u."""

    def __init__(self, problem, limit: float, max_load: float = np.inf):
        self.problem, self.limit, self.max_load = problem, limit, max_load
        self.u, self.contact = problem.u, problem.contact
        self.load = self.converged_load = 0.0
        self.start_states: list[np.ndarray] = []

    def set_load(self, t: float) -> None:
        self.load = t

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        self.start_states.append(self.u.x.array.copy())
        if self.load - self.converged_load > self.limit + 1e-12 or self.load > self.max_load:
            self.u.x.array[:] = np.nan
            return SolveResult(False, -1, 3, np.array([1.0, 2.0, 4.0]))
        self.u.x.array[:] += 1.0
        self.converged_load = self.load
        return SolveResult(True, 2, 1, np.array([1.0, 1e-12]))


def _touching_problem(comm, mesh=None):
    mesh, V, u, residual, energy = _stacked_blocks(comm, mesh=mesh)
    bcs, g = _press_bcs(mesh, V, 0.9, 0.0)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=200.0)
    return ContactProblem(residual, u, contact, bcs=bcs, energy=energy), g


def test_load_steps_cut_and_grow_back():
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    flaky = _FailsOnLargeSteps(problem, limit=0.3)
    written = []
    steps = fm.solve_load_steps(flaky, flaky.set_load, num_steps=2, writer=written.append)
    # 0.5 fails -> 0.25; grows back to 0.5 -> fails -> 0.25 ... the last increment is 0.25
    assert [s.load for s in steps] == [0.25, 0.5, 0.75, 1.0]
    assert [s.cuts for s in steps] == [1, 1, 1, 0]
    assert written == [0.25, 0.5, 0.75, 1.0]
    # every retry starts from the last converged state, not from the failed one
    assert all(np.all(np.isfinite(s)) for s in flaky.start_states)
    assert np.all(flaky.u.x.array == 4.0)


def test_load_steps_give_up_below_min_step_keeping_the_last_state():
    comm = MPI.COMM_WORLD
    problem, _ = _touching_problem(comm)
    flaky = _FailsOnLargeSteps(problem, limit=1.0, max_load=0.5)
    with pytest.raises(RuntimeError, match=r"stopped at load factor 0\.5"):
        fm.solve_load_steps(flaky, flaky.set_load, num_steps=2, min_step=0.01, progress=False)
    # 0.5 converged; 1.0, 0.75, ..., 0.515625 failed; 0.0078 < min_step
    assert len(flaky.start_states) == 7
    assert np.all(flaky.u.x.array == 1.0)
    assert flaky.load == 0.5


def test_load_steps_reach_the_one_step_solution(tmp_path_factory):
    """Pressing in three load steps (written to VTX for ParaView) ends where one step does."""
    comm = MPI.COMM_WORLD
    one, g1 = _touching_problem(comm)
    g1.x.array.reshape(-1, 3)[:, 2] = -0.04
    one.solve()
    stepped, g3 = _touching_problem(comm, one.u.function_space.mesh)

    def set_load(t):
        g3.x.array.reshape(-1, 3)[:, 2] = -0.04 * t

    folder = Path(comm.bcast(str(tmp_path_factory.mktemp("vtx")) if comm.rank == 0 else None))
    with dolfinx.io.VTXWriter(comm, folder / "press.bp", [stepped.u], engine="BP4") as vtx:
        steps = fm.solve_load_steps(stepped, set_load, num_steps=3, writer=vtx)
    assert [s.cuts for s in steps] == [0, 0, 0]
    assert np.isclose(steps[-1].load, 1.0)
    assert steps[-1].diagnostics["active_pairs"] > 0
    assert (folder / "press.bp").exists()
    a, b = one.u.x.array, stepped.u.x.array
    assert np.abs(a - b).max() <= 1e-8 * np.abs(a).max()


def test_contact_with_body_force_and_follower_pressure():
    """Contact added unchanged to a user's own form: weight plus a follower pressure on the
    upper block's top face, whose sides are held only horizontally (u_x = u_y = 0 on the
    top). At equilibrium the vertical contact force on the upper block balances the weight
    and the pressure's vertical resultant on the deformed top face (computed by UFL)."""
    comm = MPI.COMM_WORLD
    mesh, V, u, residual, _ = _stacked_blocks(comm, sink=0.005)
    top_z = 0.895
    fdim = 2
    top = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], top_z))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], 0.0))
    tags = dolfinx.mesh.meshtags(mesh, fdim, top, np.full(top.size, 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags)
    rho_g = dolfinx.fem.Constant(mesh, 0.05)
    pressure = dolfinx.fem.Constant(mesh, 0.02)
    v = ufl.TestFunction(V)
    F_def = ufl.Identity(3) + ufl.grad(u)
    N = ufl.FacetNormal(mesh)
    # follower load: the pressure acts on the current area along the current normal
    traction = -pressure * ufl.det(F_def) * ufl.inv(F_def).T * N
    body = ufl.as_vector((0.0, 0.0, -1.0)) * rho_g
    # the upper block's cells: their midpoints lie above z = 0.5 (DG0 interpolates there)
    upper = dolfinx.fem.Function(dolfinx.fem.functionspace(mesh, ("DG", 0)))
    upper.interpolate(lambda x: (x[2] > 0.5).astype(float))
    F = residual - ufl.inner(traction, v) * ds(1) - upper * ufl.inner(body, v) * ufl.dx
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, fdim, bottom)
        )
    ]
    for c in (0, 1):
        Vc = V.sub(c)
        dofs = dolfinx.fem.locate_dofs_topological(Vc, fdim, top)
        bcs.append(dolfinx.fem.dirichletbc(dolfinx.default_scalar_type(0.0), dofs, Vc))
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=200.0, allow_reference_overlap=True
    )
    problem = ContactProblem(F, u, contact, bcs=bcs, petsc_options_prefix="combined_")
    result = problem.solve()
    assert result.converged
    _assert_quadratic(result.residual_norms)

    def total(form):
        return comm.allreduce(dolfinx.fem.assemble_scalar(dolfinx.fem.form(form)))

    weight = total(upper * rho_g * ufl.dx)
    pressure_z = total(traction[2] * ds(1))
    assert pressure_z < 0.0 and weight > 0.0
    res = contact.force_resultants()
    upper_body = contact.body_of_vertex[np.argmax(contact.surface.gathered()["X"][:, 2])]
    expected = weight - pressure_z  # the contact force holds both up
    assert abs(res[upper_body, 2] - expected) <= 1e-8 * expected, (res, expected)
