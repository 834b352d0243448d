"""Local relaxation of a concentrated residual (nonlinear elimination) before a Newton step.

Late in a hard load step (the knee past 100 deg) the residual sits on a few vertices: two
vertices held more than half of ``|F|^2`` in most iterations measured, and the Newton step
answers their force by moving a soft region elsewhere, which the line search cuts to a tenth.
Each iteration then removes about a tenth of the residual (docs/measurements.md, "Where the late
steps creep").

:class:`LocalRelaxation` solves, before each Newton step after a solve's first, the equilibrium
of those vertices and of their neighbours with every other vertex held: where at most
``vertices`` vertices hold ``share`` of ``|F|^2``, the patch is those vertices and every vertex
of the cells round them (the Dirichlet dofs, and the vertices of exterior-facet integrals, left
out), and up to ``iterations`` Newton iterations on the patch's block (dense: tens to hundreds
of dofs), each with a backtracking search on the patch's energy, move it until its residual is
below ``rtol`` of its start. The global Newton step goes on from the relaxed state, whose
residual (assembled once, over the whole problem) SNES then holds. The patch is assembled over
itself alone (:mod:`fenics_matdepth.patches`): its cells and the contact pairs that hold one of
its vertices, about a millisecond to 20 ms an evaluation on the knee against 0.2 s for the
whole leg.

Opt-in, serially and on a distributed mesh (every process takes the same local steps, see
:mod:`fenics_matdepth.patches`); the knee demo sets it: 613 to 706 Newton iterations to 150 deg
on three paths against 884 to 1,136 without (docs/measurements.md).

Set it on a problem: ``problem.relaxation = fm.LocalRelaxation(energy)``, ``energy`` the bulk
energy whose derivative is the problem's residual form.
"""

from __future__ import annotations

import dataclasses
import time

from petsc4py import PETSc

import numpy as np
import ufl

from fenics_matdepth._mpi import summed
from fenics_matdepth.contact.assembly import global_dirichlet_dofs
from fenics_matdepth.patches import PatchAssembly

__all__ = ["LocalRelaxation"]

#: a patch's step is cut in half at most this many times before the local solve stops
BACKTRACKS = 8
#: the backtracking's sufficient decrease (Armijo) constant
ARMIJO = 1e-4
#: no relaxation once the residual norm is below this many times the problem's ``snes_atol``
MIN_NORM_ATOL = 10.0


@dataclasses.dataclass
class LocalRelaxation:
    """The equilibrium of the vertices holding most of the residual, and of their neighbours,
    with every other vertex held, before each Newton step of a
    :class:`~fenics_matdepth.ContactProblem` (see the module).

    Args:
        energy: the bulk energy (UFL) of the problem's ``u``: the problem's residual form is
            its derivative. Cell integrals (over cell tags or everywhere) and exterior-facet
            integrals (their vertices are held).
        share: the residual counts as concentrated where at most ``vertices`` vertices hold this
            fraction of ``|F|^2``.
        vertices: see ``share``.
        iterations: Newton iterations of one patch's solve at most.
        rtol: a patch's solve stops once its residual fell below this fraction of its start.
        det_floor: a patch's trial state whose lowest det F is at most this fraction of the
            patch's lowest at its start is refused (0: only inverted cells): a patch is moved
            towards the minimum of its own energy with the rest held, and without a floor it
            may crush a cell the global problem would not (measured on the knee).
        min_norm: no relaxation once the residual norm is below this (a force); None: ten
            times the ``snes_atol`` of the problem it is bound to.

    Attributes:
        uses: patches relaxed since the problem was given this relaxation.
        local_iterations: their Newton iterations.
        seconds: wall time spent relaxing (the relaxed state's whole residual included).
    """

    energy: ufl.Form = dataclasses.field(repr=False)
    share: float = 0.6
    vertices: int = 24
    iterations: int = 6
    rtol: float = 0.05
    det_floor: float = 0.5
    min_norm: float | None = None
    uses: int = dataclasses.field(default=0, init=False)
    local_iterations: int = dataclasses.field(default=0, init=False)
    seconds: float = dataclasses.field(default=0.0, init=False)

    def __post_init__(self):
        if not 0.0 < self.share <= 1.0:
            raise ValueError(f"share is a fraction in (0, 1], got {self.share!r}")
        if self.vertices < 1 or self.iterations < 1:
            raise ValueError(
                f"vertices and iterations are positive integers, got {self.vertices!r} and "
                f"{self.iterations!r}"
            )
        if not (0.0 < self.rtol < 1.0 and 0.0 <= self.det_floor < 1.0):
            raise ValueError(
                f"rtol is in (0, 1) and det_floor in [0, 1), got {self.rtol!r} and "
                f"{self.det_floor!r}"
            )
        self._patches: PatchAssembly | None = None

    def bind(self, problem) -> None:
        """Prepare for ``problem`` (a ContactProblem on ``energy``'s ``u``): compile the
        energy's forms for the patches. The problem's ``relaxation`` setter calls this.

        Raises:
            NotImplementedError: with friction, or for an energy with other integrals than
                cell and exterior-facet ones.
        """
        contact = problem.assembler.contact
        if getattr(contact, "friction", None) is not None:
            raise NotImplementedError(
                "a patch leaves friction out, and this contact operator has friction: leave "
                "the local relaxation off for it"
            )
        patches = PatchAssembly(self.energy, problem.u, contact)
        patches.det_floor = self.det_floor
        V = problem.u.function_space
        #: the global dofs never in a patch (Dirichlet, exterior-facet integrals), sorted
        self._fixed = np.union1d(global_dirichlet_dofs(V.mesh.comm, V, problem.bcs), patches.held)
        self._patches, self._assembler = patches, problem.assembler
        self._floor = self.min_norm
        if self._floor is None:  # the bound problem's own tolerance, on every bind
            self._floor = MIN_NORM_ATOL * problem.snes.getTolerances()[1]

    def wanted(self, norm: float) -> bool:
        """Whether a residual of norm ``norm`` is worth relaxing (finite, over ``min_norm``)."""
        return bool(np.isfinite(norm) and norm > self._floor)

    def patch(self, F: PETSc.Vec) -> np.ndarray | None:
        """The free global dofs (sorted) of the patch round the vertices holding ``share`` of
        ``|F|^2``, or None where more than ``vertices`` vertices are needed for it; the same on
        every process (collective)."""
        patches = self._patches
        comm = patches.comm
        r2 = (F.getArray(readonly=True).reshape(-1, 3) ** 2).sum(axis=1)  # the owned vertices
        total = summed(comm, [r2.sum()])[0]
        top = np.argsort(r2)[::-1][: self.vertices]  # a process's, enough for the whole
        heavy, vertex = r2[top], patches.global_vertex[top]
        if comm.size > 1:
            heavy = np.concatenate(comm.allgather(heavy))
            vertex = np.concatenate(comm.allgather(vertex))
        order = np.lexsort((vertex, -heavy))
        needed = int(np.searchsorted(np.cumsum(heavy[order]), self.share * total)) + 1
        if needed > self.vertices:
            return None
        around = patches.around(vertex[order[:needed]])
        dofs = (3 * around[:, None] + np.arange(3)).ravel()
        return dofs[~np.isin(dofs, self._fixed)].astype(PETSc.IntType)

    def relax(self, x: PETSc.Vec, F: PETSc.Vec) -> tuple | None:
        """Relax ``x`` in place from its residual ``F``, which then holds the relaxed
        iterate's; returns (the patch's dofs, iterations, the patch's residual norm before and
        after), or None (nothing changed) where the residual is not concentrated or the
        relaxed state is inadmissible to the whole problem."""
        dofs = self.patch(F)
        if dofs is None or dofs.size == 0:
            return None
        tic = time.perf_counter()
        model, comm = self._patches.model(dofs), self._patches.comm
        start_x, trial = x.copy(), x.duplicate()
        energy = model.energy(x)
        f = model.gradient(x)  # the energy's alone: the rows of F where the bcs are met
        start = np.linalg.norm(f)
        iterations, current = 0, True  # current: f is the gradient at x
        try:
            for iterations in range(1, self.iterations + 1):
                if not current:
                    f = model.gradient(x)
                    current = True
                if np.linalg.norm(f) < self.rtol * start:
                    iterations -= 1
                    break
                K = model.hessian(x)
                step = np.ascontiguousarray(np.linalg.lstsq(K, f, rcond=None)[0])
                if comm.size > 1:  # one process's solve: the same steps everywhere
                    comm.Bcast(step, root=0)
                slope = -f @ step
                if not slope < 0.0:  # the patch's Newton step climbs: a gradient step instead
                    step = f / np.abs(np.diag(K)).max()
                    slope = -f @ step
                values, moved = model.values(x), False
                for length in 0.5 ** np.arange(BACKTRACKS):
                    x.copy(trial)
                    model.put(trial, values - length * step)
                    value = model.energy(trial)
                    if value <= energy + ARMIJO * length * slope:
                        moved = True
                        break
                if not moved:
                    break
                trial.copy(x)
                energy, current = value, False
            self._assembler.set_state(x)
            admissible = self._assembler.residual(x, F)
            if not admissible:  # (a pair out of the patch's reach): back to the start
                start_x.copy(x)
                self._assembler.set_state(x)
                self._assembler.residual(x, F)
            norm = np.linalg.norm(model.values(F))
        finally:
            trial.destroy()
            start_x.destroy()
        self.uses += 1
        self.local_iterations += iterations
        self.seconds += time.perf_counter() - tic
        return (dofs, iterations, start, norm) if admissible else None
