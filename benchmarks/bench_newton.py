"""Seconds per Newton iteration on a ~40k-tetrahedron two-body contact problem, split into
bulk assembly, contact update (displacement from neighbours, refit, pair search), contact
assembly (pair kernels and insertion) and the linear solve (MUMPS LU).

A 1.5 x 1.5 x 0.5 neo-Hookean block and a 1 x 1 x 0.5 block resting on it; the upper block's
top is pushed down in two load steps, so contact is active over most of the interface.

Run: ``scripts/fenicsx python3 benchmarks/bench_newton.py`` (or under ``mpirun -n 2``). Prints
what each rank holds (vertices, tetrahedra, halo tetrahedra) and the displacement bytes it
sends per contact update.
Targets: contact update + contact assembly under 25 % of an iteration, and an iteration at most
1.3 times one Newton iteration of the same model without contact (bulk assembly + linear
solve, the matrix as dolfinx makes it). The ratio is printed a second time against the model
without contact on the pattern ContactProblem uses (no zeros stored in the Dirichlet rows and
columns), which says what contact itself costs. Also the share of the continuous collision
detection of the Newton steps (target at most 10 %). Prints figures; asserts nothing about
time.
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

import fenics_matdepth as fm
from fenics_matdepth.contact import assembly
from fenics_matdepth.meshing import box_tetrahedra, create_tetrahedral_mesh

TARGET_CONTACT_SHARE = 0.25
TARGET_ITERATION_RATIO = 1.3
#: continuous collision detection of the Newton steps (line-search cap), share of an iteration
TARGET_CCD_SHARE = 0.10
#: What each rank holds and sends (``ContactOperator.diagnostics``; absent before the halo).
HALO_KEYS = ("held_vertices", "held_tets", "halo_tets", "neighbours", "update_bytes_sent",
             "halo_refreshes")  # fmt: skip


def bulk_newton_iteration(
    residual, u, bcs, like: PETSc.KSP, repeats: int = 3, lean: bool = False
) -> tuple[float, float]:
    """Wall and CPU seconds (largest over the ranks) of one Newton iteration of the same model
    without contact: assemble the bulk residual and Jacobian, factorise and solve with the
    solver and options of ``like`` (its options prefix: tolerances, GMRES restart, the GAMG
    threshold; the rigid-body near-nullspace for GAMG; the symbolic factorisation reused after
    the first solve, as a Newton loop with a fixed pattern does); the mean of ``repeats``
    iterations after the first (collective). The matrix as dolfinx makes it (its Dirichlet
    rows and columns hold zeros), or with ``lean`` the pattern ContactProblem's matrix has
    without its contact couplings (those rows and columns hold only the diagonal)."""
    comm = u.function_space.mesh.comm
    F = dolfinx.fem.form(residual)
    J = dolfinx.fem.form(ufl.derivative(residual, u))
    if lean:
        num_vertices = u.function_space.dofmap.index_map.size_global
        dirichlet = assembly.global_dirichlet_dofs(comm, u.function_space, bcs)
        no_couplings = np.empty(0, dtype=np.int64)  # vertex-coupling keys are int64
        A = assembly.create_matrix(comm, J, no_couplings, num_vertices, dirichlet)
    else:
        A = dolfinx.fem.petsc.create_matrix(J)
    b = u.x.petsc_vec.duplicate()  # ghosted, as assembly and lifting expect
    x = b.duplicate()
    ksp = PETSc.KSP().create(comm)
    # the problem's linear solver options (tolerances, GMRES restart, GAMG threshold, MUMPS
    # controls), then the solver and preconditioner it chose at run time
    ksp.setOptionsPrefix(like.getOptionsPrefix())
    ksp.setFromOptions()
    ksp.setType(like.getType())
    ksp.getPC().setType(like.getPC().getType())
    if like.getPC().getType() in ("lu", "cholesky"):
        ksp.getPC().setFactorSolverType(like.getPC().getFactorSolverType())
    if like.getPC().getType() == "gamg":
        # ContactProblem sets the rigid-body modes as the near-nullspace for GAMG
        A.setNearNullSpace(fm.rigid_body_modes(u.function_space))
    ksp.setOperators(A)
    seconds, cpu = [], []
    for _ in range(repeats + 1):
        comm.Barrier()
        tic, cpu_tic = time.perf_counter(), time.process_time()
        A.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(A, J, bcs)
        A.assemble()
        with b.localForm() as b_local:
            b_local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(b, F)
        dolfinx.fem.petsc.apply_lifting(b, [J], [bcs], x0=[u.x.petsc_vec], alpha=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        dolfinx.fem.petsc.set_bc(b, bcs, u.x.petsc_vec, -1.0)
        ksp.solve(b, x)
        seconds.append(comm.allreduce(time.perf_counter() - tic, op=MPI.MAX))
        cpu.append(comm.allreduce(time.process_time() - cpu_tic, op=MPI.MAX))
    for obj in (ksp, A, b, x):
        obj.destroy()
    return float(np.mean(seconds[1:])), float(np.mean(cpu[1:]))


def build(comm, lower, upper):
    xa, ca = box_tetrahedra(lower, (0.0, 0.0, 0.0), (1.5, 1.5, 0.5))
    xb, cb = box_tetrahedra(upper, (0.25, 0.25, 0.5), (1.0, 1.0, 0.5))
    cells = np.vstack((ca, cb + xa.shape[0]))
    return create_tetrahedral_mesh(comm, cells, np.vstack((xa, xb))), cells.shape[0]


def clamp_and_move(mesh, V):
    """Dirichlet conditions of the two blocks: the lower block's bottom (z = 0) clamped, the
    upper block's top (z = 1) moved by the returned Function's values."""
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 1.0))
    moved = dolfinx.fem.Function(V)
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, 2, bottom)
        ),
        dolfinx.fem.dirichletbc(moved, dolfinx.fem.locate_dofs_topological(V, 2, top)),
    ]
    return bcs, moved


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lower", type=int, nargs=3, default=(24, 24, 8))
    parser.add_argument("--upper", type=int, nargs=3, default=(16, 16, 8))
    parser.add_argument("--integration", default="area", choices=("area", "collocation"))
    parser.add_argument("--petsc", nargs="*", default=[], help="extra PETSc options key=value")
    parser.add_argument(
        "--quadrature-degree",
        type=int,
        default=1,
        help="of the bulk forms; 1 is exact for P1 (constant F per cell), 0: UFL's estimate (2)",
    )
    args = parser.parse_args()
    comm = MPI.COMM_WORLD

    tic = time.perf_counter()
    mesh, num_tets = build(comm, args.lower, args.upper)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    # P1 on affine tetrahedra: F, psi(F) and the integrands are constant per cell, so one
    # quadrature point is exact; UFL's estimate for psi (degree 2) takes four.
    q = args.quadrature_degree
    dx = ufl.dx(metadata={"quadrature_degree": q}) if q > 0 else ufl.dx
    residual = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(V))) * dx
    bcs, push = clamp_and_move(mesh, V)
    moduli = fm.materials.small_strain_moduli(fm.materials.neo_hookean, mu=mu, kappa=kappa)
    penalty = fm.propose_penalty(mesh, moduli.stiffest, factor=10.0)
    depth = fm.material_depth(mesh)
    contact = fm.ContactOperator(u, depth, penalty=penalty, integration=args.integration)
    problem = fm.ContactProblem(
        residual,
        u,
        contact,
        bcs=bcs,
        energy=psi * dx,
        petsc_options=dict(opt.split("=") for opt in args.petsc),
    )
    if problem.collisions is not None:
        # the collision detection's kernels compiled (or loaded) outside the timed solves
        problem.collisions.step_fraction(u.x.array, u.x.array)
    setup = time.perf_counter() - tic

    def set_load(t):
        push.x.array.reshape(-1, 3)[:, 2] = -0.02 * t

    totals = dict.fromkeys(problem.timings, 0.0)
    iterations, wall, cpu = 0, 0.0, 0.0
    for t in (0.5, 1.0):
        set_load(t)
        tic, cpu_tic = time.perf_counter(), time.process_time()
        result = problem.solve()
        wall += time.perf_counter() - tic
        cpu += time.process_time() - cpu_tic
        iterations += result.iterations
        if comm.rank == 0:
            history = " ".join(f"{r:.1e}" for r in result.residual_norms)
            print(
                f"load {t}: {result.iterations} iterations, {result.factorisations} "
                f"factorisations, residual norms {history}"
            )
        for key, value in problem.timings.items():
            totals[key] += comm.allreduce(value, op=MPI.MAX)
    wall = comm.allreduce(wall, op=MPI.MAX)
    cpu = comm.allreduce(cpu, op=MPI.MAX)
    diag = contact.diagnostics()
    held = comm.gather({k: diag.get(k) for k in HALO_KEYS}, root=0)
    reference = bulk_newton_iteration(residual, u, bcs, problem.snes.getKSP())
    lean = bulk_newton_iteration(residual, u, bcs, problem.snes.getKSP(), lean=True)
    if comm.rank != 0:
        return
    print(
        f"{num_tets} tets, {3 * V.dofmap.index_map.size_global} dofs, {comm.size} process(es), "
        f"integration={args.integration}, penalty {penalty:.3g}, set-up {setup:.2f} s"
    )
    print(
        f"{iterations} Newton iterations in {wall:.2f} s; "
        f"{diag['active_pairs']} active of {diag['candidate_pairs']} candidate pairs; "
        f"max penetration {diag['max_penetration']:.2e}; "
        f"matrix rebuilds {problem.pattern_rebuilds}"
    )
    for rank, sizes in enumerate(held):
        print(f"  rank {rank}: " + ", ".join(f"{k} {v}" for k, v in sizes.items()))
    per_it = {k: v / iterations for k, v in totals.items()}
    other = wall / iterations - sum(per_it.values())
    for key, value in {**per_it, "other (SNES, line search)": other}.items():
        print(f"  {key:28s} {value:8.4f} s/it  {100 * value / (wall / iterations):5.1f} %")
    share = (per_it["contact_update"] + per_it["contact_assembly"]) / (wall / iterations)
    print(
        f"contact share {100 * share:.1f} % of an iteration "
        f"(target < {100 * TARGET_CONTACT_SHARE:.0f} %: ratio {share / TARGET_CONTACT_SHARE:.2f})"
    )
    if "ccd" in per_it:
        ccd_share = per_it["ccd"] / (wall / iterations)
        print(
            f"continuous collision detection {100 * ccd_share:.1f} % of an iteration "
            f"(target <= {100 * TARGET_CCD_SHARE:.0f} %: "
            f"ratio {ccd_share / TARGET_CCD_SHARE:.2f}); "
            f"{problem.collisions.num_triangles} boundary triangles, "
            f"{problem.collisions.queries} queries"
        )
    target = TARGET_ITERATION_RATIO
    # CPU seconds too: with one BLAS thread per process they are what an unloaded machine's
    # wall time would be, when other jobs share the cores
    for name, per_iteration, ref in (
        ("wall", wall / iterations, reference[0]),
        ("CPU", cpu / iterations, reference[1]),
    ):
        ratio = per_iteration / ref
        print(
            f"{name}: iteration {per_iteration:.3f} s / (bulk assembly + linear solve without "
            f"contact, {ref:.3f} s) = {ratio:.2f} (target <= {target}: ratio {ratio / target:.2f})"
        )
    # the matrix without contact but with the pattern ContactProblem gives its matrix (no
    # zeros stored in the Dirichlet rows and columns): what contact itself costs
    for name, per_iteration, ref in (
        ("wall", wall / iterations, lean[0]),
        ("CPU", cpu / iterations, lean[1]),
    ):
        print(
            f"{name}: the same against the model without contact on that lean pattern "
            f"({ref:.3f} s) = {per_iteration / ref:.2f}"
        )


if __name__ == "__main__":
    main()
