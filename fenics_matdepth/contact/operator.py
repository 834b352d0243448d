"""ContactOperator: the material-depth contact energy of a P1 displacement, in PETSc terms.

The operator owns the contact geometry of one dolfinx mesh (all bodies in one mesh): the
exterior boundary triangles, the tetrahedra, the material depth of every vertex, and an AABB
tree over the tetrahedra that is refitted at every :meth:`ContactOperator.update`. It adds the
exact first and second derivatives of the contact energy into dolfinx-assembled PETSc vectors
and matrices.

Parallel strategy (first version, correct on any partition): every rank holds the global
vertex coordinates, depths and tetrahedra (gathered once; the displacement is gathered at each
update), and handles the boundary triangles whose facets it owns against every tetrahedron.
Contributions to dofs owned by other ranks go through PETSc's off-process assembly (VecSetValues
/ MatSetValues stashes). Memory per rank therefore grows with the global mesh size.

Numbering: the vertices of the operator are the *blocks* of the P1 vector space of ``u``,
in the global block numbering of its index map; the dof of component c of vertex v is
``3 v + c`` (PETSc global numbering of dolfinx vectors and matrices).
"""

from __future__ import annotations

import typing
import warnings

from mpi4py import MPI
from mpi4py.util.dtlib import from_numpy_dtype
from petsc4py import PETSc

import dolfinx
import numpy as np

from fenics_matdepth._checks import check_contact_mesh, check_contact_state
from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._jit import announces_compilation
from fenics_matdepth.contact.kernels import (
    _accumulate_vertex_blocks,
    _area_pairs_active,
    _area_pairs_augmented_active,
    _area_pairs_max_depth,
    _area_pairs_pressure_moments,
    _blocks_to_csr,
    _collocation_pairs,
    _count_missing_couplings,
)
from fenics_matdepth.depth import (
    DepthDeficiency,
    _p1_dof_coordinates,
    boundary_triangles,
    count_depth_deficient,
    depth_deficient_tets,
    distance_to_triangles,
    owned_exterior_facets,
)
from fenics_matdepth.geometry.bvh import AABBTree, element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.clip import _near_pairs

__all__ = ["ContactOperator", "DepthDeficiencyWarning", "propose_penalty"]

_INTEGRATIONS = ("area", "collocation")


class DepthDeficiencyWarning(UserWarning):
    """Some tetrahedra have material depth 0 at all four vertices (see
    :func:`fenics_matdepth.depth.depth_deficient_tets`)."""


def _allgather_rows(comm: MPI.Comm, local: np.ndarray) -> np.ndarray:
    """Concatenate the ranks' row blocks of ``local`` (rank order) on every rank."""
    local = np.ascontiguousarray(local)
    width = int(np.prod(local.shape[1:], dtype=np.int64))
    counts = np.asarray(comm.allgather(local.shape[0] * width), dtype=np.int64)
    out = np.empty(int(counts.sum()), dtype=local.dtype)
    comm.Allgatherv(local.reshape(-1), [out, counts, from_numpy_dtype(local.dtype)])
    return out.reshape((-1, *local.shape[1:]))


class ContactOperator:
    """Material-depth penalty contact energy of the displacement ``u`` and its derivatives.

    Args:
        u: displacement, a Function on a P1 (Lagrange degree 1) vector space of dimension 3 on an
            affine tetrahedral mesh (length L).
        depth: material depth, a P1 scalar Function on the same mesh (from
            :func:`fenics_matdepth.material_depth`) (L).
        penalty: penalty parameter eps (pressure / length, F/L^3). Contact pressure is eps * g.
        integration: ``"area"`` (exact integration over triangle-tetrahedron intersection
            polygons, the paper's method) or ``"collocation"`` (boundary vertices only, the
            baseline that chatters).
        margin: inflation (L) of the triangle boxes used to find candidate pairs for the matrix
            sparsity pattern, so that the pattern survives motion of up to about ``margin``;
            default: one tenth of the mean boundary edge length.
        split_deficient: give every depth-deficient tetrahedron (all four vertices at depth 0,
            so depth 0 everywhere inside: layers one element thick, edges and corners of
            coarse meshes) an interior depth by evaluating it as four sub-tetrahedra around
            its centroid, which gets its exact distance to the boundary (default). The mesh
            and the function spaces are untouched; ``False`` keeps the plain P1 depth, through
            which a surface entering such a tetrahedron passes without force.
        allow_reference_overlap: accept bodies that overlap in the reference configuration
            (by default a ``ValueError``: their material depth is wrong).

    Typical use in a Newton loop: ``update()`` at each iterate, then ``add_residual(b)`` and
    ``add_jacobian(A, bcs)`` after dolfinx has assembled the bulk terms into ``b`` and ``A``;
    ``A`` must come from :meth:`create_matrix`.
    """

    @announces_compilation("the contact operator (pair search, overlap check)")
    def __init__(
        self,
        u: dolfinx.fem.Function,
        depth: dolfinx.fem.Function,
        penalty: float,
        integration: typing.Literal["area", "collocation"] = "area",
        margin: float | None = None,
        split_deficient: bool = True,
        allow_reference_overlap: bool = False,
    ):
        V = u.function_space
        mesh = V.mesh
        check_contact_mesh(mesh)
        if V.dofmap.index_map_bs != 3 or V.ufl_element().degree != 1:
            raise ValueError(
                "ContactOperator needs u on a P1 vector space of dimension 3, e.g. "
                'functionspace(mesh, ("Lagrange", 1, (3,)))'
            )
        if depth.function_space.mesh is not mesh or depth.function_space.dofmap.index_map_bs != 1:
            raise ValueError("depth must be a P1 scalar Function on the mesh of u")
        if integration not in _INTEGRATIONS:
            raise ValueError(f"integration must be one of {_INTEGRATIONS}, got {integration!r}")
        penalty = float(penalty)
        if not np.isfinite(penalty) or penalty <= 0.0:
            raise ValueError(f"penalty must be a positive number (pressure/length), got {penalty}")
        self.u = u
        self.penalty = penalty
        self.integration = integration
        self.comm: MPI.Comm = mesh.comm

        imap = V.dofmap.index_map
        self._n_owned = imap.size_local
        n_local = imap.size_local + imap.num_ghosts
        self._local_to_global = imap.local_to_global(np.arange(n_local, dtype=np.int32)).astype(
            INDEX
        )
        self._offset = imap.local_range[0]
        self.num_vertices = imap.size_global

        # Global reference coordinates and depths (owned blocks in rank order = global order).
        depth.x.scatter_forward()
        cells = np.asarray(V.dofmap.list, dtype=INDEX).reshape(-1, 4)
        dcells = np.asarray(depth.function_space.dofmap.list, dtype=INDEX).reshape(-1, 4)
        depth_block = np.empty(n_local, dtype=FLOAT)
        depth_block[cells.ravel()] = depth.x.array[dcells.ravel()]
        X_local = _p1_dof_coordinates(V)
        self._X = _allgather_rows(self.comm, X_local[: self._n_owned])
        self._depth = _allgather_rows(self.comm, depth_block[: self._n_owned])
        n_cells_owned = mesh.topology.index_map(3).size_local
        self._tets = _allgather_rows(self.comm, self._local_to_global[cells[:n_cells_owned]])

        # Owned exterior facets -> triangles: the three vertices of the facet's (single) cell
        # other than the opposite one (the reference tetrahedron's facet i is opposite vertex i).
        facets = owned_exterior_facets(mesh)
        mesh.topology.create_connectivity(3, 2)
        f2c = mesh.topology.connectivity(2, 3)
        c2f = np.asarray(mesh.topology.connectivity(3, 2).array).reshape(-1, 4)
        cell = np.asarray(f2c.array)[np.asarray(f2c.offsets)[facets]]
        opposite = np.argmax(c2f[cell] == facets[:, None], axis=1)
        others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
        tri = cells[cell[:, None], others[opposite]]
        self._tri = self._local_to_global[tri]
        # Collocation: owned boundary vertices with weight = 1/3 of the adjacent boundary area
        # in the reference configuration (kept constant, as the kernel's derivatives assume).
        all_tri = _allgather_rows(self.comm, self._tri)
        area = 0.5 * np.linalg.norm(
            np.cross(
                self._X[all_tri[:, 1]] - self._X[all_tri[:, 0]],
                self._X[all_tri[:, 2]] - self._X[all_tri[:, 0]],
            ),
            axis=1,
        )
        self._weight = np.zeros(self.num_vertices, dtype=FLOAT)
        np.add.at(self._weight, all_tri.ravel(), np.repeat(area / 3.0, 3))
        owned = np.arange(self._offset, self._offset + self._n_owned, dtype=INDEX)
        self._nodes = owned[self._weight[owned] > 0.0]

        if margin is None:
            edges = self._X[all_tri[:, [1, 2, 0]]] - self._X[all_tri]
            margin = 0.1 * float(np.mean(np.linalg.norm(edges, axis=2))) if all_tri.size else 0.0
        self.margin = float(margin)

        # Bodies: connected components of the mesh (vertices linked through tetrahedra).
        self.num_bodies, self.body_of_vertex = _connected_components(self.num_vertices, self._tets)

        self._setup_deficient(mesh, cells[:n_cells_owned], depth_block, X_local, split_deficient)

        self._bc_mask = np.zeros(3 * self.num_vertices, dtype=bool)
        self._x = self._X.copy()
        self._u_last: np.ndarray | None = None
        self._tree = AABBTree(self._x, self._tets)
        self._pair_a = np.empty(0, dtype=INDEX)
        self._pair_k = np.empty(0, dtype=INDEX)
        self._pattern_keys: np.ndarray | None = None
        self._cache: dict[str, typing.Any] = {}
        self._pressure: np.ndarray | None = None  # augmented Lagrangian, see set_pressure
        self.update()
        check_contact_state(self, allow_reference_overlap)

    def _setup_deficient(
        self,
        mesh: dolfinx.mesh.Mesh,
        owned_cells: np.ndarray,
        depth_block: np.ndarray,
        X_local: np.ndarray,
        split: bool,
    ) -> None:
        """Count the depth-deficient tetrahedra and set up the kernels' tetrahedron and depth
        arrays (``_kernel_tets``, ``_kernel_depth``).

        A deficient tetrahedron (four vertices at depth 0) is split, inside the kernels, into
        four sub-tetrahedra around its centroid; the fifth column of ``_kernel_tets`` gives the
        index in ``_kernel_depth`` of the centroid's depth, its exact reference distance to
        the exterior boundary (-1: not split). Without deficient tetrahedra (or with
        ``split=False``) the kernels get the plain arrays, and nothing changes.
        """
        self.split_deficient = bool(split)
        self.depth_deficiency: DepthDeficiency = count_depth_deficient(self._tets, self._depth)
        self._kernel_tets = self._tets
        self._kernel_depth = self._depth
        self.num_split_tets = 0
        if self.depth_deficiency.deficient and self.comm.rank == 0:
            n, m = self.depth_deficiency
            what = (
                "each is split around its centroid inside the contact operator, which is given "
                "its exact distance to the boundary (split_deficient=True); meshing thin layers "
                "with two or more elements across avoids the split"
                if split
                else "surfaces entering them feel no contact force (split_deficient=False): "
                "use split_deficient=True (the default) or mesh thin layers with two or more "
                "elements across"
            )
            warnings.warn(
                f"{n} of the {m} tetrahedra touching the boundary ({n / m:.1%}) have all four "
                f"vertices on the boundary, hence material depth 0 everywhere; {what}",
                DepthDeficiencyWarning,
                stacklevel=4,  # _setup_deficient, __init__, the compile-notice wrapper
            )
        if not (split and self.depth_deficiency.deficient):
            return
        # each rank computes the centroid depths of the deficient tetrahedra it owns
        mask = depth_deficient_tets(owned_cells, depth_block)
        centroids = X_local[owned_cells[mask]].mean(axis=1)
        aux = np.zeros(owned_cells.shape[0], dtype=FLOAT)
        triangles = boundary_triangles(mesh)  # collective
        if centroids.shape[0]:
            aux[mask] = distance_to_triangles(centroids, triangles)
        aux = _allgather_rows(self.comm, aux)  # global cell order, as self._tets
        split_cells = np.flatnonzero(aux > 0.0)
        self.num_split_tets = int(split_cells.size)
        column = np.full(self._tets.shape[0], -1, dtype=INDEX)
        column[split_cells] = self.num_vertices + np.arange(split_cells.size, dtype=INDEX)
        self._kernel_tets = np.ascontiguousarray(np.hstack((self._tets, column[:, None])))
        self._kernel_depth = np.concatenate((self._depth, aux[split_cells]))

    # -- geometry -------------------------------------------------------------------------

    def _current_coordinates(self) -> np.ndarray:
        u_owned = self.u.x.array[: 3 * self._n_owned].reshape(-1, 3)
        return self._X + _allgather_rows(self.comm, u_owned)

    def _candidate_pairs(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """(contact element, tetrahedron) pairs whose current boxes overlap (this rank's)."""
        if self.integration == "area":
            lo, hi = element_boxes(self._x, self._tri)
            qa, qk = self._tree.query_boxes(lo, hi, margin=margin)
            return exclude_shared_vertex_pairs(self._tri, self._tets, qa, qk)
        pts = self._x[self._nodes]
        qa, qk = self._tree.query_boxes(pts, pts, margin=margin)
        keep = np.all(self._tets[qk] != self._nodes[qa, None], axis=1)
        return qa[keep], qk[keep]

    @announces_compilation("the pair search")
    def update(self) -> None:
        """Refit the tree to the current ``u`` and find the candidate pairs (collective).

        Nothing is recomputed when ``u`` has not changed since the last update (a line search
        evaluating the energy and then the residual at the same point pays once).
        """
        u_owned = self.u.x.array[: 3 * self._n_owned]
        bad = not np.all(np.isfinite(u_owned))
        if self.comm.allreduce(bad, op=MPI.LOR):
            raise FloatingPointError(
                "the displacement contains NaN or inf: the previous solve diverged; reduce "
                "the load step or the penalty"
            )
        same = self._u_last is not None and np.array_equal(u_owned, self._u_last)
        if self.comm.allreduce(same, op=MPI.LAND):
            return
        self._u_last = u_owned.copy()
        self._x = self._current_coordinates()
        self._tree.refit(self._x)
        if self._tree.needs_rebuild():
            self._tree.rebuild(self._x)
        self._pair_a, self._pair_k = self._candidate_pairs(0.0)
        self._cache.clear()

    # -- pair contributions ---------------------------------------------------------------

    @announces_compilation("the contact pair integrals")
    def _evaluate(self, want_grad: bool, want_hess: bool) -> dict[str, np.ndarray]:
        want_grad = want_grad or want_hess  # the kernels compute the Hessian with the gradient
        key = f"{want_grad}{want_hess}"
        # a pass that computed more serves a request for less
        for have in ("TrueTrue", "TrueFalse", "FalseFalse")[: 3 - want_grad - want_hess]:
            if have in self._cache:
                return self._cache[have]
        if self.integration == "area":
            # the kernel arrays carry the split of depth-deficient tetrahedra; each pair
            # still comes out over its 7 original vertices
            if self._pressure is None:
                active, energy, grad, hess = _area_pairs_active(
                    self._x, self._kernel_depth, self._tri, self._kernel_tets, self._pair_a,
                    self._pair_k, self.penalty, want_grad, want_hess,
                )  # fmt: skip
            else:
                active, energy, grad, hess = _area_pairs_augmented_active(
                    self._x, self._kernel_depth, self._tri, self._kernel_tets, self._pair_a,
                    self._pair_k, self.penalty, self._pressure, want_grad, want_hess,
                )  # fmt: skip
            verts = np.hstack((self._tri[self._pair_a[active]], self._tets[self._pair_k[active]]))
        else:
            energy, grad, hess = _collocation_pairs(
                self._x, self._kernel_depth, self._weight, self._kernel_tets,
                self._nodes[self._pair_a], self._pair_k, self.penalty, want_grad, want_hess,
            )  # fmt: skip
            verts = np.hstack((self._nodes[self._pair_a, None], self._tets[self._pair_k]))
        dofs = (3 * verts[:, :, None] + np.arange(3)).reshape(verts.shape[0], 3 * verts.shape[1])
        out = {"energy": energy, "grad": grad, "hess": hess, "dofs": dofs, "verts": verts}
        if self.integration == "area":
            out["active"] = active
        self._cache[key] = out
        return out

    def energy(self) -> float:
        """Contact energy at the last :meth:`update` (collective; energy unit F L)."""
        return self.comm.allreduce(float(np.sum(self._evaluate(False, False)["energy"])))

    def gradient_array(self) -> tuple[np.ndarray, np.ndarray]:
        """This rank's gradient contributions: (global dofs, values), duplicates summed."""
        r = self._evaluate(True, False)
        dofs, vals = r["dofs"].ravel(), r["grad"].ravel()
        # summed over the global dofs (linear in the mesh, no sort of the pair entries)
        n = 3 * self.num_vertices
        reached = np.zeros(n, dtype=bool)
        reached[dofs] = True
        uniq = np.flatnonzero(reached).astype(INDEX)
        return uniq, np.bincount(dofs, weights=vals, minlength=n)[uniq]

    def add_residual(self, b: PETSc.Vec) -> None:
        """``b += dE/du`` for a dolfinx-assembled residual vector (collective).

        Call after ``assemble_vector`` and before ``apply_lifting``/``ghostUpdate``/``set_bc``
        (or anywhere before ``set_bc``): contributions to other ranks' dofs are sent with
        PETSc's off-process assembly here.
        """
        dofs, vals = self.gradient_array()
        b.setValues(dofs.astype(PETSc.IntType), vals, addv=PETSc.InsertMode.ADD_VALUES)
        b.assemblyBegin()
        b.assemblyEnd()

    def set_bcs(self, bcs: typing.Sequence[dolfinx.fem.DirichletBC]) -> None:
        """Remember the Dirichlet dofs, whose rows and columns :meth:`add_jacobian` skips."""
        mask_local = np.zeros(3 * self._n_owned, dtype=bool)
        for bc in bcs:
            dofs, n_owned = bc.dof_indices()
            dofs = np.asarray(dofs[:n_owned], dtype=INDEX)
            mask_local[dofs[dofs < 3 * self._n_owned]] = True
        self._bc_mask = _allgather_rows(self.comm, mask_local)

    def hessian_coo(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This rank's Hessian contributions (rows, cols, values), duplicates summed, sorted.

        Entries in a Dirichlet row or column (see :meth:`set_bcs`) are left out. Independent of
        any matrix pattern (a sort of all pair entries); :meth:`add_jacobian` sums into the
        pattern of :meth:`create_matrix` instead.
        """
        r = self._evaluate(False, True)
        dofs = r["dofs"]
        n = dofs.shape[1]
        rows = np.repeat(dofs, n, axis=1).ravel()
        cols = np.tile(dofs, (1, n)).ravel()
        vals = r["hess"].reshape(-1)
        keep = ~(self._bc_mask[rows] | self._bc_mask[cols])
        key = rows[keep] * (3 * self.num_vertices) + cols[keep]
        uniq, inv = np.unique(key, return_inverse=True)
        sums = np.bincount(inv, weights=vals[keep], minlength=uniq.size)
        return uniq // (3 * self.num_vertices), uniq % (3 * self.num_vertices), sums

    @announces_compilation("the contact Jacobian assembly")
    def add_jacobian(
        self, A: PETSc.Mat, bcs: typing.Sequence[dolfinx.fem.DirichletBC] | None = None
    ) -> None:
        """``A += d2E/du2`` for a dolfinx-assembled matrix from :meth:`create_matrix`.

        Rows and columns of Dirichlet dofs are left as dolfinx set them. Call after dolfinx's
        ``assemble_matrix`` and its ``A.assemble()``; this method assembles ``A`` again
        (collective).

        Raises:
            RuntimeError: if a contact coupling falls outside the sparsity pattern of ``A``
                (the bodies moved further than the pattern's margin since ``create_matrix``).
        """
        if bcs is not None:
            self.set_bcs(bcs)
        r = self._evaluate(False, True)
        # Pair Hessians are summed by numba into 3 x 3 blocks of the pattern's vertex couplings
        # (a binary search per coupling, no sort of the pairs' 441 entries each), and only the
        # blocks that pairs reach are inserted.
        keys = self._pattern_keys if self._pattern_keys is not None else np.empty(0, INDEX)
        blocks = np.zeros((keys.size, 3, 3), dtype=FLOAT)
        touched = np.zeros(keys.size, dtype=bool)
        missing = _accumulate_vertex_blocks(
            keys, self.num_vertices, r["verts"], r["hess"], self._bc_mask, blocks, touched
        )
        if "pattern_missing" not in self._cache:
            self._cache["pattern_missing"] = bool(self.comm.allreduce(missing > 0, op=MPI.LOR))
        if self._cache["pattern_missing"]:
            raise RuntimeError(
                "contact couplings fall outside the matrix sparsity pattern: call "
                "create_matrix(a) again (ContactProblem does this automatically), or build the "
                "operator with a larger margin"
            )
        rows, indptr, cols, vals = _blocks_to_csr(keys, self.num_vertices, blocks, touched)
        if rows.size:
            A.setValuesIJV(
                indptr.astype(PETSc.IntType), cols.astype(PETSc.IntType), vals,
                addv=PETSc.InsertMode.ADD_VALUES, rowmap=rows.astype(PETSc.IntType),
            )  # fmt: skip
        A.assemble()

    # -- sparsity ---------------------------------------------------------------------------

    def _vertex_coupling_keys(self, verts: np.ndarray) -> np.ndarray:
        n = verts.shape[1]
        a = np.repeat(verts, n, axis=1).ravel()
        b = np.tile(verts, (1, n)).ravel()
        return np.unique(a * self.num_vertices + b)

    def pattern_needs_rebuild(self) -> bool:
        """Whether a current contact coupling lies outside the pattern (collective).

        The answer is kept until the next :meth:`update` or :meth:`create_matrix`: a solver
        that asks before assembling does not pay again inside :meth:`add_jacobian`.
        """
        if "pattern_missing" in self._cache:
            return self._cache["pattern_missing"]
        verts = self._evaluate(False, False)["verts"]
        if self._pattern_keys is None:
            missing = verts.size > 0
        else:
            missing = _count_missing_couplings(self._pattern_keys, self.num_vertices, verts) > 0
        self._cache["pattern_missing"] = bool(self.comm.allreduce(missing, op=MPI.LOR))
        return self._cache["pattern_missing"]

    @announces_compilation("the contact sparsity pattern")
    def create_matrix(self, a: dolfinx.fem.Form) -> PETSc.Mat:
        """A PETSc matrix holding the bulk form's pattern plus the contact couplings.

        The contact part comes from the candidate pairs of triangle boxes inflated by
        ``margin``, so the pattern survives moderate motion; :meth:`add_jacobian` tells when
        it no longer does. Insertion into the returned matrix never mallocs (collective).

        Args:
            a: the compiled bulk Jacobian form (``dolfinx.fem.form``).
        """
        from dolfinx.fem.petsc import assemble_matrix, create_matrix

        bulk = create_matrix(a)
        assemble_matrix(bulk, a)
        bulk.assemble()
        indptr, indices, _ = bulk.getValuesCSR()
        r0, r1 = bulk.getOwnershipRange()
        bulk_rows = np.repeat(np.arange(r0, r1, dtype=INDEX), np.diff(indptr))

        pa, pk = self._candidate_pairs(self.margin)
        if self.integration == "area":
            # boxes inflated by the margin overlap for far more pairs than come within the
            # margin (7x more than the active pairs on a flat interface); the couplings of the
            # others would be explicit zeros that the factorisation treats as nonzeros
            pa, pk = _near_pairs(self._x, self._tri, self._tets, pa, pk, self.margin)
            verts = np.hstack((self._tri[pa], self._tets[pk]))
        else:
            verts = np.hstack((self._nodes[pa, None], self._tets[pk]))
        self._pattern_keys = self._vertex_coupling_keys(verts)
        self._cache.pop("pattern_missing", None)
        vi = self._pattern_keys // self.num_vertices
        vj = self._pattern_keys % self.num_vertices
        # Each vertex coupling (vi, vj) is a 3 x 3 block of dofs.
        rows = np.repeat(3 * vi[:, None] + np.arange(3), 3, axis=1).ravel()
        cols = np.tile(3 * vj[:, None] + np.arange(3), (1, 3)).ravel()

        # Send each contact entry to the rank owning its row.
        ranges = np.asarray(self.comm.allgather(r1), dtype=INDEX)
        owner = np.searchsorted(ranges, rows, side="right")
        order = np.argsort(owner, kind="stable")
        counts = np.bincount(owner, minlength=self.comm.size)
        splits = np.cumsum(counts)[:-1]
        send = [
            np.vstack(p)
            for p in zip(np.split(rows[order], splits), np.split(cols[order], splits), strict=True)
        ]
        recv = self.comm.alltoall(send)
        all_rows = np.concatenate([bulk_rows] + [m[0] for m in recv])
        all_cols = np.concatenate([indices.astype(INDEX)] + [m[1] for m in recv])
        n_global = 3 * self.num_vertices
        key = np.unique(all_rows * n_global + all_cols)
        rows_u, cols_u = key // n_global, key % n_global
        csr_ptr = np.searchsorted(rows_u, np.arange(r0, r1 + 1)).astype(PETSc.IntType)

        A = PETSc.Mat().create(comm=self.comm)
        A.setSizes(bulk.getSizes(), bsize=3)
        A.setType(PETSc.Mat.Type.AIJ)
        A.setPreallocationCSR((csr_ptr, cols_u.astype(PETSc.IntType)))
        A.setLGMap(*bulk.getLGMap())
        A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        A.setOption(PETSc.Mat.Option.KEEP_NONZERO_PATTERN, True)
        bulk.destroy()
        return A

    # -- augmented Lagrangian (nodal contact pressures; driver: fenics_matdepth.augmented) ---

    @property
    def pressure(self) -> np.ndarray | None:
        """Nodal contact pressures (global vertex numbering, pressure units), or ``None``."""
        return self._pressure

    def set_pressure(self, pressure: np.ndarray | None) -> None:
        """Set the nodal contact pressures of the augmented Lagrangian (or ``None``: plain
        penalty).

        The energy becomes ``sum over pairs of int_{T cap K} (p g + (eps/2) g^2) dA``, ``p``
        interpolated linearly on each penetrating boundary triangle from its vertices' values
        (see ``_area_pairs_augmented``); its derivatives are exact at fixed pressures.

        Args:
            pressure: ``(num_vertices,)`` values >= 0, the same on every rank (only boundary
                vertices matter).
        """
        if pressure is not None:
            pressure = np.ascontiguousarray(pressure, dtype=FLOAT)
            if pressure.shape != (self.num_vertices,):
                raise ValueError(
                    f"pressure must have shape ({self.num_vertices},), got {pressure.shape}"
                )
            if self.integration != "area":
                raise ValueError("nodal contact pressures need integration='area'")
        self._pressure = pressure
        self._cache.clear()

    def pressure_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """Per vertex, ``int mu_i g dA`` (L^3) and ``int mu_i dA`` (L^2) over every intersection
        polygon of the boundary triangles around vertex i (``mu_i`` its hat function on the
        triangle), at the last update: the Uzawa update's data (collective; global vertex
        numbering, the same on every rank)."""
        r = self._evaluate(False, False)
        active = r["active"]
        gmom, amom = _area_pairs_pressure_moments(
            self._x, self._kernel_depth, self._tri, self._kernel_tets, self._pair_a[active],
            self._pair_k[active],
        )  # fmt: skip
        verts = self._tri[self._pair_a[active]].ravel()
        n = self.num_vertices
        local = np.vstack(
            (
                np.bincount(verts, weights=gmom.ravel(), minlength=n),
                np.bincount(verts, weights=amom.ravel(), minlength=n),
            )
        )
        total = np.empty_like(local)
        self.comm.Allreduce(local, total, op=MPI.SUM)
        return total[0], total[1]

    # -- diagnostics ------------------------------------------------------------------------

    def max_penetration(self) -> float:
        """Largest material depth reached by the contact surface at the last update (L).

        Area integration: the maximum of ``g_K`` over every intersection polygon; collocation:
        the maximum of ``g_K(x_a)`` over the boundary vertices inside a tetrahedron
        (collective).
        """
        r = self._evaluate(False, False)
        if self.integration == "area":
            active = r["active"]
            g = _area_pairs_max_depth(
                self._x, self._kernel_depth, self._tri, self._kernel_tets, self._pair_a[active],
                self._pair_k[active],
            )  # fmt: skip
        else:
            w = self._weight[self._nodes[self._pair_a]]
            g = np.sqrt(2.0 * r["energy"] / (self.penalty * w))
        local = float(g.max()) if g.size else 0.0
        return self.comm.allreduce(local, op=MPI.MAX)

    def force_resultants(self) -> np.ndarray:
        """Net contact force on each body, ``(num_bodies, 3)`` (force units; collective).

        A body is a connected component of the mesh (``body_of_vertex``). The force on a
        vertex is ``-dE/dx``; contact between two bodies gives them opposite resultants, and
        self-contact contributes nothing to its body's resultant.
        """
        dofs, vals = self.gradient_array()
        out = np.zeros((self.num_bodies, 3), dtype=FLOAT)
        np.add.at(out, (self.body_of_vertex[dofs // 3], dofs % 3), -vals)
        return self.comm.allreduce(out)

    def diagnostics(self) -> dict[str, typing.Any]:
        """Contact state at the last update (collective).

        Returns:
            ``candidate_pairs`` and ``active_pairs`` (global counts; active = non-zero
            energy), ``energy`` (F L), ``max_penetration`` (L, see :meth:`max_penetration`),
            ``force_resultant``, the net contact force on each body, ``(num_bodies, 3)``, and
            the depth-deficient tetrahedra (all four vertices at depth 0): their number
            ``deficient_tets``, the number of tetrahedra touching the boundary
            ``boundary_adjacent_tets``, the ratio ``deficient_fraction`` and ``split_tets``,
            how many the operator splits around their centroid (see ``split_deficient``).
        """
        r = self._evaluate(True, False)
        return {
            "deficient_tets": self.depth_deficiency.deficient,
            "boundary_adjacent_tets": self.depth_deficiency.boundary_adjacent,
            "deficient_fraction": self.depth_deficiency.fraction,
            "split_tets": self.num_split_tets,
            "candidate_pairs": self.comm.allreduce(int(self._pair_a.size)),
            "active_pairs": self.comm.allreduce(int(np.count_nonzero(r["energy"] > 0.0))),
            "energy": self.energy(),
            "max_penetration": self.max_penetration(),
            "force_resultant": self.force_resultants(),
        }


def _connected_components(num_vertices: int, tets: np.ndarray) -> tuple[int, np.ndarray]:
    """Label the vertices by connected component of the tetrahedral mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = np.repeat(tets[:, 0], 3)
    b = tets[:, 1:].ravel()
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(num_vertices,) * 2)
    n, labels = connected_components(graph, directed=False)
    return int(n), labels.astype(INDEX)


def propose_penalty(
    mesh: dolfinx.mesh.Mesh, modulus: float, factor: float = 10.0, h: float | None = None
) -> float:
    """A penalty parameter eps (pressure / length) from the stiffest modulus and the mesh size.

    ``eps = factor * modulus / h``. Where one surface enters a body, a contact pressure p
    penetrates ``g = p / eps = (p / modulus) h / factor``: ``1 / factor`` of the compression that
    pressure causes across one element of size ``h``. Between two deformable bodies both
    surfaces enter the other body and both terms carry the load, so the overlap is about
    ``p / (2 eps)`` (the patch test in ``tests/test_validation.py`` checks this). At the edges
    and corners of the contact zone the other body's depth falls to 0 at its side faces, so
    only one surface pushes there and the overlap rises, within about one element of the
    edge, towards ``p / eps``: measured under a block on a larger block (soft penalty,
    ``tests/test_thin_layers.py``), 0.47 p/eps inside the footprint, 0.58-0.62 p/eps at its
    edge vertices and 0.60-0.65 p/eps at its corners (without the centroid split of
    depth-deficient tetrahedra, up to 1.17 p/eps on the sides where the mesh has them). A
    stiffer penalty adds the elastic stress concentration at the edges on top. The contact
    stiffness of a surface vertex (about ``eps h^2``) is ``factor`` times the stiffness of its
    element (about ``modulus h``). Larger factors reduce penetration but worsen conditioning;
    10 to 100 suits the Newton solver with a direct linear solver.

    Args:
        mesh: the tetrahedral mesh of the bodies.
        modulus: the stiffest small-strain modulus of the materials in contact (pressure), e.g.
            ``materials.small_strain_moduli(...).stiffest`` or Young's modulus.
        factor: the ratio above (dimensionless).
        h: mesh size (L); default: the median edge length of the exterior boundary triangles,
            the elements that meet in contact.

    Returns:
        The proposed penalty (collective).
    """
    from fenics_matdepth.depth import boundary_triangles

    modulus, factor = float(modulus), float(factor)
    if not (np.isfinite(modulus) and modulus > 0.0 and np.isfinite(factor) and factor > 0.0):
        raise ValueError(
            f"modulus and factor must be positive numbers, got modulus={modulus}, factor={factor}"
        )
    if h is None:
        x = boundary_triangles(mesh)  # gathered on every rank
        if x.shape[0] == 0:
            raise ValueError("the mesh has no exterior boundary triangles")
        h = float(np.median(np.linalg.norm(x[:, [1, 2, 0]] - x, axis=2)))
    return factor * modulus / float(h)
