"""Material depth: distance from each vertex to the exterior boundary, reference configuration.

``material_depth(mesh)`` returns the P1 function d with d_i = exact Euclidean distance from
vertex X_i to the nearest exterior boundary triangle of the mesh (Hirota, Fisher & State 2003,
section 4.3.1): exact point-triangle distance, not the distance to the nearest boundary vertex.
Facets shared by two cells (glued interfaces inside one conforming mesh) are not boundary.

Parallel strategy: every rank gathers all exterior triangles once (an ``Allgatherv`` of their
vertex coordinates, 9 floats each), builds an AABB tree over them, and computes the distance
for all its P1 dofs, owned and ghost, directly; the values are therefore identical to a serial
computation and no scatter is needed.

The numba core, :func:`distance_to_triangles`, works on plain arrays. The boundary
extraction (``boundary_triangles``, ``owned_exterior_facets``) lives in
:mod:`fenics_matdepth.boundary` and is re-exported here.
"""

from __future__ import annotations

import typing

import dolfinx
import numpy as np

from fenics_matdepth._constants import FLOAT, INDEX
from fenics_matdepth._jit import announces_compilation
from fenics_matdepth.boundary import (
    boundary_triangles,
    check_mesh,
    owned_exterior_facets,
    p1_dof_coordinates,
)
from fenics_matdepth.geometry.bvh import AABBTree
from fenics_matdepth.mesh_checks import check_contact_mesh

__all__ = [
    "DepthDeficiency",
    "boundary_triangles",
    "count_depth_deficient",
    "depth_deficiency",
    "depth_deficient_tets",
    "distance_to_triangles",
    "material_depth",
    "owned_exterior_facets",
]

#: Bits per axis of the Morton (Z-order) key used to sort query points: 2**10 cells per axis
#: is enough for consecutive points to be near each other, which is all the sort is for.
_MORTON_BITS = 10


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between the low 10 bits of v (uint64), for a 3D Morton key."""
    v = v & np.uint64(0x3FF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x030000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x0300F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x030C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x09249249)
    return v


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Z-order curve (spatially coherent query order)."""
    lo = points.min(axis=0)
    ext = np.maximum(points.max(axis=0) - lo, np.finfo(FLOAT).tiny)
    scale = (2**_MORTON_BITS - 1) / ext
    q = ((points - lo) * scale).astype(np.uint64)
    key = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1))
    key |= _spread_bits(q[:, 2]) << np.uint64(2)
    return np.argsort(key, kind="stable")


def distance_to_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Exact distance from each point to the nearest triangle (plain arrays, no DOLFINx).

    Builds an AABB tree over the triangles and answers the points in Z-order, so that each
    query starts from its predecessor's nearest triangle.

    Args:
        points: (n, 3) points (length unit L).
        triangles: (m, 3, 3) triangle vertex coordinates (L), m >= 1.

    Returns:
        (n,) distances (L). A point equal to a triangle vertex gets exactly 0.

    Raises:
        ValueError: on wrong shapes or when there are no triangles.
    """
    p = np.ascontiguousarray(points, dtype=FLOAT)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    tri = np.ascontiguousarray(triangles, dtype=FLOAT)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (m, 3, 3), got {tri.shape}")
    if tri.shape[0] == 0:
        raise ValueError("no boundary triangles: the distance to the boundary is undefined")
    if p.shape[0] == 0:
        return np.empty(0, dtype=FLOAT)
    m = tri.shape[0]
    tree = AABBTree(tri.reshape(3 * m, 3), np.arange(3 * m, dtype=INDEX).reshape(m, 3))
    perm = _morton_order(p)
    _, d2 = tree.nearest_squared(p[perm])
    d = np.empty_like(d2)
    d[perm] = np.sqrt(d2)
    return d


#: Kept for callers of the former private helper; the mesh checks live in ``boundary`` and
#: ``mesh_checks``.
_check_mesh = check_mesh


@announces_compilation("the material depth (distance to the boundary)")
def material_depth(mesh: dolfinx.mesh.Mesh) -> dolfinx.fem.Function:
    """Material depth of every vertex: exact distance to the exterior boundary (collective).

    Args:
        mesh: affine tetrahedral mesh holding all bodies (length unit L).

    Returns:
        P1 scalar Function named ``"material_depth"`` (L), owned and ghost values set; zero
        exactly on the exterior boundary.

    Raises:
        TypeError: if ``mesh`` is not a dolfinx Mesh.
        ValueError: for non-tetrahedral cells, non-affine geometry, non-finite coordinates,
            degenerate or folded-over tetrahedra, a non-manifold boundary, or a mesh without
            exterior boundary (see ``fenics_matdepth.mesh_checks``); raised on every rank.
    """
    check_contact_mesh(mesh)
    triangles = boundary_triangles(mesh)
    if triangles.shape[0] == 0:
        raise ValueError(
            "the mesh has no exterior boundary facets, so the material depth is undefined: "
            "material_depth needs bodies with a boundary"
        )
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1))
    depth = dolfinx.fem.Function(V, name="material_depth")
    depth.x.array[:] = distance_to_triangles(p1_dof_coordinates(V), triangles)
    return depth


class DepthDeficiency(typing.NamedTuple):
    """Tetrahedra whose material depth is zero everywhere (see :func:`count_depth_deficient`).

    Attributes:
        deficient: tetrahedra whose four vertices all have depth 0.
        boundary_adjacent: tetrahedra with at least one vertex of depth 0 (on the boundary).
    """

    deficient: int
    boundary_adjacent: int

    @property
    def fraction(self) -> float:
        """``deficient / boundary_adjacent`` (0 when no tetrahedron touches the boundary)."""
        return self.deficient / self.boundary_adjacent if self.boundary_adjacent else 0.0


def depth_deficient_tets(tets: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Mask of the tetrahedra whose four vertices all have depth 0.

    The P1 depth of such a tetrahedron is 0 everywhere inside it: a surface that enters it
    feels no contact force. This happens wherever a tetrahedron has all four vertices on the
    exterior boundary: layers one element thick, and edges and corners of coarse meshes.

    Args:
        tets: (nk, 4) vertex indices.
        depth: (nv,) material depth per vertex (length).

    Returns:
        (nk,) bool.
    """
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (nk, 4), got {tets.shape}")
    return np.all(np.asarray(depth)[tets] <= 0.0, axis=1)


def count_depth_deficient(tets: np.ndarray, depth: np.ndarray) -> DepthDeficiency:
    """Count the depth-deficient tetrahedra and the boundary-adjacent ones (plain arrays).

    Args:
        tets: (nk, 4) vertex indices (each tetrahedron once, e.g. the global list).
        depth: (nv,) material depth per vertex (length).

    Returns:
        The counts; ``.fraction`` is the share of boundary-adjacent tetrahedra that are
        deficient.
    """
    deficient = depth_deficient_tets(tets, depth)
    adjacent = np.any(np.asarray(depth)[np.asarray(tets)] <= 0.0, axis=1)
    return DepthDeficiency(int(np.count_nonzero(deficient)), int(np.count_nonzero(adjacent)))


def depth_deficiency(depth: dolfinx.fem.Function) -> DepthDeficiency:
    """Count the depth-deficient tetrahedra of a mesh from its material depth (collective).

    Args:
        depth: P1 scalar material depth (from :func:`material_depth`).

    Returns:
        Global counts over the mesh's cells (each counted once, by its owning rank).
    """
    V = depth.function_space
    _check_mesh(V.mesh)
    if V.dofmap.index_map_bs != 1 or V.dofmap.list.shape[1] != 4:
        raise ValueError("depth must be a P1 scalar Function on a tetrahedral mesh")
    n_owned = V.mesh.topology.index_map(3).size_local
    local = count_depth_deficient(np.asarray(V.dofmap.list)[:n_owned], depth.x.array)
    comm = V.mesh.comm
    return DepthDeficiency(comm.allreduce(local.deficient), comm.allreduce(local.boundary_adjacent))
