"""Energy and momentum through impacts in implicit dynamics.

Two models, no gravity, no supports (the bodies are held only by each other):

- ``cubes``: two unit cubes (5^3 cuboids, 750 tetrahedra each; neo-Hookean, E = 100,
  nu = 0.3, rho = 1) 0.1 apart along x, the second offset sideways by 0.1, flying at each
  other at 0.5 each; Newmark (beta = 1/4, gamma = 1/2), dt = 0.01, t_end = 0.6;
- ``blocks``: the same cubes face-on (no offset) at 1 each with dt = 0.05: the closing
  displacement per step is half an element (an impact resolved by one to three steps).

Printed per model and contact-force scheme (``solve_time_steps(contact_force=...)``):
the largest total energy (kinetic + strain + contact) over the steps relative to the start,
the smallest, the linear momentum drift (relative to one body's momentum), Newton iterations
per step (mean, max), cuts, contact steps, and the wall time.

Run: ``scripts/fenicsx python3 benchmarks/bench_impacts.py [--models cubes blocks]
[--schemes endpoint midpoint discrete_gradient] [--methods newmark backward_euler] [--cells 5]``
(or under ``mpirun -n 2``).
"""

from __future__ import annotations

import argparse
import inspect
import time

from mpi4py import MPI

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

import fenics_matdepth as fm

E, NU, RHO = 100.0, 0.3, 1.0


def two_cubes(comm: MPI.Comm, cells: int, gap: float, offset: float) -> dolfinx.mesh.Mesh:
    """Two unit cubes ``gap`` apart along x, the right one shifted by ``offset`` along y."""
    xa, ca = fm.meshing.box_tetrahedra(cells, origin=(-1.0 - gap / 2, 0.0, 0.0))
    xb, cb = fm.meshing.box_tetrahedra(cells, origin=(gap / 2, offset, 0.0))
    x = np.vstack([xa, xb])
    c = np.vstack([ca, cb + xa.shape[0]])
    return fm.meshing.create_tetrahedral_mesh(comm, c, x)


class Impact:
    """Neo-Hookean bodies, an integrator and a ContactProblem, set up as the docs show."""

    def __init__(self, mesh, method: str, dt: float, speed: float, energy: bool = True):
        V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        self.u = u = dolfinx.fem.Function(V)
        v = ufl.TestFunction(V)
        mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(E, NU)
        F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
        psi = fm.materials.neo_hookean(F_def, mu, kappa)
        self.strain_energy = psi * ufl.dx
        elastic = ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * ufl.dx
        self.contact = fm.ContactOperator(
            u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E)
        )
        if method == "newmark":
            self.integrator = fm.Newmark(u, dt, beta=0.25, gamma=0.5, rho=RHO)
        else:
            self.integrator = fm.BackwardEuler(u, dt, rho=RHO)
        residual = self.integrator.inertia(v) + elastic
        v0 = dolfinx.fem.Function(V)
        v0.interpolate(lambda x: np.vstack((-speed * np.sign(x[0]), 0 * x[0], 0 * x[0])))
        self.integrator.initial(None, v0, residual=residual, contact=self.contact)
        self.problem = fm.ContactProblem(
            residual, u, self.contact,
            energy=self.integrator.incremental_energy(self.strain_energy) if energy else None,
            petsc_options_prefix="impacts_",
        )  # fmt: skip


def run(
    mesh,
    method: str,
    scheme: str | None,
    dt: float,
    speed: float,
    t_end: float,
    energy_cap: float | None = None,
    energy: bool = True,
    gain_cap: float | None = None,
) -> dict:
    comm = mesh.comm
    model = Impact(mesh, method, dt, speed, energy)
    p0 = model.integrator.linear_momentum()
    kwargs = {}
    if energy_cap is not None:  # relative to the initial (kinetic) energy
        kwargs["max_energy_change"] = energy_cap * model.integrator.kinetic_energy()
    if gain_cap is not None:  # relative to the initial (kinetic) energy
        kwargs["max_energy_gain"] = gain_cap * model.integrator.kinetic_energy()
    if scheme is not None:
        kwargs["contact_force"] = scheme
    tic = time.perf_counter()
    try:
        history = fm.solve_time_steps(
            model.problem, model.integrator, t_end, dt, strain_energy=model.strain_energy,
            progress=False, **kwargs,
        )  # fmt: skip
        failure = ""
    except RuntimeError as err:
        history, failure = [], str(err)
    seconds = comm.allreduce(time.perf_counter() - tic, op=MPI.MAX)
    p1 = model.integrator.linear_momentum()
    one_body = RHO * speed * 1.0  # a unit cube's momentum
    out = {"seconds": seconds, "failure": failure}
    if history:
        energy = np.array([r.total_energy for r in history])
        its = np.array([r.iterations for r in history[1:]])
        out.update(
            max_energy=energy.max() / energy[0],
            min_energy=energy.min() / energy[0],
            end_energy=energy[-1] / energy[0],
            momentum=np.abs(p1 - p0).max() / one_body,
            mean_its=its.mean(),
            max_its=its.max(),
            cuts=sum(r.cuts for r in history),
            steps=len(history) - 1,
            contact_steps=sum(r.active_pairs > 0 for r in history),
        )
    model.problem.destroy()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--models", nargs="*", default=["cubes", "blocks"])
    parser.add_argument("--schemes", nargs="*", default=None)
    parser.add_argument("--methods", nargs="*", default=["newmark", "backward_euler"])
    parser.add_argument("--cells", type=int, default=5)
    parser.add_argument(
        "--max-energy-change", type=float, default=None,
        help="solve_time_steps(max_energy_change=...) as a fraction of the initial energy",
    )  # fmt: skip
    parser.add_argument(
        "--max-energy-gain", type=float, default=None,
        help="solve_time_steps(max_energy_gain=...) as a fraction of the initial energy",
    )  # fmt: skip
    parser.add_argument(
        "--no-energy", action="store_true",
        help="ContactProblem without energy= (solve_time_steps hands it the potential when it can)",
    )  # fmt: skip
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    has_choice = "contact_force" in inspect.signature(fm.solve_time_steps).parameters
    schemes = (
        args.schemes
        if args.schemes
        else (list(fm.impacts.CONTACT_FORCES) if has_choice else [None])
    )
    setups = {
        # (offset, speed, dt, t_end)
        "cubes": (0.1, 0.5, 0.01, 0.6),
        "blocks": (0.0, 1.0, 0.05, 0.6),
    }
    if comm.rank == 0:
        print(
            f"{comm.size} rank(s), {args.cells}^3 cuboids per cube, max_energy_change "
            f"{args.max_energy_change}, max_energy_gain {args.max_energy_gain} (of the initial "
            "energy)" + (", ContactProblem without energy=" if args.no_energy else "")
        )
        print(
            f"{'model':7s} {'method':15s} {'contact force':13s} {'E max/E0':>9s} "
            f"{'E min/E0':>9s} {'E end/E0':>9s} {'momentum':>9s} {'its mean':>8s} {'max':>4s} "
            f"{'cuts':>4s} {'steps':>5s} {'contact':>7s} {'s':>6s}"
        )
    for name in args.models:
        offset, speed, dt, t_end = setups[name]
        mesh = two_cubes(comm, args.cells, 0.1, offset)
        for method in args.methods:
            for scheme in schemes:
                if method == "backward_euler" and scheme == "midpoint":
                    continue  # average-acceleration Newmark only
                r = run(
                    mesh, method, scheme, dt, speed, t_end, args.max_energy_change,
                    not args.no_energy, args.max_energy_gain,
                )  # fmt: skip
                if comm.rank != 0:
                    continue
                label = scheme or "(default)"
                if r["failure"]:
                    print(f"{name:7s} {method:15s} {label:13s} failed: {r['failure']}")
                    continue
                print(
                    f"{name:7s} {method:15s} {label:13s} {r['max_energy']:9.4f} "
                    f"{r['min_energy']:9.4f} {r['end_energy']:9.4f} {r['momentum']:9.1e} "
                    f"{r['mean_its']:8.2f} {r['max_its']:4d} {r['cuts']:4d} {r['steps']:5d} "
                    f"{r['contact_steps']:7d} {r['seconds']:6.1f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
