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
* **Without a line search** (:class:`~fenics_matdepth.NonlinearContactProblem`), ``k`` falls
  only while the next damped solve would move a body not yet held by at most
  ``MAX_FREE_MOTION`` times ``h``, or once contact holds it (its undamped stiffness along its
  load at least the next ``k`` times its volume): a full Newton step computed before contact
  engages would otherwise carry the body from a gap deep into the other one.
* **Named on failure**: where even that fails, the result's message names the free bodies
  (number, vertices, centre, size, free rigid motions), the rigid motions contact does not
  hold at the last damped state (:meth:`FreeBodyDamping.unheld_motions`: frictionless contact
  holds a body pressed onto a face against the normal translation and the tilts, never against
  sliding along the face and turning about its normal) and the fixes, instead of the advice
  to reduce the load step or the penalty. The library does not regularise those motions
  itself: a term that held them would bias the answer wherever the discrete contact forces
  have a tangential resultant (measured: a cube free in all six motions on a block slid
  0.59 along the mesh's diagonal while the damping fell), so the fix is the user's choice.

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
    "MAX_FREE_MOTION",
    "RIGID_MOTIONS",
    "UNHELD_RTOL",
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
#: Without a line search, a damped solve moves a body that contact does not hold yet by at most
#: this fraction of ``h`` (from a gap of h / 9, the test's, a damped solve whose free motion was
#: h diverged at every k tried; with h / 10 per solve it converges).
MAX_FREE_MOTION = 0.1
#: A rigid motion is not held where its stiffness (the generalised eigenvalue of the body's
#: rigid-mode stiffness over the modes' Gram matrix) is below this fraction of the largest
#: one's, or of ``eps h^2``, whichever is larger.
UNHELD_RTOL = 1e-3
#: The names of the rigid motions, in the order of the rigid modes (translations; rotations
#: about z, x, y).
RIGID_MOTIONS = (
    "translation along x",
    "translation along y",
    "translation along z",
    "rotation about z",
    "rotation about x",
    "rotation about y",
)


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
        line_search: whether the problem's Newton solver has a line search; without one, ``k``
            falls only as far as ``MAX_FREE_MOTION`` allows until contact holds the body.

    Attributes:
        bodies: the free bodies found (empty when disabled).
        damped: whether the last solve ran damped solves.
        damped_solves: how many (the last solve).
        motions: each free body's motion under its load at the last solve's start, ``|F| / q``
            relative to ``h`` (inf without stiffness; 0 without load).
        unheld: after a failed solve, the rigid motions contact did not hold at the last
            damped state, per free body (names from ``RIGID_MOTIONS``; empty otherwise).
    """

    def __init__(
        self,
        contact: ContactOperator,
        bcs: typing.Sequence[dolfinx.fem.DirichletBC],
        assembler: SystemAssembler,
        enabled: bool = True,
        decrease: float = 0.1,
        line_search: bool = True,
    ):
        self.enabled = bool(enabled)
        self.decrease = float(decrease)
        self.line_search = bool(line_search)
        self.contact = contact
        self.assembler = assembler
        self.bodies = find_free_bodies(contact, bcs) if self.enabled else []
        self.damped = False
        self.damped_solves = 0
        self.motions = np.zeros(len(self.bodies))
        self.unheld: list[list[str]] = [[] for _ in self.bodies]
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
        self._vertex_body = vertex_body
        self._X = p1_dof_coordinates(V)[: body.size]
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

    def _loads(
        self, u: dolfinx.fem.Function, along: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each free body's load ``F`` (bodies, 3) and stiffness ``q`` against a translation
        along it (bodies,), from the residual at ``u`` and at ``u`` with each body translated
        by ``TRIAL_MOTION h`` along its load, or along ``along`` (bodies, 3) where given
        (collective; ``u`` and the contact state are left as they were)."""
        assembler = self.assembler
        x = u.x.petsc_vec
        b, trial, moved = x.duplicate(), x.duplicate(), x.duplicate()
        try:
            assembler.set_state(x)
            if not assembler.residual(x, b):
                return np.zeros((len(self.bodies), 3)), np.zeros(len(self.bodies))
            load = -self._resultants(b)
            toward = load if along is None else along
            norm = np.linalg.norm(toward, axis=1)
            direction = np.zeros_like(toward)
            np.divide(toward, norm[:, None], out=direction, where=norm[:, None] > 0)
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
        may_decrease = None
        if not self.line_search:

            def may_decrease(used: float) -> bool:
                # the next k moves a body only a little, or contact holds each body already
                following = used * self.decrease * self._volume
                term.stiffness.value = 0.0
                try:
                    _, held = self._loads(problem.u, along=load)
                finally:
                    term.stiffness.value = used
                small = force <= MAX_FREE_MOTION * self.h * following * (1.0 + 1e-9)
                return bool(np.all(small | (held >= following)))

        damping = RigidModeDamping(
            _PlainSolves(problem, plain), term.stiffness, term.anchor, decrease=self.decrease,
            may_decrease=may_decrease,
        )  # fmt: skip
        damping.stiffness = k
        # damped from the start where the load would move a body by more than h; else the
        # plain solve first (RigidModeDamping's undamped_first after a converged call)
        damping.held = not bool(np.any(self.motions > 1.0))
        result = damping.solve(raise_on_failure=False)
        self.damped_solves = damping.damped_solves
        self.damped = self.damped_solves > 0
        self.unheld = [[] for _ in self.bodies]
        if not result.converged:
            if self.damped:
                # at the last damped solve's start (its anchor)
                reached = problem.u.x.array.copy()
                problem.u.x.array[:] = term.anchor.x.array
                try:
                    self.unheld = self.unheld_motions(problem.u)
                finally:
                    problem.u.x.array[:] = reached
                    self.assembler.set_state(problem.u.x.petsc_vec)
            result = dataclasses.replace(result, advice=self.advice())
            if raise_on_failure:
                raise RuntimeError(result.failure_message())
        return result

    def rigid_stiffness(self, u: dolfinx.fem.Function) -> tuple[np.ndarray, np.ndarray] | None:
        """Each free body's stiffness against its six rigid motions at ``u``, without the
        damping term (collective; ``u`` and the contact state are left as they were).

        The modes are those of :func:`find_free_bodies` at the current positions ``X + u``,
        about the body's current centre, rotations scaled by the body's size, on its free dofs
        only (a mode its Dirichlet conditions hold deforms the body there, and is stiff).
        One residual per mode, moved by ``TRIAL_MOTION h``.

        Returns:
            ``(K, G)``, each (bodies, 6, 6): the stiffness (force / length, the generalised
            force of mode n per unit motion of mode m) and the modes' Gram matrix; None where
            a residual could not be evaluated (an inverted element).
        """
        comm, assembler = self.contact.comm, self.assembler
        n_bodies, n = len(self.bodies), self._dof_body.size
        x = u.x.petsc_vec
        P = self._X + x.getArray(readonly=True)[:n].reshape(-1, 3)
        on = self._vertex_body >= 0
        total = np.zeros((n_bodies, 3))
        np.add.at(total, self._vertex_body[on], P[on])
        count = np.bincount(self._vertex_body[on], minlength=n_bodies)
        centre = (
            comm.allreduce(total, op=MPI.SUM)
            / np.maximum(comm.allreduce(count, op=MPI.SUM), 1)[:, None]
        )
        scale = np.array([max(max(b.size), np.finfo(float).tiny) for b in self.bodies])
        dofs = np.flatnonzero(self._dof_body >= 0)
        body = self._dof_body[dofs]
        rows = _rigid_rows((P[dofs // 3] - centre[body]) / scale[body, None], dofs % 3)
        gram = np.zeros((n_bodies, 6, 6))
        np.add.at(gram, body, rows[:, :, None] * rows[:, None, :])
        s = TRIAL_MOTION * self.h
        k, stiffness = self.assembler.proximal.k, np.zeros((n_bodies, 6, 6))
        base, trial, moved = x.duplicate(), x.duplicate(), x.duplicate()
        admissible = True
        try:
            self.assembler.proximal.stiffness.value = 0.0
            assembler.set_state(x)
            admissible = assembler.residual(x, base)
            start = base.getArray(readonly=True)[dofs].copy()
            for m in range(6):
                x.copy(trial)
                trial.array[dofs] += s * rows[:, m]
                assembler.set_state(trial)
                admissible = assembler.residual(trial, moved) and admissible
                change = (moved.getArray(readonly=True)[dofs] - start) / s
                np.add.at(stiffness[:, :, m], body, rows * change[:, None])
        finally:
            self.assembler.proximal.stiffness.value = k
            u.x.scatter_forward()
            assembler.set_state(x)
            for vec in (base, trial, moved):
                vec.destroy()
        if not comm.allreduce(bool(admissible), op=MPI.LAND):
            return None
        return comm.allreduce(stiffness, op=MPI.SUM), comm.allreduce(gram, op=MPI.SUM)

    def unheld_motions(self, u: dolfinx.fem.Function) -> list[list[str]]:
        """The rigid motions of each free body that nothing holds at ``u`` (collective).

        From :meth:`rigid_stiffness`: the generalised eigenvalues of the symmetric part of K
        over G at or below ``UNHELD_RTOL`` of the largest (or of ``eps h^2``) span the motions
        not held; a rigid motion is named where more than half of it (in G's norm) lies in
        that span, or where its own stiffness (``K_ii / G_ii``) is below that bound (a motion
        without stiffness coupled to a stiff one: seen, the turning of a cube on a block,
        coupled to its tilts at a state contact had not settled).

        Returns:
            Per free body, the names (``RIGID_MOTIONS``) of its motions not held; empty lists
            where the stiffness could not be evaluated.
        """
        measured = self.rigid_stiffness(u)
        if measured is None:
            return [[] for _ in self.bodies]
        stiffness, gram = measured
        out = []
        reference = float(self.contact.penalty) * self.h**2
        for K, G in zip(stiffness, gram, strict=True):
            # G^(-1/2) through its eigenvectors (G is positive definite on a body's free dofs,
            # semi-definite only on a degenerate body: those directions are dropped)
            g, V = np.linalg.eigh(G)
            keep = g > 1e-12 * g[-1]
            W = V[:, keep] / np.sqrt(g[keep])
            lam, Y = np.linalg.eigh(W.T @ (0.5 * (K + K.T)) @ W)
            bound = UNHELD_RTOL * max(float(np.max(np.abs(lam))), reference)
            X = W @ Y[:, lam <= bound]  # G-orthonormal basis of the motions not held
            diagonal = np.maximum(np.diag(G), 1e-300)
            share = np.einsum("ij,ij->i", G @ X, G @ X) / diagonal
            own = np.diag(K) / diagonal
            free = (share > 0.5) | (own <= bound)
            out.append([name for name, f in zip(RIGID_MOTIONS, free, strict=True) if f])
        return out

    def advice(self) -> str:
        """What the failure message says about the free bodies."""
        names = "; ".join(b.describe() for b in self.bodies)
        unheld = "; ".join(
            f"body {b.index}: {', '.join(m)}"
            for b, m in zip(self.bodies, self.unheld, strict=True)
            if m
        )
        if not unheld:
            return (
                f"The mesh has bodies held only by contact: {names}. Contact did not hold "
                "them, even with the automatic proximal damping of their rigid motions: make "
                "sure the load presses each onto a body it touches or nearly touches (start it "
                "touching), or hold it with Dirichlet conditions."
            )
        return (
            f"The mesh has bodies held only by contact: {names}. Contact did not hold them, "
            "even with the automatic proximal damping of their rigid motions; at the last "
            f"damped state it did not hold these rigid motions ({unheld}). Frictionless "
            "contact does not hold a body against sliding along the faces it touches or "
            "turning about their normal. Fixes: hold those motions with Dirichlet conditions "
            "(a roller on a symmetry plane, a pinned vertex or edge), give the contact "
            "friction (fm.Coulomb), or add a weak spring to the body's energy ((k / 2) int "
            "|u|^2 dx over it, small k: it biases the answer by its force); where the "
            "translation towards the other body is among them, make sure the load presses the "
            "body onto one it touches or nearly touches (start it touching)."
        )
