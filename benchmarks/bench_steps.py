"""A knee-scale quasi-static run end to end, start-up included: a soft block pressed onto a
stiff one and slid across it, 50 load steps.

The model of ``bench_newton.py`` (39 936 tetrahedra, 8 226 vertices): a 1.5 x 1.5 x 0.5 block
(neo-Hookean, E = 100, the stiff body) under a 1 x 1 x 0.5 block (E = 1, the soft tissue).
The lower block's bottom is clamped; the upper block's top is pushed down 0.04 over the first
10 steps, then moved 0.3 along x over the last 40 (frictionless contact: the soft block slides
over the stiff one, its base sheared). ``solve_load_steps`` with automatic cutting.

Printed: the time of each phase (imports, mesh, depth, operator and problem set-up, the 50
steps), Newton iterations per step (median, max), cuts, the largest penetration relative to the
element size, and the split of the solve time as the paper's §6.3 gives it (force and
stiffness, collision detection, linear solve). Target: the whole run in at most 3 minutes on
the 2-core machine (issue #10). Prints figures; asserts nothing about time.

Run: ``scripts/fenicsx python3 benchmarks/bench_steps.py [--steps 50] [--lower 24 24 8]
[--upper 16 16 8] [--quadrature-degree 1] [--factorise-every-iteration] [--petsc pc_type=lu ...]``
(or under ``mpirun -n 2``). The bulk forms use one quadrature point (exact for P1, see the code).
"""

from __future__ import annotations

import time

START = time.perf_counter()

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from mpi4py import MPI  # noqa: E402

import dolfinx  # noqa: E402
import numpy as np  # noqa: E402
import ufl  # noqa: E402

import fenics_matdepth as fm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_newton import build, clamp_and_move  # noqa: E402

TARGET_SECONDS = 180.0
PRESS, SLIDE = 0.04, 0.3
#: share of the load steps spent pressing (the rest slides)
PRESS_SHARE = 0.2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--lower", type=int, nargs=3, default=(24, 24, 8))
    parser.add_argument("--upper", type=int, nargs=3, default=(16, 16, 8))
    parser.add_argument("--petsc", nargs="*", default=[], help="extra PETSc options key=value")
    parser.add_argument(
        "--factorise-every-iteration",
        action="store_true",
        help="ContactProblem(keep_factorisation=False): a factorisation per Newton iteration "
        "instead of GMRES on a factorisation kept across a solve's iterations (the default)",
    )
    parser.add_argument(
        "--quadrature-degree",
        type=int,
        default=1,
        help="of the bulk forms; 1 is exact for P1 (constant F per cell), 0: UFL's estimate (2)",
    )
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    phases = {"imports": time.perf_counter() - START}

    tic = time.perf_counter()
    mesh, num_tets = build(comm, args.lower, args.upper)
    phases["mesh"] = time.perf_counter() - tic

    tic = time.perf_counter()
    depth = fm.material_depth(mesh)
    phases["material depth"] = time.perf_counter() - tic

    tic = time.perf_counter()
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    X = ufl.SpatialCoordinate(mesh)
    stiff = fm.materials.shear_bulk_from_youngs_poisson(100.0, 0.3)
    soft = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    lower = ufl.lt(X[2], 0.5)
    mu = ufl.conditional(lower, stiff[0], soft[0])
    kappa = ufl.conditional(lower, stiff[1], soft[1])
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    # P1 on affine tetrahedra: F, psi(F) and the integrands are constant per cell, so one
    # quadrature point is exact; UFL's estimate for psi (degree 2) takes four.
    q = args.quadrature_degree
    dx = ufl.dx(metadata={"quadrature_degree": q}) if q > 0 else ufl.dx
    residual = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(V))) * dx
    bcs, moved = clamp_and_move(mesh, V)
    # the penalty of the soft body's modulus: the soft block's base is what penetrates
    penalty = fm.propose_penalty(mesh, 1.0, factor=10.0)
    contact = fm.ContactOperator(u, depth, penalty=penalty)
    problem = fm.ContactProblem(
        residual,
        u,
        contact,
        bcs=bcs,
        energy=psi * dx,
        petsc_options=dict(opt.split("=") for opt in args.petsc),
        keep_factorisation=not args.factorise_every_iteration,
    )
    phases["operator and problem"] = time.perf_counter() - tic

    def set_load(t: float) -> None:
        press = PRESS * min(t / PRESS_SHARE, 1.0)
        slide = SLIDE * max(t - PRESS_SHARE, 0.0) / (1.0 - PRESS_SHARE)
        values = moved.x.array.reshape(-1, 3)
        values[:, 0] = slide
        values[:, 2] = -press

    tic = time.perf_counter()
    steps = fm.solve_load_steps(problem, set_load, num_steps=args.steps)
    phases[f"{args.steps} load steps"] = time.perf_counter() - tic
    # the converged solves' split (failed attempts, cut and retried, are in "other")
    timings = {
        key: comm.allreduce(sum(step.timings[key] for step in steps), op=MPI.MAX)
        for key in fm.system_assembler.TIMING_KEYS
    }
    h = min(1.0 / args.upper[0], 0.5 / args.upper[2])  # the soft block's grid spacing
    total = time.perf_counter() - START
    total = comm.allreduce(total, op=MPI.MAX)
    if comm.rank != 0:
        return
    its = np.array([s.iterations for s in steps])
    cuts = sum(s.cuts for s in steps)
    pen = max(s.diagnostics["max_penetration"] for s in steps)
    det = min(s.diagnostics["min_det_F"] for s in steps)
    print(
        f"{num_tets} tets, {V.dofmap.index_map.size_global} vertices, {comm.size} process(es), "
        f"penalty {penalty:.3g}"
    )
    print(
        f"{len(steps)} steps converged, {cuts} cuts; Newton iterations per step median "
        f"{np.median(its):.0f}, max {its.max()}, total {its.sum()}; largest penetration "
        f"{pen:.2e} ({pen / h:.3f} of the soft block's grid spacing); min det F {det:.3f}"
    )
    for name, seconds in phases.items():
        print(f"  {name:24s} {seconds:8.2f} s")
    solve = phases[f"{args.steps} load steps"]
    force = timings["bulk_assembly"] + timings["contact_assembly"]
    collision = timings["contact_update"]
    linear = timings["linear_solve"]
    print("split of the steps' time (the paper's §6.3: 63 % / 22 % / 15 %):")
    for name, seconds in (
        ("force and stiffness", force),
        ("collision detection", collision),
        ("linear solve", linear),
        ("other (line search, output, cut steps)", solve - force - collision - linear),
    ):
        print(f"  {name:28s} {seconds:8.2f} s  {100 * seconds / solve:5.1f} %")
    print(
        f"whole run {total:.1f} s (target <= {TARGET_SECONDS:.0f} s: ratio "
        f"{total / TARGET_SECONDS:.2f})"
    )


if __name__ == "__main__":
    main()
