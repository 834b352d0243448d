"""Where the knee's Newton steps go: the energy along each full Newton direction.

Runs ``demos/demo_knee.py`` in this process (serially) with a hook at the start of each Newton
iteration of its :class:`~fenics_matdepth.ContactProblem` (before the problem's own). At the
iterate ``x`` it solves ``J y = F`` afresh (MUMPS LU: the full Newton direction, before any
shortening by the collision detection or the line search) and prints one ``DIR`` line:

- ``slope``: ``-F . y``, the energy's slope along ``x - s y`` at ``s = 0`` (negative: downhill);
- ``|y|max``, the median of ``|y|`` over the vertices, and ``n90``: how many vertices hold 90 %
  of ``|y|^2`` (a few: the step is a local mode of a few vertices);
- the change of the bulk energy and of the contact energy at ``x - s y`` for ``s`` in
  ``STEP_FRACTIONS`` (``nan``: a trial state the line search would reject, det F <= 0);
- ``PAIRS``: the same change of the total energy next to Newton's quadratic model of it,
  ``-s g + s^2 g / 2`` with ``g = F . y`` (``J y = F``, so ``y^T J y = g``), and the contact's
  change split by pair (triangle, tetrahedron): the pairs in contact at ``x`` and at the trial
  state, those entering (in contact only at the trial state: their Hessian is not in ``J``)
  and those leaving, with how many enter; then, for ``s`` in ``JACOBIAN_FRACTIONS``, how far
  the step shrinks the cells: the smallest ratio of det F at the trial state to det F at
  ``x`` and how many cells fall below one half and 0.8 of it or swell past 1.5;
- the five vertices with the longest step, with their body and reference position (mm).

At the end a ``SUMMARY`` sums the ``PAIRS`` lines (:func:`summary`). The state is restored
before the problem's own callback runs, but the contact operator has been updated at the
trial states in between (its pair search among them), and a late step's path can part from the
demo's: from the 144 deg checkpoint the diagnosed run cut its first step three times where the
demo converged it. One line costs a factorisation and a dozen energy evaluations;
``DIAGNOSE_ITERATIONS`` (default 60) bounds how many iterations are diagnosed. Settings as the
demo's (``MATDEPTH_KNEE_*``); to look at one late step, resume from a checkpoint
(``MATDEPTH_KNEE_RESUME=1``, ``MATDEPTH_DEMO_OUTPUT`` the folder holding it) and stop after it
(``MATDEPTH_KNEE_STOP_DEGREES``).

Run: ``MATDEPTH_KNEE_DEGREES=6 MATDEPTH_KNEE_STEPS=2 scripts/fenicsx python3
benchmarks/diagnose_directions.py``. Prints figures; asserts nothing.
"""

from __future__ import annotations

import os

from petsc4py import PETSc

import dolfinx
import numpy as np
from diagnose_knee import run_knee_with

#: the fractions s of the full Newton step at which the energies are evaluated
STEP_FRACTIONS = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
#: and those at which the cells' det F is compared with det F at the iterate (1.0 among them:
#: the summary reads the full step's)
JACOBIAN_FRACTIONS = (0.5, 1.0)


class DirectionDiagnosis:
    """The SNES update hook (see the module docstring); serial."""

    def __init__(self, problem, cell_body: np.ndarray, body_names, limit: int):
        self.problem = problem
        # the problem's own update callback, called after the diagnosis
        self.then, self.then_args, self.then_kwargs = problem.snes.getUpdate()
        self.assembler = problem.assembler
        self.limit = limit
        self.count = 0
        #: per direction after a solve's first iteration: ({s: (model, actual, bulk, kept,
        #: entering - leaving)}, the smallest det F ratio at the full step)
        self.records: list[tuple[dict, float]] = []
        V = problem.u.function_space
        n_cells = V.mesh.topology.index_map(3).size_local
        blocks = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
        self.body = np.full(blocks, -1)
        cells = V.dofmap.list[:n_cells]
        self.body[cells.ravel()] = np.repeat(cell_body[:n_cells], cells.shape[1])
        self.names = body_names
        self.X = V.tabulate_dof_coordinates()
        self.ksp = PETSc.KSP().create(V.mesh.comm)
        self.ksp.setType("preonly")
        pc = self.ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType("mumps")

    def energies(self, x: PETSc.Vec) -> tuple[float, float, dict | None]:
        """The bulk and contact energies at ``x`` (NaN where an element inverts) and the
        contact pairs' energies by pair (None there)."""
        self.assembler.set_state(x)
        if not self.assembler.min_det_F() > 0.0:
            return np.nan, np.nan, None
        bulk = dolfinx.fem.assemble_scalar(self.assembler.energy_form)
        verts, energy = self.problem.contact.pair_energies()
        rows = np.ascontiguousarray(verts, dtype=np.int64)
        pairs = {bytes(r): float(e) for r, e in zip(rows, energy, strict=True) if e > 0.0}
        return float(bulk), float(self.problem.contact.energy()), pairs

    def __call__(self, snes: PETSc.SNES, iteration: int) -> None:
        try:
            if self.count < self.limit:
                self.count += 1
                self.diagnose(snes, iteration)
        finally:
            self.then(snes, iteration, *self.then_args, **self.then_kwargs)

    def diagnose(self, snes: PETSc.SNES, iteration: int) -> None:
        x = snes.getSolution().copy()
        F, y, trial = x.duplicate(), x.duplicate(), x.duplicate()
        A = self.assembler.matrix.duplicate()
        try:
            self.assembler.set_state(x)
            if not self.assembler.residual(x, F):
                return
            self.assembler.jacobian(A)
            self.ksp.setOperators(A)
            self.ksp.solve(F, y)
            step = np.linalg.norm(y.getArray(readonly=True).reshape(-1, 3), axis=1)
            shares = np.sort(step**2)[::-1].cumsum() / max(float(np.sum(step**2)), 1e-300)
            bulk0, contact0, pairs0 = self.energies(x)
            slope = F.dot(y)
            profile, split = [], []
            record = {}  # s: (model, actual, bulk, pairs kept, pairs entering - leaving)
            for s in STEP_FRACTIONS:
                x.copy(trial)
                trial.axpy(-s, y)
                bulk, contact, pairs = self.energies(trial)
                profile.append(f"{s:g}: {bulk - bulk0:+.3g}/{contact - contact0:+.3g}")
                model = -s * slope + 0.5 * s * s * slope
                if pairs is None:
                    split.append(f"{s:g}: model {model:+.3g} inadmissible")
                    continue
                kept = sum(e - pairs0[k] for k, e in pairs.items() if k in pairs0)
                entering = [e for k, e in pairs.items() if k not in pairs0]
                entered = sum(entering)
                leaving = sum(e for k, e in pairs0.items() if k not in pairs)
                actual = bulk + contact - bulk0 - contact0
                record[s] = (model, actual, bulk - bulk0, kept, entered - leaving)
                split.append(
                    f"{s:g}: model {model:+.3g} actual {actual:+.3g} = bulk {bulk - bulk0:+.3g}"
                    f" kept {kept:+.3g} entering {entered:+.3g} ({len(entering)})"
                    f" leaving {-leaving:+.3g}"
                )
            longest = ", ".join(
                f"{step[i]:.2f} mm {self.names[self.body[i]]} at {np.round(self.X[i], 0).tolist()}"
                for i in np.argsort(step)[::-1][:5]
            )
            print(
                f"DIR it {iteration} |F| {snes.getFunctionNorm():.3e} slope "
                f"{-F.dot(y):.3e} |y|max {step.max():.3g} mm median {np.median(step):.3g} mm "
                f"n90 {int(np.searchsorted(shares, 0.9)) + 1} | d(bulk)/d(contact) energy "
                f"{'; '.join(profile)} | longest {longest}",
                flush=True,
            )
            # how far the step shrinks or swells the cells: det F at the trial over det F at x
            # (serial: x holds every vertex)
            cells = self.assembler.cells
            u0, step_array = x.getArray(readonly=True), y.getArray(readonly=True)
            det0 = cells.local_values(u0)
            shrink, smallest = [], {}
            for s in JACOBIAN_FRACTIONS:
                ratio = cells.local_values(u0 - s * step_array) / det0
                smallest[s] = float(ratio.min())
                shrink.append(
                    f"{s:g}: min {ratio.min():.3g}, {int(np.sum(ratio < 0.5))} below 0.5, "
                    f"{int(np.sum(ratio < 0.8))} below 0.8, {int(np.sum(ratio > 1.5))} above 1.5"
                )
            print(
                f"PAIRS it {iteration} | {'; '.join(split)} | det F ratio {'; '.join(shrink)}",
                flush=True,
            )
            if iteration > 0:  # (a first iteration moves the Dirichlet dofs: energy rises)
                self.records.append((record, smallest[1.0]))
        finally:
            self.assembler.set_state(x)  # the solve goes on from x
            for vector in (x, F, y, trial):
                vector.destroy()
            A.destroy()


def summary(records: list[tuple[dict, float]]) -> list[str]:
    """The ``PAIRS`` lines summed: at each fraction s, how many directions change the energy
    as the quadratic model says (within 25 %) and how many raise it; of the full steps that
    raise it, which term rises most (bulk, pairs kept, pairs entering less those leaving) and
    the smallest det F ratio of those where the bulk does; that ratio over the full steps the
    model predicts."""
    lines = [f"SUMMARY of {len(records)} directions after a solve's first iteration"]
    for s in STEP_FRACTIONS:
        rows = [r[s] for r, _ in records if s in r]
        within = sum(abs(actual - model) <= 0.25 * abs(model) for model, actual, *_ in rows)
        raised = sum(actual > 0.0 for _, actual, *_ in rows)
        lines.append(
            f"  s = {s:g}: within 25 % of the model {within} of {len(rows)} (admissible), "
            f"energy raised {raised}"
        )
    names = ("bulk", "pairs kept", "pairs entering")
    largest = {name: 0 for name in names}
    bulk_ratios, predicted_ratios = [], []
    for record, ratio in records:
        if 1.0 not in record:
            continue
        model, actual, *terms = record[1.0]
        if abs(actual - model) <= 0.25 * abs(model):
            predicted_ratios.append(ratio)
        if actual > 0.0:
            name = names[int(np.argmax(terms))]
            largest[name] += 1
            if name == "bulk":
                bulk_ratios.append(ratio)
    lines.append(
        "  full steps raising the energy, by the largest term: "
        + ", ".join(f"{name} {count}" for name, count in largest.items())
    )
    ratios = [round(r, 3) for r in sorted(bulk_ratios)]
    lines.append(f"  their smallest det F ratios where the bulk rises most: {ratios}")
    if predicted_ratios:
        lines.append(
            f"  the full steps the model predicts: smallest det F ratio "
            f"{min(predicted_ratios):.3g}, median {float(np.median(predicted_ratios)):.3g}"
        )
    return lines


def main() -> None:
    limit = int(os.environ.get("DIAGNOSE_ITERATIONS", 60))
    hooks: list[DirectionDiagnosis] = []

    def install(problem, demo: dict) -> None:
        hook = DirectionDiagnosis(problem, demo["cell_body"], demo["leg"].BODIES, limit)
        problem.snes.setUpdate(hook)
        hooks.append(hook)

    try:
        run_knee_with(install)
    finally:
        for line in summary([r for hook in hooks for r in hook.records]):
            print(line, flush=True)


if __name__ == "__main__":
    main()
