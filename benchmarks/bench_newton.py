"""Seconds per Newton iteration on a ~40k-tetrahedron two-body contact problem, split into
bulk assembly, contact update (gather, refit, pair search), contact assembly (pair kernels and
insertion) and the linear solve (MUMPS LU).

A 1.5 x 1.5 x 0.5 neo-Hookean block and a 1 x 1 x 0.5 block resting on it; the upper block's
top is pushed down in two load steps, so contact is active over most of the interface.

Run: ``scripts/fenicsx python3 benchmarks/bench_newton.py`` (or under ``mpirun -n 2``).
Target: contact update + contact assembly under 25 % of an iteration. Prints figures; asserts
nothing about time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl

import fenics_matdepth as fm
from fenics_matdepth._compat import create_tetrahedral_mesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_operator import _box_tets

TARGET_CONTACT_SHARE = 0.25


def build(comm, lower, upper):
    xa, ca = _box_tets(lower, (0.0, 0.0, 0.0), (1.5, 1.5, 0.5))
    xb, cb = _box_tets(upper, (0.25, 0.25, 0.5), (1.0, 1.0, 0.5))
    cells = np.vstack((ca, cb + xa.shape[0]))
    return create_tetrahedral_mesh(comm, cells, np.vstack((xa, xb))), cells.shape[0]


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lower", type=int, nargs=3, default=(24, 24, 8))
    parser.add_argument("--upper", type=int, nargs=3, default=(16, 16, 8))
    parser.add_argument("--integration", default="area", choices=("area", "collocation"))
    parser.add_argument("--petsc", nargs="*", default=[], help="extra PETSc options key=value")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD

    tic = time.perf_counter()
    mesh, num_tets = build(comm, args.lower, args.upper)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    residual = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(V))) * ufl.dx
    bottom = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 0.0))
    top = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], 1.0))
    push = dolfinx.fem.Function(V)
    bcs = [
        dolfinx.fem.dirichletbc(
            dolfinx.fem.Function(V), dolfinx.fem.locate_dofs_topological(V, 2, bottom)
        ),
        dolfinx.fem.dirichletbc(push, dolfinx.fem.locate_dofs_topological(V, 2, top)),
    ]
    moduli = fm.materials.small_strain_moduli(fm.materials.neo_hookean, mu=mu, kappa=kappa)
    penalty = fm.propose_penalty(mesh, moduli.stiffest, factor=10.0)
    depth = fm.material_depth(mesh)
    contact = fm.ContactOperator(u, depth, penalty=penalty, integration=args.integration)
    problem = fm.ContactProblem(
        residual,
        u,
        contact,
        bcs=bcs,
        energy=psi * ufl.dx,
        petsc_options=dict(opt.split("=") for opt in args.petsc),
    )
    setup = time.perf_counter() - tic

    def set_load(t):
        push.x.array.reshape(-1, 3)[:, 2] = -0.02 * t

    totals = dict.fromkeys(problem.timings, 0.0)
    iterations, wall = 0, 0.0
    for t in (0.5, 1.0):
        set_load(t)
        tic = time.perf_counter()
        result = problem.solve()
        wall += time.perf_counter() - tic
        iterations += result.iterations
        if comm.rank == 0:
            history = " ".join(f"{r:.1e}" for r in result.residual_norms)
            print(f"load {t}: {result.iterations} iterations, residual norms {history}")
        for key, value in problem.timings.items():
            totals[key] += comm.allreduce(value, op=MPI.MAX)
    wall = comm.allreduce(wall, op=MPI.MAX)
    diag = contact.diagnostics()
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
    per_it = {k: v / iterations for k, v in totals.items()}
    other = wall / iterations - sum(per_it.values())
    for key, value in {**per_it, "other (SNES, line search)": other}.items():
        print(f"  {key:28s} {value:8.4f} s/it  {100 * value / (wall / iterations):5.1f} %")
    share = (per_it["contact_update"] + per_it["contact_assembly"]) / (wall / iterations)
    print(
        f"contact share {100 * share:.1f} % of an iteration "
        f"(target < {100 * TARGET_CONTACT_SHARE:.0f} %: ratio {share / TARGET_CONTACT_SHARE:.2f})"
    )


if __name__ == "__main__":
    main()
