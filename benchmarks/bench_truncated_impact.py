"""Energy in a step the continuous collision detection ends at an impact, per contact force.

A stiff cube (0.2 wide, 2^3 cuboids, neo-Hookean E = 1000, nu = 0.3, rho = 1) 0.05 above a
0.3 x 0.3 x 0.05 plate (6 x 6 x 1 cuboids) clamped on its sides flies at it at ``speed``;
average-acceleration Newmark, dt = 0.01, ``propose_penalty(mesh, E, factor=10)``, collision
detection on (the default): the step that would carry the cube through the plate is truncated
at the impact, so the contact starts late in that step. Printed per contact force and speed:
the total energy (kinetic + strain + contact) after the first step and its largest value over
``--steps`` steps, relative to the initial kinetic energy, Newton iterations and cuts.

Run: ``scripts/fenicsx python3 benchmarks/bench_truncated_impact.py [--speeds 30 50]
[--schemes endpoint midpoint discrete_gradient] [--steps 5]``.

``--trace T`` instead runs each speed with the default contact force to time T and prints
every step: dt, truncations, cuts, Newton iterations, the cube's lowest point against the
plate's top surface (its lowest point: the plate bends), the cube's mean nodal velocity, the
smallest det F, the energies, then how the run ended (docs/dynamics.md, "What it does not
do": ``--speeds 500 --trace 0.005 --factor 5900 --min-dt 1e-7`` is the cube at the penalty
the stop names, ``--youngs 1e6 --trace 0.003 --min-dt 1e-7`` on stiff bodies;
``--max-penalty`` passes ``solve_time_steps(max_penalty=...)``).
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl

import fenics_matdepth as fm

E, NU, RHO, DT, GAP = 1000.0, 0.3, 1.0, 0.01, 0.05


def cube_over_plate(comm: MPI.Comm) -> dolfinx.mesh.Mesh:
    xp, cp = fm.meshing.box_tetrahedra(
        (6, 6, 1), origin=(-0.15, -0.15, -0.05), size=(0.3, 0.3, 0.05)
    )
    xc, cc = fm.meshing.box_tetrahedra(2, origin=(-0.1, -0.1, GAP), size=(0.2, 0.2, 0.2))
    return fm.meshing.create_tetrahedral_mesh(
        comm, np.vstack([cp, cc + xp.shape[0]]), np.vstack([xp, xc])
    )


def setup(mesh, speed: float, youngs: float = E, factor: float = 10.0):
    """The cube flying at the plate: (problem, integrator, strain energy density)."""
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(youngs, NU)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    elastic = ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(
        mesh, 2, lambda x: np.isclose(np.abs(x[0]), 0.15) | np.isclose(np.abs(x[1]), 0.15)
    )
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    ]
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, youngs, factor=factor)
    )
    integrator = fm.Newmark(u, DT, rho=RHO)
    residual = integrator.inertia(v) + elastic
    v0 = dolfinx.fem.Function(V)
    v0.interpolate(lambda x: np.vstack((0 * x[0], 0 * x[0], np.where(x[2] > 0.01, -speed, 0.0))))
    integrator.initial(None, v0, residual=residual, contact=contact, bcs=bcs)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=integrator.incremental_energy(psi * ufl.dx),
        petsc_options_prefix="truncated_",
    )  # fmt: skip
    return problem, integrator, psi


def trace(mesh, speed: float, t_end: float, args) -> None:
    """Print every step of the cube's flight to ``t_end`` and how the run ended."""
    comm = mesh.comm
    problem, integrator, psi = setup(mesh, speed, args.youngs, args.factor)
    u = problem.u
    V = u.function_space
    n = V.dofmap.index_map.size_local
    z = V.tabulate_dof_coordinates()[:n, 2]
    cube, top = z > 0.01, np.isclose(z, 0.0)
    count = comm.allreduce(int(cube.sum()))
    cells = fm.kinematics.CellDeterminants(V)

    def lowest(mask):
        height = z + u.x.array[: 3 * n].reshape(-1, 3)[:, 2]
        return comm.allreduce(float(height[mask].min()) if mask.any() else np.inf, op=MPI.MIN)

    def line(r):
        vz = integrator.v_prev.x.array[: 3 * n].reshape(-1, 3)[:, 2]
        velocity = comm.allreduce(float(vz[cube].sum())) / count
        det = cells.min(u)
        if comm.rank == 0:
            print(
                f"step {r.step:3d} t {r.t:.4g} dt {r.dt:.3g} trunc {r.truncations} cuts {r.cuts} "
                f"its {r.iterations:2d} lowest {lowest(cube) - lowest(top):+.5f} top "
                f"{lowest(top):+.5f} velocity {velocity:+8.2f} detF {det:.3f} kinetic "
                f"{r.kinetic_energy:.4g} contact {r.contact_energy:.4g} total "
                f"{r.total_energy:.6g}",
                flush=True,
            )
        else:
            lowest(cube), lowest(top)

    tic = time.perf_counter()
    try:
        history = fm.solve_time_steps(
            problem, integrator, t_end, DT, on_step=line, strain_energy=psi * ufl.dx,
            progress=False, min_dt=args.min_dt, max_penalty=args.max_penalty,
        )  # fmt: skip
        end = f"reached t = {history[-1].t:.4g} in {len(history) - 1} steps"
    except RuntimeError as err:
        end = f"stopped: {str(err)[:700]}"
    penalty = problem.contact.penalty
    problem.destroy()
    if comm.rank == 0:
        print(f"speed {speed}: {end}; penalty {penalty:.3g}; {time.perf_counter() - tic:.1f} s")


def run(mesh, speed: float, scheme: str, steps: int, gain: float | None = None) -> dict:
    problem, integrator, psi = setup(mesh, speed)
    kinetic = 0.5 * RHO * 0.2**3 * speed**2
    try:
        history = fm.solve_time_steps(
            problem, integrator, steps * DT, DT, strain_energy=psi * ufl.dx, progress=False,
            contact_force=scheme,
            max_energy_gain=None if gain is None else gain * kinetic,
        )  # fmt: skip
        failure = ""
    except RuntimeError as err:
        history, failure = [], str(err)[:200]
    problem.destroy()
    if not history:
        return {"failure": failure}
    energy = np.array([r.total_energy for r in history]) / kinetic
    return {
        "failure": "",
        "first": energy[1],
        "max": energy.max(),
        "first_dt": history[1].dt,
        "its": np.mean([r.iterations for r in history[1:]]),
        "max_its": max(r.iterations for r in history[1:]),
        "cuts": sum(r.cuts for r in history),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--speeds", nargs="*", type=float, default=[30.0, 50.0])
    parser.add_argument(
        "--schemes", nargs="*", default=["endpoint", "midpoint", "discrete_gradient"]
    )
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--trace", type=float, default=None, help="print every step to this time")
    parser.add_argument("--youngs", type=float, default=E, help="(--trace) both bodies' E")
    parser.add_argument("--factor", type=float, default=10.0, help="(--trace) propose_penalty's")
    parser.add_argument("--min-dt", type=float, default=None, help="(--trace) min_dt")
    parser.add_argument("--max-penalty", type=float, default=None, help="(--trace) max_penalty")
    parser.add_argument(
        "--max-energy-gain", type=float, default=None,
        help="solve_time_steps(max_energy_gain=...) as a fraction of the initial kinetic energy",
    )  # fmt: skip
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    mesh = cube_over_plate(comm)
    if args.trace is not None:
        for speed in args.speeds:
            trace(mesh, speed, args.trace, args)
        return
    if comm.rank == 0:
        print(
            f"{comm.size} rank(s), dt {DT}, {args.steps} steps, max_energy_gain "
            f"{args.max_energy_gain}; energy / initial kinetic"
        )
    for speed in args.speeds:
        for scheme in args.schemes:
            r = run(mesh, speed, scheme, args.steps, args.max_energy_gain)
            if comm.rank != 0:
                continue
            if r["failure"]:
                print(f"speed {speed:5.1f} {scheme:17s} failed: {r['failure']}", flush=True)
                continue
            print(
                f"speed {speed:5.1f} {scheme:17s} first step (dt {r['first_dt']:.3g}) "
                f"{r['first']:.4f}, max {r['max']:.4f}; Newton its {r['its']:.2f} mean, "
                f"{r['max_its']} max; cuts {r['cuts']}",
                flush=True,
            )


if __name__ == "__main__":
    main()
