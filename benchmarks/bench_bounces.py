"""A ball dropped on a clamped plate under gravity: its bounces, per contact-force scheme.

A ball (radius 0.2, gmsh, neo-Hookean E = 100, nu = 0.3, rho = 1) starts at rest 0.2 above a
1 x 1 x 0.2 plate clamped at its bottom, gravity 10 along -z; average-acceleration Newmark,
dt = 0.01, ``propose_penalty(mesh, E)``, the integrator's incremental potential as the energy.
Printed per scheme (``solve_time_steps(contact_force=...)``): the height of the ball's centre
of mass at each apex after a bounce (relative to its start above the plate), whether each is
at most the previous one, the largest total energy over the steps relative to the start
(kinetic + strain + contact - work of gravity; measured against the initial potential energy
of the drop), Newton iterations per step, cuts and the wall time.

Run: ``scripts/fenicsx python3 benchmarks/bench_bounces.py [--t-end 3] [--schemes endpoint
midpoint] [--size 0.08]`` (or under ``mpirun -n 2``).
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI

import dolfinx
import numpy as np
import ufl
from bench_impact_energy_split import EnergySplit

import fenics_matdepth as fm

E, NU, RHO, GRAVITY = 100.0, 0.3, 1.0, 10.0
RADIUS, DROP, PLATE = 0.2, 0.2, 0.2


def ball_over_plate(comm: MPI.Comm, size: float) -> dolfinx.mesh.Mesh:
    """A ball of radius RADIUS at DROP above a 1 x 1 x PLATE plate whose top is z = 0."""
    import gmsh

    def build(model):
        occ = model.occ
        plate = occ.addBox(-0.5, -0.5, -PLATE, 1.0, 1.0, PLATE)
        ball = occ.addSphere(0.0, 0.0, DROP + RADIUS, RADIUS)
        occ.synchronize()
        model.addPhysicalGroup(3, [plate], 1)
        model.addPhysicalGroup(3, [ball], 2)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", size)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", size)
        model.mesh.generate(3)

    mesh, _, _ = fm.meshing.gmsh_build_to_mesh(build, comm)
    return mesh


def run(
    mesh,
    scheme: str,
    dt: float,
    t_end: float,
    verbose: bool = False,
    split: bool = False,
    max_energy_change: float | None = None,
    max_energy_gain: float | None = None,
) -> dict:
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(E, NU)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    g = ufl.as_vector((0.0, 0.0, -GRAVITY))
    strain_energy = psi * ufl.dx
    gravity_work = RHO * ufl.inner(g, u) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[2], -PLATE))
    bcs = [
        dolfinx.fem.dirichletbc(np.zeros(3), dolfinx.fem.locate_dofs_topological(V, 2, facets), V)
    ]
    contact = fm.ContactOperator(u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E))
    integrator = fm.Newmark(u, dt, rho=RHO)
    elastic = ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * ufl.dx
    load = RHO * ufl.inner(g, v) * ufl.dx
    residual = integrator.inertia(v) + elastic - load
    integrator.initial(None, None, residual=residual, contact=contact, bcs=bcs)
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs,
        energy=integrator.incremental_energy(strain_energy - gravity_work),
        petsc_options_prefix="bounces_",
    )  # fmt: skip
    X = ufl.SpatialCoordinate(mesh)
    in_ball = ufl.conditional(ufl.gt(X[2], 0.5 * DROP), 1.0, 0.0)
    mass = mesh.comm.allreduce(dolfinx.fem.assemble_scalar(dolfinx.fem.form(in_ball * ufl.dx)))
    height_form = dolfinx.fem.form(in_ball * (X[2] + u[2]) * ufl.dx)
    heights = []
    drop_energy = RHO * GRAVITY * DROP * mass  # the potential energy the drop releases
    splitter = None
    if split:
        splitter = EnergySplit(problem, integrator, elastic, strain_energy, bcs, rho=RHO, load=load)
    terms = []

    def on_step(record):
        if splitter is not None and record is not None:
            t = splitter.step()
            t.update(step=record.step, t=record.t, dt=record.dt, cuts=record.cuts)
            t.update(its=record.iterations)
            terms.append(t)
            e = drop_energy
            print(
                f"  step {record.step:4d} t {record.t:.4f} dt {record.dt:.2e} cuts "
                f"{record.cuts:2d} its {record.iterations:2d} W {t['W1'] / e:.2e} "
                f"E-E0 {(t['E'] - terms[0]['E'] + terms[0]['dE']) / e:+.5f} dE "
                f"{t['dE'] / e:+.2e} = bulk {t['bulk'] / e:+.2e} contact "
                f"{t['contact'] / e:+.2e} equilibrium {t['equilibrium'] / e:+.2e}",
                flush=True,
            )
        z = mesh.comm.allreduce(dolfinx.fem.assemble_scalar(height_form)) / mass
        heights.append(z - RADIUS)  # the centre of mass above the plate, minus the radius
        if verbose and len(heights) >= 3 and heights[-3] < heights[-2] >= heights[-1]:
            if mesh.comm.rank == 0:  # an apex, as it comes (long runs)
                print(f"  {scheme}: apex {heights[-2] / DROP:.3f} at t {record.t:.3f}", flush=True)

    tic = time.perf_counter()
    on_step(None)
    history = fm.solve_time_steps(
        problem, integrator, t_end, dt, on_step=on_step, strain_energy=strain_energy,
        external_work=gravity_work, progress=False, contact_force=scheme,
        max_energy_change=None if max_energy_change is None else max_energy_change * drop_energy,
        max_energy_gain=None if max_energy_gain is None else max_energy_gain * drop_energy,
    )  # fmt: skip
    seconds = mesh.comm.allreduce(time.perf_counter() - tic, op=MPI.MAX)
    h = np.array(heights)
    apexes = [h[i] for i in range(1, h.size - 1) if h[i - 1] < h[i] >= h[i + 1]]
    energy = np.array([r.total_energy for r in history])
    its = np.array([r.iterations for r in history[1:]])
    problem.destroy()
    return {
        "apexes": np.array(apexes) / DROP,
        "max_energy": (energy.max() - energy[0]) / drop_energy,
        "end_energy": (energy[-1] - energy[0]) / drop_energy,
        "its": (its.mean(), its.max()),
        "cuts": sum(r.cuts for r in history),
        "steps": len(history) - 1,
        "seconds": seconds,
        "split": summarise(terms, drop_energy) if terms else "",
    }


def summarise(terms: list[dict], scale: float) -> str:
    """The split's sums over the steps with contact (contact energy at either end) and over
    the flight, and the five steps that gained most, relative to ``scale``."""
    lines = []
    touching = np.array([t["W0"] > 0.0 or t["W1"] > 0.0 for t in terms])
    for name, mask in (("contact steps", touching), ("flight steps", ~touching)):
        sums = {k: sum(t[k] for t, m in zip(terms, mask, strict=True) if m) / scale
                for k in ("dE", "bulk", "contact", "equilibrium")}  # fmt: skip
        lines.append(
            f"  {name} ({int(mask.sum())}): dE {sums['dE']:+.5f} = bulk {sums['bulk']:+.5f} "
            f"contact {sums['contact']:+.2e} equilibrium {sums['equilibrium']:+.2e}"
        )
    for t in sorted(terms, key=lambda t: -t["dE"])[:5]:
        lines.append(
            f"  gain at step {t['step']} (t {t['t']:.3f}, dt {t['dt']:.2e}, W {t['W1'] / scale:.1e}"
            f"): dE {t['dE'] / scale:+.2e} = bulk {t['bulk'] / scale:+.2e} contact "
            f"{t['contact'] / scale:+.2e} equilibrium {t['equilibrium'] / scale:+.2e}"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--t-end", type=float, default=3.0)
    parser.add_argument("--dt", type=float, default=0.01)
    parser.add_argument("--size", type=float, default=0.08)
    parser.add_argument("--schemes", nargs="*", default=["endpoint", "midpoint"])
    parser.add_argument("--verbose", action="store_true", help="print each apex as it comes")
    parser.add_argument(
        "--split", action="store_true",
        help="print each step's energy change split into bulk, contact and equilibrium "
        "(bench_impact_energy_split.py; serial, average-acceleration Newmark)",
    )  # fmt: skip
    parser.add_argument(
        "--max-energy-change", type=float, default=None,
        help="solve_time_steps' max_energy_change, as a fraction of the drop's energy",
    )  # fmt: skip
    parser.add_argument(
        "--max-energy-gain", type=float, default=None,
        help="solve_time_steps' max_energy_gain, as a fraction of the drop's energy",
    )  # fmt: skip
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    mesh = ball_over_plate(comm, args.size)
    cells = comm.allreduce(mesh.topology.index_map(3).size_local)
    if comm.rank == 0:
        print(f"{comm.size} rank(s), {cells} tetrahedra, dt {args.dt}, t_end {args.t_end}")
    for scheme in args.schemes:
        r = run(
            mesh, scheme, args.dt, args.t_end, args.verbose, args.split, args.max_energy_change,
            args.max_energy_gain,
        )  # fmt: skip
        if comm.rank != 0:
            continue
        a = r["apexes"]
        print(
            f"{scheme:9s} apexes/drop height: {' '.join(f'{x:.3f}' for x in a)}; each at most "
            f"the last: {bool(np.all(np.diff(a) <= 0.0))}; energy above start, max "
            f"{r['max_energy']:+.4f}, end {r['end_energy']:+.4f} (of the drop's); Newton its "
            f"{r['its'][0]:.2f} mean, {r['its'][1]} max; cuts {r['cuts']}; steps "
            f"{r['steps']}; {r['seconds']:.1f} s",
            flush=True,
        )
        if r["split"]:
            print(r["split"], flush=True)


if __name__ == "__main__":
    main()
