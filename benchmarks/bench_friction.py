"""What Coulomb friction costs: seconds per Newton iteration and iterations per step of the
model of ``bench_newton.py`` (a 1 x 1 x 0.5 neo-Hookean block on a 1.5 x 1.5 x 0.5 one,
about 40k tetrahedra by default), frictionless and with ``fm.Coulomb(mu)``.

The upper block's top is pressed down in two load steps, then pulled sideways in two more
(so the friction sticks, then slides), through ``solve_load_steps`` (which advances the
friction's reference after each step). Each run prints its iterations per step and the time
split per iteration; the last line is the ratio of the seconds per iteration with friction to
those without. Target: at most 1.3. Prints figures; asserts nothing about time.

Run: ``scripts/fenicsx python3 benchmarks/bench_friction.py`` (or under ``mpirun -n 2``);
``--switch-rule both --repeat 2`` runs the friction with and without the linear solver's
factorisation once the stick/slip set moved (``linear_solver.FRICTION_SWITCH_SHARE``), in turn,
for a comparison on the same machine state.
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl

# the model of bench_newton.py (the script's folder is on the path when it runs)
from bench_newton import build, clamp_and_move

import fenics_matdepth as fm
from fenics_matdepth import linear_solver

TARGET_RATIO = 1.3
PRESS, PULL = 0.02, 0.05


def run(comm, lower, upper, friction: fm.Coulomb | None) -> dict:
    """Solve the four steps; seconds, iterations and the time split (largest over ranks)."""
    mesh, num_tets = build(comm, lower, upper)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(1.0, 0.3)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    dx = ufl.dx(metadata={"quadrature_degree": 1})  # exact for P1
    residual = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(V))) * dx
    bcs, moved = clamp_and_move(mesh, V)
    moduli = fm.materials.small_strain_moduli(fm.materials.neo_hookean, mu=mu, kappa=kappa)
    penalty = fm.propose_penalty(mesh, moduli.stiffest, factor=10.0)
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=penalty, friction=friction)
    problem = fm.ContactProblem(residual, u, contact, bcs=bcs, energy=psi * dx)
    # the Jacobians factorised per step (the load steps' records do not keep them): the rest
    # of the linear solves are GMRES on a kept factorisation, about 30 times cheaper
    factorisations: list[int] = []
    solve = problem.solve

    def counted_solve(*args, **kwargs):
        result = solve(*args, **kwargs)
        factorisations.append(result.factorisations)
        return result

    problem.solve = counted_solve

    def set_load(t):
        values = moved.x.array.reshape(-1, 3)
        values[:, 2] = -PRESS * min(t, 2.0) / 2.0
        values[:, 0] = PULL * max(t - 2.0, 0.0) / 2.0

    tic, cpu_tic = time.perf_counter(), time.process_time()
    records = fm.solve_load_steps(problem, set_load, num_steps=4, end=4.0, progress=False)
    wall = comm.allreduce(time.perf_counter() - tic, op=MPI.MAX)
    # CPU seconds too: what an unloaded machine's wall time would be when other jobs share it
    cpu = comm.allreduce(time.process_time() - cpu_tic, op=MPI.MAX)
    iterations = sum(r.iterations for r in records)
    split: dict[str, float] = {}
    for r in records:
        for key, value in r.timings.items():
            split[key] = split.get(key, 0.0) + comm.allreduce(value, op=MPI.MAX)
    return {
        "tets": num_tets,
        "wall": wall,
        "cpu": cpu,
        "iterations": iterations,
        "per_step": [r.iterations for r in records],
        "factorisations": factorisations[-len(records) :],
        "loads": [r.load for r in records],
        "split": {k: v / iterations for k, v in split.items()},
        "last": records[-1].diagnostics,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lower", type=int, nargs=3, default=(24, 24, 8))
    parser.add_argument("--upper", type=int, nargs=3, default=(16, 16, 8))
    parser.add_argument("--mu", type=float, default=0.3)
    parser.add_argument(
        "--switch-rule", choices=("on", "off", "both"), default="on",
        help="the linear solver's factorisation once the stick/slip set moved "
        "(linear_solver.FRICTION_SWITCH_SHARE); 'both' runs the friction twice, with it and "
        "without, for a comparison on the same machine state",
    )  # fmt: skip
    parser.add_argument("--repeat", type=int, default=1, help="run the whole set this often")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    # a small model first: the kernels' compilation (or cache loading) is not measured
    run(comm, (4, 4, 2), (3, 3, 2), fm.Coulomb(args.mu))
    share = linear_solver.FRICTION_SWITCH_SHARE
    cases = [("frictionless", None, share)]
    rules = {"on": [("", share)], "off": [(", switch rule off", np.inf)]}
    rules["both"] = rules["on"] + rules["off"]
    for suffix, value in rules[args.switch_rule]:
        cases.append((f"mu = {args.mu}{suffix}", fm.Coulomb(args.mu), value))
    for _ in range(args.repeat):
        out = {}
        for name, friction, value in cases:
            linear_solver.FRICTION_SWITCH_SHARE = value
            out[name] = r = run(comm, args.lower, args.upper, friction)
            linear_solver.FRICTION_SWITCH_SHARE = share
            if comm.rank == 0:
                split = ", ".join(f"{k} {v:.3f}" for k, v in r["split"].items())
                print(
                    f"{name}: {r['tets']} tets, {comm.size} process(es); iterations per step "
                    f"{r['per_step']} (loads {r['loads']}), factorised {r['factorisations']}; "
                    f"{r['wall'] / r['iterations']:.3f} s "
                    f"({r['cpu'] / r['iterations']:.3f} s CPU) per iteration ({split} s/it)"
                )
                friction_keys = ("friction_dissipation", "stick_points", "slip_points")
                last = {k: r["last"][k] for k in friction_keys if k in r["last"]}
                if last:
                    print(f"  last step: {last}")
        if comm.rank != 0:
            continue
        a = out["frictionless"]
        for name, _, _ in cases[1:]:
            b = out[name]
            for kind in ("wall", "cpu"):
                ratio = (b[kind] / b["iterations"]) / (a[kind] / a["iterations"])
                print(
                    f"{name} / frictionless, {kind} seconds per Newton iteration: {ratio:.2f} "
                    f"(target <= {TARGET_RATIO}: ratio {ratio / TARGET_RATIO:.2f})"
                )
            print(f"Newton iterations: {b['iterations']} ({name}), {a['iterations']} without")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
