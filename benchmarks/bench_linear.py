"""Direct against AMG-preconditioned Krylov solvers on the contact Jacobian of the bench_newton
press (upper block sunk rigidly into the lower one, contact active over the interface), at
several sizes: MUMPS LU and LDL^T (the matrix is symmetric; ordering chosen by MUMPS), GMRES
with PETSc's GAMG (rigid-body near-nullspace set on the matrix) and GMRES with hypre BoomerAMG
(nodal coarsening for the 3 displacement components).

For each size and solver: set-up seconds (analysis + factorisation, or building the AMG
hierarchy), solve seconds, Krylov iterations to ``--rtol`` (relative preconditioned residual),
and the relative error of the solution against LU where LU ran. Times are process CPU seconds
(one thread per process), so other jobs on the machine affect them little.

Run: ``scripts/fenicsx python3 benchmarks/bench_linear.py --scales 1 1.587 2.32`` (40k, 160k
and 510k tetrahedra; LU is skipped above ``--lu-max`` tetrahedra). Serial only. Prints
figures; asserts nothing about time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_factor import contact_jacobian

from fenics_matdepth.problems import rigid_body_modes

BASE_LOWER, BASE_UPPER = (24, 24, 8), (16, 16, 8)


def solve(A: PETSc.Mat, b: PETSc.Vec, options: dict) -> tuple[float, float, int, PETSc.Vec]:
    """Set-up and solve CPU seconds, iterations and the solution of ``A x = b``."""
    prefix = f"bench_{id(options)}_"
    opts = PETSc.Options()
    for key, value in options.items():
        opts[prefix + key] = value
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(A)
    ksp.setFromOptions()
    x = b.duplicate()
    tic = time.process_time()
    ksp.setUp()
    setup = time.process_time() - tic
    tic = time.process_time()
    ksp.solve(b, x)
    solve_time = time.process_time() - tic
    reason = ksp.getConvergedReason()
    iterations = ksp.getIterationNumber()
    ksp.destroy()
    if reason < 0:
        iterations = -iterations  # did not converge: shown negative
    return setup, solve_time, iterations, x


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scales", type=float, nargs="*", default=[1.0, 1.587])
    parser.add_argument("--sink", type=float, default=3e-4)
    parser.add_argument("--rtol", type=float, default=1e-8)
    parser.add_argument("--lu-max", type=int, default=200_000)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    if comm.size > 1:
        raise RuntimeError("bench_linear.py runs serially (it times one process's CPU)")
    krylov = {
        "ksp_type": "gmres",
        "ksp_gmres_restart": 200,
        "ksp_rtol": args.rtol,
        "ksp_max_it": 2000,
    }
    solvers = {
        "MUMPS LU": {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
        "MUMPS LDL^T": {
            "ksp_type": "preonly",
            "pc_type": "cholesky",
            "pc_factor_mat_solver_type": "mumps",
        },
        "GMRES + GAMG": {**krylov, "pc_type": "gamg", "pc_gamg_threshold": 0.01},
        "GMRES + BoomerAMG": {
            **krylov,
            "pc_type": "hypre",
            "pc_hypre_type": "boomeramg",
            "pc_hypre_boomeramg_nodal_coarsen": 6,
            "pc_hypre_boomeramg_strong_threshold": 0.5,
        },
    }
    for scale in args.scales:
        lower = tuple(max(1, round(n * scale)) for n in BASE_LOWER)
        upper = tuple(max(1, round(n * scale)) for n in BASE_UPPER)
        tic = time.process_time()
        A, _, _, V, contact, num_tets = contact_jacobian(comm, lower, upper, args.sink)
        A.setBlockSize(3)
        A.setNearNullSpace(rigid_body_modes(V))
        build = time.process_time() - tic
        b = A.createVecLeft()
        b.setRandom()
        print(
            f"{num_tets} tets, {A.getSize()[0]} dofs, {A.getInfo()['nz_used'] / 1e6:.2f} M "
            f"entries, {contact.diagnostics()['active_pairs']} active pairs "
            f"(built in {build:.1f} s)",
            flush=True,
        )
        reference = None
        for name, options in solvers.items():
            if name.startswith("MUMPS") and num_tets > args.lu_max:
                print(f"  {name:17s} skipped (more than --lu-max = {args.lu_max} tets)")
                continue
            setup, solve_time, iterations, x = solve(A, b, options)
            error = ""
            if reference is None and name == "MUMPS LU":
                reference = x
            elif reference is not None:
                d = x.copy()
                d.axpy(-1.0, reference)
                error = f", error vs LU {d.norm() / reference.norm():.1e}"
            its = "" if name.startswith("MUMPS") else f", {iterations} iterations"
            print(
                f"  {name:17s} set-up {setup:7.2f} s, solve {solve_time:7.2f} s, "
                f"total {setup + solve_time:7.2f} s{its}{error}",
                flush=True,
            )
        A.destroy()


if __name__ == "__main__":
    main()
