"""Checks of a mesh for material-depth contact, collective, beside the boundary extraction.

Every check here looks at distributed data: each rank tests its own part and the ranks agree
(``_mpi.collective_error``) before anything is raised, so an error is
raised on every rank and no rank is left waiting in a collective call.

* :func:`~fenics_matdepth.boundary.check_mesh` (in :mod:`fenics_matdepth.boundary`, which
  needs it itself): the mesh is a dolfinx mesh of affine tetrahedra in 3D.
* :func:`check_mesh_quality`: finite coordinates, no degenerate (zero-volume) tetrahedron, no
  tetrahedron folded over a neighbour (an inverted element of a tangled mesh).
* :func:`check_manifold_boundary`: the exterior boundary is a closed manifold surface.
* :func:`check_contact_mesh`: all of them, as the material depth and the contact operator
  need.
"""

from __future__ import annotations

import dolfinx
import numpy as np
from numba import njit

from fenics_matdepth._compat import geometry_dofmap
from fenics_matdepth._mpi import allgather_rows, collective_error
from fenics_matdepth.boundary import check_mesh, face_table, global_face_vertices

__all__ = ["check_contact_mesh", "check_manifold_boundary", "check_mesh_quality"]

#: A tetrahedron whose volume is below this fraction of (its longest edge)^3 counts as
#: degenerate (a regular tetrahedron has about 0.118).
DEGENERATE_VOLUME_RATIO = 1e-10


def check_mesh_quality(mesh: dolfinx.mesh.Mesh) -> None:
    """Finite coordinates, no zero-volume tetrahedron, no tetrahedron folded over a neighbour.

    A tetrahedron is *folded over* (inverted) when it and a neighbour across a shared face
    lie on the same side of that face: the two overlap, as happens when a vertex of a valid
    mesh is moved through the opposite face. This test does not depend on the orientation
    (vertex order) of the cells. Faces shared across the partition boundary are tested where
    both cells are on one rank (always in serial).

    Raises:
        ValueError: naming the first bad cell (its reference coordinates) and the fix, on
            every rank.
    """
    check_mesh(mesh)
    comm = mesh.comm
    x_all = np.asarray(mesh.geometry.x)
    message = None
    if not np.all(np.isfinite(x_all)):
        bad = x_all[~np.all(np.isfinite(x_all), axis=1)][0]
        message = (
            f"the mesh has non-finite vertex coordinates (e.g. {bad.tolist()}): fix the mesh "
            "file or the code that builds the coordinates"
        )
    collective_error(comm, message)

    # Flat cells; folded-over cells: the opposite vertices of two cells sharing a face must
    # lie on opposite sides of the face's plane (one pass in numba, _cell_quality).
    table = face_table(mesh)
    if table.overshared:
        message = (
            f"{table.overshared} faces are shared by more than two tetrahedra (duplicated or "
            "overlapping cells): remove the duplicate cells, or re-mesh"
        )
    collective_error(comm, message)
    nodes = np.asarray(geometry_dofmap(mesh), dtype=np.int64).reshape(-1, 4)
    num_owned = mesh.topology.index_map(3).size_local
    flat, first_flat, folded, first_folded = _cell_quality(
        np.asarray(x_all, dtype=np.float64),
        nodes,
        table.neighbour,
        num_owned,
        DEGENERATE_VOLUME_RATIO,
    )
    if flat:
        message = (
            f"{flat} tetrahedra have (near) zero volume, e.g. the one with vertices "
            f"{np.round(x_all[nodes[first_flat]], 6).tolist()}: remove the degenerate (flat) "
            "tetrahedra, e.g. re-mesh with gmsh (Mesh.Optimize) or merge duplicate vertices"
        )
    collective_error(comm, message)
    if folded:
        message = (
            f"{folded} interior faces have both their tetrahedra on the same side (an "
            f"inverted, folded-over element), e.g. at the tetrahedron with vertices "
            f"{np.round(x_all[nodes[first_folded]], 6).tolist()}: the mesh is tangled; "
            "re-mesh, or fix the vertex that was moved through the opposite face"
        )
    collective_error(comm, message)


@njit(cache=True)
def _cell_quality(x, nodes, neighbour, num_owned, ratio):
    """(number of flat owned cells, the first, number of folded-over faces, a cell of the
    first) over the local cells: a cell is flat when 6 |volume| <= 6 ratio (longest edge)^3; a
    face shared by two local cells is folded over when their vertices opposite it lie on the
    same side of its plane (the reference tetrahedron's facet i is opposite its vertex i)."""
    num_flat, first_flat, num_folded, first_folded = 0, -1, 0, -1
    e = np.empty((6, 3))
    pairs = ((1, 0), (2, 0), (3, 0), (2, 1), (3, 1), (3, 2))
    for c in range(num_owned):
        for k in range(6):
            a, b = pairs[k]
            for d in range(3):
                e[k, d] = x[nodes[c, a], d] - x[nodes[c, b], d]
        vol6 = (
            e[0, 0] * (e[1, 1] * e[2, 2] - e[1, 2] * e[2, 1])
            - e[0, 1] * (e[1, 0] * e[2, 2] - e[1, 2] * e[2, 0])
            + e[0, 2] * (e[1, 0] * e[2, 1] - e[1, 1] * e[2, 0])
        )
        longest2 = 0.0
        for k in range(6):
            longest2 = max(longest2, e[k, 0] ** 2 + e[k, 1] ** 2 + e[k, 2] ** 2)
        if abs(vol6) <= 6.0 * ratio * longest2**1.5:
            if num_flat == 0:
                first_flat = c
            num_flat += 1
    for c in range(neighbour.shape[0]):
        for i in range(4):
            across = neighbour[c, i]
            if across < 0 or across // 4 < c:
                continue  # an exterior face, or the pair is tested from its first cell
            other, j = across // 4, across % 4
            # the face's vertices: those of c other than i
            q0, q1, q2 = nodes[c, (i + 1) % 4], nodes[c, (i + 2) % 4], nodes[c, (i + 3) % 4]
            ux, uy, uz = x[q1, 0] - x[q0, 0], x[q1, 1] - x[q0, 1], x[q1, 2] - x[q0, 2]
            wx, wy, wz = x[q2, 0] - x[q0, 0], x[q2, 1] - x[q0, 1], x[q2, 2] - x[q0, 2]
            nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
            a, b = nodes[c, i], nodes[other, j]
            sa = (x[a, 0] - x[q0, 0]) * nx + (x[a, 1] - x[q0, 1]) * ny + (x[a, 2] - x[q0, 2]) * nz
            sb = (x[b, 0] - x[q0, 0]) * nx + (x[b, 1] - x[q0, 1]) * ny + (x[b, 2] - x[q0, 2]) * nz
            if sa * sb > 0.0:
                if num_folded == 0:
                    first_folded = c
                num_folded += 1
    return num_flat, first_flat, num_folded, first_folded


def _gathered_boundary_triangles(mesh: dolfinx.mesh.Mesh) -> np.ndarray:
    """Global vertex indices (topology numbering) of all exterior triangles, on every rank."""
    table = face_table(mesh)
    return allgather_rows(
        mesh.comm, global_face_vertices(mesh, table.cell_vertices, table.exterior)
    )


def check_manifold_boundary(mesh: dolfinx.mesh.Mesh) -> None:
    """Every boundary edge must bound exactly two boundary triangles, and the boundary
    triangles around each boundary vertex must form one fan (collective).

    Two tetrahedra (or bodies) that share only an edge or only a vertex make the boundary
    non-manifold there: the material depth and the triangle-tetrahedron pairs cannot tell the
    two sides apart.

    Raises:
        ValueError: on every rank, with the number of non-manifold edges and vertices and one
            location.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tri = _gathered_boundary_triangles(mesh)
    if tri.shape[0] == 0:
        return
    m = tri.shape[0]
    edges = np.sort(tri[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, inverse, counts = np.unique(
        edges[:, 0] * (tri.max() + 1) + edges[:, 1], return_inverse=True, return_counts=True
    )
    bad_edges = counts != 2
    # Fans: incidences (vertex, triangle) linked when the two triangles share an edge through
    # the vertex; a manifold vertex has one connected fan.
    incidence = np.arange(3 * m).reshape(m, 3)  # incidence of corner c of triangle t
    owner_tri = np.repeat(np.arange(m), 3)
    corner = np.array([[0, 1], [1, 2], [2, 0]])
    a_idx, b_idx = [], []
    order = np.argsort(inverse, kind="stable")
    starts = np.cumsum(np.r_[0, counts])[:-1]
    pairs = starts[counts == 2]
    e1, e2 = order[pairs], order[pairs + 1]  # the two edge slots of each two-sided edge
    for k in (0, 1):
        v1 = tri[owner_tri[e1], corner[e1 % 3, k]]
        # the same vertex's corner in the other triangle
        t2 = owner_tri[e2]
        c2 = np.argmax(tri[t2] == v1[:, None], axis=1)
        a_idx.append(incidence[owner_tri[e1], corner[e1 % 3, k]])
        b_idx.append(incidence[t2, c2])
    a_idx, b_idx = np.concatenate(a_idx), np.concatenate(b_idx)
    graph = coo_matrix((np.ones(a_idx.size), (a_idx, b_idx)), shape=(3 * m, 3 * m))
    _, label = connected_components(graph, directed=False)
    vertex = tri.ravel()
    fans = np.unique(np.stack((vertex, label), axis=1), axis=0)
    vertices, fan_counts = np.unique(fans[:, 0], return_counts=True)
    bad_vertices = vertices[fan_counts > 1]
    if np.any(bad_edges) or bad_vertices.size:
        raise ValueError(
            f"the boundary is non-manifold: {int(bad_edges.sum())} edges bound other than two "
            f"boundary triangles and {bad_vertices.size} vertices join separate boundary fans "
            "(tetrahedra or bodies that touch only along an edge or at a vertex). Material-depth "
            "contact needs every body bounded by a closed surface: duplicate the shared "
            "vertices so that the bodies are separate pieces of the mesh, or glue them along "
            "whole faces"
        )


def check_contact_mesh(mesh: dolfinx.mesh.Mesh) -> None:
    """All mesh checks material-depth contact needs (collective): affine tetrahedra in 3D,
    finite coordinates, no degenerate or folded-over tetrahedron, a manifold boundary."""
    check_mesh(mesh)
    check_mesh_quality(mesh)
    check_manifold_boundary(mesh)
