"""Whether the knee's converged load steps are stable: the inertia of the Jacobian at each.

Runs ``demos/demo_knee.py`` in this process and, at each converged load step (before the
demo's own writer), assembles the Jacobian at the converged state and counts its negative and
null eigenvalues (:func:`fenics_matdepth.linear_solver.inertia`: the pivots of an LDL^T
factorisation). A negative eigenvalue makes the state a saddle of the energy, an unstable
equilibrium: the next step starts from a state a real leg would leave. One ``STABILITY`` line
a step; the summary lists the saddles. Settings as the demo's (``MATDEPTH_KNEE_*``).

Run: ``MATDEPTH_KNEE_DEGREES=6 MATDEPTH_KNEE_STEPS=2 scripts/fenicsx python3
benchmarks/diagnose_stability.py``. Prints figures; asserts nothing. A factorisation costs
about 0.2 s on the coarse leg (serial or parallel).
"""

from __future__ import annotations

import runpy

from diagnose_knee import DEMO

import fenics_matdepth as fm
from fenics_matdepth.linear_solver import inertia
from fenics_matdepth.step_control import find_contact_problem


def main() -> None:
    solve_load_steps = fm.solve_load_steps
    rows: list[tuple[float, int, int]] = []

    def checked(solver, *args, **kwargs):
        problem = find_contact_problem(solver)
        snes, writer = problem.snes, kwargs["writer"]
        residual = problem.u.x.petsc_vec.duplicate()

        def write(t: float) -> None:
            # the Jacobian at the converged state (the solve's last one is that of the
            # iterate before it), in a copy of the problem's matrix and pattern
            x = problem.u.x.petsc_vec.copy()
            snes.computeFunction(x, residual)
            A = snes.getJacobian()[0].duplicate()
            snes.computeJacobian(x, A)
            negative, null = inertia(A)
            A.destroy()
            x.destroy()
            rows.append((t, negative, null))
            if problem.u.function_space.mesh.comm.rank == 0:
                print(f"STABILITY load {t:.5f}: {negative} negative, {null} null eigenvalues")
            writer(t)

        kwargs["writer"] = write
        return solve_load_steps(solver, *args, **kwargs)

    fm.solve_load_steps = checked
    try:
        runpy.run_path(str(DEMO), run_name="__main__")
    finally:
        fm.solve_load_steps = solve_load_steps
        saddles = [f"{t:.4f} ({n})" for t, n, _ in rows if n > 0]
        print(
            f"STABILITY summary: {len(rows)} converged steps, {len(saddles)} saddles "
            f"(load, negative eigenvalues): {', '.join(saddles) or 'none'}"
        )


if __name__ == "__main__":
    main()
