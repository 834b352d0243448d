"""The linear-solver policy of the contact problems: PETSc options, the kept factorisation,
the AMG thresholds and the elasticity near-nullspace they use, the choice of LDL^T or LU,
MUMPS helpers.

Importing this module (which ``import fenics_matdepth`` does first) turns PETSc's gemv
summation of multiple dot products off (:data:`MDOT_GEMV_OPTION`), so that the vectors created
afterwards sum in a fixed order and a run repeats to the bit.
"""

from __future__ import annotations

import math

from petsc4py import PETSc

import dolfinx
import numpy as np

__all__ = [
    "AMG_KEPT_GROWTH",
    "AMG_MIN_DOFS",
    "AMG_OPTIONS",
    "DEFAULT_OPTIONS",
    "FRICTION_SWITCH_SHARE",
    "KEPT_FACTORISATION_OPTIONS",
    "KEPT_MAX_ITERATIONS",
    "KEPT_TRIES",
    "RATE_TEST_ITERATION",
    "RATE_TEST_LIMIT",
    "LDLT_WORKSPACE_PERCENT",
    "NULL_PIVOT_RTOL",
    "LINEAR_SOLVE_FAILED",
    "MDOT_GEMV_OPTION",
    "REFACTORISE_ITERATIONS",
    "SYMMETRY_RTOL",
    "BackOff",
    "KeptRateTest",
    "abs_sum",
    "choose_factorisation",
    "fix_summation_order",
    "inertia",
    "is_mumps_direct",
    "predicted_iterations",
    "rigid_body_modes",
    "set_solver_options",
]

DEFAULT_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "bt",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-12,
    "snes_stol": 0.0,
    "snes_max_it": 50,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}

#: With ``keep_factorisation=True`` (the default), ContactProblem's direct solver keeps a
#: factorisation across the Newton iterations of a solve: each Jacobian is solved by flexible
#: GMRES (right-preconditioned, to 1e-10 of the residual: an exact Newton step) preconditioned
#: by the last factorisation. A Jacobian is factorised anew after the matrix's pattern was
#: rebuilt and once GMRES needed more than REFACTORISE_ITERATIONS iterations; a solve starts on
#: the last solve's factorisation if that solve converged (a load step, a time step or a
#: pressure update later the Jacobian changed little) and the contact penalty is the same,
#: otherwise it factorises its first Jacobian. GMRES stops after KEPT_MAX_ITERATIONS, where a kept
#: factorisation no longer pays (one factorisation costs about 30 GMRES iterations on
#: benchmarks/bench_factor.py's press, 25k dofs: LDL^T analysis and factorisation 0.84 s, one
#: substitution 27 ms; about 11 on the knee's coarse leg: 0.18 s against 16 ms), and the solve
#: goes on from the iterate it had reached, whose Jacobian is factorised. When that happened
#: KEPT_TRIES times in a solve on the first GMRES after a factorisation, the Jacobian changes
#: too much from one iteration to the next: the solve factorises every Jacobian from then on,
#: and the problem's next 1, 2, 4, ... solves do not try (until a kept factorisation pays
#: again). (Once is common: a load step's first Newton step changes the contact set.) When
#: GMRES fails on the factorisation a solve started on, the next 1, 2, 4, ... solves factorise
#: their first Jacobian. Measured:
#: the press's GMRES took 3 to 11 iterations; the knee's first GMRES on a new factorisation 18
#: to 61. Giving ``ksp_type`` or ``pc_type`` turns it off.
REFACTORISE_ITERATIONS = 10
KEPT_MAX_ITERATIONS = 20
KEPT_TRIES = 2
#: GMRES on a kept factorisation stops at its RATE_TEST_ITERATION-th iteration where the mean
#: rate so far predicts more than RATE_TEST_LIMIT iterations to its tolerance
#: (:class:`KeptRateTest`): such a solve will not converge within KEPT_MAX_ITERATIONS, and the
#: iterations after the test would be spent for nothing (the solve goes on as after any
#: failure, from the same iterate, with its Jacobian factorised). Measured on the knee's
#: penalty-2 path (``benchmarks/bench_knee.py``, 554 Newton iterations): at the 5th
#: iteration the 33 solves that went on to converge predicted 5 to 38 iterations, the 72 that
#: failed at 20 predicted 16 to 826; with the test 36 of them stopped at the 5th, the path
#: the same to the bit, and the failed solves' GMRES iterations fell from 1,440 to 900.
RATE_TEST_ITERATION = 5
RATE_TEST_LIMIT = 2 * KEPT_MAX_ITERATIONS
#: With Coulomb friction a Jacobian is also factorised anew, before GMRES is tried on the kept
#: factorisation, once the tangential stiffness of more than this share of the friction points
#: moved by more than a factor 2 since the factorisation (``ContactOperator.stick_slip_change``;
#: always at the first Jacobian of a step, whose points are new and all stick): a point that
#: switches between stick (stiffness ``2 c / e``) and slip (``c / y``) changes the Jacobian by a
#: term of its rank, and thousands switch in the first iterations of a step that slides, more
#: than GMRES resolves in KEPT_MAX_ITERATIONS. Measured on benchmarks/bench_friction.py's model
#: (55k friction points) without this rule, GMRES on the kept factorisation needed 11 to 13
#: iterations after 870 to 1180 points switched, 26 to 57 after 2300 to 10200 (a factorisation
#: costs about 30) and did not converge in 60 after 13000 and more, nor on the last step's
#: factorisation at a step's start. Against the share defined here (on that model and a
#: smaller one): 8 to 16 iterations at shares up to 0.046, a failure at 0.049, and failures at
#: 0.001 only where the normal contact's set moved (as without friction). The rule spared 2 of
#: the 4 failed GMRES solves and 2 of the 26 factorisations of that benchmark.
FRICTION_SWITCH_SHARE = 0.03
KEPT_FACTORISATION_OPTIONS = {
    # flexible GMRES keeps the preconditioned vectors: no substitution more to form the
    # solution, which right-preconditioned GMRES spends on every solve (measured on the knee:
    # a factorised solve 0.18 to 0.19 s with preonly, 0.21 to 0.23 s with GMRES)
    "ksp_type": "fgmres",
    "ksp_pc_side": "right",
    "ksp_norm_type": "unpreconditioned",
    "ksp_rtol": 1e-10,
    "ksp_atol": 0.0,
    "ksp_max_it": KEPT_MAX_ITERATIONS,
    "ksp_gmres_restart": KEPT_MAX_ITERATIONS,
}

#: From this many global dofs on, ContactProblem's default linear solver is GMRES preconditioned
#: by GAMG with the rigid-body near-nullspace (AMG_OPTIONS) instead of MUMPS LU. Measured with
#: benchmarks/bench_linear.py on the press's contact Jacobian (CPU seconds of set-up + solve):
#: 24.7k dofs LU 1.24, GAMG 1.19; 92.3k dofs LU 12.2, GAMG 4.5; 282k dofs GAMG 16.9.
AMG_MIN_DOFS = 50_000
#: With ``keep_factorisation=True`` (the default), ContactProblem's default AMG preconditioner
#: keeps its hierarchy across Newton iterations, as the direct solver keeps its factorisation
#: (same rules: a new one at a solve's start unless it starts on the last solve's, on a new
#: pattern, after a GMRES failure): GAMG's set-up is redone once GMRES on the kept hierarchy
#: needs more than AMG_KEPT_GROWTH times the iterations it needed on a new one. A GAMG set-up
#: costs about 30 GMRES iterations (the Hertz benchmark, 96k dofs: 1.3 s against 0.04 s, the
#: Galerkin products PtAP most of it).
AMG_KEPT_GROWTH = 2.0
AMG_OPTIONS = {
    "ksp_type": "gmres",
    "ksp_gmres_restart": 200,
    "ksp_rtol": 1e-9,
    "ksp_max_it": 1000,
    "pc_type": "gamg",
    "pc_gamg_threshold": 0.01,
}

#: PETSc's options key that makes the multiple dot products of a vector (the orthogonalisation
#: of GMRES) one BLAS gemv, PETSc's default since 3.21. OpenBLAS's gemv sums in an order that
#: depends on where the vectors lie in memory, which varies from run to run: with it, two runs
#: of one script (benchmarks/bench_newton.py) parted in the last bits at the first GMRES on a
#: kept factorisation and ended with 10 124 or 10 126 active pairs. PETSc's own kernel sums in
#: a fixed order, at the same speed (measured: 0.56 s for 80 products of 5 to 60 vectors of
#: 300k entries either way). A vector takes the setting in force when it is created, and
#: copies of it keep it, so the package sets it off when imported (`fix_summation_order`),
#: unless it is given (PETSC_OPTIONS, the command line, or PETSc.Options() beforehand).
MDOT_GEMV_OPTION = "vec_mdot_use_gemv"


def fix_summation_order() -> None:
    """Make the multiple dot products of the vectors created from now on sum in a fixed order
    (MDOT_GEMV_OPTION off), unless the option was given: a run then repeats to the bit."""
    options = PETSc.Options()
    if not options.hasName(MDOT_GEMV_OPTION):
        options.setValue(MDOT_GEMV_OPTION, "0")
    # read once, so that PETSc does not report it as unused at exit in a run without vectors
    options.getBool(MDOT_GEMV_OPTION)


fix_summation_order()


#: An assembled Jacobian counts as symmetric when no entry differs from its transpose's by more
#: than this fraction of the matrix's infinity norm (rounding leaves about 1e-16); the
#: problems' default direct solver then factorises it as LDL^T (MUMPS, ``pc_type cholesky``,
#: symmetric indefinite) instead of LU: 0.64 s against 0.84 s for the press of
#: benchmarks/bench_factor.py (25k dofs, CPU seconds; docs/solvers.md).
SYMMETRY_RTOL = 1e-10


def _is_symmetric(A: PETSc.Mat) -> bool:
    """Whether ``A`` equals its transpose to SYMMETRY_RTOL of its infinity norm (collective)."""
    return bool(A.isSymmetric(SYMMETRY_RTOL * A.norm(PETSc.NormType.INFINITY)))


def choose_factorisation(pc: PETSc.PC, A: PETSc.Mat) -> bool:
    """Factorise the symmetric ``A`` as LDL^T, any other as LU (MUMPS both; collective).

    Checks ``A`` for symmetry (to SYMMETRY_RTOL), flags it, and sets ``pc``'s type to
    ``cholesky`` or ``lu`` accordingly (a change of type redoes the symbolic factorisation).
    Returns whether ``A`` is symmetric.
    """
    symmetric = _is_symmetric(A)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, symmetric)
    wanted = "cholesky" if symmetric else "lu"
    if pc.getType() != wanted:
        pc.setType(wanted)
        pc.setFactorSolverType("mumps")
    return symmetric


#: SNES's reason when a linear solve (or the factorisation) failed
LINEAR_SOLVE_FAILED = PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE

#: MUMPS's working space for LDL^T: this percentage above its analysis' estimate (ICNTL(14),
#: MUMPS's default 20): with pivoting near a singular Jacobian (a body held only by contact)
#: the 20 % ran out (INFOG(1) = -9) on 2 ranks in several runs of the floating cube of
#: test_augmented.py, 100 % in none of 12. A failed LDL^T factorisation is retried with LU.
LDLT_WORKSPACE_PERCENT = 100


def abs_sum(vector: PETSc.Vec) -> float:
    """The sum of the magnitudes of ``vector``'s entries (its 1-norm), correctly rounded on each
    rank and then over the ranks in rank order: the same bits wherever the entries lie in
    memory (collective).

    PETSc's ``norm(NORM_1)`` is BLAS's asum, and OpenBLAS's asum sums in an order that depends
    on the vector's address modulo 32 bytes, which varies from run to run (PETSc aligns to 16):
    the same diagonal gave 0.5707081970830532 or ...533 as the shifted Jacobian's scale
    (``SNESCallbacks._shifted_direction``), and from that step on two runs of one script parted
    (tests/test_ccd_fold.py without the collision detection ended anywhere from z = -0.30 to
    -0.006, or its load stepping gave up)."""
    local = math.fsum(np.abs(vector.getArray(readonly=True)))
    return math.fsum(vector.getComm().tompi4py().allgather(local))


#: :func:`inertia` counts a pivot of the LDL^T factorisation as null (a zero eigenvalue) below
#: this fraction of the matrix's norm (MUMPS's CNTL(3); its default, 1e-5 of the machine
#: epsilon, took the rounding of the exact zeros of a singular 40 x 40 matrix for negative
#: eigenvalues)
NULL_PIVOT_RTOL = 1e-12


def inertia(A: PETSc.Mat) -> tuple[int, int]:
    """How many eigenvalues of the symmetric ``A`` are negative, and how many are zero to
    working precision: the negative and the null pivots of its LDL^T factorisation (MUMPS,
    INFOG(12) and INFOG(28); Sylvester's law of inertia). Collective.

    A Jacobian at a converged state with a negative eigenvalue is a saddle of the energy, an
    unstable equilibrium: a real body would not stay there. (The problems' Jacobians hold 1 on
    the Dirichlet diagonal and nothing else in those rows and columns: eigenvalues 1, so the
    count is that of the energy's Hessian on the free dofs.)

    Raises:
        ValueError: ``A`` is not symmetric (to SYMMETRY_RTOL of its infinity norm).
        RuntimeError: the factorisation failed (MUMPS's INFOG(1) is negative).
    """
    if not _is_symmetric(A):
        raise ValueError("the inertia is that of a symmetric matrix; this one is not")
    B = A.copy()
    B.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    ksp = PETSc.KSP().create(A.getComm())
    try:
        ksp.setOperators(B)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        pc.setFactorSetUpSolverType()
        F = pc.getFactorMatrix()
        F.setMumpsIcntl(14, LDLT_WORKSPACE_PERCENT)
        F.setMumpsIcntl(24, 1)  # detect null pivots (counted in INFOG(28)):
        F.setMumpsCntl(3, -NULL_PIVOT_RTOL)  # those below this fraction of A's norm
        try:
            pc.setUp()
        except PETSc.Error as err:
            raise RuntimeError(
                f"inertia: the LDL^T factorisation failed (MUMPS INFOG(1) = {F.getMumpsInfog(1)})"
            ) from err
        return int(F.getMumpsInfog(12)), int(F.getMumpsInfog(28))
    finally:
        ksp.destroy()
        B.destroy()


def is_mumps_direct(pc: PETSc.PC) -> bool:
    """Whether ``pc`` is a MUMPS factorisation (LU or Cholesky)."""
    return pc.getType() in ("lu", "cholesky") and pc.getFactorSolverType() == "mumps"


class BackOff:
    """After a failure, the next 1, 2, 4, ... chances are skipped (doubling with each failure
    in a row), until a success."""

    def __init__(self):
        self._skip = self._length = 0

    def take(self) -> bool:
        """Whether this chance may be taken (one chance used either way)."""
        allowed = self._skip == 0
        self._skip = max(self._skip - 1, 0)
        return allowed

    def record(self, failed: bool, succeeded: bool) -> None:
        """The outcome of a chance taken: a failure lengthens the skip, a success ends it."""
        if failed:
            self._length = max(1, 2 * self._length)
            self._skip = self._length
        elif succeeded:
            self._length = 0


def predicted_iterations(iterations: int, reduction: float, rtol: float) -> float:
    """The iterations a Krylov solve needs to reduce its residual to ``rtol`` of the first if
    it goes on at the mean rate of its first ``iterations``, which reduced the residual to
    ``reduction`` of the first (infinite where it did not fall)."""
    if not 0.0 < reduction < 1.0:
        return 0.0 if reduction == 0.0 else math.inf
    return iterations * math.log(rtol) / math.log(reduction)


class KeptRateTest:
    """A KSP convergence test for GMRES on a kept factorisation, run after PETSc's default
    test (``KSP.addConvergenceTest``): at RATE_TEST_ITERATION it stops the solve as diverged
    (DIVERGED_MAX_IT, as if it had reached its limit) where :func:`predicted_iterations`
    exceeds RATE_TEST_LIMIT. ``stops`` counts the solves it stopped. (The residual norms are
    global, so every rank decides alike.)"""

    def __init__(self) -> None:
        self.stops = 0
        self._first = np.nan

    def __call__(self, ksp: PETSc.KSP, iteration: int, rnorm: float) -> int:
        if iteration == 0:
            self._first = rnorm
        elif iteration == RATE_TEST_ITERATION:
            rtol = ksp.getTolerances()[0]
            if predicted_iterations(iteration, rnorm / self._first, rtol) > RATE_TEST_LIMIT:
                self.stops += 1
                return PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
        return PETSc.KSP.ConvergedReason.ITERATING


def set_solver_options(
    prefix: str, user: dict, num_dofs: int, keep_factorisation: bool
) -> tuple[bool, bool]:
    """Put a problem's PETSc options under ``prefix``: the defaults, the linear solver chosen
    for its size, and the user's options over them.

    The linear solver: GMRES with GAMG (AMG_OPTIONS) from AMG_MIN_DOFS global dofs on, MUMPS
    (LDL^T or LU, :func:`choose_factorisation`) below, unless the user gives ``ksp_type`` or
    ``pc_type``; a direct solver keeps its factorisation (KEPT_FACTORISATION_OPTIONS) unless
    the user gives a linear solver or a preconditioner lag.

    Args:
        prefix: the problem's options prefix.
        user: the user's options (set last, so they win).
        num_dofs: global number of dofs of the problem.
        keep_factorisation: whether the problem asks to keep factorisations.

    Returns:
        ``(amg, keep_factorisation)``: whether the default AMG preconditioner was chosen, and
        whether keeping a factorisation remains possible.
    """
    options = dict(DEFAULT_OPTIONS)
    # a user's linear solver or preconditioner lag comes first
    keep_factorisation = keep_factorisation and not {
        "ksp_type", "pc_type", "snes_lag_preconditioner", "snes_lag_jacobian"
    } & set(user)  # fmt: skip
    # the default AMG preconditioner (AMG_OPTIONS), which keeps its hierarchy like the
    # direct solver its factorisation (AMG_KEPT_GROWTH)
    amg = num_dofs >= AMG_MIN_DOFS and not {"ksp_type", "pc_type"} & set(user)
    if amg:
        options.update(AMG_OPTIONS)
        del options["pc_factor_mat_solver_type"]
    elif "pc_type" not in user:  # LDL^T or LU, chosen per Jacobian (choose_factorisation)
        options["mat_mumps_icntl_14"] = LDLT_WORKSPACE_PERCENT
        if keep_factorisation:
            options.update(KEPT_FACTORISATION_OPTIONS)
    opts = PETSc.Options()
    opts.prefixPush(prefix)
    for key, value in {**options, **user}.items():
        opts[key] = value
    opts.prefixPop()
    if "mat_mumps_icntl_14" not in user and "mat_mumps_icntl_14" in options:
        # read once now: MUMPS reads it at the first factorisation, and a problem that
        # never factorises would otherwise leave it for PETSc to report as unused at exit
        opts.getInt(prefix + "mat_mumps_icntl_14")
    return amg, keep_factorisation


def rigid_body_modes(V: dolfinx.fem.FunctionSpace) -> PETSc.NullSpace:
    """The six rigid-body modes of a P1 displacement space (orthonormal, owned dofs) as a
    PETSc null space: the near-nullspace an AMG preconditioner (GAMG) needs for elasticity
    (collective)."""
    comm = V.mesh.comm
    n = V.dofmap.index_map.size_local
    x = V.tabulate_dof_coordinates()[:n]
    count = comm.allreduce(n)
    x = x - comm.allreduce(x.sum(axis=0)) / max(count, 1)
    modes = np.zeros((6, n, 3))
    for i in range(3):
        modes[i, :, i] = 1.0
    modes[3, :, 0], modes[3, :, 1] = -x[:, 1], x[:, 0]
    modes[4, :, 1], modes[4, :, 2] = -x[:, 2], x[:, 1]
    modes[5, :, 2], modes[5, :, 0] = -x[:, 0], x[:, 2]
    vecs = []
    for k in range(6):
        vec = PETSc.Vec().createMPI((3 * n, PETSc.DECIDE), bsize=3, comm=comm)
        vec.setArray(modes[k].ravel())
        vecs.append(vec)
    # Gram-Schmidt across ranks
    for k, vec in enumerate(vecs):
        for other in vecs[:k]:
            vec.axpy(-vec.dot(other), other)
        vec.normalize()
    return PETSc.NullSpace().create(vectors=vecs, comm=comm)
