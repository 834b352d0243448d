"""Bodies held only by contact: found, damped while contact engages, and named when it fails.

A body whose Dirichlet conditions leave a rigid motion free (a floating body, a hemisphere
resting under its own weight, a body pushed by forces) has no stiffness against that motion
until contact has spread: Newton's matrix is singular, and the first solve fails at any load
step and any penalty. :class:`~fenics_matdepth.ContactProblem` and
:class:`~fenics_matdepth.NonlinearContactProblem` handle it without a change to the user's
forms:

* **Found once** (:func:`find_free_bodies`): the bodies (connected components of the mesh, the
  contact surface's labelling, parallel) whose constrained dofs leave a rigid motion free: the
  rank of the six rigid-body modes evaluated at the body's Dirichlet dofs is below 6.
* **Tested at each solve** (:meth:`FreeBodyDamping.solve`): the residual at the start gives
  each free body's load (the resultant ``F`` over its free dofs), and one more residual, with
  the body moved by a small translation along ``F``, its stiffness ``q`` against that motion
  (bulk, contact, inertia: whatever the problem has). Where the load would move a body by more
  than its contact surface's mean edge length ``h`` (``|F| / q > h``: no contact yet, or a
  contact too small to carry the load), the solve starts damped; otherwise it solves the
  problem as it is first, and damps only if that fails.
* **Damped** by :class:`~fenics_matdepth.RigidModeDamping`'s proximal solves, on the lumped
  term ``(k / 2) sum_i m_i |u_i - a_i|^2`` over the free bodies' free dofs (``m_i`` the
  vertex's share of the body's volume, ``a`` the anchor), added by the problem's
  :class:`~fenics_matdepth.SystemAssembler` to the residual, the Jacobian and the energy.
  ``k`` starts where the load moves a body by ``FIRST_MOTION`` times ``h`` and falls tenfold
  per proximal solve while contact engages.
* **Off at the end**: the last solve of :class:`~fenics_matdepth.RigidModeDamping` runs with
  ``k = 0``, from the nearly balanced damped state, and only its convergence counts: a
  converged result solves the undamped problem (the damping force is zero there, not small).
* **Named on failure**: where even that fails, the result's message names the free bodies
  (number, vertices, centre, size, free rigid motions) and the fix, instead of the advice to
  reduce the load step or the penalty.

``ContactProblem(..., damp_free_bodies=False)`` switches all of it off.
"""

from __future__ import annotations

import dataclasses
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np

from fenics_matdepth.augmented import RigidModeDamping
from fenics_matdepth.boundary import p1_dof_coordinates
from fenics_matdepth.contact.assembly import owned_dirichlet_dofs
from fenics_matdepth.results import SolveResult

if typing.TYPE_CHECKING:
    from fenics_matdepth.contact.operator import ContactOperator
    from fenics_matdepth.system_assembler import SystemAssembler

__all__ = [
    "FIRST_MOTION",
    "FREE_MOTION_RTOL",
    "FreeBody",
    "FreeBodyDamping",
    "ProximalTerm",
    "find_free_bodies",
]

#: The first damped solve's stiffness k moves a free body by this fraction of the contact
#: surface's mean edge length under its load (as benchmarks/bench_hertz.py chose by hand).
FIRST_MOTION = 0.01
#: A rigid motion is free where the Gram matrix of the rigid modes at the body's Dirichlet dofs
#: (coordinates relative to the body's centre, in units of its size) has an eigenvalue below
#: this fraction of its largest.
FREE_MOTION_RTOL = 1e-10
#: The size of the trial translation that measures a body's stiffness, relative to ``h``.
TRIAL_MOTION = 1e-4


@dataclasses.dataclass(frozen=True)
class FreeBody:
    """A body (connected component of the mesh) with a rigid motion its Dirichlet conditions
    leave free.

    Attributes:
        index: the body's number (``ContactOperator.surface.body_of_vertex``, the rows of
            ``ContactOperator.force_resultants()``).
        vertices: its number of vertices.
        centre: the centroid of its vertices (L, reference configuration).
        size: the extent of its bounding box in x, y, z (L).
        free_motions: how many of its six rigid motions are free (6: no Dirichlet dof).
    """

    index: int
    vertices: int
    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    free_motions: int

    def describe(self) -> str:
        """One line: which body, where, how large, how free."""
        c, s = self.centre, self.size
        return (
            f"body {self.index} ({self.vertices} vertices, centre ({c[0]:.4g}, {c[1]:.4g}, "
            f"{c[2]:.4g}), size {s[0]:.4g} x {s[1]:.4g} x {s[2]:.4g}; {self.free_motions} of "
            "its 6 rigid motions free of Dirichlet conditions)"
        )


def _rigid_rows(p: np.ndarray, component: np.ndarray) -> np.ndarray:
    """Rows (n, 6) of the rigid modes (3 translations; rotations about z, x, y) at the dofs of
    ``component`` (n,) of the points ``p`` (n, 3)."""
    rows = np.zeros((p.shape[0], 6))
    rows[np.arange(p.shape[0]), component] = 1.0
    x, y, z = p.T
    on = [component == i for i in range(3)]
    rows[:, 3] = np.where(on[0], -y, np.where(on[1], x, 0.0))
    rows[:, 4] = np.where(on[1], -z, np.where(on[2], y, 0.0))
    rows[:, 5] = np.where(on[2], -x, np.where(on[0], z, 0.0))
    return rows


def _owned_body(contact: ContactOperator) -> np.ndarray:
    """The body of each owned vertex (P1 block)."""
    imap = contact.u.function_space.dofmap.index_map
    owned = imap.local_to_global(np.arange(imap.size_local, dtype=np.int32))
    return np.asarray(contact.surface.body_of_vertex)[owned]


def find_free_bodies(
    contact: ContactOperator, bcs: typing.Sequence[dolfinx.fem.DirichletBC]
) -> list[FreeBody]:
    """The bodies of the contact operator's mesh with a rigid motion that ``bcs`` leave free
    (collective).

    Args:
        contact: the contact operator (its surface labels the bodies).
        bcs: the problem's Dirichlet conditions (on the displacement space or its subspaces).

    Returns:
        One :class:`FreeBody` per such body, in the order of their numbers.
    """
    comm = contact.comm
    V = contact.u.function_space
    n_bodies = int(contact.surface.num_bodies)
    body = _owned_body(contact)
    X = p1_dof_coordinates(V)[: body.size]
    count = comm.allreduce(np.bincount(body, minlength=n_bodies), op=MPI.SUM)
    total = np.zeros((n_bodies, 3))
    np.add.at(total, body, X)
    centre = comm.allreduce(total, op=MPI.SUM) / np.maximum(count, 1)[:, None]
    low = np.full((n_bodies, 3), np.inf)
    high = np.full((n_bodies, 3), -np.inf)
    np.minimum.at(low, body, X)
    np.maximum.at(high, body, X)
    comm.Allreduce(MPI.IN_PLACE, low, op=MPI.MIN)
    comm.Allreduce(MPI.IN_PLACE, high, op=MPI.MAX)
    size = np.where(count[:, None] > 0, high - low, 0.0)
    scale = np.maximum(size.max(axis=1), np.finfo(float).tiny)

    dofs = owned_dirichlet_dofs(bcs)
    block, component = dofs // 3, dofs % 3
    b = body[block]
    rows = _rigid_rows((X[block] - centre[b]) / scale[b, None], component)
    gram = np.zeros((n_bodies, 6, 6))
    np.add.at(gram, b, rows[:, :, None] * rows[:, None, :])
    gram = comm.allreduce(gram, op=MPI.SUM)
    found = []
    for i in range(n_bodies):
        eig = np.linalg.eigvalsh(gram[i])
        free = int(np.count_nonzero(eig <= FREE_MOTION_RTOL * max(eig[-1], 0.0)))
        if free:
            found.append(
                FreeBody(i, int(count[i]), tuple(centre[i].tolist()), tuple(size[i].tolist()), free)
            )
    return found


def _lumped_volume(V: dolfinx.fem.FunctionSpace) -> np.ndarray:
    """Each owned vertex's share of the volume (a quarter of each cell's; L^3), (n_owned,)
    (collective)."""
    mesh = V.mesh
    imap = V.dofmap.index_map
    cells = np.asarray(V.dofmap.list).reshape(-1, 4)[: mesh.topology.index_map(3).size_local]
    X = p1_dof_coordinates(V)
    edges = X[cells[:, 1:]] - X[cells[:, :1]]
    volume = np.abs(np.linalg.det(edges)) / 6.0
    share = dolfinx.la.vector(imap, 1)
    share.array[:] = 0.0
    np.add.at(share.array, cells.ravel(), np.repeat(volume / 4.0, 4))
    share.scatter_reverse(dolfinx.la.InsertMode.add)
    return share.array[: imap.size_local].copy()


class ProximalTerm:
    """The proximal term ``(k / 2) sum_i m_i |u_i - a_i|^2`` of the free bodies' free dofs,
    which :class:`~fenics_matdepth.SystemAssembler` adds to the residual, the Jacobian and the
    energy while ``k > 0`` (the lumped form of :func:`~fenics_matdepth.damping_energy`'s
    ``(k / 2) int |u - a|^2 dx``).

    Args:
        weights: ``m_i`` of each owned dof (unrolled), 0 off the free bodies and on Dirichlet
            dofs (L^3).
        stiffness: a ``dolfinx.fem.Constant`` holding k (force / length^4).
        anchor: the Function holding ``a``.
    """

    def __init__(self, weights: np.ndarray, stiffness, anchor: dolfinx.fem.Function):
        self.weights = weights
        self.stiffness = stiffness
        self.anchor = anchor

    @property
    def k(self) -> float:
        """The current stiffness."""
        return float(self.stiffness.value)

    def _offset(self, x: PETSc.Vec) -> np.ndarray:
        n = self.weights.size
        return x.getArray(readonly=True)[:n] - self.anchor.x.array[:n]

    def add_residual(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """``b += k m (x - a)`` on the owned dofs (after the reverse ghost update)."""
        if self.k != 0.0:
            b.array[: self.weights.size] += self.k * self.weights * self._offset(x)

    def add_jacobian(self, A: PETSc.Mat) -> None:
        """``A += k diag(m)`` (collective; ``A`` assembled afterwards)."""
        if self.k == 0.0:
            return
        diagonal = A.createVecLeft()
        diagonal.array[:] = self.k * self.weights
        A.setDiagonal(diagonal, addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()
        diagonal.destroy()

    def energy(self, x: PETSc.Vec, comm: MPI.Comm) -> float:
        """The term's value at ``x`` (collective; energy unit F L)."""
        if self.k == 0.0:
            return 0.0
        local = 0.5 * self.k * float(np.sum(self.weights * self._offset(x) ** 2))
        return comm.allreduce(local, op=MPI.SUM)


class _PlainSolves:
    """The problem as :class:`~fenics_matdepth.RigidModeDamping` sees it: its plain solve, and
    its Newton solver for the tolerances."""

    def __init__(self, problem, plain: typing.Callable[[bool], SolveResult]):
        self.problem, self.u, self.contact = problem, problem.u, problem.contact
        self._plain = plain

    @property
    def snes(self):
        return getattr(self.problem, "snes", None)

    @property
    def _solver(self):
        return getattr(self.problem, "_solver", None)

    def solve(self, raise_on_failure: bool = True) -> SolveResult:
        return self._plain(raise_on_failure)


class FreeBodyDamping:
    """A contact problem's handling of bodies held only by contact (see the module's
    docstring).

    Args:
        contact: the problem's contact operator.
        bcs: its Dirichlet conditions.
        assembler: its assembler (gets the :class:`~fenics_matdepth.free_bodies.ProximalTerm`).
        enabled: False: find nothing, damp nothing.
        decrease: the factor on k from one damped solve to the next
            (:class:`~fenics_matdepth.RigidModeDamping`'s).

    Attributes:
        bodies: the free bodies found (empty when disabled).
        damped: whether the last solve ran damped solves.
        damped_solves: how many (the last solve).
        motions: each free body's motion under its load at the last solve's start, ``|F| / q``
            relative to ``h`` (inf without stiffness; 0 without load).
    """

    def __init__(
        self,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC],
        assembler: SystemAssembler,
        enabled: bool = True,
        decrease: float = 0.1,
    ):
        self.enabled = bool(enabled)
        self.decrease = float(decrease)
        self.contact = contact
        self.assembler = assembler
        self.bodies = find_free_bodies(contact, bcs) if self.enabled else []
        self.damped = False
        self.damped_solves = 0
        self.motions = np.zeros(len(self.bodies))
        if not self.bodies:
            return
        V = contact.u.function_space
        self.h = float(contact.surface.mean_edge) or 1.0
        body = _owned_body(contact)
        self._body_index = np.full(contact.surface.num_bodies, -1)
        self._body_index[[b.index for b in self.bodies]] = np.arange(len(self.bodies))
        # the free body of each owned vertex and dof (unrolled), -1 elsewhere and on the
        # Dirichlet dofs
        vertex_body = self._body_index[body]
        self._dof_body = np.repeat(vertex_body, 3)
        self._dof_body[owned_dirichlet_dofs(assembler.bcs)] = -1
        share = _lumped_volume(V)
        on = vertex_body >= 0
        self._volume = contact.comm.allreduce(
            np.bincount(vertex_body[on], weights=share[on], minlength=len(self.bodies)),
            op=MPI.SUM,
        )
        volume = np.repeat(share, 3)
        weights = np.where(self._dof_body >= 0, volume, 0.0)
        stiffness = dolfinx.fem.Constant(V.mesh, PETSc.ScalarType(0.0))
        anchor = dolfinx.fem.Function(V, name="free_body_anchor")
        assembler.proximal = ProximalTerm(weights, stiffness, anchor)

    def _resultants(self, b: PETSc.Vec) -> np.ndarray:
        """(bodies, 3): the sum of ``b`` over each free body's free dofs (collective)."""
        out = np.zeros((len(self.bodies), 3))
        on = self._dof_body >= 0
        comp = np.flatnonzero(on) % 3
        np.add.at(out, (self._dof_body[on], comp), b.getArray(readonly=True)[on])
        return self.contact.comm.allreduce(out, op=MPI.SUM)

    def _loads(self, u: dolfinx.fem.Function) -> tuple[np.ndarray, np.ndarray]:
        """Each free body's load ``F`` (bodies, 3) and stiffness ``q`` against a translation
        along it (bodies,), from the residual at ``u`` and at ``u`` with each body translated
        by ``TRIAL_MOTION h`` along its load (collective; ``u`` and the contact state are left
        as they were)."""
        assembler = self.assembler
        x = u.x.petsc_vec
        b, trial, moved = x.duplicate(), x.duplicate(), x.duplicate()
        try:
            assembler.set_state(x)
            if not assembler.residual(x, b):
                return np.zeros((len(self.bodies), 3)), np.zeros(len(self.bodies))
            load = -self._resultants(b)
            norm = np.linalg.norm(load, axis=1)
            direction = np.zeros_like(load)
            np.divide(load, norm[:, None], out=direction, where=norm[:, None] > 0)
            s = TRIAL_MOTION * self.h
            on = self._dof_body >= 0
            x.copy(trial)
            step = np.zeros(on.size)
            step[on] = s * direction[self._dof_body[on], np.flatnonzero(on) % 3]
            trial.array[: on.size] += step
            assembler.set_state(trial)
            stiffness = np.zeros(len(self.bodies))
            if assembler.residual(trial, moved):
                change = self._resultants(moved) + load  # the resultant's change, F(u) = -load
                stiffness = np.einsum("ij,ij->i", change, direction) / s
        finally:
            u.x.scatter_forward()
            assembler.set_state(x)
            for vec in (b, trial, moved):
                vec.destroy()
        return load, stiffness

    def solve(
        self, problem, plain: typing.Callable[[bool], SolveResult], raise_on_failure: bool
    ) -> SolveResult:
        """Solve ``problem`` with ``plain`` (its undamped solve), damped where needed (see the
        module's docstring; collective)."""
        self.damped, self.damped_solves = False, 0
        if not self.bodies:
            return plain(raise_on_failure)
        load, stiffness = self._loads(problem.u)
        force = np.linalg.norm(load, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.motions = np.where(force > 0.0, force / np.maximum(stiffness, 0.0), 0.0) / self.h
        k = float(np.max(force / (FIRST_MOTION * self.h * self._volume)))
        if k <= 0.0 or not np.isfinite(k):
            # no load on the free bodies: the first proximal motion from the penalty's scale
            k = float(self.contact.penalty) / self.h
        term = self.assembler.proximal
        damping = RigidModeDamping(
            _PlainSolves(problem, plain), term.stiffness, term.anchor, decrease=self.decrease
        )
        damping.stiffness = k
        # damped from the start where the load would move a body by more than h; else the
        # plain solve first (RigidModeDamping's undamped_first after a converged call)
        damping.held = not bool(np.any(self.motions > 1.0))
        result = damping.solve(raise_on_failure=False)
        self.damped_solves = damping.damped_solves
        self.damped = self.damped_solves > 0
        if not result.converged:
            result = dataclasses.replace(result, advice=self.advice())
            if raise_on_failure:
                raise RuntimeError(result.failure_message())
        return result

    def advice(self) -> str:
        """What the failure message says about the free bodies."""
        names = "; ".join(b.describe() for b in self.bodies)
        return (
            f"The mesh has bodies held only by contact: {names}. Contact did not hold them, "
            "even with the automatic proximal damping of their rigid motions: make sure the "
            "load presses each onto a body it touches or nearly touches (start it touching), "
            "or hold it with Dirichlet conditions."
        )
