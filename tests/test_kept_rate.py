"""The rate test of GMRES on a kept factorisation (``linear_solver.KeptRateTest``): a solve
whose first iterations predict more than RATE_TEST_LIMIT iterations stops at the
RATE_TEST_ITERATION-th as diverged; one that will converge is left alone and ends where it
ends without the test."""

from __future__ import annotations

import math

from mpi4py import MPI
from petsc4py import PETSc

import numpy as np
import pytest

from fenics_matdepth import linear_solver
from fenics_matdepth.linear_solver import (
    RATE_TEST_ITERATION,
    KeptRateTest,
    predicted_iterations,
)


def test_the_predicted_iterations_follow_the_mean_rate():
    # 1e-2 in 5 iterations is 1e-0.4 each: 1e-10 in 25
    assert predicted_iterations(5, 1e-2, 1e-10) == pytest.approx(25.0)
    assert predicted_iterations(4, 0.5, 2.0**-12) == pytest.approx(48.0)
    assert predicted_iterations(5, 1.0, 1e-10) == math.inf  # no progress
    assert predicted_iterations(5, 3.0, 1e-10) == math.inf  # the residual grew
    assert predicted_iterations(5, 0.0, 1e-10) == 0.0  # (solved exactly)


def _laplacian(comm, n: int, changed: int = 0) -> PETSc.Mat:
    """The 1D Laplacian of n points (Dirichlet ends), distributed over ``comm``; with
    ``changed`` > 0, that many diagonal entries, spread over the points, raised by 1 (a change
    of that rank, as a few contact pairs change a Jacobian between two Newton steps)."""
    A = PETSc.Mat().createAIJ([n, n], nnz=3, comm=comm)
    start, end = A.getOwnershipRange()
    raised = {int((j + 0.5) * n / changed) for j in range(changed)}
    for i in range(start, end):
        A[i, i] = 2.0 + (1.0 if i in raised else 0.0)
        if i > 0:
            A[i, i - 1] = -1.0
        if i < n - 1:
            A[i, i + 1] = -1.0
    A.assemble()
    return A


def _kept_gmres(A: PETSc.Mat, P: PETSc.Mat, pc_type: str, rate_test: KeptRateTest | None):
    """GMRES as the kept factorisation runs it (KEPT_FACTORISATION_OPTIONS' settings) on A,
    preconditioned by ``pc_type`` of P; the iterations, the reason and the solution."""
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setOperators(A, P)
    options = linear_solver.KEPT_FACTORISATION_OPTIONS
    ksp.setType(options["ksp_type"])
    ksp.setPCSide(PETSc.PC.Side.RIGHT)
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setTolerances(rtol=options["ksp_rtol"], atol=0.0, max_it=options["ksp_max_it"])
    ksp.setGMRESRestart(options["ksp_gmres_restart"])
    pc = ksp.getPC()
    pc.setType(pc_type)
    if pc_type == "lu":
        pc.setFactorSolverType("mumps")
    if rate_test is not None:
        ksp.addConvergenceTest(rate_test)
    b, x = A.createVecs()
    b.set(1.0)
    ksp.solve(b, x)
    result = ksp.getIterationNumber(), ksp.getConvergedReason(), x.copy()
    for obj in (ksp, b, x):
        obj.destroy()
    return result


def test_gmres_that_will_not_converge_stops_at_the_rate_test():
    """Jacobi on a Laplacian of 400 points falls far too slowly to reach 1e-10 in
    KEPT_MAX_ITERATIONS: with the test GMRES stops at the 5th iteration, as diverged, and the
    test counts it; without it GMRES runs to the limit."""
    A = _laplacian(MPI.COMM_WORLD, 400)
    test = KeptRateTest()
    its, reason, _ = _kept_gmres(A, A, "jacobi", test)
    assert (its, reason) == (RATE_TEST_ITERATION, PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT)
    assert test.stops == 1
    its, reason, _ = _kept_gmres(A, A, "jacobi", None)
    assert (its, reason) == (
        linear_solver.KEPT_MAX_ITERATIONS, PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
    )  # fmt: skip
    A.destroy()


def test_gmres_that_converges_is_left_alone():
    """The factorisation of a Laplacian preconditions GMRES on the Laplacian changed in rank 8:
    GMRES converges in 9 iterations, past the 5th, at a rate the test lets go on (its first
    five iterations already fell steadily); with the test it takes the same iterations to the
    same solution, and the test stops nothing."""
    comm = MPI.COMM_WORLD
    A, P = _laplacian(comm, 400, changed=8), _laplacian(comm, 400)
    test = KeptRateTest()
    with_test = _kept_gmres(A, P, "lu", test)
    without = _kept_gmres(A, P, "lu", None)
    assert with_test[:2] == (9, PETSc.KSP.ConvergedReason.CONVERGED_RTOL)
    assert with_test[0] == without[0] and test.stops == 0
    assert np.array_equal(with_test[2].getArray(), without[2].getArray())
    for obj in (A, P, with_test[2], without[2]):
        obj.destroy()
