"""Where the energy of the truncated impact goes, step by step: bulk, contact, equilibrium.

The model of ``bench_truncated_impact.py`` (a stiff cube at ``--speed`` onto a clamped plate,
average-acceleration Newmark, dt = 0.01, the collision detection on). Over a Newmark step
(beta = 1/4, gamma = 1/2) the kinetic energy changes by ``dKE = M (a_n + a_{n+1}) / 2 . du``,
so with ``r = M a + f_int + f_c`` (the equation of motion's residual at each end, free dofs),

    ``dE = dKE + dPsi + dW = [dPsi - (f_int,n + f_int,n+1) / 2 . du]``   (bulk)
    ``                     + [dW - (f_c,n + f_c,n+1) / 2 . du]``         (contact)
    ``                     + (r_n + r_n+1) / 2 . du``                    (equilibrium),

``f_c`` the contact force the step equation carries (``dW/du`` with the end-of-step force; the
carried ``f_{n+1}`` of the midpoint force and the discrete gradient). Printed per converged
step, relative to the initial kinetic energy: the total, its change and the three terms; with
the discrete gradient also the step's pairs, their energies at both ends against the
operator's ``W`` (a pair missing from the step would show there) and ``DG . du - dW``.

``--bulk`` measures the remedy for the bulk's term: the step equation in its average form,
``M (a_n + a_{n+1}) / 2 + DG_bulk + DG_contact = 0``, with ``DG_bulk`` the discrete gradient of
the strain energy (Gonzalez 1996, per quadrature point on ``C = F^T F``): ``(F_m S) : grad v``
with ``F_m = (F_n + F_{n+1}) / 2`` and ``S = S(C_m) + 2 (psi(C_{n+1}) - psi(C_n) - S(C_m) : dC
/ 2) dC / (dC : dC)``, ``S(C) = 2 dpsi/dC``, so that its work over the step is ``dPsi``. The
contact's discrete gradient then carries no force from step to step (the package has no switch
for that yet: the benchmark sets it), and the residual line search replaces the energy's.
The split's terms do not apply there; the total and its change do.

Run: ``scripts/fenicsx python3 benchmarks/bench_impact_energy_split.py [--speed 30]
[--steps 2] [--scheme discrete_gradient] [--bulk]`` (serial).
"""

from __future__ import annotations

import argparse

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl
from bench_truncated_impact import DT, NU, RHO, E, cube_over_plate

import fenics_matdepth as fm


def bulk_discrete_gradient(integ, u, v, mu, kappa) -> ufl.Form:
    """The average-form step residual with the bulk's discrete gradient (module docstring),
    the neo-Hookean energy of ``fm.materials.neo_hookean`` written in ``C``; sets the contact's
    discrete gradient to carry no force."""

    def carry_nothing(self) -> None:
        self.force.set(0.0)

    # M (a_n + a_{n+1}) / 2 + DG = 0, doubled: the contact term is then 2 DG, no f_n
    fm.impacts.DiscreteGradientContact.start = carry_nothing
    fm.impacts.DiscreteGradientContact.accept = carry_nothing

    def psi(C):
        d = ufl.det(C)  # J^2
        return mu / 2 * (d ** (-1.0 / 3.0) * ufl.tr(C) - 3) + kappa / 4 * (d - 1 - ufl.ln(d))

    identity = ufl.Identity(3)
    F0, F1 = identity + ufl.grad(integ.u_prev), identity + ufl.grad(u)
    C0, C1 = F0.T * F0, F1.T * F1
    Cm = ufl.variable(0.5 * (C0 + C1))
    Sm = 2 * ufl.diff(psi(Cm), Cm)
    dC = C1 - C0
    dCdC = ufl.inner(dC, dC)
    # no correction where dC is at rounding level (there it is of order |dC|^2 itself)
    c = ufl.conditional(
        ufl.gt(dCdC, 1e-18),
        2 * (psi(C1) - psi(C0) - 0.5 * ufl.inner(Sm, dC)) / (dCdC + 1e-300),
        0.0,
    )
    S = Sm + c * dC
    return (
        integ.inertia(v)
        + RHO * ufl.inner(integ.a_prev, v) * ufl.dx
        + 2 * ufl.inner(0.5 * (F0 + F1) * S, ufl.grad(v)) * ufl.dx
    )


class EnergySplit:
    """A Newmark run's energy change per converged step, split into the bulk's, the contact's
    and the equilibrium's terms (module docstring; serial). Call :meth:`step` from
    ``solve_time_steps``'s ``on_step``.

    Args:
        problem: the ContactProblem (its assembler's contact term is the step's during a run).
        integ: the average-acceleration Newmark integrator.
        elastic: the internal force's form (the strain energy's derivative).
        strain: the strain energy's form.
        bcs: the Dirichlet conditions (their dofs are left out of the residuals).
        rho: the density of the inertia term.
        load: the linear form of a conservative load ``f_ext . v`` (e.g. gravity), whose work
            ``f_ext . u`` the total energy subtracts, or None.
    """

    def __init__(self, problem, integ, elastic, strain, bcs, rho: float, load=None):
        self.problem, self.integ, self.contact = problem, integ, problem.contact
        self.u = u = integ.u
        V = u.function_space
        self.acceleration = dolfinx.fem.Function(V)
        v = ufl.TestFunction(V)
        self.mass_form = dolfinx.fem.form(rho * ufl.inner(self.acceleration, v) * ufl.dx)
        self.fint_form = dolfinx.fem.form(elastic)
        self.strain_form = dolfinx.fem.form(strain)
        self.n = n = V.dofmap.index_map.size_local * 3
        self.free = np.ones(n, dtype=bool)
        for bc in bcs:
            dofs, count = bc.dof_indices()
            dofs = np.asarray(dofs[:count])
            self.free[dofs[dofs < n]] = False
        self.fext = self.assembled(dolfinx.fem.form(load)) if load is not None else np.zeros(n)
        self.last = self.state(None)  # f_0 = dW/du (u_0), as the carried forces start

    @staticmethod
    def assembled(form) -> np.ndarray:
        b = dolfinx.fem.petsc.assemble_vector(form)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        out = b.array.copy()
        b.destroy()
        return out

    def contact_gradient(self) -> np.ndarray:
        self.contact.update()
        b = self.u.x.petsc_vec.duplicate()
        b.set(0.0)
        self.contact.add_residual(b)
        out = b.array.copy()
        b.destroy()
        return out

    def state(self, carried: np.ndarray | None) -> dict:
        """The last converged state's terms (u is set to it for the evaluations)."""
        u, integ, n = self.u, self.integ, self.n
        saved = u.x.array.copy()
        u.x.array[:] = integ.u_prev.x.array
        self.acceleration.x.array[:] = integ.a_prev.x.array
        try:
            fc = self.contact_gradient() if carried is None else carried
            self.contact.update()
            out = {
                "u": integ.u_prev.x.array[:n].copy(), "Ma": self.assembled(self.mass_form),
                "fint": self.assembled(self.fint_form), "fc": fc, "W": self.contact.energy(),
                "strain": float(dolfinx.fem.assemble_scalar(self.strain_form)),
                "ke": integ.kinetic_energy(),
            }  # fmt: skip
            out["external"] = float(self.fext @ out["u"])
        finally:
            u.x.array[:] = saved
        return out

    def step(self) -> dict:
        """The terms of the step just converged and advanced (energies, F L): the total ``E``
        (kinetic + strain + contact - the load's work), its change ``dE`` = ``bulk`` +
        ``contact`` + ``equilibrium``, and ``W1`` the contact energy at its end; with the
        discrete gradient, the step's pairs and their checks."""
        step = self.problem.assembler.contact  # the step's contact term during the run
        carried = step.force.array.copy() if hasattr(step, "force") else None
        s, p = self.state(carried), self.last
        du = s["u"] - p["u"]
        r0 = (p["Ma"] + p["fint"] + p["fc"] - self.fext) * self.free
        r1 = (s["Ma"] + s["fint"] + s["fc"] - self.fext) * self.free
        total = s["ke"] + s["strain"] + s["W"] - s["external"]
        out = {
            "E": total,
            "dE": total - (p["ke"] + p["strain"] + p["W"] - p["external"]),
            "bulk": s["strain"] - p["strain"] - 0.5 * (p["fint"] + s["fint"]) @ du,
            "contact": s["W"] - p["W"] - 0.5 * (p["fc"] + s["fc"]) @ du,
            "equilibrium": 0.5 * (r0 + r1) @ du,
            "W0": p["W"],
            "W1": s["W"],
            "residual": float(np.linalg.norm(r1)),
        }
        pairs = getattr(step, "pairs", None)
        if pairs is not None:
            dx = (pairs.x1[pairs.verts] - pairs.x0[pairs.verts]).reshape(-1, 21)
            work = float(np.sum(pairs.gradient * dx))
            de = float(pairs.energy1.sum() - pairs.energy0.sum())
            out.update(
                pairs=pairs.verts.shape[0], W0_check=pairs.energy0.sum() - p["W"],
                W1_check=pairs.energy1.sum() - s["W"], dg_check=work - de,
            )  # fmt: skip
        self.last = s
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--speed", type=float, default=30.0)
    parser.add_argument("--steps", type=int, default=2, help="time steps of DT = 0.01")
    parser.add_argument("--scheme", default="discrete_gradient", choices=fm.impacts.CONTACT_FORCES)
    parser.add_argument("--bulk", action="store_true", help="the bulk's discrete gradient too")
    args = parser.parse_args()
    if args.bulk and args.scheme != "discrete_gradient":
        raise SystemExit("--bulk goes with --scheme discrete_gradient")
    if MPI.COMM_WORLD.size != 1:
        raise SystemExit("serial only (the split sums owned arrays of one rank)")
    mesh = cube_over_plate(MPI.COMM_WORLD)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    u = dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    mu, kappa = fm.materials.shear_bulk_from_youngs_poisson(E, NU)
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    psi = fm.materials.neo_hookean(F_def, mu, kappa)
    elastic = ufl.inner(ufl.diff(psi, F_def), ufl.grad(v)) * ufl.dx
    facets = dolfinx.mesh.locate_entities_boundary(
        mesh, 2, lambda x: np.isclose(np.abs(x[0]), 0.15) | np.isclose(np.abs(x[1]), 0.15)
    )
    clamped = dolfinx.fem.locate_dofs_topological(V, 2, facets)
    bcs = [dolfinx.fem.dirichletbc(np.zeros(3), clamped, V)]
    contact = fm.ContactOperator(
        u, fm.material_depth(mesh), penalty=fm.propose_penalty(mesh, E, factor=10.0)
    )
    integ = fm.Newmark(u, DT, rho=RHO)
    residual = integ.inertia(v) + elastic
    v0 = dolfinx.fem.Function(V)
    v0.interpolate(
        lambda x: np.vstack((0 * x[0], 0 * x[0], np.where(x[2] > 0.01, -args.speed, 0.0)))
    )
    integ.initial(None, v0, residual=residual, contact=contact, bcs=bcs)
    energy = integ.incremental_energy(psi * ufl.dx)
    if args.bulk:
        residual, energy = bulk_discrete_gradient(integ, u, v, mu, kappa), None
    problem = fm.ContactProblem(
        residual, u, contact, bcs=bcs, energy=energy, petsc_options_prefix="split_"
    )
    kinetic0 = 0.5 * RHO * 0.2**3 * args.speed**2
    split = EnergySplit(problem, integ, elastic, psi * ufl.dx, bcs, rho=RHO)

    def on_step(record) -> None:
        t = split.step()
        line = (
            f"step {record.step:3d} t {record.t:.5f} dt {record.dt:.2e} cuts {record.cuts:2d} "
            f"its {record.iterations:2d}  E {t['E'] / kinetic0:.5f} "
            f"dE {t['dE'] / kinetic0:+.2e} = bulk {t['bulk'] / kinetic0:+.2e} contact "
            f"{t['contact'] / kinetic0:+.2e} equilibrium {t['equilibrium'] / kinetic0:+.2e}"
        )
        if "pairs" in t:
            line += (
                f"  pairs {t['pairs']} (W0 {t['W0_check']:+.1e}, W1 {t['W1_check']:+.1e}; "
                f"DG.du - dW {t['dg_check']:+.1e})"
            )
        print(line, flush=True)

    history = fm.solve_time_steps(
        problem, integ, args.steps * DT, DT, strain_energy=psi * ufl.dx, progress=False,
        contact_force=args.scheme, on_step=on_step,
    )  # fmt: skip
    largest = max(r.total_energy for r in history) / kinetic0
    print(f"largest total energy / initial kinetic: {largest:.5f}")


if __name__ == "__main__":
    main()
