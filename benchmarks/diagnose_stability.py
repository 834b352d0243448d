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

from petsc4py import PETSc

from diagnose_knee import run_knee_with

from fenics_matdepth.linear_solver import inertia


def jacobian_at(problem) -> PETSc.Mat:
    """The problem's Jacobian at its current state ``problem.u`` (the last one its solve
    assembled is that of the iterate before), in a new matrix of the problem's pattern."""
    snes = problem.snes
    x = problem.u.x.petsc_vec.copy()
    residual = x.duplicate()
    snes.computeFunction(x, residual)
    A = snes.getJacobian()[0].duplicate()
    snes.computeJacobian(x, A)
    residual.destroy()
    x.destroy()
    return A


def main() -> None:
    rows: list[tuple[float, int, int]] = []

    def install(problem, demo: dict):
        def wrap(writer):
            def write(t: float) -> None:
                A = jacobian_at(problem)
                negative, null = inertia(A)
                A.destroy()
                rows.append((t, negative, null))
                if problem.u.function_space.mesh.comm.rank == 0:
                    print(f"STABILITY load {t:.5f}: {negative} negative, {null} null eigenvalues")
                writer(t)

            return write

        return wrap

    try:
        run_knee_with(install)
    finally:
        saddles = [f"{t:.4f} ({n})" for t, n, _ in rows if n > 0]
        print(
            f"STABILITY summary: {len(rows)} converged steps, {len(saddles)} saddles "
            f"(load, negative eigenvalues): {', '.join(saddles) or 'none'}"
        )


if __name__ == "__main__":
    main()
