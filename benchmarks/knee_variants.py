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
- ``--relax``: nonlinear elimination of a concentrated residual. Before each Newton step after
  a solve's first, where at most ``RELAX_VERTICES`` vertices hold ``RELAX_SHARE`` of
  ``|F|^2``, the equilibrium of those vertices and their neighbours (the cells round them) is
  solved with every other vertex held, by up to ``RELAX_ITERATIONS`` Newton iterations on
  that patch (its block of the Jacobian, dense, and a backtracking search on the energy); the
  global step goes on from the relaxed state (:class:`LocalRelaxation`, one ``RELAX`` line per
  use). ``--relax`` (``whole``): each local iteration assembles the whole residual, Jacobian
  and energy. ``--relax patch``: over the patch alone, the bulk over the cells touching its
  vertices and the contact over the candidate pairs holding one of them
  (``patch_assembly.py``); then the whole residual once, at the relaxed state.
  ``--relax-iterations``, ``--relax-vertices``, ``--relax-share``: ``RELAX_ITERATIONS``,
  ``RELAX_VERTICES`` and ``RELAX_SHARE`` instead of the defaults. ``--relax-det-floor f``
  (``patch``): a local trial state whose lowest det F on the patch is at most f times the
  patch's lowest at its start is refused (0, the default: only inverted cells).

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
import traceback

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
#: ``--relax``: the residual counts as concentrated where at most RELAX_VERTICES vertices hold
#: RELAX_SHARE of its square
RELAX_SHARE = 0.8
RELAX_VERTICES = 12
#: ``--relax``: Newton iterations of one patch's solve (it stops sooner once the patch's
#: residual fell below RELAX_RTOL of its start)
RELAX_ITERATIONS = 6
RELAX_RTOL = 0.05
#: ``--relax``: no relaxation once the residual norm is below this (force)
RELAX_MIN_NORM = 0.1


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


class WholeSystem:
    """A patch's energy, gradient and Hessian from the whole problem's (each evaluation
    assembles everything; the energy is the whole energy): the gradient is the residual's rows
    at the patch's dofs, and the residual is left in ``F``."""

    def __init__(self, relaxation: LocalRelaxation, dofs: np.ndarray, F: PETSc.Vec):
        self.relaxation, self.dofs, self.F = relaxation, dofs, F
        self.rows = PETSc.IS().createGeneral(dofs, comm=PETSc.COMM_SELF)

    def energy(self, x: PETSc.Vec) -> float:
        return self.relaxation.energy(x)

    def gradient(self, x: PETSc.Vec) -> np.ndarray:
        self.relaxation.residual(x, self.F)
        return self.F.getValues(self.dofs)

    def hessian(self, x: PETSc.Vec) -> np.ndarray:
        block = self.relaxation.jacobian(x).createSubMatrix(self.rows, self.rows)
        K = block.convert("dense").getDenseArray().copy()
        block.destroy()
        return K

    def destroy(self) -> None:
        self.rows.destroy()


class LocalRelaxation:
    """``--relax`` (see the module docstring): the equilibrium of the vertices holding most of
    the residual, and of their neighbours, with every other vertex held. Serial.

    Args:
        residual: ``residual(x, b)`` writes ``F(x)`` into ``b``.
        jacobian: ``jacobian(x)``, the Jacobian at ``x`` (a PETSc matrix; rows and columns of
            held dofs are not read).
        energy: ``energy(x)``, the energy at ``x`` (``inf`` where inadmissible).
        cells: each cell's vertices, ``(n_cells, 4)``; dof ``3 v + i`` is vertex v's i-th.
        fixed: which dofs are held (Dirichlet), a boolean array.
        restricted: ``restricted(dofs)``, the patch's model assembled over the patch alone
            (``patch_assembly.PatchAssembly.model``: ``energy``, ``gradient`` and ``hessian``
            at a state, ``destroy``), or None: the whole problem's (:class:`WholeSystem`).
    """

    def __init__(self, residual, jacobian, energy, cells: np.ndarray, fixed: np.ndarray,
                 share: float = RELAX_SHARE, vertices: int = RELAX_VERTICES,
                 iterations: int = RELAX_ITERATIONS, restricted=None):  # fmt: skip
        self.residual, self.jacobian, self.energy = residual, jacobian, energy
        self.restricted = restricted
        self.cells, self.fixed = cells, fixed
        self.share, self.vertices, self.iterations = share, vertices, iterations
        self.uses = self.local_iterations = 0
        self.seconds = 0.0  # in relax (the relaxed state's whole residual included)

    def patch(self, F: PETSc.Vec) -> np.ndarray | None:
        """The free dofs of the patch round the vertices holding ``share`` of ``|F|^2``, or
        None where more than ``vertices`` vertices are needed for it."""
        r2 = (F.getArray(readonly=True).reshape(-1, 3) ** 2).sum(axis=1)
        order = np.argsort(r2)[::-1]
        needed = int(np.searchsorted(np.cumsum(r2[order]), self.share * r2.sum())) + 1
        if needed > self.vertices:
            return None
        around = np.unique(self.cells[np.isin(self.cells, order[:needed]).any(axis=1)])
        dofs = (3 * around[:, None] + np.arange(3)).ravel()
        return dofs[~self.fixed[dofs]].astype(PETSc.IntType)

    def relax(self, x: PETSc.Vec, F: PETSc.Vec) -> tuple | None:
        """Relax ``x`` in place from its residual ``F``, which then holds the relaxed
        iterate's; returns (the patch's dofs, iterations, the patch's residual norm before and
        after), or None (nothing changed) where the residual is not concentrated."""
        dofs = self.patch(F)
        if dofs is None or dofs.size == 0:
            return None
        tic = time.perf_counter()
        whole = self.restricted is None
        model = WholeSystem(self, dofs, F) if whole else self.restricted(dofs)
        trial = x.duplicate()
        energy = model.energy(x)
        # the whole problem's gradient at x is F's rows; a restricted one is the energy's alone
        # (without the lifting of Dirichlet values not yet reached)
        f = F.getValues(dofs) if whole else model.gradient(x)
        start = np.linalg.norm(f)
        iterations, current = 0, True  # current: f is the gradient at x
        try:
            for iterations in range(1, self.iterations + 1):
                if not current:
                    f = model.gradient(x)
                    current = True
                if np.linalg.norm(f) < RELAX_RTOL * start:
                    iterations -= 1
                    break
                K = model.hessian(x)
                step = np.linalg.lstsq(K, f, rcond=None)[0]
                slope = -f @ step
                if not slope < 0.0:  # the patch's Newton step climbs: a gradient step instead
                    step = f / np.abs(np.diag(K)).max()
                    slope = -f @ step
                moved = False
                for length in 0.5 ** np.arange(8):
                    x.copy(trial)
                    trial.setValues(dofs, x.getValues(dofs) - length * step)
                    trial.assemble()
                    value = model.energy(trial)
                    if value <= energy + 1e-4 * length * slope:
                        moved = True
                        break
                if not moved:
                    break
                trial.copy(x)
                energy, current = value, False
            if not (whole and current):  # WholeSystem.gradient leaves the residual in F
                self.residual(x, F)
            norm = np.linalg.norm(F.getValues(dofs))
        finally:
            trial.destroy()
            model.destroy()
        self.uses += 1
        self.local_iterations += iterations
        self.seconds += time.perf_counter() - tic
        return dofs, iterations, start, norm

    def install(self, problem) -> None:
        """Relax before each Newton step of ``problem`` (a ContactProblem) after a solve's
        first, chained before the problem's own update callback; the SNES's residual (updated by
        :meth:`relax`) and its norm are then those of the relaxed iterate."""
        snes = problem.snes
        then, args, kwargs = snes.getUpdate()

        def update(s: PETSc.SNES, iteration: int) -> None:
            F = s.getFunction()[0]
            norm = s.getFunctionNorm()
            if iteration > 0 and np.isfinite(norm) and norm > RELAX_MIN_NORM:
                x = s.getSolution()
                try:
                    done = self.relax(x, F)
                except Exception:
                    # the SNES turns it into a failed solve, which the load steps cut silently
                    traceback.print_exc()
                    raise
                if done is not None:
                    # the problem's residual and energy kept for the last trial state are stale
                    problem._trial_valid, problem._energy_value = False, np.nan
                    s.setFunctionNorm(F.norm())
                    dofs, iterations, before, after = done
                    print(
                        f"RELAX {dofs.size} dofs, {iterations} it, patch |F| {before:.3g} -> "
                        f"{after:.3g}, |F| {norm:.3g} -> {s.getFunctionNorm():.3g}",
                        flush=True,
                    )
            then(s, iteration, *args, **kwargs)

        snes.setUpdate(update)


def relaxation_of(
    problem, cells: np.ndarray, energy: ufl.Form | None = None, det_floor: float = 0.0
) -> LocalRelaxation:
    """``--relax``'s :class:`LocalRelaxation` on a ContactProblem's assembler; given the bulk
    ``energy`` (UFL), each patch is assembled over itself (``--relax patch``:
    :class:`patch_assembly.PatchAssembly`, its ``det_floor``), the dofs it holds held on
    every patch."""
    assembler = problem.assembler

    def residual(x, b):
        assembler.set_state(x)
        assembler.residual(x, b)

    def jacobian(x):
        assembler.set_state(x)
        assembler.rebuild_matrix_if_needed(
            lambda A: problem.snes.setJacobian(problem._jacobian, A, A)
        )
        assembler.jacobian(assembler.matrix)
        return assembler.matrix

    def value(x):
        assembler.set_state(x)
        return assembler.total_energy() if assembler.min_det_F() > 0.0 else np.inf

    fixed = dirichlet_mask(problem.u.function_space, assembler.bcs)
    restricted = None
    if energy is not None:
        from patch_assembly import PatchAssembly

        patches = PatchAssembly(energy, problem.u, assembler.contact)
        patches.det_floor = det_floor
        fixed[patches.held] = True
        restricted = patches.model
    return LocalRelaxation(residual, jacobian, value, cells, fixed, restricted=restricted)


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
    parser.add_argument("--relax", nargs="?", const="whole", choices=("whole", "patch"))
    parser.add_argument("--relax-iterations", type=int, default=RELAX_ITERATIONS)
    parser.add_argument("--relax-vertices", type=int, default=RELAX_VERTICES)
    parser.add_argument("--relax-share", type=float, default=RELAX_SHARE)
    parser.add_argument("--relax-det-floor", type=float, default=0.0)
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
    relaxations: list[LocalRelaxation] = []

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
        if args.relax:
            cells = np.asarray(problem.u.function_space.dofmap.list).reshape(-1, 4)
            energy = demo["energy"] if args.relax == "patch" else None
            relaxation = relaxation_of(problem, cells, energy, args.relax_det_floor)
            relaxation.iterations = args.relax_iterations
            relaxation.vertices, relaxation.share = args.relax_vertices, args.relax_share

            relaxation.install(problem)
            relaxations.append(relaxation)

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
        for relaxation in relaxations:
            print(
                f"local relaxation: {relaxation.uses} patches relaxed in "
                f"{relaxation.local_iterations} local Newton iterations, {relaxation.seconds:.1f} s"
            )


if __name__ == "__main__":
    main()
