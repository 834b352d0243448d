"""The contact data a rank holds: vertices, tetrahedra, boundary triangles, material depth.

A :class:`ContactSurface` numbers the vertices it holds ``0 .. num_held - 1`` ("held"
numbering); ``global_vertex`` maps them to the global P1 block numbering of ``u``'s index
map, in which the dof of component c of vertex v is ``3 v + c``. The first held vertices are
the rank's local P1 blocks (owned, then ghosts, in dolfinx's local order); the vertices of
halo tetrahedra follow.

What a rank holds (docs/operator.md, "Distributed data"):

* the boundary triangles of the exterior facets it owns (each triangle is held by exactly
  one rank, which evaluates all its pairs) and, for collocation, the boundary vertices it
  owns;
* the tetrahedra it owns, plus a *halo*: the tetrahedra of other ranks whose boxes come within
  ``halo_margin`` of the boxes of its triangles (or collocation vertices). The halo is found
  from the ranks' bounding boxes (one allgather of 12 numbers per rank), then the triangle
  boxes go to the ranks whose tetrahedra they may meet and those ranks answer with the
  tetrahedra (global vertex numbers and the per-tetrahedron centroid depth);
* per held vertex: reference coordinates, depth and body label (pulled from the vertex's
  owner when the halo is built; further per-vertex fields travel the same way, see
  ``vertex_fields``), the displacement (pulled at every update) and the Dirichlet mask
  (pulled by :meth:`ContactSurface.set_bcs` and at each halo refresh).

The halo is rebuilt when some vertex has moved by more than ``(halo_margin - margin) / 2``
(in any coordinate) since the last build; until then it contains every tetrahedron whose box
overlaps the box of one of the rank's triangles inflated by ``margin``, so the pairs of the
update (margin 0) and of the sparsity pattern (``margin``) are all found. Per update, the
displacement goes point to point between the ranks sharing held vertices only.
"""

from __future__ import annotations

import warnings

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._mpi import allgather_rows, positions
from fenics_matdepth.boundary import (
    boundary_triangles,
    face_table,
    owned_boundary_triangle_dofs,
    p1_dof_coordinates,
)
from fenics_matdepth.contact.halo import VertexExchange, alltoallv_rows
from fenics_matdepth.depth import (
    DepthDeficiency,
    count_depth_deficient,
    depth_deficient_tets,
    distance_to_triangles,
)
from fenics_matdepth.geometry.boxes import element_boxes
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
        integration: ``"area"`` (the rank's contact elements are its boundary triangles) or
            ``"collocation"`` (its boundary vertices).
        margin: the pair-search margin of the sparsity pattern (L); default one tenth of the
            mean boundary edge length.
        split_deficient: set up the centroid split of depth-deficient tetrahedra (see
            :class:`~fenics_matdepth.ContactOperator`).
        warn_stacklevel: ``stacklevel`` of the :class:`DepthDeficiencyWarning`.

    Attributes:
        num_vertices: global number of vertices (P1 blocks).
        global_vertex: (num_held,) global vertex number of each held vertex.
        X: (num_held, 3) reference coordinates (L).
        x: (num_held, 3) current coordinates (L).
        depth: (num_held,) material depth (L).
        tets: (num_tets, 4) held tetrahedra (held numbering), the owned ones first.
        tri: (num_tri, 3) boundary triangles this rank owns (held numbering).
        nodes: held indices of the boundary vertices this rank owns (collocation).
        weight: (num_held,) collocation weight (one third of the adjacent boundary area) of
            the owned boundary vertices, 0 elsewhere (L^2).
        kernel_tets: the tetrahedra the pair kernels get (a fifth column, the index in
            ``kernel_depth`` of the centroid depth of a split deficient tetrahedron, or -1).
        kernel_depth: the depths the pair kernels get (held vertices, then centroids).
        body: (num_held,) body (connected component) of each held vertex.
        body_of_vertex: (num_vertices,) body of every vertex (global numbering, on every
            rank).
        bc: (3 num_held,) True on Dirichlet dofs.
        margin: the sparsity pattern's pair-search margin (L).
        halo_margin: the halo's margin (L): ``margin`` plus the mean boundary edge length.
        vertex_fields: per-vertex fields over the owned vertices (``X``, ``depth``,
            ``body``) carried to every rank that holds the vertex: a field added here is pulled
            into ``held_fields`` at every halo build (fields that change between builds go
            through :meth:`pull`).
        held_fields: the per-vertex fields of ``vertex_fields`` over the held vertices.
        tri_cell: (num_tri,) the local cell of each boundary triangle.
        tet_fields: per-tetrahedron fields over the held tetrahedra (rows of ``tets``), added
            with :meth:`add_cell_field` and carried into the halo at every build.
        mean_edge: mean boundary edge length (L), 0 without boundary triangles.
        refreshes: number of halo builds so far.
    """

    def __init__(
        self,
        u: dolfinx.fem.Function,
        depth: dolfinx.fem.Function,
        integration: str = "area",
        margin: float | None = None,
        split_deficient: bool = True,
        warn_stacklevel: int = 2,
    ):
        V = u.function_space
        mesh = V.mesh
        self.u = u
        self.integration = integration
        self.comm: MPI.Comm = mesh.comm
        comm = self.comm
        imap = V.dofmap.index_map
        self._n_owned = n_owned = imap.size_local
        self._n_local = n_local = imap.size_local + imap.num_ghosts
        self._local_to_global = imap.local_to_global(np.arange(n_local, dtype=np.int32)).astype(
            INDEX
        )
        self.num_vertices = int(imap.size_global)
        self._ranges = np.asarray(comm.allgather(int(imap.local_range[1])), dtype=INDEX)

        depth.x.scatter_forward()
        cells = np.asarray(V.dofmap.list, dtype=INDEX).reshape(-1, 4)
        dcells = np.asarray(depth.function_space.dofmap.list, dtype=INDEX).reshape(-1, 4)
        depth_block = np.empty(n_local, dtype=FLOAT)
        depth_block[cells.ravel()] = depth.x.array[dcells.ravel()]
        X_local = p1_dof_coordinates(V)
        self._owned_cells = owned_cells = cells[: mesh.topology.index_map(3).size_local]
        self.tri = owned_boundary_triangle_dofs(mesh, cells, X_local)
        self.tri_cell = np.ascontiguousarray(face_table(mesh).exterior[:, 0], dtype=INDEX)
        self._local_exchange = VertexExchange(comm, self._ranges, self._local_to_global, n_owned)

        # Collocation: owned boundary vertices with weight = 1/3 of the adjacent boundary area
        # in the reference configuration (kept constant, as the kernel's derivatives assume);
        # the areas of triangles owned elsewhere are summed onto the vertex's owner.
        area = _triangle_areas(X_local, self.tri)
        contrib = np.zeros(n_local, dtype=FLOAT)
        np.add.at(contrib, self.tri.ravel(), np.repeat(area / 3.0, 3))
        self._weight_owned = self._local_exchange.push_add(contrib)
        self.nodes = np.flatnonzero(self._weight_owned > 0.0).astype(INDEX)
        edges = X_local[self.tri[:, [1, 2, 0]]] - X_local[self.tri]
        total = comm.allreduce(float(np.linalg.norm(edges, axis=2).sum()))
        count = comm.allreduce(int(edges.shape[0] * 3))
        # mean boundary edge length (L), 0 without boundary triangles
        self.mean_edge = total / count if count else 0.0
        self.margin = float(0.1 * self.mean_edge if margin is None else margin)
        self.halo_margin = self.margin + self.mean_edge

        self.num_bodies, body_local = _bodies(
            comm, owned_cells, self._local_to_global, self._local_exchange
        )
        self.body_of_vertex = allgather_rows(comm, body_local[:n_owned])

        self._setup_deficient(
            mesh, owned_cells, depth_block, X_local, split_deficient, warn_stacklevel + 1
        )
        # per-vertex fields carried to the ranks that hold a vertex (owned rows): add a field
        # here to have it pulled at every halo build into ``held_fields``
        self.vertex_fields: dict[str, np.ndarray] = {
            "X": X_local[:n_owned],
            "depth": depth_block[:n_owned],
            "body": body_local[:n_owned],
        }
        self._bc_owned = np.zeros((n_owned, 3), dtype=bool)
        # per-owned-cell fields carried with the halo tetrahedra (see add_cell_field)
        self._cell_fields: dict[str, np.ndarray] = {}
        self.tet_fields: dict[str, np.ndarray] = {}
        self.refreshes = 0
        self._build_halo(X_local)  # at the reference configuration (the overlap check)
        self.x = self.X.copy()

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
        """Count the depth-deficient tetrahedra and compute the centroid depth of the owned
        ones that are split (``_aux_owned``, 0 for the others).

        A deficient tetrahedron (four vertices at depth 0) is split, inside the kernels, into
        four sub-tetrahedra around its centroid, which gets its exact reference distance to
        the exterior boundary. Without deficient tetrahedra (or with ``split=False``) the
        kernels get the plain arrays, and nothing changes.
        """
        self.split_deficient = bool(split)
        local = count_depth_deficient(owned_cells, depth_block)
        self.depth_deficiency = DepthDeficiency(
            self.comm.allreduce(local.deficient), self.comm.allreduce(local.boundary_adjacent)
        )
        self._aux_owned = np.zeros(owned_cells.shape[0], dtype=FLOAT)
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
        triangles = boundary_triangles(mesh)  # collective
        if centroids.shape[0]:
            self._aux_owned[mask] = distance_to_triangles(centroids, triangles)
        self.num_split_tets = self.comm.allreduce(int(np.count_nonzero(self._aux_owned > 0.0)))

    # -- the halo -------------------------------------------------------------------------

    def _query_boxes(self, x_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes of the rank's contact elements (triangles, or collocation vertices)."""
        if self.integration == "area":
            return element_boxes(x_local, self.tri)
        pts = np.ascontiguousarray(x_local[self.nodes])
        return pts, pts.copy()

    def _build_halo(self, x_local: np.ndarray) -> None:
        """Find the halo tetrahedra at the local vertex positions ``x_local`` (owned and
        ghost rows), then pull every held vertex's fields (collective)."""
        comm, m = self.comm, self.halo_margin
        n_owned = self._n_owned
        qlo, qhi = self._query_boxes(x_local)
        tlo, thi = element_boxes(x_local, self._owned_cells)
        mine = np.concatenate([_union(qlo, qhi), _union(tlo, thi)])
        boxes = allgather_rows(comm, mine[None, :])  # (size, 12): query box, tet box
        # my query boxes go to every other rank whose tetrahedra box they come within m of
        dest_list, row_list = [], []
        for s in range(comm.size):
            if s == comm.rank or not _overlap(boxes[comm.rank, :6], boxes[s, 6:], m):
                continue
            near = _rows_overlap(qlo, qhi, boxes[s, 6:9], boxes[s, 9:12], m)
            row_list.append(np.hstack((qlo[near], qhi[near])))
            dest_list.append(np.full(int(near.sum()), s, dtype=np.int32))
        rows = np.vstack(row_list) if row_list else np.empty((0, 6), dtype=FLOAT)
        dest = np.concatenate(dest_list) if dest_list else np.empty(0, dtype=np.int32)
        qboxes, source = alltoallv_rows(comm, rows, dest)
        # answer with my tetrahedra that come within m of a received box, once per asker
        if qboxes.shape[0] and self._owned_cells.shape[0]:
            tree = AABBTree(x_local, self._owned_cells)
            q, e = tree.query_boxes(qboxes[:, :3], qboxes[:, 3:], margin=m)
            key = np.unique(source[q].astype(INDEX) * self._owned_cells.shape[0] + e)
            ask, tet = key // self._owned_cells.shape[0], key % self._owned_cells.shape[0]
        else:
            ask = tet = np.empty(0, dtype=INDEX)
        halo_tets, _ = alltoallv_rows(
            comm, self._local_to_global[self._owned_cells[tet]], ask.astype(np.int32)
        )
        halo_aux, _ = alltoallv_rows(comm, self._aux_owned[tet], ask.astype(np.int32))
        self._halo_route = (tet, ask.astype(np.int32))
        for name in self._cell_fields:
            self._pull_cell_field(name)

        # held vertices: the local ones, then the halo tetrahedra's other vertices
        new = np.setdiff1d(halo_tets.ravel(), self._local_to_global)
        self.global_vertex = np.concatenate((self._local_to_global, new)).astype(INDEX)
        self._order = np.argsort(self.global_vertex, kind="stable")
        self._sorted = self.global_vertex[self._order]
        self._exchange = VertexExchange(comm, self._ranges, self.global_vertex, n_owned)
        self.held_fields: dict[str, np.ndarray] = {}
        for name, owned in self.vertex_fields.items():
            held = np.empty((self.num_held, *owned.shape[1:]), dtype=owned.dtype)
            self._exchange.pull(owned, held)
            self.held_fields[name] = held
        self.X, self.depth = self.held_fields["X"], self.held_fields["depth"]
        self.body = self.held_fields["body"]
        self.tets = np.ascontiguousarray(
            np.vstack((self._owned_cells, self.held_index(halo_tets).reshape(-1, 4)))
        ).astype(INDEX)
        self._num_halo_tets = int(halo_tets.shape[0])
        aux = np.concatenate((self._aux_owned, halo_aux))
        self.kernel_tets, self.kernel_depth = self.tets, self.depth
        if self.split_deficient and self.depth_deficiency.deficient:
            split = np.flatnonzero(aux > 0.0)
            column = np.full(self.tets.shape[0], -1, dtype=INDEX)
            column[split] = self.num_held + np.arange(split.size, dtype=INDEX)
            self.kernel_tets = np.ascontiguousarray(np.hstack((self.tets, column[:, None])))
            self.kernel_depth = np.concatenate((self.depth, aux[split]))
        self.weight = np.zeros(self.num_held, dtype=FLOAT)
        self.weight[:n_owned] = self._weight_owned
        self._pull_bcs()
        self.refreshes += 1
        self._x_at_build = x_local[:n_owned].copy()
        self.x = np.empty((self.num_held, 3), dtype=FLOAT)
        self.tree: AABBTree | None = None

    def add_cell_field(self, name: str, owned: np.ndarray) -> None:
        """Carry a per-cell field of the owned cells to the held tetrahedra (collective):
        ``tet_fields[name]`` holds it for every row of ``tets``, now and after every halo
        build.

        Args:
            name: the field's key in ``tet_fields``.
            owned: (num owned cells, ...) its values on the owned cells.
        """
        owned = np.ascontiguousarray(owned)
        if owned.shape[0] != self._owned_cells.shape[0]:
            raise ValueError(
                f"cell field {name!r}: {owned.shape[0]} rows for "
                f"{self._owned_cells.shape[0]} owned cells"
            )
        self._cell_fields[name] = owned
        self._pull_cell_field(name)

    def _pull_cell_field(self, name: str) -> None:
        tet, ask = self._halo_route
        owned = self._cell_fields[name]
        halo, _ = alltoallv_rows(self.comm, owned[tet], ask)
        self.tet_fields[name] = np.concatenate((owned, halo))

    # -- state ----------------------------------------------------------------------------

    @property
    def num_held(self) -> int:
        """Number of vertices this rank holds."""
        return int(self.global_vertex.size)

    def held_index(self, vertices: np.ndarray) -> np.ndarray:
        """Held index of each global vertex number (-1 where this rank does not hold it)."""
        pos = positions(self._sorted, np.asarray(vertices, dtype=INDEX))
        index = np.full(pos.shape, -1, dtype=INDEX)
        found = pos >= 0
        index[found] = self._order[pos[found]]
        return index

    def pull(self, owned: np.ndarray) -> np.ndarray:
        """A per-vertex field over the held vertices, from its owned rows (collective: a
        neighbour exchange, for fields that change between halo builds, such as ``u``).

        Args:
            owned: (n_owned, ...) the field's values at this rank's owned vertices.

        Returns:
            (num_held, ...) its values at the held vertices.
        """
        owned = np.asarray(owned)
        held = np.empty((self.num_held, *owned.shape[1:]), dtype=owned.dtype)
        self._exchange.pull(owned, held)
        return held

    def _pull_displacement(self) -> np.ndarray:
        return self.pull(self.u.x.array[: 3 * self._n_owned].reshape(-1, 3))

    def update(self) -> None:
        """Current coordinates of the held vertices from ``u`` (a neighbour exchange); the halo
        is rebuilt when a vertex has moved too far since it was built; refit the tree
        (collective)."""
        x = self.X + self._pull_displacement()
        moved = np.abs(x[: self._n_owned] - self._x_at_build)
        moved = self.comm.allreduce(float(moved.max()) if moved.size else 0.0, op=MPI.MAX)
        if 2.0 * moved + self.margin > self.halo_margin:
            self._build_halo(x[: self._n_local])
            x = self.X + self._pull_displacement()
        self.x = x
        if self.tets.shape[0] == 0:
            self.tree = None
        elif self.tree is None:
            self.tree = AABBTree(self.x, self.tets)
        else:
            self.tree.refit(self.x)
            if self.tree.needs_rebuild():
                self.tree.rebuild(self.x)

    def _pull_bcs(self) -> None:
        held = np.empty((self.num_held, 3), dtype=bool)
        self._exchange.pull(self._bc_owned, held)
        self.bc = held.reshape(-1)

    def set_bcs(self, mask_owned: np.ndarray) -> None:
        """The Dirichlet mask of the owned dofs (3 per owned vertex); held from it (collective)."""
        self._bc_owned = np.asarray(mask_owned, dtype=bool).reshape(-1, 3)
        self._pull_bcs()

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
        n = self._n_owned
        return {
            "X": allgather_rows(self.comm, self.X[:n]),
            "x": allgather_rows(self.comm, self.x[:n]),
            "depth": allgather_rows(self.comm, self.depth[:n]),
            "bc": allgather_rows(self.comm, self.bc[: 3 * n]),
            "tets": allgather_rows(self.comm, self._local_to_global[self._owned_cells]),
        }

    def sizes(self) -> dict[str, int]:
        """What this rank holds and sends (counts on this rank).

        ``held_vertices``, ``held_tets`` (owned plus halo), ``halo_tets``, ``neighbours``
        (ranks exchanged with per update), ``update_bytes_sent`` (displacement bytes this
        rank sends per update) and ``halo_refreshes``.
        """
        return {
            "held_vertices": self.num_held,
            "held_tets": int(self.tets.shape[0]),
            "halo_tets": self._num_halo_tets,
            "neighbours": self._exchange.neighbours,
            "update_bytes_sent": 24 * self._exchange.sent_vertices,
            "halo_refreshes": self.refreshes,
        }


def _union(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The box (lo xyz, hi xyz) around boxes; an empty box (inf, -inf) for none."""
    if lo.shape[0] == 0:
        return np.concatenate((np.full(3, np.inf), np.full(3, -np.inf)))
    return np.concatenate((lo.min(axis=0), hi.max(axis=0)))


def _overlap(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    """Whether box a (6,) inflated by margin overlaps box b (6,) (closed boxes)."""
    return bool(np.all(a[:3] - margin <= b[3:]) and np.all(b[:3] <= a[3:] + margin))


def _rows_overlap(
    lo: np.ndarray, hi: np.ndarray, blo: np.ndarray, bhi: np.ndarray, margin: float
) -> np.ndarray:
    """Which boxes (lo, hi) inflated by margin overlap the box (blo, bhi)."""
    return np.all(lo - margin <= bhi, axis=1) & np.all(blo <= hi + margin, axis=1)


def _triangle_areas(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Area of each triangle ``tri`` (rows of vertex indices into ``x``)."""
    return 0.5 * np.linalg.norm(
        np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]), axis=1
    )


def _bodies(
    comm: MPI.Comm, cells: np.ndarray, local_to_global: np.ndarray, exchange: VertexExchange
) -> tuple[int, np.ndarray]:
    """Body (connected component of the whole mesh) of every local vertex (collective).

    Components of the owned cells on each rank, linked across ranks through the ghosts (a
    ghost's component meets its owner's), then the small graph of components gathered.
    Bodies are numbered in the order of their smallest global vertex, as in a serial labelling.

    Returns:
        (number of bodies, (num local,) body of each local vertex).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_local, n_owned = local_to_global.size, exchange.n_owned
    a = np.repeat(cells[:, 0], 3)
    b = cells[:, 1:].ravel()
    graph = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(n_local, n_local))
    if n_local:
        n_comp, label = connected_components(graph, directed=False)
    else:
        n_comp, label = 0, np.empty(0, dtype=np.int32)
    first = comm.exscan(int(n_comp)) or 0
    comp = label.astype(INDEX) + first
    owner_comp = np.empty(n_local, dtype=INDEX)
    exchange.pull(comp[:n_owned], owner_comp)
    links = np.unique(np.stack((comp[n_owned:], owner_comp[n_owned:]), axis=1), axis=0)
    links = allgather_rows(comm, links.reshape(-1, 2))
    smallest = np.full(n_comp, np.iinfo(INDEX).max, dtype=INDEX)
    np.minimum.at(smallest, label, local_to_global)
    smallest = allgather_rows(comm, smallest)
    total = smallest.size
    cgraph = coo_matrix(
        (np.ones(links.shape[0], dtype=np.int8), (links[:, 0], links[:, 1])), shape=(total, total)
    )
    n_bodies, body_of_comp = connected_components(cgraph, directed=False)
    body_min = np.full(n_bodies, np.iinfo(INDEX).max, dtype=INDEX)
    np.minimum.at(body_min, body_of_comp, smallest)
    rank = np.empty(n_bodies, dtype=INDEX)
    rank[np.argsort(body_min, kind="stable")] = np.arange(n_bodies, dtype=INDEX)
    return int(n_bodies), rank[body_of_comp[comp]]
