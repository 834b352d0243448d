"""Checks of a new contact operator's state: the bodies can push out, nothing overlaps at u = 0.

:func:`check_contact_state` runs on what a rank holds (a
:class:`~fenics_matdepth.contact.surface.ContactSurface`) before the operator's first update,
with the operator's own pair search and pair kernels; the checks of the mesh itself are in
:mod:`fenics_matdepth.mesh_checks`.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np

from fenics_matdepth.contact.kernels.drivers import intersecting
from fenics_matdepth.contact.kernels.polygon import area_pairs_max_depth
from fenics_matdepth.contact.surface import ContactSurface
from fenics_matdepth.geometry.boxes import element_boxes, exclude_shared_vertex_pairs
from fenics_matdepth.geometry.bvh import AABBTree

__all__ = ["check_contact_state"]

#: Material depth (relative to the mean boundary edge) above which a boundary triangle is
#: counted as inside another tetrahedron in the reference configuration; below it, coincident
#: surfaces touch (round-off of the barycentric coordinates gives depths of about 1e-16).
OVERLAP_DEPTH_RTOL = 1e-6


def check_contact_state(surface: ContactSurface, allow_reference_overlap: bool = False) -> None:
    """Checks of a new contact operator's surface, before its first update (collective).

    * Every body (connected component of the mesh) has a vertex with positive material depth;
      otherwise nothing can push out of it (a single tetrahedron, a layer one element thick).
    * No boundary triangle lies inside a tetrahedron of the mesh in the reference
      configuration (u = 0): the operator's own pair search and pair kernels at u = 0, between
      different bodies or within one. Bodies that overlap in the reference configuration get
      a wrong material depth (each one's surface counts as boundary inside the other).
      Surfaces that coincide without being glued touch with zero depth and pass.

    Args:
        surface: what the operator's rank holds, at u = 0 (held numbering, see
            :mod:`fenics_matdepth.contact.surface`).
        allow_reference_overlap: skip the overlap check (for tests that start intersected on
            purpose).

    Raises:
        ValueError: on every rank, naming the problem and the fix.
    """
    deepest = np.zeros(surface.num_bodies)
    np.maximum.at(deepest, surface.body, surface.depth)
    # Depth-deficient tetrahedra split around their centroid carry the centroid's depth.
    tets, depth = surface.kernel_tets, surface.kernel_depth
    if tets.shape[1] == 5:
        split = tets[:, 4] >= 0
        np.maximum.at(deepest, surface.body[tets[split, 0]], depth[tets[split, 4]])
    surface.comm.Allreduce(MPI.IN_PLACE, deepest, op=MPI.MAX)
    shallow = np.flatnonzero(deepest <= 0.0)
    if shallow.size:
        raise ValueError(
            f"{shallow.size} of the {surface.num_bodies} bodies have no vertex inside them "
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
    active = intersecting(X, tri, tets, pa, pk)
    pa, pk = pa[active], pk[active]
    g = area_pairs_max_depth(X, depth, tri, tets, pa, pk)
    tolerance = OVERLAP_DEPTH_RTOL * 10.0 * surface.margin
    inside = g > tolerance
    count = surface.comm.allreduce(int(np.count_nonzero(inside)))
    if count:
        bodies = surface.body
        between = inside & (bodies[tri[pa, 0]] != bodies[tets[pk, 0]])
        n_between = surface.comm.allreduce(int(np.count_nonzero(between)))
        deepest_g = surface.comm.allreduce(float(g.max(initial=0.0)), op=MPI.MAX)
        raise ValueError(
            f"the bodies overlap in the reference configuration: {count} boundary triangle / "
            f"tetrahedron pairs intersect at u = 0 ({n_between} between different bodies, "
            f"{count - n_between} within one body), up to a material depth of {deepest_g:.3g}. "
            "The material depth is then wrong. Move the bodies apart in the mesh (start them "
            "touching or separated and press them together with the load), or pass "
            "allow_reference_overlap=True if the overlap is intended"
        )
