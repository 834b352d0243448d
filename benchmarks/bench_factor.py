"""CPU seconds of the MUMPS factorisation of the contact Jacobian of the bench_newton press,
for the matrix the Newton solver factorises (bulk + contact pattern), the same without its
explicit zeros, and the bulk matrix alone, as LU and as LDL^T (the matrix is symmetric: MUMPS
Cholesky, symmetric indefinite, what ContactProblem uses for symmetric Jacobians), with
several MUMPS orderings for LU.

The upper block is sunk rigidly by ``--sink`` into the lower one, so contact is active over the
whole interface. Times are process CPU seconds (MUMPS and the BLAS run on one thread per
process here), so they are little affected by other jobs on the machine. Compare BLAS
libraries by running it twice, e.g. inside the Debian root of ``scripts/fenicsx``::

    scripts/fenicsx python3 benchmarks/bench_factor.py
    LD_LIBRARY_PATH=/usr/lib/x86_64-linux-gnu/blas:/usr/lib/x86_64-linux-gnu/lapack \\
        scripts/fenicsx python3 benchmarks/bench_factor.py   # Debian's reference BLAS

Serial only. Prints figures; asserts nothing about time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

import fenics_matdepth as fm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_newton import build

#: MUMPS ICNTL(7) values of the orderings compared.
ORDERINGS = {"metis": 5, "scotch": 3, "pord": 4, "amd": 0, "auto": 7}


def _without_zeros(A: PETSc.Mat) -> PETSc.Mat:
    """A copy of the (serial) AIJ matrix ``A`` without its explicitly stored zeros."""
    indptr, indices, values = A.getValuesCSR()
    rows = np.repeat(np.arange(indptr.size - 1), np.diff(indptr))
    keep = (values != 0.0) | (indices == rows)
    new_indptr = np.concatenate(
        ([0], np.cumsum(np.bincount(rows[keep], minlength=indptr.size - 1)))
    )
    P = PETSc.Mat().createAIJ(
        A.getSizes(), csr=(new_indptr.astype(PETSc.IntType), indices[keep], values[keep])
    )
    P.assemble()
    return P


def factorise(M: PETSc.Mat, ordering: int, kind: str = "lu") -> tuple[float, float]:
    """CPU seconds of (analysis + factorisation, factorisation again with the analysis kept);
    ``kind`` lu or cholesky (LDL^T)."""
    ksp = PETSc.KSP().create(M.getComm())
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType(kind)
    pc.setFactorSolverType("mumps")
    ksp.setOperators(M)
    pc.setFactorSetUpSolverType()
    pc.getFactorMatrix().setMumpsIcntl(7, ordering)
    tic = time.process_time()
    ksp.setUp()
    first = time.process_time() - tic
    # "new values, same pattern", what a Newton iteration hands the solver: an assembly
    # raises the matrix's state (a zero shift would not), so the factorisation is redone
    M.assemble()
    ksp.setOperators(M)
    tic = time.process_time()
    ksp.setUp()
    again = time.process_time() - tic
    del pc  # before its KSP: on several ranks a PC outliving it waits in PETSc's garbage
    ksp.destroy()
    return first, again


def contact_jacobian(comm, lower, upper, sink: float):
    """The bench_newton press with the upper block sunk rigidly by ``sink``: the Jacobian the
    Newton solver factorises (bulk + contact pattern), the bulk form, the Dirichlet conditions,
    the space and the operator."""
    mesh, num_tets = build(comm, lower, upper)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    residual = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(V))) * ufl.dx
    J = dolfinx.fem.form(ufl.derivative(residual, u))
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, 2, bottom)
        )
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=215.0)
    upper_body = contact.body_of_vertex[np.argmax(contact.surface.gathered()["X"][:, 2])]
    u.x.array.reshape(-1, 3)[contact.body_of_vertex == upper_body, 2] = -sink
    contact.update()
    contact.set_bcs(bcs)
    A = contact.create_matrix(J)
    dolfinx.fem.petsc.assemble_matrix(A, J, bcs)
    A.assemble()
    contact.add_jacobian(A)
    return A, J, bcs, V, contact, num_tets


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lower", type=int, nargs=3, default=(24, 24, 8))
    parser.add_argument("--upper", type=int, nargs=3, default=(16, 16, 8))
    parser.add_argument("--sink", type=float, default=3e-4)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    if comm.size > 1:
        raise RuntimeError("bench_factor.py runs serially (it times one process's CPU)")
    A, J, bcs, _, contact, num_tets = contact_jacobian(comm, args.lower, args.upper, args.sink)
    compact = _without_zeros(A)
    bulk = dolfinx.fem.petsc.create_matrix(J)
    dolfinx.fem.petsc.assemble_matrix(bulk, J, bcs)
    bulk.assemble()
    diag = contact.diagnostics()
    print(
        f"{num_tets} tets, {3 * contact.num_vertices} dofs, upper block sunk {args.sink:g}: "
        f"{diag['active_pairs']} active pairs"
    )
    matrices = {
        "bulk only": bulk,
        "bulk + contact pattern": A,
        "the same without zeros": compact,
    }
    for name, M in matrices.items():
        nz = M.getInfo()["nz_used"]
        for kind in ("lu", "cholesky"):
            for ordering, icntl in ORDERINGS.items():
                if ordering != "auto" and (name != "bulk + contact pattern" or kind != "lu"):
                    continue
                first, again = factorise(M, icntl, kind)
                print(
                    f"  {name:24s} {nz / 1e6:5.2f} M entries  {kind:8s} {ordering:6s}  "
                    f"analysis + factorisation {first:6.2f} s, factorisation (analysis kept) "
                    f"{again:6.2f} s"
                )
    for M in matrices.values():
        M.destroy()


if __name__ == "__main__":
    main()
