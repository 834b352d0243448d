"""Input validation and element checks, in one place.

Every check here is collective where it looks at distributed data: each rank tests its own
part and the ranks agree (``allreduce``) before anything is raised, so an error is raised on
every rank and no rank is left waiting in a collective call.

* :func:`check_mesh`: the mesh is a dolfinx mesh of affine tetrahedra in 3D.
* :func:`check_mesh_quality`: finite coordinates, no degenerate (zero-volume) tetrahedron, no
  tetrahedron folded over a neighbour (an inverted element of a tangled mesh).
* :class:`CellDeterminants`: the smallest ``det F`` over the cells of a P1 displacement, a cheap
  per-cell evaluation used to reject trial states that invert elements.
"""

from __future__ import annotations

from mpi4py import MPI

import dolfinx
import numpy as np
from numba import njit

from fenics_matdepth._compat import geometry_cmap, geometry_dofmap

__all__ = [
    "CellDeterminants",
    "check_contact_mesh",
    "check_contact_state",
    "check_function_space",
    "check_manifold_boundary",
    "check_mesh",
    "check_mesh_quality",
    "collective_error",
]

#: Material depth (relative to the mean boundary edge) above which a boundary triangle is
#: counted as inside another tetrahedron in the reference configuration; below it, coincident
#: surfaces touch (round-off of the barycentric coordinates gives depths of about 1e-16).
OVERLAP_DEPTH_RTOL = 1e-6

#: A tetrahedron whose volume is below this fraction of (its longest edge)^3 counts as
#: degenerate (a regular tetrahedron has about 0.118).
DEGENERATE_VOLUME_RATIO = 1e-10


def collective_error(comm: MPI.Comm, message: str | None, error: type = ValueError) -> None:
    """Raise ``error`` on every rank if any rank has a ``message`` (the first one found).

    Args:
        comm: communicator of the ranks that must agree.
        message: this rank's error message, or None if this rank found nothing wrong.
        error: exception class raised.
    """
    messages = comm.allgather(message)
    first = next((m for m in messages if m is not None), None)
    if first is not None:
        raise error(first)


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


def _signed_volumes6(x: np.ndarray) -> np.ndarray:
    """Six times the signed volume of each tetrahedron of ``x`` (n, 4, 3)."""
    e = x[:, 1:] - x[:, :1]
    return np.einsum("ij,ij->i", e[:, 0], np.cross(e[:, 1], e[:, 2]))


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
    from fenics_matdepth.boundary import face_table

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
    from fenics_matdepth._mpi import allgather_rows
    from fenics_matdepth.boundary import face_table, global_face_vertices

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


def check_contact_state(contact, allow_reference_overlap: bool = False) -> None:
    """Checks of a new contact operator (collective).

    * Every body (connected component of the mesh) has a vertex with positive material depth;
      otherwise nothing can push out of it (a single tetrahedron, a layer one element thick).
    * No boundary triangle lies inside a tetrahedron of the mesh in the reference
      configuration (u = 0): the operator's own pair search and pair kernels at u = 0, between
      different bodies or within one. Bodies that overlap in the reference configuration get
      a wrong material depth (each one's surface counts as boundary inside the other).
      Surfaces that coincide without being glued touch with zero depth and pass.

    Args:
        contact: the :class:`~fenics_matdepth.ContactOperator`.
        allow_reference_overlap: skip the overlap check (for tests that start intersected on
            purpose).

    Raises:
        ValueError: on every rank, naming the problem and the fix.
    """
    from fenics_matdepth.contact.kernels.drivers import intersecting as _intersecting
    from fenics_matdepth.contact.kernels.polygon import (
        area_pairs_max_depth as _area_pairs_max_depth,
    )
    from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
    from fenics_matdepth.geometry.bvh import AABBTree

    surface = contact.surface  # held numbering (see fenics_matdepth.contact.surface)
    deepest = np.zeros(contact.num_bodies)
    np.maximum.at(deepest, surface.body, surface.depth)
    # Depth-deficient tetrahedra split around their centroid carry the centroid's depth.
    tets, depth = surface.kernel_tets, surface.kernel_depth
    if tets.shape[1] == 5:
        split = tets[:, 4] >= 0
        np.maximum.at(deepest, surface.body[tets[split, 0]], depth[tets[split, 4]])
    contact.comm.Allreduce(MPI.IN_PLACE, deepest, op=MPI.MAX)
    shallow = np.flatnonzero(deepest <= 0.0)
    if shallow.size:
        raise ValueError(
            f"{shallow.size} of the {contact.num_bodies} bodies have no vertex inside them "
            "(material depth zero everywhere, e.g. a single tetrahedron or a layer one element "
            "thick, with split_deficient=False), so contact cannot push anything out of them: "
            "keep split_deficient=True (the default), or refine the mesh so that each body has "
            "interior vertices (at least two elements through its thickness)"
        )
    if allow_reference_overlap:
        return
    # the surface holds, at u = 0, every tetrahedron its triangles can meet
    X, tri, held_tets = surface.X, surface.tri, surface.tets
    tree = AABBTree(X, held_tets)
    lo, hi = element_boxes(X, tri)
    pa, pk = tree.query_boxes(lo, hi)
    pa, pk = exclude_shared_vertex_pairs(tri, held_tets, pa, pk)
    active = _intersecting(X, tri, tets, pa, pk)
    pa, pk = pa[active], pk[active]
    g = _area_pairs_max_depth(X, depth, tri, tets, pa, pk)
    tolerance = OVERLAP_DEPTH_RTOL * 10.0 * contact.margin
    inside = g > tolerance
    count = contact.comm.allreduce(int(np.count_nonzero(inside)))
    if count:
        bodies = surface.body
        between = inside & (bodies[tri[pa, 0]] != bodies[tets[pk, 0]])
        n_between = contact.comm.allreduce(int(np.count_nonzero(between)))
        deepest_g = contact.comm.allreduce(float(g.max(initial=0.0)), op=MPI.MAX)
        raise ValueError(
            f"the bodies overlap in the reference configuration: {count} boundary triangle / "
            f"tetrahedron pairs intersect at u = 0 ({n_between} between different bodies, "
            f"{count - n_between} within one body), up to a material depth of {deepest_g:.3g}. "
            "The material depth is then wrong. Move the bodies apart in the mesh (start them "
            "touching or separated and press them together with the load), or pass "
            "allow_reference_overlap=True if the overlap is intended"
        )


def check_function_space(u: dolfinx.fem.Function, what: str = "u") -> None:
    """``u`` must be a Function on a P1 (Lagrange degree 1) vector space of dimension 3.

    Raises:
        TypeError: if ``u`` is not a dolfinx Function.
        ValueError: for another element, naming it and the space to use.
    """
    if not isinstance(u, dolfinx.fem.Function):
        raise TypeError(
            f"{what} must be a dolfinx.fem.Function, got {type(u).__name__}: create it with "
            'dolfinx.fem.Function(functionspace(mesh, ("Lagrange", 1, (3,))))'
        )
    V = u.function_space
    element = V.ufl_element()
    if V.dofmap.index_map_bs != 3 or element.degree != 1 or len(element.reference_value_shape) != 1:
        raise ValueError(
            f"{what} must live on a P1 vector space of dimension 3, got a space of degree "
            f"{element.degree} with {V.dofmap.index_map_bs} component(s): use "
            'functionspace(mesh, ("Lagrange", 1, (3,)))'
        )


class CellDeterminants:
    """Smallest ``det F = det(I + grad u)`` over the cells of a P1 vector displacement.

    On affine tetrahedra ``F`` is constant per cell: ``det F = V_current / V_reference`` with
    signed volumes from the vertex positions. The reference volumes are kept; each call costs a
    few vector operations per cell (collective).

    Args:
        V: the P1 vector space (dimension 3) of the displacement.
    """

    def __init__(self, V: dolfinx.fem.FunctionSpace):
        from fenics_matdepth.boundary import p1_dof_coordinates

        mesh = V.mesh
        self._comm = mesh.comm
        num_owned = mesh.topology.index_map(3).size_local
        self._cells = np.asarray(V.dofmap.list).reshape(-1, 4)[:num_owned]
        self._X = p1_dof_coordinates(V)
        self._vol6 = _signed_volumes6(self._X[self._cells])

    def local_min(self, u_local: np.ndarray) -> float:
        """This rank's smallest det F for the local (owned + ghost) displacement values."""
        if self._cells.shape[0] == 0:
            return np.inf
        x = self._X + np.asarray(u_local).reshape(-1, 3)
        det = _signed_volumes6(x[self._cells]) / self._vol6
        value = float(det.min())
        return value if np.isfinite(value) else -np.inf

    def min(self, u: dolfinx.fem.Function | np.ndarray) -> float:
        """Smallest det F over all cells (collective); NaN displacements give ``-inf``.

        Args:
            u: the displacement Function (ghost values current), or its local array.
        """
        values = u.x.array if isinstance(u, dolfinx.fem.Function) else u
        return self._comm.allreduce(self.local_min(values), op=MPI.MIN)
