"""The contact data a rank holds: vertices, tetrahedra, boundary triangles, material depth.

A :class:`ContactSurface` numbers the vertices it holds ``0 .. num_held - 1`` ("held"
numbering); ``global_vertex`` maps them to the global P1 block numbering of ``u``'s index
map, in which the dof of component c of vertex v is ``3 v + c``. The boundary triangles it
holds are the exterior facets this rank owns (each triangle is held by exactly one rank); the
tetrahedra are every tetrahedron the rank's triangles can meet. Per-vertex data (reference
and current coordinates, depth, Dirichlet mask, body label) are arrays over the held
vertices.

This version holds the whole mesh on every rank: the reference coordinates, depths and
tetrahedra are gathered once, the displacement at every :meth:`ContactSurface.update`.
"""

from __future__ import annotations

import warnings

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._mpi import allgather_rows
from fenics_matdepth.boundary import (
    boundary_triangles,
    owned_boundary_triangle_dofs,
    p1_dof_coordinates,
)
from fenics_matdepth.depth import (
    DepthDeficiency,
    count_depth_deficient,
    depth_deficient_tets,
    distance_to_triangles,
)
from fenics_matdepth.geometry.bvh import AABBTree

__all__ = ["ContactSurface", "DepthDeficiencyWarning"]


class DepthDeficiencyWarning(UserWarning):
    """Some tetrahedra have material depth 0 at all four vertices (see
    :func:`fenics_matdepth.depth.depth_deficient_tets`)."""


class ContactSurface:
    """The vertices, tetrahedra and boundary triangles this rank holds for contact.

    Args:
        u: displacement, P1 vector Function (dimension 3).
        depth: material depth, P1 scalar Function on the same mesh.
        split_deficient: set up the centroid split of depth-deficient tetrahedra (see
            :class:`~fenics_matdepth.ContactOperator`).
        warn_stacklevel: ``stacklevel`` of the :class:`DepthDeficiencyWarning`.

    Attributes:
        num_vertices: global number of vertices (P1 blocks).
        global_vertex: (num_held,) global vertex number of each held vertex.
        X: (num_held, 3) reference coordinates; x: current coordinates (L).
        depth: (num_held,) material depth (L).
        tets: (num_tets, 4) held tetrahedra (held numbering).
        tri: (num_tri, 3) boundary triangles this rank owns (held numbering).
        nodes: held indices of the boundary vertices this rank owns (collocation).
        weight: (num_held,) collocation weight (one third of the adjacent boundary area) of
            the owned boundary vertices, 0 elsewhere (L^2).
        kernel_tets, kernel_depth: the tetrahedra and depths the pair kernels get (a fifth
            column and centroid depths for split deficient tetrahedra).
        body: (num_held,) body (connected component) of each held vertex.
        bc: (3 num_held,) True on Dirichlet dofs.
    """

    def __init__(
        self,
        u: dolfinx.fem.Function,
        depth: dolfinx.fem.Function,
        split_deficient: bool,
        warn_stacklevel: int = 2,
    ):
        V = u.function_space
        mesh = V.mesh
        self.u = u
        self.comm: MPI.Comm = mesh.comm
        imap = V.dofmap.index_map
        self._n_owned = imap.size_local
        n_local = imap.size_local + imap.num_ghosts
        self._local_to_global = imap.local_to_global(np.arange(n_local, dtype=np.int32)).astype(
            INDEX
        )
        self._offset = imap.local_range[0]
        self.num_vertices = int(imap.size_global)

        depth.x.scatter_forward()
        cells = np.asarray(V.dofmap.list, dtype=INDEX).reshape(-1, 4)
        dcells = np.asarray(depth.function_space.dofmap.list, dtype=INDEX).reshape(-1, 4)
        depth_block = np.empty(n_local, dtype=FLOAT)
        depth_block[cells.ravel()] = depth.x.array[dcells.ravel()]
        X_local = p1_dof_coordinates(V)
        n_cells_owned = mesh.topology.index_map(3).size_local
        owned_cells = cells[:n_cells_owned]

        self.global_vertex = np.arange(self.num_vertices, dtype=INDEX)
        self.X = allgather_rows(self.comm, X_local[: self._n_owned])
        self.depth = allgather_rows(self.comm, depth_block[: self._n_owned])
        self.tets = allgather_rows(self.comm, self._local_to_global[owned_cells])
        self.tri = self._local_to_global[owned_boundary_triangle_dofs(mesh, cells)]

        # Collocation: owned boundary vertices with weight = 1/3 of the adjacent boundary area
        # in the reference configuration (kept constant, as the kernel's derivatives assume).
        all_tri = allgather_rows(self.comm, self.tri)
        area = _triangle_areas(self.X, all_tri)
        self.weight = np.zeros(self.num_vertices, dtype=FLOAT)
        np.add.at(self.weight, all_tri.ravel(), np.repeat(area / 3.0, 3))
        owned = np.arange(self._offset, self._offset + self._n_owned, dtype=INDEX)
        self.nodes = owned[self.weight[owned] > 0.0]
        edges = self.X[all_tri[:, [1, 2, 0]]] - self.X[all_tri]
        #: mean boundary edge length (L), 0 without boundary triangles
        self.mean_edge = float(np.mean(np.linalg.norm(edges, axis=2))) if all_tri.size else 0.0

        self.num_bodies, self.body_of_vertex = _connected_components(self.num_vertices, self.tets)
        self.body = self.body_of_vertex

        self._setup_deficient(
            mesh, owned_cells, depth_block, X_local, split_deficient, warn_stacklevel + 1
        )
        self._bc_owned = np.zeros(3 * self._n_owned, dtype=bool)
        self.bc = np.zeros(3 * self.num_vertices, dtype=bool)
        self.x = self.X.copy()
        self.tree = AABBTree(self.x, self.tets)

    # -- set-up ---------------------------------------------------------------------------

    def _setup_deficient(
        self,
        mesh: dolfinx.mesh.Mesh,
        owned_cells: np.ndarray,
        depth_block: np.ndarray,
        X_local: np.ndarray,
        split: bool,
        stacklevel: int,
    ) -> None:
        """Count the depth-deficient tetrahedra and set up ``kernel_tets``, ``kernel_depth``.

        A deficient tetrahedron (four vertices at depth 0) is split, inside the kernels, into
        four sub-tetrahedra around its centroid; the fifth column of ``kernel_tets`` gives the
        index in ``kernel_depth`` of the centroid's depth, its exact reference distance to
        the exterior boundary (-1: not split). Without deficient tetrahedra (or with
        ``split=False``) the kernels get the plain arrays, and nothing changes.
        """
        self.split_deficient = bool(split)
        local = count_depth_deficient(owned_cells, depth_block)
        self.depth_deficiency = DepthDeficiency(
            self.comm.allreduce(local.deficient), self.comm.allreduce(local.boundary_adjacent)
        )
        self.kernel_tets = self.tets
        self.kernel_depth = self.depth
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
                stacklevel=stacklevel,
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
        aux = allgather_rows(self.comm, aux)  # global cell order, as self.tets
        split_cells = np.flatnonzero(aux > 0.0)
        self.num_split_tets = int(split_cells.size)
        column = np.full(self.tets.shape[0], -1, dtype=INDEX)
        column[split_cells] = self.num_vertices + np.arange(split_cells.size, dtype=INDEX)
        self.kernel_tets = np.ascontiguousarray(np.hstack((self.tets, column[:, None])))
        self.kernel_depth = np.concatenate((self.depth, aux[split_cells]))

    # -- state ----------------------------------------------------------------------------

    @property
    def num_held(self) -> int:
        """Number of vertices this rank holds."""
        return int(self.global_vertex.size)

    def held_index(self, vertices: np.ndarray) -> np.ndarray:
        """Held index of each global vertex number (-1 where this rank does not hold it)."""
        return np.asarray(vertices, dtype=INDEX).copy()

    def update(self) -> None:
        """Current coordinates of the held vertices from ``u``; refit the tree (collective)."""
        u_owned = self.u.x.array[: 3 * self._n_owned].reshape(-1, 3)
        self.x = self.X + allgather_rows(self.comm, u_owned)
        self.tree.refit(self.x)
        if self.tree.needs_rebuild():
            self.tree.rebuild(self.x)

    def set_bcs(self, mask_owned: np.ndarray) -> None:
        """The Dirichlet mask of the owned dofs (3 per owned vertex); held from it (collective)."""
        self._bc_owned = np.asarray(mask_owned, dtype=bool)
        self.bc = allgather_rows(self.comm, self._bc_owned)

    def owned_dof_count(self) -> int:
        """Number of owned dofs of ``u`` (3 per owned vertex)."""
        return 3 * self._n_owned

    def gathered(self) -> dict[str, np.ndarray]:
        """The whole model in global numbering, on every rank (collective; for tests and
        small-model inspection only: memory grows with the global mesh).

        Returns:
            ``X``, ``x`` (num_vertices, 3), ``depth`` (num_vertices,), ``bc`` (3
            num_vertices,) and ``tets`` (global tetrahedra, global vertex numbers).
        """
        return {
            "X": self.X.copy(),
            "x": self.x.copy(),
            "depth": self.depth.copy(),
            "bc": self.bc.copy(),
            "tets": self.tets.copy(),
        }

    def sizes(self) -> dict[str, int]:
        """What this rank holds: ``held_vertices``, ``held_tets`` (counts on this rank)."""
        return {"held_vertices": self.num_held, "held_tets": int(self.tets.shape[0])}


def _triangle_areas(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Area of each triangle ``tri`` (rows of vertex indices into ``x``)."""
    return 0.5 * np.linalg.norm(
        np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]), axis=1
    )


def _connected_components(num_vertices: int, tets: np.ndarray) -> tuple[int, np.ndarray]:
    """Label the vertices by connected component of the tetrahedral mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = np.repeat(tets[:, 0], 3)
    b = tets[:, 1:].ravel()
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(num_vertices,) * 2)
    n, labels = connected_components(graph, directed=False)
    return int(n), labels.astype(INDEX)
