"""The knee demo with Newton variants that were measured and not kept (docs/measurements.md,
"Hessians made definite, other penalties and bulk moduli, the trust region").

- ``--hessian definite``: each tetrahedron's Hessian of the bulk energy made positive
  semi-definite (its negative eigenvalues replaced by their absolute values, the projected
  Newton of soft-body solvers) in every Jacobian; ``definite-after-slow`` only after an
  iteration whose residual fell less than half; ``definite-once`` the same, never in two
  iterations in a row. ``exact`` (the default): the demo's Jacobian.
- ``--snes newtontr``: PETSc's trust-region Newton (dogleg) instead of the line search.
- ``--escape-saddles``: after each converged step whose Jacobian has a negative eigenvalue
  (:func:`fenics_matdepth.linear_solver.inertia`; ``diagnose_stability.py`` lists them), the
  state is a saddle of the energy: it is moved along the eigenvector of the lowest eigenvalue
  (SLEPc, shift-and-invert at a shift found by the inertia of shifted matrices), by
  ``ESCAPE_TRAVEL`` median boundary edges at the vertex that moves most, to the side of lower
  energy, and solved again at the same load; the step keeps the new state if that solve
  converges (one ``ESCAPE`` line each).
- The local relaxation (``--relax patch`` here until it moved into the library) is
  ``fm.LocalRelaxation``: the demo's ``MATDEPTH_KNEE_RELAX=1`` (``bench_knee.py --env``).

Serial only. The demo's output goes to stdout with ``bench_knee.py``'s monitors on; its
figures come from ``bench_knee.py --from-log``::

    python3 benchmarks/knee_variants.py --hessian definite-once --output OUT > OUT.log
    python3 benchmarks/bench_knee.py --degrees 150 --steps 50 --from-log OUT.log --output OUT

The other variants of that section are the demo's own settings (``MATDEPTH_KNEE_PENALTY``,
``MATDEPTH_KNEE_BULK_RATIO``: ``bench_knee.py --env``).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

# PETSc reads PETSC_OPTIONS when petsc4py starts: the monitors go in before any import of it
if __name__ == "__main__":
    from bench_knee import MONITORS

    os.environ["PETSC_OPTIONS"] = (os.environ.get("PETSC_OPTIONS", "") + " " + MONITORS).strip()

from petsc4py import PETSc

import dolfinx
import scipy.sparse
import ufl

from fenics_matdepth.contact.assembly import global_dirichlet_dofs
from fenics_matdepth.linear_solver import inertia

HESSIANS = ("exact", "definite", "definite-after-slow", "definite-once")
#: an eigenvalue counts as negative below this fraction of the element matrix's largest
#: (the rigid motions' zero eigenvalues round to either sign)
NEGATIVE_TOL = 1e-9
#: ``definite-after-slow``: an iteration is slow when its residual norm fell less than this
SLOW_RATE = 0.5
#: ``--escape-saddles``: the longest vertex move along the unstable mode, in median boundary
#: edges
ESCAPE_TRAVEL = 0.25
#: ``--escape-saddles``: eigenpairs computed nearest the shift below the lowest eigenvalue
ESCAPE_PAIRS = 2


def element_matrices(energy: ufl.Form, u: dolfinx.fem.Function) -> tuple:
    """A compiled form whose matrix holds each cell's Hessian of ``energy`` as a block of its
    own (the second derivative taken along a discontinuous space of ``u``'s degree), and the
    cells' scalar dofs in that space, ``(n_cells, n)`` (owned cells)."""
    V = u.function_space
    mesh = V.mesh
    degree = V.ufl_element().embedded_superdegree
    broken = dolfinx.fem.functionspace(mesh, ("DG", degree, (mesh.geometry.dim,)))
    form = ufl.derivative(
        ufl.derivative(energy, u, ufl.TestFunction(broken)), u, ufl.TrialFunction(broken)
    )
    n_cells = mesh.topology.index_map(mesh.topology.dim).size_local
    return dolfinx.fem.form(form), scalar_dofs(broken, n_cells)


def scalar_dofs(V: dolfinx.fem.FunctionSpace, n_cells: int) -> np.ndarray:
    """Each cell's scalar (unrolled) dofs of the blocked space ``V``, ``(n_cells, n)``."""
    bs = V.dofmap.index_map_bs
    blocks = V.dofmap.list[:n_cells]
    return (bs * blocks[:, :, None] + np.arange(bs)).reshape(n_cells, -1)


def dirichlet_mask(V: dolfinx.fem.FunctionSpace, bcs: list) -> np.ndarray:
    """Which scalar dofs of ``V`` the conditions ``bcs`` hold (serial: global = local)."""
    fixed = np.zeros(V.dofmap.index_map.size_local * V.dofmap.index_map_bs, dtype=bool)
    fixed[global_dirichlet_dofs(V.mesh.comm, V, bcs)] = True
    return fixed


def definite_correction(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``|K| - K`` for each symmetric matrix of the stack ``K`` with a negative eigenvalue
    (twice the negative eigenvalues' part, its sign turned), and which of ``K`` they are."""
    w, v = np.linalg.eigh(0.5 * (K + K.transpose(0, 2, 1)))
    lift = np.where(w < -NEGATIVE_TOL * np.abs(w).max(axis=1, keepdims=True), -2.0 * w, 0.0)
    negative = np.flatnonzero((lift > 0).any(axis=1))
    v = v[negative]
    return np.einsum("cij,cj,ckj->cik", v, lift[negative], v), negative


def cell_entries(matrix: dolfinx.la.MatrixCSR, broken_dofs: np.ndarray) -> np.ndarray:
    """Where each cell's matrix lies in ``matrix.data`` (a form of :func:`element_matrices`):
    ``matrix.data[entries]`` is the ``(n_cells, n, n)`` stack. Found once by filling the
    matrix with its entries' positions and taking the blocks of the matrix with each cell's
    dofs made consecutive (block diagonal, a block per cell)."""
    n_cells, n = broken_dofs.shape
    order = broken_dofs.ravel()
    matrix.data[:] = np.arange(1, matrix.data.size + 1)  # 1-based: no position reads as 0
    blocked = matrix.to_scipy().tocsr()[order][:, order]
    cells = scipy.sparse.bsr_matrix(blocked, blocksize=(n, n))
    cells.sort_indices()
    assert np.array_equal(cells.indices, np.arange(n_cells))
    return cells.data.astype(np.int64) - 1


class DefiniteHessians:
    """The part that makes every cell's Hessian of ``energy`` positive semi-definite, rows and
    columns of Dirichlet dofs left out; :meth:`install` adds it to a ContactProblem's bulk
    Jacobian where :attr:`active`. Serial.

    Args:
        u: the displacement.
        bcs: the Dirichlet conditions.
        energy: the bulk energy form of ``u``.
    """

    def __init__(self, u: dolfinx.fem.Function, bcs: list, energy: ufl.Form):
        V = u.function_space
        if V.mesh.comm.size > 1:
            raise NotImplementedError("DefiniteHessians runs serially only")
        self.form, broken_dofs = element_matrices(energy, u)
        self.matrix = dolfinx.fem.create_matrix(self.form)
        self.dofs = scalar_dofs(V, broken_dofs.shape[0])
        self.size = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self.free = ~dirichlet_mask(V, bcs)[self.dofs]  # (n_cells, n)
        self._entries = cell_entries(self.matrix, broken_dofs)
        #: whether the next Jacobians are corrected
        self.active = True
        #: Jacobians corrected, seconds spent, cells with a negative eigenvalue per Jacobian
        self.corrected = 0
        self.seconds = 0.0
        self.negative_cells: list[int] = []

    def install(self, problem) -> None:
        """Add the correction to ``problem``'s bulk Jacobian (a
        :class:`fenics_matdepth.ContactProblem` whose bulk Jacobian is the Hessian of the
        energy) whenever :attr:`active`."""
        bulk = problem.assembler.bulk
        add_exact = bulk.add_to

        def add_to(A: PETSc.Mat) -> None:
            add_exact(A)
            if self.active:
                self.add_to(A)

        bulk.add_to = add_to

    def cell_matrices(self) -> np.ndarray:
        """Each cell's Hessian of the energy at the current state, ``(n_cells, n, n)``."""
        self.matrix.set_value(0.0)
        dolfinx.fem.assemble_matrix(self.matrix, self.form)
        return self.matrix.data[self._entries]

    def correction(self) -> scipy.sparse.csr_matrix:
        """The correction at the current state, on the problem's dofs."""
        C, negative = definite_correction(self.cell_matrices())
        self.negative_cells.append(negative.size)
        dofs, free = self.dofs[negative], self.free[negative]
        keep = free[:, :, None] & free[:, None, :]
        rows = np.broadcast_to(dofs[:, :, None], C.shape)[keep]
        cols = np.broadcast_to(dofs[:, None, :], C.shape)[keep]
        return scipy.sparse.coo_matrix(
            (C[keep], (rows, cols)), shape=(self.size, self.size)
        ).tocsr()

    def add_to(self, A: PETSc.Mat) -> None:
        """Add the correction at the current state to ``A`` (not assembled here)."""
        tic = time.perf_counter()
        C = self.correction()
        C.sort_indices()
        A.setValuesCSR(
            C.indptr.astype(PETSc.IntType),
            C.indices.astype(PETSc.IntType),
            C.data,
            addv=PETSc.InsertMode.ADD_VALUES,
        )
        self.corrected += 1
        self.seconds += time.perf_counter() - tic

    def follow(self, snes: PETSc.SNES, once: bool) -> None:
        """Correct only the Jacobian after an iteration whose residual fell less than
        SLOW_RATE, and (``once``) never two in a row; chained before the problem's own
        update callback."""
        then, args, kwargs = snes.getUpdate()
        last = np.inf  # the last iteration's residual norm (each solve starts at iteration 0)

        def update(s: PETSc.SNES, iteration: int) -> None:
            nonlocal last
            norm = s.getFunctionNorm()
            slow = iteration > 0 and norm > SLOW_RATE * last
            self.active = slow and not (once and self.active)
            last = norm
            then(s, iteration, *args, **kwargs)

        snes.setUpdate(update)


def lowest_eigenvalue_bracket(A: PETSc.Mat) -> float:
    """A shift ``sigma`` just below the lowest eigenvalue of the symmetric ``A``, which has a
    negative one: no eigenvalue below ``sigma``, one or more below ``0.9 sigma`` (the inertia
    of ``A - sigma I``, by halving the exponent and then the interval)."""

    def below(sigma: float) -> int:
        B = A.copy()
        B.shift(-sigma)
        count = inertia(B)[0]
        B.destroy()
        return count

    high = -1e-6  # an eigenvalue below it
    while below(10.0 * high) > 0:
        high *= 10.0
    low = 10.0 * high  # none below it
    while high / low < 0.9:
        middle = -np.sqrt(low * high)
        if below(middle) > 0:
            high = middle
        else:
            low = middle
    return low


def unstable_mode(A: PETSc.Mat) -> tuple[float, PETSc.Vec]:
    """The lowest eigenpair of the symmetric ``A``, which has a negative eigenvalue (SLEPc,
    shift-and-invert with MUMPS at a shift just below it)."""
    from slepc4py import SLEPc

    eps = SLEPc.EPS().create(A.getComm())
    eps.setOperators(A)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setDimensions(ESCAPE_PAIRS)
    eps.setTarget(lowest_eigenvalue_bracket(A))
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    st = eps.getST()
    st.setType(SLEPc.ST.Type.SINVERT)
    ksp = st.getKSP()
    ksp.setType("preonly")
    ksp.getPC().setType("cholesky")
    ksp.getPC().setFactorSolverType("mumps")
    eps.solve()
    values = [eps.getEigenvalue(i).real for i in range(eps.getConverged())]
    i = int(np.argmin(values))
    vector = A.createVecRight()
    eps.getEigenvector(i, vector)
    eps.destroy()
    return values[i], vector


class SaddleEscape:
    """``--escape-saddles`` (see the module docstring) around the demo's solver's ``solve``."""

    def __init__(self, solver, problem, travel: float):
        self.problem, self.travel = problem, travel
        self.solve_once = solver.solve
        self.saddles = self.escaped = self.iterations = 0

    def solve(self, *args, **kwargs):
        result = self.solve_once(*args, **kwargs)
        if result.converged:
            self.escape()
        return result

    def escape(self) -> None:
        from diagnose_stability import jacobian_at

        snes, u = self.problem.snes, self.problem.u
        x = u.x.petsc_vec.copy()
        A = jacobian_at(self.problem)
        negative, _ = inertia(A)
        if negative == 0:
            A.destroy()
            return
        self.saddles += 1
        value, v = unstable_mode(A)
        A.destroy()
        longest = np.max(np.linalg.norm(v.getArray().reshape(-1, 3), axis=1))
        v.scale(self.travel / longest)
        energies = {}
        for sign in (1.0, -1.0):
            trial = x.copy()
            trial.axpy(sign, v)
            energies[sign] = snes.computeObjective(trial)
            trial.destroy()
        base = snes.computeObjective(x)
        sign = min(energies, key=lambda k: energies[k] if np.isfinite(energies[k]) else np.inf)
        state = u.x.array.copy()
        u.x.array[:] += sign * v.getArray()
        u.x.scatter_forward()
        result = self.solve_once(raise_on_failure=False)
        self.iterations += result.iterations
        after = None
        if result.converged:
            self.escaped += 1
            A = jacobian_at(self.problem)
            after = inertia(A)[0]
            A.destroy()
        else:  # back to the saddle
            u.x.array[:] = state
            u.x.scatter_forward()
        print(
            f"ESCAPE {negative} negative (lowest {value:.3e}); energy {base:.6e}, "
            f"moved {energies[sign] - base:+.3e}; solved again: {result.iterations} it, "
            f"{'converged' if result.converged else 'failed'}, negative after: {after}",
            flush=True,
        )
        x.destroy()
        v.destroy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--hessian", choices=HESSIANS, default="exact")
    parser.add_argument("--snes", choices=("newtonls", "newtontr"), default="newtonls")
    parser.add_argument("--escape-saddles", action="store_true")
    parser.add_argument("--degrees", type=float, default=150.0)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--output", required=True, help="the demo's output folder")
    args = parser.parse_args()
    os.environ.update(
        MATDEPTH_KNEE_DEGREES=str(args.degrees),
        MATDEPTH_KNEE_STEPS=str(args.steps),
        MATDEPTH_DEMO_OUTPUT=os.path.abspath(args.output),
    )
    from diagnose_knee import run_knee_with

    installed: list[DefiniteHessians] = []
    escapes: list[SaddleEscape] = []

    def install(problem, demo: dict) -> None:
        if args.snes == "newtontr":
            options = PETSc.Options()
            options[problem.prefix + "snes_type"] = "newtontr"
            options[problem.prefix + "snes_tr_fallback_type"] = "dogleg"
            problem.snes.setFromOptions()
        if args.hessian != "exact":
            definite = DefiniteHessians(problem.u, problem.bcs, demo["energy"])
            definite.install(problem)
            if args.hessian != "definite":
                definite.follow(problem.snes, once=args.hessian == "definite-once")
            installed.append(definite)
        if args.escape_saddles:
            solver = demo["solver"]  # the augmented Lagrangian (or the problem)
            escape = SaddleEscape(solver, problem, ESCAPE_TRAVEL * demo["h_boundary"])
            solver.solve = escape.solve
            escapes.append(escape)

    try:
        run_knee_with(install)
    finally:
        for definite in installed:
            counts = definite.negative_cells or [0]
            print(
                f"Hessians made definite ({args.hessian}): {definite.corrected} Jacobians in "
                f"{definite.seconds:.1f} s; cells with a negative eigenvalue: median "
                f"{np.median(counts):.0f}, most {max(counts)} of {len(definite.dofs)}"
            )
        for escape in escapes:
            print(
                f"saddles: {escape.saddles} converged steps, {escape.escaped} left to a "
                f"converged state in {escape.iterations} Newton iterations"
            )


if __name__ == "__main__":
    main()
