"""Newton solvers with contact: PETSc SNES over a user's UFL residual plus the contact operator."""

from __future__ import annotations

import dataclasses
import typing

from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import numpy as np
import ufl

from fenics_matdepth.contact.operator import ContactOperator

__all__ = ["ContactProblem", "SolveResult"]

_DEFAULT_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "bt",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-12,
    "snes_stol": 0.0,
    "snes_max_it": 50,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}


@dataclasses.dataclass
class SolveResult:
    """Outcome of :meth:`ContactProblem.solve`.

    Attributes:
        converged: whether SNES reported convergence.
        reason: SNES converged reason (a ``PETSc.SNES.ConvergedReason`` value; > 0 converged).
        iterations: Newton iterations taken.
        residual_norms: residual norm before each iteration and after the last one.
    """

    converged: bool
    reason: int
    iterations: int
    residual_norms: np.ndarray


class ContactProblem:
    """Nonlinear problem F(u) + dE_contact/du = 0 solved with PETSc SNES.

    Args:
        F: the user's residual form (any UFL physics), linear in the test function.
        u: the unknown displacement (P1 vector Function, the one the contact operator uses).
        contact: the contact operator of ``u``.
        bcs: Dirichlet conditions.
        J: Jacobian form; default ``ufl.derivative(F, u)``.
        energy: optional UFL energy functional whose derivative is ``F``; when given, the
            backtracking line search works on the total energy (bulk + contact) instead of the
            residual norm.
        petsc_options_prefix: prefix of this problem's PETSc options.
        petsc_options: options set under the prefix (defaults: newtonls, bt line search, LU with
            MUMPS, rtol 1e-10).
    """

    def __init__(
        self,
        F: ufl.Form,
        u: dolfinx.fem.Function,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC] = (),
        J: ufl.Form | None = None,
        energy: ufl.Form | None = None,
        petsc_options_prefix: str = "matdepth_",
        petsc_options: dict | None = None,
    ):
        if contact.u is not u:
            raise ValueError("the contact operator must be built on the same Function u")
        self.u = u
        self.contact = contact
        self.bcs = list(bcs)
        self._F = dolfinx.fem.form(F)
        self._J = dolfinx.fem.form(J if J is not None else ufl.derivative(F, u))
        self._energy = dolfinx.fem.form(energy) if energy is not None else None
        contact.set_bcs(self.bcs)
        self.prefix = petsc_options_prefix
        comm = u.function_space.mesh.comm

        self._A = contact.create_matrix(self._J)
        # Ghosted, as dolfinx's assembly and lifting read and write ghost entries.
        self._b = u.x.petsc_vec.duplicate()
        self._x = u.x.petsc_vec.duplicate()
        self.snes = PETSc.SNES().create(comm)
        self.snes.setOptionsPrefix(self.prefix)
        opts = PETSc.Options()
        opts.prefixPush(self.prefix)
        for key, value in {**_DEFAULT_OPTIONS, **(petsc_options or {})}.items():
            opts[key] = value
        opts.prefixPop()
        self.snes.setFunction(self._residual, self._b)
        self.snes.setJacobian(self._jacobian, self._A, self._A)
        if self._energy is not None:
            self.snes.setObjective(self._objective)
        self.snes.setFromOptions()
        self.snes.getKSP().setFromOptions()

    # -- callbacks ----------------------------------------------------------------------------

    def _set_state(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.u.x.petsc_vec)
        self.u.x.scatter_forward()
        self.contact.update()

    def _residual(self, snes: PETSc.SNES, x: PETSc.Vec, b: PETSc.Vec) -> None:
        self._set_state(x)
        with b.localForm() as b_local:
            b_local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(b, self._F)
        self.contact.add_residual(b)
        dolfinx.fem.petsc.apply_lifting(b, [self._J], [self.bcs], x0=[x], alpha=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        dolfinx.fem.petsc.set_bc(b, self.bcs, x, -1.0)

    def _jacobian(self, snes: PETSc.SNES, x: PETSc.Vec, A: PETSc.Mat, P: PETSc.Mat) -> None:
        # SNES evaluates the residual at x before the Jacobian, so the contact state is current.
        A.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(A, self._J, self.bcs)
        A.assemble()
        self.contact.add_jacobian(A)

    def _objective(self, snes: PETSc.SNES, x: PETSc.Vec) -> float:
        self._set_state(x)
        comm = self.u.function_space.mesh.comm
        bulk = comm.allreduce(dolfinx.fem.assemble_scalar(self._energy))
        return bulk + self.contact.energy()

    # -- solve ----------------------------------------------------------------------------------

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        """Solve from the current ``u``; ``u`` holds the solution afterwards (collective).

        Args:
            raise_on_failure: raise ``RuntimeError`` (with the residual history) when SNES does
                not converge; otherwise return the result with ``converged=False``.
        """
        self.u.x.petsc_vec.copy(self._x)
        dolfinx.fem.petsc.set_bc(self._x, self.bcs)
        self.snes.setConvergenceHistory(reset=True)
        self.snes.solve(None, self._x)
        self._set_state(self._x)
        history = np.asarray(self.snes.getConvergenceHistory()[0], dtype=float)
        reason = int(self.snes.getConvergedReason())
        result = SolveResult(reason > 0, reason, int(self.snes.getIterationNumber()), history)
        if raise_on_failure and not result.converged:
            raise RuntimeError(
                f"contact Newton solve did not converge (SNES reason {reason}) after "
                f"{result.iterations} iterations; residual norms: "
                + ", ".join(f"{r:.3e}" for r in history)
                + ". Reduce the load step, or lower the penalty."
            )
        return result

    def __del__(self):
        for obj in ("snes", "_A", "_b", "_x"):
            if hasattr(self, obj):
                getattr(self, obj).destroy()
