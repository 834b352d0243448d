"""Why the knee's full Newton steps converge slowly: every iteration taken apart.

Runs ``demos/demo_knee.py`` in this process (serially) with a SNES monitor on its
:class:`~fenics_matdepth.ContactProblem` that, after each Newton iteration ``x_k -> x_k+1``
with the step ``d = x_k - x_k+1``, measures at ``x_k`` (the state is restored afterwards):

- the contact set: the (triangle, tetrahedron) pairs whose intersection is not empty, how
  many entered and left over the step, and how many of them flip-flopped: left over the last
  step and entered again over this one, or the other way round;
- whether the step was a full Newton step: ``|F(x_k) - J d| / |F(x_k)|`` is the linear solve's
  error for a full step (about 1e-10) and ``1 - lambda`` for a step shortened to ``lambda``;
- the Jacobian against the residual: a central difference ``(F(x_k + h d) - F(x_k - h d)) / 2h``
  against ``J d`` (relative error; ``h |d|_inf = 1e-5`` mm), for the whole residual and for the
  contact gradient alone against the contact Hessian;
- the tendon's and ligament's tension-only fibres: the cells whose fibre stretch ``I4`` crossed
  1 over the step (their fibre stiffness, 4 k1 = 400 MPa against a matrix of 0.5 MPa, switched
  on or off: the energy is only once differentiable there);
- where the new residual comes from: ``F(x_k+1) = F(x_k) - J d + e`` with ``e`` the
  linearisation error of the step, split into the contact part (contact gradient at ``x_k+1``
  minus its linear model from ``x_k``) and the rest (the bulk's), and the share of
  ``|F(x_k+1)|^2`` on the vertices of the pairs that entered or left; the bulk part on the
  vertices of the fibre cells that switched.

Each iteration prints one ``diag`` line; the end prints the full steps grouped into quadratic
(residual fell at least tenfold) and slow ones, with the mean of each figure. Settings as the
demo's (``MATDEPTH_KNEE_DEGREES``, ``MATDEPTH_KNEE_STEPS``, ``MATDEPTH_KNEE_AL_TOL_H`` ...).

Run: ``MATDEPTH_KNEE_DEGREES=30 MATDEPTH_KNEE_STEPS=10 scripts/fenicsx python3
benchmarks/diagnose_knee.py``. Prints figures; asserts nothing.
"""

from __future__ import annotations

import inspect
import runpy
import typing
from pathlib import Path

from petsc4py import PETSc

import numpy as np

import fenics_matdepth as fm
from fenics_matdepth.contact.pairs import pair_vertices
from fenics_matdepth.step_control import find_contact_problem

HERE = Path(__file__).resolve().parent
DEMO = HERE.parent / "demos" / "demo_knee.py"
#: the central difference's step along d, in mm (largest dof change)
FD_STEP = 1e-5
#: a step counts as full where the linear model's residual is below this fraction of |F|
FULL_STEP_RTOL = 1e-6


class FibreCells:
    """The cells of a tension-only fibre term (``fm.materials.fiber_reinforced``): their
    squared fibre stretch ``I4 = |F a0|^2`` at a displacement (P1, serial)."""

    def __init__(self, fibre, V):
        domain = V.mesh
        W = fibre.function_space
        n_cells = domain.topology.index_map(3).size_local
        a = fibre.x.array.reshape(-1, 3)[W.dofmap.list[:n_cells, 0]]
        self.cells = np.flatnonzero(np.linalg.norm(a, axis=1) > 0.0)
        self.a = a[self.cells]
        X = domain.geometry.x[domain.geometry.dofmap[self.cells]]
        self.inverse = np.linalg.inv((X[:, 1:] - X[:, :1]).transpose(0, 2, 1))
        self.dofs = V.dofmap.list[self.cells]  # (n, 4) vertex blocks

    def stretch(self, u: np.ndarray) -> np.ndarray:
        """``I4`` of each fibre cell at the displacement ``u`` (dof array)."""
        U = u.reshape(-1, 3)[self.dofs]
        F = np.eye(3) + (U[:, 1:] - U[:, :1]).transpose(0, 2, 1) @ self.inverse
        return np.sum(np.einsum("nij,nj->ni", F, self.a) ** 2, axis=1)


class IterationDiagnosis:
    """The SNES monitor (see the module docstring); ``rows`` holds one dict per iteration."""

    def __init__(self, problem, fibres: FibreCells | None = None):
        self.problem = problem
        self.fibres = fibres
        self.assembler, self.contact = problem.assembler, problem.contact
        self.surface = self.contact.surface
        self.snes = problem.snes
        n = self.problem.u.x.petsc_vec.getLocalSize()
        self.free = np.ones(n, dtype=bool)
        for bc in self.assembler.bcs:
            dofs = bc.dof_indices()[0]
            self.free[dofs[dofs < n]] = False
        self.x_prev = None
        self.k_prev = -1
        self.solve = 0
        self.rows: list[dict] = []
        # the pairs that entered and left over the last diagnosed step of this solve
        self.last_change = (np.empty(0, np.int64), np.empty(0, np.int64))

    # -- helpers at the current state --------------------------------------------------

    def _state(self, x: PETSc.Vec) -> None:
        self.assembler.set_state(x)

    def _residual(self, x: PETSc.Vec) -> np.ndarray:
        self._state(x)
        b = x.duplicate()
        self.assembler.residual(x, b)
        out = b.getArray(readonly=True).copy()
        b.destroy()
        return out

    def _contact_gradient(self) -> np.ndarray:
        dofs, vals = self.contact.gradient_array()
        g = np.zeros(self.free.size)
        np.add.at(g, dofs, vals)
        return g

    def _contact_hessian_times(self, d: np.ndarray) -> np.ndarray:
        rows, cols, vals = self.contact.hessian_coo()
        out = np.zeros(self.free.size)
        np.add.at(out, rows, vals * d[cols])
        return out

    def _pairs(self) -> np.ndarray:
        search = self.contact.pair_search
        hit = search.intersecting(self.surface)
        n_tets = self.surface.tets.shape[0]
        return np.sort(search.pair_a[hit].astype(np.int64) * n_tets + search.pair_k[hit])

    def _pair_dofs(self, keys: np.ndarray) -> np.ndarray:
        """The owned dofs of the vertices of the pairs ``keys``."""
        n_tets = self.surface.tets.shape[0]
        held = np.unique(pair_vertices(self.surface, "area", keys // n_tets, keys % n_tets))
        vertex = self.surface.global_vertex[held]
        dofs = (3 * vertex[:, None] + np.arange(3)).ravel()
        return dofs[dofs < self.free.size]

    # -- the monitor ---------------------------------------------------------------------

    def __call__(self, snes: PETSc.SNES, k: int, fnorm: float) -> None:
        x = snes.getSolution()
        if k == 0 or k != self.k_prev + 1 or self.x_prev is None or not np.isfinite(fnorm):
            if k == 0:
                self.solve += 1
            self.last_change = (np.empty(0, np.int64), np.empty(0, np.int64))
            self._remember(x, k)
            return
        try:
            self._diagnose(x, k, fnorm)
        finally:
            self._state(x)  # the solve goes on from x_k+1
        self._remember(x, k)

    def _remember(self, x: PETSc.Vec, k: int) -> None:
        if self.x_prev is None:
            self.x_prev = x.duplicate()
        x.copy(self.x_prev)
        self.k_prev = k

    def _diagnose(self, x_new: PETSc.Vec, k: int, fnorm: float) -> None:
        free = self.free
        x0 = self.x_prev
        d_vec = x0.duplicate()
        x0.copy(d_vec)
        d_vec.axpy(-1.0, x_new)  # d = x_k - x_k+1 (SNES steps x - lambda y)
        d = d_vec.getArray(readonly=True).copy()
        # at x_k: residual, Jacobian, contact gradient and Hessian, pairs. Where x_k's
        # Dirichlet dofs are off their values (a solve's first step) the residual holds the
        # lifting of the increment left, linear in x by construction, and its central
        # difference does not measure J
        scale = max(x0.norm(PETSc.NormType.NORM_INFINITY), 1.0)
        bcs_met = self.assembler.bc_offset(x0) <= 1e-12 * scale
        F0 = self._residual(x0)
        pairs0 = self._pairs()
        g0 = self._contact_gradient()
        Hd = self._contact_hessian_times(d)
        A = self.assembler.matrix.duplicate()
        self.assembler.jacobian(A)
        Jd_vec = d_vec.duplicate()
        A.mult(d_vec, Jd_vec)
        Jd = Jd_vec.getArray(readonly=True).copy()
        A.destroy()
        Jd_vec.destroy()
        # central differences along d
        h = FD_STEP / max(np.abs(d).max(), 1e-300)
        trial = x0.duplicate()
        fd, gfd = [], []
        for sign in (1.0, -1.0):
            x0.copy(trial)
            trial.axpy(sign * h, d_vec)
            fd.append(self._residual(trial))
            gfd.append(self._contact_gradient())
        trial.destroy()
        d_vec.destroy()
        fd_total = (fd[0] - fd[1]) / (2 * h)
        fd_contact = (gfd[0] - gfd[1]) / (2 * h)
        # at x_k+1
        F1 = self._residual(x_new)
        pairs1 = self._pairs()
        g1 = self._contact_gradient()

        def norm(v):
            return float(np.linalg.norm(v[free]))

        entered = np.setdiff1d(pairs1, pairs0, assume_unique=True)
        left = np.setdiff1d(pairs0, pairs1, assume_unique=True)
        flipped = (
            np.intersect1d(entered, self.last_change[1]).size
            + np.intersect1d(left, self.last_change[0]).size
        )
        self.last_change = (entered, left)
        changed_dofs = self._pair_dofs(np.concatenate((entered, left)))
        changed = np.zeros(free.size, dtype=bool)
        changed[changed_dofs] = True
        e_total = F1 - F0 + Jd
        e_contact = g1 - g0 + Hd
        e_bulk = e_total - e_contact
        fibre_switch, e_bulk_fibre = 0, 0.0
        if self.fibres is not None:
            # tension-only fibres: I4 crossing 1 switches their stiffness (4 k1) on or off
            taut0 = self.fibres.stretch(x0.getArray(readonly=True)) > 1.0
            taut1 = self.fibres.stretch(x_new.getArray(readonly=True)) > 1.0
            switched = taut0 != taut1
            fibre_switch = int(np.count_nonzero(switched))
            at = np.zeros(free.size, dtype=bool)
            blocks = np.unique(self.fibres.dofs[switched])
            at[(3 * blocks[:, None] + np.arange(3)).ravel()] = True
            e_bulk_fibre = float(np.linalg.norm(e_bulk[free & at]))
        f0 = norm(F0)
        row = {
            "solve": self.solve,
            "k": k,
            "bcs_met": bcs_met,
            "f0": f0,
            "f1": norm(F1),
            "rate": norm(F1) / f0,
            "linear": norm(F0 - Jd) / f0,
            "active": int(pairs1.size),
            "entered": int(entered.size),
            "left": int(left.size),
            "flipped": int(flipped),
            "fd_error": norm(fd_total - Jd) / max(norm(Jd), 1e-300),
            "fd_contact_error": norm(fd_contact - Hd) / max(norm(Hd), 1e-300),
            "e_contact": norm(e_contact) / f0,
            "e_bulk": norm(e_bulk) / f0,
            "share_changed": float(np.sum(F1[free & changed] ** 2) / max(norm(F1) ** 2, 1e-300)),
            "e_contact_changed": norm(np.where(changed, e_contact, 0.0)) / f0,
            "fibre_switch": fibre_switch,
            "e_bulk_fibre": e_bulk_fibre / f0,
        }
        row["full"] = row["linear"] < FULL_STEP_RTOL
        self.rows.append(row)
        step = "full" if row["full"] else f"lambda {1 - row['linear']:.3f}"
        step += "" if bcs_met else ", Dirichlet increment"
        print(
            f"diag solve {row['solve']} it {k:3d} |F| {f0:.3e} -> {row['f1']:.3e} "
            f"(rate {row['rate']:.3f}, {step}) "
            f"pairs {row['active']} +{row['entered']} -{row['left']} ({flipped} back) | "
            f"FD/J d {row['fd_error']:.1e}"
            f" (contact {row['fd_contact_error']:.1e}) | lin. error / |F_k|: contact "
            f"{row['e_contact']:.3f} (on changed pairs {row['e_contact_changed']:.3f}), bulk "
            f"{row['e_bulk']:.3f} (round fibre cells switched {row['e_bulk_fibre']:.3f}, "
            f"{fibre_switch} switched) | |F_k+1|^2 on changed pairs {row['share_changed']:.2f}",
            flush=True,
        )


def summarise(rows: list[dict]) -> None:
    rows = [r for r in rows if r["bcs_met"]]  # see IterationDiagnosis._diagnose
    full = [r for r in rows if r["full"]]
    groups = {
        "quadratic (rate <= 0.1)": [r for r in full if r["rate"] <= 0.1],
        "slow (rate > 0.1)": [r for r in full if r["rate"] > 0.1],
        "shortened steps": [r for r in rows if not r["full"]],
    }
    print(f"\ndiagnosis of {len(rows)} Newton iterations from a state on its Dirichlet values "
          f"({len(full)} full steps)")  # fmt: skip
    keys = ("rate", "entered", "left", "flipped", "fd_error", "fd_contact_error", "e_contact",
            "e_contact_changed", "e_bulk", "e_bulk_fibre", "fibre_switch",
            "share_changed")  # fmt: skip
    print("  means over each group:")
    for name, group in groups.items():
        if not group:
            continue
        means = ", ".join(f"{k} {np.mean([r[k] for r in group]):.3g}" for k in keys)
        print(f"  {name} ({len(group)}): {means}")
    if full:
        no_change = [r for r in full if r["entered"] + r["left"] == 0]
        print(f"  full steps with no pair entering or leaving: {len(no_change)}, of which slow: "
              f"{sum(r['rate'] > 0.1 for r in no_change)}")  # fmt: skip
        print(f"  largest FD error of J d: {max(r['fd_error'] for r in rows):.2e}; of the "
              f"contact Hessian: {max(r['fd_contact_error'] for r in rows):.2e}")  # fmt: skip


def run_knee_with(install: typing.Callable[[typing.Any, dict], typing.Any]) -> None:
    """Run ``demos/demo_knee.py`` in this process, calling ``install(problem, demo)`` with its
    :class:`~fenics_matdepth.ContactProblem` and the demo's namespace before its load steps
    (to set SNES hooks). Where ``install`` returns a callable, that is given the demo's writer
    of each converged step and returns the writer the load steps call instead."""
    solve_load_steps = fm.solve_load_steps

    def diagnosed(solver, *args, **kwargs):
        demo = inspect.currentframe().f_back.f_globals  # the demo's namespace
        wrap = install(find_contact_problem(solver), demo)
        if wrap is not None:
            kwargs["writer"] = wrap(kwargs.get("writer"))
        return solve_load_steps(solver, *args, **kwargs)

    fm.solve_load_steps = diagnosed
    try:
        runpy.run_path(str(DEMO), run_name="__main__")
    finally:
        fm.solve_load_steps = solve_load_steps


def main() -> None:
    diagnoses: list[IterationDiagnosis] = []

    def install(problem, demo: dict) -> None:
        fibres = FibreCells(demo["fibre"], demo["V"]) if "fibre" in demo else None
        diagnosis = IterationDiagnosis(problem, fibres)
        problem.snes.setMonitor(diagnosis)
        diagnoses.append(diagnosis)

    try:
        run_knee_with(install)
    finally:
        for diagnosis in diagnoses:
            summarise(diagnosis.rows)


if __name__ == "__main__":
    main()
