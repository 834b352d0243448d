"""Mesh and boundary extraction shared by the material depth and the contact operator.

What a rank reads off a dolfinx mesh and its P1 spaces: the exterior faces it owns, their
triangles (as coordinates, gathered, for the distance to the boundary; or as local P1 dofs,
for contact), and the exact coordinates of the P1 dofs; :func:`check_mesh` tells whether a mesh
is one the package handles (affine tetrahedra in 3D), and :mod:`fenics_matdepth.mesh_checks`
checks its quality and its boundary on top.

The faces are found by :func:`~fenics_matdepth.boundary.face_table`, from the cells' vertices
alone, not by DOLFINx's facet entities: creating those (``create_entities(2)``) took 7.3 s of
the 11.3 s of the material depth of a 1M-vertex box, the face table 1.1 s
(``docs/spatial.md``).
"""

from __future__ import annotations

import typing
import weakref

from mpi4py import MPI

import dolfinx
import numpy as np
from numba import njit

from fenics_matdepth._compat import geometry_cmap, geometry_dofmap
from fenics_matdepth._constants import FLOAT, INDEX

__all__ = [
    "FaceTable",
    "boundary_triangles",
    "check_mesh",
    "face_table",
    "global_face_vertices",
    "owned_boundary_triangle_dofs",
    "owned_exterior_facets",
    "p1_dof_coordinates",
]


def check_mesh(mesh: dolfinx.mesh.Mesh) -> None:
    """The mesh must be a dolfinx mesh of affine (straight-sided) tetrahedra in 3D.

    Raises:
        TypeError: if ``mesh`` is not a ``dolfinx.mesh.Mesh``.
        ValueError: for other cells, another geometric dimension or curved geometry.
    """
    if not isinstance(mesh, dolfinx.mesh.Mesh):
        raise TypeError(
            f"expected a dolfinx.mesh.Mesh, got {type(mesh).__name__}: pass the mesh itself "
            "(e.g. u.function_space.mesh)"
        )
    cell_type = mesh.topology.cell_type
    if cell_type != dolfinx.mesh.CellType.tetrahedron:
        raise ValueError(
            f"material-depth contact needs a tetrahedral mesh, got {cell_type.name} cells: mesh "
            "the bodies with tetrahedra (e.g. create_box(..., CellType.tetrahedron) or gmsh 3D)"
        )
    if mesh.geometry.dim != 3:
        raise ValueError(
            f"material-depth contact needs a 3D geometry, got gdim={mesh.geometry.dim}: create "
            "the mesh with three coordinates per vertex"
        )
    degree = geometry_cmap(mesh).degree
    if degree != 1:
        raise ValueError(
            f"material-depth contact needs affine (degree-1) geometry, got a degree-{degree} "
            "coordinate element: generate the mesh with straight-sided tetrahedra "
            "(gmsh: model.mesh.setOrder(1))"
        )


#: The vertices of the reference tetrahedron's face i (the face opposite vertex i).
FACE_VERTICES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.int64)


@njit(cache=True)
def _face_neighbours(c2v, num_vertices):
    """Match the faces of the cells ``c2v`` (n, 4) that have the same three vertices.

    Returns ``neighbour`` (n, 4), ``4 c' + i'`` for the cell c' whose face i' is face i
    (opposite vertex i) of cell c, -1 where no other cell has that face, and the number of
    faces met by more than two cells (each such face leaves one of its cells unmatched).

    The faces are bucketed by their smallest vertex (a counting sort, two linear passes) and
    matched within each bucket, which holds a few dozen faces in a tetrahedral mesh.
    """
    n = c2v.shape[0]
    start = np.zeros(num_vertices + 1, np.int64)
    for c in range(n):
        for i in range(4):
            lo = num_vertices
            for k in range(4):
                if k != i and c2v[c, k] < lo:
                    lo = c2v[c, k]
            start[lo + 1] += 1
    for v in range(num_vertices):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    key = np.empty(4 * n, np.int64)  # the two larger vertices, as one number
    code = np.empty(4 * n, np.int64)  # 4 c + i
    for c in range(n):
        for i in range(4):
            a, b, d = c2v[c, (i + 1) % 4], c2v[c, (i + 2) % 4], c2v[c, (i + 3) % 4]
            if a > b:
                a, b = b, a
            if b > d:
                b, d = d, b
            if a > b:
                a, b = b, a
            slot = fill[a]
            fill[a] += 1
            key[slot] = b * num_vertices + d
            code[slot] = 4 * c + i
    neighbour = np.full((n, 4), -1, np.int64)
    overshared = 0
    for v in range(num_vertices):
        for j in range(start[v], start[v + 1]):
            for k in range(j + 1, start[v + 1]):
                if key[k] != key[j]:
                    continue
                cj, ck = code[j], code[k]
                if neighbour[cj // 4, cj % 4] >= 0 or neighbour[ck // 4, ck % 4] >= 0:
                    overshared += 1
                    continue
                neighbour[cj // 4, cj % 4] = ck
                neighbour[ck // 4, ck % 4] = cj
    return neighbour, overshared


class FaceTable(typing.NamedTuple):
    """The faces of a rank's tetrahedra (see :func:`~fenics_matdepth.boundary.face_table`).

    Attributes:
        cell_vertices: (num local cells, 4) local topology vertices of every local cell
            (owned, then ghost), in the reference vertex order.
        neighbour: (num local cells, 4) ``4 c' + i'`` for the local cell c' whose face i' is
            face i (opposite vertex i) of cell c; -1 where no other local cell has it.
        exterior: (m, 2) ``(cell, i)`` of the exterior faces this rank owns: face i of owned
            cell ``cell``, which no other cell of the whole mesh has.
        overshared: the number of faces met by more than two local cells (a broken mesh).
    """

    cell_vertices: np.ndarray
    neighbour: np.ndarray
    exterior: np.ndarray
    overshared: int


_FACE_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _exterior_faces(mesh: dolfinx.mesh.Mesh, c2v: np.ndarray, neighbour: np.ndarray):
    """(cell, i) of the faces of owned cells that no cell of the whole mesh shares (collective).

    A face of an owned cell with no local neighbour is either exterior or, when the cell
    across it is on another rank and not a ghost here (``GhostMode.none``), a face between
    ranks; the latter are the faces that another rank also has without a local neighbour.
    They are found by gathering those faces' global vertex triples, which are few beside the
    exterior faces themselves.
    """
    num_owned = mesh.topology.index_map(3).size_local
    cell, face = np.nonzero(neighbour[:num_owned] < 0)
    candidates = np.stack((cell, face), axis=1).astype(np.int64)
    comm = mesh.comm
    if comm.size == 1:
        return candidates
    from fenics_matdepth._mpi import allgather_rows

    keys = np.sort(global_face_vertices(mesh, c2v, candidates), axis=1)
    gathered = allgather_rows(comm, keys)
    rows, counts = np.unique(gathered, axis=0, return_counts=True)
    shared = rows[counts > 1]
    if shared.shape[0] == 0:
        return candidates
    dtype = np.dtype([("a", np.int64), ("b", np.int64), ("c", np.int64)])
    between = np.isin(
        np.ascontiguousarray(keys).view(dtype).ravel(),
        np.ascontiguousarray(shared).view(dtype).ravel(),
    )
    return candidates[~between]


def global_face_vertices(
    mesh: dolfinx.mesh.Mesh, cell_vertices: np.ndarray, faces: np.ndarray
) -> np.ndarray:
    """(m, 3) global topology vertices of the faces ``faces`` (m, 2) = (local cell, i), in
    the cell's vertex order; ``cell_vertices`` as in :class:`FaceTable`."""
    cell, face = faces.T
    local = cell_vertices[cell[:, None], FACE_VERTICES[face]]
    glob = mesh.topology.index_map(0).local_to_global(local.ravel().astype(np.int32))
    return np.asarray(glob, dtype=np.int64).reshape(-1, 3)


def face_table(mesh: dolfinx.mesh.Mesh) -> FaceTable:
    """The face neighbours and owned exterior faces of a tetrahedral mesh (collective).

    Computed from the cells' vertices (one numba pass, no DOLFINx facet entities) once per
    mesh and kept with it; the topology of a dolfinx mesh does not change.
    """
    table = _FACE_TABLES.get(mesh)
    if table is not None:
        return table
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(0)
    c2v = np.asarray(mesh.topology.connectivity(tdim, 0).array, dtype=np.int64).reshape(-1, 4)
    neighbour, overshared = _face_neighbours(c2v, imap.size_local + imap.num_ghosts)
    exterior = _exterior_faces(mesh, c2v, neighbour)
    table = FaceTable(c2v, neighbour, exterior, int(overshared))
    _FACE_TABLES[mesh] = table
    return table


def owned_exterior_facets(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Local indices of the exterior facets (one cell in the whole mesh) this rank owns.

    Every exterior facet is owned by exactly one rank, so each boundary triangle is handled
    once across the ranks. These are DOLFINx facet entities (created here if the mesh has
    none yet), for facet tags and boundary conditions; the package itself uses
    :func:`~fenics_matdepth.boundary.face_table`.
    """
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facets = np.asarray(dolfinx.mesh.exterior_facet_indices(mesh.topology), dtype=np.int32)
    # exterior_facet_indices returns owned facets; keep only those in case a version adds ghosts.
    return facets[facets < mesh.topology.index_map(tdim - 1).size_local]


def boundary_triangles(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Vertex coordinates of all exterior boundary triangles of the mesh, on every rank.

    A facet is exterior when it belongs to exactly one cell of the whole (distributed) mesh.
    Each rank contributes the exterior facets it owns; the result is gathered on all ranks in
    rank order (collective).

    Args:
        mesh: affine tetrahedral mesh.

    Returns:
        (m, 3, 3) triangle vertex coordinates (mesh length unit).
    """
    check_mesh(mesh)
    cell, face = face_table(mesh).exterior.T
    nodes = np.asarray(geometry_dofmap(mesh)).reshape(-1, 4)[cell[:, None], FACE_VERTICES[face]]
    local = np.ascontiguousarray(mesh.geometry.x[nodes.reshape(-1, 3)], dtype=FLOAT)
    local = local.reshape(-1, 9)
    comm = mesh.comm
    counts = np.asarray(comm.allgather(local.size), dtype=np.int64)
    gathered = np.empty(int(counts.sum()), dtype=FLOAT)
    comm.Allgatherv(local.ravel(), [gathered, counts, MPI.DOUBLE])
    return gathered.reshape(-1, 3, 3)


def p1_dof_coordinates(V: dolfinx.fem.FunctionSpace) -> np.ndarray:
    """Exact vertex coordinates of every local (owned + ghost) P1 dof (block).

    Taken from the geometry nodes through the cell-wise maps (P1 dofs and degree-1 geometry
    nodes both follow the reference vertex order), not from tabulate_dof_coordinates, so that
    boundary vertices coincide bit for bit with the triangle vertices and get depth exactly 0.
    """
    mesh = V.mesh
    imap = V.dofmap.index_map
    n_dofs = imap.size_local + imap.num_ghosts
    dofs = np.asarray(V.dofmap.list).reshape(-1)
    nodes = np.asarray(geometry_dofmap(mesh)).reshape(-1)
    if dofs.shape != nodes.shape:
        raise RuntimeError("P1 dofmap and geometry dofmap differ in shape: not an affine mesh")
    node_of_dof = np.full(n_dofs, -1, dtype=np.int64)
    node_of_dof[dofs] = nodes
    if np.any(node_of_dof < 0):
        raise RuntimeError("some P1 dofs belong to no local cell")
    return np.ascontiguousarray(mesh.geometry.x[node_of_dof], dtype=FLOAT)


def owned_boundary_triangle_dofs(
    mesh: dolfinx.mesh.Mesh, cells: np.ndarray, X: np.ndarray
) -> np.ndarray:
    """The exterior triangles this rank owns, as local P1 dofs (blocks) of their cell.

    The three vertices of each owned exterior facet's (single) cell other than the opposite
    one (the reference tetrahedron's facet i is opposite vertex i), ordered so that the
    normal ``(x1 - x0) x (x2 - x0)`` points out of the cell in the reference configuration
    ``X``: the clipper shifts each triangle a rounding-scale distance along that normal
    (`fenics_matdepth.geometry.clip.CLIP_SHIFT`), so a triangle lying in a face of another
    body counts as touching it.

    Args:
        mesh: the tetrahedral mesh.
        cells: (num local cells, 4) local P1 dofs (blocks) of every local cell.
        X: (num local dofs, 3) reference coordinates of the P1 dofs.

    Returns:
        (num owned exterior facets, 3) local dofs.
    """
    cell, opposite = face_table(mesh).exterior.T
    cells = np.asarray(cells, dtype=INDEX)
    tri = cells[cell[:, None], FACE_VERTICES[opposite]].reshape(-1, 3)
    apex = cells[cell, opposite]
    x = X[tri]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    inward = np.einsum("ij,ij->i", normal, X[apex] - x[:, 0]) > 0.0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    return np.ascontiguousarray(tri)
