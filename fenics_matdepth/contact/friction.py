"""Coulomb friction of the contact operator: the law (:class:`Coulomb`) and the operator's
lagged friction potential (:class:`FrictionMixin`).

Each step's friction is a potential of the displacement since the last converged state (the
reference), at normal pressures, contact normals and quadrature points lagged from it
(``kernels.friction``): a Newton solve of the step minimises the elastic and contact energies
plus that potential, with exact derivatives, and the energy line search keeps working.
:meth:`FrictionMixin.advance` makes the current state the reference; the stepping loops call
it after every converged step. A failed or cut step goes back to the last converged state,
which is the reference still: nothing else is restored.
"""

from __future__ import annotations

import dataclasses
import typing

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx.la
import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth.contact import assembly, pairs
from fenics_matdepth.contact.fields import contact_fields
from fenics_matdepth.contact.kernels.friction import (
    empty_reference,
    friction_blocks,
    friction_pairs,
    friction_points,
    friction_reference,
)

__all__ = ["Coulomb", "FrictionMixin", "local_cell_tags", "solve_with_updates"]

_POINT_KEYS = ("coef", "normal", "weight", "area")

#: the default slip tolerance, as a fraction of the mean boundary edge length
SLIP_TOL_FRACTION = 1e-3
#: A friction point whose tangential stiffness stays below this fraction of the normal
#: penalty's at its place (``k w``: its pressure is about 0) does not count in
#: ``stick_slip_change``: its change does not move the Jacobian.
STIFFNESS_FLOOR = 1e-2


def _check_mu(value: typing.Any, what: str) -> float:
    try:
        mu = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number >= 0, got {value!r}") from None
    if not (np.isfinite(mu) and mu >= 0.0):
        raise ValueError(f"{what} must be a number >= 0, got {value!r}")
    return mu


class Coulomb:
    """Coulomb friction: the tangential traction bounded by ``mu`` times the contact pressure.

    Args:
        mu: the friction coefficient (dimensionless, >= 0), or a dict ``{(a, b): mu}`` by pair
            of body indices (the operator's ``body_of_vertex``; order within a key does not
            matter, ``(a, a)`` is a body's self-contact), with ``default`` for the pairs of
            bodies it does not name.
        slip_tol: the slip tolerance e (L): below a slip of e per step the traction grows
            smoothly from 0 to ``mu p`` (IPC's mollifier ``f1(y) = 2 y / e - y^2 / e^2``), so a
            sticking point creeps by less than e per step. Default: 1e-3 times the mean
            boundary edge length. In dynamics, ``e = eps_v dt`` for a velocity tolerance
            ``eps_v``.
        default: the coefficient of the pairs of bodies a dict ``mu`` does not name.
        cell_tags: cell MeshTags of ``u``'s mesh: the keys of a dict ``mu`` are then pairs of
            cell tags instead of body indices, ``{(CARTILAGE, CARTILAGE): 0.01, (SKIN, SKIN):
            0.5}``: a (boundary triangle, tetrahedron) pair gets the coefficient of the tag of
            the triangle's cell and the tag of the tetrahedron, so regions of one body (skin
            and bone glued in one mesh) can have their own; untagged cells get ``default``.
        updates: fixed-point updates of the lagged quantities within a step, as IPC's: after
            a converged Newton solve the normal pressures, contact normals and quadrature
            points are taken again at the solution (the slip still measured from the step's
            start) and the step solved again, ``updates`` times. 0: lagged from the last
            converged step only.
    """

    def __init__(
        self,
        mu: float | dict[tuple[int, int], float],
        slip_tol: float | None = None,
        default: float = 0.0,
        cell_tags: typing.Any = None,
        updates: int = 0,
    ):
        self.default = _check_mu(default, "default")
        if cell_tags is not None:
            if not isinstance(mu, dict):
                raise ValueError(
                    "cell_tags name the keys of a dict mu={(tag_a, tag_b): value}; with one "
                    "coefficient for all pairs leave cell_tags out"
                )
            if getattr(cell_tags, "dim", None) != 3:
                raise ValueError(
                    f"cell_tags must be the cell MeshTags (dim 3) of the mesh, got {cell_tags!r}"
                )
        self.cell_tags = cell_tags
        if not (isinstance(updates, (int, np.integer)) and updates >= 0):
            raise ValueError(f"updates must be a whole number >= 0, got {updates!r}")
        self.updates = int(updates)
        if isinstance(mu, dict):
            table = {}
            for key, value in mu.items():
                if not (
                    isinstance(key, tuple)
                    and len(key) == 2
                    and all(isinstance(b, (int, np.integer)) and b >= 0 for b in key)
                ):
                    what = "cell tags" if cell_tags is not None else "body indices"
                    raise ValueError(f"the keys of mu must be pairs of {what} (a, b), got {key!r}")
                table[(min(key), max(key))] = _check_mu(value, f"mu[{key!r}]")
            self.mu: float | dict[tuple[int, int], float] = table
        else:
            self.mu = _check_mu(mu, "mu")
        if slip_tol is not None:
            slip_tol = float(slip_tol)
            if not (np.isfinite(slip_tol) and slip_tol > 0.0):
                raise ValueError(f"slip_tol must be a positive length, got {slip_tol}")
        self.slip_tol = slip_tol

    def __repr__(self) -> str:
        tags = "" if self.cell_tags is None else ", cell_tags=..."
        return (
            f"Coulomb(mu={self.mu!r}, slip_tol={self.slip_tol!r}, default={self.default!r}"
            f"{tags}, updates={self.updates})"
        )

    def pair_mu(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The coefficient of each pair ``(a[i], b[i])``: of body indices, or with
        ``cell_tags`` of cell tags (-1: untagged, ``default``)."""
        a, b = np.asarray(a), np.asarray(b)
        if not isinstance(self.mu, dict):
            return np.full(a.shape, self.mu, dtype=FLOAT)
        out = np.full(a.shape, self.default, dtype=FLOAT)
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        for (ka, kb), value in self.mu.items():
            out[(lo == ka) & (hi == kb)] = value
        return out


def local_cell_tags(mesh: typing.Any, cell_tags: typing.Any) -> np.ndarray:
    """The tag of every local cell, owned and ghost (-1 where none; collective: the owners'
    tags are sent to the ghosts, so tags given on the owned cells only are enough).

    Args:
        mesh: the mesh.
        cell_tags: cell MeshTags of ``mesh``.
    """
    imap = mesh.topology.index_map(3)
    n_owned, n_local = imap.size_local, imap.size_local + imap.num_ghosts
    indices, values = np.asarray(cell_tags.indices), np.asarray(cell_tags.values)
    vec = dolfinx.la.vector(imap, 1, dtype=np.float64)
    vec.array[:] = -1.0
    owned = indices < n_owned
    vec.array[indices[owned]] = values[owned]
    vec.scatter_forward()
    return np.rint(vec.array[:n_local]).astype(np.int64)


class _Reference(typing.NamedTuple):
    """The lagged data of a rank's friction pairs (see ``kernels.friction``)."""

    verts: np.ndarray  #: (np, 7) global vertex numbers
    xref: np.ndarray  #: (np, 7, 3) their reference coordinates
    qptr: np.ndarray  #: (np + 1,) each pair's points
    coef: np.ndarray  #: (nq, 7)
    normal: np.ndarray  #: (nq, 3)
    weight: np.ndarray  #: (nq,)
    area: np.ndarray  #: (nq,)


class FrictionMixin:
    """The friction part of :class:`~fenics_matdepth.ContactOperator` (its state: ``surface``,
    ``comm``, ``penalty``, the pair search and the cache of a state)."""

    friction: Coulomb | None
    slip_tol: float

    def _init_friction(self, friction: Coulomb | None) -> None:
        if friction is not None and not isinstance(friction, Coulomb):
            raise TypeError(f"friction must be fm.Coulomb(mu, slip_tol) or None, got {friction!r}")
        if friction is not None and self.integration != "area":
            raise ValueError("friction needs integration='area'")
        self.friction = friction
        self._friction_ref: _Reference | None = None
        self._friction_advanced: _Reference | None = None  # the lagged data of advance()
        self._friction_held: tuple[int, dict[str, np.ndarray]] | None = None
        self._friction_mark: tuple | None = None  # the stick/slip set of mark_stick_slip()
        self.slip_tol = 0.0
        self._friction_tri_tag: np.ndarray | None = None
        if friction is not None and friction.cell_tags is not None:
            mesh = self.u.function_space.mesh
            tags = local_cell_tags(mesh, friction.cell_tags)
            self._friction_tri_tag = tags[self.surface.tri_cell]
            self.surface.add_cell_field("tag", tags[: mesh.topology.index_map(3).size_local])
        if friction is not None:
            tol = friction.slip_tol
            self.slip_tol = float(
                SLIP_TOL_FRACTION * self.surface.mean_edge if tol is None else tol
            )
            self.advance()

    def contact_points(self, friction: bool = False) -> dict[str, np.ndarray]:
        """The quadrature points of this rank's intersection polygons at the last update where
        the normal traction is positive (see ``kernels.friction``; the points the friction
        is integrated at, and the contact fields' normal traction; area integration).

        Args:
            friction: weigh each point by its pair's friction coefficient (pairs with 0 get no
                points); else by 1.

        Returns:
            ``verts`` (np, 7): the global vertex numbers of every evaluated pair (triangle
            then tetrahedron), and per point
            ``pair`` (its row), ``coef`` (7: the triangle's barycentrics, then minus the
            tetrahedron's), ``normal`` (the unit contact normal, ``grad g`` over its length),
            ``weight`` (``w p`` times the coefficient: force) and ``area`` (``w``, L^2).
        """
        s = self.surface
        pa, pk = self._evaluated_pairs()
        verts = np.hstack((s.tri[pa], s.tets[pk]))
        glob = s.global_vertex[verts]
        scale = np.ones(pa.size, dtype=FLOAT)
        if friction and self._friction_tri_tag is not None:
            scale = self.friction.pair_mu(self._friction_tri_tag[pa], s.tet_fields["tag"][pk])
        elif friction:
            body = s.body_of_vertex
            scale = self.friction.pair_mu(body[glob[:, 0]], body[glob[:, 3]])
        stiffness = np.full(pa.size, self.penalty, dtype=FLOAT)
        offset = np.zeros((pa.size, 3), dtype=FLOAT)
        if self._pressure is not None:
            corner = self._pressure[glob[:, :3]]
            if self._pressure_width > 0.0:
                stiffness += corner.mean(axis=1) / self._pressure_width
            else:
                offset[:] = corner
        args = (s.x, s.kernel_depth, s.tri, s.kernel_tets, pa, pk, stiffness, offset, scale)
        nq = friction_reference(*args, False, *empty_reference())
        out = {
            "verts": glob,
            "pair": np.empty(nq, dtype=INDEX),
            "coef": np.empty((nq, 7), dtype=FLOAT),
            "normal": np.empty((nq, 3), dtype=FLOAT),
            "weight": np.empty(nq, dtype=FLOAT),
            "area": np.empty(nq, dtype=FLOAT),
        }
        friction_reference(*args, True, out["pair"], *(out[k] for k in _POINT_KEYS))
        return out

    def advance(self) -> None:
        """Make the current state of ``u`` the friction's reference (collective): the normal
        pressures, contact normals and quadrature points of the next step's friction are
        taken here, and its slip is measured from here. ``solve_load_steps`` and
        ``solve_time_steps`` call it after every converged step; call it after each converged
        step of a loop of your own (nothing happens without friction)."""
        if self.friction is None:
            return
        self.update()
        n_owned = self.surface.owned_dof_count() // 3
        self._friction_u_ref = self.u.x.array[: 3 * n_owned].reshape(-1, 3).copy()
        self._lag()
        self._friction_advanced = self._friction_ref

    def reset_lagged(self) -> None:
        """Go back to the lagged data taken at the last :meth:`advance` (undoing
        :meth:`update_lagged`; a retried step starts from them)."""
        if self._friction_ref is None or self._friction_ref is self._friction_advanced:
            return
        self._friction_ref = self._friction_advanced
        self._friction_held = None
        for key in [k for k in self._cache if k.startswith("friction")]:
            del self._cache[key]

    def update_lagged(self) -> None:
        """Take the friction's normal pressures, contact normals and quadrature points at the
        current state of ``u``, the slip still measured from the reference (collective): one
        fixed-point update within a step (``Coulomb(updates=k)`` has ``ContactProblem.solve``
        do it ``k`` times after converging, solving again after each)."""
        if self._friction_ref is None:
            return
        self.update()
        self._lag()

    def _lag(self) -> None:
        """The lagged data at the current update, the slip's reference from ``advance``."""
        s = self.surface
        pts = self.contact_points(friction=True)
        counts = np.bincount(pts["pair"], minlength=pts["verts"].shape[0])
        keep = counts > 0
        qptr = np.concatenate(([0], np.cumsum(counts[keep]))).astype(INDEX)
        xref = (s.X + s.pull(self._friction_u_ref))[s.held_index(pts["verts"][keep])]
        self._friction_ref = _Reference(
            pts["verts"][keep], xref, qptr, *(pts[k] for k in _POINT_KEYS)
        )
        self._friction_held = None
        for key in [k for k in self._cache if k.startswith("friction")]:
            del self._cache[key]

    # -- the potential at the current state ---------------------------------------------------

    def _friction_held_data(self) -> dict[str, np.ndarray]:
        """The reference pairs the rank holds all 7 vertices of, kept until the halo is
        rebuilt: ``rows`` (rows of the reference), ``verts`` (their vertices in the held
        numbering), ``xref`` and their points ``qptr``, ``coef``, ``normal``, ``weight``. A
        pair leaves only when its vertices left the halo (a step far longer than the halo
        margin)."""
        s, ref = self.surface, self._friction_ref
        if self._friction_held is None or self._friction_held[0] != s.refreshes:
            held = s.held_index(ref.verts)
            keep = np.all(held >= 0, axis=1)
            counts = np.diff(ref.qptr)
            pts = np.repeat(keep, counts)
            data = {
                "rows": np.flatnonzero(keep).astype(INDEX),
                "verts": np.ascontiguousarray(held[keep]),
                "xref": np.ascontiguousarray(ref.xref[keep]),
                "qptr": np.concatenate(([0], np.cumsum(counts[keep]))).astype(INDEX),
                "coef": np.ascontiguousarray(ref.coef[pts]),
                "normal": np.ascontiguousarray(ref.normal[pts]),
                "weight": np.ascontiguousarray(ref.weight[pts]),
                "area": ref.area[pts],
            }
            self._friction_held = (s.refreshes, data)
        return self._friction_held[1]

    def _friction_pass(self, want_hess: bool) -> dict[str, np.ndarray] | None:
        """The friction's per-pair energies, gradients and, with ``want_hess``, Hessians at the
        last update, kept until the next one (None without friction)."""
        if self._friction_ref is None:
            return None
        for key in ("friction_True", f"friction_{want_hess}"):
            if key in self._cache:
                return self._cache[key]
        d = self._friction_held_data()
        energy, grad, hess = friction_pairs(
            self.surface.x, d["verts"], d["xref"], d["qptr"], d["coef"], d["normal"],
            d["weight"], self.slip_tol, True, want_hess,
        )  # fmt: skip
        out = {"energy": energy, "grad": grad, "hess": hess, "verts": d["verts"]}
        self._cache[f"friction_{want_hess}"] = out
        return out

    def _friction_energy(self) -> float:
        """This rank's friction potential at the last update (0 without friction)."""
        r = self._friction_pass(False)
        return 0.0 if r is None else float(np.sum(r["energy"]))

    def _add_friction_residual(self, b: PETSc.Vec) -> None:
        """``b += dD/du`` (set, not yet assembled: the caller assembles ``b``)."""
        r = self._friction_pass(False)
        if r is None:
            return
        dofs, vals = assembly.gradient_array(self.surface, r["verts"], r["grad"])
        b.setValues(dofs.astype(PETSc.IntType), vals, addv=PETSc.InsertMode.ADD_VALUES)

    def _add_friction_lifting(self, b: PETSc.Vec, offset: np.ndarray) -> None:
        """``b += H_f[:, D] offset[D]``: the friction Hessian's share of the lifting, as
        ``add_lifting`` adds the normal contact's (collective; nothing without friction). The
        pair Hessians are evaluated only when a Dirichlet dof of a friction pair is not yet on
        its value (the first Newton iteration of a step that moves a body)."""
        if self._friction_ref is None:
            return
        assembly.add_lifting_pairs(
            self.surface, b, offset, lambda: self._friction_held_data()["verts"],
            lambda sel: self._friction_pass(True)["hess"][sel],
        )  # fmt: skip

    def _friction_positions(self) -> tuple[np.ndarray, bool, np.ndarray]:
        """Where the friction pairs' couplings lie in the pattern, and whether one lies outside
        it on some rank (collective), kept until the next update; and the friction's own
        blocks: ``(slot, outside, reached)``, ``reached`` the sorted pattern indices the pairs
        reach and ``slot`` (np, 7, 7) each coupling's row in it (-1 outside the pattern)."""
        if "friction_positions" not in self._cache:
            verts = self._friction_held_data()["verts"]
            pos, missing = assembly.coupling_positions(
                self.surface, self._pattern_in_held_numbering(), verts, self._pattern_transposed()
            )
            outside = bool(self.comm.allreduce(missing > 0, op=MPI.LOR))
            # the friction's blocks only (a few per pair), not a buffer of the whole pattern
            inside = pos >= 0
            reached, index = np.unique(pos[inside], return_inverse=True)
            slot = np.full(pos.shape, -1, dtype=INDEX)
            slot[inside] = index
            self._cache["friction_positions"] = (slot, outside, reached)
        return self._cache["friction_positions"]

    def _friction_outside_pattern(self) -> bool:
        """Whether a friction coupling lies outside the matrix pattern (collective)."""
        return self._friction_ref is not None and self._friction_positions()[1]

    def _add_friction_jacobian(self, A: PETSc.Mat) -> None:
        """``A += d2D/du2`` into the pattern (not assembled here); Dirichlet rows and columns
        left out."""
        if self._friction_ref is None:
            return
        slot, _, reached = self._friction_positions()
        d = self._friction_held_data()
        blocks = np.zeros((reached.size, 3, 3), dtype=FLOAT)
        # summed per point straight into the blocks: no (np, 21, 21) pair Hessians
        friction_blocks(
            self.surface.x, d["verts"], d["xref"], d["qptr"], d["coef"], d["normal"],
            d["weight"], self.slip_tol, slot, self.surface.bc, blocks,
        )  # fmt: skip
        keys = self._pattern_in_held_numbering()[reached]
        touched = np.ones(reached.size, dtype=bool)
        assembly.insert_blocks(A, self.surface, keys, blocks, touched)

    def _with_friction_keys(self, keys: np.ndarray) -> np.ndarray:
        """The pattern keys ``keys`` with the friction pairs' couplings (global numbering),
        for a new matrix (whose pattern the friction's kept positions are not in)."""
        self._cache.pop("friction_positions", None)
        if self._friction_ref is None:
            return keys
        friction = pairs.coupling_keys(self._friction_ref.verts, self.surface.num_vertices)
        return np.union1d(keys, friction)

    # -- diagnostics ----------------------------------------------------------------------------

    def fields(self) -> dict[str, typing.Any]:
        """The contact state at the last update as DOLFINx P1 Functions, for VTX/XDMF files
        and pyvista (collective; area integration; see :mod:`fenics_matdepth.contact.fields`):

        - ``pressure`` (F/L^2): the normal traction ``(eps g + p_aug) |grad g|`` averaged on
          each boundary vertex's hat function over the boundary triangles around it;
        - ``penetration`` (L): :meth:`~fenics_matdepth.ContactOperator.vertex_penetration`;
        - ``traction`` (F/L^2, vector): the contact traction on the surface, normal plus
          friction, averaged the same way;
        - ``slip`` (L, vector): the slip of the surface relative to the body it is in since the
          friction's reference (area-weighted over the friction points at the vertex; 0
          without friction);
        - ``status``: 0 open, 1 stick, 2 slip (a vertex slips where most of its friction
          points' slip exceeds the slip tolerance; frictionless contact always slips).

        Scalars live on a collapsed component space of ``u``'s space, vectors on it; each
        Function is named after its key.
        """
        if self.integration != "area":
            raise ValueError("contact fields need integration='area'")
        return contact_fields(self)

    def friction_diagnostics(self) -> dict[str, typing.Any]:
        """The friction of the step at the last update (collective; empty without friction;
        :meth:`~fenics_matdepth.ContactOperator.diagnostics` includes it, and so the records of
        the stepping loops).

        Returns:
            ``friction_dissipation``: ``sum_q c_q f1(y_q) y_q``, the work of the friction
            forces over the slip since the reference (F L, >= 0); ``stick_points`` and
            ``slip_points``: the quadrature points with slip below and above the slip
            tolerance; ``max_traction_ratio``: the largest ``|t_T| / (mu p)`` (at most 1).
        """
        if self._friction_ref is None:
            return {}
        slip, ratio, _, _ = self._friction_point_state()
        weight = self._friction_held_data()["weight"]
        sticking = int(np.count_nonzero(slip < self.slip_tol))
        comm = self.comm
        return {
            "friction_dissipation": comm.allreduce(float(np.sum(weight * ratio * slip))),
            "stick_points": comm.allreduce(sticking),
            "slip_points": comm.allreduce(int(slip.size) - sticking),
            "max_traction_ratio": comm.allreduce(
                float(ratio.max()) if ratio.size else 0.0, op=MPI.MAX
            ),
        }

    # -- the stick/slip set, for the linear solver ---------------------------------------------

    def _tangential_stiffness(self) -> np.ndarray:
        """Each held friction point's tangential stiffness across its slip at the last update,
        ``c f1(y) / y`` (``2 c / e`` at rest, ``c / y`` sliding: the Hessian's larger
        eigenvalue), kept until the next update."""
        if "friction_stiffness" not in self._cache:
            y = self._friction_point_state()[0]
            e = self.slip_tol
            per_weight = np.where(y < e, 2.0 / e - y / e**2, 1.0 / np.maximum(y, e))
            self._cache["friction_stiffness"] = self._friction_held_data()["weight"] * per_weight
        return self._cache["friction_stiffness"]

    def mark_stick_slip(self) -> None:
        """Remember the friction's tangential stiffness at the last update (nothing without
        friction): :meth:`stick_slip_change` measures from here. ``ContactProblem`` marks it
        at each Jacobian it factorises."""
        if self._friction_ref is None:
            return
        stiffness = self._tangential_stiffness()
        self._friction_mark = (self._friction_ref, self.surface.refreshes, stiffness)

    def stick_slip_change(self) -> float:
        """The share of the friction points whose tangential stiffness changed by more than a
        factor of 2 since the last :meth:`mark_stick_slip` (collective; 0 without friction).

        A point that switches between stick (stiffness ``2 c / e``) and slip (``c / y``)
        changes the Jacobian by a term of the rank of its slip directions, so this share says
        how far the Jacobian has moved from the one factorised at the mark (the linear
        solver's FRICTION_SWITCH_SHARE). Points whose stiffness stays below STIFFNESS_FLOOR
        times the normal penalty's (``k w``; the pressure about 0) do not count. On points
        other than the mark's (a new reference after :meth:`advance`, a new halo), or before
        any mark: 1 where some point's stiffness exceeds that floor, else 0.
        """
        if self._friction_ref is None:
            return 0.0
        stiffness = self._tangential_stiffness()
        floor = STIFFNESS_FLOOR * self.penalty * self._friction_held_data()["area"]
        mark = self._friction_mark
        same = (
            mark is not None and mark[0] is self._friction_ref and mark[1] == self.surface.refreshes
        )
        if not self.comm.allreduce(same, op=MPI.LAND):
            return float(self.comm.allreduce(bool(np.any(stiffness > floor)), op=MPI.LOR))
        marked = mark[2]
        changed = (np.maximum(stiffness, marked) > floor) & (
            (stiffness > 2.0 * marked) | (marked > 2.0 * stiffness)
        )
        counts = self.comm.allreduce(np.array([np.count_nonzero(changed), stiffness.size]))
        return float(counts[0] / max(counts[1], 1))

    def _friction_point_state(self) -> tuple[np.ndarray, ...]:
        """Per point of the held reference pairs: slip length, traction ratio, tangential
        force on the triangle's side, slip vector (see ``kernels.friction.friction_points``)."""
        d = self._friction_held_data()
        return friction_points(
            self.surface.x, d["verts"], d["xref"], d["qptr"], d["coef"], d["normal"],
            d["weight"], self.slip_tol,
        )  # fmt: skip

    def friction_points(self) -> dict[str, np.ndarray] | None:
        """The friction's quadrature points on this rank at the last update (the lagged ones,
        of the reference pairs whose vertices the rank holds; None without friction).

        Returns:
            A dict of per-point arrays; ``verts`` (nq, 7), the global vertex numbers of its pair
            (triangle then tetrahedron); ``coef`` (nq, 7), the slip's coefficients on them (the
            triangle's barycentrics, then minus the tetrahedron's); ``area`` (``w``, L^2);
            ``weight`` (``c = w mu p``, F); ``slip_length`` (``y``, L) and ``slip`` (nq, 3; the
            tangential slip of the triangle's point relative to the tetrahedron's since the
            reference, L); ``ratio`` (``f1(y) = |t_T| / (mu p)``); ``force`` (nq, 3; the tangential
            force on the triangle's side, F). A point sticks where ``slip_length`` is below
            ``slip_tol``.
        """
        if self._friction_ref is None:
            return None
        d = self._friction_held_data()
        y, ratio, force, vector = self._friction_point_state()
        rows = np.repeat(d["rows"], np.diff(d["qptr"]))
        return {
            "verts": self._friction_ref.verts[rows],
            "coef": d["coef"],
            "area": d["area"],
            "weight": d["weight"],
            "slip_length": y,
            "slip": vector,
            "ratio": ratio,
            "force": force,
        }


def solve_with_updates(
    contact: typing.Any, solve: typing.Callable[[bool], typing.Any], raise_on_failure: bool
) -> typing.Any:
    """``solve(raise_on_failure)``, then the friction's fixed-point updates of ``contact``'s
    ``Coulomb(updates=k)``: k times, :meth:`FrictionMixin.update_lagged` and ``solve`` again
    from the solution (collective). Each call starts from the lagged data of the last
    ``advance`` (a step retried after a failure does not inherit a failed attempt's). The
    result's iterations are those of all solves; a solve that fails ends the updates with its
    result."""
    friction = getattr(contact, "friction", None)
    if friction is None or not friction.updates:
        return solve(raise_on_failure)
    contact.reset_lagged()  # a retried step: from the reference's lagged data again
    result = solve(raise_on_failure)
    total = result.iterations
    for _ in range(friction.updates):
        if not result.converged:
            break
        contact.update_lagged()
        result = solve(raise_on_failure)
        total += result.iterations
    return dataclasses.replace(result, iterations=total)
