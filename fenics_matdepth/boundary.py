"""Mesh and boundary extraction shared by the material depth and the contact operator.

What a rank reads off a dolfinx mesh and its P1 spaces: the exterior facets it owns, their
triangles (as coordinates, gathered, for the distance to the boundary; or as local P1 dofs,
for contact), and the exact coordinates of the P1 dofs.
"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np

from fenics_matdepth._checks import check_mesh
from fenics_matdepth._compat import geometry_dofmap
from fenics_matdepth._constants import FLOAT, INDEX

__all__ = [
    "boundary_triangles",
    "owned_boundary_triangle_dofs",
    "owned_exterior_facets",
    "p1_dof_coordinates",
]


def owned_exterior_facets(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Local indices of the exterior facets (one cell in the whole mesh) this rank owns.

    Every exterior facet is owned by exactly one rank, so each boundary triangle is handled
    once across the ranks.
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
    tdim = mesh.topology.dim
    facets = owned_exterior_facets(mesh)
    if facets.size:
        nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets, False)
    else:  # DOLFINx 0.9 divides by zero (SIGFPE) on a rank without cells
        nodes = np.empty((0, 3), dtype=np.int32)
    local = np.ascontiguousarray(mesh.geometry.x[np.asarray(nodes).reshape(-1, 3)], dtype=FLOAT)
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
    facets = owned_exterior_facets(mesh)
    mesh.topology.create_connectivity(3, 2)
    f2c = mesh.topology.connectivity(2, 3)
    c2f = np.asarray(mesh.topology.connectivity(3, 2).array).reshape(-1, 4)
    cell = np.asarray(f2c.array)[np.asarray(f2c.offsets)[facets]]
    opposite = np.argmax(c2f[cell] == facets[:, None], axis=1)
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    cells = np.asarray(cells, dtype=INDEX)
    tri = cells[cell[:, None], others[opposite]].reshape(-1, 3)
    apex = cells[cell, opposite]
    x = X[tri]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    inward = np.einsum("ij,ij->i", normal, X[apex] - x[:, 0]) > 0.0
    tri[inward] = tri[inward][:, [0, 2, 1]]
    return np.ascontiguousarray(tri)
