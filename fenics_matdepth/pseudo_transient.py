"""Pseudo-transient continuation of a Newton solve (Kelley & Keyes 1998): a Jacobian shift that
regularises the steps through a limit point and vanishes as the residual falls.

Where the load path has a limit point (the equilibrium the load steps follow ends and the
solution has to snap to another one), Newton's method meets an indefinite or nearly singular
Jacobian: its steps are long and point anywhere, and the line search cuts them to little
(measured on the knee past 105.5 deg: isolated steps of 20 to 70 Newton iterations whatever
the increment). Pseudo-transient continuation (Psi-tc) takes instead the steps of

    (J + sigma_k D) dx = -F,

the Newton steps of ``F(u) + sigma_k D (u - u_k) = 0``, a backward-Euler step of the
pseudo-time flow ``D du/dt = -F(u)`` with the time step ``1 / sigma_k``: ``D`` is a diagonal
matrix, mass-like (here the absolute diagonal of the solve's Jacobian at its reference iterate,
below, kept for the solve, so that ``sigma`` has no unit; zero on the Dirichlet rows, whose
steps impose the prescribed values as before). ``D`` is frozen rather than taken from each
Jacobian: where the path nears a limit point the Jacobian's diagonal can itself approach zero
(one degree of freedom: it does), and a shift proportional to it would vanish where it is
needed. Where J is indefinite the shift makes the step a descent step of the energy for
``sigma`` large enough; the residual is not changed, so a converged solve is the exact
equilibrium (unlike a fixed viscous stabilisation such as Abaqus's automatic stabilisation,
which leaves the damping force in the equilibrium). ``sigma_k`` follows switched evolution
relaxation (SER): ``sigma_k = sigma_0 |F_k| / |F_ref|``, ``F_ref`` the residual at the
solve's first iterate where the Dirichlet dofs hold their values; below ``off_rtol |F_ref|``
the shift is off and the iterations are Newton's (quadratic convergence).

Measured: on a block in a tilted double well past its limit load, fewer iterations than plain
Newton (tests/test_pseudo_transient.py); on the knee's snaps past 105.5 deg, more (sigma0 0.3:
the retries crawled to the iteration limit; 0.03: 53 iterations where plain Newton took 34,
and 7 to 13 on the easy steps where it takes 4 to 9): the shifted steps follow the energy's
pseudo-time flow, slow across the flat region past a limit point, which Newton's long step
leaps (docs/measurements.md). Opt-in.

Set it on a problem: ``problem.pseudo_transient = fm.PseudoTransient(sigma0=0.1)``; the
problem's Jacobian callback calls :meth:`PseudoTransient.shift` after each assembly.
"""

from __future__ import annotations

import dataclasses

from petsc4py import PETSc

import numpy as np

from fenics_matdepth.contact.assembly import owned_dirichlet_dofs

__all__ = ["PseudoTransient"]


@dataclasses.dataclass
class PseudoTransient:
    """Pseudo-transient continuation (switched evolution relaxation) of a
    :class:`~fenics_matdepth.ContactProblem`'s Newton solves (see the module).

    Args:
        sigma0: the shift at the reference residual, relative to each row's absolute diagonal
            (0: plain Newton).
        off_rtol: the shift is off (plain Newton) once the residual is below this fraction of
            the reference residual.
        max_ratio: ``|F_k| / |F_ref|`` is capped at this (a residual that grew a thousandfold
            does not make the steps a thousand times shorter).

    One control serves one problem (it keeps a mask of that problem's Dirichlet rows); call
    :meth:`destroy` with the problem's (its two PETSc vectors; on more than one rank petsc4py
    otherwise leaves them in PETSc's garbage).

    Attributes:
        shifted: Newton iterations of the last solve whose Jacobian was shifted.
        last_sigma: the shift of the last Jacobian (0 where none).
    """

    sigma0: float = 0.1
    off_rtol: float = 1e-3
    max_ratio: float = 10.0
    shifted: int = dataclasses.field(default=0, init=False)
    last_sigma: float = dataclasses.field(default=0.0, init=False)

    def __post_init__(self):
        if not self.sigma0 >= 0.0:
            raise ValueError(f"sigma0 must be >= 0, got {self.sigma0}")
        if not 0.0 <= self.off_rtol < 1.0:
            raise ValueError(f"off_rtol must be in [0, 1), got {self.off_rtol}")
        if not self.max_ratio >= 1.0:
            raise ValueError(f"max_ratio must be >= 1, got {self.max_ratio}")
        self._reference = np.nan
        self._free: PETSc.Vec | None = None
        self._scaling: PETSc.Vec | None = None  # D, set at the reference iterate

    def start_solve(self) -> None:
        """A Newton solve starts: its reference residual is taken anew."""
        self._reference = np.nan
        if self._scaling is not None:
            self._scaling.destroy()
            self._scaling = None
        self.shifted = 0
        self.last_sigma = 0.0

    def sigma(self, norm: float, bcs_met: bool) -> float:
        """The shift for an iterate of residual norm ``norm``; ``bcs_met``: whether its
        Dirichlet dofs hold their values (before that: no shift, and no reference yet)."""
        if not bcs_met or self.sigma0 == 0.0 or not np.isfinite(norm):
            return 0.0
        if not np.isfinite(self._reference):
            self._reference = norm
        if self._reference <= 0.0 or norm <= self.off_rtol * self._reference:
            return 0.0
        return self.sigma0 * min(norm / self._reference, self.max_ratio)

    def _free_rows(self, assembler) -> PETSc.Vec:
        """1 on the rows without a Dirichlet condition, 0 on theirs (built once)."""
        if self._free is None:
            self._free = assembler.u.x.petsc_vec.duplicate()
            self._free.set(1.0)
            self._free.array[owned_dirichlet_dofs(assembler.bcs)] = 0.0
        return self._free

    def shift(self, A: PETSc.Mat, assembler, norm: float, bcs_met: bool) -> float:
        """Add ``sigma D`` to the diagonal of the assembled Jacobian ``A`` (``D`` taken from
        ``A`` at the solve's reference iterate; see the module; collective). Returns sigma (0:
        ``A`` unchanged)."""
        sigma = self.sigma(norm, bcs_met)
        self.last_sigma = sigma
        if sigma == 0.0:
            return 0.0
        if self._scaling is None:  # the reference iterate: D = |diag J| off the Dirichlet rows
            self._scaling = A.getDiagonal()
            self._scaling.abs()
            self._scaling.pointwiseMult(self._scaling, self._free_rows(assembler))
        shift = self._scaling.copy()
        shift.scale(sigma)
        A.setDiagonal(shift, addv=PETSc.InsertMode.ADD_VALUES)
        shift.destroy()
        self.shifted += 1
        return sigma

    def destroy(self) -> None:
        """Release the vectors (the Dirichlet mask, the scaling D)."""
        for name in ("_free", "_scaling"):
            vector = getattr(self, name)
            if vector is not None:
                vector.destroy()
                setattr(self, name, None)
